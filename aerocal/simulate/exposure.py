"""The true sensor model of one simulated frame: every effect applied, forwards and backwards.

:meth:`Exposure.project` (world -> pixels) makes the observations; :meth:`Exposure.rays` (pixels ->
world rays) drives the renderer. They are exact inverses of each other (tested to 1e-9 px), so that
rendered images and generated observations share one geometry.

Order of the forward model (world point X -> pixel):
``p = R_cw (X - C(t_row))`` -> normalised ``p_xy / p_z`` -> atmospheric refraction -> Brown distortion
-> pixels with the true IO at the frame's sensor temperature (affinity, skew, k3 included). With a
rolling shutter ``t_row`` depends on the row the point lands on; it is found by fixed-point
iteration (contraction factor = rolling-shutter shift / image height, ~1e-2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aerocal.camera import Camera
from aerocal.effects import refract, row_time_offset, unrefract


@dataclass(frozen=True)
class Exposure:
    """One frame: true IO, true pose at the recorded time, motion, and the effects that act per row.

    ``R_cw`` is world-to-camera; ``C`` the projection centre (world metres) when the middle row is
    exposed; ``velocity`` m/s in the world frame; ``readout_s`` the rolling-shutter readout time
    (0 for a global shutter); ``refraction_k`` Bertram's K (0 = no refraction).
    """

    image_id: int
    camera: Camera
    R_cw: np.ndarray
    C: np.ndarray
    velocity: np.ndarray
    readout_s: float = 0.0
    refraction_k: float = 0.0

    def centre_at(self, dt: np.ndarray) -> np.ndarray:
        """Projection centre(s) ``dt`` seconds after the recorded time."""
        return np.asarray(self.C) + np.asarray(dt, dtype=float)[..., None] * np.asarray(self.velocity)

    def _project_from(self, X: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = (X - centres) @ self.R_cw.T
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / np.where(z > 0, z, np.nan)[:, None]
        if self.refraction_k:
            xy = refract(xy, self.refraction_k)
        return self.camera.normalised_to_pixels(self.camera.distort(xy)), z

    def project(self, X: np.ndarray, tol_px: float = 1e-10, max_iter: int = 12) -> np.ndarray:
        """World points (N, 3) -> pixels (N, 2); NaN for points behind the camera."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        uv, _ = self._project_from(X, np.asarray(self.C)[None, :])
        if not self.readout_s:
            return uv
        for _ in range(max_iter):
            dt = row_time_offset(np.nan_to_num(uv[:, 1], nan=self.camera.height / 2), self.camera.height,
                                 self.readout_s)
            new, _ = self._project_from(X, self.centre_at(dt))
            step = np.nanmax(np.abs(new - uv)) if np.isfinite(new).any() else 0.0
            uv = new
            if step < tol_px:
                break
        return uv

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) -> ray origins (N, 3) and unit directions (N, 3) in the world frame."""
        uv = np.atleast_2d(np.asarray(uv, dtype=float))
        xy = self.camera.unproject(uv)
        if self.refraction_k:
            xy = unrefract(xy, self.refraction_k)
        d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d = d_cam @ self.R_cw  # = (R_cw^T d_cam^T)^T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        if self.readout_s:
            origins = self.centre_at(row_time_offset(uv[:, 1], self.camera.height, self.readout_s))
        else:
            origins = np.broadcast_to(np.asarray(self.C, dtype=float), d.shape).copy()
        return origins, d
