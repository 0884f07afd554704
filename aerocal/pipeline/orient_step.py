"""The orient step: the poses the adjustment starts from (recorded GNSS/IMU, else incremental SfM)."""

from __future__ import annotations

import numpy as np

from aerocal.camera import Camera
from aerocal.orient import (
    OrientationError,
    georeference,
    has_priors,
    images_with_poses,
    orient_from_priors,
    orient_incremental,
)
from aerocal.pipeline.config import OrientStepConfig
from aerocal.pipeline.dataset import FlightInputError
from aerocal.pipeline.figures import step_figures
from aerocal.pipeline.runner import EXTRA, Runner, StepInputs, StepResult, TableOutput

#: ``extra["method"]`` of a block oriented by SfM
INCREMENTAL = "incremental"


def orient_step(runner: Runner, ingest: StepResult, observations: str, config: OrientStepConfig | None = None,
                matched: StepResult | None = None) -> StepResult:
    """Initial poses (``initial_poses``) and the tie-point statistics the adjustment starts from.

    A block oriented by SfM also outputs ``images``: the registered images with the oriented exterior
    orientation in place of the missing records (:func:`aerocal.orient.images_with_poses`), and
    ``extra["method"] == "incremental"``; later steps then adjust it without GNSS/IMU observations.

    Raises:
        FlightInputError: when the step is computed: an image lacks a recorded position or attitude and there are no
            matches to orient from (give an EO file with ``--eo FILE``), or incremental orientation or its
            georeferencing on the control points fails; the message names the flight.
    """
    config = config or OrientStepConfig()
    inputs = {"images": ingest["images"], "observations": observations, "flight": ingest["flight"]}
    if matched is not None:
        inputs.update(keypoints=matched["keypoints"], matches=matched["matches"], camera=ingest["camera"],
                      gcps=ingest["gcps"], gcp_observations=ingest["gcp_observations"])

    def compute(inp: StepInputs) -> dict:
        images, obs = inp.table("images"), inp.table("observations")
        flight = inp.json("flight")
        where = flight.get("folder") or flight.get("name")
        out: dict = {}
        info: dict = {"method": "priors"}
        if has_priors(images) or not inp.has("keypoints"):
            try:
                poses = orient_from_priors(images)
            except OrientationError as exc:
                raise FlightInputError(
                    f"{where}: {exc}; give an EO file with positions and attitudes (--eo FILE): an "
                    "observations-mode block starts from the recorded exterior orientation"
                ) from None
        else:
            camera = Camera.from_dict(inp.json("camera")["camera"])
            try:
                local, _, _ = orient_incremental(images, inp.table("keypoints"), inp.table("matches"), camera,
                                                 config.incremental)
                poses, sim = georeference(local, camera, inp.table("gcps"), inp.table("gcp_observations"))
            except OrientationError as exc:
                raise FlightInputError(f"{where}: no GNSS/IMU for every image, and {exc}") from None
            oriented = images_with_poses(images, poses)
            registered = set(oriented.column("image_id").to_pylist())
            missing = [n for i, n in zip(images.column("image_id").to_pylist(), images.column("name").to_pylist(),
                                         strict=True) if i not in registered]
            info = {"method": INCREMENTAL, "registered": oriented.num_rows, "not_registered": missing,
                    "georeference_scale": float(sim.scale)}
            images = oriented
            out["images"] = TableOutput(oriented, "images")
        ids = images.column("image_id").to_numpy().astype(int)
        per_image = np.bincount(obs.column("image_id").to_numpy().astype(int), minlength=ids.max() + 1)
        out["initial_poses"] = TableOutput(poses, "poses")
        out[EXTRA] = step_figures(
            "orient", **info, images=images.num_rows, observations=obs.num_rows,
            tracks=len(set(obs.column("track_id").to_pylist())),
            images_without_observations=int(np.sum(per_image[ids] == 0)),
        )
        return out

    return runner.run("orient", inputs, config, compute)
