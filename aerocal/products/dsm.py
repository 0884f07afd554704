"""Digital surface model (DSM) from the adjusted block's tie points.

Grid
----
A north-up grid in the flight's projected CRS (E, N, Up metres). Row 0 is the northern edge, column 0
the western edge; cell ``(row, col)`` is centred on ``E = west + (col + 0.5) cell``,
``N = north - (row + 0.5) cell`` (GDAL's "pixel is area" convention, as rasterio writes it). Heights
are float32 metres; cells without a value are NaN in memory and :data:`NODATA` on disk.

Method (what :func:`dsm_from_points` does)
------------------------------------------
1. **Outlier rejection by local median**: each point is compared with the median height of its
   ``outlier_neighbours`` nearest neighbours (within ``outlier_radius_cells`` cells); it is rejected
   when it departs from that median by more than ``max(outlier_min_m, outlier_nmad * NMAD)`` of the
   neighbours. The NMAD term keeps roof points at building edges (mixed neighbourhoods, large NMAD)
   and removes isolated blunders (a 30 m spike among flat neighbours). A point with fewer than 3
   neighbours within the radius (sparse thermal tie points: one per ~150 cells on conte-city) is
   compared with its nearest neighbours at whatever distance, and the limit grows by
   ``outlier_isolated_slope`` times their median distance (terrain and roofs may differ that much
   over that distance). Without this test, a rendered city flight kept tie points 7 km below the
   ground (weak two-ray intersections), and the orthomosaic, whose frame footprints span the DSM's
   height range, gave every tile every frame.
2. **Median per cell** of the remaining points (robust to a residual blunder in a crowded cell).
3. **Hole filling** by linear interpolation on the Delaunay triangulation of the filled cells
   (``scipy.interpolate.griddata``'s values but where cells are cocircular, rasterised triangle by triangle; the
   triangulation is :mod:`aerocal.products.delaunay`'s, exact on grid cells), nearest value outside their
   convex hull (everywhere when the data cells lie on one line), optionally limited to
   ``max_fill_distance_m`` from the nearest data cell. :attr:`Dsm.distance_m` keeps, per cell, the distance
   to the nearest cell that held a tie point, so users (and :mod:`aerocal.assess`) can tell measured heights
   from interpolated ones.

Tie points and the dense surface: on a flight with frames the pipeline grids the dense cloud
(:mod:`aerocal.products.dense`) with this same function, at one cell per ground sample; the tie points' DSM
remains the surface of a flight without frames and the comparison printed beside the dense one (the two against
a true surface: ``benchmarks/RESULTS.md``, "Dense surface").
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numba
import numpy as np
import rasterio
import rasterio.shutil
from rasterio.enums import Resampling
from rasterio.transform import from_origin
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError, cKDTree

from aerocal.io import atomic_path
from aerocal.products.delaunay import grid_delaunay
from aerocal.products.kernels import tile_heights

#: Value written for cells without a height in DSM GeoTIFFs (float32).
NODATA = -9999.0


@dataclass(frozen=True)
class DsmConfig:
    """How a DSM is gridded from tie points. Lengths in metres unless a name says otherwise.

    ``cell_m`` fixes the cell size; when ``None`` it is ``cell_gsd`` ground sampling distances (2 GSD by
    default: about one tie point per few cells on thermal blocks, a cell still small against buildings).
    """

    cell_m: float | None = None  #: cell size; None = cell_gsd * gsd_m
    cell_gsd: float = 2.0  #: cell size in GSD when cell_m is None
    outlier_neighbours: int = 8  #: neighbours whose median a point is compared with
    outlier_radius_cells: float = 10.0  #: neighbours farther than this (cells) are ignored
    outlier_min_m: float = 5.0  #: a point within this of the local median is always kept
    outlier_nmad: float = 4.0  #: ... and within this many local NMADs
    outlier_isolated_slope: float = 1.0  #: height change per metre allowed to far neighbours (see above)
    #: the local-median test of step 1; off for clouds already filtered (the dense cloud's multi-view agreement),
    #: where its neighbour search over millions of points costs more than the gridding
    reject_outliers: bool = True
    fill: bool = True  #: interpolate holes (linear on the Delaunay triangulation, nearest outside)
    #: before the triangulation, fill pinholes (a cell whose 8 neighbours hold half a height or more) with the
    #: mean of those neighbours, :data:`PINHOLE_PASSES` times: a dense cloud leaves millions of them, and their
    #: rims made the triangulation of a city's DSM take minutes
    fill_pinholes: bool = False
    max_fill_distance_m: float | None = None  #: leave cells farther than this from data empty (None = fill all)
    margin_cells: int = 2  #: grid margin around the data (or given bounds), cells
    #: cells are never smaller than this fraction of the mean tie-point spacing (sqrt(area / points)): a grid
    #: finer than its data holds only interpolation, and at GSD it can outgrow memory (72 UltraCam frames with
    #: 1,782 tie points asked for 2 x 18146 x 18264 cells, over 23 GB); None = GSD rule only
    min_point_spacing: float | None = 0.25

    def __post_init__(self) -> None:
        if self.cell_m is not None and not self.cell_m > 0:
            raise ValueError(f"DsmConfig.cell_m must be positive, got {self.cell_m}")
        if not self.cell_gsd > 0:
            raise ValueError(f"DsmConfig.cell_gsd must be positive, got {self.cell_gsd}")
        if not self.outlier_isolated_slope >= 0:
            raise ValueError(f"DsmConfig.outlier_isolated_slope must be >= 0, got {self.outlier_isolated_slope}")
        if self.outlier_neighbours < 3:
            raise ValueError(f"DsmConfig.outlier_neighbours must be at least 3, got {self.outlier_neighbours}")

    def cell_size(self, gsd_m: float | None) -> float:
        """The cell size in metres: ``cell_m``, else ``cell_gsd`` times ``gsd_m``.

        Raises:
            ValueError: ``cell_m`` is not set and ``gsd_m`` is ``None`` or not positive.
        """
        if self.cell_m is not None:
            return float(self.cell_m)
        if gsd_m is None or not gsd_m > 0:
            raise ValueError("DsmConfig: give cell_m, or a positive gsd_m to size cells as cell_gsd * GSD")
        return float(self.cell_gsd * gsd_m)


@dataclass
class Dsm:
    """A north-up height grid (see the module docstring for the grid convention).

    ``heights`` float32 (rows, cols) metres, NaN = no value; ``distance_m`` float32 (rows, cols): distance
    from each cell centre to the nearest cell that held data (0 on those cells); ``counts`` int32
    (rows, cols): points that fell into each cell after outlier rejection.
    """

    heights: np.ndarray
    west: float
    north: float
    cell_m: float
    crs: str
    distance_m: np.ndarray | None = None
    counts: np.ndarray | None = None
    stats: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape  # type: ignore[return-value]

    def measured(self) -> np.ndarray:
        """bool (rows, cols): the cells that hold a height of their own (``distance_m`` 0); every other cell's
        height, where it has one, is interpolated across a hole.

        A hole of a dense DSM is where the views disagreed or none could match (an occlusion beside a wall, a tree's
        crown): the cells beside it that hold no point lay several ground samples off the true surface, however many
        of their 8 neighbours held points (``benchmarks/RESULTS.md``, "Dense surface: where its error lives"), so a
        hole's rim is not called measured.

        Raises:
            ValueError: the grid carries no ``distance_m`` (made without :func:`filled`)."""
        if self.distance_m is None:
            raise ValueError("Dsm.measured: the grid carries no distance to data (made without filled())")
        return self.distance_m == 0

    def bounds(self) -> tuple[float, float, float, float]:
        """(west, south, east, north), metres."""
        rows, cols = self.shape
        return (self.west, self.north - rows * self.cell_m, self.west + cols * self.cell_m, self.north)

    def transform(self):
        """The rasterio (affine) transform of the grid."""
        return from_origin(self.west, self.north, self.cell_m, self.cell_m)

    def grid_coords(self, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World E, N -> fractional (col, row) with cell centres at integers."""
        col = (np.asarray(e, dtype=float) - self.west) / self.cell_m - 0.5
        row = (self.north - np.asarray(n, dtype=float)) / self.cell_m - 0.5
        return col, row

    def centre_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """E (cols,) of the columns' and N (rows,) of the rows' cell centres, metres."""
        rows, cols = self.shape
        return (self.west + (np.arange(cols) + 0.5) * self.cell_m,
                self.north - (np.arange(rows) + 0.5) * self.cell_m)

    def cell_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """E, N (rows, cols) arrays of every cell centre, metres."""
        return np.meshgrid(*self.centre_axes())

    def centre_blocks(self, rows_per_block: int = 512) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
        """(rows, e, n) for blocks of ``rows_per_block`` grid rows: the rows' slice, the E (cols,) of every column's
        cell centres and the N (block rows,) of the block's rows, metres (:meth:`cell_centres` a block at a time,
        unmeshed). What is computed over a whole grid from its centres (a reference's heights, a difference) then
        takes a block's memory: a city's dense DSM holds 76 M cells, and its centres alone are 1.2 GB."""
        e, n = self.centre_axes()
        for r0 in range(0, len(n), rows_per_block):
            rows = slice(r0, min(r0 + rows_per_block, len(n)))
            yield rows, e, n[rows]

    def heights_on(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """:meth:`height_at` on the grid of E ``e`` (cols,) x N ``n`` (rows,): (rows, cols) float64, the same bits,
        in one compiled pass instead of numpy's full-grid temporaries."""
        out = np.empty((len(n), len(e)))
        tile_heights(self.heights, float(self.west), float(self.north), float(self.cell_m),
                     np.asarray(e, dtype=float), np.asarray(n, dtype=float), out)
        return out

    def height_at(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Heights at world E, N (any matching shapes), bilinear between cell centres, metres.

        Outside the grid the edge cells are extended; NaN where a contributing cell is empty.
        """
        col, row = self.grid_coords(e, n)
        return bilinear(self.heights, col, row)

    def window(self, bounds: tuple[float, float, float, float], margin_cells: int = 2) -> Dsm:
        """The sub-grid covering ``bounds`` (west, south, east, north) plus a margin, as a new Dsm."""
        rows, cols = self.shape
        w, s, e, n = bounds
        c0 = int(np.clip(np.floor((w - self.west) / self.cell_m) - margin_cells, 0, cols - 1))
        c1 = int(np.clip(np.ceil((e - self.west) / self.cell_m) + margin_cells, c0 + 1, cols))
        r0 = int(np.clip(np.floor((self.north - n) / self.cell_m) - margin_cells, 0, rows - 1))
        r1 = int(np.clip(np.ceil((self.north - s) / self.cell_m) + margin_cells, r0 + 1, rows))
        sub = (slice(r0, r1), slice(c0, c1))
        return Dsm(
            heights=self.heights[sub].copy(), west=self.west + c0 * self.cell_m,
            north=self.north - r0 * self.cell_m, cell_m=self.cell_m, crs=self.crs,
            distance_m=None if self.distance_m is None else self.distance_m[sub].copy(),
            counts=None if self.counts is None else self.counts[sub].copy(),
        )

    def height_range(self) -> tuple[float, float]:
        """(min, max) of the heights, metres (NaN cells ignored)."""
        return float(np.nanmin(self.heights)), float(np.nanmax(self.heights))


def bilinear(grid: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``grid`` at fractional (col, row), cell centres at integers, edges
    extended (float64). Same formula as :meth:`aerocal.simulate.scene.Scene.height_at`, so a DSM holding a
    scene's grid reproduces its heights exactly."""
    rows, cols = grid.shape
    col = np.clip(np.asarray(col, dtype=float), 0.0, cols - 1.0)
    row = np.clip(np.asarray(row, dtype=float), 0.0, rows - 1.0)
    c0 = np.minimum(col.astype(np.int64), max(cols - 2, 0))
    r0 = np.minimum(row.astype(np.int64), max(rows - 2, 0))
    fc = col - c0
    fr = row - r0
    dc = 1 if cols > 1 else 0
    dr = 1 if rows > 1 else 0
    g = np.asarray(grid, dtype=float)
    top = g[r0, c0] + fc * (g[r0, c0 + dc] - g[r0, c0])
    bottom = g[r0 + dr, c0] + fc * (g[r0 + dr, c0 + dc] - g[r0 + dr, c0])
    return top + fr * (bottom - top)


def reject_outliers(points: np.ndarray, config: DsmConfig, cell_m: float,
                    return_supported: bool = False):
    """Boolean mask of the points (N, 3) kept by the local-median test (see the module docstring).

    With ``return_supported`` also the mask of points with at least 3 neighbours within the radius
    (isolated points, tested against their nearest neighbours at any distance, do not set the DSM's
    extent).
    """
    pts = np.asarray(points, dtype=float)
    n = len(pts)
    k = min(config.outlier_neighbours, n - 1)
    if k < 3:
        everything = np.ones(n, dtype=bool)
        return (everything, everything) if return_supported else everything
    tree = cKDTree(pts[:, :2])
    dist, idx = tree.query(pts[:, :2], k=k + 1, distance_upper_bound=config.outlier_radius_cells * cell_m)
    dist, idx = dist[:, 1:], idx[:, 1:]  # drop the point itself
    z = np.where(np.isfinite(dist), pts[np.minimum(idx, n - 1), 2], np.nan)
    enough = np.sum(np.isfinite(z), axis=1) >= 3
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(z, axis=1)
            nmad = 1.4826 * np.nanmedian(np.abs(z - med[:, None]), axis=1)
    limit = np.maximum(config.outlier_min_m, config.outlier_nmad * nmad)
    keep = ~enough | (np.abs(pts[:, 2] - med) <= limit)
    lone = np.flatnonzero(~enough)
    if len(lone):
        d, j = tree.query(pts[lone, :2], k=k + 1)
        d, j = d[:, 1:], j[:, 1:]
        zl = pts[j, 2]
        med_l = np.median(zl, axis=1)
        nmad_l = 1.4826 * np.median(np.abs(zl - med_l[:, None]), axis=1)
        limit_l = np.maximum(config.outlier_min_m, config.outlier_nmad * nmad_l) + (
            config.outlier_isolated_slope * np.median(d, axis=1))
        keep[lone] = np.abs(pts[lone, 2] - med_l) <= limit_l
    return (keep, enough) if return_supported else keep


def _cell_medians(points: np.ndarray, west: float, north: float, cell: float, shape: tuple[int, int]):
    """Median height per cell of the points (N, 3: E, N, height, metres) on the grid whose top-left corner is
    (``west``, ``north``) and whose cells are ``cell`` metres, and the points per cell: (heights (rows, cols)
    float64, NaN where no point; counts (rows, cols) int32); points outside the grid are left out. The points
    are bucketed by cell and each bucket sorted (:func:`_bucket_medians`): linear in the points, where sorting
    them all by cell and height took 24 s of a 38-million-point cloud."""
    heights, counts = _bucket_medians(np.ascontiguousarray(points, dtype=np.float64), float(west), float(north),
                                      float(cell), shape[0], shape[1])
    return heights.reshape(shape), counts.reshape(shape)


@numba.njit(cache=True, nogil=True)
def _bucket_medians(points: np.ndarray, west: float, north: float, cell: float, rows: int,
                    cols: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_cell_medians` flat: per cell, the median height (NaN for none) and the count (int32); the cell
    of each point computed where it is used, so no per-point index array is held beside the cloud."""
    n_cells = rows * cols
    counts = np.zeros(n_cells, dtype=np.int32)
    for i in range(points.shape[0]):
        k = _cell_of(points[i, 0], points[i, 1], west, north, cell, rows, cols)
        if k >= 0:
            counts[k] += 1
    end = np.empty(n_cells, dtype=np.int64)  # where each cell's bucket ends once filled
    total = 0
    for c in range(n_cells):
        end[c] = total  # its start while filling
        total += counts[c]
    bucket = np.empty(total, dtype=np.float64)
    for i in range(points.shape[0]):
        k = _cell_of(points[i, 0], points[i, 1], west, north, cell, rows, cols)
        if k >= 0:
            bucket[end[k]] = points[i, 2]
            end[k] += 1
    heights = np.full(n_cells, np.nan)
    for c in range(n_cells):
        if counts[c]:
            heights[c] = median_in_place(bucket[end[c] - counts[c]:end[c]])
    return heights, counts


@numba.njit(cache=True, nogil=True)
def _cell_of(e: float, n: float, west: float, north: float, cell: float, rows: int, cols: int) -> int:
    """The flat index (row-major) of the cell holding (``e``, ``n``), -1 outside the grid."""
    c = int(np.floor((e - west) / cell))
    r = int(np.floor((north - n) / cell))
    return r * cols + c if 0 <= c < cols and 0 <= r < rows else -1


@numba.njit(cache=True, nogil=True)
def median_in_place(values: np.ndarray) -> float:
    """The median of a few values (``values`` is sorted in place: insertion sort, for the handful of points a
    cell holds)."""
    n = values.shape[0]
    for j in range(1, n):
        v = values[j]
        k = j - 1
        while k >= 0 and values[k] > v:
            values[k + 1] = values[k]
            k -= 1
        values[k + 1] = v
    return 0.5 * (values[(n - 1) // 2] + values[n // 2])


def dsm_from_points(
    points: np.ndarray,
    crs: str,
    gsd_m: float | None = None,
    config: DsmConfig | None = None,
    bounds: tuple[float, float, float, float] | None = None,
) -> Dsm:
    """Grid a DSM from 3D tie points (N, 3: E, N, height, metres in ``crs``) or a ``points`` table.

    ``bounds`` (west, south, east, north) fixes the extent (default: the points' extent), to which a margin
    of ``config.margin_cells`` is added; the grid is snapped to multiples of the cell size. The same as
    :func:`filled` of :func:`cells_from_points`, which a caller holding a large cloud calls in turn, releasing the
    cloud between them.
    """
    config = config or DsmConfig()
    return filled(cells_from_points(points, crs, gsd_m, config, bounds), config)


def cells_from_points(
    points: np.ndarray,
    crs: str,
    gsd_m: float | None = None,
    config: DsmConfig | None = None,
    bounds: tuple[float, float, float, float] | None = None,
) -> Dsm:
    """The first half of :func:`dsm_from_points` (same arguments): the grid and the median height of the points in
    each cell (float64, as :func:`filled` takes them), NaN where a cell holds none (``counts`` per cell,
    ``distance_m`` not yet computed); nothing filled.

    Raises:
        ValueError: ``points`` is not (N, 3) or holds fewer than 3 finite points.
    """
    config = config or DsmConfig()
    if hasattr(points, "column"):  # an Arrow points table
        pts = np.column_stack([points.column(c).to_numpy() for c in ("X", "Y", "Z")])
    else:
        pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"dsm_from_points: points must be (N, 3) E, N, height; got shape {pts.shape}")
    finite = np.all(np.isfinite(pts), axis=1)
    if not finite.all():  # a copy only where a point must go: a dense cloud is a gigabyte
        pts = pts[finite]
    if len(pts) < 3:
        raise ValueError(f"dsm_from_points: need at least 3 finite points, got {len(pts)}")
    cell = config.cell_size(gsd_m)
    if config.cell_m is None and config.min_point_spacing is not None:
        if bounds is not None:
            lo, hi = np.array(bounds[:2], dtype=float), np.array(bounds[2:], dtype=float)
        else:
            lo, hi = bulk_extent(pts[:, :2])
        spacing = float(np.sqrt(max(float(np.prod(hi - lo)), 0.0) / len(pts)))
        cell = max(cell, config.min_point_spacing * spacing)
    if config.reject_outliers:
        keep, supported = reject_outliers(pts, config, cell, return_supported=True)
    else:
        keep = supported = np.ones(len(pts), dtype=bool)
    n_points, n_rejected = len(pts), int(np.count_nonzero(~keep))
    good = pts if not n_rejected else pts[keep]
    # the extent comes from points with neighbours: a lone point (a weakly intersected tie point far off
    # the block) would otherwise stretch the grid over kilometres of nothing
    both = keep & supported
    core = (good if both.all() else pts[both]) if np.count_nonzero(both) >= 3 else good
    w, s, e, n = bounds if bounds is not None else (core[:, 0].min(), core[:, 1].min(),
                                                      core[:, 0].max(), core[:, 1].max())
    del pts, core, keep, supported, both, finite
    m = config.margin_cells * cell
    west = np.floor((w - m) / cell) * cell
    north = np.ceil((n + m) / cell) * cell
    cols = int(np.ceil((e + m - west) / cell))
    rows = int(np.ceil((north - (s - m)) / cell))
    heights, counts = _cell_medians(good, west, north, cell, (rows, cols))
    del good
    stats = {"points": n_points, "rejected_outliers": n_rejected, "cells": int(rows * cols), "cell_m": float(cell)}
    return Dsm(heights=heights, west=float(west), north=float(north), cell_m=float(cell), crs=crs, counts=counts,
               stats=stats)


def filled(cells: Dsm, config: DsmConfig | None = None) -> Dsm:
    """The second half of :func:`dsm_from_points`: ``cells`` (from :func:`cells_from_points`, NaN where no point)
    with each cell's distance to the nearest cell that held data (``distance_m``, metres) and, as ``config`` asks,
    its holes filled (:func:`fill_holes`) up to ``config.max_fill_distance_m``; heights float32."""
    config = config or DsmConfig()
    heights = cells.heights
    has = np.isfinite(heights)
    distance = distance_to_data(has) * np.float32(cells.cell_m)
    if config.fill and has.sum() >= 3:
        heights = fill_holes(heights, has, pinholes=config.fill_pinholes)
        if config.max_fill_distance_m is not None:
            heights[distance > config.max_fill_distance_m] = np.nan
    stats = {**cells.stats, "cells_with_data": int(has.sum())}
    return replace(cells, heights=heights.astype(np.float32), distance_m=distance, stats=stats)


def distance_to_data(has: np.ndarray) -> np.ndarray:
    """Each cell's Euclidean distance, in cells, to the nearest cell where ``has`` (a 2-D bool grid) is True.

    Returns:
        float32, ``has``' shape: 0 on the cells that hold data, ``inf`` everywhere when none does.

    The exact transform (OpenCV's ``DIST_L2`` with ``DIST_MASK_PRECISE``, Felzenszwalb and Huttenlocher's
    algorithm): the values of ``scipy.ndimage.distance_transform_edt`` to float32 rounding, several times faster
    on a dense DSM's grid (benchmarks/RESULTS.md, "Dense surface: the filling's grid passes")."""
    has = np.asarray(has, dtype=bool)
    if not has.any():
        return np.full(has.shape, np.inf, dtype=np.float32)
    return cv2.distanceTransform((~has).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def bulk_extent(xy: np.ndarray, tail: float = 0.01, max_points: int = 1_000_000) -> tuple[np.ndarray, np.ndarray]:
    """The (min, max) corners of the bulk of the points ``xy`` (N, 2): the ``tail`` and ``1 - tail`` quantiles
    of each axis, widened by ``1 / (1 - 2 tail)`` (exact for points spread evenly between the true extremes).

    The tie points' spacing comes from this extent, not from the extremes: on a rendered 129-frame city block
    (2 km x 1.7 km, 48,659 points) one two-ray point intersected 320 km away made the spacing 2.5 km and
    the DSM 8 x 8 cells of 635 m, and the orthomosaic was resampled on it. Up to ``tail`` of the points may
    lie anywhere on either side.

    Above ``max_points`` the quantiles are those of every k-th point (at least ``max_points`` of them): a quantile
    of a million points is within 1e-4 of its rank, and a dense cloud's 10^8 points would otherwise be copied
    and partitioned whole (gigabytes) for it."""
    step = max(1, len(xy) // max_points)
    lo, hi = np.quantile(xy[::step], [tail, 1.0 - tail], axis=0)
    half = 0.5 * (hi - lo) / (1.0 - 2.0 * tail)
    mid = 0.5 * (hi + lo)
    return mid - half, mid + half


#: passes of the pinhole filling (:attr:`DsmConfig.fill_pinholes`): each fills the cells half surrounded by
#: heights, so holes up to about twice this many cells across close before the triangulation
PINHOLE_PASSES = 3


def _fill_pinholes(heights: np.ndarray, has: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(heights, has) with the cells whose 8 neighbours hold at least 4 heights set to their mean, in
    :data:`PINHOLE_PASSES` passes (each pass reads the heights the one before left)."""
    heights, has = heights.copy(), has.copy()
    # one compiled pass over the hole cells per round: scipy's and OpenCV's neighbour sums over the whole grid took
    # 9 s on a city's 79-million-cell DSM (benchmarks/RESULTS.md, "City scale with the dense surface: the flow's
    # memory"); the same cells and means (tests/test_dsm.py compares them with scipy's convolution)
    after = has.copy()
    for _ in range(PINHOLE_PASSES):
        if not _pinhole_pass(heights, has, after):
            break
        has[:] = after
    return heights, has


@numba.njit(cache=True, nogil=True)
def _pinhole_pass(heights: np.ndarray, has: np.ndarray, after: np.ndarray) -> int:
    """One round of :func:`_fill_pinholes`: each cell not in ``has`` with at least 4 of its 8 neighbours in it takes
    their mean height (zero neighbours beyond the grid) and is set in ``after``; returns how many were. Only cells
    outside ``has`` are written, and only cells in it read, so the round reads the heights of the round before."""
    rows, cols = has.shape
    filled = 0
    for r in range(rows):
        for c in range(cols):
            if has[r, c]:
                continue
            count = 0
            total = 0.0
            for dr in range(-1, 2):
                rr = r + dr
                if rr < 0 or rr >= rows:
                    continue
                for dc in range(-1, 2):
                    cc = c + dc
                    if (dr == 0 and dc == 0) or cc < 0 or cc >= cols or not has[rr, cc]:
                        continue
                    count += 1
                    total += heights[rr, cc]
            if count >= 4:
                heights[r, c] = total / count
                after[r, c] = True
                filled += 1
    return filled


def fill_holes(heights: np.ndarray, has: np.ndarray, pinholes: bool = False) -> np.ndarray:
    """Linear interpolation on the Delaunay triangulation of the data cells, nearest outside the hull; with
    ``pinholes``, the pinholes filled first (:func:`_fill_pinholes`).

    The values of ``scipy.interpolate.griddata`` (linear, then nearest), computed differently: the data cells
    lie on the grid, so each Delaunay triangle is rasterised over the hole cells it covers
    (:func:`_raster_triangles`) instead of locating every hole cell in the triangulation, and the nearest data
    cell outside the hull comes from the distance transform's indices; faster than ``griddata``, with the same
    heights inside the hull to rounding but inside a circle through four or more rim cells (where either
    diagonal is Delaunay, :mod:`aerocal.products.delaunay`), and outside it the same but where two data cells are
    equally near (``benchmarks/history/engine_measurements.md``)."""
    if not (~has).any():
        return heights
    if pinholes:
        heights, has = _fill_pinholes(heights, has)  # copies: filled in place below
        if has.all():
            return heights
    # the vertices are the data cells on a hole's rim: linear interpolation inside a hole needs no others, and a
    # dense DSM (millions of data cells) would otherwise be triangulated whole
    rim = has & ndimage.binary_dilation(~has, structure=np.ones((3, 3), dtype=bool))
    rr, cc = np.nonzero(rim)
    # the hole cells are written, the data cells only read: the pinholes' copy is filled in place (a city's grid
    # is 76 million cells)
    out = heights if pinholes and heights.dtype == np.float64 else heights.astype(np.float64, copy=True)
    filled = has.copy()
    simplices = rim_triangles(rr, cc)
    if len(simplices):
        corners = np.stack([rr[simplices], cc[simplices]], axis=2).astype(np.int64)
        _raster_triangles(corners, heights[rr, cc][simplices].astype(np.float64), out, filled)
    if not filled.all():
        # outside the hull, the nearest data cell. It is always a rim cell (the cell before it on the line from a hole
        # cell is a hole cell, and touches it), so where those cells are few the rim's k-d tree answers; a query
        # costs about as much as NEAREST_QUERY_CELLS cells of the exact transform over the whole grid
        hr, hc = np.nonzero(~filled)
        if len(hr) * NEAREST_QUERY_CELLS < heights.size:
            _, near = cKDTree(np.column_stack([rr, cc])).query(np.column_stack([hr, hc]))
            out[hr, hc] = heights[rr[near], cc[near]]
        else:
            index = ndimage.distance_transform_edt(~has, return_distances=False, return_indices=True)
            out[hr, hc] = heights[index[0, hr, hc], index[1, hr, hc]]
    return out


def rim_triangles(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The Delaunay triangles of the cells (``rows``, ``cols``): (T, 3) indices into them, none when the cells lie on
    one line. :func:`aerocal.products.delaunay.grid_delaunay`'s sweep, or Qhull where the sweep declines (a grid
    :data:`~aerocal.products.delaunay.MAX_EXTENT` cells wide or more, a repeated cell)."""
    simplices = grid_delaunay(rows, cols)
    if simplices is not None:
        return simplices
    try:
        return Delaunay(np.column_stack([rows, cols]).astype(float)).simplices
    except QhullError:  # the cells lie on one line: no triangle
        return np.empty((0, 3), dtype=np.int64)


#: cells of the exact distance transform one k-d tree query costs (:func:`fill_holes`; from seneca's dense DSM, the
#: one both were timed on; ``benchmarks/RESULTS.md``, "City scale with the dense surface: the flow's memory")
NEAREST_QUERY_CELLS = 45


@numba.njit(cache=True, nogil=True)
def _raster_triangles(rows: np.ndarray, values: np.ndarray, out: np.ndarray, filled: np.ndarray) -> None:
    """Fill the cells of ``out`` (not yet ``filled``) that triangles cover, by barycentric interpolation.

    ``rows`` (T, 3, 2) int64: each triangle's vertices as (row, col) cell indices; ``values`` (T, 3) their
    heights. A cell on an edge shared by two triangles takes the first one's value (the two agree there).
    Cells covered get ``filled[r, c] = True``."""
    n_rows, n_cols = out.shape
    for t in range(rows.shape[0]):
        r0, c0 = rows[t, 0, 0], rows[t, 0, 1]
        r1, c1 = rows[t, 1, 0], rows[t, 1, 1]
        r2, c2 = rows[t, 2, 0], rows[t, 2, 1]
        det = (r1 - r0) * (c2 - c0) - (r2 - r0) * (c1 - c0)
        if det == 0:
            continue
        inv = 1.0 / det
        v0, v1, v2 = values[t, 0], values[t, 1], values[t, 2]
        for r in range(max(min(r0, r1, r2), 0), min(max(r0, r1, r2), n_rows - 1) + 1):
            for c in range(max(min(c0, c1, c2), 0), min(max(c0, c1, c2), n_cols - 1) + 1):
                if filled[r, c]:
                    continue
                # integer cross products: exact, so a cell on an edge is inside both triangles
                a1 = (r - r0) * (c2 - c0) - (r2 - r0) * (c - c0)
                a2 = (r1 - r0) * (c - c0) - (r - r0) * (c1 - c0)
                a0 = det - a1 - a2
                if (det > 0 and a0 >= 0 and a1 >= 0 and a2 >= 0) or (det < 0 and a0 <= 0 and a1 <= 0 and a2 <= 0):
                    out[r, c] = (a0 * v0 + a1 * v1 + a2 * v2) * inv
                    filled[r, c] = True


#: the products' deflate level, the DSM's and the orthomosaic's (GDAL's default is 6): on a city's
#: 79-million-cell dense DSM level 1 wrote the file in 55 % of the time for 4 % more bytes (benchmarks/RESULTS.md,
#: "City scale with the dense surface: the flow's memory"; the orthomosaic: :func:`aerocal.products.mosaic._finalise`)
DEFLATE_LEVEL = 1


#: the DSM's COG blocks, pixels (GDAL's default)
COG_BLOCK = 256


def cog_overview_factors(width: int, height: int, block: int = COG_BLOCK) -> list[int]:
    """The overview levels (decimation factors 2, 4, ...) GDAL's COG driver makes of a ``width`` x ``height``
    raster with ``block``-pixel tiles: halving until the coarsest level fits in one block; none when the raster
    does."""
    factors, f = [], 2
    while -(-width // (f // 2)) > block or -(-height // (f // 2)) > block:
        factors.append(f)
        f *= 2
    return factors


def write_dsm(dsm: Dsm, path: str | Path, measured: np.ndarray | None = None,
              views: np.ndarray | None = None) -> Path:
    """Write ``dsm`` as a Cloud-Optimized GeoTIFF (GDAL's COG driver: 256-pixel tiles, overviews averaged, deflate
    with the floating-point predictor), float32, nodata :data:`NODATA`, atomically: a GIS or a web map reads a
    window of a city's DSM without the whole file.

    The overviews are GDAL's average (:func:`cog_overview_factors`' levels), made on the uncompressed working
    file before the COG copy takes them: made by the COG driver itself (from a compressed temporary file of its
    own), they took a city's dense DSM (10371 x 7944 cells, three bands) 16.8 CPU-s to copy against 2.9 + 8.4
    (``benchmarks/RESULTS.md``, "Products: the DSM's overviews made before its COG copy").

    ``measured`` (bool, the DSM's shape), when given, is written as a second band (1: a measured height, 0: a
    filled hole) named ``measured``: a GIS shows where the surface was interpolated; readers of the heights
    (:func:`read_dsm`) read band 1 only. ``views`` (the DSM's shape, with ``measured``), when given, is a third
    band named ``views``: the frames that agree on the cell's height (2: one pair, unchecked; 0: filled).

    Raises:
        ValueError: ``views`` without ``measured``."""
    if views is not None and measured is None:
        raise ValueError("write_dsm: a views band needs the measured band beside it")
    path = Path(path)
    data = np.where(np.isfinite(dsm.heights), dsm.heights, NODATA).astype(np.float32)
    rows, cols = dsm.shape
    bands = [data] if measured is None else [data, np.where(np.isfinite(dsm.heights), measured, NODATA)
                                             .astype(np.float32)]
    if views is not None:
        bands.append(np.where(np.isfinite(dsm.heights), views, NODATA).astype(np.float32))
    profile = {
        "driver": "GTiff", "width": cols, "height": rows, "count": len(bands), "dtype": "float32", "crs": dsm.crs,
        "transform": dsm.transform(), "nodata": NODATA,
    }
    with atomic_path(path) as tmp:
        work = tmp.with_name(tmp.name + ".work.tif")  # the plain GeoTIFF the COG driver copies
        try:
            with rasterio.open(work, "w", **profile) as dst:
                for k, band in enumerate(bands, start=1):
                    dst.write(band, k)
                dst.set_band_description(1, "height")
                if measured is not None:
                    dst.set_band_description(2, "measured")
                if views is not None:
                    dst.set_band_description(3, "views")
                dst.update_tags(AREA_OR_POINT="Area", units="metre")
                factors = cog_overview_factors(cols, rows)
                if factors:
                    dst.build_overviews(factors, Resampling.average)
            rasterio.shutil.copy(work, tmp, driver="COG", COMPRESS="DEFLATE", LEVEL=DEFLATE_LEVEL, PREDICTOR="YES",
                                 BLOCKSIZE=COG_BLOCK, OVERVIEWS="FORCE_USE_EXISTING", BIGTIFF="IF_SAFER",
                                 NUM_THREADS="ALL_CPUS")
        finally:
            work.unlink(missing_ok=True)
    return path


def read_measured(path: str | Path) -> np.ndarray | None:
    """The measured-cell band of a DSM written by :func:`write_dsm` with ``measured`` (bool, the DSM's shape), or
    ``None`` when the file has no band named ``measured`` (a tie-point DSM, a user's surface)."""
    with rasterio.open(path) as src:
        if src.count < 2 or src.descriptions[1] != "measured":
            return None
        band = src.read(2, masked=True)
        return np.ma.getdata(band) == 1.0


def read_views(path: str | Path) -> np.ndarray | None:
    """The views band of a DSM written by :func:`write_dsm` with ``views`` (uint8, the DSM's shape: 0 filled or no
    height, 2 one pair, 3 or more checked), or ``None`` when the file has no band named ``views``."""
    with rasterio.open(path) as src:
        if src.count < 3 or src.descriptions[2] != "views":
            return None
        band = src.read(3, masked=True)
        return np.where(np.ma.getmaskarray(band), 0, np.ma.getdata(band)).astype(np.uint8)


def read_dsm(path: str | Path) -> Dsm:
    """Read a single-band north-up GeoTIFF (as :func:`write_dsm` writes) into a :class:`Dsm`.

    Raises:
        ValueError: ``path`` is not a readable GeoTIFF; its transform is not north-up with square cells (warp it first,
            e.g. with gdalwarp); it has no CRS.
    """
    return _read_surface(Path(path), with_measured=False)[0]


def read_dsm_and_measured(path: str | Path) -> tuple[Dsm, np.ndarray | None]:
    """:func:`read_dsm` and :func:`read_measured` of one file, from one read of its bands.

    :func:`write_dsm`'s bands are interleaved by pixel, so reading any one of them decompresses them all: a city's
    dense DSM (82 million cells, three bands) read band by band was decompressed once for the heights and once
    more for the measured cells (``benchmarks/RESULTS.md``, "Report: the DSM read once, its difference formed
    once").

    Raises:
        ValueError: as :func:`read_dsm`.
    """
    return _read_surface(Path(path), with_measured=True)


def _read_surface(path: Path, with_measured: bool) -> tuple[Dsm, np.ndarray | None]:
    """The DSM of ``path``'s band 1 and, with ``with_measured``, its band named ``measured`` (``None`` without one);
    the grid is checked before any pixel is read (:func:`read_dsm`'s errors)."""
    try:
        src = rasterio.open(path)
    except rasterio.errors.RasterioIOError as exc:
        raise ValueError(f"{path}: not a readable GeoTIFF ({exc})") from exc
    with src:
        t = src.transform
        if abs(t.b) > 0 or abs(t.d) > 0 or abs(abs(t.a) - abs(t.e)) > 1e-9 * abs(t.a) or t.e > 0:
            raise ValueError(f"{path}: transform {tuple(t)[:6]} is not north-up with square cells; "
                             "warp it to a north-up grid first (gdalwarp)")
        if src.crs is None:
            raise ValueError(f"{path}: the raster has no CRS; assign the flight's CRS (gdal_edit.py -a_srs)")
        has_measured = with_measured and src.count >= 2 and src.descriptions[1] == "measured"
        bands = src.read([1, 2] if has_measured else [1], masked=True)
        crs = src.crs.to_string()
    heights = np.where(np.ma.getmaskarray(bands[0]), np.float32(np.nan), np.ma.getdata(bands[0]))
    dsm = Dsm(heights=heights.astype(np.float32, copy=False), west=t.c, north=t.f, cell_m=t.a, crs=crs)
    return dsm, (np.ma.getdata(bands[1]) == 1.0) if has_measured else None
