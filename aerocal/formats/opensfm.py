"""OpenSfM / OpenDroneMap ``cameras.json`` (``{camera_key: {...}}``), projection type ``brown``.

OpenSfM's conventions, read from its sources (``opensfm/io.py`` camera_from_json / camera_to_json,
``opensfm/features.py`` normalized_image_coordinates, ``geometry/camera_functions.h`` Affine and
``camera_distortions_functions.h`` DistoBrown):

* Normalised image coordinates: ``n = (pixel_opencv + 0.5 - size_axis / 2) / max(width, height)`` with
  pixel_opencv in OpenCV's convention (centre of the first pixel at 0). In aerocal pixels (centre of
  the first pixel at 0.5): ``n = (u - width / 2) / max(width, height)``.
* ``n_x = focal_x x_d + c_x``, ``n_y = focal_y y_d + c_y`` (``focal_y = focal * aspect_ratio``).
  So ``focal_x = (f + b1) / size``, ``focal_y = f / size``, ``c_x = (cx - width / 2) / size``,
  ``c_y = (cy - height / 2) / size``.
* DistoBrown: ``x_d = x radial + 2 p1 x y + p2 (r^2 + 2 x^2)``: OpenCV's order, so OpenSfM's p1/p2 are
  aerocal's p2/p1.

The importer also reads the ``perspective`` (focal, k1, k2; principal point at the centre), ``radial``
and ``simple_radial`` projection types, and the ``cameras`` of the first reconstruction of a
``reconstruction.json``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aerocal.camera import Camera
from aerocal.certificates.document import Certificate
from aerocal.certificates.identity import CameraIdentity
from aerocal.certificates.schema import MAX_IMAGE_SIDE_PX
from aerocal.formats.imported import imported_certificate
from aerocal.formats.safe_parsing import (
    FormatError,
    decode_text,
    finite_float,
    format_error,
    read_bytes,
    short_repr,
)
from aerocal.io import write_text_atomic

#: Projection types the importer reads and their parameters (beyond width/height).
PROJECTIONS: dict[str, tuple[str, ...]] = {
    "brown": ("focal_x", "focal_y", "c_x", "c_y", "k1", "k2", "k3", "p1", "p2"),
    "radial": ("focal_x", "focal_y", "c_x", "c_y", "k1", "k2"),
    "simple_radial": ("focal_x", "focal_y", "c_x", "c_y", "k1"),
    "perspective": ("focal", "k1", "k2"),
}
_REQUIRED = {"brown": ("focal_x", "focal_y"), "radial": ("focal_x", "focal_y"),
             "simple_radial": ("focal_x", "focal_y"), "perspective": ("focal",)}


def to_opensfm(camera: Camera, drop_skew: bool = False) -> dict[str, Any]:
    """OpenSfM ``brown`` camera parameters (normalised by ``max(width, height)``; see module docstring).

    A non-zero ``b2`` raises unless ``drop_skew=True`` (OpenSfM has no skew).
    """
    if camera.b2 != 0.0 and not drop_skew:
        raise ValueError(f"camera has skew b2={camera.b2:g} px, which OpenSfM cannot represent; "
                         "pass drop_skew=True to discard it")
    w, h = camera.width, camera.height
    size = float(max(w, h))
    return {
        "projection_type": "brown",
        "width": w,
        "height": h,
        "focal_x": (camera.f + camera.b1) / size,
        "focal_y": camera.f / size,
        "c_x": (camera.cx - w / 2.0) / size,
        "c_y": (camera.cy - h / 2.0) / size,
        "k1": camera.k1,
        "k2": camera.k2,
        "p1": camera.p2,
        "p2": camera.p1,
        "k3": camera.k3,
    }


def from_opensfm(obj: Mapping[str, Any], where: str = "camera") -> Camera:
    """Inverse of :func:`to_opensfm` for the projection types of :data:`PROJECTIONS`.

    Raises ``ValueError`` whose message starts with the field path under ``where``.
    """
    if not isinstance(obj, Mapping):
        raise ValueError(f"{where}: expected a JSON object, got {type(obj).__name__}; "
                         "write the camera's fields")
    ptype = obj.get("projection_type", "perspective")
    if ptype not in PROJECTIONS:
        raise ValueError(f"{where}.projection_type: {ptype!r} cannot be held by the Brown model; "
                         f"use one of {', '.join(PROJECTIONS)}")
    known = set(PROJECTIONS[ptype]) | {"projection_type", "width", "height"}
    for k in obj:
        # OpenSfM's older files carry *_prior copies of each parameter: accepted and ignored.
        if k not in known and not (k.endswith("_prior") and k[: -len("_prior")] in known):
            raise ValueError(f"{where}.{k}: not a parameter of the {ptype} projection (which has "
                             f"{', '.join(PROJECTIONS[ptype])}); remove it")
    size_wh = []
    for k in ("width", "height"):
        v = obj.get(k)
        if isinstance(v, float) and v.is_integer():
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 < v <= MAX_IMAGE_SIDE_PX:
            raise ValueError(f"{where}.{k}: expected a positive integer of at most {MAX_IMAGE_SIDE_PX}, got "
                             f"{short_repr(v)}; "
                             f"write the image {k} in pixels")
        size_wh.append(v)
    w, h = size_wh
    vals = {}
    for k in PROJECTIONS[ptype]:
        if k not in obj and k in _REQUIRED[ptype]:
            raise ValueError(f"{where}.{k}: missing; add the normalised focal length")
        v = obj.get(k, 0.0)
        if finite_float(v) is None:
            raise ValueError(f"{where}.{k}: expected a finite number, got {v!r}; write a JSON number")
        vals[k] = float(v)
    size = float(max(w, h))
    if ptype == "perspective":
        vals.update(focal_x=vals["focal"], focal_y=vals["focal"], c_x=0.0, c_y=0.0)
    for k in ("focal_x", "focal_y"):
        if vals[k] <= 0:
            raise ValueError(f"{where}.{k}: expected a positive number, got {vals[k]!r}; "
                             "write focal / max(w, h)")
    f = vals["focal_y"] * size
    return Camera(
        width=w, height=h, f=f, b1=vals["focal_x"] * size - f,
        cx=w / 2.0 + vals["c_x"] * size, cy=h / 2.0 + vals["c_y"] * size,
        k1=vals.get("k1", 0.0), k2=vals.get("k2", 0.0), k3=vals.get("k3", 0.0),
        p1=vals.get("p2", 0.0), p2=vals.get("p1", 0.0),
    )


def default_camera_key(cert: Certificate) -> str:
    """OpenSfM's key layout ``v2 <make> <model> <width> <height> brown <focal>``, lower case.

    OpenDroneMap matches cameras.json entries to images by this key; pass ``key=`` to the exporter to
    match the key OpenSfM derived from the images' EXIF.
    """
    cam = cert.camera
    focal = cam.f / max(cam.width, cam.height)
    make, model = cert.identity.make, cert.identity.model
    return f"v2 {make} {model} {cam.width} {cam.height} brown {focal:.4f}".lower()


def write_opensfm_cameras(
    cert: Certificate, path: str | Path, *, key: str | None = None, drop_skew: bool = False
) -> Path:
    """Write ``cert``'s camera as an OpenSfM/ODM ``cameras.json`` with one ``brown`` camera, atomically.

    The format cannot hold: sigmas, correlations, significance, the thermal model, conditions,
    provenance, the pixel size, and ``b2`` (no skew in OpenSfM: a non-zero ``b2`` raises unless
    ``drop_skew=True``). ``key`` defaults to :func:`default_camera_key`.
    """
    path = Path(path)
    try:
        cam = to_opensfm(cert.camera, drop_skew=drop_skew)
    except ValueError as e:
        raise format_error(path, "b2", str(e), "export to Metashape XML, which holds skew") from None
    doc = {key or default_camera_key(cert): cam}
    return write_text_atomic(path, json.dumps(doc, indent=4, allow_nan=False) + "\n")


def read_opensfm_cameras(
    path: str | Path, identity: CameraIdentity | None = None, key: str | None = None
) -> Certificate:
    """Read an OpenSfM/ODM ``cameras.json`` (or a ``reconstruction.json``); ``key`` chooses among cameras.

    Raises:
        FormatError: the file is missing, too large or not UTF-8; invalid JSON (the message names the line and column)
            or a NaN/Infinity constant; neither a ``{camera_key: camera}`` object nor a ``reconstruction.json`` with
            cameras; several cameras and no ``key``, or no camera ``key``; a camera whose values cannot be read, or make
            no consistent certificate.
    """
    path = Path(path)
    data = read_bytes(path)
    text = decode_text(path, data)
    try:
        doc = json.loads(text, parse_constant=_refuse_constant)
    except json.JSONDecodeError as e:
        raise format_error(path, f"line {e.lineno}, column {e.colno}", f"invalid JSON ({e.msg})",
                           "fix the syntax there") from None
    except ValueError as e:
        raise format_error(path, None, str(e), "write finite numbers") from None
    if isinstance(doc, list):  # reconstruction.json: a list of reconstructions with "cameras"
        if not doc or not isinstance(doc[0], Mapping) or "cameras" not in doc[0]:
            raise format_error(path, "[0].cameras", "a JSON list but not a reconstruction.json with cameras",
                               "give cameras.json or reconstruction.json")
        doc = doc[0]["cameras"]
    if not isinstance(doc, Mapping) or not doc:
        raise format_error(path, None, "expected a JSON object {camera_key: camera}",
                           "give an OpenSfM cameras.json")
    if key is None:
        if len(doc) > 1:
            raise format_error(path, None, f"{len(doc)} cameras ({', '.join(map(repr, doc))})",
                               "pass key= to choose one")
        key = next(iter(doc))
    if key not in doc:
        raise format_error(path, repr(key), f"no such camera; the file has {', '.join(map(repr, doc))}",
                           "pass one of those as key")
    try:
        camera = from_opensfm(doc[key], where=repr(key))
    except ValueError as e:
        raise FormatError(f"{path}: {e}") from None
    return imported_certificate(camera, source=path, data=data, fmt="opensfm", identity=identity)


def _refuse_constant(name: str) -> None:
    raise ValueError(f"JSON constant {name} is not allowed (strict JSON)")
