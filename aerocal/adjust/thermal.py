"""Linear thermal IO model fitted to several calibrations made at different sensor temperatures.

Daakir 2019 calibrates the camera at several sensor temperatures on a well-conditioned calibration
block and fits the drift of the focal length and principal point with temperature. This is the
alternative to estimating the slopes jointly in the bundle (``AdjustConfig.thermal``), which fails on
blocks where a focal change is absorbed by the flying height (a nadir corridor).

Model, per parameter ``p`` of ("f", "cx", "cy")::

    p(T) = p0 + dp/dT (T - T0)        p0 in pixels (IO at T0), dp/dT in pixels per degC

fitted by generalised (weighted) least squares to the calibrations' values ``p_i`` at their sensor
temperatures ``T_i`` (degC) with their 3 x 3 covariances (f, cx, cy of one calibration are correlated;
different calibrations are independent). The temperatures are taken as exact (a recorded sensor
temperature is good to ~0.1 degC, negligible against the calibration sigmas). The fit's chi-square tells
whether the calibrations are consistent with a straight line: a large chi2/dof means the drift is not
linear or the calibrations' sigmas are optimistic, and :attr:`ThermalFit.consistent` is then False.

Why this module: fitting is an estimation over adjustment outputs, the sibling of the joint estimate of
the bundle, so it lives in :mod:`aerocal.adjust`; :mod:`aerocal.certificates.document` only holds and validates
records and already has the field this model goes into (:class:`~aerocal.certificates.document.ThermalCalibration`),
which :func:`thermal_certificate` fills.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from aerocal.adjust.bundle import AdjustmentResult
from aerocal.adjust.problem import AdjustmentError
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

#: IO parameters the linear model can drift (pixels), and the names of their slopes (pixels per degC).
THERMAL_IO: tuple[str, ...] = ("f", "cx", "cy")
SLOPE_NAME: dict[str, str] = {"f": "df_dt", "cx": "dcx_dt", "cy": "dcy_dt"}

#: Two-sided 95 % critical value of the normal distribution (slope sigmas are propagated, not estimated).
Z_95 = 1.959963984540054


@dataclass(frozen=True)
class CalibrationAtTemperature:
    """One calibration reduced to what the thermal fit needs.

    ``camera``: the calibrated IO at ``temperature_c`` (degC, the calibration's median sensor
    temperature); ``sigmas``: standard deviations of the estimated IO parameters (units of
    :data:`aerocal.camera.PARAM_UNITS`); ``covariance``: (3, 3) covariance of f, cx, cy in pixels^2
    (rows and columns of parameters that were not estimated are zero).
    """

    temperature_c: float
    camera: Camera
    sigmas: dict[str, float]
    covariance: np.ndarray
    n_images: int | None = None
    label: str = ""


def calibration_at_temperature(
    source: AdjustmentResult | Certificate | CalibrationAtTemperature,
    temperature_c: float | None = None,
    label: str | None = None,
) -> CalibrationAtTemperature:
    """Reduce an adjustment result or a certificate to (temperature, IO, covariance of f, cx, cy).

    The temperature, unless given: for an :class:`AdjustmentResult` its ``t0``, which is the median
    sensor temperature of the images (``AdjustConfig.thermal_t0`` left at ``None``) or the reference
    temperature of jointly estimated slopes (the camera is then IO at ``t0``); for a :class:`Certificate`
    the ``t0`` of its linear thermal model, else the middle of ``conditions.temperature_range``.
    A certificate without correlations of f, cx, cy is taken as uncorrelated. A result adjusted with
    ``thermal_correction`` holds IO at that model's t0, which the result does not record: pass it as
    ``temperature_c``.

    Raises:
        AdjustmentError: ``temperature_c`` is not given and the temperature is unknown: an :class:`AdjustmentResult`
            whose ``t0`` was set by ``AdjustConfig.thermal_t0`` without estimated slopes, or a certificate with neither
            a linear thermal model nor ``conditions.temperature_range``; ``source`` is of another type; the temperature
            is not a finite number.
    """
    if isinstance(source, CalibrationAtTemperature):
        if temperature_c is None and label is None:
            return source
        return CalibrationAtTemperature(
            source.temperature_c if temperature_c is None else float(temperature_c), source.camera,
            source.sigmas, source.covariance, source.n_images, source.label if label is None else label,
        )
    cov = np.zeros((3, 3))
    if isinstance(source, AdjustmentResult):
        if temperature_c is None:
            if source.config.thermal_t0 is not None and source.thermal is None:
                raise AdjustmentError(
                    f"calibration {label or ''}: its t0 ({source.t0} degC) was set by AdjustConfig.thermal_t0, "
                    "not measured; pass temperature_c (the calibration's median sensor temperature)"
                )
            temperature_c = source.t0
        sigmas = {n: float(source.sigmas[n]) for n in source.names if n in PARAM_NAMES}
        idx = {n: k for k, n in enumerate(source.names)}
        for a, na in enumerate(THERMAL_IO):
            for b, nb in enumerate(THERMAL_IO):
                if na in idx and nb in idx:
                    cov[a, b] = source.covariance[idx[na], idx[nb]]
        camera, n_images = source.camera, source.poses.num_rows
    elif isinstance(source, Certificate):
        if temperature_c is None:
            th = source.thermal
            if th is not None and isinstance(th.model, LinearThermalModel):
                temperature_c = th.model.t0
            elif source.conditions.temperature_range is not None:
                temperature_c = 0.5 * sum(source.conditions.temperature_range)
            else:
                raise AdjustmentError(
                    f"certificate {source.id}: no thermal model and no conditions.temperature_range, so the "
                    "temperature of its IO is unknown; pass temperature_c (degC)"
                )
        sigmas = {n: float(s) for n, s in source.sigmas.items() if n in source.estimated}
        names = source.correlation.names
        for a, na in enumerate(THERMAL_IO):
            for b, nb in enumerate(THERMAL_IO):
                if na not in sigmas or nb not in sigmas:
                    continue
                r = 1.0 if a == b else (source.correlation.value(na, nb) if na in names and nb in names else 0.0)
                cov[a, b] = r * sigmas[na] * sigmas[nb]
        camera, n_images = source.camera, source.conditions.n_images
        label = source.id if label is None else label
    else:
        raise AdjustmentError(
            f"a calibration must be an AdjustmentResult or a Certificate, got {type(source).__name__}"
        )
    t = float(temperature_c)
    if not math.isfinite(t):
        raise AdjustmentError(f"calibration {label or ''}: temperature {temperature_c!r} is not a number (degC)")
    return CalibrationAtTemperature(t, camera, sigmas, cov, n_images, label or "")


@dataclass(frozen=True)
class ThermalFit:
    """A linear thermal model fitted to N calibrations, with its precision and a consistency test.

    * ``model``: the fitted :class:`LinearThermalModel` (slopes of parameters not fitted are 0), its
      ``valid_range`` the span of the calibration temperatures (degC).
    * ``camera``: IO at ``model.t0``: f, cx, cy from the fit; the other parameters, which the model
      keeps constant, are the inverse-variance weighted means over the calibrations that estimated them
      (correlations within a calibration ignored), else the value of the calibration nearest T0 (as are
      f, cx or cy when left out of ``params``).
    * ``names`` / ``covariance``: the fitted unknowns (values at T0 of ``params``, then their slopes
      named as :data:`SLOPE_NAME`) and their covariance propagated from the calibrations' covariances
      (not scaled by the fit's chi2/dof; :meth:`scaled_sigmas` does that).
    * ``sigmas``: standard deviation per name, and per other estimated IO parameter (weighted mean).
    * ``chi2`` with ``dof`` = P (N - 2) and ``p_value`` (upper tail): consistency with a line;
      ``consistent`` is False when ``p_value`` < ``alpha``, and ``message`` then says so.
    * ``residuals``: (N, P) calibration value minus the line, pixels; ``normalised`` the same divided
      by each calibration's sigma.
    """

    model: LinearThermalModel
    camera: Camera
    params: tuple[str, ...]
    names: tuple[str, ...]
    covariance: np.ndarray
    sigmas: dict[str, float]
    estimated: tuple[str, ...]
    temperatures: tuple[float, ...]
    chi2: float
    dof: int
    p_value: float
    alpha: float
    residuals: np.ndarray
    normalised: np.ndarray
    labels: tuple[str, ...] = ()
    n_images: int | None = None
    message: str | None = field(default=None)

    @property
    def slopes(self) -> dict[str, float]:
        """The fitted slopes, pixels per degC, keyed ``df_dt``, ``dcx_dt``, ``dcy_dt``."""
        return {SLOPE_NAME[p]: float(getattr(self.model, SLOPE_NAME[p])) for p in self.params}

    @property
    def slope_sigmas(self) -> dict[str, float]:
        return {SLOPE_NAME[p]: self.sigmas[SLOPE_NAME[p]] for p in self.params}

    @property
    def chi2_dof(self) -> float:
        """chi2 / dof (NaN with two calibrations: no redundancy)."""
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    @property
    def consistent(self) -> bool:
        """Whether the calibrations agree with a straight line at level ``alpha`` (True when dof = 0)."""
        return self.dof == 0 or self.p_value >= self.alpha

    def scaled_sigmas(self) -> dict[str, float]:
        """``sigmas`` of the fitted unknowns inflated by sqrt(chi2/dof) when that exceeds 1."""
        k = math.sqrt(max(1.0, self.chi2_dof)) if self.dof > 0 else 1.0
        return {n: self.sigmas[n] * k for n in self.names}


def fit_thermal_model(
    calibrations: Sequence[AdjustmentResult | Certificate | CalibrationAtTemperature],
    params: Sequence[str] = THERMAL_IO,
    t0: float | None = None,
    temperatures: Sequence[float | None] | None = None,
    alpha: float = 0.01,
) -> ThermalFit:
    """Fit ``p(T) = p0 + dp/dT (T - T0)`` for ``params`` (subset of f, cx, cy) to N >= 2 calibrations.

    ``calibrations``: adjustment results or certificates (see :func:`calibration_at_temperature` for the
    temperature each stands at; ``temperatures`` overrides it per calibration, ``None`` entries keep it).
    ``t0``: reference temperature (degC) of the model and of ``ThermalFit.camera``; default the mean of
    the calibration temperatures, where the values at T0 and the slopes are uncorrelated for equal
    sigmas. ``alpha``: level of the chi-square consistency test.
    Every calibration must have estimated every parameter of ``params``.

    Raises:
        AdjustmentError: ``params`` is empty or not a subset of f, cx, cy; ``temperatures`` has not one value per
            calibration; fewer than 2 calibrations, or all at the same temperature; a calibration did not estimate a
            parameter of ``params``, or its covariance of them is not positive definite; a calibration's temperature is
            unknown (see :func:`calibration_at_temperature`). The message names the calibration.
    """
    params = tuple(params)
    bad = [p for p in params if p not in THERMAL_IO]
    if bad or not params:
        raise AdjustmentError(f"thermal fit params {list(params)}: choose one or more of {THERMAL_IO}")
    if temperatures is not None and len(temperatures) != len(calibrations):
        raise AdjustmentError(
            f"temperatures has {len(temperatures)} values for {len(calibrations)} calibrations; give one each"
        )
    cals = [
        calibration_at_temperature(c, None if temperatures is None else temperatures[k], label=None)
        for k, c in enumerate(calibrations)
    ]
    cals = [c if c.label else CalibrationAtTemperature(c.temperature_c, c.camera, c.sigmas, c.covariance,
                                                       c.n_images, f"#{k + 1}") for k, c in enumerate(cals)]
    N, P = len(cals), len(params)
    if N < 2:
        raise AdjustmentError(f"a thermal model needs calibrations at >= 2 temperatures, got {N}")
    T = np.array([c.temperature_c for c in cals])
    if np.ptp(T) <= 0.0:
        raise AdjustmentError(
            f"all {N} calibrations are at {T[0]:.2f} degC: a slope needs calibrations at different temperatures"
        )
    sel = [THERMAL_IO.index(p) for p in params]
    for c in cals:
        missing = [p for p in params if not c.sigmas.get(p, 0.0) > 0.0]
        if missing:
            raise AdjustmentError(
                f"calibration {c.label} ({c.temperature_c:.2f} degC) did not estimate {missing}; "
                "calibrate with them free, or fit fewer params"
            )
    t0 = float(np.mean(T)) if t0 is None else float(t0)

    # generalised least squares: unknowns x = [p0 (P), dp/dT (P)]; calibration i: v_i = A_i x + e_i
    Nmat = np.zeros((2 * P, 2 * P))
    rhs = np.zeros(2 * P)
    weights, values = [], []
    for c, t in zip(cals, T, strict=True):
        C = c.covariance[np.ix_(sel, sel)]
        try:
            W = np.linalg.inv(C)
            np.linalg.cholesky(W)
        except np.linalg.LinAlgError:
            raise AdjustmentError(
                f"calibration {c.label}: the covariance of {list(params)} is not positive definite"
            ) from None
        A = np.hstack([np.eye(P), (t - t0) * np.eye(P)])
        v = np.array([getattr(c.camera, p) for p in params])
        Nmat += A.T @ W @ A
        rhs += A.T @ W @ v
        weights.append(W)
        values.append(v)
    cov = np.linalg.inv(Nmat)
    x = cov @ rhs
    res = np.array([v - (x[:P] + (t - t0) * x[P:]) for v, t in zip(values, T, strict=True)])
    chi2 = float(sum(r @ W @ r for r, W in zip(res, weights, strict=True)))
    dof = P * (N - 2)
    p_value = float(stats.chi2.sf(chi2, dof)) if dof > 0 else 1.0
    sig = np.sqrt(np.diag(cov))
    names = params + tuple(SLOPE_NAME[p] for p in params)
    sigmas = dict(zip(names, sig.tolist(), strict=True))
    normalised = res / np.array([[math.sqrt(c.covariance[k, k]) for k in sel] for c in cals])

    # the parameters the model holds constant: weighted mean over the calibrations that estimated them
    near = cals[int(np.argmin(np.abs(T - t0)))]
    other: dict[str, float] = {}
    for n in PARAM_NAMES:
        if n in THERMAL_IO:
            continue
        est = [(getattr(c.camera, n), c.sigmas[n]) for c in cals if c.sigmas.get(n, 0.0) > 0.0]
        if est:
            w = np.array([1.0 / s**2 for _, s in est])
            other[n] = float(np.sum(w * np.array([v for v, _ in est])) / np.sum(w))
            sigmas[n] = float(1.0 / math.sqrt(np.sum(w)))
    for p in THERMAL_IO:  # f, cx or cy left out of the fit: value and sigma of the nearest calibration
        if p not in params and near.sigmas.get(p, 0.0) > 0.0:
            sigmas[p] = near.sigmas[p]
    fitted = {p: float(x[k]) for k, p in enumerate(params)}
    camera = near.camera.with_params({**other, **fitted})
    estimated = tuple(n for n in PARAM_NAMES if n in sigmas)
    model = LinearThermalModel(
        t0=t0,
        valid_range=(float(T.min()), float(T.max())),
        **{SLOPE_NAME[p]: float(x[P + k]) for k, p in enumerate(params)},
    )
    message = None
    if dof > 0 and p_value < alpha:
        message = (
            f"the {N} calibrations are not consistent with a linear drift: chi2/dof = {chi2 / dof:.2f} "
            f"(chi2 {chi2:.1f}, dof {dof}, p = {p_value:.2g} < {alpha}); the drift is not linear in T or "
            "the calibrations' sigmas are optimistic (scaled_sigmas() inflates the slope sigmas)"
        )
    elif dof == 0:
        message = "two calibrations: the line passes through both, its consistency cannot be tested"
    n_img = [c.n_images for c in cals]
    return ThermalFit(
        model=model,
        camera=camera,
        params=params,
        names=names,
        covariance=cov,
        sigmas=sigmas,
        estimated=estimated,
        temperatures=tuple(float(t) for t in T),
        chi2=chi2,
        dof=dof,
        p_value=p_value,
        alpha=alpha,
        residuals=res,
        normalised=normalised,
        labels=tuple(c.label for c in cals),
        n_images=None if any(n is None for n in n_img) else int(sum(n_img)),
        message=message,
    )


def thermal_certificate(
    fit: ThermalFit,
    identity: CameraIdentity,
    date: str | None = None,
    provenance: Provenance | None = None,
) -> Certificate:
    """A certificate carrying the fitted model in its thermal field (valid over the calibration span).

    The camera is :attr:`ThermalFit.camera` (IO at the model's T0) with the fit's sigmas; the
    correlation matrix covers the fitted values at T0 and the slopes; the significance of each slope is
    t = |slope| / sigma against the normal 95 % value. ``quality`` holds the line fit's a-posteriori
    sigma0 = sqrt(chi2/dof) and its dof (no reprojection figure: no images were adjusted here);
    ``conditions.temperature_range`` is the span of the calibration temperatures and ``n_images`` the
    calibrations' images together.
    """
    slopes = tuple(SLOPE_NAME[p] for p in fit.params)
    significance = {
        s: ParameterSignificance(
            t=abs(getattr(fit.model, s)) / fit.sigmas[s],
            significant=bool(abs(getattr(fit.model, s)) / fit.sigmas[s] > Z_95),
        )
        for s in slopes
    }
    sd = np.sqrt(np.diag(fit.covariance))
    corr = fit.covariance / np.outer(sd, sd)
    sigma0 = math.sqrt(fit.chi2_dof) if fit.dof > 0 and fit.chi2 > 0 else None
    return Certificate(
        identity=identity,
        camera=fit.camera,
        sigmas={n: fit.sigmas[n] for n in fit.estimated},
        estimated=fit.estimated,
        correlation=Correlation(fit.names, corr),
        significance=significance,
        thermal=ThermalCalibration(fit.model, {s: fit.sigmas[s] for s in slopes}),
        conditions=Conditions(date=date, temperature_range=fit.model.valid_range, n_images=fit.n_images),
        quality=Quality(sigma0=sigma0, dof=fit.dof),
        provenance=provenance or Provenance(),
    )


__all__ = [
    "SLOPE_NAME",
    "THERMAL_IO",
    "CalibrationAtTemperature",
    "ThermalFit",
    "calibration_at_temperature",
    "fit_thermal_model",
    "thermal_certificate",
]
