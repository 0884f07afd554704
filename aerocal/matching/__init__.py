"""Tie points for a flight: tile-parallel SIFT, candidate pairs, verified matches and tracks.

The steps, each usable alone and each exchanging the Arrow tables of :mod:`aerocal.tables`::

    with local_client(n_workers=2) as client:                    # or client=None: run here
        kp = extract_features(images, loader, FeatureConfig(), client)          # keypoints table
        pairs = candidate_pairs_from_footprints(images, camera, terrain_height)  # (P, 2) image ids
        matches = match_pairs(pairs, kp, MatchConfig(), client)                   # matches table
    obs = build_tracks(matches, kp)                                               # observations table

On a cluster, :func:`detect_and_match` gives the same keypoints and matches with detection and matching
streamed as one set of tasks (a pair is matched as soon as its two images are detected).

Modules: :mod:`.features` (detection on tiles), :mod:`.pairs` (footprint overlap),
:mod:`.verify` (FLANN, ratio test, RANSAC), :mod:`.tracks` (connected components),
:mod:`.retrieval` (candidate pairs from a coarse match, for flights without records),
:mod:`.stream` (detection and matching streamed on Dask), :mod:`.cluster` (Dask), :mod:`.config` (the
configuration dataclasses).

Tests: tests/test_matching.py, tests/test_rendered_matching.py, tests/test_retrieval.py, tests/test_dask_cluster.py.
"""

from aerocal.matching.cluster import ExecutionConfig, dask_client, local_client
from aerocal.matching.config import FeatureConfig, MatchConfig
from aerocal.matching.features import detect, extract_features, image_features, keypoints_table, tile_boxes
from aerocal.matching.pairs import (
    candidate_pairs_from_footprints,
    convex_overlap_area,
    exhaustive_pairs,
    footprints,
    prior_poses,
    sequential_pairs,
)
from aerocal.matching.stream import detect_and_match
from aerocal.matching.tracks import build_tracks
from aerocal.matching.verify import (
    PAIR_STATS,
    MatchResult,
    match_descriptors,
    match_pairs,
    match_pairs_detailed,
    pair_summary,
    sampson_distance,
    verify,
)

__all__ = [
    "PAIR_STATS",
    "ExecutionConfig",
    "FeatureConfig",
    "MatchConfig",
    "MatchResult",
    "build_tracks",
    "dask_client",
    "candidate_pairs_from_footprints",
    "convex_overlap_area",
    "detect",
    "detect_and_match",
    "exhaustive_pairs",
    "extract_features",
    "footprints",
    "image_features",
    "keypoints_table",
    "local_client",
    "match_descriptors",
    "match_pairs",
    "match_pairs_detailed",
    "pair_summary",
    "prior_poses",
    "sampson_distance",
    "sequential_pairs",
    "tile_boxes",
    "verify",
]
