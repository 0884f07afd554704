"""Bundle adjustment on simulated flights: Jacobians, recovered IO within its sigma, honest sigmas, rho."""

from __future__ import annotations

import numpy as np
import pyarrow.compute as pc
import pytest
from tolerance import assert_within_sigma

from aerocal import tables
from aerocal.adjust import AdjustConfig, AdjustmentError, adjust
from aerocal.adjust.covariance import rho_band
from aerocal.adjust.projection import project, rotation_update
from aerocal.camera import PARAM_NAMES, Camera
from aerocal.simulate import simulate_flight

FREE = ("f", "cx", "cy", "k1", "k2", "p1", "p2")
N_SEEDS = 20


def _config(sim, **kw) -> AdjustConfig:
    s = sim.spec.sensors
    return AdjustConfig(
        gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
        attitude_sigma_deg=s.imu_sigma_deg,
        free=FREE,
        **kw,
    )


def _scene(rng: np.random.Generator, n_poses: int, n_points: int) -> tuple:
    """``(io, slopes, dT, R, C, X)``: a distorted thermal camera, its slopes, ``n_poses`` nadir poses at 850 m
    with their temperature offsets, and ``n_points`` ground points."""
    io = Camera(640, 480, 1670.0, 322.0, 238.0, -0.08, 0.12, 0.3, 2e-4, -1.5e-4, 0.7, 0.3).params()
    slopes = np.array([0.05, 0.02, -0.03])
    dT = rng.uniform(-3, 3, n_poses)
    R = rotation_update(np.repeat(np.diag([1.0, -1.0, -1.0])[None], n_poses, 0),
                        rng.normal(0, 0.05, (n_poses, 3)))
    C = rng.normal(0, 20, (n_poses, 3)) + [0, 0, 850]
    X = rng.normal(0, 60, (n_points, 3))
    return io, slopes, dT, R, C, X


def test_projection_jacobians_match_central_differences():
    rng = np.random.default_rng(11)
    M = 40
    io, slopes, dT, R, C, X = _scene(rng, M, M)
    pr = project(io, slopes, dT, R, C, X)
    h = 1e-6

    def num(fn):
        cols = []
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            cols.append((fn(e) - fn(-e)) / (2 * h))
        return np.stack(cols, axis=-1)

    dX = num(lambda e: project(io, slopes, dT, R, C, X + e, False).uv)
    dw = num(
        lambda e: project(io, slopes, dT, rotation_update(R, np.broadcast_to(e, (M, 3))), C, X, False).uv
    )
    dS = num(lambda e: project(io, slopes + e, dT, R, C, X, False).uv)
    assert np.allclose(pr.d_point, dX, atol=1e-4, rtol=1e-5), "seed 11: d(uv)/dX"
    assert np.allclose(pr.d_rot, dw, atol=1e-3, rtol=1e-5), "seed 11: d(uv)/dw"
    assert np.allclose(pr.d_slope, dS, atol=1e-5, rtol=1e-5), "seed 11: d(uv)/d(slope)"
    for k, name in enumerate(PARAM_NAMES):
        step = 1e-4 if name in ("f", "cx", "cy", "b1", "b2") else 1e-7
        e = np.zeros(10)
        e[k] = step
        d = (
            project(io + e, slopes, dT, R, C, X, False).uv - project(io - e, slopes, dT, R, C, X, False).uv
        ) / (2 * step)
        assert np.allclose(pr.d_io[:, :, k], d, atol=1e-4 * max(1.0, np.abs(d).max()), rtol=1e-5), name


def test_compiled_projection_of_a_blocks_observations_equals_the_batched_one():
    """The adjustment's compiled loop (poses and points read in place by index) gives the pixels, depths and
    pose/point Jacobians of :func:`project`, and with ``io_jacobians`` its IO and thermal-slope Jacobians too,
    distortion and thermal drift included."""
    from aerocal.adjust.projection import project_observations

    seed = 12
    rng = np.random.default_rng(seed)
    N, P, M = 7, 30, 90
    io, slopes, dT, R, C, X = _scene(rng, N, P)
    image, point = rng.integers(0, N, M).astype(np.int32), rng.integers(0, P, M)
    ref = project(io, slopes, dT[image], R[image], C[image], X[point])
    got = project_observations(io, slopes, dT, R, C, X, image, point)
    for name in ("uv", "d_point", "d_rot", "depth"):
        a, b = getattr(got, name), getattr(ref, name)
        assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max()), f"seed {seed}: {name}"
    assert got.d_io.shape == (M, 2, 0)
    full = project_observations(io, slopes, dT, R, C, X, image, point, io_jacobians=True)
    for name in ("uv", "d_point", "d_rot", "d_io", "d_slope"):
        a, b = getattr(full, name), getattr(ref, name)
        assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max()), f"seed {seed}: {name} (IO free)"
    plain = project_observations(io, slopes, dT, R, C, X, image, point, jacobians=False)
    assert np.array_equal(plain.uv, got.uv) and plain.d_point.shape == (M, 2, 0)
    # a point in the camera's own plane (depth 0) projects to a non-finite pixel, as numpy's division gives,
    # so that a Levenberg-Marquardt step that puts one there is rejected, not raised
    X[point[0]] = C[image[0]]
    edge = project_observations(io, slopes, dT, R, C, X, image, point)
    assert edge.depth[0] == 0.0 and not np.isfinite(edge.uv[0]).all(), f"seed {seed}"


@pytest.fixture(scope="module")
def conte_runs():
    """Self-calibration of conte-calibration (no effects) over N_SEEDS seeds."""
    runs = []
    for seed in range(N_SEEDS):
        sim = simulate_flight("conte-calibration", seed=seed)
        res = adjust(
            sim.images, sim.observations, sim.camera_nominal, _config(sim), sim.gcps, sim.gcp_observations
        )
        runs.append((seed, sim, res))
    return runs


def test_conte_calibration_recovers_io_within_three_sigma(conte_runs):
    seed, sim, res = conte_runs[0]
    true = sim.spec.camera_true
    for name in ("f", "cx", "cy"):
        err = getattr(res.camera, name) - getattr(true, name)
        # bounded: the calibration block determines f and the principal point to well under 0.2 % of f
        assert_within_sigma(err, res.sigmas[name], 3, 0.002 * true.f, f"seed {seed}: {name} (px)")
    assert res.converged and abs(res.sigma0 - 1.0) < 0.05, f"seed {seed}: sigma0 {res.sigma0:.3f}"
    # outputs a user opens: poses and points validate, residuals align with the observations table
    tables.validate(res.poses, "poses")
    tables.validate(res.points, "points")
    assert res.residuals.shape == (sim.observations.num_rows, 2)
    assert np.sqrt(np.nanmean(res.residuals**2)) < 0.5, (
        f"seed {seed}: reprojection RMS above the 0.5 px noise"
    )
    assert res.correlation.shape == (len(FREE), len(FREE))
    assert np.allclose(np.diag(res.correlation), 1.0)


def test_io_sigmas_are_honest_over_seeds(conte_runs):
    z = {n: [] for n in ("f", "cx", "cy")}
    for _, sim, res in conte_runs:
        for n in z:
            z[n].append((getattr(res.camera, n) - getattr(sim.spec.camera_true, n)) / res.sigmas[n])
    for n, v in z.items():
        sd = float(np.std(v, ddof=1))
        print(f"{n}: std of normalised errors over {len(v)} seeds = {sd:.3f}, mean {np.mean(v):+.3f}")
        assert 0.7 <= sd <= 1.4, (
            f"seeds 0..{N_SEEDS - 1}: {n} normalised errors have std {sd:.3f} ({np.round(v, 2)})"
        )


def test_check_point_rho_inside_chi_square_band(conte_runs):
    errs, var = [], []
    for _, _, res in conte_runs:
        good = np.isfinite(res.check_errors).all(axis=1)
        errs.append(res.check_errors[good])
        var.append(res.check_sigma[good] ** 2)
    e, v = np.vstack(errs), np.vstack(var)
    rho = np.sqrt(np.mean(e**2, axis=0) / np.mean(v, axis=0))
    lo, hi = rho_band(len(e))
    print(
        f"pooled rho over {len(e)} check points (seeds 0..{N_SEEDS - 1}): {np.round(rho, 3)}, "
        f"band [{lo:.3f}, {hi:.3f}]"
    )
    assert np.all((rho > lo) & (rho < hi)), f"seeds 0..{N_SEEDS - 1}: rho {rho} outside [{lo:.3f}, {hi:.3f}]"


def test_thermal_model_without_temperatures_names_the_column():
    sim = simulate_flight("conte-calibration", seed=1)
    images = sim.images.set_column(
        sim.images.schema.get_field_index("temperature_c"),
        "temperature_c",
        pc.if_else(pc.equal(sim.images.column("image_id"), 5), None, sim.images.column("temperature_c")),
    )
    with pytest.raises(AdjustmentError, match=r"image_id 5\): temperature_c is missing"):
        adjust(
            images,
            sim.observations,
            sim.camera_nominal,
            _config(sim, thermal=("f",)),
            sim.gcps,
            sim.gcp_observations,
        )


def test_no_datum_is_refused_with_the_fix():
    sim = simulate_flight("conte-calibration", seed=1)
    with pytest.raises(AdjustmentError, match="gnss_sigma_m=None"):
        adjust(
            sim.images, sim.observations, sim.camera_nominal, AdjustConfig(gnss_sigma_m=None, use_gcps=False)
        )


@pytest.mark.parametrize("free", [(), ("f", "cx", "cy", "k1")])
def test_structured_schur_complement_equals_the_sparse_products(free):
    """The reduced camera system formed from the observations' blocks (pairs of observations of a
    point) equals the one of general sparse products: matrix, right-hand side and point step."""
    import scipy.sparse as sp

    from aerocal.adjust import schur_kernels
    from aerocal.adjust.bundle import initial_state
    from aerocal.adjust.problem import build_block
    from aerocal.adjust.solver import BundleProblem, schur_complement

    default_threads = schur_kernels.REDUCE_THREADS
    seed = 31
    sim = simulate_flight("conte-calibration", seed=seed, max_images=20)
    cfg = AdjustConfig(free=free, gnss_sigma_m=(0.1, 0.1, 0.15), robust_loss="huber")
    blk = build_block(sim.images, sim.observations, sim.gcps, sim.gcp_observations, cfg)
    blk, st = initial_state(blk, sim.camera_nominal)
    prob = BundleProblem(blk, cfg, 0.0)
    _, _, _, r, Jc, Jp, Hpp = prob.residuals(st, jac=True)
    assert prob.blocks is not None and prob.blocks.n_global == len(free)
    for lam, threads in ((0.0, 1), (1e-3, 1), (0.0, 3), (1e-3, 2)):
        S0, rhs0, Hi0, Hcp0, gp0 = schur_complement(Jc, Jp, Hpp, r, lam)
        schur_kernels.REDUCE_THREADS = threads  # the compiled pass shared by threads sums to the same system
        try:
            S1, rhs1, Hi1, Hcp1, gp1 = schur_complement(Jc, Jp, Hpp, r, lam, prob.blocks)
        finally:
            schur_kernels.REDUCE_THREADS = default_threads
        assert np.allclose(Hi1, Hi0, rtol=1e-9, atol=0), f"seed {seed}: point inverses"
        assert sp.issparse(S0) and sp.issparse(S1)
        S0, S1 = S0.toarray(), S1.toarray()
        scale = np.abs(S0).max()
        assert np.abs(S1 - S0).max() < 1e-9 * scale, f"seed {seed}"
        assert np.allclose(S1, S1.T, rtol=0, atol=1e-9 * scale)
        assert np.allclose(rhs1, rhs0, rtol=1e-9, atol=1e-9 * np.abs(rhs0).max()), f"seed {seed}"
        dc = np.random.default_rng(seed).normal(size=S0.shape[0])
        back0 = np.asarray(Hcp0.T @ dc).ravel()
        assert np.allclose(Hcp1.T @ dc, back0, rtol=1e-9, atol=1e-9 * np.abs(back0).max()), f"seed {seed}"
        dp = np.random.default_rng(seed + 1).normal(size=Hcp0.shape[1])
        fwd0 = np.asarray(Hcp0 @ dp).ravel()
        assert np.allclose(Hcp1 @ dp, fwd0, rtol=1e-9, atol=1e-9 * np.abs(fwd0).max()), f"seed {seed}"
        assert sp.issparse(Hcp0)


def test_a_point_step_is_the_points_gauss_newton_step_with_the_cameras_held():
    """What a failed Levenberg-Marquardt step is retried with (:meth:`BundleProblem.point_step`): every point's
    Gauss-Newton step with the cameras and IO held, from the blocks of the linearisation, equals the one from the
    sparse point Jacobian, ``-(Jp^T Jp)^-1 Jp^T r``; and from points moved off their intersection it lowers the cost
    most of the way back."""
    import scipy.sparse.linalg as spla

    from aerocal.adjust.bundle import initial_state
    from aerocal.adjust.problem import build_block
    from aerocal.adjust.solver import BundleProblem

    seed = 33
    sim = simulate_flight("conte-calibration", seed=seed, max_images=12)
    cfg = AdjustConfig(free=(), gnss_sigma_m=(0.1, 0.1, 0.15))
    blk, st = initial_state(build_block(sim.images, sim.observations, sim.gcps, sim.gcp_observations, cfg),
                            sim.spec.camera_true)
    prob = BundleProblem(blk, cfg, 0.0)
    settled = prob.residuals(st, jac=True, sparse=False)
    st.X += prob.point_step(settled[6], 0.0)  # the points at their intersection with the cameras held
    cost0 = prob.residuals(st, jac=False)[0]
    moved = st.copy()
    moved.X[: blk.n_tie] += np.random.default_rng(seed).normal(0.0, 0.3, (blk.n_tie, 3))
    cost1, _, _, r, _, Jp, Hpp = prob.residuals(moved, jac=True)
    step = prob.point_step(Hpp, 0.0)
    direct = spla.spsolve((Jp.T @ Jp).tocsc(), -(Jp.T @ r))
    assert np.allclose(step.ravel(), direct, rtol=1e-6, atol=1e-9), f"seed {seed}"
    moved.X += step
    cost2 = prob.residuals(moved, jac=False)[0]
    print(f"seed {seed}: cost {cost0:.1f} intersected, {cost1:.1f} moved 0.3 m, {cost2:.1f} after one point step")
    assert cost2 - cost0 < 0.01 * (cost1 - cost0), f"seed {seed}: {cost0}, {cost1}, {cost2}"


def test_tie_sigma_estimated_from_the_block_keeps_check_points_honest():
    """Matched tie points are more precise than the matcher's a-priori 0.5 px (SIFT on rendered frames:
    0.19 px). Left at 0.5 px, sigma0 falls to ~0.3 and shrinks every predicted sigma, the GCP measurements'
    included, so check points miss their prediction; estimated from the robust pass, rho stays in band."""
    import dataclasses

    from aerocal.adjust import scale_tie_sigma
    from aerocal.simulate.presets import PRESETS

    spec = PRESETS["conte-calibration"]
    spec = dataclasses.replace(spec, sensors=dataclasses.replace(spec.sensors, tie_sigma_px=0.15, gcp_sigma_px=1.0))
    pooled = {True: ([], []), False: ([], [])}
    scales = []
    for seed in range(6):
        sim = simulate_flight(spec, seed=seed)
        obs = scale_tie_sigma(sim.observations, 0.5 / 0.15)  # what the matcher writes: 0.5 px
        for estimate in (True, False):
            cfg = AdjustConfig(free=(), robust_loss="huber", estimate_tie_sigma=estimate)
            res = adjust(sim.images, obs, sim.spec.camera_true, cfg, sim.gcps, sim.gcp_observations)
            good = np.isfinite(res.check_errors).all(axis=1)
            pooled[estimate][0].append(res.check_errors[good])
            pooled[estimate][1].append(res.check_sigma[good] ** 2)
            if estimate:
                scales.append(res.tie_sigma_scale)
                assert 0.7 < res.sigma0 < 1.5, f"seed {seed}: sigma0 {res.sigma0:.3f} with the estimated tie sigma"
    rho = {k: np.sqrt(np.mean(np.vstack(e) ** 2, axis=0) / np.mean(np.vstack(v), axis=0))
           for k, (e, v) in pooled.items()}
    lo, hi = rho_band(len(np.vstack(pooled[True][0])))
    print(f"tie sigma scale {np.round(scales, 3)}; rho estimated {np.round(rho[True], 3)}, "
          f"a priori {np.round(rho[False], 3)}, band [{lo:.3f}, {hi:.3f}]")
    assert np.all(np.abs(np.array(scales) - 0.3) < 0.03), f"seeds 0..5: tie sigma scales {scales}, truth 0.3"
    assert np.all((rho[True] > lo) & (rho[True] < hi)), f"seeds 0..5: rho {rho[True]} outside [{lo:.3f}, {hi:.3f}]"
    assert rho[False][2] > hi, f"seeds 0..5: without the estimate rho Up {rho[False][2]:.3f} should exceed {hi:.3f}"


def test_a_warm_start_intersects_the_tie_points_the_earlier_points_table_lacks():
    """A track missing from an earlier adjustment's points table is intersected from the adjusted poses, not
    left where consumer-grade GNSS/IMU records put it (real seneca: 1251 such tracks started the diagnosis
    baseline at sigma0 87 and left 2.5 % of its observations beyond the 99.9 % point)."""
    import pyarrow as pa

    from aerocal.adjust.bundle import initial_state, warm_start
    from aerocal.adjust.problem import build_block
    from aerocal.adjust.solver import BundleProblem

    seed = 71
    rng = np.random.default_rng(seed)
    sim = simulate_flight("conte-calibration", seed=seed)
    images = sim.images
    for k in ("gnss_x", "gnss_y", "gnss_z"):  # consumer GNSS: metres off
        col = images.column(k).to_numpy() + rng.normal(0.0, 3.0, images.num_rows)
        images = images.set_column(images.column_names.index(k), k, pa.array(col))
    cfg = AdjustConfig(gnss_sigma_m=(3.0, 3.0, 3.0), attitude_sigma_deg=sim.spec.sensors.imu_sigma_deg, free=())
    res = adjust(images, sim.observations, sim.spec.camera_true, cfg)
    points = res.points
    drop = rng.random(points.num_rows) < 0.1  # a tenth of the tracks not in the table
    partial = points.filter(pa.array(~drop))
    block, start = initial_state(build_block(images, sim.observations, config=cfg), sim.spec.camera_true)
    full = warm_start(block, start, res.poses, points)
    warm = warm_start(block, start, res.poses, partial)
    lost = np.isin(block.track_ids, points.column("track_id").to_numpy()[drop])
    miss = np.linalg.norm(warm.X[: block.n_tie][lost] - full.X[: block.n_tie][lost], axis=1)
    assert lost.sum() > 10 and np.median(miss) < 0.05 and np.max(miss) < 1.0, f"seed {seed}: {np.sort(miss)[-5:]}"
    problem = BundleProblem(block, cfg, 0.0)
    assert problem.residuals(warm, jac=False)[0] < 1.05 * problem.residuals(full, jac=False)[0], f"seed {seed}"


def test_factorise_solves_by_cholesky_and_falls_back_to_superlu(monkeypatch):
    """The reduced camera system's factor: MKL PARDISO's Cholesky (installed with aerocal on x86-64 Linux, so
    the fast path is what runs here), one and several right-hand sides; without MKL, SuperLU in the images'
    nested-dissection order; an indefinite system goes to SuperLU, an exactly singular one gives no factor."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from aerocal.adjust import cholesky
    from aerocal.adjust.solver import factorise

    seed = 12
    rng = np.random.default_rng(seed)
    n_images = 99
    n = 2 + 6 * n_images  # a reduced camera system's layout: 2 global columns, then 6 per image
    A = sp.random(n, n, density=0.01, random_state=seed) + sp.identity(n)
    S = (A @ A.T + 0.1 * sp.identity(n)).tocsc()
    B = rng.normal(size=(n, 3))
    want = spla.spsolve(S, B)
    assert cholesky.available(), "MKL PARDISO did not load: is the 'mkl' package installed?"
    f, d = factorise(S, n_global=2)
    assert isinstance(f, cholesky.PardisoCholesky) and f.factor_entries > n, f"seed {seed}"
    assert np.allclose(f.solve(B / d[:, None]) / d[:, None], want, rtol=1e-9, atol=1e-12), f"seed {seed}"
    assert np.allclose(f.solve(B[:, 0] / d) / d, want[:, 0], rtol=1e-9, atol=1e-12), f"seed {seed}: one column"
    assert f.solve(np.zeros((n, 0))).shape == (n, 0)  # no check points: no columns
    # the next step's system (same pattern, other numbers) factorised with the first one's analysis
    S2 = (S + sp.diags(rng.uniform(0.1, 2.0, n))).tocsc()  # S holds its diagonal: the same pattern
    f2, d2 = factorise(S2, n_global=2, earlier=f)
    assert f2 is f, f"seed {seed}: the analysis of the same pattern is kept"
    assert np.allclose(f2.solve(B / d2[:, None]) / d2[:, None], spla.spsolve(S2, B), rtol=1e-9, atol=1e-12)
    corner = sp.csc_matrix(([0.01, 0.01], ([0, n - 1], [n - 1, 0])), shape=(n, n))
    other = (S + corner).tocsc()  # another pattern: a new analysis
    assert not f.refactor(other)
    f3, d3 = factorise(other, earlier=f)
    assert f3 is not f and np.allclose(f3.solve(B / d3[:, None]) / d3[:, None], spla.spsolve(other, B),
                                       rtol=1e-9, atol=1e-12), f"seed {seed}"
    with monkeypatch.context() as m:
        m.setattr(cholesky, "available", lambda: False)
        lu, d = factorise(S, n_global=2)
        assert not isinstance(lu, cholesky.PardisoCholesky), f"seed {seed}"
        assert np.allclose(lu.solve(B / d[:, None]) / d[:, None], want, rtol=1e-9, atol=1e-12), f"seed {seed}"
    indefinite = (S - 2.0 * sp.diags(np.where(np.arange(n) == 5, S.diagonal(), 0.0))).tocsc()
    with pytest.raises(cholesky.NotPositiveDefinite, match="not positive definite"):
        cholesky.PardisoCholesky(indefinite)
    lu, d = factorise(indefinite)
    x = lu.solve(B[:, 0] / d) / d
    assert np.allclose(indefinite @ x, B[:, 0], rtol=1e-8, atol=1e-9), f"seed {seed}: indefinite by SuperLU"
    singular = sp.csc_matrix(np.ones((4, 4)))
    assert factorise(singular)[0] is None


def test_reduced_solver_reuses_its_factor_and_factorises_again_when_the_system_moved_away():
    """Steps of one adjustment: the second system (a step's change of the linearisation) is solved by
    conjugate gradients on the first one's factor, to the solver's tolerance; a system far from the kept factor
    is factorised again; a non-finite right-hand side is refused with the unknowns named."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from aerocal.adjust.solver import REUSE_TOLERANCE, ReducedSolver

    seed = 11
    rng = np.random.default_rng(seed)
    n = 600
    A = sp.random(n, n, density=0.01, random_state=seed) + sp.identity(n)
    S1 = (A @ A.T + 0.1 * sp.identity(n)).tocsc()
    S2 = (S1 + 1e-3 * sp.diags(rng.uniform(0, 1, n)) @ S1 @ sp.diags(rng.uniform(0, 1, n))).tocsc()
    S2 = (0.5 * (S2 + S2.T)).tocsc()
    S3 = (S1 + sp.diags(rng.uniform(0, 50, n))).tocsc()
    b = rng.normal(size=n)
    solver = ReducedSolver(reuse=True)
    x1 = solver.solve(S1, b)
    assert solver.factorisations == 1 and np.allclose(x1, spla.spsolve(S1, b), rtol=1e-9, atol=1e-12), f"seed {seed}"
    x2 = solver.solve(S2, b)
    want = spla.spsolve(S2, b)
    energy = np.sqrt((x2 - want) @ (S2 @ (x2 - want)) / (want @ b))
    assert solver.factorisations == 1 and solver.cg_iterations, f"seed {seed}: the kept factor was not reused"
    assert energy < 10 * REUSE_TOLERANCE, f"seed {seed}: relative energy error {energy:g}"
    x3 = solver.solve(S3, b)
    assert solver.factorisations == 2, f"seed {seed}: a system far from the factor was not factorised again"
    assert np.allclose(x3, spla.spsolve(S3, b), rtol=1e-9, atol=1e-12), f"seed {seed}"
    bad = b.copy()
    bad[7] = np.nan
    with pytest.raises(AdjustmentError, match=r"unknowns \[7\]"):
        solver.solve(S1, bad)


def test_residuals_and_points_line_up_with_the_input_tables_whatever_the_internal_numbering():
    """The block numbers its tie points along the images' neighbourhood, not by track id: the points table
    still lists the tracks by id, and each observation's residual is its own (the adjusted camera's projection
    of its track's adjusted point, less the measurement of that row)."""
    from aerocal.adjust import adjust_fixed_io
    from aerocal.geometry import matrix_from_quat_wxyz

    seed = 3
    sim = simulate_flight("conte-city", seed=seed, max_images=40)
    s = sim.spec.sensors
    cfg = AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                       attitude_sigma_deg=s.imu_sigma_deg)
    res = adjust_fixed_io(sim.images, sim.observations, sim.spec.camera_true, cfg, sim.gcps, sim.gcp_observations)
    tracks = res.points.column("track_id").to_numpy()
    assert np.array_equal(tracks, np.unique(sim.observations.column("track_id").to_numpy())), f"seed {seed}"
    pose_id = res.poses.column("image_id").to_numpy()
    R = matrix_from_quat_wxyz(np.column_stack([res.poses.column(c).to_numpy() for c in ("qw", "qx", "qy", "qz")]))
    C = np.column_stack([res.poses.column(c).to_numpy() for c in ("X", "Y", "Z")])
    X = np.column_stack([res.points.column(c).to_numpy() for c in ("X", "Y", "Z")])
    obs = sim.observations
    i = np.searchsorted(pose_id, obs.column("image_id").to_numpy())
    assert np.array_equal(pose_id[i], obs.column("image_id").to_numpy())
    j = np.searchsorted(tracks, obs.column("track_id").to_numpy())
    origin = C.mean(axis=0)  # a local origin keeps the projection's precision
    pr = project(res.camera.params(), np.zeros(3), np.zeros(len(i)), R.reshape(-1, 3, 3)[i], C[i] - origin,
                 X[j] - origin, jacobians=False)
    measured = np.column_stack([obs.column("x").to_numpy(), obs.column("y").to_numpy()])
    ok = np.isfinite(res.residuals).all(axis=1)
    assert ok.mean() > 0.95, f"seed {seed}"
    gap = np.abs(pr.uv[ok] - measured[ok] - res.residuals[ok]).max()
    assert gap < 1e-6, f"seed {seed}: residuals differ from the tables' own projection by {gap:g} px"


def test_counting_order_and_unique_ids_equal_numpys():
    """The block's stable orders by counting and its track numbering by a presence mask give exactly what
    numpy's stable argsort and np.unique give, for compact and for scattered ids."""
    from aerocal.adjust.problem import unique_ids
    from aerocal.adjust.schur_kernels import stable_order

    seed = 21
    rng = np.random.default_rng(seed)
    for n_keys in (1, 7, 5000):
        keys = rng.integers(0, n_keys, 20_000)
        assert np.array_equal(stable_order(keys, n_keys), np.argsort(keys, kind="stable")), f"seed {seed}"
    for ids in (rng.integers(-50, 9000, 20_000), rng.integers(0, 2**40, 20_000), np.zeros(0, np.int64)):
        got, want = unique_ids(ids), np.unique(ids, return_inverse=True)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1].ravel()), f"seed {seed}"


def test_a_point_a_step_brings_next_to_a_camera_is_put_back_from_the_candidates_own_depths():
    """The depths of the candidate's linearisation find the tie points a step moved next to a camera that
    sees them (below a fraction of the start's median depth), as projecting them again does; those points go
    back to where they were, the others keep their step."""
    from aerocal.adjust.bundle import initial_state
    from aerocal.adjust.problem import build_block
    from aerocal.adjust.solver import MIN_DEPTH_FRACTION, BundleProblem

    seed = 32
    sim = simulate_flight("conte-calibration", seed=seed, max_images=12)
    cfg = AdjustConfig(gnss_sigma_m=(0.1, 0.1, 0.15))
    blk = build_block(sim.images, sim.observations, sim.gcps, sim.gcp_observations, cfg)
    blk, st = initial_state(blk, sim.camera_nominal)
    prob = BundleProblem(blk, cfg, 0.0)
    prob.residuals(st, jac=True, sparse=False)
    view = prob.point_view()
    prob.set_depth_floor(prob.last_depth[view.is_tie])
    median = float(np.median(prob.last_depth[view.is_tie]))
    assert prob.depth_floor == pytest.approx(MIN_DEPTH_FRACTION * median), f"seed {seed}"
    rng = np.random.default_rng(seed)
    step = st.copy()
    step.X = st.X + rng.normal(0, 0.05, st.X.shape)  # every point moves a little
    m = int(np.flatnonzero(view.is_tie)[0])
    i, p = int(view.image[m]), int(view.point[m])
    step.X[p] = st.C[i] + 0.5 * prob.depth_floor * st.R[i][2]  # and one to half the floor in front of camera i
    a, b = step.copy(), step.copy()
    prob.residuals(a, jac=True, sparse=False)
    held = prob.hold_close_points(st, a, prob.last_depth)
    assert held == prob.hold_close_points(st, b) == 1, f"seed {seed}"
    assert np.array_equal(a.X, b.X) and np.array_equal(a.X[p], st.X[p]), f"seed {seed}"
    others = np.arange(len(st.X)) != p
    assert np.array_equal(a.X[others], step.X[others]), f"seed {seed}"


def test_blocks_formed_in_the_projection_equal_the_separate_pass():
    """Without a robust loss the rows' scale is known before the residuals, so the projection forms the scaled
    image and point blocks and the points' J^T J itself; with one (weights all 1 here: a huge Huber threshold)
    a separate pass scales them once the residuals give the weights. Both give the same blocks."""
    from aerocal.adjust.bundle import initial_state
    from aerocal.adjust.problem import build_block
    from aerocal.adjust.solver import BundleProblem

    seed = 33
    sim = simulate_flight("conte-calibration", seed=seed, max_images=12)
    got = {}
    for loss in ("none", "huber"):
        cfg = AdjustConfig(gnss_sigma_m=(0.1, 0.1, 0.15), robust_loss=loss, robust_scale=1e9)
        blk = build_block(sim.images, sim.observations, sim.gcps, sim.gcp_observations, cfg)
        blk, st = initial_state(blk, sim.camera_nominal)
        prob = BundleProblem(blk, cfg, 0.0)
        Hpp = prob.residuals(st, jac=True, sparse=False)[6]
        got[loss] = (prob.blocks.Ji.copy(), prob.blocks.Jx.copy(), Hpp)
    for a, b, name in zip(got["none"], got["huber"], ("Ji", "Jx", "Hpp"), strict=True):
        assert np.allclose(a, b, rtol=1e-12, atol=1e-12 * np.abs(b).max()), f"seed {seed}: {name}"
