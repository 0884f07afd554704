"""Exterior-orientation CSV files: recorded positions, attitudes and temperatures that override metadata.

Two layouts, with a header line (names are case-insensitive; aliases in brackets)::

    # crs: EPSG:4326
    # attitude: dji_gimbal
    image,lat,lon,alt,roll,pitch,yaw[,temperature]

    # crs: EPSG:32632
    image,x,y,z,omega,phi,kappa[,temperature]

* ``image`` [name, filename, file, image_name, photo]: the image file name.
* Geographic: ``lat`` [latitude], ``lon`` [lng, long, longitude] in degrees, ``alt`` [altitude, height, h]
  in metres; the CRS defaults to EPSG:4326 (x = longitude, y = latitude as pyproj orders them).
* Projected: ``x`` [easting], ``y`` [northing], ``z`` [alt, altitude, height] in metres of the CRS named by
  ``# crs:`` or, failing that, by the ``crs`` argument of :func:`aerocal.ingest.ingest_folder`.
* Angles in degrees: ``roll,pitch,yaw`` in the convention named by ``# attitude:`` (``dji_gimbal``,
  ``body_rpy`` or ``opk``; default ``IngestConfig.eo_default_attitude``), or ``omega,phi,kappa`` (``opk``).
* ``temperature`` [temperature_c, temp, sensor_temperature]: camera temperature in degC (optional).

Heights are passed through unchanged (no vertical datum transformation). Empty cells leave the metadata
value in place; bad cells are reported by line and field and not applied.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aerocal.geometry import CONVENTIONS, transformer
from aerocal.ingest.crs_strings import CrsTextError, crs_kind, normalise_crs
from aerocal.ingest.delimited import find_column, keyed_rows, normalise_header, read_text_lines, split_csv
from aerocal.ingest.numbers import PLAUSIBLE_RANGES, describe_bad_number, in_range, to_float
from aerocal.ingest.problems import ProblemLog

IMAGE_COLUMNS = ("image", "name", "filename", "file", "image_name", "photo")
LAT_COLUMNS, LON_COLUMNS = ("lat", "latitude"), ("lon", "lng", "long", "longitude")
X_COLUMNS, Y_COLUMNS = ("x", "easting"), ("y", "northing")
HEIGHT_COLUMNS = ("alt", "altitude", "height", "h", "z", "ellipsoidal_height")
TEMPERATURE_COLUMNS = ("temperature", "temperature_c", "temp", "sensor_temperature")


@dataclass
class EoRecord:
    """One row: position in the file's CRS and in WGS84, angles (degrees), temperature (degC)."""

    line: int
    name: str
    x: float | None = None  # first coordinate in the file's CRS (lon for geographic CRSs)
    y: float | None = None
    z: float | None = None
    lon: float | None = None
    lat: float | None = None
    angles: tuple[float, float, float] | None = None
    temperature_c: float | None = None


@dataclass
class EoFile:
    path: Path
    crs: str
    convention: str | None
    has_temperature: bool
    records: dict[str, EoRecord] = field(default_factory=dict)


def read_eo_csv(
    path: str | Path, problems: ProblemLog, crs: str | None = None, default_attitude: str = "body_rpy"
) -> EoFile | None:
    """Parse an EO CSV; bad rows are reported by line; a file that cannot be used returns ``None``."""
    path = Path(path)
    text = read_text_lines(path, problems)
    if text is None:
        return None
    if not text.lines:
        problems.error(path, "has no header and no rows; ignored")
        return None
    header_line, header_text = text.lines[0]
    header = normalise_header(split_csv(header_text))
    c_img = find_column(header, IMAGE_COLUMNS)
    if c_img is None:
        problems.error(
            path,
            f"header {header_text.strip()[:80]!r} has no image column ({'/'.join(IMAGE_COLUMNS)}); ignored",
            "header",
            header_line,
        )
        return None
    c_lat, c_lon = find_column(header, LAT_COLUMNS), find_column(header, LON_COLUMNS)
    geographic = c_lat is not None and c_lon is not None
    if geographic:
        c1, c2 = c_lon, c_lat
    else:
        c1, c2 = find_column(header, X_COLUMNS), find_column(header, Y_COLUMNS)
    c3 = find_column(header, HEIGHT_COLUMNS)
    if c1 is None or c2 is None:
        problems.warning(
            path, "header has neither lat/lon nor x/y columns: positions not read", "header", header_line
        )
    angle_names: tuple[str, str, str] | None = None
    for names in (("roll", "pitch", "yaw"), ("omega", "phi", "kappa")):
        if all(n in header for n in names):
            angle_names = names
    c_ang = None if angle_names is None else [header.index(n) for n in angle_names]
    c_temp = find_column(header, TEMPERATURE_COLUMNS)
    for names in (("roll", "pitch", "yaw"), ("omega", "phi", "kappa")):
        present = [n for n in names if n in header]
        if present and len(present) < 3 and angle_names is None:
            missing = [n for n in names if n not in header]
            problems.blocker(
                path,
                f"header has {', '.join(present)} but no {', '.join(missing)}: angles come in threes, so no "
                "attitude is read from this file (the images' own attitude, if any, would be used instead). "
                f"Fix: name the columns {','.join(names)}",
                "header",
                header_line,
            )
    known = set(IMAGE_COLUMNS + LAT_COLUMNS + LON_COLUMNS + X_COLUMNS + Y_COLUMNS + HEIGHT_COLUMNS
                + TEMPERATURE_COLUMNS + ("roll", "pitch", "yaw", "omega", "phi", "kappa"))
    unknown = [f"{k + 1} ({name!r})" for k, name in enumerate(header) if name not in known]
    if unknown:
        problems.warning(path, f"column(s) {', '.join(unknown)} not known; ignored", "header", header_line)

    # CRS of the coordinates
    src_crs: str | None = None
    if "crs" in text.directives:
        value, line = text.directives["crs"]
        try:
            src_crs = normalise_crs(value)
        except CrsTextError as exc:
            problems.error(
                path, f"unknown CRS: {exc}; file ignored (write e.g. '# crs: EPSG:4326')", "crs", line
            )
            return None
    elif crs is not None:
        src_crs = crs
    elif geographic:
        src_crs = "EPSG:4326"
    elif c1 is not None:
        problems.error(
            path, "projected x/y columns but no '# crs: ...' line and no crs argument; file ignored", "crs"
        )
        return None
    kind = crs_kind(src_crs) if src_crs else "other"
    if geographic and kind == "projected":
        problems.error(path, f"lat/lon columns but the CRS {src_crs} is projected; file ignored", "crs")
        return None

    # attitude convention
    convention: str | None = None
    if c_ang is not None:
        convention = "opk" if angle_names == ("omega", "phi", "kappa") else default_attitude
        if "attitude" in text.directives:
            value, line = text.directives["attitude"]
            value = value.strip().lower()
            if value not in CONVENTIONS:
                problems.error(
                    path,
                    f"attitude convention {value!r} unknown (valid: {', '.join(CONVENTIONS)}); "
                    "angles ignored",
                    "attitude",
                    line,
                )
                c_ang, convention = None, None
            else:
                convention = value
        elif angle_names == ("roll", "pitch", "yaw"):
            problems.warning(
                path,
                f"no '# attitude: ...' line: roll/pitch/yaw read as {default_attitude} "
                f"(valid: {', '.join(CONVENTIONS)})",
                "attitude",
            )

    out = EoFile(path, src_crs or "EPSG:4326", convention, c_temp is not None)
    rows = keyed_rows(text, len(header), c_img, problems, out.records, "image name", "image", "row", "image ")
    for line, fields, name in rows:
        rec = EoRecord(line, name)

        def number(col: int | None, label: str, fields: list[str] = fields, line: int = line) -> float | None:
            if col is None or not fields[col]:
                return None
            value = to_float(fields[col])
            if value is None:
                problems.error(path, f"{label} {describe_bad_number(fields[col])}; not applied", label, line)
            return value

        xyz = [
            number(c, h)
            for c, h in (
                (c1, header[c1] if c1 is not None else "x"),
                (c2, header[c2] if c2 is not None else "y"),
                (c3, header[c3] if c3 is not None else "z"),
            )
        ]
        bad_pos = any(
            c is not None and fields[c] and v is None for c, v in zip((c1, c2), xyz[:2], strict=True)
        )
        if not bad_pos and xyz[0] is not None and xyz[1] is not None:
            if kind == "geographic" and not (
                in_range(xyz[0], *PLAUSIBLE_RANGES["lon"]) and in_range(xyz[1], *PLAUSIBLE_RANGES["lat"])
            ):
                problems.error(
                    path,
                    f"position lat={xyz[1]}, lon={xyz[0]} is outside the globe; not applied",
                    "lat/lon",
                    line,
                )
            else:
                rec.x, rec.y, rec.z = xyz
        if c_ang is not None and angle_names is not None:
            values = [number(c, n) for c, n in zip(c_ang, angle_names, strict=True)]
            present = [fields[c] != "" for c in c_ang]
            if all(v is not None for v in values):
                lims = ((-180.0, 180.0), (-180.0, 180.0), (-360.0, 360.0))
                if all(lo <= v <= hi for v, (lo, hi) in zip(values, lims, strict=True)):  # type: ignore[operator]
                    rec.angles = (values[0], values[1], values[2])  # type: ignore[assignment]
                else:
                    problems.error(
                        path, f"angles {values} deg are outside their ranges; not applied", "attitude", line
                    )
            elif any(present) and all(v is not None or not p for v, p in zip(values, present, strict=True)):
                problems.error(path, "attitude incomplete (some angles empty); not applied", "attitude", line)
        t = number(c_temp, "temperature")
        if t is not None:
            if -60.0 <= t <= 120.0:
                rec.temperature_c = t
            else:
                problems.error(path, f"temperature {t} degC is implausible; not applied", "temperature", line)
        out.records[name] = rec
    _to_wgs84(out)
    return out


def _to_wgs84(eo: EoFile) -> None:
    recs = [r for r in eo.records.values() if r.x is not None and r.y is not None]
    if not recs:
        return
    x = np.array([r.x for r in recs], dtype=float)
    y = np.array([r.y for r in recs], dtype=float)
    if eo.crs == "EPSG:4326":
        lon, lat = x, y
    else:
        lon, lat = transformer(eo.crs, "EPSG:4326").transform(x, y)
    for r, lo, la in zip(recs, np.asarray(lon), np.asarray(lat), strict=True):
        if np.isfinite(lo) and np.isfinite(la):
            r.lon, r.lat = float(lo), float(la)
