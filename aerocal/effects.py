"""The catalogue of systematic effects: names, units, parameters, and how each displaces image points.

The simulator applies these effects (:mod:`aerocal.simulate`); the diagnosis tests for them. The
diagnosis imports this module, never the simulator. Every formula that moves an image point lives here
once, so that the two cannot disagree.

Magnitudes are given on the command line as ``NAME=VALUE`` with VALUE a number, a comma-separated
vector, or ``on``/``off`` for switches (see :func:`parse_effect`).

Frames and signs
----------------
* ``boresight`` angles (degrees) are a rotation about the *camera* axes x, y, z (x right, y down,
  z forward): ``R_cw_true = Rot(boresight) @ R_cw_recorded``. A positive angle about x moves image
  points up (towards smaller v) by about ``f * angle`` pixels.
* ``lever_arm`` (metres) is the GNSS antenna position in the *camera* frame: ``antenna = C + R_cw^T
  lever``. Its component along the optical axis is constant in the world for a nadir block and cannot
  be told from a vertical ``gnss_bias``.
* ``gnss_bias`` (metres east, north, up) is a constant offset of all recorded positions (e.g. a height
  read against the wrong reference).
* ``gnss_time_offset`` (seconds): the recorded position is the true position ``dt`` seconds later,
  ``C_recorded = C(t + dt)``, i.e. shifted by ``v dt`` along the track.
* ``rolling_shutter`` (seconds of readout): row ``v`` is exposed at ``t + readout (v / height - 0.5)``,
  so the middle row is exposed at the recorded time.
* ``thermal_rotation`` (pixels per degC at the image corner): the image rotates about the principal point
  by ``theta = rate (T - T_ref) / r_corner`` radians (``r_corner`` the distance in pixels from the principal
  point to the farthest image corner, :attr:`aerocal.camera.Camera.corner_radius`), positive
  from the image x axis (right) towards y (down); Daakir 2019's Eq. 2 rotation term. A rotation about the
  principal point is a rotation of the camera about its optical axis: with free attitudes a block absorbs
  it in each image's kappa, and only attitude observations can tell it apart.
* ``refraction`` (on/off): standard-atmosphere radial refraction, displacement outwards
  ``dr = K (r + r^3 / f^2)`` (pixels, r from the principal point) with ``K`` from Bertram's formula.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Effect:
    """One systematic effect of the catalogue."""

    name: str
    units: str
    labels: tuple[str, ...]  # one per value
    kind: str  # "interior" | "exterior" | "atmosphere"
    depends_on: tuple[str, ...]  # metadata the effect varies with
    description: str
    switch: bool = False  # True: the value is on/off (1.0 / 0.0)
    # the largest magnitude a real instrument can have, per value, in ``units`` once scaled to the camera
    # (``scale``: "focal" = times the focal length in pixels; "corner" = times the corner's distance from the
    # principal point in pixels; "corner_r6" = divided by r^6 at the image corner, normalised coordinates, i.e.
    # the r^6 term moves the corner by that fraction of its radius): an
    # estimate beyond it is a symptom of another cause, not this effect
    plausible: float = math.inf
    scale: str = ""
    # True where only non-negative values are physical (a readout time): a negative estimate is a symptom of
    # another cause sharing the signature, never this effect
    nonnegative: bool = False

    @property
    def size(self) -> int:
        return len(self.labels)


#: Plausible sizes (``Effect.plausible``), the largest a real survey instrument shows:
#: * thermal focal / principal-point drift 0.2 % of f per degC: ten times a non-athermalised germanium
#:   singlet's 5 um/degC on 39 mm (NOTES: 0.013 %/degC), twenty times a compact's;
#: * thermal image rotation 2e-4 rad per degC (at the corner: times its distance from the principal point),
#:   about 30 times the < 0.02 px/degC Daakir 2019 measured at the corner of a ~3,000 px half-diagonal;
#: * rolling-shutter readout 0.1 s (CMOS frames read in 10-80 ms); boresight 3 deg (a mounting tilt);
#: * lever arm 2 m (antenna to camera on drones and survey aircraft); GNSS time offset 2 s;
#: * GNSS bias 100 m (a height read against the ellipsoid instead of the geoid is at most ~100 m off);
#: * affinity/skew 0.5 % of f; a k3 term that moves the image corners by 5 % of their radius (k3 in
#:   normalised coordinates is large for a narrow lens: 8 moves a 640x480 corner at f 1668 px by 0.6 px).
CATALOGUE: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect("thermal_focal", "px/degC", ("df_dT",), "interior", ("temperature",),
               "focal length changes linearly with sensor temperature",
               plausible=2e-3, scale="focal"),
        Effect("thermal_principal_point", "px/degC", ("dcx_dT", "dcy_dT"), "interior", ("temperature",),
               "principal point moves linearly with sensor temperature",
               plausible=2e-3, scale="focal"),
        Effect("thermal_rotation", "px/degC", ("dtheta_dT",), "interior", ("temperature",),
               "the image rotates about the principal point linearly with sensor temperature (px at the "
               "image corner)", plausible=2e-4, scale="corner"),
        Effect("rolling_shutter", "s", ("readout",), "interior", ("image row", "velocity"),
               "rows are read out one after the other while the camera moves", plausible=0.1, nonnegative=True),
        Effect("boresight", "deg", ("about_x", "about_y", "about_z"), "exterior", ("attitude",),
               "misalignment between the IMU and the camera axes", plausible=3.0),
        Effect("lever_arm", "m", ("x", "y", "z"), "exterior", ("attitude", "flight direction"),
               "unmodelled offset between the GNSS antenna and the projection centre (camera frame)",
               plausible=2.0),
        Effect("gnss_bias", "m", ("east", "north", "up"), "exterior", (),
               "constant offset of the recorded positions (datum or height reference)", plausible=100.0),
        Effect("gnss_time_offset", "s", ("dt",), "exterior", ("velocity", "flight direction"),
               "clock offset between camera and GNSS: positions shifted along the track", plausible=2.0),
        Effect("affinity_skew", "px", ("b1", "b2"), "interior", ("image position",),
               "affinity (different x and y scale) and skew of the pixel grid", plausible=5e-3, scale="focal"),
        Effect("radial_k3", "1", ("k3",), "interior", ("radius",),
               "unmodelled third radial distortion term (r^6)", plausible=0.05,
               scale="corner_r6"),
        Effect("refraction", "on/off", ("on",), "atmosphere", ("radius", "flying height"),
               "standard-atmosphere refraction: radial displacement outwards", switch=True, plausible=1.0),
    )
}


class EffectError(ValueError):
    """An effect given by the user is unknown or malformed; the message lists the valid choices."""


def plausible_size(name: str, f_px: float, corner_radius_px: float | None = None) -> float:
    """The largest plausible magnitude of each value of effect ``name`` for a camera of focal length ``f_px``
    pixels whose image corners lie ``corner_radius_px`` from the principal point (needed for ``radial_k3`` and
    ``thermal_rotation``),
    in the effect's units (``math.inf`` when the catalogue sets no bound)."""
    e = CATALOGUE[name]
    if e.scale == "focal":
        return e.plausible * f_px
    if e.scale == "corner":
        return e.plausible * corner_radius_px if corner_radius_px else math.inf
    if e.scale == "corner_r6":
        if not corner_radius_px:
            return math.inf
        return e.plausible / (corner_radius_px / f_px) ** 6
    return e.plausible


def parse_effect(text: str) -> tuple[str, tuple[float, ...]]:
    """Parse ``NAME=VALUE`` (``VALUE`` a number, comma-separated numbers, or on/off for switches).

    Raises:
        EffectError: ``text`` has no ``=``, names an unknown effect, or gives a value the effect does not take (see
            :func:`effect_values`).
    """
    if "=" not in text:
        raise EffectError(f"effect {text!r} must be NAME=VALUE; valid names: {', '.join(CATALOGUE)}")
    name, _, raw = text.partition("=")
    name = name.strip()
    return name, effect_values(name, raw.strip())


def effect_values(name: str, raw: object) -> tuple[float, ...]:
    """Validate a magnitude for effect ``name`` (string, number or sequence) and return its values.

    Raises:
        EffectError: ``name`` is not in :data:`CATALOGUE`; a switch given other than on/off (or 0/1); a value that is
            not numbers, or not the effect's count of finite numbers. The message names the valid values.
    """
    if name not in CATALOGUE:
        raise EffectError(f"unknown effect {name!r}; valid effects: {', '.join(CATALOGUE)}")
    effect = CATALOGUE[name]
    if effect.switch:
        if isinstance(raw, str):
            low = raw.lower()
            if low in ("on", "true", "1", "yes"):
                return (1.0,)
            if low in ("off", "false", "0", "no"):
                return (0.0,)
        elif isinstance(raw, bool | int | float) and raw in (0, 1):
            return (float(raw),)
        raise EffectError(f"effect {name} is a switch: give {name}=on or {name}=off, not {raw!r}")
    if isinstance(raw, str):
        parts = [p for p in raw.replace(" ", "").split(",") if p != ""]
    elif isinstance(raw, int | float):
        parts = [raw]
    else:
        parts = list(raw)  # type: ignore[call-overload]
    try:
        values = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        raise EffectError(
            f"effect {name} takes {effect.size} number(s) in {effect.units} "
            f"({', '.join(effect.labels)}), got {raw!r}"
        ) from None
    if len(values) != effect.size or not all(math.isfinite(v) for v in values):
        raise EffectError(
            f"effect {name} takes {effect.size} finite number(s) in {effect.units} "
            f"({', '.join(effect.labels)}), got {raw!r}"
        )
    return values


def normalise_effects(effects: dict[str, object] | None) -> dict[str, tuple[float, ...]]:
    """Validate a ``{name: magnitude}`` mapping; returns values as float tuples."""
    return {name: effect_values(name, value) for name, value in (effects or {}).items()}


# ------------------------------------------------------------------------------ refraction
def bertram_refraction_k(flying_height_m: float, ground_height_m: float = 0.0) -> float:
    """Refraction constant K (radians per unit tan) of the standard atmosphere (Bertram 1969).

    ``K = (2410 H / (H^2 - 6 H + 250) - 2410 h^2 / ((h^2 - 6 h + 250) H)) 1e-6`` with H the flying
    height and h the ground height above sea level in kilometres.
    """
    H = flying_height_m / 1000.0
    h = ground_height_m / 1000.0
    if H <= 0:
        return 0.0
    return (2410.0 * H / (H * H - 6.0 * H + 250.0) - 2410.0 * h * h / ((h * h - 6.0 * h + 250.0) * H)) * 1e-6


def refract(xy: np.ndarray, k: float) -> np.ndarray:
    """Apply radial refraction to undistorted normalised coordinates: ``r' = r (1 + K (1 + r^2))``.

    In pixels this is ``dr = K (r + r^3 / f^2)`` (Kraus, Photogrammetry Vol. 1).
    """
    xy = np.asarray(xy, dtype=float)
    r2 = np.sum(xy * xy, axis=-1, keepdims=True)
    return xy * (1.0 + k * (1.0 + r2))


def unrefract(xy: np.ndarray, k: float, iterations: int = 6) -> np.ndarray:
    """Inverse of :func:`refract` by fixed-point iteration (K ~ 1e-5: converges to 1e-15 in 3 steps)."""
    xy = np.asarray(xy, dtype=float)
    out = xy.copy()
    for _ in range(iterations):
        r2 = np.sum(out * out, axis=-1, keepdims=True)
        out = xy / (1.0 + k * (1.0 + r2))
    return out


def refraction_displacement_px(r_px: np.ndarray, f_px: float, k: float) -> np.ndarray:
    """Radial refraction displacement (pixels, outwards) at radius ``r_px`` from the principal point."""
    r = np.asarray(r_px, dtype=float)
    return k * (r + r**3 / f_px**2)


# ------------------------------------------------------------------------------ rolling shutter
def row_time_offset(v: np.ndarray, height: int, readout_s: float) -> np.ndarray:
    """Exposure time of image row ``v`` (pixels, top-left convention) relative to the recorded time (s)."""
    return readout_s * (np.asarray(v, dtype=float) / float(height) - 0.5)


def rolling_shutter_shift_px(speed_m_s: float, readout_s: float, gsd_m: float) -> float:
    """Displacement between the first and the last row of a frame (pixels): ``v t_readout / GSD``."""
    return speed_m_s * readout_s / gsd_m


# ------------------------------------------------------------------------------ sizes for reports
def boresight_shift_px(f_px: float, angle_deg: float) -> float:
    """Image shift at the principal point of a rotation ``angle_deg`` about a camera x or y axis."""
    return f_px * math.radians(angle_deg)


def focal_shift_px(df_px: float, r_px: float, f_px: float) -> float:
    """Radial displacement at radius ``r_px`` when the focal length changes by ``df_px``."""
    return df_px * r_px / f_px


# ------------------------------------------------------------------------------ thermal rotation
def thermal_rotation_angle(rate_px_per_c: float, dt_c, corner_radius_px: float):
    """Image rotation (radians) of ``thermal_rotation`` at ``dt_c`` degC (a number or an array) from the reference
    temperature, for a camera whose farthest corner lies ``corner_radius_px`` from the principal point."""
    return rate_px_per_c * np.asarray(dt_c, dtype=float) / corner_radius_px


def rotation_zero_point(names: set[str] | list[str], values, sigmas) -> bool:
    """Whether a boresight (``values``, ``sigmas``: degrees about the camera's x, y, z) named beside the effects
    ``names`` is a thermal rotation's zero point: a thermal rotation is among them and the boresight turns the
    frames about the optical axis alone (x and y within two sigmas of zero, or not applied).

    A thermal rotation turns the frames by its rate times the temperature's distance from a reference that one
    flight cannot know (the block's mean temperature is used); the frames' turn at that reference is a constant
    rotation about the optical axis, which the block sees as a boresight about z. One flight cannot tell it from
    a yaw mounting offset, so the two are reported as one finding (:func:`rotation_zero_point_text`)."""
    v = np.asarray(values, dtype=float)
    s = np.asarray([np.inf if x is None else x for x in sigmas], dtype=float)
    return ("thermal_rotation" in names and len(v) == 3 and v[2] != 0.0
            and bool(np.all((v[:2] == 0.0) | (np.abs(v[:2]) <= 2.0 * s[:2]))))


def rotation_zero_point_text(turn_deg: float, sigma_deg: float | None) -> str:
    """The words for a thermal rotation's zero point (:func:`rotation_zero_point`) of ``turn_deg`` +- ``sigma_deg``."""
    sigma = "?" if sigma_deg is None else f"{sigma_deg:.2g}"
    return (f"the frames turned {turn_deg:+.4g} +- {sigma} deg about the optical axis at the thermal rotation's "
            "reference temperature (its zero point, or a yaw mounting offset: one flight cannot tell them apart; "
            "applied as a boresight)")


def image_rotation(theta_rad: float) -> np.ndarray:
    """Rotation of camera coordinates about the optical axis by ``theta_rad`` (x towards y): applied as
    ``R_cw' = image_rotation(theta) @ R_cw`` it rotates the image about the principal point."""
    c, s = math.cos(theta_rad), math.sin(theta_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
