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
  (:func:`aerocal.report.html.write_report`): the block with check-point residuals, reprojection
  residuals over the image, the IO each image was adjusted with against its sensor temperature, the DSM
  minus a reference surface (when the flight folder holds one, :data:`REFERENCE_DSM`) and the certificate.
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


def _skipped_text(names: list[str]) -> str:
    """``"none"`` or ``"3: a.jpg, b.jpg, c.jpg (see the ingest errors)"``."""
    from aerocal.ingest.problems import name_list

    return f"{len(names)}: {name_list(names)} (see the ingest errors)" if names else "none"


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
    DSM-minus-reference statistics (:func:`aerocal.report.flight_figures.dem_difference_for_flight`)."""

    title: str | None = None
    extra: dict = field(default_factory=dict)
    measured_within_m: float = 2.0


def _check_point_block(poses, adj: dict, gcps):
    """The block figure: camera centres and the check-point residuals of the adjustment."""
    from aerocal.report.figures import block_figure

    centres = np.column_stack([poses.column("X").to_numpy(), poses.column("Y").to_numpy()])
    ids = adj.get("check_ids") or []
    if not ids:
        return block_figure(centres)
    where = {
        g: (x, y)
        for g, x, y in zip(
            gcps.column("gcp_id").to_pylist(),
            gcps.column("X").to_pylist(),
            gcps.column("Y").to_pylist(),
            strict=True,
        )
    }
    en = np.array([where[i] for i in ids], dtype=float)
    errs = np.asarray(adj["check_errors_m"], dtype=float).reshape(-1, 3)
    return block_figure(centres, points_en=en, residuals=errs, ids=ids)


def _screening_text(screening: dict) -> str:
    """One line of what the ground-control screening found (:mod:`aerocal.adjust.control`)."""
    if screening.get("datum") == "none":
        return "; ".join(screening.get("notes") or []) or "none"
    verdicts = screening.get("verdicts") or []
    kept = sum(v["status"] == "kept" for v in verdicts)
    untested = sum(v["status"] == "not tested" for v in verdicts)
    head = f"{kept} point(s) consistent with the block, {len(screening.get('demoted') or [])} demoted, " \
           f"{untested} not testable"
    return "; ".join([head] + list(screening.get("lines") or []))


def report_step(
    ctx: StepContext,
    ingest: StepResult,
    certificate: str,
    adjusted: StepResult,
    mosaic: StepResult,
    assessment: StepResult,
    diagnosis: StepResult,
    config: ReportStepConfig | None = None,
) -> StepResult:
    """Outputs ``report`` (self-contained HTML) and ``report_summary`` (its numbers as JSON).

    Inputs beyond the step outputs: the flight folder's reference DSM (:data:`REFERENCE_DSM`), when it
    exists, is stored as an artifact (kind ``reference-dsm``) and keys the step by its content; without
    one the report says that the DSM was not compared.
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
    with ctx.database.session() as session:
        flight_doc = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["flight"])))
        reference = reference_dsm_path(flight_doc)
        if reference is not None:
            inputs["reference_dsm"] = ctx.store.put_file(session, reference, "reference-dsm").sha256
            session.commit()

    def compute(inp: StepInputs) -> dict:
        from aerocal.dsm import read_dsm
        from aerocal.report.flight_figures import (
            FigureSkipped,
            dem_difference_for_flight,
            image_residuals_from_assessment,
            temperature_io_for_flight,
        )
        from aerocal.report.html import CertificateTable, write_report

        flight, adj, assess = inp.json("flight"), inp.json("adjustment"), inp.json("assessment")
        diag, mos = inp.json("diagnosis"), inp.json("mosaic")
        cert = Certificate.from_dict(inp.json("certificate"))
        images = inp.table("images")
        cp = assess.get("check_points", {})
        review = cert.review.notes[0] if cert.review is not None and cert.review.notes and not cert.estimated \
            else (cert.review.summary() if cert.review is not None else "not reviewed (made elsewhere)")
        summary = {
            "flight": flight["name"],
            "mode": flight["mode"],
            "images": flight["n_images"],
            "images_skipped_at_ingest": _skipped_text(flight.get("skipped_images") or []),
            "crs": flight["crs"],
            "date": flight["date"],
            "temperature_c": flight.get("temperature_range"),
            "flight_facts": "; ".join(f"{k}: {v}" for k, v in (flight.get("facts") or {}).items()) or None,
            "temperature_raster": mos.get("temperature"),
            "certificate": f"{cert.id} (version {cert.version})",
            "certificate_review": review,
            "thermal_model": cert.thermal.kind if cert.thermal is not None else None,
            "adjustment": "converged" if adj.get("converged", True) else (
                f"NOT converged in {adj.get('iterations')} iterations: sigma0, residuals and products describe an "
                "unfinished solution"),
            "sigma0": adj["sigma0"],
            "reprojection_rms_px": adj["reprojection_rms_px"],
            "check_rmse_m": adj.get("check_rmse_m"),
            "rho": cp.get("rho"),
            "verdict": cp.get("verdict"),
            "diagnosis": diag.get("summary"),
            "recorded_eo_checks": recorded_eo_text(diag.get("recorded_eo") or {}),
            "recorded_eo_corrections": "; ".join((adj.get("recorded_eo_corrections") or {}).get("notes") or [])
                                       or "none tested",
            "twin": (diag.get("twin") or {}).get("summary", "not made"),
            "gsd_m": mos.get("gsd_m"),
            "mosaic_frames": mos.get("frames"),
            "ground_control": _screening_text(inp.json("control_screening"))
                              if inp.has("control_screening") else "not screened",
        }
        figs = [_check_point_block(inp.table("poses"), adj, inp.table("gcps"))]
        notes: list[str] = []
        temps = dict(
            zip(
                images.column("image_id").to_pylist(),
                images.column("temperature_c").to_pylist(),
                strict=True,
            )
        )

        def dem_difference():
            if not inp.has("reference_dsm"):
                raise FigureSkipped(
                    f"DSM minus reference: not drawn, the flight folder has no reference DSM "
                    f"({REFERENCE_DSM.as_posix()}, a GeoTIFF of surface heights in the flight's CRS)."
                )
            points = inp.table("points")
            tie_en = np.column_stack([points.column("X").to_numpy(), points.column("Y").to_numpy()])
            return dem_difference_for_flight(
                read_dsm(inp.path("dsm")),
                read_dsm(inp.path("reference_dsm")),
                tie_en,
                config.measured_within_m,
                f"the reference DSM ({REFERENCE_DSM.as_posix()})",
            )

        builders = (
            lambda: image_residuals_from_assessment(assess),
            lambda: temperature_io_for_flight(
                cert.camera,
                _thermal(cert),
                temps,
                None if cert.thermal is None else cert.thermal.valid_range,
            ),
            dem_difference,
        )
        for build in builders:
            try:
                figs.append(build())
            except FigureSkipped as why:
                notes.append(str(why))
        dem = next((f.numbers for f in figs if f.name == "dem_difference"), None)
        if dem is not None:
            summary["dsm_minus_reference_m"] = {
                k: dem[k] for k in ("n", "mean_m", "median_m", "nmad_m", "rmse_m")
            }
        summary.update(config.extra)
        table = CertificateTable.from_values(
            f"Certificate {cert.id[:8]} (version {cert.version})",
            {n: getattr(cert.camera, n) for n in cert.estimated} or {"f": cert.camera.f},
            dict(cert.sigmas),
            info={"camera": cert.identity.key, "conditions": cert.conditions.to_dict()},
        )
        work = Path(tempfile.mkdtemp(prefix="aerocal-report-"))
        html = write_report(
            work, summary, figs, table, config.title or f"Flight report: {flight['name']}", notes=notes
        )
        return {
            "report": FileOutput(html, "report", temporary=True),
            "report_summary": FileOutput(work / "summary.json", "report-summary", temporary=True),
        }

    return run_step(ctx, "report", inputs, config, compute)


def recorded_eo_text(checks: dict) -> str:
    """One line per recorded-EO check of a diagnosis (``Diagnosis.recorded_eo``): estimate +- sigma, status."""
    parts = []
    for name, c in checks.items():
        if "estimate" in c:
            est = ", ".join(f"{v:.3g}" for v in c["estimate"])
            sig = ", ".join("?" if v is None else f"{v:.2g}" for v in c["sigma"])
            parts.append(f"{name} {est} +- {sig} {c['units']} ({c['status']})")
        else:
            parts.append(f"{name}: {c['status']}")
    return "; ".join(parts) or "no GNSS/IMU observations: not checked"


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
