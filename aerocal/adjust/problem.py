"""The adjustment problem: configuration, and the arrays built from the Arrow tables.

Everything is solved in a local frame: world coordinates (the flight's projected CRS, metres) minus a
local origin (the mean recorded GNSS position), so that the normal equations stay well conditioned.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.adjust.laser import fitted_lasers
from aerocal.adjust.projection import THERMAL_PARAMS
from aerocal.adjust.schur_kernels import image_graph, point_visit_rank, stable_order
from aerocal.adjust.thinning import ThinningConfig
from aerocal.camera import PARAM_NAMES, Camera, LinearThermalModel, correct_measurements
from aerocal.geometry import attitude_to_R_cw
from aerocal.poses import poses_arrays


class AdjustmentError(ValueError):
    """Input the adjustment cannot use; the message names the table, the field and the fix."""


class RobustLoss(StrEnum):
    """The loss of an adjustment's tie-point observations (:attr:`AdjustConfig.robust_loss`), of their squared
    normalised residual ``s`` with the scale ``c`` (``AdjustConfig.robust_scale``, in sigmas)."""

    NONE = "none"  #: least squares: rho(s) = s
    HUBER = "huber"  #: rho(s) = s up to s = c^2, 2 c sqrt(s) - c^2 beyond: a gross residual's influence is bounded
    CAUCHY = "cauchy"  #: rho(s) = c^2 ln(1 + s / c^2): a gross residual's influence falls towards zero


#: the values of :class:`RobustLoss` (what a configuration may give as a string)
ROBUST_LOSSES = tuple(loss.value for loss in RobustLoss)


@dataclass(frozen=True)
class AdjustConfig:
    """Configuration of a bundle adjustment (all defaults documented).

    * ``free``: IO parameters estimated (names of :data:`aerocal.camera.PARAM_NAMES`); the others are
      held at the starting camera's values. Default: focal length, principal point, k1..k3, p1, p2.
    * ``thermal``: IO parameters given a linear temperature slope estimated jointly
      (``f_i = f0 + a (T_i - T0)``), a subset of ("f", "cx", "cy"); default none.
    * ``thermal_t0``: reference temperature T0 (degC) of the estimated camera; ``None`` = median of the
      images' ``temperature_c``.
    * ``gnss_sigma_m``: a-priori std (east, north, up), metres, of the recorded projection centres used
      as weighted observations; ``None`` = GNSS not used. Default (0.10, 0.10, 0.15).
    * ``attitude_sigma_deg``: a-priori std of the recorded attitude about the camera x, y, z axes,
      degrees; ``None`` (default) = attitude not used as an observation (only as starting value).
    * ``use_gcps``: GCPs with role "control" enter as weighted observations with their survey sigmas.
    * ``robust_loss``: :class:`RobustLoss` ("none", default; "huber" or "cauchy"; its string value is accepted
      and held as the member), on tie-point observations only, with ``robust_scale`` in units of the
      observation's sigma (default 3). With a robust loss and ``reject_chi2`` (default 13.8, the 99.9 % point
      of chi-square with 2 degrees of freedom) the robust pass (at most ``robust_iterations``, default 100) only
      screens, and runs to its optimum: which observations it removes must not depend on where an iteration cap
      stopped it (``benchmarks/RESULTS.md``, "copr: the damping rule"); observations whose squared normalised
      residual exceeds ``reject_chi2`` times the robust variance factor are removed and the block is adjusted
      again by least squares, so sigma0 and the covariances describe clean data; ``reject_chi2=None`` keeps the
      robust solution itself.
    * ``estimate_tie_sigma``: with that screening, the tie observations' sigma is estimated from the block
      (default True): scaled by the square root of their variance factor (mean normalised squared
      residual over the mean redundancy), first from the robust pass, then from the least-squares
      adjustment until it changes by less than 5 % (at most 3 rounds, each starting from the last). A
      variance component for the tie points, whose a-priori sigma (``MatchConfig.sigma_px``, 0.5 px) is
      a guess; GNSS, attitude and GCP sigmas keep their a-priori values. Without it, tie points more
      precise than assumed give a sigma0 below 1 that shrinks every predicted sigma, the GCP measurements'
      included, and check points then miss their prediction (``benchmarks/history/engine_measurements.md``).
    * ``tie_thinning``: adjust a thinned set of the tie tracks (:class:`~aerocal.adjust.thinning.ThinningConfig`:
      the tracks with the most rays, a few per cell of a grid over every image), then intersect the
      others with the adjusted poses and IO held fixed, so the points table and the residuals still cover
      every track. Default ``None`` (every track adjusted); the flow thins the block adjustment of
      matched flights (``ProcessConfig.matched_tie_thinning``). On a rendered block, 4 tracks per cell of 8 x 6
      kept about a quarter of the observations at the same check-point accuracy and in about half the time
      (``benchmarks/history/engine_measurements.md``).
    * ``max_iterations`` / ``tolerance`` / ``step_tolerance``: Levenberg-Marquardt stops when the relative
      decrease of the cost falls below ``tolerance`` (default 1e-10), when the step of the camera-side
      unknowns (poses, IO, slopes) is below ``step_tolerance`` (default 1e-3) of their standard deviation
      in the Mahalanobis norm of the reduced normal matrix (this ends the tail in which only undetermined
      tie points still move, e.g. two-ray tracks holding a blunder under a robust loss), or after
      ``max_iterations`` (default 50).
    * ``scale_covariance``: multiply the covariance by the a-posteriori variance factor sigma0^2
      (default True).
    * ``adaptive``: drop insignificant or near-singular parameters and re-adjust (default False);
      ``corr_limit`` (0.95) and ``t_limit`` (1.96, 95 % two-sided) are the thresholds, a correlated pair
      whose members are both significant is kept unless its |correlation| exceeds ``singular_corr``
      (0.999), and ``always_keep`` (f, cx, cy) are the parameters never dropped for insignificance. The
      sigmas, covariance and correlation of the result are then marginal over the IO parameters dropped
      (:func:`aerocal.adjust.bundle.marginal_covariance`); ``AdjustmentResult.conditional_sigmas`` keeps the
      ones given the dropped parameters' values, and the selection's t values are those of its last model.
    * ``marginal_over``: IO parameters held at their value (not in ``free``) that the sigmas are made
      marginal over all the same, as for dropped ones (default none): the re-adjustment of a selected model.
    * ``laser_ranges``: the ranges a laser range finder on the camera's axis measured (``images.laser_range_m``)
      observe the block's depth (default True; :mod:`aerocal.adjust.laser`): those of alternate frames, the
      others kept out of every fit to judge the surface (:func:`aerocal.adjust.laser.fitted_lasers`).
    """

    free: tuple[str, ...] = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2")
    thermal: tuple[str, ...] = ()
    thermal_t0: float | None = None
    gnss_sigma_m: tuple[float, float, float] | None = (0.10, 0.10, 0.15)
    attitude_sigma_deg: tuple[float, float, float] | None = None
    use_gcps: bool = True
    robust_loss: RobustLoss = RobustLoss.NONE
    robust_scale: float = 3.0
    reject_chi2: float | None = 13.8
    robust_iterations: int = 100
    estimate_tie_sigma: bool = True
    tie_thinning: ThinningConfig | None = None
    max_iterations: int = 50
    tolerance: float = 1e-10
    step_tolerance: float = 1e-3
    scale_covariance: bool = True
    adaptive: bool = False
    corr_limit: float = 0.95
    singular_corr: float = 0.999
    t_limit: float = 1.96
    always_keep: tuple[str, ...] = ("f", "cx", "cy")
    marginal_over: tuple[str, ...] = ()
    laser_ranges: bool = True

    def __post_init__(self) -> None:
        for field_name in ("free", "marginal_over"):
            bad = [n for n in getattr(self, field_name) if n not in PARAM_NAMES]
            if bad:
                raise AdjustmentError(
                    f"AdjustConfig.{field_name} has unknown parameter(s) {bad}; valid: {PARAM_NAMES}")
        bad = [n for n in self.thermal if n not in THERMAL_PARAMS]
        if bad:
            raise AdjustmentError(
                f"AdjustConfig.thermal has unknown parameter(s) {bad}; valid: {THERMAL_PARAMS}"
            )
        try:
            object.__setattr__(self, "robust_loss", RobustLoss(self.robust_loss))
        except ValueError:
            raise AdjustmentError(
                f"AdjustConfig.robust_loss {self.robust_loss!r} unknown; valid: {ROBUST_LOSSES}"
            ) from None


@dataclass
class Block:
    """The arrays of one adjustment, in the local frame (``origin`` subtracted), indices 0-based.

    Image observations of tie points and of control GCPs share one point array: tie tracks first
    (``n_tie`` of them), then the control GCPs. Check-point observations are kept apart.
    """

    crs: str | None
    origin: np.ndarray  # (3,) local origin, world metres
    image_ids: np.ndarray  # (N,)
    R_rec: np.ndarray  # (N, 3, 3) recorded world-to-camera rotations
    gnss: np.ndarray  # (N, 3) recorded positions, local metres (NaN where missing)
    temperature: np.ndarray  # (N,) degC (NaN where missing)
    obs_image: np.ndarray  # (M,) image index of each image observation
    obs_point: np.ndarray  # (M,) point index
    obs_uv: np.ndarray  # (M, 2) pixels
    obs_sigma: np.ndarray  # (M,) pixels
    obs_is_tie: np.ndarray  # (M,) bool
    obs_row: np.ndarray  # (M,) row of the observations table (-1 for GCP observations)
    n_tie: int
    track_ids: np.ndarray  # (n_tie,) track id of each tie point
    control_ids: list[str]
    control_xyz: np.ndarray  # (G, 3) surveyed, local
    control_sigma: np.ndarray  # (G, 3)
    check_ids: list[str]
    check_xyz: np.ndarray  # (K, 3) surveyed, local
    check_sigma: np.ndarray  # (K, 3)
    check_image: np.ndarray  # (Mk,)
    check_point: np.ndarray  # (Mk,)
    check_uv: np.ndarray  # (Mk, 2)
    check_sigma_px: np.ndarray  # (Mk,)
    n_tie_obs: int = field(default=0)
    #: (N,) the range a laser range finder on each camera's axis measured, metres (NaN where none; ``None``: no image
    #: has one): observations of the block's depth (:mod:`aerocal.adjust.laser`)
    laser_range: np.ndarray | None = None

    @property
    def n_images(self) -> int:
        return len(self.image_ids)

    @property
    def n_points(self) -> int:
        return self.n_tie + len(self.control_ids)


def _col(table: pa.Table, name: str, what: str) -> np.ndarray:
    if name not in table.schema.names:
        raise AdjustmentError(f"{what} table lacks column {name!r}")
    return table.column(name).to_numpy(zero_copy_only=False)


def unique_ids(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(ids, return_inverse=True)`` for int64 ids; ids within a range of a few times their number
    (the track ids of matching and simulation) by a presence mask instead of a sort."""
    ids = np.asarray(ids, dtype=np.int64)
    if not len(ids):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    lo, hi = int(ids.min()), int(ids.max())
    if hi - lo > 4 * len(ids) + 1024:
        return np.unique(ids, return_inverse=True)
    present = np.zeros(hi - lo + 1, dtype=bool)
    present[ids - lo] = True
    number = np.cumsum(present) - 1
    return np.flatnonzero(present) + lo, number[ids - lo]


def build_block(
    images: pa.Table,
    observations: pa.Table,
    gcps: pa.Table | None = None,
    gcp_observations: pa.Table | None = None,
    config: AdjustConfig | None = None,
    thermal_correction: LinearThermalModel | None = None,
    correction_camera: Camera | None = None,
    initial_poses: pa.Table | None = None,
) -> Block:
    """Validate the tables and build the :class:`Block` arrays.

    With ``thermal_correction`` the tie-point and GCP measurements are first corrected to the model's
    reference temperature (Daakir 2019's workflow) using ``correction_camera`` (IO at T0).

    Raises:
        AdjustmentError: a table lacks a needed column; ``images.image_id`` has duplicates; ``initial_poses`` with
            ``config.gnss_sigma_m`` or ``config.attitude_sigma_deg`` set, or without a pose for an image; without
            ``initial_poses``, an image lacks its attitude (roll/pitch/yaw/attitude_convention) or gnss_x/gnss_y/gnss_z;
            an image lacks ``temperature_c`` while ``config.thermal`` or ``thermal_correction`` is set; an observation
            or GCP observation names an image_id absent from ``images``; an observation sigma is not positive; a control
            GCP's sigma_x/sigma_y/sigma_z is not positive; a ``gcp_observations`` gcp_id is absent from ``gcps``;
            ``thermal_correction`` without ``correction_camera``. The message names the row and the fix.
    """
    config = config or AdjustConfig()
    images = tables.validate(images, "images", source="images")
    observations = tables.validate(observations, "observations", source="observations")
    gcps = tables.validate(gcps, "gcps", source="gcps") if gcps is not None else tables.empty("gcps")
    gcp_observations = (
        tables.validate(gcp_observations, "gcp_observations", source="gcp_observations")
        if gcp_observations is not None
        else tables.empty("gcp_observations")
    )

    image_ids = _col(images, "image_id", "images").astype(np.int64)
    if len(np.unique(image_ids)) != len(image_ids):
        raise AdjustmentError("images.image_id has duplicate values; every image needs a unique id")
    N = len(image_ids)
    if initial_poses is not None:
        # starting poses from an orientation (e.g. incremental SfM georeferenced on GCPs): they are
        # starting values only, so GNSS and attitude priors must be off
        if config.gnss_sigma_m is not None or config.attitude_sigma_deg is not None:
            raise AdjustmentError(
                "initial_poses are starting values, not recorded GNSS/IMU: set AdjustConfig.gnss_sigma_m=None "
                "and attitude_sigma_deg=None (the datum then comes from at least 3 control GCPs)")

        p_ids, p_R, p_C = poses_arrays(initial_poses)
        pos = {int(v): k for k, v in enumerate(p_ids)}
        missing = [int(v) for v in image_ids if int(v) not in pos]
        if missing:
            raise AdjustmentError(f"initial_poses: image_id {missing[0]} (and {len(missing) - 1} more) has no pose; "
                                  "adjust only the oriented images (select_images)")
        rows = np.array([pos[int(v)] for v in image_ids])
        R_rec, gnss = p_R[rows], p_C[rows]
    else:
        conv = images.column("attitude_convention").to_pylist()
        roll, pitch, yaw = (_col(images, n, "images").astype(float) for n in ("roll", "pitch", "yaw"))
        R_rec = np.empty((N, 3, 3))
        for i in range(N):
            if conv[i] is None or not np.isfinite([roll[i], pitch[i], yaw[i]]).all():
                raise AdjustmentError(
                    f"images row {i} (image_id {image_ids[i]}): attitude (roll/pitch/yaw/attitude_convention) is "
                    "missing; the adjustment starts from the recorded attitude, so every image needs one"
                )
            R_rec[i] = attitude_to_R_cw(conv[i], roll[i], pitch[i], yaw[i])
        gnss = np.column_stack([_col(images, n, "images").astype(float) for n in ("gnss_x", "gnss_y", "gnss_z")])
        if not np.isfinite(gnss).all():
            bad = int(np.flatnonzero(~np.isfinite(gnss).all(axis=1))[0])
            raise AdjustmentError(
                f"images row {bad} (image_id {image_ids[bad]}): gnss_x/gnss_y/gnss_z missing; "
                "the adjustment starts from the recorded positions"
            )
    origin = gnss.mean(axis=0)
    temperature = _col(images, "temperature_c", "images").astype(float)
    laser = _col(images, "laser_range_m", "images").astype(float)
    if (config.thermal or thermal_correction is not None) and not np.isfinite(temperature).all():
        bad = int(np.flatnonzero(~np.isfinite(temperature))[0])
        raise AdjustmentError(
            f"images row {bad} (image_id {image_ids[bad]}): temperature_c is missing; a "
            "thermal model needs every image's sensor temperature"
        )

    id_order = np.argsort(image_ids)
    sorted_ids = image_ids[id_order]

    def image_index(ids: np.ndarray, what: str) -> np.ndarray:
        # a sorted search, not a dict lookup per row
        ids = np.asarray(ids, dtype=np.int64)
        if not N:
            out = np.full(len(ids), -1, dtype=np.int64)
        else:
            at = np.minimum(np.searchsorted(sorted_ids, ids), N - 1)
            out = np.where(sorted_ids[at] == ids, id_order[at], -1).astype(np.int64)
        if (out < 0).any():
            bad = int(np.flatnonzero(out < 0)[0])
            raise AdjustmentError(f"{what} row {bad}: image_id {int(ids[bad])} is not in the images table")
        return out

    o_img = image_index(_col(observations, "image_id", "observations"), "observations")
    track = _col(observations, "track_id", "observations").astype(np.int64)
    track_ids, o_pt = unique_ids(track)
    o_uv = np.column_stack([_col(observations, "x", "observations"), _col(observations, "y", "observations")])
    o_sig = _col(observations, "sigma", "observations").astype(float)
    if not (o_sig > 0).all():
        bad = int(np.flatnonzero(~(o_sig > 0))[0])
        raise AdjustmentError(f"observations row {bad}: sigma must be a positive number of pixels")

    g_id = gcps.column("gcp_id").to_pylist()
    g_xyz = np.column_stack([_col(gcps, n, "gcps") for n in ("X", "Y", "Z")]) - origin
    g_sig = np.column_stack([_col(gcps, n, "gcps") for n in ("sigma_x", "sigma_y", "sigma_z")])
    role = gcps.column("role").to_pylist()
    ctrl = [i for i, r in enumerate(role) if r == "control" and config.use_gcps]
    chk = [i for i, r in enumerate(role) if r == "check"]
    if ctrl and not (g_sig[ctrl] > 0).all():
        raise AdjustmentError("gcps: sigma_x/sigma_y/sigma_z of control points must be positive metres")
    go_gid = gcp_observations.column("gcp_id").to_pylist()
    go_img = image_index(_col(gcp_observations, "image_id", "gcp_observations"), "gcp_observations")
    go_uv = np.column_stack(
        [_col(gcp_observations, "x", "gcp_observations"), _col(gcp_observations, "y", "gcp_observations")]
    ).reshape(-1, 2)
    go_sig = _col(gcp_observations, "sigma", "gcp_observations").astype(float)
    known = set(g_id)
    unknown = [g for g in go_gid if g not in known]
    if unknown:
        raise AdjustmentError(f"gcp_observations: gcp_id {unknown[0]!r} is not in the gcps table")

    if thermal_correction is not None:
        if correction_camera is None:
            raise AdjustmentError("a thermal correction needs the camera (IO at the model's T0)")
        o_uv = correct_measurements(correction_camera, o_uv, temperature[o_img], thermal_correction)
        go_uv = correct_measurements(correction_camera, go_uv, temperature[go_img], thermal_correction)

    ctrl_pos = {g_id[i]: k for k, i in enumerate(ctrl)}
    chk_pos = {g_id[i]: k for k, i in enumerate(chk)}
    sel_c = np.array([g in ctrl_pos for g in go_gid], dtype=bool)
    sel_k = np.array([g in chk_pos for g in go_gid], dtype=bool)
    n_tie = len(track_ids)
    # tie points numbered, and their observations stored, along a reverse Cuthill-McKee order of the images
    # (:func:`point_visit_rank`): the adjustment's per-observation passes then read and write each point's
    # and each image's rows in sequence. In the order of their track ids, the points of a simulated block lie
    # at random across it, and every pair of a point's observations writes far from the last
    o_row = np.arange(len(o_pt))
    if n_tie:
        rank = point_visit_rank(image_graph(o_img, o_pt, N, n_tie), o_img, o_pt, n_tie)
        track_ids = track_ids[np.argsort(rank)]
        o_pt = rank[o_pt]
        o_row = stable_order(o_pt, n_tie)
        o_img, o_pt, o_uv, o_sig = o_img[o_row], o_pt[o_row], o_uv[o_row], o_sig[o_row]
    c_pt = n_tie + np.array([ctrl_pos[g] for g, s in zip(go_gid, sel_c, strict=True) if s], dtype=np.int64)
    k_pt = np.array([chk_pos[g] for g, s in zip(go_gid, sel_k, strict=True) if s], dtype=np.int64)

    return Block(
        crs=tables.crs_of(images),
        origin=origin,
        image_ids=image_ids,
        R_rec=R_rec,
        gnss=gnss - origin,
        temperature=temperature,
        obs_image=np.concatenate([o_img, go_img[sel_c]]),
        obs_point=np.concatenate([o_pt, c_pt]),
        obs_uv=np.vstack([o_uv, go_uv[sel_c]]),
        obs_sigma=np.concatenate([o_sig, go_sig[sel_c]]),
        obs_is_tie=np.concatenate([np.ones(len(o_pt), bool), np.zeros(int(sel_c.sum()), bool)]),
        obs_row=np.concatenate([o_row, np.full(int(sel_c.sum()), -1)]),
        n_tie=n_tie,
        track_ids=track_ids,
        control_ids=[g_id[i] for i in ctrl],
        control_xyz=g_xyz[ctrl].reshape(-1, 3),
        control_sigma=g_sig[ctrl].reshape(-1, 3),
        check_ids=[g_id[i] for i in chk],
        check_xyz=g_xyz[chk].reshape(-1, 3),
        check_sigma=g_sig[chk].reshape(-1, 3),
        check_image=go_img[sel_k],
        check_point=k_pt,
        check_uv=go_uv[sel_k],
        check_sigma_px=go_sig[sel_k],
        n_tie_obs=len(o_pt),
        laser_range=fitted_lasers(image_ids, laser) if config.laser_ranges and np.isfinite(laser).any() else None,
    )
