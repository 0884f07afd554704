"""Starting values of the adjustment when the recorded attitude is an autopilot's (a few degrees).

A daakir-uav block (30 frames, 70 m above ground, like the real seneca flight) whose recorded attitude has
errors of 5/5/10 degrees about the camera x/y/z axes: triangulated from the recorded poses, some tie
points land centimetres from a camera or far below the ground. Those points start on the ground plane
(:data:`aerocal.adjust.bundle.PLAUSIBLE_DEPTH`), and the self-calibrating adjustment with GNSS and attitude
priors lands on the truth; started where they were triangulated, the same adjustment stops in a wrong
minimum.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from aerocal.adjust import AdjustConfig, adjust, bundle
from aerocal.adjust.problem import build_block
from aerocal.adjust.triangulate import pixels_to_rays, triangulate_linear
from aerocal.simulate import simulate_flight
from aerocal.simulate.presets import get_preset

IMU_SIGMA_DEG = (5.0, 5.0, 10.0)
SEEDS = (0, 1)


def _flight(seed: int):
    spec = get_preset("daakir-uav")
    spec = dataclasses.replace(spec, sensors=dataclasses.replace(spec.sensors, imu_sigma_deg=IMU_SIGMA_DEG))
    sim = simulate_flight(spec, seed=seed, max_images=30)
    s = sim.spec.sensors
    cfg = AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                       attitude_sigma_deg=IMU_SIGMA_DEG, free=("f", "cx", "cy", "k1", "k2", "p1", "p2"))
    return sim, cfg


def _depths(block, X) -> tuple[np.ndarray, np.ndarray]:
    """Depth of every tie observation's point in its image (recorded poses) and the observations' points."""
    i, j = block.obs_image[block.obs_is_tie], block.obs_point[block.obs_is_tie]
    return np.einsum("mk,mk->m", block.R_rec[i][:, 2], X[j] - block.gnss[i]), j


def _errors(sim, res) -> dict[str, float]:
    true = sim.spec.camera_true
    return {n: (getattr(res.camera, n) - getattr(true, n)) / res.sigmas[n] for n in ("f", "cx", "cy")}


@pytest.mark.parametrize("seed", SEEDS)
def test_points_triangulated_at_absurd_depths_start_on_the_ground(seed):
    sim, cfg = _flight(seed)
    block = build_block(sim.images, sim.observations, sim.gcps, sim.gcp_observations, cfg)
    tie = block.obs_is_tie
    rays = pixels_to_rays(sim.camera_nominal.params(), np.zeros(3), np.zeros(int(tie.sum())),
                          block.R_rec[block.obs_image[tie]], block.obs_uv[tie])
    X, ok = triangulate_linear(block.obs_point[tie], block.n_tie, block.gnss[block.obs_image[tie]], rays)
    d, j = _depths(block, np.nan_to_num(X))
    med = np.median(d[ok[j] & (d > 0)])
    front = ok.copy()  # points behind a camera are left out by design
    np.logical_and.at(front, j, d > 0)
    absurd = np.zeros(block.n_tie, bool)
    np.logical_or.at(absurd, j, (d < 0.5 * med) | (d > 2.0 * med))
    n_absurd = int(np.sum(absurd & front))
    print(f"seed {seed}: {n_absurd} of {int(front.sum())} points in front of their cameras triangulated "
          f"outside 0.5-2 x the median depth {med:.1f} m")
    assert n_absurd > 0, f"seed {seed}: the recorded attitude triangulated every point plausibly"

    started, st = bundle.initial_state(block, sim.camera_nominal)
    d0, _ = _depths(started, st.X[: started.n_tie])
    ratio = d0 / np.median(d0)
    print(f"seed {seed}: {started.n_tie} points start, depth / median {ratio.min():.2f}-{ratio.max():.2f}")
    assert started.n_tie == int(front.sum()), (
        f"seed {seed}: {int(front.sum()) - started.n_tie} points dropped instead of started on the ground")
    assert 0.25 < ratio.min() and ratio.max() < 4.0, f"seed {seed}: starting depths {ratio.min()}-{ratio.max()}"


@pytest.mark.parametrize("seed", SEEDS)
def test_autopilot_attitude_block_recovers_the_camera(seed, monkeypatch):
    sim, cfg = _flight(seed)
    res = adjust(sim.images, sim.observations, sim.camera_nominal, cfg, sim.gcps, sim.gcp_observations)
    err = _errors(sim, res)
    print(f"seed {seed}: sigma0 {res.sigma0:.3f}, {res.iterations} iterations, IO error / sigma "
          f"{ {n: round(v, 2) for n, v in err.items()} }, check RMSE {np.round(res.check_rmse, 3)} m, "
          f"rho {np.round(res.rho, 2)}")
    assert res.converged, f"seed {seed}: not converged in {res.iterations} iterations"
    assert abs(res.sigma0 - 1.0) < 0.1, f"seed {seed}: sigma0 {res.sigma0:.3f}"
    assert max(abs(v) for v in err.values()) < 3.0, f"seed {seed}: IO off the truth: {err}"
    assert (res.rho < 2.5).all(), f"seed {seed}: check points off their prediction, rho {res.rho}"

    monkeypatch.setattr(bundle, "PLAUSIBLE_DEPTH", (0.0, np.inf))  # every point starts where triangulated
    off = adjust(sim.images, sim.observations, sim.camera_nominal, cfg, sim.gcps, sim.gcp_observations)
    print(f"seed {seed}, started where triangulated: sigma0 {off.sigma0:.2f}, IO error / sigma "
          f"{ {n: round(v, 1) for n, v in _errors(sim, off).items()} }")
    assert off.sigma0 > 5.0, f"seed {seed}: the triangulated start converged too (sigma0 {off.sigma0:.2f})"
