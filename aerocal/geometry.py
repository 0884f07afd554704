"""Rotations with named conventions, coordinate frames and similarity transforms.

Frames
------
* **World**: a right-handed projected frame, x = easting, y = northing, z = up (metres). Flights live in
  a UTM zone chosen from their centre (:func:`utm_crs_for`); a local frame subtracts an origin.
* **Camera**: x right, y down, z along the viewing direction (COLMAP/OpenCV).
* Stored rotations are **world-to-camera** (``R_cw``, COLMAP's ``cam_from_world``): ``p_cam = R_cw
  (p_world - C)`` with ``C`` the projection centre.

Sensor conventions converted here (each function names its convention):

* :func:`opk_to_R_cw`: photogrammetric omega-phi-kappa (degrees), ``M = R_z(kappa) R_y(phi) R_x(omega)``
  applied as in Kraus, image space x right / y up / z towards the sky. Zero angles give a nadir camera
  whose image top points north.
* :func:`dji_gimbal_to_R_cw`: DJI gimbal roll/pitch/yaw (degrees; yaw clockwise from north, pitch -90 =
  nadir, aerospace Z-Y-X order in a north-east-down frame; the optical axis is the gimbal's x axis).
* :func:`body_rpy_to_R_cw`: aircraft roll/pitch/yaw (senseFly autopilot, degrees, Z-Y-X, NED), camera
  rigidly mounted looking down with the image top towards the nose.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from pyproj import CRS, Transformer
from pyproj.exceptions import CRSError
from scipy.spatial.transform import Rotation

# ----------------------------------------------------------------------------- elementary rotations
#: Rotation from north-east-down to east-north-up axes (its own inverse).
R_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ypr_ned(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Aerospace Z-Y-X rotation body -> NED (``C_nb = R_z(yaw) R_y(pitch) R_x(roll)``)."""
    y, p, r = np.radians([yaw_deg, pitch_deg, roll_deg])
    return rot_z(y) @ rot_y(p) @ rot_x(r)


# camera axes expressed in the frames they are mounted in (columns = camera x, y, z)
_CAM_IN_GIMBAL = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # optical axis = gimbal x
_CAM_IN_BODY_NADIR = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # optical axis = body z
_OPK_TO_CAM = np.diag([1.0, -1.0, -1.0])  # image space (y up, z to the sky) -> camera (y down, z forward)


def opk_to_R_cw(omega_deg: float, phi_deg: float, kappa_deg: float) -> np.ndarray:
    """Omega-phi-kappa (degrees, photogrammetric, world axes E-N-U) -> world-to-camera rotation."""
    o, p, k = np.radians([omega_deg, phi_deg, kappa_deg])
    m = (rot_x(o) @ rot_y(p) @ rot_z(k)).T  # Kraus: M = R_kappa R_phi R_omega as world->image
    return _OPK_TO_CAM @ m


def R_cw_to_opk(R_cw: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`opk_to_R_cw` (degrees)."""
    m = _OPK_TO_CAM @ np.asarray(R_cw)
    a = m.T  # = R_x(o) R_y(p) R_z(k)
    phi = np.arcsin(np.clip(a[0, 2], -1.0, 1.0))
    omega = np.arctan2(-a[1, 2], a[2, 2])
    kappa = np.arctan2(-a[0, 1], a[0, 0])
    return tuple(float(v) for v in np.degrees([omega, phi, kappa]))  # type: ignore[return-value]


def dji_gimbal_to_R_cw(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """DJI ``GimbalRollDegree/GimbalPitchDegree/GimbalYawDegree`` -> world(ENU)-to-camera rotation."""
    R_wc = R_ENU_FROM_NED @ ypr_ned(yaw_deg, pitch_deg, roll_deg) @ _CAM_IN_GIMBAL
    return R_wc.T


def R_cw_to_dji_gimbal(R_cw: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`dji_gimbal_to_R_cw`: (roll, pitch, yaw) in degrees.

    At pitch = -90 (exact nadir) roll and yaw are not separable; the decomposition returned then still
    reproduces ``R_cw`` exactly.
    """
    C_nb = R_ENU_FROM_NED @ np.asarray(R_cw).T @ _CAM_IN_GIMBAL.T
    pitch = -np.arcsin(np.clip(C_nb[2, 0], -1.0, 1.0))
    roll = np.arctan2(C_nb[2, 1], C_nb[2, 2])
    yaw = np.arctan2(C_nb[1, 0], C_nb[0, 0])
    if abs(np.cos(pitch)) < 1e-9:  # gimbal lock: put everything into yaw
        roll = 0.0
        yaw = np.arctan2(-C_nb[0, 1], C_nb[1, 1])
    return tuple(float(v) for v in np.degrees([roll, pitch, yaw]))  # type: ignore[return-value]


def body_rpy_to_R_cw(
    roll_deg: float, pitch_deg: float, yaw_deg: float, mount: np.ndarray | None = None
) -> np.ndarray:
    """Aircraft roll/pitch/yaw (senseFly XMP, degrees) -> world(ENU)-to-camera rotation.

    ``mount`` is an optional camera-in-body rotation replacing the default nadir mount (image top to
    the nose); a boresight misalignment is a small rotation applied to it.
    """
    cam_in_body = _CAM_IN_BODY_NADIR if mount is None else np.asarray(mount)
    R_wc = R_ENU_FROM_NED @ ypr_ned(yaw_deg, pitch_deg, roll_deg) @ cam_in_body
    return R_wc.T


def R_cw_to_body_rpy(R_cw: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`body_rpy_to_R_cw` with the default mount: (roll, pitch, yaw) in degrees."""
    C_nb = R_ENU_FROM_NED @ np.asarray(R_cw).T @ _CAM_IN_BODY_NADIR.T
    pitch = -np.arcsin(np.clip(C_nb[2, 0], -1.0, 1.0))
    roll = np.arctan2(C_nb[2, 1], C_nb[2, 2])
    yaw = np.arctan2(C_nb[1, 0], C_nb[0, 0])
    return tuple(float(v) for v in np.degrees([roll, pitch, yaw]))  # type: ignore[return-value]


def nadir_R_cw(heading_deg: float) -> np.ndarray:
    """A level nadir camera whose image top points along ``heading_deg`` (clockwise from north)."""
    return body_rpy_to_R_cw(0.0, 0.0, heading_deg)


CONVENTIONS = {
    "opk": opk_to_R_cw,  # (omega, phi, kappa)
    "dji_gimbal": lambda r, p, y: dji_gimbal_to_R_cw(r, p, y),  # (roll, pitch, yaw)
    "body_rpy": lambda r, p, y: body_rpy_to_R_cw(r, p, y),  # (roll, pitch, yaw)
}


def attitude_to_R_cw(convention: str, a: float, b: float, c: float) -> np.ndarray:
    """Dispatch on a convention name stored in the ``images`` table (see :data:`CONVENTIONS`).

    Raises:
        ValueError: ``convention`` is not a key of :data:`CONVENTIONS` (the message lists the valid ones).
    """
    if convention not in CONVENTIONS:
        raise ValueError(f"attitude convention {convention!r} unknown; valid: {', '.join(CONVENTIONS)}")
    return CONVENTIONS[convention](a, b, c)


# ----------------------------------------------------------------------------- rotation utilities
def small_rotation(angles_rad: np.ndarray) -> np.ndarray:
    """Rotation matrix for a rotation vector (radians), exact (Rodrigues)."""
    v = np.asarray(angles_rad, dtype=float)
    theta = np.linalg.norm(v)
    if theta < 1e-15:
        return np.eye(3)
    k = v / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def rotvec_from_matrix(R: np.ndarray) -> np.ndarray:
    """Rotation vector (radians) of a rotation matrix."""
    return Rotation.from_matrix(R).as_rotvec()


def quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (or a stack of them)."""
    q = Rotation.from_matrix(R).as_quat()  # x, y, z, w
    q = np.roll(q, 1, axis=-1)
    return np.where(q[..., :1] < 0, -q, q)


def matrix_from_quat_wxyz(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    return Rotation.from_quat(np.roll(q, -1, axis=-1)).as_matrix()


def world_to_camera(R_cw: np.ndarray, C: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Points (N, 3) in the world frame -> camera frame, ``R_cw (X - C)``."""
    return (np.asarray(X, dtype=float) - np.asarray(C, dtype=float)) @ np.asarray(R_cw).T


# ----------------------------------------------------------------------------- CRS helpers
def utm_crs_for(lon: float, lat: float) -> str:
    """The WGS84 UTM zone CRS (``"EPSG:326zz"`` north, ``"EPSG:327zz"`` south) holding (lon, lat).

    Raises:
        ValueError: (lon, lat) is outside the UTM domain (longitude -180..180, latitude -80..84 degrees).
    """
    if not (-180.0 <= lon <= 180.0 and -80.0 <= lat <= 84.0):
        raise ValueError(f"position lon={lon}, lat={lat} is outside the UTM domain")
    zone = int((lon + 180.0) // 6.0) % 60 + 1
    return f"EPSG:{32600 + zone if lat >= 0 else 32700 + zone}"


@lru_cache(maxsize=64)
def transformer(src: str, dst: str):
    """A cached pyproj transformer (always x=lon/easting, y=lat/northing order)."""
    return Transformer.from_crs(src, dst, always_xy=True)


def lonlat_to_projected(lon, lat, crs: str):
    """WGS84 lon/lat (degrees) -> easting/northing (metres) in ``crs``."""
    return transformer("EPSG:4326", crs).transform(lon, lat)


def projected_to_lonlat(x, y, crs: str):
    return transformer(crs, "EPSG:4326").transform(x, y)


def validate_crs(crs: str) -> str:
    """Return ``crs`` if pyproj knows it and it is projected in metres; else raise naming it."""
    try:
        c = CRS.from_user_input(crs)
    except CRSError as exc:
        raise ValueError(f"unknown CRS {crs!r}: {exc}") from exc
    if not c.is_projected:
        raise ValueError(f"CRS {crs!r} is not projected; use a projected CRS in metres (e.g. a UTM zone)")
    return crs


@dataclass(frozen=True)
class LocalFrame:
    """A local frame: world coordinates minus ``origin`` (metres), for well-conditioned adjustment."""

    crs: str
    origin: tuple[float, float, float]

    def to_local(self, X: np.ndarray) -> np.ndarray:
        return np.asarray(X, dtype=float) - np.asarray(self.origin)

    def to_world(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x, dtype=float) + np.asarray(self.origin)


# ----------------------------------------------------------------------------- similarity transforms
@dataclass(frozen=True)
class Similarity:
    """``y = scale R x + t``: a 7-parameter 3D similarity."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x, dtype=float) @ self.R.T + self.t

    def inverse(self) -> Similarity:
        Rt = self.R.T
        return Similarity(1.0 / self.scale, Rt, -(Rt @ self.t) / self.scale)


def estimate_similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None,
                        with_scale: bool = True) -> Similarity:
    """Least-squares similarity ``dst ~ s R src + t`` (Umeyama 1991), optionally weighted.

    Needs at least three non-collinear points.

    Raises:
        ValueError: ``src`` and ``dst`` are not both (N, 3) arrays of the same shape with N >= 3, or the points are
            collinear.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"need matching (N>=3, 3) point arrays, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mu_s = w @ src
    mu_d = w @ dst
    a = src - mu_s
    b = dst - mu_d
    cov = (b * w[:, None]).T @ a
    U, S, Vt = np.linalg.svd(cov)
    if S[1] < 1e-12 * max(S[0], 1e-300):
        raise ValueError("points are collinear: a similarity is not determined")
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_s = float(w @ np.sum(a * a, axis=1))
    scale = float(np.trace(np.diag(S) @ D) / var_s) if with_scale else 1.0
    t = mu_d - scale * R @ mu_s
    return Similarity(scale, R, t)
