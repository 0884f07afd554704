"""Sensors of a simulated flight: GNSS, IMU, lever arm, boresight, clock offset, sensor temperature.

The true trajectory (:mod:`aerocal.simulate.flight_plan`) is what the camera did; these functions make what
the aircraft *recorded*, with noise and with the exterior-orientation effects of the catalogue
(:mod:`aerocal.effects`) applied, and the sensor temperature curve that drives the thermal effects;
:func:`recorded_R_cw` reads the recorded attitude of an ``images`` table back as rotations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from aerocal.geometry import attitude_to_R_cw, small_rotation


@dataclass(frozen=True)
class TemperatureCurve:
    """Sensor temperature (degC) relaxing exponentially from ``start_c`` towards ``equilibrium_c``.

    ``T(t) = T_eq + (T_start - T_eq) exp(-t / tau)``: heating when the camera starts colder than its
    equilibrium (Daakir 2019, Conte 2018), cooling otherwise (the seneca flight: 37 -> 23 degC in ~7
    minutes). ``quantum_c`` rounds the *recorded* value (Canon maker notes: 1 degC); 0 = no rounding.
    """

    start_c: float = 20.0
    equilibrium_c: float = 20.0
    tau_s: float = 600.0
    noise_c: float = 0.05  # std of the recorded value
    quantum_c: float = 0.0

    def true_at(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return self.equilibrium_c + (self.start_c - self.equilibrium_c) * np.exp(-t / self.tau_s)

    def recorded_at(self, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        rec = self.true_at(t) + rng.normal(0.0, self.noise_c, np.shape(t))
        if self.quantum_c > 0:
            rec = np.round(rec / self.quantum_c) * self.quantum_c
        return rec

    @classmethod
    def linear_between(cls, t_start: float, t_end: float, duration_s: float, **kw: float) -> TemperatureCurve:
        """A curve passing through ``t_start`` at 0 s and ``t_end`` at ``duration_s`` (tau = duration)."""
        tau = max(duration_s, 1.0)
        # T(d) = Teq + (Ts - Teq) e^-1 = t_end  ->  Teq = (t_end - Ts e^-1) / (1 - e^-1)
        e = math.exp(-duration_s / tau)
        teq = (t_end - t_start * e) / (1.0 - e)
        return cls(start_c=t_start, equilibrium_c=teq, tau_s=tau, **kw)


@dataclass(frozen=True)
class SensorConfig:
    """Noise of the recorded exterior orientation and of the image measurements."""

    gnss_sigma_h_m: float = 0.05
    gnss_sigma_v_m: float = 0.10
    imu_sigma_deg: tuple[float, float, float] = (0.005, 0.005, 0.008)  # about camera x, y, z
    tie_sigma_px: float = 0.5
    gcp_sigma_px: float = 0.5
    gcp_survey_sigma_m: tuple[float, float] = (0.02, 0.03)  # planimetric, height
    temperature: TemperatureCurve = TemperatureCurve()
    reference_temperature_c: float = 20.0  # the temperature at which the true IO equals camera_true

    def __post_init__(self) -> None:
        values = (self.gnss_sigma_h_m, self.gnss_sigma_v_m, *self.imu_sigma_deg, self.tie_sigma_px, self.gcp_sigma_px,
                  *self.gcp_survey_sigma_m)
        if not all(v >= 0 and math.isfinite(v) for v in values):
            raise ValueError(f"SensorConfig: sigmas must be finite and 0 or more, got {values}")


def recorded_exterior(
    C: np.ndarray,
    R_cw: np.ndarray,
    velocity: np.ndarray,
    config: SensorConfig,
    effects: dict[str, tuple[float, ...]],
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Recorded GNSS positions (N, 3) and IMU world-to-camera rotations (N, 3, 3).

    Effects: ``gnss_bias``, ``gnss_time_offset``, ``lever_arm`` act on the positions; ``boresight``
    on the rotations (see the sign conventions in :mod:`aerocal.effects`).
    """
    N = len(C)
    pos = np.array(C, dtype=float, copy=True)
    if "gnss_time_offset" in effects:
        pos = pos + velocity * effects["gnss_time_offset"][0]
    if "lever_arm" in effects:
        lever = np.asarray(effects["lever_arm"], dtype=float)
        pos = pos + np.einsum("nji,j->ni", R_cw, lever)  # R_cw^T lever
    if "gnss_bias" in effects:
        pos = pos + np.asarray(effects["gnss_bias"], dtype=float)
    noise = np.column_stack([
        rng.normal(0.0, config.gnss_sigma_h_m, (N, 2)), rng.normal(0.0, config.gnss_sigma_v_m, N)
    ])
    pos = pos + noise

    B = np.eye(3)
    if "boresight" in effects:
        B = small_rotation(np.radians(effects["boresight"]))
    imu_noise = rng.normal(0.0, 1.0, (N, 3)) * np.radians(config.imu_sigma_deg)
    R_rec = np.stack([small_rotation(n) @ B.T @ R for n, R in zip(imu_noise, R_cw, strict=True)])
    return pos, R_rec


def recorded_R_cw(images: pa.Table) -> np.ndarray:
    """World-to-camera rotations from the recorded attitude columns of an ``images`` table."""
    conv = images.column("attitude_convention").to_pylist()
    r = images.column("roll").to_numpy()
    p = images.column("pitch").to_numpy()
    y = images.column("yaw").to_numpy()
    return np.stack([attitude_to_R_cw(c, a, b, d) for c, a, b, d in zip(conv, r, p, y, strict=True)])
