"""The full-block adjustment with IO fixed from the certificate, image measurements corrected for the sensor
temperature where the certificate has a linear thermal model (Daakir 2019: tie points and GCP measurements are
corrected, not pixels; :func:`aerocal.adjust.adjust_fixed_io`)."""

from __future__ import annotations

import dataclasses
from contextlib import nullcontext

import numpy as np

from aerocal.adjust import AdjustConfig, adjust_fixed_io
from aerocal.adjust.partition import PartitionedSolver
from aerocal.calibrate.eo_checks import correct_recorded_eo
from aerocal.certificates.document import Certificate
from aerocal.diagnose.extension import measurement_terms, remove_image_terms
from aerocal.diagnose.io_uncertainty import IOUncertainty
from aerocal.matching.cluster import ExecutionConfig, n_workers
from aerocal.pipeline.config import BlockStepConfig
from aerocal.pipeline.runner import ArrayOutput, JsonOutput, Runner, StepInputs, StepResult, TableOutput


def adjust_step(runner: Runner, ingest: StepResult, observations: str, certificate: str,
                config: BlockStepConfig | None = None, adjust_config: AdjustConfig | None = None,
                execution: ExecutionConfig | None = None, geometry: StepResult | None = None,
                name: str = "adjust") -> StepResult:
    """Adjust the whole flight with the certificate's model: its IO, its linear thermal model (the measurements
    corrected to T0) and its camera terms applied to the measurements (a rolling-shutter readout, a thermal
    rotation: :func:`aerocal.diagnose.extension.measurement_terms`), corrected at the adjusted geometry of
    ``geometry`` (a previous adjustment of the same block: its ``poses`` and ``points``) or, without it, of a
    first adjustment of the uncorrected measurements.

    Outputs: ``poses``, ``points`` (tables), ``adjustment`` (summary, check-point and control residuals,
    predicted check-point sigmas; metres, E N Up; ``recorded_eo_corrections``: the GNSS time lag and offset
    tested on the recorded positions and removed where they passed, with the notes; ``camera_terms``: the
    certificate's terms applied to the measurements), ``residuals``
    ((M, 2) pixels, predicted minus observed, aligned with the observations table) and ``obs_weight``
    ((M,) the weight of each observation at the solution: 0 for a blunder the screening rejected, NaN for one
    the block left out); the block's data as the adjustment used them, which the assessment and the diagnosis
    read so that they see the block's own model: ``block_images`` (recorded positions as corrected),
    ``block_observations`` and ``block_gcp_observations`` (the measurements as corrected for the camera terms,
    row for row the input's). A block of ``config.partition_min_images`` images or more is adjusted in
    sub-blocks on the Dask cluster of ``execution``;
    ``adjustment["partitioned"]`` then says how it was cut. ``name``: the step's name in the run (the adjustment
    of a block extended by its diagnosis is another step of the same run).
    """
    config = config or BlockStepConfig()
    acfg = adjust_config or config.adjust
    run_on = execution or ExecutionConfig()
    inputs = {"images": ingest["images"], "observations": observations, "gcps": ingest["gcps"],
              "gcp_observations": ingest["gcp_observations"], "certificate": certificate}
    if geometry is not None:
        inputs.update(geometry_poses=geometry["poses"], geometry_points=geometry["points"])

    def compute(inp: StepInputs) -> dict:
        cert = Certificate.from_dict(inp.json("certificate"))
        thermal = cert.linear_thermal if config.thermal_correction else None
        images, obs = inp.table("images"), inp.table("observations")
        gcps, gobs = inp.table("gcps"), inp.table("gcp_observations")
        terms = measurement_terms(cert)
        if terms:
            if inp.has("geometry_poses"):
                poses, points = inp.table("geometry_poses"), inp.table("geometry_points")
            else:  # the geometry the corrections are taken at: the block adjusted without them
                first = adjust_fixed_io(images, obs, cert.camera, acfg, gcps, gobs, thermal)
                poses, points = first.poses, first.points
            t0 = thermal.t0 if thermal is not None else 0.0  # each thermal term carries its own reference
            obs, gobs = remove_image_terms(terms, images, obs, gobs, gcps, cert.camera, poses, points, t0)
        corrections = None
        if config.recorded_eo_images and acfg.gnss_sigma_m is not None:
            n, m = images.num_rows, config.recorded_eo_images
            block = (f"the {m} images nearest the centre of the {n}-image block" if m and m < n
                     else f"the whole {n}-image block") + ", IO held fixed"
            att, eo = correct_recorded_eo(images, obs, cert.camera, dataclasses.replace(acfg, free=()), gcps, gobs,
                                          config.recorded_eo_images, IOUncertainty.from_certificate(cert),
                                          block=block)
            images = eo.images
            corrections = {"offset_m": eo.offset_m, "sigma_m": eo.sigma_m, "time_offset_s": eo.time_offset_s,
                           "time_sigma_s": eo.time_sigma_s, "notes": att.notes + eo.notes, "evidence": eo.evidence,
                           "attitude_offset_deg": att.offset_deg,
                           "attitude_check": att.check.to_dict() if att.check is not None else None}
        solver = PartitionedSolver(config.partition_min_images, config.partition_max_images, run_on.local_workers)
        parted = solver.n_parts(images.num_rows) > 1  # a smaller block needs no cluster, not even a given one
        with (run_on.client() if parted else nullcontext(None)) as client:
            if client is not None:  # one sub-block per worker at least, on the cluster the step was given
                solver.client, solver.n_workers = client, n_workers(client)
            res = adjust_fixed_io(images, obs, cert.camera, acfg, gcps, gobs, thermal, solver=solver)
        summary = res.summary()
        summary.update({
            "certificate_id": cert.id,
            "thermal_correction": thermal is not None,
            "converged": res.converged,
            "iterations": res.iterations,
            "check_ids": list(res.check_ids),
            "check_errors_m": np.asarray(res.check_errors).tolist(),
            "check_sigma_m": np.asarray(res.check_sigma).tolist(),
            "control_ids": list(res.control_ids),
            "control_errors_m": np.asarray(res.control_errors).tolist(),
            "recorded_eo_corrections": corrections,
            "camera_terms": [t.text() for t in terms],
            "partitioned": solver.runs[-1] if solver.runs else None,
        })
        return {
            "poses": TableOutput(res.poses, "poses"),
            "points": TableOutput(res.points, "points"),
            "adjustment": JsonOutput(summary, "adjustment"),
            "residuals": ArrayOutput(np.asarray(res.residuals, dtype=float), "residuals"),
            "obs_weight": ArrayOutput(np.asarray(res.obs_weight, dtype=float), "obs_weight"),
            "block_images": TableOutput(images, "images"),
            "block_observations": TableOutput(obs, "observations"),
            "block_gcp_observations": TableOutput(gobs, "gcp_observations"),
        }

    return runner.run(name, inputs, {"config": config, "adjust": acfg}, compute)
