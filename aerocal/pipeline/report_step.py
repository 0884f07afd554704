"""The report step: the self-contained HTML report and its ``summary.json``
(:func:`aerocal.report.flight_report.write_flight_report`): overview map, tie points, calibration, ground
control and check points, residuals, the DSM minus a reference surface (when the flight folder holds one,
:data:`aerocal.pipeline.dataset.REFERENCE_DSM`), the diagnosis in words, the step times."""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from pathlib import Path

from aerocal.certificates.document import Certificate
from aerocal.pipeline.config import ReportStepConfig
from aerocal.pipeline.dataset import REFERENCE_DSM
from aerocal.pipeline.mosaic_step import reference_dsm_path
from aerocal.pipeline.runner import FileOutput, Runner, StepInputs, StepResult
from aerocal.report.figures import figures_drawn
from aerocal.report.flight_report import write_flight_report
from aerocal.report.html import REPORT_NAME, SUMMARY_NAME


def report_step(runner: Runner, ingest: StepResult, certificate: str, adjusted: StepResult, mosaic: StepResult,
                assessment: StepResult, diagnosis: StepResult, config: ReportStepConfig | None = None,
                step_seconds: Mapping[str, float] | None = None, extension: str | None = None,
                certificate_terms: str | None = None) -> StepResult:
    """Outputs ``report`` (self-contained HTML) and ``report_summary`` (its numbers as JSON).

    Inputs beyond the step outputs: the flight folder's reference DSM, when it exists, is kept by the runner
    (kind ``reference-dsm``) and keys the step by its content; without one the report says that the DSM was
    not compared. ``step_seconds`` (step name -> wall time, s) are shown in the report; they do not key the
    step. ``extension``: the record of the block's extension by its diagnosis
    (:func:`aerocal.pipeline.extend_step.extension_record`), shown as the block before and after.
    ``certificate_terms``: a JSON document whose ``lines`` say whether each camera term of the stored certificate
    the block used holds on this flight (:func:`aerocal.pipeline.certificates.certificate_term_remainders`).
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
    if extension is not None:
        inputs["extension"] = extension
    if certificate_terms is not None:
        inputs["certificate_terms"] = certificate_terms
    for name, result in (("control_screening", ingest), ("orthomosaic", mosaic)):
        if name in result.outputs:
            inputs[name] = result[name]
    reference = reference_dsm_path(runner.inputs({"flight": ingest["flight"]}).json("flight"))
    if reference is not None:
        inputs["reference_dsm"] = runner.put(FileOutput(reference, "reference-dsm"))
    seconds = dict(step_seconds or {})

    def compute(inp: StepInputs) -> dict:
        work = Path(tempfile.mkdtemp(prefix="aerocal-report-"))
        with figures_drawn(config.figures):
            write_flight_report(
                work, inp.json("flight"), inp.table("images"), Certificate.from_dict(inp.json("certificate")),
                inp.json("adjustment"), inp.table("poses"), inp.table("points"), inp.path("dsm"), inp.json("mosaic"),
                inp.json("assessment"), inp.json("diagnosis"), inp.table("gcps"),
                inp.json("control_screening") if inp.has("control_screening") else None,
                inp.path("reference_dsm") if inp.has("reference_dsm") else None,
                inp.path("orthomosaic") if inp.has("orthomosaic") else None,
                config.title, config.extra, config.measured_within_m, seconds or None, REFERENCE_DSM.as_posix(),
                inp.json("extension") if inp.has("extension") else None,
                tuple(inp.json("certificate_terms")["lines"]) if inp.has("certificate_terms") else (),
            )
        return {
            "report": FileOutput(work / REPORT_NAME, "report", temporary=True),
            "report_summary": FileOutput(work / SUMMARY_NAME, "report-summary", temporary=True),
        }

    return runner.run("report", inputs, config, compute)
