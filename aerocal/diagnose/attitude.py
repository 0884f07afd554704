"""The recorded attitudes against the adjusted ones: a gimbal's yaw recorded for the camera's, a mounting tilt, an
angle convention read the wrong way.

Small drones record the attitude of the gimbal or of the aircraft, not always of the camera, and to a few degrees.
Where the block observes the recorded attitudes, a constant offset of them turns the whole block when nothing
else holds its orientation firmly (consumer GNSS over a small block, no ground control: a 4 deg yaw offset recorded
by a rendered XT2 survey turned its adjusted block by 3 deg). So the offset is measured against the orientation
the images and the recorded positions give without the attitudes (:func:`offset_statistics` on an adjustment
that does not observe them), and judged on the images the estimate did not use: each image's offset predicted
from the others' (leave one out).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aerocal.adjust.projection import rotation_log
from aerocal.diagnose.prediction import HELD_OUT_SIGMAS

#: an offset (of the recorded attitudes about an axis, of the block against its check points in
#: :func:`aerocal.diagnose.engine.check_point_offset`) is one beyond this many of its sigmas, and with a
#: leave-one-out gain beyond :data:`~aerocal.diagnose.prediction.HELD_OUT_SIGMAS` of its standard errors
OFFSET_SIGMAS = 3.0


@dataclass(frozen=True)
class AttitudeOffset:
    """How the recorded attitudes are turned from the adjusted ones, about the camera axes x, y, z (degrees,
    ``log(R_adjusted R_recorded^T)``, the convention of ``boresight`` in :mod:`aerocal.effects`): the median over the
    images (``estimate``), its sigma (1.253 x 1.4826 MAD / sqrt(n), the median's, and the block's orientation's own
    uncertainty where given), the images' ``spread`` (1.4826 MAD), and the gain of predicting each image's offset
    from the others' medians (``held_out_gain``: relative reduction of the images' squared offsets, with its
    standard error ``held_out_sigma``)."""

    estimate: tuple[float, float, float]
    sigma: tuple[float, float, float]
    spread: tuple[float, float, float]
    n_images: int
    held_out_gain: float
    held_out_sigma: float

    @property
    def axes(self) -> list[str]:
        """The camera axes about which the offset is beyond :data:`OFFSET_SIGMAS` of its sigma."""
        z = np.abs(np.asarray(self.estimate)) / np.maximum(np.asarray(self.sigma), 1e-12)
        return [a for a, big in zip(("x", "y", "z"), z > OFFSET_SIGMAS, strict=True) if big]

    @property
    def significant(self) -> bool:
        """Beyond its sigma about an axis and predicting the images the estimate did not use."""
        return bool(self.axes) and self.held_out_gain > HELD_OUT_SIGMAS * max(self.held_out_sigma, 1e-12)

    def applied(self) -> np.ndarray:
        """The rotation vector (degrees) to remove: the components beyond their sigma, zero elsewhere."""
        keep = np.array([a in self.axes for a in ("x", "y", "z")])
        return np.where(keep, np.asarray(self.estimate), 0.0)

    def text(self) -> str:
        est = ", ".join(f"{v:+.3g}" for v in self.estimate)
        sig = ", ".join(f"{v:.2g}" for v in self.sigma)
        return (f"{est} +- {sig} deg about the camera's x, y, z (median of {self.n_images} images, spread "
                f"{', '.join(f'{v:.2g}' for v in self.spread)} deg; leave-one-out gain {100 * self.held_out_gain:+.1f} "
                f"+- {100 * self.held_out_sigma:.1f} %)")

    def to_dict(self) -> dict:
        return {"estimate": list(self.estimate), "sigma": list(self.sigma), "spread": list(self.spread),
                "units": "deg", "n_images": self.n_images, "held_out_gain": self.held_out_gain,
                "held_out_sigma": self.held_out_sigma}


def mean_rotation_covariance(solution, n_images: int) -> np.ndarray:
    """Covariance (3, 3, degrees^2) of the mean of the adjusted rotations of ``n_images`` images (about the camera
    axes) of an adjustment's :class:`~aerocal.adjust.solver.Solution`, scaled by its sigma0^2: what the block's
    datum (its recorded positions, its control) leaves of its orientation, common to every image and not in their
    scatter."""
    lay = solution.layout
    E = np.zeros((lay.n_camera, 3))
    for k in range(3):
        E[lay.n_global + 6 * np.arange(n_images) + k, k] = 1.0 / n_images
    cov = E.T @ solution.cov_camera.solve(E) * solution.sigma0**2
    return np.degrees(np.degrees(0.5 * (cov + cov.T)))


def offset_statistics(R_adjusted: np.ndarray, R_recorded: np.ndarray,
                      datum_covariance: np.ndarray | None = None) -> AttitudeOffset | None:
    """:class:`AttitudeOffset` of adjusted world-to-camera rotations (N, 3, 3) against the recorded ones; None with
    fewer than three images. ``datum_covariance`` (3, 3, degrees^2, :func:`mean_rotation_covariance`): the
    uncertainty of the adjusted block's orientation as a whole, added to the sigma the images' scatter gives (a block
    whose datum only consumer GNSS holds has its tilt known to degrees, whatever its images agree on)."""
    n = len(R_adjusted)
    if n < 3:
        return None
    w = np.degrees(rotation_log(np.einsum("nij,nkj->nik", R_adjusted, R_recorded)))
    est = np.median(w, axis=0)
    spread = 1.4826 * np.median(np.abs(w - est), axis=0)
    sigma = 1.2533 * spread / np.sqrt(n)
    if datum_covariance is not None:
        sigma = np.sqrt(sigma**2 + np.maximum(np.diag(datum_covariance), 0.0))
    others = np.array([np.median(np.delete(w, j, axis=0), axis=0) for j in range(n)])
    a = np.sum(w**2, axis=1)
    d = a - np.sum((w - others) ** 2, axis=1)
    scale = max(float(np.mean(a)), 1e-300)
    return AttitudeOffset(tuple(float(v) for v in est), tuple(float(v) for v in sigma),
                          tuple(float(v) for v in spread), n, float(np.mean(d)) / scale,
                          float(np.std(d, ddof=1) / np.sqrt(n)) / scale)
