"""Accuracy assessment of an adjusted block and its products.

Every result is a dataclass with ``to_dict()`` (JSON-ready: floats, lists, strings) for reports.

* :func:`point_residuals`: 3D residuals (estimated - surveyed) at check points or GCPs, per axis.
* :func:`triangulate_gcps`: multi-view triangulation of the GCP / check-point image measurements through
  the adjusted frames (full camera model), the "estimated" side of :func:`point_residuals`.
* :func:`mosaic_target_residuals`: planimetric residuals of targets located in the orthomosaic.
* :func:`reprojection_stats`: reprojection RMS overall, per image, per strip, and binned over the image.
* :func:`compare_dems`: difference of DEMs on a common grid (mean, std, median, NMAD, histogram,
  transects).
* :func:`loop_closure`: Daakir 2019's loop-closure error.
* :func:`accuracy_ratio`: achieved vs predicted accuracy (rho per axis, chi-square band, verdict).

Conventions: world E, N, Up metres in the flight's projected CRS; pixels with the origin at the
top-left corner of the top-left pixel; residuals are always *estimated minus reference*.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rasterio

from aerocal import tables
from aerocal.camera import correct_measurements
from aerocal.targets import locate_targets

AXES = ("E", "N", "U")

#: Verdicts of :func:`accuracy_ratio`.
VERDICT_OK = "the model explains the data"
VERDICT_SYSTEMATIC = "something systematic is unmodelled"
VERDICT_PESSIMISTIC = "the predicted accuracy is pessimistic (sigmas too large)"


def _f(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def _rms(a: np.ndarray, axis=None) -> np.ndarray:
    return np.sqrt(np.mean(np.square(a), axis=axis))


def nmad(x: np.ndarray, median: float | None = None) -> float:
    """Normalised median absolute deviation, 1.4826 median(|x - median(x)|) (a robust std); ``median``: x's median
    where the caller has it already (a DSM difference's 10^7 cells are not partitioned again for it)."""
    x = np.asarray(x, dtype=float)
    if not x.size:
        return float("nan")
    centre = np.median(x) if median is None else median
    return float(1.4826 * np.median(np.abs(x - centre), overwrite_input=True))  # the deviations are a copy


# ============================================================================================ points
@dataclass
class PointResiduals:
    """Residuals estimated - reference at named points, metres, per axis E, N, U."""

    ids: list[str]
    residuals: np.ndarray  #: (n, 3) or (n, 2) for planimetric residuals
    positions: np.ndarray  #: (n, 3) or (n, 2) reference positions
    role: str = "check"

    @property
    def n(self) -> int:
        return len(self.ids)

    def rmse(self) -> np.ndarray:
        return _rms(self.residuals, axis=0) if self.n else np.full(self.residuals.shape[1], np.nan)

    def to_dict(self) -> dict:
        k = self.residuals.shape[1]
        axes = AXES[:k]
        r = self.residuals
        d = {
            "role": self.role, "n": self.n,
            "mean_m": dict(zip(axes, (_f(v) for v in r.mean(axis=0)), strict=True)) if self.n else {},
            "std_m": dict(zip(axes, (_f(v) for v in r.std(axis=0, ddof=1)), strict=True)) if self.n > 1 else {},
            "rmse_m": dict(zip(axes, (_f(v) for v in self.rmse()), strict=True)) if self.n else {},
            "max_abs_m": dict(zip(axes, (_f(v) for v in np.abs(r).max(axis=0)), strict=True)) if self.n else {},
            "rmse_horizontal_m": _f(np.sqrt(np.mean(np.sum(r[:, :2] ** 2, axis=1)))) if self.n else None,
            "points": [{"id": i, "position": [float(v) for v in p], "residual_m": [_f(v) for v in e]}
                       for i, p, e in zip(self.ids, self.positions, r, strict=True)],
        }
        return d


def _gcp_arrays(gcps, role: str | None) -> tuple[list[str], np.ndarray, np.ndarray]:
    g = tables.validate(gcps, "gcps")
    ids = g.column("gcp_id").to_pylist()
    roles = g.column("role").to_pylist()
    xyz = np.column_stack([g.column(c).to_numpy() for c in ("X", "Y", "Z")])
    sig = np.column_stack([g.column(c).to_numpy() for c in ("sigma_x", "sigma_y", "sigma_z")])
    keep = [i for i, r in enumerate(roles) if role is None or r == role]
    return [ids[i] for i in keep], xyz[keep], sig[keep]


def point_residuals(estimated: Mapping[str, Sequence[float]], gcps, role: str | None = "check") -> PointResiduals:
    """Residuals ``estimated[id] - surveyed`` (3D, metres) for the ``gcps`` table rows of ``role``
    (``"check"``, ``"control"`` or None for all) that have an estimate."""
    ids, xyz, _ = _gcp_arrays(gcps, role)
    keep = [k for k, i in enumerate(ids) if i in estimated and np.all(np.isfinite(estimated[i]))]
    est = np.array([estimated[ids[k]] for k in keep], dtype=float).reshape(-1, 3)
    return PointResiduals(ids=[ids[k] for k in keep], residuals=est - xyz[keep], positions=xyz[keep],
                          role=role or "all")


def intersect_rays(origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Least-squares intersection of rays (the point minimising the summed squared distances to them).

    Closed form ``(sum (I - d d^T)) X = sum (I - d d^T) o``; the linear (midpoint) triangulation that
    pycolmap's ``TriangulateMultiViewPoint`` also solves, here with the full Brown model for the rays.
    """
    o = np.asarray(origins, dtype=float)
    d = np.asarray(directions, dtype=float)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    A = P.sum(axis=0)
    b = np.einsum("kij,kj->i", P, o)
    return np.linalg.solve(A, b)


def view_counts(frames: Sequence, X: np.ndarray,
                first_hit: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                tolerance_m: float = 0.0) -> np.ndarray:
    """How many of ``frames`` (:class:`aerocal.products.mosaic.FrameGeometry`) see each world point ``X`` (..., 3)
    (metres): in front of the camera and inside its image, the denominator of a dense surface's completeness.

    Without ``first_hit``, occlusions are not tested: the count of frames whose image holds the point, hidden or not.
    With it, a frame counts only where the point is not hidden from it: ``first_hit(origins, directions)`` (both
    (M, 3), unit directions, world metres) gives the distance from each origin to the first surface along its ray
    (``inf`` where none; the reference surface's, as :func:`aerocal.simulate.raycast.intersect_dsm` gives the
    simulator's), and a frame sees the point unless its ray from the projection centre meets that surface more
    than ``tolerance_m`` short of it (a wall, a roof's edge in between)."""
    X = np.asarray(X, dtype=float)
    flat = X.reshape(-1, 3)
    count = np.zeros(len(flat), dtype=int)
    for f in frames:
        uv = f.project(flat)
        seen = np.all(np.isfinite(uv), axis=-1) & f.camera.in_image(uv)
        if first_hit is not None and seen.any():
            idx = np.flatnonzero(seen)
            C = np.asarray(f.C, dtype=float)
            ray = flat[idx] - C
            dist = np.linalg.norm(ray, axis=1)
            hit = np.asarray(first_hit(np.broadcast_to(C, ray.shape).copy(), ray / dist[:, None]), dtype=float)
            seen[idx[hit < dist - tolerance_m]] = False
        count += seen
    return count.reshape(X.shape[:-1])


def _frame_rays(frame, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays of pixels ``uv`` (N, 2) in a :class:`aerocal.products.mosaic.FrameGeometry`."""
    uv = np.atleast_2d(np.asarray(uv, dtype=float))
    if frame.thermal_model is not None:
        uv = correct_measurements(frame.camera, uv, frame.temperature, frame.thermal_model)
    d_cam = np.column_stack([frame.camera.unproject(uv), np.ones(len(uv))])
    d = d_cam @ np.asarray(frame.R_cw)
    return np.broadcast_to(np.asarray(frame.C, dtype=float), d.shape), d


def triangulate_gcps(frames: Sequence, gcp_observations) -> dict[str, np.ndarray]:
    """Triangulate every GCP / check point seen in at least two frames: {gcp_id: (3,) world metres}.

    ``frames``: :class:`aerocal.products.mosaic.FrameGeometry` (adjusted poses with their per-image IO).
    """
    obs = tables.validate(gcp_observations, "gcp_observations")
    by_id = {f.image_id: f for f in frames}
    gid = obs.column("gcp_id").to_pylist()
    iid = obs.column("image_id").to_numpy()
    uv = np.column_stack([obs.column("x").to_numpy(), obs.column("y").to_numpy()])
    out: dict[str, np.ndarray] = {}
    for name in sorted(set(gid)):
        rows = [k for k, g in enumerate(gid) if g == name and int(iid[k]) in by_id]
        if len(rows) < 2:
            continue
        o, d = zip(*(_frame_rays(by_id[int(iid[k])], uv[k]) for k in rows), strict=True)
        out[name] = intersect_rays(np.vstack(o), np.vstack(d))
    return out


def mosaic_target_residuals(
    mosaic_path: str | Path, gcps, role: str | None = "check", window_px: int = 11,
) -> PointResiduals:
    """Planimetric residuals (E, N, metres) of signalised targets located in an orthomosaic.

    Each target is searched around its surveyed E, N with :func:`aerocal.targets.locate_targets`
    (intensity-weighted centroid of the bright disc; ``window_px`` must be smaller than the target's dark
    square in mosaic pixels). Nodata pixels in the window are replaced by the window's median. Targets
    not found (outside the mosaic, no blob) are left out; ``n`` says how many were found.

    Raises:
        ValueError: ``mosaic_path`` is not a readable GeoTIFF, or the mosaic is not north-up.
    """
    ids, xyz, _ = _gcp_arrays(gcps, role)
    mosaic_path = Path(mosaic_path)
    try:
        src = rasterio.open(mosaic_path)
    except rasterio.errors.RasterioIOError as exc:
        raise ValueError(f"{mosaic_path}: not a readable GeoTIFF ({exc})") from exc
    half = window_px // 2 + 2
    found_ids, res, pos = [], [], []
    with src:
        t = src.transform
        if abs(t.b) > 0 or abs(t.d) > 0:
            raise ValueError(f"{mosaic_path}: the mosaic is not north-up; locate targets on a north-up grid")
        for name, p in zip(ids, xyz, strict=True):
            col, row = (p[0] - t.c) / t.a, (p[1] - t.f) / t.e
            c0, r0 = int(np.floor(col)) - half, int(np.floor(row)) - half
            if c0 < 0 or r0 < 0 or c0 + 2 * half + 1 > src.width or r0 + 2 * half + 1 > src.height:
                continue
            win = rasterio.windows.Window(c0, r0, 2 * half + 1, 2 * half + 1)
            data = src.read(window=win, masked=True).astype(float)
            img = data.mean(axis=0)
            mask = np.ma.getmaskarray(img)
            if mask.all():
                continue
            patch = np.where(mask, np.ma.median(img), np.ma.getdata(img))
            uv = locate_targets(patch, np.array([[col - c0, row - r0]]), window_px=window_px)[0]
            if not np.all(np.isfinite(uv)):
                continue
            e, n = t.c + (uv[0] + c0) * t.a, t.f + (uv[1] + r0) * t.e
            found_ids.append(name)
            res.append((e - p[0], n - p[1]))
            pos.append(p[:2])
    return PointResiduals(ids=found_ids, residuals=np.asarray(res, dtype=float).reshape(-1, 2),
                          positions=np.asarray(pos, dtype=float).reshape(-1, 2), role=role or "all")


# ============================================================================================ reprojection
@dataclass
class BinnedResiduals:
    """Mean residual vectors on a grid over the image plane (pixels). ``mean`` (rows, cols, 2), ``count``
    (rows, cols); bin (r, c) spans x in [c w/cols, (c+1) w/cols), y likewise."""

    width: int
    height: int
    mean: np.ndarray
    count: np.ndarray

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        rows, cols = self.count.shape
        x = (np.arange(cols) + 0.5) * self.width / cols
        y = (np.arange(rows) + 0.5) * self.height / rows
        return np.meshgrid(x, y)

    def to_dict(self) -> dict:
        m = np.where(self.count[..., None] > 0, self.mean, np.nan)
        return {"width": self.width, "height": self.height, "bins": list(self.count.shape),
                "mean_px": [[[_f(v) for v in cell] for cell in row] for row in m],
                "count": self.count.tolist()}

    @classmethod
    def from_dict(cls, d: Mapping) -> BinnedResiduals:
        """The inverse of :meth:`to_dict` (empty bins, ``None`` there, get a zero mean and count 0).

        Raises:
            ValueError: ``d['bins']`` disagrees with the shape of ``d['count']``.
        """
        count = np.asarray(d["count"], dtype=np.int64)
        mean = np.array([[[np.nan if v is None else float(v) for v in cell] for cell in row]
                         for row in d["mean_px"]], dtype=float).reshape(*count.shape, 2)
        mean[count == 0] = 0.0
        if tuple(d.get("bins", count.shape)) != count.shape:
            raise ValueError(f"binned residuals: bins {d['bins']} but counts of shape {count.shape}")
        return cls(width=int(d["width"]), height=int(d["height"]), mean=np.nan_to_num(mean), count=count)


def bin_residuals(xy: np.ndarray, residuals: np.ndarray, width: int, height: int,
                  bins: tuple[int, int] = (6, 8)) -> BinnedResiduals:
    """Mean residual (N, 2) per bin of image position ``xy`` (N, 2) on a ``bins`` = (rows, cols) grid."""
    xy = np.asarray(xy, dtype=float)
    r = np.asarray(residuals, dtype=float)
    rows, cols = bins
    bc = np.clip((xy[:, 0] / width * cols).astype(int), 0, cols - 1)
    br = np.clip((xy[:, 1] / height * rows).astype(int), 0, rows - 1)
    flat = br * cols + bc
    count = np.bincount(flat, minlength=rows * cols)
    sx = np.bincount(flat, weights=r[:, 0], minlength=rows * cols)
    sy = np.bincount(flat, weights=r[:, 1], minlength=rows * cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.stack([sx / count, sy / count], axis=-1)
    mean[count == 0] = 0.0
    return BinnedResiduals(width=int(width), height=int(height), mean=mean.reshape(rows, cols, 2),
                           count=count.reshape(rows, cols))


@dataclass
class ReprojectionStats:
    """Reprojection residual statistics (pixels): overall, per image, per strip, binned over the image."""

    n: int
    rms_px: float
    rms_xy_px: tuple[float, float]
    per_image: dict[int, dict]
    per_strip: dict[int, dict]
    binned: BinnedResiduals | None = None

    def to_dict(self) -> dict:
        return {
            "n": self.n, "rms_px": _f(self.rms_px), "rms_xy_px": [_f(v) for v in self.rms_xy_px],
            "per_image": {str(k): v for k, v in self.per_image.items()},
            "per_strip": {str(k): v for k, v in self.per_strip.items()},
            "binned": self.binned.to_dict() if self.binned is not None else None,
        }


def reprojection_stats(
    observations, residuals: np.ndarray, images=None, image_size: tuple[int, int] | None = None,
    bins: tuple[int, int] = (6, 8),
) -> ReprojectionStats:
    """Statistics of reprojection ``residuals`` (N, 2 pixels, projected - measured) aligned with the rows of
    an ``observations`` table. ``images`` (an images table) gives strips and image size; RMS is the root
    mean square of the residual vector length.

    Raises:
        ValueError: ``residuals`` is not of shape (N, 2), one row per row of ``observations``.
    """
    obs = tables.validate(observations, "observations")
    r = np.asarray(residuals, dtype=float)
    if r.shape != (obs.num_rows, 2):
        raise ValueError(f"reprojection_stats: residuals have shape {r.shape}, expected ({obs.num_rows}, 2) "
                         "(one row per observation)")
    iid = obs.column("image_id").to_numpy()
    xy = np.column_stack([obs.column("x").to_numpy(), obs.column("y").to_numpy()])
    sq = np.sum(r * r, axis=1)

    def group(keys: np.ndarray) -> dict[int, dict]:
        out = {}
        for k in np.unique(keys):
            m = keys == k
            out[int(k)] = {"n": int(m.sum()), "rms_px": _f(np.sqrt(sq[m].mean())),
                           "mean_px": [_f(v) for v in r[m].mean(axis=0)]}
        return out

    per_strip: dict[int, dict] = {}
    binned = None
    if images is not None:
        im = tables.validate(images, "images")
        strip_of = dict(zip(im.column("image_id").to_pylist(), im.column("strip").to_pylist(), strict=True))
        strips = np.array([strip_of.get(int(i)) if strip_of.get(int(i)) is not None else -1 for i in iid])
        per_strip = group(strips)
        if image_size is None and im.num_rows:
            image_size = (int(im.column("width")[0].as_py()), int(im.column("height")[0].as_py()))
    if image_size is not None and len(r):
        binned = bin_residuals(xy, r, image_size[0], image_size[1], bins)
    return ReprojectionStats(
        n=len(r), rms_px=float(np.sqrt(sq.mean())) if len(r) else float("nan"),
        rms_xy_px=tuple(float(v) for v in _rms(r, axis=0)) if len(r) else (float("nan"), float("nan")),
        per_image=group(iid), per_strip=per_strip, binned=binned,
    )


# ============================================================================================ DEMs
@dataclass
class DemDifference:
    """Tested minus reference heights on the tested DEM's grid (metres).

    ``difference`` (rows, cols) NaN outside the compared cells; the statistics cover those cells.
    """

    n: int
    mean: float
    std: float
    median: float
    nmad: float
    rmse: float
    histogram_edges: np.ndarray
    histogram_counts: np.ndarray
    difference: np.ndarray = field(repr=False)
    extent: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  #: (west, south, east, north)
    transects: list[dict] = field(default_factory=list)
    selection: str = "all cells with both heights"

    def to_dict(self) -> dict:
        return {
            "n": self.n, "mean_m": _f(self.mean), "std_m": _f(self.std), "median_m": _f(self.median),
            "nmad_m": _f(self.nmad), "rmse_m": _f(self.rmse), "selection": self.selection,
            "extent": list(self.extent),
            "histogram": {"edges_m": [float(v) for v in self.histogram_edges],
                          "counts": [int(v) for v in self.histogram_counts]},
            "transects": self.transects,
        }

    def within(self, mask: np.ndarray, selection: str) -> DemDifference:
        """The same comparison on the compared cells where ``mask`` (bool, the grid's shape) holds, described by
        ``selection``: :func:`compare_dems` with that mask too, without sampling the reference again (a city's
        DSM has 8 * 10^7 cells). The differences are those of :attr:`difference` (float32: within 10^-7 of
        their value); no transects.

        Raises:
            ValueError: ``mask`` has another shape than the grid."""
        if mask.shape != self.difference.shape:
            raise ValueError(f"DemDifference.within: mask has shape {mask.shape}, the grid {self.difference.shape}")
        grid = np.where(mask, self.difference, np.float32(np.nan))
        d = grid[np.isfinite(grid)].astype(float)
        return _difference_of(d, grid, self.extent, [], selection)


def compare_dems(
    dem,
    reference: Callable[[np.ndarray, np.ndarray], np.ndarray] | object,
    mask: np.ndarray | None = None,
    bins: int | np.ndarray = 41,
    histogram_range_m: tuple[float, float] | None = None,
    transects: Sequence[tuple[tuple[float, float], tuple[float, float]]] = (),
    selection: str | None = None,
) -> DemDifference:
    """Difference of DEMs on a common grid: ``dem`` (an :class:`aerocal.products.dsm.Dsm`) minus ``reference``.

    The common grid is ``dem``'s; ``reference`` is a Dsm or any ``height_at(E, N)`` callable, sampled
    bilinearly at the cell centres. ``mask`` (bool, dem's shape) restricts the compared cells (e.g.
    ``dem.distance_m <= 2`` for cells measured by tie points); describe it in ``selection``.
    ``transects``: ((E0, N0), (E1, N1)) lines sampled every cell: distance, tested and reference heights.

    Raises:
        ValueError: ``mask`` has another shape than ``dem``.
    """
    ref = reference.height_at if hasattr(reference, "height_at") else reference
    if mask is not None and mask.shape != dem.shape:
        raise ValueError(f"compare_dems: mask has shape {mask.shape}, the DEM {dem.shape}")
    # a block of rows at a time (Dsm.centre_blocks): a city's dense DSM has 76 M cells
    out = np.full(dem.shape, np.nan, dtype=np.float32)
    parts = []
    grid = getattr(reference, "heights_on", None)  # a Dsm: its heights on the grid in one compiled pass
    for rows, e, n in dem.centre_blocks():
        diff = dem.heights[rows].astype(float) - (grid(e, n) if grid is not None else ref(*np.meshgrid(e, n)))
        ok = np.isfinite(diff)
        if mask is not None:
            ok &= mask[rows]
        parts.append(diff[ok])
        out[rows][ok] = parts[-1]
    d = np.concatenate(parts) if parts else np.zeros(0)
    del parts
    lines = []
    for (e0, n0), (e1, n1) in transects:
        length = float(np.hypot(e1 - e0, n1 - n0))
        s = np.linspace(0.0, length, max(2, int(length / dem.cell_m) + 1))
        t = s / max(length, 1e-12)
        ee, nn = e0 + t * (e1 - e0), n0 + t * (n1 - n0)
        lines.append({"start": [float(e0), float(n0)], "end": [float(e1), float(n1)],
                      "distance_m": s.tolist(), "height_m": [_f(v) for v in dem.height_at(ee, nn)],
                      "reference_m": [_f(v) for v in ref(ee, nn)]})
    return _difference_of(d, out, tuple(float(v) for v in dem.bounds()), lines,
                          selection or ("all cells with both heights" if mask is None else "masked cells"), bins,
                          histogram_range_m)


def _difference_of(d: np.ndarray, grid: np.ndarray, extent: tuple[float, ...], transects: list[dict], selection: str,
                   bins: int | np.ndarray = 41, histogram_range_m: tuple[float, float] | None = None
                   ) -> DemDifference:
    """The :class:`DemDifference` of the compared cells' differences ``d`` (1-D, metres; reordered in place),
    ``grid`` the differences on the DEM's grid (NaN elsewhere)."""
    empty = d.size == 0
    # the order-free figures first; then the median of d itself, reordered in place, and the NMAD about it (a
    # city's 7 * 10^7 cells: the seven medians of copies before were most of the report's time)
    mean = float("nan") if empty else float(d.mean())
    std = float("nan") if d.size < 2 else float(d.std(ddof=1))
    rmse = float("nan") if empty else float(np.sqrt(np.mean(d * d)))
    median = spread = float("nan")
    if not empty:
        median = float(np.median(d, overwrite_input=True))
        spread = nmad(d, median)
    if histogram_range_m is None and not empty:
        lim = max(4.0 * spread, 1e-3)
        histogram_range_m = (median - lim, median + lim)
    counts, edges = np.histogram(d, bins=bins, range=histogram_range_m)
    return DemDifference(n=int(d.size), mean=mean, std=std, median=median, nmad=spread, rmse=rmse,
                         histogram_edges=edges, histogram_counts=counts, difference=grid, extent=extent,
                         transects=transects, selection=selection)


# ============================================================================================ loop closure
@dataclass
class LoopClosure:
    """Daakir 2019's loop-closure error: for tie points seen in the first and in the last pair of a
    closed loop, the distance between their triangulation from the first pair and from the last pair."""

    first_pair: tuple[int, int]
    last_pair: tuple[int, int]
    n: int
    mean_vector_m: np.ndarray
    mean_m: float
    median_m: float
    rms_m: float
    max_m: float

    def to_dict(self) -> dict:
        return {"first_pair": list(self.first_pair), "last_pair": list(self.last_pair), "n": self.n,
                "mean_vector_m": [_f(v) for v in self.mean_vector_m], "mean_m": _f(self.mean_m),
                "median_m": _f(self.median_m), "rms_m": _f(self.rms_m), "max_m": _f(self.max_m)}


def loop_closure(frames: Sequence, observations, first_pair: tuple[int, int],
                 last_pair: tuple[int, int]) -> LoopClosure:
    """Loop-closure error from tie points (``observations`` table, pixels) seen in all four images.

    ``frames``: :class:`aerocal.products.mosaic.FrameGeometry` of the adjusted block.

    Raises:
        ValueError: an image of ``first_pair`` or ``last_pair`` has no frame in ``frames``.
    """
    obs = tables.validate(observations, "observations")
    by_id = {f.image_id: f for f in frames}
    for i in (*first_pair, *last_pair):
        if i not in by_id:
            raise ValueError(f"loop_closure: image {i} has no adjusted frame")
    iid = obs.column("image_id").to_numpy()
    tid = obs.column("track_id").to_numpy()
    uv = np.column_stack([obs.column("x").to_numpy(), obs.column("y").to_numpy()])
    lookup: dict[int, dict[int, np.ndarray]] = {}
    for i in (*first_pair, *last_pair):
        m = iid == i
        lookup[i] = dict(zip(tid[m].tolist(), uv[m], strict=True))
    common = sorted(set.intersection(*(set(lookup[i]) for i in (*first_pair, *last_pair))))
    d = []
    for t in common:
        pts = []
        for pair in (first_pair, last_pair):
            o, dirs = zip(*(_frame_rays(by_id[i], lookup[i][t]) for i in pair), strict=True)
            pts.append(intersect_rays(np.vstack(o), np.vstack(dirs)))
        d.append(pts[1] - pts[0])
    v = np.asarray(d, dtype=float).reshape(-1, 3)
    dist = np.linalg.norm(v, axis=1)
    nan = float("nan")
    return LoopClosure(
        first_pair=tuple(first_pair), last_pair=tuple(last_pair), n=len(v),
        mean_vector_m=v.mean(axis=0) if len(v) else np.full(3, np.nan),
        mean_m=float(dist.mean()) if len(v) else nan, median_m=float(np.median(dist)) if len(v) else nan,
        rms_m=float(np.sqrt(np.mean(dist**2))) if len(v) else nan, max_m=float(dist.max()) if len(v) else nan,
    )


# ============================================================================================ achieved/predicted
@dataclass
class AccuracyRatio:
    """Achieved vs predicted accuracy at check points, per axis.

    ``rho = RMSE / sqrt(mean predicted variance)``; ``chi2_mean = mean(e^2 / sigma^2)``. With n points a
    correct model puts rho inside ``band`` = [1 - 1.96/sqrt(2n), 1 + 1.96/sqrt(2n)] (95 %) and chi2_mean
    inside [1 - 1.96 sqrt(2/n), 1 + 1.96 sqrt(2/n)].
    """

    n: int
    axes: tuple[str, ...]
    rho: np.ndarray
    chi2_mean: np.ndarray
    rmse_m: np.ndarray
    predicted_sigma_m: np.ndarray  #: sqrt(mean predicted variance) per axis
    band: tuple[float, float]
    chi2_band: tuple[float, float]
    verdict: str
    verdict_per_axis: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for k in ("rho", "chi2_mean", "rmse_m", "predicted_sigma_m"):
            d[k] = dict(zip(self.axes, (_f(v) for v in getattr(self, k)), strict=True))
        d["axes"] = list(self.axes)
        d["band"] = list(self.band)
        d["chi2_band"] = list(self.chi2_band)
        return d


def accuracy_ratio(residuals: np.ndarray, predicted_sigma: np.ndarray,
                   axes: Sequence[str] | None = None) -> AccuracyRatio:
    """Compare residuals (n, k metres) with their predicted standard deviations (n, k, or (k,) for all
    points): the full prediction (adjustment covariance scaled by the variance factor, plus the survey
    variance). The verdict: any axis above the band -> :data:`VERDICT_SYSTEMATIC`; else any below ->
    :data:`VERDICT_PESSIMISTIC`; else :data:`VERDICT_OK`.

    Raises:
        ValueError: a predicted sigma is not positive, or fewer than 2 check points (rows of ``residuals``).
    """
    e = np.atleast_2d(np.asarray(residuals, dtype=float))
    s = np.broadcast_to(np.asarray(predicted_sigma, dtype=float), e.shape)
    if np.any(~(s > 0)):
        raise ValueError("accuracy_ratio: predicted sigmas must be positive")
    n, k = e.shape
    if n < 2:
        raise ValueError(f"accuracy_ratio: need at least 2 check points, got {n}")
    axes = tuple(axes) if axes is not None else AXES[:k]
    rmse = _rms(e, axis=0)
    pred = np.sqrt(np.mean(s * s, axis=0))
    rho = rmse / pred
    chi2 = np.mean((e / s) ** 2, axis=0)
    half = 1.96 / np.sqrt(2.0 * n)
    band = (1.0 - half, 1.0 + half)
    half2 = 1.96 * np.sqrt(2.0 / n)
    per_axis = {}
    for a, r in zip(axes, rho, strict=True):
        per_axis[a] = VERDICT_SYSTEMATIC if r > band[1] else VERDICT_PESSIMISTIC if r < band[0] else VERDICT_OK
    verdicts = set(per_axis.values())
    verdict = (VERDICT_SYSTEMATIC if VERDICT_SYSTEMATIC in verdicts
               else VERDICT_PESSIMISTIC if VERDICT_PESSIMISTIC in verdicts else VERDICT_OK)
    return AccuracyRatio(n=n, axes=axes, rho=rho, chi2_mean=chi2, rmse_m=rmse, predicted_sigma_m=pred,
                         band=band, chi2_band=(max(0.0, 1.0 - half2), 1.0 + half2), verdict=verdict,
                         verdict_per_axis=per_axis)
