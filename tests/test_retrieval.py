"""Candidate pairs of a flight without position records: a coarse match of each image's strongest keypoints keeps
the pairs that overlap and leaves out those that do not."""

from __future__ import annotations

import numpy as np
import pytest

from aerocal.matching import keypoints_table
from aerocal.matching.retrieval import RetrievalConfig, retrieve_pairs

SEED = 7


def _strip(seed: int, n_images: int = 10, per_image: int = 800, step: int = 300):
    """A strip of images over a line of ground points, each point with its own SIFT-like descriptor: image i sees
    points [i step, i step + per_image), so image i shares per_image - k step points with image i + k; each
    sighting's descriptor is the point's with noise, and an image's keypoints are in a random order (their
    strength does not depend on being shared)."""
    rng = np.random.default_rng(seed)
    n_points = step * (n_images - 1) + per_image
    points = rng.integers(0, 256, size=(n_points, 128)).astype(np.float64)
    features = []
    for i in range(n_images):
        seen = rng.permutation(np.arange(i * step, i * step + per_image))
        desc = np.clip(points[seen] + rng.normal(0.0, 6.0, size=(per_image, 128)), 0, 255).astype(np.uint8)
        kp = np.column_stack([rng.uniform(0, 640, per_image), rng.uniform(0, 480, per_image),
                              np.full(per_image, 2.0), np.zeros(per_image)])
        features.append((i, kp, desc))
    return keypoints_table(features)


def test_the_coarse_match_keeps_the_overlapping_pairs_and_only_those():
    kp = _strip(SEED)
    got = retrieve_pairs(kp, config=RetrievalConfig(strongest=256, neighbours=0, sequence_window=0))
    gap = got.candidates[:, 1] - got.candidates[:, 0]
    print(f"seed {SEED}: scores by index gap:",
          {int(g): sorted(set(got.scores[gap == g].tolist()))[:3] for g in np.unique(gap)[:4]})
    # overlap 500 and 200 of 800 points (gaps 1, 2) score many coarse matches; no shared point scores (nearly) none
    assert np.all(got.scores[gap <= 2] >= 8), f"seed {SEED}: {got.scores[gap <= 2]}"
    assert np.all(got.scores[gap >= 3] <= 2), f"seed {SEED}: {got.scores[gap >= 3]}"
    kept = {tuple(p) for p in got.pairs.tolist()}
    assert kept == {(i, j) for i in range(10) for j in range(i + 1, min(i + 3, 10))}, f"seed {SEED}: {sorted(kept)}"
    assert got.fraction == pytest.approx(17 / 45)


def test_capture_order_and_an_images_best_partners_are_kept_whatever_their_scores():
    kp = _strip(SEED, n_images=6, per_image=400, step=390)  # consecutive images share 10 points: weak pairs
    order = np.array([0, 1, 2, 3, 4, 5])
    none = retrieve_pairs(kp, order, RetrievalConfig(strongest=128, min_matches=50, neighbours=0, sequence_window=0))
    assert len(none.pairs) == 0, f"seed {SEED}: {none.pairs}"
    seq = retrieve_pairs(kp, order, RetrievalConfig(strongest=128, min_matches=50, neighbours=0, sequence_window=1))
    assert {tuple(p) for p in seq.pairs.tolist()} == {(i, i + 1) for i in range(5)}
    # capture order given, not the ids': image 5 was taken between 0 and 1
    shuffled = retrieve_pairs(kp, np.array([0, 5, 1, 2, 3, 4]),
                              RetrievalConfig(strongest=128, min_matches=50, neighbours=0, sequence_window=1))
    assert (0, 5) in {tuple(p) for p in shuffled.pairs.tolist()}
    # the best partner of each image, even below min_matches, when it shares anything at all
    best = retrieve_pairs(kp, order, RetrievalConfig(strongest=400, min_matches=50, neighbours=1, sequence_window=0))
    assert {tuple(p) for p in best.pairs.tolist()} <= {(i, i + 1) for i in range(5)} and len(best.pairs) >= 3


def test_retrieval_settings_are_checked():
    with pytest.raises(ValueError, match="strongest"):
        RetrievalConfig(strongest=4)
    with pytest.raises(ValueError, match="ratio"):
        RetrievalConfig(ratio=1.5)
    with pytest.raises(ValueError, match="min_matches"):
        RetrievalConfig(min_matches=0)
    with pytest.raises(ValueError, match="neighbours"):
        RetrievalConfig(neighbours=-1)
