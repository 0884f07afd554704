"""Ground control as read from one file, before it is checked against the images and projected."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass
class GcpCoordinate:
    """A GCP's coordinates in its file's CRS (metres, or degrees x = lon, y = lat for geographic CRSs)."""

    gcp_id: str
    x: float
    y: float
    z: float
    file: Path
    line: int
    sigma_xy: float | None = None
    sigma_z: float | None = None
    role: str | None = None


@dataclass
class GcpMeasurement:
    """One image measurement of a GCP, in aerocal pixels (origin at the top-left corner of the image)."""

    gcp_id: str
    image: str
    x: float
    y: float
    file: Path
    line: int


@dataclass
class GcpFile:
    """The content of one GCP file: ``kind`` "odm" (gcp_list.txt) or "csv" (coordinate list)."""

    path: Path
    kind: str
    crs: str
    points: dict[str, GcpCoordinate] = field(default_factory=dict)
    measurements: list[GcpMeasurement] = field(default_factory=list)
    heights_unknown: bool = False  # every height 0.0, or no height column
    heights_absent: bool = False  # no height column at all (already reported when read)
    first_data_line: int | None = None
    last_data_line: int | None = None
