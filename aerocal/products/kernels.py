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
def _pixel(de, dn, dh, R, io):
    """The recorded pixel (u, v) of a ground point ``(de, dn, dh)`` metres from the projection centre, and whether
    it lies in front of the camera."""
    f, cx, cy, k1, k2, k3, p1, p2, b1, b2 = io[0], io[1], io[2], io[3], io[4], io[5], io[6], io[7], io[8], io[9]
    px = de * R[0, 0] + dn * R[0, 1] + dh * R[0, 2]
    py = de * R[1, 0] + dn * R[1, 1] + dh * R[1, 2]
    pz = de * R[2, 0] + dn * R[2, 1] + dh * R[2, 2]
    if not pz > 0:
        return 0.0, 0.0, False
    x = px / pz
    y = py / pz
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + p1 * (r2 + 2 * x * x) + 2 * p2 * x * y
    yd = y * radial + p2 * (r2 + 2 * y * y) + 2 * p1 * x * y
    return cx + xd * (f + b1) + yd * b2, cy + yd * f, True


@numba.njit(cache=True, nogil=True, error_model="numpy")
def frame_view(e, n, h, R, C, io, width, height, feather_px, map_u, map_v, score, taper, motion):
    """Fill, for one frame, the tile's ``map_u``/``map_v`` (float32, OpenCV's pixel convention: ours minus
    0.5, :data:`NO_PIXEL` where the ground point is behind the camera or has no height), ``score`` (float64
    distance to the principal point, inf where the pixel is not inside the frame) and ``taper`` (min(border
    distance / feather_px, 1), at least 1e-6 inside the frame, 0 outside). Returns whether any pixel is
    inside the frame. ``motion`` (3,): the projection centre's displacement (world metres) per unit of
    ``row / height - 0.5`` of a frame read out row by row (velocity x readout; zeros: a global shutter), found
    for each pixel by fixed-point iteration on its row as :class:`aerocal.simulate.exposure.Exposure` does."""
    cx, cy = io[1], io[2]
    feather = max(feather_px, 1e-9)
    half = np.float32(0.5)
    seen = False
    moving = motion[0] != 0.0 or motion[1] != 0.0 or motion[2] != 0.0
    rows, cols = h.shape
    for r in range(rows):
        dn = n[r] - C[1]
        for c in range(cols):
            score[r, c] = np.inf
            taper[r, c] = 0.0
            map_u[r, c] = NO_PIXEL
            map_v[r, c] = NO_PIXEL
            hh = h[r, c]
            if not np.isfinite(hh):
                continue
            de = e[c] - C[0]
            dh = hh - C[2]
            u, v, front = _pixel(de, dn, dh, R, io)
            if moving:
                for _ in range(3):  # the readout's shift is a few pixels of a frame's height: converges at once
                    frac = v / height - 0.5
                    u, v, front = _pixel(de - frac * motion[0], dn - frac * motion[1], dh - frac * motion[2], R, io)
            if not front:
                continue
            if not (np.isfinite(u) and np.isfinite(v)):
                continue
            map_u[r, c] = np.float32(u) - half
            map_v[r, c] = np.float32(v) - half
            if not (u >= 0.0 and u <= width and v >= 0.0 and v <= height):
                continue
            score[r, c] = np.hypot(u - cx, v - cy)
            border = min(u, width - u, v, height - v)
            taper[r, c] = min(max(border / feather, 1e-6), 1.0)
            seen = True
    return seen
