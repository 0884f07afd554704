"""Hole filling of a city-sized DSM: the rims' Delaunay triangulation by the grid sweep against Qhull, in one run.

A grid of the rendered city's dense DSM size (7944 x 10371 cells by default) whose holes are the lowest tenth of a
smoothed random field (blobs a few cells across, as a dense DSM's are after its pinholes close), heights a sloping
plane with noise and a building every 5000 m2. Timed, one after the other on the same grid: the rims'
triangulation by :func:`aerocal.products.delaunay.grid_delaunay` and by scipy's Qhull, then
:func:`aerocal.products.dsm.fill_holes` with each (the pinholes first, as :func:`aerocal.products.dsm.filled` runs
it) and the DTM of :func:`aerocal.products.terrain.dtm_from_dsm`. Printed: the seconds, their ratio, and how many
filled cells differ between the two triangulations (inside circles through four or more rim cells, where either is
Delaunay) and by how much.

Run: ``python -m benchmarks.fill_bench [--rows R --cols C]``.
"""

from __future__ import annotations

import argparse
import time
from unittest import mock

import numpy as np
from scipy import ndimage
from scipy.spatial import Delaunay

import aerocal.products.dsm as dsm_module
from aerocal.products.delaunay import grid_delaunay
from aerocal.products.dsm import Dsm, fill_holes
from aerocal.products.terrain import dtm_from_dsm
from benchmarks.common import record


def grid(rows: int, cols: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(heights float32 with NaN holes, the data cells)."""
    rng = np.random.default_rng(seed)
    field = ndimage.gaussian_filter(rng.normal(size=(rows, cols)).astype(np.float32), 3)
    has = field > np.quantile(field[::7, ::7], 0.1)
    r, c = np.mgrid[0:rows, 0:cols]
    heights = (100.0 + 0.01 * r - 0.02 * c + rng.normal(0.0, 0.3, (rows, cols))).astype(np.float32)
    for _ in range(rows * cols // 20000):  # buildings of 10-40 m (20-80 cells of 0.5 m) a side, 6-30 m high
        r0, c0 = rng.integers(0, rows), rng.integers(0, cols)
        h, w = rng.integers(20, 80, 2)
        heights[r0:r0 + h, c0:c0 + w] += rng.uniform(6.0, 30.0)
    heights[~has] = np.nan
    return heights, has


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=7944)
    ap.add_argument("--cols", type=int, default=10371)
    args = ap.parse_args(argv)
    heights, has = grid(args.rows, args.cols)
    grid_delaunay(np.array([0, 1, 0]), np.array([0, 0, 1]))  # compiled (or loaded from numba's cache) first

    _, has_after = dsm_module._fill_pinholes(heights, has)
    rim = has_after & ndimage.binary_dilation(~has_after, structure=np.ones((3, 3), dtype=bool))
    rr, cc = np.nonzero(rim)
    t0 = time.perf_counter()
    ours = grid_delaunay(rr, cc)
    t_sweep = time.perf_counter() - t0
    t0 = time.perf_counter()
    qhull = Delaunay(np.column_stack([rr, cc]).astype(float)).simplices
    t_qhull = time.perf_counter() - t0
    del has_after, rim

    t0 = time.perf_counter()
    swept = fill_holes(heights, has, pinholes=True)
    f_sweep = time.perf_counter() - t0
    with mock.patch.object(dsm_module, "grid_delaunay", lambda rows, cols: None):
        t0 = time.perf_counter()
        hulled = fill_holes(heights, has, pinholes=True)
        f_qhull = time.perf_counter() - t0
    differ = swept != hulled
    worst = float(np.abs(swept - hulled).max())

    dsm = Dsm(heights=swept.astype(np.float32), west=0.0, north=0.0, cell_m=0.5, crs="EPSG:32617")
    dtm_from_dsm(Dsm(heights=swept[:200, :200].astype(np.float32), west=0.0, north=0.0, cell_m=0.5,
                     crs="EPSG:32617"))  # its kernels compiled or loaded first
    t0 = time.perf_counter()
    terrain = dtm_from_dsm(dsm, has)
    t_dtm = time.perf_counter() - t0
    with mock.patch.object(dsm_module, "grid_delaunay", lambda rows, cols: None):
        t0 = time.perf_counter()
        dtm_from_dsm(dsm, has)
        t_dtm_q = time.perf_counter() - t0

    record("Hole filling: a Delaunay triangulation of grid cells", [
        f"grid {args.rows} x {args.cols} cells, {(~has).mean():.1%} holes; {len(rr):,} rim cells after the pinholes, "
        f"{len(ours):,} triangles (Qhull {len(qhull):,})",
        "",
        "| part | grid sweep | Qhull | ratio |",
        "|---|---|---|---|",
        f"| the rims' triangulation | {t_sweep:.2f} s | {t_qhull:.2f} s | {t_qhull / t_sweep:.1f} |",
        f"| `fill_holes` (pinholes, triangles, nearest outside) | {f_sweep:.2f} s | {f_qhull:.2f} s | "
        f"{f_qhull / f_sweep:.1f} |",
        f"| `dtm_from_dsm` ({terrain.note}) | {t_dtm:.2f} s | {t_dtm_q:.2f} s | {t_dtm_q / t_dtm:.1f} |",
        "",
        f"- filled cells that differ between the two triangulations: {int(differ.sum()):,} of {int((~has).sum()):,} "
        f"({differ.sum() / max((~has).sum(), 1):.2%}), at most {worst:.3f} m",
    ])


if __name__ == "__main__":
    main()
