"""The diagnosis step: residual analysis against the catalogue of unmodelled effects, IO fixed from the
certificate (:func:`aerocal.diagnose.engine.diagnose`), with the flight's twin. The block's model is diagnosed: where
the block adjustment corrected the measurements with the certificate's thermal model, so are the diagnosis's, and a
thermal effect it names is what that model leaves."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pyarrow as pa

from aerocal.adjust import AdjustConfig, corrected_to_t0, scale_tie_sigma, screened_rows
from aerocal.camera import PARAM_NAMES, Camera
from aerocal.certificates.document import Certificate
from aerocal.diagnose.engine import DiagnoseConfig, Diagnosis, diagnose
from aerocal.diagnose.io_uncertainty import IOUncertainty
from aerocal.diagnose.run import diagnose_tables
from aerocal.pipeline.dataset import FlightInputError, FolderDataset, IngestStepConfig
from aerocal.pipeline.runner import JsonOutput, Runner, StepInputs, StepResult


def diagnose_step(runner: Runner, ingest: StepResult, observations: str, certificate: str,
                  config: DiagnoseConfig | None = None, adjust_config: AdjustConfig | None = None,
                  adjusted: StepResult | None = None, thermal_correction: bool = False,
                  calibrated_on_flight: bool = False, name: str = "diagnose") -> StepResult:
    """Output ``diagnosis``: the hypotheses tested, the effects named with magnitude and evidence, the gain on
    check points, the recorded-EO checks, the twin, and a one-line verdict (``summary``). With the block
    adjustment's result (``adjusted``) the block is diagnosed on the data that adjustment used: its recorded
    positions as it corrected them (a GNSS lag removed) and its measurements as the certificate's camera terms
    corrected them, so that what is named is what the block's own model leaves.

    With the block adjustment's result (``adjusted``), the observations its blunder screening rejected (weight
    0 in its ``obs_weight``) are left out and the diagnosis adjusts by least squares at once, instead of
    screening the same block again (a robust pass and a least-squares re-adjustment of the whole block, the
    cost of a second block adjustment).

    ``thermal_correction``: the block adjustment corrected the measurements with the certificate's linear thermal
    model; the diagnosis does too. Without it, a Daakir corridor processed with a certificate holding the
    principal point's slopes, its correction applied, still had that drift named (-0.084 / +0.272 px/degC).

    ``calibrated_on_flight``: the certificate was made by this flight's self-calibration. Its IO is then no
    independent knowledge: the calibration fitted it to these images, absorbing part of any effect they hold (a
    readout's stretch along the track in the focal length, an affinity in f), and an effect tested against it
    held fixed is tested against a camera bent towards it. The parameters the calibration estimated are then
    estimated again with every hypothesis (the self-calibration extended by it); those it held at their nominal
    values stay fixed with their tolerances.

    Raises:
        ValueError: when the step is computed: the block adjustment's ``obs_weight`` has another number of rows than the
            observations; re-run the adjust step.
    """
    inputs = {k: ingest[k] for k in ("images", "gcps", "gcp_observations")}
    inputs.update(observations=observations, certificate=certificate)
    if adjusted is not None and "obs_weight" in adjusted.outputs:
        inputs.update({k: adjusted[k] for k in ("obs_weight", "residuals", "adjustment", "poses", "points")})
    if adjusted is not None and "block_images" in adjusted.outputs:
        # the block's own data: its recorded positions and measurements as its adjustment corrected them
        inputs.update(images=adjusted["block_images"], observations=adjusted["block_observations"],
                      gcp_observations=adjusted["block_gcp_observations"])
    acfg = adjust_config or AdjustConfig()

    def compute(inp: StepInputs) -> dict:
        cert = Certificate.from_dict(inp.json("certificate"))
        t0 = getattr(None if cert.thermal is None else cert.thermal.model, "t0", None)
        dcfg = config or DiagnoseConfig(reference_temperature=t0)
        thermal = cert.linear_thermal if thermal_correction else None
        images = inp.table("images")
        obs = corrected_to_t0(images, inp.table("observations"), cert.camera, thermal)
        gobs = corrected_to_t0(images, inp.table("gcp_observations"), cert.camera, thermal)
        free = tuple(n for n in cert.estimated if n in PARAM_NAMES) if calibrated_on_flight else ()
        run_cfg = dataclasses.replace(acfg, free=free, thermal=(), adaptive=False)
        screening = None
        if inp.has("obs_weight"):
            weight = inp.array("obs_weight")
            if len(weight) != obs.num_rows:
                raise ValueError(f"diagnose: the block adjustment's obs_weight has {len(weight)} rows, the "
                                 f"observations {obs.num_rows}; re-run the adjust step")
            # its estimate of the tie observations' sigma (1 for an adjustment that made none)
            tie_scale = float(inp.json("adjustment").get("tie_sigma_scale", 1.0))
            keep = screened_rows(obs, inp.array("residuals"), weight, tie_scale, acfg.reject_chi2)
            screening = (f"the block adjustment's screening: {obs.num_rows - len(keep)} of {obs.num_rows} "
                         "observations left out (blunders, observations it could not place, and observations "
                         "left alone in their tracks)")
            obs = scale_tie_sigma(obs.take(pa.array(keep, pa.int64())), tie_scale)
            screening += f"; tie-point sigma x {tie_scale:.3f} as estimated by the block adjustment"
            run_cfg = dataclasses.replace(run_cfg, robust_loss="none")
        result = diagnose(images, obs, cert.camera, run_cfg, inp.table("gcps"), gobs, dcfg,
                          IOUncertainty.from_certificate(cert),
                          (inp.table("poses"), inp.table("points")) if inp.has("poses") else None)
        doc = result.to_dict()
        doc["summary"] = result.summary()
        doc["screening"] = screening
        return {"diagnosis": JsonOutput(doc, "diagnosis")}

    return runner.run(name, inputs, {"diagnose": config or DiagnoseConfig(), "adjust": acfg,
                                           "thermal_correction": bool(thermal_correction),
                                           "calibrated_on_flight": bool(calibrated_on_flight)}, compute)


def diagnose_folder(folder: str | Path, certificate: str | Path | None = None,
                    config: DiagnoseConfig | None = None) -> Diagnosis:
    """``aerocal diagnose FOLDER`` on a flight folder: read as ``aerocal process`` reads it in observations mode
    (:class:`~aerocal.pipeline.dataset.FolderDataset`: the observation tables, camera.json and flight.json, with
    eo.csv and the GCP files checked against the tables), then diagnosed by
    :func:`aerocal.diagnose.run.diagnose_tables` (IO fixed from ``certificate`` when given, else the baseline
    self-calibrates camera.json's camera).

    Raises:
        FlightInputError: the folder holds no observation tables (they come from ``aerocal match`` or an
            observations-mode flight) or its files contradict them; the message names the file and the fix.
        DiagnoseInputError: the certificate file does not read.
    """
    dataset = FolderDataset(folder)
    if not dataset.observations_mode:
        raise FlightInputError(f"{dataset.folder / 'observations' / 'observations.parquet'} is missing; the "
                               f"diagnosis needs a block's measurements: run `aerocal match {folder}` first, or "
                               "`aerocal process` and diagnose its run folder")
    read = dataset.read(IngestStepConfig())
    t = read.tables
    return diagnose_tables(t["images"], t["observations"], t["gcps"], t["gcp_observations"], read.metadata,
                           Camera.from_dict(read.camera["camera"]), certificate, config)
