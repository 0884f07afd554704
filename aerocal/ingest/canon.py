"""Canon maker notes: the camera's own temperature, serial number and lens name.

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

from aerocal.ingest.tiff import IfdEntry, TiffStructure, entry_text

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
COMPACT_FAMILIES = ("POWERSHOT", "IXUS", "IXY", "ELPH")


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


def read_canon_maker_note(tiff: TiffStructure, maker_note: IfdEntry, model: str | None) -> CanonMakerNote:
    """Parse the Canon maker note IFD the EXIF ``MakerNote`` entry points to."""
    out = CanonMakerNote()
    ifd = tiff.read_ifd(maker_note.offset, "Canon maker note")
    if not ifd:
        out.notes.append(("MakerNote", "Canon maker note could not be read; no camera temperature"))
        return out
    model_up = (model or "").upper()
    is_eos = "EOS" in model_up
    is_compact = any(f in model_up for f in COMPACT_FAMILIES)

    raw: float | None = None
    source: str | None = None
    shot = ifd.get(TAG_SHOT_INFO)
    if is_eos and shot is not None and isinstance(shot.value, tuple) and shot.type in (3, 8):
        values = shot.value
        if len(values) > SHOT_INFO_TEMPERATURE_INDEX:
            v = int(values[SHOT_INFO_TEMPERATURE_INDEX])
            if shot.type == 3 and v >= 0x8000:  # stored as int16s
                v -= 0x10000
            if v != 0:
                raw = float(v - SHOT_INFO_TEMPERATURE_BIAS)
                source = "canon:ShotInfo[12]-128"
    info = ifd.get(TAG_CAMERA_INFO)
    if (
        raw is None
        and is_compact
        and info is not None
        and info.type in (4, 9)
        and isinstance(info.value, tuple)
    ):
        values = info.value
        if len(values) >= CAMERA_INFO_TEMPERATURE_FROM_END:
            v = int(values[-CAMERA_INFO_TEMPERATURE_FROM_END])
            if info.type == 4 and v >= 0x80000000:  # stored as int32s
                v -= 0x100000000
            raw = float(v)
            source = "canon:CameraInfo[-3]"
    if raw is not None and math.isfinite(raw):
        out.temperature_c = raw
        out.temperature_source = source

    serial = ifd.get(TAG_SERIAL)
    if serial is not None and isinstance(serial.value, tuple) and serial.value and serial.type in (3, 4):
        out.serial = str(int(serial.value[0]))
    if out.serial is None:
        out.serial = entry_text(ifd, TAG_INTERNAL_SERIAL)
    out.lens = entry_text(ifd, TAG_LENS_MODEL)
    return out
