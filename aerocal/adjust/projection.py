"""Vectorised projection of world points into frames with per-frame interior orientation, and its Jacobians.

The model is :class:`aerocal.camera.Camera`'s Brown model (Metashape convention, pixels, origin at the
top-left corner of the image) with the focal length and principal point of each observation allowed to
differ (the thermal model: ``f_i = f0 + a_f (T_i - T0)``, likewise ``cx``, ``cy``).

Poses are world-to-camera: ``p = R (X - C)`` with ``X`` and ``C`` in a local frame (metres). Rotation
updates are applied on the left, ``R <- exp([w]) R``, so ``dp/dw = -[p]_x``.

The analytic Jacobians here are checked against central differences in ``tests/test_adjust_core.py``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial.transform import Rotation

from aerocal.adjust.schur_kernels import scale_observation_blocks
from aerocal.camera import PARAM_NAMES

#: Index of each IO parameter in the parameter vector (order of :data:`aerocal.camera.PARAM_NAMES`).
IDX = {n: i for i, n in enumerate(PARAM_NAMES)}
#: IO parameters a thermal slope can act on.
THERMAL_PARAMS: tuple[str, ...] = ("f", "cx", "cy")


@dataclass
class Projection:
    """Predicted pixels and the Jacobians of one batch of observations (M observations).

    ``uv`` (M, 2) pixels; ``d_point`` (M, 2, 3) d(uv)/dX; ``d_centre`` = -d_point; ``d_rot`` (M, 2, 3)
    d(uv)/dw; ``d_io`` (M, 2, 10) d(uv)/d(IO) in PARAM_NAMES order; ``d_slope`` (M, 2, 3) d(uv)/d(slope of
    f, cx, cy); ``depth`` (M,) the point's depth along the optical axis (metres).
    """

    uv: np.ndarray
    d_point: np.ndarray
    d_rot: np.ndarray
    d_io: np.ndarray
    d_slope: np.ndarray
    depth: np.ndarray


def project(
    io: np.ndarray,
    slopes: np.ndarray,
    dtemp: np.ndarray,
    R: np.ndarray,
    C: np.ndarray,
    X: np.ndarray,
    jacobians: bool = True,
    io_jacobians: bool = True,
) -> Projection:
    """Project points ``X`` (M, 3) through poses ``R`` (M, 3, 3), ``C`` (M, 3), one row per observation.

    ``io`` is the IO vector at the reference temperature (PARAM_NAMES order), ``slopes`` the thermal
    slopes of (f, cx, cy) in pixels per degC, ``dtemp`` (M,) the frame temperature minus the reference.
    With ``io_jacobians=False`` (IO and slopes held fixed) ``d_io`` and ``d_slope`` are empty (M, 2, 0):
    208 bytes per observation a fixed-IO block does not need.
    """
    f0, cx0, cy0, k1, k2, k3, p1, p2, b1, b2 = (float(v) for v in io)
    f = f0 + slopes[0] * dtemp
    cx = cx0 + slopes[1] * dtemp
    cy = cy0 + slopes[2] * dtemp
    p = np.einsum("mij,mj->mi", R, X - C)
    z = p[:, 2]
    x = p[:, 0] / z
    y = p[:, 1] / z
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
    yd = y * radial + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
    fx = f + b1
    uv = np.stack([cx + xd * fx + yd * b2, cy + yd * f], axis=-1)
    M = len(z)
    if not jacobians:
        empty = np.zeros((M, 2, 0))
        return Projection(uv, empty, empty, empty, empty, z)

    # distortion Jacobian d(xd, yd)/d(x, y)
    dr = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    a = radial + 2 * x * x * dr + 6 * p1 * x + 2 * p2 * y
    b = 2 * x * y * dr + 2 * p1 * y + 2 * p2 * x
    c = 2 * x * y * dr + 2 * p2 * x + 2 * p1 * y
    e = radial + 2 * y * y * dr + 6 * p2 * y + 2 * p1 * x
    # d(uv)/d(x, y): pixel mapping [[fx, b2], [0, f]] times the distortion Jacobian
    m00 = fx * a + b2 * c
    m01 = fx * b + b2 * e
    m10 = f * c
    m11 = f * e
    iz = 1.0 / z
    # d(uv)/dp = M @ [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    A = np.empty((M, 2, 3))
    A[:, 0, 0] = m00 * iz
    A[:, 0, 1] = m01 * iz
    A[:, 0, 2] = -(m00 * x + m01 * y) * iz
    A[:, 1, 0] = m10 * iz
    A[:, 1, 1] = m11 * iz
    A[:, 1, 2] = -(m10 * x + m11 * y) * iz
    d_point = np.einsum("mij,mjk->mik", A, R)
    # dp/dw = -[p]_x
    px = np.zeros((M, 3, 3))
    px[:, 0, 1], px[:, 0, 2] = p[:, 2], -p[:, 1]
    px[:, 1, 0], px[:, 1, 2] = -p[:, 2], p[:, 0]
    px[:, 2, 0], px[:, 2, 1] = p[:, 1], -p[:, 0]
    d_rot = np.einsum("mij,mjk->mik", A, px)
    del px
    if not io_jacobians:
        empty = np.zeros((M, 2, 0))
        return Projection(uv, d_point, d_rot, empty, empty, z)

    d_io = np.zeros((M, 2, len(PARAM_NAMES)))
    d_io[:, 0, 0], d_io[:, 1, 0] = xd, yd
    d_io[:, 0, 1] = 1.0
    d_io[:, 1, 2] = 1.0
    for i, power in ((3, 1), (4, 2), (5, 3)):
        rp = r2**power
        d_io[:, 0, i] = fx * x * rp + b2 * y * rp
        d_io[:, 1, i] = f * y * rp
    t1x, t1y = r2 + 2 * x * x, 2 * x * y  # d(xd, yd)/dp1
    t2x, t2y = 2 * x * y, r2 + 2 * y * y  # d(xd, yd)/dp2
    d_io[:, 0, 6], d_io[:, 1, 6] = fx * t1x + b2 * t1y, f * t1y
    d_io[:, 0, 7], d_io[:, 1, 7] = fx * t2x + b2 * t2y, f * t2y
    d_io[:, 0, 8] = xd
    d_io[:, 0, 9] = yd
    d_slope = np.zeros((M, 2, 3))
    d_slope[:, 0, 0], d_slope[:, 1, 0] = xd * dtemp, yd * dtemp
    d_slope[:, 0, 1] = dtemp
    d_slope[:, 1, 2] = dtemp
    return Projection(uv, d_point, d_rot, d_io, d_slope, z)


def rotation_update(R: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``exp([w]) R`` for stacks of rotations (N, 3, 3) and rotation vectors (N, 3), radians."""
    theta = np.linalg.norm(w, axis=1)
    safe = np.where(theta < 1e-15, 1.0, theta)
    k = w / safe[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -k[:, 2], k[:, 1]
    K[:, 1, 0], K[:, 1, 2] = k[:, 2], -k[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -k[:, 1], k[:, 0]
    s = np.sin(theta)[:, None, None]
    c = (1 - np.cos(theta))[:, None, None]
    E = np.eye(3)[None] + s * K + c * np.einsum("nij,njk->nik", K, K)
    E[theta < 1e-15] = np.eye(3)
    return np.einsum("nij,njk->nik", E, R)


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3), radians, of a stack of rotation matrices."""
    return Rotation.from_matrix(R).as_rotvec()


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _project_observations(io, slopes, dtemp, R, C, X, image, point, jac, io_jac, uv, d_point, d_rot, d_io, d_slope,
                          depth, scale, Hpp):  # pragma: no cover
    """:func:`project` of observation ``m`` through image ``image[m]`` and point ``point[m]``, one loop. With
    ``scale`` (M,) (not empty), the pose and point Jacobians are scaled by it as they are formed, ``d_rot``
    (M, 2, 6) gets -d_point in its last 3 columns (the image's (w, C) block) and ``Hpp`` the points' 3 x 3
    blocks of J^T J, as :func:`aerocal.adjust.schur_kernels.jacobian_blocks` does in a pass of its own."""
    fused = len(scale) > 0
    f0, cx0, cy0, k1, k2, k3, p1, p2, b1, b2 = io[0], io[1], io[2], io[3], io[4], io[5], io[6], io[7], io[8], io[9]
    A = np.empty((2, 3))
    for m in range(len(image)):
        i, j = image[m], point[m]
        dt = dtemp[i]
        f = f0 + slopes[0] * dt
        cx = cx0 + slopes[1] * dt
        cy = cy0 + slopes[2] * dt
        d0, d1, d2 = X[j, 0] - C[i, 0], X[j, 1] - C[i, 1], X[j, 2] - C[i, 2]
        q0 = R[i, 0, 0] * d0 + R[i, 0, 1] * d1 + R[i, 0, 2] * d2
        q1 = R[i, 1, 0] * d0 + R[i, 1, 1] * d1 + R[i, 1, 2] * d2
        z = R[i, 2, 0] * d0 + R[i, 2, 1] * d1 + R[i, 2, 2] * d2
        x, y = q0 / z, q1 / z
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
        yd = y * radial + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
        fx = f + b1
        uv[m, 0] = cx + xd * fx + yd * b2
        uv[m, 1] = cy + yd * f
        depth[m] = z
        if not jac:
            continue
        dr = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        a = radial + 2 * x * x * dr + 6 * p1 * x + 2 * p2 * y
        b = 2 * x * y * dr + 2 * p1 * y + 2 * p2 * x
        c = 2 * x * y * dr + 2 * p2 * x + 2 * p1 * y
        e = radial + 2 * y * y * dr + 6 * p2 * y + 2 * p1 * x
        m00, m01 = fx * a + b2 * c, fx * b + b2 * e
        m10, m11 = f * c, f * e
        iz = 1.0 / z
        A[0, 0], A[0, 1], A[0, 2] = m00 * iz, m01 * iz, -(m00 * x + m01 * y) * iz
        A[1, 0], A[1, 1], A[1, 2] = m10 * iz, m11 * iz, -(m10 * x + m11 * y) * iz
        for u in range(2):
            for k in range(3):
                d_point[m, u, k] = A[u, 0] * R[i, 0, k] + A[u, 1] * R[i, 1, k] + A[u, 2] * R[i, 2, k]
            # dp/dw = -[p]_x with p = (q0, q1, z)
            d_rot[m, u, 0] = -A[u, 1] * z + A[u, 2] * q1
            d_rot[m, u, 1] = A[u, 0] * z - A[u, 2] * q0
            d_rot[m, u, 2] = -A[u, 0] * q1 + A[u, 1] * q0
        if fused:
            scale_observation_blocks(m, j, scale[m], d_rot, d_point, Hpp)
        if not io_jac:
            continue
        # d(uv)/d(IO) in PARAM_NAMES order and d(uv)/d(slopes of f, cx, cy), as :func:`project`
        d_io[m, 0, 0], d_io[m, 1, 0] = xd, yd
        d_io[m, 0, 1], d_io[m, 1, 1] = 1.0, 0.0
        d_io[m, 0, 2], d_io[m, 1, 2] = 0.0, 1.0
        rp = r2
        for k in range(3, 6):
            d_io[m, 0, k] = fx * x * rp + b2 * y * rp
            d_io[m, 1, k] = f * y * rp
            rp *= r2
        t1x, t1y = r2 + 2 * x * x, 2 * x * y
        t2x, t2y = 2 * x * y, r2 + 2 * y * y
        d_io[m, 0, 6], d_io[m, 1, 6] = fx * t1x + b2 * t1y, f * t1y
        d_io[m, 0, 7], d_io[m, 1, 7] = fx * t2x + b2 * t2y, f * t2y
        d_io[m, 0, 8], d_io[m, 1, 8] = xd, 0.0
        d_io[m, 0, 9], d_io[m, 1, 9] = yd, 0.0
        d_slope[m, 0, 0], d_slope[m, 1, 0] = xd * dt, yd * dt
        d_slope[m, 0, 1], d_slope[m, 1, 1] = dt, 0.0
        d_slope[m, 0, 2], d_slope[m, 1, 2] = 0.0, dt


def project_observations(io: np.ndarray, slopes: np.ndarray, dtemp_img: np.ndarray, R: np.ndarray, C: np.ndarray,
                         X: np.ndarray, image: np.ndarray, point: np.ndarray, jacobians: bool = True,
                         io_jacobians: bool = False, d_rot_out: np.ndarray | None = None,
                         d_point_out: np.ndarray | None = None, scale: np.ndarray | None = None,
                         Hpp: np.ndarray | None = None) -> Projection:
    """:func:`project` of the observations (``image``, ``point``) of a block: the same model and Jacobians
    (``d_io``, ``d_slope`` only with ``io_jacobians``, else empty), computed in one compiled loop that reads each
    observation's pose and point in place instead of gathering (M, 3, 3) rotations first.

    ``dtemp_img`` (N,): each image's temperature minus the reference; ``R`` (N, 3, 3), ``C`` (N, 3), ``X``
    (P, 3). It replaces :func:`project`'s batched numpy products, which were a large share of an adjustment
    iteration (``benchmarks/history/engine_measurements.md``); the agreement with :func:`project` is checked
    in ``tests/test_adjust_core.py``.
    ``d_rot_out`` (M, 2, k >= 3) and ``d_point_out`` (M, 2, 3), C-contiguous float64: arrays to write the
    Jacobians into (``d_rot`` into the first 3 columns of the last axis) instead of new ones, e.g. the
    adjustment's image blocks of the last iteration (:func:`aerocal.adjust.schur_kernels.jacobian_blocks`).
    ``scale`` (M,) and ``Hpp`` (P, 3, 3, zeroed by the caller), with ``d_rot_out`` (M, 2, 6): the loop also
    does :func:`aerocal.adjust.schur_kernels.jacobian_blocks`' work (the returned ``d_rot`` and ``d_point``
    are then the scaled blocks, ``d_rot_out`` the whole image block, ``Hpp`` summed): one pass over the
    observations less.

    Raises:
        ValueError: ``d_rot_out`` or ``d_point_out`` is not a C-contiguous float64 array of shape (M, 2, >= 3);
            ``scale`` without ``Hpp`` or with a ``d_rot_out`` not of shape (M, 2, 6).
    """
    M = len(image)
    uv, depth = np.empty((M, 2)), np.empty(M)
    shape = (M, 2, 3) if jacobians else (0, 2, 3)
    d_point = d_point_out if jacobians and d_point_out is not None else np.empty(shape)
    d_rot = d_rot_out if jacobians and d_rot_out is not None else np.empty(shape)
    for name, a in (("d_rot_out", d_rot), ("d_point_out", d_point)):
        if a.shape[:2] != shape[:2] or a.shape[2] < 3 or a.dtype != np.float64 or not a.flags.c_contiguous:
            raise ValueError(f"{name}: a C-contiguous float64 array ({M}, 2, >= 3) is needed, not {a.shape}")
    io_jacobians = io_jacobians and jacobians
    d_io = np.empty((M, 2, len(PARAM_NAMES)) if io_jacobians else (0, 2, len(PARAM_NAMES)))
    d_slope = np.empty((M, 2, 3) if io_jacobians else (0, 2, 3))
    f8 = np.float64
    fused = jacobians and scale is not None
    if fused and (Hpp is None or d_rot.shape[2] != 6):
        raise ValueError("scale needs Hpp and a d_rot_out of shape (M, 2, 6)")
    scale = np.ascontiguousarray(scale, dtype=f8) if fused else np.zeros(0)
    Hpp = Hpp if fused else np.zeros((0, 3, 3))
    _project_observations(np.ascontiguousarray(io, dtype=f8), np.ascontiguousarray(slopes, dtype=f8),
                          np.ascontiguousarray(dtemp_img, dtype=f8), np.ascontiguousarray(R, dtype=f8),
                          np.ascontiguousarray(C, dtype=f8), np.ascontiguousarray(X, dtype=f8),
                          np.ascontiguousarray(image, dtype=np.int64), np.ascontiguousarray(point, dtype=np.int64),
                          jacobians, io_jacobians, uv, d_point, d_rot, d_io, d_slope, depth, scale, Hpp)
    empty = np.zeros((M, 2, 0))
    if not jacobians:
        d_point = d_rot = empty
    if not io_jacobians:
        d_io = d_slope = empty
    return Projection(uv, d_point, d_rot[:, :, :3], d_io, d_slope, depth)
