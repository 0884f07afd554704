"""Multi-ray triangulation of tracks from known poses: linear least squares, then Gauss-Newton.

All tracks are solved at once (vectorised over tracks with ``np.add.at`` on 3x3 normal matrices).
The linear step minimises the sum of squared perpendicular distances from the point to the rays
(metres), the refinement minimises the weighted reprojection error (pixels) with the cameras held fixed.
"""

from __future__ import annotations

import numba
import numpy as np

from aerocal.adjust.projection import project
from aerocal.camera import ROW_CHUNK, Camera


def pixels_to_rays(
    io: np.ndarray, slopes: np.ndarray, dtemp: np.ndarray, R: np.ndarray, uv: np.ndarray,
    image: np.ndarray | None = None,
) -> np.ndarray:
    """Unit viewing rays in the world frame (M, 3) of pixels ``uv`` (M, 2) seen by frames ``R`` (M, 3, 3),
    or with ``image`` (M,) by frames ``R[image]`` (``R`` per image: no (M, 3, 3) gather); ``dtemp``: each
    row's temperature difference from the thermal model's reference (scalar or (M,)).

    By :data:`aerocal.camera.ROW_CHUNK` rows, as the camera's distortion maths, for the same reason."""
    dtemp = np.broadcast_to(np.asarray(dtemp, dtype=float), (len(uv),))
    out = np.empty((len(uv), 3))
    cam = Camera(width=1, height=1, f=1.0, cx=0.0, cy=0.0, k1=io[3], k2=io[4], k3=io[5], p1=io[6], p2=io[7])
    b1, b2 = io[8], io[9]
    for s in range(0, len(uv), ROW_CHUNK):
        rows = slice(s, s + ROW_CHUNK)
        f = io[0] + slopes[0] * dtemp[rows]
        cx = io[1] + slopes[1] * dtemp[rows]
        cy = io[2] + slopes[2] * dtemp[rows]
        yd = (uv[rows, 1] - cy) / f
        xd = (uv[rows, 0] - cx - yd * b2) / (f + b1)
        xy = cam.undistort(np.stack([xd, yd], axis=-1))
        d_cam = np.column_stack([xy, np.ones(len(xy))])
        d = np.einsum("mji,mj->mi", R[rows] if image is None else R[image[rows]], d_cam)  # R^T d_cam
        out[rows] = d / np.linalg.norm(d, axis=1, keepdims=True)
    return out


def triangulate_linear(
    point_idx: np.ndarray, n_points: int, centres: np.ndarray, rays: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares intersection of rays (origins ``centres`` (M, 3), unit ``rays`` (M, 3)) per point.

    Returns the points (P, 3) and a boolean mask of points with a well-conditioned intersection
    (at least two rays and a normal matrix with condition number below 1e8).
    """
    # sums over each point's rays of (I - d d^T) and (I - d d^T) c, by one bincount per component (np.add.at
    # on (M, 3, 3) blocks is unbuffered and slow)
    count = np.bincount(point_idx, minlength=n_points).astype(float)
    A = np.zeros((n_points, 3, 3))
    for u in range(3):
        for v in range(u, 3):
            A[:, u, v] = A[:, v, u] = -np.bincount(point_idx, weights=rays[:, u] * rays[:, v], minlength=n_points)
        A[:, u, u] += count
    dc = np.einsum("mj,mj->m", rays, centres)
    b = np.stack([np.bincount(point_idx, weights=centres[:, u] - rays[:, u] * dc, minlength=n_points)
                  for u in range(3)], axis=1)
    count = count.astype(int)
    ok = count >= 2
    eig = np.linalg.eigvalsh(np.where(ok[:, None, None], A, np.eye(3)[None]))
    ok &= eig[:, 0] > 1e-8 * eig[:, 2]
    A[~ok] = np.eye(3)
    X = np.linalg.solve(A, b[:, :, None])[:, :, 0]
    X[~ok] = np.nan
    return X, ok


def refine_points(
    io: np.ndarray,
    slopes: np.ndarray,
    dtemp: np.ndarray,
    R: np.ndarray,
    C: np.ndarray,
    point_idx: np.ndarray,
    uv: np.ndarray,
    sigma: np.ndarray,
    X: np.ndarray,
    iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the weighted reprojection error of each point with the cameras fixed.

    Per-observation arrays (``dtemp``, ``R``, ``C``, ``point_idx``, ``uv``, ``sigma``) are aligned; returns
    the refined points and their normal matrices ``A^T A`` (P, 3, 3) in units of 1/sigma^2.
    """
    X = np.array(X, dtype=float, copy=True)
    P = len(X)
    N = np.zeros((P, 3, 3))
    for _ in range(iterations):
        pr = project(io, slopes, dtemp, R, C, X[point_idx])
        r = (pr.uv - uv) / sigma[:, None]
        J = pr.d_point / sigma[:, None, None]
        N = np.zeros((P, 3, 3))
        g = np.zeros((P, 3))
        np.add.at(N, point_idx, np.einsum("mki,mkj->mij", J, J))
        np.add.at(g, point_idx, np.einsum("mki,mk->mi", J, r))
        good = np.isfinite(N).all(axis=(1, 2)) & (np.linalg.det(np.nan_to_num(N)) > 0)
        Ns = np.where(good[:, None, None], N, np.eye(3)[None])
        step = -np.linalg.solve(Ns, np.where(good[:, None], g, 0.0)[:, :, None])[:, :, 0]
        X += step
        if np.nanmax(np.abs(step), initial=0.0) < 1e-9:
            break
    return X, N


#: A tie point is handed back only when its rays place it: in front of every camera seeing it, and spread
#: by an angle that puts its sigma along them below this fraction of its depth (for rays spread by ``theta``
#: radians the sigma along them is about ``depth sqrt(2) sigma_px / (f theta)``). A two-ray thermal point
#: 850 m deep on a 60 m base at 0.2 px has 0.002 of its depth; nearly parallel rays have more than all of it.
MAX_POINT_SIGMA_FRACTION = 0.1

#: ... and only when no camera sees it deeper than this many times the mean depth of that camera's points.
#: Rays spread well enough still place a mismatch along the epipolar line: on the rendered 818-frame city
#: (850 m above ground), two-ray points up to 6.8 km below the ground passed the test above with residuals
#: of tenths of a pixel. Three times the mean depth is 1.7 km below the ground there. Relief and oblique views
#: need room (computed, not measured: a view 60 degrees off nadir with a 40 degree field sees its far edge
#: 2.7 times as deep as its centre; wider or more oblique views would need a larger ratio).
MAX_DEPTH_RATIO = 3.0


def placed_by_rays(
    X: np.ndarray, R: np.ndarray, C: np.ndarray, image: np.ndarray, point: np.ndarray, sigma_px: np.ndarray,
    f: float,
) -> np.ndarray:
    """Mask (P,) of the points ``X`` (P, 3) that their rays place (:data:`MAX_POINT_SIGMA_FRACTION`,
    :data:`MAX_DEPTH_RATIO`).

    ``R`` (N, 3, 3) world-to-camera and ``C`` (N, 3) per image; one row per observation in ``image``,
    ``point`` and ``sigma_px`` (pixels); ``f`` the focal length in pixels. The spread of a point's rays is
    the largest angle between its first ray and another: exact for two rays, at least half the largest
    angle between any two of more (their spread is then far above the limit anyway).

    On a rendered 129-frame city block one two-ray point the adjustment handed back lay 320 km off the
    block and 9,700 km deep (a residual of 0.17 px), and the DSM gridded with it had 8 x 8 cells of 635 m.
    Compiled (numba), one pass over the observations, grouped by point: several times faster than numpy's
    ``bincount`` and ``minimum.at`` (``benchmarks/history/engine_measurements.md``).
    """
    X = np.ascontiguousarray(X, dtype=float)
    axis = np.ascontiguousarray(np.asarray(R, dtype=float)[:, 2])
    acc = _ray_spread(X, axis, np.ascontiguousarray(C, dtype=float), np.asarray(image, dtype=np.int64),
                      np.asarray(point, dtype=np.int64), np.asarray(sigma_px, dtype=float))
    min_cos, sigma_sum, n, front = acc[:, 3], acc[:, 4], acc[:, 5], acc[:, 6] > 0
    spread = np.arccos(np.clip(min_cos, -1.0, 1.0))
    sigma = sigma_sum / np.maximum(n, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma_fraction = np.sqrt(2.0) * sigma / (f * spread)
    finite = np.isfinite(X).all(axis=1)
    shallow = _depth_ratio(X, axis, np.ascontiguousarray(C, dtype=float), np.asarray(image, dtype=np.int64),
                           np.asarray(point, dtype=np.int64), front & finite) <= MAX_DEPTH_RATIO
    return front & finite & (n >= 2) & (sigma_fraction < MAX_POINT_SIGMA_FRACTION) & shallow


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _depth_ratio(X, axis, C, image, point, usable):
    """Per point, the largest ratio of its depth in a camera (along the optical axis) to the mean depth of that
    camera's ``usable`` points; two passes over the observations."""
    n_images = C.shape[0]
    depth_sum = np.zeros(n_images)
    depth_n = np.zeros(n_images)
    for m in range(point.shape[0]):
        i, j = image[m], point[m]
        if usable[j]:
            depth_sum[i] += _depth(X, axis, C, i, j)
            depth_n[i] += 1.0
    ratio = np.zeros(X.shape[0])
    for m in range(point.shape[0]):
        i, j = image[m], point[m]
        if usable[j]:
            r = _depth(X, axis, C, i, j) * depth_n[i] / depth_sum[i]
            if r > ratio[j]:
                ratio[j] = r
    return ratio


@numba.njit(cache=True, nogil=True, inline="always")
def _depth(X, axis, C, i, j):
    """Depth of point ``j`` along camera ``i``'s optical axis (metres)."""
    return axis[i, 0] * (X[j, 0] - C[i, 0]) + axis[i, 1] * (X[j, 1] - C[i, 1]) + axis[i, 2] * (X[j, 2] - C[i, 2])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _ray_spread(X, axis, C, image, point, sigma_px):
    """Per point, in one pass over the observations, a row of 8 (one cache line: the observations need not be
    grouped by point, so the points are visited in any order): its first ray's direction (3), the smallest cosine
    between that ray and another, the sum of its sigmas, its rays, and 1 while it is in front of every
    camera seeing it, else 0."""
    P = X.shape[0]
    acc = np.zeros((P, 8))
    acc[:, 3] = 1.0
    acc[:, 6] = 1.0
    for m in range(point.shape[0]):
        i, j = image[m], point[m]
        v0, v1, v2 = X[j, 0] - C[i, 0], X[j, 1] - C[i, 1], X[j, 2] - C[i, 2]
        a = acc[j]
        if not axis[i, 0] * v0 + axis[i, 1] * v1 + axis[i, 2] * v2 > 0:
            a[6] = 0.0
        norm = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if norm > 0:
            v0, v1, v2 = v0 / norm, v1 / norm, v2 / norm
            if a[5] == 0:
                a[0], a[1], a[2] = v0, v1, v2
            else:
                c = v0 * a[0] + v1 * a[1] + v2 * a[2]
                if c < a[3]:
                    a[3] = c
        a[5] += 1.0
        a[4] += sigma_px[m]
    return acc
