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


@dataclass(frozen=True)
class LaserRangeCheck:
    """Per image, the range along the camera's axis to the block's surface against the laser's: the products'
    DSM (:func:`aerocal.products.range_check.laser_range_check`) or the tie points around the axis
    (:func:`held_out_tie_ranges`, the self-calibration's review).

    Attributes:
        image_ids: images with a laser range whose axis meets the surface.
        laser_m: the laser's ranges (metres).
        surface_m: the ranges from the adjusted camera to the surface along the axis through the principal point
            (metres).
        unmatched: images with a laser range whose axis met no surface (off the DSM, a filled cell, no
            convergence; no tie point near the principal point).
    """

    image_ids: tuple[int, ...]
    laser_m: tuple[float, ...]
    surface_m: tuple[float, ...]
    unmatched: int

    @property
    def difference_m(self) -> np.ndarray:
        """Surface minus laser range (metres): positive when the DSM lies farther from the camera (lower)."""
        return np.asarray(self.surface_m) - np.asarray(self.laser_m)

    @property
    def median_m(self) -> float:
        return float(np.median(self.difference_m)) if self.image_ids else float("nan")

    @property
    def nmad_m(self) -> float:
        d = self.difference_m
        return float(1.4826 * np.median(np.abs(d - np.median(d)))) if self.image_ids else float("nan")

    @property
    def median_relative(self) -> float:
        """Median of surface over laser range, less 1: a depth scale error reads the same at every range."""
        if not self.image_ids:
            return float("nan")
        return float(np.median(np.asarray(self.surface_m) / np.asarray(self.laser_m)) - 1.0)

    @property
    def median_error_m(self) -> float:
        """Standard error of the median difference (metres): 1.2533 NMAD / sqrt(n), normal errors."""
        return 1.2533 * self.nmad_m / np.sqrt(len(self.image_ids)) if self.image_ids else float("nan")

    def agrees(self, gsd_m: float) -> bool:
        """Whether the surface agrees with the laser: the median difference within 2 ground samples plus twice its
        standard error (the issue's "within 2 GSD", widened by what the rough surfaces leave uncertain)."""
        return bool(abs(self.median_m) <= 2.0 * gsd_m + 2.0 * self.median_error_m)

    def verdict(self, gsd_m: float) -> str:
        """The comparison in words: the median difference, its standard error and what it means."""
        if not self.image_ids:
            return f"not compared: none of the {self.unmatched} frames' axes meets a measured cell of the DSM"
        figures = (f"median {self.median_m:+.2f} +- {self.median_error_m:.2f} m, NMAD {self.nmad_m:.2f} m over "
                   f"{len(self.image_ids)} frames, laser ranges about {float(np.median(self.laser_m)):.0f} m")
        if self.agrees(gsd_m):
            return f"agrees with the laser range finder ({figures})"
        side = "farther from" if self.median_m > 0 else "closer to"
        return (f"DISAGREES with the laser range finder: the surface lies {abs(self.median_m):.1f} m "
                f"({100 * abs(self.median_relative):.0f} % of the range) {side} the cameras than the laser measured "
                f"({figures}); the block's depth is wrong (a focal length, a principal point or a bending the "
                "images do not determine), and the heights of the DSM with it")

    def figures(self) -> dict:
        """The comparison's figures as plain JSON (metres; ``median_relative`` dimensionless)."""
        return {"n": len(self.image_ids), "unmatched": self.unmatched, "median_m": self.median_m,
                "median_relative": self.median_relative,
                "median_error_m": self.median_error_m, "nmad_m": self.nmad_m,
                "median_laser_m": float(np.median(self.laser_m)) if self.image_ids else None}

    def to_json(self, gsd_m: float) -> dict:
        return {"verdict": self.verdict(gsd_m), "agrees": self.agrees(gsd_m) if self.image_ids else None,
                **self.figures(),
                "images": {str(i): [round(a, 3), round(b, 3)]
                           for i, a, b in zip(self.image_ids, self.laser_m, self.surface_m, strict=True)}}


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


def held_out_tie_ranges(image_ids: np.ndarray, laser_range: np.ndarray, R: np.ndarray, C: np.ndarray,
                        obs_image: np.ndarray, obs_X: np.ndarray, obs_uv: np.ndarray,
                        principal_point: tuple[float, float], f_px: float) -> LaserRangeCheck | None:
    """The block's depth against the laser ranges no fit used (the images of even id, :func:`fitted_lasers`): per
    image, the median depth along its axis (camera z, metres) of the tie points it sees within
    :data:`MAX_OFFSET_FRACTION` of ``f_px`` of its principal point.

    Args:
        image_ids, laser_range: (N,) the block's image ids and their laser ranges (metres, NaN where none).
        R, C: (N, 3, 3) world-to-camera rotations and (N, 3) projection centres of the adjusted block (metres).
        obs_image, obs_X, obs_uv: per tie observation the image's index (into the N images), its point (M, 3)
            metres (NaN where the adjustment kept no point), and its measured pixel (M, 2).
        principal_point, f_px: the block's camera (pixels).

    Returns:
        the comparison, or ``None`` when no held-out image records a range.
    """
    held = np.asarray(image_ids, dtype=np.int64) % 2 == 0
    rng = np.where(held, np.asarray(laser_range, dtype=float), np.nan)
    with_range = np.flatnonzero(np.isfinite(rng) & (rng > 0))
    if not len(with_range):
        return None
    near = (np.hypot(obs_uv[:, 0] - principal_point[0], obs_uv[:, 1] - principal_point[1])
            <= MAX_OFFSET_FRACTION * f_px) & np.isfinite(obs_X).all(axis=1) & np.isfinite(rng[obs_image])
    idx = np.flatnonzero(near)
    depth = np.einsum("mj,mj->m", R[obs_image[idx], 2, :], obs_X[idx] - C[obs_image[idx]])
    ids, laser, surface = [], [], []
    for i in with_range:
        d = depth[obs_image[idx] == i]
        d = d[d > 0]
        if len(d):
            ids.append(int(image_ids[i]))
            laser.append(float(rng[i]))
            surface.append(float(np.median(d)))
    return LaserRangeCheck(tuple(ids), tuple(laser), tuple(surface), len(with_range) - len(ids))
