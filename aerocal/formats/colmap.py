"""COLMAP ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...`` per line, ``#`` comments.

The exporter writes one ``FULL_OPENCV`` camera (``fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6``) through
:func:`aerocal.camera.to_pycolmap`, which owns the mapping: ``fx = f + b1``, ``fy = f``, principal point
unchanged (COLMAP, like aerocal, puts the centre of the first pixel at (0.5, 0.5)), OpenCV-order p1/p2
(aerocal's p2/p1), k4..k6 = 0. The importer reads every model :func:`aerocal.camera.from_pycolmap`
converts (SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV).
"""

from __future__ import annotations

import math
from pathlib import Path

import pycolmap

from aerocal.camera import from_pycolmap, to_pycolmap
from aerocal.certificates.document import Certificate
from aerocal.certificates.identity import CameraIdentity
from aerocal.certificates.schema import MAX_IMAGE_SIDE_PX
from aerocal.formats.imported import imported_certificate
from aerocal.formats.safe_parsing import decode_text, format_error, read_bytes
from aerocal.io import write_text_atomic

#: COLMAP camera models the Brown model can hold.
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def write_colmap_cameras(
    cert: Certificate, path: str | Path, *, camera_id: int = 1, drop_skew: bool = False
) -> Path:
    """Write ``cert``'s camera as a one-line COLMAP ``cameras.txt`` (model FULL_OPENCV), atomically.

    The format cannot hold: sigmas, correlations, significance, the thermal model, conditions,
    provenance, the pixel size (the certificate id and camera key go into a comment line), and ``b2``
    (no COLMAP model has skew: a non-zero ``b2`` raises unless ``drop_skew=True``).
    """
    path = Path(path)
    try:
        cam = to_pycolmap(cert.camera, camera_id=camera_id, drop_skew=drop_skew)
    except ValueError as e:
        raise format_error(path, "b2", str(e), "export to Metashape XML, which holds skew") from None
    params = " ".join(repr(float(p)) for p in cam.params)
    text = (
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "# Number of cameras: 1\n"
        f"# aerocal certificate {cert.id} for camera {cert.identity.key}\n"
        f"{camera_id} FULL_OPENCV {cert.camera.width} {cert.camera.height} {params}\n"
    )
    return write_text_atomic(path, text)


def read_colmap_cameras(
    path: str | Path, identity: CameraIdentity | None = None, camera_id: int | None = None
) -> Certificate:
    """Read a COLMAP ``cameras.txt``; with several cameras, ``camera_id`` chooses one.

    Errors name the file, the line and the field (model, width, height, parameter count).

    Raises:
        FormatError: the file is missing, too large or not UTF-8; a camera line with fewer than 4 fields, a CAMERA_ID,
            WIDTH or HEIGHT that is not a positive whole number, a model the Brown model cannot hold, parameters that
            are not finite numbers or not as many as the model needs, or a repeated CAMERA_ID; no camera line; several
            cameras and no ``camera_id``, or no camera ``camera_id``; the camera's values do not convert or make no
            consistent certificate. The message names the file, the line and the field.
    """
    path = Path(path)
    data = read_bytes(path)
    text = decode_text(path, data)
    cameras: dict[int, tuple[int, object]] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        tokens = line.split()
        where = f"line {lineno}"
        if len(tokens) < 4:
            raise format_error(path, where, f"expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., got {line!r}",
                               "write one camera per line")
        ints = []
        named = zip(("CAMERA_ID", "WIDTH", "HEIGHT"), (tokens[0], tokens[2], tokens[3]), strict=True)
        for name, token in named:
            try:
                value = int(token)
            except ValueError:
                value = 0
            limit = MAX_IMAGE_SIDE_PX if name != "CAMERA_ID" else 2**31 - 1
            if not 0 < value <= limit:
                problem = f"expected a positive integer of at most {limit}, got {token[:40]!r}" + (
                    "..." if len(token) > 40 else "")
                raise format_error(path, f"{where}, field {name}", problem, f"write {name} as a whole number")
            ints.append(value)
        cid, width, height = ints
        model = tokens[1]
        if model not in SUPPORTED_MODELS:
            raise format_error(path, f"{where}, field MODEL",
                               f"camera model {model} cannot be held by the Brown model",
                               f"use one of {', '.join(SUPPORTED_MODELS)}")
        try:
            params = [float(t) for t in tokens[4:]]
            if not all(math.isfinite(v) for v in params):
                raise ValueError
        except ValueError:
            raise format_error(path, f"{where}, field PARAMS", "parameters must be finite numbers",
                               "write the model's parameters as decimal numbers") from None
        cam = pycolmap.Camera(model=model, width=width, height=height, params=params, camera_id=cid)
        if not cam.verify_params():
            names = str(cam.params_info)
            raise format_error(path, f"{where}, field PARAMS", f"{model} needs {len(names.split(','))} "
                               f"parameters ({names}), got {len(params)}", "write all of them")
        if cid in cameras:
            raise format_error(path, f"{where}, field CAMERA_ID", f"camera {cid} is already defined on line "
                               f"{cameras[cid][0]}", "give each camera its own id")
        cameras[cid] = (lineno, cam)
    if not cameras:
        raise format_error(path, None, "no camera line", "write 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'")
    if camera_id is None:
        if len(cameras) > 1:
            raise format_error(path, "field CAMERA_ID", f"{len(cameras)} cameras ({sorted(cameras)})",
                               "pass camera_id= to choose one")
        camera_id = next(iter(cameras))
    if camera_id not in cameras:
        raise format_error(path, "field CAMERA_ID", f"no camera {camera_id}; the file has {sorted(cameras)}",
                           "pass one of those as camera_id")
    lineno, cam = cameras[camera_id]
    try:
        camera = from_pycolmap(cam)
    except ValueError as e:
        raise format_error(path, f"line {lineno}, field PARAMS", str(e), "recalibrate without those terms") \
            from None
    return imported_certificate(camera, source=path, data=data, fmt="colmap", identity=identity)
