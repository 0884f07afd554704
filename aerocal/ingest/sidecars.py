"""The files beside an observations-mode flight's tables, which must agree with them.

An observations-mode folder (``observations/*.parquet``: images, observations, gcps, gcp_observations) is
processed from its tables alone. The simulator, and a user exporting for other tools, also writes the same
records as text beside them: ``eo.csv`` (recorded GNSS/IMU) and GCP files (``gcps.csv``, ``gcp_list.txt``). A
user who edits one of those files expects the change to count; processing would not see it. So both
``aerocal ingest`` and ``aerocal process`` read those files with ingest's own readers (whose problems keep the
severity they have in an image-mode ingest) and compare them with the tables: a position more than
:data:`AGREEMENT_M` away from the table's stops processing, named by file, line and field, with the fix (make
the file and the table agree, or remove the file); an image or GCP the tables do not hold is a warning (ingest
leaves out images it cannot read, and ``aerocal match`` writes the tables of what it ingested).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa

from aerocal.ingest.eo_csv import read_eo_csv
from aerocal.ingest.gcp import read_gcp_file, to_flight_crs
from aerocal.ingest.problems import ProblemLog

#: largest difference (metres, horizontal and vertical alike) between a file's position and the table's that
#: is still agreement: the files are written with 1e-4 m (projected) or 1e-12 degree (geographic) precision,
#: and a position a user moved on purpose moves by more than a few centimetres
AGREEMENT_M = 0.05
#: the GCP files an observations-mode folder may hold beside its tables
GCP_FILES = ("gcps.csv", "gcp_list.txt")
#: metres per degree of latitude (and of longitude at the equator), for comparing geographic positions
METRES_PER_DEGREE = 111_320.0

FIX = ("an observations-mode flight is processed from observations/*.parquet: make this file agree with "
       "the table, or remove it")


def sidecar_problems(folder: str | Path, images: pa.Table, gcps: pa.Table, crs: str | None) -> ProblemLog:
    """Problems of the text files beside an observations-mode flight's tables (module docstring).

    ``images`` and ``gcps``: the folder's ``images`` and ``gcps`` tables (schemas of :mod:`aerocal.tables`);
    ``crs``: the tables' CRS (their ``aerocal.crs`` metadata). Disagreements stop processing
    (``stops_processing``); the readers' own problems and rows the tables do not hold do not."""
    folder = Path(folder)
    problems = ProblemLog()
    eo_path = folder / "eo.csv"
    if eo_path.is_file():
        _check_eo(eo_path, images, problems)
    for name in GCP_FILES:
        path = folder / name
        if path.is_file():
            _check_gcps(path, gcps, crs, problems)
    return problems


def _read(reader, path: Path, problems: ProblemLog, *args):
    """Run an ingest reader, its problems added to ``problems`` as ingest reports them."""
    found = ProblemLog()
    content = reader(path, found, *args)
    problems.extend(found)
    return content


def _check_eo(path: Path, images: pa.Table, problems: ProblemLog) -> None:
    eo = _read(read_eo_csv, path, problems)
    if eo is None:
        return
    rows = {name: k for k, name in enumerate(images.column("name").to_pylist())}
    lat = images.column("lat").to_numpy(zero_copy_only=False)
    lon = images.column("lon").to_numpy(zero_copy_only=False)
    alt = images.column("alt").to_numpy(zero_copy_only=False)
    for name, rec in eo.records.items():
        k = rows.get(name)
        if k is None:
            problems.warning(path, f"image {name} is not in observations/images.parquet; its row is not used",
                             "image", rec.line)
            continue
        if rec.lat is not None and rec.lon is not None and np.isfinite(lat[k]) and np.isfinite(lon[k]):
            d = np.hypot((rec.lat - lat[k]) * METRES_PER_DEGREE,
                         (rec.lon - lon[k]) * METRES_PER_DEGREE * np.cos(np.radians(lat[k])))
            if d > AGREEMENT_M:
                problems.blocker(path, f"{name} lies {d:.2f} m from its position in observations/images.parquet; "
                                 f"{FIX}", "position", rec.line)
        if rec.z is not None and np.isfinite(alt[k]) and abs(rec.z - alt[k]) > AGREEMENT_M:
            problems.blocker(path, f"{name}: height {rec.z:.3f} m, observations/images.parquet "
                             f"{alt[k]:.3f} m; {FIX}", "alt", rec.line)


def _check_gcps(path: Path, gcps: pa.Table, crs: str | None, problems: ProblemLog) -> None:
    gfile = _read(read_gcp_file, path, problems)
    if gfile is None or crs is None:
        return
    rows = {gid: k for k, gid in enumerate(gcps.column("gcp_id").to_pylist())}
    xyz = np.column_stack([gcps.column(c).to_numpy(zero_copy_only=False) for c in ("X", "Y", "Z")]) \
        if gcps.num_rows else np.zeros((0, 3))
    for gid, point in gfile.points.items():
        k = rows.get(gid)
        if k is None:
            problems.warning(path, f"{gid} is not in observations/gcps.parquet; not used", "gcp_id", point.line)
            continue
        here = to_flight_crs(point, gfile.crs, crs)
        if not np.all(np.isfinite(here)):
            continue
        dh = float(np.hypot(*(here[:2] - xyz[k, :2])))
        dz = 0.0 if gfile.heights_unknown else float(abs(here[2] - xyz[k, 2]))
        if max(dh, dz) > AGREEMENT_M:
            problems.blocker(path, f"{gid} lies {dh:.2f} m horizontally and {dz:.2f} m vertically from its "
                             f"coordinates in observations/gcps.parquet; {FIX}", "coordinates", point.line)
