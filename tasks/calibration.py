"""Calibration steps: self-calibration -> certificate, storing it, and choosing a stored one.

* :func:`calibrate_step` (cached): :func:`aerocal.calibration.self_calibrate` (the calibration block, what
  it can determine, the adjustment, the held-out test of thermal slopes, the review) and the certificate
  document built from it (:func:`aerocal.calibration.certificate_from_calibration`).
* :func:`issue_step`: store that certificate (once: a re-run that reuses the step finds it by id). A
  certificate whose review rejected it is stored as rejected, and the flight goes on with the nominal camera.
* :func:`select_step`: ask the store for the certificate that applies to the flight
  (:func:`storage.certificates.select_certificate`), then review it against this flight's nominal camera
  before reusing it; never cached, since the answer depends on what the store holds now.

Both record the certificate the run uses and why (:func:`storage.runs.record_certificate`) and store the
certificate document as an artifact (kind ``certificate``), the input of the block adjustment.
"""

from __future__ import annotations

import json

from prefect import task

from aerocal.adjust import AdjustConfig
from aerocal.calibration import CalibrationConfig, certificate_from_calibration, self_calibrate
from aerocal.camera import Camera
from aerocal.certificate import CameraIdentity, Certificate, ParameterSignificance, Provenance
from aerocal.decision import NOMINAL_PARAMETERS, Review, nominal_sigma, review_camera
from storage.certificates import get_certificate, issue_certificate, select_certificate
from storage.errors import NoCertificateError, NotFoundError
from storage.runs import record_certificate
from tasks.resume import JsonOutput, StepContext, StepInputs, StepResult, run_step
from tasks.retries import TASK_RETRIES, TASK_RETRY_DELAYS_S, retry_condition

#: the step's configuration is the engine's (kept under this name for flow configurations)
CalibrationStepConfig = CalibrationConfig


def identity_of(cam_doc: dict) -> CameraIdentity:
    """The camera identity of an ingested ``camera.json`` document ("unknown" for a missing part)."""
    return CameraIdentity(**{k: str(cam_doc.get("identity", {}).get(k) or "unknown")
                             for k in ("make", "model", "serial", "lens")})


def calibrate_step(
    ctx: StepContext,
    ingest: StepResult,
    observations: str,
    config: CalibrationConfig | None = None,
    adjust_config: AdjustConfig | None = None,
) -> StepResult:
    """Self-calibrate the flight and build the certificate document.

    Outputs: ``certificate`` (the document, not yet stored; its ``review`` says accepted or rejected),
    ``calibration`` (:meth:`aerocal.calibration.Calibration.summary`: the block and why, predicted sigmas,
    parameters held at nominal, held-out tests, the review). ``adjust_config`` overrides ``config.adjust``
    (e.g. with the flight's declared GNSS sigmas).
    """
    config = config or CalibrationConfig()
    acfg = adjust_config or config.adjust
    inputs = {
        "images": ingest["images"],
        "observations": observations,
        "gcps": ingest["gcps"],
        "gcp_observations": ingest["gcp_observations"],
        "camera": ingest["camera"],
        "flight": ingest["flight"],
    }

    def compute(inp: StepInputs) -> dict:
        images, obs = inp.table("images"), inp.table("observations")
        gcps, gobs = inp.table("gcps"), inp.table("gcp_observations")
        cam_doc, flight = inp.json("camera"), inp.json("flight")
        camera = Camera.from_dict(cam_doc["camera"])
        errors = tuple(p for p in flight.get("problems") or [] if str(p).endswith("[error]"))
        cal = self_calibrate(images, obs, camera, gcps, gobs, flight.get("height_agl_m"), config, acfg, errors)
        cert = certificate_from_calibration(cal, identity_of(cam_doc), images, gobs, flight.get("date"), ctx.run_id,
                                            dict(inp.shas), gcps=gcps)
        return {
            "certificate": JsonOutput(cert.to_dict(), "certificate"),
            "calibration": JsonOutput(
                {**cal.summary(), "high_correlations": cert.correlation.high_pairs(0.9)}, "calibration"),
            "_extra": JsonOutput({"certificate_id": cert.id, "review": cal.review.status}, "extra"),
        }

    return run_step(ctx, "calibrate", inputs, {"config": config, "adjust": acfg}, compute)


def _store_document(ctx: StepContext, session, document: dict) -> str:
    data = json.dumps(document, sort_keys=True, indent=1).encode()
    return ctx.store.put_bytes(session, data, "certificate", "json", run_id=ctx.run_id).sha256


def _nominal_document(ctx: StepContext, cam_doc: dict, why: str) -> dict:
    """A certificate document of the flight's nominal camera (nothing estimated), for the block adjustment of
    a flight whose own calibration was rejected or not made; kept as an artifact, never issued to the store."""
    camera = Camera.from_dict(cam_doc["camera"])
    source = cam_doc.get("source") or "camera.json"
    # nothing estimated, and nothing exact: the nominal values' own uncertainty goes to the diagnosis
    held = {n: ParameterSignificance(0.0, False, "nominal value, not calibrated", prior_sigma=nominal_sigma(n, camera))
            for n in NOMINAL_PARAMETERS}
    cert = Certificate(identity=identity_of(cam_doc), camera=camera, significance=held,
                       provenance=Provenance(flow_run=ctx.run_id),
                       review=Review(notes=(f"the nominal camera of the flight ({source}): {why}",)))
    return cert.to_dict()


def issue_step(ctx: StepContext, calibration: StepResult, ingest: StepResult) -> tuple[str, str, str]:
    """Store the calibration's certificate (once) and record it as the run's certificate.

    A certificate its review rejected is stored as rejected (never selected for a flight), and the flight
    goes on with the nominal camera; the reason says so. Returns (certificate id, SHA-256 of the document
    the block adjustment uses, reason).
    """
    with ctx.database.session() as session:
        art = ctx.store.get(session, calibration["certificate"])
        document = json.loads(ctx.store.read_bytes(art))
        try:
            stored = get_certificate(session, document["id"])
            reason = f"made by this flight's self-calibration (run {calibration.computed_by}), issued before"
        except NotFoundError:
            stored = issue_certificate(session, document)
            reason = "made by this flight's self-calibration"
        reason += f"; version {stored.version} of camera {stored.camera.make} {stored.camera.model}"
        use = stored.document
        if stored.status != "accepted":
            problems = "; ".join((use.get("review") or {}).get("problems") or [])
            reason += f", stored as REJECTED ({problems}): the block uses the nominal camera instead"
            cam_doc = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["camera"])))
            use = _nominal_document(ctx, cam_doc, f"this flight's calibration {stored.id} was rejected")
        sha = _store_document(ctx, session, use)
        record_certificate(session, ctx.run_id, stored.id, reason)
        session.commit()
        return stored.id, sha, reason


def select_step(
    ctx: StepContext, ingest: StepResult, pin: str | None = None, max_age_days: float | None = None
) -> tuple[str | None, str | None, str]:
    """The stored certificate that applies to the flight (or the one pinned by id), recorded on the run, as
    (id, SHA-256 of its document artifact, reason); ``(None, None, why)`` when none qualifies (unless pinned:
    then the store's error propagates).

    Before it is reused, the certificate is reviewed against this flight's nominal camera
    (:func:`aerocal.decision.review_camera`: image size, f within its band, principal point, distortion,
    thermal slopes); one that fails is not used, and the reason says why.
    """
    with ctx.database.session() as session:
        cam_doc = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["camera"])))
        flight = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["flight"])))
        try:
            cert, reason = select_certificate(
                session,
                identity_of(cam_doc).key,
                flight["date"],
                flight.get("temperature_range"),
                max_age_days=max_age_days,
                pin=pin,
            )
        except NoCertificateError as exc:
            if pin:
                raise
            return None, None, f"no stored certificate applies ({exc})"
        parsed = Certificate.from_dict(cert.document)
        slopes = {}
        if parsed.thermal is not None:
            slopes = {k: getattr(parsed.thermal.model, k, None) for k in ("df_dt", "dcx_dt", "dcy_dt")}
        review = review_camera(parsed.camera, Camera.from_dict(cam_doc["camera"]), dict(parsed.sigmas), slopes)
        if not review.accepted:
            why = f"stored certificate {cert.id} not reused: {'; '.join(review.problems)}"
            if pin:
                raise NoCertificateError(f"pinned {why}")
            return None, None, why
        sha = _store_document(ctx, session, cert.document)
        record_certificate(session, ctx.run_id, cert.id, reason)
        session.commit()
        return cert.id, sha, reason


_RETRY = {
    "retries": TASK_RETRIES,
    "retry_delay_seconds": TASK_RETRY_DELAYS_S,
    "retry_condition_fn": retry_condition,
}

calibrate_task = task(calibrate_step, name="self-calibrate", **_RETRY)
issue_task = task(issue_step, name="issue-certificate", **_RETRY)
select_task = task(select_step, name="select-certificate", **_RETRY)
