"""Building a :class:`~aerocal.certificates.document.Certificate` from what a foreign calibration file holds.

Foreign formats hold a camera model and, at best, a date, a covariance or an RMS error. Everything else
of a certificate stays unknown (``None``): no sigmas unless the file has them, no image counts, no
quality figures beyond what the file states. Provenance records no flow run and the sha256 of the
imported file under ``"<format>:<file name>"`` (e.g. ``"opencv:camera.yaml"``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path

from aerocal.camera import Camera
from aerocal.certificates.document import (
    Certificate,
    CertificateError,
    Conditions,
    Correlation,
    Provenance,
    Quality,
)
from aerocal.certificates.identity import CameraIdentity
from aerocal.formats.safe_parsing import format_error


def imported_certificate(
    camera: Camera,
    *,
    source: str | Path,
    data: bytes,
    fmt: str,
    identity: CameraIdentity | None = None,
    sigmas: Mapping[str, float] | None = None,
    correlation: Correlation | None = None,
    estimated: tuple[str, ...] = (),
    date: str | None = None,
    reprojection_rms_px: float | None = None,
) -> Certificate:
    """A certificate holding what an imported file said; ``data`` are the file's bytes (hashed).

    Raises:
        FormatError: the values do not make a consistent certificate; the message names ``source``.
    """
    source = Path(source)
    try:
        return Certificate(
            identity=identity or CameraIdentity.unknown(),
            camera=camera,
            sigmas=dict(sigmas or {}),
            estimated=tuple(estimated),
            correlation=correlation or Correlation(),
            conditions=Conditions(date=date),
            quality=Quality(reprojection_rms_px=reprojection_rms_px),
            provenance=Provenance(
                flow_run=None,
                inputs={f"{fmt}:{source.name}": hashlib.sha256(data).hexdigest()},
            ),
        )
    except CertificateError as e:
        raise format_error(source, None, f"the imported calibration is inconsistent ({e})",
                           "check the file's values") from None
