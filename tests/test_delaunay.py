"""The grid cells' Delaunay triangulation (aerocal.products.delaunay): every cell a vertex, the triangles tiling the
cells' convex hull, no cell inside a triangle's circumcircle (checked with exact integers), and Qhull's triangles
where no four cells are cocircular."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import ConvexHull, Delaunay, cKDTree

from aerocal.products.delaunay import EXACT_EXTENT, MAX_EXTENT, grid_delaunay


def _assert_delaunay(rows: np.ndarray, cols: np.ndarray, tri: np.ndarray, label: str) -> None:
    x, y = cols.astype(np.int64), rows.astype(np.int64)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    cross = (x[b] - x[a]) * (y[c] - y[a]) - (y[b] - y[a]) * (x[c] - x[a])
    assert (cross > 0).all(), f"{label}: a triangle not counter-clockwise or of no area"
    assert np.array_equal(np.unique(tri), np.arange(len(x))), f"{label}: a cell is no vertex"
    hull = ConvexHull(np.column_stack([x, y]).astype(float)).volume
    assert cross.sum() / 2 == pytest.approx(hull, abs=1e-6), f"{label}: the triangles do not tile the hull"
    # the empty circle: the cells within each circumcircle (a k-d tree finds them, the determinant decides in exact
    # Python integers)
    d = 2.0 * cross
    s = [x[k] ** 2 + y[k] ** 2 for k in (a, b, c)]
    ux = (s[0] * (y[b] - y[c]) + s[1] * (y[c] - y[a]) + s[2] * (y[a] - y[b])) / d
    uy = (s[0] * (x[c] - x[b]) + s[1] * (x[a] - x[c]) + s[2] * (x[b] - x[a])) / d
    radius = np.hypot(x[a] - ux, y[a] - uy)
    near = cKDTree(np.column_stack([x, y]).astype(float)).query_ball_point(np.column_stack([ux, uy]), radius + 1e-6)
    for t, cells in enumerate(near):
        for p in cells:
            if p in tri[t]:
                continue
            rows_ = [(int(x[v]) - int(x[p]), int(y[v]) - int(y[p])) for v in tri[t]]
            (ax, ay), (bx, by), (cx, cy) = rows_
            al, bl, cl = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
            det = ax * (by * cl - cy * bl) - ay * (bx * cl - cx * bl) + al * (bx * cy - cx * by)
            assert det <= 0, f"{label}: cell {p} inside the circumcircle of {tri[t]}"


def _rims(seed: int, share: float) -> tuple[np.ndarray, np.ndarray]:
    """Cells on the rims of holes, as the filling triangulates them (most of them cocircular with others)."""
    rng = np.random.default_rng(seed)
    noise = ndimage.gaussian_filter(rng.normal(size=(300, 260)), 3)
    has = noise < np.quantile(noise, share)
    return np.nonzero(has & ndimage.binary_dilation(~has, structure=np.ones((3, 3), dtype=bool)))


def _sparse(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """300 cells drawn from a 120 x 90 grid."""
    return np.divmod(np.random.default_rng(seed).choice(120 * 90, 300, replace=False), 90)


@pytest.mark.parametrize("cells,seed", [(functools.partial(_rims, share=0.8), 0),
                                        (functools.partial(_rims, share=0.5), 1), *((_sparse, s) for s in range(6))])
def test_grid_cells_are_triangulated_delaunay(cells, seed):
    rows, cols = cells(seed)
    tri = grid_delaunay(rows, cols)
    assert tri is not None, f"seed {seed}"
    _assert_delaunay(rows, cols, tri, f"seed {seed}")


@pytest.mark.parametrize("seed,extent", [(0, 9000), (1, 9000), (2, 9000), (3, 5 * EXACT_EXTENT)])
def test_cells_with_no_four_on_a_circle_give_qhulls_triangles(seed, extent):
    """Cells spread over a wide grid (cocircular quadruples rare): the very triangles of Qhull, on a grid wider than
    the int64 test's reach too."""
    rng = np.random.default_rng(seed)
    rows, cols = np.divmod(rng.choice(extent * extent, 2000, replace=False), extent)
    tri = grid_delaunay(rows, cols)
    assert tri is not None, f"seed {seed}"
    ours = {tuple(sorted(t)) for t in tri.tolist()}
    qhull = {tuple(sorted(t)) for t in Delaunay(np.column_stack([rows, cols]).astype(float)).simplices.tolist()}
    assert ours == qhull, f"seed {seed}: {len(ours ^ qhull)} triangles differ"


def test_a_grid_wider_than_the_int64_test_is_triangulated_delaunay():
    """Rims of holes scattered over a grid 2.5 times as wide as the int64 in-circle test reaches: the far points'
    tests fall to the float64 determinant, which decides every one a grid's cells need here."""
    rows, cols = _rims(4, 0.7)
    rows = rows * 137  # the same rims spread out: 300 x 260 cells -> 41,000 x 260
    tri = grid_delaunay(rows, cols)
    assert tri is not None
    _assert_delaunay(rows, cols, tri, "wide grid")


def test_cells_on_one_line_give_no_triangle_and_a_grid_too_wide_for_float64_is_left_to_qhull():
    line = np.arange(10)
    assert grid_delaunay(line, 2 * line + 3).shape == (0, 3)
    assert grid_delaunay(np.array([0, 1]), np.array([0, 0])).shape == (0, 3)
    assert grid_delaunay(np.array([0, 5, MAX_EXTENT]), np.array([0, 9, 1])) is None
