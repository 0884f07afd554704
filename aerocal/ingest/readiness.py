"""Can this flight be processed? The checks ``aerocal process`` would otherwise fail on, one step later.

Ingest runs :func:`check_processable` on every image-mode flight and reports what it finds as errors
marked ``stops_processing``, each naming the file, the field and the fix; ``aerocal process`` runs
ingest first and stops with that same report, before any work, when there is one. So a user sees every
blocking problem of a flight at once, from either command.

Also here: :func:`read_flight_json`, the flight plan file (``flight.json``) with every value checked.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pyarrow as pa

from aerocal.camera import Camera
from aerocal.certificates.identity import CameraIdentity
from aerocal.ingest.camera_json import MAX_JSON_BYTES
from aerocal.ingest.crs_strings import CrsTextError, crs_kind, normalise_crs
from aerocal.ingest.problems import ProblemLog
from aerocal.poses import has_priors

#: flight.json fields and their checks: name -> (kind, low, high); lists are checked element-wise
FLIGHT_FIELDS: dict[str, tuple[str, float, float]] = {
    "height_agl_m": ("number", 1.0, 20000.0),
    "gnss_sigma_m": ("list", 1e-4, 1000.0),
    "imu_sigma_deg": ("list", 1e-6, 90.0),
    "tie_sigma_px": ("number", 1e-3, 100.0),
}
_CAMERA_TEMPLATE = (
    '{"identity": {"make": "...", "model": "...", "serial": "...", "lens": "..."}, '
    '"camera": {"width": W, "height": H, "f": F, "cx": W/2, "cy": H/2}} with f in pixels '
    "(focal length in mm / pixel pitch in mm)"
)


def read_flight_json(path: str | Path, problems: ProblemLog) -> dict:
    """The fields of ``flight.json``; an unreadable file, or a value that fails its check, is an error that
    stops processing (a wrong sigma or height must not be replaced by a default without the user knowing)."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_JSON_BYTES:
            problems.error(path, f"larger than {MAX_JSON_BYTES} bytes; ignored")
            return {}
        obj = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        problems.blocker(path, f"cannot be read ({exc.strerror or exc}). Fix: make it readable or remove it")
        return {}
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        problems.blocker(path, f"is not valid JSON ({exc}). Fix: correct it or remove it", None,
                         getattr(exc, "lineno", None))
        return {}
    if not isinstance(obj, dict):
        problems.blocker(path, "must hold a JSON object (height_agl_m, gnss_sigma_m, ...). Fix: correct it or "
                         "remove it")
        return {}
    out = dict(obj)
    for key, (kind, lo, hi) in FLIGHT_FIELDS.items():
        if key not in obj or obj[key] is None:
            continue
        value = obj[key]
        values = value if kind == "list" and isinstance(value, list) else [value]
        ok = (kind != "list" or isinstance(value, list)) and 0 < len(values) <= 3 and all(
            isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and lo <= v <= hi
            for v in values
        )
        if not ok:
            shape = "a list of 1-3 numbers" if kind == "list" else "a number"
            problems.blocker(path, f"{key} = {value!r} must be {shape} in {lo:g}..{hi:g}. Fix: correct it or "
                             "remove the key", key)  # never replaced silently by a default or inferred value
            del out[key]
    if obj.get("crs") is not None:
        try:
            norm = normalise_crs(str(obj["crs"]))
            if crs_kind(norm) != "projected":
                raise CrsTextError(f"{obj['crs']!r} is not a projected CRS in metres")
            out["crs"] = norm
        except CrsTextError as exc:
            problems.blocker(path, f"{exc}. Fix: write a projected CRS in metres (e.g. \"EPSG:32632\") or "
                             "remove the key (the UTM zone of the images is then chosen)", "crs")
            del out["crs"]
    return out


def check_processable(
    problems: ProblemLog,
    where: str,
    images: pa.Table,
    gcps: pa.Table,
    camera: Camera | None,
    camera_source: str,
    identity: CameraIdentity | None,
    height_agl_m: float | None,
    sidecar_dir: Path | None,
    skipped: list[str],
    eo_errors: list | None = None,
) -> None:
    """Add a ``stops_processing`` error for everything image-mode processing cannot go past.

    ``eo_errors``: the errors found in the EO file's rows. Any one stops processing: a row whose cell was
    not applied leaves that image with the metadata's own position (another source, another vertical
    reference) or none, and the block would mix them silently (one bad altitude cell once moved a
    certificate's f by 80 px and every later flight that reused it)."""
    folder = sidecar_dir or Path(where)
    if eo_errors:
        lines = sorted({p.line for p in eo_errors if p.line is not None})
        at = f" (line{'s' if len(lines) > 1 else ''} {', '.join(map(str, lines[:10]))})" if lines else ""
        problems.blocker(
            eo_errors[0].file,
            f"{len(eo_errors)} cell(s) of the EO file could not be applied{at}: those images would keep another "
            "source's position and vertical reference, or none. Fix: correct the cells, or remove the rows to "
            "use the images' own metadata for them on purpose",
            "eo",
        )
    n = images.num_rows
    if n < 2:
        why = f"; {len(skipped)} skipped (see the errors above)" if skipped else ""
        problems.blocker(
            where, f"{n} image(s) could be ingested{why}: a block needs at least 2 overlapping images", "images"
        )
    if camera is None:
        problems.blocker(
            folder / "camera.json",
            f"no nominal camera: {camera_source}. Fix: write {folder / 'camera.json'} as {_CAMERA_TEMPLATE}",
            "camera",
        )
    elif n:
        sizes = {(int(w), int(h)) for w, h in zip(images.column("width").to_pylist(),
                                                   images.column("height").to_pylist(), strict=True)}
        if (camera.width, camera.height) not in sizes:
            problems.blocker(
                folder / "camera.json",
                f"the nominal camera is {camera.width}x{camera.height} but the images' raw frames are "
                f"{', '.join(f'{w}x{h}' for w, h in sorted(sizes))}. Fix: correct width/height in camera.json",
                "camera",
            )
    if identity is None or not identity.is_known:
        problems.blocker(
            folder / "camera.json",
            "no camera make and model in the images or camera.json: a certificate must name its camera. "
            'Fix: add "identity": {"make": ..., "model": ..., "serial": ...} to camera.json',
            "identity",
        )
    if n and gcps.num_rows == 0 and height_agl_m is None and has_priors(images):
        # not a stop: `aerocal process` measures it from the block's tie points
        # (:func:`aerocal.matching.ground.flying_height`) and stops only if that fails
        problems.warning(
            folder / "flight.json",
            "flying height not recorded: no GCPs, no height_agl_m in flight.json and no height above ground in "
            "the images (DJI RelativeAltitude, senseFly Height); `aerocal process` measures it from the block's "
            f'tie points. To give it instead: write {folder / "flight.json"} with {{"height_agl_m": H}} (metres '
            "above ground)",
            "height_agl_m",
        )
