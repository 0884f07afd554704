"""EXIF fields ingest uses, read through Pillow: camera identity, capture time, GNSS position, TIFF layout.

Pillow's IFD reader (``PIL.TiffImagePlugin.ImageFileDirectory_v2``, what ``Image.getexif()`` and its
``get_ifd()`` use) parses the IFDs: byte order, classic TIFF and little-endian BigTIFF, every field type,
values stored out of line, rationals (``IFDRational``; a zero denominator reads NaN). It checks each value's
offset and length against the block and skips what does not fit with a ``UserWarning``; :func:`read_ifd`
turns those warnings into notes that ingest reports per file and field, and notes the entries Pillow dropped
without a word, so a damaged block is a message, never a traceback. Only IFD0 and the EXIF and GPS IFDs it
points to are read (no IFD chain is followed, so no input can make it loop), and of the EXIF IFD only the
tags used here are decoded.

Compared with the struct reader this replaced: the same values on every image of ``shared/data``; from a
damaged IFD Pillow keeps less (it stops reading an IFD at the first value outside the block, and skips every
later out-of-line value once one entry claims more bytes than the block holds, where the struct reader
skipped the one entry), and it does not read big-endian BigTIFF.

This module only interprets the values. A value of the wrong kind (a latitude stored as text, a make stored
as a number) is not guessed at: the field is left empty and a note says which tag held what.

Tags (EXIF 2.32, CIPA DC-008; Pillow's :mod:`PIL.ExifTags` names them): Make, Model, Orientation and XMLPacket
(700) in IFD0; DateTimeOriginal, SubsecTimeOriginal, OffsetTimeOriginal, FocalLength, FocalLengthIn35mmFilm,
FocalPlaneXResolution with FocalPlaneResolutionUnit and ExifImageWidth (the pixel pitch at the width the camera
recorded), AmbientTemperature (0x9400), BodySerialNumber, LensModel and MakerNote in the EXIF IFD (also accepted in
IFD0, where some writers put them); GPSLatitude(Ref), GPSLongitude(Ref), GPSAltitude(Ref), GPSTimeStamp and
GPSDateStamp in the GPS IFD. Altitude in EXIF GPS is referenced to sea level (EXIF 2.32, GPSAltitudeRef).
"""

from __future__ import annotations

import datetime as dt
import io
import math
import re
import struct
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from PIL.ExifTags import GPS, IFD, Base
from PIL.TiffImagePlugin import IFDRational, ImageFileDirectory_v2

T = TypeVar("T")

TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
BIGTIFF_MAGICS = (b"II+\x00", b"MM\x00+")
_DATETIME_RE = re.compile(r"^(\d{4})[:\-](\d{2})[:\-](\d{2})[ T](\d{2}):(\d{2}):(\d{2})")
_OFFSET_RE = re.compile(r"^([+-])(\d{2}):?(\d{2})$")


class ExifFormatError(ValueError):
    """The bytes do not start with a TIFF header, so Pillow cannot read them as IFDs."""


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
    focal_length_35mm: float | None = None  # FocalLengthIn35mmFilm (mm)
    #: the sensor's pixel pitch in mm at the width ``exif_image_width`` (FocalPlaneXResolution and its unit)
    focal_plane_pitch_mm: float | None = None
    exif_image_width: int | None = None  # ExifImageWidth (PixelXDimension): the width the pitch refers to
    ambient_temperature_c: float | None = None
    maker_note: bytes | None = None
    xmp_packet: bytes | None = None
    block: bytes = b""  # the TIFF bytes the IFD offsets (and a Canon maker note's) count from
    notes: list[tuple[str, str]] = field(default_factory=list)  # (field, message)


def capture_pillow_warnings(fn: Callable[[], T], notes: list[tuple[str, str]], field_name: str) -> T:
    """``fn()`` with the ``UserWarning``\\ s Pillow emits for corrupt IFD data appended to ``notes``.

    ``warnings.catch_warnings`` swaps the process-wide warning filters for the call (it is not thread-safe);
    ingest reads its files one after the other in one thread.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = fn()
    for w in caught:
        notes.append((field_name, "Pillow: " + " ".join(str(w.message).split())))
    return result


def read_ifd(
    block: bytes,
    offset: int,
    notes: list[tuple[str, str]],
    name: str,
    field_name: str,
    group: int | None = None,
    wanted: tuple[int, ...] | None = None,
) -> tuple[dict[int, Any], dict[int, int]]:
    """The IFD at ``offset`` of the TIFF ``block``, read by Pillow: ``({tag: value}, {tag: TIFF type})``.

    Values are those of Pillow's ``Image.getexif()`` (``str`` for ASCII, ``bytes`` for BYTE/UNDEFINED, an
    ``int`` or ``IFDRational``, a tuple of them when there are several); only the ``wanted`` tags are decoded,
    all when ``None``. ``group`` is Pillow's tag table for the IFD (``IFD.Exif``, ``IFD.GPSInfo``; ``None`` for IFD0).
    Pillow's warnings and entries it dropped become ``notes`` under ``field_name``; ``name`` says which IFD.
    """
    bigtiff = block[:4] in BIGTIFF_MAGICS
    ifd = ImageFileDirectory_v2(block[:16] if bigtiff else block[:8], group=group)  # byte order, BigTIFF
    fp = io.BytesIO(block)
    fp.seek(offset)

    def load() -> dict[int, Any]:
        ifd.load(fp)
        values = {int(tag): ifd[tag] for tag in (list(ifd) if wanted is None else wanted) if tag in ifd}
        # one value unwrapped from its tuple, as Image.getexif() and its get_ifd() give it
        return {tag: v[0] if isinstance(v, tuple) and len(v) == 1 else v for tag, v in values.items()}

    values = capture_pillow_warnings(load, notes, field_name)
    size = 8 if bigtiff else 2
    if 0 <= offset <= len(block) - size:
        # Pillow skips an entry of unknown type without a warning, and stops reading the IFD at the first
        # value that runs past the block; the count the IFD declares shows both
        endian = "<" if block[:2] == b"II" else ">"
        declared = struct.unpack_from(endian + ("Q" if bigtiff else "H"), block, offset)[0]
        if len(ifd) < declared:
            notes.append(
                (
                    field_name,
                    f"{name} at byte {offset} declares {declared} entries, Pillow read {len(ifd)} (it skips an "
                    "entry of unknown type, and stops at a value that lies outside the block); the others are "
                    "ignored",
                )
            )
    return values, dict(ifd.tagtype)


def load_exif(data: bytes, notes: list[tuple[str, str]], field_name: str = "EXIF") -> dict[int, Any]:
    """IFD0 of a TIFF structure (a JPEG's APP1 EXIF block without ``Exif\\0\\0``, or a whole TIFF file).

    Raises :class:`ExifFormatError` when ``data`` has no TIFF header, or is a big-endian BigTIFF (Pillow 13
    takes the version from byte 2 of the header, which is 0 there, and reads it as a classic TIFF); damage
    past the header becomes notes.
    """
    if data[:4] not in TIFF_MAGICS or len(data) < (16 if data[:4] in BIGTIFF_MAGICS else 8):
        raise ExifFormatError(f"no TIFF header (starts with {data[:4]!r})")
    if data[:4] == b"MM\x00+":
        raise ExifFormatError("big-endian BigTIFF, which Pillow's TIFF reader does not read")
    first = ImageFileDirectory_v2(data[:16] if data[:4] in BIGTIFF_MAGICS else data[:8]).next
    if not 8 <= first < len(data):
        raise ExifFormatError(f"first IFD offset {first} lies outside the {len(data)}-byte block")
    try:
        return read_ifd(data, first, notes, "IFD0", field_name)[0]
    except Exception as exc:  # Pillow warns on most damage, but a header it accepts can still fail to unpack
        raise ExifFormatError(f"Pillow cannot read IFD0 ({type(exc).__name__}: {exc})") from exc


def sub_ifd(
    ifd0: dict[int, Any], block: bytes, tag: IFD, notes: list[tuple[str, str]], wanted: tuple[int, ...] | None = None
) -> dict[int, Any]:
    """The EXIF or GPS IFD IFD0 points to, as ``{tag: value}`` (``{}`` when absent or unreadable, noted)."""
    name = "EXIF IFD" if tag == IFD.Exif else "GPS IFD"
    pointer = ifd0.get(tag)
    if pointer is None:
        return {}
    if not isinstance(pointer, int) or pointer < 0:
        notes.append((name, f"{name} pointer (tag {int(tag)}) holds {_kind(pointer)}, expected an offset; ignored"))
        return {}
    try:
        return read_ifd(block, pointer, notes, name, name, group=tag, wanted=wanted)[0]
    except Exception as exc:  # Pillow raises several types on IFDs it cannot place (seek, struct)
        notes.append((name, f"{name} at byte {pointer} cannot be read ({type(exc).__name__}: {exc}); ignored"))
        return {}


def text_value(value: Any) -> str | None:
    """An ASCII (or UNDEFINED) value as text up to its first NUL, printable characters only, else ``None``."""
    if isinstance(value, bytes):
        value = value.decode("latin-1", errors="replace")
    if not isinstance(value, str):
        return None
    value = "".join(ch for ch in value.split("\x00", 1)[0] if ch.isprintable()).strip()
    return value or None


def int_values(value: Any) -> tuple[int, ...] | None:
    """An integer-typed value (one or several) as a tuple of ints, else ``None`` (rationals, text, bytes)."""
    if isinstance(value, int) and not isinstance(value, bool):
        return (value,)
    if isinstance(value, tuple) and value and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return value
    return None


def number_values(value: Any) -> tuple[float, ...] | None:
    """A numeric value (integers, rationals, floats; one or several) as floats, else ``None``."""
    items = value if isinstance(value, tuple) else (value,)
    if not items or not all(isinstance(v, int | float | IFDRational) and not isinstance(v, bool) for v in items):
        return None
    return tuple(float(v) for v in items)


def _rationals(value: Any) -> tuple[float, ...] | None:
    """A RATIONAL/SRATIONAL value as floats (``None`` for any other type: EXIF GPS values are rationals)."""
    items = value if isinstance(value, tuple) else (value,)
    if not items or not all(isinstance(v, IFDRational) for v in items):
        return None
    return tuple(float(v) for v in items)


def _kind(value: Any) -> str:
    """What a value is, for a message."""
    if isinstance(value, str):
        return f"text {value[:40]!r}"
    if isinstance(value, bytes):
        return f"{len(value)} bytes"
    if isinstance(value, IFDRational):
        return "a rational number"
    if isinstance(value, tuple):
        return f"{len(value)} values"
    return f"the number {value!r}" if isinstance(value, int | float) else type(value).__name__


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


#: the tags of the EXIF IFD read here (only these are decoded)
EXIF_TAGS = (
    Base.BodySerialNumber,
    Base.LensModel,
    Base.DateTimeOriginal,
    Base.SubsecTimeOriginal,
    Base.OffsetTimeOriginal,
    Base.FocalLength,
    Base.FocalLengthIn35mmFilm,
    Base.FocalPlaneXResolution,
    Base.FocalPlaneResolutionUnit,
    Base.ExifImageWidth,
    Base.AmbientTemperature,
    Base.MakerNote,
)

#: FocalPlaneResolutionUnit -> millimetres per unit (EXIF 2.32: 2 inch, 3 centimetre; 1 "no unit" is read as
#: inch, as most writers that set it mean, and 4 mm / 5 um as some writers use beyond the standard)
FOCAL_PLANE_UNIT_MM = {1: 25.4, 2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


def read_exif(ifd0: dict[int, Any], block: bytes) -> ExifData:
    """Interpret IFD0 (from :func:`load_exif`) and the EXIF and GPS IFDs of the TIFF ``block``."""
    out = ExifData(block=block)
    merged = {**ifd0, **sub_ifd(ifd0, block, IFD.Exif, out.notes, EXIF_TAGS)}  # some writers use IFD0
    gps = sub_ifd(ifd0, block, IFD.GPSInfo, out.notes)

    def text(ifd: dict[int, Any], tag: Base) -> str | None:
        value = text_value(ifd.get(tag))
        if value is None and ifd.get(tag) is not None and not isinstance(ifd[tag], str | bytes):
            out.notes.append((tag.name, f"holds {_kind(ifd[tag])}, expected ASCII text; ignored"))
        return value

    out.make = text(ifd0, Base.Make)
    out.model = text(ifd0, Base.Model)
    orientation = int_values(ifd0.get(Base.Orientation))
    out.orientation = orientation[0] if orientation else None
    out.serial = text(merged, Base.BodySerialNumber)
    out.lens = text(merged, Base.LensModel)
    raw_time = text(merged, Base.DateTimeOriginal)
    out.datetime_original = parse_exif_datetime(raw_time)
    if raw_time and out.datetime_original is None:
        out.notes.append(
            ("DateTimeOriginal", f"value {raw_time!r} is not a valid 'YYYY:MM:DD HH:MM:SS'; ignored")
        )
    subsec = text(merged, Base.SubsecTimeOriginal)
    if out.datetime_original is not None and subsec:
        digits = subsec.strip()
        if digits.isdigit():
            out.datetime_original += dt.timedelta(seconds=int(digits) / 10 ** len(digits))
        else:
            out.notes.append(("SubSecTimeOriginal", f"value {subsec!r} is not digits; ignored"))
    raw_offset = text(merged, Base.OffsetTimeOriginal)
    out.utc_offset = parse_utc_offset(raw_offset)
    if raw_offset and out.utc_offset is None:
        out.notes.append(("OffsetTimeOriginal", f"value {raw_offset!r} is not '+HH:MM'; ignored"))
    focal = number_values(merged.get(Base.FocalLength))
    if focal and math.isfinite(focal[0]) and focal[0] > 0:
        out.focal_length_mm = focal[0]
    _read_focal_plane(merged, out)
    ambient = number_values(merged.get(Base.AmbientTemperature))
    if ambient and math.isfinite(ambient[0]):
        out.ambient_temperature_c = ambient[0]
    maker_note = merged.get(Base.MakerNote)
    out.maker_note = maker_note if isinstance(maker_note, bytes) and maker_note else None
    xmp = ifd0.get(Base.XMLPacket)
    if isinstance(xmp, str):
        xmp = xmp.encode("latin-1", errors="replace")
    if isinstance(xmp, bytes):
        out.xmp_packet = xmp or None
    elif xmp is not None:
        out.notes.append(("XMLPacket", f"holds {_kind(xmp)}, expected the XMP packet's bytes; ignored"))
    _read_gps(gps, out)
    return out


def _read_focal_plane(merged: dict[int, Any], out: ExifData) -> None:
    """FocalLengthIn35mmFilm, and the pixel pitch from FocalPlaneXResolution (pixels per unit) at ExifImageWidth."""
    f35 = number_values(merged.get(Base.FocalLengthIn35mmFilm))
    if f35 and math.isfinite(f35[0]) and f35[0] > 0:
        out.focal_length_35mm = f35[0]
    resolution = number_values(merged.get(Base.FocalPlaneXResolution))
    if not resolution:
        return
    unit = int_values(merged.get(Base.FocalPlaneResolutionUnit))
    per_unit = FOCAL_PLANE_UNIT_MM.get(unit[0] if unit else 2)
    if per_unit is None:
        out.notes.append(("FocalPlaneResolutionUnit", f"value {unit[0]} is not a unit of EXIF 2.32; the pixel pitch "
                          "is not taken from FocalPlaneXResolution"))
        return
    if not (math.isfinite(resolution[0]) and resolution[0] > 0):
        out.notes.append(("FocalPlaneXResolution", f"value {resolution[0]} is not a positive number; ignored"))
        return
    pitch_mm = per_unit / resolution[0]
    if not 1e-4 <= pitch_mm <= 0.1:  # 0.1 um .. 100 um: beyond, the field holds something else
        out.notes.append(("FocalPlaneXResolution", f"gives a pixel pitch of {pitch_mm * 1000:.4g} um, outside "
                          "0.1-100 um; ignored"))
        return
    out.focal_plane_pitch_mm = pitch_mm
    width = int_values(merged.get(Base.ExifImageWidth))
    out.exif_image_width = width[0] if width and width[0] > 0 else None


def _read_gps(gps: dict[int, Any], out: ExifData) -> None:
    if not gps:
        return
    values: dict[GPS, tuple[float, ...] | None] = {}
    for tag in (GPS.GPSLatitude, GPS.GPSLongitude, GPS.GPSAltitude, GPS.GPSTimeStamp):
        raw = gps.get(tag)
        values[tag] = None if raw is None else _rationals(raw)
        if raw is not None and values[tag] is None:
            out.notes.append((tag.name, f"holds {_kind(raw)}, expected RATIONAL; ignored"))
    lat, lon = _dms(values[GPS.GPSLatitude]), _dms(values[GPS.GPSLongitude])
    lat_ref = (text_value(gps.get(GPS.GPSLatitudeRef)) or "N").upper()[:1]
    lon_ref = (text_value(gps.get(GPS.GPSLongitudeRef)) or "E").upper()[:1]
    if lat is not None and lon is not None:
        out.gps_lat = -lat if lat_ref == "S" else lat
        out.gps_lon = -lon if lon_ref == "W" else lon
    alt = values[GPS.GPSAltitude]
    if alt and math.isfinite(alt[0]):
        ref = gps.get(GPS.GPSAltitudeRef)  # BYTE (Pillow: bytes); some writers use SHORT
        below = ref[:1] == b"\x01" if isinstance(ref, bytes) else (int_values(ref) or (0,))[0] == 1
        out.gps_alt = -alt[0] if below else alt[0]
    stamp = values[GPS.GPSTimeStamp]
    day = text_value(gps.get(GPS.GPSDateStamp))
    if stamp and len(stamp) == 3 and day and all(math.isfinite(v) for v in stamp):
        base = parse_exif_datetime(f"{day.strip()} 00:00:00")
        if base is not None and 0 <= stamp[0] < 24 and 0 <= stamp[1] < 60 and 0 <= stamp[2] < 61:
            out.gps_utc = base + dt.timedelta(hours=stamp[0], minutes=stamp[1], seconds=stamp[2])
