"""Camera identity (make, model, serial, lens) and the nominal camera of a flight folder's ``camera.json``.

``camera_id`` in the ``images`` table is ``"make|model|serial|lens"`` with empty parts where unknown, and
``|`` removed from the parts themselves. ``camera.json`` (written by the simulator, or by hand)::

    {"identity": {"make": ..., "model": ..., "serial": ..., "lens": ...},
     "camera": {fields of aerocal.camera.Camera: width, height, f, cx, cy, k1, ...}}
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from aerocal.camera import Camera
from aerocal.certificate import validate_camera
from aerocal.ingest.problems import ProblemLog

UNKNOWN_CAMERA_ID = "unknown|unknown||"
#: serial part of the identity of a camera whose images record no serial number: ``"no-serial WxH"``
#: (make, model, lens and frame size identify it; several bodies may share its certificates)
NO_SERIAL = "no-serial"
MAX_JSON_BYTES = 4 * 1024 * 1024


@dataclass(frozen=True)
class CameraIdentity:
    make: str = ""
    model: str = ""
    serial: str = ""
    lens: str = ""

    @property
    def camera_id(self) -> str:
        parts = [p.replace("|", "/").strip() for p in (self.make, self.model, self.serial, self.lens)]
        return "|".join(parts)

    @property
    def is_known(self) -> bool:
        return bool(self.make or self.model)


def is_shared_identity(serial: str | None) -> bool:
    """True for the serial part of a camera that records none (:data:`NO_SERIAL`)."""
    return bool(serial) and str(serial).startswith(NO_SERIAL)


def identity_of(make: str | None, model: str | None, serial: str | None, lens: str | None) -> CameraIdentity:
    return CameraIdentity(make or "", model or "", serial or "", lens or "")


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
        values = {k: ident.get(k) for k in ("make", "model", "serial", "lens")}
        bad = [k for k, v in values.items() if v is not None and not isinstance(v, str | int)]
        if bad:
            problems.warning(path, f"identity field(s) {bad} are not text; ignored", "identity")
        identity = CameraIdentity(
            *(
                str(values[k]) if isinstance(values[k], str | int) else ""
                for k in ("make", "model", "serial", "lens")
            )
        )
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
