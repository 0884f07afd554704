"""Ground-control screening: a GCP the block contradicts is demoted with its reason, never used silently.

Why
---
A control point enters the adjustment with its survey sigma (centimetres) against GNSS sigmas of
decimetres to metres, so least squares bends the whole block to one wrong coordinate: a control point
1000 m off in a 24-image flight left the check points 22-87 m off and a "GNSS bias" of -161 m named by the
diagnosis. Wrong labels (one target measured under another's name) and wrong image measurements do the
same on a smaller scale. The copr ground control (measured data) has both kinds.

Method (data snooping, one point at a time, on a reference the control did not shape)
-------------------------------------------------------------------------------------
1. **Reference poses**: with recorded GNSS/IMU the block is adjusted with the control points left out
   (:func:`reference_poses`; the datum is the GNSS), on the images that see a GCP and their tie-point
   neighbours; without GNSS the orientation's poses are used (their georeferencing similarity was itself
   fitted on the points this module keeps, :func:`screen_points`).
2. **Intersection**: each GCP is intersected from its image measurements (least-squares ray
   intersection). A measurement whose leave-one-out reprojection residual exceeds
   ``ControlScreeningConfig.measurement_limit_px`` is dropped, the worst first, while at least three rays
   remain (with two rays a bad one cannot be told from a good one).
3. **Datum transformation**: intersected minus surveyed, ``d_i``, is explained by a transformation: a
   common translation with the GNSS bias as its prior (``gnss_sigma_m``) when the GNSS gives the datum,
   a 3D similarity when the control does. Each point is tested against the transformation fitted on the
   *other* points (leave-one-out, so a blunder cannot hide by pulling the fit towards itself).
4. **Test**: ``T_i = r_i^T C_i^-1 r_i`` with ``C_i`` the survey covariance, the intersection's
   covariance, the transformation's, and a model floor for what the reference block itself gets wrong
   (``floor_gsd`` ground sampling distances across, ``floor_vertical`` times that in height: the
   nominal camera's focal error and the GNSS noise). The point with the largest ``T_i`` above the
   chi-square(3) quantile ``1 - alpha`` is demoted and the test repeated on the others.
   Surveyed heights that are all 0.0 are unknown (ingest's rule): the points are then tested in plan only.

A demoted point is removed from control *and* from the check points (its coordinates are what is in
doubt, so it would only inflate the check-point error); the report lists it with its misfit. Points with
fewer than two measured images cannot be tested and say so. Where the control gives the datum and only
three points are usable, a blunder cannot be localised (a similarity on three points has two redundant
observations): nothing is demoted and the note says why.

This is the textbook data snooping of geodetic networks (Baarda 1968, Foerstner 1987); pycolmap and
OpenDroneMap use GCPs as they come (ODM's ``gcp_list.txt`` enters OpenSfM's bundle with a fixed weight),
so there is no library implementation to measure it against.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from scipy.stats import chi2

from aerocal import tables
from aerocal.adjust.strategy import adjust_fixed_io
from aerocal.adjust.triangulate import triangulate_linear
from aerocal.camera import Camera
from aerocal.geometry import Similarity, estimate_similarity, matrix_from_quat_wxyz

#: the height sigma (metres) a point whose height is unknown gets in the test: its height then never decides
UNKNOWN_HEIGHT_SIGMA_M = 1.0e4


@dataclass(frozen=True)
class ControlScreeningConfig:
    """How ground control is screened (see the module docstring). Lengths in metres, pixels where named.

    * ``alpha`` (1e-3): false-alarm probability of one point's test (chi-square with 3 degrees of freedom).
    * ``measurement_limit_px`` (10 px): a GCP image measurement farther than this from where the other
      rays put the point is dropped; the reference poses carry the nominal camera's errors (1 % in f is
      10 px at 1000 px from the centre), so this catches wrong targets and labels, not sub-pixel noise.
    * ``floor_gsd`` (3): what the reference block gets wrong across, in ground sampling distances.
    * ``floor_vertical`` (3): the height floor as a multiple of the across floor (aerial base-to-height
      ratios of 0.3-0.6 make heights 2-3 times less certain than positions).
    * ``neighbour_tracks`` (20): images sharing at least this many tie tracks with an image that sees a GCP
      join the reference adjustment (GNSS datum).
    * ``camera_tolerance`` (0.01): what the nominal camera may be off by (f, principal point; relative),
      as a floor of ``camera_tolerance x distance`` on every axis when fewer than ``min_points_for_scatter``
      (5) points are tested; with more, their own scatter scales the sigmas (:func:`screen_points`).
    """

    alpha: float = 1e-3
    measurement_limit_px: float = 10.0
    floor_gsd: float = 3.0
    floor_vertical: float = 3.0
    neighbour_tracks: int = 20
    camera_tolerance: float = 0.01
    min_points_for_scatter: int = 5

    def __post_init__(self) -> None:
        if not 0 < self.alpha < 0.5:
            raise ValueError(f"ControlScreeningConfig.alpha must be in (0, 0.5), got {self.alpha}")
        for name in ("measurement_limit_px", "floor_gsd", "floor_vertical"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ControlScreeningConfig.{name} must be positive, got {getattr(self, name)}")
        if self.neighbour_tracks < 1:
            raise ValueError(f"ControlScreeningConfig.neighbour_tracks must be at least 1, got {self.neighbour_tracks}")
        if not 0.0 < self.camera_tolerance < 0.5:
            raise ValueError("ControlScreeningConfig.camera_tolerance must be in (0, 0.5), got "
                             f"{self.camera_tolerance}")
        if self.min_points_for_scatter < 2:
            raise ValueError("ControlScreeningConfig.min_points_for_scatter must be at least 2 (a scatter needs two "
                             f"points), got {self.min_points_for_scatter}")

    @property
    def limit(self) -> float:
        """The chi-square(3) value above which a point is demoted."""
        return float(chi2.ppf(1.0 - self.alpha, 3))


@dataclass
class GcpVerdict:
    """What the screening found for one GCP. ``misfit_m``: intersected minus surveyed after the datum
    transformation fitted on the other points (E, N, Up metres); ``statistic`` its chi-square(3) value."""

    gcp_id: str
    role: str
    status: str  # "kept", "demoted" or "not tested"
    n_rays: int
    misfit_m: list[float] | None = None
    statistic: float | None = None
    limit: float | None = None
    dropped_images: list[int] = field(default_factory=list)
    reason: str = ""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class ControlScreening:
    """The screened ground control: tables without the demoted points and dropped measurements, the verdict
    per point, the datum the test used and notes for the report."""

    gcps: pa.Table
    gcp_observations: pa.Table
    verdicts: list[GcpVerdict]
    datum: str  # "gnss", "control" or "none"
    notes: list[str] = field(default_factory=list)

    @property
    def demoted(self) -> list[GcpVerdict]:
        return [v for v in self.verdicts if v.status == "demoted"]

    def lines(self) -> list[str]:
        """One line per demoted point or dropped measurement, then the notes: what a user reads."""
        out = []
        for v in self.verdicts:
            if v.status == "demoted" or v.dropped_images:
                out.append(f"{v.gcp_id} ({v.role}): {v.reason}")
        return out + self.notes

    def to_dict(self) -> dict:
        return {"datum": self.datum, "verdicts": [v.to_dict() for v in self.verdicts], "notes": self.notes,
                "demoted": [v.gcp_id for v in self.demoted], "lines": self.lines()}


@dataclass
class _Intersection:
    xyz: np.ndarray  # (3,)
    cov: np.ndarray  # (3, 3)
    n_rays: int
    dropped: list[int]
    depth: float  # median distance camera - point, metres


def _rays(camera: Camera, R: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Unit viewing rays in the world frame (n, 3) of pixels uv seen by frames R_cw (n, 3, 3)."""
    return np.einsum("nji,nj->ni", R, camera.rays(uv))  # R^T d_cam


def _intersect(C: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Least-squares intersection (metres) of rays with origins C (n, 3) and unit directions d (n, 3)."""
    return triangulate_linear(np.zeros(len(C), dtype=np.intp), 1, C, d)[0][0]


def _project(camera: Camera, R: np.ndarray, C: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixels of world point X (3,) in frames R_cw (n, 3, 3) with centres C (n, 3)."""
    return camera.project(np.einsum("nij,nj->ni", R, X[None] - C))


def intersect_gcp(camera: Camera, R: np.ndarray, C: np.ndarray, uv: np.ndarray, sigma_px: np.ndarray,
                  image_ids: np.ndarray, limit_px: float) -> _Intersection | None:
    """Intersect one GCP from its measurements (poses R_cw (n, 3, 3), centres C (n, 3), pixels uv (n, 2)),
    dropping measurements beyond ``limit_px`` (leave-one-out reprojection), worst first, while >= 3 rays
    remain. None with fewer than two rays or parallel rays."""
    keep = np.ones(len(C), bool)
    dropped: list[int] = []
    d = _rays(camera, R, uv)
    if len(C) < 2:
        return None
    while keep.sum() >= 3:
        idx = np.flatnonzero(keep)
        errs = np.zeros(len(idx))
        for k, j in enumerate(idx):
            others = idx[idx != j]
            X = _intersect(C[others], d[others])
            errs[k] = float(np.linalg.norm(_project(camera, R[j:j + 1], C[j:j + 1], X)[0] - uv[j]))
        worst = int(np.argmax(errs))
        if not errs[worst] > limit_px:
            break
        keep[idx[worst]] = False
        dropped.append(int(image_ids[idx[worst]]))
    idx = np.flatnonzero(keep)
    X = _intersect(C[idx], d[idx])
    depth = np.linalg.norm(C[idx] - X, axis=1)
    sig_m = np.maximum(sigma_px[idx], 1e-3) / camera.f * depth  # across-ray sigma, metres
    P = np.eye(3)[None] - d[idx][:, :, None] * d[idx][:, None, :]
    A = np.einsum("n,nij->ij", 1.0 / sig_m**2, P)
    if np.linalg.cond(A) > 1e10:
        return None
    return _Intersection(X, np.linalg.inv(A), len(idx), dropped, float(np.median(depth)))


def heights_unknown(surveyed: np.ndarray) -> bool:
    """Ingest's rule (:mod:`aerocal.ingest.gcp`): surveyed heights that are all 0.0 are unknown, not sea
    level (copr: gcp01 had been demoted on its 3.9 m "height" misfit)."""
    return bool(len(surveyed)) and bool(np.all(np.asarray(surveyed)[:, 2] == 0.0))


def plan_only(measured: np.ndarray, surveyed: np.ndarray) -> np.ndarray:
    """``measured`` with the surveyed heights: where those are unknown, the block's heights must neither
    tilt the datum transformation nor count in the test."""
    out = np.array(measured, dtype=float)
    out[:, 2] = np.asarray(surveyed)[:, 2]
    return out


def misfit_covariance(hits: list[_Intersection], survey_sigma: np.ndarray, f: float,
                      config: ControlScreeningConfig, scale: float = 1.0, heights_unknown: bool = False,
                      ) -> np.ndarray:
    """Covariance (n, 3, 3), world metres, of intersected minus surveyed: the intersection's (scaled by
    ``scale`` when it was made in a model frame), the survey's (``survey_sigma`` (n, 3)) and the floor of
    what the reference block gets wrong (see :class:`ControlScreeningConfig`); with ``heights_unknown``
    the height gets :data:`UNKNOWN_HEIGHT_SIGMA_M`, so the points are tested in plan only."""
    depth = np.array([h.depth for h in hits]) * scale
    floor = config.floor_gsd * depth / f
    diag = survey_sigma**2 + np.column_stack([floor**2, floor**2, (config.floor_vertical * floor) ** 2])
    if len(hits) < config.min_points_for_scatter:
        diag = diag + (config.camera_tolerance * depth[:, None]) ** 2
    if heights_unknown:
        diag[:, 2] += UNKNOWN_HEIGHT_SIGMA_M**2
    cov = np.stack([h.cov for h in hits]) * scale**2
    return cov + np.einsum("ni,ij->nij", diag, np.eye(3))


def _fit(kind: str, src: np.ndarray, dst: np.ndarray, prior_sigma: np.ndarray | None,
         weights: np.ndarray) -> Similarity:
    """The datum transformation dst ~ T(src): a translation (with a zero-mean prior of ``prior_sigma``
    per axis on it) or a similarity."""
    if kind == "similarity":
        return estimate_similarity(src, dst, weights=weights)
    w = weights[:, None] * np.ones((1, 3))
    num = (w * (dst - src)).sum(axis=0)
    den = w.sum(axis=0) + (0.0 if prior_sigma is None else 1.0 / prior_sigma**2)
    return Similarity(1.0, np.eye(3), num / den)


def screen_points(surveyed: np.ndarray, measured: np.ndarray, covariance: np.ndarray, kind: str,
                  config: ControlScreeningConfig, prior_sigma: np.ndarray | None = None,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, str]:
    """Data snooping of point pairs: ``measured`` (n, 3) should map onto ``surveyed`` (n, 3) by a ``kind``
    transformation ("translation" or "similarity"); ``covariance`` (n, 3, 3) of their difference.

    Returns (kept mask, misfit (n, 3) of each point against the fit on the others, statistic (n,), the
    factors (3,) the a-priori variances were scaled by per axis, note). With ``min_points_for_scatter``
    points or more the variances are scaled per axis by the points' robust scatter (median squared
    normalised residual over the chi-square(1) median, never below 1). The similarity needs four points to
    test any (three to fit, one to test); fewer: all kept, NaN misfits.
    """
    n = len(surveyed)
    keep = np.ones(n, bool)
    misfit = np.full((n, 3), np.nan)
    stat = np.full(n, np.nan)
    need = 4 if kind == "similarity" else (1 if prior_sigma is not None else 2)
    if n < need:
        return keep, misfit, stat, np.ones(3), \
            f"{n} usable point(s): a {kind} needs {need} to test any; nothing tested"
    note, factor = "", np.ones(3)
    while True:
        idx = np.flatnonzero(keep)
        if len(idx) < need:
            note = f"{len(idx)} point(s) left: a {kind} cannot test them further"
            break
        r_round = np.full((n, 3), np.nan)
        c_round = np.tile(np.eye(3), (n, 1, 1))
        inside: dict[int, np.ndarray] = {}  # in-sample squared normalised residuals of the fit without i
        for i in idx:
            others = idx[idx != i]
            if len(others):
                w = 1.0 / np.trace(covariance[others], axis1=1, axis2=2)
                T = _fit(kind, measured[others], surveyed[others], None if len(others) > 1 else prior_sigma, w)
                inside[int(i)] = (T.apply(measured[others]) - surveyed[others]) ** 2 / np.diagonal(
                    covariance[others], axis1=1, axis2=2)
            else:
                T = Similarity(1.0, np.eye(3), np.zeros(3))
            if kind == "similarity":
                var_fit = np.zeros(3)  # the similarity's own uncertainty is left to the floor
            else:
                info = np.sum(1.0 / np.diagonal(covariance[others], axis1=1, axis2=2), axis=0) if len(others) \
                    else np.zeros(3)
                if len(others) <= 1 and prior_sigma is not None:
                    info = info + 1.0 / prior_sigma**2
                var_fit = 1.0 / info
            r = T.apply(measured[i:i + 1])[0] - surveyed[i]
            r_round[i], c_round[i] = r, covariance[i] + np.diag(var_fit)
        # the scatter of a round never drops below an earlier round's: demoting points must not make the
        # others' a-priori sigmas small again (a cascade that demoted 6 of 8 copr points before this rule)
        if len(idx) >= config.min_points_for_scatter:
            # the points scatter more than the a-priori sigmas say (the reference block's own errors, e.g.
            # the nominal camera's): per axis, the tests use their robust scatter, never less than the
            # a-priori. The scatter comes from the leave-one-out fit that fits its own points best (a
            # blunder inflates every fit that contains it, so the best one left it out), corrected for the
            # parameters that fit took per axis
            best = min(inside, key=lambda i: float(np.median(inside[i])))
            m = len(inside[best])
            dof = m / max(m - (7.0 if kind == "similarity" else 3.0) / 3.0, 1.0)
            factor = np.maximum(factor, dof * np.median(inside[best], axis=0) / chi2.ppf(0.5, 1))
        scale = np.sqrt(factor)
        c_scaled = c_round * scale[None, :, None] * scale[None, None, :]
        t_round = np.full(n, np.nan)
        solved = np.linalg.solve(c_scaled[idx], r_round[idx][..., None])[..., 0]
        t_round[idx] = np.einsum("ni,ni->n", r_round[idx], solved)
        misfit[idx], stat[idx] = r_round[idx], t_round[idx]
        worst = idx[int(np.argmax(t_round[idx]))]
        if not t_round[worst] > config.limit:
            break
        keep[worst] = False  # demoted with the misfit and statistic of this round
    return keep, misfit, stat, factor, note


def reference_poses(images: pa.Table, observations: pa.Table, gcp_observations: pa.Table, camera: Camera,
                    adjust_config, config: ControlScreeningConfig, gcps: pa.Table) -> tuple[pa.Table, str]:
    """Poses the control did not shape (GNSS datum): the images that see a GCP and their tie-point
    neighbours (``neighbour_tracks``), adjusted with IO fixed at ``camera`` and control points left out."""
    seen = set(pc.unique(gcp_observations.column("image_id")).to_pylist())
    img = observations.column("image_id").to_numpy(zero_copy_only=False)
    trk = observations.column("track_id").to_numpy(zero_copy_only=False)
    in_seen = np.isin(img, list(seen))
    tracks = np.unique(trk[in_seen])
    linked = np.isin(trk, tracks)
    ids, counts = np.unique(img[linked], return_counts=True)
    chosen = set(int(i) for i, c in zip(ids, counts, strict=True) if c >= config.neighbour_tracks) | seen
    sub_images = images.filter(pc.is_in(images.column("image_id"), pa.array(sorted(chosen), pa.int32())))
    sub_obs = observations.filter(pa.array(np.isin(img, list(chosen))))
    cfg = dataclasses.replace(adjust_config, use_gcps=False, tie_thinning=None)
    res = adjust_fixed_io(sub_images, sub_obs, camera, cfg, gcps, gcp_observations)
    return res.poses, f"{sub_images.num_rows} images adjusted on their GNSS/IMU with the control left out"


def screen_control(
    gcps: pa.Table,
    gcp_observations: pa.Table,
    poses: pa.Table,
    camera: Camera,
    datum: str,
    config: ControlScreeningConfig | None = None,
    gnss_sigma_m: tuple[float, float, float] | None = None,
    reference: str = "",
) -> ControlScreening:
    """Screen every GCP (control and check) against ``poses`` (world-to-camera, flight CRS).

    ``datum`` "gnss": the poses' datum is the GNSS (a common translation is allowed, with the GNSS sigma
    as its prior); "control": the poses were georeferenced on the control (a similarity is allowed).
    """
    config = config or ControlScreeningConfig()
    gcps = tables.validate(gcps, "gcps", source="gcps")
    gcp_observations = tables.validate(gcp_observations, "gcp_observations", source="gcp_observations")
    g = gcps.to_pydict()
    if not gcps.num_rows:
        return ControlScreening(gcps, gcp_observations, [], "none", [])
    p = poses.to_pydict()
    pose_index = {int(i): k for k, i in enumerate(p["image_id"])}
    q = np.column_stack([p["qw"], p["qx"], p["qy"], p["qz"]])
    Rall = matrix_from_quat_wxyz(q).reshape(-1, 3, 3)
    Call = np.column_stack([p["X"], p["Y"], p["Z"]])
    go = gcp_observations.to_pydict()
    go_gid = np.asarray(go["gcp_id"], dtype=object)
    go_img = np.asarray(go["image_id"], dtype=np.int64)
    uv_all = np.column_stack([go["x"], go["y"]])
    sig_all = np.asarray(go["sigma"], dtype=float)
    verdicts: list[GcpVerdict] = []
    inter: dict[str, _Intersection] = {}
    drop_rows: set[int] = set()
    for k, gid in enumerate(g["gcp_id"]):
        rows = np.flatnonzero((go_gid == gid) & np.isin(go_img, list(pose_index)))
        v = GcpVerdict(gid, g["role"][k], "not tested", int(len(rows)))
        verdicts.append(v)
        if len(rows) < 2:
            v.reason = f"measured in {len(rows)} oriented image(s): a point needs two to be tested; kept untested"
            continue
        pk = np.array([pose_index[int(i)] for i in go_img[rows]])
        res = intersect_gcp(camera, Rall[pk], Call[pk], uv_all[rows], sig_all[rows], go_img[rows],
                            config.measurement_limit_px)
        if res is None:
            v.reason = "its rays do not intersect (parallel or too few); kept untested"
            continue
        inter[gid] = res
        v.n_rays = res.n_rays
        v.dropped_images = res.dropped
        drop_rows |= {int(r) for r, i in zip(rows, go_img[rows], strict=True) if int(i) in res.dropped}
    tested = [k for k, gid in enumerate(g["gcp_id"]) if gid in inter]
    notes: list[str] = []
    kind = "translation" if datum == "gnss" else "similarity"
    if tested:
        surveyed = np.column_stack([g["X"], g["Y"], g["Z"]])[tested]
        hits = [inter[g["gcp_id"][k]] for k in tested]
        measured = np.stack([h.xyz for h in hits])
        survey = np.column_stack([g["sigma_x"], g["sigma_y"], g["sigma_z"]])[tested]
        cov = misfit_covariance(hits, survey, camera.f, config, heights_unknown=heights_unknown(surveyed))
        if heights_unknown(surveyed):
            notes.append("every GCP height is 0.0 (unknown): the points are tested in plan only")
            measured = plan_only(measured, surveyed)
        prior = None
        if kind == "translation" and gnss_sigma_m is not None:
            depth = float(np.median([h.depth for h in hits]))
            prior = np.hypot(np.asarray(gnss_sigma_m, float), config.camera_tolerance * depth)
        keep, misfit, stat, factor, note = screen_points(surveyed, measured, cov, kind, config, prior)
        if note:
            notes.append(note)
        if np.any(factor > 1.0):
            s = np.sqrt(factor)
            notes.append(f"the points scatter {s[0]:.1f}, {s[1]:.1f}, {s[2]:.1f} times (E, N, Up) more than the "
                         "a-priori sigmas (survey, intersection, floor) say; the tests use their scatter")
        for j, k in enumerate(tested):
            v = verdicts[k]
            v.limit = config.limit
            if np.isfinite(stat[j]):
                v.misfit_m = [float(x) for x in misfit[j]]
                v.statistic = float(stat[j])
            if not keep[j]:
                v.status = "demoted"
                v.reason = (f"demoted, not used as {v.role} point: the block puts it "
                            f"{np.linalg.norm(misfit[j]):.2f} m from its surveyed coordinates (E N Up "
                            f"{misfit[j][0]:+.2f} {misfit[j][1]:+.2f} {misfit[j][2]:+.2f} m; test "
                            f"{stat[j]:.1f} > {config.limit:.1f}, chi-square(3) at alpha {config.alpha:g})")
            elif np.isfinite(stat[j]):
                v.status = "kept"
            else:
                v.reason = "not testable with the points left; kept untested"
            if v.dropped_images:
                v.reason = ((v.reason + "; ") if v.reason else "") + (
                    f"measurement(s) in image(s) {', '.join(map(str, v.dropped_images))} dropped: more than "
                    f"{config.measurement_limit_px:g} px from where its other rays put it")
    demoted = {v.gcp_id for v in verdicts if v.status == "demoted"}
    keep_rows = np.array([i not in drop_rows and go_gid[i] not in demoted for i in range(len(go_gid))], bool)
    out_gcps = gcps.filter(pa.array([gid not in demoted for gid in g["gcp_id"]]))
    out_obs = gcp_observations.filter(pa.array(keep_rows)) if len(keep_rows) else gcp_observations
    if reference:
        notes.insert(0, f"screened on {reference}")
    return ControlScreening(out_gcps, out_obs, verdicts, datum, notes)
