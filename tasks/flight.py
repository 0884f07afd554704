"""Steps that turn a flight folder into tables: manifest, ingest, enhance + match, orient.

Two kinds of flight folder are read:

* **observations mode** (``observations/observations.parquet`` exists, as the simulator writes it): the
  image measurements are given; ingest reads the tables and ``camera.json`` / ``flight.json``, and
  enhance + match are skipped (frames in ``images/``, if any, are used for the mosaic only);
* **image mode**: :func:`aerocal.ingest.ingest_folder` reads images, metadata, EO and GCP files, then
  enhance + match (tile-parallel SIFT on a Dask client) produce the ``observations`` table.

Each step is a plain function (``*_step``: usable without Prefect) and a Prefect task wrapping it with
retries of transient failures (:mod:`tasks.retries`).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from prefect import task

from aerocal import tables
from aerocal.camera import Camera
from tasks.resume import JsonOutput, StepContext, StepInputs, StepResult, TableOutput, run_step
from tasks.retries import TASK_RETRIES, TASK_RETRY_DELAYS_S, retry_condition

#: stem of the simulator's truth files and folder, which processing never reads (nor hashes)
TRUTH_STEM = "truth"

OBSERVATION_TABLES = ("images", "observations", "gcps", "gcp_observations")


class FlightInputError(ValueError):
    """A flight folder lacks what processing needs; the message names the file and the fix."""


def observations_mode(flight_dir: str | Path) -> bool:
    """True when the folder holds measured image observations (``observations/observations.parquet``)."""
    return (Path(flight_dir) / "observations" / "observations.parquet").is_file()


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def flight_manifest(flight_dir: str | Path) -> dict[str, Any]:
    """Every file of the flight folder (relative path -> SHA-256 and size), truth and hidden files left out.

    The manifest is the ingest step's input artifact: a changed, added or removed file changes its hash
    and so re-runs ingest and everything after it.
    """
    root = Path(flight_dir)
    if not root.is_dir():
        raise FlightInputError(
            f"{root} is not a folder; give a flight folder (images/ or observations/, "
            "eo.csv, gcp files, camera.json)"
        )
    files = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        hidden = any(part.startswith(".") for part in rel.parts)
        if not p.is_file() or hidden or rel.parts[0].split(".")[0] == TRUTH_STEM:
            continue
        files[rel.as_posix()] = {"sha256": _sha256(p), "size": p.stat().st_size}
    if not files:
        raise FlightInputError(f"{root} holds no files; give a flight folder")
    return {
        "schema": "aerocal.flight-manifest/1",
        "mode": "observations" if observations_mode(root) else "images",
        "files": files,
    }


def register_manifest(ctx: StepContext, flight_dir: str | Path) -> str:
    """Store the flight's manifest as an artifact (kind ``flight-manifest``) and return its SHA-256."""
    manifest = flight_manifest(flight_dir)
    data = json.dumps(manifest, sort_keys=True, indent=1).encode()
    with ctx.database.session() as session:
        art = ctx.store.put_bytes(session, data, "flight-manifest", "json", run_id=ctx.run_id)
        session.commit()
        return art.sha256


# ------------------------------------------------------------------------------------------- ingest
@dataclass(frozen=True)
class IngestStepConfig:
    """Ingest settings: ``gcp_file`` / ``eo_file`` override the folder's own files, ``crs`` the automatic
    UTM zone (image mode only); ``flight_name`` defaults to the folder's name."""

    gcp_file: str | None = None
    eo_file: str | None = None
    crs: str | None = None
    flight_name: str | None = None


def _flight_summary(
    images: pa.Table, meta: dict, crs: str | None, name: str, mode: str, folder: Path
) -> dict[str, Any]:
    times = [t for t in images.column("time").to_pylist() if t is not None]
    start = meta.get("start_time")
    if times:
        day = min(times).date().isoformat()
    elif start:
        day = str(start)[:10]
    else:
        day = dt.date.today().isoformat()
    temps = np.array([t for t in images.column("temperature_c").to_pylist() if t is not None], dtype=float)
    xy = np.column_stack(
        [
            images.column("gnss_x").to_numpy(zero_copy_only=False),
            images.column("gnss_y").to_numpy(zero_copy_only=False),
        ]
    ).astype(float)
    ok = np.isfinite(xy).all(axis=1)
    return {
        "name": name,
        "folder": str(folder),
        "mode": mode,
        "crs": crs,
        "date": day,
        "n_images": images.num_rows,
        "temperature_range": [float(temps.min()), float(temps.max())] if temps.size else None,
        "bbox": [float(v) for v in (*xy[ok].min(axis=0), *xy[ok].max(axis=0))] if ok.any() else None,
        "gnss_sigma_m": meta.get("gnss_sigma_m"),
        "imu_sigma_deg": meta.get("imu_sigma_deg"),
        "tie_sigma_px": meta.get("tie_sigma_px"),
        "height_agl_m": meta.get("height_agl_m"),
        "description": meta.get("description"),
    }


def blocking_report(result) -> str:
    """The message of a flight that cannot be processed: every blocking problem of ingest, one per line."""
    lines = [f"{result.sources.get('images', 'flight')}: cannot be processed ({len(result.blocking)} problem(s); "
             "`aerocal ingest FOLDER` shows the whole report):"]
    lines += [f"  - {p}" for p in result.blocking]
    return "\n".join(lines)


def _camera_document(path: Path) -> dict:
    """An observations-mode ``camera.json``, checked as a certificate's camera is (finite, plausible values)."""
    from aerocal.certificate import validate_camera

    try:
        doc = json.loads(path.read_text())
        validate_camera(Camera.from_dict(doc["camera"]))
    except json.JSONDecodeError as exc:
        raise FlightInputError(f"{path}:{exc.lineno}: not valid JSON ({exc.msg}); fix the file there") from None
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise FlightInputError(f"{path}: 'camera' is not a valid camera ({exc}); fix the file") from None
    return doc


def _with_shared_identity(cam_doc: dict) -> dict:
    """An observations-mode ``camera.json`` whose identity records no serial gets the serial-less identity an
    image-mode flight of that camera gets (``no-serial WxH``, :func:`aerocal.ingest.inferred.certificate_identity`):
    a thermal camera that writes no serial into its files must still be processable, and its certificate
    found again."""
    from aerocal.ingest.camera_identity import identity_of
    from aerocal.ingest.inferred import certificate_identity

    ident = cam_doc.get("identity") or {}
    serial = str(ident.get("serial") or "") if isinstance(ident, dict) else ""
    if not isinstance(ident, dict) or serial.strip().lower() not in ("", "unknown") \
            or not isinstance(cam_doc.get("camera"), dict):
        return cam_doc
    given = identity_of(ident.get("make"), ident.get("model"), "", ident.get("lens"))
    shared = certificate_identity([], given, Camera.from_dict(cam_doc["camera"]))
    if shared is None:
        return cam_doc
    return {**cam_doc, "identity": {k: getattr(shared, k) for k in ("make", "model", "serial", "lens")}}


def ingest_step(
    ctx: StepContext, flight_dir: str | Path, manifest: str, config: IngestStepConfig | None = None
) -> StepResult:
    """Read the flight folder into the images, observations (observations mode), gcps and gcp_observations
    tables, the camera (identity and nominal model: ``camera``) and the flight's summary (``flight``)."""
    config = config or IngestStepConfig()
    folder = Path(flight_dir).resolve()
    name = config.flight_name or folder.name

    def compute(inp: StepInputs) -> dict:
        meta_path, cam_path = folder / "flight.json", folder / "camera.json"
        out: dict[str, Any] = {}
        skipped: list[str] = []
        facts: dict[str, str] | None = None
        if observations_mode(folder):
            meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
            tabs = {}
            for kind in OBSERVATION_TABLES:
                path = folder / "observations" / f"{kind}.parquet"
                if not path.exists():
                    raise FlightInputError(
                        f"{path} is missing; an observations-mode flight needs "
                        f"{', '.join(OBSERVATION_TABLES)}"
                    )
                tabs[kind] = tables.read(path, kind)
            if not cam_path.exists():
                raise FlightInputError(
                    f"{cam_path} is missing; write the camera identity and nominal model there"
                )
            cam_doc = _with_shared_identity(_camera_document(cam_path))
            crs = (tabs["images"].schema.metadata or {}).get(b"aerocal.crs", b"").decode() or meta.get("crs")
            problems: list[str] = []
            mode = "observations"
        else:
            from aerocal.ingest import ingest_folder

            res = ingest_folder(folder, gcp_file=config.gcp_file, eo_file=config.eo_file, crs=config.crs)
            if res.blocking:
                raise FlightInputError(blocking_report(res))
            ident = res.camera_identity
            cam_doc = {
                "identity": {k: getattr(ident, k) for k in ("make", "model", "serial", "lens")},
                "camera": res.camera.to_dict(),
                "source": res.camera_source,
            }
            tabs = {"images": res.images, "gcps": res.gcps, "gcp_observations": res.gcp_observations}
            crs, mode = res.crs, "images"
            problems = [str(p) for p in res.problems]
            # flight.json as ingest checked it, with what the images tell where it is silent
            meta = {**res.plan, "height_agl_m": res.height_agl_m,
                    "gnss_sigma_m": None if res.gnss_sigma_m is None else list(res.gnss_sigma_m)}
            skipped, facts = res.skipped_images, res.flight_facts
        for kind, tab in tabs.items():
            out[kind] = TableOutput(tab, kind)
        out["camera"] = JsonOutput(cam_doc, "camera")
        summary = _flight_summary(tabs["images"], meta, crs, name, mode, folder)
        summary["problems"] = problems
        summary["skipped_images"] = skipped
        if facts is not None:
            summary["facts"] = facts
        out["flight"] = JsonOutput(summary, "flight")
        return out

    return run_step(ctx, "ingest", {"manifest": manifest}, config, compute)


# ---------------------------------------------------------------------------------- enhance + match
@dataclass(frozen=True)
class MatchStepConfig:
    """Enhance and match settings (defaults: :class:`aerocal.enhance.EnhanceConfig`,
    :class:`aerocal.matching.FeatureConfig`, :class:`aerocal.matching.MatchConfig`); ``min_overlap`` of
    candidate footprints (0.1); ``dask_workers`` of the local cluster when no address is given (2);
    flights without a recorded position and attitude for every image are matched exhaustively (all
    pairs) up to ``exhaustive_max_images`` (150, ~11,000 pairs). Flights of at most
    ``serial_max_megapixels`` (10) in all are matched in this process without a local cluster: 16 rendered
    640 x 480 frames (4.9 MP) took 5.8 s serially and 11.3 s on a fresh 2-worker cluster, whose start and
    worker imports cost ~8 s (crossover near 13 MP on this 2-core machine)."""

    enhance: Any = None
    features: Any = None
    match: Any = None
    min_overlap: float = 0.1
    dask_workers: int = 2
    exhaustive_max_images: int = 150
    serial_max_megapixels: float = 10.0


def _enhanced(path: str, params: Any, config: Any) -> np.ndarray:
    """Read a frame with its original radiometry and enhance it to 8 bit (runs on Dask workers)."""
    from aerocal.enhance import enhance
    from aerocal.ingest import read_raw

    return enhance(read_raw(path), params, config)


def _terrain_height(images: pa.Table, gcps: pa.Table, flight: dict) -> float:
    """Ground height (metres, datum of ``gnss_z``) for footprints: the GCPs' mean, else flying height."""
    if gcps.num_rows:
        return float(np.mean(gcps.column("Z").to_numpy()))
    if flight.get("height_agl_m"):
        z = images.column("gnss_z").to_numpy(zero_copy_only=False).astype(float)
        return float(np.nanmean(z)) - float(flight["height_agl_m"])
    raise FlightInputError(
        f"{flight.get('folder')}: no GCPs and no height_agl_m in flight.json; the "
        "terrain height for candidate pairs is unknown, give one of them"
    )


def match_images(
    images: pa.Table,
    camera: Camera,
    gcps: pa.Table,
    flight: dict,
    config: MatchStepConfig | None = None,
    dask_address: str | None = None,
) -> tuple[pa.Table, pa.Table, pa.Table, int]:
    """Enhance and match the frames of an ``images`` table: (keypoints, matches, observations, pairs tried).

    Candidate pairs come from the GNSS/IMU footprints on a plane at the GCPs' mean height, else at the
    mean GNSS height minus ``flight["height_agl_m"]``; without GNSS/IMU for every image, all pairs.
    """
    from aerocal.enhance import EnhanceConfig, grey, stretch_params
    from aerocal.ingest import read_raw
    from aerocal.matching import (
        FeatureConfig,
        MatchConfig,
        build_tracks,
        candidate_pairs_from_footprints,
        exhaustive_pairs,
        extract_features,
        local_client,
        match_pairs,
    )
    from aerocal.orient import has_priors

    config = config or MatchStepConfig()
    paths = images.column("path").to_pylist()
    ecfg = config.enhance or EnhanceConfig()
    params = stretch_params(paths, percent=ecfg.percent, loader=lambda p: grey(read_raw(p)))
    loader = functools.partial(_enhanced, params=params, config=ecfg)
    if has_priors(images):
        pairs = candidate_pairs_from_footprints(
            images, camera, _terrain_height(images, gcps, flight), min_overlap=config.min_overlap
        )
    elif images.num_rows <= config.exhaustive_max_images:
        pairs = exhaustive_pairs(images.column("image_id").to_numpy())
    else:
        raise FlightInputError(
            f"{flight.get('folder')}: {images.num_rows} images without a recorded position and attitude for "
            f"every one; all-pairs matching is limited to exhaustive_max_images = "
            f"{config.exhaustive_max_images}: give an EO file (--eo FILE) or raise the limit"
        )
    mcfg = config.match or MatchConfig()
    megapixels = float(np.sum(images.column("width").to_numpy().astype(float)
                              * images.column("height").to_numpy().astype(float))) / 1e6
    if dask_address:
        from distributed import Client

        client_cm = Client(dask_address)
    elif config.dask_workers <= 0 or megapixels <= config.serial_max_megapixels:
        client_cm = contextlib.nullcontext(None)
    else:
        client_cm = local_client(n_workers=config.dask_workers)
    with client_cm as client:
        kp = extract_features(images, loader, config.features or FeatureConfig(), client)
        matches = match_pairs(pairs, kp, mcfg, client)
    return kp, matches, build_tracks(matches, kp, mcfg), int(len(pairs))


def match_step(
    ctx: StepContext,
    ingest: StepResult,
    config: MatchStepConfig | None = None,
    dask_address: str | None = None,
) -> StepResult:
    """Enhance (dataset-wide stretch, then Wallis for thermal counts) and match the frames: keypoints, matches,
    observations.

    SIFT runs on image tiles on a Dask cluster: a fresh ``LocalCluster`` or the scheduler at
    ``dask_address``. Candidate pairs come from the GNSS/IMU footprints at the GCPs' mean height (or the
    flying height above ground from ``flight.json``).
    """
    config = config or MatchStepConfig()
    inputs = {k: ingest[k] for k in ("images", "camera", "flight", "gcps")}

    def compute(inp: StepInputs) -> dict:
        from aerocal.ingest.pixels import ImageReadError

        try:
            kp, matches, obs, n_pairs = match_images(
                inp.table("images"),
                Camera.from_dict(inp.json("camera")["camera"]),
                inp.table("gcps"),
                inp.json("flight"),
                config,
                dask_address,
            )
        except ImageReadError as exc:
            # its header read at ingest, its pixels not: bad input, named, not a failure of the run
            raise FlightInputError(f"{exc}; the pixels of this image cannot be decoded although its header was "
                                   "read. Fix: replace the file, or move it out of images/ to process the others"
                                   ) from None
        return {
            "keypoints": TableOutput(kp, "keypoints"),
            "matches": TableOutput(matches, "matches"),
            "observations": TableOutput(obs, "observations"),
            "_extra": JsonOutput({"pairs": n_pairs, "observations": obs.num_rows}, "extra"),
        }

    return run_step(ctx, "match", inputs, config, compute)


# ------------------------------------------------------------------------------------------- orient
@dataclass(frozen=True)
class OrientStepConfig:
    """Initial orientation. With a recorded position and attitude for every image the poses are those
    records (:func:`aerocal.orient.orient_from_priors`). Without them, and when the frames were matched,
    incremental SfM on our matches (:func:`aerocal.orient.orient_incremental`, options ``incremental``,
    default :class:`aerocal.orient.IncrementalConfig`) georeferenced on the control GCPs
    (:func:`aerocal.orient.georeference`); images it cannot register are left out of the block and named."""

    incremental: Any = None


def orient_step(
    ctx: StepContext,
    ingest: StepResult,
    observations: str,
    config: OrientStepConfig | None = None,
    matched: StepResult | None = None,
) -> StepResult:
    """Initial poses (``initial_poses``) and the tie-point statistics the adjustment starts from.

    A block oriented by SfM also outputs ``images``: the registered images with the oriented exterior
    orientation in place of the missing records (:func:`aerocal.orient.images_with_poses`), and
    ``extra["method"] == "incremental"``; later steps then adjust it without GNSS/IMU observations.
    """
    config = config or OrientStepConfig()
    inputs = {"images": ingest["images"], "observations": observations, "flight": ingest["flight"]}
    if matched is not None:
        inputs.update(
            keypoints=matched["keypoints"],
            matches=matched["matches"],
            camera=ingest["camera"],
            gcps=ingest["gcps"],
            gcp_observations=ingest["gcp_observations"],
        )

    def compute(inp: StepInputs) -> dict:
        from aerocal.orient import (
            OrientationError,
            georeference,
            has_priors,
            images_with_poses,
            orient_from_priors,
            orient_incremental,
        )

        images, obs = inp.table("images"), inp.table("observations")
        folder = inp.json("flight")["folder"]
        out: dict = {}
        info: dict = {"method": "priors"}
        if has_priors(images) or not inp.has("keypoints"):
            try:
                poses = orient_from_priors(images)
            except OrientationError as exc:
                raise FlightInputError(
                    f"{folder}: {exc}; give an EO file with positions and attitudes (--eo FILE): an "
                    "observations-mode block starts from the recorded exterior orientation"
                ) from None
        else:
            camera = Camera.from_dict(inp.json("camera")["camera"])
            gcps = inp.table("gcps")
            try:
                local, _, _ = orient_incremental(
                    images, inp.table("keypoints"), inp.table("matches"), camera, config.incremental
                )
                poses, sim = georeference(local, camera, gcps, inp.table("gcp_observations"))
            except OrientationError as exc:
                raise FlightInputError(f"{folder}: no GNSS/IMU for every image, and {exc}") from None
            oriented = images_with_poses(images, poses)
            registered = set(oriented.column("image_id").to_pylist())
            missing = [n for i, n in zip(images.column("image_id").to_pylist(), images.column("name").to_pylist(),
                                         strict=True) if i not in registered]
            info = {
                "method": "incremental",
                "registered": oriented.num_rows,
                "not_registered": missing,
                "georeference_scale": float(sim.scale),
            }
            images = oriented
            out["images"] = TableOutput(oriented, "images")
        ids = images.column("image_id").to_numpy().astype(int)
        per_image = np.bincount(obs.column("image_id").to_numpy().astype(int), minlength=ids.max() + 1)
        seen = per_image[ids]
        out["initial_poses"] = TableOutput(poses, "poses")
        out["_extra"] = JsonOutput(
            {
                **info,
                "images": images.num_rows,
                "observations": obs.num_rows,
                "tracks": len(set(obs.column("track_id").to_pylist())),
                "images_without_observations": int(np.sum(seen == 0)),
            },
            "extra",
        )
        return out

    return run_step(ctx, "orient", inputs, config, compute)


# ------------------------------------------------------------------------------------- Prefect tasks
_RETRY = {
    "retries": TASK_RETRIES,
    "retry_delay_seconds": TASK_RETRY_DELAYS_S,
    "retry_condition_fn": retry_condition,
}

ingest_task = task(ingest_step, name="ingest", **_RETRY)
match_task = task(match_step, name="enhance-match", **_RETRY)
orient_task = task(orient_step, name="orient", **_RETRY)
manifest_task = task(register_manifest, name="manifest", **_RETRY)

__all__ = [
    "FlightInputError",
    "IngestStepConfig",
    "MatchStepConfig",
    "OrientStepConfig",
    "flight_manifest",
    "ingest_step",
    "ingest_task",
    "manifest_task",
    "match_step",
    "match_task",
    "observations_mode",
    "orient_step",
    "orient_task",
    "register_manifest",
]
