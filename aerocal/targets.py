"""Signalised ground-control targets in images: sub-pixel centres of bright discs on dark squares.

Used on rendered frames (the simulator's targets) and on orthomosaics (the assessment), so it lives in
the engine, not in the simulator.
"""

from __future__ import annotations

import numpy as np


def locate_targets(
    image: np.ndarray, approx_uv: np.ndarray, window_px: int = 11, iterations: int = 3,
    threshold_sigma: float = 3.0,
) -> np.ndarray:
    """Sub-pixel centres of bright (hot) target blobs: (N, 2) pixels, aerocal convention (the centre of
    pixel (row, col) is (col + 0.5, row + 0.5)); NaN where the window leaves the image or holds no blob.

    For each approximate position: a round window of diameter ``window_px`` around it; background =
    median of the window's outer ring of pixels, noise = their MAD; weights = the signal above background
    by more than ``threshold_sigma`` noise sigmas; intensity-weighted centroid; re-centre and repeat
    ``iterations`` times. The window must lie inside the target's dark square (its diameter below the
    square's side, minus the blur) and contain the whole blurred disc: for the scene's default targets
    (square half-side 3 radii) a disc of radius r px wants a window of about 4 r px. RGB images are
    averaged over channels.
    """
    img = np.asarray(image, dtype=float)
    if img.ndim == 3:
        img = img.mean(axis=2)
    approx = np.atleast_2d(np.asarray(approx_uv, dtype=float))
    half = int(window_px) // 2
    height, width = img.shape
    out = np.full(approx.shape, np.nan)
    ry, rx = np.mgrid[-half:half + 1, -half:half + 1]
    rho = np.hypot(rx, ry)
    inside = rho <= half + 0.5  # a round window: any rotation of the target square fits the same way
    border = inside & (rho > half - 1.0)
    for k, (u, v) in enumerate(approx):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        cu, cv = u, v
        found = False
        for _ in range(max(1, iterations)):
            col, row = int(np.floor(cu)), int(np.floor(cv))
            if row - half < 0 or col - half < 0 or row + half >= height or col + half >= width:
                found = False
                break
            patch = img[row - half:row + half + 1, col - half:col + half + 1]
            edge = patch[border]
            bg = np.median(edge)
            noise = 1.4826 * np.median(np.abs(edge - bg))
            w = patch - bg
            w = np.where(inside & (w > threshold_sigma * noise), w, 0.0)
            total = w.sum()
            if total <= 0:
                found = False
                break
            cu = col + 0.5 + float((w * rx).sum() / total)
            cv = row + 0.5 + float((w * ry).sum() / total)
            found = True
        if found:
            out[k] = (cu, cv)
    return out
