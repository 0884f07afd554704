"""The extension step: the effects the diagnosis named become the block's model
(:mod:`aerocal.diagnose.extension`).

The diagnosis names an effect only when it passes the decision rule, a gain on images the fit did not use
included. This step turns those effects into the data of the extended block, taken at the geometry of the block
adjustment the diagnosis examined: the recorded positions and attitudes without the record terms (GNSS offset,
lag, lever arm, boresight), the measurements without refraction, and, for a re-calibration of the camera on this
flight, the measurements without every image-side term (the calibration then estimates the camera without them,
and the terms are added to its certificate); the certificate extended by the camera terms.
"""

from __future__ import annotations

from aerocal.certificates.document import Certificate
from aerocal.diagnose.engine import MISFIT_SIGMA0
from aerocal.diagnose.extension import (
    BLOCK_TERMS,
    ModelTerm,
    apply_block_terms,
    extend_certificate,
    remove_image_terms,
    terms_of_diagnosis,
)
from aerocal.effects import rotation_zero_point, rotation_zero_point_text
from aerocal.pipeline.runner import JsonOutput, Runner, StepInputs, StepResult, TableOutput


def model_terms(diagnosis: dict) -> tuple[ModelTerm, ...]:
    """The terms a diagnosis document adds to the block's model: its named effects, none where its baseline does
    not fit its own weights (its statistics then describe the misfit, not the flight)."""
    if (diagnosis.get("sigma0") or {}).get("before", 0.0) > MISFIT_SIGMA0:
        return ()
    return terms_of_diagnosis(diagnosis)


def extend_step(runner: Runner, ingest: StepResult, observations: str, certificate: str, diagnosed: StepResult,
                adjusted: StepResult) -> StepResult:
    """Outputs: ``terms`` (the model terms: each named effect with its size, sigma and held-out evidence, split
    into camera and block terms), ``images`` (the block adjustment's recorded positions and attitudes without the
    record terms), ``observations`` and ``gcp_observations`` (the measurements without refraction: the extended
    block's measurements, to which the block adjustment applies the certificate's own terms),
    ``calibration_observations`` and ``calibration_gcp_observations`` (without every image-side term: what a
    re-calibration of the camera on this flight fits) and ``certificate`` (the certificate in use extended by the
    camera terms, :func:`aerocal.diagnose.extension.extend_certificate`; not yet issued to a store)."""
    inputs = {"images": adjusted["block_images"], "observations": observations, "gcps": ingest["gcps"],
              "gcp_observations": ingest["gcp_observations"], "certificate": certificate,
              "diagnosis": diagnosed["diagnosis"], "poses": adjusted["poses"], "points": adjusted["points"],
              "flight": ingest["flight"]}

    def compute(inp: StepInputs) -> dict:
        diagnosis, flight = inp.json("diagnosis"), inp.json("flight")
        cert = Certificate.from_dict(inp.json("certificate"))
        terms = model_terms(diagnosis)
        images, obs, gobs, gcps = (inp.table(k) for k in ("images", "observations", "gcp_observations", "gcps"))
        poses, points = inp.table("poses"), inp.table("points")
        t_ref = float(diagnosis.get("reference_temperature") or 0.0)
        block = tuple(t for t in terms if t.name in BLOCK_TERMS)
        camera = tuple(t for t in terms if t.belongs_to_camera)
        ext_images = apply_block_terms(block, images, poses)
        ext_obs, ext_gobs = remove_image_terms(block, ext_images, obs, gobs, gcps, cert.camera, poses, points,
                                               t_ref)
        cal_obs, cal_gobs = remove_image_terms(terms, ext_images, obs, gobs, gcps, cert.camera, poses, points,
                                               t_ref)
        extended = extend_certificate(cert, camera, flight.get("name") or "unnamed flight", t_ref)
        doc = {"terms": [t.to_dict() for t in terms], "camera_terms": [t.name for t in camera],
               "block_terms": [t.name for t in block], "reference_temperature": t_ref,
               "certificate_extended_from": cert.id if camera else None}
        return {
            "terms": JsonOutput(doc, "model-terms"),
            "images": TableOutput(ext_images, "images"),
            "observations": TableOutput(ext_obs, "observations"),
            "gcp_observations": TableOutput(ext_gobs, "gcp_observations"),
            "calibration_observations": TableOutput(cal_obs, "observations"),
            "calibration_gcp_observations": TableOutput(cal_gobs, "gcp_observations"),
            "certificate": JsonOutput(extended.to_dict(), "certificate"),
        }

    return runner.run("extend", inputs, None, compute)


def block_figures(runner: Runner, adjusted: StepResult, assessed: StepResult, diagnosed: StepResult,
                  certificate_id: str | None) -> dict:
    """What a reader compares between a block and its extension: sigma0, the check points' RMSE and rho per axis
    (metres; None without check points), the twin's verdict, the diagnosis in one line, the certificate."""
    docs = runner.inputs({"adjustment": adjusted["adjustment"], "assessment": assessed["assessment"],
                          "diagnosis": diagnosed["diagnosis"]})
    adjustment, assessment, diagnosis = docs.json("adjustment"), docs.json("assessment"), docs.json("diagnosis")
    check = assessment.get("check_points") or {}
    return {"certificate_id": certificate_id, "sigma0": adjustment.get("sigma0"),
            "check_points": {k: check.get(k) for k in ("n", "rmse_m", "rho", "verdict")} if check.get("rho") else None,
            "twin": (diagnosis.get("twin") or {}).get("summary"), "diagnosis": diagnosis.get("summary")}


def extension_record(runner: Runner, before: dict, after: dict, terms: dict) -> dict:
    """The record of a block's extension (``extension.json``): the terms applied with their evidence, and the
    block's figures before and after (:func:`block_figures`; ``before`` and ``after`` hold the adjust, assess and
    diagnose step results and the certificate id each used); ``named`` says in one line what was applied."""
    b = block_figures(runner, before["adjust"], before["assess"], before["diagnose"], before["certificate_id"])
    a = block_figures(runner, after["adjust"], after["assess"], after["diagnose"], after["certificate_id"])
    applied = [ModelTerm.from_dict(t) for t in terms["terms"]]
    where = ["the block adjusted again with them"]
    if terms["camera_terms"]:
        where.append(f"{', '.join(terms['camera_terms'])} written into certificate {after['certificate_id']}")
    names = {t.name for t in applied}
    named = "; ".join(rotation_zero_point_text(t.values[2], t.sigmas[2])
                      if t.name == "boresight" and rotation_zero_point(names, t.values, t.sigmas)
                      else f"{t.text()} ({t.evidence})" for t in applied) + f": applied, {', '.join(where)}"
    return {"terms": terms["terms"], "camera_terms": terms["camera_terms"], "block_terms": terms["block_terms"],
            "before": b, "after": a, "named": named}
