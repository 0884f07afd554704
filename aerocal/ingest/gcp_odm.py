"""OpenDroneMap ``gcp_list.txt``: ground control coordinates with their image measurements.

Format (whitespace separated, ``#`` comments allowed)::

    <CRS>                      EPSG:xxxx | a PROJ string | WGS84 UTM 11N | WGS84
    X Y Z px py image [label]  one image measurement per line; extra columns after the label are ignored

X/Y/Z are in the CRS of the first line (for geographic CRSs X = longitude, Y = latitude, as ODM writes
them). Pixels ``px py`` count from the top-left of the image with the centre of the first pixel at
(0, 0), as OpenSfM reads them; ``IngestConfig.odm_pixel_offset_px`` (0.5) moves them to aerocal's
corner convention. Lines without a label belong to the point with identical coordinates (OpenSfM's
rule) and get the id ``unlabelled-<n>``.
"""

from __future__ import annotations

from pathlib import Path

from aerocal.ingest.config import IngestConfig
from aerocal.ingest.crs_strings import CrsTextError, normalise_crs
from aerocal.ingest.delimited import read_text_lines, split_whitespace
from aerocal.ingest.gcp_records import GcpCoordinate, GcpFile, GcpMeasurement
from aerocal.ingest.numbers import describe_bad_number, to_float
from aerocal.ingest.problems import ProblemLog

ODM_FORMAT = "'X Y Z px py image [label]'"
_COLUMNS = ("X", "Y", "Z", "px", "py")


def looks_like_data_line(fields: list[str]) -> bool:
    return len(fields) >= 3 and to_float(fields[0]) is not None and to_float(fields[1]) is not None


def read_odm_gcp_list(
    path: str | Path, problems: ProblemLog, config: IngestConfig | None = None
) -> GcpFile | None:
    """Parse a ``gcp_list.txt``; bad lines are reported and skipped, an unusable file returns ``None``."""
    cfg = config or IngestConfig()
    path = Path(path)
    text = read_text_lines(path, problems)
    if text is None:
        return None
    if not text.lines:
        problems.error(path, "is empty; expected a CRS line then " + ODM_FORMAT + " lines; ignored")
        return None
    crs_line, crs_text = text.lines[0]
    if looks_like_data_line(split_whitespace(crs_text)):
        problems.error(
            path,
            "the first line must name the CRS (e.g. 'EPSG:32611' or 'WGS84 UTM 11N'), found a data line; "
            "file ignored",
            "crs",
            crs_line,
        )
        return None
    try:
        crs = normalise_crs(crs_text)
    except CrsTextError as exc:
        problems.error(path, f"unknown CRS: {exc}; file ignored", "crs", crs_line)
        return None
    out = GcpFile(path, "odm", crs)
    by_coords: dict[tuple[float, float, float], str] = {}
    n_unlabelled = 0
    offset = cfg.odm_pixel_offset_px
    for line, raw in text.lines[1:]:
        fields = split_whitespace(raw)
        if len(fields) < 6:
            hint = ""
            if len(fields) == 4 and to_float(fields[0]) is None:
                hint = (
                    " (looks like 'label X Y Z': coordinates without image measurements belong in a GCP CSV "
                    "'id,X,Y,Z')"
                )
            elif len(fields) == 3 and to_float(fields[0]) is not None and to_float(fields[2]) is None:
                hint = " (looks like 'px py image': image measurements without coordinates)"
            problems.error(
                path,
                f"has {len(fields)} columns, expected {ODM_FORMAT} (6 or 7){hint}; line ignored",
                "columns",
                line,
            )
            continue
        values = [to_float(f) for f in fields[:5]]
        bad = [(name, f) for name, f, v in zip(_COLUMNS, fields[:5], values, strict=True) if v is None]
        if bad:
            name, f = bad[0]
            problems.error(path, f"{name} {describe_bad_number(f)}; line ignored", name, line)
            continue
        x, y, z, px, py = values  # type: ignore[misc]
        image = fields[5]
        key = (x, y, z)
        if len(fields) >= 7:
            label = fields[6]
        elif key in by_coords:
            label = by_coords[key]
        else:
            n_unlabelled += 1
            label = f"unlabelled-{n_unlabelled}"
        point = out.points.get(label)
        if point is None:
            out.points[label] = GcpCoordinate(label, x, y, z, path, line)  # type: ignore[arg-type]
            by_coords.setdefault(key, label)  # type: ignore[arg-type]
        elif (point.x, point.y, point.z) != key:
            problems.error(
                path,
                f"{label} has coordinates ({x}, {y}, {z}) here but ({point.x}, {point.y}, {point.z}) on line "
                f"{point.line}; measurement ignored",
                "label",
                line,
            )
            continue
        out.first_data_line = out.first_data_line or line
        out.last_data_line = line
        out.measurements.append(GcpMeasurement(label, image, px + offset, py + offset, path, line))  # type: ignore[operator]
    if not out.measurements:
        problems.error(path, "no usable " + ODM_FORMAT + " line; file ignored")
        return None
    if all(p.z == 0.0 for p in out.points.values()):
        out.heights_unknown = True
    return out
