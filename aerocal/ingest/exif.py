"""EXIF fields ingest uses: camera identity, capture time, GNSS position, image layout of TIFF files.

Reads IFD0, the EXIF sub-IFD (tag 34665) and the GPS sub-IFD (tag 34853) of a
:class:`~aerocal.ingest.tiff.TiffStructure` (the EXIF block of a JPEG's APP1 segment, or a TIFF file).
Values of the wrong type (a latitude stored as text, a make stored as a number) are not guessed at:
the field is left empty and a note says which tag and type were found.

Tag numbers are those of EXIF 2.32 (CIPA DC-008): Make 271, Model 272, Orientation 274, XMP 700,
DateTimeOriginal 0x9003, OffsetTimeOriginal 0x9011, SubSecTimeOriginal 0x9291, FocalLength 0x920A,
Temperature 0x9400 (ambient), BodySerialNumber 0xA431, LensModel 0xA434, MakerNote 0x927C;
GPS: LatitudeRef 1, Latitude 2, LongitudeRef 3, Longitude 4, AltitudeRef 5, Altitude 6, TimeStamp 7,
DateStamp 29. Altitude in EXIF GPS is referenced to sea level (EXIF 2.32, GPSAltitudeRef).
"""

from __future__ import annotations

import datetime as dt
import math
import re
from dataclasses import dataclass, field

from aerocal.ingest.tiff import (
    IfdEntry,
    TiffStructure,
    entry_bytes,
    entry_int,
    entry_numbers,
    entry_text,
)

TAG_MAKE, TAG_MODEL, TAG_ORIENTATION, TAG_XMP = 271, 272, 274, 700
TAG_EXIF_IFD, TAG_GPS_IFD = 34665, 34853
TAG_DATETIME_ORIGINAL, TAG_OFFSET_TIME_ORIGINAL, TAG_SUBSEC_ORIGINAL = 0x9003, 0x9011, 0x9291
TAG_FOCAL_LENGTH, TAG_AMBIENT_TEMPERATURE = 0x920A, 0x9400
TAG_BODY_SERIAL, TAG_LENS_MODEL, TAG_MAKER_NOTE = 0xA431, 0xA434, 0x927C
# TIFF image layout
TAG_WIDTH, TAG_HEIGHT, TAG_BITS, TAG_COMPRESSION, TAG_SAMPLES = 256, 257, 258, 259, 277
TAG_STRIP_OFFSETS, TAG_STRIP_COUNTS, TAG_TILE_OFFSETS, TAG_TILE_COUNTS = 273, 279, 324, 325
TAG_SAMPLE_FORMAT = 339

_DATETIME_RE = re.compile(r"^(\d{4})[:\-](\d{2})[:\-](\d{2})[ T](\d{2}):(\d{2}):(\d{2})")
_OFFSET_RE = re.compile(r"^([+-])(\d{2}):?(\d{2})$")


@dataclass
class ExifData:
    """EXIF fields of one image; ``None`` where absent or unusable (``notes`` says why)."""

    make: str | None = None
    model: str | None = None
    serial: str | None = None
    lens: str | None = None
    orientation: int | None = None
    datetime_original: dt.datetime | None = None  # naive, camera clock
    utc_offset: dt.timedelta | None = None  # from OffsetTimeOriginal
    gps_lat: float | None = None
    gps_lon: float | None = None
    gps_alt: float | None = None  # above sea level per EXIF
    gps_utc: dt.datetime | None = None  # GPSDateStamp + GPSTimeStamp (UTC)
    focal_length_mm: float | None = None
    ambient_temperature_c: float | None = None
    maker_note: IfdEntry | None = None
    xmp_packet: bytes | None = None
    ifd0: dict[int, IfdEntry] = field(default_factory=dict)
    tiff: TiffStructure | None = None  # the structure the maker note's offsets refer to
    notes: list[tuple[str, str]] = field(default_factory=list)  # (field, message)


def parse_exif_datetime(text: str | None) -> dt.datetime | None:
    """``"YYYY:MM:DD HH:MM:SS"`` (EXIF) or ISO ``YYYY-MM-DDTHH:MM:SS`` -> naive datetime, else ``None``."""
    if not text:
        return None
    m = _DATETIME_RE.match(text.strip())
    if not m:
        return None
    try:
        return dt.datetime(*(int(g) for g in m.groups()))
    except ValueError:
        return None


def parse_utc_offset(text: str | None) -> dt.timedelta | None:
    """``"+02:00"`` / ``"-0400"`` -> timedelta (``None`` if absent or malformed, or beyond +-14 h)."""
    if not text:
        return None
    m = _OFFSET_RE.match(text.strip())
    if not m:
        return None
    sign = -1 if m.group(1) == "-" else 1
    hours, minutes = int(m.group(2)), int(m.group(3))
    if hours > 14 or minutes >= 60:
        return None
    return sign * dt.timedelta(hours=hours, minutes=minutes)


def _dms(values: tuple[float, ...] | None) -> float | None:
    if values is None or len(values) != 3 or not all(math.isfinite(v) for v in values):
        return None
    return values[0] + values[1] / 60.0 + values[2] / 3600.0


def read_exif(tiff: TiffStructure) -> ExifData:
    """Interpret IFD0, EXIF and GPS IFDs of ``tiff``."""
    out = ExifData(tiff=tiff)
    chain = tiff.ifd_chain()
    ifd0 = chain[0] if chain else {}
    out.ifd0 = ifd0
    exif = tiff.sub_ifd(ifd0, TAG_EXIF_IFD, "EXIF IFD")
    gps = tiff.sub_ifd(ifd0, TAG_GPS_IFD, "GPS IFD")

    def text(ifd: dict[int, IfdEntry], tag: int, name: str) -> str | None:
        value = entry_text(ifd, tag)
        if value is None and tag in ifd:
            out.notes.append((name, f"has type {ifd[tag].type_name}, expected ASCII text; ignored"))
        return value

    out.make = text(ifd0, TAG_MAKE, "Make")
    out.model = text(ifd0, TAG_MODEL, "Model")
    out.orientation = entry_int(ifd0, TAG_ORIENTATION)
    # some writers put EXIF tags in IFD0: accept them there when the EXIF IFD lacks them
    merged = {**ifd0, **exif}
    out.serial = text(merged, TAG_BODY_SERIAL, "BodySerialNumber")
    out.lens = text(merged, TAG_LENS_MODEL, "LensModel")
    raw_time = text(merged, TAG_DATETIME_ORIGINAL, "DateTimeOriginal")
    out.datetime_original = parse_exif_datetime(raw_time)
    if raw_time and out.datetime_original is None:
        out.notes.append(
            ("DateTimeOriginal", f"value {raw_time!r} is not a valid 'YYYY:MM:DD HH:MM:SS'; ignored")
        )
    subsec = text(merged, TAG_SUBSEC_ORIGINAL, "SubSecTimeOriginal")
    if out.datetime_original is not None and subsec:
        digits = subsec.strip()
        if digits.isdigit():
            out.datetime_original += dt.timedelta(seconds=int(digits) / 10 ** len(digits))
        else:
            out.notes.append(("SubSecTimeOriginal", f"value {subsec!r} is not digits; ignored"))
    raw_offset = text(merged, TAG_OFFSET_TIME_ORIGINAL, "OffsetTimeOriginal")
    out.utc_offset = parse_utc_offset(raw_offset)
    if raw_offset and out.utc_offset is None:
        out.notes.append(("OffsetTimeOriginal", f"value {raw_offset!r} is not '+HH:MM'; ignored"))
    focal = entry_numbers(merged, TAG_FOCAL_LENGTH)
    if focal and math.isfinite(focal[0]) and focal[0] > 0:
        out.focal_length_mm = focal[0]
    ambient = entry_numbers(merged, TAG_AMBIENT_TEMPERATURE)
    if ambient and math.isfinite(ambient[0]):
        out.ambient_temperature_c = ambient[0]
    out.maker_note = merged.get(TAG_MAKER_NOTE)
    out.xmp_packet = entry_bytes(ifd0, TAG_XMP)
    _read_gps(gps, out)
    return out


def _read_gps(gps: dict[int, IfdEntry], out: ExifData) -> None:
    if not gps:
        return
    for tag, name in ((2, "GPSLatitude"), (4, "GPSLongitude"), (6, "GPSAltitude"), (7, "GPSTimeStamp")):
        entry = gps.get(tag)
        if entry is not None and entry.type not in (5, 10):
            out.notes.append((name, f"has type {entry.type_name}, expected RATIONAL; ignored"))
    lat = _dms(entry_numbers(gps, 2)) if gps.get(2) and gps[2].type in (5, 10) else None
    lon = _dms(entry_numbers(gps, 4)) if gps.get(4) and gps[4].type in (5, 10) else None
    lat_ref = (entry_text(gps, 1) or "N").upper()[:1]
    lon_ref = (entry_text(gps, 3) or "E").upper()[:1]
    if lat is not None and lon is not None:
        out.gps_lat = -lat if lat_ref == "S" else lat
        out.gps_lon = -lon if lon_ref == "W" else lon
    alt = entry_numbers(gps, 6) if gps.get(6) and gps[6].type in (5, 10) else None
    if alt and math.isfinite(alt[0]):
        ref = gps.get(5)
        below = False
        if ref is not None and isinstance(ref.value, bytes):
            below = ref.value[:1] == b"\x01"
        elif ref is not None and isinstance(ref.value, tuple) and ref.value:
            below = int(ref.value[0]) == 1
        out.gps_alt = -alt[0] if below else alt[0]
    stamp = entry_numbers(gps, 7) if gps.get(7) and gps[7].type in (5, 10) else None
    day = entry_text(gps, 29)
    if stamp and len(stamp) == 3 and day and all(math.isfinite(v) for v in stamp):
        base = parse_exif_datetime(f"{day.strip()} 00:00:00")
        if base is not None and 0 <= stamp[0] < 24 and 0 <= stamp[1] < 60 and 0 <= stamp[2] < 61:
            out.gps_utc = base + dt.timedelta(hours=stamp[0], minutes=stamp[1], seconds=stamp[2])
