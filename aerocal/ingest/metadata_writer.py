"""Writing the metadata ingest reads: EXIF (IFD0, EXIF and GPS IFDs) and XMP, into TIFF and JPEG files.

The inverse of the readers, for flights the project makes itself (the simulator's contract: 16-bit
single-channel TIFF or 8-bit JPEG, EXIF Make/Model/BodySerialNumber/DateTimeOriginal, an XMP packet with
``drone-dji`` fields) and for tests. Files are little-endian classic TIFF, one uncompressed strip;
JPEGs get an APP1 EXIF segment and an APP1 XMP segment right after SOI (existing APPn segments other
than APP0 are removed).

The IFDs are laid out here rather than by Pillow's ``Exif.tobytes``: Pillow reduces every rational (the
47000000/1000000 written here becomes 47/1), so the files the simulator and the tests write would change
byte for byte. Tag numbers are Pillow's (:mod:`PIL.ExifTags`).
"""

from __future__ import annotations

import datetime as dt
import struct
from collections.abc import Mapping
from pathlib import Path
from xml.sax.saxutils import quoteattr

import cv2
import numpy as np
from PIL.ExifTags import IFD, Base

from aerocal.ingest.flir import CAMERA_INFO_BYTES, CAMERA_INFO_FLOATS, CAMERA_INFO_TEXT, PLANCK_O_OFFSET
from aerocal.ingest.jpeg import parse_jpeg
from aerocal.ingest.xmp import XMP_APP1_HEADER
from aerocal.io import atomic_path

#: one IFD entry to write: (tag, TIFF type, values); values are str (ASCII), bytes (BYTE/UNDEFINED),
#: a sequence of ints (SHORT/LONG) or of floats (RATIONAL: written as num/10**6)
Entry = tuple[int, int, object]

#: the XML namespace of the ``drone-dji`` XMP fields DJI drones write (position, gimbal and aircraft attitude;
#: :mod:`aerocal.ingest.dji`)
DJI_NAMESPACE = "http://www.dji.com/drone-dji/1.0/"


def _encode_value(typ: int, values: object) -> tuple[int, bytes]:
    if typ == 2:
        raw = str(values).encode("latin-1", errors="replace") + b"\x00"
        return len(raw), raw
    if typ in (1, 7):
        raw = bytes(values)  # type: ignore[arg-type]
        return len(raw), raw
    seq = list(values)  # type: ignore[call-overload]
    if typ == 3:
        return len(seq), struct.pack(f"<{len(seq)}H", *seq)
    if typ == 4:
        return len(seq), struct.pack(f"<{len(seq)}I", *seq)
    if typ == 5:
        parts = []
        for v in seq:  # the finest denominator (up to 1e6) whose numerator fits 32 bits
            den = max(1, min(1_000_000, int(0xFFFFFFFF // max(abs(float(v)), 1.0))))
            parts += [int(round(float(v) * den)), den]
        return len(seq), struct.pack(f"<{len(parts)}I", *parts)
    if typ == 11:
        return len(seq), struct.pack(f"<{len(seq)}f", *seq)
    if typ == 12:
        return len(seq), struct.pack(f"<{len(seq)}d", *seq)
    raise ValueError(f"TIFF type {typ} is not written by this module")


def _ifd_bytes(entries: list[Entry], start: int) -> bytes:
    """An IFD placed at byte ``start`` of the file, followed by its out-of-line values (no next IFD)."""
    entries = sorted(entries, key=lambda e: e[0])
    n = len(entries)
    header_len = 2 + 12 * n + 4
    data_pos = start + header_len
    head = bytearray(struct.pack("<H", n))
    tail = bytearray()
    for tag, typ, values in entries:
        count, raw = _encode_value(typ, values)
        if len(raw) <= 4:
            head += struct.pack("<HHI", tag, typ, count) + raw.ljust(4, b"\x00")
        else:
            offset = data_pos + len(tail)
            head += struct.pack("<HHII", tag, typ, count, offset)
            tail += raw
            if len(tail) % 2:
                tail += b"\x00"
    head += struct.pack("<I", 0)
    return bytes(head + tail)


def _exif_entries(
    serial: str | None,
    lens: str | None,
    time: dt.datetime | None,
    utc_offset: str | None,
    focal_mm: float | None = None,
) -> list[Entry]:
    exif: list[Entry] = []
    if focal_mm is not None:
        exif.append((Base.FocalLength, 5, [float(focal_mm)]))
    if time is not None:
        exif.append((Base.DateTimeOriginal, 2, time.strftime("%Y:%m:%d %H:%M:%S")))
        if time.microsecond:
            exif.append((Base.SubsecTimeOriginal, 2, f"{time.microsecond:06d}".rstrip("0")))
    if utc_offset:
        exif.append((Base.OffsetTimeOriginal, 2, utc_offset))
    if serial:
        exif.append((Base.BodySerialNumber, 2, serial))
    if lens:
        exif.append((Base.LensModel, 2, lens))
    return exif


def _gps_entries(lat: float | None, lon: float | None, alt: float | None) -> list[Entry]:
    if lat is None or lon is None:
        return []

    def dms(v: float) -> list[float]:
        v = abs(v)
        d = int(v)
        m = int((v - d) * 60)
        return [float(d), float(m), (v - d - m / 60.0) * 3600.0]

    gps: list[Entry] = [
        (0, 1, b"\x02\x03\x00\x00"),
        (1, 2, "N" if lat >= 0 else "S"),
        (2, 5, dms(lat)),
        (3, 2, "E" if lon >= 0 else "W"),
        (4, 5, dms(lon)),
    ]
    if alt is not None:
        gps += [(5, 1, b"\x00" if alt >= 0 else b"\x01"), (6, 5, [abs(alt)])]
    return gps


def exif_block(
    make: str | None = None,
    model: str | None = None,
    serial: str | None = None,
    lens: str | None = None,
    time: dt.datetime | None = None,
    utc_offset: str | None = None,
    gps: tuple[float, float, float | None] | None = None,
    ifd0_extra: list[Entry] | None = None,
    focal_mm: float | None = None,
    exif_extra: list[Entry] | None = None,
) -> bytes:
    """A little-endian TIFF block: IFD0 (Make, Model), the EXIF IFD and the GPS IFD (a JPEG APP1 body).

    ``ifd0_extra`` and ``exif_extra``: further ``(tag, TIFF type, values)`` entries of IFD0 and of the EXIF IFD
    (e.g. ``(Base.FocalPlaneXResolution, 5, [16393.44])``)."""
    ifd0: list[Entry] = list(ifd0_extra or [])
    if make:
        ifd0.append((Base.Make, 2, make))
    if model:
        ifd0.append((Base.Model, 2, model))
    exif = _exif_entries(serial, lens, time, utc_offset, focal_mm) + list(exif_extra or [])
    gps_e = _gps_entries(*gps) if gps else []
    # lay out: header (8) | IFD0 | EXIF IFD | GPS IFD; pointers are fixed up once sizes are known
    ifd0_full = ifd0 + ([(IFD.Exif, 4, [0])] if exif else []) + ([(IFD.GPSInfo, 4, [0])] if gps_e else [])
    exif_pos = 8 + len(_ifd_bytes(ifd0_full, 8))
    b1 = _ifd_bytes(exif, exif_pos) if exif else b""
    gps_pos = exif_pos + len(b1)
    b2 = _ifd_bytes(gps_e, gps_pos) if gps_e else b""
    fixed = list(ifd0)
    if exif:
        fixed.append((IFD.Exif, 4, [exif_pos]))
    if gps_e:
        fixed.append((IFD.GPSInfo, 4, [gps_pos]))
    b0 = _ifd_bytes(fixed, 8)
    return b"II*\x00" + struct.pack("<I", 8) + b0 + b1 + b2


def dji_xmp_packet(fields: Mapping[str, object]) -> str:
    """An XMP packet of ``drone-dji:<name>="<value>"`` attributes (floats signed, as DJI writes them)."""
    attrs = []
    for name, value in fields.items():
        text = f"{value:+.7f}" if isinstance(value, float) else str(value)
        attrs.append(f"   drone-dji:{name}={quoteattr(text)}")
    return (
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        f'  <rdf:Description rdf:about="" xmlns:drone-dji="{DJI_NAMESPACE}"\n'
        + "\n".join(attrs)
        + ">\n  </rdf:Description>\n </rdf:RDF>\n</x:xmpmeta>"
    )


def write_tiff_with_metadata(
    path: str | Path,
    pixels: np.ndarray,
    make: str | None = None,
    model: str | None = None,
    serial: str | None = None,
    time: dt.datetime | None = None,
    xmp: str | None = None,
    lens: str | None = None,
) -> Path:
    """Write an uncompressed TIFF (uint8/uint16, (H, W) or (H, W, C)) with EXIF and XMP, atomically.

    Raises:
        ValueError: ``pixels`` is not uint8 or uint16, or not of shape (H, W) or (H, W, C).
    """
    arr = np.ascontiguousarray(pixels)
    if arr.dtype not in (np.uint8, np.uint16) or arr.ndim not in (2, 3):
        raise ValueError(f"pixels must be uint8/uint16 (H, W[, C]); got {arr.dtype} {arr.shape}")
    h, w = arr.shape[:2]
    spp = 1 if arr.ndim == 2 else arr.shape[2]
    bits = arr.dtype.itemsize * 8
    data = arr.astype(arr.dtype.newbyteorder("<"), copy=False).tobytes()
    ifd0: list[Entry] = [
        (256, 4, [w]),
        (257, 4, [h]),
        (258, 3, [bits] * spp),
        (259, 3, [1]),
        (262, 3, [1 if spp == 1 else 2]),
        (273, 4, [0]),
        (277, 3, [spp]),
        (278, 4, [h]),
        (279, 4, [len(data)]),
        (284, 3, [1]),
    ]
    if make:
        ifd0.append((Base.Make, 2, make))
    if model:
        ifd0.append((Base.Model, 2, model))
    if xmp:
        ifd0.append((Base.XMLPacket, 1, xmp.encode("utf-8")))
    exif = _exif_entries(serial, lens, time, None)
    if exif:
        ifd0.append((IFD.Exif, 4, [0]))
    # two passes: sizes first, then real offsets
    exif_pos = 8 + len(_ifd_bytes(ifd0, 8))
    b1 = _ifd_bytes(exif, exif_pos) if exif else b""
    pix_pos = exif_pos + len(b1)
    ifd0 = [e for e in ifd0 if e[0] not in (273, IFD.Exif)] + [(273, 4, [pix_pos])]
    if exif:
        ifd0.append((IFD.Exif, 4, [exif_pos]))
    b0 = _ifd_bytes(ifd0, 8)
    blob = b"II*\x00" + struct.pack("<I", 8) + b0 + b1 + data
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(blob)
    return path


def _segment(marker: int, payload: bytes) -> bytes:
    if len(payload) + 2 > 0xFFFF:
        raise ValueError(f"APP{marker - 0xE0} payload of {len(payload)} bytes does not fit a JPEG segment")
    return bytes([0xFF, marker]) + struct.pack(">H", len(payload) + 2) + payload


def jpeg_without_metadata(jpeg: bytes) -> bytes:
    """The JPEG with every APP1..APP15 segment removed (EXIF, XMP, maker data); pixels untouched."""
    s = parse_jpeg(jpeg)
    out = bytearray(b"\xff\xd8")
    i = 2
    while i < s.sos_offset:
        while jpeg[i] == 0xFF and jpeg[i + 1] == 0xFF:
            i += 1
        marker = jpeg[i + 1]
        length = struct.unpack_from(">H", jpeg, i + 2)[0]
        if not 0xE1 <= marker <= 0xEF:
            out += jpeg[i : i + 2 + length]
        i += 2 + length
    return bytes(out + jpeg[s.sos_offset :])


def jpeg_with_metadata(jpeg: bytes, exif: bytes | None = None, xmp: str | None = None) -> bytes:
    """The JPEG with its APP1..APP15 segments replaced by an EXIF block and an XMP packet."""
    body = jpeg_without_metadata(jpeg)
    segs = b""
    if exif is not None:
        segs += _segment(0xE1, b"Exif\x00\x00" + exif)
    if xmp is not None:
        segs += _segment(0xE1, XMP_APP1_HEADER + xmp.encode("utf-8"))
    return body[:2] + segs + body[2:]


# ------------------------------------------------------------------------------ FLIR radiometric JPEG
def fff_file(raw: np.ndarray, info, byte_order: str = "<", payload: str = "raw", creator: str = "ATAU_RBFO") -> bytes:
    """A FLIR FFF file holding ``raw`` (uint16 (H, W) counts) and the camera information ``info``
    (:class:`aerocal.ingest.flir.FlirCameraInfo`), laid out as :mod:`aerocal.ingest.flir` documents.

    ``byte_order`` ``"<"`` writes the header and records little-endian (DJI Zenmuse XT family), ``">"``
    a big-endian header (FLIR handhelds; records stay little-endian, as those cameras write them);
    ``payload`` ``"raw"`` stores the counts unwrapped, ``"png"`` as a 16-bit PNG with FLIR's swapped bytes.

    Raises:
        ValueError: ``raw`` is not a 2-D uint16 array; ``payload`` is neither ``"raw"`` nor ``"png"``; OpenCV cannot
            encode the frame as PNG.
    """
    raw = np.asarray(raw)
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise ValueError(f"a FLIR raw frame must be a 2-D uint16 array, got {raw.dtype} {raw.shape}")
    h, w = raw.shape
    rec_order = "<"  # FLIR's records are little-endian on every sample of shared/data/flir_samples
    header = struct.pack(rec_order + "HHH", 2, w, h).ljust(32, b"\x00")
    if payload == "png":
        ok, png = cv2.imencode(".png", raw.byteswap())
        if not ok:
            raise ValueError("OpenCV could not encode the raw frame as PNG")
        raw_rec = header + png.tobytes()
    elif payload == "raw":
        raw_rec = header + raw.astype(rec_order + "u2").tobytes()
    else:
        raise ValueError(f"payload {payload!r} unknown; valid: raw, png")
    info_rec = bytearray(CAMERA_INFO_BYTES + 4)
    struct.pack_into(rec_order + "H", info_rec, 0, 2)
    for name, off in CAMERA_INFO_FLOATS.items():
        struct.pack_into(rec_order + "f", info_rec, off, float(getattr(info, name)))
    struct.pack_into(rec_order + "i", info_rec, PLANCK_O_OFFSET, int(round(info.planck_o)))
    for name, (off, size) in CAMERA_INFO_TEXT.items():
        text = str(getattr(info, name) or "").encode("latin-1", "replace")[: size - 1]
        info_rec[off : off + len(text)] = text
    # (type, subtype, record): the raw record's subtype says its coding (2 little-endian, 3 PNG), others 1
    records = [(1, 3 if payload == "png" else 2, raw_rec), (0x20, 1, bytes(info_rec))]
    directory_at = 64
    data_at = directory_at + 32 * len(records)
    directory, blob = b"", b""
    for k, (kind, sub, rec) in enumerate(records):
        offset = data_at + len(blob)
        directory += struct.pack(byte_order + "HHIIIIIII", kind, sub, 100, k + 1, offset, len(rec), 0, 0, 0)
        blob += rec
    head = b"FFF\x00" + creator.encode("ascii")[:16].ljust(16, b"\x00")
    head += struct.pack(byte_order + "III", 100, directory_at, len(records)).ljust(44, b"\x00")
    return head + directory + blob


def flir_app1_segments(fff: bytes, chunk: int = 65000) -> list[bytes]:
    """The APP1 payloads carrying ``fff``: ``FLIR\\0``, 1, segment index, last index, then the bytes.

    Raises:
        ValueError: ``fff`` needs more than 256 segments of ``chunk`` bytes.
    """
    parts = [fff[i : i + chunk] for i in range(0, len(fff), chunk)]
    if len(parts) > 256:
        raise ValueError(f"an FFF file of {len(fff)} bytes needs more than 256 APP1 segments")
    return [b"FLIR\x00\x01" + bytes([k, len(parts) - 1]) + p for k, p in enumerate(parts)]


def jpeg_with_flir(jpeg: bytes, fff: bytes) -> bytes:
    """``jpeg`` with the FFF file's APP1 ``FLIR`` segments inserted after its leading APPn segments."""
    s = parse_jpeg(jpeg)
    i = 2
    while i < s.sos_offset and 0xE0 <= jpeg[i + 1] <= 0xEF:
        i += 2 + struct.unpack_from(">H", jpeg, i + 2)[0]
    segs = b"".join(_segment(0xE1, p) for p in flir_app1_segments(fff))
    return jpeg[:i] + segs + jpeg[i:]
