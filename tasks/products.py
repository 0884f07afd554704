"""Products and quality of an adjusted flight: DSM + orthomosaic, assessment, diagnosis, report.

* :func:`mosaic_step`: a DSM gridded from the adjusted tie points (:func:`aerocal.dsm.dsm_from_points`,
  GeoTIFF) and, when frames with pixels exist (``images/`` of the flight folder), the orthomosaic in the
  flight's CRS from their original radiometry (:func:`aerocal.mosaic.build_mosaic`, tiles on a Dask
  client). A flight in observations mode without frames gets the DSM only.
* :func:`assess_step`: check-point residuals with achieved / predicted accuracy
  (:func:`aerocal.assess.accuracy_ratio`), control residuals, reprojection statistics.
* :func:`diagnose_step`: residual analysis against the catalogue of unmodelled effects
  (:func:`aerocal.diagnose.engine.diagnose`), IO fixed from the certificate.
* :func:`report_step`: the self-contained HTML report and its ``summary.json``
  (:func:`aerocal.report.flight_report.write_flight_report`): overview map, tie points, calibration,
  ground control and check points, residuals, the DSM minus a reference surface (when the flight folder
  holds one, :data:`REFERENCE_DSM`), the diagnosis in words.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from prefect import task

from aerocal.certificate import Certificate
from aerocal.report.flight_report import write_flight_report
from aerocal.report.html import REPORT_NAME, SUMMARY_NAME
from aerocal.report.wording import recorded_eo_text as recorded_eo_text  # re-exported for flows.cli, benchmarks
from storage.runs import get_run
from tasks.resume import FileOutput, JsonOutput, StepContext, StepInputs, StepResult, run_step
from tasks.retries import TASK_RETRIES, TASK_RETRY_DELAYS_S, retry_condition

_RETRY = {
    "retries": TASK_RETRIES,
    "retry_delay_seconds": TASK_RETRY_DELAYS_S,
    "retry_condition_fn": retry_condition,
}


def _thermal(cert: Certificate):
    return None if cert.thermal is None else cert.thermal.model


#: a reference surface for the DSM (e.g. a LiDAR DSM) in the flight folder: a single-band north-up GeoTIFF
#: of heights in metres, in the flight's CRS
REFERENCE_DSM = Path("reference") / "dsm.tif"


def reference_dsm_path(flight: dict) -> Path | None:
    """The flight folder's reference DSM (:data:`REFERENCE_DSM`), or ``None`` when it has none."""
    path = Path(flight["folder"]) / REFERENCE_DSM
    return path if path.is_file() else None


def frame_paths(flight: dict, images) -> dict[int, Path]:
    """Image id -> frame file for the frames that exist: the ``path`` column, else ``images/<name>`` of
    the flight folder (rendered frames beside an observations-mode flight)."""
    folder = Path(flight["folder"])
    out = {}
    for iid, name, path in zip(
        images.column("image_id").to_pylist(),
        images.column("name").to_pylist(),
        images.column("path").to_pylist(),
        strict=True,
    ):
        for cand in (Path(path) if path else None, folder / "images" / name if name else None):
            if cand is not None and cand.is_file():
                out[int(iid)] = cand
                break
    return out


# ------------------------------------------------------------------------------------------- mosaic
@dataclass(frozen=True)
class MosaicStepConfig:
    """DSM and orthomosaic settings (:class:`aerocal.dsm.DsmConfig`, :class:`aerocal.mosaic.MosaicConfig`;
    ``None`` = their defaults); ``dask_workers`` of the local cluster for the mosaic tiles (2; 0 = serial);
    mosaics of at most ``serial_max_frames`` frames (4) run here without a cluster, since starting the
    worker processes (a few seconds) costs more than the tiles."""

    dsm: Any = None
    mosaic: Any = None
    dask_workers: int = 2
    serial_max_frames: int = 4


def mosaic_step(
    ctx: StepContext,
    ingest: StepResult,
    adjusted: StepResult,
    certificate: str,
    config: MosaicStepConfig | None = None,
    dask_address: str | None = None,
) -> StepResult:
    """Outputs: ``dsm`` (GeoTIFF, float32 metres), ``orthomosaic`` (GeoTIFF/COG, when frames exist) and
    ``mosaic`` (grid, GSD, coverage, frames used)."""
    config = config or MosaicStepConfig()
    inputs = {
        "images": ingest["images"],
        "flight": ingest["flight"],
        "poses": adjusted["poses"],
        "points": adjusted["points"],
        "certificate": certificate,
    }
    # the frames' pixels are inputs too: their SHA-256 enter the cache key (a frame added to images/ or
    # re-rendered re-runs the mosaic)

    def frames_key(inp_flight: dict, images) -> dict[str, str]:
        import hashlib

        return {
            str(i): hashlib.sha256(p.read_bytes()).hexdigest()
            for i, p in sorted(frame_paths(inp_flight, images).items())
        }

    def compute(inp: StepInputs) -> dict:
        from aerocal.dsm import DsmConfig, dsm_from_points, write_dsm
        from aerocal.mosaic import MosaicConfig, build_mosaic, frames_from_poses

        flight, images, poses = inp.json("flight"), inp.table("images"), inp.table("poses")
        points = inp.table("points")
        cert = Certificate.from_dict(inp.json("certificate"))
        cam = cert.camera
        ground = float(np.median(points.column("Z").to_numpy()))
        height = float(np.median(poses.column("Z").to_numpy())) - ground
        gsd = height / cam.f  # GSD = H p / c with the focal length c/p in pixels
        work = Path(tempfile.mkdtemp(prefix="aerocal-mosaic-"))
        dsm = dsm_from_points(points, flight["crs"], gsd_m=gsd, config=config.dsm or DsmConfig())
        out: dict[str, Any] = {"dsm": FileOutput(write_dsm(dsm, work / "dsm.tif"), "dsm", temporary=True)}
        info: dict[str, Any] = {
            "gsd_m": gsd,
            "ground_height_m": ground,
            "dsm_cell_m": dsm.cell_m,
            "dsm_shape": list(dsm.heights.shape),
            "frames": 0,
        }
        paths = frame_paths(flight, images)
        if paths:
            temps = dict(
                zip(
                    images.column("image_id").to_pylist(),
                    images.column("temperature_c").to_pylist(),
                    strict=True,
                )
            )
            thermal = _thermal(cert)
            sel = poses.filter(np.isin(poses.column("image_id").to_numpy(), list(paths)))
            frames = frames_from_poses(
                sel,
                cam,
                {int(k): float(v) for k, v in temps.items() if v is not None}
                if thermal is not None
                else None,
                thermal,
            )
            mcfg = config.mosaic or MosaicConfig()
            path = work / "orthomosaic.tif"
            if dask_address:
                from distributed import Client

                with Client(dask_address) as client:
                    res = build_mosaic(frames, paths, dsm, path, mcfg, client)
            elif config.dask_workers > 0 and len(frames) > config.serial_max_frames:
                from aerocal.matching import local_client

                with local_client(n_workers=config.dask_workers) as client:
                    res = build_mosaic(frames, paths, dsm, path, mcfg, client)
            else:
                res = build_mosaic(frames, paths, dsm, path, mcfg, None)
            out["orthomosaic"] = FileOutput(res.path, "orthomosaic", temporary=True)
            info.update({k: v for k, v in res.to_dict().items() if k != "path"})
            if res.dtype == "uint16":
                out.update(_temperature_output(paths.values(), res.path, work, info))
            info["frames"] = len(frames)
        out["mosaic"] = JsonOutput(info, "mosaic")
        return out

    with ctx.database.session() as session:
        images_tab = ctx.store.read_table(ctx.store.get(session, ingest["images"]), "images")
        flight = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["flight"])))
    return run_step(
        ctx, "mosaic", inputs, {"config": config, "frames": frames_key(flight, images_tab)}, compute
    )


def _temperature_output(paths, counts_path: Path, work: Path, info: dict[str, Any]) -> dict[str, Any]:
    """``temperature`` (float32 degC GeoTIFF on the orthomosaic's grid) when every frame is a FLIR
    radiometric JPEG with one temperature scale; ``info["temperature"]`` says what was done and why."""
    from aerocal.ingest.flir import common_camera_info, raw_to_celsius
    from aerocal.mosaic import write_temperature_raster

    flir, why = common_camera_info(list(paths))
    if flir is None:
        info["temperature"] = f"no temperature raster: {why}"
        return {}
    path = write_temperature_raster(counts_path, work / "temperature.tif", lambda raw: raw_to_celsius(raw, flir))
    info["temperature"] = (
        f"temperature.tif: object temperature (degC) from the counts mosaic, emissivity {flir.emissivity:g}, "
        f"object distance {flir.object_distance_m:g} m, as the camera recorded them ({why})"
    )
    return {"temperature": FileOutput(path, "temperature", temporary=True)}


# ------------------------------------------------------------------------------------------- assess
def assess_step(ctx: StepContext, ingest: StepResult, observations: str, adjusted: StepResult) -> StepResult:
    """Output ``assessment``: achieved vs predicted accuracy at check points (rho per axis and verdict),
    control-point residuals, reprojection statistics (pixels) overall, per image, per strip and binned."""
    inputs = {
        "images": ingest["images"],
        "observations": observations,
        "adjustment": adjusted["adjustment"],
        "residuals": adjusted["residuals"],
    }

    def compute(inp: StepInputs) -> dict:
        from aerocal.assess import accuracy_ratio, reprojection_stats

        adj, res = inp.json("adjustment"), inp.array("residuals")
        obs, images = inp.table("observations"), inp.table("images")
        out: dict[str, Any] = {}
        e = np.asarray(adj["check_errors_m"], dtype=float).reshape(-1, 3)
        s = np.asarray(adj["check_sigma_m"], dtype=float).reshape(-1, 3) if adj["check_sigma_m"] else None
        ids = list(adj.get("check_ids") or [])
        measured = (np.isfinite(e).all(axis=1) & (s > 0).all(axis=1)) if s is not None else np.zeros(len(e), bool)
        unmeasured = [ids[i] if i < len(ids) else str(i) for i in np.flatnonzero(~measured)]
        if measured.sum() >= 2:
            out["check_points"] = accuracy_ratio(e[measured], s[measured]).to_dict()
        else:
            out["check_points"] = {"n": int(measured.sum()),
                                   "verdict": "fewer than 2 check points: accuracy not assessed"}
        if unmeasured:  # e.g. seen in one image only: no intersection, no prediction
            out["check_points"]["not_measured"] = unmeasured
        c = np.asarray(adj["control_errors_m"], dtype=float).reshape(-1, 3)
        out["control_points"] = {
            "n": len(c),
            "rmse_m": np.sqrt(np.mean(c**2, axis=0)).tolist() if len(c) else None,
        }
        ok = np.isfinite(res).all(axis=1)
        stats = reprojection_stats(obs.filter(ok), res[ok], images)
        out["reprojection"] = stats.to_dict()
        out["sigma0"] = adj["sigma0"]
        return {"assessment": JsonOutput(out, "assessment")}

    return run_step(ctx, "assess", inputs, None, compute)


# ----------------------------------------------------------------------------------------- diagnose
def diagnose_step(
    ctx: StepContext,
    ingest: StepResult,
    observations: str,
    certificate: str,
    config: Any = None,
    adjust_config: Any = None,
    adjusted: StepResult | None = None,
) -> StepResult:
    """Output ``diagnosis``: the hypotheses tested, the effects named with magnitude and evidence, the
    gain on check points, and a one-line verdict (``summary``). IO fixed from the certificate.

    With the block adjustment's result (``adjusted``), the observations its blunder screening rejected
    (weight 0 in its ``obs_weight``) are left out and the diagnosis adjusts by least squares at once,
    instead of screening the same block again (a robust pass and a least-squares re-adjustment of the
    whole block: on the 818-image city flight the block adjustment that does this took 180 s).
    """
    from aerocal.adjust import AdjustConfig
    from aerocal.diagnose.engine import DiagnoseConfig

    inputs = {
        "images": ingest["images"],
        "observations": observations,
        "gcps": ingest["gcps"],
        "gcp_observations": ingest["gcp_observations"],
        "certificate": certificate,
    }
    if adjusted is not None and "obs_weight" in adjusted.outputs:
        inputs["obs_weight"] = adjusted["obs_weight"]
        inputs["residuals"] = adjusted["residuals"]
        inputs["adjustment"] = adjusted["adjustment"]
        inputs["poses"] = adjusted["poses"]
        inputs["points"] = adjusted["points"]
    acfg = adjust_config or AdjustConfig()
    cfg = config

    def compute(inp: StepInputs) -> dict:
        import dataclasses

        import pyarrow as pa

        from aerocal.adjust import scale_tie_sigma, screened_rows
        from aerocal.diagnose.engine import diagnose
        from aerocal.diagnose.io_uncertainty import IOUncertainty

        cert = Certificate.from_dict(inp.json("certificate"))
        t0 = getattr(_thermal(cert), "t0", None)
        dcfg = cfg or DiagnoseConfig(reference_temperature=t0)
        obs = inp.table("observations")
        run_cfg = dataclasses.replace(acfg, free=(), thermal=(), adaptive=False)
        screening = None
        if inp.has("obs_weight"):
            weight = inp.array("obs_weight")
            if len(weight) != obs.num_rows:
                raise ValueError(f"diagnose: the block adjustment's obs_weight has {len(weight)} rows, the "
                                 f"observations {obs.num_rows}; re-run the adjust step")
            # its estimate of the tie observations' sigma (1 for an adjustment that made none)
            tie_scale = float(inp.json("adjustment").get("tie_sigma_scale", 1.0)) if inp.has("adjustment") else 1.0
            keep = screened_rows(obs, inp.array("residuals"), weight, tie_scale, acfg.reject_chi2)
            screening = (f"the block adjustment's screening: {obs.num_rows - len(keep)} of {obs.num_rows} "
                         "observations left out (blunders, observations it could not place, and observations "
                         "left alone in their tracks)")
            obs = scale_tie_sigma(obs.take(pa.array(keep, pa.int64())), tie_scale)
            screening += f"; tie-point sigma x {tie_scale:.3f} as estimated by the block adjustment"
            run_cfg = dataclasses.replace(run_cfg, robust_loss="none")
        result = diagnose(
            inp.table("images"),
            obs,
            cert.camera,
            run_cfg,
            inp.table("gcps"),
            inp.table("gcp_observations"),
            dcfg,
            IOUncertainty.from_certificate(cert),
            (inp.table("poses"), inp.table("points")) if inp.has("poses") else None,
        )
        doc = result.to_dict()
        doc["summary"] = result.summary()
        doc["screening"] = screening
        return {"diagnosis": JsonOutput(doc, "diagnosis")}

    return run_step(ctx, "diagnose", inputs, {"diagnose": cfg or DiagnoseConfig(), "adjust": acfg}, compute)


# ------------------------------------------------------------------------------------------- report
@dataclass(frozen=True)
class ReportStepConfig:
    """``title`` of the report (default "Flight report: <flight name>"); ``extra`` key figures added to
    the summary; DSM cells within ``measured_within_m`` (2 m) of a tie point count as measured in the
    DSM-minus-reference statistics (:func:`aerocal.report.flight_figures.dem_difference_for_flight`). Passed to
    :func:`aerocal.report.flight_report.write_flight_report`."""

    title: str | None = None
    extra: dict = field(default_factory=dict)
    measured_within_m: float = 2.0


def report_step(
    ctx: StepContext,
    ingest: StepResult,
    certificate: str,
    adjusted: StepResult,
    mosaic: StepResult,
    assessment: StepResult,
    diagnosis: StepResult,
    config: ReportStepConfig | None = None,
    step_seconds: dict[str, float] | None = None,
) -> StepResult:
    """Outputs ``report`` (self-contained HTML) and ``report_summary`` (its numbers as JSON), written by
    :func:`aerocal.report.flight_report.write_flight_report`.

    Inputs beyond the step outputs: the flight folder's reference DSM (:data:`REFERENCE_DSM`), when it
    exists, is stored as an artifact (kind ``reference-dsm``) and keys the step by its content; without
    one the report says that the DSM was not compared. ``step_seconds`` (step name -> wall time, s; default
    the timings the run recorded for its steps so far) are shown in the report; they do not key the step.
    """
    config = config or ReportStepConfig()
    inputs = {
        "flight": ingest["flight"],
        "images": ingest["images"],
        "certificate": certificate,
        "adjustment": adjusted["adjustment"],
        "poses": adjusted["poses"],
        "points": adjusted["points"],
        "dsm": mosaic["dsm"],
        "mosaic": mosaic["mosaic"],
        "assessment": assessment["assessment"],
        "diagnosis": diagnosis["diagnosis"],
        "gcps": ingest["gcps"],
    }
    if "control_screening" in ingest.outputs:
        inputs["control_screening"] = ingest["control_screening"]
    if "orthomosaic" in mosaic.outputs:
        inputs["orthomosaic"] = mosaic["orthomosaic"]
    with ctx.database.session() as session:
        flight_doc = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["flight"])))
        reference = reference_dsm_path(flight_doc)
        if reference is not None:
            inputs["reference_dsm"] = ctx.store.put_file(session, reference, "reference-dsm").sha256
            session.commit()
        if step_seconds is None:  # the run's steps so far, as recorded (storage.runs.record_timing)
            step_seconds = dict(get_run(session, ctx.run_id).timings or {})

    def compute(inp: StepInputs) -> dict:
        work = Path(tempfile.mkdtemp(prefix="aerocal-report-"))
        write_flight_report(
            work, inp.json("flight"), inp.table("images"), Certificate.from_dict(inp.json("certificate")),
            inp.json("adjustment"), inp.table("poses"), inp.table("points"), inp.path("dsm"), inp.json("mosaic"),
            inp.json("assessment"), inp.json("diagnosis"), inp.table("gcps"),
            inp.json("control_screening") if inp.has("control_screening") else None,
            inp.path("reference_dsm") if inp.has("reference_dsm") else None,
            inp.path("orthomosaic") if inp.has("orthomosaic") else None,
            config.title, config.extra, config.measured_within_m, step_seconds, REFERENCE_DSM.as_posix(),
        )
        return {
            "report": FileOutput(work / REPORT_NAME, "report", temporary=True),
            "report_summary": FileOutput(work / SUMMARY_NAME, "report-summary", temporary=True),
        }

    return run_step(ctx, "report", inputs, config, compute)


def export_file(ctx: StepContext, sha: str, target: Path) -> Path:
    """Copy a stored artifact (verified) to ``target`` (atomically)."""
    from aerocal.io import atomic_path

    with ctx.database.session() as session:
        src = ctx.store.verify(ctx.store.get(session, sha))
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp:
        shutil.copyfile(src, tmp)
    return target


mosaic_task = task(mosaic_step, name="dsm-mosaic", **_RETRY)
assess_task = task(assess_step, name="assess", **_RETRY)
diagnose_task = task(diagnose_step, name="diagnose", **_RETRY)
report_task = task(report_step, name="report", **_RETRY)
