"""Self-calibration of a flight, governed by the decision rule (:mod:`aerocal.certificates.review`), and its
certificate.

:func:`self_calibrate` does, in order:

1. **The calibration block.** The images given by the user; else the whole flight when it has at most
   ``whole_flight_max_images``; else the sub-block of :func:`aerocal.calibrate.subset.propose_subset` (parallel strips
   near the centre, a transversal strip when flown). A flight whose geometry yields no candidate (a corridor
   of one or two strips) is calibrated on its central ``corridor_max_images`` images, and the reason says so.
2. **What the block can determine.** The precision of f, cx, cy (and slopes) is predicted from the block's
   geometry and its GNSS/GCP weights before any fit (:func:`aerocal.calibrate.subset.predict_io_sigmas`); a parameter
   the block cannot determine stays at the nominal value (:func:`aerocal.certificates.review.undetermined_io`), and
   so does its temperature slope.
3. **The recorded GNSS offset** is tested against the control GCPs and subtracted where the diagnosis names
   it (:func:`aerocal.calibrate.eo_checks.correct_gnss_offset`): unmodelled, it is absorbed by f.
   **The adjustment** with adaptive parameter selection (:func:`aerocal.adjust.adjust`); the formal statistics
   are then calibrated by the block's overdispersion, the selection repeated against t > 1.96 sqrt(phi), and
   f, cx, cy whose calibrated sigma fails the determinability test go back to nominal.
4. **Held-out test of the thermal slopes** it kept (:func:`aerocal.calibrate.heldout.compare_models`, k-fold over
   strips): a slope whose held-out gain is not positive beyond ``DecisionConfig.held_out_sigmas`` standard
   errors is dropped and the block adjusted again without it. The formal t of a slope on matched tie
   points can be 7 where the held-out gain is nil (the real seneca flight).
5. **Review** (:func:`aerocal.certificates.review.review_calibration`): plausibility against the nominal camera,
   convergence, sigma0, check points; where the camera's laser range finder measured ranges no fit used, the
   block's depth against them (:func:`held_out_laser_depth`, :func:`aerocal.certificates.review.review_laser_depth`).
   A rejected calibration still yields a certificate, marked rejected with every reason, so that the store keeps
   the record; it is never used for a flight.

Everything is returned as fields (:class:`Calibration`), never as prose to be parsed.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyarrow as pa

from aerocal.adjust import AdjustConfig, AdjustmentResult, adjust, corrected_to_t0, scale_tie_sigma, select_images
from aerocal.adjust.covariance import t_critical
from aerocal.adjust.laser import LaserRangeCheck, held_out_tie_ranges
from aerocal.adjust.strategy import central_images
from aerocal.calibrate.eo_checks import correct_gnss_offset
from aerocal.calibrate.heldout import HeldOutComparison, HeldOutConfig, compare_models
from aerocal.calibrate.subset import SubsetConfig, predict_io_sigmas, propose_subset
from aerocal.camera import PARAM_NAMES, Camera, LinearThermalModel
from aerocal.certificates.document import (
    CameraIdentity,
    Certificate,
    Conditions,
    Correlation,
    ParameterSignificance,
    Provenance,
    Quality,
    ThermalCalibration,
)
from aerocal.certificates.review import (
    DecisionConfig,
    Review,
    nominal_sigma,
    review_calibration,
    review_laser_depth,
    undetermined_io,
)
from aerocal.diagnose.engine import overdispersion
from aerocal.diagnose.model import fit_baseline
from aerocal.poses import poses_arrays

#: adjustment names of thermal slopes -> certificate names (pixels per degC)
SLOPE_NAMES = {"df/dT": "df_dt", "dcx/dT": "dcx_dt", "dcy/dT": "dcy_dt"}


@dataclass(frozen=True)
class CalibrationConfig:
    """Self-calibration settings.

    * ``adjust``: the self-calibrating adjustment (default: f, cx, cy, k1..k3, p1, p2 free, a focal-length
      temperature slope, adaptive selection dropping insignificant or |r| > 0.95 parameters).
    * ``subset``: :class:`aerocal.calibrate.subset.SubsetConfig` for :func:`~aerocal.calibrate.subset.propose_subset`
      (``None``: its defaults, with the flight's height above ground and this adjustment's weights).
    * ``whole_flight_max_images`` (44, Conte 2018's sub-block size): a flight of at most this many images
      is calibrated whole, with no sub-block search.
    * ``corridor_max_images`` (100): a flight whose strips yield no sub-block candidate (a corridor) is
      calibrated on at most this many images nearest its centre.
    * ``subset_images``: image ids of the sub-block, chosen by hand (``None``: propose one);
      ``subset_names``: the same by image name.
    * ``decision``: :class:`aerocal.certificates.review.DecisionConfig`, the thresholds of the decision rule.
    * ``held_out``: :class:`aerocal.calibrate.heldout.HeldOutConfig`, the k-fold test of thermal slopes.
    * ``null_draws`` (40): random per-image focal hypotheses whose statistics measure how optimistic the
      formal sigmas are on this block (:func:`aerocal.diagnose.engine.overdispersion`); the certificate's
      calibrated t values and the review's sigma of f are scaled by it (0: formal statistics only).
    """

    adjust: AdjustConfig = field(default_factory=lambda: AdjustConfig(thermal=("f",), adaptive=True))
    subset: SubsetConfig | None = None
    whole_flight_max_images: int = 44
    corridor_max_images: int = 100
    subset_images: tuple[int, ...] | None = None
    subset_names: tuple[str, ...] | None = None
    decision: DecisionConfig = field(default_factory=DecisionConfig)
    held_out: HeldOutConfig = field(default_factory=HeldOutConfig)
    null_draws: int = 40

    def __post_init__(self) -> None:
        for name in ("whole_flight_max_images", "corridor_max_images"):
            if getattr(self, name) < 1:
                raise ValueError(f"CalibrationConfig.{name} must be 1 or more, got {getattr(self, name)}")
        if self.subset_images is not None and self.subset_names is not None:
            raise ValueError("CalibrationConfig: give subset_images or subset_names, not both")
        for name in ("subset_images", "subset_names"):
            if getattr(self, name) is not None and not len(getattr(self, name)):
                raise ValueError(f"CalibrationConfig.{name} is empty; give the sub-block's images or None")
        if self.null_draws < 0:
            raise ValueError(f"CalibrationConfig.null_draws must be 0 or more, got {self.null_draws}")


@dataclass
class Calibration:
    """A finished self-calibration.

    * ``result``: the adjustment of the calibration block (IO at ``result.t0``).
    * ``image_ids``: the block's images; ``subset``: how they were chosen (``reasons``, and for a proposed
      sub-block its strips, GCPs and predicted sigmas); ``transversal``: whether a transversal strip is in.
    * ``predicted``: predicted sigmas of the free parameters from the geometry (``None``: terrain unknown).
    * ``held_at_nominal``: parameters not freed, each with the reason; ``held_sigmas``: the standard
      deviation of each nominal value held (the certificate records it for the diagnosis).
    * ``held_out``: the k-fold comparison of each thermal slope tested, by adjustment name (``df/dT``).
    * ``review``: the verdict.
    * ``usable_on_its_flight``: the fit passed its review and only the flight's input errors rejected it: the
      items they name were skipped at ingest and never reached the fit, so the flight it was made on may use it,
      while later flights never do (they are told to fix the input and calibrate again).
    * ``laser_depth``: the block's tie points around each axis against the laser ranges no fit used
      (:func:`held_out_laser_depth`; ``None`` when the images record none), which the review judged.
    * ``overdispersion``: how many times larger than chi-square the statistics of pure-noise hypotheses are
      on the block (1: the formal sigmas hold); calibrated sigmas are the formal ones times its square root.
      ``overdispersion_measured``: False when it was not measured (``null_draws`` 0, or the null could not be
      fitted): the certificate then says its sigmas are the formal ones.
    """

    result: AdjustmentResult
    image_ids: list[int]
    subset: dict[str, Any]
    transversal: bool | None
    predicted: dict[str, float] | None
    held_at_nominal: dict[str, str]
    held_out: dict[str, HeldOutComparison]
    review: Review
    overdispersion: float = 1.0
    #: standard deviation (px) of each nominal value held (:func:`aerocal.certificates.review.nominal_sigma`)
    held_sigmas: dict[str, float] = dataclasses.field(default_factory=dict)
    overdispersion_measured: bool = True
    laser_depth: LaserRangeCheck | None = None
    usable_on_its_flight: bool = False

    def summary(self) -> dict:
        """JSON-ready figures a user checks."""
        return {
            "subset": self.subset,
            "adjustment": self.result.summary(),
            "predicted_sigmas": self.predicted,
            "held_at_nominal": self.held_at_nominal,
            "held_out": {k: v.to_dict() for k, v in self.held_out.items()},
            "review": self.review.to_dict(),
            "usable_on_its_flight": self.usable_on_its_flight,
            "overdispersion": self.overdispersion,
            "laser_depth": None if self.laser_depth is None else self.laser_depth.figures(),
        }


def _choose_block(images: pa.Table, camera: Camera, gcps: pa.Table | None, config: CalibrationConfig,
                  scfg: SubsetConfig) -> tuple[list[int], dict[str, Any], bool | None]:
    if config.subset_names is not None:
        by_name = dict(zip(images.column("name").to_pylist(), images.column("image_id").to_pylist(), strict=True))
        unknown = [n for n in config.subset_names if n not in by_name]
        if unknown:
            raise ValueError(f"calibration sub-block: images {unknown[:5]} are not in the flight; give names of "
                             "the flight's images")
        return [int(by_name[n]) for n in config.subset_names], {"reasons": ["sub-block given by the user "
                                                                           "(image names)"]}, None
    if config.subset_images is not None:
        ids = [int(i) for i in config.subset_images]
        known = set(images.column("image_id").to_pylist())
        missing = sorted(set(ids) - known)
        if missing:
            raise ValueError(f"calibration sub-block: image ids {missing[:5]} are not in the flight; give ids of "
                             "the images table")
        return ids, {"reasons": ["sub-block given by the user"]}, None
    n = images.num_rows
    if n <= config.whole_flight_max_images:
        return images.column("image_id").to_pylist(), {"reasons": [
            f"the flight has {n} images, no more than whole_flight_max_images = {config.whole_flight_max_images}: "
            "it is calibrated whole"]}, None
    try:
        prop = propose_subset(images, camera, gcps, scfg)
    except ValueError as exc:
        ids = [int(i) for i in central_images(images, config.corridor_max_images)]
        return ids, {"reasons": [
            f"no calibration sub-block of parallel strips ({exc}): calibrated on the {len(ids)} images nearest "
            f"the flight's centre (corridor_max_images = {config.corridor_max_images})"]}, None
    return prop.image_ids, {"image_ids": prop.image_ids, "strips": prop.strips, "transversal": prop.transversal,
                            "gcp_ids": prop.gcp_ids, "predicted_sigmas": prop.predicted_sigmas,
                            "score": prop.score, "reasons": prop.reasons}, prop.transversal


def _held_at_nominal(undetermined: dict[str, str], cfg: AdjustConfig) -> AdjustConfig:
    drop = set(undetermined)
    return dataclasses.replace(
        cfg, free=tuple(n for n in cfg.free if n not in drop), thermal=tuple(n for n in cfg.thermal if n not in drop),
        always_keep=tuple(n for n in cfg.always_keep if n not in drop))


def self_calibrate(
    images: pa.Table,
    observations: pa.Table,
    camera: Camera,
    gcps: pa.Table | None = None,
    gcp_observations: pa.Table | None = None,
    height_agl_m: float | None = None,
    config: CalibrationConfig | None = None,
    adjust_config: AdjustConfig | None = None,
    input_errors: tuple[str, ...] = (),
) -> Calibration:
    """Self-calibrate a flight under the decision rule (see the module docstring).

    Args:
        images, observations, gcps, gcp_observations: the flight's tables (:mod:`aerocal.tables`; flight CRS,
            metres; pixels).
        camera: the nominal camera (starting values, and the prior every estimate is checked against; pixels).
        height_agl_m: the flying height above ground (metres), for the geometry's prediction without GCPs.
        config: the sub-block, the decision rule and the held-out test (default :class:`CalibrationConfig`).
        adjust_config: overrides ``config.adjust`` (e.g. with the flight's declared GNSS sigmas).
        input_errors: errors the ingest reported for this flight. A calibration made from input with errors is
            rejected (its certificate stays on record, never used): one bad cell must not poison later flights.

    Returns:
        :class:`Calibration`: the adjustment of the calibration block, the review (accepted or rejected, and why),
        what was held at its nominal value and why, the thermal slopes with their held-out gains, the notes.

    Raises:
        ValueError: ``config.subset_images`` / ``subset_names`` name images the flight does not hold.
        AdjustmentError: the calibration block has no datum (see :func:`aerocal.adjust.adjust`).
    """
    config = config or CalibrationConfig()
    acfg = adjust_config or config.adjust
    scfg = config.subset or SubsetConfig()
    if scfg.height_agl_m is None and height_agl_m:
        scfg = dataclasses.replace(scfg, height_agl_m=float(height_agl_m))
    # the sub-block's IO precision is predicted with the weights the calibration will have
    scfg = dataclasses.replace(scfg, adjust=dataclasses.replace(acfg, adaptive=False, robust_loss="none"))
    ids, info, transversal = _choose_block(images, camera, gcps, config, scfg)
    sub_images = select_images(images, ids)
    sub_obs = select_images(observations, ids)
    sub_gobs = select_images(gcp_observations, ids) if gcp_observations is not None else None
    run_cfg = acfg
    notes: list[str] = []
    temps = sub_images.column("temperature_c").to_numpy(zero_copy_only=False).astype(float)
    if acfg.thermal and not (np.isfinite(temps).all() and np.ptp(temps) > 0):
        run_cfg = dataclasses.replace(acfg, thermal=())
        missing = int(np.sum(~np.isfinite(temps)))
        why = (f"{missing} of {len(temps)} calibration images have no sensor temperature" if missing
               else f"every calibration image was taken at {temps[0]:g} degC")
        notes.append(f"thermal slopes {list(acfg.thermal)} not estimated: {why}")
        info["thermal"] = notes[-1]
    predicted = info.get("predicted_sigmas") if config.subset_images is None and config.subset_names is None \
        else None
    if predicted is None:
        predicted = predict_io_sigmas(images, camera, gcps, dataclasses.replace(
            scfg, adjust=dataclasses.replace(run_cfg, adaptive=False, robust_loss="none")), ids)
    held: dict[str, str] = {}
    by_prediction: set[str] = set()  # held on the geometry's prediction alone (not on the fit's own sigmas)
    if predicted is None:
        notes.append("the terrain height is unknown (no GCPs, no height above ground): the IO precision could not "
                     "be predicted before the fit; the review checks the estimate afterwards")
    else:
        held = undetermined_io(predicted, camera, config.decision)
        by_prediction = set(held)
        if held:
            run_cfg = _held_at_nominal(held, run_cfg)
            notes.extend(held.values())

    def fit(cfg: AdjustConfig, start: AdjustmentResult | None = None) -> AdjustmentResult:
        # ``start``: the fit of the model this one extends or reduces, which it starts from and whose blunder
        # screening it keeps (from the records, the real h20t_forest block with the principal point freed did
        # not always converge: benchmarks/RESULTS.md, "h20t_forest: the self-calibration starts each model
        # from the one it extends")
        result = adjust(sub_images, sub_obs, camera, cfg, gcps, sub_gobs, initial=start)
        if result.converged:
            return result
        # the adaptive selection's last adjustment can stop in a slow tail (as on the real seneca calibration
        # block); a certificate needs the optimum, so adjust the selected model again with a longer budget, and
        # let the review reject it if that fails too
        longer = dataclasses.replace(cfg, free=result.config.free, thermal=result.config.thermal, adaptive=False,
                                     max_iterations=3 * cfg.max_iterations,
                                     marginal_over=_dropped_io(result, cfg))
        again = adjust(sub_images, sub_obs, camera, longer, gcps, sub_gobs, initial=result)
        notes.append(f"the self-calibration stopped after {result.iterations} iterations without converging; "
                     f"adjusted again with up to {longer.max_iterations}: "
                     + ("converged" if again.converged else "did not converge either")
                     + f" in {again.iterations} (f {result.camera.f:.2f} -> {again.camera.f:.2f} px)")
        again.dropped, again.selection = result.dropped, result.selection + [notes[-1]]
        return again

    eo = correct_gnss_offset(sub_images, sub_obs, camera, run_cfg, gcps, sub_gobs,
                             block=f"the {sub_images.num_rows}-image calibration block, IO free")
    sub_images = eo.images
    notes.extend(eo.notes)
    info["gnss_offset"] = {"offset_m": eo.offset_m, "sigma_m": eo.sigma_m, "time_offset_s": eo.time_offset_s,
                           "time_sigma_s": eo.time_sigma_s}
    result = fit(run_cfg)
    phi, failure = _overdispersion(sub_images, sub_obs, camera, run_cfg, result, gcps, sub_gobs, config.null_draws)
    if failure:
        notes.append(f"the block's overdispersion could not be measured ({failure}): the sigmas and t values are "
                     "the formal ones, which real blocks have shown several times too small")
    if phi > 1.0:
        notes.append(f"the formal statistics are {phi:.1f}x too large on this block (median of {config.null_draws} "
                     "random per-image focal hypotheses): sigmas and t values are calibrated by its square root")
        if run_cfg.adaptive:
            # (b) of the rule: a parameter is kept when significant against the null measured on the block
            run_cfg = dataclasses.replace(run_cfg, t_limit=run_cfg.t_limit * float(np.sqrt(phi)))
            notes.append(f"parameters selected again with t > {run_cfg.t_limit:.2f} (1.96 x sqrt({phi:.1f}))")
            result = fit(run_cfg, result)
        # (a) again, with the fit's own sigmas calibrated: f, cx, cy the block does not determine go back to nominal
        calibrated = {n: float(result.sigmas[n]) * float(np.sqrt(phi)) for n in ("f", "cx", "cy")
                      if n in result.sigmas}
        late = undetermined_io(calibrated, camera, config.decision, "calibrated sigma (formal x sqrt of the "
                                                                    "overdispersion)")
        if late:
            held.update(late)
            notes.extend(late.values())
            run_cfg = _held_at_nominal(late, run_cfg)
            result = fit(run_cfg, result)
    held_out: dict[str, HeldOutComparison] = {}
    point = [n for n in ("cx", "cy") if n in by_prediction and n in acfg.free]
    if point:
        freed, cmp = _free_if_it_predicts(point, held, run_cfg, result, fit, sub_images, sub_obs, camera, gcps,
                                          sub_gobs, config, notes, float(np.sqrt(phi)))
        for n in point:
            held_out[n] = cmp
        if freed is not None:
            run_cfg, result = freed
    if result.thermal_slopes:
        final = dataclasses.replace(run_cfg, free=result.config.free, thermal=result.config.thermal,
                                    adaptive=False, marginal_over=_dropped_io(result, run_cfg))
        simple = dataclasses.replace(final, thermal=())
        cmp = compare_models(sub_images, sub_obs, camera, simple, final, gcps, sub_gobs, config.held_out)
        for name in result.thermal_slopes:
            held_out[name] = cmp
        k = config.decision.held_out_sigmas
        if not cmp.beyond(k):
            slopes = ", ".join(f"{n} = {v:+.3g} +- {result.thermal_sigmas.get(n, float('nan')):.2g} px/degC"
                               for n, v in result.thermal_slopes.items())
            notes.append(f"{slopes} dropped: it does not predict held-out images better beyond {k:g} sigma "
                         f"({cmp.describe()}); the certificate holds a constant IO")
            dropped = dict(result.dropped)
            for n in result.thermal_slopes:
                dropped[n] = (f"no held-out gain beyond {k:g} sigma ({cmp.describe()})",
                              float(result.t_values[result.names.index(n)]))
            selection = result.selection
            result = fit(simple, result)
            result.dropped, result.selection = dropped, selection + [notes[-1]]
        else:
            notes.append(f"thermal slope(s) {', '.join(result.thermal_slopes)} kept: {cmp.describe()}")
            limit = config.decision.max_thermal_slope * camera.f
            fast = {n: v for n, v in result.thermal_slopes.items() if abs(v) > limit}
            if fast:
                # (2) of the rule: a held-out gain from a slope no lens has is another cause's signal (the real
                # seneca flight's slope, which its study refuted: benchmarks/history/engine_measurements.md)
                notes.append(f"{', '.join(f'{n} = {v:+.3g}' for n, v in fast.items())} px/degC dropped all the "
                             f"same: beyond {config.decision.max_thermal_slope:g} x f = {limit:.3g} px/degC, no lens "
                             "drifts that fast; the certificate holds a constant IO")
                dropped = dict(result.dropped)
                for n in result.thermal_slopes:
                    dropped[n] = (notes[-1], float(result.t_values[result.names.index(n)]))
                selection = result.selection
                result = fit(simple, result)
                result.dropped, result.selection = dropped, selection + [notes[-1]]
    if result.marginal_note:  # the sigmas are marginal over the dropped IO parameters: say over which
        notes.append(result.marginal_note + (f" (formal; the certificate's are these x {np.sqrt(phi):.3g}, the "
                                             "square root of the block's overdispersion)" if phi > 1.0 else ""))
    review = review_calibration(result, camera, config.decision, calibration=float(np.sqrt(phi))).merged(notes=notes)
    laser = held_out_laser_depth(sub_images, sub_obs, result)
    if laser is not None:
        verdict = review_laser_depth(len(laser.image_ids), laser.median_m, laser.median_error_m,
                                     float(np.median(laser.laser_m)) if laser.image_ids else float("nan"),
                                     config.decision)
        review = review.merged(verdict.problems, verdict.checks, verdict.notes)
    usable_here = review.accepted
    if input_errors:
        review = review.merged(problems=[
            f"the flight's input has {len(input_errors)} error(s) (first: {input_errors[0]}); fix them and "
            "calibrate again"])
    held_sigmas = {n: nominal_sigma(n, camera, config.decision) for n in held if n in ("f", "cx", "cy")}
    return Calibration(result, [int(i) for i in ids], info, transversal, predicted, held, held_out, review, phi,
                       held_sigmas, overdispersion_measured=config.null_draws > 0 and failure is None,
                       laser_depth=laser, usable_on_its_flight=usable_here)


def _free_if_it_predicts(names: list[str], held: dict[str, str], run_cfg: AdjustConfig, result: AdjustmentResult,
                         fit: Callable[[AdjustConfig, AdjustmentResult], AdjustmentResult], images: pa.Table,
                         observations: pa.Table,
                         camera: Camera, gcps: pa.Table | None, gcp_observations: pa.Table | None,
                         config: CalibrationConfig, notes: list[str], calibration: float
                         ) -> tuple[tuple[AdjustConfig, AdjustmentResult] | None, HeldOutComparison]:
    """Test the IO parameters ``names`` that the geometry's prediction held at their nominal values on data the fit
    did not use: the selected model against it with ``names`` free, k-fold over strips
    (:func:`aerocal.calibrate.heldout.compare_models`). Freed (``held`` and ``notes`` updated in place, the
    block adjusted again with ``fit``) when the gain is beyond ``held_out_sigmas`` standard errors and at least
    ``min_freeing_gain`` of the held-out misfit, the values stay
    within the decision rule's band and their sigmas, calibrated by ``calibration`` (the square root of the block's
    overdispersion), pass its determinability test; else held, with the comparison in the notes.

    Why: the prediction models the block as a tie grid on a plane; a real block can determine more than that,
    and a principal point held at the frame's centre when the lens sits off it is a confident wrong answer that
    the other parameters absorb (real h20t_forest: the lens 18 px off the centre, held there, bent the block by a
    k1 that put its surface 8 % too deep by the camera's laser range finder; ``benchmarks/RESULTS.md``,
    "h20t_forest: the principal point")."""
    k = config.decision.held_out_sigmas
    selected = dataclasses.replace(run_cfg, free=result.config.free, thermal=result.config.thermal, adaptive=False,
                                   marginal_over=_dropped_io(result, run_cfg))
    extended = dataclasses.replace(selected, free=selected.free + tuple(names))
    cmp = compare_models(images, observations, camera, selected, extended, gcps, gcp_observations, config.held_out)
    label = ", ".join(names)
    floor = config.decision.min_freeing_gain
    if not (cmp.beyond(k) and cmp.gain >= floor):
        notes.append(f"{label} held at the nominal all the same: freed, they do not predict held-out images better "
                     f"beyond {k:g} sigma and {100 * floor:g} % ({cmp.describe()})")
        return None, cmp
    free_cfg = dataclasses.replace(run_cfg, free=run_cfg.free + tuple(names),
                                   always_keep=run_cfg.always_keep + tuple(names))
    freed = fit(free_cfg, result)
    band = config.decision.principal_point_band
    off = {n: getattr(freed.camera, n) - getattr(camera, n) for n in names}
    sides = {"cx": camera.width, "cy": camera.height}
    late = undetermined_io({n: float(freed.sigmas.get(n, np.inf)) * calibration for n in names}, camera,
                           config.decision, "calibrated sigma")
    why = ("the adjustment did not converge" if not freed.converged
           else "; ".join(late[n] for n in names if n in late) if any(n in late for n in names)
           else ("the adjustment moves them beyond " + f"{100 * band:g} % of the image side ("
                 + ", ".join(f"{n} {v:+.1f} px" for n, v in off.items()) + ")")
           if any(abs(v) > band * sides[n] for n, v in off.items()) else "")
    if why:
        notes.append(f"{label} held at the nominal all the same: freed, they predict held-out images better "
                     f"({cmp.describe()}), but {why}")
        return None, cmp
    for n in names:
        notes.remove(held.pop(n))
    for n in ("p1", "p2"):
        if n in held:
            notes.remove(held[n])
            held[n] = (f"{n} held at 0: decentring distortion moves the image as a principal-point error does, and "
                       "the principal point was freed on its held-out gain alone")
            notes.append(held[n])
    notes.append(f"{label} freed although the geometry's prediction held them: with them free the model predicts "
                 f"held-out images better ({cmp.describe()}); " + ", ".join(
                     f"{n} {getattr(freed.camera, n):.2f} px ({v:+.1f} from the nominal)" for n, v in off.items()))
    return (free_cfg, freed), cmp


def held_out_laser_depth(images: pa.Table, observations: pa.Table, result: AdjustmentResult
                         ) -> LaserRangeCheck | None:
    """The adjusted block's tie points around each camera's axis against the laser ranges no fit used
    (:func:`aerocal.adjust.laser.held_out_tie_ranges`); ``None`` when the images record no laser range."""
    if "laser_range_m" not in images.column_names:
        return None
    laser = images.column("laser_range_m").to_numpy(zero_copy_only=False).astype(float)
    if not np.isfinite(laser).any():
        return None
    ids, R, C = poses_arrays(result.poses)
    by_id = dict(zip(images.column("image_id").to_pylist(), laser, strict=True))
    laser = np.array([by_id.get(int(i), np.nan) for i in ids])
    order = np.argsort(ids)
    obs_ids = observations.column("image_id").to_numpy()
    pos = np.clip(np.searchsorted(ids[order], obs_ids), 0, len(ids) - 1)
    keep = ids[order][pos] == obs_ids
    obs_image = order[pos][keep]
    tracks = result.points.column("track_id").to_numpy()
    xyz = np.column_stack([result.points.column(c).to_numpy() for c in ("X", "Y", "Z")])
    t_order = np.argsort(tracks)
    obs_tracks = observations.column("track_id").to_numpy()[keep]
    tpos = np.clip(np.searchsorted(tracks[t_order], obs_tracks), 0, max(len(tracks) - 1, 0))
    obs_X = np.full((len(obs_tracks), 3), np.nan)
    if len(tracks):
        found = tracks[t_order][tpos] == obs_tracks
        obs_X[found] = xyz[t_order][tpos[found]]
    uv = np.column_stack([observations.column("x").to_numpy()[keep], observations.column("y").to_numpy()[keep]])
    cam = result.camera
    return held_out_tie_ranges(ids, laser, R, C, obs_image, obs_X, uv, (cam.cx, cam.cy), cam.f)


def _dropped_io(result: AdjustmentResult, config: AdjustConfig) -> tuple[str, ...]:
    """The IO parameters an adaptive selection dropped (``result.dropped``) or ``config`` already keeps the
    sigmas marginal over (a re-adjustment of a re-adjustment: seneca's selected model, its slope dropped, then
    refitted with a longer budget): the re-adjustment keeps its sigmas marginal over them
    (``AdjustConfig.marginal_over``)."""
    return tuple(dict.fromkeys([*config.marginal_over, *(n for n in result.dropped if n in PARAM_NAMES)]))


def _overdispersion(images: pa.Table, observations: pa.Table, camera: Camera, run_cfg: AdjustConfig,
                    result: AdjustmentResult, gcps, gcp_observations, draws: int) -> tuple[float, str | None]:
    """The overdispersion of the calibration block (:func:`aerocal.diagnose.engine.overdispersion`), measured
    on the calibration's own model: its blunders left out, its tie sigma, least squares, its thermal slopes as a
    correction of the measurements to their reference temperature (the null's random per-image focal lengths
    otherwise take part of a drift the model holds: on a warming Daakir calibration block they measured an
    overdispersion many times the drift-free block's and raised the significance bar with it:
    ``benchmarks/history/engine_measurements.md``).

    Returns ``(phi, failure)``: 1.0 and a sentence saying why when the null could not be fitted."""
    if draws <= 0:
        return 1.0, None
    w = np.asarray(result.obs_weight, dtype=float)
    keep = np.flatnonzero(np.nan_to_num(w, nan=1.0) != 0) if len(w) == observations.num_rows else \
        np.arange(observations.num_rows)
    obs = scale_tie_sigma(observations.take(pa.array(keep, pa.int64())), result.tie_sigma_scale)
    thermal = result.thermal if isinstance(result.thermal, LinearThermalModel) and result.thermal_slopes else None
    obs = corrected_to_t0(images, obs, result.camera, thermal)
    gcp_observations = corrected_to_t0(images, gcp_observations, result.camera, thermal)
    cfg = dataclasses.replace(run_cfg, free=result.config.free, thermal=(), adaptive=False, robust_loss="none",
                              tie_thinning=None)
    try:
        base = fit_baseline(images, obs, camera, cfg, gcps, gcp_observations)
        phi = float(overdispersion(base, draws)[0])
    except (np.linalg.LinAlgError, ValueError) as exc:
        return 1.0, f"{type(exc).__name__}: {exc}"
    if not np.isfinite(phi):
        return 1.0, f"the null's median statistic is {phi}"
    return phi, None


def certificate_from_calibration(
    calibration: Calibration,
    identity: CameraIdentity,
    images: pa.Table,
    gcp_observations: pa.Table | None,
    date: str | None,
    run_id: str | None,
    inputs: dict[str, str],
    gcps: pa.Table | None = None,
) -> Certificate:
    """The certificate of a self-calibration: IO and sigmas, correlations, significance (formal t, why each
    dropped parameter was dropped, the held-out gain of each thermal slope tested), the thermal model over the
    block's temperature range, the conditions (date, images, strips, GCPs, priors), quality figures and the
    review. ``images`` and ``gcp_observations`` are the flight's; the calibration block is taken from them.

    The sigmas written are the calibrated ones (formal x the square root of the block's measured
    overdispersion, recorded in ``quality.overdispersion``), and a parameter is marked significant only when
    its calibrated t is: on the real seneca flight's matches the formal sigmas were several times too small
    (``benchmarks/history/engine_measurements.md``)."""
    cal = calibration.result
    sub_images = select_images(images, calibration.image_ids)
    sub_gobs = select_images(gcp_observations, calibration.image_ids) if gcp_observations is not None else None
    io_names = [n for n in cal.names if n in PARAM_NAMES]
    names = [SLOPE_NAMES.get(n, n) for n in cal.names]

    root_phi = float(np.sqrt(max(calibration.overdispersion, 1.0)))
    measured_phi = float(calibration.overdispersion) if calibration.overdispersion_measured else None

    def tested(n: str) -> dict[str, float | None]:
        h = calibration.held_out.get(n)
        if h is None or not h.measured:
            return {}
        return {"held_out_gain": h.gain, "held_out_sigma": h.sigma}

    significance: dict[str, ParameterSignificance] = {}
    for n, t in zip(cal.names, np.asarray(cal.t_values, dtype=float), strict=True):
        t = float(t) if np.isfinite(t) else 0.0
        # significant against the calibrated t: seneca's cx was significant by its formal t and not by its
        # calibrated one (benchmarks/history/engine_measurements.md)
        significance[SLOPE_NAMES.get(n, n)] = ParameterSignificance(
            t, bool(cal.significant.get(n, False)) and abs(t) / root_phi > t_critical(int(cal.dof)),
            calibrated_t=t / root_phi, **tested(n))
    for n, (why, t) in cal.dropped.items():
        significance[SLOPE_NAMES.get(n, n)] = ParameterSignificance(float(t) if np.isfinite(t) else 0.0, False, why,
                                                                     **tested(n))
    for n, why in calibration.held_at_nominal.items():
        significance[n] = ParameterSignificance(0.0, False, why, prior_sigma=calibration.held_sigmas.get(n),
                                                **tested(n))
    temps = np.array([t for t in sub_images.column("temperature_c").to_pylist() if t is not None], dtype=float)
    trange = (float(temps.min()), float(temps.max())) if temps.size else None
    thermal = None
    if isinstance(cal.thermal, LinearThermalModel) and trange is not None:
        model = dataclasses.replace(cal.thermal, valid_range=trange)
        thermal = ThermalCalibration(model, {SLOPE_NAMES.get(k, k): float(v) * root_phi
                                             for k, v in cal.thermal_sigmas.items()})
    if thermal is None:  # a slope dropped leaves no thermal model to attach it to: the review's notes say why
        significance = {n: s for n, s in significance.items() if n not in SLOPE_NAMES.values()}
    cfg = cal.config
    priors = {}
    if cfg.gnss_sigma_m is not None:
        priors["gnss_position_m"] = float(max(cfg.gnss_sigma_m))
    if cfg.attitude_sigma_deg is not None:
        priors["imu_attitude_deg"] = float(max(cfg.attitude_sigma_deg))
    gcp_ids = set(sub_gobs.column("gcp_id").to_pylist()) if sub_gobs is not None else set()
    if gcps is not None:  # only control points enter the adjustment; check points are held out
        roles = dict(zip(gcps.column("gcp_id").to_pylist(), gcps.column("role").to_pylist(), strict=True))
        gcp_ids = {g for g in gcp_ids if roles.get(g) == "control"}
    return Certificate(
        identity=identity,
        camera=cal.camera,
        sigmas={n: float(cal.sigmas[n]) * root_phi for n in io_names},
        estimated=tuple(io_names),
        correlation=Correlation(tuple(names), np.asarray(cal.correlation, dtype=float)),
        significance=significance,
        thermal=thermal,
        conditions=Conditions(
            date=date,
            temperature_range=trange,
            n_images=sub_images.num_rows,
            strips=len(set(sub_images.column("strip").to_pylist())),
            transversal_strip=calibration.transversal,
            n_gcp=len(gcp_ids) if cfg.use_gcps else 0,
            priors=priors,
            images=tuple(sub_images.column("name").to_pylist()),
        ),
        quality=Quality(float(cal.sigma0), float(cal.reprojection_rms), int(cal.dof), measured_phi),
        provenance=Provenance(flow_run=run_id, inputs=inputs),
        review=calibration.review,
    )
