"""The baseline block and its linearisation, on the bundle adjustment of :mod:`aerocal.adjust`.

The diagnosis reasons about the adjusted block's residuals and Jacobian: which residuals would move if
an effect's parameter moved (its columns, :mod:`aerocal.diagnose.hypotheses`), and how much of that the
block's own unknowns (poses, points, interior orientation) already absorb. Eliminating the points
(Schur complement) once for the camera columns *and* every hypothesis's columns lets all hypotheses be
scored against one reduced system.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import scipy.sparse as sp

from aerocal.adjust.bundle import initial_state, warm_start
from aerocal.adjust.problem import AdjustConfig, Block, build_block
from aerocal.adjust.projection import project
from aerocal.adjust.solver import BundleProblem, Solution, State, factorise, inverse_spd, schur_complement, solve
from aerocal.adjust.triangulate import pixels_to_rays, triangulate_linear
from aerocal.camera import Camera


@dataclass
class Covariates:
    """Per-image metadata the hypotheses depend on (aligned with ``Block.image_ids``)."""

    time_s: np.ndarray  # seconds after the first image
    strip: np.ndarray  # strip number (-1 = none)


@dataclass
class Baseline:
    """An adjusted block: the measurements, the model they were fitted with, and the solution."""

    block: Block
    covariates: Covariates
    config: AdjustConfig
    solution: Solution
    template: Camera  # image size and pixel pitch; IO values come from the solution

    @property
    def state(self) -> State:
        return self.solution.state

    @property
    def camera(self) -> Camera:
        return self.template.with_params(self.solution.state.io)


@dataclass
class Linear:
    """Whitened residuals and Jacobian of a block at a state, and what the signatures need."""

    r: np.ndarray
    Jc: sp.csr_matrix  # camera-side columns (free IO + 6 per image)
    Jp: sp.csr_matrix  # point columns
    Hpp: np.ndarray  # (P, 3, 3) point blocks of J^T J
    groups: dict[str, slice]
    xn: np.ndarray  # (M, 2) undistorted normalised coordinates of each image measurement
    pc: np.ndarray  # (M, 3) measured point in its camera frame
    duv_dpc: np.ndarray  # (M, 2, 3) d(pixels)/d(camera-frame point)

    @property
    def chi2(self) -> float:
        return float(self.r @ self.r)


def image_times_s(images: pa.Table) -> np.ndarray | None:
    """Seconds after the first image of each row of ``images`` (None when a time is missing)."""
    t = images.column("time").to_numpy(zero_copy_only=False)
    if not len(t) or np.isnat(t).any():
        return None
    return (t - t.min()).astype("timedelta64[us]").astype(float) / 1e6


def image_strips(images: pa.Table) -> np.ndarray:
    """Strip number of each row of ``images`` (-1 = none)."""
    return np.array([-1 if v is None else v for v in images.column("strip").to_pylist()], dtype=np.int64)


def covariates_from_images(images: pa.Table, block: Block) -> Covariates:
    ids = images.column("image_id").to_numpy()
    pos = {int(v): k for k, v in enumerate(ids)}
    rows = np.array([pos[int(v)] for v in block.image_ids])
    secs = image_times_s(images)
    if secs is None:
        secs = np.arange(len(ids), dtype=float)  # no times: assume the table is in acquisition order
    return Covariates(time_s=secs[rows], strip=image_strips(images)[rows])


def fit_baseline(images: pa.Table, observations: pa.Table, camera: Camera, config: AdjustConfig,
                 gcps: pa.Table | None = None, gcp_observations: pa.Table | None = None,
                 start: tuple[pa.Table, pa.Table] | None = None) -> Baseline:
    """Adjust the block with ``config`` (the model whose shortcomings the diagnosis looks for).

    ``start``: the (poses, points) tables of an adjustment of the same block to start from instead of the
    recorded GNSS/IMU: from consumer-grade records a block can stop unconverged at the iteration cap where its
    block adjustment converged (real seneca: ``benchmarks/history/engine_measurements.md``).
    """
    block0 = build_block(images, observations, gcps, gcp_observations, config)
    block, state = initial_state(block0, camera)
    if start is not None:
        state = warm_start(block, state, *start)
    sol = solve(BundleProblem(block, config, 0.0), state)
    return Baseline(block, covariates_from_images(images, block), config, sol, camera)


#: 99.9 % point of chi-square with 2 dof: a tie observation beyond it (times the block's robust scale) is in the tail
#: of its residuals (:mod:`aerocal.diagnose.twin`)
TAIL_CHI2 = 13.8
#: median of chi-square with 2 dof (2 ln 2): the robust scale of a block's normalised squared tie residuals
CHI2_2_MEDIAN = 1.386


def refit(base: Baseline, block: Block, covariance: bool = True) -> Baseline:
    """Re-adjust corrected measurements of the same block, starting from the previous solution (without the
    camera covariance where ``covariance`` is False: :func:`~aerocal.adjust.solver.solve`)."""
    sol = solve(BundleProblem(block, base.config, 0.0), base.state.copy(), covariance)
    return dataclasses.replace(base, block=block, solution=sol)


def linearise(base: Baseline, state: State | None = None) -> Linear:
    state = state or base.state
    problem = BundleProblem(base.block, base.config, 0.0)
    _, _, _, r, Jc, Jp, Hpp = problem.residuals(state, jac=True)
    b = base.block
    xn, pc, duv_dpc = observation_geometry(b, state)
    M, N, G = len(b.obs_image), b.n_images, len(b.control_ids)
    groups = {"image": slice(0, 2 * M)}
    row = 2 * M
    if base.config.gnss_sigma_m is not None:
        groups["gnss"] = slice(row, row + 3 * N)
        row += 3 * N
    if base.config.attitude_sigma_deg is not None:
        groups["imu"] = slice(row, row + 3 * N)
        row += 3 * N
    if G:
        groups["control"] = slice(row, row + 3 * G)
    return Linear(r, Jc, Jp, Hpp, groups, xn, pc, duv_dpc)


def observation_geometry(block: Block, state: State) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the signatures of the hypotheses need of every image measurement of ``block`` at ``state``: the
    undistorted normalised coordinates ``xn`` (M, 2) and camera-frame position ``pc`` (M, 3, metres) of its
    adjusted point, and d(pixels)/d(camera-frame point) ``duv_dpc`` (M, 2, 3)."""
    i, j = block.obs_image, block.obs_point
    return point_geometry(state.io, state.slopes, state.R, state.C, i, state.X[j])


def point_geometry(io: np.ndarray, slopes: np.ndarray, R: np.ndarray, C: np.ndarray, image: np.ndarray,
                   X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`observation_geometry` of points ``X`` (M, 3, local metres) seen in images ``image`` (indices into
    ``R`` and ``C``)."""
    pr = project(io, slopes, np.zeros(len(image)), R[image], C[image], X)
    pc = np.einsum("mab,mb->ma", R[image], X - C[image])
    duv_dpc = np.einsum("mab,mcb->mac", pr.d_point, R[image])  # d_point = duv_dpc R
    return pc[:, :2] / pc[:, 2:], pc, duv_dpc


@dataclass
class Reduced:
    """Reduced normal equations (points eliminated) of [camera | extra] columns at the solution."""

    S: sp.csc_matrix  # sparse: images couple only with the images they share tie points with
    g: np.ndarray  # reduced gradient J^T r (after elimination)
    n_camera: int


def reduce(lin: Linear, extra: np.ndarray) -> Reduced:
    """The reduced normal equations of the block's camera columns and ``extra`` (dense, one column per hypothesis
    parameter or random draw, rows aligned with ``lin.r``), the points eliminated.

    The camera part is the sparse Schur complement; the extra columns' parts are formed densely from
    ``Jp^T E`` and the point blocks' inverses. Appending hundreds of dense columns to the sparse Jacobian (as
    this did before) made every sparse product of the elimination dense in those rows, a large share of a whole
    `process` run of a conte-calibration flight (``benchmarks/history/engine_measurements.md``)."""
    S_cc, rhs_c, Hpp_inv, Hcp, gp = schur_complement(lin.Jc, lin.Jp, lin.Hpp, lin.r, 0.0)
    nc = lin.Jc.shape[1]
    g_c = -np.asarray(rhs_c).ravel()
    ne = extra.shape[1]
    if not ne:
        return Reduced(S_cc.tocsc(), g_c, nc)
    E = np.asarray(extra, dtype=float)
    P = len(lin.Hpp)
    JpE = np.asarray(lin.Jp.T @ E).reshape(P, 3, ne)
    HiJpE = np.einsum("pij,pjk->pik", Hpp_inv, JpE).reshape(3 * P, ne)
    JpE = JpE.reshape(3 * P, ne)
    S_ce = np.asarray(lin.Jc.T @ E) - np.asarray(Hcp @ HiJpE)
    S_ee = E.T @ E - JpE.T @ HiJpE
    g_e = E.T @ lin.r - HiJpE.T @ gp
    S = sp.bmat([[S_cc, sp.csr_matrix(S_ce)], [sp.csr_matrix(S_ce.T), sp.csr_matrix(0.5 * (S_ee + S_ee.T))]],
                format="csc")
    return Reduced(S, np.concatenate([g_c, g_e]), nc)


class Conditional:
    """Information and gradient of test columns given free base columns, for many tests at once.

    For columns ``t`` given free columns ``b`` of the reduced system: ``I = S_tt - S_tb S_bb^-1 S_bt`` and
    ``g_t|b = g_t - S_tb S_bb^-1 g_b``; the chi-square drop of freeing ``t`` is ``g^T I^-1 g`` and the
    Gauss-Newton estimate ``-I^-1 g``. ``S_bb`` is factorised once (sparse LU,
    :func:`aerocal.adjust.solver.factorise`) for every test.
    """

    def __init__(self, red: Reduced, base: np.ndarray, tests: np.ndarray) -> None:
        S, g = red.S, red.g
        self.S, self.g, self.base = S, g, base
        self.tests = tests
        self._S_base = S[base, :].tocsc()  # the base rows, sliced by column for each test
        Sbb = self._S_base[:, base]
        rhs = np.column_stack([self._S_base[:, tests].toarray(), g[base]])
        lu, d = factorise(Sbb)
        if lu is not None:
            self.X = lu.solve(rhs / d[:, None]) / d[:, None]
        else:  # exactly singular: the pseudo-inverse
            self.X = inverse_spd(Sbb.toarray()) @ rhs
        self.pos = {int(t): k for k, t in enumerate(tests)}

    def _block(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        return self.S[:, cols][rows, :].toarray()

    def __call__(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cols = [self.pos[int(t)] for t in idx]
        Sbt = self._S_base[:, idx].toarray()
        info = self._block(idx, idx) - Sbt.T @ self.X[:, cols]
        grad = self.g[idx] - Sbt.T @ self.X[:, -1]
        return 0.5 * (info + info.T), grad

    def cross(self, idx: np.ndarray, other: np.ndarray) -> np.ndarray:
        """Conditional cross-information ``S_io - S_ib S_bb^-1 S_bo`` of test columns ``idx`` and ``other``
        (both among the tests)."""
        cols = [self.pos[int(t)] for t in other]
        Sbt = self._S_base[:, idx].toarray()
        return self._block(idx, other) - Sbt.T @ self.X[:, cols]


def triangulate_checks(base: Baseline, block: Block | None = None) -> np.ndarray:
    """Check points triangulated from their image measurements with the adjusted block (local frame)."""
    b = block or base.block
    st = base.state
    if not len(b.check_ids) or not len(b.check_image):
        return np.zeros((0, 3))
    rays = pixels_to_rays(st.io, st.slopes, np.zeros(len(b.check_image)), st.R[b.check_image], b.check_uv)
    X, ok = triangulate_linear(b.check_point, len(b.check_ids), st.C[b.check_image], rays)
    X[~ok] = np.nan
    return X


def check_rmse(base: Baseline, block: Block | None = None) -> tuple[float, np.ndarray]:
    """3D RMSE (metres) of the check points against their surveyed coordinates, and the errors."""
    b = block or base.block
    X = triangulate_checks(base, b)
    if not len(X):
        return float("nan"), np.zeros((0, 3))
    err = X - b.check_xyz
    ok = np.isfinite(err).all(axis=1)
    return float(np.sqrt(np.mean(np.sum(err[ok] ** 2, axis=1)))), err
