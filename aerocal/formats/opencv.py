"""OpenCV calibration files (``cv2.FileStorage`` YAML; the XML variant is read too).

Fields, as OpenCV's calibration sample writes them::

    image_width: 640
    image_height: 512
    camera_matrix: !!opencv-matrix {rows: 3, cols: 3, dt: d, data: [fx, s, cx, 0, fy, cy, 0, 0, 1]}
    distortion_coefficients: !!opencv-matrix {rows: 1, cols: 5, dt: d, data: [k1, k2, p1, p2, k3]}
    avg_reprojection_error: 0.31          (optional: RMS in pixels)

Conventions converted here:

* OpenCV puts the *centre* of the first pixel at (0, 0); aerocal puts it at (0.5, 0.5). So
  ``cx_opencv = cx - 0.5`` and ``cy_opencv = cy - 0.5``.
* OpenCV's p1/p2 are aerocal's (Metashape's) p2/p1: ``distortion = [k1, k2, p2, p1, k3]`` in aerocal
  names.
* ``fx = f + b1``, ``fy = f``.
* The skew ``s = camera_matrix[0][1]`` enters ``u = fx x + s y + cx`` exactly as aerocal's ``b2`` does, so
  the importer reads it as ``b2``; OpenCV's own functions (projectPoints, undistortPoints,
  calibrateCamera) ignore it, so the exporter refuses a non-zero ``b2`` unless ``drop_skew=True``.

Distortion vectors of 4, 5, 8, 12 or 14 coefficients are read; the rational (k4..k6), thin-prism
(s1..s4) and tilt (tauX, tauY) terms must be zero, as aerocal's Brown model has none.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from aerocal.camera import Camera
from aerocal.certificates.document import Certificate
from aerocal.certificates.identity import CameraIdentity
from aerocal.formats.imported import imported_certificate
from aerocal.formats.safe_parsing import (
    decode_text,
    finite_float,
    format_error,
    load_yaml_mapping,
    parse_xml,
    read_bytes,
)
from aerocal.io import write_text_atomic

#: Accepted field names, canonical first.
CAMERA_MATRIX_KEYS = ("camera_matrix", "cameraMatrix", "K")
DISTORTION_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
WIDTH_KEYS = ("image_width", "width")
HEIGHT_KEYS = ("image_height", "height")
SIZE_KEYS = ("image_size", "imageSize")

#: Names of OpenCV's distortion coefficients beyond the fifth (all must be zero).
_EXTRA_COEFFICIENTS = ("k4", "k5", "k6", "s1", "s2", "s3", "s4", "tauX", "tauY")


def to_opencv(camera: Camera, drop_skew: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(camera_matrix (3, 3), distortion (5,))`` in OpenCV's conventions (see the module docstring).

    A non-zero ``b2`` raises unless ``drop_skew=True`` (then it is left out: not a faithful conversion).
    """
    if camera.b2 != 0.0 and not drop_skew:
        raise ValueError(f"camera has skew b2={camera.b2:g} px, which OpenCV's functions ignore; "
                         "pass drop_skew=True to discard it")
    K = np.array([
        [camera.f + camera.b1, 0.0, camera.cx - 0.5],
        [0.0, camera.f, camera.cy - 0.5],
        [0.0, 0.0, 1.0],
    ])
    dist = np.array([camera.k1, camera.k2, camera.p2, camera.p1, camera.k3])
    return K, dist


def from_opencv(camera_matrix: np.ndarray, distortion: np.ndarray, width: int, height: int,
                pixel_size_mm: float | None = None) -> Camera:
    """Inverse of :func:`to_opencv` (skew ``camera_matrix[0][1]`` becomes ``b2``). Checks shapes only
    loosely; :func:`read_opencv` validates files field by field."""
    K = np.asarray(camera_matrix, dtype=float).reshape(3, 3)
    d = np.zeros(5)
    dist = np.asarray(distortion, dtype=float).ravel()
    d[: min(5, dist.size)] = dist[:5]
    return Camera(
        width=int(width), height=int(height), f=float(K[1, 1]), b1=float(K[0, 0] - K[1, 1]),
        b2=float(K[0, 1]), cx=float(K[0, 2] + 0.5), cy=float(K[1, 2] + 0.5),
        k1=float(d[0]), k2=float(d[1]), p2=float(d[2]), p1=float(d[3]), k3=float(d[4]),
        pixel_size_mm=pixel_size_mm,
    )


# ------------------------------------------------------------------------------------------ export
def write_opencv_yaml(cert: Certificate, path: str | Path, *, drop_skew: bool = False) -> Path:
    """Write ``cert``'s camera as an OpenCV YAML file (with ``cv2.FileStorage``), atomically.

    The format cannot hold: sigmas, correlations, significance, the thermal model, the conditions and
    provenance (the certificate id and camera key go into a comment), the pixel size, and ``b2``
    (OpenCV's functions ignore skew: a non-zero ``b2`` raises unless ``drop_skew=True``). It holds the
    reprojection RMS as ``avg_reprojection_error`` when the certificate knows it.
    """
    path = Path(path)
    try:
        K, dist = to_opencv(cert.camera, drop_skew=drop_skew)
    except ValueError as e:
        raise format_error(path, "b2", str(e), "export to Metashape XML, which holds skew") from None
    flags = cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY | cv2.FILE_STORAGE_FORMAT_YAML
    fs = cv2.FileStorage(".yaml", flags)
    fs.writeComment(f"aerocal certificate {cert.id} for camera {cert.identity.key}")
    fs.writeComment("pixel centres at integer coordinates (OpenCV); distortion [k1, k2, p1, p2, k3] (OpenCV)")
    fs.write("image_width", int(cert.camera.width))
    fs.write("image_height", int(cert.camera.height))
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(1, 5))
    if cert.quality.reprojection_rms_px is not None:
        fs.write("avg_reprojection_error", float(cert.quality.reprojection_rms_px))
    text = fs.releaseAndGetString()
    return write_text_atomic(path, text)


# ------------------------------------------------------------------------------------------ import
def read_opencv(path: str | Path, identity: CameraIdentity | None = None) -> Certificate:
    """Read an OpenCV calibration file (``cv2.FileStorage`` YAML or XML) into a certificate.

    The certificate holds the camera and, when present, ``avg_reprojection_error`` as the reprojection
    RMS; no sigmas. Errors name the file, the line (YAML) and the field.
    """
    path = Path(path)
    data = read_bytes(path)
    text = decode_text(path, data)
    if text.lstrip().startswith("<"):
        fields, lines = _xml_fields(path, data), {}
    else:
        fields, lines = load_yaml_mapping(path, text)
    camera, rms = _camera_from_fields(path, fields, lines)
    return imported_certificate(camera, source=path, data=data, fmt="opencv", identity=identity,
                                reprojection_rms_px=rms)


def _where(lines: dict[str, int], key: str) -> str:
    return f"line {lines[key]}, field {key}" if key in lines else f"field {key}"


def _pick(fields: dict[str, Any], keys: tuple[str, ...]) -> str | None:
    found = [k for k in keys if k in fields]
    return found[0] if found else None


def _camera_from_fields(
    path: Path, fields: dict[str, Any], lines: dict[str, int]
) -> tuple[Camera, float | None]:
    kkey = _pick(fields, CAMERA_MATRIX_KEYS)
    if kkey is None:
        raise format_error(path, f"field {CAMERA_MATRIX_KEYS[0]}", "missing",
                           "add the 3x3 camera_matrix (!!opencv-matrix)")
    K = _matrix(path, fields[kkey], _where(lines, kkey), "3x3")
    if K.shape != (3, 3):
        raise format_error(path, _where(lines, kkey), f"expected a 3x3 matrix, got {K.shape[0]}x{K.shape[1]}",
                           "write rows: 3, cols: 3")
    if K[1, 0] != 0 or not np.allclose(K[2], [0, 0, 1]):
        raise format_error(path, _where(lines, kkey), f"not a camera matrix (rows 2-3 are {K[1].tolist()}, "
                           f"{K[2].tolist()})", "write [fx, s, cx, 0, fy, cy, 0, 0, 1]")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise format_error(path, _where(lines, kkey), f"focal lengths must be positive, got fx={K[0, 0]:g}, "
                           f"fy={K[1, 1]:g}", "write fx and fy in pixels")

    dkey = _pick(fields, DISTORTION_KEYS)
    if dkey is None:
        dist = np.zeros(5)
    else:
        dist = _matrix(path, fields[dkey], _where(lines, dkey), "1xN").ravel()
        if dist.size not in (4, 5, 8, 12, 14):
            raise format_error(path, _where(lines, dkey), f"{dist.size} distortion coefficients",
                               "write 4, 5, 8, 12 or 14 coefficients [k1, k2, p1, p2, k3, ...]")
        for name, value in zip(_EXTRA_COEFFICIENTS, dist[5:], strict=False):
            if value != 0.0:
                raise format_error(path, _where(lines, dkey),
                                   f"coefficient {name} = {value:g} is not zero and the Brown model "
                                   "cannot hold it",
                                   "recalibrate without that term")

    width, height = _size(path, fields, lines)
    rms = None
    if "avg_reprojection_error" in fields:
        rms = fields["avg_reprojection_error"]
        if finite_float(rms) is None or rms < 0:
            raise format_error(path, _where(lines, "avg_reprojection_error"),
                               f"expected a number >= 0, got {rms!r}",
                               "write the RMS reprojection error in pixels, or remove the field")
        rms = float(rms)
    return from_opencv(K, dist, width, height), rms


def _matrix(path: Path, value: Any, where: str, shape: str) -> np.ndarray:
    if isinstance(value, np.ndarray):
        return value
    flat = np.ravel(np.array(value, dtype=object)) if isinstance(value, list) else []
    if len(flat) and all(isinstance(v, int | float) and not isinstance(v, bool) for v in flat):
        a = np.asarray(value, dtype=float)
        return a.reshape(3, 3) if shape == "3x3" and a.size == 9 else a
    raise format_error(path, where, f"expected a {shape} !!opencv-matrix, got {type(value).__name__}",
                       "write it as OpenCV does (rows, cols, dt, data)")


def _size(path: Path, fields: dict[str, Any], lines: dict[str, int]) -> tuple[int, int]:
    wkey, hkey, skey = _pick(fields, WIDTH_KEYS), _pick(fields, HEIGHT_KEYS), _pick(fields, SIZE_KEYS)
    if wkey is not None and hkey is not None:
        pairs = [(wkey, fields[wkey]), (hkey, fields[hkey])]
    elif skey is not None:
        given = fields[skey]
        v = np.ravel(np.asarray(given, dtype=object)) if isinstance(given, list | np.ndarray) else []
        if len(v) != 2:
            raise format_error(path, _where(lines, skey), f"expected [width, height], got {fields[skey]!r}",
                               "write the image size in pixels")
        pairs = [(skey, v[0]), (skey, v[1])]
    else:
        raise format_error(path, "field image_width",
                           "missing (the image size is needed to place the principal point)",
                           "add image_width and image_height in pixels")
    out = []
    for key, v in pairs:
        if isinstance(v, float) and v.is_integer():
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise format_error(path, _where(lines, key), f"expected a positive integer, got {v!r}",
                               "write the image size in pixels")
        out.append(v)
    return out[0], out[1]


def _xml_fields(path: Path, data: bytes) -> dict[str, Any]:
    """Top-level fields of an OpenCV XML FileStorage (``<opencv_storage>``)."""
    root = parse_xml(path, data)
    if root.tag != "opencv_storage":
        raise format_error(path, f"<{root.tag}>", "not an OpenCV XML storage (root must be <opencv_storage>)",
                           "give a cv2.FileStorage file, or import it as Metashape XML (fmt='metashape')")
    fields: dict[str, Any] = {}
    for el in root:
        if el.get("type_id") in ("opencv-matrix", "opencv-nd-matrix"):
            parts = {c.tag: (c.text or "").strip() for c in el}
            try:
                if el.get("type_id") == "opencv-nd-matrix":
                    sizes = [int(t) for t in parts["sizes"].split()]
                    rows, cols = sizes[0], (sizes[1] if len(sizes) == 2 else 1)
                else:
                    rows, cols = int(parts["rows"]), int(parts["cols"])
                values = np.array([float(t) for t in parts["data"].split()])
                fields[el.tag] = values.reshape(rows, cols)
            except (KeyError, ValueError):
                raise format_error(path, f"<{el.tag}>", "malformed opencv-matrix (rows, cols or sizes, data)",
                                   "write the matrix as cv2.FileStorage does") from None
        else:
            text = (el.text or "").strip()
            fields[el.tag] = _scalar(text)
    return fields


def _scalar(text: str) -> Any:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            continue
    parts = text.split()
    if len(parts) > 1:
        try:
            return [float(p) for p in parts]
        except ValueError:
            pass
    return text
