"""The ground-control screening step, before any adjustment uses the control (:mod:`aerocal.adjust.control`).

The step's ``gcps`` and ``gcp_observations`` replace the ingested ones for every later step (calibration,
block adjustment, assessment, diagnosis, report): a demoted point is in none of them, and ``screening``
says why it is not.
"""

from __future__ import annotations

from typing import cast

from aerocal.adjust import AdjustConfig, AdjustmentError
from aerocal.adjust.control import reference_poses, screen_control
from aerocal.camera import Camera
from aerocal.pipeline.config import ControlStepConfig
from aerocal.pipeline.figures import OrientFigures, step_figures
from aerocal.pipeline.orient_step import INCREMENTAL
from aerocal.pipeline.runner import EXTRA, JsonOutput, Runner, StepInputs, StepResult, TableOutput


def control_step(runner: Runner, ingest: StepResult, observations: str, orient: StepResult,
                 adjust_config: AdjustConfig, config: ControlStepConfig | None = None) -> StepResult:
    """Screen the GCPs against a block they did not shape. Outputs ``gcps``, ``gcp_observations`` (the
    screened tables) and ``screening`` (the verdict per point, the datum, notes); ``extra``: the datum, the
    demoted points and one line per point."""
    config = config or ControlStepConfig()
    oriented_by_sfm = cast(OrientFigures, orient.extra)["method"] == INCREMENTAL
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
                    EXTRA: step_figures("control", datum=datum, demoted=[], lines=[])}
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
            EXTRA: step_figures("control", datum=datum, demoted=[v.gcp_id for v in result.demoted],
                                lines=result.lines()),
        }

    params = {"config": config, "adjust": adjust_config, "sfm": oriented_by_sfm}
    return runner.run("control", inputs, params, compute)
