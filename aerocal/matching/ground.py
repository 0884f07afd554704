"""The flying height of a block from its own images, where nothing records it.

A flight with GNSS positions but neither ground control nor a recorded height above ground (a senseFly or DJI
height field, ``height_agl_m`` in flight.json) still holds its ground: two overlapping frames, oriented
relative to each other from their matches and scaled by the GNSS baseline between them, intersect their tie
points, and the distance of those points below the first camera is the flying height. :func:`flying_height`
does this on a few pairs of consecutive frames spread over the flight and takes the median:

1. pairs: frames consecutive in time with a GNSS baseline of at least ``min_baseline_m``, up to ``max_pairs``
   of them spread evenly over the flight;
2. per pair: SIFT (OpenCV), Lowe's ratio test and the fundamental matrix's RANSAC inliers, intersected
   (``cv2.triangulatePoints``) from the recorded positions and attitudes with the nominal camera; where a
   frame records no attitude, from the essential matrix's relative pose (``cv2.recoverPose``) scaled by the
   GNSS baseline, the first camera taken as looking straight down;
3. per pair: the median height of the points below the first camera;
4. the flight's height: the median over pairs, with their spread.

The scale comes from the GNSS baseline between two frames a few seconds apart, whose error is mostly common to
both (time-correlated GNSS), and the median over pairs removes a pair whose matches or attitudes went wrong. The
result is the starting geometry for candidate pairs and the self-calibration's prediction, not a measurement the
block adjustment uses: the adjusted tie points give the ground afterwards.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import pyarrow as pa

from aerocal.camera import Camera
from aerocal.geometry import CONVENTIONS, attitude_to_R_cw


@dataclass(frozen=True)
class GroundConfig:
    """``max_pairs``: frame pairs measured (each costs two SIFT extractions); ``min_baseline_m``: shortest GNSS
    baseline of a pair (below, the GNSS error is a large part of the scale); ``max_features``: SIFT keypoints per
    frame; ``min_points``: triangulated points a pair needs to count; ``ratio``: Lowe's ratio test."""

    max_pairs: int = 8
    min_baseline_m: float = 2.0
    max_features: int = 3000
    min_points: int = 30
    ratio: float = 0.75

    def __post_init__(self) -> None:
        if self.max_pairs < 1 or self.min_points < 5 or self.max_features < 100:
            raise ValueError("GroundConfig: max_pairs >= 1, min_points >= 5 and max_features >= 100 are needed")
        if not (self.min_baseline_m > 0 and 0 < self.ratio < 1):
            raise ValueError("GroundConfig: min_baseline_m > 0 and 0 < ratio < 1 are needed")


@dataclass(frozen=True)
class FlyingHeight:
    """The flying height above the block's ground (metres; ``None`` where no pair gave one), the heights of the
    pairs measured, and one sentence on where it came from (or why there is none)."""

    height_m: float | None
    pair_heights_m: tuple[float, ...]
    source: str


def _pairs(images: pa.Table, cfg: GroundConfig) -> list[tuple[int, int]]:
    """Row indices of consecutive frames (in time) with positions and a baseline of ``min_baseline_m``, in the
    same strip where the flight has strips."""
    x = np.asarray(images.column("gnss_x").to_pylist(), dtype=float)
    y = np.asarray(images.column("gnss_y").to_pylist(), dtype=float)
    z = np.asarray(images.column("gnss_z").to_pylist(), dtype=float)
    times = images.column("time").to_pylist()
    strip = (images.column("strip").to_pylist() if "strip" in images.column_names else [None] * len(x))
    order = sorted(range(len(x)), key=lambda i: (times[i] is None, times[i] or 0, i))
    out = []
    for a, b in zip(order[:-1], order[1:], strict=True):
        base = np.sqrt((x[b] - x[a]) ** 2 + (y[b] - y[a]) ** 2 + (z[b] - z[a]) ** 2)
        turning = strip[a] is None or strip[a] < 0 or strip[a] != strip[b]  # a turn: a roll the records lag
        if np.isfinite(base) and base >= cfg.min_baseline_m and not (turning and any(s is not None and s >= 0
                                                                                     for s in strip)):
            out.append((a, b))
    if len(out) > cfg.max_pairs:
        pick = np.unique(np.round(np.linspace(0, len(out) - 1, cfg.max_pairs)).astype(int))
        out = [out[k] for k in pick]
    return out


def _recorded_R_cw(images: pa.Table, row: int) -> np.ndarray | None:
    """The recorded world-to-camera rotation of ``row`` (camera x right, y down, z forward), or ``None``."""
    names = images.column_names
    conv = images.column("attitude_convention")[row].as_py() if "attitude_convention" in names else None
    angles = [images.column(c)[row].as_py() if c in names else None for c in ("roll", "pitch", "yaw")]
    if conv in CONVENTIONS and all(a is not None and np.isfinite(a) for a in angles):
        return attitude_to_R_cw(conv, *angles)
    return None


def _matches(grey_a: np.ndarray, grey_b: np.ndarray, cfg: GroundConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """Matched pixel positions of a pair (SIFT, ratio test, fundamental-matrix RANSAC inliers), or ``None``."""
    sift = cv2.SIFT_create(nfeatures=cfg.max_features)
    ka, da = sift.detectAndCompute(grey_a, None)
    kb, db = sift.detectAndCompute(grey_b, None)
    if da is None or db is None or len(ka) < cfg.min_points or len(kb) < cfg.min_points:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
    good = [m for m, n in (p for p in knn if len(p) == 2) if m.distance < cfg.ratio * n.distance]
    if len(good) < cfg.min_points:
        return None
    xa = np.float64([ka[m.queryIdx].pt for m in good])
    xb = np.float64([kb[m.trainIdx].pt for m in good])
    F, mask = cv2.findFundamentalMat(xa, xb, cv2.FM_RANSAC, 1.0, 0.999)
    if F is None or mask is None or int(mask.sum()) < cfg.min_points:
        return None
    inl = mask.ravel() > 0
    return xa[inl], xb[inl]


def _pair_height(xa: np.ndarray, xb: np.ndarray, camera: Camera, centres: np.ndarray,
                 rotations: tuple[np.ndarray | None, np.ndarray | None], cfg: GroundConfig) -> float | None:
    """Median height (m) of the pair's intersected points below the first camera, or ``None``.

    With both attitudes recorded, the rays are intersected from the recorded poses: on a flat block seen through
    a narrow lens, the relative rotation of two frames and the height trade against each other to first order
    (a rotation shifts the image as a baseline does), so the images alone leave the height loose (0.5-3.7 deg
    between the essential matrix's rotation and the recorded one on the rendered 22-degree conte frames, heights
    from 540 to 790 m for 850 m) where the recorded rotation holds it. Without attitudes, the essential matrix
    gives the relative pose and the first camera is taken as looking straight down.
    """
    K = np.array([[camera.f, 0.0, camera.cx], [0.0, camera.f, camera.cy], [0.0, 0.0, 1.0]])
    ca, cb = centres
    Ra, Rb = rotations
    if Ra is not None and Rb is not None:
        P1 = K @ np.hstack([Ra, -Ra @ ca.reshape(3, 1)])
        P2 = K @ np.hstack([Rb, -Rb @ cb.reshape(3, 1)])
        X = cv2.triangulatePoints(P1, P2, xa.T, xb.T)
        X = (X[:3] / X[3]).T
        below = ca[2] - X[np.isfinite(X).all(axis=1), 2]
    else:
        E, mask = cv2.findEssentialMat(xa, xb, K, method=cv2.RANSAC, prob=0.999, threshold=1.0)
        if E is None or E.shape != (3, 3):
            return None
        _, R, t, mask = cv2.recoverPose(E, xa, xb, K, mask=mask)
        inl = mask.ravel() > 0
        P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
        P2 = K @ np.hstack([R, t.reshape(3, 1) * float(np.linalg.norm(cb - ca))])  # |t| = 1: the GNSS baseline
        X = cv2.triangulatePoints(P1, P2, xa[inl].T, xb[inl].T)
        X = (X[:3] / X[3]).T
        below = X[np.isfinite(X).all(axis=1), 2]
    below = below[below > 0]
    return float(np.median(below)) if len(below) >= cfg.min_points else None


def flying_height(images: pa.Table, camera: Camera, load: Callable[[str], np.ndarray],
                  config: GroundConfig | None = None) -> FlyingHeight:
    """The flying height above the ground of a block with GNSS positions (module docstring for the method).

    ``images``: an ``images`` table (:mod:`aerocal.tables`: ``path``, ``time``, ``gnss_x/y/z`` in a projected
    CRS in metres, the recorded attitude where there is one); ``camera``: the nominal camera (pixels);
    ``load(path)``: the frame as an 8-bit grey image (the enhanced frames matching uses).
    """
    cfg = config or GroundConfig()
    pairs = _pairs(images, cfg)
    if not pairs:
        return FlyingHeight(None, (), f"no two consecutive frames with positions {cfg.min_baseline_m:g} m or more "
                                      "apart: the block's ground cannot be measured from its images")
    paths = images.column("path").to_pylist()
    xyz = np.column_stack([np.asarray(images.column(c).to_pylist(), dtype=float) for c in ("gnss_x", "gnss_y",
                                                                                          "gnss_z")])
    heights = []
    for a, b in pairs:
        grey_a, grey_b = load(paths[a]), load(paths[b])
        if grey_a.ndim == 3:
            grey_a, grey_b = (cv2.cvtColor(g, cv2.COLOR_RGB2GRAY) for g in (grey_a, grey_b))
        matched = _matches(grey_a, grey_b, cfg)
        if matched is None:
            continue
        h = _pair_height(*matched, camera, xyz[[a, b]], (_recorded_R_cw(images, a), _recorded_R_cw(images, b)), cfg)
        if h is not None:
            heights.append(h)
    if not heights:
        return FlyingHeight(None, (), f"none of {len(pairs)} pairs of consecutive frames gave enough tie points to "
                                      "measure the ground")
    med = float(np.median(heights))
    spread = (f", {min(heights):.1f}-{max(heights):.1f} m over pairs" if len(heights) > 1 else "")
    return FlyingHeight(med, tuple(heights), f"from the block's tie points: median {med:.1f} m below the cameras over "
                                             f"{len(heights)} of {len(pairs)} pairs of consecutive frames intersected "
                                             f"from their recorded positions{spread}")
