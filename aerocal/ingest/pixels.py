"""Image pixels with their original radiometry, for enhancement and mosaicking.

:func:`read_raw` returns the sensor's pixel grid as stored (EXIF orientation is *not* applied: the
camera model refers to the stored grid):

* FLIR radiometric JPEG: the raw frame of the FFF records (:mod:`aerocal.ingest.flir`), ``uint16`` (H, W)
  counts (temperatures: :func:`read_temperature_c`);
* DJI R-JPEG: the raw thermal frame from the APP3 (XT S: APP4) segments, ``uint16`` (H, W) counts;
* TIFF: the first page via :mod:`tifffile`, in its own dtype (``uint16`` for 16-bit thermal frames),
  (H, W) or (H, W, C);
* JPEG: decoded by ``cv2.imdecode`` with ``IMREAD_UNCHANGED``, ``uint8`` (H, W) for greyscale or
  (H, W, 3) in **RGB** order (OpenCV decodes BGR; the channels are swapped here).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from aerocal.ingest.dji import raw_thermal_frame
from aerocal.ingest.flir import FlirFormatError, read_flir
from aerocal.ingest.jpeg import JpegFormatError, parse_jpeg
from aerocal.ingest.metadata import sniff_container


class ImageReadError(ValueError):
    """An image's pixels cannot be read; the message names the file and the reason."""


def read_raw(path: str | Path) -> np.ndarray:
    """Pixels of ``path`` with original radiometry, on the stored grid (module docstring).

    Args:
        path: a FLIR radiometric JPEG, a DJI R-JPEG, another JPEG, or a TIFF.

    Returns:
        The stored pixel grid, EXIF orientation not applied: FLIR and DJI thermal frames as ``uint16`` (H, W)
        counts; a TIFF's first page in its own dtype, (H, W) or (H, W, C); any other JPEG as ``uint8`` (H, W)
        grey or (H, W, 3) RGB.

    Raises:
        ImageReadError: the file cannot be read, is neither JPEG nor TIFF, or cannot be decoded (including a
            FLIR JPEG with broken FLIR segments); the message names the file and the reason.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageReadError(f"{path}: cannot be read ({exc.strerror or exc})") from exc
    kind = sniff_container(data)
    if kind == "jpeg":
        try:
            jpeg = parse_jpeg(data)
        except JpegFormatError as exc:
            raise ImageReadError(f"{path}: not a readable JPEG: {exc}") from exc
        try:
            flir = read_flir(jpeg)
        except FlirFormatError as exc:
            raise ImageReadError(f"{path}: FLIR radiometric JPEG with broken FLIR segments: {exc}") from exc
        if flir is not None:
            return flir.raw
        raw = raw_thermal_frame(jpeg)
        if raw is not None:
            return raw
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ImageReadError(f"{path}: OpenCV cannot decode this JPEG")
        if img.ndim == 3 and img.shape[2] >= 3:
            # OpenCV's own conversion, an order of magnitude faster than numpy's reordering copy (benchmarks/
            # RESULTS.md, "Orthomosaic of large visible frames against the decode-and-resample limit")
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB if img.shape[2] == 3 else cv2.COLOR_BGRA2RGB)
        return img
    if kind == "tiff":
        # lazy: tifffile is slow to import, and every `import aerocal.ingest` would pay it
        import tifffile

        try:
            return tifffile.imread(path, key=0)
        except Exception as exc:  # tifffile raises many types (TiffFileError, ValueError, struct.error, ...)
            raise ImageReadError(f"{path}: not a readable TIFF ({type(exc).__name__}: {exc})") from exc
    raise ImageReadError(f"{path}: not a JPEG or TIFF image")


def read_temperature_c(path: str | Path) -> np.ndarray | None:
    """Object temperatures (degC, float32, (H, W)) of a FLIR radiometric JPEG, on the grid of :func:`read_raw`;
    ``None`` for any other image (DJI R-JPEG counts have no documented conversion) or when the file's
    camera information cannot convert them (the reason is in ingest's problems)."""
    path = Path(path)
    try:
        data = path.read_bytes()
        flir = read_flir(parse_jpeg(data)) if sniff_container(data) == "jpeg" else None
        return None if flir is None else flir.celsius().astype(np.float32)
    except (OSError, JpegFormatError, FlirFormatError):
        return None
