"""Camera models: the Brown frame-camera model in pixels, its inverse, and thermal IO models.

Conventions
-----------
* Camera frame: x right, y down, z along the viewing direction (COLMAP, OpenCV).
* Pixel coordinates: origin at the top-left *corner* of the top-left pixel, x right, y down; the centre
  of the first pixel is (0.5, 0.5). This is COLMAP's convention. OpenCV puts the centre of the first
  pixel at (0, 0): subtract 0.5 when handing points to OpenCV, add 0.5 when taking them back.
* Brown model, written as Agisoft Metashape (and PhotoScan, which Conte 2018 used) writes it, with the
  principal point in absolute pixels instead of an offset from the image centre::

      x, y   = X / Z, Y / Z                      (normalised, undistorted)
      r2     = x^2 + y^2
      radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
      x'     = x radial + p1 (r2 + 2 x^2) + 2 p2 x y
      y'     = y radial + p2 (r2 + 2 y^2) + 2 p1 x y
      u      = cx + x' (f + b1) + y' b2           (b1 affinity, b2 skew, both pixels)
      v      = cy + y' f

  Note that OpenCV's and COLMAP's p1/p2 are Metashape's p2/p1 (swapped); :func:`to_pycolmap` and the
  exporters in :mod:`aerocal.formats` do the swap.
* Units: f, cx, cy, b1, b2 in pixels; k1, k2, k3, p1, p2 dimensionless (normalised coordinates).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

#: Names of the interior-orientation parameters, in the order of :meth:`Camera.params`.
PARAM_NAMES: tuple[str, ...] = ("f", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "b1", "b2")

#: Units of each parameter, for reports.
PARAM_UNITS: dict[str, str] = {
    "f": "px", "cx": "px", "cy": "px", "k1": "1", "k2": "1", "k3": "1",
    "p1": "1", "p2": "1", "b1": "px", "b2": "px",
}


#: Rows per pass of the element-wise distortion maths on long inputs (:meth:`Camera.distort`,
#: :meth:`Camera.undistort`): the temporaries of a pass stay in the cache. What makes one long pass slow is
#: not the arithmetic but every temporary streamed through memory and faulted in afresh
#: (``benchmarks/history/engine_measurements.md``).
ROW_CHUNK = 1 << 14


def _by_rows(fn, xy: np.ndarray) -> np.ndarray:
    """``fn`` (N, 2) -> (N, 2) applied to ``xy`` by :data:`ROW_CHUNK` rows."""
    out = np.empty_like(xy)
    for s in range(0, len(xy), ROW_CHUNK):
        out[s:s + ROW_CHUNK] = fn(xy[s:s + ROW_CHUNK])
    return out


@dataclass(frozen=True)
class Camera:
    """A frame camera: image size and Brown-model interior orientation, all in pixels.

    ``pixel_size_mm`` is only needed to report focal length and drifts in millimetres or micrometres.
    """

    width: int
    height: int
    f: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    b1: float = 0.0
    b2: float = 0.0
    pixel_size_mm: float | None = None

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not np.isfinite(self.f) or self.f <= 0:
            raise ValueError(f"focal length must be a positive number of pixels, got {self.f}")

    # ----------------------------------------------------------------- construction / parameters
    @classmethod
    def from_mm(
        cls, width: int, height: int, focal_mm: float, pixel_size_um: float, **kwargs: float
    ) -> Camera:
        """A camera with its principal point at the image centre, from focal length and pixel pitch."""
        pix_mm = pixel_size_um / 1000.0
        kwargs.setdefault("cx", width / 2.0)
        kwargs.setdefault("cy", height / 2.0)
        return cls(width=width, height=height, f=focal_mm / pix_mm, pixel_size_mm=pix_mm, **kwargs)

    def params(self) -> np.ndarray:
        """The IO parameters as a vector in the order of :data:`PARAM_NAMES`."""
        return np.array([getattr(self, n) for n in PARAM_NAMES], dtype=float)

    def with_params(self, values: np.ndarray | dict[str, float]) -> Camera:
        """A copy with some or all parameters replaced (a vector in PARAM_NAMES order, or a dict)."""
        if not isinstance(values, dict):
            values = dict(zip(PARAM_NAMES, np.asarray(values, dtype=float).tolist(), strict=True))
        return dataclasses.replace(self, **{k: float(v) for k, v in values.items()})

    def replace(self, **kwargs: float) -> Camera:
        return dataclasses.replace(self, **kwargs)

    @property
    def focal_mm(self) -> float | None:
        return None if self.pixel_size_mm is None else self.f * self.pixel_size_mm

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        """A camera from the dict :meth:`to_dict` returns.

        Raises:
            ValueError: ``d`` has a key that is not a camera field (the message lists the valid ones).
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown camera field(s) {sorted(unknown)}; valid: {sorted(names)}")
        return cls(**d)

    def corners(self) -> np.ndarray:
        """The four image corners in pixels (top-left corner convention), shape (4, 2)."""
        w, h = float(self.width), float(self.height)
        return np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])

    @property
    def corner_radius(self) -> float:
        """Distance (pixels) from the principal point to the farthest image corner."""
        return float(np.max(np.hypot(*(self.corners() - [self.cx, self.cy]).T)))

    # ----------------------------------------------------------------- distortion in normalised space
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Undistorted normalised coordinates (N, 2) -> distorted normalised coordinates (N, 2)."""
        xy = np.asarray(xy, dtype=float)
        if xy.ndim == 2 and len(xy) > ROW_CHUNK:
            return _by_rows(self._distort, xy)
        return self._distort(xy)

    def _distort(self, xy: np.ndarray) -> np.ndarray:
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        xd = x * radial + self.p1 * (r2 + 2 * x * x) + 2 * self.p2 * x * y
        yd = y * radial + self.p2 * (r2 + 2 * y * y) + 2 * self.p1 * x * y
        return np.stack([xd, yd], axis=-1)

    def _distort_jacobian(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        r2 = x * x + y * y
        radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3))
        dradial_dr2 = self.k1 + r2 * (2 * self.k2 + 3 * self.k3 * r2)
        dxd_dx = radial + 2 * x * x * dradial_dr2 + self.p1 * 6 * x + 2 * self.p2 * y
        dxd_dy = 2 * x * y * dradial_dr2 + self.p1 * 2 * y + 2 * self.p2 * x
        dyd_dx = 2 * x * y * dradial_dr2 + self.p2 * 2 * x + 2 * self.p1 * y
        dyd_dy = radial + 2 * y * y * dradial_dr2 + self.p2 * 6 * y + 2 * self.p1 * x
        return dxd_dx, dxd_dy, dyd_dx, dyd_dy

    def undistort(self, xy_distorted: np.ndarray, iterations: int = 20, tol: float = 1e-15) -> np.ndarray:
        """Distorted normalised coordinates -> undistorted, by Newton iteration on the 2x2 Jacobian.

        Newton rather than the fixed-point iteration of OpenCV's ``undistortPoints``: on a strongly
        distorted corner (k1 = -0.3) the fixed point needs > 50 iterations to reach 1e-6 px and can
        diverge; Newton converges in 4-6 (measured against cv2.undistortPoints with 50 iterations and
        eps 1e-12 in tests/test_camera.py).
        """
        target = np.asarray(xy_distorted, dtype=float)
        shape = target.shape
        target = target.reshape(-1, 2)
        if len(target) > ROW_CHUNK:
            return _by_rows(lambda t: self.undistort(t, iterations, tol), target).reshape(shape)
        x = target[:, 0].copy()
        y = target[:, 1].copy()
        # each iteration on the points still moving only, not on all of them until the slowest converged;
        # long inputs go by ROW_CHUNK rows
        # A point beyond where the distortion polynomial can be inverted (far outside the image of a strongly
        # distorted camera) diverges: it stops at NaN, without overflow warnings, and is iterated no more.
        act = np.arange(len(x))
        for _ in range(iterations):
            xa, ya = x[act], y[act]
            with np.errstate(over="ignore", invalid="ignore"):
                d = self.distort(np.stack([xa, ya], axis=-1))
                ex = d[:, 0] - target[act, 0]
                ey = d[:, 1] - target[act, 1]
                a, b, c, e = self._distort_jacobian(xa, ya)
                det = a * e - b * c
                det = np.where(np.abs(det) < 1e-12, 1e-12, det)
                dx = (e * ex - b * ey) / det
                dy = (-c * ex + a * ey) / det
                x[act] = xa - dx
                y[act] = ya - dy
                step = np.abs(dx) + np.abs(dy)
            lost = ~np.isfinite(step)
            x[act[lost]] = y[act[lost]] = np.nan
            act = act[~lost & ~(step < tol)]
            if not len(act):
                break
        return np.stack([x, y], axis=-1).reshape(shape)

    # ----------------------------------------------------------------- pixels <-> normalised
    def normalised_to_pixels(self, xy_distorted: np.ndarray) -> np.ndarray:
        """Distorted normalised coordinates -> pixels (applies f, principal point, b1, b2)."""
        xy = np.asarray(xy_distorted, dtype=float)
        u = self.cx + xy[..., 0] * (self.f + self.b1) + xy[..., 1] * self.b2
        v = self.cy + xy[..., 1] * self.f
        return np.stack([u, v], axis=-1)

    def pixels_to_normalised(self, uv: np.ndarray) -> np.ndarray:
        """Pixels -> distorted normalised coordinates (inverse of :meth:`normalised_to_pixels`)."""
        uv = np.asarray(uv, dtype=float)
        yd = (uv[..., 1] - self.cy) / self.f
        xd = (uv[..., 0] - self.cx - yd * self.b2) / (self.f + self.b1)
        return np.stack([xd, yd], axis=-1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Points in the camera frame (N, 3), metres -> pixels (N, 2). Points behind give NaN."""
        p = np.asarray(points_cam, dtype=float)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[..., :2] / np.where(z > 0, z, np.nan)[..., None]
        return self.normalised_to_pixels(self.distort(xy))

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> undistorted normalised coordinates (N, 2): the ray is (x, y, 1)."""
        return self.undistort(self.pixels_to_normalised(uv))

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> unit viewing rays in the camera frame (N, 3)."""
        xy = self.unproject(uv)
        r = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return r / np.linalg.norm(r, axis=-1, keepdims=True)

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Pixels -> pixels of the ideal pinhole camera with the same f, cx, cy (no distortion, b1, b2)."""
        xy = self.unproject(uv)
        return np.stack([self.cx + self.f * xy[..., 0], self.cy + self.f * xy[..., 1]], axis=-1)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels inside the image (with an optional margin in pixels)."""
        uv = np.asarray(uv, dtype=float)
        return (
            (uv[..., 0] >= margin)
            & (uv[..., 0] <= self.width - margin)
            & (uv[..., 1] >= margin)
            & (uv[..., 1] <= self.height - margin)
        )

    def param_jacobian(self, xy: np.ndarray) -> np.ndarray:
        """d(u, v)/d(params) at undistorted normalised coordinates ``xy`` (N, 2) -> (N, 2, 10).

        Order of :data:`PARAM_NAMES`. Used by the subset planner and the diagnosis.
        """
        xy = np.asarray(xy, dtype=float)
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        d = self.distort(xy)
        xd, yd = d[..., 0], d[..., 1]
        fx = self.f + self.b1
        J = np.zeros(xy.shape[:-1] + (2, len(PARAM_NAMES)))
        J[..., 0, 0], J[..., 1, 0] = xd, yd  # f
        J[..., 0, 1] = 1.0  # cx
        J[..., 1, 2] = 1.0  # cy
        for i, power in ((3, 1), (4, 2), (5, 3)):  # k1, k2, k3
            J[..., 0, i] = fx * x * r2**power
            J[..., 1, i] = self.f * y * r2**power
        # p1: x' += p1 (r2 + 2x^2), y' += 2 p1 x y ; p2: x' += 2 p2 x y, y' += p2 (r2 + 2y^2)
        J[..., 0, 6] = fx * (r2 + 2 * x * x) + self.b2 * 2 * x * y
        J[..., 1, 6] = self.f * 2 * x * y
        J[..., 0, 7] = fx * 2 * x * y + self.b2 * (r2 + 2 * y * y)
        J[..., 1, 7] = self.f * (r2 + 2 * y * y)
        for i in (3, 4, 5):
            J[..., 0, i] += self.b2 * y * r2 ** (i - 2)
        J[..., 0, 8] = xd  # b1
        J[..., 0, 9] = yd  # b2
        return J


# --------------------------------------------------------------------------- pycolmap conversion
def to_pycolmap(camera: Camera, camera_id: int = 1, drop_skew: bool = False):
    """Convert to a ``pycolmap.Camera`` of model FULL_OPENCV.

    Mapping: fx = f + b1, fy = f, cx, cy unchanged (both conventions put the origin at the top-left
    corner of the image), k1, k2, k3 unchanged, OpenCV p1 = our p2 and OpenCV p2 = our p1 (swapped),
    k4..k6 = 0. Skew ``b2`` has no counterpart in any COLMAP model: a non-zero b2 raises unless
    ``drop_skew=True``, which discards it (and is then not a faithful conversion).
    """
    # lazy: pycolmap is slow to import and every engine module imports aerocal.camera
    import pycolmap

    if camera.b2 != 0.0 and not drop_skew:
        raise ValueError(
            f"camera has skew b2={camera.b2:g} px, which COLMAP cannot represent; pass drop_skew=True to discard it"
        )
    params = [
        camera.f + camera.b1, camera.f, camera.cx, camera.cy,
        camera.k1, camera.k2, camera.p2, camera.p1, camera.k3, 0.0, 0.0, 0.0,
    ]
    return pycolmap.Camera(
        model="FULL_OPENCV", width=camera.width, height=camera.height, params=params, camera_id=camera_id
    )


def from_pycolmap(cam, pixel_size_mm: float | None = None) -> Camera:
    """Convert a ``pycolmap.Camera`` (pinhole, radial and OpenCV families) to :class:`Camera`.

    Models with parameters our Brown model cannot hold (fisheye, thin-prism, rational k4..k6 != 0)
    raise ``ValueError`` naming the model and the parameter.
    """
    name = cam.model.name if hasattr(cam.model, "name") else str(cam.model)
    p = [float(v) for v in cam.params]
    w, h = int(cam.width), int(cam.height)
    base = {"width": w, "height": h, "pixel_size_mm": pixel_size_mm}
    if name == "SIMPLE_PINHOLE":
        return Camera(f=p[0], cx=p[1], cy=p[2], **base)
    if name == "PINHOLE":
        return Camera(f=p[1], b1=p[0] - p[1], cx=p[2], cy=p[3], **base)
    if name == "SIMPLE_RADIAL":
        return Camera(f=p[0], cx=p[1], cy=p[2], k1=p[3], **base)
    if name == "RADIAL":
        return Camera(f=p[0], cx=p[1], cy=p[2], k1=p[3], k2=p[4], **base)
    if name == "OPENCV":
        fx, fy, cx, cy, k1, k2, q1, q2 = p
        return Camera(f=fy, b1=fx - fy, cx=cx, cy=cy, k1=k1, k2=k2, p1=q2, p2=q1, **base)
    if name == "FULL_OPENCV":
        fx, fy, cx, cy, k1, k2, q1, q2, k3, k4, k5, k6 = p
        if any(abs(v) > 0 for v in (k4, k5, k6)):
            raise ValueError(f"FULL_OPENCV camera has rational terms k4..k6={k4, k5, k6}; Brown cannot hold them")
        return Camera(f=fy, b1=fx - fy, cx=cx, cy=cy, k1=k1, k2=k2, k3=k3, p1=q2, p2=q1, **base)
    raise ValueError(f"cannot convert COLMAP camera model {name}; supported: SIMPLE_PINHOLE, PINHOLE, "
                     "SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV")


# --------------------------------------------------------------------------- thermal IO models
@dataclass(frozen=True)
class LinearThermalModel:
    """IO(T) = IO(T0) + dIO/dT (T - T0) for focal length and principal point.

    Slopes in pixels per degree Celsius. ``valid_range`` is the temperature range (degC) the model was
    estimated over; :meth:`check_range` says when a temperature falls outside it.
    """

    t0: float
    df_dt: float = 0.0
    dcx_dt: float = 0.0
    dcy_dt: float = 0.0
    valid_range: tuple[float, float] | None = None

    def camera_at(self, camera: Camera, temperature: float) -> Camera:
        """The camera's IO at ``temperature`` given ``camera`` holds IO(T0)."""
        dt = float(temperature) - self.t0
        return camera.replace(
            f=camera.f + self.df_dt * dt, cx=camera.cx + self.dcx_dt * dt, cy=camera.cy + self.dcy_dt * dt
        )

    def correct(self, camera: Camera, uv: np.ndarray, temperature: np.ndarray | float) -> np.ndarray:
        """Map image measurements taken at ``temperature`` to where the camera at T0 would have seen them.

        Daakir 2019's workflow: the tie points and GCP measurements are corrected, not the pixels.
        Exact for this model: distortion acts in normalised coordinates, which the focal length and the
        principal point do not change.
        """
        uv = np.asarray(uv, dtype=float)
        dt = np.broadcast_to(np.asarray(temperature, dtype=float) - self.t0, uv.shape[:-1])
        f_t = camera.f + self.df_dt * dt
        cx_t = camera.cx + self.dcx_dt * dt
        cy_t = camera.cy + self.dcy_dt * dt
        yd = (uv[..., 1] - cy_t) / f_t
        xd = (uv[..., 0] - cx_t - yd * camera.b2) / (f_t + camera.b1)
        return camera.normalised_to_pixels(np.stack([xd, yd], axis=-1))

    def check_range(self, temperatures: np.ndarray) -> str | None:
        """A message when ``temperatures`` leave the valid range, else ``None``."""
        if self.valid_range is None:
            return None
        t = np.asarray(temperatures, dtype=float)
        lo, hi = self.valid_range
        if t.size and (np.nanmin(t) < lo or np.nanmax(t) > hi):
            return (f"temperatures {np.nanmin(t):.1f}-{np.nanmax(t):.1f} degC leave the thermal model's "
                    f"valid range {lo:.1f}-{hi:.1f} degC")
        return None

    def to_dict(self) -> dict:
        return {"kind": "linear", **dataclasses.asdict(self)}


@dataclass(frozen=True)
class SimilarityThermalModel:
    """Daakir 2019, Eq. 2: a 4-parameter 2D similarity per temperature, interpolated in T.

    For each tabulated temperature T_i the correction is
    ``p_C = c + t(T) + k(T) R(theta(T)) (p_R - c)`` with ``c`` the image centre (pixels), translation
    ``t`` (pixels), scale ``k`` and angle ``theta`` (radians). Between tabulated temperatures the four
    parameters are interpolated linearly, outside they are extrapolated from the nearest two
    (Daakir: "a correction function is interpolated"). The reference temperature is where
    t = 0, k = 1, theta = 0.
    """

    temperatures: tuple[float, ...]
    tx: tuple[float, ...]
    ty: tuple[float, ...]
    scale: tuple[float, ...]
    theta: tuple[float, ...]
    centre: tuple[float, float]

    def _params(self, temperature: np.ndarray) -> tuple[np.ndarray, ...]:
        t = np.asarray(self.temperatures, dtype=float)
        order = np.argsort(t)
        t = t[order]
        out = []
        for values in (self.tx, self.ty, self.scale, self.theta):
            v = np.asarray(values, dtype=float)[order]
            if len(t) == 1:
                out.append(np.full_like(temperature, v[0], dtype=float))
                continue
            idx = np.clip(np.searchsorted(t, temperature) - 1, 0, len(t) - 2)
            w = (temperature - t[idx]) / (t[idx + 1] - t[idx])
            out.append(v[idx] + w * (v[idx + 1] - v[idx]))
        return tuple(out)

    def correct(self, uv: np.ndarray, temperature: np.ndarray | float) -> np.ndarray:
        uv = np.asarray(uv, dtype=float)
        temp = np.broadcast_to(np.asarray(temperature, dtype=float), uv.shape[:-1])
        tx, ty, k, th = self._params(temp)
        c = np.asarray(self.centre)
        d = uv - c
        cos, sin = np.cos(th), np.sin(th)
        x = c[0] + tx + k * (cos * d[..., 0] - sin * d[..., 1])
        y = c[1] + ty + k * (sin * d[..., 0] + cos * d[..., 1])
        return np.stack([x, y], axis=-1)

    @staticmethod
    def fit_one(uv_observed: np.ndarray, uv_reference: np.ndarray, centre: tuple[float, float]) -> tuple:
        """Least-squares similarity mapping observed -> reference points: (tx, ty, scale, theta)."""
        c = np.asarray(centre)
        a = np.asarray(uv_observed, dtype=float) - c
        b = np.asarray(uv_reference, dtype=float) - c
        n = len(a)
        A = np.zeros((2 * n, 4))
        A[0::2] = np.column_stack([np.ones(n), np.zeros(n), a[:, 0], -a[:, 1]])
        A[1::2] = np.column_stack([np.zeros(n), np.ones(n), a[:, 1], a[:, 0]])
        sol, *_ = np.linalg.lstsq(A, b.reshape(-1), rcond=None)
        tx, ty, kc, ks = sol
        return float(tx), float(ty), float(np.hypot(kc, ks)), float(np.arctan2(ks, kc))

    def to_dict(self) -> dict:
        return {"kind": "similarity", **dataclasses.asdict(self)}


@dataclass(frozen=True)
class PolynomialThermalModel:
    """Daakir 2019, Eq. 3: displacement as a polynomial in temperature and image position.

    ``M(x, y, T) = sum_{k=1..3} sum_{i,j} a_kij (T - T0)^k x^i y^j`` for each image axis, with
    ``x, y`` the pixel position relative to ``centre`` divided by ``norm`` (conditioning). The paper
    sums i, j from 1 to 4; we sum from 0 to ``degree`` so that a translation and terms in x or y alone
    are included (Eq. 2's similarity is then a special case), and we use T - T0 so that M(T0) = 0.
    ``coefficients`` has shape (2, 3, degree + 1, degree + 1).
    The correction subtracts M: ``p_C = p_R - M(p_R, T)``.
    """

    t0: float
    centre: tuple[float, float]
    norm: float
    coefficients: tuple = field(default=())
    degree: int = 2

    def _design(self, uv: np.ndarray, temperature: np.ndarray) -> np.ndarray:
        c = np.asarray(self.centre)
        x = (uv[..., 0] - c[0]) / self.norm
        y = (uv[..., 1] - c[1]) / self.norm
        dt = temperature - self.t0
        cols = []
        for k in range(1, 4):
            for i in range(self.degree + 1):
                for j in range(self.degree + 1):
                    cols.append(dt**k * x**i * y**j)
        return np.stack(cols, axis=-1)

    def displacement(self, uv: np.ndarray, temperature: np.ndarray | float) -> np.ndarray:
        uv = np.asarray(uv, dtype=float)
        temp = np.broadcast_to(np.asarray(temperature, dtype=float), uv.shape[:-1])
        A = self._design(uv, temp)
        coef = np.asarray(self.coefficients, dtype=float).reshape(2, -1)
        return np.stack([A @ coef[0], A @ coef[1]], axis=-1)

    def correct(self, uv: np.ndarray, temperature: np.ndarray | float) -> np.ndarray:
        return np.asarray(uv, dtype=float) - self.displacement(uv, temperature)

    @classmethod
    def fit(
        cls,
        uv: np.ndarray,
        temperature: np.ndarray,
        displacement: np.ndarray,
        t0: float,
        centre: tuple[float, float],
        norm: float,
        degree: int = 2,
    ) -> PolynomialThermalModel:
        """Least-squares fit from sampled displacements (pixels) at positions ``uv`` and temperatures."""
        model = cls(t0=t0, centre=centre, norm=norm, degree=degree)
        A = model._design(np.asarray(uv, dtype=float), np.asarray(temperature, dtype=float))
        d = np.asarray(displacement, dtype=float)
        cx, *_ = np.linalg.lstsq(A, d[:, 0], rcond=None)
        cy, *_ = np.linalg.lstsq(A, d[:, 1], rcond=None)
        shape = (3, degree + 1, degree + 1)
        coeffs = np.stack([cx.reshape(shape), cy.reshape(shape)])
        return cls(t0=t0, centre=centre, norm=norm, degree=degree, coefficients=_as_tuple(coeffs))

    def to_dict(self) -> dict:
        return {"kind": "polynomial", **dataclasses.asdict(self)}


def _as_tuple(a: np.ndarray) -> tuple:
    return tuple(_as_tuple(x) for x in a) if a.ndim > 1 else tuple(float(v) for v in a)


ThermalModel = LinearThermalModel | SimilarityThermalModel | PolynomialThermalModel


def thermal_model_from_dict(d: dict) -> ThermalModel:
    """Inverse of the models' ``to_dict``; an unknown ``kind`` raises naming the valid ones."""
    d = dict(d)
    kind = d.pop("kind", None)
    classes = {"linear": LinearThermalModel, "similarity": SimilarityThermalModel,
               "polynomial": PolynomialThermalModel}
    if kind not in classes:
        raise ValueError(f"thermal model kind {kind!r} unknown; valid: {', '.join(classes)}")
    if kind == "linear" and d.get("valid_range") is not None:
        d["valid_range"] = tuple(d["valid_range"])
    if kind in ("similarity", "polynomial"):
        d = {k: tuple(v) if isinstance(v, list) and k != "coefficients" else v for k, v in d.items()}
        if kind == "polynomial":
            d["coefficients"] = _as_tuple(np.asarray(d.get("coefficients", ()), dtype=float))
    return classes[kind](**d)


def correct_measurements(
    camera: Camera, uv: np.ndarray, temperature: np.ndarray | float, model: ThermalModel | None
) -> np.ndarray:
    """Correct image measurements (pixels) taken at ``temperature`` to the model's reference state.

    With ``model=None`` the measurements are returned unchanged (a copy).
    """
    if model is None:
        return np.array(uv, dtype=float, copy=True)
    if isinstance(model, LinearThermalModel):
        return model.correct(camera, uv, temperature)
    return model.correct(uv, temperature)
