"""Precision of an adjustment: IO covariance, correlation, significance and check-point covariance.

* IO covariance: the IO / thermal-slope block of the inverse of the reduced camera-side normal matrix
  (the Schur complement of the points, so the points are marginalised, not held fixed), times the
  a-posteriori variance factor sigma0^2.
* Check points are kept out of the adjustment and triangulated afterwards with the adjusted cameras;
  their *marginal* covariance propagates the camera covariance through the triangulation::

      X = X(obs, cams),  G = (A^T W A)^-1 A^T W
      Cov(X) = sigma0^2 [ (A^T W A)^-1 + G B Cov(cams) B^T G^T ] + diag(survey sigma^2)

  with ``A`` = d(uv)/dX and ``B`` = d(uv)/d(camera unknowns). Conditioning on fixed cameras (the first
  term alone, as pycolmap's ``get_point_cov``) is 1.5-7x too optimistic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from aerocal.adjust.problem import Block
from aerocal.adjust.projection import THERMAL_PARAMS, project
from aerocal.adjust.solver import Solution
from aerocal.adjust.triangulate import pixels_to_rays, refine_points, triangulate_linear
from aerocal.camera import PARAM_NAMES


def global_names(solution: Solution) -> list[str]:
    """Names of the global unknowns: free IO parameters, then thermal slopes as ``d<name>/dT``."""
    lay = solution.layout
    return [PARAM_NAMES[i] for i in lay.io_free] + [f"d{THERMAL_PARAMS[i]}/dT" for i in lay.slope_free]


def global_covariance(solution: Solution, scale: bool = True) -> np.ndarray:
    """Covariance of the free IO parameters and thermal slopes (order of :func:`global_names`)."""
    ng = solution.layout.n_global
    cov = solution.cov_camera[:ng, :ng]
    cov = 0.5 * (cov + cov.T)  # the Schur-complement inverse is symmetric only to rounding
    return cov * solution.sigma0**2 if scale else cov


def correlation(cov: np.ndarray) -> np.ndarray:
    """Correlation matrix of a covariance matrix."""
    s = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    c = cov / s[:, None] / s[None, :]
    return 0.5 * (c + c.T)


def t_values(estimates: np.ndarray, references: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """|estimate - reference| / sigma (the t statistic of a parameter against its reference value)."""
    return np.abs(np.asarray(estimates) - np.asarray(references)) / np.maximum(np.asarray(sigmas), 1e-300)


def t_critical(dof: int, level: float = 0.95) -> float:
    """Two-sided critical value of Student's t at ``level`` (1.96 for large ``dof``)."""
    return float(stats.t.ppf(0.5 + level / 2.0, max(dof, 1)))


@dataclass
class CheckPoints:
    """Check points triangulated after the adjustment (local frame) with their marginal covariance."""

    ids: list[str]
    xyz: np.ndarray  # (K, 3) triangulated, local metres (NaN when seen in fewer than 2 images)
    cov: np.ndarray  # (K, 3, 3) marginal covariance of the triangulated point, without survey variance
    n_obs: np.ndarray  # (K,)


def triangulate_check_points(block: Block, solution: Solution, scale: bool = True) -> CheckPoints:
    """Triangulate every check point with the adjusted cameras and propagate the camera covariance."""
    st, lay = solution.state, solution.layout
    K = len(block.check_ids)
    out_xyz = np.full((K, 3), np.nan)
    out_cov = np.full((K, 3, 3), np.nan)
    n_obs = np.bincount(block.check_point, minlength=K) if K else np.zeros(0, int)
    if K == 0 or len(block.check_point) == 0:
        return CheckPoints(block.check_ids, out_xyz, out_cov, n_obs)
    dt_img = np.nan_to_num(block.temperature - solution.t0) if lay.slope_free else np.zeros(block.n_images)
    i, k = block.check_image, block.check_point
    rays = pixels_to_rays(st.io, st.slopes, dt_img[i], st.R[i], block.check_uv)
    X0, ok = triangulate_linear(k, K, st.C[i], rays)
    use = ok[k]
    X, _ = refine_points(
        st.io,
        st.slopes,
        dt_img[i][use],
        st.R[i][use],
        st.C[i][use],
        k[use],
        block.check_uv[use],
        block.check_sigma_px[use],
        np.nan_to_num(X0),
    )
    pr = project(st.io, st.slopes, dt_img[i], st.R[i], st.C[i], X[k])
    s = block.check_sigma_px
    A = pr.d_point / s[:, None, None]
    ng = lay.n_global
    Bg = (
        np.concatenate([pr.d_io[:, :, lay.io_free], pr.d_slope[:, :, lay.slope_free]], axis=2)
        / s[:, None, None]
    )
    Bi = np.concatenate([pr.d_rot, -pr.d_point], axis=2) / s[:, None, None]
    var0 = solution.sigma0**2 if scale else 1.0
    # the camera term G B Cov(cams) B^T G^T = V^T S^-1 V with V = (G B)^T scattered onto the camera-side
    # unknowns: three solves per check point, all in one multi-column solve, instead of the ~6 x (images
    # seeing it) columns of the inverse
    good = np.flatnonzero(ok)
    n_camera = solution.cov_camera.shape[0]
    V = np.zeros((n_camera, 3 * len(good)))
    Ninv_all = np.zeros((len(good), 3, 3))
    for q, kk in enumerate(good):
        sel = np.flatnonzero(k == kk)
        Ak = A[sel].reshape(-1, 3)
        cols = np.concatenate([np.arange(ng), lay.image_cols(i[sel]).ravel()])
        Bk = np.zeros((2 * len(sel), len(cols)))
        if ng:
            Bk[:, :ng] = Bg[sel].reshape(-1, ng)
        for m in range(len(sel)):
            Bk[2 * m : 2 * m + 2, ng + 6 * m : ng + 6 * m + 6] = Bi[sel[m]]
        Ninv = np.linalg.inv(Ak.T @ Ak)
        GB = Ninv @ Ak.T @ Bk  # (3, len(cols))
        np.add.at(V[:, 3 * q : 3 * q + 3], cols, GB.T)  # an image seen twice adds up
        Ninv_all[q] = Ninv
    SV = solution.cov_camera.solve(V)
    for q, kk in enumerate(good):
        v, sv = V[:, 3 * q : 3 * q + 3], SV[:, 3 * q : 3 * q + 3]
        cam = v.T @ sv
        out_cov[kk] = var0 * (Ninv_all[q] + 0.5 * (cam + cam.T))
        out_xyz[kk] = X[kk]
    return CheckPoints(block.check_ids, out_xyz, out_cov, n_obs)


def rho_per_axis(errors: np.ndarray, variances: np.ndarray) -> np.ndarray:
    """Per axis rho = RMSE / sqrt(mean predicted variance) over the rows with finite values."""
    e = np.asarray(errors, dtype=float)
    v = np.asarray(variances, dtype=float)
    good = np.isfinite(e).all(axis=1) & np.isfinite(v).all(axis=1)
    if not good.any():
        return np.full(e.shape[1], np.nan)
    return np.sqrt(np.mean(e[good] ** 2, axis=0)) / np.sqrt(np.mean(v[good], axis=0))


def rho_band(n: int, level: float = 0.95) -> tuple[float, float]:
    """Approximate chi-square band of rho for ``n`` check points: 1 -+ z / sqrt(2n)."""
    z = float(stats.norm.ppf(0.5 + level / 2.0))
    return 1.0 - z / np.sqrt(2.0 * n), 1.0 + z / np.sqrt(2.0 * n)
