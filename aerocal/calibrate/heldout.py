"""Prediction on data the fit did not use: k-fold over strips (or time blocks) for two camera models.

The question a calibration parameter must answer before it is kept: does the model with it predict images
the fit did not see better than the model without it? For each fold the two models are fitted on the other
images; the fold's images are then adjusted with IO *fixed* at each model's prediction for their sensor
temperature (their poses and tie points are re-estimated, nothing of the IO), with one set of weights for
both (the tie sigma the simpler model's fit estimated), and each held-out image's misfit is compared:

    chi2_i = sum over its tie observations of (residual / sigma)^2 + ((adjusted - recorded GNSS) / sigma)^2
    d_i    = chi2_i(simpler model) - chi2_i(extended model)

The GNSS term matters: a focal length wrong for the held-out strip's temperature is absorbed by the flying
height, which shows against the recorded positions, not in the tie residuals (a rendered conte-calibration
block with a 1 px/degC drift: the tie residuals alone moved by 0.03 %). The gain is
``mean(d) / mean(chi2(simpler))`` (> 0: the extended model predicts better) with its standard error over the
held-out images. Images, not observations, are the units: the observations of one image share its pose and
are far from independent.

Folds are the flight's strips (strips flown at other times, hence other temperatures, held out together);
a flight with fewer than ``min_groups`` strips is cut into blocks of consecutive exposures instead.

This is the method of the seneca study (real data, camera cooling from 37 to 23 degC), where a focal-length
temperature slope with a formal t of 7 predicted the held-out strips no better than a constant IO.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa

from aerocal.adjust import (
    AdjustConfig,
    AdjustmentError,
    adjust,
    adjust_fixed_io,
    long_tracks,
    scale_tie_sigma,
    select_images,
)
from aerocal.camera import Camera


@dataclass(frozen=True)
class HeldOutConfig:
    """k-fold settings (defaults documented inline)."""

    folds: int = 3  # number of folds (strips are dealt round-robin in flight order)
    min_groups: int = 3  # fewer strips than this: folds are blocks of consecutive exposures
    min_images: int = 3  # a fold needs this many images on each side
    min_track_length: int = 3  # tie tracks of the held-out images seen in at least this many of them
    max_iterations: int = 20  # of every fold's adjustments

    def __post_init__(self) -> None:
        if self.folds < 2:
            raise ValueError(f"HeldOutConfig.folds must be 2 or more, got {self.folds}")
        for name in ("min_groups", "min_images", "max_iterations"):
            if getattr(self, name) < 1:
                raise ValueError(f"HeldOutConfig.{name} must be 1 or more, got {getattr(self, name)}")
        if self.min_track_length < 2:
            raise ValueError(f"HeldOutConfig.min_track_length must be 2 or more, got {self.min_track_length}")


@dataclass
class HeldOutComparison:
    """The outcome of a k-fold comparison (see the module docstring).

    ``gain``: relative reduction of the held-out images' misfit (chi-square of tie and GNSS observations;
    dimensionless, NaN when no fold could be adjusted); ``sigma``: its standard error over the held-out
    images; ``folds``: per fold, the held-out images, both models' chi-square and tie RMS (pixels);
    ``units``: "strips" or "time blocks".
    """

    gain: float
    sigma: float
    n_images: int
    units: str
    folds: list[dict] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def measured(self) -> bool:
        return bool(np.isfinite(self.gain) and np.isfinite(self.sigma) and self.n_images >= 2)

    def beyond(self, k_sigma: float) -> bool:
        """True when the extended model's gain is positive beyond ``k_sigma`` standard errors."""
        return self.measured and self.gain > k_sigma * max(self.sigma, 1e-12)

    def describe(self) -> str:
        if not self.measured:
            return "held-out gain not measured (" + "; ".join(self.notes or ["no fold could be adjusted"]) + ")"
        return (f"held-out gain {100 * self.gain:+.2f} +- {100 * self.sigma:.2f} % of the misfit of "
                f"{self.n_images} held-out images ({len(self.folds)} folds of {self.units})")

    def to_dict(self) -> dict:
        return {"gain": _finite(self.gain), "sigma": _finite(self.sigma), "n_images": self.n_images,
                "units": self.units, "folds": self.folds, "notes": self.notes}


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def fold_groups(images: pa.Table, config: HeldOutConfig) -> tuple[dict[int, int], str]:
    """Fold number of every image id, and what the folds are made of ("strips" or "time blocks")."""
    ids = images.column("image_id").to_numpy().astype(int)
    strip = np.array([-1 if s is None else int(s) for s in images.column("strip").to_pylist()])
    strips = [s for s in dict.fromkeys(strip[np.argsort(_times(images), kind="stable")].tolist()) if s >= 0]
    if len(strips) >= config.min_groups:
        fold_of_strip = {s: k % config.folds for k, s in enumerate(strips)}
        return {int(i): fold_of_strip.get(int(s), -1) for i, s in zip(ids, strip, strict=True)}, "strips"
    order = np.argsort(_times(images), kind="stable")
    blocks = np.array_split(order, config.folds)
    out = {}
    for k, rows in enumerate(blocks):
        for r in rows:
            out[int(ids[r])] = k
    return out, "time blocks"


def _times(images: pa.Table) -> np.ndarray:
    if "time" in images.schema.names:
        t = images.column("time").cast(pa.int64()).to_numpy(zero_copy_only=False).astype(float)
        if np.isfinite(t).all():
            return t
    return images.column("image_id").to_numpy().astype(float)


def _per_image_chi2(result, obs: pa.Table, images: pa.Table, gnss_sigma) -> dict[int, np.ndarray]:
    """Per held-out image: the chi-square of its tie observations (squared residuals over their sigma) per
    observation row (NaN where rejected or not triangulated), and of its recorded GNSS position against the
    adjusted projection centre (0 without GNSS observations)."""
    r = np.asarray(result.residuals, dtype=float)
    sigma = obs.column("sigma").to_numpy(zero_copy_only=False).astype(float)
    s = np.sum(r * r, axis=1) / sigma**2
    w = np.asarray(result.obs_weight, dtype=float) if len(result.obs_weight) == len(s) else np.ones(len(s))
    s[~(np.isfinite(s) & (np.nan_to_num(w, nan=1.0) > 0))] = np.nan
    gnss = {}
    if gnss_sigma is not None:
        g_ids = images.column("image_id").to_numpy().astype(int)
        G = np.column_stack([images.column(c).to_numpy(zero_copy_only=False) for c in ("gnss_x", "gnss_y", "gnss_z")])
        rec = dict(zip(g_ids.tolist(), G, strict=True))
        p_ids = result.poses.column("image_id").to_numpy().astype(int)
        C = np.column_stack([result.poses.column(c).to_numpy() for c in ("X", "Y", "Z")])
        sg = np.asarray(gnss_sigma, dtype=float)
        for i, c in zip(p_ids.tolist(), C, strict=True):
            gnss[i] = float(np.sum(((c - rec[i]) / sg) ** 2)) if i in rec else 0.0
    return {"tie": s, "gnss": gnss}


def _rms(chi2: np.ndarray, obs: pa.Table, mask: np.ndarray) -> float | None:
    """RMS per coordinate (pixels) of residuals given as chi-square per observation and the sigma column."""
    if not len(chi2):
        return None
    sigma = obs.column("sigma").to_numpy(zero_copy_only=False).astype(float)[mask]
    return float(np.sqrt(np.mean(chi2 * sigma**2) / 2))


def compare_models(
    images: pa.Table,
    observations: pa.Table,
    camera: Camera,
    simple: AdjustConfig,
    extended: AdjustConfig,
    gcps: pa.Table | None = None,
    gcp_observations: pa.Table | None = None,
    config: HeldOutConfig | None = None,
) -> HeldOutComparison:
    """k-fold comparison of the camera models of two adjustment configurations (see the module docstring).

    ``simple`` and ``extended`` are self-calibrating configurations (their ``free`` and ``thermal`` say what
    each model estimates); ``camera`` is the starting (nominal) camera. Both are run without adaptive
    selection, for at most ``config.max_iterations`` iterations, the extended one started from the simpler one's
    fit of the fold (``adjust(..., initial=...)``: its poses, tie points and blunder screening).
    """
    config = config or HeldOutConfig()
    fold_of, units = fold_groups(images, config)
    ids = images.column("image_id").to_numpy().astype(int)
    cfgs = [dataclasses.replace(c, adaptive=False, max_iterations=config.max_iterations, tie_thinning=None)
            for c in (simple, extended)]
    diffs: list[np.ndarray] = []
    base: list[np.ndarray] = []
    folds: list[dict] = []
    notes: list[str] = []
    for k in range(config.folds):
        test = np.array([i for i in ids if fold_of.get(int(i)) == k])
        train = np.array([i for i in ids if fold_of.get(int(i), -1) != k])
        if len(test) < config.min_images or len(train) < config.min_images:
            notes.append(f"fold {k}: {len(test)} held-out and {len(train)} fitting images, too few")
            continue
        test_obs = long_tracks(select_images(observations, test), config.min_track_length)
        if test_obs.num_rows == 0:
            notes.append(f"fold {k}: no tie track is seen in {config.min_track_length} held-out images")
            continue

        def sub(table, which):
            return select_images(table, which) if table is not None else None

        chi2 = []
        fit = None
        try:
            for n, cfg in enumerate(cfgs):
                # the extended model starts from the simpler one's fit on the same images (its poses, tie points
                # and blunder screening): both then end next to their optimum within the iteration budget, and
                # the gain is the model's, not the start's (from the records, the extended fits of real
                # h20t_forest stopped at the cap: benchmarks/RESULTS.md, "h20t_forest: the self-calibration
                # starts each model from the one it extends")
                fit = adjust(select_images(images, train), select_images(observations, train), camera, cfg,
                             gcps, sub(gcp_observations, train), initial=fit)
                if n == 0:  # one tie weight for both evaluations: the simpler model's estimate on the fit
                    eval_obs = scale_tie_sigma(test_obs, fit.tie_sigma_scale)
                ev = adjust_fixed_io(select_images(images, test), eval_obs, fit.camera,
                                     dataclasses.replace(cfg, estimate_tie_sigma=False), gcps,
                                     sub(gcp_observations, test), thermal=fit.thermal)
                chi2.append(_per_image_chi2(ev, eval_obs, select_images(images, test), cfg.gnss_sigma_m))
        except (AdjustmentError, np.linalg.LinAlgError, ValueError) as exc:
            notes.append(f"fold {k}: an adjustment failed ({exc})")
            continue
        img = eval_obs.column("image_id").to_numpy().astype(int)
        sa, sb = chi2[0]["tie"], chi2[1]["tie"]
        both = np.isfinite(sa) & np.isfinite(sb)
        imgs = np.unique(img[both])
        da = np.array([np.sum(sa[both & (img == i)]) + chi2[0]["gnss"].get(int(i), 0.0) for i in imgs])
        db = np.array([np.sum(sb[both & (img == i)]) + chi2[1]["gnss"].get(int(i), 0.0) for i in imgs])
        diffs.append(da - db)
        base.append(da)
        folds.append({"fold": k, "held_out_images": int(len(imgs)),
                      "chi2_simple": float(np.sum(da)), "chi2_extended": float(np.sum(db)),
                      "tie_rms_simple_px": _rms(sa[both], eval_obs, both),
                      "tie_rms_extended_px": _rms(sb[both], eval_obs, both)})
    if not diffs:
        return HeldOutComparison(float("nan"), float("nan"), 0, units, folds, notes)
    d, a = np.concatenate(diffs), np.concatenate(base)
    n = len(d)
    scale = float(np.mean(a)) if len(a) else float("nan")
    if n < 2 or not scale > 0:
        return HeldOutComparison(float("nan"), float("nan"), n, units, folds, notes + ["too few held-out images"])
    return HeldOutComparison(float(np.mean(d)) / scale, float(np.std(d, ddof=1) / np.sqrt(n)) / scale, n, units,
                             folds, notes)
