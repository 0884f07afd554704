"""The Delaunay triangulation of grid cells: the vertices of the DSM's hole filling and the DTM's interpolation.

Both interpolate linearly on the Delaunay triangles of the data cells around the holes, which lie on the grid:
millions of integer points, most of them cocircular with others (every square of four cells). Qhull (scipy's
``Delaunay``) lifts them onto a paraboloid and takes the 3-D convex hull, and on the 3.7 million rim cells of a
synthetic grid the size of the rendered city's DSM it took 17 times as long as this module's sweep
(``benchmarks/RESULTS.md``, "Hole filling: a Delaunay triangulation of grid cells", where the same triangles'
count and the filled heights are compared).

:func:`grid_delaunay` is the sweep-hull algorithm (Sinclair 2010, "S-hull"), with Lawson's edge flips
(Lawson 1977) after each insertion:

1. the seed triangle is the point nearest the points' centre, its nearest neighbour and the third point that makes
   the smallest circle with them; the other points are inserted in order of their distance from that circle's
   centre, so each lies outside the hull built so far (the hull is star-shaped about the centre);
2. a point is joined to every hull edge it sees (found from a hash of the hull's vertices by their angle about
   the centre), and the edges opposite it are flipped while the triangle beyond lies in its circumcircle.

The predicates are exact: the points are integers, so the orientation is an int64 cross product, and the in-circle
test is decided by its float64 determinant where that is farther from zero than its rounding can reach, else by the
int64 determinant, exact for four points within :data:`EXACT_EXTENT` cells of each other. Four points spread wider
whose float64 test cannot decide (nearly cocircular on a grid more than 16,384 cells across) keep their edge: the
triangulation stays valid, and Delaunay but for such an edge. Where four points are cocircular, either diagonal is a
Delaunay triangulation and the edge is left as it is; the triangles differ from Qhull's there, and so can the
interpolated values inside such a circle (both are linear on a Delaunay triangulation).

A point no hull edge sees (which the distance order rules out for distinct points, but not for duplicates) makes
:func:`grid_delaunay` return ``None``, and the caller uses Qhull.
"""

from __future__ import annotations

import numba
import numpy as np

#: coordinate differences (cells) below which the int64 in-circle determinant cannot overflow (its terms are bounded
#: by 3 * 2^58 for differences under 2^14)
EXACT_EXTENT = 1 << 14
#: cells along each axis up to which the sweep triangulates: the float64 test's inputs (squared distances) stay exact
MAX_EXTENT = 1 << 24


def grid_delaunay(rows: np.ndarray, cols: np.ndarray) -> np.ndarray | None:
    """The Delaunay triangles of the grid cells (``rows``, ``cols``), each cell given once.

    Args:
        rows, cols: integer cell indices, (N,) each, with no cell repeated.

    Returns:
        (T, 3) int64 indices into the points, each triangle counter-clockwise in (col, row) axes; an empty
        (0, 3) array when the points are fewer than 3 or all on one line; ``None`` when the sweep cannot insert
        a point or the grid spans :data:`MAX_EXTENT` cells or more (the caller then triangulates with Qhull).
    """
    x = np.ascontiguousarray(cols, dtype=np.int64)
    y = np.ascontiguousarray(rows, dtype=np.int64)
    if len(x) < 3:
        return np.empty((0, 3), dtype=np.int64)
    if max(int(x.max() - x.min()), int(y.max() - y.min())) >= MAX_EXTENT:
        return None
    x = x - x.min()
    y = y - y.min()
    triangles, count, ok = _sweep(x, y)
    if not ok:
        return None
    return triangles[: 3 * count].reshape(-1, 3)


@numba.njit(cache=True, nogil=True, inline="always")
def _cross(ax, ay, bx, by, cx, cy):
    """Twice the signed area of (a, b, c): positive counter-clockwise (exact on int64)."""
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@numba.njit(cache=True, nogil=True)
def _in_circle(ax, ay, bx, by, cx, cy, px, py) -> bool:
    """Whether p lies strictly inside the circumcircle of the counter-clockwise triangle (a, b, c)."""
    adx, ady = ax - px, ay - py
    bdx, bdy = bx - px, by - py
    cdx, cdy = cx - px, cy - py
    al = adx * adx + ady * ady
    bl = bdx * bdx + bdy * bdy
    cl = cdx * cdx + cdy * cdy
    # float64 first, with a bound on its rounding (Shewchuk's for the in-circle test, with margin)
    fa, fb, fc = float(adx), float(ady), float(al)
    ga, gb, gc = float(bdx), float(bdy), float(bl)
    ha, hb, hc = float(cdx), float(cdy), float(cl)
    det = fa * (gb * hc - hb * gc) - fb * (ga * hc - ha * gc) + fc * (ga * hb - ha * gb)
    permanent = (abs(fa) * (abs(gb * hc) + abs(hb * gc)) + abs(fb) * (abs(ga * hc) + abs(ha * gc))
                 + fc * (abs(ga * hb) + abs(ha * gb)))
    if abs(det) > 1e-14 * permanent:
        return det > 0.0
    if max(abs(adx), abs(ady), abs(bdx), abs(bdy), abs(cdx), abs(cdy)) >= EXACT_EXTENT:
        return False  # undecided and too wide for int64: the edge stays (module docstring)
    exact = adx * (bdy * cl - cdy * bl) - ady * (bdx * cl - cdx * bl) + al * (bdx * cdy - cdx * bdy)
    return exact > 0


@numba.njit(cache=True, nogil=True, inline="always")
def _pseudo_angle(dx, dy):
    """A monotone stand-in for the angle of (dx, dy), in [0, 1)."""
    s = abs(dx) + abs(dy)
    if s == 0.0:
        return 0.0
    p = dx / s
    a = (3.0 - p) / 4.0 if dy > 0 else (1.0 + p) / 4.0
    return a - np.floor(a)


@numba.njit(cache=True, nogil=True)
def _link(twin, a, b):
    twin[a] = b
    if b >= 0:
        twin[b] = a


@numba.njit(cache=True, nogil=True)
def _add(tri, twin, hull_edge, t, i0, i1, i2, a, b, c):
    """Triangle ``t`` = (i0, i1, i2), its half-edges 3t (i0 -> i1), 3t + 1, 3t + 2 linked to a, b, c (-1: on the
    hull, where ``hull_edge`` of the half-edge's first vertex records it)."""
    e = 3 * t
    tri[e], tri[e + 1], tri[e + 2] = i0, i1, i2
    _link(twin, e, a)
    _link(twin, e + 1, b)
    _link(twin, e + 2, c)
    for k in range(3):
        if twin[e + k] < 0:
            hull_edge[tri[e + k]] = e + k
    return t + 1


@numba.njit(cache=True, nogil=True)
def _legalise(x, y, tri, twin, hull_edge, start, stack):
    """Flip edges from half-edge ``start`` on, while the triangle beyond lies in the circumcircle.

    Every edge on the stack is opposite the point being inserted: for half-edge ``a`` of triangle (u, v, p)
    (``a`` from u to v), the triangle beyond, (v, u, z), is replaced with (z, v, p) and (p, u, z) when z lies in
    the circle of (u, v, p); their edges opposite p are checked in turn."""
    top = 0
    stack[top] = start
    top += 1
    while top > 0:
        top -= 1
        a = stack[top]
        b = twin[a]
        if b < 0:
            continue
        a0 = a - a % 3
        b0 = b - b % 3
        an = a0 + (a + 1) % 3
        ap = a0 + (a + 2) % 3
        bn = b0 + (b + 1) % 3
        bp = b0 + (b + 2) % 3
        u, v, p, z = tri[a], tri[an], tri[ap], tri[bp]
        if not _in_circle(x[u], y[u], x[v], y[v], x[p], y[p], x[z], y[z]):
            continue
        ha = twin[ap]  # p -> u, which becomes b
        hb = twin[bp]  # z -> v, which becomes a
        tri[a] = z
        tri[b] = p
        _link(twin, a, hb)
        _link(twin, b, ha)
        _link(twin, ap, bp)
        if hb < 0:
            hull_edge[z] = a
        if ha < 0:
            hull_edge[p] = b
        if top + 2 > len(stack):  # more flips than points: not on distinct points; the caller falls back
            return False
        stack[top] = a
        stack[top + 1] = bn
        top += 2
    return True


@numba.njit(cache=True, nogil=True)
def _sweep(x, y):
    """(triangles' vertices, flat; how many triangles; whether every point was inserted)."""
    n = len(x)
    fx = x.astype(np.float64)
    fy = y.astype(np.float64)
    mx = 0.5 * (fx.min() + fx.max())
    my = 0.5 * (fy.min() + fy.max())
    tri = np.empty(3 * max(2 * n - 5, 1), dtype=np.int64)
    twin = np.full(len(tri), -1, dtype=np.int64)
    # the seed: nearest the centre, its nearest neighbour, and the smallest circle with them
    i0 = np.argmin((fx - mx) ** 2 + (fy - my) ** 2)
    d0 = (fx - fx[i0]) ** 2 + (fy - fy[i0]) ** 2
    d0[i0] = np.inf
    i1 = np.argmin(d0)
    best = np.inf
    i2 = -1
    for k in range(n):
        if k == i0 or k == i1:
            continue
        area = _cross(x[i0], y[i0], x[i1], y[i1], x[k], y[k])
        if area == 0:
            continue
        ux, uy = _circumcentre_from_a(fx[i0], fy[i0], fx[i1], fy[i1], fx[k], fy[k])
        r = ux * ux + uy * uy
        if r < best:
            best = r
            i2 = k
    if i2 < 0:  # every point on one line: no triangle
        return tri, 0, True
    if _cross(x[i0], y[i0], x[i1], y[i1], x[i2], y[i2]) < 0:
        i1, i2 = i2, i1
    ux, uy = _circumcentre_from_a(fx[i0], fy[i0], fx[i1], fy[i1], fx[i2], fy[i2])
    cx, cy = fx[i0] + ux, fy[i0] + uy
    order = np.argsort((fx - cx) ** 2 + (fy - cy) ** 2, kind="mergesort")

    hull_next = np.full(n, -1, dtype=np.int64)
    hull_prev = np.full(n, -1, dtype=np.int64)
    hull_edge = np.full(n, -1, dtype=np.int64)
    size = max(int(np.ceil(np.sqrt(n))), 1)
    bucket = np.full(size, -1, dtype=np.int64)
    hull_next[i0], hull_next[i1], hull_next[i2] = i1, i2, i0
    hull_prev[i1], hull_prev[i2], hull_prev[i0] = i0, i1, i2
    for i in (i0, i1, i2):
        bucket[int(_pseudo_angle(fx[i] - cx, fy[i] - cy) * size) % size] = i
    t = _add(tri, twin, hull_edge, 0, i0, i1, i2, -1, -1, -1)
    stack = np.empty(n + 64, dtype=np.int64)  # a flip pops one edge and pushes two

    for j in range(n):
        i = order[j]
        if i == i0 or i == i1 or i == i2:
            continue
        px, py = x[i], y[i]
        # a hull vertex near i's angle, then the first edge from it that i sees
        key = int(_pseudo_angle(fx[i] - cx, fy[i] - cy) * size) % size
        first = -1
        for k in range(size):
            s = bucket[(key + k) % size]
            if s >= 0 and hull_next[s] >= 0:
                first = s
                break
        if first < 0:
            return tri, t, False
        first = hull_prev[first]
        e = first
        while _cross(x[e], y[e], x[hull_next[e]], y[hull_next[e]], px, py) >= 0:
            e = hull_next[e]
            if e == first:
                return tri, t, False  # seen by no edge: a repeated point
        # the triangle on the edge it sees, then the edges after it and before it that it also sees
        q = hull_next[e]
        t = _add(tri, twin, hull_edge, t, e, i, q, -1, -1, hull_edge[e])
        if not _legalise(x, y, tri, twin, hull_edge, 3 * t - 1, stack):
            return tri, t, False
        n_ = q
        while True:
            q = hull_next[n_]
            if _cross(x[n_], y[n_], x[q], y[q], px, py) >= 0:
                break
            t = _add(tri, twin, hull_edge, t, n_, i, q, hull_edge[i], -1, hull_edge[n_])
            if not _legalise(x, y, tri, twin, hull_edge, 3 * t - 1, stack):
                return tri, t, False
            hull_next[n_] = -1  # no longer on the hull
            n_ = q
        if e == first:
            while True:
                q = hull_prev[e]
                if _cross(x[q], y[q], x[e], y[e], px, py) >= 0:
                    break
                t = _add(tri, twin, hull_edge, t, q, i, e, -1, hull_edge[e], hull_edge[q])
                if not _legalise(x, y, tri, twin, hull_edge, 3 * t - 1, stack):
                    return tri, t, False
                hull_next[e] = -1
                e = q
        hull_prev[i], hull_next[i] = e, n_
        hull_next[e] = i
        hull_prev[n_] = i
        bucket[key] = i
        bucket[int(_pseudo_angle(fx[e] - cx, fy[e] - cy) * size) % size] = e
    return tri, t, True


@numba.njit(cache=True, nogil=True)
def _circumcentre_from_a(ax, ay, bx, by, cx, cy):
    """The circumcentre of (a, b, c) less a: its (x, y) offsets, so the radius squared is their squared sum."""
    dx, dy = bx - ax, by - ay
    ex, ey = cx - ax, cy - ay
    bl = dx * dx + dy * dy
    cl = ex * ex + ey * ey
    d = 0.5 / (dx * ey - dy * ex)
    return (ey * bl - dy * cl) * d, (dx * cl - ex * bl) * d
