"""The flight's twin: what the simulation gets wrong about a real block, named, modelled and measured.

The twin is the adjusted block made again with the simulation's noise model: the same cameras and tie points
(as adjusted), the same image measurements' layout and weights, the same GNSS, attitude and GCP priors;
image measurements are the adjusted points projected with the adjusted camera plus white noise of their
sigma, recorded positions and attitudes the adjusted ones plus noise of theirs. It is adjusted the same way
(:func:`aerocal.adjust.solver.solve`). Its statistics (:func:`block_statistics`) set beside the real block's
show what white, independent noise cannot produce:

* ``variance_tie`` / ``variance_gnss`` / ``variance_attitude`` / ``variance_gcp``: mean squared normalised
  residual per observation group (a prior sigma that is off);
* ``image_field_px``: RMS of the mean residual vector over a 4 x 3 grid of image cells (a systematic field
  over the image plane: an IO term the model lacks);
* ``per_image_scale``: the spread (RMS, relative) of a scale fitted per image to its tie residuals about the
  principal point (a per-frame focal length or flying-height error: matching at another scale, a per-frame IO
  effect, a rolling readout);
* ``gnss_lag1``: lag-1 correlation of the GNSS residuals in time order (time-correlated GNSS errors);
* ``tail_fraction``: tie observations beyond the 99.9 % point of chi-square with 2 dof (mismatches).

A statistic whose real value lies beyond ``z_limit`` twin standard deviations of the twins' mean is what the
simulation gets wrong (:func:`compare`). For per-image scale errors the simulation is then extended: the twins
are made again with a per-image focal jitter of the measured size, and the gap it closes is the gain; a jitter
beyond :data:`PLAUSIBLE_FOCAL_JITTER` is reported as not the cause, whatever it closes.
The twin never imports the simulator: like the diagnosis, it works from the measurements and the adjustment.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from aerocal.adjust.projection import project, rotation_log, rotation_update
from aerocal.adjust.solver import Problem, solve
from aerocal.diagnose.model import Baseline

#: the statistics of :func:`block_statistics`, with what a large real value says (the likely cause)
CAUSES = {
    "variance_tie": "the tie points' sigma is not what the block assumes",
    "variance_gnss": "the GNSS sigma is not what the block assumes (or its errors are not white)",
    "variance_attitude": "the attitude sigma is not what the block assumes",
    "variance_gcp": "a GCP survey sigma (or a GCP) is off",
    "image_field_px": "a systematic field over the image plane: an IO term the model lacks",
    "per_image_scale": "per-image scale errors (a per-frame focal length or height: matching, readout, IO) that "
                       "white noise lacks",
    "gnss_lag1": "time-correlated GNSS errors, drawn white by the simulation",
    "tail_fraction": "mismatches beyond the blunder screening",
}
#: rounds that size an extension (the first injects the residual excess, the next ones correct it by the share of
#: the injected variance the adjustment leaves in the residuals, pooled over the rounds so far)
EXTENSION_ROUNDS = 3
#: iterations of a twin's adjustment (it starts at its truth)
TWIN_ITERATIONS = 8
#: largest per-frame focal jitter (relative standard deviation) taken as physically possible: 0.2 % of f, the
#: same bound as the largest thermal drift per degC (DecisionConfig.max_thermal_slope). It is an assumption,
#: not a measurement; fixed-focus survey and thermal lenses are expected to hold far less. An extension that
#: needs more is not the cause of the gap, whatever it closes
PLAUSIBLE_FOCAL_JITTER = 2e-3
#: grid of image cells for ``image_field_px`` (columns, rows)
FIELD_GRID = (4, 3)


@dataclass
class TwinComparison:
    """Real statistics against the twins' (mean and standard deviation over ``n_twins`` draws), each
    statistic's z, which ones differ (``differs``: name -> likely cause), and, where the simulation was
    extended, the extended twins' statistics and the fraction of the gap they close."""

    real: dict[str, float]
    twin_mean: dict[str, float]
    twin_sd: dict[str, float]
    z: dict[str, float]
    differs: dict[str, str]
    n_twins: int
    extended: dict[str, dict] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def summary(self) -> str:
        if not self.differs:
            return f"the block's statistics are within {self.n_twins} twins' spread: the simulation explains it"
        parts = [f"{k} {self.real[k]:.3g} vs twin {self.twin_mean[k]:.3g} +- {self.twin_sd[k]:.2g} ({v})"
                 for k, v in self.differs.items()]
        for name, ext in self.extended.items():
            closed = ", ".join(f"{k} {100 * v:.0f} %" if v <= 1.5 else f"{k} overshot ({100 * v:.0f} %)"
                               for k, v in ext["gap_closed"].items())
            if ext.get("plausible", True):
                parts.append(f"twin extended with {name} ({ext['jitter']:.2g}): gap closed {closed}")
            else:
                parts.append(
                    f"a {name} would need {100 * ext['jitter']:.2g} % of f per frame, beyond any lens (taken as "
                    f"at most {100 * PLAUSIBLE_FOCAL_JITTER:.1g} %, an assumption): it is not the cause, and the "
                    f"per-image scale errors stay unexplained (twin so extended: gap closed {closed})")
        return "; ".join(parts)


def block_statistics(base: Baseline) -> dict[str, float]:
    """The statistics of an adjusted block (see the module docstring); NaN where a group is absent."""
    b, st, cfg = base.block, base.state, base.config
    prob = Problem(b, cfg, base.solution.t0)
    _, res_px, _ = prob.residuals(st, jac=False)
    tie = b.obs_is_tie
    z = res_px[tie] / b.obs_sigma[tie, None]
    s = np.sum(z * z, axis=1)
    out = {k: float("nan") for k in CAUSES}
    if len(s):
        out["variance_tie"] = float(np.mean(s) / 2.0)
        out["tail_fraction"] = float(np.mean(s > 13.8))
        img = b.obs_image[tie]
        out["per_image_scale"] = float(np.sqrt(np.mean(_image_scales(base, res_px[tie], img) ** 2)))
        uv = b.obs_uv[tie]
        cx = np.clip((uv[:, 0] / base.template.width * FIELD_GRID[0]).astype(int), 0, FIELD_GRID[0] - 1)
        cy = np.clip((uv[:, 1] / base.template.height * FIELD_GRID[1]).astype(int), 0, FIELD_GRID[1] - 1)
        cell = cy * FIELD_GRID[0] + cx
        k = FIELD_GRID[0] * FIELD_GRID[1]
        cnt = np.bincount(cell, minlength=k)
        field_mean = np.stack([np.bincount(cell, weights=res_px[tie][:, d], minlength=k) for d in (0, 1)], axis=1)
        ok = cnt > 0
        out["image_field_px"] = float(np.sqrt(np.mean(np.sum((field_mean[ok] / cnt[ok, None]) ** 2, axis=1))))
    if cfg.gnss_sigma_m is not None:
        r = (st.C - b.gnss) / np.asarray(cfg.gnss_sigma_m, dtype=float)
        out["variance_gnss"] = float(np.mean(r * r))
        order = np.argsort(base.covariates.time_s, kind="stable")
        rr = r[order]
        if len(rr) > 2:
            a, c = rr[:-1] - rr.mean(axis=0), rr[1:] - rr.mean(axis=0)
            out["gnss_lag1"] = float(np.sum(a * c) / max(np.sum((rr - rr.mean(axis=0)) ** 2), 1e-300))
    if cfg.attitude_sigma_deg is not None:
        rot = rotation_log(np.einsum("nij,nkj->nik", st.R, b.R_rec)) / np.radians(cfg.attitude_sigma_deg)
        out["variance_attitude"] = float(np.mean(rot * rot))
    if len(b.control_ids):
        g = (st.X[b.n_tie :] - b.control_xyz) / b.control_sigma
        out["variance_gcp"] = float(np.mean(g * g))
    return out


def _image_scales(base: Baseline, res_px: np.ndarray, img: np.ndarray) -> np.ndarray:
    """Per image, the relative scale about the principal point that best fits its tie residuals (least squares
    of residual = scale x (measurement - principal point)); 0 for images without tie measurements."""
    b, cam = base.block, base.camera
    d = b.obs_uv[b.obs_is_tie] - np.array([cam.cx, cam.cy])
    num = np.bincount(img, weights=np.sum(res_px * d, axis=1), minlength=b.n_images)
    den = np.bincount(img, weights=np.sum(d * d, axis=1), minlength=b.n_images)
    return np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)


def make_twin(base: Baseline, seed: int, per_image_scale: float = 0.0) -> Baseline:
    """One twin of ``base`` (see the module docstring), adjusted; ``per_image_scale``: the extension, a focal
    jitter of this relative standard deviation per image (the tie measurements scaled about the principal
    point)."""
    rng = np.random.default_rng(seed)
    b, st, cfg = base.block, base.state, base.config
    prob = Problem(b, cfg, base.solution.t0)
    i, j = b.obs_image, b.obs_point
    uv = project(st.io, st.slopes, prob.dtemp_img[i], st.R[i], st.C[i], st.X[j], jacobians=False).uv
    uv = uv + rng.normal(0.0, 1.0, uv.shape) * b.obs_sigma[:, None]
    if per_image_scale > 0:
        pp = np.array([base.camera.cx, base.camera.cy])
        jitter = rng.normal(0.0, per_image_scale, b.n_images)[i] * b.obs_is_tie
        uv = pp + (uv - pp) * (1.0 + jitter[:, None])
    gnss = st.C.copy()
    if cfg.gnss_sigma_m is not None:
        gnss = gnss + rng.normal(0.0, 1.0, gnss.shape) * np.asarray(cfg.gnss_sigma_m, dtype=float)
    R_rec = b.R_rec
    if cfg.attitude_sigma_deg is not None:
        w = rng.normal(0.0, 1.0, (b.n_images, 3)) * np.radians(cfg.attitude_sigma_deg)
        R_rec = rotation_update(st.R, w)
    control = b.control_xyz
    if len(b.control_ids):
        control = st.X[b.n_tie :] + rng.normal(0.0, 1.0, b.control_xyz.shape) * b.control_sigma
    block = dataclasses.replace(b, obs_uv=uv, gnss=gnss, R_rec=R_rec, control_xyz=control)
    # it starts at its own truth: a few iterations reach its optimum (the real block's budget would cost minutes
    # on a real block of 166 images)
    quick = dataclasses.replace(cfg, max_iterations=min(cfg.max_iterations, TWIN_ITERATIONS))
    sol = solve(Problem(block, quick, base.solution.t0), st.copy())
    return dataclasses.replace(base, block=block, solution=sol)


def compare(base: Baseline, n_twins: int = 5, seed: int = 0, z_limit: float = 3.0) -> TwinComparison:
    """The real block's statistics against ``n_twins`` twins'; for per-image errors, the twins extended."""
    real = block_statistics(base)
    twins = [block_statistics(make_twin(base, seed + k)) for k in range(n_twins)]
    mean, sd = _spread(twins)
    z, differs = {}, {}
    n_tie = max(int(np.sum(base.block.obs_is_tie)), 1)
    for k, v in real.items():
        floor = 0.05 * abs(mean[k]) + 1e-12  # the twins' spread can be tiny for precise statistics
        if k == "tail_fraction":
            # a count: its Poisson spread, at least that of 3 events (4 of 8,000 observations beyond the
            # 99.9 % point against twins with none had been named "mismatches beyond the blunder screening")
            floor = max(floor, float(np.sqrt(max(mean[k] * n_tie, 3.0))) / n_tie)
        z[k] = float((v - mean[k]) / max(sd[k], floor)) if np.isfinite(v) and np.isfinite(mean[k]) else float("nan")
        if np.isfinite(z[k]) and z[k] > z_limit:
            differs[k] = CAUSES[k]
    out = TwinComparison(real, mean, sd, z, differs, n_twins)
    if "per_image_scale" in differs:
        # extend: a per-frame focal jitter. The adjustment absorbs most of it in the camera heights (and shows it
        # against the GNSS), so its size is found in EXTENSION_ROUNDS rounds
        excess = float(np.sqrt(max(real["per_image_scale"] ** 2 - mean["per_image_scale"] ** 2, 0.0)))
        jitter, ext, injected, seen = excess, [], [], []
        for round_no in range(EXTENSION_ROUNDS):
            ext = [block_statistics(make_twin(base, seed + 100 * (round_no + 1) + k, per_image_scale=jitter))
                   for k in range(n_twins)]
            injected += [jitter**2] * n_twins
            seen += [max(t["per_image_scale"] ** 2 - mean["per_image_scale"] ** 2, 0.0) for t in ext]
            # the fraction of the injected variance the adjustment leaves in the residuals, pooled over rounds
            left = float(np.sum(seen) / max(np.sum(injected), 1e-300))
            if round_no < EXTENSION_ROUNDS - 1:
                jitter = excess / float(np.sqrt(max(left, 1e-12)))
        ext_mean, _ = _spread(ext)
        out.extended["per-image focal jitter"] = {
            "jitter": jitter, "plausible": bool(jitter <= PLAUSIBLE_FOCAL_JITTER), "twin_mean": ext_mean,
            "gap_closed": {k: float((ext_mean[k] - mean[k]) / (real[k] - mean[k])) for k in differs
                           if np.isfinite(ext_mean[k]) and abs(real[k] - mean[k]) > 0}}
    return out


def _spread(stats: list[dict[str, float]]) -> tuple[dict[str, float], dict[str, float]]:
    """Mean and standard deviation of each statistic over twins (NaN where a group is absent)."""
    mean, sd = {}, {}
    for k in stats[0]:
        v = np.array([t[k] for t in stats], dtype=float)
        v = v[np.isfinite(v)]
        mean[k] = float(np.mean(v)) if len(v) else float("nan")
        sd[k] = float(np.std(v, ddof=1)) if len(v) > 1 else float("nan")
    return mean, sd
