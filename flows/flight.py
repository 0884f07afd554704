"""The flight flows: :func:`process_flight` (one flow run per flight) and :func:`calibrate_camera`.

``process_flight`` composes the steps of :mod:`tasks`::

    manifest -> ingest -> enhance + match (image mode) -> orient
        -> certificate: selected from the store, or (none qualifies / ``certificate="none"``)
           calibration sub-block + self-calibration -> certificate issued to the store
        -> full-block adjustment with fixed IO (+ thermal correction) -> DSM + orthomosaic
        -> assess -> diagnose -> report

Every step is content-addressed (:mod:`tasks.resume`): re-running a flight after a crash reuses the
completed steps and computes from the first missing one. The run (storage ``runs`` row, id = the Prefect
flow-run id) records the full configuration, the certificate and why, timings of every step and its
inputs and outputs with lineage; the run folder gets the report, the products and ``provenance.json``.
"""

from __future__ import annotations

import dataclasses
import json
import uuid
from pathlib import Path
from typing import Any

from prefect import flow

from aerocal.certificate import CameraIdentity
from flows.config import CERTIFICATE_MODES, ProcessConfig, with_flight_sigmas
from flows.environment import resolve_storage
from storage.flights import register_flight
from storage.provenance import provenance
from storage.runs import finish_run, get_run, start_run
from tasks.block import adjust_task
from tasks.calibration import calibrate_task, issue_task, select_task
from tasks.control import control_task
from tasks.flight import ingest_task, manifest_task, match_task, observations_mode, orient_task
from tasks.products import assess_task, diagnose_task, export_file, mosaic_task, report_task
from tasks.resume import StepContext, StepResult, configuration_json, skip_step

#: files written into the run folder: output name of a step -> file name
EXPORTS = {
    "report": "report.html",
    "report_summary": "summary.json",
    "dsm": "dsm.tif",
    "orthomosaic": "orthomosaic.tif",
    "temperature": "temperature.tif",
    "certificate": "certificate.json",
    "calibration_certificate": "calibration_certificate.json",
    "calibration": "calibration.json",
    "diagnosis": "diagnosis.json",
    "assessment": "assessment.json",
    "adjustment": "adjustment.json",
    "ground_control": "ground_control.json",
}


class FlowInputError(ValueError):
    """A flow argument is wrong; the message names it and the fix."""


def current_run_id() -> str:
    """The Prefect flow-run id, or a new uuid4 hex when running outside Prefect."""
    try:
        from prefect.runtime import flow_run

        rid = flow_run.id
    except Exception:  # outside a flow run prefect.runtime may raise anything
        rid = None
    return str(rid) if rid else uuid.uuid4().hex


def _step_info(res: StepResult) -> dict[str, Any]:
    if "skipped" in res.extra:
        return {"status": "skipped", "reason": res.extra["skipped"]}
    return {
        "status": "reused" if res.reused else "computed",
        "computed_by": res.computed_by,
        "seconds": round(res.seconds, 3),
        "key": res.key,
        "outputs": res.outputs,
        **({"extra": res.extra} if res.extra else {}),
    }


def _record_configuration(ctx, config, certificate, flight_dir, out_dir, dask_address, cal_cfg, blk_cfg) -> None:
    """Record the run's configuration, with the adjustment settings in effect, on its ``runs`` row."""
    with ctx.database.session() as session:
        run = get_run(session, ctx.run_id)
        run.configuration = {
            "process": config.to_json(),
            "certificate": certificate,
            "flight_dir": str(flight_dir),
            "out_dir": str(out_dir),
            "dask": dask_address,
            "effective": {
                "calibration_adjust": configuration_json(cal_cfg),
                "block_adjust": configuration_json(blk_cfg),
            },
        }
        session.commit()


def _process(
    ctx: StepContext,
    flight_dir: Path,
    out_dir: Path,
    certificate: str,
    config: ProcessConfig,
    dask_address: str | None,
    calibrate_only: bool = False,
) -> dict[str, Any]:
    steps: dict[str, dict] = {}
    manifest = manifest_task(ctx, flight_dir)
    ing = ingest_task(ctx, flight_dir, manifest, config.ingest)
    steps["ingest"] = _step_info(ing)
    with ctx.database.session() as session:
        flight = json.loads(ctx.store.read_bytes(ctx.store.get(session, ing["flight"])))
        cam_doc = json.loads(ctx.store.read_bytes(ctx.store.get(session, ing["camera"])))
        ident = cam_doc.get("identity", {})
        identity = CameraIdentity(
            **{k: str(ident.get(k) or "unknown") for k in ("make", "model", "serial", "lens")}
        )
        fl = register_flight(
            session,
            flight["name"],
            flight["date"],
            identity.key,
            crs=flight.get("crs"),
            n_images=flight["n_images"],
            bbox=flight.get("bbox"),
            temperature_range=flight.get("temperature_range"),
        )
        run = get_run(session, ctx.run_id)
        run.flight = fl
        cal_cfg = config.calibration.adjust
        blk_cfg = config.block.adjust
        if config.use_flight_sigmas:
            cal_cfg, blk_cfg = with_flight_sigmas(cal_cfg, flight), with_flight_sigmas(blk_cfg, flight)
        if not observations_mode(flight_dir) and config.matched_robust_loss != "none":
            cal_cfg = dataclasses.replace(cal_cfg, robust_loss=config.matched_robust_loss)
            blk_cfg = dataclasses.replace(blk_cfg, robust_loss=config.matched_robust_loss)
        if not observations_mode(flight_dir) and config.matched_tie_thinning is not None:
            blk_cfg = dataclasses.replace(blk_cfg, tie_thinning=config.matched_tie_thinning)
        session.commit()
    _record_configuration(ctx, config, certificate, flight_dir, out_dir, dask_address, cal_cfg, blk_cfg)

    matched = None
    if observations_mode(flight_dir):
        observations = ing["observations"]
        steps["enhance"] = steps["match"] = _step_info(skip_step(ctx, "match", "observations mode"))
    else:
        matched = match_task(ctx, ing, config.match, dask_address)
        steps["match"] = _step_info(matched)
        observations = matched["observations"]
    ori = orient_task(ctx, ing, observations, config.orient, matched)
    steps["orient"] = _step_info(ori)
    if ori.extra.get("method") == "incremental":
        # oriented by SfM: later steps read the registered images with the oriented poses, which are
        # starting values, not GNSS/IMU measurements; the datum comes from the control GCPs
        ing = dataclasses.replace(ing, outputs={**ing.outputs, "images": ori["images"]})
        cal_cfg = dataclasses.replace(cal_cfg, gnss_sigma_m=None, attitude_sigma_deg=None)
        blk_cfg = dataclasses.replace(blk_cfg, gnss_sigma_m=None, attitude_sigma_deg=None)
        _record_configuration(ctx, config, certificate, flight_dir, out_dir, dask_address, cal_cfg, blk_cfg)

    ctl = control_task(ctx, ing, observations, ori, blk_cfg, config.control)
    steps["control"] = _step_info(ctl)
    # every later step sees the screened ground control: a demoted point is neither control nor check
    ing = dataclasses.replace(ing, outputs={**ing.outputs, "gcps": ctl["gcps"],
                                            "gcp_observations": ctl["gcp_observations"],
                                            "control_screening": ctl["screening"]})

    chosen: tuple[str | None, str | None, str] = (None, None, "self-calibration asked for")
    if certificate == "auto" and not calibrate_only:
        chosen = select_task(ctx, ing, None, config.max_certificate_age_days)
    elif certificate not in CERTIFICATE_MODES:
        chosen = select_task(ctx, ing, certificate, config.max_certificate_age_days)
    calibration = None
    if chosen[0] is None:
        why_not = chosen[2]
        cal = calibrate_task(ctx, ing, observations, config.calibration, cal_cfg)
        steps["calibrate"] = _step_info(cal)
        calibration = cal
        chosen = issue_task(ctx, cal, ing)
        if certificate == "auto":
            chosen = (chosen[0], chosen[1], f"{chosen[2]} ({why_not})")
    cert_id, cert_sha, reason = chosen
    summary: dict[str, Any] = {
        "run_id": ctx.run_id,
        "flight": flight["name"],
        "mode": flight["mode"],
        "images_skipped_at_ingest": flight.get("skipped_images") or [],
        "ingest_problems": flight.get("problems") or [],
        "flight_facts": flight.get("facts") or {},
        "certificate_id": cert_id,
        "certificate_reason": reason,
        "ground_control": {"datum": ctl.extra.get("datum"), "demoted": ctl.extra.get("demoted", []),
                           "lines": ctl.extra.get("lines", [])},
        "steps": steps,
        "out_dir": str(out_dir),
    }
    outputs: dict[str, str] = {"certificate": cert_sha, "ground_control": ctl["screening"]}
    if calibration is not None:
        outputs["calibration"] = calibration["calibration"]
        outputs["calibration_certificate"] = calibration["certificate"]
    if not calibrate_only:
        adj = adjust_task(ctx, ing, observations, cert_sha, config.block, blk_cfg)
        steps["adjust"] = _step_info(adj)
        mos = mosaic_task(ctx, ing, adj, cert_sha, config.mosaic, dask_address)
        steps["mosaic"] = _step_info(mos)
        ass = assess_task(ctx, ing, observations, adj)
        steps["assess"] = _step_info(ass)
        dia = diagnose_task(ctx, ing, observations, cert_sha, config.diagnose, blk_cfg, adj)
        steps["diagnose"] = _step_info(dia)
        rep = report_task(ctx, ing, cert_sha, adj, mos, ass, dia, config.report)
        steps["report"] = _step_info(rep)
        for res in (adj, mos, ass, dia, rep):
            outputs.update(res.outputs)
    files = {}
    for name, fname in EXPORTS.items():
        if name in outputs:
            files[name] = str(export_file(ctx, outputs[name], out_dir / fname))
    summary["outputs"] = outputs
    summary["files"] = files
    if "diagnosis" in outputs:
        with ctx.database.session() as session:
            diag = json.loads(ctx.store.read_bytes(ctx.store.get(session, outputs["diagnosis"])))
            assess = json.loads(ctx.store.read_bytes(ctx.store.get(session, outputs["assessment"])))
            adjustment = json.loads(ctx.store.read_bytes(ctx.store.get(session, outputs["adjustment"])))
        summary["diagnosis"] = diag.get("summary")
        summary["recorded_eo"] = diag.get("recorded_eo")
        summary["recorded_eo_corrections"] = (adjustment.get("recorded_eo_corrections") or {}).get("notes")
        summary["twin"] = (diag.get("twin") or {}).get("summary")
        summary["accuracy"] = assess.get("check_points")
        summary["adjustment_converged"] = bool(adjustment.get("converged", True))
        summary["adjustment_iterations"] = adjustment.get("iterations")
    return summary


def _run_flow(
    kind: str,
    flight_dir: str | Path,
    out_dir: str | Path | None,
    certificate: str,
    config: ProcessConfig | None,
    database_url: str | None,
    artifact_root: str | None,
    dask_address: str | None,
    campaign: str | None,
    calibrate_only: bool,
) -> dict[str, Any]:
    from aerocal.io import write_json_atomic

    flight_dir = Path(flight_dir).resolve()
    if not flight_dir.is_dir():
        raise FlowInputError(f"{flight_dir} is not a folder; give a flight folder (images/ or observations/)")
    if not certificate:
        raise FlowInputError("certificate is empty; give auto, none or a certificate id")
    config = config or ProcessConfig()
    out = Path(out_dir).resolve() if out_dir else flight_dir.with_name(flight_dir.name + "-processed")
    where = resolve_storage(database_url, artifact_root)  # a bad URL fails here, before any folder is made
    ctx = StepContext(where.database_url, where.artifact_root, current_run_id())
    with ctx.database.session() as session:
        start_run(
            session,
            ctx.run_id,
            kind,
            configuration={
                "process": config.to_json(),
                "certificate": certificate,
                "flight_dir": str(flight_dir),
                "out_dir": str(out),
            },
            campaign=campaign,
        )
        session.commit()
    out.mkdir(parents=True, exist_ok=True)
    try:
        summary = _process(ctx, flight_dir, out, certificate, config, dask_address, calibrate_only)
    except BaseException as exc:
        interrupted = isinstance(exc, KeyboardInterrupt)
        status = "cancelled" if interrupted else "failed"
        with ctx.database.session() as session:
            finish_run(session, ctx.run_id, status, error=f"{type(exc).__name__}: {exc}")
            session.commit()
        _record_failure(out, ctx.run_id, status, exc)
        raise
    with ctx.database.session() as session:
        finish_run(session, ctx.run_id, "completed")
        session.commit()
        prov = provenance(session, ctx.run_id).to_dict()
    summary["storage"] = where.describe()
    summary["files"]["provenance"] = str(write_json_atomic(out / "provenance.json", prov))
    summary["files"]["run"] = str(write_json_atomic(out / "run.json", summary))
    return summary


#: the file a failed or interrupted run leaves in its run folder, beside ``run.json``
FAILURE_LOG = "aerocal-error.log"


def _record_failure(out: Path, run_id: str, status: str, exc: BaseException) -> None:
    """``run.json`` saying the run failed (or was interrupted), why and how to resume, and the full traceback
    in :data:`FAILURE_LOG`: the console shows one line, the run folder keeps the rest."""
    import traceback

    from aerocal.io import write_json_atomic

    try:
        log = out / FAILURE_LOG
        log.write_text("".join(traceback.format_exception(type(exc), exc, exc.__traceback__)))
        write_json_atomic(out / "run.json", {
            "run_id": run_id,
            "status": status,
            "error": f"{type(exc).__name__}: {exc}",
            "log": str(log),
            "resume": "the completed steps are kept in the store: run the same command again to resume after "
                      "the last of them",
        })
    except OSError:  # the run folder itself is the problem: the database row still records the failure
        pass


@flow(name="process-flight", validate_parameters=False)
def process_flight(
    flight_dir: str | Path,
    out_dir: str | Path | None = None,
    certificate: str = "auto",
    config: ProcessConfig | None = None,
    database_url: str | None = None,
    artifact_root: str | None = None,
    dask_address: str | None = None,
    campaign: str | None = None,
) -> dict[str, Any]:
    """Process one flight end to end; returns the run's summary (run id, certificate and reason, steps
    computed or reused, output SHA-256s, files written, diagnosis, accuracy verdict).

    ``certificate``: ``"auto"`` (the stored certificate that applies, else self-calibrate and store one),
    ``"none"`` (always self-calibrate) or a certificate id (pinned). ``out_dir`` defaults to
    ``<flight_dir>-processed``. See :mod:`flows.environment` for the defaults of the other arguments.
    """
    return _run_flow(
        "process_flight",
        flight_dir,
        out_dir,
        certificate,
        config,
        database_url,
        artifact_root,
        dask_address,
        campaign,
        calibrate_only=False,
    )


@flow(name="calibrate-camera", validate_parameters=False)
def calibrate_camera(
    flight_dir: str | Path,
    out_dir: str | Path | None = None,
    config: ProcessConfig | None = None,
    database_url: str | None = None,
    artifact_root: str | None = None,
    dask_address: str | None = None,
) -> dict[str, Any]:
    """Calibrate the camera of a (calibration) flight: ingest, match, orient, sub-block, self-calibration;
    the certificate is issued to the store and written to ``out_dir/certificate.json``."""
    return _run_flow(
        "calibrate_camera",
        flight_dir,
        out_dir,
        "none",
        config,
        database_url,
        artifact_root,
        dask_address,
        None,
        calibrate_only=True,
    )
