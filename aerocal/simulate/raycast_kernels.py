"""Compiled ray marching over a bilinear DSM, one ray at a time: the inner loops of
:func:`aerocal.simulate.raycast.intersect_dsm` and its near-hit refinement.

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
def hits_near(dsm, rows, cols, c0, r0, z0, dc, dr, dz, t_start, max_patches):  # pragma: no cover - compiled
    """Hit distances of rays known to be above the surface up to ``t_start`` and to hit within ``max_patches``
    patches after it; inf where the ray is not above the surface at ``t_start`` or no hit was found there."""
    n = len(c0)
    out = np.full(n, _INF)
    for i in range(n):
        t0 = t_start[i]
        pc = int(math.floor(c0[i] + t0 * dc[i]))
        pr = int(math.floor(r0[i] + t0 * dr[i]))
        t_root, t, pc, pr = _patch_step(dsm, rows, cols, c0[i], r0[i], z0[i], dc[i], dr[i], dz[i], t0, pc, pr,
                                        _INF)
        res = _INF if t_root <= t0 else t_root
        if not math.isfinite(t_root) and t > t0:
            for _ in range(max_patches - 1):
                t_root, t_out, pc, pr = _patch_step(dsm, rows, cols, c0[i], r0[i], z0[i], dc[i], dr[i], dz[i], t,
                                                    pc, pr, _INF)
                t = t_out
                if math.isfinite(t_root):
                    res = t_root
                    break
        out[i] = res
    return out
