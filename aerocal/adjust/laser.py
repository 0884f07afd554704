"""Laser ranges along the camera's axis as observations of the block.

Thermal gimbals such as DJI's Zenmuse H20T carry a laser range finder boresighted with the camera and record, per
image, the distance it measured along the camera's axis (ingest: ``images.laser_range_m``). A block of near-nadir
frames over gentle terrain whose camera is calibrated on the same frames does not determine its own depth: a
radial distortion and a steady turn of the frames along each strip (the "dome" of James & Robson 2014) fit the
images as well as the true camera does, and the surface comes out metres too far or too near. A range from each
camera to the surface fixes that depth.

The observation: image ``i``'s tie point ``j`` seen nearest the principal point lies at the laser's range along the
camera's axis, ``z_ij = (R_i (X_j - C_i))_z = r_i``, with a standard deviation that covers the laser (decimetres)
and the surface between the laser's spot and that tie point (a tree crown's height varies by a metre over the
few pixels between them). A laser that passed through a gap in a canopy to the ground is a blunder for that tie
point: the rows always carry a Cauchy loss (at the adjustment's robust scale), also in a least-squares pass.

The rows enter the normal equations as one more observation of (image ``i``, point ``j``), a pair the block
already holds: the reduced camera system keeps its pattern (:func:`aerocal.adjust.solver.BundleProblem.residuals`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: a-priori standard deviation of a laser row (metres): the laser's own ~0.2 m plus the surface between its spot
#: and the tie point used, at most :data:`MAX_OFFSET_FRACTION` of the focal length away from the axis
SIGMA_M = 1.0
#: the tie point's distance from the principal point, at most this fraction of the focal length (pixels): 3 % of
#: f is 3 % of the range on the ground (2.4 m at 80 m)
MAX_OFFSET_FRACTION = 0.03


@dataclass(frozen=True)
class LaserRows:
    """The laser observations of a block: image index, tie-point index, range (metres) and sigma (metres)."""

    image: np.ndarray
    point: np.ndarray
    range_m: np.ndarray
    sigma_m: np.ndarray

    def __len__(self) -> int:
        return len(self.image)


def fitted_lasers(image_ids: np.ndarray, laser_range: np.ndarray) -> np.ndarray:
    """``laser_range`` (N,) with the ranges the fits leave out set to NaN: those of the images with an even id. Ingest
    numbers a flight's images 1, 2, 3 ... in the order of their names, so every second frame's range observes the
    block and the others judge its surface (:mod:`aerocal.products.range_check`); a rule on the id itself, so that a
    sub-block (the calibration's images, a held-out fold) keeps out the same ranges as the whole block."""
    laser_range = np.asarray(laser_range, dtype=float)
    odd = np.asarray(image_ids, dtype=np.int64) % 2 == 1
    return np.where(odd, laser_range, np.nan)


def laser_rows(laser_range: np.ndarray | None, obs_image: np.ndarray, obs_point: np.ndarray, obs_uv: np.ndarray,
               obs_is_tie: np.ndarray, principal_point: tuple[float, float], f_px: float) -> LaserRows:
    """For every image with a laser range (``laser_range`` (N,) metres, NaN where none), the tie observation
    nearest its principal point (``principal_point`` (cx, cy), pixels), when it lies within
    :data:`MAX_OFFSET_FRACTION` of ``f_px`` of it. Images without such an observation get no row."""
    empty = LaserRows(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    if laser_range is None or not np.isfinite(laser_range).any():
        return empty
    d = np.hypot(obs_uv[:, 0] - principal_point[0], obs_uv[:, 1] - principal_point[1])
    cand = np.flatnonzero(obs_is_tie & np.isfinite(laser_range[obs_image]) & (d <= MAX_OFFSET_FRACTION * f_px))
    if not len(cand):
        return empty
    # per image, the candidate of least distance: sort by (image, distance), take each image's first
    order = cand[np.lexsort((d[cand], obs_image[cand]))]
    first = np.r_[True, obs_image[order][1:] != obs_image[order][:-1]]
    pick = order[first]
    img = obs_image[pick].astype(np.int64)
    return LaserRows(img, obs_point[pick].astype(np.int64), laser_range[img].astype(float),
                     np.full(len(pick), SIGMA_M))


def laser_residuals(R: np.ndarray, C: np.ndarray, X: np.ndarray, rows: LaserRows
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows' residuals and Jacobians: ``(res (L,) metres, z_ij - r_i; d_pose (L, 6) d(res)/d(w, C);
    d_point (L, 3) d(res)/dX)``, with the rotation updated on the left (``R <- exp([w]) R``, as
    :mod:`aerocal.adjust.projection`): ``dz/dw = (p_y, -p_x, 0)``, ``dz/dC = -R[2]``, ``dz/dX = R[2]``."""
    Ri = R[rows.image]
    p = np.einsum("lij,lj->li", Ri, X[rows.point] - C[rows.image])
    res = p[:, 2] - rows.range_m
    axis = Ri[:, 2, :]
    d_pose = np.column_stack([p[:, 1], -p[:, 0], np.zeros(len(p)), -axis])
    return res, d_pose, axis.copy()
