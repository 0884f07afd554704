"""The marker structure of a JPEG file, read without decoding pixels.

Walks the marker segments from SOI up to the first SOS (start of scan), collecting the APPn payloads
(EXIF in APP1, XMP in APP1, DJI radiometric data in APP3/APP4) and the frame header (SOFn: size,
sample precision, components). Each step advances by at least two bytes and every length is checked
against the buffer, so a corrupted file cannot make it loop or read out of bounds. A file whose entropy
coded data has no EOI marker after the scan is reported as truncated: inside entropy-coded data a
0xFF byte is always followed by 0x00 or a restart marker, so ``FF D9`` after SOS can only be EOI.

Kept as our own walk: Pillow's ``JpegImagePlugin`` walks the same markers (its ``applist`` holds the APPn
payloads) but keeps no offsets, so the end-of-image check has no start of scan to search from; it opens a
DJI R-JPEG (whose APP2 holds an MPF index) as a multi-picture ``MpoImageFile``; and any break in the
structure comes back as "cannot identify image file" without saying where. tifffile reads no JPEG. This
walk is also faster than Pillow's ``Image.open`` (``benchmarks/history/engine_measurements.md``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

SOI = b"\xff\xd8"
EOI = b"\xff\xd9"
#: frame-header markers (baseline, extended, progressive, lossless, arithmetic); not DHT/JPG/DAC
SOF_MARKERS = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})
MAX_SEGMENTS = 65536


class JpegFormatError(ValueError):
    """The bytes are not a readable JPEG; the message says where the structure breaks."""


@dataclass
class JpegStructure:
    """What ingest needs from a JPEG: frame size, APPn payloads (without the length field), scan start."""

    width: int
    height: int
    precision: int  # bits per sample (8 for ordinary JPEGs)
    components: int
    app_segments: list[tuple[int, bytes]] = field(default_factory=list)  # (marker 0xE0..0xEF, payload)
    sos_offset: int = 0
    has_eoi: bool = False

    def app(self, marker: int) -> list[bytes]:
        """Payloads of all APPn segments with this marker (e.g. ``0xE3`` for APP3), in file order."""
        return [payload for m, payload in self.app_segments if m == marker]


def is_jpeg(data: bytes) -> bool:
    return data[:3] == b"\xff\xd8\xff"


def parse_jpeg(data: bytes) -> JpegStructure:
    """Parse the marker segments of ``data``; raise :class:`JpegFormatError` naming the byte offset."""
    if not data.startswith(SOI):
        raise JpegFormatError("does not start with the JPEG SOI marker FF D8")
    n = len(data)
    i = 2
    apps: list[tuple[int, bytes]] = []
    frame: tuple[int, int, int, int] | None = None
    sos = 0
    for _ in range(MAX_SEGMENTS):
        if i >= n:
            raise JpegFormatError(f"truncated: the file ends at byte {n} before the image data starts")
        if data[i] != 0xFF:
            raise JpegFormatError(f"corrupt: expected a marker (FF) at byte {i}, found {data[i]:02X}")
        while i < n and data[i] == 0xFF:  # fill bytes
            i += 1
        if i >= n:
            raise JpegFormatError(f"truncated: the file ends at byte {n} inside a marker")
        marker = data[i]
        i += 1
        if marker in _STANDALONE:
            continue
        if marker == 0xD9:
            raise JpegFormatError(f"corrupt: end-of-image marker at byte {i - 2} before any image data")
        if marker == 0xD8:
            raise JpegFormatError(f"corrupt: second start-of-image marker at byte {i - 2}")
        if i + 2 > n:
            raise JpegFormatError(f"truncated: segment length of marker {marker:02X} cut at byte {n}")
        length = struct.unpack_from(">H", data, i)[0]
        if length < 2:
            raise JpegFormatError(f"corrupt: marker {marker:02X} at byte {i - 2} has length {length}")
        end = i + length
        if end > n:
            raise JpegFormatError(
                f"truncated: marker {marker:02X} at byte {i - 2} needs {length} bytes, the file ends at {n}"
            )
        payload = data[i + 2 : end]
        if 0xE0 <= marker <= 0xEF:
            apps.append((marker, payload))
        elif marker in SOF_MARKERS and frame is None:
            if len(payload) < 6:
                raise JpegFormatError(f"corrupt: frame header at byte {i - 2} is {len(payload)} bytes long")
            precision, height, width, comps = struct.unpack_from(">BHHB", payload, 0)
            frame = (width, height, precision, comps)
        elif marker == 0xDA:
            sos = i - 2
            break
        i = end
    else:
        raise JpegFormatError(f"corrupt: more than {MAX_SEGMENTS} marker segments")
    if frame is None:
        raise JpegFormatError("corrupt: no frame header (SOF marker) before the image data")
    width, height, precision, comps = frame
    has_eoi = data.rfind(EOI, sos) != -1
    return JpegStructure(width, height, precision, comps, apps, sos, has_eoi)
