"""Canon maker notes: the camera's own temperature, serial number and lens name.

Kept as our own reader: Pillow's ``Exif.get_ifd(ExifTags.IFD.MakerNote)`` parses only Fujifilm and Nintendo
maker notes and tifffile returns the MakerNote as opaque bytes; neither knows Canon's CameraInfo or ShotInfo
arrays. What is ours is only the part no library reads: where the maker note's IFD starts and which array
element holds the temperature; the IFD itself is parsed by Pillow's ``ImageFileDirectory_v2``.

The Canon maker note (EXIF tag 0x927C) is a bare IFD (no header) whose offsets count from the start
of the EXIF TIFF header, in the EXIF byte order. Where the camera temperature lives depends on the
model family; the positions follow ExifTool's ``Canon.pm`` and were checked on the measured data:

* **EOS** models: ``CanonShotInfo`` (tag 0x0004, int16 array), index 12, stored as degC + 128, and 0
  when not recorded (ExifTool: ``ValueConv => '$val - 128'``, ``RawConv => '$val ? $val : undef'``).
  On the EOS Rebel XSi of ``copr`` this reads 153 -> 25 degC.
* **PowerShot / IXUS / IXY / ELPH** compacts: ``CanonCameraInfo`` (tag 0x000D, int32 array), the third
  value from the end, plain degC (ExifTool's CameraInfoPowerShot tables). On the PowerShot ELPH 300 HS
  of ``seneca`` (469 values) it reads 37 degC in the first image and 23 degC in the last, as the data
  set's description states; ShotInfo index 12 is 0 (not recorded) on that camera.

Other tags read: 0x000C SerialNumber (int32), 0x0095 LensModel (text), 0x0096 InternalSerialNumber.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from PIL.ExifTags import IFD

from aerocal.ingest.exif import int_values, read_ifd, text_value

TAG_SHOT_INFO, TAG_SERIAL, TAG_CAMERA_INFO, TAG_LENS_MODEL, TAG_INTERNAL_SERIAL = (
    0x0004,
    0x000C,
    0x000D,
    0x95,
    0x96,
)
SHOT_INFO_TEMPERATURE_INDEX = 12
SHOT_INFO_TEMPERATURE_BIAS = 128
CAMERA_INFO_TEMPERATURE_FROM_END = 3
TAGS_READ = (TAG_SHOT_INFO, TAG_SERIAL, TAG_CAMERA_INFO, TAG_LENS_MODEL, TAG_INTERNAL_SERIAL)
COMPACT_FAMILIES = ("POWERSHOT", "IXUS", "IXY", "ELPH")
#: TIFF field types (TIFF 6.0): SHORT, SSHORT, LONG, SLONG
SHORT, SSHORT, LONG, SLONG = 3, 8, 4, 9


@dataclass
class CanonMakerNote:
    """What ingest takes from a Canon maker note; ``notes`` lists (field, message) for unusable values."""

    temperature_c: float | None = None
    temperature_source: str | None = None
    serial: str | None = None
    lens: str | None = None
    notes: list[tuple[str, str]] = field(default_factory=list)


def is_canon(make: str | None) -> bool:
    return bool(make) and make.strip().upper().startswith("CANON")


def _maker_note_ifd(
    block: bytes, maker_note: bytes, notes: list[tuple[str, str]]
) -> tuple[dict[int, Any], dict[int, int]]:
    """The maker note's IFD (values of the tags read here, and every tag's type), read by Pillow from the EXIF
    block so that its offsets resolve as Canon means them.

    Pillow gives the MakerNote's bytes, not where they lie; the IFD is read where those bytes lie in the
    block. Should the same bytes also lie earlier, reading there gives the same entries, and their
    out-of-line values (offsets from the block start) are the same bytes: the result cannot differ.
    """
    start = block.find(maker_note)
    if len(maker_note) < 2 or start < 0:
        return {}, {}
    try:
        return read_ifd(block, start, notes, "Canon maker note", "MakerNote", group=IFD.MakerNote, wanted=TAGS_READ)
    except Exception as exc:  # Pillow warns on most damage; whatever else it raises is reported, not raised
        notes.append(("MakerNote", f"Pillow cannot read the maker note ({type(exc).__name__}: {exc})"))
        return {}, {}


def read_canon_maker_note(block: bytes, maker_note: bytes, model: str | None) -> CanonMakerNote:
    """Parse the Canon maker note (the EXIF ``MakerNote`` value) of the EXIF TIFF ``block``."""
    out = CanonMakerNote()
    values, types = _maker_note_ifd(block, maker_note, out.notes)
    if not types:
        out.notes.append(("MakerNote", "Canon maker note could not be read; no camera temperature"))
        return out
    model_up = (model or "").upper()
    is_eos = "EOS" in model_up
    is_compact = any(f in model_up for f in COMPACT_FAMILIES)

    def array(tag: int, kinds: tuple[int, int]) -> tuple[int, ...] | None:
        return int_values(values.get(tag)) if types.get(tag) in kinds else None

    raw: float | None = None
    source: str | None = None
    shot = array(TAG_SHOT_INFO, (SHORT, SSHORT))
    if is_eos and shot is not None and len(shot) > SHOT_INFO_TEMPERATURE_INDEX:
        v = shot[SHOT_INFO_TEMPERATURE_INDEX]
        if types[TAG_SHOT_INFO] == SHORT and v >= 0x8000:  # stored as int16s
            v -= 0x10000
        if v != 0:
            raw = float(v - SHOT_INFO_TEMPERATURE_BIAS)
            source = "canon:ShotInfo[12]-128"
    info = array(TAG_CAMERA_INFO, (LONG, SLONG))
    if raw is None and is_compact and info is not None and len(info) >= CAMERA_INFO_TEMPERATURE_FROM_END:
        v = info[-CAMERA_INFO_TEMPERATURE_FROM_END]
        if types[TAG_CAMERA_INFO] == LONG and v >= 0x80000000:  # stored as int32s
            v -= 0x100000000
        raw = float(v)
        source = "canon:CameraInfo[-3]"
    if raw is not None and math.isfinite(raw):
        out.temperature_c = raw
        out.temperature_source = source

    serial = array(TAG_SERIAL, (SHORT, LONG))
    if serial:
        out.serial = str(int(serial[0]))
    if out.serial is None:
        out.serial = text_value(values.get(TAG_INTERNAL_SERIAL))
    out.lens = text_value(values.get(TAG_LENS_MODEL))
    return out
