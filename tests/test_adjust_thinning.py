"""Tie-point thinning (``AdjustConfig.tie_thinning``, :func:`aerocal.adjust.thinning.thin_tracks`).

A block adjusted on a few tracks per image cell must land where the block with every track lands (within
its sigmas, on the truth of a simulated flight), and still hand back every track: the left-out ones are
intersected from the adjusted poses, with residuals aligned to the observations table, and a blunder among
them is flagged (weight 0) and kept out of the points.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from tolerance import assert_within_sigma

from aerocal.adjust import AdjustConfig, ThinningConfig, adjust, thin_tracks
from aerocal.simulate import simulate_flight

SEED = 3
THIN = ThinningConfig(grid=(4, 3), per_cell=3, seed=SEED)


@pytest.fixture(scope="module")
def flight():
    return simulate_flight("conte-calibration", seed=SEED, max_images=24)


def _cells(obs: pa.Table, width: int, height: int, grid) -> np.ndarray:
    x, y = obs.column("x").to_numpy(), obs.column("y").to_numpy()
    col = np.clip((x * grid[0] / width).astype(int), 0, grid[0] - 1)
    row = np.clip((y * grid[1] / height).astype(int), 0, grid[1] - 1)
    return (obs.column("image_id").to_numpy().astype(np.int64) * grid[1] + row) * grid[0] + col


def test_thinning_keeps_the_longest_tracks_of_every_cell_whole(flight):
    obs, cam = flight.observations, flight.camera_nominal
    rows = thin_tracks(obs, cam.width, cam.height, THIN)
    track = obs.column("track_id").to_numpy()
    kept_tracks = np.unique(track[rows])
    kept = np.isin(track, kept_tracks)
    print(f"seed {SEED}: {len(rows)} of {obs.num_rows} observations, {len(kept_tracks)} of "
          f"{len(np.unique(track))} tracks kept")
    assert np.array_equal(np.flatnonzero(kept), rows), f"seed {SEED}: a kept track lost observations"
    assert 0.05 * obs.num_rows < len(rows) < 0.6 * obs.num_rows, f"seed {SEED}: {len(rows)} rows kept"
    _, inv, counts = np.unique(track, return_inverse=True, return_counts=True)
    length = counts[inv]
    cell = _cells(obs, cam.width, cam.height, THIN.grid)
    for c in np.unique(cell):
        here = cell == c
        lengths = np.sort(length[here])[::-1]
        bar = lengths[min(THIN.per_cell, len(lengths)) - 1]
        longer = here & (length > bar)
        assert kept[longer].all(), f"seed {SEED}: cell {c} left out a track longer than its {THIN.per_cell} kept"
        assert kept[here].sum() >= min(THIN.per_cell, here.sum()), f"seed {SEED}: cell {c} kept too few"
    again = thin_tracks(obs, cam.width, cam.height, THIN)
    assert np.array_equal(rows, again), "thinning is not repeatable with the same seed"
    assert len(thin_tracks(obs, cam.width, cam.height, ThinningConfig(per_cell=0))) == obs.num_rows


def test_thinned_block_lands_on_the_truth_and_returns_every_track(flight):
    sim = flight
    s = sim.spec.sensors
    obs = sim.observations
    rng = np.random.default_rng(SEED)
    left_out = np.setdiff1d(np.arange(obs.num_rows), thin_tracks(obs, sim.camera_nominal.width,
                                                                 sim.camera_nominal.height, THIN))
    bad = np.sort(rng.choice(left_out, 20, replace=False))
    x = obs.column("x").to_numpy().copy()
    x[bad] += rng.choice([-1.0, 1.0], len(bad)) * rng.uniform(20.0, 40.0, len(bad))
    dirty = obs.set_column(obs.schema.get_field_index("x"), "x", pa.array(x))
    base = dict(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                attitude_sigma_deg=s.imu_sigma_deg, free=("f", "cx", "cy", "k1"), robust_loss="huber")
    full = adjust(sim.images, dirty, sim.camera_nominal, AdjustConfig(**base), sim.gcps, sim.gcp_observations)
    thin = adjust(sim.images, dirty, sim.camera_nominal, AdjustConfig(**base, tie_thinning=THIN), sim.gcps,
                  sim.gcp_observations)
    true = sim.spec.camera_true
    for n in ("f", "cx", "cy", "k1"):
        err = getattr(thin.camera, n) - getattr(true, n)
        print(f"{n}: thinned {err:+.4g} +- {thin.sigmas[n]:.2g}, all tracks "
              f"{getattr(full.camera, n) - getattr(true, n):+.4g} +- {full.sigmas[n]:.2g}")
        cap = 0.02 if n == "k1" else 0.002 * true.f
        assert_within_sigma(err, thin.sigmas[n], 3.5, cap, f"seed {SEED}: thinned {n}")
        assert thin.sigmas[n] < 3 * full.sigmas[n], f"seed {SEED}: thinning lost too much precision in {n}"
    print("check RMSE thinned", thin.check_rmse.round(3), "all", full.check_rmse.round(3), "rho", thin.rho.round(2))
    assert np.all(thin.check_rmse < 1.5 * full.check_rmse + 0.02), f"seed {SEED}: check points worse when thinned"
    print(thin.selection[0])
    assert thin.selection[0].startswith("tie points thinned")
    # every row has its residual; left-out rows are NaN-weighted, the blunders among them weight 0
    assert thin.residuals.shape == (obs.num_rows, 2)
    assert np.isfinite(thin.residuals).all(axis=1).mean() > 0.97
    assert (thin.obs_weight[bad] == 0).all(), f"seed {SEED}: blunders among the intersected tracks not flagged"
    clean_left = np.setdiff1d(left_out, bad)
    flagged = np.mean(thin.obs_weight[clean_left] == 0)
    assert np.isnan(thin.obs_weight[clean_left]).mean() > 0.97, f"seed {SEED}: {flagged:.1%} good rows flagged"
    # the points: every track, the blunders' excepted, at its true position within the noise
    bad_tracks = np.unique(obs.column("track_id").to_numpy()[bad])
    n_tracks = len(np.unique(obs.column("track_id").to_numpy()))
    got = thin.points.column("track_id").to_numpy()
    assert not np.isin(bad_tracks, got).any(), f"seed {SEED}: a blunder's track was intersected into the points"
    assert len(got) > 0.97 * (n_tracks - len(bad_tracks))
    assert np.all(np.diff(got) > 0), "points are not sorted by track id"
    truth = sim.tie.points[got]
    xyz = np.column_stack([thin.points.column(c).to_numpy() for c in ("X", "Y", "Z")])
    d = np.linalg.norm(xyz - truth, axis=1)
    ref = np.linalg.norm(np.column_stack([full.points.column(c).to_numpy() for c in ("X", "Y", "Z")])
                         - sim.tie.points[full.points.column("track_id").to_numpy()], axis=1)
    print(f"point error median thinned {np.median(d):.3f} m, all tracks {np.median(ref):.3f} m")
    assert np.median(d) < 1.3 * np.median(ref), f"seed {SEED}: intersected points worse than adjusted ones"


def test_a_point_the_rays_cannot_place_is_not_handed_back():
    """Two frames 60 m apart, 850 m up (the city's base and height): a ground point seen by both is placed to
    ~2 m and kept; rays off by 0.002 px from parallel put a point 50,000 km away, and one behind the cameras
    is not kept either (a single such point once made a city's DSM 8 x 8 cells of 635 m)."""
    from aerocal.adjust.projection import project
    from aerocal.adjust.triangulate import placed_by_rays, refine_points
    from aerocal.camera import Camera

    cam = Camera(width=640, height=480, f=1674.0, cx=320.0, cy=240.0)
    io, slopes = cam.params(), np.zeros(3)
    R = np.repeat(np.diag([1.0, -1.0, -1.0])[None], 2, axis=0)  # world-to-camera, looking down
    C = np.array([[0.0, 0.0, 850.0], [60.0, 0.0, 850.0]])
    image, j = np.tile([0, 1], 3), np.repeat(np.arange(3), 2)
    truth = np.array([[30.0, 10.0, 0.0], [30.0, 10.0, 0.0], [30.0, 10.0, 1700.0]])
    uv = project(io, slopes, np.zeros(6), R[image], C[image], truth[j], jacobians=False).uv
    uv[3] = uv[2] - [0.002, 0.0]  # point 1: rays parallel to within 0.002 px (the ground's parallax: 118 px)
    sigma = np.full(6, 0.2)
    start = truth.copy()
    start[1] = [0.0, 0.0, 850.0 - 1674.0 * 60.0 / 0.002]
    X, _ = refine_points(io, slopes, np.zeros(6), R[image], C[image], j, uv, sigma, start)
    keep = placed_by_rays(X, R, C, image, j, sigma, cam.f)
    assert np.abs(X[0] - truth[0]).max() < 1e-6 and keep[0], (X[0], keep)
    assert abs(X[1, 2]) > 1e6 and not keep[1], (X[1], keep)
    assert not keep[2], "a point behind the cameras"
    assert placed_by_rays(X[:1], R, C, image[:2], j[:2], sigma[:2], cam.f)[0]
    assert not placed_by_rays(X[:1], R, C, image[:1], j[:1], sigma[:1], cam.f)[0], "one ray places nothing"


def test_a_mismatch_placed_kilometres_below_the_ground_is_not_handed_back():
    """Rays spread well enough still place a mismatch along the epipolar line: on the rendered city two-ray
    points lay up to 6.8 km below the ground with tenths of a pixel of residual. Deeper than 3 times the mean
    depth of a camera's points, such a point is left out; a valley 400 m below the 850 m flying height stays."""
    from aerocal.adjust.projection import project
    from aerocal.adjust.triangulate import MAX_POINT_SIGMA_FRACTION, placed_by_rays
    from aerocal.camera import Camera

    cam = Camera(width=640, height=480, f=1674.0, cx=320.0, cy=240.0)
    R = np.repeat(np.diag([1.0, -1.0, -1.0])[None], 2, axis=0)  # world-to-camera, looking down
    C = np.array([[0.0, 0.0, 850.0], [60.0, 0.0, 850.0]])
    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(-40.0, 100.0, 50), rng.uniform(-60.0, 60.0, 50), np.zeros(50)])
    X = np.vstack([ground, [[30.0, 0.0, -400.0], [30.0, 0.0, -6000.0]]])
    image, j = np.tile([0, 1], len(X)), np.repeat(np.arange(len(X)), 2)
    sigma = np.full(len(j), 0.2)
    uv = project(cam.params(), np.zeros(3), np.zeros(len(j)), R[image], C[image], X[j], jacobians=False).uv
    assert np.isfinite(uv).all()
    spread = 60.0 / 6850.0  # the deep point's rays are spread enough for the sigma test alone
    assert np.sqrt(2.0) * 0.2 / (cam.f * spread) < MAX_POINT_SIGMA_FRACTION
    keep = placed_by_rays(X, R, C, image, j, sigma, cam.f)
    assert keep[:50].all() and keep[50], "the ground and a valley 400 m below it are kept"
    assert not keep[51], "a point 6 km below the ground is not handed back"
