"""Ingest of real and simulated flights: images, metadata, exterior orientation, ground control.

Entry points:

* :func:`ingest_folder` -> :class:`IngestResult` (``images``, ``gcps``, ``gcp_observations``, ``extra``
  tables, the flight ``crs`` and the ``problems`` found);
* :func:`read_raw`: pixels with their original radiometry (uint16 raw thermal, 16-bit TIFF, 8-bit JPEG);
* :func:`write_ingest` / :func:`read_ingest`: persist a result atomically;
* :func:`summary_rows`: (item, value) rows for a CLI summary.

Tests: tests/test_ingest_real.py, tests/test_ingest_robustness.py, tests/test_ingest_sidecars.py,
tests/test_thermal_formats.py, tests/test_flight_from_images.py, tests/test_camera_identity.py.
"""

from aerocal.certificates.identity import CameraIdentity
from aerocal.ingest.config import IngestConfig
from aerocal.ingest.folder import IngestResult, ingest_folder
from aerocal.ingest.output import IngestOutputError, read_ingest, write_ingest
from aerocal.ingest.pixels import ImageReadError, read_raw
from aerocal.ingest.problems import Problem
from aerocal.ingest.strips import StripConfig, find_strips
from aerocal.ingest.summary import summary_rows

__all__ = [
    "CameraIdentity",
    "ImageReadError",
    "IngestConfig",
    "IngestOutputError",
    "IngestResult",
    "Problem",
    "StripConfig",
    "find_strips",
    "ingest_folder",
    "read_ingest",
    "read_raw",
    "summary_rows",
    "write_ingest",
]
