"""Image measurements of a simulated flight: tie points and ground control, with noise.

Tie points are surface points of the scene's DSM, projected through each frame's true sensor model
(:class:`aerocal.simulate.exposure.Exposure`, every effect applied) and perturbed with Gaussian noise.
Occlusion is not modelled in this mode (it is in rendered images): at the seeds' geometries (nadir,
narrow field of view) it removes few measurements and biases none. Points seen in fewer than two
frames are dropped.

Fast enough for city scale: a KD-tree finds the candidate points of each frame, and all projection is
vectorised per frame (``conte-city``, ~800 frames, ~400k measurements, in seconds).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from aerocal.simulate.exposure import Exposure


@dataclass
class Measurements:
    """Noisy image measurements and the true object points they belong to."""

    image_id: np.ndarray  # int32 (M,)
    point_id: np.ndarray  # int64 (M,)
    uv: np.ndarray  # (M, 2) measured pixels (with noise)
    uv_true: np.ndarray  # (M, 2) noise-free projection
    points: np.ndarray  # (P, 3) true object coordinates indexed by point_id


def _frame_measurements(
    exposures: list[Exposure], points: np.ndarray, ground_radius: float, margin_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    tree = cKDTree(points[:, :2])
    img, pid, uv_all = [], [], []
    for ex in exposures:
        # ground point below the camera (the optical axis meets the mean point height)
        axis = ex.R_cw[2]  # camera z in the world frame
        zc = float(np.mean(points[:, 2]))
        s = (zc - ex.C[2]) / axis[2] if abs(axis[2]) > 1e-6 else 0.0
        foot = ex.C[:2] + s * axis[:2]
        cand = np.asarray(tree.query_ball_point(foot, ground_radius), dtype=np.int64)
        if cand.size == 0:
            continue
        uv = ex.project(points[cand])
        ok = np.isfinite(uv).all(axis=1) & ex.camera.in_image(uv, margin=margin_px)
        img.append(np.full(int(ok.sum()), ex.image_id, dtype=np.int32))
        pid.append(cand[ok])
        uv_all.append(uv[ok])
    if not img:
        return np.zeros(0, np.int32), np.zeros(0, np.int64), np.zeros((0, 2))
    return np.concatenate(img), np.concatenate(pid), np.concatenate(uv_all)


def observe_points(
    exposures: list[Exposure],
    points: np.ndarray,
    sigma_px: float,
    rng: np.random.Generator,
    ground_radius_m: float,
    margin_px: float = 2.0,
    min_views: int = 2,
) -> Measurements:
    """Project ``points`` (P, 3) into every frame that sees them; keep points seen ``min_views`` times."""
    if len(points) == 0:
        empty = np.zeros((0, 2))
        return Measurements(np.zeros(0, np.int32), np.zeros(0, np.int64), empty, empty, np.zeros((0, 3)))
    img, pid, uv = _frame_measurements(exposures, points, ground_radius_m, margin_px)
    counts = np.bincount(pid, minlength=len(points))
    keep = counts[pid] >= min_views
    img, pid, uv = img[keep], pid[keep], uv[keep]
    noisy = uv + rng.normal(0.0, sigma_px, uv.shape)
    return Measurements(image_id=img, point_id=pid, uv=noisy, uv_true=uv, points=points)


def sample_surface_points(scene, bounds: tuple[float, float, float, float], n: int,
                          rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniformly over ``bounds`` (e_min, n_min, e_max, n_max) on the scene's DSM surface."""
    e0, n0, e1, n1 = bounds
    e = rng.uniform(e0, e1, n)
    nn = rng.uniform(n0, n1, n)
    return np.column_stack([e, nn, scene.height_at(e, nn)])


def place_control(scene, bounds: tuple[float, float, float, float], n: int, rng: np.random.Generator,
                  inset: float = 0.08, avoid: np.ndarray | None = None, min_separation_m: float = 10.0) -> np.ndarray:
    """``n`` well-spread ground points (stratified over a grid with jitter) on the terrain (not roofs).

    Points keep ``min_separation_m`` from each other and from ``avoid`` (M, 2 or 3), so that their
    signalised targets never overlap.
    """
    if n <= 0:
        return np.zeros((0, 3))
    e0, n0, e1, n1 = bounds
    w, h = e1 - e0, n1 - n0
    cols = max(1, int(np.ceil(np.sqrt(n * w / max(h, 1e-9)))))
    rows = max(1, int(np.ceil(n / cols)))
    cells = [(i, j) for j in range(rows) for i in range(cols)]
    order = rng.permutation(len(cells))[:n]
    pts = []
    for k in order:
        i, j = cells[k]
        u = (i + 0.5 + rng.uniform(-0.3, 0.3)) / cols
        v = (j + 0.5 + rng.uniform(-0.3, 0.3)) / rows
        pts.append((e0 + w * (inset + (1 - 2 * inset) * u), n0 + h * (inset + (1 - 2 * inset) * v)))
    pts_arr = np.asarray(pts)
    if hasattr(scene, "open_ground_positions"):
        # signalised targets stand on open ground: move each to the nearest open cell (no roof or tree)
        cand = scene.open_ground_positions(40 * n, rng, clearance_m=4.0)
        inside = (cand[:, 0] >= e0) & (cand[:, 0] <= e1) & (cand[:, 1] >= n0) & (cand[:, 1] <= n1)
        cand = cand[inside] if inside.sum() >= n else cand
        taken = [] if avoid is None else [tuple(a[:2]) for a in np.atleast_2d(avoid)]
        chosen = []
        for p in pts_arr:  # greedy: nearest open cell not too close to a point already taken
            order = np.argsort(np.hypot(*(cand - p).T))
            for k in order:
                if all(np.hypot(cand[k, 0] - q[0], cand[k, 1] - q[1]) >= min_separation_m for q in taken):
                    break
            chosen.append(cand[k])
            taken.append(tuple(cand[k]))
        pts_arr = np.asarray(chosen)
    z = scene.ground_height_at(pts_arr[:, 0], pts_arr[:, 1])
    return np.column_stack([pts_arr, z])
