"""Partitioned adjustment (:mod:`aerocal.adjust.partition`): sub-blocks that eliminate their own points and sum
their shares of the reduced camera system, in this process and as actors on a real Dask cluster, give the single
adjustment's solution and covariances; the pipeline's adjust step partitions a block past its threshold and the
flight's products stay the same."""

from __future__ import annotations

import numpy as np
import pytest

from aerocal.adjust import AdjustConfig
from aerocal.adjust.bundle import initial_state
from aerocal.adjust.covariance import triangulate_check_points
from aerocal.adjust.partition import plan_partition, solve_partitioned
from aerocal.adjust.problem import build_block
from aerocal.adjust.projection import project
from aerocal.adjust.solver import BundleProblem, solve
from aerocal.simulate import simulate_flight

SEED = 5


def _block(preset: str, n: int, free: tuple[str, ...]):
    sim = simulate_flight(preset, seed=SEED, max_images=n)
    cfg = AdjustConfig(free=free, gnss_sigma_m=(0.1, 0.1, 0.15), attitude_sigma_deg=(0.5, 0.5, 1.0))
    blk = build_block(sim.images, sim.observations, sim.gcps, sim.gcp_observations, cfg)
    blk, st = initial_state(blk, sim.camera_nominal)
    return blk, st, cfg


def _assert_same(blk, a, b, what: str) -> None:
    """Same poses, points, IO, sigma0, dof and check-point covariances (to rounding)."""
    assert b.dof == a.dof and b.iterations == a.iterations and b.converged == a.converged, what
    assert abs(b.sigma0 - a.sigma0) < 1e-9 * a.sigma0, f"{what}: sigma0 {b.sigma0} vs {a.sigma0}"
    for name in ("C", "X", "io"):
        d = np.abs(getattr(a.state, name) - getattr(b.state, name)).max()
        assert d < 1e-8, f"{what}: {name} differs by {d:g}"
    assert np.abs(np.einsum("nij,nkj->nik", a.state.R, b.state.R) - np.eye(3)).max() < 1e-10, what
    ca, cb = triangulate_check_points(blk, a), triangulate_check_points(blk, b)
    ok = np.isfinite(ca.xyz).all(axis=1)
    assert ok.sum() >= 5, what
    assert np.allclose(cb.cov[ok], ca.cov[ok], rtol=1e-7, atol=1e-12), f"{what}: check-point covariances differ"
    ng = a.layout.n_global
    if ng:
        assert np.allclose(b.cov_camera[:ng, :ng], a.cov_camera[:ng, :ng], rtol=1e-7, atol=0), f"{what}: IO cov"


@pytest.mark.parametrize("n_parts", [2, 3])
def test_a_partitioned_fixed_io_block_gives_the_single_adjustment(n_parts):
    blk, st, cfg = _block("conte-city", 60, ())
    plan = plan_partition(blk, st.C[:, :2], n_parts)
    # every point (and every observation) in exactly one sub-block; boundary images are those in more than one
    assert sorted(np.concatenate(plan.points).tolist()) == list(range(blk.n_points))
    assert sorted(np.concatenate(plan.observations).tolist()) == list(range(len(blk.obs_image)))
    member = np.bincount(np.concatenate(plan.images), minlength=blk.n_images)
    assert set(plan.boundary.tolist()) == set(np.flatnonzero(member > 1).tolist()) and len(plan.boundary) > 0
    assert sum(o.sum() for o in plan.owned) == blk.n_images, "each image's priors are counted once"
    a = solve(BundleProblem(blk, cfg, 0.0), st.copy())
    b = solve_partitioned(BundleProblem(blk, cfg, 0.0), st.copy(), n_parts)
    _assert_same(blk, a, b, f"seed {SEED}, {n_parts} sub-blocks")


def test_a_partitioned_self_calibration_gives_the_same_io_and_sigmas():
    blk, st, cfg = _block("conte-calibration", 44, ("f", "cx", "cy", "k1", "k2", "p1", "p2"))
    a = solve(BundleProblem(blk, cfg, 0.0), st.copy())
    b = solve_partitioned(BundleProblem(blk, cfg, 0.0), st.copy(), 3)
    _assert_same(blk, a, b, f"seed {SEED}, IO free")


def test_sub_blocks_as_actors_on_a_dask_cluster_give_the_single_adjustment():
    from aerocal.matching.cluster import local_client

    blk, st, cfg = _block("conte-city", 60, ())
    a = solve(BundleProblem(blk, cfg, 0.0), st.copy())
    with local_client(n_workers=2) as client:
        b = solve_partitioned(BundleProblem(blk, cfg, 0.0), st.copy(), 2, client)
        assert len(client.scheduler_info()["workers"]) == 2
        _assert_same(blk, a, b, f"seed {SEED}, Dask actors")


def test_the_pipeline_adjusts_a_block_past_its_threshold_in_sub_blocks_with_the_same_products(tmp_path):
    """``process`` with ``BlockStepConfig.partition_min_images`` below the flight's size: the adjust step runs on
    a local Dask cluster in sub-blocks, says so in its summary, and the poses and check points are the ones
    of the single adjustment."""
    from aerocal.pipeline import LocalRunner, MemoryCertificates, process
    from aerocal.pipeline.config import BlockStepConfig, ProcessConfig
    from aerocal.simulate import write_flight

    sim = simulate_flight("conte-city", seed=SEED, max_images=40)
    folder = write_flight(sim, tmp_path / "city", mode="observations")
    runner, store = LocalRunner(), MemoryCertificates()
    single = process(folder, certificate="none", runner=runner, certificates=store)
    cut = ProcessConfig(block=BlockStepConfig(partition_min_images=30, partition_max_images=15))
    parted = process(folder, cut, certificate="auto", runner=runner, certificates=store)
    assert not parted.steps["adjust"].reused
    adj_a, adj_b = single.json("adjustment"), parted.json("adjustment")
    assert adj_a["partitioned"] is None
    info = adj_b["partitioned"]
    assert info is not None and info["images"] == 40 and info["sub_blocks"] == 3 and info["boundary_images"] > 0
    a, b = single.table("poses"), parted.table("poses")
    for col in ("X", "Y", "Z"):
        np.testing.assert_allclose(b.column(col).to_numpy(), a.column(col).to_numpy(), rtol=0, atol=1e-6)
    for key, tol in (("check_errors_m", {"atol": 1e-6}), ("check_sigma_m", {"rtol": 1e-6})):
        va, vb = (np.array(adj[key], dtype=float) for adj in (adj_a, adj_b))  # null: a check point not seen
        assert np.isfinite(va).sum() >= 10, key
        np.testing.assert_allclose(vb, va, **tol, err_msg=key)


def test_check_point_covariance_equals_the_propagation_through_the_whole_camera_covariance():
    """The check points' camera term from three solves each equals ``G B Cov(cams) B^T G^T`` formed from
    the dense inverse of the reduced camera system, IO free (global columns) and fixed."""
    for preset, n, free in (("conte-calibration", 44, ("f", "cx", "cy", "k1", "k2", "p1", "p2")),
                            ("conte-city", 60, ())):
        blk, st, cfg = _block(preset, n, free)
        sol = solve(BundleProblem(blk, cfg, 0.0), st.copy())
        cp = triangulate_check_points(blk, sol)
        ok = np.flatnonzero(np.isfinite(cp.xyz).all(axis=1))
        assert len(ok) >= 3, f"{preset}: seed {SEED}"
        dense = sol.cov_camera.dense()
        lay, s = sol.layout, sol.state
        for kk in ok:
            sel = np.flatnonzero(blk.check_point == kk)
            i = blk.check_image[sel]
            pr = project(s.io, s.slopes, np.zeros(len(sel)), s.R[i], s.C[i], np.repeat(cp.xyz[kk][None], len(sel), 0))
            sig = blk.check_sigma_px[sel][:, None, None]
            A = (pr.d_point / sig).reshape(-1, 3)
            ng = lay.n_global
            cols = np.concatenate([np.arange(ng), lay.image_cols(i).ravel()])
            B = np.zeros((2 * len(sel), len(cols)))
            if ng:
                B[:, :ng] = (np.concatenate([pr.d_io[:, :, lay.io_free], pr.d_slope[:, :, lay.slope_free]], 2)
                             / sig).reshape(-1, ng)
            for m in range(len(sel)):
                Bm = np.concatenate([pr.d_rot[m], -pr.d_point[m]], 1) / sig[m]
                B[2 * m:2 * m + 2, ng + 6 * m:ng + 6 * m + 6] = Bm
            Ninv = np.linalg.inv(A.T @ A)
            GB = Ninv @ A.T @ B
            want = sol.sigma0**2 * (Ninv + GB @ dense[np.ix_(cols, cols)] @ GB.T)
            assert np.allclose(cp.cov[kk], want, rtol=1e-8, atol=1e-14), f"{preset}: check point {kk}, seed {SEED}"
