"""Compiled inner loop of the orthomosaic: where one frame sees every pixel of an output tile.

:func:`aerocal.products.mosaic.render_tile` needs, for every candidate frame and every output pixel, the recorded
pixel of the ground point (the full Brown + affinity camera model), whether it falls inside the frame, its
distance to the principal point (the nadir score) and the border taper. numpy formed these with ~20
full-tile float64 temporaries per frame (the ground points, the camera-frame points, the distortion terms,
the masks), most of a tile's time (``benchmarks/history/engine_measurements.md``). Here it is one pass over the
pixels per frame, compiled by numba, with the operations of :meth:`aerocal.camera.Camera.project` in the same order;
``tests/test_mosaic.py`` checks it against that numpy path (:func:`aerocal.products.mosaic._frame_view_numpy`, still
used for the thermal models that correct measurements) on a strongly distorted affine camera: scores to
1e-9, maps to 1e-3 px (float32); in a whole mosaic a handful of pixels came out 1 DN apart from that path's (a
sum rounded the other way).

Conventions: ``e`` (cols,) and ``n`` (rows,) are the world E, N of the tile's pixel centres, ``h``
(rows, cols) the DSM heights (NaN: none); ``R`` is world-to-camera, ``C`` the projection centre; ``io``
the camera parameters in the order of :data:`aerocal.camera.PARAM_NAMES`; pixels from the top-left corner.
"""

from __future__ import annotations

import numba
import numpy as np

#: Map value (OpenCV pixel convention) written where a frame has no projection: outside any image.
NO_PIXEL = -10.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _projected(de, dn, dh, R, io):
    """The recorded pixel (u, v) of a ground point ``(de, dn, dh)`` metres from the projection centre and its depth
    along the optical axis, computed without a branch whatever the depth (behind the camera, u and v are any
    value): :func:`frame_view`'s vector loop chooses by the depth afterwards."""
    f, cx, cy, k1, k2, k3, p1, p2, b1, b2 = io[0], io[1], io[2], io[3], io[4], io[5], io[6], io[7], io[8], io[9]
    px = de * R[0, 0] + dn * R[0, 1] + dh * R[0, 2]
    py = de * R[1, 0] + dn * R[1, 1] + dh * R[1, 2]
    pz = de * R[2, 0] + dn * R[2, 1] + dh * R[2, 2]
    x = px / pz
    y = py / pz
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
    yd = y * radial + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
    return cx + xd * (f + b1) + yd * b2, cy + yd * f, pz


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _pixel(de, dn, dh, R, io):
    """The recorded pixel (u, v) of a ground point ``(de, dn, dh)`` metres from the projection centre, and whether
    it lies in front of the camera ((0, 0) when not)."""
    u, v, pz = _projected(de, dn, dh, R, io)
    if not pz > 0:
        return 0.0, 0.0, False
    return u, v, True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def frame_view(e, n, h, R, C, io, width, height, feather_px, map_u, map_v, score, taper, motion):
    """Fill, for one frame, the tile's ``map_u``/``map_v`` (float32, OpenCV's pixel convention: ours minus
    0.5, :data:`NO_PIXEL` where the ground point is behind the camera or has no height), ``score`` (float64
    distance to the principal point, inf where the pixel is not inside the frame) and ``taper`` (min(border
    distance / feather_px, 1), at least 1e-6 inside the frame, 0 outside). Returns whether any pixel is
    inside the frame. ``motion`` (3,): the projection centre's displacement (world metres) per unit of
    ``row / height - 0.5`` of a frame read out row by row (velocity x readout; zeros: a global shutter), found
    for each pixel by fixed-point iteration on its row as :class:`aerocal.simulate.exposure.Exposure` does.

    A global shutter's pixels go through a loop without branches, each output chosen by a select, which the
    compiler turns into vector instructions: the same bits as the pixel-by-pixel loop (:func:`_frame_view_moving`,
    which the readout's iteration needs) in a quarter of its time on a 256 x 256 tile (AVX2; measured against it
    in one process, benchmarks/RESULTS.md, "Orthomosaic: a frame's view of a tile in vector instructions")."""
    if motion[0] != 0.0 or motion[1] != 0.0 or motion[2] != 0.0:
        return _frame_view_moving(e, n, h, R, C, io, width, height, feather_px, map_u, map_v, score, taper, motion)
    cx, cy = io[1], io[2]
    feather = max(feather_px, 1e-9)
    half = np.float32(0.5)
    no_pixel = np.float32(NO_PIXEL)
    seen = 0
    rows, cols = h.shape
    for r in range(rows):
        dn = n[r] - C[1]
        for c in range(cols):
            # a point behind the camera or without a height is computed too (any value) and then not chosen
            hh = h[r, c]
            u, v, pz = _projected(e[c] - C[0], dn, hh - C[2], R, io)
            valid = (np.abs(hh) < np.inf) & (pz > 0) & (np.abs(u) < np.inf) & (np.abs(v) < np.inf)
            inside = valid & (u >= 0.0) & (u <= width) & (v >= 0.0) & (v <= height)
            du, dv = u - cx, v - cy
            map_u[r, c] = np.float32(u) - half if valid else no_pixel
            map_v[r, c] = np.float32(v) - half if valid else no_pixel
            score[r, c] = np.sqrt(du * du + dv * dv) if inside else np.inf
            border = min(min(u, width - u), min(v, height - v))
            taper[r, c] = min(max(border / feather, 1e-6), 1.0) if inside else 0.0
            seen += inside
    return seen > 0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _frame_view_moving(e, n, h, R, C, io, width, height, feather_px, map_u, map_v, score, taper, motion):
    """:func:`frame_view` pixel by pixel, for a frame read out row by row (``motion`` not zero)."""
    cx, cy = io[1], io[2]
    feather = max(feather_px, 1e-9)
    half = np.float32(0.5)
    seen = False
    rows, cols = h.shape
    for r in range(rows):
        dn = n[r] - C[1]
        for c in range(cols):
            # each output written once, at the end (the pixels a frame does not see are most of its candidates')
            mu = mv = np.float32(NO_PIXEL)
            sc, tp = np.inf, 0.0
            hh = h[r, c]
            if np.isfinite(hh):
                de = e[c] - C[0]
                dh = hh - C[2]
                u, v, front = _pixel(de, dn, dh, R, io)
                for _ in range(3):  # the readout's shift is a few pixels of a frame's height: converges at once
                    frac = v / height - 0.5
                    u, v, front = _pixel(de - frac * motion[0], dn - frac * motion[1], dh - frac * motion[2],
                                         R, io)
                if front and np.isfinite(u) and np.isfinite(v):
                    mu = np.float32(u) - half
                    mv = np.float32(v) - half
                    if u >= 0.0 and u <= width and v >= 0.0 and v <= height:
                        du, dv = u - cx, v - cy
                        sc = np.sqrt(du * du + dv * dv)
                        tp = min(max(min(u, width - u, v, height - v) / feather, 1e-6), 1.0)
                        seen = True
            map_u[r, c] = mu
            map_v[r, c] = mv
            score[r, c] = sc
            taper[r, c] = tp
    return seen


@numba.njit(cache=True, nogil=True, error_model="numpy")
def tile_heights(grid, west, north, cell_m, e, n, out):
    """Fill ``out`` (rows, cols) with the heights of the DSM ``grid`` (north-up, ``west``/``north`` its outer
    corner, cells of ``cell_m`` metres) at the tile's pixel centres ``e`` (cols,) x ``n`` (rows,):
    :meth:`aerocal.products.dsm.Dsm.height_at` with the operations of :func:`aerocal.products.dsm.bilinear` in
    the same order (the same bits), without its full-tile temporaries."""
    rows_g, cols_g = grid.shape
    dc = 1 if cols_g > 1 else 0
    dr = 1 if rows_g > 1 else 0
    cols = e.shape[0]
    col0 = np.empty(cols, np.int64)  # each column's cell and fraction, found once for every row
    frac = np.empty(cols)
    for c in range(cols):
        col = min(max((e[c] - west) / cell_m - 0.5, 0.0), cols_g - 1.0)
        col0[c] = min(int(col), max(cols_g - 2, 0))
        frac[c] = col - col0[c]
    for r in range(n.shape[0]):
        row = min(max((north - n[r]) / cell_m - 0.5, 0.0), rows_g - 1.0)
        r0 = min(int(row), max(rows_g - 2, 0))
        fr = row - r0
        for c in range(cols):
            c0 = col0[c]
            fc = frac[c]
            g00 = np.float64(grid[r0, c0])
            top = g00 + fc * (np.float64(grid[r0, c0 + dc]) - g00)
            g10 = np.float64(grid[r0 + dr, c0])
            bottom = g10 + fc * (np.float64(grid[r0 + dr, c0 + dc]) - g10)
            out[r, c] = top + fr * (bottom - top)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def seam_weight(score, best, taper, width, r, c):
    """One frame's blending weight at the tile's pixel (``r``, ``c``): ``1 - (score - best) / width`` clipped to
    [0, 1], times its border ``taper``; 0 where the frame does not see the pixel (``score`` inf). ``best``: the
    smallest score of any frame at each pixel."""
    s = score[r, c]
    if not s < np.inf:
        return 0.0
    return min(max(1.0 - (s - best[r, c]) / width, 0.0), 1.0) * taper[r, c]


@numba.njit(cache=True, nogil=True, error_model="numpy")
def weighed_box(map_u, map_v, score, best, taper, width):
    """Where one frame's :func:`seam_weight` is positive in the tile: whether anywhere (when not, its pixels are
    not needed), the bounding box of the positions it is sampled at there (u_min, u_max, v_min, v_max; OpenCV's
    pixel convention, as the maps), and the tile's rows and columns that hold them (row_start, row_stop,
    col_start, col_stop; stop exclusive, all 0 when nowhere)."""
    u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
    rows, cols = score.shape
    r_lo, r_hi, c_lo, c_hi = rows, 0, cols, 0
    for r in range(rows):
        for c in range(cols):
            if seam_weight(score, best, taper, width, r, c) > 0.0:
                u, v = map_u[r, c], map_v[r, c]
                u_lo, u_hi, v_lo, v_hi = min(u_lo, u), max(u_hi, u), min(v_lo, v), max(v_hi, v)
                r_lo, r_hi, c_lo, c_hi = min(r_lo, r), max(r_hi, r + 1), min(c_lo, c), max(c_hi, c + 1)
    if not u_lo <= u_hi:
        return False, u_lo, u_hi, v_lo, v_hi, 0, 0, 0, 0
    return True, u_lo, u_hi, v_lo, v_hi, r_lo, r_hi, c_lo, c_hi


@numba.njit(cache=True, nogil=True, error_model="numpy")
def add_weighted(values, score, best, taper, width, acc, wsum):
    """Add one frame's resampled ``values`` (rows, cols, bands) times its :func:`seam_weight` to ``acc`` (bands,
    rows, cols) and the weight to ``wsum`` (rows, cols), where the weight is positive (elsewhere ``values`` may
    hold anything)."""
    rows, cols, bands = values.shape
    for r in range(rows):
        for c in range(cols):
            w = seam_weight(score, best, taper, width, r, c)
            if w > 0.0:
                for b in range(bands):
                    acc[b, r, c] += np.float64(values[r, c, b]) * w
                wsum[r, c] += w


@numba.njit(cache=True, nogil=True, error_model="numpy")
def score_bounds(box, R, C, io, width, height):
    """Bounds on a frame's nadir score (:func:`frame_view`'s ``score``, px) over a tile: (low, high, sees_all).

    ``box`` (2, 3): the tile's ground volume, (west, south, lowest height) and (east, north, highest height),
    world metres. Every ground point in it that the frame sees scores in [low, high]; ``sees_all``: the frame
    sees every point of the volume (it lies in the circle about the principal point inscribed in the frame).
    Perspective maps the box into the hull of its 8 corners' images, which lies in their bounding box in the
    normalised image plane; the Brown radial term is taken at its extremes over the radii there (33 samples,
    and 1 px of slack), the decentring and affinity terms at their largest. ``(0, inf, False)`` when a corner is
    not in front of the camera: no bound."""
    f, cx, cy, k1, k2, k3, p1, p2, b1, b2 = io[0], io[1], io[2], io[3], io[4], io[5], io[6], io[7], io[8], io[9]
    xlo, xhi, ylo, yhi = np.inf, -np.inf, np.inf, -np.inf
    rho_hi = 0.0
    for i in range(2):
        for j in range(2):
            for k in range(2):
                de = box[i, 0] - C[0]
                dn = box[j, 1] - C[1]
                dh = box[k, 2] - C[2]
                px = de * R[0, 0] + dn * R[0, 1] + dh * R[0, 2]
                py = de * R[1, 0] + dn * R[1, 1] + dh * R[1, 2]
                pz = de * R[2, 0] + dn * R[2, 1] + dh * R[2, 2]
                if not pz > 0:
                    return 0.0, np.inf, False
                x = px / pz
                y = py / pz
                xlo, xhi, ylo, yhi = min(xlo, x), max(xhi, x), min(ylo, y), max(yhi, y)
                rho_hi = max(rho_hi, np.hypot(x, y))
    # the nearest point of the corners' bounding box to the principal point: a lower bound on the hull's radii
    rho_lo = np.hypot(max(xlo, 0.0, -xhi), max(ylo, 0.0, -yhi))
    g_lo, g_hi = np.inf, 0.0
    for s in range(33):
        rho = rho_lo + (rho_hi - rho_lo) * s / 32.0
        r2 = rho * rho
        g = rho * (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
        g_lo, g_hi = min(g_lo, g), max(g_hi, g)
    # the decentring term's length: each component at most (3 |p1| + |p2|) r^2 or (|p1| + 3 |p2|) r^2
    tangential = 4.0 * (abs(p1) + abs(p2)) * rho_hi * rho_hi
    skew = abs(b1) + abs(b2)
    low = max((f - skew) * (g_lo - tangential) - 1.0, 0.0)
    high = (f + skew) * (g_hi + tangential) + 1.0
    return low, high, high < min(cx, width - cx, cy, height - cy) - 1.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def weighted_mean(acc, wsum, lo, hi, nodata, out):
    """Write into ``out`` (bands, rows, cols; an integer dtype) the weighted mean ``acc / wsum`` where ``wsum`` is
    positive, rounded half to even and clipped to [``lo``, ``hi``]; a mean equal to ``nodata`` is moved one
    count inward, so that a valid pixel never reads as nodata. Pixels without weight keep their value."""
    bands, rows, cols = acc.shape
    for r in range(rows):
        for c in range(cols):
            w = wsum[r, c]
            if not w > 0.0:
                continue
            for b in range(bands):
                m = min(max(np.rint(acc[b, r, c] / w), lo), hi)
                if m == nodata:
                    m = nodata - 1 if nodata == hi else nodata + 1
                out[b, r, c] = m


@numba.njit(cache=True, nogil=True, error_model="numpy")
def halve(src, nodata, hi, out):
    """Write into ``out`` (bands, ceil(rows / 2), ceil(cols / 2)) the mean of each 2 x 2 block of ``src`` (bands,
    rows, cols; an integer dtype) over its valid pixels (band 0 not ``nodata``: a mosaic's pixel is nodata in
    every band or in none), rounded half up as GDAL's average overviews round; nodata where the block has no valid
    pixel, and a mean equal to ``nodata`` moved one count inward (as :func:`weighted_mean`, ``hi`` the dtype's
    maximum). The last row or column of an odd size is a block of its own pixels alone (a mosaic's tiles are made
    whole numbers of their coarsest level's pixels, so none is odd there)."""
    bands, rows, cols = src.shape
    for r in range(out.shape[1]):
        r0 = 2 * r
        r1 = min(r0 + 1, rows - 1)  # an odd last row: the same row twice, counted once below
        for c in range(out.shape[2]):
            c0 = 2 * c
            c1 = min(c0 + 1, cols - 1)
            v00 = src[0, r0, c0] != nodata
            v01 = c1 != c0 and src[0, r0, c1] != nodata
            v10 = r1 != r0 and src[0, r1, c0] != nodata
            v11 = r1 != r0 and c1 != c0 and src[0, r1, c1] != nodata
            n = int(v00) + int(v01) + int(v10) + int(v11)
            for b in range(bands):
                if n == 0:
                    out[b, r, c] = nodata
                    continue
                s = 0.0
                if v00:
                    s += np.float64(src[b, r0, c0])
                if v01:
                    s += np.float64(src[b, r0, c1])
                if v10:
                    s += np.float64(src[b, r1, c0])
                if v11:
                    s += np.float64(src[b, r1, c1])
                m = np.floor(s / n + 0.5)
                if m == nodata:
                    m = nodata - 1 if nodata == hi else nodata + 1
                out[b, r, c] = m
