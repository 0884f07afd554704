"""Compiled ray marching over a bilinear DSM, one ray at a time: the inner loops of
:func:`aerocal.simulate.raycast.intersect_dsm`, and the sub-pixel rays of a rendered frame and their hits near
those of the pixel centres.

The vectorised numpy marcher these replace kept every active ray in arrays and stepped them together, which
spent most of a frame's time gathering and scattering the shrinking set of active rays (1.9 s of a 640 x 480
thermal frame with 3 x 3 sub-pixel rays). Here each ray walks its own patches with the same arithmetic, in the
same order, so the distances are the numpy marcher's to the last bit (compared on rendered frames and random rays
when it replaced it; ``tests/test_raycast.py`` checks the hits against the surface and the rays);
``benchmarks/history/engine_measurements.md`` has the timings.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_INF = np.inf


@njit(cache=True, error_model="numpy")
def _first_root(dsm, rows, cols, pc, pr, u0, v0, du, dv, z_in, dz, length):  # pragma: no cover - compiled
    """Smallest s in [0, length] where the ray crosses below the bilinear surface of patch (pr, pc) of the padded
    ``dsm``, else inf. The ray enters at ``(u0, v0)`` (position within the patch, in cells) at height ``z_in`` and
    moves by ``(du, dv, dz)`` per unit of s; the crossing is the first root of the quadratic in s that the
    surface's height less the ray's is along the ray."""
    stride = cols + 2
    prc = min(max(pr, -1), rows - 1)
    pcc = min(max(pc, -1), cols - 1)
    i00 = (prc + 1) * stride + pcc + 1
    h00 = np.float64(dsm[i00])
    h01 = dsm[i00 + 1]
    h10 = dsm[i00 + stride]
    h11 = dsm[i00 + stride + 1]
    a = h01 - h00
    b = h10 - h00
    c = h00 - h01 - h10 + h11
    cc = z_in - (h00 + a * u0 + b * v0 + c * u0 * v0)
    bb = dz - (a * du + b * dv + c * (u0 * dv + v0 * du))
    aa = -c * du * dv
    disc = bb * bb - 4.0 * aa * cc
    sq = math.sqrt(disc) if disc > 0.0 else (0.0 if disc <= 0.0 else disc)
    q = -0.5 * (bb + (sq if bb >= 0 else -sq))
    r1 = q / aa if aa != 0 else _INF
    r2 = cc / q if q != 0 else _INF
    babs = abs(bb)
    if abs(aa) * length < 1e-12 * (babs if babs > 1e-300 or babs != babs else 1e-300):
        r1 = -cc / bb if bb < 0 else _INF
        r2 = _INF
    slack = 1e-9 * (1.0 + length)
    if not (disc >= 0 and r1 >= 0 and r1 <= length + slack):
        r1 = _INF
    if not (disc >= 0 and r2 >= 0 and r2 <= length + slack):
        r2 = _INF
    root = r1 if r1 < r2 else r2
    root = (root if root < length else length) if math.isfinite(root) else _INF
    return 0.0 if cc <= 0 else root


@njit(cache=True, error_model="numpy")
def _patch_step(dsm, rows, cols, c0, r0, z0, dc, dr, dz, t, pc, pr, t_end):  # pragma: no cover - compiled
    """One patch of one ray: (hit parameter or inf, exit parameter, next patch col, next patch row)."""
    t_col = (pc + (1 if dc > 0 else 0) - c0) / dc if dc != 0 else _INF
    t_row = (pr + (1 if dr > 0 else 0) - r0) / dr if dr != 0 else _INF
    t_out = min(min(t_col, t_row), t_end)
    if t_out < t:
        t_out = t
    s_root = _first_root(dsm, rows, cols, pc, pr, c0 + t * dc - pc, r0 + t * dr - pr, dc, dr, z0 + t * dz, dz,
                         t_out - t)
    pc_next = pc + ((1 if dc > 0 else -1) if t_col <= t_out else 0)
    pr_next = pr + ((1 if dr > 0 else -1) if t_row <= t_out else 0)
    return t + s_root, t_out, pc_next, pr_next


@njit(cache=True, error_model="numpy")
def march(dsm, rows, cols, c0, r0, z0, dc, dr, dz, down, t_first, t_end, h_len, cell, grids, blocks,
          n_levels):  # pragma: no cover - compiled
    """First hit distance (metres, inf: none) of each ray from ``t_first`` to ``t_end``.

    Rays in grid units as in :func:`aerocal.simulate.raycast.intersect_dsm` (``c0, r0`` grid position,
    ``dc, dr`` cells per metre, ``z0, dz`` height and vertical rate; ``down`` rays going down, ``h_len`` cells
    per metre horizontally). ``grids[:n_levels]`` are the empty-space-skipping max grids of block sizes
    ``blocks`` (coarse first): a ray skips the longest step the coarsest grid proves to stay above the surface,
    else steps through one patch and solves for its first root there.
    """
    n = len(c0)
    out = np.full(n, _INF)
    half_cell = 0.5 * cell
    for i in range(n):
        c0i, r0i, z0i, dci, dri, dzi = c0[i], r0[i], z0[i], dc[i], dr[i], dz[i]
        t = t_first[i]
        te = t_end[i]
        located = False
        pc = 0
        pr = 0
        while True:
            skipped = False
            if n_levels > 0:
                za = z0i + t * dzi
                cc = c0i + t * dci
                rr = r0i + t * dri
                for lv in range(n_levels):
                    g = grids[lv]
                    b = blocks[lv]
                    gr, gc = g.shape
                    bc = cc // b
                    br = rr // b
                    bc = int(min(max(bc, 0.0), gc - 1.0))
                    br = int(min(max(br, 0.0), gr - 1.0))
                    clearance = za - g[br, bc]
                    safe = clearance / -dzi if down[i] else _INF
                    h_limit = b / h_len[i]
                    s = (h_limit if h_limit < safe else safe) if clearance > 0 else 0.0
                    if s >= half_cell:
                        t = t + s
                        located = False
                        skipped = True
                        break
            if not skipped:
                if not located:
                    pc = int(math.floor(c0i + t * dci))
                    pr = int(math.floor(r0i + t * dri))
                    located = True
                t_root, t_out, pc, pr = _patch_step(dsm, rows, cols, c0i, r0i, z0i, dci, dri, dzi, t, pc, pr, te)
                if math.isfinite(t_root):
                    out[i] = t_root
                    break
                t = t_out
            if t >= te:
                break
    return out


@njit(cache=True, error_model="numpy")
def _near_one(dsm, rows, cols, c0, r0, z0, dc, dr, dz, t0, max_patches):  # pragma: no cover - compiled
    """The hit distance of a ray known to be above the surface up to ``t0`` and to hit within ``max_patches``
    patches after it; inf where the ray is not above the surface at ``t0`` or no hit was found there."""
    pc = int(math.floor(c0 + t0 * dc))
    pr = int(math.floor(r0 + t0 * dr))
    t_root, t, pc, pr = _patch_step(dsm, rows, cols, c0, r0, z0, dc, dr, dz, t0, pc, pr, _INF)
    res = _INF if t_root <= t0 else t_root
    if not math.isfinite(t_root) and t > t0:
        for _ in range(max_patches - 1):
            t_root, t_out, pc, pr = _patch_step(dsm, rows, cols, c0, r0, z0, dc, dr, dz, t, pc, pr, _INF)
            t = t_out
            if math.isfinite(t_root):
                res = t_root
                break
    return res


@njit(cache=True, error_model="numpy")
def subpixel_rays(oa, da, ss):  # pragma: no cover - compiled
    """The ``ss x ss`` sub-pixel rays of the inner pixels of a grid of pixel-centre rays with a one-pixel border
    (``oa``, ``da``: (H + 2, W + 2, 3) origins and unit directions), interpolated bilinearly and the directions
    normalised: (origins, directions), each (H ss W ss, 3) ordered (row, sub-row, col, sub-col). Sub-pixel k of a
    pixel sits (k + 0.5) / ss - 0.5 pixels from its centre; the arithmetic is that of interpolating along the
    columns, then along the rows, as numpy did it before (the same rays to the last bit)."""
    h = oa.shape[0] - 2
    w = oa.shape[1] - 2
    n_cols = w * ss
    o = np.empty((h * ss * n_cols, 3))
    d = np.empty((h * ss * n_cols, 3))
    for i in range(h):
        for k in range(ss):
            y = (k + 0.5) / ss + 0.5
            y0 = int(math.floor(y))
            fy = y - y0
            base = (i * ss + k) * n_cols
            for j in range(w):
                for m in range(ss):
                    x = (m + 0.5) / ss + 0.5
                    x0 = int(math.floor(x))
                    fx = x - x0
                    at = base + j * ss + m
                    r_top = i + y0
                    c_left = j + x0
                    for a in range(3):
                        top = oa[r_top, c_left, a] * (1.0 - fx) + oa[r_top, c_left + 1, a] * fx
                        bottom = oa[r_top + 1, c_left, a] * (1.0 - fx) + oa[r_top + 1, c_left + 1, a] * fx
                        o[at, a] = top * (1.0 - fy) + bottom * fy
                        top = da[r_top, c_left, a] * (1.0 - fx) + da[r_top, c_left + 1, a] * fx
                        bottom = da[r_top + 1, c_left, a] * (1.0 - fx) + da[r_top + 1, c_left + 1, a] * fx
                        d[at, a] = top * (1.0 - fy) + bottom * fy
                    norm = math.sqrt(d[at, 0] * d[at, 0] + d[at, 1] * d[at, 1] + d[at, 2] * d[at, 2])
                    for a in range(3):
                        d[at, a] = d[at, a] / norm
    return o, d


@njit(cache=True, error_model="numpy")
def coherent_hits(dsm, rows, cols, origin_e, top_n, cell, o, d, ta, pa, ss):  # pragma: no cover - compiled
    """Hit distances of sub-pixel rays (``o``, ``d`` as :func:`subpixel_rays` orders them) from the pixel-centre
    hits around them (``ta`` (H + 2, W + 2) distances, inf for the sky; ``pa`` (H + 2, W + 2, 2) their E, N).

    A pixel is coherent where its 9 pixel-centre rays all hit, the distance has no step along any of the four lines
    through the centre (second difference under half a cell) and every neighbour's hit lies within a cell of the
    centre's horizontally: no DSM feature a cell wide fits between the rays unseen. Its sub-pixel rays are
    intersected from 0.3 cell before their interpolated distance (:func:`_near_one`, 3 patches). Returns (t, todo):
    the distances (inf where none was found) and the rays to trace from the top (incoherent pixels, and coherent
    ones whose near search found nothing). ``origin_e`` and ``top_n`` are the DSM grid's west and north edges
    (metres), ``cell`` its cell size."""
    h = ta.shape[0] - 2
    w = ta.shape[1] - 2
    n_cols = w * ss
    n = h * ss * n_cols
    t = np.full(n, _INF)
    todo = np.ones(n, dtype=np.bool_)
    tol = 0.5 * cell
    for i in range(h):
        for j in range(w):
            ci = i + 1
            cj = j + 1
            tc = ta[ci, cj]
            ok = math.isfinite(tc)
            if ok:
                for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
                    a = ta[ci - dy, cj - dx]
                    b = ta[ci + dy, cj + dx]
                    if not (math.isfinite(a) and math.isfinite(b) and abs(a + b - 2.0 * tc) < tol):
                        ok = False
                        break
                    for sgn in (-1, 1):
                        qe = pa[ci + sgn * dy, cj + sgn * dx, 0] - pa[ci, cj, 0]
                        qn = pa[ci + sgn * dy, cj + sgn * dx, 1] - pa[ci, cj, 1]
                        if not math.sqrt(qe * qe + qn * qn) < cell:
                            ok = False
                    if not ok:
                        break
            if not ok:
                continue
            for k in range(ss):
                y = (k + 0.5) / ss + 0.5
                y0 = int(math.floor(y))
                fy = y - y0
                for m in range(ss):
                    x = (m + 0.5) / ss + 0.5
                    x0 = int(math.floor(x))
                    fx = x - x0
                    top = ta[i + y0, j + x0] * (1.0 - fx) + ta[i + y0, j + x0 + 1] * fx
                    bottom = ta[i + y0 + 1, j + x0] * (1.0 - fx) + ta[i + y0 + 1, j + x0 + 1] * fx
                    guess = top * (1.0 - fy) + bottom * fy
                    at = (i * ss + k) * n_cols + j * ss + m
                    c0 = (o[at, 0] - origin_e) / cell - 0.5
                    r0 = (top_n - o[at, 1]) / cell - 0.5
                    start = guess - 0.3 * cell
                    hit = _near_one(dsm, rows, cols, c0, r0, o[at, 2], d[at, 0] / cell, -d[at, 1] / cell, d[at, 2],
                                    start if start > 0.0 else 0.0, 3)
                    if math.isfinite(hit):
                        t[at] = hit
                        todo[at] = False
    return t, todo
