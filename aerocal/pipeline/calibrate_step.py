"""The self-calibration step: the calibration block, what it can determine, the adjustment, the held-out test
of thermal slopes, the review (:func:`aerocal.calibrate.self_calibration.self_calibrate`), and the certificate
document built from it (:func:`aerocal.calibrate.self_calibration.certificate_from_calibration`), not yet issued
to a store."""

from __future__ import annotations

from aerocal.adjust import AdjustConfig
from aerocal.calibrate.self_calibration import CalibrationConfig, certificate_from_calibration, self_calibrate
from aerocal.camera import Camera
from aerocal.pipeline.certificates import identity_of
from aerocal.pipeline.figures import step_figures
from aerocal.pipeline.runner import EXTRA, JsonOutput, Runner, StepInputs, StepResult


def calibrate_step(runner: Runner, ingest: StepResult, observations: str, config: CalibrationConfig | None = None,
                   adjust_config: AdjustConfig | None = None, name: str = "calibrate") -> StepResult:
    """Self-calibrate the flight and build the certificate document.

    Outputs: ``certificate`` (the document; its ``review`` says accepted or rejected), ``calibration``
    (:meth:`aerocal.calibrate.self_calibration.Calibration.summary`: the block and why, predicted sigmas,
    parameters held at nominal, held-out tests, the review, the parameter pairs correlated beyond 0.9).
    ``adjust_config`` overrides ``config.adjust`` (e.g. with the flight's declared GNSS sigmas). ``name``: the
    step's name in the run (a re-calibration of the camera once the diagnosis named a camera term is another step
    of the same run).
    """
    config = config or CalibrationConfig()
    acfg = adjust_config or config.adjust
    inputs = {k: ingest[k] for k in ("images", "gcps", "gcp_observations", "camera", "flight")}
    inputs["observations"] = observations

    def compute(inp: StepInputs) -> dict:
        images, obs = inp.table("images"), inp.table("observations")
        gcps, gobs = inp.table("gcps"), inp.table("gcp_observations")
        cam_doc, flight = inp.json("camera"), inp.json("flight")
        camera = Camera.from_dict(cam_doc["camera"])
        errors = tuple(p for p in flight.get("problems") or [] if str(p).endswith("[error]"))
        cal = self_calibrate(images, obs, camera, gcps, gobs, flight.get("height_agl_m"), config, acfg, errors)
        cert = certificate_from_calibration(cal, identity_of(cam_doc), images, gobs, flight.get("date"),
                                            runner.run_id, dict(inp.refs), gcps=gcps)
        return {
            "certificate": JsonOutput(cert.to_dict(), "certificate"),
            "calibration": JsonOutput(
                {**cal.summary(), "high_correlations": cert.correlation.high_pairs(0.9)}, "calibration"),
            EXTRA: step_figures(name, certificate_id=cert.id, review=str(cal.review.status)),
        }

    return runner.run(name, inputs, {"config": config, "adjust": acfg}, compute)
