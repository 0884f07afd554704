"""The flight flows: :func:`process_flight` (one flow run per flight) and :func:`calibrate_camera`.

Both run :func:`aerocal.pipeline.process` (manifest -> ingest -> enhance + match -> orient -> control ->
certificate (stored or self-calibrated) -> fixed-IO block adjustment -> DSM + orthomosaic -> assess ->
diagnose -> report) with the platform's parts: :class:`tasks.runner.StoreRunner` (every step a Prefect task,
content-addressed in the artifact store: re-running a flight after a crash reuses the completed steps and
computes from the first missing one), :class:`tasks.certificates.DatabaseCertificates` and
:class:`tasks.run_records.RunRecorder`. The run (storage ``runs`` row, id = the Prefect flow-run id) records
the full configuration, the certificate and why, timings of every step and its inputs and outputs with
lineage; the run folder gets the report, the products and ``provenance.json``.
"""

from __future__ import annotations

import dataclasses
import gc
import traceback
import uuid
from pathlib import Path

from prefect import flow
from prefect.runtime import flow_run

from aerocal.io import write_json_atomic
from aerocal.matching.cluster import ExecutionConfig
from aerocal.pipeline import FlightInputError, ProcessConfig, RunSummary, process
from aerocal.pipeline.interrupts import was_interrupted
from flows.environment import resolve_storage
from storage.provenance import provenance
from storage.runs import finish_run, start_run
from storage.steps import StepContext
from tasks.certificates import DatabaseCertificates
from tasks.run_records import RunRecorder
from tasks.runner import StoreRunner


class FlowInputError(FlightInputError):
    """A flow argument is wrong; the message names it and the fix."""


def current_run_id() -> str:
    """The Prefect flow-run id, or a new uuid4 hex when running outside Prefect."""
    try:
        rid = flow_run.id
    except Exception:  # outside a flow run prefect.runtime may raise anything
        rid = None
    return str(rid) if rid else uuid.uuid4().hex


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
) -> RunSummary:
    flight_dir = Path(flight_dir).resolve()
    if not flight_dir.is_dir():
        raise FlowInputError(f"{flight_dir} is not a folder; give a flight folder (images/ or observations/)")
    if not certificate:
        raise FlowInputError("certificate is empty; give auto, none, nominal or a certificate id")
    config = config or ProcessConfig()
    out = Path(out_dir).resolve() if out_dir else flight_dir.with_name(flight_dir.name + "-processed")
    where = resolve_storage(database_url, artifact_root)  # a bad URL fails here, before any folder is made
    ctx = StepContext(where.database_url, where.artifact_root, current_run_id())
    record = {"process": config.to_json(), "certificate": certificate, "flight_dir": str(flight_dir),
              "out_dir": str(out)}
    with ctx.database.session() as session:
        start_run(session, ctx.run_id, kind, configuration=record, campaign=campaign)
        session.commit()
    out.mkdir(parents=True, exist_ok=True)
    try:
        run = process(flight_dir, config, certificate=certificate, out_dir=out, runner=StoreRunner(ctx),
                      certificates=DatabaseCertificates(ctx),
                      recorder=RunRecorder(ctx, {**record, "dask": dask_address}),
                      execution=ExecutionConfig(dask_address), calibrate_only=calibrate_only)
    except BaseException as exc:
        status = "cancelled" if isinstance(exc, KeyboardInterrupt) or was_interrupted() else "failed"
        # the run folder first: it needs no database
        _record_failure(out, ctx.run_id, status, exc)
        # a Ctrl-C landing inside a database transaction leaves its session in the traceback's frames, holding
        # SQLite's write lock: recording the run then waited the 30 s busy timeout and failed, and the run
        # folder was never written (seen once in the full test suite). The frames' locals are let go first.
        traceback.clear_frames(exc.__traceback__)
        gc.collect()
        with ctx.database.session() as session:
            finish_run(session, ctx.run_id, status, error=f"{type(exc).__name__}: {exc}")
            session.commit()
        raise
    with ctx.database.session() as session:
        finish_run(session, ctx.run_id, "completed")
        session.commit()
        prov = provenance(session, ctx.run_id).to_dict()
    summary = dataclasses.replace(run.summary, storage=where.describe())
    summary = summary.with_files(provenance=str(write_json_atomic(out / "provenance.json", prov)),
                                 run=str(out / "run.json"))
    write_json_atomic(out / "run.json", summary.to_json())
    # a failed run's traceback left in a folder this run completed in would sit beside outputs it does not
    # describe; the failed run and its error stay in the database
    (out / FAILURE_LOG).unlink(missing_ok=True)
    return summary


#: the file a failed or interrupted run leaves in its run folder, beside ``run.json``
FAILURE_LOG = "aerocal-error.log"


def _record_failure(out: Path, run_id: str, status: str, exc: BaseException) -> None:
    """``run.json`` saying the run failed (or was interrupted), why and how to resume, and the full traceback
    in :data:`FAILURE_LOG`: the console shows one line, the run folder keeps the rest."""
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
) -> RunSummary:
    """Process one flight end to end; returns the run's :class:`~aerocal.pipeline.RunSummary` (run id, certificate
    and reason, steps computed or reused, output SHA-256s, files written, diagnosis, accuracy verdict).

    ``certificate``: ``"auto"`` (the stored certificate that applies, else self-calibrate and store one),
    ``"none"`` (always self-calibrate), ``"nominal"`` (the flight's nominal camera, not calibrated) or a
    certificate id (pinned). ``out_dir`` defaults to
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
) -> RunSummary:
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
