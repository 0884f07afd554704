"""Tie points from rendered frames agree with the simulator's truth within the noise.

Frames of a simulated thermal flight are rendered, enhanced and matched like real ones; each verified
match is then checked against the true geometry: the keypoint of the first frame, cast onto the true
surface through the true pose, must re-project onto its partner in the second frame.
"""

import functools

import numpy as np

from aerocal.enhance import EnhanceConfig, enhance, stretch_params
from aerocal.matching import MatchConfig, exhaustive_pairs, extract_features, match_pairs
from aerocal.simulate import simulate_flight
from aerocal.simulate.raycast import RenderConfig, intersect_dsm, render_frame


def _load(frames: dict, params, config: EnhanceConfig, image_id: int) -> np.ndarray:
    return enhance(frames[image_id], params, config)


def test_matches_on_rendered_frames_agree_with_the_true_geometry():
    seed = 12
    sim = simulate_flight("conte-calibration", seed=seed, max_images=6)
    rng = np.random.default_rng(seed)
    frames = {ex.image_id: render_frame(sim.scene, ex, RenderConfig(), rng) for ex in sim.exposures}
    ecfg = EnhanceConfig()
    params = stretch_params(list(frames.values()))
    loader = functools.partial(_load, frames, params, ecfg)
    keypoints = extract_features([(i, i) for i in frames], loader)
    matches = match_pairs(exhaustive_pairs(sorted(frames)), keypoints, MatchConfig())
    assert matches.num_rows > 500, f"seed {seed}: only {matches.num_rows} verified matches"

    kp = keypoints.to_pydict()
    xy = {(i, k): (x, y) for i, k, x, y in zip(kp["image_id"], kp["keypoint_id"], kp["x"], kp["y"], strict=True)}
    m = matches.to_pydict()
    by_id = {ex.image_id: ex for ex in sim.exposures}
    errors = []
    for i1 in sorted(set(m["image_id1"])):
        rows = [r for r, a in enumerate(m["image_id1"]) if a == i1]
        for i2 in sorted({m["image_id2"][r] for r in rows}):
            sel = [r for r in rows if m["image_id2"][r] == i2]
            uv1 = np.array([xy[(i1, m["keypoint_id1"][r])] for r in sel])
            uv2 = np.array([xy[(i2, m["keypoint_id2"][r])] for r in sel])
            o, d = by_id[i1].rays(uv1)
            hits = intersect_dsm(sim.scene, o, d)
            pred = by_id[i2].project(hits.points[hits.hit])
            errors.append(np.linalg.norm(pred - uv2[hits.hit], axis=1))
    err = np.concatenate(errors)
    # a building edge or a tree seen from two sides can fool one match in a hundred; the rest must sit
    # at the matching noise (SIFT on low-contrast 640x480 thermal frames: a few tenths of a pixel)
    inlier = err < 2.0
    assert inlier.mean() > 0.95, f"seed {seed}: {1 - inlier.mean():.1%} of matches off the true geometry"
    assert np.median(err) < 0.5, f"seed {seed}: median transfer error {np.median(err):.2f} px"
    rms = float(np.sqrt(np.mean(err[inlier] ** 2)))
    print(f"seed {seed}: {len(err)} matches, {inlier.mean():.1%} within 2 px, median {np.median(err):.3f} px, "
          f"RMS {rms:.3f} px")
    assert rms < 0.8, f"seed {seed}: RMS transfer error {rms:.2f} px"
