"""FLIR radiometric JPEG: the FFF file in APP1 ``FLIR`` segments, its raw frame and its Planck constants.

Layout (as ExifTool's ``FLIR.pm`` documents it, checked on ``shared/data/flir_samples``):

* **APP1 segments** whose payload starts ``FLIR\\0``: byte 5 is 1, byte 6 the segment's index, byte 7 the
  index of the last segment; bytes 8.. concatenated in index order form one FFF file.
* **FFF header** (64 bytes): ``FFF\\0`` (``AFF\\0`` on some models), a 16-byte creator (``ATAU_RBFO`` on
  the Tau cores of DJI Zenmuse XT/XT2), then version (100..199), directory offset and entry count as
  uint32. The byte order is the one in which the version reads 100..199: big-endian on FLIR handhelds,
  little-endian on the DJI Zenmuse XT family.
* **Directory**: 32-byte entries (type, subtype uint16; version, index id, offset, length uint32, ...).
  Type 1 is the raw frame, 0x20 the camera information; 14 (visual image), 0x21, 0x22, 0x2a, 0x2b are
  not needed here.
* **Raw frame record**: a 32-byte header whose first uint16 is 2 in the record's byte order, width and
  height at bytes 2 and 4; from byte 32 either a 16-bit PNG whose samples are stored **little-endian**,
  contrary to the PNG standard (so bytes are swapped after decoding), or ``width x height`` uint16 in the
  record's byte order with no wrapper (the "TIFF" of ExifTool's listing on the E40/E60 and the XT2).
* **Camera information record** (offsets in bytes): 0x20 emissivity, 0x24 object distance (m), 0x28
  reflected apparent temperature (K), 0x2c atmospheric temperature (K), 0x30 IR window temperature (K),
  0x34 IR window transmission, 0x3c relative humidity (fraction; > 2 read as percent), 0x58/0x5c/0x60
  Planck R1, B, F, 0x70..0x80 atmospheric transmission alpha1, alpha2, beta1, beta2, X, 0xd4 camera model
  (32 chars), 0xf4 part number, 0x104 serial number (16 each), 0x170 lens model (32), 0x1a0 lens serial
  (16), 0x1b4 horizontal field of view (deg), 0x308 Planck O (int32), 0x30c Planck R2.

Temperatures follow FLIR's radiometric chain as published by ExifTool's author and implemented in
Thermimage ``raw2temp`` and ``flyr`` (object signal = raw counts corrected for atmosphere, window and
reflected radiation, then T = B / ln(R1 / (R2 (S + O)) + F)). ``flyr`` 5.1 is the reference reader the
tests compare with (it cannot read the little-endian DJI files; those are checked against ExifTool's raw
frame and an independent Planck evaluation in ``shared/data/flir_samples/README.md``).

None of these cameras records its focal-plane (core) temperature in the FFF records read here; the XMP
``FLIR:CentralTemperature`` of DJI XT files is a *scene* temperature and is never taken for the sensor's.

Kept as our own reader: Pillow returns the APP1 ``FLIR`` segments as opaque bytes and tifffile reads no
JPEG; ``flyr`` reads FFF files but is licensed EUPL-1.2 (a development-only reference here, never imported
by the product), cannot read the little-endian Zenmuse layout and takes 12-15x longer per file to temperatures
(``benchmarks/ingest_bench.py``). The 16-bit PNG inside the raw-frame record is decoded by OpenCV.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aerocal.ingest.jpeg import JpegFormatError, JpegStructure, parse_jpeg

APP1 = 0xE1
SEGMENT_MAGIC = b"FLIR\x00"
FFF_MAGICS = (b"FFF\x00", b"AFF\x00")
RECORD_RAW, RECORD_CAMERA_INFO = 0x01, 0x20
_HEADER_BYTES, _ENTRY_BYTES, _RAW_HEADER_BYTES = 64, 32, 32
_MAX_SIDE = 8192
KELVIN = 273.15


class FlirFormatError(ValueError):
    """The FLIR segments are present but do not form a readable FFF file; the message says where."""


@dataclass(frozen=True)
class FlirCameraInfo:
    """The FFF camera-information record. Temperatures in kelvin, distance in metres, humidity 0..1."""

    emissivity: float
    object_distance_m: float
    reflected_temperature_k: float
    atmospheric_temperature_k: float
    window_temperature_k: float
    window_transmission: float
    relative_humidity: float
    planck_r1: float
    planck_b: float
    planck_f: float
    planck_o: float
    planck_r2: float
    atm_alpha1: float
    atm_alpha2: float
    atm_beta1: float
    atm_beta2: float
    atm_x: float
    camera_model: str = ""
    camera_part_number: str = ""
    camera_serial: str = ""
    lens_model: str = ""
    lens_serial: str = ""
    field_of_view_deg: float = 0.0

    def problems(self) -> list[str]:
        """What makes the temperature conversion meaningless (empty when it can be used)."""
        out = []
        for name in ("planck_r1", "planck_b", "planck_f", "planck_r2"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                out.append(f"Planck {name[7:].upper()} = {value!r} (must be finite and > 0)")
        if not (math.isfinite(self.emissivity) and 0.0 < self.emissivity <= 1.0):
            out.append(f"emissivity {self.emissivity!r} (must be in (0, 1])")
        if not (math.isfinite(self.window_transmission) and 0.0 < self.window_transmission <= 1.0):
            out.append(f"IR window transmission {self.window_transmission!r} (must be in (0, 1])")
        for name in ("reflected_temperature_k", "atmospheric_temperature_k", "window_temperature_k"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 100.0 < value < 600.0):
                out.append(f"{name[:-2].replace('_', ' ')} {value!r} K (outside 100..600 K)")
        if not (math.isfinite(self.object_distance_m) and 0.0 <= self.object_distance_m < 1e5):
            out.append(f"object distance {self.object_distance_m!r} m")
        return out


@dataclass(frozen=True)
class FlirThermogram:
    """A FLIR radiometric frame: raw counts (uint16, (H, W), pixels from the top-left corner) and the
    camera information that converts them to temperatures. ``payload`` is ``"png"`` or ``"raw"``;
    ``byte_order`` (``"<"`` or ``">"``) is the FFF header's; ``creator`` the FFF creator string."""

    raw: np.ndarray
    info: FlirCameraInfo | None
    payload: str
    byte_order: str
    creator: str

    def celsius(self) -> np.ndarray:
        """Object temperatures (degC, float64, (H, W)); raises ``FlirFormatError`` without usable constants."""
        if self.info is None:
            raise FlirFormatError("no camera-information record: the Planck constants are unknown")
        bad = self.info.problems()
        if bad:
            raise FlirFormatError("camera information unusable for temperatures: " + "; ".join(bad))
        return raw_to_celsius(self.raw, self.info)


# ------------------------------------------------------------------------------------------- segments
def has_flir(jpeg: JpegStructure) -> bool:
    """True when the JPEG carries APP1 ``FLIR`` segments."""
    return any(m == APP1 and p.startswith(SEGMENT_MAGIC) for m, p in jpeg.app_segments)


def fff_bytes(jpeg: JpegStructure) -> bytes | None:
    """The FFF file assembled from the APP1 ``FLIR`` segments, or ``None`` when there are none.

    Raises:
        FlirFormatError: a FLIR segment is shorter than its 8-byte header, the segments disagree on their count, an
            index appears twice, or segments are missing (file cut or edited).
    """
    segments = [p for m, p in jpeg.app_segments if m == APP1 and p.startswith(SEGMENT_MAGIC)]
    if not segments:
        return None
    parts: dict[int, bytes] = {}
    last = None
    for p in segments:
        if len(p) < 8:
            raise FlirFormatError(f"a FLIR APP1 segment is {len(p)} bytes long, shorter than its 8-byte header")
        index, final = p[6], p[7]
        if last is not None and final != last:
            raise FlirFormatError(f"FLIR APP1 segments disagree on their count ({last + 1} and {final + 1})")
        last = final
        if index in parts:
            raise FlirFormatError(f"FLIR APP1 segment {index} appears twice")
        parts[index] = p[8:]
    assert last is not None
    missing = [i for i in range(last + 1) if i not in parts]
    if missing:
        raise FlirFormatError(
            f"FLIR APP1 segment(s) {', '.join(map(str, missing))} of {last + 1} missing (file cut or edited)"
        )
    return b"".join(parts[i] for i in range(last + 1))


# ------------------------------------------------------------------------------------------------ FFF
@dataclass(frozen=True)
class _Record:
    kind: int
    offset: int
    length: int


def _directory(fff: bytes) -> tuple[str, str, list[_Record]]:
    if len(fff) < _HEADER_BYTES or fff[:4] not in FFF_MAGICS:
        raise FlirFormatError(f"the FLIR segments do not start with an FFF header (found {fff[:4]!r})")
    version_be = struct.unpack_from(">I", fff, 20)[0]
    order = ">" if 100 <= version_be < 200 else "<"
    version, offset, count = struct.unpack_from(order + "III", fff, 20)
    if not 100 <= version < 200:
        raise FlirFormatError(f"FFF version {version} unknown (100..199 are read)")
    if count > 4096 or offset + count * _ENTRY_BYTES > len(fff):
        raise FlirFormatError(f"FFF directory of {count} entries at byte {offset} runs past the {len(fff)} bytes")
    creator = fff[4:20].split(b"\x00")[0].decode("ascii", "replace")
    records = []
    for k in range(count):
        kind, _sub, _ver, _idx, r_off, r_len = struct.unpack_from(order + "HHIIII", fff, offset + k * _ENTRY_BYTES)
        if kind == 0:
            continue
        if r_off + r_len > len(fff):
            raise FlirFormatError(f"FFF record of type {kind} at byte {r_off} runs past the end of the file")
        records.append(_Record(kind, r_off, r_len))
    return order, creator, records


def _record_order(block: bytes, default: str) -> str:
    """A record's byte order: the one in which its first uint16 reads 2 (ExifTool's rule)."""
    if len(block) >= 2:
        if struct.unpack_from("<H", block)[0] == 2:
            return "<"
        if struct.unpack_from(">H", block)[0] == 2:
            return ">"
    return default


def _raw_size(block: bytes, order: str) -> tuple[int, int]:
    if len(block) < _RAW_HEADER_BYTES:
        raise FlirFormatError(f"raw-frame record is {len(block)} bytes, shorter than its 32-byte header")
    w, h = struct.unpack_from(order + "HH", block, 2)
    if not (0 < w <= _MAX_SIDE and 0 < h <= _MAX_SIDE):
        raise FlirFormatError(f"raw-frame record gives an impossible size {w}x{h}")
    return w, h


def _decode_raw(block: bytes, order: str) -> tuple[np.ndarray, str]:
    w, h = _raw_size(block, order)
    data = block[_RAW_HEADER_BYTES:]
    if data[:4] == b"\x89PNG":
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.dtype != np.uint16 or img.ndim != 2:
            raise FlirFormatError("the raw frame's PNG cannot be decoded as a 16-bit greyscale image")
        if img.shape != (h, w):
            raise FlirFormatError(f"the raw frame's PNG is {img.shape[1]}x{img.shape[0]}, its header says {w}x{h}")
        return img.byteswap(), "png"  # FLIR writes the 16-bit samples little-endian inside the PNG
    need = 2 * w * h
    if len(data) < need:
        raise FlirFormatError(f"raw frame {w}x{h} needs {need} bytes, the record holds {len(data)}")
    return np.frombuffer(data[:need], dtype=order + "u2").reshape(h, w).astype(np.uint16), "raw"


def _text(block: bytes, offset: int, size: int) -> str:
    raw = block[offset : offset + size].split(b"\x00")[0]
    text = raw.decode("latin-1", "replace")
    return "".join(ch for ch in text if ch.isprintable()).strip()


#: float32 fields of the camera-information record: attribute -> byte offset (module docstring)
CAMERA_INFO_FLOATS = {
    "emissivity": 0x20,
    "object_distance_m": 0x24,
    "reflected_temperature_k": 0x28,
    "atmospheric_temperature_k": 0x2C,
    "window_temperature_k": 0x30,
    "window_transmission": 0x34,
    "relative_humidity": 0x3C,
    "planck_r1": 0x58,
    "planck_b": 0x5C,
    "planck_f": 0x60,
    "atm_alpha1": 0x70,
    "atm_alpha2": 0x74,
    "atm_beta1": 0x78,
    "atm_beta2": 0x7C,
    "atm_x": 0x80,
    "field_of_view_deg": 0x1B4,
    "planck_r2": 0x30C,
}
#: text fields: attribute -> (byte offset, size); Planck O is an int32 at :data:`PLANCK_O_OFFSET`
CAMERA_INFO_TEXT = {
    "camera_model": (0xD4, 32),
    "camera_part_number": (0xF4, 16),
    "camera_serial": (0x104, 16),
    "lens_model": (0x170, 32),
    "lens_serial": (0x1A0, 16),
}
PLANCK_O_OFFSET = 0x308
CAMERA_INFO_BYTES = 0x310


def _camera_info(block: bytes, default: str) -> FlirCameraInfo | None:
    if len(block) < CAMERA_INFO_BYTES:
        return None
    o = _record_order(block, default)
    values: dict[str, object] = {
        name: float(struct.unpack_from(o + "f", block, off)[0]) for name, off in CAMERA_INFO_FLOATS.items()
    }
    rh = float(values["relative_humidity"])  # type: ignore[arg-type]
    values["relative_humidity"] = rh / 100.0 if rh > 2.0 else rh
    values["planck_o"] = float(struct.unpack_from(o + "i", block, PLANCK_O_OFFSET)[0])
    for name, (off, size) in CAMERA_INFO_TEXT.items():
        values[name] = _text(block, off, size)
    return FlirCameraInfo(**values)  # type: ignore[arg-type]


@dataclass(frozen=True)
class _Fff:
    """The parts of an FFF file the readers need: the raw-frame record and its byte order, the camera
    information (``None`` without a record), the header's byte order and creator."""

    raw_block: bytes
    raw_order: str
    info: FlirCameraInfo | None
    order: str
    creator: str


def _read_fff(jpeg: JpegStructure) -> _Fff | None:
    fff = fff_bytes(jpeg)
    if fff is None:
        return None
    order, creator, records = _directory(fff)
    by_kind: dict[int, _Record] = {}
    for r in records:
        by_kind.setdefault(r.kind, r)
    if RECORD_RAW not in by_kind:
        raise FlirFormatError("the FFF file has no raw-frame record (type 1): not a radiometric image")
    raw = by_kind[RECORD_RAW]
    block = fff[raw.offset : raw.offset + raw.length]
    info_rec = by_kind.get(RECORD_CAMERA_INFO)
    info = None if info_rec is None else _camera_info(fff[info_rec.offset : info_rec.offset + info_rec.length], order)
    return _Fff(block, _record_order(block, order), info, order, creator)


def flir_layout(jpeg: JpegStructure) -> tuple[int, int, FlirCameraInfo | None] | None:
    """(width, height, camera info) of the raw frame, read from the headers only; ``None`` when the JPEG
    has no FLIR segments. Raises :class:`FlirFormatError` when they are present but broken."""
    found = _read_fff(jpeg)
    if found is None:
        return None
    w, h = _raw_size(found.raw_block, found.raw_order)
    return w, h, found.info


def read_flir(jpeg: JpegStructure) -> FlirThermogram | None:
    """The thermogram of a FLIR radiometric JPEG; ``None`` when it has no FLIR segments.

    Raises :class:`FlirFormatError` (naming what is wrong) when the segments are present but broken.
    """
    found = _read_fff(jpeg)
    if found is None:
        return None
    raw, payload = _decode_raw(found.raw_block, found.raw_order)
    return FlirThermogram(raw, found.info, payload, found.order, found.creator)


# ------------------------------------------------------------------------------------------ radiometry
def _planck_counts(t_k: float, info: FlirCameraInfo) -> float:
    """Raw counts a black body at ``t_k`` kelvin gives (FLIR's Planck curve with offset O)."""
    return info.planck_r1 / (info.planck_r2 * (math.exp(info.planck_b / t_k) - info.planck_f)) - info.planck_o


def atmospheric_transmission(info: FlirCameraInfo) -> float:
    """Transmission of the air path of ``object_distance_m`` (FLIR's two-term model of water vapour)."""
    t_c = info.atmospheric_temperature_k - KELVIN
    h2o = info.relative_humidity * math.exp(1.5587 + 0.06939 * t_c - 0.00027816 * t_c**2 + 0.00000068455 * t_c**3)
    d = -math.sqrt(max(info.object_distance_m, 0.0) / 2.0)
    a1 = math.exp(d * (info.atm_alpha1 + info.atm_beta1 * math.sqrt(h2o)))
    a2 = math.exp(d * (info.atm_alpha2 + info.atm_beta2 * math.sqrt(h2o)))
    return info.atm_x * a1 + (1.0 - info.atm_x) * a2


def object_signal(raw: np.ndarray, info: FlirCameraInfo) -> np.ndarray:
    """Raw counts with the atmosphere, the IR window and the reflected radiation removed (float64)."""
    e, tw = info.emissivity, info.window_transmission
    tau = atmospheric_transmission(info)
    refl = _planck_counts(info.reflected_temperature_k, info)
    atm = _planck_counts(info.atmospheric_temperature_k, info)
    window = _planck_counts(info.window_temperature_k, info)
    gain = e * tau * tw * tau
    offset = (
        (1.0 - e) / e * refl  # reflected by the object
        + (1.0 - tau) / e / tau * atm  # emitted by the air before the window
        + (1.0 - tw) / (e * tau * tw) * window  # emitted by the window (no reflection by it)
        + (1.0 - tau) / (e * tau * tw * tau) * atm  # emitted by the air after the window
    )
    return np.asarray(raw, dtype=np.float64) / gain - offset


def raw_to_celsius(raw: np.ndarray, info: FlirCameraInfo) -> np.ndarray:
    """Object temperature (degC) of raw counts; NaN where the signal is outside the Planck curve."""
    s = object_signal(raw, info) + info.planck_o
    with np.errstate(divide="ignore", invalid="ignore"):
        arg = info.planck_r1 / (info.planck_r2 * s) + info.planck_f
        t = info.planck_b / np.log(arg)
    t = np.where((s > 0) & (arg > 1.0), t, np.nan)
    return t - KELVIN


def celsius_to_raw(t_c: np.ndarray, info: FlirCameraInfo) -> np.ndarray:
    """Inverse of :func:`raw_to_celsius` (float64 counts), for writing simulated radiometric frames."""
    t_k = np.asarray(t_c, dtype=np.float64) + KELVIN
    s = info.planck_r1 / (info.planck_r2 * (np.exp(info.planck_b / t_k) - info.planck_f)) - info.planck_o
    e, tw = info.emissivity, info.window_transmission
    tau = atmospheric_transmission(info)
    offset = -object_signal(np.zeros(1), info)[0]  # the counts object_signal subtracts
    return (s + offset) * (e * tau * tw * tau)


def common_camera_info(paths) -> tuple[FlirCameraInfo | None, str]:
    """The camera information shared by every FLIR frame of ``paths``, with one sentence on why not when
    there is none (not FLIR files, broken, or frames recorded with different constants or emissivity:
    a counts mosaic then has no single temperature scale)."""
    first: FlirCameraInfo | None = None
    for p in paths:
        if Path(p).suffix.lower() not in (".jpg", ".jpeg"):
            return None, (f"the frames carry no radiometric calibration ({Path(p).name} is a {Path(p).suffix} file, "
                          "not a FLIR radiometric JPEG): their values are counts, with no conversion to temperature")
        try:
            layout = flir_layout(parse_jpeg(Path(p).read_bytes()))
        except (OSError, JpegFormatError, FlirFormatError) as exc:
            return None, f"{p}: not a readable FLIR radiometric JPEG ({exc})"
        if layout is None or layout[2] is None:
            return None, (f"{p}: not a FLIR radiometric JPEG with camera information (DJI R-JPEG counts have no "
                          "documented conversion to temperature)")
        info = layout[2]
        if info.problems():
            return None, f"{p}: camera information unusable for temperatures ({'; '.join(info.problems())})"
        if first is None:
            first = info
            continue
        keys = (*CAMERA_INFO_FLOATS, "planck_o")
        differ = [k for k in keys if not math.isclose(getattr(info, k), getattr(first, k), rel_tol=1e-6, abs_tol=1e-9)]
        if differ:
            what = ", ".join(differ)
            return None, f"{p}: recorded with other {what} than the first frame: no single temperature scale"
    if first is None:
        return None, "no frames"
    return first, "every frame records the same Planck constants, emissivity and atmosphere"
