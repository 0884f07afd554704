"""Levenberg-Marquardt bundle adjustment with the Schur complement on the points.

Why our own solver rather than pyceres: the adjustment needs, besides the solution, the reduced
camera-side normal matrix (IO, thermal slopes and poses) to give the IO covariance and the *marginal*
covariance of check points; with the Schur complement both fall out of the solve at no extra cost, and
every residual (tie points, GCPs, GNSS and attitude priors, thermal focal) is evaluated vectorised in
numpy instead of one Python ``pyceres.CostFunction`` call per observation, whose call overhead would dominate
(measurements: ``benchmarks/history/engine_measurements.md``). The analytic Jacobians are checked against
central differences and the IO sigmas against the scatter of estimates over 20 simulated seeds
(``tests/test_adjust_core.py``).
The tie-point projection is isolated in :func:`aerocal.adjust.projection.project` so that a C++ path
(``pycolmap.cost_functions``) can replace it for city-scale blocks.

Unknowns: camera side ``[free IO | free thermal slopes | per image (w, C)]`` and points ``X``.
Residuals (all divided by their a-priori sigma): image observations (2 per observation), GNSS
positions (3 per image), attitudes (3 per image, ``log(R R_rec^T)``), control GCPs (3 per point).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pymetis
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg import lapack

from aerocal.adjust import cholesky
from aerocal.adjust.laser import LaserRows, laser_residuals, laser_rows
from aerocal.adjust.problem import AdjustConfig, AdjustmentError, Block, RobustLoss
from aerocal.adjust.projection import (
    IDX,
    THERMAL_PARAMS,
    project_observations,
    rotation_log,
    rotation_update,
)
from aerocal.adjust.schur_kernels import (
    PairLayout,
    global_blocks,
    global_image_coupling,
    image_graph,
    image_pair_layout,
    jacobian_blocks,
    point_visit_rank,
    points_from_images,
    reduce_points,
    stable_order,
)

#: A tie point intersected closer to a camera that sees it than this fraction of the block's median depth
#: is dropped before the adjustment (:func:`aerocal.adjust.bundle.initial_state`), and a step that would
#: bring one there leaves it where it was (:meth:`BundleProblem.hold_close_points`). In an aerial block such a
#: point is a wrong intersection from a poor start, not terrain, and its Jacobian grows as 1 / depth^2:
#: on seneca (autopilot attitude good to a few degrees) points centimetres in front of a camera made the
#: reduced normal matrix overflow (diagonal > 1e20) and the factorisation fail. Oblique low blocks
#: (daakir-calibration, 25 degrees of attitude spread) have all their depths within a factor of 2-3 of
#: the median.
MIN_DEPTH_FRACTION = 0.1


@dataclass
class State:
    """Current values of every unknown (local frame)."""

    io: np.ndarray  # (10,) PARAM_NAMES order, IO at the reference temperature
    slopes: np.ndarray  # (3,) px/degC of f, cx, cy
    R: np.ndarray  # (N, 3, 3) world-to-camera
    C: np.ndarray  # (N, 3) projection centres
    X: np.ndarray  # (P, 3) tie points then control GCPs

    def copy(self) -> State:
        return State(self.io.copy(), self.slopes.copy(), self.R.copy(), self.C.copy(), self.X.copy())


@dataclass
class Layout:
    """Column layout of the camera-side unknowns."""

    io_free: list[int]  # indices into the IO vector
    slope_free: list[int]  # indices into the slope vector
    n_images: int
    n_points: int

    @property
    def n_global(self) -> int:
        return len(self.io_free) + len(self.slope_free)

    @property
    def n_camera(self) -> int:
        return self.n_global + 6 * self.n_images

    def image_cols(self, i: np.ndarray) -> np.ndarray:
        """(len(i), 6) columns of (w, C) of images ``i``."""
        return self.n_global + 6 * np.asarray(i)[:, None] + np.arange(6)[None, :]


@dataclass
class Solution:
    """The solved state and what the covariance needs."""

    state: State
    layout: Layout
    cov_camera: SparseInverse | None  # inverse of the reduced normal matrix (unscaled), blocks on demand;
    # None where it was not asked for (:func:`solve`)
    sigma0: float
    dof: int
    cost: float
    iterations: int
    converged: bool
    obs_residual_px: np.ndarray  # (M, 2) predicted - observed, pixels
    obs_weight: np.ndarray  # (M,) robust weight (1 without a robust loss)
    t0: float = 0.0  # reference temperature of the thermal slopes, degC
    history: list[float] = field(default_factory=list)


@dataclass
class ObsBlocks:
    """The image-observation rows of the last Jacobian, block by block (rows scaled like the Jacobian).

    Observation ``m`` (image ``image[m]``, point ``point[m]``) has a 2 x 6 block ``Ji[m]`` in its image's
    (w, C) columns, a 2 x 3 block ``Jx[m]`` in its point's columns and nothing else but the ``n_global``
    IO and slope columns: what :func:`schur_complement` needs to form the image-image part of the
    reduced system without general sparse products.
    """

    image: np.ndarray  # (M,) image index
    point: np.ndarray  # (M,) point index
    Ji: np.ndarray  # (M, 2, 6)
    Jx: np.ndarray  # (M, 2, 3)
    n_global: int
    Jg: np.ndarray  # (M, 2, n_global) IO and slope columns
    r: np.ndarray  # (M, 2) the rows' residuals, scaled like the Jacobian
    prior_info: np.ndarray  # (N, 6) diagonal information of the GNSS / attitude priors
    prior_grad: np.ndarray  # (N, 6) their J^T r
    point_grad: np.ndarray  # (P, 3) J^T r of the control-point rows (zero for tie points)
    layout: PairLayout  # the image-image blocks of the reduced system and the observations by point


def _robust(s: np.ndarray, loss: RobustLoss, c: float) -> tuple[np.ndarray, np.ndarray]:
    """rho(s) and rho'(s) of squared normalised residual norms ``s``."""
    if loss == RobustLoss.HUBER:
        c2 = c * c
        root = np.sqrt(np.maximum(s, 1e-300))
        rho = np.where(s <= c2, s, 2 * c * root - c2)
        drho = np.where(s <= c2, 1.0, c / root)
        return rho, drho
    if loss == RobustLoss.CAUCHY:
        c2 = c * c
        return c2 * np.log1p(s / c2), 1.0 / (1.0 + s / c2)
    return s, np.ones_like(s)


@dataclass(frozen=True)
class ObsView:
    """A block's image observations in point order (each point's observations together, the block's order
    within a point, the points in their visiting order, :func:`point_visit_rank`): the order of the rows of
    :class:`ObsBlocks`. The compiled passes over them (:mod:`aerocal.adjust.schur_kernels`,
    :func:`project_observations`) then read each point's observations and the point itself in sequence
    instead of at random, so that they come from the cache rather than from memory."""

    order: np.ndarray  # (M,) the block's rows in this order
    image: np.ndarray  # (M,) int64
    point: np.ndarray  # (M,) int64
    uv: np.ndarray  # (M, 2) measured pixels
    sigma: np.ndarray  # (M,) a-priori sigma, pixels
    is_tie: np.ndarray  # (M,) bool

    @classmethod
    def by_point(cls, b: Block, rank: np.ndarray) -> ObsView:
        """``rank``: (P,) when each point is visited."""
        order = stable_order(rank[b.obs_point], len(rank))
        return cls(order, b.obs_image[order].astype(np.int64), b.obs_point[order].astype(np.int64),
                   np.ascontiguousarray(b.obs_uv[order]), b.obs_sigma[order], b.obs_is_tie[order])


class BundleProblem:
    """Residuals and Jacobians of a :class:`Block` under an :class:`AdjustConfig`."""

    def __init__(self, block: Block, config: AdjustConfig, t0: float, check_datum: bool = True) -> None:
        """``check_datum=False`` for a sub-block of a partitioned adjustment, whose datum is the whole block's
        (:mod:`aerocal.adjust.partition`)."""
        self.b = block
        self.cfg = config
        self.t0 = t0
        self.layout = Layout(
            io_free=[IDX[n] for n in config.free],
            slope_free=[THERMAL_PARAMS.index(n) for n in config.thermal],
            n_images=block.n_images,
            n_points=block.n_points,
        )
        self.dtemp_img = np.nan_to_num(block.temperature - t0) if config.thermal else np.zeros(block.n_images)
        #: (N,) 1 where an image's GNSS / attitude priors count, 0 where another sub-block of a partitioned
        #: adjustment counts them (each prior enters the whole block's normal equations once)
        self.prior_weight = np.ones(block.n_images)
        self.blocks: ObsBlocks | None = None  # of the last Jacobian (see :class:`ObsBlocks`)
        self._view: ObsView | None = None  # formed on first use (:meth:`point_view`)
        self._graph: tuple[sp.csr_matrix, np.ndarray] | None = None  # image graph and points' visiting rank
        self._pair_layout: PairLayout | None = None  # formed on the first Jacobian (:meth:`by_point`)
        self._block_layout: PairLayout | None = None  # formed on first use (:meth:`block_order_layout`)
        self.depth_floor: float | None = None  # metres, set from the first state a step starts from
        self.last_depth: np.ndarray | None = None  # see :meth:`residuals`
        self._inv_sigma: np.ndarray | None = None  # 1 / the point view's sigma (:meth:`residuals`)
        self._work: dict[str, np.ndarray] = {}  # arrays reused from one Jacobian to the next (:meth:`_buffer`)
        #: the laser rows (:mod:`aerocal.adjust.laser`), chosen at the first state the residuals see
        self.laser: LaserRows | None = None
        self._laser_layouts: dict[bool, PairLayout] = {}
        self.gnss_sigma = None if config.gnss_sigma_m is None else np.asarray(config.gnss_sigma_m, float)
        self.att_sigma = (
            None
            if config.attitude_sigma_deg is None
            else np.radians(np.asarray(config.attitude_sigma_deg, float))
        )
        if check_datum and self.gnss_sigma is None and len(block.control_ids) < 3:
            raise AdjustmentError(
                "the datum is not defined: GNSS priors are off (AdjustConfig.gnss_sigma_m=None) and "
                f"there are "
                f"{len(block.control_ids)} control GCPs; give GNSS sigmas or at least 3 control points"
            )

    def in_block_order(self, a: np.ndarray | None) -> np.ndarray:
        """Per-observation values in point order (:meth:`point_view`) put in the block's order; ``None``: the
        weights of an adjustment without a robust loss (all 1)."""
        view = self.point_view()
        if a is None:
            return np.ones(len(view.order))
        out = np.empty_like(a)
        out[view.order] = a
        return out

    def _buffer(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """A float64 array of ``shape`` kept for the next call (its content is not kept): the per-observation
        blocks of the Jacobian are formed again at every step of an adjustment, and new arrays of that size
        cost page faults on every call."""
        a = self._work.get(name)
        if a is None or a.shape != shape:
            self._work.pop(name, None)
            a = self._work[name] = np.empty(shape)
        return a

    def release(self) -> None:
        """Free the last Jacobian and the arrays kept for the next one (after the last step)."""
        self.blocks = None
        self._work.clear()

    def point_view(self) -> ObsView:
        """The observations in point order (:class:`ObsView`), formed once for the block."""
        if self._view is None:
            b = self.b
            G = image_graph(b.obs_image, b.obs_point, b.n_images, b.n_points)
            # formed again rather than carried on the Block: both cost little next to one step
            self._graph = G, point_visit_rank(G, b.obs_image, b.obs_point, b.n_points)
            self._view = ObsView.by_point(b, self._graph[1])
        return self._view

    def by_point(self) -> tuple[ObsView, PairLayout]:
        """The observations in point order and the block layout of the reduced camera system
        (:func:`image_pair_layout`): both depend only on which image observes which point, so they are formed
        once for the block; the layout on the first Jacobian only (a residuals-only BundleProblem never needs it)."""
        view = self.point_view()
        if self._pair_layout is None:
            b = self.b
            G, rank = self._graph
            self._pair_layout = image_pair_layout(view.image, view.point, b.n_images, b.n_points, G, rank)
        return view, self._pair_layout

    def block_order_layout(self) -> PairLayout:
        """:func:`image_pair_layout` of the observations in the block's own order (the rows of the sparse
        Jacobians of :meth:`residuals`)."""
        if self._block_layout is None:
            b = self.b
            self._block_layout = image_pair_layout(b.obs_image, b.obs_point, b.n_images, b.n_points)
        return self._block_layout

    def laser_rows(self, st: State) -> LaserRows:
        """The block's laser observations (:func:`aerocal.adjust.laser.laser_rows`), chosen once, at ``st``'s
        principal point and focal length."""
        if self.laser is None:
            b = self.b
            self.laser = laser_rows(b.laser_range, b.obs_image, b.obs_point, b.obs_uv, b.obs_is_tie,
                                    (float(st.io[IDX["cx"]]), float(st.io[IDX["cy"]])), float(st.io[IDX["f"]]))
        return self.laser

    def _with_laser_layout(self, image: np.ndarray, point: np.ndarray, point_order: bool) -> PairLayout:
        """The pair layout of the observations followed by the laser rows (a laser row observes a pair of image
        and point the block holds, so the image graph is the block's)."""
        if point_order not in self._laser_layouts:
            b = self.b
            G, rank = self._graph if point_order else (None, None)
            self._laser_layouts[point_order] = image_pair_layout(image, point, b.n_images, b.n_points, G, rank)
        return self._laser_layouts[point_order]

    # ------------------------------------------------------------------ residuals
    def residuals(self, st: State, jac: bool, sparse: bool = True) -> tuple:
        """``(cost, res_px, w)``, with ``jac`` also ``(r, Jc, Jp, Hpp)``: the scaled residual vector, the
        camera-side and point-side Jacobians (``scipy.sparse`` CSR) and the 3 x 3 point blocks of J^T J.
        With ``sparse=False`` ``r``, ``Jc`` and ``Jp`` are ``None``: :attr:`blocks` holds everything
        :func:`schur_complement` needs, without the sparse matrices' indices (~0.5 kB per observation), and
        ``res_px`` and ``w`` are in point order (:class:`ObsView`; :meth:`in_block_order` puts them back):
        an adjustment's steps need neither, and each (M,)-sized array a step does not form saves its page
        faults. Otherwise ``res_px`` and ``w`` are in the block's order."""
        b, lay = self.b, self.layout
        if jac and sparse:
            view, pair_layout = None, None
        elif jac:
            view, pair_layout = self.by_point()
        else:
            view, pair_layout = self.point_view(), None
        if view is None:
            i, j, uv_obs, sigma, is_tie = b.obs_image, b.obs_point, b.obs_uv, b.obs_sigma, b.obs_is_tie
        else:
            i, j, uv_obs, sigma, is_tie = view.image, view.point, view.uv, view.sigma, view.is_tie
        # the compiled loop over the observations, no (M, 3, 3) gathers; IO and slope Jacobians when they are free
        if view is not None:  # 1 / sigma of the point-ordered observations, formed once for the block
            if self._inv_sigma is None:
                self._inv_sigma = 1.0 / sigma
            inv_sigma = self._inv_sigma
        else:
            inv_sigma = 1.0 / sigma
        robust = self.cfg.robust_loss != RobustLoss.NONE
        Hpp = None
        if jac:
            self.blocks = None  # the last Jacobian's blocks go before the new ones are formed
            # the image and point blocks of the last Jacobian are written over (:func:`jacobian_blocks`)
            Ji_buf, Jx_buf = self._buffer("Ji", (len(i), 2, 6)), self._buffer("Jx", (len(i), 2, 3))
            if not robust:  # the rows' scale is known before the residuals: blocks formed in the projection
                Hpp = np.zeros((lay.n_points, 3, 3))
        else:
            Ji_buf = Jx_buf = None
        pr = project_observations(st.io, st.slopes, self.dtemp_img, st.R, st.C, st.X, i, j, jacobians=jac,
                                  io_jacobians=lay.n_global > 0, d_rot_out=Ji_buf, d_point_out=Jx_buf,
                                  scale=None if Hpp is None else inv_sigma, Hpp=Hpp)
        # depths (metres) of this state's observations in point order, for :meth:`hold_close_points`
        self.last_depth = None if view is None else pr.depth
        res_px = pr.uv
        res_px -= uv_obs
        d_io, d_slope = pr.d_io, pr.d_slope
        del pr
        r_obs = res_px * inv_sigma[:, None]
        s = np.einsum("ij,ij->i", r_obs, r_obs)
        if robust:
            rho_t, w_t = _robust(s[is_tie], self.cfg.robust_loss, self.cfg.robust_scale)
            rho = s.copy()
            rho[is_tie] = rho_t
            w = np.ones_like(s)
            w[is_tie] = w_t
        else:
            rho, w = s, None  # every weight 1: formed only where it is returned
        res_out, w_out = res_px, w
        if jac and not sparse:
            pass  # in point order, and w None without a robust loss (see the docstring)
        elif view is not None:  # back to the block's order
            res_out, w_out = self.in_block_order(res_px), self.in_block_order(w)
        elif w_out is None:
            w_out = np.ones(len(i))
        parts = [r_obs.ravel()]
        cost_parts = [float(np.sum(rho))]
        pw = self.prior_weight[:, None]
        if self.gnss_sigma is not None:
            r = ((st.C - b.gnss) / self.gnss_sigma * pw).ravel()
            parts.append(r)
            cost_parts.append(float(r @ r))
        if self.att_sigma is not None:
            rot = rotation_log(np.einsum("nij,nkj->nik", st.R, b.R_rec))
            r = (rot / self.att_sigma * pw).ravel()
            parts.append(r)
            cost_parts.append(float(r @ r))
        G = len(b.control_ids)
        if G:
            r = ((st.X[b.n_tie :] - b.control_xyz) / b.control_sigma).ravel()
            parts.append(r)
            cost_parts.append(float(r @ r))
        laser = self.laser_rows(st)
        L = len(laser)
        if L:
            l_res, l_pose, l_point = laser_residuals(st.R, st.C, st.X, laser)
            l_r = l_res / laser.sigma_m
            l_s = l_r * l_r
            # always under a Cauchy loss: a laser that passed a canopy's gap to the ground is a blunder of tens of
            # sigmas that no screening of the image observations sees
            l_rho, l_w = _robust(l_s, RobustLoss.CAUCHY, self.cfg.robust_scale)
            cost_parts.append(float(np.sum(l_rho)))
        cost = 0.5 * sum(cost_parts)
        if not jac:
            return cost, res_out, w_out
        # ---- Jacobian (rows scaled by sqrt of the robust weight for IRLS)
        # (M,)-sized temporaries are formed only where they differ from what is at hand: each fresh one costs
        # page faults on every call
        M = len(i)
        sw = np.sqrt(w) * inv_sigma if robust else inv_sigma
        Jg = np.concatenate([d_io[:, :, lay.io_free], d_slope[:, :, lay.slope_free]], axis=2) * sw[:, None, None]
        del d_io, d_slope
        # the pose and point blocks and the points' blocks of J^T J (each row touches one point), one pass
        Ji, Jx = Ji_buf, Jx_buf
        if Hpp is None:  # robust weights: the rows scaled now that the residuals give them
            Hpp = jacobian_blocks(j, Ji, Jx, sw, lay.n_points)
        ng = lay.n_global
        if robust:
            r_obs *= np.sqrt(w)[:, None]  # the cost is summed above; from here on the rows are IRLS-scaled
        rw = r_obs
        Nimg = b.n_images
        info, grad = np.zeros((Nimg, 6)), np.zeros((Nimg, 6))
        if self.gnss_sigma is not None:
            info[:, 3:] += pw / self.gnss_sigma**2
            grad[:, 3:] += parts[1].reshape(Nimg, 3) / self.gnss_sigma
        if self.att_sigma is not None:
            info[:, :3] += pw / self.att_sigma**2
            grad[:, :3] += parts[2 if self.gnss_sigma is not None else 1].reshape(Nimg, 3) / self.att_sigma
        pgrad = np.zeros((lay.n_points, 3))
        if G:
            pgrad[b.n_tie :] = parts[-1].reshape(G, 3) / b.control_sigma
        o_image, o_point, o_Ji, o_Jx, o_Jg, o_r = i, j, Ji, Jx, Jg, rw
        laser_layout = None
        if L:
            # the laser rows as one more observation each of (image, point): a first row, a second of zeros
            l_sw = np.sqrt(l_w) / laser.sigma_m
            l_Ji, l_Jx, l_rw = np.zeros((L, 2, 6)), np.zeros((L, 2, 3)), np.zeros((L, 2))
            l_Ji[:, 0] = l_pose * l_sw[:, None]
            l_Jx[:, 0] = l_point * l_sw[:, None]
            l_rw[:, 0] = l_res * l_sw
            np.add.at(Hpp, laser.point, np.einsum("li,lj->lij", l_Jx[:, 0], l_Jx[:, 0]))
            o_image, o_point = np.concatenate([i, laser.image]), np.concatenate([j, laser.point])
            o_Ji, o_Jx, o_r = np.concatenate([Ji, l_Ji]), np.concatenate([Jx, l_Jx]), np.concatenate([rw, l_rw])
            o_Jg = np.concatenate([Jg, np.zeros((L, 2, ng))])
            laser_layout = self._with_laser_layout(o_image, o_point, view is not None)
        self.blocks = ObsBlocks(image=o_image, point=o_point, Ji=o_Ji, Jx=o_Jx, n_global=ng, Jg=o_Jg, r=o_r,
                                prior_info=info, prior_grad=grad, point_grad=pgrad,
                                layout=laser_layout if L else (self.block_order_layout() if view is None
                                                               else pair_layout))
        if G:
            Hpp[b.n_tie :] += np.einsum("gi,ij->gij", 1.0 / b.control_sigma**2, np.eye(3))
        if not sparse:
            return cost, res_out, w_out, None, None, None, Hpp
        r_all = [rw.ravel()] + parts[1:]
        rr, cc, vv = [], [], []
        rows_obs = np.arange(2 * M).reshape(M, 2)
        if ng:
            rr.append(np.repeat(rows_obs[:, :, None], ng, axis=2).ravel())
            cc.append(np.broadcast_to(np.arange(ng), (M, 2, ng)).ravel())
            vv.append(Jg.ravel())
        icols = lay.image_cols(i)  # (M, 6)
        rr.append(np.repeat(rows_obs[:, :, None], 6, axis=2).ravel())
        cc.append(np.broadcast_to(icols[:, None, :], (M, 2, 6)).ravel())
        vv.append(Ji.ravel())
        pr_rows = [np.repeat(rows_obs[:, :, None], 3, axis=2).ravel()]
        pr_cols = [np.broadcast_to((3 * j)[:, None, None] + np.arange(3), (M, 2, 3)).ravel()]
        pr_vals = [Jx.ravel()]
        row = 2 * M
        allimg = lay.image_cols(np.arange(Nimg))
        if self.gnss_sigma is not None:
            rr.append(row + np.arange(3 * Nimg))
            cc.append(allimg[:, 3:].ravel())
            vv.append((pw / self.gnss_sigma).ravel())
            row += 3 * Nimg
        if self.att_sigma is not None:
            # d log(exp(w) R R_rec^T)/dw ~ identity for the small angles between recorded and adjusted
            rr.append(row + np.arange(3 * Nimg))
            cc.append(allimg[:, :3].ravel())
            vv.append((pw / self.att_sigma).ravel())
            row += 3 * Nimg
        if G:
            pr_rows.append(row + np.arange(3 * G))
            pr_cols.append(3 * b.n_tie + np.arange(3 * G))
            pr_vals.append((1.0 / b.control_sigma).ravel())
            row += 3 * G
        if L:
            rr.append(np.repeat(row + np.arange(L), 6))
            cc.append(lay.image_cols(laser.image).ravel())
            vv.append(l_Ji[:, 0].ravel())
            pr_rows.append(np.repeat(row + np.arange(L), 3))
            pr_cols.append(((3 * laser.point)[:, None] + np.arange(3)).ravel())
            pr_vals.append(l_Jx[:, 0].ravel())
            r_all.append(l_rw[:, 0])
            row += L
        Jc = sp.csr_matrix(
            (np.concatenate(vv), (np.concatenate(rr), np.concatenate(cc))), shape=(row, lay.n_camera)
        )
        Jp = sp.csr_matrix(
            (np.concatenate(pr_vals), (np.concatenate(pr_rows), np.concatenate(pr_cols))),
            shape=(row, 3 * lay.n_points),
        )
        return cost, res_out, w_out, np.concatenate(r_all), Jc, Jp, Hpp

    # ------------------------------------------------------------------ updates
    def hold_close_points(self, old: State, new: State, depth: np.ndarray | None = None) -> int:
        """Put back (in ``new``) the tie points a step brought closer to a camera that sees them than
        :data:`MIN_DEPTH_FRACTION` of the median depth of ``old``'s first call; returns how many.
        ``depth``: ``new``'s depths of every observation in point order (:attr:`last_depth` of its residuals),
        when they are at hand; else they are projected here.

        Their Jacobian grows as 1 / depth^2: one such point makes the reduced normal matrix overflow."""
        view = self.point_view()

        def depths(st: State) -> np.ndarray:  # of every observation, in point order
            return project_observations(st.io, st.slopes, self.dtemp_img, st.R, st.C, st.X, view.image, view.point,
                                        jacobians=False).depth

        if self.depth_floor is None:
            self.set_depth_floor(depths(old)[view.is_tie])
        z = depths(new) if depth is None else depth
        close = np.unique(view.point[np.flatnonzero(~(z > self.depth_floor) & view.is_tie)])
        new.X[close] = old.X[close]
        return len(close)

    def set_depth_floor(self, tie_depth: np.ndarray) -> None:
        """The depth (metres) below which a step's tie point is held (:meth:`hold_close_points`), from the tie
        observations' depths at the start."""
        z = tie_depth[tie_depth > 0]
        self.depth_floor = MIN_DEPTH_FRACTION * float(np.median(z)) if len(z) else 0.0

    def point_step(self, Hpp: np.ndarray, lam: float) -> np.ndarray:
        """The Gauss-Newton step (P, 3), metres, of every point with the cameras and IO held, from the last
        linearisation (:attr:`blocks` and its point blocks ``Hpp``), damped like the points of a
        Levenberg-Marquardt step by ``lam``."""
        b = self.blocks
        gp = _sum_by(b.point, np.einsum("muj,mu->mj", b.Jx, b.r), self.layout.n_points) + b.point_grad
        return -np.einsum("pij,pj->pi", _damped_point_inverse(Hpp, lam), gp)

    def apply(self, st: State, dc: np.ndarray, dp: np.ndarray) -> State:
        lay = self.layout
        new = st.copy()
        k = 0
        for idx in lay.io_free:
            new.io[idx] += dc[k]
            k += 1
        for idx in lay.slope_free:
            new.slopes[idx] += dc[k]
            k += 1
        d_img = dc[lay.n_global :].reshape(-1, 6)
        new.R = rotation_update(st.R, d_img[:, :3])
        new.C = st.C + d_img[:, 3:]
        new.X = st.X + dp.reshape(-1, 3)
        return new


def _damped_point_inverse(Hpp: np.ndarray, lam: float) -> np.ndarray:
    """Inverses of the 3 x 3 point blocks, their diagonals scaled by ``1 + lam``."""
    Hpp_d = Hpp.copy()
    if lam:
        d = np.einsum("pii->pi", Hpp_d)
        d *= 1.0 + lam
    try:
        return np.linalg.inv(Hpp_d)
    except np.linalg.LinAlgError:
        # a point seen along (nearly) one ray has a singular block: load its diagonal so that it simply
        # does not move, instead of failing the whole adjustment
        load = 1e-9 * np.maximum(np.einsum("pii->p", Hpp_d) / 3.0, 1e-12)
        return np.linalg.inv(Hpp_d + load[:, None, None] * np.eye(3))


def schur_complement(Jc, Jp, Hpp, r, lam: float, blocks: ObsBlocks | None = None):
    """Reduced camera system (sparse) and the pieces to back-substitute the points.

    Returns ``(S, rhs, Hpp_inv, Hcp, gp)``: ``S dc = rhs`` gives the camera-side step, then
    ``dp = -Hpp_inv (gp + Hcp^T dc)`` point by point; ``lam`` scales the diagonal of the camera-side
    normal matrix and of the point blocks by ``1 + lam`` (Levenberg-Marquardt). ``S`` is a ``scipy.sparse``
    CSC matrix: an image couples only with the images it shares tie points with, so it holds
    ~36 x (1 + neighbours) entries per image instead of (6 N)^2 (2745 images: 2.2 GB dense per copy).
    With ``blocks`` (:class:`ObsBlocks` of the Jacobian, :meth:`BundleProblem.residuals`) everything is formed
    from the observations' blocks and ``Jc``, ``Jp`` and ``r`` are not read (they may be ``None``), and
    ``Hcp`` is an operator; without, from general sparse products of ``Jc`` and ``Jp``.
    """
    if blocks is not None:
        return _structured_schur(Hpp, lam, blocks)
    Hcc = (Jc.T @ Jc).tocsr()
    gc = Jc.T @ r
    gp = Jp.T @ r
    if lam:
        Hcc = (Hcc + sp.diags(lam * Hcc.diagonal())).tocsr()
    Hpp_inv = _damped_point_inverse(Hpp, lam)
    Hcp = (Jc.T @ Jp).tocsr()
    P = len(Hpp)
    Hpp_inv_sp = sp.bsr_matrix((Hpp_inv, np.arange(P), np.arange(P + 1)), shape=(3 * P, 3 * P)).tocsr()
    HcpHi = (Hcp @ Hpp_inv_sp).tocsr()
    S = (Hcc - HcpHi @ Hcp.T).tocsc()
    rhs = -gc + HcpHi @ gp
    return S, rhs, Hpp_inv, Hcp, gp


def _structured_schur(Hpp, lam: float, b: ObsBlocks):
    """:func:`schur_complement` from the observations' blocks.

    ``J^T J`` and ``J^T r`` of the camera side are sums over observations of ``Ji^T Ji``, ``Jg^T Ji``,
    ``Ji^T r`` ... per image, plus the priors' diagonals. The image-image part of ``Hcp Hpp^-1 Hcp^T`` is
    ``sum_p sum_(m, m' of p) W_m Hpp_p^-1 W_m'^T`` with ``W_m = Ji_m^T Jx_m`` (6 x 3): the 6 x 6 blocks of
    every pair of observations of a point, summed per image pair into a block-sparse (BSR, 6 x 6) matrix
    by one compiled pass over the points (:func:`aerocal.adjust.schur_kernels.reduce_points`). Measured
    against the numpy pair sums it replaced and against pycolmap's Ceres on the same problem:
    ``benchmarks/colmap_ba_bench.py``, ``benchmarks/RESULTS.md``; ``tests/test_adjust_core.py`` checks the
    agreement with the general sparse products (1e-9 relative).
    """
    ng, N, P = b.n_global, len(b.prior_info), len(Hpp)
    n_camera = ng + 6 * N
    damp = 1.0 + lam
    red = reduce_points(b.layout, b.image, b.Ji, b.Jx, b.r, Hpp, lam, b.point_grad, N)
    Hpp_inv, gpp = red.Hpp_inv, red.gpp
    gp = gpp.ravel()
    # gradients J^T r: camera side per image (+ priors) and global
    gc = np.zeros(n_camera)
    gc[ng:] = (red.grad + b.prior_grad).ravel()
    rhs = -gc
    rhs[ng:] += red.back.ravel()
    # the image's own 6 x 6 block of J^T J (its observations and priors), damped
    Hii = red.Hii
    Hii[:, np.arange(6), np.arange(6)] += b.prior_info
    Hii[:, np.arange(6), np.arange(6)] *= damp
    data = red.data
    data[b.layout.diagonal] += Hii
    S_ii = sp.bsr_matrix((data, b.layout.indices, b.layout.indptr), shape=(6 * N, 6 * N)).tocsr()
    S_ii.sort_indices()
    del data, red
    if ng:
        # global columns (IO, thermal slopes): few, so their blocks are dense
        Hgg = b.Jg.reshape(-1, ng).T @ b.Jg.reshape(-1, ng)
        Hgg[np.diag_indices(ng)] *= damp
        gc[:ng] = b.Jg.reshape(-1, ng).T @ b.r.ravel()
        rhs[:ng] = -gc[:ng]
        # the global-image and global-point blocks, then the points eliminated from them (compiled passes)
        Hgi, Hcp_p = global_blocks(b.image, b.point, b.Jg, b.Ji, b.Jx, N, P)  # (N, ng, 6), (P, ng, 3)
        Tg_p = np.matmul(Hcp_p, Hpp_inv)  # (P, ng, 3): Hcp_g Hpp^-1 per point
        S_gg = Hgg - Tg_p.transpose(1, 0, 2).reshape(ng, -1) @ Hcp_p.transpose(1, 0, 2).reshape(ng, -1).T
        # global-image: Hgi minus the sum over observations of Tg[p] W_m^T
        S_gi = Hgi - global_image_coupling(b.image, b.point, Tg_p, b.Ji, b.Jx, N)
        S_gi = S_gi.transpose(1, 0, 2).reshape(ng, 6 * N)
        S = sp.bmat([[sp.csr_matrix(S_gg), sp.csr_matrix(S_gi)], [sp.csr_matrix(S_gi.T), S_ii]], format="csc")
        rhs[:ng] += np.einsum("pgj,pj->g", Tg_p, gpp)
        Hcp_g = Hcp_p.transpose(1, 0, 2)  # (ng, P, 3) for the operator below
    else:
        Hcp_g = np.zeros((0, P, 3))
        # the system is symmetric (each image pair's block is written with its transpose, the image's own
        # block is symmetric), so its CSR arrays are its CSC arrays: no conversion
        S = sp.csc_matrix((S_ii.data, S_ii.indices, S_ii.indptr), shape=S_ii.shape)

    def hcp_t(dc: np.ndarray) -> np.ndarray:
        """``Hcp^T dc`` (3P,): per point, the sum over its observations of ``W_m^T dc_image``."""
        dc = np.asarray(dc, dtype=float).ravel()
        out = points_from_images(b.layout, b.image, b.Ji, b.Jx, dc[ng:].reshape(N, 6))
        if ng:
            out += np.einsum("gpj,g->pj", Hcp_g, dc[:ng])
        return out.ravel()

    def hcp(dp: np.ndarray) -> np.ndarray:
        """``Hcp dp`` (n_camera,): per image, the sum over its observations of ``W_m dp_point``."""
        dp = np.asarray(dp, dtype=float).reshape(P, 3)
        out = np.zeros(n_camera)
        # W_m dp = Ji_m^T (Jx_m dp)
        out[ng:] = _sum_by(b.image, np.einsum("mui,mu->mi", b.Ji, np.einsum("muj,mj->mu", b.Jx, dp[b.point])),
                           N).ravel()
        if ng:
            out[:ng] = np.einsum("gpj,pj->g", Hcp_g, dp)
        return out

    Hcp = spla.LinearOperator((n_camera, 3 * P), matvec=hcp, rmatvec=hcp_t, dtype=float)
    return S, rhs, Hpp_inv, Hcp, gp


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """``out[k]``: the sum of ``values[index == k]`` for (M, c) values: (n, c).

    Few columns: one ``np.bincount`` per column; more: one sparse (n, M) indicator product for all of them,
    the cheaper of the two beyond three columns (``benchmarks/history/engine_measurements.md``)."""
    values = np.asarray(values, dtype=float)
    if values.shape[1] <= 3:
        return np.stack([np.bincount(index, weights=values[:, c], minlength=n) for c in range(values.shape[1])], 1)
    M = len(index)
    ind = sp.csr_matrix((np.ones(M), (index, np.arange(M))), shape=(n, M))
    return np.asarray(ind @ values)


#: Fill-reducing ordering of SuperLU for systems without the camera layout. See :func:`factorise`.
ORDERING = "MMD_AT_PLUS_A"


class _PermutedLU:
    """A SuperLU factor of ``S[p][:, p]``, solving with ``S``'s own unknowns' order."""

    def __init__(self, lu, p: np.ndarray) -> None:
        self._lu, self._p = lu, p

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = np.empty_like(b)
        x[self._p] = self._lu.solve(np.ascontiguousarray(b[self._p]))
        return x


def camera_ordering(S, n_global: int) -> np.ndarray:
    """A fill-reducing order of the reduced camera system's unknowns (``n_global`` global columns, then 6 per
    image): the images in METIS's nested-dissection order of the graph of images that share a point (pymetis),
    each image's 6 unknowns together, the global columns (dense rows) last."""
    n = S.shape[0]
    N = (n - n_global) // 6
    coo = sp.coo_matrix(S)
    keep = (coo.row >= n_global) & (coo.col >= n_global)
    bi, bj = (coo.row[keep] - n_global) // 6, (coo.col[keep] - n_global) // 6
    off = bi != bj
    G = sp.csr_matrix((np.ones(int(off.sum()), dtype=np.int8), (bi[off], bj[off])), shape=(N, N))
    G.sort_indices()
    perm, _ = pymetis.nested_dissection(adjacency=pymetis.CSRAdjacency(adj_starts=G.indptr, adjacent=G.indices),
                                        options=pymetis.Options(seed=0))
    perm = np.asarray(perm, dtype=np.int64)
    return np.concatenate([(n_global + 6 * perm[:, None] + np.arange(6)).ravel(), np.arange(n_global)])


def jacobi_scaled(S, d: np.ndarray):
    """``D^-1 S D^-1`` for ``D = diag(d)``, in ``S``'s sparse format (CSR or CSC), by scaling its entries
    instead of two sparse products, each of which forms a new matrix."""
    inv = 1.0 / d
    major = np.repeat(inv, np.diff(S.indptr))  # the row (CSR) or column (CSC) of each entry, scaled
    out = S.copy()
    out.data *= major
    out.data *= inv[S.indices]
    return out


def factorise(S, n_global: int | None = None, earlier=None) -> tuple:
    """Sparse factor of the Jacobi-scaled reduced camera system: ``(f, d)`` with ``S = D (F) D``,
    ``D = diag(d)`` and ``f.solve`` applying ``F^-1``; ``f`` is ``None`` when ``S`` is exactly singular.

    First choice: the Cholesky factor by MKL PARDISO (:mod:`aerocal.adjust.cholesky`; ``S`` is symmetric
    positive definite once GNSS/attitude priors or GCPs fix the datum), multi-threaded and several times
    faster than the SuperLU factor below on city-scale blocks (``benchmarks/history/engine_measurements.md``).
    Where MKL is missing, or PARDISO finds ``S`` not positive definite: SuperLU (scipy) with no pivoting
    off the diagonal, so the factor keeps the fill of a sparse Cholesky. Its order: with ``n_global``
    (``S`` laid out as :class:`Layout`'s camera side), :func:`camera_ordering`; else SuperLU's symmetric
    minimum-degree ordering of ``S + S^T``. Nested dissection leaves less fill than minimum degree on large
    blocks, and a sparse factor replaces a dense matrix whose size grows with the square of the images
    (measurements: ``benchmarks/history/engine_measurements.md``).

    ``earlier``: a factor an earlier call returned for a system of the same pattern (the steps of one
    adjustment); PARDISO's analysis of it is kept and only the numbers are factorised again (the factor
    given is then spent: it becomes the one returned).

    Raises:
        AdjustmentError: ``S`` has non-finite entries: a projection overflowed, the start poses or a tie point are far
            from any consistent geometry.
    """
    S = S if sp.issparse(S) and S.format == "csc" else sp.csc_matrix(S)
    diag = S.diagonal()
    if not (np.isfinite(S.data).all()):
        bad = np.flatnonzero(~np.isfinite(diag))
        raise AdjustmentError(
            f"the reduced normal matrix has non-finite entries (camera-side unknowns {bad[:6].tolist()}...): "
            "a projection overflowed; the start poses or a tie point are far from any consistent geometry"
        )
    d = np.sqrt(np.maximum(diag, 1e-300))
    Ss = jacobi_scaled(S, d)
    if cholesky.available() and np.all(diag > 0):
        try:
            if isinstance(earlier, cholesky.PardisoCholesky) and earlier.refactor(Ss):
                return earlier, d
            return cholesky.PardisoCholesky(Ss), d
        except cholesky.NotPositiveDefinite:
            pass  # SuperLU tells a singular system from an indefinite one
    p = camera_ordering(Ss, n_global) if n_global is not None and Ss.shape[0] > n_global else None
    try:
        if p is None:
            lu = spla.splu(Ss, permc_spec=ORDERING, diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        else:
            lu = _PermutedLU(spla.splu(Ss[p][:, p].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                       options={"SymmetricMode": True}), p)
    except RuntimeError:  # exactly singular
        lu = None
    return lu, d


#: Reduced camera systems with fewer unknowns are factorised at every step (their factorisation is cheap);
#: from this size on :class:`ReducedSolver` reuses the first factor.
REUSE_MIN_UNKNOWNS = 6000
#: Relative error, in the system's energy norm, at which the preconditioned conjugate gradients stop. A
#: Levenberg-Marquardt step needs no exact solution of its damped system (an inexact Newton step: Ceres'
#: iterative Schur solver stops at 1e-1 by default). At 1e-3 an adjustment takes the same steps to the same
#: poses, sigma0 and check-point errors as at 1e-6, in about half the iterations
#: (``benchmarks/history/engine_measurements.md``)
REUSE_TOLERANCE = 1e-3
#: Conjugate-gradient iterations after which the system is factorised again (each costs one solve with the
#: old factor, a small fraction of a factorisation). The bound was set against SuperLU's factorisation;
#: PARDISO's cheaper Cholesky makes the reuse save less, and the bound was not measured again
#: (``benchmarks/history/engine_measurements.md``)
REUSE_MAX_ITERATIONS = 20


class ReducedSolver:
    """Solves the reduced camera systems of one adjustment, step after step.

    Every Levenberg-Marquardt step factorises a new system (:func:`factorise`), though it differs from the
    last one only by the step's change of the linearisation and of the damping. From
    :data:`REUSE_MIN_UNKNOWNS` on, the last factor is kept and preconditions conjugate gradients on the next
    system (started from the old factor's solution), which then converge in a few iterations; the system is
    factorised again when they need more than :data:`REUSE_MAX_ITERATIONS`. The solution equals the direct
    one to :data:`REUSE_TOLERANCE` in the energy norm. Measured on the conte-city plans: see
    ``benchmarks/RESULTS.md`` (adjustment scaling). Singular systems get the least-squares solution."""

    def __init__(self, reuse: bool | None = None, n_global: int | None = None) -> None:
        """``reuse``: keep the factor between calls (None: by the system's size); ``n_global``: the systems
        are reduced camera systems with that many global columns (:func:`factorise`)."""
        self.reuse = reuse
        self.n_global = n_global
        self._lu = None
        self._d: np.ndarray | None = None
        self.factorisations = 0
        self.cg_iterations: list[int] = []

    def _factor(self, S) -> None:
        self._lu, self._d = factorise(S, self.n_global, earlier=self._lu)
        self.factorisations += 1

    def spend(self):
        """The factor held, handed over (to :class:`SparseInverse`, which factorises the last system with
        its analysis) and no longer this solver's."""
        lu, self._lu = self._lu, None
        return lu

    def _direct(self, S, rhs: np.ndarray) -> np.ndarray:
        d = self._d
        rhs_d = rhs / (d[:, None] if rhs.ndim == 2 else d)
        if self._lu is None:
            Ss = sp.csc_matrix(S).toarray() / d[:, None] / d[None, :]
            x = np.linalg.lstsq(Ss, rhs_d, rcond=None)[0]
        else:
            x = self._lu.solve(rhs_d)
        return x / (d[:, None] if rhs.ndim == 2 else d)

    def _conjugate_gradients(self, S, rhs: np.ndarray) -> np.ndarray | None:
        """Conjugate gradients on ``S`` preconditioned by the kept factor, every column of ``rhs`` (n, k) at
        once; ``None`` when they do not converge in :data:`REUSE_MAX_ITERATIONS`."""
        # (a symmetric CSC matrix multiplies as fast as its CSR twin: no conversion)
        X = self._direct(S, rhs)
        R = rhs - S @ X
        Z = self._direct(S, R)
        rz = np.einsum("ik,ik->k", R, Z)
        goal = REUSE_TOLERANCE**2 * np.maximum(np.abs(np.einsum("ik,ik->k", rhs, X)), 1e-300)
        P = Z
        for it in range(REUSE_MAX_ITERATIONS + 1):
            if np.all(rz <= goal):
                self.cg_iterations.append(it)
                return X
            if it == REUSE_MAX_ITERATIONS or not np.all(np.isfinite(rz)):
                return None
            Q = S @ P
            pq = np.einsum("ik,ik->k", P, Q)
            alpha = np.where(pq > 0, rz / np.where(pq > 0, pq, 1.0), 0.0)
            X = X + alpha * P
            R = R - alpha * Q
            Z = self._direct(S, R)
            rz_new = np.einsum("ik,ik->k", R, Z)
            P = Z + (rz_new / np.maximum(rz, 1e-300)) * P
            rz = rz_new
        return None

    def solve(self, S, rhs: np.ndarray) -> np.ndarray:
        """``S x = rhs`` (``rhs`` (n,) or (n, k)).

        Raises:
            AdjustmentError: ``rhs`` has non-finite entries: a projection overflowed, the start poses or a tie point are
                far from any consistent geometry.
        """
        rhs = np.asarray(rhs, dtype=float)
        if not np.isfinite(rhs).all():
            bad = np.flatnonzero(~np.isfinite(rhs.reshape(len(rhs), -1)).all(axis=1))
            raise AdjustmentError(
                f"the reduced normal equations have non-finite entries (camera-side unknowns {bad[:6].tolist()}...): "
                "a projection overflowed; the start poses or a tie point are far from any consistent geometry"
            )
        if self.will_reuse(S):
            x = self._conjugate_gradients(S, rhs.reshape(len(rhs), -1))
            if x is not None:
                return x.reshape(rhs.shape)
        self._factor(S)
        return self._direct(S, rhs)

    def will_reuse(self, S) -> bool:
        """Whether :meth:`solve` starts from the kept factor on ``S``."""
        reuse = self.reuse if self.reuse is not None else S.shape[0] >= REUSE_MIN_UNKNOWNS
        return bool(reuse and self._lu is not None and np.isfinite(S.data).all())


def inverse_spd(S: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi)definite matrix, Jacobi-scaled; pseudo-inverse if singular.

    Small systems use SuperLU (see above); from a few hundred unknowns LAPACK's Cholesky inverse (potrf +
    potri) gives the same result far faster than SuperLU on an identity right-hand side
    (``benchmarks/history/engine_measurements.md``).
    """
    d = np.sqrt(np.maximum(np.diag(S), 1e-300))
    Ss = S / d[:, None] / d[None, :]
    inv = None
    if len(S) > 400:
        c, info = lapack.dpotrf(Ss, lower=False)
        if info == 0:
            inv, info = lapack.dpotri(c, lower=False)
            if info == 0:
                inv = np.triu(inv) + np.triu(inv, 1).T
            else:
                inv = None
    if inv is None:
        try:
            inv = spla.splu(sp.csc_matrix(Ss)).solve(np.eye(len(S)))
            inv = 0.5 * (inv + inv.T)
        except RuntimeError:
            inv = np.linalg.pinv(Ss, rcond=1e-12, hermitian=True)
    return inv / d[:, None] / d[None, :]


#: Most bytes of inverse columns a :class:`SparseInverse` keeps between calls.
CACHE_BYTES = 256e6


class SparseInverse:
    """Blocks of the inverse of a sparse symmetric positive definite matrix, computed on demand.

    The reduced camera system of a block is sparse (an image couples only with the images it shares
    points with), so one sparse factorisation (:func:`factorise`, Jacobi-scaled) and a solve for the columns
    a caller needs beats forming the dense inverse, whose cost grows with the cube of the unknowns
    (measurements: ``benchmarks/history/engine_measurements.md``).
    Indexing works like a dense array for ``[a:b, a:b]`` and ``[np.ix_(rows, cols)]``; ``dense()`` forms
    the whole inverse when it is really wanted.
    """

    def __init__(self, S, n_global: int | None = None, earlier=None) -> None:
        """``earlier``: a factor of a system of ``S``'s pattern (:meth:`ReducedSolver.spend`), whose analysis
        serves (:func:`factorise`)."""
        # factorised, not solved by conjugate gradients on a step's factor (:class:`ReducedSolver`): each of
        # their iterations would solve for every column asked, which costs more than one factorisation
        self.n = S.shape[0]
        self._lu, self.d = factorise(S, n_global, earlier=earlier)
        self._dense = None
        if self._lu is None:  # exactly singular: fall back to the pseudo-inverse
            self._dense = inverse_spd(sp.csc_matrix(S).toarray())
        self._cols: dict[int, np.ndarray] = {}

    def columns(self, cols: np.ndarray) -> np.ndarray:
        """The inverse's columns ``cols`` (n, len(cols))."""
        cols = np.asarray(cols, dtype=np.int64)
        if self._dense is not None:
            return self._dense[:, cols]
        missing = [int(c) for c in cols if int(c) not in self._cols]
        if missing and (len(self._cols) + len(missing)) * self.n * 8 > CACHE_BYTES:
            # the cached columns are whole columns (n each): 50 check points seen in ~8 images each ask for
            # ~2400 columns, 1.5 GB at 12,800 images (76,800 rows); keep only what this call asks for
            asked = set(cols.tolist())
            self._cols = {c: v for c, v in self._cols.items() if c in asked}
        if missing:
            E = np.zeros((self.n, len(missing)))
            E[missing, np.arange(len(missing))] = 1.0
            X = self.solve(E)
            for k, c in enumerate(missing):
                self._cols[c] = X[:, k]
        return np.column_stack([self._cols[int(c)] for c in cols]) if len(cols) else np.zeros((self.n, 0))

    def solve(self, E: np.ndarray) -> np.ndarray:
        """``S^-1 E`` for (n, k) ``E``, without keeping the columns."""
        E = np.asarray(E, dtype=float).reshape(self.n, -1)
        if self._dense is not None:
            return self._dense @ E
        return self._lu.solve(E / self.d[:, None]) / self.d[:, None]

    def __getitem__(self, key) -> np.ndarray:
        rows, cols = key
        idx = np.arange(self.n)
        rows = idx[rows] if isinstance(rows, slice) else np.asarray(rows).ravel()
        cols = idx[cols] if isinstance(cols, slice) else np.asarray(cols).ravel()
        return self.columns(cols)[rows]

    def dense(self) -> np.ndarray:
        return self._dense if self._dense is not None else self.columns(np.arange(self.n))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n, self.n)


#: a Levenberg-Marquardt step that lowers the chi-square (twice the cost) by less than this has converged: the
#: step moved the estimate by about sqrt(0.05) = 0.22 of its standard deviation along it
CHI2_TOLERANCE = 0.05


def levenberg_marquardt(
    cfg: AdjustConfig, cost: float, step: Callable[[float], tuple[float, float]], accept: Callable[[], float],
    reject: Callable[[], None],
) -> tuple[float, int, bool, list[float]]:
    """The damping and stopping rule of :func:`solve` and :func:`aerocal.adjust.partition.solve_partitioned`.

    ``cost``: at the start, already linearised there; ``step(lam)``: solve the normal equations damped by
    ``lam``, form the candidate state and return ``(its cost, dc . rhs)``; ``accept()``: move to the candidate,
    linearise there and return the cost; ``reject()``: drop it. Returns ``(cost, iterations, converged,
    history)``.

    The damping follows Nielsen's rule (as Ceres's Levenberg-Marquardt strategy does): an accepted step divides
    ``lam`` by at most 3, less where the cost fell by less than the linear model predicted (half the step's
    ``dc . rhs``); a rejected one multiplies it by 2, 4, 8, ... A fixed factor of 10 both ways leaves a block
    whose full step overshoots alternating between two dampings a decade apart, one short step in two iterations,
    and a capped robust pass then ends short of the optimum (a real block where it did, and what it cost the
    certificate: ``benchmarks/RESULTS.md``, "copr: the damping rule").
    """
    lam = 1e-4
    grow = 2.0  # the factor of the next rejection
    history = [cost]
    converged = False
    it = 0
    for _ in range(cfg.max_iterations):
        it += 1
        new_cost, step_metric = step(lam)
        if np.isfinite(new_cost) and new_cost <= cost:
            rel = (cost - new_cost) / max(cost, 1e-300)
            history.append(new_cost)
            # gain ratio: the decrease against the linear model's (dc . rhs / 2, the points' share left out)
            gain = (cost - new_cost) / max(0.5 * abs(step_metric), 1e-300)
            lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * min(gain, 1.0) - 1.0) ** 3), 1e-12)
            grow = 2.0
            cost = accept()
            # camera-side step in its own metric (dc' S dc = dc' rhs): below step_tolerance^2 the cameras
            # and IO moved by less than step_tolerance of their standard deviation; what still moves then
            # are tie points without a determined position (e.g. a two-ray track with a blunder under a
            # robust loss, which slides off along its rays and would keep the cost creeping down)
            # or the step lowered the chi-square by less than CHI2_TOLERANCE. A block whose datum only weak GNSS
            # holds (the rendered xt2-survey, no GCPs, 2 / 5 m: a direction of 1e-8 of the others' information)
            # otherwise creeps along that direction, a fraction of a sigma a step, and never meets the relative
            # tolerance; stopped there it is about a sigma along that datum-like direction from where many more
            # steps take it, with the same sigma0 (benchmarks/history/engine_measurements.md)
            if (rel < cfg.tolerance or abs(step_metric) < cfg.step_tolerance**2
                    or 2.0 * (history[-2] - new_cost) < CHI2_TOLERANCE):
                converged = True
                break
        else:
            reject()
            lam *= grow
            grow *= 2.0
            if lam > 1e8:
                converged = True  # no further decrease possible: at the minimum to machine precision
                break
    return cost, it, converged, history


def redundancy(problem: BundleProblem) -> int:
    """Degrees of freedom of ``problem``: its residuals (2 per image observation, 3 per image and prior, 3 per
    control GCP) less its unknowns; an :class:`AdjustmentError` when there is no redundancy.

    Raises:
        AdjustmentError: the problem has no more residuals than unknowns (no redundancy).
    """
    b, lay = problem.b, problem.layout
    priors = (problem.gnss_sigma is not None) + (problem.att_sigma is not None)
    n_res = 2 * len(b.obs_image) + 3 * b.n_images * priors + 3 * len(b.control_ids) + len(problem.laser or ())
    n_unk = lay.n_camera + 3 * lay.n_points
    if n_res <= n_unk:
        raise AdjustmentError(f"the adjustment has {n_res} observations for {n_unk} unknowns: no redundancy")
    return n_res - n_unk


def solve(problem: BundleProblem, start: State, covariance: bool = True) -> Solution:
    """Levenberg-Marquardt from ``start``; returns the solution and the camera-side covariance.

    ``covariance=False``: the solution's ``cov_camera`` is None, for callers that read only its state and
    residuals (a simulated twin, a held-out fold's fit): the covariance costs a Schur reduction and a
    factorisation at the solution, about one iteration more."""
    # the linearisation at the current state: (cost, res_px, w, r, Jc, Jp, Hpp); problem.blocks holds its blocks
    st, cand = start, None
    lin = problem.residuals(st, jac=True, sparse=False)
    if problem.depth_floor is None:
        problem.set_depth_floor(problem.last_depth[problem.point_view().is_tie])
    cand_lin = None
    reduced = ReducedSolver(n_global=problem.layout.n_global)

    def step(lam: float) -> tuple[float, float]:
        nonlocal cand, cand_lin
        _, _, _, r, Jc, Jp, Hpp = lin
        S, rhs, Hpp_inv, Hcp, gp = schur_complement(Jc, Jp, Hpp, r, lam, problem.blocks)
        dc = reduced.solve(S, rhs)
        dp = -np.einsum("pij,pj->pi", Hpp_inv, (gp + Hcp.T @ dc).reshape(-1, 3)).ravel()
        step_metric = float(dc @ rhs)
        # the reduced system and the operator's per-observation blocks (~0.3 kB per observation) are not
        # needed past the step: freed before the next residuals are evaluated next to them
        del S, Hpp_inv, Hcp, gp
        cand = problem.apply(st, dc, dp)
        # linearised at the candidate at once: most steps are accepted, and an accepted step then needs no
        # second projection of every observation (a rejected one re-linearises at the current state). The
        # points the step brought too close to a camera are found from the same projection's depths and,
        # when there are any (rarely), put back and the candidate linearised again (one projection without
        # Jacobians a step less)
        cand_lin = problem.residuals(cand, jac=True, sparse=False)
        if problem.hold_close_points(st, cand, problem.last_depth):
            cand_lin = None
            cand_lin = problem.residuals(cand, jac=True, sparse=False)
        if not cand_lin[0] <= lin[0] and problem.b.n_tie:
            # the linear step failed: before it is damped, the points are moved to where the candidate cameras
            # put them (one Gauss-Newton step per point, cameras fixed; an embedded point iteration). A step that
            # turns the whole block (a direction that only weak GNSS holds) moves far-off points by omega x X to
            # first order only: on real h20t_forest (two strips, 2 / 5 m GNSS, no attitude records) a 2 degree turn
            # left about 0.5 px RMS of second-order error (from the cost of a rejected step), each undamped step was
            # rejected and Levenberg-Marquardt crept along the turn between lam 1e-5 and 1e-6 for 150 iterations
            cand.X += problem.point_step(cand_lin[6], lam)
            cand_lin = None
            cand_lin = problem.residuals(cand, jac=True, sparse=False)
            if problem.hold_close_points(st, cand, problem.last_depth):
                cand_lin = None
                cand_lin = problem.residuals(cand, jac=True, sparse=False)
        return cand_lin[0], step_metric

    def accept() -> float:
        nonlocal st, cand, lin, cand_lin
        st, lin, cand, cand_lin = cand, cand_lin, None, None
        return lin[0]

    def reject() -> None:
        nonlocal cand, cand_lin, lin
        cand, cand_lin, lin = None, None, None
        lin = problem.residuals(st, jac=True, sparse=False)

    _, it, converged, history = levenberg_marquardt(problem.cfg, lin[0], step, accept, reject)
    cost, res_px, w, r, Jc, Jp, Hpp = lin
    cov = None
    if covariance:
        S, _, _, _, _ = schur_complement(Jc, Jp, Hpp, r, 0.0, problem.blocks)
    problem.release()
    res_px, w = problem.in_block_order(res_px), problem.in_block_order(w)
    if covariance:
        cov = SparseInverse(S, problem.layout.n_global, earlier=reduced.spend())
    dof = redundancy(problem)
    sigma0 = float(np.sqrt(2.0 * cost / dof))
    return Solution(
        state=st,
        layout=problem.layout,
        cov_camera=cov,
        sigma0=sigma0,
        dof=dof,
        cost=cost,
        iterations=it,
        converged=converged,
        obs_residual_px=res_px,
        obs_weight=w,
        t0=problem.t0,
        history=history,
    )
