"""Prediction on data the fit did not use: does a model extension predict held-out images better?

The question every named effect must answer (the decision rule's third): with the effect in the model, are
images the fit did not see predicted better than without it? A k-fold over the flight's strips (over blocks of
consecutive exposures when it has fewer than ``min_groups`` strips, e.g. a single line):

1. the block without the fold's images is adjusted with the baseline model (the *training* block: the
   effects already accepted are in its data), and extended with the hypothesis: estimated on the training
   block and removed from its data (``extend``, the diagnosis's correct-and-refit);
2. each held-out image is *resected* into each of the two fitted blocks: its pose estimated from its
   measurements of the points the fit placed (held fixed), from its recorded position and attitude where the
   block observes them, with the fit's IO; in the extended case its measurements and records corrected for the
   estimate first (the signature taken at the held-out image's own geometry);
3. its misfit under each model is the chi-square of its image measurements, recorded position and attitude::

       d_i = chi2_i(baseline) - chi2_i(extended)

The gain is ``mean(d) / mean(chi2(baseline))`` (> 0: the extension predicts better) with its standard error
over the held-out images, the units that are nearly independent (the measurements of one image share its
pose). Resecting into a fixed block tests what a model predicts for a new image, including what a free
re-adjustment of a held-out strip alone would absorb: a GNSS time lag moves a held-out image's recorded
position away from where the training block's points put it, a readout stretches its rows against them.

This is :mod:`aerocal.calibrate.heldout`'s question (there for the camera models of a self-calibration) asked of the
diagnosis's hypotheses.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy import stats

from aerocal.adjust.problem import AdjustmentError, Block
from aerocal.adjust.projection import rotation_log
from aerocal.adjust.solver import BundleProblem, State, solve
from aerocal.diagnose.model import Baseline, Covariates

#: a gain on data the fit did not use counts when it is positive beyond this many standard errors (the decision
#: rule's third question, :mod:`aerocal.certificates.review`): a named effect's held-out gain here, the leave-one-out
#: gain of an offset of the recorded attitudes (:mod:`aerocal.diagnose.attitude`) or of the block against its check
#: points; and a named effect must not make the check points worse beyond as many
HELD_OUT_SIGMAS = 2.0


class UndeterminedFold(ValueError):
    """The hypothesis is not determined on a fold's fitting images (raised by an :data:`Extension`): e.g. a GNSS
    time lag on strips all flown one way. The fold is left out of the comparison, with the reason."""


@dataclass(frozen=True)
class PredictionConfig:
    """k-fold settings. ``folds`` (5): strips are dealt round-robin in flight order into this many folds
    (a flight of 5 strips leaves one strip out at a time, one of 3 or 4 half a strip, see
    :func:`fold_of_images`): each fit keeps most of the block, so its
    estimate is nearly the whole block's (a rendered conte-calibration block, 5 strips warming 10 -> 23 degC, with
    a 0.15 px/degC focal drift: held-out gain +0.12 +- 0.17 % with 3 folds, whose fits scattered the slope by up to
    2 of their sigmas, +0.60 +- 0.14 % with 5); ``min_groups`` (3): with
    fewer strips the folds are blocks of consecutive exposures; ``min_images`` (3): images on each side of a
    fold; ``min_measurements`` (8): measurements of points of the fitted block a held-out image needs to be
    resected (6 pose unknowns and some redundancy); ``iterations`` (10): Gauss-Newton steps of a resection."""

    folds: int = 5
    min_groups: int = 3
    min_images: int = 3
    min_measurements: int = 8
    iterations: int = 10

    def __post_init__(self) -> None:
        if self.folds < 2:
            raise ValueError(f"PredictionConfig.folds must be at least 2, got {self.folds}")
        if self.min_images < 1 or self.min_measurements < 4 or self.iterations < 1:
            raise ValueError("PredictionConfig: min_images >= 1, min_measurements >= 4 and iterations >= 1 are "
                             f"needed, got {self.min_images}, {self.min_measurements}, {self.iterations}")


#: folds whose estimates :meth:`HeldOutGain.fold_dispersion` needs: fewer leave its chi-square with 1 degree of
#: freedom, whose 95 % point (3.84) no real overdispersion short of 4x would pass
MIN_DISPERSION_FOLDS = 3
#: one-sided level at which :meth:`FoldDispersion.excess` takes the folds' scatter for more than their sigmas
#: allow (the level of the per-image null's bound in :func:`aerocal.diagnose.engine.overdispersion`)
DISPERSION_LEVEL = 0.05


@dataclass(frozen=True)
class FoldDispersion:
    """The folds' scatter of an estimate against its formal sigmas (:meth:`HeldOutGain.fold_dispersion`): per
    component, ``ratio`` (lambda: 1 when the formal sigmas hold) and the number of folds it is measured on."""

    ratio: list[float]
    folds: list[int]

    def to_dict(self) -> dict:
        return {"ratio": [None if not np.isfinite(r) else r for r in self.ratio], "folds": self.folds,
                "excess": self.excess()}

    def excess(self) -> list[float]:
        """Per component, the factor by which the estimate's variance exceeds its formal one: ``ratio`` where it
        is beyond the chi-square's one-sided :data:`DISPERSION_LEVEL` bound for its folds, else 1 (a scatter
        within sampling of the formal sigmas is no evidence against them)."""
        return [r if np.isfinite(r) and r > stats.chi2.ppf(1.0 - DISPERSION_LEVEL, k - 1) / (k - 1) else 1.0
                for r, k in zip(self.ratio, self.folds, strict=True)]


@dataclass
class HeldOutGain:
    """The outcome of a k-fold comparison (module docstring). ``gain``: relative reduction of the held-out
    images' misfit (dimensionless; NaN when no fold could be evaluated) and ``sigma`` its standard error;
    ``units``: "strips", "half strips" or "time blocks"; ``image_ids``, ``reduction`` (d_i) and ``baseline``
    (chi2_i of the baseline model) per held-out image; ``folds``: per fold, its images and both models' chi-square."""

    gain: float
    sigma: float
    units: str
    image_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    reduction: np.ndarray = field(default_factory=lambda: np.zeros(0))
    baseline: np.ndarray = field(default_factory=lambda: np.zeros(0))
    folds: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def n_images(self) -> int:
        return len(self.image_ids)

    @property
    def measured(self) -> bool:
        return bool(np.isfinite(self.gain) and np.isfinite(self.sigma) and self.n_images >= 2)

    def beyond(self, k_sigma: float) -> bool:
        """True when the gain is positive beyond ``k_sigma`` standard errors."""
        return self.measured and self.gain > k_sigma * max(self.sigma, 1e-12)

    def worse_beyond(self, k_sigma: float) -> bool:
        """True when the gain is negative beyond ``k_sigma`` standard errors (the extension predicts worse)."""
        return self.measured and self.gain < -k_sigma * max(self.sigma, 1e-12)

    def fold_dispersion(self, estimate, sigma) -> FoldDispersion | None:
        """How much more the folds' estimates scatter about the whole block's than their formal sigmas allow.

        ``estimate`` and ``sigma``: the whole block's estimate of the hypothesis and its formal sigma (the units
        of the folds' ``estimate`` and ``sigma``). Each fold's fit leaves out one group of images, so its estimate
        differs from the whole block's by what that group alone says; for an efficient estimator that difference
        has variance ``sigma_k**2 - sigma**2`` (Hausman's test of nested estimators), and

            lambda = sum_k ((theta_k - theta) / sqrt(sigma_k**2 - sigma**2))**2 / K

        is chi-square with K - 1 degrees of freedom over K - 1 when the formal sigmas hold (the K differences of a
        delete-one-group jackknife are tied by one constraint). Measurement errors correlated within an image
        or a strip, or a signature the model reproduces differently strip by strip, make it larger: the
        per-image null of :func:`aerocal.diagnose.engine.overdispersion` does not see either. Per component;
        NaN for a component with fewer than :data:`MIN_DISPERSION_FOLDS` folds whose estimate and a sigma above
        the block's are known; None when no component has as many."""
        theta, s = np.atleast_1d(np.asarray(estimate, float)), np.atleast_1d(np.asarray(sigma, float))
        z2, n = np.zeros(len(theta)), np.zeros(len(theta), dtype=int)
        for fold in self.folds:
            if "estimate" not in fold or "sigma" not in fold or len(fold["estimate"]) != len(theta):
                continue
            tk, sk = np.asarray(fold["estimate"], float), np.asarray(fold["sigma"], float)
            var = sk ** 2 - s ** 2
            # a component a fit set to zero (within its noise of it: aerocal.diagnose.engine._extend) or the
            # whole block did not estimate (NaN) says nothing of the scatter
            ok = np.isfinite(tk) & np.isfinite(theta) & np.isfinite(var) & (var > 0) & (tk != 0) & (theta != 0)
            z2[ok] += (tk[ok] - theta[ok]) ** 2 / var[ok]
            n[ok] += 1
        if n.max(initial=0) < MIN_DISPERSION_FOLDS:
            return None
        enough = n >= MIN_DISPERSION_FOLDS
        return FoldDispersion([float(v) if k else float("nan") for v, k in zip(z2 / np.maximum(n, 1), enough,
                                                                                strict=True)],
                              [int(v) for v in n])

    def describe(self) -> str:
        if not self.measured:
            return "held-out gain not measured (" + "; ".join(self.notes or ["no fold could be evaluated"]) + ")"
        return (f"held-out gain {100 * self.gain:+.2f} +- {100 * self.sigma:.2f} % of the misfit of "
                f"{self.n_images} held-out images ({len(self.folds)} folds of {self.units})")

    def to_dict(self) -> dict:
        return {"gain": _finite(self.gain), "sigma": _finite(self.sigma), "n_images": self.n_images,
                "units": self.units, "folds": self.folds, "notes": list(self.notes)}


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def fold_of_images(covariates: Covariates, config: PredictionConfig) -> tuple[np.ndarray, str]:
    """Fold number of every image of a block (aligned with its ``image_ids``) and what the folds are made of:
    its strips dealt round-robin in the order they were flown ("strips"); with fewer strips than
    ``config.folds``, each strip's first and second half in their place ("half strips"); with fewer than
    ``config.min_groups`` strips, ``config.folds`` blocks of consecutive exposures ("time blocks").

    Half strips keep every fold's fitting images flown in both directions where the block is: with whole strips
    of a 3-strip block flown back and forth, leaving the middle strip out leaves two strips flown one way, on
    which a GNSS time lag is a constant offset (the datum itself without GCPs) and that fold tells nothing; its
    images were then never held out (the xt2-survey preset, 3 strips of 8: how often its lag is named before
    and after, ``benchmarks/detection_rate_bench.py`` in ``benchmarks/RESULTS.md``)."""
    t, strip = np.asarray(covariates.time_s, float), np.asarray(covariates.strip)
    order = np.argsort(t, kind="stable")
    flown = [s for s in dict.fromkeys(strip[order].tolist()) if s >= 0]
    if len(flown) >= config.min_groups:
        if len(flown) >= config.folds:
            of_strip = {s: k % config.folds for k, s in enumerate(flown)}
            return np.array([of_strip.get(int(s), -1) for s in strip]), "strips"
        out = np.full(len(t), -1, dtype=np.int64)
        k = 0
        for s in flown:
            rows = order[strip[order] == s]
            for half in np.array_split(rows, 2):
                out[half] = k % config.folds
                k += 1
        return out, "half strips"
    out = np.empty(len(t), dtype=np.int64)
    for k, rows in enumerate(np.array_split(order, config.folds)):
        out[rows] = k
    return out, "time blocks"


def sub_block(block: Block, state: State, keep: np.ndarray, min_rays: int = 2) -> tuple[Block, State, np.ndarray]:
    """The images of ``block`` where ``keep`` (N,) is True, their measurements of tie points they see at least
    ``min_rays`` times (control points: once), their check-point measurements; the matching part of ``state``;
    and each old point's index in the new block (-1 where dropped). The local frame (``origin``) is kept, so
    that sub-blocks share coordinates with the block."""
    keep = np.asarray(keep, dtype=bool)
    img_new = np.cumsum(keep) - 1
    obs_keep = keep[block.obs_image]
    counts = np.bincount(block.obs_point[obs_keep], minlength=block.n_points)
    control = np.arange(block.n_points) >= block.n_tie
    pt_keep = np.where(control, counts >= 1, counts >= min_rays)
    obs_keep &= pt_keep[block.obs_point]
    pt_new = np.cumsum(pt_keep) - 1
    ctrl_keep = pt_keep[block.n_tie:]
    chk_keep = keep[block.check_image]
    new = dataclasses.replace(
        block,
        image_ids=block.image_ids[keep],
        R_rec=block.R_rec[keep],
        gnss=block.gnss[keep],
        temperature=block.temperature[keep],
        laser_range=None if block.laser_range is None else block.laser_range[keep],
        obs_image=img_new[block.obs_image[obs_keep]],
        obs_point=pt_new[block.obs_point[obs_keep]],
        obs_uv=block.obs_uv[obs_keep],
        obs_sigma=block.obs_sigma[obs_keep],
        obs_is_tie=block.obs_is_tie[obs_keep],
        obs_row=block.obs_row[obs_keep],
        n_tie=int(pt_keep[: block.n_tie].sum()),
        track_ids=block.track_ids[pt_keep[: block.n_tie]],
        control_ids=[c for c, k in zip(block.control_ids, ctrl_keep, strict=True) if k],
        control_xyz=block.control_xyz[ctrl_keep],
        control_sigma=block.control_sigma[ctrl_keep],
        check_image=img_new[block.check_image[chk_keep]],
        check_point=block.check_point[chk_keep],
        check_uv=block.check_uv[chk_keep],
        check_sigma_px=block.check_sigma_px[chk_keep],
        n_tie_obs=int((obs_keep & block.obs_is_tie).sum()),
    )
    st = State(state.io.copy(), state.slopes.copy(), state.R[keep].copy(), state.C[keep].copy(),
               state.X[pt_keep].copy())
    return new, st, np.where(pt_keep, pt_new, -1)


def sub_baseline(base: Baseline, keep: np.ndarray) -> Baseline:
    """The baseline's block restricted to the images where ``keep`` is True (:func:`sub_block`), adjusted again
    with the baseline's configuration, from the baseline's solution; without its camera covariance (a fold's fit
    is read for its state and residuals only)."""
    block, start, _ = sub_block(base.block, base.state, keep)
    problem = BundleProblem(block, base.config, base.solution.t0, check_datum=False)
    sol = solve(problem, start, covariance=False)
    cov = Covariates(time_s=base.covariates.time_s[keep], strip=base.covariates.strip[keep])
    return Baseline(block, cov, base.config, sol, base.template)


def held_out_images(base: Baseline, fitted: Baseline, keep_fit: np.ndarray) -> tuple[Block, State]:
    """The images of ``base`` the fit left out (``~keep_fit``) with their measurements of the points ``fitted``
    placed, those points held at ``fitted``'s positions, and starting poses from ``base``."""
    held = ~np.asarray(keep_fit, dtype=bool)
    # points of the base block that the fit kept: their index in the fitted block
    _, _, in_fit = sub_block(base.block, base.state, keep_fit)
    test, st, in_test = sub_block(base.block, base.state, held, min_rays=1)
    in_test_points = np.flatnonzero(in_test >= 0)
    fitted_index = in_fit[in_test_points]
    placed = fitted_index >= 0
    # the held-out images' measurements of points the fit did not place are left out
    keep_points = np.zeros(test.n_points, dtype=bool)
    keep_points[in_test[in_test_points[placed]]] = True
    obs_keep = keep_points[test.obs_point]
    renumber = np.cumsum(keep_points) - 1
    ctrl_keep = keep_points[test.n_tie:]
    test = dataclasses.replace(
        test,
        obs_image=test.obs_image[obs_keep], obs_point=renumber[test.obs_point[obs_keep]],
        obs_uv=test.obs_uv[obs_keep], obs_sigma=test.obs_sigma[obs_keep], obs_is_tie=test.obs_is_tie[obs_keep],
        obs_row=test.obs_row[obs_keep], n_tie=int(keep_points[: test.n_tie].sum()),
        track_ids=test.track_ids[keep_points[: test.n_tie]],
        control_ids=[c for c, k in zip(test.control_ids, ctrl_keep, strict=True) if k],
        control_xyz=test.control_xyz[ctrl_keep], control_sigma=test.control_sigma[ctrl_keep],
        n_tie_obs=int((obs_keep & test.obs_is_tie).sum()),
    )
    X = np.empty((test.n_points, 3))
    X[renumber[in_test[in_test_points[placed]]]] = fitted.state.X[fitted_index[placed]]
    start = State(fitted.state.io.copy(), fitted.state.slopes.copy(), st.R, st.C, X)
    return test, start


def resect(block: Block, start: State, base: Baseline, iterations: int = 10) -> tuple[State, np.ndarray, np.ndarray]:
    """Poses of ``block``'s images with its points and the IO held at ``start``'s values: Gauss-Newton with
    Levenberg damping on the image measurements and the recorded position and attitude priors of ``base``'s
    configuration. Returns the state, each image's misfit (chi-square of its measurements, recorded position
    and attitude residuals, whitened by their sigmas) and its number of measurements."""
    problem = BundleProblem(block, base.config, base.solution.t0, check_datum=False)
    ng = problem.layout.n_global
    st, lam = start, 1e-3
    cost = problem.residuals(st, jac=False)[0]
    for _ in range(iterations):
        _, _, _, r, Jc, _, _ = problem.residuals(st, jac=True)
        Ji = Jc[:, ng:]
        H = (Ji.T @ Ji).tocsc()
        g = Ji.T @ r
        improved = False
        for _ in range(6):
            d = spla.spsolve(H + lam * sp.diags(H.diagonal() + 1e-12), -g)
            cand = problem.apply(st, np.concatenate([np.zeros(ng), d]), np.zeros(3 * block.n_points))
            c = problem.residuals(cand, jac=False)[0]
            if c < cost:
                st, improved = cand, c < cost * (1 - 1e-10)
                cost, lam = c, max(lam / 10, 1e-9)
                break
            lam *= 10
        if not improved:
            break
    return st, _image_chi2(problem, block, st), np.bincount(block.obs_image, minlength=block.n_images)


def _image_chi2(problem: BundleProblem, block: Block, st: State) -> np.ndarray:
    """Per image: the chi-square of its measurements, and of its recorded position and attitude where the
    configuration observes them, at ``st``."""
    _, res, _ = problem.residuals(st, jac=False)
    s = np.sum((res / block.obs_sigma[:, None]) ** 2, axis=1)
    out = np.bincount(block.obs_image, weights=s, minlength=block.n_images)
    if problem.gnss_sigma is not None:
        out += np.sum(((st.C - block.gnss) / problem.gnss_sigma) ** 2, axis=1)
    if problem.att_sigma is not None:
        rot = rotation_log(np.einsum("nij,nkj->nik", st.R, block.R_rec))
        out += np.sum((rot / problem.att_sigma) ** 2, axis=1)
    return out


#: ``extend(training, keep) -> (extended, correct, estimate, sigma)``: the hypothesis estimated on a training block
#: (a :class:`Baseline` of the images where ``keep`` is True) and removed from its data; ``correct(block, state)``
#: removes the same estimate from a held-out block at a state of it; ``estimate`` and its formal ``sigma``: the
#: training block's (the hypothesis's units)
Extension = Callable[[Baseline, np.ndarray],
                     tuple[Baseline, Callable[[Block, State], Block], np.ndarray, np.ndarray]]


#: folds adjusted at a time (:func:`held_out_gain`)
FOLD_THREADS = 2


def held_out_gain(base: Baseline, extend: Extension, config: PredictionConfig | None = None,
                  training: dict[int, Baseline] | None = None) -> HeldOutGain:
    """k-fold comparison of ``base``'s model with its extension by ``extend`` (module docstring).

    ``training``: the folds' training blocks by fold number, filled as they are adjusted and read where present.
    They depend on ``base`` and the folds only, not on the hypothesis: a caller that tests several hypotheses on
    one ``base`` passes one dict to every call and adjusts each training block once."""
    config = config or PredictionConfig()
    training = {} if training is None else training
    fold, units = fold_of_images(base.covariates, config)

    def one_fold(k: int) -> str | tuple:
        """Fold ``k``: a note saying why it was left out, or (image ids, d, chi2 baseline, fold record)."""
        keep = fold != k
        n_held, n_fit = int(np.sum(fold == k)), int(np.sum(keep))
        if n_held < config.min_images or n_fit < config.min_images:
            return f"fold {k}: {n_held} held-out and {n_fit} fitting images, too few"
        try:
            if k not in training:
                training[k] = sub_baseline(base, keep)
            fit = training[k]
            extended, correct, estimate, estimate_sigma = extend(fit, keep)
        except UndeterminedFold as exc:
            return f"fold {k}: {exc}"
        except (AdjustmentError, np.linalg.LinAlgError, ValueError, RuntimeError) as exc:
            return f"fold {k}: an adjustment failed ({exc})"
        try:
            test, start = held_out_images(base, fit, keep)
            count = np.bincount(test.obs_image, minlength=test.n_images)
            if not np.any(count >= config.min_measurements):
                return f"fold {k}: no held-out image measures {config.min_measurements} points of the fit"
            st_a, chi_a, n_a = resect(test, start, base, config.iterations)
            test_b, start_b = held_out_images(base, extended, keep)
            corrected = correct(test_b, dataclasses.replace(start_b, R=st_a.R, C=st_a.C))
            st_b, chi_b, _ = resect(corrected, dataclasses.replace(start_b, R=st_a.R, C=st_a.C), base,
                                    config.iterations)
        except (AdjustmentError, np.linalg.LinAlgError, ValueError, RuntimeError) as exc:
            return f"fold {k}: an adjustment failed ({exc})"
        ok = (n_a >= config.min_measurements) & np.isfinite(chi_a) & np.isfinite(chi_b)
        record = {"fold": k, "held_out_images": int(ok.sum()), "chi2_baseline": float(np.sum(chi_a[ok])),
                  "chi2_extended": float(np.sum(chi_b[ok])),
                  "estimate": [float(v) for v in np.atleast_1d(estimate)],
                  "sigma": [float(v) for v in np.atleast_1d(estimate_sigma)]}
        return test.image_ids[ok], chi_a[ok] - chi_b[ok], chi_a[ok], record

    n_folds = int(fold.max()) + 1 if len(fold) else 0
    # the folds are independent: two at a time, as the Schur reduction's kernels release the interpreter
    with ThreadPoolExecutor(max(1, min(FOLD_THREADS, n_folds))) as pool:
        outcomes = list(pool.map(one_fold, range(n_folds)))
    ids, red, chi_base, folds, notes = [], [], [], [], []
    for outcome in outcomes:
        if isinstance(outcome, str):
            notes.append(outcome)
            continue
        ids.append(outcome[0])
        red.append(outcome[1])
        chi_base.append(outcome[2])
        folds.append(outcome[3])
    if not ids:
        return HeldOutGain(float("nan"), float("nan"), units, notes=notes)
    image_ids, d, a = np.concatenate(ids), np.concatenate(red), np.concatenate(chi_base)
    scale = float(np.mean(a)) if len(a) else float("nan")
    if len(d) < 2 or not scale > 0:
        return HeldOutGain(float("nan"), float("nan"), units, image_ids, d, a, folds,
                           notes + ["too few held-out images"])
    gain = float(np.mean(d)) / scale
    sigma = float(np.std(d, ddof=1) / np.sqrt(len(d))) / scale
    return HeldOutGain(gain, sigma, units, image_ids, d, a, folds, notes)


