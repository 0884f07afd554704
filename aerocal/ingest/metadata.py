"""Everything ingest reads from one image file, without decoding its pixels.

:func:`read_image_metadata` recognises the container by its first bytes (JPEG or TIFF, whatever the
extension says), hashes the content, reads the frame size and bit depth from the JPEG frame header or
the TIFF IFD (for a DJI R-JPEG: the raw thermal frame's size and 16 bits), the EXIF identity and
capture time, the vendor XMP (DJI, senseFly) or EXIF GPS position and attitude, the camera temperature
(Canon maker notes; DJI APP4 only on request), and checks every value against its physical range.
It never raises on bad input: what cannot be used is reported as a :class:`Problem` naming the file and
field, and a file that cannot be ingested at all returns ``None`` with an error.

Who reads what. A maintained library reads a field wherever one reads it with the same result (checked by
ingesting every set of ``shared/data`` before and after the change: identical ``images`` tables); our own
code is kept only where no installed library (Pillow, tifffile, defusedxml) reads the field:

================================  ==============================  ==============================================
what                              read by                         why
================================  ==============================  ==============================================
IFD0, EXIF and GPS IFDs of a      Pillow's IFD reader, as         the same values as the struct reader it
JPEG's APP1 block and of a TIFF   ``Image.getexif()`` uses it     replaced, at about the same speed; it
file; the TIFF layout tags        (:mod:`.exif` interprets the    salvages less from a damaged IFD (it stops at
                                  values)                         the first value outside the block) and skips
                                                                  unknown types silently, so the declared entry
                                                                  count is checked and reported; big-endian
                                                                  BigTIFF is not read
Canon maker note (temperature,    ours (:mod:`.canon`); its IFD   Pillow parses Fujifilm and Nintendo maker
serial, lens)                     parsed by Pillow                notes only; tifffile returns the bytes
JPEG markers (frame size, APPn,   ours (:mod:`.jpeg`)             Pillow keeps no segment offsets (the EOI
end-of-image check)                                               check needs the start of scan), opens DJI
                                                                  R-JPEGs as MPO, says only "cannot identify"
XMP (DJI, senseFly, Parrot,       ours (:mod:`.xmp`) on           Pillow's ``getxmp`` drops namespace URIs;
FLIR, Pix4D, Adobe namespaces)    defusedxml                      :mod:`.dji`, :mod:`.sensefly`, :mod:`.parrot`
                                                                  map names
DJI R-JPEG raw frame, APP4        ours (:mod:`.dji`)              no library reads them (Pillow: opaque bytes)
FLIR FFF records in APP1          ours (:mod:`.flir`)             Pillow: opaque bytes; flyr is EUPL-1.2 (test
                                                                  reference only) and misses DJI's layout
time zone from GNSS UTC           ours (:mod:`.capture_time`)     a flight-wide inference, not a format
pixels                            tifffile, OpenCV; ours for      (:mod:`.pixels`)
                                  FLIR and DJI raw frames
================================  ==============================  ==============================================
"""

from __future__ import annotations

import datetime as dt
import hashlib
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from PIL.ExifTags import Base

from aerocal.ingest.canon import is_canon, read_canon_maker_note
from aerocal.ingest.config import IngestConfig
from aerocal.ingest.dji import app4_field_name, app4_floats, has_dji, raw_thermal_layout, read_dji_xmp
from aerocal.ingest.exif import (
    TIFF_MAGICS,
    ExifData,
    ExifFormatError,
    int_values,
    load_exif,
    parse_utc_offset,
    read_exif,
)
from aerocal.ingest.flir import FlirCameraInfo, FlirFormatError, flir_layout, has_flir
from aerocal.ingest.jpeg import JpegFormatError, is_jpeg, parse_jpeg
from aerocal.ingest.numbers import PLAUSIBLE_RANGES, in_range
from aerocal.ingest.parrot import has_parrot, read_parrot
from aerocal.ingest.problems import Problem
from aerocal.ingest.recorded_pose import RecordedPose
from aerocal.ingest.sensefly import has_sensefly, read_sensefly
from aerocal.ingest.xmp import XmpError, packet_from_app1, parse_xmp

#: DJI models whose APP4 floats were seen to drift like internal temperatures (``h20t_forest``); on the
#: M2EA, M30T and H30T samples the same bytes hold zeros or values like 1e28, so they are not read there
APP4_TEMPERATURE_MODELS = ("H20T",)
MAX_IMAGE_SIDE = 1 << 17  # 131072 px: larger frame sizes are corrupt headers, not cameras
_XMP_TIME = re.compile(r"^(\d{4})-(\d{2})-(\d{2})T(\d{2}):(\d{2}):(\d{2})(\.\d+)?(Z|[+-]\d{2}:?\d{2})?$")


@dataclass
class ImageMetadata:
    """Metadata of one image. Positions WGS84 (degrees, metres), angles degrees, temperatures degC."""

    path: Path
    name: str
    sha256: str
    container: str  # "jpeg" or "tiff"
    width: int
    height: int
    bit_depth: int
    raw_thermal: bool = False
    raw_format: str | None = None  # "flir-fff", "dji-rjpeg" (counts read from the JPEG's APPn segments)
    make: str | None = None
    model: str | None = None
    serial: str | None = None
    lens: str | None = None
    local_time: dt.datetime | None = None  # naive, as the camera clock wrote it
    utc_offset: dt.timedelta | None = None  # camera clock minus UTC, where a tag states it
    utc_offset_source: str | None = None
    gnss_utc: dt.datetime | None = None  # a UTC time recorded by the GNSS receiver, if any
    gnss_utc_source: str | None = None
    pose: RecordedPose = field(default_factory=lambda: RecordedPose(source="none"))
    temperature_c: float | None = None
    temperature_source: str | None = None
    has_metadata: bool = False
    extra: dict[str, float | str] = field(default_factory=dict)


def sniff_container(data: bytes) -> str | None:
    """``"jpeg"``, ``"tiff"`` or ``None`` from the first bytes."""
    if is_jpeg(data):
        return "jpeg"
    if data[:4] in TIFF_MAGICS:
        return "tiff"
    return None


def _describe_magic(data: bytes) -> str:
    head = data[:8]
    known = {b"\x89PNG": "PNG", b"GIF8": "GIF", b"BM": "BMP", b"%PDF": "PDF", b"PK\x03\x04": "ZIP"}
    for magic, kind in known.items():
        if head.startswith(magic):
            return f"a {kind} file"
    return "starts with bytes " + " ".join(f"{b:02X}" for b in head)


def read_image_metadata(
    path: str | Path, config: IngestConfig | None = None
) -> tuple[ImageMetadata | None, list[Problem]]:
    """Read one image's metadata; ``None`` (with an error problem) when the file cannot be ingested."""
    cfg = config or IngestConfig()
    path = Path(path)
    where = str(path)
    problems: list[Problem] = []

    def error(message: str, field_name: str | None = None) -> None:
        """Record an error that skips the file; the container readers return its ``None``."""
        problems.append(Problem(where, None, field_name, message, "error"))

    def warn(message: str, field_name: str | None = None) -> None:
        problems.append(Problem(where, None, field_name, message, "warning"))

    try:
        size = path.stat().st_size
        if size > cfg.max_file_bytes:
            error(
                f"file is {size} bytes, larger than IngestConfig.max_file_bytes={cfg.max_file_bytes}; skipped"
            )
            return None, problems
        data = path.read_bytes()
    except OSError as exc:
        error(f"cannot be read ({exc.strerror or exc}); skipped")
        return None, problems
    if not data:
        error("file is empty; skipped")
        return None, problems
    container = sniff_container(data)
    if container is None:
        error(f"not a JPEG or TIFF image ({_describe_magic(data)}); skipped")
        return None, problems
    ext = path.suffix.lower()
    expected = {".jpg": "jpeg", ".jpeg": "jpeg", ".tif": "tiff", ".tiff": "tiff"}.get(ext)
    if expected is not None and expected != container:
        warn(f"extension {path.suffix} but the content is {container.upper()}; read as {container.upper()}")

    digest = hashlib.sha256(data).hexdigest()
    if container == "jpeg":
        result = _read_jpeg(data, path, digest, cfg, error, warn)
    else:
        result = _read_tiff(data, path, digest, cfg, error, warn)
    if result is None:
        return None, problems
    meta, exif, xmp = result
    _interpret(meta, exif, xmp, cfg, warn)
    return meta, problems


# ---------------------------------------------------------------------------- containers
def _read_jpeg(data, path, digest, cfg, error, warn):
    try:
        jpeg = parse_jpeg(data)
    except JpegFormatError as exc:
        return error(f"not a readable JPEG: {exc}; skipped")
    flir_present, layout = has_flir(jpeg), raw_thermal_layout(jpeg)
    if not jpeg.has_eoi and not (flir_present or layout is not None):
        return error("truncated JPEG: no end-of-image marker after the image data; skipped")
    if not jpeg.has_eoi:
        warn(
            "the JPEG preview has no end-of-image marker (cut); the raw thermal frame stored before it is "
            "complete and is what is used",
            "EOI",
        )
    if not (0 < jpeg.width <= MAX_IMAGE_SIDE and 0 < jpeg.height <= MAX_IMAGE_SIDE):
        return error(
            f"JPEG frame header gives an impossible size {jpeg.width}x{jpeg.height}; skipped", "size"
        )
    meta = ImageMetadata(path, path.name, digest, "jpeg", jpeg.width, jpeg.height, jpeg.precision)
    exif: ExifData | None = None
    xmp: dict[str, str] = {}
    for marker, payload in jpeg.app_segments:
        if marker != 0xE1:
            continue
        if payload.startswith(b"Exif\x00\x00") and exif is None:
            exif = _exif_from(payload[6:], warn)
        else:
            packet = packet_from_app1(payload)
            if packet is not None and not xmp:
                xmp = _xmp_from(packet, warn)
    if flir_present:
        try:
            flir = flir_layout(jpeg)
        except FlirFormatError as exc:
            return error(
                f"FLIR radiometric JPEG whose FLIR segments are broken ({exc}); the 8-bit picture beside them "
                "is a palette rendering, not the measurement; skipped",
                "FLIR",
            )
        assert flir is not None
        meta.width, meta.height, info = flir
        meta.bit_depth = 16
        meta.raw_thermal = True
        meta.raw_format = "flir-fff"
        _flir_extra(meta, info, warn)
        return meta, exif, xmp
    if layout is not None:
        meta.width, meta.height = layout
        meta.bit_depth = 16
        meta.raw_thermal = True
        meta.raw_format = "dji-rjpeg"
        model = (exif.model if exif is not None else None) or ""
        floats = app4_floats(jpeg) if any(m in model for m in APP4_TEMPERATURE_MODELS) else {}
        lo, hi = cfg.temperature_range_c
        for off, value in floats.items():
            name = app4_field_name(off)
            if in_range(value, lo, hi):
                meta.extra[name] = value
            else:
                warn(
                    f"undocumented DJI APP4 float at byte {off} reads {value!r}, "
                    f"outside {lo}..{hi} degC; nulled",
                    name,
                )
        if cfg.dji_app4_temperature is not None and cfg.dji_app4_temperature in floats:
            name = app4_field_name(cfg.dji_app4_temperature)
            if name in meta.extra:
                meta.temperature_c = float(meta.extra[name])
                meta.temperature_source = (
                    f"dji:APP4 float at byte {cfg.dji_app4_temperature} (undocumented, opted in)"
                )
    elif jpeg.app(0xE3):
        total = sum(len(p) for p in jpeg.app(0xE3))
        warn(
            f"APP3 segments hold {total} bytes, which match no raw thermal frame size "
            f"(2 x width x height); read as an ordinary {jpeg.precision}-bit JPEG",
            "APP3",
        )
    return meta, exif, xmp


#: FLIR camera-information fields kept per image in ``extra`` (name -> attribute, unit in the name)
FLIR_EXTRA = {
    "flir_emissivity": "emissivity",
    "flir_object_distance_m": "object_distance_m",
    "flir_reflected_temperature_k": "reflected_temperature_k",
    "flir_atmospheric_temperature_k": "atmospheric_temperature_k",
    "flir_relative_humidity": "relative_humidity",
    "flir_planck_r1": "planck_r1",
    "flir_planck_b": "planck_b",
    "flir_planck_f": "planck_f",
    "flir_planck_o": "planck_o",
    "flir_planck_r2": "planck_r2",
    "flir_field_of_view_deg": "field_of_view_deg",
}


def _flir_extra(meta: ImageMetadata, info: FlirCameraInfo | None, warn) -> None:
    """Record the FLIR camera information of one frame in ``meta.extra``; warn where temperatures fail."""
    if info is None:
        warn("FLIR file without a camera-information record: counts are read, temperatures cannot be", "FLIR")
        return
    for key, attr in FLIR_EXTRA.items():
        value = float(getattr(info, attr))
        if math.isfinite(value):
            meta.extra[key] = value
    for key, text in (
        ("flir_camera_model", info.camera_model),
        ("flir_camera_serial", info.camera_serial),
        ("flir_lens_model", info.lens_model),
    ):
        if text and text != "*":
            meta.extra[key] = text[:64]
    bad = info.problems()
    if bad:
        warn("FLIR camera information unusable for temperatures (" + "; ".join(bad) + "): counts only", "FLIR")


def _first_int(ifd: dict[int, Any], tag: int) -> int | None:
    """The first value of an integer-typed tag (``None`` if absent or of another type)."""
    values = int_values(ifd.get(tag))
    return values[0] if values else None


def _read_tiff(data, path, digest, cfg, error, warn):
    notes: list[tuple[str, str]] = []
    try:
        ifd0 = load_exif(data, notes, "TIFF")
    except ExifFormatError as exc:
        return error(f"not a readable TIFF: {exc}; skipped")
    for field_name, message in notes:
        warn(message, field_name)
    exif = read_exif(ifd0, data)
    width, height = _first_int(ifd0, Base.ImageWidth), _first_int(ifd0, Base.ImageLength)
    if width is None or height is None or not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
        return error(f"TIFF ImageWidth/ImageLength give an impossible size {width}x{height}; skipped", "size")
    bit_depth = _first_int(ifd0, Base.BitsPerSample) or 1
    if bit_depth not in (1, 8, 12, 14, 16, 32, 64):
        return error(f"TIFF BitsPerSample {bit_depth} is not supported; skipped", "BitsPerSample")
    samples = _first_int(ifd0, Base.SamplesPerPixel) or 1
    compression = _first_int(ifd0, Base.Compression) or 1
    fmt = _first_int(ifd0, Base.SampleFormat) or 1
    if fmt == 3:
        warn(f"floating-point samples ({bit_depth}-bit); radiometry kept as float", "SampleFormat")
    offsets = int_values(ifd0.get(Base.StripOffsets)) or int_values(ifd0.get(Base.TileOffsets))
    counts = int_values(ifd0.get(Base.StripByteCounts)) or int_values(ifd0.get(Base.TileByteCounts))
    if not offsets or not counts or len(offsets) != len(counts):
        return error("TIFF has no usable strip or tile offsets/byte counts; skipped", "StripOffsets")
    end = max(o + c for o, c in zip(offsets, counts, strict=True))
    if end > len(data):
        return error(f"truncated TIFF: image data runs to byte {int(end)}, the file has {len(data)}; skipped")
    if compression == 1:
        needed = width * height * samples * max(bit_depth, 8) // 8
        if sum(counts) < needed:
            return error(
                f"truncated TIFF: {int(sum(counts))} bytes of uncompressed image data, {needed} needed for "
                f"{width}x{height}x{samples} at {bit_depth} bits; skipped"
            )
    meta = ImageMetadata(path, path.name, digest, "tiff", width, height, bit_depth)
    xmp: dict[str, str] = {}
    if exif.xmp_packet:
        xmp = _xmp_from(exif.xmp_packet, warn)
    return meta, exif, xmp


def _exif_from(block: bytes, warn) -> ExifData | None:
    notes: list[tuple[str, str]] = []
    try:
        ifd0 = load_exif(block, notes)
    except ExifFormatError as exc:
        warn(f"EXIF block is not readable ({exc}); ignored", "EXIF")
        return None
    for field_name, message in notes:
        warn(message, field_name)
    return read_exif(ifd0, block)


def _xmp_from(packet: bytes, warn) -> dict[str, str]:
    try:
        return parse_xmp(packet)
    except XmpError as exc:
        warn(f"{exc}; XMP ignored", "XMP")
        return {}


# ---------------------------------------------------------------------------- interpretation
def _parse_xmp_time(text: str | None) -> tuple[dt.datetime | None, dt.timedelta | None]:
    if not text:
        return None, None
    m = _XMP_TIME.match(text.strip())
    if not m:
        return None, None
    try:
        local = dt.datetime(*(int(g) for g in m.groups()[:6]))
    except ValueError:
        return None, None
    if m.group(7):
        local += dt.timedelta(seconds=float(m.group(7)))
    tz = m.group(8)
    offset = dt.timedelta(0) if tz == "Z" else parse_utc_offset(tz) if tz else None
    return local, offset


#: numbers of the Pix4D camera namespace (``http://pix4d.com/camera/1.0/``, written by MicaSense, Parrot and other
#: cameras that follow Pix4D's XMP layout), all in metres: the GNSS standard deviations, the height above ground
PIX4D_CAMERA_NUMBERS = {"Camera:GPSXYAccuracy": "xmp_gps_xy_accuracy_m", "Camera:GPSZAccuracy": "xmp_gps_z_accuracy_m",
                        "Camera:AboveGroundAltitude": "xmp_above_ground_altitude_m"}


def _gps_accuracy(xmp: dict[str, str], meta: ImageMetadata, warn) -> None:
    """The numbers of :data:`PIX4D_CAMERA_NUMBERS` into ``meta.extra`` (metres); a value that is not a positive
    number below 1 km (10 km for a height) is a warning and left out."""
    for key, name in PIX4D_CAMERA_NUMBERS.items():
        if key not in xmp:
            continue
        try:
            value = float(xmp[key])
        except ValueError:
            value = float("nan")
        if math.isfinite(value) and 0 < value < (10000 if "Altitude" in key else 1000):
            meta.extra[name] = value
        else:
            warn(f"XMP {key} = {xmp[key]!r} is not a length in metres within its range; ignored", key)


def _interpret(
    meta: ImageMetadata, exif: ExifData | None, xmp: dict[str, str], cfg: IngestConfig, warn
) -> None:
    meta.has_metadata = exif is not None or bool(xmp)
    if exif is not None:
        for field_name, message in exif.notes:
            warn(message, field_name)
        meta.make, meta.model, meta.serial, meta.lens = exif.make, exif.model, exif.serial, exif.lens
        meta.local_time = exif.datetime_original
        if exif.utc_offset is not None:
            meta.utc_offset, meta.utc_offset_source = exif.utc_offset, "EXIF OffsetTimeOriginal"
        if exif.gps_utc is not None:
            meta.gnss_utc, meta.gnss_utc_source = exif.gps_utc, "EXIF GPSDateStamp/GPSTimeStamp"
        if exif.orientation not in (None, 1):
            warn(
                f"EXIF Orientation is {exif.orientation}: pixels are used as stored "
                "(not rotated for display)",
                "Orientation",
            )
        if exif.focal_length_mm is not None:
            meta.extra["exif_focal_length_mm"] = exif.focal_length_mm
        if exif.focal_length_35mm is not None:
            meta.extra["exif_focal_length_35mm"] = exif.focal_length_35mm
        if exif.focal_plane_pitch_mm is not None:
            # the pitch of the pixels as stored: a camera that records a 4000-pixel sensor width and a
            # 1800-pixel image (resized after capture) has pixels 4000/1800 times larger than the sensor's
            recorded = exif.exif_image_width or meta.width
            meta.extra["exif_pixel_pitch_mm"] = exif.focal_plane_pitch_mm * recorded / meta.width if meta.width \
                else exif.focal_plane_pitch_mm
        if exif.ambient_temperature_c is not None:
            meta.extra["exif_ambient_temperature_c"] = exif.ambient_temperature_c
        if exif.maker_note is not None and is_canon(exif.make):
            canon = read_canon_maker_note(exif.block, exif.maker_note, exif.model)
            for field_name, message in canon.notes:
                warn(message, field_name)
            meta.serial = meta.serial or canon.serial
            meta.lens = meta.lens or canon.lens
            if canon.temperature_c is not None and meta.temperature_c is None:
                meta.temperature_c, meta.temperature_source = canon.temperature_c, canon.temperature_source
    # identity and time from XMP where EXIF lacks them
    meta.make = meta.make or _clean(xmp.get("tiff:Make"))
    meta.model = meta.model or _clean(xmp.get("tiff:Model"))
    meta.serial = meta.serial or _clean(xmp.get("aux:SerialNumber"))
    meta.lens = meta.lens or _clean(xmp.get("aux:Lens"))
    if meta.serial and set(meta.serial) <= {"0"}:  # DJI M2EA/M30T/H30T write "0": no serial recorded
        meta.serial = None
    if meta.raw_format == "flir-fff":  # the FFF record names the core where EXIF does not
        meta.serial = meta.serial or _clean(str(meta.extra.get("flir_camera_serial") or "")) or None
        if not meta.model and meta.extra.get("flir_camera_model"):
            meta.make = meta.make or "FLIR"
            meta.model = str(meta.extra["flir_camera_model"])
    central = xmp.get("FLIR:CentralTemperature")
    if central is not None:
        try:
            meta.extra["flir_central_temperature_scene_c"] = float(central)
        except ValueError:
            warn(f"XMP FLIR:CentralTemperature {central[:40]!r} is not a number; ignored", "CentralTemperature")
    for key in ("exif:DateTimeOriginal", "xmp:CreateDate"):
        local, offset = _parse_xmp_time(xmp.get(key))
        if local is None:
            continue
        if meta.local_time is None:
            meta.local_time = local
        same_clock = abs((local - meta.local_time).total_seconds()) < 1.0
        if offset is not None and meta.utc_offset is None and same_clock:
            meta.utc_offset, meta.utc_offset_source = offset, f"XMP {key}"
    if meta.local_time is not None and not (1990 <= meta.local_time.year <= 2100):
        warn(f"capture time {meta.local_time.isoformat()} is implausible; nulled", "DateTimeOriginal")
        meta.local_time = None

    # recorded pose: vendor XMP first, EXIF GPS otherwise
    if has_dji(xmp):
        pose = read_dji_xmp(xmp)
    elif has_parrot(xmp):
        pose = read_parrot(xmp)
    elif has_sensefly(xmp):
        pose = read_sensefly(xmp)
        if pose.utc_time and meta.gnss_utc is None:
            local, offset = _parse_xmp_time(pose.utc_time)
            if local is not None:
                meta.gnss_utc = local - (offset or dt.timedelta(0))
                meta.gnss_utc_source = "XMP sensefly:UTCTime"
    else:
        pose = RecordedPose(source="none")
    if pose.lat is None and exif is not None and exif.gps_lat is not None:
        pose.source = "exif:gps" if pose.source == "none" else pose.source
        pose.lat, pose.lon = exif.gps_lat, exif.gps_lon
        if pose.alt is None and exif.gps_alt is not None:
            pose.alt, pose.alt_reference = exif.gps_alt, "sea level (EXIF GPSAltitude)"
    for field_name, message in pose.notes:
        warn(message, field_name)
    meta.extra.update(pose.extra)
    _gps_accuracy(xmp, meta, warn)
    _check_pose(pose, cfg, warn)
    meta.pose = pose
    if meta.temperature_c is not None:
        lo, hi = cfg.temperature_range_c
        if not in_range(meta.temperature_c, lo, hi):
            warn(
                f"camera temperature {meta.temperature_c} degC ({meta.temperature_source}) is outside "
                f"{lo}..{hi} degC; nulled",
                "temperature_c",
            )
            meta.temperature_c = meta.temperature_source = None
    if not meta.has_metadata:
        warn("no EXIF or XMP metadata: camera, capture time and position are unknown", "metadata")


def _check_pose(pose: RecordedPose, cfg: IngestConfig, warn) -> None:
    """Null (and report) positions and angles outside their physical ranges."""
    lat_ok = pose.lat is None or in_range(pose.lat, *PLAUSIBLE_RANGES["lat"])
    lon_ok = pose.lon is None or in_range(pose.lon, *PLAUSIBLE_RANGES["lon"])
    if not (lat_ok and lon_ok):
        warn(
            f"position lat={pose.lat}, lon={pose.lon} ({pose.source}) is outside the globe; nulled", "lat/lon"
        )
        pose.lat = pose.lon = None
    if (pose.lat is None) != (pose.lon is None):
        warn(f"only one of latitude/longitude is present ({pose.source}); position nulled", "lat/lon")
        pose.lat = pose.lon = None
    if pose.alt is not None and not in_range(pose.alt, *cfg.altitude_range_m):
        lo, hi = cfg.altitude_range_m
        warn(f"altitude {pose.alt} m ({pose.source}) is outside {lo}..{hi} m; nulled", "alt")
        pose.alt = None
    for name in ("roll", "pitch", "yaw"):
        value = getattr(pose, name)
        lo, hi = PLAUSIBLE_RANGES[name]
        if value is not None and not in_range(value, lo, hi):
            warn(f"{name} {value} deg ({pose.source}) is outside {lo}..{hi} deg; nulled", name)
            setattr(pose, name, None)
    if pose.convention is not None and any(getattr(pose, n) is None for n in ("roll", "pitch", "yaw")):
        if any(getattr(pose, n) is not None for n in ("roll", "pitch", "yaw")):
            warn(f"attitude incomplete ({pose.source}): roll/pitch/yaw nulled together", "attitude")
        pose.roll = pose.pitch = pose.yaw = None
        pose.convention = None


def _clean(text: str | None) -> str | None:
    if text is None:
        return None
    text = "".join(ch for ch in text if ch.isprintable()).strip()
    return text[:200] or None
