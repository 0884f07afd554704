"""Ground-control screening before any adjustment uses the control (:mod:`aerocal.adjust.control`).

The step's ``gcps`` and ``gcp_observations`` replace the ingested ones for every later step (calibration,
block adjustment, assessment, diagnosis, report): a demoted point is in none of them, and ``screening``
says why it is not.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from prefect import task

from aerocal.adjust import AdjustConfig, AdjustmentError
from aerocal.adjust.control import ControlScreeningConfig, reference_poses, screen_control
from aerocal.camera import Camera
from tasks.resume import JsonOutput, StepContext, StepInputs, StepResult, TableOutput, run_step
from tasks.retries import TASK_RETRIES, TASK_RETRY_DELAYS_S, retry_condition


@dataclass(frozen=True)
class ControlStepConfig:
    """``screening``: the data snooping's thresholds; ``enabled`` (True): False uses the ground control
    as ingested (the report then says it was not screened)."""

    screening: ControlScreeningConfig = field(default_factory=ControlScreeningConfig)
    enabled: bool = True


def control_step(
    ctx: StepContext,
    ingest: StepResult,
    observations: str,
    orient: StepResult,
    adjust_config: AdjustConfig,
    config: ControlStepConfig | None = None,
) -> StepResult:
    """Screen the GCPs against a block they did not shape. Outputs ``gcps``, ``gcp_observations`` (the
    screened tables) and ``screening`` (the verdict per point, the datum, notes)."""
    config = config or ControlStepConfig()
    oriented_by_sfm = orient.extra.get("method") == "incremental"
    inputs = {
        "images": ingest["images"],
        "observations": observations,
        "gcps": ingest["gcps"],
        "gcp_observations": ingest["gcp_observations"],
        "camera": ingest["camera"],
        "initial_poses": orient["initial_poses"],
    }

    def compute(inp: StepInputs) -> dict:
        gcps, gobs = inp.table("gcps"), inp.table("gcp_observations")
        camera = Camera.from_dict(inp.json("camera")["camera"])
        poses, reference = inp.table("initial_poses"), ""
        if not config.enabled or not gcps.num_rows or not gobs.num_rows:
            datum = "none"
            why = "not screened: screening turned off" if not config.enabled else "no ground control measured"
            doc = {"datum": datum, "verdicts": [], "notes": [why], "demoted": [], "lines": []}
            return {"gcps": TableOutput(gcps, "gcps"), "gcp_observations": TableOutput(gobs, "gcp_observations"),
                    "screening": JsonOutput(doc, "screening"),
                    "_extra": JsonOutput({"datum": datum, "demoted": [], "lines": []}, "extra")}
        if oriented_by_sfm or adjust_config.gnss_sigma_m is None:
            datum = "control"
            reference = ("the orientation georeferenced on the control it kept" if oriented_by_sfm else
                         "the recorded poses (no GNSS sigma configured: a similarity is allowed)")
        else:
            datum = "gnss"
            try:
                poses, reference = reference_poses(inp.table("images"), inp.table("observations"), gobs, camera,
                                                   adjust_config, config.screening, gcps)
            except AdjustmentError as exc:
                reference = f"the recorded GNSS/IMU poses (the reference adjustment failed: {exc})"
        result = screen_control(gcps, gobs, poses, camera, datum, config.screening,
                                adjust_config.gnss_sigma_m, reference)
        return {
            "gcps": TableOutput(result.gcps, "gcps"),
            "gcp_observations": TableOutput(result.gcp_observations, "gcp_observations"),
            "screening": JsonOutput(result.to_dict(), "screening"),
            "_extra": JsonOutput({"datum": datum, "demoted": [v.gcp_id for v in result.demoted],
                                  "lines": result.lines()}, "extra"),
        }

    params = {"config": config, "adjust": adjust_config, "sfm": oriented_by_sfm}
    return run_step(ctx, "control", inputs, params, compute)


control_task = task(
    control_step,
    name="screen-control",
    retries=TASK_RETRIES,
    retry_delay_seconds=TASK_RETRY_DELAYS_S,
    retry_condition_fn=retry_condition,
)
