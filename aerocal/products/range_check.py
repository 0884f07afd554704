"""The surface against a laser range finder on the camera's axis: an independent measurement of the DSM on real
flights without a reference surface.

Thermal gimbals such as DJI's Zenmuse H20T and H20N carry a laser range finder boresighted with their cameras and
record, per image, the distance it measured along the camera's axis (XMP ``LRFTargetDistance``; ingest keeps it as
``dji_lrf_target_distance_m``). The same distance follows from the adjusted block: the ray from the adjusted
projection centre through the principal point, intersected with the DSM. The two agree when the surface heights,
the block's scale along the view and the camera's attitude are right; their difference is a check on the dense
surface that owes nothing to the images (the laser) and nothing to the GNSS datum (both are distances from the
camera).

Where the ranges also observe the block (:mod:`aerocal.adjust.laser`, every second frame's), the products step
judges the surface on the others, which no fit used, and gives the fitted frames' figures beside them.

What the comparison cannot tell apart: the laser's spot (a few decimetres at 100 m) against the DSM's cell, and the
laser's axis against the camera's (a fraction of a degree moves the spot along a canopy's slopes). Over rough
surfaces the per-image differences are therefore wide; their median is the figure to read.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from aerocal.adjust.laser import LaserRangeCheck
from aerocal.products.dsm import Dsm
from aerocal.products.mosaic import FrameGeometry

#: fixed-point steps of the ray-surface intersection; a near-nadir ray settles in two or three
RAY_ITERATIONS = 30
#: the intersection has converged when a step moves the range by less than this (metres)
RAY_TOLERANCE_M = 0.01


def axis_range(frame: FrameGeometry, dsm: Dsm, measured: np.ndarray | None) -> float | None:
    """The distance (metres) from ``frame``'s projection centre to the DSM along the ray through its principal
    point, or ``None`` when that ray meets no measured cell (``measured``: the DSM's measured cells, ``None``:
    every cell with a height).

    The ray-surface point by fixed-point iteration on the height: range = (Z_C - h(E, N)) / -d_z, with h the
    DSM's bilinear height at the ray's point of the last range (converges while the surface's slope along the ray
    is below the ray's steepness, so always for the near-nadir axes of a mapping flight)."""
    cam = frame.camera
    xy = cam.unproject(np.array([[cam.cx, cam.cy]], dtype=float))[0]
    d = np.array([xy[0], xy[1], 1.0]) @ np.asarray(frame.R_cw, dtype=float)
    d /= np.linalg.norm(d)
    if d[2] >= -1e-3:
        return None  # an axis at or above the horizon
    C = np.asarray(frame.C, dtype=float)
    t = None
    h = dsm.height_at(C[0], C[1])
    for _ in range(RAY_ITERATIONS):
        if not np.isfinite(h):
            return None
        t_new = (C[2] - float(h)) / -d[2]
        if t is not None and abs(t_new - t) < RAY_TOLERANCE_M:
            t = t_new
            break
        t = t_new
        p = C + t * d
        h = dsm.height_at(p[0], p[1])
    else:
        return None
    p = C + t * d
    col, row = dsm.grid_coords(p[0], p[1])
    r, c = int(np.floor(row + 0.5)), int(np.floor(col + 0.5))
    rows, cols = dsm.shape
    if not (0 <= r < rows and 0 <= c < cols) or t <= 0:
        return None
    if measured is not None and not measured[r, c]:
        return None
    return float(t)


def laser_range_check(frames: Sequence[FrameGeometry], laser_m: Mapping[int, float], dsm: Dsm,
                      measured: np.ndarray | None = None) -> LaserRangeCheck | None:
    """The DSM against the laser ranges of the frames that record one.

    Args:
        frames: the adjusted frames.
        laser_m: image id -> the laser's range along the camera's axis (metres); ids without a frame are skipped.
        dsm: the surface, in the frames' world frame.
        measured: the DSM's measured cells (``None``: every cell with a height).

    Returns:
        the check, or ``None`` when no frame records a laser range.
    """
    ids, laser, surface, unmatched = [], [], [], 0
    for frame in frames:
        r = laser_m.get(frame.image_id)
        if r is None or not np.isfinite(r) or r <= 0:
            continue
        s = axis_range(frame, dsm, measured)
        if s is None:
            unmatched += 1
            continue
        ids.append(frame.image_id)
        laser.append(float(r))
        surface.append(s)
    if not ids and not unmatched:
        return None
    return LaserRangeCheck(tuple(ids), tuple(laser), tuple(surface), unmatched)


def flying_height_check(frames: Sequence[FrameGeometry], ground: Dsm, recorded_m: float) -> dict | None:
    """The flying height the surface gives against the one the flight recorded (a height above take-off: DJI
    RelativeAltitude, senseFly Height, or ``flight.json``): the median over frames of the camera's height above
    ``ground`` (a DTM, else the DSM) at its nadir point, and its difference to ``recorded_m`` (metres). A
    take-off point above or below the ground under the block, or a barometer's drift, differ too: a check of
    the depth to a few per cent, not to a ground sample. ``None`` when no frame is over the ground grid."""
    C = np.array([np.asarray(f.C, dtype=float) for f in frames]).reshape(-1, 3)
    h = ground.height_at(C[:, 0], C[:, 1]) if len(C) else np.zeros(0)
    col, row = ground.grid_coords(C[:, 0], C[:, 1]) if len(C) else (np.zeros(0), np.zeros(0))
    rows, cols = ground.shape
    over = np.isfinite(h) & (col >= 0) & (col <= cols - 1) & (row >= 0) & (row <= rows - 1)
    if not over.any():
        return None
    above = C[over, 2] - h[over]
    measured = float(np.median(above))
    return {"recorded_m": float(recorded_m), "from_surface_m": measured, "difference_m": measured - recorded_m,
            "relative": measured / recorded_m - 1.0, "frames": int(over.sum()),
            "nmad_m": float(1.4826 * np.median(np.abs(above - measured)))}
