"""The enhance + match step: tie-point observations measured in the frames (image mode)."""

from __future__ import annotations

import functools

import numpy as np
import pyarrow as pa

from aerocal.camera import Camera
from aerocal.enhance import EnhanceConfig, enhance, grey, stretch_params
from aerocal.ingest import read_raw
from aerocal.ingest.pixels import ImageReadError
from aerocal.matching import (
    FeatureConfig,
    MatchConfig,
    build_tracks,
    candidate_pairs_from_footprints,
    detect_and_match,
    exhaustive_pairs,
)
from aerocal.matching.cluster import ExecutionConfig, Progress
from aerocal.pipeline.config import MatchStepConfig
from aerocal.pipeline.dataset import FlightInputError
from aerocal.pipeline.progress import step_progress
from aerocal.pipeline.runner import JsonOutput, Runner, StepInputs, StepResult, TableOutput
from aerocal.poses import has_priors


def enhanced_frame(path: str, params, config: EnhanceConfig) -> np.ndarray:
    """A frame read with its original radiometry and enhanced to 8 bit with the flight's stretch ``params``
    (module level: it runs on Dask workers)."""
    return enhance(read_raw(path), params, config)


def frame_loader(paths: list[str], config: EnhanceConfig | None = None):
    """``loader(path) -> uint8 image`` with the stretch of the whole flight (:func:`stretch_params` over
    ``paths``), then Wallis for thermal counts (:func:`aerocal.enhance.enhance`)."""
    ecfg = config or EnhanceConfig()
    params = stretch_params(paths, percent=ecfg.percent, loader=lambda p: grey(read_raw(p)))
    return functools.partial(enhanced_frame, params=params, config=ecfg)


def terrain_height(images: pa.Table, gcps: pa.Table, flight: dict) -> float:
    """Ground height (metres, datum of ``gnss_z``) for footprints: the GCPs' mean, else the mean GNSS height
    minus ``flight["height_agl_m"]``."""
    if gcps.num_rows:
        return float(np.mean(gcps.column("Z").to_numpy()))
    if flight.get("height_agl_m"):
        z = images.column("gnss_z").to_numpy(zero_copy_only=False).astype(float)
        return float(np.nanmean(z)) - float(flight["height_agl_m"])
    raise FlightInputError(
        f"{flight.get('folder') or flight.get('name')}: no GCPs and no height_agl_m in flight.json; the "
        "terrain height for candidate pairs is unknown, give one of them"
    )


def match_images(
    images: pa.Table,
    camera: Camera,
    gcps: pa.Table,
    flight: dict,
    config: MatchStepConfig | None = None,
    execution: ExecutionConfig | None = None,
    progress: Progress | None = None,
) -> tuple[pa.Table, pa.Table, pa.Table, int]:
    """Enhance and match the frames of an ``images`` table: (keypoints, matches, observations, pairs tried).

    Candidate pairs come from the GNSS/IMU footprints on a plane at :func:`terrain_height`; without GNSS/IMU
    for every image, all pairs (up to ``config.exhaustive_max_images``). SIFT and the pairs run on the Dask
    cluster of ``execution`` (in this process for a flight of at most ``config.serial_max_megapixels``),
    streamed (:func:`aerocal.matching.detect_and_match`); ``progress(done, total)`` counts images detected plus
    pairs matched.
    """
    config = config or MatchStepConfig()
    loader = frame_loader(images.column("path").to_pylist(), config.enhance)
    if has_priors(images):
        pairs = candidate_pairs_from_footprints(images, camera, terrain_height(images, gcps, flight),
                                                min_overlap=config.min_overlap)
    elif images.num_rows <= config.exhaustive_max_images:
        pairs = exhaustive_pairs(images.column("image_id").to_numpy())
    else:
        raise FlightInputError(
            f"{flight.get('folder') or flight.get('name')}: {images.num_rows} images without a recorded position "
            f"and attitude for every one; all-pairs matching is limited to exhaustive_max_images = "
            f"{config.exhaustive_max_images}: give an EO file (--eo FILE) or raise the limit"
        )
    mcfg = config.match or MatchConfig()
    megapixels = float(np.sum(images.column("width").to_numpy().astype(float)
                              * images.column("height").to_numpy().astype(float))) / 1e6
    with (execution or ExecutionConfig()).client(megapixels <= config.serial_max_megapixels) as client:
        kp, result = detect_and_match(images, loader, pairs, config.features or FeatureConfig(), mcfg, client,
                                      progress)
    matches = result.matches
    return kp, matches, build_tracks(matches, kp, mcfg), int(len(pairs))


def match_step(runner: Runner, ingest: StepResult, config: MatchStepConfig | None = None,
               execution: ExecutionConfig | None = None) -> StepResult:
    """Outputs ``keypoints``, ``matches`` and ``observations`` (tables) of :func:`match_images`."""
    config = config or MatchStepConfig()
    inputs = {k: ingest[k] for k in ("images", "camera", "flight", "gcps")}

    def compute(inp: StepInputs) -> dict:
        try:
            kp, matches, obs, n_pairs = match_images(inp.table("images"),
                                                     Camera.from_dict(inp.json("camera")["camera"]),
                                                     inp.table("gcps"), inp.json("flight"), config, execution,
                                                     step_progress("match"))
        except ImageReadError as exc:
            # its header read at ingest, its pixels not: bad input, named, not a failure of the run
            raise FlightInputError(f"{exc}; the pixels of this image cannot be decoded although its header was "
                                   "read. Fix: replace the file, or move it out of images/ to process the others"
                                   ) from None
        return {
            "keypoints": TableOutput(kp, "keypoints"),
            "matches": TableOutput(matches, "matches"),
            "observations": TableOutput(obs, "observations"),
            "_extra": JsonOutput({"pairs": n_pairs, "observations": obs.num_rows}, "extra"),
        }

    return runner.run("match", inputs, config, compute)
