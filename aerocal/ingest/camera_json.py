"""The camera identity and nominal camera of a flight folder's ``camera.json``.

The identity is :class:`aerocal.certificates.identity.CameraIdentity`; ingest writes its ``camera_id`` form
into the ``images`` table: ``"make|model|serial|lens"`` with empty parts where unknown and ``|`` inside a part
written as ``/``. ``camera.json`` (written by the simulator, or by hand)::

    {"identity": {"make": ..., "model": ..., "serial": ..., "lens": ...},
     "camera": {fields of aerocal.camera.Camera: width, height, f, cx, cy, k1, ...}}
"""

from __future__ import annotations

import json
from pathlib import Path

from aerocal.camera import Camera
from aerocal.certificates.document import validate_camera
from aerocal.certificates.identity import IDENTITY_PARTS, CameraIdentity
from aerocal.ingest.problems import ProblemLog

#: ``images.camera_id`` of an image nothing identifies (kept as earlier flights' tables hold it)
UNKNOWN_CAMERA_ID = "unknown|unknown||"
#: the largest ``camera.json`` or ``flight.json`` ingest reads (bytes; both hold a few hundred): a larger file is
#: not one of them and is reported and ignored unread (also :func:`aerocal.ingest.readiness.read_flight_json`)
MAX_JSON_BYTES = 4 * 1024 * 1024


__all__ = ["MAX_JSON_BYTES", "UNKNOWN_CAMERA_ID", "read_camera_json"]


def read_camera_json(path: str | Path, problems: ProblemLog) -> tuple[CameraIdentity | None, Camera | None]:
    """Identity and nominal :class:`Camera` of a ``camera.json``; problems name the file and the key."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_JSON_BYTES:
            problems.error(path, f"larger than {MAX_JSON_BYTES} bytes; ignored")
            return None, None
        obj = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        problems.error(path, f"cannot be read ({exc.strerror or exc}); ignored")
        return None, None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        line = getattr(exc, "lineno", None)
        problems.error(path, f"is not valid JSON ({exc}); ignored", None, line)
        return None, None
    if not isinstance(obj, dict):
        problems.error(path, "must hold a JSON object with 'identity' and 'camera'; ignored")
        return None, None
    identity = None
    ident = obj.get("identity")
    if isinstance(ident, dict):
        values = {k: ident.get(k) for k in IDENTITY_PARTS}
        bad = [k for k, v in values.items() if v is not None and not isinstance(v, str | int)]
        if bad:
            problems.warning(path, f"identity field(s) {bad} are not text; ignored", "identity")
        identity = CameraIdentity.from_mapping({k: v for k, v in values.items() if k not in bad})
    elif ident is not None:
        problems.warning(path, "'identity' is not an object; ignored", "identity")
    camera = None
    cam = obj.get("camera")
    if isinstance(cam, dict):
        try:
            parsed = Camera.from_dict(cam)
            validate_camera(parsed)
            camera = parsed
        except (TypeError, ValueError, OverflowError) as exc:
            problems.error(path, f"'camera' is not a valid Camera: {exc}; ignored", "camera")
    elif cam is not None:
        problems.warning(path, "'camera' is not an object; ignored", "camera")
    return identity, camera
