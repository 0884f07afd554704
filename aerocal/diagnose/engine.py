"""Find what the model gets wrong: score every hypothesis, name the winner, extend the model, measure.

Method
------
1. Start from the adjusted block (the baseline model) and its linearisation.
2. Score every hypothesis of :data:`~aerocal.diagnose.hypotheses.HYPOTHESES` against one reduced system:
   the chi-square drop of freeing its parameters given every parameter of the block (and of effects
   already accepted), in units of the baseline's variance factor; its p-value from the chi-square
   distribution; Bonferroni over the hypotheses of a round (family-wise false alarm ``family_alpha``).
3. Among the significant ones, the winner maximises the BIC gain ``statistic - k ln(n)``: a
   one-parameter thermal drift beats twelve per-strip IO offsets that could mimic it.
4. Extend the model: remove the estimated effect from the measurements, re-adjust, re-estimate; iterate
   until the estimate settles. Then look for a further effect in the corrected block.
5. Measure the gain on data the fit did not use: the check points, triangulated from their image
   measurements with the baseline and with the extended model.

6. Confirm: the formal statistics assume the a-priori sigmas are right up to the variance factor. On
   real blocks correlated matching errors make them optimistic, many times over on the real seneca flight
   (``benchmarks/history/engine_measurements.md``). So the
   statistics of pure-noise hypotheses (a focal length varying with a random number per image) are
   measured on the extended model (:func:`overdispersion`), and a named effect that is not significant
   once its statistic is divided by their excess is withdrawn, with a note. :func:`permutation_null`
   calibrates one hypothesis by shuffling its own covariate. Errors correlated over a strip, or a signature
   the block reproduces differently strip by strip, the per-image null does not see; the held-out folds do:
   each fold's fit estimates the effect without one group of images, and where those estimates scatter about
   the whole block's beyond their formal sigmas
   (:meth:`~aerocal.diagnose.prediction.HeldOutGain.fold_dispersion`) that excess calibrates the effect's
   statistic and sigma instead, whichever is the larger.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
from scipy import stats

from aerocal.adjust import adjust, scale_tie_sigma
from aerocal.adjust.problem import AdjustConfig
from aerocal.adjust.solver import BundleProblem, inverse_spd, solve
from aerocal.adjust.strategy import central_images, long_tracks
from aerocal.camera import Camera, LinearThermalModel
from aerocal.diagnose import hypotheses as hyp
from aerocal.diagnose.attitude import OFFSET_SIGMAS, mean_rotation_covariance, offset_statistics
from aerocal.diagnose.io_uncertainty import IOUncertainty
from aerocal.diagnose.model import (
    Baseline,
    Conditional,
    Linear,
    check_rmse,
    fit_baseline,
    linearise,
    observation_geometry,
    reduce,
    refit,
)
from aerocal.diagnose.prediction import (
    HELD_OUT_SIGMAS,
    Extension,
    HeldOutGain,
    PredictionConfig,
    UndeterminedFold,
    held_out_gain,
)
from aerocal.diagnose.twin import compare as compare_twins
from aerocal.effects import CATALOGUE, rotation_zero_point, rotation_zero_point_text

#: A switch effect (refraction) has a known size: on = 1. An estimate further than this many sigmas from
#: 1 is a signal of the effect's shape but not the effect, and is not named. On a rendered, effect-free
#: conte-city block "refraction" came out at many times on, well determined: the signature of a focal length
#: off the truth by about its certificate sigma at a constant flying height
#: (``benchmarks/history/engine_measurements.md``).
SWITCH_TOLERANCE_SIGMA = 4.0


#: An effect is testable on a block only when every parameter's sigma is at most this fraction of its
#: plausible size (:func:`aerocal.diagnose.hypotheses.plausible`): per-strip IO with sigmas many times its
#: plausible 12 px on a real block without GCPs says nothing about the camera (seneca: ``benchmarks/RESULTS.md``,
#: the notes of "City scale: conte-city rendered, end to end" of 2026-11-22).
DETERMINED_FRACTION = 1.0 / 3.0

#: An image effect is named only when its estimate moves at least 1 % of the block's measurements by this many
#: pixels (:attr:`Evidence.shift_px`). Below it an effect cannot be told from the measurements' own systematic
#: errors: sub-pixel matching biases (pixel locking), a rendering's interpolation, a lens's residual profile.
#: The rendered, effect-free 818-frame conte-city block (global shutter) named a rolling shutter that moved its
#: last row against its first by a few hundredths of a pixel (``benchmarks/RESULTS.md``, "2026-11-28: the city
#: flow's calibration, the expert COLMAP pipeline, seneca again").
MATERIAL_SHIFT_PX = 0.05


def physical_verdict(e: Evidence, camera: Camera, ctx: hyp.Context, sigma_scale: float = 1.0) -> str | None:
    """``None`` when hypothesis ``e`` can be named on physical grounds; else why not: "not determined" (its
    sigma, times ``sigma_scale``, is large against its plausible size) or "beyond physical size" (its estimate
    exceeds any real instrument's, e.g. a lever arm of tens of metres: a symptom of another cause).
    ``sigma_scale``: the square root of the block's measured overdispersion where the sigmas are reported
    calibrated (on the real seneca block with the nominal camera a boresight had been called beyond physical
    size and a GNSS lag consistent with zero, where neither is determined once the sigmas are calibrated:
    ``benchmarks/history/engine_measurements.md``)."""
    if not e.estimate:
        return None
    # a switch (refraction: 1 = on) is determined only when its sigma is small against on: the rendered
    # 818-frame city named refraction = -420 +- 110, a radial signal 420 times refraction's size and of the
    # other sign, "consistent with on" within SWITCH_TOLERANCE_SIGMA of its own sigma
    switch = CATALOGUE.get(e.name, None) is not None and CATALOGUE[e.name].switch
    size = np.ones(len(e.estimate)) if switch else hyp.plausible(e.name, camera, ctx)
    theta = np.abs(np.asarray(e.estimate, dtype=float))
    sigma = np.asarray(e.sigma, dtype=float) * sigma_scale
    if not np.all(np.isfinite(sigma)):
        return ("not testable: its signature is zero on this block, or the block's other unknowns absorb it "
                "(e.g. a GNSS bias is the datum itself without GCPs)")
    if np.any(sigma > DETERMINED_FRACTION * size):
        k = int(np.argmax(sigma / size))
        what = ("formal sigma" if sigma_scale == 1.0 else
                f"sigma (formal x {sigma_scale:.3g}, the square root of this block's measured overdispersion)")
        return (f"not determined on this block: {what} {sigma[k]:.3g} {e.units} against a plausible size of "
                f"{size[k]:.3g} {e.units}")
    if switch:
        return None  # on is 1: how far the estimate is from it is judged by implausible_switch
    effect = CATALOGUE.get(e.name)
    signed = np.asarray(e.estimate, dtype=float)
    if effect is not None and effect.nonnegative and np.any(signed < 0):
        k = int(np.argmin(signed))
        return (f"{signed[k]:.3g} {e.units} is negative, which no instrument's {e.name} is: a symptom of another "
                "cause with its signature (for a readout: an affinity of the pixel grid, a focal length or principal "
                "point off the certificate's), not this effect")
    if np.any(theta > size):
        k = int(np.argmax(theta / size))
        return (f"{theta[k]:.3g} {e.units} is beyond any physical size ({size[k]:.3g} {e.units}): a symptom of "
                "another cause, not this effect")
    return None


def implausible_switch(e: Evidence) -> bool:
    """True for a switch effect whose estimate is inconsistent with its physical size (1 = on)."""
    effect = CATALOGUE.get(e.name)
    if effect is None or not effect.switch or not e.estimate:
        return False
    theta, sigma = float(e.estimate[0]), float(e.sigma[0])
    return bool(np.isfinite(sigma) and abs(theta - 1.0) > SWITCH_TOLERANCE_SIGMA * max(sigma, 1e-12))


@dataclass(frozen=True)
class DiagnoseConfig:
    """How the diagnosis decides. Defaults are documented inline."""

    hypotheses: tuple[str, ...] = hyp.HYPOTHESES  # what to test
    family_alpha: float = 0.01  # family-wise false-alarm probability per round (Bonferroni)
    max_effects: int = 3  # stop after this many named effects
    refine_iterations: int = 4  # correct-and-refit iterations for an accepted effect
    reference_temperature: float | None = None  # T0 of thermal hypotheses (a certificate's); None = mean
    confusion_ratio: float = 0.8  # a significant rival with this fraction of the winner's statistic is reported
    null_draws: int = 40  # random per-image focal covariates that calibrate the statistics (0 = formal only)
    seed: int = 0  # of those draws
    # blocks with more images are diagnosed on the max_images nearest the block centre (None = all); see
    # :func:`central_images`
    max_images: int | None = 200
    # blocks with more tie observations are diagnosed on their tracks of three rays or more (None = every track);
    # see :func:`diagnose`
    two_ray_tracks_up_to: int | None = 200_000
    twins: int = 3  # twins of the adjusted block whose statistics are set beside the real ones (0 = none)
    # the k-fold over strips (time blocks) that measures each candidate's gain on held-out images
    prediction: PredictionConfig = field(default_factory=PredictionConfig)

    def __post_init__(self) -> None:
        unknown = [h for h in self.hypotheses if h not in hyp.HYPOTHESES]
        if unknown:
            raise ValueError(f"DiagnoseConfig.hypotheses {unknown} unknown; valid: {', '.join(hyp.HYPOTHESES)}")
        if not 0.0 < self.family_alpha < 1.0:
            raise ValueError(f"DiagnoseConfig.family_alpha must be a probability in (0, 1), got {self.family_alpha}")
        if not 0.0 < self.confusion_ratio <= 1.0:
            raise ValueError(f"DiagnoseConfig.confusion_ratio must be in (0, 1], got {self.confusion_ratio}")
        for name in ("max_effects", "refine_iterations", "null_draws", "twins"):
            if getattr(self, name) < 0:
                raise ValueError(f"DiagnoseConfig.{name} must be 0 or more, got {getattr(self, name)}")
        if self.max_images is not None and self.max_images < 3:
            raise ValueError(f"DiagnoseConfig.max_images must be 3 or more, or None, got {self.max_images}")
        if self.two_ray_tracks_up_to is not None and self.two_ray_tracks_up_to < 0:
            raise ValueError("DiagnoseConfig.two_ray_tracks_up_to must be 0 or more, or None, got "
                             f"{self.two_ray_tracks_up_to}")


@dataclass
class Evidence:
    """The evidence for one hypothesis in one round."""

    name: str
    round: int
    k: int
    statistic: float  # chi-square drop / sigma0^2 (chi-square with k dof under the null)
    p_value: float
    p_adjusted: float
    estimate: list[float]
    sigma: list[float]
    bic_gain: float
    significant: bool
    units: str
    # how far the estimate moves the image measurements (pixels, the 99th percentile over the block's
    # observations); None for effects that act on the GNSS or attitude observations
    shift_px: float | None = None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class NamedEffect:
    name: str
    magnitude: list[float]
    sigma: list[float]
    units: str
    statistic: float
    p_value: float
    alternatives: list[str] = field(default_factory=list)  # explain the data almost as well: not told apart
    # its gain on data the fit did not use: held-out images (:meth:`aerocal.diagnose.prediction.HeldOutGain.to_dict`)
    # and, where the block has check points, their paired gain; None where not measured
    held_out: dict | None = None
    check_points: dict | None = None
    # how far its held-out folds' estimates scatter beyond their formal sigmas
    # (:meth:`aerocal.diagnose.prediction.FoldDispersion.to_dict`); None where fewer than 3 folds estimated it
    fold_dispersion: dict | None = None

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if len(self.magnitude) == 1:  # scalars as numbers, vectors as lists
            d["magnitude"], d["sigma"] = self.magnitude[0], self.sigma[0]
        return d


@dataclass
class Gain:
    metric: str
    before: float
    after: float

    @property
    def ratio(self) -> float:
        return self.before / self.after if self.after > 0 else float("nan")

    def to_dict(self) -> dict:
        return {"metric": self.metric, "before": self.before, "after": self.after, "ratio": self.ratio}


@dataclass
class Diagnosis:
    effects: list[NamedEffect]
    hypotheses: list[Evidence]
    gain: Gain | None
    sigma0_before: float
    sigma0_after: float
    reference_temperature: float
    extended_model: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    overdispersion: float = 1.0  # statistics were divided by this (>= 1), measured on the block itself
    recorded_eo: dict = field(default_factory=dict)  # see :func:`recorded_eo_checks`
    twin: dict = field(default_factory=dict)  # :meth:`aerocal.diagnose.twin.TwinComparison.to_dict` and its summary
    # effects the block could not tell apart: {"effects": [a, b], "estimates", "separated_by", "note"}; neither named
    pairs: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "effects": [e.to_dict() for e in self.effects],
            "pairs": self.pairs,
            "recorded_eo": self.recorded_eo,
            "twin": self.twin,
            "gain": self.gain.to_dict() if self.gain else None,
            "hypotheses": [h.to_dict() for h in self.hypotheses],
            "sigma0": {"before": self.sigma0_before, "after": self.sigma0_after},
            "overdispersion": self.overdispersion,
            "reference_temperature": self.reference_temperature,
            "extended_model": self.extended_model,
            "notes": self.notes,
        }

    def summary(self) -> str:
        """The effects named, each with its size +- sigma; without one, "no systematic effect found" only when
        the flight's twin agrees: a block that differs from its simulated twin lacks something the catalogue
        does not hold, and the summary says so instead of a clean bill."""
        pairs = "; ".join(f"{' or '.join(p['effects'])}: not told apart on this block, "
                          f"{'neither' if len(p['effects']) == 2 else 'none'} applied" for p in self.pairs)
        if not self.effects and pairs:
            return pairs
        if not self.effects:
            differs = sorted((self.twin or {}).get("differs") or {})
            if differs:
                return ("no effect of the catalogue named, but the block differs from its simulated twin in "
                        f"{', '.join(differs)}: the model lacks something (see the twin)")
            return "no systematic effect found"
        parts = []
        names = {e.name for e in self.effects}
        for e in self.effects:
            mag = ", ".join(f"{m:.4g}" for m in e.magnitude)
            sig = ", ".join(f"{s:.2g}" for s in e.sigma)
            alt = f" (or {', '.join(e.alternatives)}: not separable here)" if e.alternatives else ""
            if e.name == "boresight" and rotation_zero_point(names, e.magnitude, e.sigma):
                parts.append(rotation_zero_point_text(e.magnitude[2], e.sigma[2]))
                continue
            parts.append(f"{e.name} = {mag} +- {sig} {e.units}{alt}")
        return "; ".join(parts + ([pairs] if pairs else []))


def _io_columns(base: Baseline, lin, io: IOUncertainty) -> np.ndarray:
    """d(whitened residuals)/d(fixed IO parameters ``io.names``): (rows, k), image rows only."""
    b = base.block
    M = len(b.obs_image)
    J = base.camera.param_jacobian(lin.xn)[:, :, io.columns] / b.obs_sigma[:, None, None]
    out = np.zeros((len(lin.r), len(io.names)))
    out[: 2 * M] = J.reshape(2 * M, len(io.names))
    return out


def score(base: Baseline, ctx: hyp.Context, names: list[str], accepted: list[str], round_no: int,
          family_alpha: float, overdispersion: float = 1.0, io: IOUncertainty | None = None,
          lin: Linear | None = None) -> list[Evidence]:
    """Evidence for each of ``names`` given the block and the ``accepted`` effects' parameters.

    With ``io`` (the covariance of the IO held fixed, :mod:`aerocal.diagnose.io_uncertainty`) each
    estimate's covariance also holds that IO's uncertainty propagated to it, and the statistic is taken
    against the sum. ``lin``: the block's linearisation at its solution where the caller has it
    (:func:`~aerocal.diagnose.model.linearise`)."""
    lin = lin if lin is not None else linearise(base)
    all_names = list(accepted) + [n for n in names if n not in accepted]
    cols = [hyp.columns(n, lin, base, ctx) for n in all_names]
    offsets = np.cumsum([0] + [c.shape[1] for c in cols])
    if io is not None and base.config.free:  # the free IO is estimated with the block: only the held part is fixed
        io = io.without(base.config.free)
    io_cols = [_io_columns(base, lin, io)] if io is not None else []
    extra = np.hstack(cols + io_cols) if cols + io_cols else np.zeros((len(lin.r), 0))
    red = reduce(lin, extra)
    nc = red.n_camera
    base_idx = np.concatenate([np.arange(nc)] + [nc + np.arange(offsets[k], offsets[k + 1])
                                                 for k in range(len(accepted))])
    tests = nc + np.arange(offsets[len(accepted)], extra.shape[1])
    io_idx = nc + offsets[-1] + np.arange(len(io.names)) if io_cols else None
    conditional = Conditional(red, base_idx, tests)
    s02 = max(base.solution.sigma0, 1e-12) ** 2
    n_obs = len(lin.r)
    m = max(1, len([n for n in names if n not in accepted]))
    out = []
    for k, name in enumerate(all_names):
        if name in accepted:
            continue
        idx = nc + np.arange(offsets[k], offsets[k + 1])
        dof = len(idx)
        if dof == 0 or not np.any(cols[k]):
            out.append(Evidence(name, round_no, dof, 0.0, 1.0, 1.0, [0.0] * dof, [float("inf")] * dof, 0.0, False,
                                hyp.UNITS[name]))
            continue
        info, grad = conditional(idx)
        if _singular(info):
            # the block's other unknowns absorb the signature (a GNSS bias without GCPs is the datum itself)
            out.append(Evidence(name, round_no, dof, 0.0, 1.0, 1.0, [0.0] * dof, [float("inf")] * dof, 0.0, False,
                                hyp.UNITS[name]))
            continue
        inv = inverse_spd(info)
        theta = -inv @ grad
        shift = _image_shift_px(cols[k], theta, base.block.obs_sigma) if name in hyp.IMAGE_EFFECTS else None
        cov = inv * s02 * overdispersion
        if io_idx is not None:
            A = inv @ conditional.cross(idx, io_idx)
            cov = cov + A @ io.covariance @ A.T
        stat = float(theta @ inverse_spd(cov) @ theta)
        p = float(stats.chi2.sf(stat, dof))
        sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
        bic = stat - dof * np.log(n_obs)
        p_adj = min(1.0, p * m)
        out.append(Evidence(name, round_no, dof, stat, p, p_adj, theta.tolist(), sigma.tolist(), float(bic),
                            p_adj < family_alpha, hyp.UNITS[name], shift))
    return out


def _estimate_text(e: Evidence) -> str:
    """``"0.000243 +- 5.1e-05 s"``, or the values and sigmas comma-separated for several parameters."""
    values = ", ".join(f"{v:.3g}" for v in e.estimate)
    sigmas = ", ".join(f"{v:.2g}" for v in e.sigma)
    return f"{values} +- {sigmas} {e.units}"


def _image_shift_px(cols: np.ndarray, theta: np.ndarray, obs_sigma: np.ndarray) -> float:
    """How far an image effect's estimate ``theta`` moves the measurements: the 99th percentile over the block's
    image observations of the length (pixels) of the move, from its whitened signature ``cols`` (the first
    ``2 M`` rows: x and y of each observation, over its sigma)."""
    M = len(obs_sigma)
    if not M:
        return 0.0
    move = (cols[: 2 * M] @ theta).reshape(M, 2) * obs_sigma[:, None]
    return float(np.percentile(np.hypot(move[:, 0], move[:, 1]), 99.0))


#: a hypothesis whose conditional information matrix has eigenvalues below this fraction of its diagonal is
#: not determined by the block (on real seneca, without GCPs, a GNSS bias came out with a sigma of zero:
#: ``benchmarks/history/engine_measurements.md``)
SINGULAR_RELATIVE = 1e-9


def _singular(info: np.ndarray) -> bool:
    """True when ``info`` (the conditional information of a hypothesis) is singular to working precision."""
    info = np.asarray(info, dtype=float)
    d = np.diag(info)
    if not np.all(np.isfinite(info)) or np.any(d <= 0):
        return True
    s = 1.0 / np.sqrt(d)
    w = np.linalg.eigvalsh(info * s[:, None] * s[None, :])
    return bool(w.min() < SINGULAR_RELATIVE * max(w.max(), 1e-300))


def overdispersion(base: Baseline, draws: int, seed: int = 0, group: str = "image") -> tuple[float, np.ndarray]:
    """How much larger than a chi-square the statistics of pure-noise hypotheses are on this block.

    Each draw is a hypothesis no physics predicts, acting on one group of observations (``group``):

    * ``"image"``: a focal length that changes with a random number drawn per image. Its statistic should be
      chi-square with one degree of freedom (median 0.455) when the a-priori sigmas and the independence of the
      measurements hold; on real blocks correlated matching errors and unmodelled per-image effects make it far
      larger. It calibrates the hypotheses that act on the image measurements.
    * ``"gnss"`` / ``"imu"``: an offset of each image's recorded position (attitude) by a random 3-vector drawn per
      image, in units of the group's a-priori sigma. It calibrates the hypotheses that act on the records (a GNSS
      lag, bias or lever arm; a boresight), whose statistics come from how the records disagree with the
      orientation the images give: the records' own noise against their assumed sigma, and the images'
      correlated errors where they determine the positions as well as the records do (RTK). The image
      measurements' excess says nothing of the first: on an as-recorded drone block with consumer GNSS assumed
      at 2 m (1.5 m in truth) the images' phi of 2.8 turned a 0.3 s lag's z of 4.6 into 2.8, under the
      recorded-EO check's 3.

    Returns median / 0.455 and the draws' statistics (1 when the median is within its sampling scatter of a
    chi-square's, or the block has no such group). All draws share one reduced system, so this costs about one
    scoring round.
    """
    return overdispersions(base, draws, seed, (group,))[group]


def overdispersions(base: Baseline, draws: int, seed: int = 0,
                    groups: tuple[str, ...] = ("image",)) -> dict[str, tuple[float, np.ndarray]]:
    """:func:`overdispersion` of several groups from one linearisation and one reduced system (what costs)."""
    out: dict[str, tuple[float, np.ndarray]] = {g: (1.0, np.zeros(0)) for g in groups}
    if draws <= 0:
        return out
    lin = linearise(base)
    b = base.block
    present = [g for g in groups if g == "image" or lin.groups.get(g) is not None]
    if not present:
        return out
    E = np.zeros((len(lin.r), draws * len(present)))
    for j, group in enumerate(present):
        cols = slice(j * draws, (j + 1) * draws)
        rng = np.random.default_rng(seed)  # each group's draws as it alone would get them
        if group == "image":
            Jf = base.camera.param_jacobian(lin.xn)[:, :, 0] / b.obs_sigma[:, None]  # d(whitened)/d f
            cov = rng.normal(0.0, 1.0, (b.n_images, draws))
            M = len(b.obs_image)
            E[: 2 * M, cols] = (Jf[:, :, None] * cov[b.obs_image][:, None, :]).reshape(2 * M, draws)
        else:
            rows = lin.groups[group]
            E[rows, cols] = rng.normal(0.0, 1.0, (rows.stop - rows.start, draws))  # whitened rows: sigma units
    red = reduce(lin, E)
    nc = red.n_camera
    cond = Conditional(red, np.arange(nc), nc + np.arange(E.shape[1]))
    s02 = max(base.solution.sigma0, 1e-12) ** 2
    stat = []
    for k in range(E.shape[1]):
        info, grad = cond(np.array([nc + k]))
        stat.append(float(grad[0] ** 2 / max(info[0, 0], 1e-300)) / s02)
    med = float(stats.chi2.median(1))
    # the median of n chi-square(1) draws scatters with sd 1 / (2 f(med) sqrt(n)): only a median above its
    # one-sided 95 % bound is evidence of overdispersion (else a well-modelled block would lose power)
    bound = med + 1.645 / (2.0 * float(stats.chi2.pdf(med, 1)) * np.sqrt(draws))
    for j, group in enumerate(present):
        null = np.asarray(stat[j * draws:(j + 1) * draws])
        phi = float(np.median(null)) / med
        out[group] = ((phi if np.median(null) > bound else 1.0), null)
    return out


#: the observations each recorded-EO hypothesis acts on, whose own overdispersion calibrates its statistic
#: (:func:`overdispersion`); every other hypothesis acts on the image measurements
RECORDS_GROUP = {"gnss_bias": "gnss", "gnss_time_offset": "gnss", "lever_arm": "gnss", "boresight": "imu"}


@dataclass(frozen=True)
class Overdispersion:
    """The measured overdispersion of each group of observations (:func:`overdispersion`): ``image`` for the
    hypotheses acting on the image measurements, ``gnss`` and ``imu`` for those acting on the records."""

    image: float = 1.0
    gnss: float = 1.0
    imu: float = 1.0

    def of(self, name: str) -> float:
        """The overdispersion that calibrates hypothesis ``name``'s statistic."""
        return float(getattr(self, RECORDS_GROUP.get(name, "image")))


def measured_overdispersion(base: Baseline, names: list[str], draws: int, seed: int = 0) -> Overdispersion:
    """:class:`Overdispersion` of ``base``: the image group's always, the records' groups where one of ``names``
    acts on them."""
    groups = ("image", *sorted({RECORDS_GROUP[n] for n in names if n in RECORDS_GROUP}))
    phis = overdispersions(base, draws, seed, groups)
    return Overdispersion(*(phis[g][0] if g in phis else 1.0 for g in ("image", "gnss", "imu")))


def _extend(base: Baseline, ctx: hyp.Context, name: str, accepted: list[str], iterations: int,
            round_no: int, alpha: float, phi: float = 1.0,
            covariance: bool = True) -> tuple[Baseline, np.ndarray, Evidence, int]:
    """Remove effect ``name`` from the data by correct-and-refit iterations, at most ``iterations``; the extended
    block, the total estimate, the first iteration's evidence and the number of re-adjustments made.

    The iterations stop before re-adjusting for an increment within :data:`CONVERGED_SIGMAS` of its sigma (or a
    thousandth of the total): such a re-adjustment changes nothing the diagnosis reports, and each costs a block
    adjustment and a Schur reduction of the block's points. ``covariance``: whether the re-adjustments compute
    the camera covariance (a held-out fold's do not read it).

    Of an effect with several components only those beyond :data:`COMPONENT_SIGMAS` of their sigma are removed (the
    others are set to zero and the block corrected again from the start): a component the block does not determine
    adds only its noise to the model (a lever arm hidden across the track on daakir-uav came out with a vertical
    component of 0.0116 +- 0.0069 m, the height offset the GCPs tolerate, which moved the check points' heights by
    1.2 cm where the true lever arm moved them by 0.02 cm)."""
    start = base
    total = None
    first = None
    refits = 0
    for _ in range(iterations):
        lin = linearise(base)
        ev = score(base, ctx, [name], accepted, round_no, alpha, phi, lin=lin)[0]  # IO's sigma irrelevant here
        first = first or ev
        theta = np.asarray(ev.estimate)
        if total is not None and np.all((np.abs(theta) <= CONVERGED_SIGMAS * np.asarray(first.sigma))
                                        | (np.abs(theta) <= 1e-3 * np.abs(total))):
            break
        total = theta if total is None else total + theta
        base = refit(base, hyp.correct(name, theta, base, lin, ctx), covariance)
        refits += 1
    if total is not None and len(total) > 1:
        sigma = np.asarray(first.sigma, dtype=float)
        keep = np.abs(total) >= COMPONENT_SIGMAS * sigma
        if keep.any() and not keep.all():
            total = np.where(keep, total, 0.0)
            base = refit(start, hyp.correct(name, total, start, linearise(start), ctx), covariance)
    return base, total, first, refits


#: an increment of the correct-and-refit iterations within this many of its sigmas is not applied (:func:`_extend`)
CONVERGED_SIGMAS = 0.01
#: components of a several-valued effect within this many sigmas of zero are not applied (:func:`_extend`)
COMPONENT_SIGMAS = 2.0


def diagnose_baseline(baseline: Baseline, config: DiagnoseConfig | None = None,
                      io: IOUncertainty | None = None) -> Diagnosis:
    """Diagnose an adjusted block (see the module docstring for the method); ``io``: the covariance of the
    IO the block holds fixed (:mod:`aerocal.diagnose.io_uncertainty`), taken into every statistic.

    Raises:
        ValueError: ``config.hypotheses`` names an unknown hypothesis (the message lists the valid ones).
    """
    config = config or DiagnoseConfig()
    unknown = [n for n in config.hypotheses if n not in hyp.HYPOTHESES]
    if unknown:
        raise ValueError(f"unknown hypothesis {unknown[0]!r}; valid: {', '.join(hyp.HYPOTHESES)}")
    ctx = hyp.make_context(baseline, config.reference_temperature)
    # the twin compares the baseline and decides nothing the rounds below do: made beside them, in a thread of its
    # own (the rounds' scoring is mostly one thread; the twin's adjustments release the interpreter)
    twin_made = BackgroundCall(_twin, baseline, config) if config.twins > 1 else None
    names = list(config.hypotheses)
    notes: list[str] = []
    free = set(baseline.config.free)
    if {"cx", "cy"} & free:
        notes.append("the principal point is self-calibrated: it absorbs a boresight about the camera x/y axes "
                     "and a thermal drift of the principal point's mean; fix IO from a certificate to test them")
    if {"f", "k1"} <= free:
        notes.append("f and k1 are self-calibrated: they absorb refraction at a constant flying height")
    T = baseline.block.temperature
    if not (np.isfinite(T).all() and np.ptp(T) > 0):
        untestable = [n for n in names if n in THERMAL_HYPOTHESES]
        if untestable:
            names = [n for n in names if n not in untestable]
            notes.append(f"{', '.join(untestable)} not tested: the images have no sensor temperature, or one "
                         "temperature only")
    if baseline.config.gnss_sigma_m is None:
        untestable = [n for n in names if n in GNSS_HYPOTHESES]
        if untestable:
            names = [n for n in names if n not in untestable]
            notes.append(f"{', '.join(untestable)} not tested: the block was adjusted without GNSS observations")
    if baseline.config.attitude_sigma_deg is None and "thermal_rotation" in names:
        names = [n for n in names if n != "thermal_rotation"]
        notes.append("thermal_rotation not tested: without attitude observations each image's kappa absorbs a "
                     "rotation of the image about the principal point")
    if baseline.config.free:
        names = [n for n in names if not (n == "radial_k3" and "k3" in baseline.config.free)
                 and not (n == "affinity_skew" and {"b1", "b2"} <= set(baseline.config.free))]
    evidence: list[Evidence] = []
    effects: list[NamedEffect] = []
    accepted: list[str] = []
    untestable: list[str] = []
    pairs: list[dict] = []
    excluded: set[str] = set()  # not told apart from a rival, or without held-out gain: not tested again
    current = baseline
    for round_no in range(1, config.max_effects + 1):
        remaining = [n for n in names if n not in accepted and n not in excluded]
        if not remaining:
            break
        ev = score(current, ctx, remaining, accepted, round_no, config.family_alpha, io=io)
        evidence.extend(ev)
        candidates = [e for e in ev if e.significant and e.bic_gain > 0]
        for e in [e for e in candidates if implausible_switch(e)]:
            candidates.remove(e)
            if any(n.startswith(f"{e.name}: a signal of its shape") for n in notes):
                continue  # said in an earlier round
            notes.append(f"{e.name}: a signal of its shape, {e.estimate[0]:.3g} +- {e.sigma[0]:.2g} times its "
                         "physical size (1 = on): not named, another cause shares its signature (for refraction "
                         "at a constant flying height: a focal length or radial distortion off the certificate's)")
        # too small to name, but still a rival: a look-alike over the floor that it explains as well is not told
        # apart from it (a readout's remainder under the floor was named as an affinity over it: benchmarks/
        # RESULTS.md, the XT2 loop of 2026-12-05)
        small = [e for e in candidates if e.shift_px is not None and e.shift_px < MATERIAL_SHIFT_PX]
        for e in small:
            candidates.remove(e)
            notes.append(f"{e.name}: {_estimate_text(e)} (statistic {e.statistic:.1f}) moves 1 % of the "
                         f"measurements by {e.shift_px:.2g} px at the most, under {MATERIAL_SHIFT_PX:g} px: too small "
                         "to tell from the measurements' own sub-pixel errors (matching, rendering, the lens's "
                         "residual profile); not named")
        for e in ev:
            why = physical_verdict(e, current.camera, ctx)
            if why is None:
                continue
            if e in candidates:
                candidates.remove(e)
                if not any(n.startswith(f"{e.name}: ") for n in notes):
                    notes.append(f"{e.name}: {why}; not named (statistic {e.statistic:.1f})")
            elif round_no == 1 and why.startswith("not determined"):
                untestable.append(f"{e.name} ({why[len('not determined on this block: '):]})")
        if round_no == 1:
            zero = [e.name for e in ev if e.k == 0 or not np.all(np.isfinite(e.sigma))]
            if zero:
                notes.append(f"{', '.join(zero)} not testable: the block holds no observation its signature acts on "
                             "(boresight needs the recorded attitude as an observation), or its other unknowns "
                             "absorb it (a GNSS bias is the datum itself without GCPs)")
            if untestable:
                notes.append("not determined on this block, so not testable here: " + "; ".join(untestable))
        trials = RoundTrials()
        grouped: list[Evidence] = []  # inseparable in this round: a later candidate is tested against them too
        while candidates:
            best = max(candidates, key=lambda e: e.bic_gain)
            best, rival_note, pair = _contest(current, ctx, best, candidates, accepted, config, io, grouped, small)
            if pair is not None:
                new_members = [n for n in pair["effects"] if n not in excluded]
                if len(new_members) < len(pair["effects"]):  # joins a group found before in this round
                    old = next(p for p in pairs if set(p["effects"]) & set(pair["effects"]))
                    old["effects"] += [n for n in new_members if n not in old["effects"]]
                    old["estimates"].update(pair["estimates"])
                    notes.append(pair["note"])
                else:
                    pairs.append(pair)
                    notes.append(pair["note"])
                grouped += [e for e in candidates if e.name in pair["effects"]]
                excluded.update(pair["effects"])
                candidates = [e for e in candidates if e.name not in pair["effects"]]
                continue
            outcome = _try_extension(current, ctx, best, accepted, config, trials, round_no, len(names))
            if isinstance(outcome, str):
                notes.append(outcome)
                excluded.add(best.name)
                candidates = [e for e in candidates if e.name != best.name]
                continue
            extended_base, total, held, check, dispersion = outcome
            current = extended_base
            accepted.append(best.name)
            effects.append(NamedEffect(best.name, [float(v) for v in total], best.sigma, best.units, best.statistic,
                                       best.p_value, [], held.to_dict() if held is not None else None,
                                       check.to_dict() if check is not None else None,
                                       None if dispersion is None else dispersion.to_dict()))
            if rival_note:
                notes.append(rival_note)
            break
        else:
            break
    # confirm against an empirical null measured on the extended model (so that the named effects, now
    # removed from the data, do not leak into it): on real blocks the formal statistics can be far too large
    over = measured_overdispersion(current, names, config.null_draws, config.seed)
    phi = over.image
    if effects:
        m = max(1, len(names))
        confirmed = []
        for e in effects:
            phi_e = over.of(e.name)
            # the estimate's own excess where its folds scatter beyond their sigmas: correlations the per-image
            # null does not see (rendered frames: benchmarks/RESULTS.md, "fold dispersion")
            excess = [1.0] * len(e.sigma) if e.fold_dispersion is None else e.fold_dispersion["excess"]
            factor = [max(phi_e, x) for x in excess]
            if not max(factor) > 1.0:
                confirmed.append(e)
                continue
            stat, p_adj = _calibrated_p(e.statistic, len(e.magnitude), max(factor), m)
            if p_adj < config.family_alpha:
                confirmed.append(dataclasses.replace(e, statistic=stat, p_value=p_adj / m,
                                                     sigma=[s_ * float(np.sqrt(f_))
                                                            for s_, f_ in zip(e.sigma, factor, strict=True)]))
            else:
                why = (f"its folds' estimates scatter {np.sqrt(max(excess)):.1f}x their formal sigmas"
                       if max(excess) > phi_e else "the statistics are calibrated on this block")
                notes.append(f"{e.name} ({e.statistic:.1f} formally) is not significant once {why} ({stat:.1f}, p "
                             f"{p_adj:.2g} after {m} tests): not named")
        effects = confirmed
    if phi > 1.5:
        notes.append(f"the formal statistics are {phi:.1f}x too large on this block (median of "
                     f"{config.null_draws} random per-image hypotheses, measured on the extended model)")
    before, _ = check_rmse(baseline)
    after, _ = check_rmse(current)
    gain = Gain("check_point_rmse_m", before, after) if np.isfinite(before) else None
    if gain is None:
        notes.append("no check points: the gain on held-out data was not measured")
    extended = _extended_model(effects, ctx, current.camera)
    s0 = float(baseline.solution.sigma0)
    if s0 > MISFIT_SIGMA0:
        # a baseline that does not fit its own weights makes every figure below describe the misfit, not the
        # flight (as on the real seneca block, whose sigma0 was many times its block adjustment's)
        notes.insert(0, f"the diagnosis baseline does not fit its weights (sigma0 {s0:.3g}, above {MISFIT_SIGMA0:g}): "
                        "its statistics, the recorded-EO checks and the twin describe that misfit (mismatches or "
                        "wrong sigmas), not the flight; do not rely on them")
    eo = recorded_eo_checks([e for e in evidence if e.round == 1], over, baseline.camera, ctx, effects,
                            block=tested_block(baseline))
    attitude = attitude_offset(baseline, effects)
    if attitude is not None:
        eo["attitude_offset"] = attitude
    if len(baseline.block.control_ids) < MIN_CONTROL_FOR_OFFSET:  # the control alone cannot test an offset
        offset = check_point_offset(baseline)
        if offset is not None:
            eo["gnss_bias_check_points"] = offset
    twin = twin_made.result() if twin_made is not None else {}
    return Diagnosis(effects, evidence, gain, baseline.solution.sigma0, current.solution.sigma0, ctx.t_ref,
                     extended, notes, phi, eo, twin, pairs)


class BackgroundCall:
    """``fn(*args)`` run in a daemon thread from construction; :meth:`result` waits for it and returns its value
    or raises its exception. A daemon, so that an interrupted diagnosis does not wait for it to end."""

    def __init__(self, fn: Callable, *args) -> None:
        self._value, self._error = None, None

        def run() -> None:
            try:
                self._value = fn(*args)
            except BaseException as exc:  # handed to the caller of result()
                self._error = exc

        self._thread = threading.Thread(target=run, daemon=True, name=f"aerocal-{fn.__name__}")
        self._thread.start()

    def result(self):
        """Wait for the call to end and return its value.

        Raises:
            BaseException: whatever ``fn`` raised, raised again here in the caller's thread.
        """
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value


def _twin(baseline: Baseline, config: DiagnoseConfig) -> dict:
    """What the simulation gets wrong: the block as adjusted, made again with the simulation's noise model
    (:func:`aerocal.diagnose.twin.compare`), as the diagnosis reports it."""
    try:
        comparison = compare_twins(baseline, config.twins, config.seed)
        return {**comparison.to_dict(), "summary": comparison.summary()}
    except (ValueError, np.linalg.LinAlgError) as exc:  # an AdjustmentError is a ValueError
        # the twin compares; it decides nothing the diagnosis names: a twin that cannot be made is said, and the
        # run goes on
        return {"summary": f"the twin could not be made on this block ({type(exc).__name__}: {exc})"}


#: check points a block needs for their paired gain to count (as :class:`aerocal.certificates.review.DecisionConfig`)
MIN_CHECK_POINTS = 3
#: an effect is not named when it makes the check points' squared error worse by more than this fraction (10 % in
#: RMSE) beyond HELD_OUT_SIGMAS standard errors. The standard error is over the check points, but a model change moves
#: them together: a true lever arm of 5 cm across the track on 40 images of daakir-uav moved its 10 check points
#: (2 cm RMSE) by 1 mm together, -9.9 +- 3.4 % of their squared error
CHECK_LOSS = 1.1**2 - 1.0

#: what would tell apart two hypotheses a block could not: pairs of hypotheses -> the flight that separates them
SEPARATED_BY = {
    frozenset({"rolling_shutter", "affinity_skew"}): (
        "with the camera turning with the aircraft at one ground speed, a readout stretches every frame along the "
        "track as an affinity with a focal length change does; strips flown at other speeds or heights, a camera "
        "heading kept fixed across strips, or a focal length fixed by a certificate from another flight separate "
        "them"),
    frozenset({"rolling_shutter", "gnss_time_offset"}): (
        "both move each exposure along its track; a focal length fixed by a certificate, ground control, or strips "
        "at other speeds separate them"),
    frozenset({"gnss_time_offset", "lever_arm"}): (
        "at one ground speed an along-track lever arm is a time lag; strips flown at other speeds separate them"),
    frozenset({"lever_arm", "boresight"}): (
        "at one flying height a lever arm across the track tilts the images as a boresight does; another flying "
        "height separates them"),
    frozenset({"gnss_bias", "lever_arm"}): (
        "for nadir frames the vertical lever arm is a height offset; oblique or rotated frames separate them"),
    frozenset({"refraction", "radial_k3"}): "strips at other flying heights separate them",
}


def separated_by(a: str, b: str) -> str:
    """What flight would tell hypotheses ``a`` and ``b`` apart, in words."""
    return SEPARATED_BY.get(frozenset({a, b}), "a block of another geometry (cross strips, other flying heights and "
                                               "speeds, ground control) would")


def _hypothesis_extension(name: str, accepted: list[str], ctx: hyp.Context, config: DiagnoseConfig,
                          round_no: int, refits: int) -> Extension:
    """The :data:`aerocal.diagnose.prediction.Extension` of hypothesis ``name``: estimated on a training block
    given the ``accepted`` effects, removed from it by at most ``refits`` correct-and-refit iterations (as many
    as the whole block needed: a training block is most of it, with the same signature), and the same estimate
    removed from a held-out block."""

    def extend(fit: Baseline, keep: np.ndarray):
        ctx_fit = hyp.sub_context(ctx, keep)
        extended, total, first, _ = _extend(fit, ctx_fit, name, accepted, max(1, refits), round_no,
                                            config.family_alpha, covariance=False)
        why = physical_verdict(dataclasses.replace(first, estimate=[float(v) for v in total]), fit.camera, ctx_fit)
        if why is not None:
            raise UndeterminedFold(f"{name} on the {int(np.sum(keep))} fitting images: {why}")
        ctx_held = hyp.sub_context(ctx, ~keep)

        def correct(block, state):
            strip = np.full(block.n_images, -1)  # per-strip IO of strips held out is not predicted
            camera = fit.template.with_params(state.io)
            return hyp.correct_block(name, total, block, camera, state.R, strip, ctx_held,
                                     observation_geometry(block, state))

        return extended, correct, total, np.asarray(first.sigma, dtype=float)

    return extend


def check_point_gain(before: Baseline, after: Baseline) -> HeldOutGain | None:
    """The check points' paired gain from ``before`` to ``after`` (the same block, an effect removed): per check
    point the squared 3D error of its intersection from its image measurements, ``d_j = e_j^2(before) -
    e_j^2(after)``, as :class:`~aerocal.diagnose.prediction.HeldOutGain`; None with fewer than
    :data:`MIN_CHECK_POINTS` intersected check points."""
    _, e0 = check_rmse(before)
    _, e1 = check_rmse(after)
    if len(e0) == 0 or len(e1) != len(e0):
        return None
    ok = np.isfinite(e0).all(axis=1) & np.isfinite(e1).all(axis=1)
    if ok.sum() < MIN_CHECK_POINTS:
        return None
    a, b = np.sum(e0[ok] ** 2, axis=1), np.sum(e1[ok] ** 2, axis=1)
    d = a - b
    scale = float(np.mean(a))
    if not scale > 0:
        return None
    ids = np.flatnonzero(ok)
    return HeldOutGain(float(np.mean(d)) / scale, float(np.std(d, ddof=1) / np.sqrt(len(d))) / scale,
                       "check points", ids, d, a)


@dataclass
class RoundTrials:
    """What one round's candidates share: their held-out gains by name (``gains``) and the folds' training blocks
    by fold (``training``: they depend on the round's block, not on the hypothesis tried)."""

    gains: dict[str, HeldOutGain] = field(default_factory=dict)
    training: dict[int, Baseline] = field(default_factory=dict)


def _held_out(current: Baseline, ctx: hyp.Context, e: Evidence, accepted: list[str], config: DiagnoseConfig,
              trials: RoundTrials, round_no: int, refits: int) -> HeldOutGain:
    """The held-out gain of hypothesis ``e`` on ``current`` (cached in ``trials`` for the round); each fold
    refits the hypothesis at most ``refits`` times."""
    if e.name not in trials.gains:
        extension = _hypothesis_extension(e.name, accepted, ctx, config, round_no, refits)
        trials.gains[e.name] = held_out_gain(current, extension, config.prediction, trials.training)
    return trials.gains[e.name]


def _contest(current: Baseline, ctx: hyp.Context, best: Evidence, candidates: list[Evidence], accepted: list[str],
             config: DiagnoseConfig, io: IOUncertainty | None,
             grouped: list[Evidence] = (), small: list[Evidence] = ()) -> tuple[Evidence, str | None, dict | None]:
    """Whether ``best`` is told apart from the candidates that explain the data almost as well (statistic at least
    ``config.confusion_ratio`` of its own, or within :data:`CONFUSION_CHI2` of it; among them the significant
    hypotheses too small to be named, ``small``) and from those already found inseparable in this round
    (``grouped``): each is tested given the other. A rival that remains significant given ``best`` while ``best``
    does not given it is the better explanation and takes its place (a rival too small to name leaves ``best``
    in a group with it instead); those where neither remains significant given the other are what the block cannot
    tell from ``best``, and with it they form a group (returned as the third value: none of them is named).
    Held-out images do not break such a tie: signatures the block cannot separate predict them alike, and the one
    with fewer parameters merely overfits less (a rendered conte-calibration block at one ground speed with a hidden
    affinity predicted its held-out images 0.2 % better with a readout). Returns the hypothesis to try, a note on
    how it was told apart, and the group."""
    # per-strip IO is no cause but a symptom with a parameter set that mimics many (a lag, a boresight): it is
    # never grouped with a catalogue effect, which explains the same signal with far fewer parameters
    if best.name == hyp.PER_STRIP:
        return best, None, None
    rivals = sorted([e for e in [*candidates, *small] if e is not best and e.name != hyp.PER_STRIP
                     and (e.statistic >= config.confusion_ratio * best.statistic
                          or best.statistic - e.statistic <= CONFUSION_CHI2)], key=lambda e: -e.statistic)
    rivals += [e for e in grouped if e.name != best.name]
    told, alike = [], []
    m = max(1, len(candidates) + len(grouped))
    for rival in rivals[:MAX_RIVALS]:
        given_rival = score(current, ctx, [best.name], accepted + [rival.name], 0, config.family_alpha, io=io)[0]
        given_best = score(current, ctx, [rival.name], accepted + [best.name], 0, config.family_alpha, io=io)[0]
        b_sig = min(1.0, given_rival.p_value * m) < config.family_alpha
        r_sig = min(1.0, given_best.p_value * m) < config.family_alpha
        conditional = (f"{best.name} given {rival.name}: statistic {given_rival.statistic:.1f}; {rival.name} given "
                       f"{best.name}: {given_best.statistic:.1f}")
        if b_sig:
            told.append(f"{best.name} told apart from {rival.name} on this block ({conditional})")
        elif r_sig:
            # the better explanation is one the block could not tell from others, or one too small to name: best is
            # not told from it
            if rival in grouped or rival in small:
                alike.append((rival, conditional))
                continue
            return rival, f"{rival.name} preferred to {best.name}: {conditional}", None
        else:
            alike.append((rival, conditional))
    if not alike:
        return best, "; ".join(told) or None, None
    members = [best] + [r for r, _ in alike]
    names = [e.name for e in members]
    conditional = "; ".join(c for _, c in alike)
    separated = "; ".join(separated_by(best.name, r.name) for r, _ in alike)
    group = {"effects": names,
             "estimates": {e.name: {"value": e.estimate, "sigma": e.sigma, "units": e.units} for e in members},
             "conditional": conditional, "separated_by": separated}
    sizes = ", ".join(f"{e.name} ({_estimate_text(e)})" for e in members)
    group["note"] = (f"{sizes} explain the data alike and this block cannot tell them apart ({conditional}): none is "
                     f"named nor applied; {separated}")
    return best, None, group


#: rivals of a hypothesis tested against it, most explaining first
MAX_RIVALS = 4
#: a significant rival whose statistic is within this of the winner's is tested against it too, whatever their
#: ratio: at small statistics a ratio under :attr:`DiagnoseConfig.confusion_ratio` is no decisive difference (10 is
#: "very strong" evidence for a BIC difference; a simulated UltraCam block with refraction hidden named radial_k3
#: at 38.1 against refraction's 30.2, neither tested given the other)
CONFUSION_CHI2 = 10.0


def _gain_text(g: HeldOutGain) -> str:
    if not g.measured:
        return "not measured"
    return f"{100 * g.gain:+.2f} +- {100 * g.sigma:.2f} %"


def _calibrated_p(statistic: float, dof: int, factor: float, n_tests: int) -> tuple[float, float]:
    """A statistic divided by its block's measured overdispersion ``factor``, and its p-value adjusted for
    ``n_tests`` hypotheses (Bonferroni)."""
    stat = statistic / factor
    return stat, min(1.0, float(stats.chi2.sf(stat, dof)) * n_tests)


def _calibrated(best: Evidence, extended: Baseline, config: DiagnoseConfig, n_tests: int) -> str | None:
    """Whether ``best`` stays significant once its statistic is calibrated by the overdispersion of the block it
    extends (``extended``, the block with ``best`` removed: measured as the final confirmation measures it,
    :func:`measured_overdispersion`, so that the effect does not leak into its own calibration). A note saying why
    it is not named, or None.

    The confirmation of the named effects asks the same at the end; asked before the held-out folds it spares a
    candidate that cannot survive it their cost, five re-adjustments of most of the block with the hypothesis
    refitted in each (on a real block with many such candidates, most of its diagnosis: ``benchmarks/RESULTS.md``,
    "Diagnosis of the whole seneca flight")."""
    if config.null_draws <= 0:
        return None
    group = RECORDS_GROUP.get(best.name, "image")
    factor = overdispersions(extended, config.null_draws, config.seed, (group,))[group][0]
    if not factor > 1.0:
        return None
    stat, p_adj = _calibrated_p(best.statistic, best.k, factor, n_tests)
    if p_adj < config.family_alpha:
        return None
    return (f"{best.name} ({_estimate_text(best)}, statistic {best.statistic:.1f} formally) is not significant once "
            f"the statistics are calibrated on this block ({factor:.1f}x too large with it removed: {stat:.1f}, p "
            f"{p_adj:.2g} after {n_tests} tests): not named")


def _try_extension(current: Baseline, ctx: hyp.Context, best: Evidence, accepted: list[str], config: DiagnoseConfig,
                   trials: RoundTrials, round_no: int, n_tests: int):
    """Extend ``current`` by ``best`` and put it to the decision rule: the extended block must fit, the settled
    estimate be physical, the statistic remain significant once calibrated on the extended block
    (:func:`_calibrated`; ``n_tests``: the hypotheses of the diagnosis), and the extension predict data the fit
    did not use better: held-out images, or the
    check points (a GNSS offset shows against ground control only, which held-out images resected into a block
    that floats on the same offset do not see), one of them beyond :data:`HELD_OUT_SIGMAS` standard errors and
    neither worse beyond as many. Returns (extended baseline, settled estimate, held-out gain, check-point gain,
    the folds' :class:`~aerocal.diagnose.prediction.FoldDispersion` or None), or a note saying why the effect is not
    named."""
    extended_base, total, first, refits = _extend(current, ctx, best.name, accepted, config.refine_iterations,
                                                  round_no, config.family_alpha)
    settled = dataclasses.replace(best, estimate=[float(v) for v in total])
    if extended_base.solution.sigma0 > EXTENSION_WORSE * current.solution.sigma0:
        # the data corrected for the effect fit worse than before (real seneca, radial_k3: sigma0 an order of
        # magnitude larger, benchmarks/history/engine_measurements.md): the refit did not settle; an
        # overdispersion measured on it would be that failure, not the block
        return (f"{best.name}: the block corrected for {total[0]:.3g} {best.units} fits worse (sigma0 "
                f"{current.solution.sigma0:.3g} -> {extended_base.solution.sigma0:.3g}): not named")
    why = physical_verdict(settled, current.camera, ctx)
    if why is not None:
        # the correct-and-refit iterations ran away from the first estimate (the real seneca block's k3 changed
        # sign and grew beyond any lens: benchmarks/history/engine_measurements.md): the effect is not named and
        # the model not extended
        return (f"{best.name}: {best.estimate[0]:.3g} at first, {total[0]:.3g} once the data were corrected "
                f"and refitted: {why}; not named")
    calibrated = _calibrated(best, extended_base, config, n_tests)
    if calibrated is not None:
        return calibrated
    held = _held_out(current, ctx, best, accepted, config, trials, round_no, refits)
    check = check_point_gain(current, extended_base)
    size = _estimate_text(settled)
    checks = "no check points" if check is None else f"check points {_gain_text(check)} of their squared error"
    if check is not None and check.worse_beyond(HELD_OUT_SIGMAS) and check.gain < -CHECK_LOSS:
        return (f"{best.name}: {size} makes the check points worse ({_gain_text(check)} of their squared error; "
                f"{held.describe()}); not named")
    if held.worse_beyond(HELD_OUT_SIGMAS):
        return f"{best.name}: {size} predicts held-out images worse ({held.describe()}; {checks}); not named"
    if not (held.beyond(HELD_OUT_SIGMAS) or (check is not None and check.beyond(HELD_OUT_SIGMAS))):
        return (f"{best.name}: a signal without held-out gain, {size} (statistic {best.statistic:.1f}): "
                f"{held.describe()}; {checks}; neither beyond {HELD_OUT_SIGMAS:g} standard errors; not named")
    # the folds' scatter of the estimate against its formal sigmas (components the block set to zero left out)
    dispersion = held.fold_dispersion(np.where(np.asarray(total) != 0, total, np.nan), first.sigma)
    return extended_base, total, held if held.measured else None, check, dispersion


#: the checks of the recorded exterior orientation every flight with GNSS/IMU gets (NOTES: small drones'
#: recorded EO carries height-reference errors, GNSS time lags of tenths of a second, mounting tilts)
RECORDED_EO = ("gnss_bias", "gnss_time_offset", "lever_arm", "boresight")


def tested_block(baseline: Baseline) -> str:
    """What a diagnosis tested on, in words: the number of images and whether the IO was free or held fixed (the
    same check on another block, e.g. the calibration's, gives another sigma)."""
    free = [n for n in baseline.config.free]
    io = f"IO free ({', '.join(free)})" if free else "IO held fixed"
    return f"the whole {baseline.block.n_images}-image block, {io}"


def recorded_eo_checks(round1: list[Evidence], over: Overdispersion | float, camera: Camera, ctx: hyp.Context,
                       named: list[NamedEffect], block: str | None = None) -> dict:
    """The recorded-EO checks, each with its estimate and sigma whether or not it was named: height datum
    and GNSS offset (``gnss_bias``), GNSS time lag (``gnss_time_offset``), lever arm, boresight (attitude
    convention or mounting). ``sigma`` is the formal sigma (``sigma_formal``, what the geometry determines)
    scaled by the square root of the measured overdispersion of the records the check acts on (``over``, or one
    ``phi`` for all: what the noise allows); ``status`` is
    "named" (in the extended model), "consistent with zero", "a signal below the naming threshold", "not
    determined", "beyond physical size" or "not testable", with the reason."""
    out = {}
    by_name = {e.name: e for e in round1}
    named_names = {e.name for e in named}
    for name in RECORDED_EO:
        e = by_name.get(name)
        if e is None:
            out[name] = {"status": "not testable", "reason": "not tested on this block (no GNSS or attitude "
                                                             "observations)"}
            continue
        phi = over.of(name) if isinstance(over, Overdispersion) else float(over)
        why = physical_verdict(e, camera, ctx, float(np.sqrt(max(phi, 1.0))))
        if not np.all(np.isfinite(e.sigma)):
            out[name] = {"status": "not testable", "reason": why}
            continue
        sigma = [float(s_ * np.sqrt(phi)) for s_ in e.sigma]
        entry = {"estimate": [float(v) for v in e.estimate], "sigma": sigma,
                 "sigma_formal": [float(s_) for s_ in e.sigma], "units": e.units, "statistic": float(e.statistic / phi),
                 "overdispersion": phi}
        if name in named_names:
            entry["status"] = "named"
        elif why is not None:
            entry["status"] = "not testable" if why.startswith("not testable") else (
                "not determined" if why.startswith("not determined") else "beyond physical size")
            entry["reason"] = why
        else:
            z = np.abs(np.asarray(e.estimate)) / np.maximum(np.asarray(sigma), 1e-300)
            entry["status"] = "consistent with zero" if np.all(z < 2.0) else "a signal below the naming threshold"
        out[name] = entry
    if block:
        for entry in out.values():
            entry["block"] = block
    return out


#: control GCPs a block needs to test a GNSS offset against them (as
#: :data:`aerocal.calibrate.eo_checks.MIN_CONTROL`); with fewer the check points are asked (:func:`check_point_offset`)
MIN_CONTROL_FOR_OFFSET = 3


def attitude_offset(base: Baseline, named: list[NamedEffect]) -> dict | None:
    """How the recorded attitudes are turned from the orientation the images and the recorded positions give
    (:mod:`aerocal.diagnose.attitude`), about the camera axes, with its sigma and leave-one-out gain. Checked on
    every flight that records attitudes, observed by the block or not: where the block observes them it is adjusted
    again without them first, as an offset of them would otherwise turn the block with it. None for a block without
    recorded attitudes (oriented by incremental SfM)."""
    if base.config.gnss_sigma_m is None or base.block.n_images < 3:
        return None
    sol = base.solution
    if base.config.attitude_sigma_deg is not None:
        problem = BundleProblem(base.block, dataclasses.replace(base.config, attitude_sigma_deg=None), base.solution.t0)
        sol = solve(problem, base.state.copy())
    off = offset_statistics(sol.state.R, base.block.R_rec, mean_rotation_covariance(sol, base.block.n_images))
    if off is None:
        return None
    if not off.significant:
        status = "consistent with the adjusted attitudes"
    else:
        status = (f"offset about the camera's {', '.join(off.axes)} axis: the recorded attitudes are turned from the "
                  "orientation the images and the recorded positions give (a gimbal's yaw for the camera's, a mounting "
                  "tilt, or another angle convention)")
        if any(e.name == "boresight" for e in named):
            status += "; named as a boresight and removed from the recorded attitudes"
        elif base.config.attitude_sigma_deg is None:
            status += "; the block does not observe the recorded attitudes, so the offset does not reach its products"
    return {**off.to_dict(), "status": status}


def check_point_offset(base: Baseline) -> dict | None:
    """A constant offset of the block (a GNSS offset where too few control GCPs test it) measured on the check
    points, which stay independent: each check point's error predicted from the mean error of the others (leave one
    out), and the gain of that prediction, ``mean(|e_j|^2 - |e_j - mean_(k != j) e_k|^2) / mean(|e_j|^2)`` with its
    standard error. None with fewer than :data:`MIN_CHECK_POINTS` intersected check points. Reported, not applied:
    applied, the check points would no longer assess the block."""
    _, e = check_rmse(base)
    e = e[np.isfinite(e).all(axis=1)] if len(e) else e
    n = len(e)
    if n < MIN_CHECK_POINTS:
        return None
    mean = e.mean(axis=0)
    sigma = e.std(axis=0, ddof=1) / np.sqrt(n)
    others = (mean * n - e) / (n - 1)
    a = np.sum(e**2, axis=1)
    d = a - np.sum((e - others) ** 2, axis=1)
    gain, gain_sigma = float(d.mean() / a.mean()), float(d.std(ddof=1) / np.sqrt(n) / a.mean())
    big = np.abs(mean) > OFFSET_SIGMAS * sigma
    if gain > HELD_OUT_SIGMAS * gain_sigma and big.any():
        status = (f"an offset of the block against its {n} check points (leave-one-out gain {100 * gain:+.1f} +- "
                  f"{100 * gain_sigma:.1f} %): a GNSS offset (height reference, datum) the control cannot test; "
                  "reported, not applied (the check points assess the block)")
    else:
        status = (f"no offset beyond {OFFSET_SIGMAS:g} sigma with a leave-one-out gain on the {n} check points "
                  f"({100 * gain:+.1f} +- {100 * gain_sigma:.1f} %)")
    return {"estimate": mean.tolist(), "sigma": sigma.tolist(), "units": "m", "n_check_points": n,
            "held_out_gain": gain, "held_out_sigma": gain_sigma, "status": status}


#: a baseline sigma0 above this says the block does not fit its weights: the diagnosis says not to rely on it
MISFIT_SIGMA0 = 3.0
#: an effect whose correct-and-refit leaves the block's sigma0 this much larger is not named
EXTENSION_WORSE = 1.05

#: hypotheses that need every image's sensor temperature, and those that act on GNSS observations
THERMAL_HYPOTHESES = ("thermal_focal", "thermal_principal_point", "thermal_rotation")
GNSS_HYPOTHESES = ("gnss_bias", "gnss_time_offset", "lever_arm")


def _extended_model(effects: list[NamedEffect], ctx: hyp.Context, camera: Camera) -> dict:
    model: dict = {"camera": camera.to_dict()}
    thermal = {e.name: e.magnitude for e in effects if e.name in ("thermal_focal", "thermal_principal_point")}
    if thermal:
        df = thermal.get("thermal_focal", [0.0])[0]
        dcx, dcy = thermal.get("thermal_principal_point", [0.0, 0.0])
        model["thermal"] = LinearThermalModel(t0=ctx.t_ref, df_dt=df, dcx_dt=dcx, dcy_dt=dcy).to_dict()
    for e in effects:
        if e.name not in ("thermal_focal", "thermal_principal_point"):
            model[e.name] = e.magnitude
    return model


def diagnose(images: pa.Table, observations: pa.Table, camera: Camera, adjust_config: AdjustConfig,
             gcps: pa.Table | None = None, gcp_observations: pa.Table | None = None,
             config: DiagnoseConfig | None = None, io: IOUncertainty | None = None,
             start: tuple[pa.Table, pa.Table] | None = None) -> Diagnosis:
    """Adjust the block with ``adjust_config`` and diagnose it.

    Args:
        images, observations, gcps, gcp_observations: the block's tables (:mod:`aerocal.tables`; flight CRS,
            metres; pixels).
        camera: the IO the block is adjusted with (fixed unless ``adjust_config.free`` frees part of it).
        adjust_config: the block's weights (GNSS/IMU sigmas), robust loss and free IO.
        config: the hypotheses, the family-wise false-alarm rate, the held-out test (default
            :class:`DiagnoseConfig`).
        io: the uncertainty of the fixed IO (:mod:`aerocal.diagnose.io_uncertainty`), added to every estimate's
            covariance (:func:`diagnose_baseline`).
        start: poses and points of an adjustment of the block to start from
            (:func:`aerocal.diagnose.model.fit_baseline`).

    Returns:
        :class:`Diagnosis`: every hypothesis tested (statistic, adjusted p, estimate and sigma in the catalogue's
        units), the effects named with their held-out gain, the pairs the block cannot tell apart, the gain on
        check points, the recorded-EO checks and a one-line verdict (``summary()``).

    Raises:
        AdjustmentError: the block has no datum (see :func:`aerocal.adjust.adjust`).

    With a robust loss (and ``adjust_config.reject_chi2``) the blunders are found by a robust adjustment
    and removed first (:func:`aerocal.adjust.bundle.adjust`, which also estimates the tie observations'
    sigma), then the clean block is diagnosed by least squares: a systematic effect is looked for in the
    data, not in the mismatches. A block of more than ``config.max_images`` images is diagnosed on its
    central sub-block (:func:`central_images`: every accepted effect is refitted several times, so a whole
    city-scale block costs many block adjustments), and a note says so. ``adjust_config.tie_thinning`` is
    ignored: a systematic effect is looked for in every track.
    """
    config = config or DiagnoseConfig()
    sub_note = None
    if config.max_images is not None and images.num_rows > config.max_images:
        keep_ids = central_images(images, config.max_images)
        sub_note = (f"diagnosed on the {len(keep_ids)} images nearest the block centre of {images.num_rows} "
                    f"(DiagnoseConfig.max_images = {config.max_images})")

        def only(table: pa.Table | None) -> pa.Table | None:
            if table is None:
                return None
            return table.filter(pa.array(np.isin(table.column("image_id").to_numpy(), keep_ids)))

        images, observations, gcp_observations = only(images), only(observations), only(gcp_observations)
    if adjust_config.robust_loss != "none" and adjust_config.reject_chi2 is not None:
        screened = adjust(images, observations, camera, dataclasses.replace(adjust_config, adaptive=False),
                          gcps, gcp_observations)
        keep = np.flatnonzero(screened.obs_weight != 0)
        observations = scale_tie_sigma(observations.take(pa.array(keep, pa.int64())), screened.tie_sigma_scale)
        adjust_config = dataclasses.replace(adjust_config, robust_loss="none")
    # every track, not the thinned ones (AdjustConfig.tie_thinning): on the 818-frame city flight a radial
    # term the certificate lacked came out at 0.60 +- 0.15 from every track and 0.87 +- 0.22 from the
    # thinned ones (sigma x 1.5, so less power against smaller effects)
    adjust_config = dataclasses.replace(adjust_config, tie_thinning=None)
    # a two-ray track adds one redundant measurement to its four (the point takes three), along the epipolar line
    # only, where a mismatch cannot be told from a parallax: it costs the Schur reductions as much per measurement
    # as any track and tells the diagnosis least; where they are many they are most of its cost and much of the
    # overdispersion (the whole seneca flight: benchmarks/RESULTS.md, "Diagnosis of the whole seneca flight")
    limit = config.two_ray_tracks_up_to
    if limit is not None and observations.num_rows > limit:
        multi = long_tracks(observations, 3)
        if multi.num_rows < observations.num_rows:
            sub_note = "; ".join(filter(None, [sub_note, (
                f"diagnosed on the {multi.num_rows} measurements of tie points seen in three images or more of "
                f"{observations.num_rows} (DiagnoseConfig.two_ray_tracks_up_to = {limit})")]))
            observations = multi
    base = fit_baseline(images, observations, camera, adjust_config, gcps, gcp_observations, start)
    result = diagnose_baseline(base, config, io)
    if sub_note:
        result.notes.insert(0, sub_note)
    return result


def permutation_null(baseline: Baseline, name: str, n: int = 20, seed: int = 0) -> np.ndarray:
    """Statistics of hypothesis ``name`` with its covariate shuffled across images (an empirical null).

    Temperature (thermal hypotheses) is permuted; for the other hypotheses the image order is, which
    scrambles velocities and strips. Compare the observed statistic with these.
    """
    rng = np.random.default_rng(seed)
    ctx = hyp.make_context(baseline)
    out = []
    for _ in range(n):
        perm = rng.permutation(baseline.block.n_images)
        c = dataclasses.replace(ctx, dT=ctx.dT[perm], velocity=ctx.velocity[perm])
        out.append(score(baseline, c, [name], [], 0, 1.0)[0].statistic)
    return np.asarray(out)
