"""Nominal cameras of thermal (and a few survey) cameras, for flights that come without ``camera.json``.

A flight straight off the drone carries the make, the model, often the focal length (EXIF FocalLength)
and the frame size, but never the pixel pitch, which turns millimetres into pixels. This table holds
the manufacturers' published specifications (sensor size in pixels, pixel pitch, the fixed lens's focal
length or the lenses offered, the readout), entered from their product pages and not checked against a
data sheet kept in this repository: each nominal camera says so, and a ``camera.json`` overrides it.
:func:`nominal_camera` builds the nominal :class:`~aerocal.camera.Camera` from it and says which value
came from where. Nothing here is a
calibration: it is the starting point a self-calibration or a certificate improves on, checked the same
way as a hand-written ``camera.json``.

Focal length, in order: the image's EXIF FocalLength when it agrees with the camera (a lens on offer,
or within 10 % of the fixed lens); else the FLIR FFF field of view (``f = (w / 2) / tan(fov / 2)``);
else the fixed lens. A camera with interchangeable lenses and neither of the first two is not guessed.

A camera not in the catalogue (a visible or compact camera) is built from what its files say, in order:

1. EXIF FocalLength over the pixel pitch of EXIF FocalPlaneXResolution (scaled by ingest to the width the
   image is stored at, :mod:`aerocal.ingest.metadata`): the camera's own statement of its sensor;
2. EXIF FocalLengthIn35mmFilm over the 36 mm long side of 35 mm film, ``f = f35 / 36 * max(w, h)`` (the
   convention OpenSfM and OpenDroneMap use; makers that scale by the diagonal give 4 % less on a 4:3
   sensor, within the nominal tolerance of :func:`aerocal.certificates.review.nominal_sigma`);
3. EXIF FocalLength over the pixel pitch of the sensor-width table ``data/sensor_widths.csv``.

The catalogue comes first for the cameras it holds: its pitch is the maker's, where a thermal camera's
35-mm equivalent is rounded to whole millimetres (a DJI H20T records 58 mm: 1031 px where its 13.5 mm lens
on 12 um pixels is 1125 px).

Principal point at the frame centre: ``cx = width / 2``, ``cy = height / 2`` in pixels from the top-left
corner of the top-left pixel (:class:`aerocal.camera.Camera`'s convention).
"""

from __future__ import annotations

import csv
import functools
import math
import re
from dataclasses import dataclass
from importlib import resources

from aerocal.camera import Camera

#: readout kinds: a microbolometer is read line by line while each pixel integrates with a thermal time
#: constant of ~10 ms, so its image of a moving scene is sheared like a rolling shutter's
READOUTS = ("global", "rolling", "microbolometer")


@dataclass(frozen=True)
class CatalogueCamera:
    """One camera (one sensor format) of the catalogue. Lengths in millimetres / micrometres."""

    name: str
    make: str  # EXIF Make, compared case-insensitively
    models: tuple[str, ...]  # EXIF Model strings (compared without case, spaces, '-' and '_')
    width: int
    height: int
    pixel_pitch_um: float
    focal_mm: float | None  # the fixed lens; None when lenses are interchangeable
    lenses_mm: tuple[float, ...] = ()  # lenses on offer (interchangeable lenses)
    readout: str = "microbolometer"
    source: str = "published specification, not checked against a data sheet here"

    def __post_init__(self) -> None:
        if self.readout not in READOUTS:
            raise ValueError(f"camera {self.name}: readout {self.readout!r} unknown; valid: {', '.join(READOUTS)}")
        if not (self.width > 0 and self.height > 0 and self.pixel_pitch_um > 0):
            raise ValueError(f"camera {self.name}: size and pixel pitch must be > 0")


def _tau(name: str, models: tuple[str, ...], width: int = 640, height: int = 512) -> CatalogueCamera:
    """A FLIR Tau 2 based camera (17 um; lenses 9, 13, 19, 25 mm; 6.8 and 7.5 mm on the 336 format)."""
    lenses = (9.0, 13.0, 19.0, 25.0) if width == 640 else (6.8, 7.5, 9.0, 13.0, 19.0)
    return CatalogueCamera(name, "DJI" if name.startswith("DJI") else "FLIR", models, width, height, 17.0, None,
                           lenses)


CATALOGUE: tuple[CatalogueCamera, ...] = (
    # DJI Zenmuse XT and XT2 write EXIF Model "FLIR" (XT) or "XT2"; both are FLIR Tau 2 cores
    _tau("DJI Zenmuse XT/XT2 640", ("FLIR", "XT", "XT2", "ZENMUSEXT", "ZENMUSEXT2")),
    _tau("DJI Zenmuse XT/XT2 336", ("FLIR", "XT", "XT2", "ZENMUSEXT", "ZENMUSEXT2"), 336, 256),
    CatalogueCamera("DJI Zenmuse XT S", "DJI", ("XTS",), 640, 512, 17.0, 19.0),
    CatalogueCamera("DJI Zenmuse H20T", "DJI", ("ZH20T", "H20T"), 640, 512, 12.0, 13.5),
    CatalogueCamera("DJI Zenmuse H20N (thermal)", "DJI", ("ZH20N", "H20N"), 640, 512, 12.0, None),
    CatalogueCamera("DJI Zenmuse H30T (thermal)", "DJI", ("H30T", "ZH30T"), 1280, 1024, 12.0, 24.0),
    CatalogueCamera("DJI Mavic 2 Enterprise Advanced (thermal)", "DJI", ("MAVIC2ENTERPRISEADVANCED", "M2EA"),
                    640, 512, 12.0, 9.0),
    CatalogueCamera("DJI Matrice 30T (thermal)", "DJI", ("M30T",), 640, 512, 12.0, 9.1),
    CatalogueCamera("DJI Mavic 3 Thermal (thermal)", "DJI", ("M3T",), 640, 512, 12.0, 9.1),
    _tau("FLIR Vue Pro R 640", ("VUEPROR640", "VUEPROR", "VUEPRO640", "VUEPRO")),
    _tau("FLIR Vue Pro R 336", ("VUEPROR336", "VUEPROR", "VUEPRO336", "VUEPRO"), 336, 256),
    _tau("FLIR Duo Pro R 640", ("DUOPROR640", "DUOPROR", "DUOPRO")),
    _tau("FLIR Duo Pro R 336", ("DUOPROR336", "DUOPROR", "DUOPRO"), 336, 256),
    CatalogueCamera("FLIR Boson 640", "FLIR", ("BOSON", "BOSON640"), 640, 512, 12.0, None,
                    (4.9, 6.3, 8.7, 14.0, 18.0, 24.0, 36.0)),
    CatalogueCamera("NEC TS9260", "NEC", ("TS9260",), 640, 480, 23.5, 39.2,
                    source="Conte et al. 2018 (the seed paper's camera)"),
)


def _norm(text: str | None) -> str:
    return re.sub(r"[\s\-_/]", "", (text or "")).upper()


def lookup(make: str | None, model: str | None, width: int, height: int) -> CatalogueCamera | None:
    """The catalogue entry of this make, model and raw frame size, or ``None``."""
    m, mk = _norm(model), _norm(make)
    for cam in CATALOGUE:
        if (cam.width, cam.height) != (width, height) or _norm(cam.make) not in mk:
            continue
        if m in cam.models:
            return cam
    return None


@dataclass(frozen=True)
class NominalCamera:
    """A nominal camera built from the catalogue, with where each value came from (or why there is none)."""

    camera: Camera | None
    entry: CatalogueCamera | None
    focal_source: str
    reason: str  # one sentence: what was used, or what is missing and the fix


def nominal_camera(
    make: str | None,
    model: str | None,
    width: int,
    height: int,
    exif_focal_mm: float | None = None,
    field_of_view_deg: float | None = None,
    pixel_pitch_mm: float | None = None,
    focal_35mm: float | None = None,
) -> NominalCamera:
    """The nominal camera of one camera as its images describe it (module docstring for the rules).

    ``exif_focal_mm``: EXIF FocalLength (mm); ``field_of_view_deg``: the FLIR FFF horizontal field of view;
    ``pixel_pitch_mm``: the pitch of the stored pixels from FocalPlaneXResolution (mm); ``focal_35mm``: EXIF
    FocalLengthIn35mmFilm (mm). Returns the camera (``None`` with the reason where the images do not tell)."""
    entry = lookup(make, model, width, height)
    if entry is None:
        return _from_exif(make, model, width, height, exif_focal_mm, pixel_pitch_mm, focal_35mm)
    pitch_mm = entry.pixel_pitch_um / 1000.0
    focal_mm, source = None, ""
    if exif_focal_mm and math.isfinite(exif_focal_mm) and exif_focal_mm > 0:
        known = entry.lenses_mm or ((entry.focal_mm,) if entry.focal_mm else ())
        if any(abs(exif_focal_mm - lens) <= 0.1 * lens for lens in known) or not known:
            focal_mm, source = float(exif_focal_mm), "EXIF FocalLength"
    f_px = None if focal_mm is None else focal_mm / pitch_mm
    if f_px is None and field_of_view_deg and 1.0 < field_of_view_deg < 170.0:
        f_px, source = (width / 2.0) / math.tan(math.radians(field_of_view_deg) / 2.0), "FLIR field of view"
    if f_px is None and entry.focal_mm:
        f_px, source = entry.focal_mm / pitch_mm, "the fixed lens of the data sheet"
    if f_px is None:
        lenses = ", ".join(f"{v:g}" for v in entry.lenses_mm)
        return NominalCamera(
            None, entry, "",
            f"{entry.name} takes interchangeable lenses ({lenses} mm) and the images record no focal length",
        )
    camera = Camera(width=width, height=height, f=float(f_px), cx=width / 2.0, cy=height / 2.0, pixel_size_mm=pitch_mm)
    reason = (
        f"nominal camera of the {entry.name} from aerocal's camera catalogue: {width}x{height}, pixel pitch "
        f"{entry.pixel_pitch_um:g} um ({entry.source}), f {f_px:.1f} px from {source}, principal point at the "
        f"frame centre, no distortion, {entry.readout} readout"
    )
    return NominalCamera(camera, entry, source, reason)


@dataclass(frozen=True)
class SensorWidth:
    """A row of ``data/sensor_widths.csv``: the long side of a camera's sensor (mm) and its format."""

    make: str
    model: str
    width_mm: float
    format: str


@functools.cache
def sensor_widths() -> tuple[SensorWidth, ...]:
    """The sensor-width table (``aerocal/ingest/data/sensor_widths.csv``; its header says where it comes from)."""
    text = resources.files("aerocal.ingest").joinpath("data/sensor_widths.csv").read_text(encoding="utf-8")
    rows = csv.DictReader(line for line in text.splitlines() if not line.startswith("#"))
    return tuple(SensorWidth(r["make"], r["model"], float(r["sensor_width_mm"]), r["format"]) for r in rows)


def sensor_width(make: str | None, model: str | None) -> SensorWidth | None:
    """The table's row of this make and model (compared without case, spaces, '-', '_' and '/'), or ``None``."""
    m, mk = _norm(model), _norm(make)
    return next((row for row in sensor_widths() if _norm(row.model) == m and _norm(row.make) in mk), None)


def _valid(value: float | None) -> bool:
    return value is not None and math.isfinite(value) and value > 0


def _from_exif(make: str | None, model: str | None, width: int, height: int, focal_mm: float | None,
               pitch_mm: float | None, focal_35mm: float | None) -> NominalCamera:
    """The nominal camera of a camera the catalogue does not hold, from its EXIF (module docstring)."""
    what = f"{make or '?'} {model or '?'} ({width}x{height})"
    long_side = max(width, height)
    row = sensor_width(make, model)
    if _valid(focal_mm) and _valid(pitch_mm):
        f_px, source = focal_mm / pitch_mm, (f"EXIF FocalLength {focal_mm:g} mm over the pixel pitch "
                                             f"{pitch_mm * 1000:.4g} um of EXIF FocalPlaneXResolution at the "
                                             f"stored width {width} px")
    elif _valid(focal_35mm):
        f_px, source = focal_35mm / 36.0 * long_side, (f"EXIF FocalLengthIn35mmFilm {focal_35mm:g} mm over the "
                                                       "36 mm long side of 35 mm film")
        pitch_mm = focal_mm / f_px if _valid(focal_mm) else None
    elif _valid(focal_mm) and row is not None:
        pitch_mm = row.width_mm / long_side
        f_px, source = focal_mm / pitch_mm, (f"EXIF FocalLength {focal_mm:g} mm over the pixel pitch "
                                             f"{pitch_mm * 1000:.4g} um of a {row.width_mm:g} mm wide "
                                             f"{row.format} sensor (aerocal's sensor-width table)")
    else:
        missing = "no focal length (EXIF FocalLength)" if not _valid(focal_mm) else \
            "no pixel pitch (EXIF FocalPlaneXResolution), no 35 mm equivalent (FocalLengthIn35mmFilm)"
        return NominalCamera(None, None, "", f"camera {what} is not in aerocal's camera catalogue or sensor-width "
                             f"table, and the images record {missing}")
    camera = Camera(width=width, height=height, f=float(f_px), cx=width / 2.0, cy=height / 2.0,
                    pixel_size_mm=pitch_mm if _valid(pitch_mm) else None)
    reason = (f"nominal camera of the {what} from its images: f {f_px:.1f} px from {source}, principal point "
              "at the frame centre, no distortion, readout unknown")
    return NominalCamera(camera, None, source, reason)
