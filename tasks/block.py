"""The full-block adjustment with IO fixed from the certificate, image measurements corrected for the
sensor temperature where the certificate has a linear thermal model (Daakir 2019: tie points and GCP
measurements are corrected, not pixels; :func:`aerocal.adjust.adjust_fixed_io`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from prefect import task

from aerocal.adjust import AdjustConfig, adjust_fixed_io
from aerocal.camera import LinearThermalModel
from aerocal.certificate import Certificate
from aerocal.eo_checks import correct_gnss_offset
from tasks.resume import ArrayOutput, JsonOutput, StepContext, StepInputs, StepResult, TableOutput, run_step
from tasks.retries import TASK_RETRIES, TASK_RETRY_DELAYS_S, retry_condition


@dataclass(frozen=True)
class BlockStepConfig:
    """``adjust``: the full-block adjustment (IO is fixed whatever ``adjust.free`` says; default GNSS
    sigmas 0.10/0.10/0.15 m, GCPs weighted by their survey sigmas); ``thermal_correction`` (True): apply
    the certificate's linear thermal model to the measurements."""

    adjust: AdjustConfig = field(default_factory=AdjustConfig)
    thermal_correction: bool = True
    #: test the recorded positions for a GNSS time lag (and, with 3 control GCPs, a horizontal offset) on this
    #: many central images and remove what passes before adjusting (:func:`aerocal.eo_checks.correct_gnss_offset`);
    #: 0 = use the positions as recorded
    recorded_eo_images: int = 200


def adjust_step(
    ctx: StepContext,
    ingest: StepResult,
    observations: str,
    certificate: str,
    config: BlockStepConfig | None = None,
    adjust_config: AdjustConfig | None = None,
) -> StepResult:
    """Adjust the whole flight with the certificate's IO.

    Outputs: ``poses``, ``points`` (tables), ``adjustment`` (summary, check-point and control residuals,
    predicted check-point sigmas; metres, E N Up; ``recorded_eo_corrections``: the GNSS time lag and offset
    tested on the recorded positions and removed where they passed, with the notes), ``residuals``
    ((M, 2) pixels, predicted minus observed, aligned with the observations table) and ``obs_weight``
    ((M,) the weight of each observation at the solution: 0 for a blunder the screening rejected, NaN for one
    the block left out).
    """
    config = config or BlockStepConfig()
    acfg = adjust_config or config.adjust
    inputs = {
        "images": ingest["images"],
        "observations": observations,
        "gcps": ingest["gcps"],
        "gcp_observations": ingest["gcp_observations"],
        "certificate": certificate,
    }

    def compute(inp: StepInputs) -> dict:
        cert = Certificate.from_dict(inp.json("certificate"))
        thermal = None
        if (
            config.thermal_correction
            and cert.thermal is not None
            and isinstance(cert.thermal.model, LinearThermalModel)
        ):
            thermal = cert.thermal.model
        images, corrections = inp.table("images"), None
        if config.recorded_eo_images and acfg.gnss_sigma_m is not None:
            eo = correct_gnss_offset(images, inp.table("observations"), cert.camera,
                                     dataclasses.replace(acfg, free=()), inp.table("gcps"),
                                     inp.table("gcp_observations"), config.recorded_eo_images)
            images = eo.images
            corrections = {"offset_m": eo.offset_m, "sigma_m": eo.sigma_m, "time_offset_s": eo.time_offset_s,
                           "time_sigma_s": eo.time_sigma_s, "notes": eo.notes}
        res = adjust_fixed_io(
            images,
            inp.table("observations"),
            cert.camera,
            acfg,
            inp.table("gcps"),
            inp.table("gcp_observations"),
            thermal,
        )
        summary = res.summary()
        summary.update(
            {
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
            }
        )
        return {
            "poses": TableOutput(res.poses, "poses"),
            "points": TableOutput(res.points, "points"),
            "adjustment": JsonOutput(summary, "adjustment"),
            "residuals": ArrayOutput(np.asarray(res.residuals, dtype=float), "residuals"),
            "obs_weight": ArrayOutput(np.asarray(res.obs_weight, dtype=float), "obs_weight"),
        }

    return run_step(ctx, "adjust", inputs, {"config": config, "adjust": acfg}, compute)


adjust_task = task(
    adjust_step,
    name="adjust-fixed-io",
    retries=TASK_RETRIES,
    retry_delay_seconds=TASK_RETRY_DELAYS_S,
    retry_condition_fn=retry_condition,
)
