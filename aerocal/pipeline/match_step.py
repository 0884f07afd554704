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
    extract_features,
    match_pairs_detailed,
)
from aerocal.matching.cluster import ExecutionConfig, Progress
from aerocal.matching.retrieval import retrieve_pairs
from aerocal.pipeline.config import MatchStepConfig
from aerocal.pipeline.dataset import FlightInputError
from aerocal.pipeline.figures import step_figures
from aerocal.pipeline.progress import step_progress
from aerocal.pipeline.runner import EXTRA, Runner, StepInputs, StepResult, TableOutput
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
    minus ``flight["height_agl_m"]``.

    Raises:
        FlightInputError: no GCPs and no ``height_agl_m`` in ``flight``; give one of them.
    """
    if gcps.num_rows:
        return float(np.mean(gcps.column("Z").to_numpy()))
    if flight.get("height_agl_m"):
        z = images.column("gnss_z").to_numpy(zero_copy_only=False).astype(float)
        return float(np.nanmean(z)) - float(flight["height_agl_m"])
    raise FlightInputError(
        f"{flight.get('folder') or flight.get('name')}: no GCPs and no height_agl_m in flight.json; the "
        "terrain height for candidate pairs is unknown, give one of them"
    )


def capture_order(images: pa.Table) -> np.ndarray:
    """Image ids in capture order: by the recorded time where every image has one, else by file name (cameras
    number their frames in order)."""
    ids = images.column("image_id").to_numpy()
    times = images.column("time")
    if times.null_count == 0 and len(ids):
        return ids[np.argsort(times.cast("int64").to_numpy(), kind="stable")]
    return ids[np.argsort(np.asarray(images.column("name").to_pylist(), dtype=object), kind="stable")]


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
    for every image, from a coarse match of every pair's strongest keypoints (:func:`aerocal.matching.retrieval.
    retrieve_pairs` with ``config.retrieval``, frames in :func:`capture_order`; up to
    ``config.exhaustive_max_images`` images). SIFT and the pairs run on the Dask cluster of ``execution`` (in this
    process for a flight of at most ``config.serial_max_megapixels``), streamed where the pairs are known before
    detection (:func:`aerocal.matching.detect_and_match`); ``progress(done, total)`` counts images detected plus
    pairs matched.

    Raises:
        FlightInputError: no GCPs and no flying height for footprints; more than ``exhaustive_max_images`` images
            without records.
    """
    config = config or MatchStepConfig()
    loader = frame_loader(images.column("path").to_pylist(), config.enhance)
    pairs = None  # without records: retrieved from the images' strongest keypoints once they are detected
    if has_priors(images):
        pairs = candidate_pairs_from_footprints(images, camera, terrain_height(images, gcps, flight),
                                                min_overlap=config.min_overlap,
                                                max_pairs_per_image=config.max_pairs_per_image)
    elif images.num_rows > config.exhaustive_max_images:
        raise FlightInputError(
            f"{flight.get('folder') or flight.get('name')}: {images.num_rows} images without a recorded position "
            f"and attitude for every one; candidate pairs from all pairs' coarse matches are limited to "
            f"exhaustive_max_images = {config.exhaustive_max_images}: give an EO file (--eo FILE) or raise the limit"
        )
    mcfg = config.match or MatchConfig()
    fcfg = config.features or FeatureConfig()
    megapixels = float(np.sum(images.column("width").to_numpy().astype(float)
                              * images.column("height").to_numpy().astype(float))) / 1e6
    with (execution or ExecutionConfig()).client(megapixels <= config.serial_max_megapixels) as client:
        if pairs is not None:
            kp, result = detect_and_match(images, loader, pairs, fcfg, mcfg, client, progress)
        else:
            # two phases: every image detected, its candidates chosen, then the chosen pairs matched in full
            n = images.num_rows
            kp = extract_features(images, loader, fcfg, client, None if progress is None else
                                  (lambda d, t: progress(d * n // max(t, 1), 2 * n)))
            pairs = retrieve_pairs(kp, capture_order(images), config.retrieval, mcfg).pairs
            result = match_pairs_detailed(pairs, kp, mcfg, client, None if progress is None else
                                          (lambda d, t: progress(n + d * n // max(t, 1), 2 * n)))
    matches = result.matches
    return kp, matches, build_tracks(matches, kp, mcfg), int(len(pairs))


def pairs_from(images: pa.Table, config: MatchStepConfig | None = None) -> str:
    """In words, where :func:`match_images` takes the candidate pairs of ``images`` from with ``config``."""
    if has_priors(images):
        cap = (config or MatchStepConfig()).max_pairs_per_image
        return "footprints of the recorded positions and attitudes" + (
            f", each image's {cap} of largest overlap" if cap is not None else "")
    n = images.num_rows
    return f"a coarse match of all {n * (n - 1) // 2} pairs' strongest keypoints (no recorded positions)"


def match_step(runner: Runner, ingest: StepResult, config: MatchStepConfig | None = None,
               execution: ExecutionConfig | None = None) -> StepResult:
    """Outputs ``keypoints``, ``matches`` and ``observations`` (tables) of :func:`match_images`.

    Raises:
        FlightInputError: when the step is computed: an image's pixels cannot be decoded although its header was read
            (replace the file, or move it out of ``images/``); and as :func:`match_images`.
    """
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
            EXTRA: step_figures("match", pairs=n_pairs, observations=obs.num_rows,
                                pairs_from=pairs_from(inp.table("images"), config)),
        }

    return runner.run("match", inputs, config, compute)
