"""GCP coordinate lists in CSV: ``id,X,Y,Z[,sigma_xy,sigma_z,role]`` with a header line.

* ``id`` [gcp_id, gcp, name, label, point, point_name]; ``X`` [easting], ``Y`` [northing], ``Z`` [height,
  elevation, alt, altitude, h] in metres of the CRS of a ``# crs: ...`` line (else the ``crs`` argument
  of :func:`aerocal.ingest.ingest_folder`); or ``lat``/``lon`` [latitude/longitude] columns, degrees,
  EPSG:4326 unless a ``# crs:`` says otherwise.
* ``sigma_xy``, ``sigma_z``: survey standard deviations in metres (default ``IngestConfig.gcp_sigma_*``).
* ``role``: ``control`` or ``check`` (default ``IngestConfig.gcp_default_role``).

A file without a height column (``copr/GPS_average.txt``) is kept with heights 0.0 marked unknown.
"""

from __future__ import annotations

from pathlib import Path

from aerocal.ingest.crs_strings import CrsTextError, crs_kind, normalise_crs
from aerocal.ingest.delimited import find_column, keyed_rows, normalise_header, read_text_lines, split_csv
from aerocal.ingest.gcp_records import GcpCoordinate, GcpFile
from aerocal.ingest.numbers import PLAUSIBLE_RANGES, describe_bad_number, in_range, to_float
from aerocal.ingest.problems import ProblemLog
from aerocal.tables import GCP_ROLES

ID_COLUMNS = ("id", "gcp_id", "gcp", "name", "label", "point", "point_name")
X_COLUMNS, Y_COLUMNS = ("x", "easting"), ("y", "northing")
Z_COLUMNS = ("z", "height", "elevation", "alt", "altitude", "h")
LAT_COLUMNS, LON_COLUMNS = ("lat", "latitude"), ("lon", "lng", "long", "longitude")
SIGMA_XY_COLUMNS, SIGMA_Z_COLUMNS = ("sigma_xy", "std_xy", "sxy"), ("sigma_z", "std_z", "sz")
ROLE_COLUMNS = ("role", "use", "type")


def looks_like_gcp_csv(first_line: str) -> bool:
    """True if ``first_line`` is a CSV header naming an id column (used to tell CSVs from ODM lists)."""
    if "," not in first_line:
        return False
    return find_column(normalise_header(split_csv(first_line)), ID_COLUMNS) is not None


def read_gcp_csv(path: str | Path, problems: ProblemLog, crs: str | None = None) -> GcpFile | None:
    """Parse a GCP CSV; bad rows are reported by line and skipped; an unusable file returns ``None``.

    Missing sigmas and roles stay ``None`` here; configured defaults are applied when tables are built.
    """
    path = Path(path)
    text = read_text_lines(path, problems)
    if text is None:
        return None
    if not text.lines:
        problems.error(path, "has no header and no rows; ignored")
        return None
    header_line, header_text = text.lines[0]
    header = normalise_header(split_csv(header_text))
    c_id = find_column(header, ID_COLUMNS)
    c_lat, c_lon = find_column(header, LAT_COLUMNS), find_column(header, LON_COLUMNS)
    geographic = c_lat is not None and c_lon is not None
    c_x, c_y = (
        (c_lon, c_lat) if geographic else (find_column(header, X_COLUMNS), find_column(header, Y_COLUMNS))
    )
    c_z = find_column(header, Z_COLUMNS)
    if c_id is None or c_x is None or c_y is None:
        problems.error(
            path,
            f"header {header_text.strip()[:80]!r} must name id, X, Y[, Z, sigma_xy, sigma_z, role] columns "
            "(or id, lat, lon); file ignored",
            "header",
            header_line,
        )
        return None
    c_sxy, c_sz = find_column(header, SIGMA_XY_COLUMNS), find_column(header, SIGMA_Z_COLUMNS)
    c_role = find_column(header, ROLE_COLUMNS)

    if "crs" in text.directives:
        value, line = text.directives["crs"]
        try:
            src_crs = normalise_crs(value)
        except CrsTextError as exc:
            problems.error(path, f"unknown CRS: {exc}; file ignored", "crs", line)
            return None
    elif crs is not None:
        src_crs = crs
    elif geographic:
        src_crs = "EPSG:4326"
    else:
        problems.error(
            path,
            "no '# crs: ...' line and no crs argument: coordinates cannot be placed; file ignored",
            "crs",
        )
        return None
    kind = crs_kind(src_crs)
    out = GcpFile(path, "csv", src_crs)
    if c_z is None:
        problems.warning(path, "no height column: heights are unknown and set to 0.0", "Z", header_line)
        out.heights_unknown = out.heights_absent = True
    for line, fields, gcp_id in keyed_rows(text, len(header), c_id, problems, out.points, "GCP id", "id", "columns"):
        cols = [(c_x, header[c_x]), (c_y, header[c_y])] + ([(c_z, header[c_z])] if c_z is not None else [])
        values = [to_float(fields[c]) for c, _ in cols]
        bad = [(name, fields[c]) for (c, name), v in zip(cols, values, strict=True) if v is None]
        if bad:
            name, f = bad[0]
            problems.error(path, f"{name} {describe_bad_number(f)}; row ignored", name, line)
            continue
        x, y = values[0], values[1]
        z = values[2] if c_z is not None else 0.0
        if kind == "geographic" and not (
            in_range(x, *PLAUSIBLE_RANGES["lon"]) and in_range(y, *PLAUSIBLE_RANGES["lat"])
        ):
            problems.error(path, f"lat={y}, lon={x} is outside the globe; row ignored", "lat/lon", line)
            continue
        point = GcpCoordinate(gcp_id, x, y, z, path, line)  # type: ignore[arg-type]
        ok = True
        for col, attr in ((c_sxy, "sigma_xy"), (c_sz, "sigma_z")):
            if col is None:
                continue
            if not fields[col].strip():
                problems.warning(path, f"{gcp_id}: {attr} empty; the default sigma is used", attr, line)
                continue
            value = to_float(fields[col])
            if value is None or value <= 0:
                why = describe_bad_number(fields[col]) if value is None else f"{value} is not > 0"
                problems.error(path, f"{attr} {why}; row ignored", attr, line)
                ok = False
                break
            setattr(point, attr, value)
        if ok and c_role is not None and not fields[c_role].strip():
            problems.warning(path, f"{gcp_id}: role empty; the default role is used", "role", line)
        if ok and c_role is not None and fields[c_role].strip():
            role = fields[c_role].strip().lower()
            if role not in GCP_ROLES:
                problems.error(
                    path,
                    f"role {fields[c_role]!r} is not one of {', '.join(GCP_ROLES)}; row ignored",
                    "role",
                    line,
                )
                ok = False
            point.role = role
        if not ok:
            continue
        out.points[gcp_id] = point
        out.first_data_line = out.first_data_line or line
        out.last_data_line = line
    if out.points and not out.heights_unknown and all(p.z == 0.0 for p in out.points.values()):
        out.heights_unknown = True
    if not out.points:
        problems.error(path, "no usable GCP rows; file ignored")
        return None
    return out
