"""Rendered frames written as a camera writes them: 16-bit TIFF (thermal) or JPEG (RGB), with EXIF and XMP.

Where each field goes (as in DJI files, so the ingest reads simulated and real flights the same way):

* TIFF tags 271 Make, 272 Model, 306 DateTime (``YYYY:MM:DD HH:MM:SS``);
* the EXIF IFD (TIFF tag 34665 / JPEG APP1 ``Exif``): 0x9003 DateTimeOriginal, 0x9291 SubSecTimeOriginal
  (milliseconds), 0x9011 OffsetTimeOriginal (only for a time with a time zone), 0xA431 BodySerialNumber;
* an XMP packet (TIFF tag 700 / JPEG APP1 ``http://ns.adobe.com/xap/1.0/``) with DJI's ``drone-dji``
  namespace (``http://www.dji.com/drone-dji/1.0/``): GpsLatitude, GpsLongitude (degrees WGS84, signed),
  AbsoluteAltitude (metres), GimbalRollDegree, GimbalPitchDegree, GimbalYawDegree (degrees, DJI gimbal
  convention: see :func:`aerocal.geometry.dji_gimbal_to_R_cw`), plus any ``extra_xmp`` fields.

The values are the *recorded* GNSS/IMU values (with whatever errors the simulator gave them), not the
truth. Files are written atomically (:func:`aerocal.io.atomic_path`).
"""

from __future__ import annotations

import datetime as dt
import io
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import tifffile
from PIL import Image

from aerocal.ingest.flir import KELVIN, FlirCameraInfo, celsius_to_raw
from aerocal.ingest.metadata_writer import (
    DJI_NAMESPACE,
    dji_xmp_packet,
    exif_block,
    fff_file,
    jpeg_with_flir,
    jpeg_with_metadata,
)
from aerocal.io import atomic_path

# EXIF tag codes
TAG_MAKE, TAG_MODEL, TAG_DATETIME, TAG_XMP, TAG_EXIF_IFD = 271, 272, 306, 700, 34665
EXIF_DATETIME_ORIGINAL, EXIF_OFFSET_TIME_ORIGINAL, EXIF_SUBSEC_TIME_ORIGINAL = 0x9003, 0x9011, 0x9291
EXIF_BODY_SERIAL_NUMBER = 0xA431

#: Permissions of written images (the temporary file of an atomic write is private, 0600)
_FILE_MODE = 0o644


@dataclass(frozen=True)
class FrameMetadata:
    """What a camera records with a frame. Angles in degrees, altitude in metres, positions WGS84.

    ``time`` is the exposure time; a naive datetime is written as is, an aware one as its own local
    time with an OffsetTimeOriginal. ``extra_xmp`` adds ``drone-dji`` fields (name -> value).
    """

    make: str
    model: str
    serial: str
    time: dt.datetime
    gps_latitude: float
    gps_longitude: float
    absolute_altitude: float
    gimbal_roll_deg: float
    gimbal_pitch_deg: float
    gimbal_yaw_deg: float
    extra_xmp: dict[str, str | float] = field(default_factory=dict)

    def exif_datetime(self) -> str:
        """``YYYY:MM:DD HH:MM:SS`` (EXIF's DateTime format, no time zone)."""
        return self.time.strftime("%Y:%m:%d %H:%M:%S")

    def exif_subsec(self) -> str:
        """Milliseconds of the exposure time, three digits."""
        return f"{self.time.microsecond // 1000:03d}"

    def exif_offset(self) -> str | None:
        """``+HH:MM`` for an aware time, else None."""
        off = self.time.utcoffset()
        if off is None:
            return None
        minutes = int(off.total_seconds() // 60)
        sign = "+" if minutes >= 0 else "-"
        return f"{sign}{abs(minutes) // 60:02d}:{abs(minutes) % 60:02d}"


def xmp_packet(meta: FrameMetadata) -> bytes:
    """The XMP packet (UTF-8) holding the ``drone-dji`` fields, formatted as DJI writes them
    (attributes of one ``rdf:Description``, signed decimals).

    Raises:
        ValueError: a key of ``meta.extra_xmp`` is not a valid XML name.
    """
    fields: dict[str, str] = {
        "GpsLatitude": f"{meta.gps_latitude:+.9f}",
        "GpsLongitude": f"{meta.gps_longitude:+.9f}",
        "AbsoluteAltitude": f"{meta.absolute_altitude:+.3f}",
        "GimbalRollDegree": f"{meta.gimbal_roll_deg:+.4f}",
        "GimbalPitchDegree": f"{meta.gimbal_pitch_deg:+.4f}",
        "GimbalYawDegree": f"{meta.gimbal_yaw_deg:+.4f}",
    }
    for k, v in meta.extra_xmp.items():
        if not k.isidentifier():
            raise ValueError(f"extra_xmp field name {k!r} is not a valid XML name")
        fields[k] = f"{v:+.6f}" if isinstance(v, float) else str(v)
    attrs = "\n".join(f"    drone-dji:{k}={quoteattr(v)}" for k, v in fields.items())
    text = (
        '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        f'  <rdf:Description rdf:about="" xmlns:drone-dji="{DJI_NAMESPACE}"\n'
        f"{attrs}>\n"
        "  </rdf:Description>\n"
        " </rdf:RDF>\n"
        "</x:xmpmeta>\n"
        '<?xpacket end="w"?>'
    )
    return text.encode("utf-8")


def _exif_entries(meta: FrameMetadata) -> dict[int, str]:
    entries = {
        EXIF_DATETIME_ORIGINAL: meta.exif_datetime(),
        EXIF_SUBSEC_TIME_ORIGINAL: meta.exif_subsec(),
        EXIF_BODY_SERIAL_NUMBER: meta.serial,
    }
    offset = meta.exif_offset()
    if offset is not None:
        entries[EXIF_OFFSET_TIME_ORIGINAL] = offset
    return entries


# --------------------------------------------------------------------------------------------- TIFF
def write_thermal_tiff(path: str | Path, img_uint16: np.ndarray, meta: FrameMetadata) -> Path:
    """Write a (H, W) uint16 frame as a single-page uncompressed TIFF with EXIF and XMP metadata.

    tifffile cannot write IFD-type tags, so the EXIF IFD is appended after tifffile has written the
    file and the ExifIFD tag (34665, written as a LONG placeholder) is patched to point at it.

    Raises:
        ValueError: ``img_uint16`` is not a 2-D uint16 array, or a key of ``meta.extra_xmp`` is not a valid XML name.
    """
    img = np.asarray(img_uint16)
    if img.dtype != np.uint16 or img.ndim != 2:
        raise ValueError(f"{path}: a thermal frame must be a 2-D uint16 array, got {img.dtype} {img.shape}")
    xmp = xmp_packet(meta)
    extratags = [
        (TAG_MAKE, "s", 0, meta.make, True),
        (TAG_MODEL, "s", 0, meta.model, True),
        (TAG_XMP, "B", len(xmp), xmp, True),
        ("ExifTag", "I", 1, 0, True),  # by name: tifffile filters tag 34665 given as a number
    ]
    path = Path(path)
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, img, photometric="minisblack", datetime=meta.exif_datetime(),
                         software="aerocal", extratags=extratags, metadata=None)
        _append_exif_ifd(tmp, _exif_entries(meta))
        os.chmod(tmp, _FILE_MODE)
    return path


def _append_exif_ifd(path: Path, entries: dict[int, str]) -> None:
    """Append an EXIF IFD of ASCII entries to a classic TIFF and point its ExifIFD tag at it.

    The first IFD is parsed here (tifffile refuses to read the placeholder offset 0)."""
    with open(path, "rb+") as fh:
        head = fh.read(8)
        byteorder = {b"II": "<", b"MM": ">"}.get(head[:2])
        if byteorder is None or struct.unpack(byteorder + "H", head[2:4])[0] != 42:
            raise ValueError(f"{path}: not a classic TIFF file, cannot add EXIF metadata")
        ifd = struct.unpack(byteorder + "I", head[4:8])[0]
        fh.seek(ifd)
        (count,) = struct.unpack(byteorder + "H", fh.read(2))
        patch_at = None
        for i in range(count):
            code = struct.unpack(byteorder + "H", fh.read(12)[:2])[0]
            if code == TAG_EXIF_IFD:
                patch_at = ifd + 2 + 12 * i + 8
        if patch_at is None:
            raise ValueError(f"{path}: the ExifIFD placeholder tag was not written")
        fh.seek(0, 2)
        start = fh.tell()
        start += start % 2  # IFDs begin on a word boundary
        n = len(entries)
        data_at = start + 2 + 12 * n + 4
        table = bytearray(struct.pack(byteorder + "H", n))
        data = bytearray()
        for code in sorted(entries):
            value = entries[code].encode("ascii", "replace") + b"\x00"
            if len(value) <= 4:
                table += struct.pack(byteorder + "HHI", code, 2, len(value)) + value.ljust(4, b"\x00")
            else:
                table += struct.pack(byteorder + "HHII", code, 2, len(value), data_at + len(data))
                data += value + (b"\x00" if len(value) % 2 else b"")
        table += struct.pack(byteorder + "I", 0)
        fh.seek(start)
        fh.write(bytes(table) + bytes(data))
        fh.seek(patch_at)
        fh.write(struct.pack(byteorder + "I", start))


# --------------------------------------------------------------------------------------------- JPEG
def write_rgb_jpeg(path: str | Path, img_uint8: np.ndarray, meta: FrameMetadata, quality: int = 95) -> Path:
    """Write a (H, W, 3) uint8 RGB frame as a baseline JPEG with EXIF (APP1 ``Exif``) and XMP (APP1
    ``http://ns.adobe.com/xap/1.0/``) segments. Channel order of the array: R, G, B.

    Raises:
        ValueError: ``img_uint8`` is not an (H, W, 3) uint8 array, or a key of ``meta.extra_xmp`` is not a valid XML
            name.
    """
    img = np.asarray(img_uint8)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{path}: an RGB frame must be an (H, W, 3) uint8 array, got {img.dtype} {img.shape}")
    exif = Image.Exif()
    exif[TAG_MAKE] = meta.make
    exif[TAG_MODEL] = meta.model
    exif[TAG_DATETIME] = meta.exif_datetime()
    sub = exif.get_ifd(TAG_EXIF_IFD)
    for code, value in _exif_entries(meta).items():
        sub[code] = value
    path = Path(path)
    with atomic_path(path) as tmp:
        Image.fromarray(img, mode="RGB").save(
            tmp, format="JPEG", quality=int(quality), exif=exif.tobytes(), xmp=xmp_packet(meta)
        )
        os.chmod(tmp, _FILE_MODE)
    return path


# ------------------------------------------------------------------------------ FLIR radiometric JPEG
def zenmuse_xt2_camera_info(object_distance_m: float = 20.0, air_temperature_c: float = 20.0):
    """FLIR camera information as a DJI Zenmuse XT2 (Tau 2 core) records it: the Planck constants of
    ``shared/data/flir_samples/fff_dji_xt2.jpg`` (R1 17096.453, B 1428, F 1, O -267, R2 0.04658), emissivity 1,
    FLIR's default atmospheric-transmission constants, the given object distance and air temperature."""
    return FlirCameraInfo(
        emissivity=1.0, object_distance_m=float(object_distance_m), reflected_temperature_k=KELVIN + 20.0,
        atmospheric_temperature_k=KELVIN + float(air_temperature_c), window_temperature_k=KELVIN + 20.0,
        window_transmission=1.0, relative_humidity=0.5, planck_r1=17096.453, planck_b=1428.0, planck_f=1.0,
        planck_o=-267.0, planck_r2=0.046582058, atm_alpha1=0.006569, atm_alpha2=0.01262, atm_beta1=-0.002276,
        atm_beta2=-0.00667, atm_x=1.9,
    )


def write_flir_rjpeg(path: str | Path, dn_uint16: np.ndarray, meta: FrameMetadata, info, dn_per_kelvin: float,
                     focal_mm: float | None = None) -> Path:
    """Write a rendered thermal frame as a DJI Zenmuse XT/XT2 writes it: a FLIR radiometric JPEG.

    ``dn_uint16`` holds ``dn_per_kelvin`` x scene temperature (the renderer's counts); they become FLIR
    counts through ``info``'s Planck curve, so that the file's temperatures are the scene's. The file has an
    8-bit grey preview, EXIF Make/Model/DateTimeOriginal/FocalLength and the GNSS position in the GPS IFD
    (no serial number when ``meta.serial`` is empty, as on the XT2), the DJI XMP altitude and gimbal
    attitude (plus ``meta.extra_xmp``, e.g. RelativeAltitude), and the FFF file in APP1 ``FLIR`` segments
    (little-endian, unwrapped counts, as in ``fff_dji_xt2.jpg``).

    Raises:
        ValueError: ``dn_uint16`` is not a 2-D uint16 array.
    """
    dn = np.asarray(dn_uint16)
    if dn.dtype != np.uint16 or dn.ndim != 2:
        raise ValueError(f"{path}: a thermal frame must be a 2-D uint16 array, got {dn.dtype} {dn.shape}")
    counts = celsius_to_raw(dn / float(dn_per_kelvin) - KELVIN, info)
    raw = np.clip(np.rint(counts), 0, 65535).astype(np.uint16)
    lo, hi = np.percentile(raw, (1, 99))
    grey = np.clip((raw - lo) / max(hi - lo, 1.0) * 255.0, 0, 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(np.dstack([grey] * 3), mode="RGB").save(buf, format="JPEG", quality=90)
    xmp = {"AbsoluteAltitude": float(meta.absolute_altitude), "GimbalRollDegree": float(meta.gimbal_roll_deg),
           "GimbalPitchDegree": float(meta.gimbal_pitch_deg), "GimbalYawDegree": float(meta.gimbal_yaw_deg)}
    xmp.update(meta.extra_xmp)
    time = meta.time.replace(tzinfo=None) if meta.time.tzinfo else meta.time
    exif = exif_block(make=meta.make, model=meta.model, serial=meta.serial or None, time=time,
                      utc_offset=meta.exif_offset(),
                      gps=(meta.gps_latitude, meta.gps_longitude, meta.absolute_altitude), focal_mm=focal_mm)
    blob = jpeg_with_flir(jpeg_with_metadata(buf.getvalue(), exif, dji_xmp_packet(xmp)), fff_file(raw, info))
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(blob)
        os.chmod(tmp, _FILE_MODE)
    return path


def write_frame(path: str | Path, img: np.ndarray, meta: FrameMetadata) -> Path:
    """Write a rendered frame by its type: uint16 (H, W) -> TIFF, uint8 (H, W, 3) -> JPEG."""
    img = np.asarray(img)
    if img.dtype == np.uint16:
        return write_thermal_tiff(path, img, meta)
    return write_rgb_jpeg(path, img, meta)
