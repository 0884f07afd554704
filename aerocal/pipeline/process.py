"""A whole flight, from its inputs to the report: :func:`process`.

::

    manifest -> ingest -> enhance + match (image mode) -> orient -> control screening
        -> certificate: chosen from the store, or (none applies / ``certificate="none"``)
           calibration sub-block + self-calibration -> certificate issued to the store
        -> full-block adjustment with fixed IO (+ thermal correction) -> DSM + orthomosaic
        -> assess -> diagnose -> report

The same function runs a flight in a notebook (``process("flight/")``: every value in memory, certificates in
a :class:`~aerocal.pipeline.certificates.MemoryCertificates`, no Prefect, no database) and on the platform,
whose runner stores every step content-addressed in the artifact store and runs it as a Prefect task, whose
certificate store is the database, and whose recorder writes the run's record (``flows.process``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, cast

from aerocal.certificates.identity import CameraIdentity
from aerocal.matching.cluster import ExecutionConfig
from aerocal.pipeline.adjust_step import adjust_step
from aerocal.pipeline.assess_step import assess_step
from aerocal.pipeline.calibrate_step import calibrate_step
from aerocal.pipeline.certificates import (
    CertificateStore,
    MemoryCertificates,
    certificate_term_remainders,
    choose_stored,
    extended_certificate,
    identity_of,
    issue_calibration,
    issue_extension,
    nominal_certificate,
    term_agreement,
)
from aerocal.pipeline.config import (
    CERTIFICATE_MODES,
    NOMINAL,
    Adjustments,
    ProcessConfig,
    effective_adjustments,
    without_recorded_eo,
)
from aerocal.pipeline.control_step import control_step
from aerocal.pipeline.dataset import FlightDataset, FlightInputError, dataset_of
from aerocal.pipeline.diagnose_step import diagnose_step
from aerocal.pipeline.extend_step import extend_step, extension_record, model_terms
from aerocal.pipeline.figures import ControlFigures, OrientFigures
from aerocal.pipeline.findings import run_findings
from aerocal.pipeline.ingest_step import ingest_step
from aerocal.pipeline.match_step import match_step
from aerocal.pipeline.mosaic_step import mosaic_step, surface_text
from aerocal.pipeline.orient_step import INCREMENTAL, orient_step
from aerocal.pipeline.progress import step_started
from aerocal.pipeline.report_step import report_step
from aerocal.pipeline.runner import JsonOutput, LocalRunner, Runner, StepResult
from aerocal.pipeline.summary import GroundControlSummary, RunSummary

#: files written into the run folder: output name of a step -> file name
EXPORTS = {
    "report": "report.html",
    "report_summary": "summary.json",
    "dsm": "dsm.tif",
    "sparse_dsm": "sparse_dsm.tif",
    "dtm": "dtm.tif",
    "cloud": "cloud.laz",
    "orthomosaic": "orthomosaic.tif",
    "temperature": "temperature.tif",
    "certificate": "certificate.json",
    "calibration_certificate": "calibration_certificate.json",
    "calibration": "calibration.json",
    "diagnosis": "diagnosis.json",
    "diagnosis_before_extension": "diagnosis_before_extension.json",
    "extension": "extension.json",
    "assessment": "assessment.json",
    "adjustment": "adjustment.json",
    "ground_control": "ground_control.json",
    "poses": "poses.parquet",
    "points": "points.parquet",
}


class RunRecorder(Protocol):
    """What the platform records of a run as it goes (the default records nothing)."""

    def flight_ingested(self, flight: dict[str, Any], camera: CameraIdentity) -> None:
        """The flight's summary and camera, once ingested."""
        ...

    def configuration(self, adjustments: Adjustments) -> None:
        """The adjustment settings in effect (again when they change: a block oriented by SfM)."""
        ...

    def certificate(self, certificate_id: str | None, reason: str) -> None:
        """The certificate the run uses and why (``None``: the nominal camera, which is no stored certificate)."""
        ...


class NoRecord:
    """A :class:`RunRecorder` that records nothing."""

    def flight_ingested(self, flight, camera) -> None:
        pass

    def configuration(self, adjustments) -> None:
        pass

    def certificate(self, certificate_id, reason) -> None:
        pass


@dataclass
class FlightRun:
    """A processed flight: the run's :class:`~aerocal.pipeline.summary.RunSummary` (flight, certificate and why,
    steps, accuracy, diagnosis), every step's result by name, the references of the outputs (name -> reference
    in the runner) and the files written to ``out_dir`` (name -> path)."""

    summary: RunSummary
    steps: dict[str, StepResult]
    outputs: dict[str, str]
    files: dict[str, str] = field(default_factory=dict)
    runner: Runner | None = None

    def json(self, name: str) -> Any:
        """An output document (e.g. ``"diagnosis"``, ``"assessment"``, ``"certificate"``) as plain JSON."""
        return self.runner.inputs({name: self.outputs[name]}).json(name)

    def table(self, name: str):
        """An output table (``"poses"``, ``"points"``)."""
        return self.runner.inputs({name: self.outputs[name]}).table(name)


def process(
    flight: str | Path | FlightDataset,
    config: ProcessConfig | None = None,
    *,
    certificate: str = "auto",
    out_dir: str | Path | None = None,
    runner: Runner | None = None,
    certificates: CertificateStore | None = None,
    recorder: RunRecorder | None = None,
    execution: ExecutionConfig | None = None,
    calibrate_only: bool = False,
) -> FlightRun:
    """Process one flight end to end (see the module docstring).

    Args:
        flight: a flight folder or a :class:`~aerocal.pipeline.dataset.FlightDataset`.
        config: every step's settings (default :class:`ProcessConfig`).
        certificate: ``"auto"`` (the stored certificate that applies, else self-calibrate and issue one),
            ``"none"`` (always self-calibrate), ``"nominal"`` (the nominal camera of the flight's camera.json, as
            a metric camera's laboratory calibration is used: not calibrated, not stored) or a certificate id
            (pinned).
        out_dir: where the products, report and documents are written (:data:`EXPORTS`); ``None``: nowhere
            (read them from the returned :class:`FlightRun`).
        runner: computes the steps (default: a :class:`~aerocal.pipeline.runner.LocalRunner`, in memory).
        certificates: the certificate store (default: an empty
            :class:`~aerocal.pipeline.certificates.MemoryCertificates`; pass one to reuse its certificates
            across flights).
        recorder: what the platform records of the run as it goes (default: nothing).
        execution: where the tile work runs (default :class:`~aerocal.matching.cluster.ExecutionConfig`: a local
            cluster of 2 workers where the work pays for it; give a Dask scheduler address to run on a cluster).
        calibrate_only: stop after the certificate (a calibration flight).

    Raises:
        FlightInputError: the flight's input lacks what processing needs (the message names it and the fix).
        NoCertificateError: a pinned certificate does not apply.
    """
    if not certificate:
        raise FlightInputError("certificate is empty; give auto, none, nominal or a certificate id")
    if certificate == NOMINAL and calibrate_only:
        raise FlightInputError("certificate nominal with calibrate_only: a calibration flight makes a certificate; "
                               "give auto or none")
    dataset = dataset_of(flight)
    config = config or ProcessConfig()
    given = runner or LocalRunner()
    runner = _Announcing(given)
    store = certificates if certificates is not None else MemoryCertificates()
    record = recorder or NoRecord()
    steps: dict[str, StepResult] = {}

    manifest = runner.put(JsonOutput(dataset.manifest(), "flight-manifest"))
    ing = steps["ingest"] = ingest_step(runner, dataset, manifest, config.ingest)
    docs = runner.inputs({"flight": ing["flight"], "camera": ing["camera"]})
    flight_doc, cam_doc = docs.json("flight"), docs.json("camera")
    record.flight_ingested(flight_doc, identity_of(cam_doc))
    matched_mode = not dataset.observations_mode
    adjustments = effective_adjustments(config, flight_doc, matched_mode)
    record.configuration(adjustments)

    matched = None
    if matched_mode:
        matched = steps["match"] = match_step(runner, ing, config.match, execution)
        observations = matched["observations"]
    else:
        steps["match"] = runner.skip("match", "observations mode")
        observations = ing["observations"]
    ori = steps["orient"] = orient_step(runner, ing, observations, config.orient, matched)
    if cast(OrientFigures, ori.extra)["method"] == INCREMENTAL:
        # oriented by SfM: later steps read the registered images with the oriented poses, which are starting
        # values, not GNSS/IMU measurements; the datum comes from the control GCPs
        ing = ing.with_outputs(images=ori["images"])
        adjustments = without_recorded_eo(adjustments)
        record.configuration(adjustments)
    ctl = steps["control"] = control_step(runner, ing, observations, ori, adjustments.block, config.control)
    control = cast(ControlFigures, ctl.extra)
    # every later step sees the screened ground control: a demoted point is neither control nor check
    ing = ing.with_outputs(gcps=ctl["gcps"], gcp_observations=ctl["gcp_observations"],
                           control_screening=ctl["screening"])

    document, reason = None, "self-calibration asked for"
    if certificate == "auto" and not calibrate_only:
        document, reason = choose_stored(store, cam_doc, flight_doc, None, config.max_certificate_age_days)
    elif certificate == NOMINAL:
        document = nominal_certificate(cam_doc, runner.run_id, "asked for (certificate nominal)")
        reason = "the nominal camera of the flight's camera.json, as asked (certificate nominal): not calibrated"
    elif certificate not in CERTIFICATE_MODES:
        document, reason = choose_stored(store, cam_doc, flight_doc, certificate, config.max_certificate_age_days)
    outputs: dict[str, str] = {"ground_control": ctl["screening"]}
    if document is None:
        why_not = reason
        cal = steps["calibrate"] = calibrate_step(runner, ing, observations, config.calibration,
                                                  adjustments.calibration)
        outputs["calibration"], outputs["calibration_certificate"] = cal["calibration"], cal["certificate"]
        made_docs = runner.inputs({"certificate": cal["certificate"], "calibration": cal["calibration"]})
        made = made_docs.json("certificate")
        cert_id, document, reason = issue_calibration(
            store, made, cam_doc, runner.run_id, cal.computed_by,
            usable_here=bool(made_docs.json("calibration").get("usable_on_its_flight")))
        if certificate == "auto":
            reason = f"{reason} ({why_not})"
    else:
        cert_id = document["id"]
    record.certificate(None if certificate == NOMINAL else cert_id, reason)
    cert_ref = outputs["certificate"] = runner.put(JsonOutput(document, "certificate"))

    extension: dict[str, Any] | None = None
    remainders: list[str] = []
    if not calibrate_only:
        calibrated_here = "calibrate" in steps
        adj = steps["adjust"] = adjust_step(runner, ing, observations, cert_ref, config.block, adjustments.block,
                                            execution)
        ass = steps["assess"] = assess_step(runner, ing, observations, adj)
        dia = steps["diagnose"] = diagnose_step(runner, ing, observations, cert_ref, config.diagnose,
                                                adjustments.block, adj, config.block.thermal_correction,
                                                calibrated_on_flight=calibrated_here)
        before = {"adjust": adj, "assess": ass, "diagnose": dia, "certificate_id": cert_id}
        used = document
        # a stored certificate's camera terms, applied to this block: does each hold here (the remainder the
        # diagnosis finds of it, named or not)
        remainders = ([] if calibrated_here else
                      certificate_term_remainders(used, runner.inputs({"d": dia["diagnosis"]}).json("d")))
        if config.extend and model_terms(runner.inputs({"d": dia["diagnosis"]}).json("d")):
            # the loop: what the diagnosis named becomes the block's model, and the camera's in its certificate
            ext = steps["extend"] = extend_step(runner, ing, observations, cert_ref, dia, adj)
            terms = runner.inputs({"t": ext["terms"]}).json("t")
            ext_ing = ing.with_outputs(images=ext["images"], gcp_observations=ext["gcp_observations"])
            agreement: list[str] = []
            if terms["camera_terms"]:
                agreement = term_agreement(store, cam_doc, flight_doc, terms, in_use=used)
                if calibrated_here:  # the camera calibrated again on the measurements without the named terms
                    cal_ing = ext_ing.with_outputs(gcp_observations=ext["calibration_gcp_observations"])
                    recal = steps["recalibrate"] = calibrate_step(runner, cal_ing, ext["calibration_observations"],
                                                                  config.calibration, adjustments.calibration,
                                                                  name="recalibrate")
                    outputs["calibration"] = recal["calibration"]
                    made_docs = runner.inputs({"c": recal["certificate"], "calibration": recal["calibration"]})
                    extended_doc = extended_certificate(made_docs.json("c"), terms, flight_doc)
                    usable_here = bool(made_docs.json("calibration").get("usable_on_its_flight"))
                else:
                    extended_doc = runner.inputs({"c": ext["certificate"]}).json("c")
                    usable_here = False
                cert_id, document, reason = issue_extension(store, extended_doc, cam_doc, runner.run_id, reason,
                                                            terms, usable_here)
                record.certificate(cert_id, reason)
                cert_ref = outputs["certificate"] = runner.put(JsonOutput(document, "certificate"))
            adj = steps["adjust_extended"] = adjust_step(runner, ext_ing, ext["observations"], cert_ref, config.block,
                                                         adjustments.block, execution, geometry=adj,
                                                         name="adjust_extended")
            ass = steps["assess_extended"] = assess_step(runner, ext_ing, ext["observations"], adj,
                                                         name="assess_extended")
            dia = steps["diagnose_extended"] = diagnose_step(runner, ext_ing, ext["observations"], cert_ref,
                                                             config.diagnose, adjustments.block, adj,
                                                             config.block.thermal_correction,
                                                             calibrated_on_flight=calibrated_here,
                                                             name="diagnose_extended")
            extension = extension_record(runner, before, {"adjust": adj, "assess": ass, "diagnose": dia,
                                                          "certificate_id": cert_id}, terms)
            extension["agreement"] = agreement
            outputs["extension"] = runner.put(JsonOutput(extension, "extension"))
            outputs["diagnosis_before_extension"] = before["diagnose"]["diagnosis"]
        mos = steps["mosaic"] = mosaic_step(runner, ing, adj, cert_ref, config.mosaic, execution)
        seconds = {name: res.seconds for name, res in steps.items() if not res.skipped}
        if remainders:
            outputs["certificate_terms"] = runner.put(JsonOutput({"lines": remainders}, "certificate-terms"))
        rep = steps["report"] = report_step(runner, ing, cert_ref, adj, mos, ass, dia, config.report, seconds,
                                            outputs.get("extension"), outputs.get("certificate_terms"))
        for res in (adj, mos, ass, dia, rep):
            outputs.update({k: v for k, v in res.outputs.items() if not k.startswith("block_")})

    results: dict[str, Any] = {}
    if "diagnosis" in outputs:
        docs = runner.inputs({k: outputs[k] for k in ("diagnosis", "assessment", "adjustment", "mosaic")})
        diag, assess, adjustment = docs.json("diagnosis"), docs.json("assessment"), docs.json("adjustment")
        first = runner.inputs({"a": before["adjust"]["adjustment"]}).json("a")
        calibration = (runner.inputs({"c": steps["calibrate"]["certificate"]}).json("c")
                       if "calibrate" in steps else None)
        results = {
            "findings": tuple(run_findings(calibration, first, extension)),
            "model_extension": extension,
            "diagnosis": extension["named"] if extension is not None else diag.get("summary"),
            "diagnosis_after_extension": diag.get("summary") if extension is not None else None,
            "recorded_eo": diag.get("recorded_eo"),
            # what the first adjustment removed from the records (the extended one tests them again, corrected)
            "recorded_eo_corrections": tuple((first.get("recorded_eo_corrections") or {}).get("notes") or ()),
            "twin": (diag.get("twin") or {}).get("summary"),
            "certificate_terms": tuple(remainders),
            "accuracy": assess.get("check_points"),
            "adjustment_converged": bool(adjustment.get("converged", True)),
            "adjustment_iterations": adjustment.get("iterations"),
            "surface": surface_text(docs.json("mosaic")),
        }
    files = {}
    if out_dir is not None:
        files = {name: str(runner.export(outputs[name], Path(out_dir) / fname))
                 for name, fname in EXPORTS.items() if name in outputs}
    summary = RunSummary(
        run_id=runner.run_id,
        flight=flight_doc["name"],
        mode=flight_doc["mode"],
        certificate_id=cert_id,
        certificate_reason=reason,
        steps={name: res.record() for name, res in steps.items()},
        images_skipped_at_ingest=tuple(flight_doc.get("skipped_images") or ()),
        ingest_problems=tuple(flight_doc.get("problems") or ()),
        flight_facts=dict(flight_doc.get("facts") or {}),
        ground_control=GroundControlSummary(control["datum"], tuple(control["demoted"]), tuple(control["lines"])),
        out_dir=None if out_dir is None else str(out_dir),
        outputs=outputs,
        files=files,
        **results,
    )
    return FlightRun(summary, steps, outputs, files, given)


class _Announcing:
    """``runner``, announcing each step to :mod:`aerocal.pipeline.progress` as it starts."""

    def __init__(self, runner: Runner) -> None:
        self._runner = runner
        self.run_id = runner.run_id

    def run(self, step: str, inputs, config: Any, compute) -> StepResult:
        step_started(step)
        return self._runner.run(step, inputs, config, compute)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._runner, name)
