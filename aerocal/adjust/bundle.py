"""The top-level bundle adjustment: tables in, :class:`AdjustmentResult` out.

Inputs are the Arrow tables of :mod:`aerocal.tables` (images with recorded GNSS/IMU and sensor
temperature, tie-point observations, GCPs and their image observations), a starting :class:`Camera`
and an :class:`AdjustConfig`. Initial values: poses from the recorded GNSS/IMU, tie points by
multi-ray triangulation with those poses and the starting camera, control GCPs at their surveyed
coordinates. Check points stay out of the adjustment and are triangulated afterwards.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from aerocal import tables
from aerocal.adjust.covariance import (
    correlation,
    global_covariance,
    global_names,
    rho_per_axis,
    t_critical,
    t_values,
    triangulate_check_points,
)
from aerocal.adjust.problem import AdjustConfig, AdjustmentError, Block, RobustLoss, build_block
from aerocal.adjust.projection import IDX, THERMAL_PARAMS, project
from aerocal.adjust.selection import select_parameters
from aerocal.adjust.solver import (
    MIN_DEPTH_FRACTION,
    BundleProblem,
    Solution,
    SparseInverse,
    State,
    schur_complement,
    solve,
)
from aerocal.adjust.thinning import ThinningConfig, thin_tracks
from aerocal.adjust.triangulate import (
    MAX_DEPTH_RATIO,
    MAX_POINT_SIGMA_FRACTION,
    pixels_to_rays,
    placed_by_rays,
    refine_points,
    triangulate_linear,
)
from aerocal.camera import PARAM_NAMES, Camera, LinearThermalModel, correct_measurements
from aerocal.geometry import matrix_from_quat_wxyz, quat_wxyz_from_matrix
from aerocal.poses import poses_arrays


@dataclass
class AdjustmentResult:
    """Everything an adjustment estimated, with its precision; world coordinates in the flight CRS.

    * ``camera``: IO at the reference temperature ``t0`` (degC); ``thermal`` the estimated linear model
      (``None`` without thermal slopes).
    * ``names``: the free global unknowns (IO names, thermal slopes as ``df/dT``, ``dcx/dT``, ...);
      ``covariance`` / ``correlation`` in that order; ``sigmas`` / ``t_values`` per name; ``significant``
      = t above the two-sided 95 % critical value. t is measured against the starting camera's value
      for f, cx, cy and against zero for the other parameters and the slopes.
    * ``residuals``: predicted minus observed pixels (M, 2) aligned with the rows of the observations
      table (NaN for observations of tracks that could not be triangulated).
    * ``obs_weight``: the robust weight rho'(s) (M,) of each tie observation at the solution, aligned
      the same way (1 without a robust loss; near 0 for a blunder; NaN where ``residuals`` is NaN).
    * check points: ``check_errors`` triangulated minus surveyed (K, 3) metres (E, N, Up);
      ``check_sigma`` predicted std per axis (marginal covariance scaled by sigma0^2, plus survey
      variance); ``rho`` = RMSE / sqrt(mean predicted variance) per axis.
    * ``tie_sigma_scale``: the factor the tie observations' sigma was multiplied by after the blunder
      screening (``AdjustConfig.estimate_tie_sigma``; 1 without).
    * ``dropped``: parameters the adaptive selection dropped -> (why, their t value when dropped).
    """

    camera: Camera
    thermal: LinearThermalModel | None
    t0: float
    names: list[str]
    sigmas: dict[str, float]
    covariance: np.ndarray
    correlation: np.ndarray
    t_values: np.ndarray
    significant: dict[str, bool]
    thermal_slopes: dict[str, float]
    thermal_sigmas: dict[str, float]
    poses: pa.Table
    points: pa.Table
    sigma0: float
    reprojection_rms: float
    dof: int
    iterations: int
    converged: bool
    residuals: np.ndarray
    control_ids: list[str]
    control_errors: np.ndarray
    check_ids: list[str]
    check_errors: np.ndarray
    check_sigma: np.ndarray
    check_rmse: np.ndarray
    rho: np.ndarray
    config: AdjustConfig
    selection: list[str] = field(default_factory=list)
    crs: str | None = None
    obs_weight: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tie_sigma_scale: float = 1.0
    dropped: dict[str, tuple[str, float]] = field(default_factory=dict)
    #: the sigmas given the dropped parameters' values (the last adjustment's own) where an adaptive selection
    #: dropped IO parameters and :attr:`sigmas` are marginal over them (:func:`marginal_covariance`); else empty
    conditional_sigmas: dict[str, float] = field(default_factory=dict)
    #: one sentence: what :attr:`sigmas` are marginal over (and what they are still given), with both sigmas
    marginal_note: str = ""
    #: the rows of the observations table the least-squares adjustment used after the blunder screening; None
    #: where none was run (``robust_loss`` "none" or ``reject_chi2`` None)
    kept_rows: np.ndarray | None = None

    def summary(self) -> dict:
        """Figures a user checks, JSON-serialisable."""
        return {
            "camera": self.camera.to_dict(),
            "t0": self.t0,
            "sigmas": self.sigmas,
            "t_values": dict(zip(self.names, np.round(self.t_values, 3).tolist(), strict=True)),
            "thermal_slopes": self.thermal_slopes,
            "thermal_sigmas": self.thermal_sigmas,
            "sigma0": self.sigma0,
            "reprojection_rms_px": self.reprojection_rms,
            "dof": self.dof,
            "check_rmse_m": self.check_rmse.tolist(),
            "rho": self.rho.tolist(),
            "selection": self.selection,
            "tie_sigma_scale": self.tie_sigma_scale,
        }


def _drop_points(block: Block, keep: np.ndarray) -> Block:
    """The block without the points where ``keep`` is False (and their observations)."""
    new_index = np.cumsum(keep) - 1
    obs_keep = keep[block.obs_point]
    n_tie = int(keep[: block.n_tie].sum())
    return dataclasses.replace(
        block,
        obs_image=block.obs_image[obs_keep],
        obs_point=new_index[block.obs_point[obs_keep]],
        obs_uv=block.obs_uv[obs_keep],
        obs_sigma=block.obs_sigma[obs_keep],
        obs_is_tie=block.obs_is_tie[obs_keep],
        obs_row=block.obs_row[obs_keep],
        n_tie=n_tie,
        track_ids=block.track_ids[keep[: block.n_tie]],
    )


def _intersect_in_front(
    point_idx: np.ndarray, n_points: int, axis: np.ndarray, C: np.ndarray, rays: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rays intersected per point (:func:`triangulate_linear`; per-observation optical ``axis`` (the third row
    of the world-to-camera rotation), centre ``C`` and ``rays``) and the mask of points that lie in front of
    every camera seeing them, not closer to one than ``MIN_DEPTH_FRACTION`` of the median depth."""
    X, ok = triangulate_linear(point_idx, n_points, C, rays)
    if ok.any():
        depth = np.einsum("mk,mk->m", axis, np.nan_to_num(X[point_idx]) - C)
        typical = np.median(depth[depth > 0]) if (depth > 0).any() else 0.0
        front = np.ones(n_points, bool)
        np.logical_and.at(front, point_idx, depth > MIN_DEPTH_FRACTION * typical)
        ok &= front
    return X, ok


def initial_state(block: Block, camera: Camera) -> tuple[Block, State]:
    """Poses from the recorded GNSS/IMU, tie points triangulated, control GCPs at their surveyed position.

    Raises:
        AdjustmentError: no tie track can be triangulated in front of the cameras from the recorded poses; check the
            images' GNSS positions and attitude convention.
    """
    io = camera.params()
    slopes = np.zeros(3)
    i, j = block.obs_image, block.obs_point
    tie = block.obs_is_tie
    it = i[tie]
    rays = pixels_to_rays(io, slopes, 0.0, block.R_rec, block.obs_uv[tie], image=it)
    X, ok = _intersect_in_front(j[tie], block.n_tie, block.R_rec[it, 2], block.gnss[it], rays)
    keep = np.concatenate([ok, np.ones(len(block.control_ids), bool)])
    if not ok.any():
        raise AdjustmentError("observations: no tie track could be triangulated from the recorded poses")
    if not keep.all():
        block = _drop_points(block, keep)
        X = X[ok]
    Xall = np.vstack([X, block.control_xyz]) if len(block.control_ids) else X
    return block, State(io=io, slopes=slopes, R=block.R_rec.copy(), C=block.gnss.copy(), X=Xall)


def _poses_table(block: Block, st: State) -> pa.Table:
    q = quat_wxyz_from_matrix(st.R)
    C = st.C + block.origin
    return tables.from_columns(
        "poses",
        {
            "image_id": block.image_ids,
            "qw": q[:, 0],
            "qx": q[:, 1],
            "qy": q[:, 2],
            "qz": q[:, 3],
            "X": C[:, 0],
            "Y": C[:, 1],
            "Z": C[:, 2],
        },
        crs=block.crs,
    )


def _points_table(block: Block, sol: Solution) -> tuple[pa.Table, int]:
    """The adjusted tie points the rays place (:func:`placed_by_rays`), by track id, and how many were not."""
    tie = block.obs_is_tie
    j = block.obs_point[tie]
    err = np.linalg.norm(sol.obs_residual_px[tie], axis=1)
    n = np.bincount(j, minlength=block.n_tie)
    mean_err = np.bincount(j, weights=err, minlength=block.n_tie) / np.maximum(n, 1)
    st = sol.state
    placed = placed_by_rays(st.X[: block.n_tie], st.R, st.C, block.obs_image[tie], j, block.obs_sigma[tie],
                            float(st.io[0]))
    X = st.X[: block.n_tie] + block.origin
    order = np.argsort(block.track_ids, kind="stable")  # by track id, whatever the block's numbering
    order = order[placed[order]]
    return tables.from_columns(
        "points",
        {
            "track_id": block.track_ids[order],
            "X": X[order, 0],
            "Y": X[order, 1],
            "Z": X[order, 2],
            "n_obs": n[order].astype(np.int32),
            "error": mean_err[order],
        },
        crs=block.crs,
    ), int(block.n_tie - len(order))


def _result(
    block: Block, sol: Solution, camera: Camera, config: AdjustConfig, n_obs_rows: int
) -> AdjustmentResult:
    st = sol.state
    names = global_names(sol)
    cov = global_covariance(sol, scale=config.scale_covariance)
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    est = np.concatenate([st.io[sol.layout.io_free], st.slopes[sol.layout.slope_free]])
    start = camera.params()
    ref = np.array(
        [start[IDX[n]] if n in ("f", "cx", "cy") else 0.0 for n in names[: len(sol.layout.io_free)]]
        + [0.0] * len(sol.layout.slope_free)
    )
    t = t_values(est, ref, sig)

    tcrit = t_critical(sol.dof)
    cam = camera.with_params(st.io)
    thermal = None
    slopes: dict[str, float] = {}
    slope_sig: dict[str, float] = {}
    if sol.layout.slope_free:
        for k, idx in enumerate(sol.layout.slope_free):
            name = f"d{THERMAL_PARAMS[idx]}/dT"
            slopes[name] = float(st.slopes[idx])
            slope_sig[name] = float(sig[len(sol.layout.io_free) + k])
        temps = block.temperature[np.isfinite(block.temperature)]
        thermal = LinearThermalModel(
            t0=sol.t0,
            df_dt=float(st.slopes[0]),
            dcx_dt=float(st.slopes[1]),
            dcy_dt=float(st.slopes[2]),
            valid_range=(float(temps.min()), float(temps.max())),
        )
    # residuals aligned with the observations table
    res = np.full((n_obs_rows, 2), np.nan)
    rows = block.obs_row
    res[rows[rows >= 0]] = sol.obs_residual_px[rows >= 0]
    weight = np.full(n_obs_rows, np.nan)
    weight[rows[rows >= 0]] = sol.obs_weight[rows >= 0]
    tie_res = sol.obs_residual_px[block.obs_is_tie]
    rms = float(np.sqrt(np.mean(np.sum(tie_res**2, axis=1)) / 2.0)) if len(tie_res) else float("nan")
    # control points: adjusted minus surveyed
    ctrl_err = (st.X[block.n_tie :] - block.control_xyz) if block.control_ids else np.zeros((0, 3))
    # check points
    chk = triangulate_check_points(block, sol, scale=config.scale_covariance)
    err = chk.xyz - block.check_xyz
    var = np.einsum("kii->ki", chk.cov) + block.check_sigma**2 if len(chk.ids) else np.zeros((0, 3))
    good = np.isfinite(err).all(axis=1)
    rmse = np.sqrt(np.mean(err[good] ** 2, axis=0)) if good.any() else np.full(3, np.nan)
    points, unplaced = _points_table(block, sol)
    return AdjustmentResult(
        camera=cam,
        thermal=thermal,
        t0=sol.t0,
        names=names,
        sigmas=dict(zip(names, sig.tolist(), strict=True)),
        covariance=cov,
        correlation=correlation(cov),
        t_values=t,
        significant={n: bool(v > tcrit) for n, v in zip(names, t, strict=True)},
        thermal_slopes=slopes,
        thermal_sigmas=slope_sig,
        poses=_poses_table(block, st),
        points=points,
        sigma0=sol.sigma0,
        reprojection_rms=rms,
        dof=sol.dof,
        iterations=sol.iterations,
        converged=sol.converged,
        residuals=res,
        control_ids=list(block.control_ids),
        control_errors=ctrl_err,
        check_ids=list(chk.ids),
        check_errors=err,
        check_sigma=np.sqrt(var),
        check_rmse=rmse,
        rho=rho_per_axis(err, var),
        config=config,
        crs=block.crs,
        obs_weight=weight,
        selection=[f"{unplaced} adjusted tie points not handed back: their rays do not place them (behind a "
                   f"camera, nearly parallel: sigma along them above {MAX_POINT_SIGMA_FRACTION:g} of their depth, "
                   f"or deeper in a camera than {MAX_DEPTH_RATIO:g} times the mean depth of its points)"]
        if unplaced else [],
    )


def adjust(
    images: pa.Table,
    observations: pa.Table,
    camera: Camera,
    config: AdjustConfig | None = None,
    gcps: pa.Table | None = None,
    gcp_observations: pa.Table | None = None,
    thermal_correction: LinearThermalModel | None = None,
    initial_poses: pa.Table | None = None,
    solver: Callable[[BundleProblem, State], Solution] | None = None,
    initial: AdjustmentResult | None = None,
) -> AdjustmentResult:
    """Bundle adjustment with self-calibration (IO free or fixed per parameter) and an optional thermal model.

    Args:
        images: the ``images`` table (:mod:`aerocal.tables`): recorded positions in the flight CRS (metres) and
            attitudes, temperatures (degC), strips.
        observations: tie-point measurements, pixels (top-left corner origin, x right, y down).
        camera: the starting IO (pixels); the nominal camera, or a certificate's.
        config: what is free and how the block is weighted (default :class:`AdjustConfig`: GNSS 0.10 / 0.10 /
            0.15 m, IO fixed). With ``config.adaptive`` insignificant or near-singular parameters are dropped one
            at a time and the block re-adjusted; ``result.selection`` says why each was dropped.
        gcps, gcp_observations: ground control (flight CRS, metres, with survey sigmas) and its pixels; a
            ``check`` point is held out of the adjustment and triangulated afterwards.
        thermal_correction: correct tie-point and GCP measurements to the model's reference temperature before
            adjusting (Daakir 2019), ``camera`` then being the IO at that temperature.
        initial_poses: starting poses from an orientation (a poses table) for blocks without recorded
            GNSS/IMU; the priors must then be off and at least 3 control GCPs give the datum.
        solver: what solves each least-squares problem (default :func:`aerocal.adjust.solver.solve`; a
            partitioned one, :class:`aerocal.adjust.partition.PartitionedSolver`, for city-scale blocks).
        initial: an earlier adjustment of the same images and ``observations`` table to start from: its poses
            and tie points, and its estimate of the IO parameters and thermal slopes ``config`` frees (the ones
            it holds start at ``camera``'s values); where it screened blunders (``initial.kept_rows``), the same
            observations are left out and its tie sigma is the start of this one's, with no robust pass. A
            nested model (a parameter freed or dropped) then starts next to its optimum and is fitted to the
            same data as the model it extends.

    Returns:
        :class:`AdjustmentResult`: poses, points, IO with covariance, residuals aligned with ``observations``,
        check-point errors and their predicted sigmas (metres, E N Up), and whether it converged.

    Raises:
        AdjustmentError: the block has no datum (no GNSS/IMU priors and fewer than 3 control GCPs), or no tie
            track can be triangulated from the starting poses; the message names the fix.
    """
    config = config or AdjustConfig()
    if config.tie_thinning is not None and config.tie_thinning.per_cell:
        used = thin_tracks(observations, camera.width, camera.height, config.tie_thinning)
        inner = adjust(images, observations.take(pa.array(used, pa.int64())), camera,
                       dataclasses.replace(config, tie_thinning=None), gcps, gcp_observations,
                       thermal_correction, initial_poses, solver, initial)
        return _intersect_left_out(inner, images, observations, used, camera, thermal_correction,
                                   config.tie_thinning)
    n_rows = observations.num_rows
    kept = np.arange(n_rows)
    tie_scale = 1.0
    rejection: list[str] = []
    first = None
    screened = config.robust_loss != RobustLoss.NONE and config.reject_chi2 is not None
    reuse = (screened and initial is not None and initial.kept_rows is not None
             and len(initial.residuals) == n_rows)
    if reuse:
        # the blunders the adjustment this one starts from found are left out again: nested models are compared
        # on the same observations, and no robust pass runs (one can slide away from the optimum it starts at:
        # benchmarks/RESULTS.md, "h20t_forest: the self-calibration starts each model from the one it extends")
        kept = initial.kept_rows
        rejection.append(f"{n_rows - len(kept)} of {n_rows} observations left out as the adjustment this one "
                         "starts from screened them")
        observations = observations.take(pa.array(kept, pa.int64()))
        a_priori = float(np.median(observations.column("sigma").to_numpy(zero_copy_only=False)))
        if config.estimate_tie_sigma:
            tie_scale = initial.tie_sigma_scale
            observations = scale_tie_sigma(observations, tie_scale)
        config = dataclasses.replace(config, robust_loss=RobustLoss.NONE)
    elif screened:
        # a robust pass finds the blunders, they are removed, and the block is adjusted by least squares
        # (data snooping): sigma0, covariances and the check-point prediction then describe clean data
        robust_cfg = dataclasses.replace(config, adaptive=False, max_iterations=config.robust_iterations)
        first = adjust(images, observations, camera, dataclasses.replace(robust_cfg, reject_chi2=None), gcps,
                       gcp_observations, thermal_correction, initial_poses, solver, initial)
        kept, why, variance_factor = _snoop(observations, first, config.reject_chi2)
        rejection.append(why)
        observations = observations.take(pa.array(kept, pa.int64()))
        a_priori = float(np.median(observations.column("sigma").to_numpy(zero_copy_only=False)))
        if config.estimate_tie_sigma:
            tie_scale = float(np.sqrt(variance_factor))
            observations = scale_tie_sigma(observations, tie_scale)
        config = dataclasses.replace(config, robust_loss=RobustLoss.NONE)

    def setup(obs: pa.Table, previous: AdjustmentResult | None) -> tuple[Block, State]:
        blk0 = build_block(images, obs, gcps, gcp_observations, config, thermal_correction=thermal_correction,
                           correction_camera=camera, initial_poses=initial_poses)
        blk, st = initial_state(blk0, camera)
        return blk, (_warm_start(blk, st, previous) if previous is not None else st)

    warm = [first if first is not None else initial]  # the adjustment the free IO starts from (None: ``camera``)
    block, start = setup(observations, warm[0])
    if config.thermal_t0 is not None:
        t0 = float(config.thermal_t0)
    elif np.isfinite(block.temperature).any():
        t0 = float(np.nanmedian(block.temperature))
    else:
        t0 = 0.0

    last: list[Solution] = []  # the last run's solution (the selection's result is the last run's)

    def run(cfg: AdjustConfig) -> AdjustmentResult:
        # the adaptive selection's next model starts where the last one ended on this block: a dropped
        # parameter back at its starting value, the others as they were
        st = (_held_at_start(last[0].state, start, cfg) if last and last[0].state.X.shape == start.X.shape
              else _free_io_from(start, warm[0], cfg, t0) if warm[0] is not None else start)
        sol = (solver or solve)(BundleProblem(block, cfg, t0), st)
        last[:] = [sol]
        return _result(block, sol, camera, cfg, observations.num_rows)

    final = None  # the least-squares result with the final tie sigma, when it is already at hand
    if screened and config.estimate_tie_sigma:
        # the robust pass's residuals estimate the tie sigma only as well as that pass converged (a nominal
        # camera far off in f leaves it far off): re-estimate from the least-squares residuals until the factor
        # is within TIE_SIGMA_TOLERANCE
        for _ in range(TIE_SIGMA_ROUNDS):
            trial = run(dataclasses.replace(config, adaptive=False))
            factor = float(np.sqrt(_tie_variance_factor(trial, observations)))
            if abs(factor - 1.0) <= TIE_SIGMA_TOLERANCE:
                final = trial
                break
            tie_scale *= factor
            observations = scale_tie_sigma(observations, factor)
            block, start = setup(observations, trial)
            warm[0] = trial
            last.clear()
        rejection.append(
            f"tie-point sigma estimated from the block: {a_priori:.3g} px a priori x {tie_scale:.3f} = "
            f"{a_priori * tie_scale:.3g} px (GNSS, attitude and GCP sigmas keep their a-priori values)"
        )
    if not config.adaptive:
        result = final if final is not None else run(config)
        final_cfg, freed = config, []
    else:
        result, reasons, final_cfg = select_parameters(run, config)
        result.selection = reasons + result.selection
        freed = [n for n in result.dropped if n in config.free]
    freed += [n for n in config.marginal_over if n not in final_cfg.free and n not in freed]
    if freed:
        cov, note = marginal_covariance(block, last[0], final_cfg, freed, config.singular_corr,
                                        scale=config.scale_covariance)
        result.conditional_sigmas = dict(result.sigmas)
        sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
        result.sigmas = dict(zip(result.names, sig.tolist(), strict=True))
        result.covariance, result.correlation = cov, correlation(cov)
        result.thermal_sigmas = {n: result.sigmas[n] for n in result.thermal_sigmas}
        result.marginal_note = note
    if rejection:
        result.selection = rejection + result.selection
        res = np.full((n_rows, 2), np.nan)
        res[kept] = result.residuals
        weight = np.zeros(n_rows)  # a rejected observation has weight 0
        weight[kept] = result.obs_weight
        result.residuals, result.obs_weight = res, weight
    result.tie_sigma_scale = tie_scale
    result.kept_rows = kept if screened else None
    return result


def marginal_covariance(block: Block, sol: Solution, config: AdjustConfig, freed: list[str], singular_corr: float,
                        scale: bool = True) -> tuple[np.ndarray, str]:
    """Covariance of the free parameters of ``config`` (an adjustment's solution ``sol``, order of
    :func:`global_names`) with the IO parameters ``freed`` (ones an adaptive selection dropped and held at
    their value) free again at the same solution, and one sentence saying so: ``(cov, note)``.

    A dropped parameter is held exactly, so the sigmas of the kept ones are conditional on its value. On a
    narrow field they were several times too small: conte-calibration (44 images, tie noise 0.15 px, the
    pipeline's selection), seeds 0-3, the errors of the kept parameters reached 10.9 (k1, k2 true 0.12 dropped),
    4.9 (cx) and 3.7 (cy, p2 dropped) of their conditional sigmas, and at most 2.3 of the sigmas marginal over
    the dropped parameters (k1's 0.0008 -> 0.0067). A freed parameter the block cannot tell from another
    (|correlation| above ``singular_corr`` with the others free) would make the matrix singular: it stays held,
    and the note says so."""
    keep = [n for n in freed if n in PARAM_NAMES]
    held: list[str] = []
    names = global_names(sol)
    while True:
        cfg = dataclasses.replace(config, free=tuple(config.free) + tuple(keep))
        prob = BundleProblem(block, cfg, sol.t0)
        Hpp = prob.residuals(sol.state, jac=True, sparse=False)[6]
        S = schur_complement(None, None, Hpp, None, 0.0, prob.blocks)[0]
        prob.release()
        ng = prob.layout.n_global
        full = SparseInverse(S, ng).columns(np.arange(ng))[:ng]
        full = 0.5 * (full + full.T) * (sol.sigma0**2 if scale else 1.0)
        full_names = [PARAM_NAMES[i] for i in prob.layout.io_free] + \
            [f"d{THERMAL_PARAMS[i]}/dT" for i in prob.layout.slope_free]
        corr = np.abs(correlation(full)) - np.eye(ng)
        worst = {n: float(corr[full_names.index(n)].max()) for n in keep}
        bad = [n for n in keep if worst[n] > singular_corr]
        if not bad:
            break
        n = max(bad, key=lambda q: worst[q])
        keep.remove(n)
        held.append(f"{n} (|correlation| {worst[n]:.4f} > {singular_corr:g} with the others free)")
    k = [full_names.index(n) for n in names]
    cov = full[np.ix_(k, k)]
    sig = np.sqrt(np.maximum(np.diag(cov), 0.0))
    note = ""
    if keep:
        values = ", ".join(f"{n} = {sol.state.io[PARAM_NAMES.index(n)]:.4g}" for n in keep)
        cond = np.sqrt(np.maximum(np.diag(sol.cov_camera[:len(names), :len(names)]), 0.0)) * \
            (sol.sigma0 if scale else 1.0)
        note = (f"sigmas marginal over {', '.join(keep)} (dropped and held at {values}; free again at the "
                "solution, what the block determines of the kept parameters whatever their value): "
                + ", ".join(f"{n} +-{s:.3g} (+-{c:.3g} given them)" for n, s, c in zip(names, sig, cond, strict=True)))
    if held:
        note += ("; " if note else "sigmas ") + "given " + ", ".join(held)
    return cov, note


#: Least-squares rounds that re-estimate the tie observations' sigma, and the relative change of it below
#: which they stop (:data:`AdjustConfig.estimate_tie_sigma`).
TIE_SIGMA_ROUNDS = 3
TIE_SIGMA_TOLERANCE = 0.05


def _tie_variance_factor(result: AdjustmentResult, observations: pa.Table) -> float:
    """Mean normalised squared residual of the tie observations over their mean redundancy: one number per
    block, the tie observations' share of the redundancy taken as the block's (dof / residual components),
    as in :func:`_snoop`."""
    sigma = observations.column("sigma").to_numpy(zero_copy_only=False).astype(float)
    s = np.sum(result.residuals**2, axis=1) / sigma**2
    s = s[np.isfinite(s)]
    if not len(s):
        return 1.0
    return _mean_variance_factor(s, float(np.clip(result.dof / (2.0 * len(s)), 0.1, 1.0)))


def _mean_variance_factor(s: np.ndarray, redundancy: float) -> float:
    """Mean of the normalised squared residuals ``s`` (2 components each) over the mean redundancy."""
    return max(float(np.mean(s)) / 2.0 / redundancy, 1e-12)


def scale_tie_sigma(observations: pa.Table, factor: float) -> pa.Table:
    """``observations`` with its ``sigma`` column (pixels) multiplied by ``factor``."""
    i = observations.schema.get_field_index("sigma")
    sigma = observations.column("sigma").to_numpy(zero_copy_only=False) * factor
    return observations.set_column(i, observations.schema.field(i), pa.array(sigma.astype(np.float32)))


def corrected_to_t0(images: pa.Table, observations: pa.Table | None, camera: Camera,
                    model: LinearThermalModel | None) -> pa.Table | None:
    """``observations`` (tie points or GCP measurements, pixels) corrected to ``model``'s reference temperature
    with each image's ``temperature_c``, as the block adjustment corrects them
    (:func:`aerocal.camera.correct_measurements`); unchanged without a model, a table or rows."""
    if model is None or observations is None or observations.num_rows == 0:
        return observations
    temp = dict(zip(images.column("image_id").to_pylist(), images.column("temperature_c").to_numpy(), strict=True))
    T = np.array([temp[i] for i in observations.column("image_id").to_pylist()], dtype=float)
    uv = np.column_stack([observations.column("x").to_numpy(), observations.column("y").to_numpy()])
    uv = correct_measurements(camera, uv, T, model)
    for k, name in enumerate(("x", "y")):
        observations = observations.set_column(observations.schema.get_field_index(name), name,
                                               pa.array(uv[:, k], observations.schema.field(name).type))
    return observations


def screened_rows(
    observations: pa.Table,
    residuals: np.ndarray,
    obs_weight: np.ndarray,
    tie_sigma_scale: float = 1.0,
    chi2: float | None = 13.8,
) -> np.ndarray:
    """Rows of ``observations`` a least-squares re-adjustment of the same block may use: those the
    adjustment kept (``obs_weight`` not 0), that it could place (finite ``residuals``, pixels), whose
    squared residual normalised by ``sigma x tie_sigma_scale`` is at most ``chi2`` (a robust pass leaves
    blunders with small but non-zero weights; tracks that thinning left out and intersection could not
    place have NaN residuals and NaN weights), and that still share their track with another such row.

    Keeping the robustly down-weighted and unplaced observations gave a re-adjustment of real seneca a
    sigma0 many times the block adjustment's (``benchmarks/history/engine_measurements.md``).
    """
    residuals = np.asarray(residuals, dtype=float).reshape(-1, 2)
    weight = np.asarray(obs_weight, dtype=float)
    sigma = observations.column("sigma").to_numpy(zero_copy_only=False).astype(float) * tie_sigma_scale
    s = np.sum(residuals**2, axis=1) / sigma**2
    good = np.isfinite(s) & (weight != 0)
    if chi2 is not None:
        good &= s <= chi2
    track = observations.column("track_id").to_numpy(zero_copy_only=False)
    _, inv, counts = np.unique(track[good], return_inverse=True, return_counts=True)
    rows = np.flatnonzero(good)
    return rows[counts[inv] >= 2]


def _intersect_left_out(
    inner: AdjustmentResult,
    images: pa.Table,
    observations: pa.Table,
    used: np.ndarray,
    camera: Camera,
    thermal_correction: LinearThermalModel | None,
    thinning: ThinningConfig,
) -> AdjustmentResult:
    """``inner`` (the adjustment of the rows ``used`` of ``observations``) completed with the tracks that
    thinning left out: each is intersected from the adjusted poses and IO held fixed (linear, then
    Gauss-Newton on the reprojection error, :mod:`aerocal.adjust.triangulate`).

    Their residuals fill the result's ``residuals``; their ``obs_weight`` is NaN (not in the block). An
    observation whose normalised squared residual, with the block's estimate of the tie sigma, exceeds
    ``reject_chi2`` gets weight 0 (a blunder) and its track is not added to ``points``. ``selection`` says
    how many tracks were adjusted and how many intersected.
    """
    n_rows = observations.num_rows
    res = np.full((n_rows, 2), np.nan)
    res[used] = inner.residuals
    weight = np.full(n_rows, np.nan)
    weight[used] = inner.obs_weight
    rest = np.setdiff1d(np.arange(n_rows), used)
    n_tracks = len(np.unique(observations.column("track_id").to_numpy()))
    n_used = len(np.unique(observations.column("track_id").to_numpy()[used]))
    added = flagged = unplaced = 0
    if len(rest):
        obs = observations.take(pa.array(rest, pa.int64()))
        p_ids, R, C = poses_arrays(inner.poses)
        origin = C.mean(axis=0)  # local frame: projected coordinates are ~1e6 m
        C = C - origin
        where = {int(k): n for n, k in enumerate(p_ids)}
        img = np.array([where.get(int(k), -1) for k in obs.column("image_id").to_numpy()])
        track_ids, j = np.unique(obs.column("track_id").to_numpy().astype(np.int64), return_inverse=True)
        uv = np.column_stack([obs.column(c).to_numpy(zero_copy_only=False) for c in ("x", "y")]).astype(float)
        sigma = obs.column("sigma").to_numpy(zero_copy_only=False).astype(float) * inner.tie_sigma_scale
        ids = images.column("image_id").to_numpy()
        temp = dict(zip(ids.tolist(), images.column("temperature_c").to_numpy(zero_copy_only=False).tolist(),
                        strict=True))
        T = np.array([temp[int(k)] for k in obs.column("image_id").to_numpy()], dtype=float)
        if thermal_correction is not None:
            uv = correct_measurements(camera, uv, T, thermal_correction)
        th = inner.thermal if isinstance(inner.thermal, LinearThermalModel) else None
        slopes = np.array([th.df_dt, th.dcx_dt, th.dcy_dt]) if th is not None else np.zeros(3)
        dtemp = np.nan_to_num(T - inner.t0) if th is not None else np.zeros(len(T))
        io = inner.camera.params()
        posed = img >= 0
        ok_track = np.ones(len(track_ids), bool)
        np.logical_and.at(ok_track, j, posed)
        i_safe = np.where(posed, img, 0)
        rays = pixels_to_rays(io, slopes, dtemp, R[i_safe], uv)
        X, ok = _intersect_in_front(j, len(track_ids), R[i_safe, 2], C[i_safe], rays)
        ok &= ok_track
        X, _ = refine_points(io, slopes, dtemp, R[i_safe], C[i_safe], j, uv, sigma, np.where(ok[:, None], X, 0.0))
        use = ok[j]  # the rays of the intersected points only: the others' X is a placeholder
        placed = ok & placed_by_rays(X, R, C, img[use], j[use], sigma[use], float(io[0]))
        unplaced = int(np.count_nonzero(ok & ~placed))
        ok &= placed
        r = project(io, slopes, dtemp, R[i_safe], C[i_safe], X[j], jacobians=False).uv - uv
        good_obs = ok[j] & np.isfinite(r).all(axis=1)
        res[rest[good_obs]] = r[good_obs]
        chi2 = inner.config.reject_chi2
        if chi2 is not None:
            s = np.sum(r**2, axis=1) / sigma**2
            bad = good_obs & (s > chi2)
            weight[rest[bad]] = 0.0
            flagged = int(bad.sum())
            np.logical_and.at(ok, j, ~bad)
        keep = ok & np.isfinite(X).all(axis=1)
        err = np.linalg.norm(np.where(good_obs[:, None], r, 0.0), axis=1)
        n_obs = np.bincount(j, minlength=len(track_ids))
        mean_err = np.bincount(j, weights=err, minlength=len(track_ids)) / np.maximum(n_obs, 1)
        X = X + origin
        extra = tables.from_columns("points", {
            "track_id": track_ids[keep], "X": X[keep, 0], "Y": X[keep, 1], "Z": X[keep, 2],
            "n_obs": n_obs[keep].astype(np.int32), "error": mean_err[keep],
        }, crs=inner.crs)
        added = int(keep.sum())
        points = pa.concat_tables([inner.points, extra.cast(inner.points.schema)])
        inner.points = points.take(pc.sort_indices(points, [("track_id", "ascending")]))
    inner.residuals, inner.obs_weight = res, weight
    inner.selection = [
        f"tie points thinned: {n_used} of {n_tracks} tracks adjusted ({len(used)} of {n_rows} observations: "
        f"the {thinning.per_cell} tracks with the most rays in each cell of {thinning.grid[0]} x "
        f"{thinning.grid[1]} per image); {added} more intersected afterwards from the adjusted poses and IO"
        + (f" ({unplaced} whose rays do not place them left out)" if unplaced else "")
        + (f", {flagged} of their observations rejected as blunders (normalised squared residual above "
           f"{inner.config.reject_chi2:g})" if inner.config.reject_chi2 is not None else "")
    ] + inner.selection
    return inner


def _warm_start(block: Block, start: State, first: AdjustmentResult) -> State:
    """``start`` with the poses and tie points of the robust pass ``first`` where it has them.

    The least-squares adjustment after the blunders are removed then starts next to its solution and needs
    fewer iterations. Each adjustment then starts its free IO at ``first``'s estimate too
    (:func:`_free_io_from`); the IO it holds keeps its starting value.
    """
    return warm_start(block, start, first.poses, first.points)


def _free_io_from(start: State, previous: AdjustmentResult, config: AdjustConfig, t0: float) -> State:
    """``start`` with the IO parameters and thermal slopes that ``config`` frees at ``previous``'s estimate (at the
    reference temperature ``t0``, degC); the ones it holds keep their starting values (the nominal camera's or a
    certificate's), so a parameter the adaptive selection drops is held where the caller put it.

    Why: the poses and tie points of a warm start are the earlier adjustment's, which its IO bent to fit; with
    the IO back at the nominal values they disagree with it, and the adjustment starts far from both (benchmarks/
    RESULTS.md, "h20t_forest: the self-calibration starts each model from the one it extends")."""
    st = start.copy()
    io = previous.camera.params()
    slopes = np.zeros(3)
    if previous.thermal is not None:
        slopes = np.array([previous.thermal.df_dt, previous.thermal.dcx_dt, previous.thermal.dcy_dt])
        io[[IDX[n] for n in THERMAL_PARAMS]] += slopes * (t0 - previous.t0)
    for name in config.free:
        if name in IDX:
            st.io[IDX[name]] = io[IDX[name]]
    for name in config.thermal:
        k = THERMAL_PARAMS.index(name)
        st.slopes[k] = slopes[k]
    return st


def _held_at_start(state: State, start: State, config: AdjustConfig) -> State:
    """``state`` (an adjustment's solution) with the IO parameters and thermal slopes ``config`` does not free
    put back at their values in ``start``."""
    st = state.copy()
    held = [IDX[n] for n in PARAM_NAMES if n not in config.free]
    st.io[held] = start.io[held]
    fixed = [k for k, n in enumerate(THERMAL_PARAMS) if n not in config.thermal]
    st.slopes[fixed] = start.slopes[fixed]
    return st


def warm_start(block: Block, start: State, poses: pa.Table, points: pa.Table) -> State:
    """``start`` with the poses and tie points of an earlier adjustment of the same images (``poses`` and
    ``points`` tables, world coordinates) where they have them; IO, the recorded observations and their
    weights are unchanged. A tie point the ``points`` table lacks is intersected again from the poses so set
    (where its rays meet in front of the cameras): left where the recorded GNSS/IMU put it, it is metres off
    the adjusted poses: on real seneca such tracks, started from the records, left some of the diagnosis
    re-adjustment's tie observations beyond the blunder threshold (``benchmarks/history/engine_measurements.md``)."""
    st = start.copy()
    where = {int(k): n for n, k in enumerate(block.image_ids.tolist())}
    pid = poses.column("image_id").to_numpy()
    rows = np.array([where.get(int(k), -1) for k in pid])
    ok = rows >= 0
    if ok.any():
        q = np.column_stack([poses.column(c).to_numpy() for c in ("qw", "qx", "qy", "qz")])[ok]
        st.R[rows[ok]] = matrix_from_quat_wxyz(q / np.linalg.norm(q, axis=1, keepdims=True)).reshape(-1, 3, 3)
        C = np.column_stack([poses.column(c).to_numpy() for c in ("X", "Y", "Z")])[ok]
        st.C[rows[ok]] = C - block.origin
    if block.n_tie:
        tid = points.column("track_id").to_numpy()
        X = np.column_stack([points.column(c).to_numpy() for c in ("X", "Y", "Z")])
        order = np.argsort(block.track_ids)
        ids = block.track_ids[order]
        pos = np.clip(np.searchsorted(ids, tid), 0, len(ids) - 1)
        found = (ids[pos] == tid) & np.isfinite(X).all(axis=1)
        st.X[order[pos[found]]] = X[found] - block.origin
        missing = np.ones(block.n_tie, dtype=bool)
        missing[order[pos[found]]] = False
        if missing.any():
            i, j = block.obs_image, block.obs_point
            sel = block.obs_is_tie & missing[np.minimum(j, block.n_tie - 1)] & (j < block.n_tie)
            if sel.any():
                isel = i[sel]
                rays = pixels_to_rays(st.io, st.slopes, 0.0, st.R, block.obs_uv[sel], image=isel)
                Xn, ok = _intersect_in_front(j[sel], block.n_tie, st.R[isel, 2], st.C[isel], rays)
                redo = missing & ok
                st.X[: block.n_tie][redo] = Xn[redo]
    return st


def _snoop(observations: pa.Table, first: AdjustmentResult, chi2: float) -> tuple[np.ndarray, str, float]:
    """Rows of ``observations`` kept after a robust adjustment ``first``, a sentence saying what went, and
    the variance factor of the kept tie observations.

    An observation is rejected when its squared residual, normalised by its sigma and by the robust
    variance factor, exceeds ``chi2``; tracks left with fewer than two observations go too. The robust
    variance factor is the median of the squared normalised residuals over 1.386 (the median of
    chi-square with 2 degrees of freedom) divided by the mean redundancy (dof / residual components):
    residuals of an adjustment are smaller than the errors they stand for by that much on average.
    """
    sigma = observations.column("sigma").to_numpy(zero_copy_only=False).astype(float)
    s = np.sum(first.residuals**2, axis=1) / sigma**2
    finite = np.isfinite(s)
    if not finite.any():
        return np.arange(observations.num_rows), "no residuals to screen for blunders", 1.0
    redundancy = float(np.clip(first.dof / (2.0 * np.count_nonzero(finite)), 0.1, 1.0))
    scale = max(float(np.median(s[finite])) / (2.0 * np.log(2.0)) / redundancy, 1e-12)
    bad = finite & (s > chi2 * scale)
    track = observations.column("track_id").to_numpy(zero_copy_only=False)
    _, inv, counts = np.unique(track[~bad], return_inverse=True, return_counts=True)
    lone = np.zeros(len(s), dtype=bool)
    lone[np.flatnonzero(~bad)[counts[inv] < 2]] = True
    kept = np.flatnonzero(~bad & ~lone)
    # the tie observations' variance factor: the mean of the kept (blunder-free) normalised squared
    # residuals, not the median: redundancy differs between observations (two-ray tracks have less), so the
    # median under-reads it (by 10-20 % in variance on conte-calibration, sigma0 1.11 after re-weighting)
    clean = kept[np.isfinite(s[kept])]
    variance = _mean_variance_factor(s[clean], redundancy) if len(clean) else scale
    why = (
        f"rejected {int(bad.sum())} of {len(s)} tie observations as blunders after a robust "
        f"({first.config.robust_loss}) pass: normalised squared residual above {chi2:g} x the robust "
        f"variance factor {scale:.3f} (sigma0 {np.sqrt(scale):.3f}); {int(lone.sum())} more left alone in "
        "their tracks; the block was then adjusted by least squares"
    )
    return kept, why, variance


__all__ = ["PARAM_NAMES", "AdjustConfig", "AdjustmentResult", "adjust", "scale_tie_sigma", "screened_rows"]
