"""The decision rule: never a confident wrong answer.

Every choice that shapes a result (freeing an IO parameter, keeping a thermal slope, storing or reusing a
certificate, naming an effect) asks three questions, and where the answer is no or unknown the simpler
model is kept and the reason said:

1. **Is it determined on this block?** Before the self-calibration, the precision of f, cx and cy is
   predicted from the block's geometry (:func:`aerocal.calibrate.subset.predict_io_sigmas`: recorded poses, a tie
   grid on the terrain plane, the GNSS and GCP weights). A parameter whose predicted sigma is large
   against the prior knowledge of it (the nominal camera) stays at the nominal value: a flat nadir block
   without GCPs cannot tell f from the flying height, and freeing it there gives f 2x off with a sigma
   that looks fine (a real 40 m thermal survey: 1560 +- 42 px against a nominal 765 px; the geometry had
   predicted a sigma of 191 px). The prediction models the block as a tie grid on a plane and can be wrong the
   other way: a principal point it holds is tested as 3 asks, and freed when it predicts held-out images better
   (real h20t_forest: 18 px off the frame's centre; held there, it bent the block 8 % too deep by the camera's
   laser range finder).
2. **Is it plausible against its prior?** The estimate is compared with the nominal camera (EXIF focal
   length over the pixel pitch, principal point at the centre): f within ``focal_band``, the principal
   point within ``principal_point_band`` of the image size, the distortion at the image corners below
   ``max_corner_distortion`` of their radius, thermal slopes below ``max_thermal_slope`` (relative to f per
   degC: ten times a non-athermalised germanium singlet's 5 um/degC on 39 mm).
3. **Does it predict data the fit did not use?** A thermal slope is kept only when a k-fold over strips
   (:mod:`aerocal.calibrate.heldout`) shows a held-out gain beyond ``held_out_sigmas`` standard errors; check points
   the calibration block sees must agree with their predicted accuracy (rho below ``max_check_rho``).

:func:`review_calibration` applies 2 and 3 to a finished self-calibration and returns a :class:`Review`:
"accepted", or "rejected" with every reason. A rejected certificate is stored so that the failure is on
record, but it is never selected for a flight.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from aerocal.camera import Camera

#: review statuses of a certificate
ACCEPTED, REJECTED = "accepted", "rejected"
STATUSES = (ACCEPTED, REJECTED)


@dataclass(frozen=True)
class DecisionConfig:
    """Thresholds of the decision rule (all relative, so they hold for any camera).

    * ``determined_focal`` (0.005): f is freed only when its predicted sigma is at most this fraction of f
      (0.5 %: 6 px on a 1231 px compact, 3.8 px on a 765 px thermal core); nominal focal lengths from EXIF
      are good to a few per cent, so a calibration less precise than that adds nothing but risk.
    * ``determined_principal_point`` (0.005): the same for cx and cy, as a fraction of the larger image side.
    * ``focal_band`` (0.15): a calibrated f must lie within 15 % of the nominal.
    * ``principal_point_band`` (0.10): cx, cy within 10 % of the width (height) of the nominal's.
    * ``max_corner_distortion`` (0.15): lens distortion at the image corners at most 15 % of their radius.
    * ``max_thermal_slope`` (2e-3): |df/dT|, |dcx/dT|, |dcy/dT| at most 0.2 % of f per degC.
    * ``certified_focal_sigma`` (0.01): a certificate's own sigma of f at most 1 % of f.
    * ``max_sigma0`` (3.0): the calibration's a-posteriori sigma0 (GNSS and GCP misfit shows here once the
      tie sigma has been estimated).
    * ``max_check_rho`` (3.0) with at least ``min_check_points`` (3) check points in the calibration block:
      their error against their predicted accuracy, per axis.
    * ``held_out_sigmas`` (2.0): a thermal slope needs a held-out gain beyond this many standard errors.
    * ``min_freeing_gain`` (0.01): a principal point the geometry's prediction held is freed only when its held-out
      gain is also at least this fraction of the held-out images' misfit. On simulated blocks with the lens at the
      frame's centre the gains scatter about twice as widely as their standard errors (within +-0.06 %), and 2 of
      8 passed 2 standard errors; a lens 3 % of the side off the centre gives 6-9 %, the real H20T 4.6 %
      (``benchmarks/RESULTS.md``, "Principal point freed on held-out frames").
    * ``max_depth_disagreement`` (0.03): where the camera's laser range finder measured ranges no fit used, the
      calibration block's tie points around each axis must lie at the laser's range within this fraction of it
      (plus twice the median's standard error), on at least ``min_check_points`` frames. 3 %: the tie points
      used lie up to 3 % of the range off the axis (:data:`aerocal.adjust.laser.MAX_OFFSET_FRACTION`), where a
      canopy's or roof's height differs from the laser's spot. A radial distortion traded against a bend of the
      block (the dome) fits the images and fails here.
    * ``nominal_focal_tolerance`` (0.01), ``nominal_principal_point_tolerance`` (0.01): the standard deviation
      of a nominal f (fraction of f) and of a nominal principal point (fraction of the image side) when the
      block cannot determine them and they are held. Both are assumptions, not measurements: a nominal
      focal length taken as good to about 1 % (the simulated XT2's true f is set 0.4 % off its
      13 mm / 17 um), the principal point as within 1 % of the image side of the frame centre.
      The certificate records them and the diagnosis carries them, so that the nominal's error is not
      named as an effect (the XT2 survey named a 2.7 px per-strip cx with f held 3 px off).
    * ``nominal_corner_distortion`` (0.02): a nominal camera has no distortion; the block that uses one as it
      is (no certificate, or its calibration rejected) carries an unknown radial distortion of this size at
      the corners (an assumption). Without it the real H20T flight's diagnosis named ``radial_k3 = -6.1``
      on the nominal camera: its lens's own distortion, not an effect.
    """

    determined_focal: float = 0.005
    determined_principal_point: float = 0.005
    focal_band: float = 0.15
    principal_point_band: float = 0.10
    max_corner_distortion: float = 0.15
    max_thermal_slope: float = 2e-3
    certified_focal_sigma: float = 0.01
    max_sigma0: float = 3.0
    max_check_rho: float = 3.0
    min_check_points: int = 3
    held_out_sigmas: float = 2.0
    min_freeing_gain: float = 0.01
    max_depth_disagreement: float = 0.03
    nominal_focal_tolerance: float = 0.01
    nominal_principal_point_tolerance: float = 0.01
    nominal_corner_distortion: float = 0.02

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "min_check_points":
                if value < 0:
                    raise ValueError(f"DecisionConfig.min_check_points must be 0 or more, got {value}")
            elif not (value > 0 and math.isfinite(value)):
                raise ValueError(f"DecisionConfig.{f.name} must be a positive finite number, got {value}")


@dataclass(frozen=True)
class Review:
    """The verdict on a calibration: ``status`` (accepted / rejected), the ``problems`` that rejected it, the
    ``checks`` it passed and the ``notes`` on decisions taken on the way (a parameter held at its nominal
    value, a slope dropped for want of a held-out gain), each one sentence with its numbers."""

    status: str = ACCEPTED
    problems: tuple[str, ...] = ()
    checks: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise ValueError(f"review status {self.status!r} unknown; valid: {', '.join(STATUSES)}")
        for name in ("problems", "checks", "notes"):
            object.__setattr__(self, name, tuple(str(x) for x in getattr(self, name)))
        if self.problems and self.status == ACCEPTED:
            raise ValueError("an accepted review lists problems; a problem rejects the calibration")

    @classmethod
    def of(cls, problems=(), checks=(), notes=()) -> Review:
        """Rejected when there is any problem, else accepted."""
        return cls(REJECTED if problems else ACCEPTED, tuple(problems), tuple(checks), tuple(notes))

    def merged(self, problems=(), checks=(), notes=()) -> Review:
        """This review with more problems, checks and notes."""
        return Review.of(self.problems + tuple(problems), self.checks + tuple(checks), self.notes + tuple(notes))

    @property
    def accepted(self) -> bool:
        return self.status == ACCEPTED

    def summary(self) -> str:
        if self.accepted:
            return "accepted"
        return "rejected: " + "; ".join(self.problems)

    def to_dict(self) -> dict:
        return {"status": self.status, "problems": list(self.problems), "checks": list(self.checks),
                "notes": list(self.notes)}


def undetermined_io(predicted: dict[str, float], camera: Camera, config: DecisionConfig | None = None,
                    what: str = "predicted sigma") -> dict[str, str]:
    """IO parameters the block cannot determine, each with the reason: f, cx, cy by their predicted sigma,
    and p1, p2 with an undetermined principal point (decentring distortion takes its error).

    ``predicted``: standard deviations (pixels) of the self-calibration's parameters on the block: predicted
    from its geometry alone before the fit (:func:`aerocal.calibrate.subset.predict_io_sigmas`), or the fit's own
    calibrated by the block's overdispersion after it (``what`` names which, for the reason).
    """
    config = config or DecisionConfig()
    out = {}
    f_lim = config.determined_focal * camera.f
    s = predicted.get("f")
    if s is not None and not (np.isfinite(s) and s <= f_lim):
        out["f"] = (f"f not determined by this block: {what} {s:.3g} px > {f_lim:.3g} px "
                    f"({100 * config.determined_focal:g} % of the nominal {camera.f:.1f} px); the nominal f is kept")
    p_lim = config.determined_principal_point * max(camera.width, camera.height)
    for name in ("cx", "cy"):
        s = predicted.get(name)
        if s is not None and not (np.isfinite(s) and s <= p_lim):
            out[name] = (f"{name} not determined by this block: {what} {s:.3g} px > {p_lim:.3g} px "
                         f"({100 * config.determined_principal_point:g} % of the image size); the nominal "
                         f"{name} is kept")
    if "cx" in out or "cy" in out:
        # decentring distortion moves the image like a principal-point offset: freed beside a principal point
        # held at a wrong nominal, it takes the offset (the rendered XT2 survey: cx held 3.1 px off, p1 -1.4e-3
        # "significant" at t 57 on a lens without decentring)
        for name in ("p1", "p2"):
            out[name] = (f"{name} held at 0: the principal point is not determined by this block, and decentring "
                         "distortion is not separable from its error")
    return out


def nominal_sigma(name: str, camera: Camera, config: DecisionConfig | None = None) -> float:
    """Standard deviation of a nominal IO value of ``camera`` held as it is: ``f``, ``cx``, ``cy`` in pixels;
    ``k1``, ``k2`` (a nominal camera has no distortion: its lens's unknown radial distortion, sized so that
    either term alone moves the image corners by ``nominal_corner_distortion`` of their radius).

    Raises:
        ValueError: ``name`` is not one of f, cx, cy, k1, k2.
    """
    config = config or DecisionConfig()
    if name == "f":
        return config.nominal_focal_tolerance * camera.f
    if name in ("cx", "cy"):
        side = camera.width if name == "cx" else camera.height
        return config.nominal_principal_point_tolerance * side
    if name in ("k1", "k2"):
        r2 = (camera.width / 2.0) ** 2 + (camera.height / 2.0) ** 2
        r2 /= camera.f**2  # squared corner radius in normalised image coordinates
        return config.nominal_corner_distortion / (r2 if name == "k1" else r2**2)
    raise ValueError(f"nominal_sigma: no tolerance for {name!r}; give f, cx, cy, k1 or k2")


#: the nominal IO values a camera taken as it is (no calibration) is uncertain in
NOMINAL_PARAMETERS = ("f", "cx", "cy", "k1", "k2")


def corner_distortion(camera: Camera) -> float:
    """Largest lens-distortion displacement at the four image corners over their distance from the
    principal point (dimensionless: 0.05 = the corner moves by 5 % of its radius)."""
    corners = camera.corners()
    xy = (corners - np.array([camera.cx, camera.cy])) / camera.f
    radius = np.linalg.norm(xy, axis=1)
    moved = np.linalg.norm(camera.distort(xy) - xy, axis=1)
    ok = radius > 0
    return float(np.max(moved[ok] / radius[ok])) if ok.any() else 0.0


def review_camera(camera: Camera, nominal: Camera, sigmas: dict[str, float] | None = None,
                  slopes: dict[str, float] | None = None, config: DecisionConfig | None = None) -> Review:
    """Plausibility of a calibrated ``camera`` against the ``nominal`` one (question 2 of the rule).

    ``sigmas``: standard deviations (pixels) of the estimated parameters; ``slopes``: thermal slopes in
    pixels per degC keyed ``df_dt``/``dcx_dt``/``dcy_dt`` (or ``df/dT``...).
    """
    config = config or DecisionConfig()
    problems: list[str] = []
    checks: list[str] = []
    if not np.all(np.isfinite(camera.params())):
        return Review.of(["the camera holds non-finite parameters"])
    if (camera.width, camera.height) != (nominal.width, nominal.height):
        return Review.of([f"the camera is {camera.width}x{camera.height} px, the images {nominal.width}x"
                      f"{nominal.height} px"])
    rel = camera.f / nominal.f - 1.0
    if abs(rel) > config.focal_band:
        problems.append(f"f {camera.f:.1f} px is {100 * rel:+.1f} % off the nominal {nominal.f:.1f} px (the band is "
                      f"+-{100 * config.focal_band:g} %): not a focal length this camera can have")
    else:
        checks.append(f"f {camera.f:.1f} px within {100 * config.focal_band:g} % of the nominal "
                             f"{nominal.f:.1f} px ({100 * rel:+.2f} %)")
    for name, size in (("cx", camera.width), ("cy", camera.height)):
        off = getattr(camera, name) - getattr(nominal, name)
        if abs(off) > config.principal_point_band * size:
            problems.append(f"{name} {getattr(camera, name):.1f} px is {off:+.1f} px off the nominal (more than "
                          f"{100 * config.principal_point_band:g} % of the image)")
    dist = corner_distortion(camera)
    if dist > config.max_corner_distortion:
        problems.append(f"lens distortion moves the image corners by {100 * dist:.1f} % of their radius (more than "
                      f"{100 * config.max_corner_distortion:g} %): the distortion terms ran away")
    sf = (sigmas or {}).get("f")
    if sf is not None and sf > config.certified_focal_sigma * camera.f:
        problems.append(f"sigma of f {sf:.3g} px is more than {100 * config.certified_focal_sigma:g} % of f: "
                      "the block did not determine it")
    for key, value in (slopes or {}).items():
        if value is not None and abs(value) > config.max_thermal_slope * nominal.f:
            problems.append(f"thermal slope {key} = {value:+.3g} px/degC exceeds {config.max_thermal_slope:g} x f "
                          f"= {config.max_thermal_slope * nominal.f:.3g} px/degC: no lens drifts that fast")
    return Review.of(problems, checks)


def review_calibration(result, nominal: Camera, config: DecisionConfig | None = None,
                       calibration: float = 1.0) -> Review:
    """The verdict on a self-calibration (an :class:`aerocal.adjust.AdjustmentResult`): plausibility of its
    camera and thermal slopes against ``nominal``, convergence, sigma0 and the check points it saw (data the
    fit did not use). ``calibration`` (>= 1) scales the formal sigmas to what the block supports (the square
    root of its measured overdispersion)."""
    config = config or DecisionConfig()
    sig = {n: float(s) * calibration for n, s in result.sigmas.items()}
    first = review_camera(result.camera, nominal, sig, dict(result.thermal_slopes), config)
    problems, checks = list(first.problems), list(first.checks)
    if not result.converged:
        problems.append(f"the self-calibration did not converge in {result.iterations} iterations")
    if not (np.isfinite(result.sigma0) and result.sigma0 <= config.max_sigma0):
        problems.append(f"sigma0 {result.sigma0:.3g} is above {config.max_sigma0:g}: the observations disagree "
                      "with their weights (GNSS, GCPs or tie points)")
    else:
        checks.append(f"sigma0 {result.sigma0:.3f}")
    n_chk = len(result.check_ids)
    rho = np.asarray(result.rho, dtype=float)
    if n_chk >= config.min_check_points and rho.size == 3 and np.isfinite(rho).all():
        if np.any(rho > config.max_check_rho):
            problems.append(f"{n_chk} check points miss their predicted accuracy: rho E/N/Up "
                          f"{rho[0]:.2f} / {rho[1]:.2f} / {rho[2]:.2f} (limit {config.max_check_rho:g})")
        else:
            checks.append(f"{n_chk} check points within their predicted accuracy: rho E/N/Up "
                                 f"{rho[0]:.2f} / {rho[1]:.2f} / {rho[2]:.2f}")
    return Review.of(problems, checks)


def review_laser_depth(n: int, median_m: float, median_error_m: float, range_m: float,
                       config: DecisionConfig | None = None) -> Review:
    """The calibration block's depth against the laser ranges no fit used (data the fit did not use, as check
    points are): ``n`` frames, the median of the block's range minus the laser's (metres) with its standard error,
    and the median laser range (metres). Rejected when the median lies beyond ``max_depth_disagreement`` of the
    range plus twice its standard error; fewer than ``min_check_points`` frames decide nothing (a note)."""
    config = config or DecisionConfig()
    figures = (f"median {median_m:+.2f} +- {median_error_m:.2f} m over {n} frames whose range no fit used, "
               f"ranges about {range_m:.0f} m")
    if n < max(config.min_check_points, 1):
        return Review.of(notes=[f"the laser ranges no fit used were not compared: {n} frames see tie points on "
                                f"their axis (at least {config.min_check_points} are needed)"])
    limit = config.max_depth_disagreement * range_m + 2.0 * median_error_m
    if abs(median_m) > limit:
        side = "farther from" if median_m > 0 else "nearer to"
        return Review.of(problems=[
            f"the calibration block's depth disagrees with the camera's laser range finder: its tie points lie "
            f"{abs(median_m):.1f} m ({100 * abs(median_m) / range_m:.0f} % of the range) {side} the cameras than "
            f"the laser measured ({figures}; limit {limit:.1f} m): the distortion found bends the block (a dome) "
            "or its scale is wrong, and the certificate would carry it to other flights"])
    return Review.of(checks=[f"depth agrees with the laser range finder ({figures}; limit {limit:.1f} m)"])


def nominal_parameters(camera: Camera, nominal: Camera, names) -> Camera:
    """``camera`` with the parameters ``names`` set back to the ``nominal`` camera's values."""
    return dataclasses.replace(camera, **{n: getattr(nominal, n) for n in names})
