"""Dense surface of an adjusted block: semi-global matching on rectified pairs, fused across views.

What :func:`dense_cloud` does, for every frame of the block (the *reference*), as one task per frame:

1. **Neighbours** (:func:`select_neighbours`): the frames whose footprints on the ground plane cover at least
   ``min_overlap`` of the reference's, with a base-to-height ratio between ``min_base_to_height`` (depth too
   weak) and ``max_base_to_height`` (views too different for area matching); the ``neighbours`` of them with the
   largest overlap times base-to-height ratio (a narrow thermal camera's consecutive frames are 0.06 apart); then
   any frame, whatever its overlap, that sees ground of the reference's footprint none of those sees.
2. **Rectification** (:func:`rectify`): both frames are resampled (``cv2.remap``) onto a common plane whose x
   axis is the baseline, through the full model of each frame (the certificate's IO with its distortion and
   affinity, a rolling readout's row-by-row centres and the thermal corrections, taken at the frame's viewing
   depth): a ground point lies on the same row of both, ``d = f B / z`` pixels apart. The construction is
   Fusiello, Trucco & Verri (2000), with the plane's z axis the mean of the two optical axes; OpenCV's
   ``stereoRectify`` does the same for a pinhole with its own distortion model, not ours.
3. **Semi-global matching**: OpenCV's ``StereoSGBM`` (3-way, Birchfield-Tomasi cost on the x-Sobel prefiltered
   8-bit frames, uniqueness and speckle filters; its ``disp12MaxDiff`` is the left-right consistency check).
   The disparity search spans the adjusted tie points seen in both frames, widened by ``disparity_margin_px``:
   the surface cannot be where no tie point suggests it, and a narrow search is both faster and harder to fool.
   The frames are moved along their rows so that the search starts at 0 (:func:`matching_window`): SGBM matches
   no column left of its search's end.
   Pixels whose neighbourhood holds less than ``min_texture`` grey levels of contrast get no disparity: SGBM
   carries its paths' values across a uniform area, and two pairs would carry them alike.
4. **Depth in the reference**: each disparity map is read back at the reference's own pixels (its rays through
   the rectification), giving one depth map along the reference's optical axis per neighbour.
5. **Multi-view fusion**: a pixel keeps a depth only where at least ``min_agreeing_pairs`` pairs agree within
   ``agreement_px`` pixels of disparity (the reference and at least two other views: where the pairs disagree,
   a moving object, or find nothing, a uniform area, the surface stays a hole); the depth is the mean of the
   agreeing pairs weighted by their precision (the inverse square of their tolerance). A pixel that one pair
   alone covers (a ground point two frames see, as much of a block flown at 60 % forward overlap) keeps that
   pair's depth as a two-view point (``two_view``): nothing can check it, so the cloud's ``views`` say 2, it is
   left out of any cell where a point of three views lies, and the DSM's views band flags its cells. A pixel that
   other pairs cover but could not match stays a hole. The fused map is smoothed where its neighbours lie at a
   similar depth (:func:`smooth_depth`: an edge-preserving filter; a hole stays a hole). A point is kept by the
   ``keep_frames`` frames whose projection centres are nearest to it in plan (each ground point from the most
   nadir frames that measured it), so the cloud holds a few points per ground sample, not one per view, and the
   DSM takes the median of their heights. Where the nearest frame's pairs left a hole (an occlusion, pairs that
   disagree), the farther frames fill it only where two of them agree, in the cell or one next to it
   (:func:`confirmed`).

Frames larger than ``max_image_pixels`` are matched at a reduced scale (the same for all frames); the cloud's
ground sampling distance is then that of the reduced frames.

Conventions: world coordinates are the flight's projected CRS (E, N, up, metres); frame pixels follow
:class:`aerocal.camera.Camera` (top-left corner of the first pixel at (0, 0)); arrays passed to OpenCV use its
convention (centre of the first pixel at (0, 0)).
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numba
import numpy as np
from scipy.ndimage import maximum_filter
from scipy.spatial import cKDTree

from aerocal.camera import correct_measurements
from aerocal.products.dsm import Dsm, median_in_place
from aerocal.products.mosaic import FrameGeometry

#: A frame's pixels for matching: image id -> (8-bit grey frame for SGBM, frame values for the cloud's
#: attribute (counts, grey level) at full resolution; both (height, width) of the camera)
FrameLoader = Callable[[int], tuple[np.ndarray, np.ndarray]]

#: the rectification maps are computed every MAP_STEP rectified pixels and interpolated between
MAP_STEP = 8
#: rectified columns two frames must share at every searched disparity for their pair to be matched
MIN_SEARCH_COLUMNS = 32
#: ground points per side of the grid over a frame's footprint on which neighbours' overlap and coverage are judged
COVERAGE_SAMPLES = 12


@dataclass(frozen=True)
class DenseConfig:
    """How the dense surface is matched and fused. Pixels are those of the matched (possibly reduced) frames.

    Defaults: 6 neighbours give each pixel up to 6 depths, enough for two to agree where one pair is occluded.
    The block, the smoothness and the agreement were chosen on rendered thermal frames against their true surface
    (``benchmarks/RESULTS.md``, "Dense surface"): OpenCV's suggested penalties (``smoothness`` 1) pull low-contrast
    roofs and trees towards the ground around them; with a twentieth of them the matching is nearly local and the
    multi-view agreement, not the smoothness, removes the noise.
    """

    neighbours: int = 6  #: neighbours matched with each reference frame
    min_overlap: float = 0.3  #: fraction of the reference footprint a neighbour must cover
    min_base_to_height: float = 0.03  #: weaker baselines give depth too noisy to fuse
    max_base_to_height: float = 1.0  #: wider baselines see the surface too differently for area matching
    #: larger frames are matched at a reduced scale (the same for every frame), their cloud then one point per
    #: reduced pixel: SGBM's time and memory grow with the pixels matched, and a thermal frame (0.3 MP) is matched
    #: whole; the default keeps a visible flight's dense step near its thermal ones' (not measured apart)
    max_image_pixels: int = 1_000_000
    block_size: int = 7  #: SGBM matching block, pixels (odd)
    #: SGBM's penalties for disparity changes of 1 and more pixels, as a multiple of OpenCV's suggested
    #: P1 = 8 b^2 and P2 = 32 b^2 (b the block size)
    smoothness: float = 0.05
    uniqueness_ratio: int = 10  #: SGBM: best cost must beat the second by this percentage
    speckle_window: int = 64  #: SGBM: disparity blobs smaller than this (pixels) are removed ...
    speckle_range: int = 2  #: ... when their disparity varies within this (pixels)
    min_texture: float = 1.0  #: grey levels of standard deviation a pixel's neighbourhood needs to be matched
    disparity_margin_px: float = 8.0  #: added on each side of the tie points' disparity range
    max_disparities: int = 256  #: cap on the disparity search width (pixels; SGBM's cost grows with it)
    agreement_px: float = 0.5  #: two pairs agree when their depths differ by at most this disparity
    min_agreeing_pairs: int = 2  #: pairs that must agree (2: the reference and two other views)
    #: where one pair alone covers a pixel (a ground point two frames see: most of a block flown at 60 % forward
    #: overlap), keep its depth as a two-view point; nothing can check it against a third view, so it is kept
    #: only where no other pair covers the pixel, and only in cells where no point of three views or more lies
    two_view: bool = True
    #: frames that keep a ground point, the nearest in plan first (module docstring, step 5): with one, a point
    #: the nearest frame's pairs could not fuse is a hole however many other frames measured it
    keep_frames: int = 3
    #: a farther frame's point is kept within this many ground samples of the nearest frames' median height in
    #: its cell or, where they measured none, of the farther frames' when two of them agree (:func:`confirmed`)
    fill_agreement_gsd: float = 3.0
    #: the fused depth map is smoothed by an edge-preserving (bilateral) filter over a window of this radius
    #: (pixels; 0: not smoothed) before its points are made (:func:`smooth_depth`): a pixel's depth becomes the
    #: mean of its neighbours' weighted by nearness (a Gaussian of ``0.8 * smoothing_radius_px`` pixels) and by
    #: depth (a Gaussian of ``smoothing_range_gsd`` ground samples), so noise averages out where the surface is
    #: smooth and a step of several ground samples (a roof's rim) keeps both its sides
    smoothing_radius_px: int = 5
    smoothing_range_gsd: float = 1.5

    def __post_init__(self) -> None:
        if self.neighbours < 1:
            raise ValueError(f"DenseConfig.neighbours must be at least 1, got {self.neighbours}")
        if not 0.0 < self.min_overlap < 1.0:
            raise ValueError(f"DenseConfig.min_overlap must be in (0, 1), got {self.min_overlap}")
        if not 0.0 <= self.min_base_to_height < self.max_base_to_height:
            raise ValueError("DenseConfig: need 0 <= min_base_to_height < max_base_to_height, got "
                             f"{self.min_base_to_height} and {self.max_base_to_height}")
        if self.block_size < 3 or self.block_size % 2 == 0:
            raise ValueError(f"DenseConfig.block_size must be odd and at least 3, got {self.block_size}")
        if self.max_image_pixels < 10_000:
            raise ValueError(f"DenseConfig.max_image_pixels must be at least 10000, got {self.max_image_pixels}")
        if not 16 <= self.max_disparities <= 1024:
            raise ValueError(f"DenseConfig.max_disparities must be in [16, 1024], got {self.max_disparities}")
        if self.min_texture < 0:
            raise ValueError(f"DenseConfig.min_texture must be >= 0, got {self.min_texture}")
        if not self.smoothness > 0:
            raise ValueError(f"DenseConfig.smoothness must be positive, got {self.smoothness}")
        if not self.agreement_px > 0:
            raise ValueError(f"DenseConfig.agreement_px must be positive, got {self.agreement_px}")
        if self.min_agreeing_pairs < 1:
            raise ValueError(f"DenseConfig.min_agreeing_pairs must be at least 1, got {self.min_agreeing_pairs}")
        if self.keep_frames < 1:
            raise ValueError(f"DenseConfig.keep_frames must be at least 1, got {self.keep_frames}")
        if not self.fill_agreement_gsd > 0:
            raise ValueError(f"DenseConfig.fill_agreement_gsd must be positive, got {self.fill_agreement_gsd}")
        if self.smoothing_radius_px < 0:
            raise ValueError(f"DenseConfig.smoothing_radius_px must be >= 0, got {self.smoothing_radius_px}")
        if not self.smoothing_range_gsd > 0:
            raise ValueError(f"DenseConfig.smoothing_range_gsd must be positive, got {self.smoothing_range_gsd}")


@dataclass(frozen=True)
class PairPlan:
    """One reference-neighbour pair to match: the neighbour and the SGBM disparity search for it."""

    other: int  #: image id of the neighbour
    min_disparity: int  #: SGBM minDisparity (rectified pixels, may be negative)
    num_disparities: int  #: SGBM numDisparities (a multiple of 16)
    #: the pair's :func:`rectify` as planned (None: :func:`pair_depth` computes it)
    rect: Rectification | None = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class DenseCloud:
    """The fused dense cloud. ``xyz`` (N, 3) float64 world metres; ``value`` (N,) float32 the reference frame's
    value at the point (counts of a radiometric frame, grey level otherwise); ``views`` (N,) uint8 frames that
    agree on it; ``image_id`` (N,) int32 the reference frame that kept it. ``gsd_m`` is the matched frames'
    median ground sample distance; ``stats`` counts frames, pairs and points."""

    xyz: np.ndarray
    value: np.ndarray
    views: np.ndarray
    image_id: np.ndarray
    gsd_m: float
    stats: Mapping[str, float]
    rank: np.ndarray | None = None  #: (N,) uint8: 0 where the frame that kept the point is the nearest to it


def matching_scale(frames: Sequence[FrameGeometry], max_image_pixels: int) -> float:
    """The scale (<= 1) at which frames are matched: at most ``max_image_pixels`` per frame."""
    px = max(f.camera.width * f.camera.height for f in frames)
    return float(min(1.0, np.sqrt(max_image_pixels / px)))


def _border(frame: FrameGeometry, n: int = 12) -> np.ndarray:
    w, h = float(frame.camera.width), float(frame.camera.height)
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    return np.concatenate([np.column_stack([t * w, 0 * t]), np.column_stack([0 * t + w, t * h]),
                           np.column_stack([w - t * w, 0 * t + h]), np.column_stack([0 * t, h - t * h])])


def _border_rays(frame: FrameGeometry) -> np.ndarray:
    """The world ray directions (48, 3) of points along the frame's border (:func:`rectify` bounds a pair's
    rectified frames by them)."""
    return _world_rays(frame, _border(frame))


def _world_rays(frame: FrameGeometry, uv: np.ndarray) -> np.ndarray:
    """Frame pixels (..., 2) -> world ray directions (..., 3) with unit z in the camera frame."""
    xy = frame.camera.unproject(uv)
    ray = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    return ray @ np.asarray(frame.R_cw)


def select_neighbours(frames: Sequence[FrameGeometry], ground_height_m: float,
                      config: DenseConfig) -> dict[int, list[int]]:
    """Image id -> the ids of the frames matched with it, best first (see the module docstring).

    Overlap is measured on the plane at ``ground_height_m`` (metres): the fraction of a grid of ground points
    in the reference's footprint that the other frame sees. Candidates are ranked by overlap times
    base-to-height ratio: the area the pair measures times the precision it measures it with; the first
    ``config.neighbours`` of those covering ``config.min_overlap`` are matched. Then ground of the footprint that
    none of them sees but another frame does (a block's side-lap under 30 %, a strip's end) gets that frame too,
    best ranked first, whatever its overlap: without it, ground that two frames of different strips alone see is a
    hole however well both frames match.
    """
    cam_xy = np.array([f.C[:2] for f in frames])
    heights = np.array([f.C[2] - ground_height_m for f in frames])
    side = np.linspace(0.02, 0.98, COVERAGE_SAMPLES)
    grid = np.stack(np.meshgrid(side, side), -1).reshape(-1, 2)
    samples = []
    for f in frames:
        uv = grid * [f.camera.width, f.camera.height]
        d = _world_rays(f, uv)
        s = (ground_height_m - f.C[2]) / np.where(d[:, 2] < -1e-9, d[:, 2], np.nan)
        X = np.column_stack([f.C[:2] + s[:, None] * d[:, :2], np.full(len(s), ground_height_m)])
        samples.append(X[np.all(np.isfinite(X), axis=1)])
    # a frame that sees any of the reference's footprint has its centre within the two footprints' reach
    radius = np.array([float(np.max(np.linalg.norm(s[:, :2] - f.C[:2], axis=1), initial=0.0))
                       for s, f in zip(samples, frames, strict=True)])
    reach = min(2.0 * np.max(heights) * max(1.0, config.max_base_to_height), 2.5 * float(np.max(radius)))
    tree = cKDTree(cam_xy)
    # the pairs within reach and base-to-height, grouped by the frame that sees the other's samples: one projection
    # per frame of every sample set it is asked about (a projection per pair took 3.5-5.0 s of a city's 818 frames)
    asked: list[list[int]] = [[] for _ in frames]
    usable: list[list[tuple[int, float]]] = []  # per frame, its pairs (j, base-to-height) in the tree's order
    for i, f in enumerate(frames):
        usable.append([])
        for j in tree.query_ball_point(cam_xy[i], reach):
            bh = float(np.linalg.norm(frames[j].C - f.C)) / max(heights[i], 1e-9)
            if j != i and len(samples[i]) and config.min_base_to_height <= bh <= config.max_base_to_height:
                asked[j].append(i)
                usable[i].append((j, bh))
    seen_by: dict[tuple[int, int], np.ndarray] = {}
    for j, refs in enumerate(asked):
        if not refs:
            continue
        uv = frames[j].project(np.concatenate([samples[i] for i in refs]))
        seen = np.all(np.isfinite(uv), axis=1) & frames[j].camera.in_image(uv)
        bounds = np.cumsum([0] + [len(samples[i]) for i in refs])
        for i, lo, hi in zip(refs, bounds[:-1], bounds[1:], strict=True):
            seen_by[i, j] = seen[lo:hi]
    out: dict[int, list[int]] = {}
    for i, f in enumerate(frames):
        cand = []
        for j, bh in usable[i]:  # the tree's order: the stable sort's ties
            seen = seen_by[i, j]
            if seen.any():
                cand.append((float(np.mean(seen)) * bh, float(np.mean(seen)), j, seen))
        cand.sort(key=lambda t: -t[0])
        chosen = [c for c in cand if c[1] >= config.min_overlap][:config.neighbours]
        covered = np.zeros(len(samples[i]), dtype=bool)
        for c in chosen:
            covered |= c[3]
        taken = {c[2] for c in chosen}
        for c in cand:
            if c[2] not in taken and (c[3] & ~covered).any():
                chosen.append(c)
                covered |= c[3]
        out[f.image_id] = [frames[c[2]].image_id for c in chosen]
    return out


@dataclass(frozen=True)
class Rectification:
    """A rectified pair at the matching scale. ``R`` (3, 3) world-to-rectified rotation; ``f`` focal length
    (rectified pixels); ``cy`` common principal row; ``cx_left`` / ``cx_right`` principal columns of each
    rectified frame; ``size`` (width, height); ``baseline_m`` the distance between the projection centres."""

    R: np.ndarray
    f: float
    cy: float
    cx_left: float
    cx_right: float
    size: tuple[int, int]
    baseline_m: float

    def rect_pixels(self, rays_world: np.ndarray, left: bool) -> np.ndarray:
        """World ray directions (..., 3) from the left (or right) projection centre -> rectified pixels
        (OpenCV convention, ..., 2); NaN behind the plane."""
        r = rays_world @ self.R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(r[..., 2] > 1e-9, r[..., 2], np.nan)
        cx = self.cx_left if left else self.cx_right
        return np.stack([cx + self.f * r[..., 0] / z, self.cy + self.f * r[..., 1] / z], axis=-1)

    def disparity_of(self, X: np.ndarray, C_left: np.ndarray) -> np.ndarray:
        """Disparity (left column minus right column, rectified pixels) of world points ``X`` (N, 3)."""
        z = (np.asarray(X) - C_left) @ self.R[2]
        return self.f * self.baseline_m / z + (self.cx_left - self.cx_right)


def rectify(left: FrameGeometry, right: FrameGeometry, scale: float, max_size_factor: float = 2.0,
            border_rays: tuple[np.ndarray, np.ndarray] | None = None) -> Rectification:
    """The rectification of a pair (module docstring, step 2) at ``scale``; rectified frames are at most
    ``max_size_factor`` times the matched frames' size (a strongly oblique pair is cropped, not blown up).
    ``border_rays``: each frame's :func:`_border_rays`, where the caller holds them (a frame of a block is in
    several pairs).

    Raises:
        ValueError: the projection centres coincide (no baseline).
    """
    base = np.asarray(right.C, dtype=float) - np.asarray(left.C, dtype=float)
    b = float(np.linalg.norm(base))
    if not b > 1e-6:
        raise ValueError(f"rectify: frames {left.image_id} and {right.image_id} share a projection centre")
    e1 = base / b
    axis = np.asarray(left.R_cw)[2] + np.asarray(right.R_cw)[2]
    e2 = np.cross(axis, e1)
    e2 /= np.linalg.norm(e2)
    R = np.stack([e1, e2, np.cross(e1, e2)])
    f = 0.5 * (left.camera.f + right.camera.f) * scale
    ext = []
    for rays in border_rays or (_border_rays(left), _border_rays(right)):
        r = rays @ R.T
        ok = r[:, 2] > 1e-9
        ext.append(f * r[ok, :2] / r[ok, 2:3])
    w0, h0 = max(left.camera.width, right.camera.width) * scale, max(left.camera.height, right.camera.height) * scale
    vmin = max(float(e[:, 1].min()) for e in ext)
    vmax = min(float(e[:, 1].max()) for e in ext)
    vmid, vhalf = 0.5 * (vmin + vmax), 0.5 * min(vmax - vmin, max_size_factor * h0)
    widths = [min(float(e[:, 0].max() - e[:, 0].min()), max_size_factor * w0) for e in ext]
    cx = [-0.5 * (float(e[:, 0].max() + e[:, 0].min())) + 0.5 * w for e, w in zip(ext, widths, strict=True)]
    width = int(np.ceil(max(widths)))
    height = max(int(np.ceil(2 * vhalf)), 1)
    return Rectification(R=R, f=f, cy=vhalf - vmid, cx_left=cx[0], cx_right=cx[1], size=(width, height),
                         baseline_m=b)


def viewing_depth(frame: FrameGeometry, ground_height_m: float) -> float:
    """The depth (metres, along the optical axis) at which the frame sees the plane at ``ground_height_m``."""
    down = -float(np.asarray(frame.R_cw)[2, 2])
    return float((frame.C[2] - ground_height_m) / max(down, 0.2))


def _upsample(coarse: np.ndarray, step: int, h: int, w: int, channels_last: bool = False) -> np.ndarray:
    """Bilinear interpolation of ``coarse`` (hs, ws, C), whose node (i, j) lies at pixel (i step, j step), onto
    the pixels of an (h, w) grid (nodes past the last are extrapolated from the last two): float32 (C, h, w), each
    plane contiguous as ``cv2.remap`` takes its maps, or (h, w, C) with ``channels_last``.

    Float32 (OpenCV's resize and remap quantise the weights to 1/32, and float32 keeps a 4000-pixel coordinate to
    0.0005 px), in one compiled pass per plane (:func:`_upsample_into`): 3.4 times as fast as the two products with
    the interpolation weights it replaced, whose weights were mostly zeros (a 330 x 620 rectified frame, 2 planes;
    ``benchmarks/RESULTS.md``, "Dense surface: the rectification's maps in one pass")."""
    c = coarse.shape[2]
    out = np.empty((h, w, c) if channels_last else (c, h, w), dtype=np.float32)
    _upsample_into(np.ascontiguousarray(coarse, dtype=np.float32), step,
                   np.moveaxis(out, -1, 0) if channels_last else out)
    return out


@numba.njit(cache=True, nogil=True)
def _upsample_into(coarse: np.ndarray, step: int, out: np.ndarray) -> None:
    """:func:`_upsample` into ``out`` (C, h, w): per output row, its nodes between the two node rows around it,
    then each pixel between its two nodes."""
    hs, ws = coarse.shape[0], coarse.shape[1]
    h, w = out.shape[1], out.shape[2]
    one = np.float32(1.0)
    node = np.empty(w, dtype=np.int64)
    frac = np.empty(w, dtype=np.float32)
    for x in range(w):
        node[x] = min(x // step, ws - 2)
        frac[x] = np.float32(x / step - node[x])
    row = np.empty(ws, dtype=np.float32)
    slope = np.empty(ws, dtype=np.float32)
    for k in range(out.shape[0]):
        for y in range(h):
            i = min(y // step, hs - 2)
            fy = np.float32(y / step - i)
            for j in range(ws):
                row[j] = (one - fy) * coarse[i, j, k] + fy * coarse[i + 1, j, k]
            for j in range(ws - 1):
                slope[j] = row[j + 1] - row[j]
            for x in range(w):
                out[k, y, x] = row[node[x]] + frac[x] * slope[node[x]]


def _rectified(frame: FrameGeometry, rect: Rectification, image: np.ndarray, left: bool,
               scale: float, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """``image`` (the frame at ``scale``) resampled onto the rectified grid (bilinear; outside: 0), and where the
    rectified grid lies inside the frame (bool).

    Each rectified pixel is looked up where the frame recorded the point at ``depth`` (metres) on its ray
    (:meth:`FrameGeometry.project`: the rows of a rolling readout, each exposed from its own centre, and the
    thermal models that correct measurements): the rectified frame is the frame a global shutter at ``C`` would
    have taken, to within the readout's displacement times the relief over the depth."""
    w, h = rect.size
    cx = rect.cx_left if left else rect.cx_right
    # the frame model on a grid every MAP_STEP pixels, bilinear between: the map is smooth (distortion, readout),
    # and the full model at every pixel took half of a pair's time (at most 0.006 px apart on a
    # 640x512 camera with k1 = -0.25, k2 = 0.1)
    hs, ws = -(-(h - 1) // MAP_STEP) + 1, -(-(w - 1) // MAP_STEP) + 1
    uu, vv = np.meshgrid(np.arange(ws, dtype=float) * MAP_STEP, np.arange(hs, dtype=float) * MAP_STEP)
    ray_rect = np.stack([(uu - cx) / rect.f, (vv - rect.cy) / rect.f, np.ones_like(uu)], -1)
    ray_w = ray_rect @ rect.R
    with np.errstate(divide="ignore", invalid="ignore"):
        along = ray_w @ np.asarray(frame.R_cw)[2]
        X = np.asarray(frame.C) + depth * ray_w / np.where(along > 1e-9, along, np.nan)[..., None]
    uv = frame.project(X)  # frame pixels, top-left convention
    coarse = np.nan_to_num(uv * scale - 0.5, nan=-10.0)
    map_x, map_y = _upsample(coarse, MAP_STEP, h, w)  # each plane contiguous
    h_img, w_img = image.shape[:2]
    inside = (map_x >= 0) & (map_x <= w_img - 1) & (map_y >= 0) & (map_y <= h_img - 1)
    out = cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out, inside


def plan_pairs(frames: Sequence[FrameGeometry], neighbours: Mapping[int, Sequence[int]], tie_xyz: np.ndarray,
               scale: float, config: DenseConfig) -> dict[int, list[PairPlan]]:
    """The disparity search of every pair from the tie points (world metres, (N, 3)) both frames see: their
    2nd to 98th percentile disparity, widened by a quarter of that span and ``disparity_margin_px``; with fewer
    than 10 shared tie points, those the reference sees. Pairs without any are left out, and pairs whose search
    leaves fewer than :data:`MIN_SEARCH_COLUMNS` columns of the rectified frame to match."""
    planner = _PairPlanner(frames, tie_xyz, scale, config)
    return {ref: planner.plans(ref, others) for ref, others in neighbours.items()}


class _PairPlanner:
    """:func:`plan_pairs` one reference at a time (a Dask client is handed each reference's pairs as they are
    planned): which tie points each frame sees is settled once, on construction."""

    def __init__(self, frames: Sequence[FrameGeometry], tie_xyz: np.ndarray, scale: float,
                 config: DenseConfig) -> None:
        self.by_id = {f.image_id: f for f in frames}
        self.tie_xyz = np.asarray(tie_xyz, dtype=float)
        self.scale, self.config = scale, config
        tree = cKDTree(self.tie_xyz[:, :2])
        self.seen = {}
        self.border_rays = {f.image_id: _border_rays(f) for f in frames}
        typical = float(np.median(self.tie_xyz[:, 2]))
        for f in frames:  # the tie points near the frame's footprint only: a city block holds 10^5 of them
            reach = 1.5 * float(np.max(np.linalg.norm(f.ground_footprint([typical]) - f.C[:2], axis=1), initial=0.0))
            near = np.asarray(tree.query_ball_point(f.C[:2], max(reach, 1.0)), dtype=np.int64)
            uv = f.project(self.tie_xyz[near])
            mask = np.zeros(len(self.tie_xyz), dtype=bool)
            mask[near[np.all(np.isfinite(uv), axis=1) & f.camera.in_image(uv)]] = True
            self.seen[f.image_id] = mask

    def plans(self, ref: int, others: Sequence[int]) -> list[PairPlan]:
        """The pairs of ``ref`` with ``others`` that can be matched, with their disparity search."""
        config, by_id = self.config, self.by_id
        plans = []
        for o in others:
            both = self.seen[ref] & self.seen[o]
            pts = self.tie_xyz[both] if both.sum() >= 10 else self.tie_xyz[self.seen[ref]]
            if len(pts) < 3:
                continue
            rect = rectify(by_id[ref], by_id[o], self.scale,
                           border_rays=(self.border_rays[ref], self.border_rays[o]))
            d = rect.disparity_of(pts, by_id[ref].C)
            d = d[np.isfinite(d)]
            if len(d) < 3:
                continue
            lo, hi = np.percentile(d, [2.0, 98.0])
            pad = 0.25 * (hi - lo) + config.disparity_margin_px
            lo, hi = int(np.floor(lo - pad)), int(np.ceil(hi + pad))
            num = int(min(config.max_disparities, 16 * np.ceil(max(hi - lo, 16) / 16)))
            if num < hi - lo:  # capped: centre the search on the median
                lo = int(np.round(np.median(d))) - num // 2
            # frames that overlap by fewer than MIN_SEARCH_COLUMNS rectified columns at every searched disparity
            # give no depth (and OpenCV's 3-way SGBM fails on a window that narrow with a negative allocation)
            if rect.size[0] - max(abs(lo), abs(lo + num)) < MIN_SEARCH_COLUMNS:
                continue
            plans.append(PairPlan(other=o, min_disparity=lo, num_disparities=num, rect=rect))
        return plans


def _reference_grid(frame: FrameGeometry, scale: float, depth: float) -> np.ndarray:
    """The world rays (h, w, 3) from ``C`` of the reference's pixel centres at ``scale``, with unit length along the
    optical axis: as :func:`_rectified` sees them (a thermal model's correction applied, a rolling readout's row
    centre moved to ``C`` at ``depth`` metres)."""
    w, h = int(round(frame.camera.width * scale)), int(round(frame.camera.height * scale))
    # the model on a grid every MAP_STEP pixels, bilinear between (as the rectification maps: the rays are as
    # smooth as the distortion and the readout; the full model at every pixel took a tenth of a reference's time)
    hs, ws = -(-(h - 1) // MAP_STEP) + 1, -(-(w - 1) // MAP_STEP) + 1
    uu, vv = np.meshgrid((np.arange(ws) * MAP_STEP + 0.5) / scale, (np.arange(hs) * MAP_STEP + 0.5) / scale)
    uv = np.stack([uu, vv], -1)
    if frame.thermal_model is not None:
        uv_ideal = correct_measurements(frame.camera, uv.reshape(-1, 2), frame.temperature, frame.thermal_model)
        rays = _world_rays(frame, uv_ideal.reshape(uv.shape))
    else:
        rays = _world_rays(frame, uv)
    if frame.motion is not None:
        frac = uv[..., 1:2] / frame.camera.height - 0.5
        g = frac * np.asarray(frame.motion, dtype=float) + depth * rays
        rays = g / (g @ np.asarray(frame.R_cw)[2])[..., None]
    return _upsample(rays, MAP_STEP, h, w, channels_last=True)  # (h, w, 3) contiguous: each pair reads it


def matching_window(rect: Rectification, plan: PairPlan) -> tuple[Rectification, PairPlan]:
    """The pair's rectification with its frames moved along the rows so that SGBM matches every column of the
    reference the other frame can see and no other, and the search in the moved frames (from disparity 0).

    OpenCV's SGBM gives no disparity to the reference's columns x < minDisparity + numDisparities (its cost volume
    needs x - d inside the frame for every searched d) nor to x >= width + minDisparity, and costs every column of
    the frame. With each frame at its own principal column, the disparities of a pair are its frames' offset, often
    most of a thermal frame's width (a search of 221-253 px on a 493-px rectified pair): SGBM left half of such a
    reference unmatched, and the ground that pair alone sees (a block's outer strips) a hole, while it costed those
    columns all the same. Moving the reference ``a = numDisparities - max(minDisparity, 0)`` columns right (left
    where negative) and the other frame ``a + minDisparity`` (both principal columns; the depth of a disparity is
    unchanged, as it is measured from the principal columns' difference) starts the search at 0 and puts the first
    column that the other frame can see (``max(minDisparity, 0)``) at ``numDisparities``: the columns before it,
    which no searched disparity pairs with the other frame, are cut off, and SGBM's frame is ``a`` columns wider
    (narrower where negative)."""
    lo, num = plan.min_disparity, plan.num_disparities
    a = num - max(lo, 0)
    moved = Rectification(R=rect.R, f=rect.f, cy=rect.cy, cx_left=rect.cx_left + a, cx_right=rect.cx_right + a + lo,
                          size=(rect.size[0] + a, rect.size[1]), baseline_m=rect.baseline_m)
    return moved, PairPlan(other=plan.other, min_disparity=0, num_disparities=num)


def _resize(image: np.ndarray, scale: float) -> np.ndarray:
    if scale == 1.0:
        return image
    h, w = image.shape[:2]
    return cv2.resize(image, (int(round(w * scale)), int(round(h * scale))), interpolation=cv2.INTER_AREA)


def _sgbm(config: DenseConfig, plan: PairPlan) -> cv2.StereoSGBM:
    bs = config.block_size
    return cv2.StereoSGBM.create(
        minDisparity=plan.min_disparity, numDisparities=plan.num_disparities, blockSize=bs,
        P1=max(1, round(8 * config.smoothness * bs * bs)), P2=max(2, round(32 * config.smoothness * bs * bs)),
        disp12MaxDiff=1, preFilterCap=63,
        uniquenessRatio=config.uniqueness_ratio, speckleWindowSize=config.speckle_window,
        speckleRange=config.speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)


@numba.njit(cache=True)
def _disparity_px(raw: np.int16) -> np.float32:
    """One of SGBM's disparities (int16 sixteenths, a found one) in pixels, as :func:`sgbm_disparity` reads it."""
    d = np.float32(raw)
    sixteenth = raw & 15
    if sixteenth >= 9:
        d -= np.float32(1.0)
    elif sixteenth == 0:
        d -= np.float32(0.5)
    return d / np.float32(16.0)


def sgbm_disparity(raw: np.ndarray, min_disparity: int) -> np.ndarray:
    """OpenCV SGBM's disparities (int16, sixteenths of a rectified pixel) as pixels (float32), NaN where SGBM found
    none (below ``min_disparity``), with SGBM's sub-pixel rounding taken out.

    SGBM places the minimum of the parabola through the costs at d - 1, d, d + 1 with C integer division,
    ``(16 (S[d-1] - S[d+1]) + den) / (2 den)``, which truncates towards zero: an offset below -1/32 px comes out one
    sixteenth too high, and a reported whole pixel stands for [-3/32, +1/32) px. Read as is, disparities are 1/32 px
    too large on average, and every height is biased upwards by that much disparity (a test of sub-pixel shifts
    measures the 1/32 and its removal). Here the sixteenths 9-15 (the negative offsets) lose one sixteenth and a
    whole pixel half of one, the centre of what it stands for."""
    return _disparities(np.ascontiguousarray(raw, dtype=np.int16), np.int32(16 * min_disparity))


@numba.njit(cache=True)
def _disparities(raw: np.ndarray, min16: np.int32) -> np.ndarray:
    disp = np.full(raw.shape, np.nan, dtype=np.float32)
    for i in range(raw.shape[0]):
        for j in range(raw.shape[1]):
            if raw[i, j] >= min16:
                disp[i, j] = _disparity_px(raw[i, j])
    return disp


def pair_depth(ref: FrameGeometry, other: FrameGeometry, ref8: np.ndarray, other8: np.ndarray, plan: PairPlan,
               rays: np.ndarray, scale: float, config: DenseConfig,
               ground_height_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pair's depth at the reference's pixels: (depth along the reference's optical axis, metres, NaN where
    the pair found none; the depth tolerance of ``config.agreement_px`` disparity pixels at each pixel, metres;
    where the pair covers the pixel, bool: the other frame sees it at the middle of the disparity search, whether
    or not a depth was found).

    ``ref8`` / ``other8`` are the 8-bit frames at ``scale``; ``rays`` the reference's world rays
    (:func:`_reference_grid`); ``ground_height_m`` the plane at whose depth the frames are rectified."""
    rect, plan = matching_window(plan.rect if plan.rect is not None else rectify(ref, other, scale), plan)
    left, inside = _rectified(ref, rect, ref8, True, scale, viewing_depth(ref, ground_height_m))
    right, inside_right = _rectified(other, rect, other8, False, scale, viewing_depth(other, ground_height_m))
    raw = _sgbm(config, plan).compute(left, right)
    # semi-global matching carries disparities across a region without texture along its paths, and two pairs
    # interpolate it alike, so the fusion would keep it: a pixel whose block holds no texture gets no depth
    win = (2 * config.block_size + 1,) * 2
    mean = cv2.boxFilter(left, cv2.CV_32F, win)  # on the 8-bit frame: a fifth of the time of a float copy's
    var = cv2.sqrBoxFilter(left, cv2.CV_32F, win) - mean * mean
    usable = inside & (var >= config.min_texture ** 2)
    # back at the reference's pixels, in one compiled pass over them that reads SGBM's sixteenths as
    # sgbm_disparity does (the numpy passes and OpenCV's nearest-pixel remaps it replaces were about a third of a
    # reference's time: benchmarks/RESULTS.md, "City scale with the dense surface: the flow's memory"); covered:
    # the rectified left(x) inside the reference and right(x - d) inside the other frame, d the middle of the
    # search (the pair could have measured the pixel, whether it did or not)
    middle = np.float32(plan.min_disparity + 0.5 * plan.num_disparities)
    return _depth_at_reference(raw, np.int32(16 * plan.min_disparity), usable, inside, inside_right, rays,
                               np.ascontiguousarray(rect.R, dtype=np.float64),
                               float(rect.f), float(rect.cx_left), float(rect.cy), middle,
                               np.float32(rect.cx_left - rect.cx_right), float(rect.f * rect.baseline_m),
                               np.float32(config.agreement_px))


@numba.njit(cache=True)
def _depth_at_reference(raw: np.ndarray, min16: np.int32, usable: np.ndarray, inside: np.ndarray,
                        inside_right: np.ndarray, rays: np.ndarray,
                        R: np.ndarray, f: float, cx: float, cy: float, middle: np.float32, shift: np.float32,
                        f_base: float, agreement: np.float32) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`pair_depth` at the reference's pixels: each reference ray (``rays`` (h, w, 3), unit length along the
    optical axis) into the rectified left frame (``R``, ``f``, ``cx``, ``cy``; float32 pixels, the nearest rectified
    pixel as OpenCV's nearest-pixel remap takes it, round half to even), its disparity there (``raw``: SGBM's
    sixteenths, none below ``min16`` or where not ``usable``; read as :func:`sgbm_disparity` reads them) less
    ``shift`` (the rectified frames' principal columns apart) to a depth along the reference's axis and the
    depth tolerance of ``agreement`` disparity pixels (``f_base``: the rectified focal length times the baseline);
    covered where the rectified pixel is ``inside`` the reference and the pixel ``middle`` columns left of it is
    ``inside_right`` the other frame. Returns (depth, tolerance) float32, NaN where no depth, and covered (bool)."""
    h, w = rays.shape[0], rays.shape[1]
    rh, rw = raw.shape[0], raw.shape[1]
    depth = np.full((h, w), np.nan, dtype=np.float32)
    tol = np.full((h, w), np.nan, dtype=np.float32)
    covered = np.zeros((h, w), dtype=np.bool_)
    for i in range(h):
        for j in range(w):
            x0, x1, x2 = np.float64(rays[i, j, 0]), np.float64(rays[i, j, 1]), np.float64(rays[i, j, 2])
            r2 = R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2
            if not r2 > 1e-9:
                continue
            col = np.float32(cx + f * (R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2) / r2)
            row = np.float32(cy + f * (R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2) / r2)
            if not (-1.0 < col < rw and -1.0 < row < rh):  # outside (and no integer conversion of a huge value)
                continue
            c, r = int(np.rint(col)), int(np.rint(row))
            if not (0 <= c < rw and 0 <= r < rh):
                continue
            cr = int(np.rint(col - middle))
            covered[i, j] = inside[r, c] and 0 <= cr < rw and inside_right[r, cr]
            r16 = raw[r, c]
            if r16 < min16 or not usable[r, c]:
                continue
            d = _disparity_px(r16) - shift
            if d > 0:
                z_rect = np.float32(f_base) / d
                depth[i, j] = np.float32(np.float64(z_rect) / r2)
                tol[i, j] = np.float32(np.float64(agreement * z_rect * z_rect) / (f_base * r2))
    return depth, tol, covered


def fuse_depths(depths: np.ndarray, tols: np.ndarray, min_agreeing: int,
                covered: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fuse K depth maps (K, h, w) with their tolerances: per pixel the depth of the largest group of pairs that
    agree with one of them (|d_k - d_l| <= max(tol_k, tol_l); the first such pair on a tie), its mean weighted
    by precision (the inverse square of the tolerance, proportional to the sigma); NaN where fewer than
    ``min_agreeing`` pairs agree. With ``covered`` (K, h, w) bool, where each pair covers the pixel, a pixel that
    one pair alone covers keeps that pair's depth (a two-view point: no third view could check it; a pixel other
    pairs cover but could not match stays a hole). Returns (depth (h, w) float32, agreeing pairs (h, w) uint8).

    One pass per pixel (:func:`_fuse_pixels`): the same values as comparing every pair of maps with numpy
    (a test), in a tenth of the time and without its (K, K, h, w) arrays."""
    depths = np.ascontiguousarray(depths, dtype=np.float32)
    lone = covered is not None
    cover = (np.ascontiguousarray(covered, dtype=np.bool_) if lone
             else np.zeros((1, 1, 1), dtype=np.bool_))
    return _fuse_pixels(depths, np.ascontiguousarray(tols, dtype=np.float32), int(min_agreeing), cover, lone)


@numba.njit(cache=True)
def _fuse_pixels(depths: np.ndarray, tols: np.ndarray, min_agreeing: int, covered: np.ndarray,
                 lone: bool) -> tuple[np.ndarray, np.ndarray]:
    n_maps, h, w = depths.shape
    fused = np.full((h, w), np.nan, dtype=np.float32)
    agreeing = np.zeros((h, w), dtype=np.uint8)
    for y in range(h):
        for x in range(w):
            best, best_k = 0, -1
            for k in range(n_maps):
                dk = depths[k, y, x]
                if not np.isfinite(dk):
                    continue
                count = 0
                for m in range(n_maps):
                    dm = depths[m, y, x]
                    if np.isfinite(dm) and abs(dk - dm) <= max(tols[k, y, x], tols[m, y, x]):
                        count += 1
                if count > best:
                    best, best_k = count, k
            agreeing[y, x] = best
            if best_k < 0:
                continue
            if best < min_agreeing:
                if not lone or best != 1:
                    continue
                n_cover = 0
                for m in range(n_maps):
                    if covered[m, y, x]:
                        n_cover += 1
                if n_cover != 1 or not covered[best_k, y, x]:
                    continue
            dk = depths[best_k, y, x]
            total, weight = 0.0, 0.0
            for m in range(n_maps):
                dm = depths[m, y, x]
                if np.isfinite(dm) and abs(dk - dm) <= max(tols[best_k, y, x], tols[m, y, x]):
                    wm = 1.0 / (float(tols[m, y, x]) * float(tols[m, y, x]))
                    total += wm * dm
                    weight += wm
            fused[y, x] = total / weight
    return fused, agreeing


def smooth_depth(depth: np.ndarray, f_px: float, config: DenseConfig) -> np.ndarray:
    """``depth`` (h, w) float32 metres along the optical axis, NaN where none, smoothed by OpenCV's bilateral
    filter (``config.smoothing_radius_px``, ``config.smoothing_range_gsd``; the ground sample is the map's median
    depth over ``f_px``, the matched frame's focal length in pixels). A pixel without a depth stays without one and
    lends nothing to its neighbours: it enters the filter at a depth a hundred range widths beyond the map's
    deepest, where its weight underflows to zero. Returns a new float32 map (``depth`` itself when smoothing is off
    or no pixel has a depth).

    Why: a fused depth is each pixel's own; its noise (on the rendered test block's flat cells, 0.68-0.76 ground
    samples of height, NMAD) passes into the DSM, whose cells take the median of the few frames' points that fall
    in them. Averaging over the neighbours at a similar depth takes much of it out (0.55-0.62) and leaves a roof's
    rim (several ground samples high) where it was; a weighted median with the frame's grey levels as its guide did
    as well there but took 0.4-0.7 s per thermal frame against 11 ms on OpenCV's two threads, 26 ms on the one a
    worker gives it (``benchmarks/RESULTS.md``, "Dense surface: the depth maps smoothed" and "Dense surface: the
    cloud's tail on two threads").
    """
    if config.smoothing_radius_px == 0:
        return depth
    ok = np.isfinite(depth)
    if not ok.any():
        return depth
    width = float(config.smoothing_range_gsd * np.median(depth[ok]) / f_px)
    far = float(depth[ok].max()) + 100.0 * width
    x = np.where(ok, depth, np.float32(far)).astype(np.float32)
    y = cv2.bilateralFilter(x, 2 * config.smoothing_radius_px + 1, width, 0.8 * config.smoothing_radius_px)
    return np.where(ok, y, np.float32(np.nan))


@dataclass(frozen=True)
class ReferencePoints:
    """What one reference frame hands on (module docstring, steps 2-5): the points it keeps, ``origin + offset``
    world metres (``origin`` (3,) float64, the reference's projection centre; ``offset`` (N, 3) float32, each point's
    depth times its ray, as it is computed: float32 holds a kilometre to a tenth of a millimetre, and a city's
    workers send 18 bytes a point rather than 30 with float64 points), ``value`` (N,) float32, ``views`` (N,) uint8 and
    ``rank`` (N,) uint8 (0 where the reference is the frame nearest the point in plan, 1 the next, ...)."""

    origin: np.ndarray
    offset: np.ndarray
    value: np.ndarray
    views: np.ndarray
    rank: np.ndarray

    @classmethod
    def empty(cls) -> ReferencePoints:
        return cls(np.zeros(3), np.zeros((0, 3), np.float32), np.zeros(0, np.float32), np.zeros(0, np.uint8),
                   np.zeros(0, np.uint8))


def _nearness_rank(xy: np.ndarray, centre_xy: np.ndarray, centres_xy: np.ndarray, k: int) -> np.ndarray:
    """Rank (uint8) of the frame at ``centre_xy`` among the projection centres nearest each point ``xy`` (N, 2)
    in plan: the number of centres nearer to the point, capped at ``k`` (not among the k nearest).

    Only the centres within twice the points' reach of ``centre_xy`` can be nearer to any of them; the points
    are taken in square tiles (a 64th of that reach), and each tile settles what it can for all its points
    (:func:`_count_nearer`). A k-d tree of every centre gave the same ranks (a test) three times slower on a
    city block (818 centres, 300,000 points)."""
    rel = np.asarray(xy, dtype=float) - centre_xy
    if not len(rel):
        return np.zeros(0, dtype=np.uint8)
    reach = 2.0 * float(np.sqrt(np.max(np.einsum("ij,ij->i", rel, rel))))
    others = np.asarray(centres_xy, dtype=float) - centre_xy
    dist2 = np.einsum("ij,ij->i", others, others)
    near = (dist2 > 0) & (dist2 <= reach * reach)
    tile = max(reach / 64.0, 1e-6)
    # the points grouped by tile (the tiles' order is immaterial: each is settled on its own)
    order, bounds = _cells_in_order(_cell_keys(rel, tile)[0])
    return _count_nearer(rel, order, bounds, np.ascontiguousarray(others[near]), dist2[near], k, tile)


@numba.njit(cache=True)
def _count_nearer(rel: np.ndarray, order: np.ndarray, bounds: np.ndarray, others: np.ndarray, dist2: np.ndarray,
                  k: int, tile: float) -> np.ndarray:
    """Per point ``rel`` (N, 2), relative to a centre at the origin: how many of ``others`` (M, 2) are nearer,
    capped at ``k`` (``c`` is nearer to ``x`` than the origin when ``2 x . c > |c|^2``). The points
    ``order[bounds[t]:bounds[t + 1]]`` share a tile of side ``tile``: a centre nearer than the origin to every
    point of the disc around the tile counts for all of them, and one nearer to none is not tested."""
    out = np.empty(rel.shape[0], dtype=np.uint8)
    cand = np.empty(others.shape[0], dtype=np.int64)
    rho = 0.7072 * tile
    for t in range(bounds.shape[0] - 1):
        i0 = order[bounds[t]]
        cx = (np.floor(rel[i0, 0] / tile) + 0.5) * tile
        cy = (np.floor(rel[i0, 1] / tile) + 0.5) * tile
        dref = np.sqrt(cx * cx + cy * cy)
        lo, hi = dref - rho, dref + rho
        definite, nc = 0, 0
        for j in range(others.shape[0]):
            dj = np.sqrt((others[j, 0] - cx) ** 2 + (others[j, 1] - cy) ** 2)
            if dj + rho < lo:
                definite += 1
            elif dj - rho < hi:
                cand[nc] = j
                nc += 1
        for p in range(bounds[t], bounds[t + 1]):
            i = order[p]
            n = definite
            x, y = 2.0 * rel[i, 0], 2.0 * rel[i, 1]
            for q in range(nc):
                if n >= k:
                    break
                j = cand[q]
                if x * others[j, 0] + y * others[j, 1] > dist2[j]:
                    n += 1
            out[i] = min(n, k)
    return out


def reference_points(ref: FrameGeometry, others: Sequence[FrameGeometry], plans: Sequence[PairPlan],
                     load: FrameLoader, scale: float, centres_xy: np.ndarray, config: DenseConfig,
                     ground_height_m: float) -> ReferencePoints:
    """The fused points one reference frame keeps (module docstring, steps 2-5). ``centres_xy`` (M, 2): every
    frame's projection centre in plan, ``ref``'s among them; a point is kept when ``ref``'s is among the
    ``config.keep_frames`` nearest."""
    if not plans:
        return ReferencePoints.empty()
    ref8, ref_value = load(ref.image_id)
    ref8 = _resize(ref8, scale)
    rays = _reference_grid(ref, scale, viewing_depth(ref, ground_height_m))
    depths, tols, covered = [], [], []
    for other, plan in zip(others, plans, strict=True):
        other8, _ = load(other.image_id)
        d, t, c = pair_depth(ref, other, ref8, _resize(other8, scale), plan, rays, scale, config, ground_height_m)
        depths.append(d)
        tols.append(t)
        covered.append(c)
    fused, n = fuse_depths(np.stack(depths), np.stack(tols), config.min_agreeing_pairs,
                           np.stack(covered) if config.two_view else None)
    fused = smooth_depth(fused, float(ref.camera.f * scale), config)
    keep = np.isfinite(fused) & (fused > 0)
    C = np.asarray(ref.C, dtype=np.float64)
    offset = fused[keep][:, None] * rays[keep]  # float32, as both are
    rank = _nearness_rank(C[:2] + offset[:, :2], C[:2], centres_xy, config.keep_frames)
    mine = rank < config.keep_frames
    value = _resize(np.asarray(ref_value, dtype=np.float32), scale)
    if value.ndim == 3:
        value = value.mean(axis=2)
    return ReferencePoints(origin=C, offset=offset[mine], value=value[keep][mine].astype(np.float32),
                           views=(1 + n[keep][mine]).astype(np.uint8), rank=rank[mine])


def confirmed(xyz: np.ndarray, rank: np.ndarray, image_id: np.ndarray, cell_m: float, tol_m: float,
              views: np.ndarray | None = None) -> np.ndarray:
    """The points (bool mask) the cloud keeps (module docstring, step 5), cell by cell (``cell_m`` metres): every
    point of a frame nearest to it (rank 0); the farther frames' points within ``tol_m`` of the median height of
    the nearest frames' points where the cell has some, and where it has none, within ``tol_m`` of the median of
    the farther frames' points when two frames or more have such points, in the cell or, for the second frame, in
    one of the 8 cells around it at a height within ``tol_m`` (:func:`_confirm_cells`). With ``views`` (N,), the
    frames that agree on each point, a two-view point is left out of a cell that holds a point of three views or
    more: the cell has a checked height, and the unchecked one would only add its noise; its frame still counts
    among the two that confirm the cell (the nearest frame's one pair agreeing with a farther frame's three views).

    A farther frame's three agreeing views are not enough on their own: a vehicle moving along a pair's
    baseline looks like a height to every pair along it, and the nearest frame left the cell out because its
    pairs saw the vehicle move. A second frame, with other pairs, rarely agrees on the same wrong height."""
    if not len(xyz):
        return np.zeros(0, dtype=bool)
    xyz = np.asarray(xyz, dtype=np.float64)
    key, cols = _cell_keys(xyz, float(cell_m))
    if int(key.max()) < 4 * len(key) + 1_000_000:
        order, bounds = _cells_in_order(key)
    else:  # the cloud's box holds far more cells than points (a few points far off): no array per cell
        order = np.argsort(key, kind="stable")
        bounds = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1], True])
    cell_keys = key[order[bounds[:-1]]]  # each occupied cell's key, ascending
    del key
    views = (np.full(len(xyz), 3, dtype=np.uint8) if views is None else np.asarray(views, dtype=np.uint8))
    return _confirm_cells(order, bounds, cell_keys, int(cols), xyz, np.asarray(rank, dtype=np.uint8),
                          np.asarray(image_id), views, float(tol_m), 64 * numba.get_num_threads())


@numba.njit(cache=True)
def _cell_keys(xyz: np.ndarray, cell_m: float) -> tuple[np.ndarray, int]:
    """Each point's cell (``cell_m`` metres, counted from the cloud's south-west cell) as one int64, row-major, and
    the number of columns of that grid (a cell's key is row * columns + column): numpy's ``floor(xy / cell_m)`` per
    point without its (N, 2) temporaries (a city's cloud holds tens of millions of points)."""
    n = xyz.shape[0]
    c_min, r_min, c_max = np.inf, np.inf, -np.inf
    for i in range(n):
        c = np.floor(xyz[i, 0] / cell_m)
        r = np.floor(xyz[i, 1] / cell_m)
        c_min, r_min, c_max = min(c_min, c), min(r_min, r), max(c_max, c)
    cols = np.int64(c_max - c_min) + 1
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        key[i] = (np.int64(np.floor(xyz[i, 1] / cell_m)) - np.int64(r_min)) * cols + (
            np.int64(np.floor(xyz[i, 0] / cell_m)) - np.int64(c_min))
    return key, cols


def _cells_in_order(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_counting_order` of ``key`` on numba's threads, one per million keys at most (a reference's points
    on a worker: one)."""
    return _counting_order(key, max(1, min(numba.get_num_threads(), len(key) // 1_000_000)))


def _counting_order(key: np.ndarray, threads: int) -> tuple[np.ndarray, np.ndarray]:
    """The points ordered by cell, in their own order within a cell (``np.argsort(key, kind="stable")``), and
    where each occupied cell's run starts in that order, with the count at the end: a counting sort, linear in
    the points and the cells, without the sort's and the comparison's copies of the keys (a city's cloud holds
    10^8 points). ``key`` (N,) int64, each point's cell (0 or more).

    On ``threads`` threads, each counting and placing the points of its own range of cells (ranges of about equal
    points, from a sample of the keys): every thread reads all the keys, but writes only its cells' counts and
    places, so the threads never write the same element and the order is the serial one. One thread opens no
    parallel region: on a Dask worker, beside another busy worker, numba's idle threads waiting at the region's
    end took a 300,000-point reference's sort from under 1 ms to 3-19 ms (``benchmarks/RESULTS.md``, "Dense
    surface: a reference's counting sort without a parallel region")."""
    key = np.asarray(key)
    n = len(key)
    n_cells = int(key.max()) + 1 if n else 0
    edges = np.array([0, n_cells], dtype=np.int64)
    if threads > 1 and n > 0:
        sample = np.sort(key[::max(1, n // 100_000)])
        inner = sample[(np.arange(1, threads) * len(sample)) // threads]
        edges = np.concatenate([[0], np.maximum.accumulate(np.maximum(inner, 0)), [n_cells]]).astype(np.int64)
    start = np.zeros(n_cells + 1, dtype=np.int64)
    order = np.empty(n, dtype=np.int64)
    if threads > 1:
        _count_ranges(key, edges, start)
    else:
        _count_range(key, 0, n_cells, start)
    bounds = _runs_of_cells(start, n)
    if threads > 1:
        _place_ranges(key, edges, start, order)
    else:
        _place_range(key, 0, n_cells, start, order)
    return order, bounds


@numba.njit(cache=True, nogil=True)
def _count_range(key: np.ndarray, lo: int, hi: int, start: np.ndarray) -> None:
    """:func:`_counting_order`'s count of the keys in [``lo``, ``hi``): ``start[k + 1]`` += 1 for each key k."""
    for i in range(key.shape[0]):
        if lo <= key[i] < hi:
            start[key[i] + 1] += 1


@numba.njit(cache=True, nogil=True)
def _place_range(key: np.ndarray, lo: int, hi: int, start: np.ndarray, order: np.ndarray) -> None:
    """:func:`_counting_order`'s placing of the points whose keys lie in [``lo``, ``hi``): each at its cell's next
    free place ``start[k]``, in the points' order."""
    for i in range(key.shape[0]):
        k = key[i]
        if lo <= k < hi:
            order[start[k]] = i
            start[k] += 1


@numba.njit(cache=True, parallel=True)
def _count_ranges(key: np.ndarray, edges: np.ndarray, start: np.ndarray) -> None:
    for t in numba.prange(edges.shape[0] - 1):
        _count_range(key, edges[t], edges[t + 1], start)


@numba.njit(cache=True, parallel=True)
def _place_ranges(key: np.ndarray, edges: np.ndarray, start: np.ndarray, order: np.ndarray) -> None:
    for t in numba.prange(edges.shape[0] - 1):
        _place_range(key, edges[t], edges[t + 1], start, order)


@numba.njit(cache=True, nogil=True)
def _runs_of_cells(start: np.ndarray, n: int) -> np.ndarray:
    """The counts ``start[c + 1]`` of :func:`_counting_order` turned in place into each cell's first place
    (``start[c]``), and where each occupied cell's run starts, with ``n`` at the end."""
    n_cells = start.shape[0] - 1
    occupied = 0
    for c in range(n_cells):
        if start[c + 1] > 0:
            occupied += 1
        start[c + 1] += start[c]
    bounds = np.empty(occupied + 1, dtype=np.int64)
    j = 0
    for c in range(n_cells):
        if start[c + 1] > start[c]:
            bounds[j] = start[c]
            j += 1
    bounds[occupied] = n
    return bounds


@numba.njit(cache=True)
def _settle_cells(first: int, last: int, order: np.ndarray, bounds: np.ndarray, xyz: np.ndarray, rank: np.ndarray,
                  image_id: np.ndarray, views: np.ndarray, tol: float, keep: np.ndarray, height: np.ndarray,
                  frame_a: np.ndarray, frame_b: np.ndarray, settled: np.ndarray) -> None:
    """The first pass of :func:`_confirm_cells` over the cells ``first`` to ``last`` (exclusive): each cell's
    reference height, the frames of its close points, whether it is settled, and its points' ``keep``."""
    largest = 0
    for c in range(first, last):
        largest = max(largest, bounds[c + 1] - bounds[c])
    buf = np.empty(largest, dtype=np.float64)
    for c in range(first, last):
        lo, hi = bounds[c], bounds[c + 1]
        fewest = 2  # the fewest views a point of the cell may have: 3 where some point has three or more
        for p in range(lo, hi):
            if views[order[p]] >= 3:
                fewest = 3
                break
        n_near, n_all = 0, 0
        for p in range(lo, hi):
            if rank[order[p]] == 0 and views[order[p]] >= fewest:
                buf[n_near] = xyz[order[p], 2]
                n_near += 1
        if n_near > 0:
            reference = median_in_place(buf[:n_near])
        else:
            for p in range(lo, hi):
                if views[order[p]] >= fewest:
                    buf[n_all] = xyz[order[p], 2]
                    n_all += 1
            if n_all == 0:
                continue
            reference = median_in_place(buf[:n_all])
        height[c] = reference
        settled[c] = n_near > 0
        # the frames of the close points (a frame whose point one pair measured counts, though the point itself is
        # not kept beside a checked one)
        for p in range(lo, hi):
            i = order[p]
            close = abs(xyz[i, 2] - reference) <= tol
            if views[i] >= fewest and (rank[i] == 0 or close):
                keep[i] = True
            if close:
                if frame_a[c] < 0:
                    frame_a[c] = image_id[i]
                elif image_id[i] != frame_a[c] and frame_b[c] < 0:
                    frame_b[c] = image_id[i]
                    settled[c] = True


@numba.njit(cache=True, parallel=True)
def _confirm_cells(order: np.ndarray, bounds: np.ndarray, cell_keys: np.ndarray, cols: int, xyz: np.ndarray,
                   rank: np.ndarray, image_id: np.ndarray, views: np.ndarray, tol: float, runs: int) -> np.ndarray:
    """:func:`confirmed` cell by cell: the points ``order[bounds[c]:bounds[c + 1]]`` share cell ``c``, whose key
    (row * ``cols`` + column) is ``cell_keys[c]`` (ascending).

    A cell without the nearest frame's points is confirmed by a second frame's close point in the cell or in one of
    its 8 neighbours whose height agrees with the cell's within ``tol``: a frame's points are about one per cell, so
    where two frames alone see the ground (a block's edge, beside a wall) their points often miss each other's
    cell, and asking for both in the same one left such ground a hole (``benchmarks/RESULTS.md``, "Dense surface: a
    second frame confirms a cell from the next one"). The cells are taken in ``runs`` runs on numba's threads."""
    n_cells = bounds.shape[0] - 1
    keep = np.zeros(xyz.shape[0], dtype=np.bool_)
    # per occupied cell (a city's 70 million: 4-byte fields): its reference height, up to two frames with a close
    # point in it
    height = np.full(n_cells, np.nan, dtype=np.float32)
    frame_a = np.full(n_cells, -1, dtype=np.int32)
    frame_b = np.full(n_cells, -1, dtype=np.int32)
    settled = np.zeros(n_cells, dtype=np.bool_)  # the nearest frame's points, or two frames in the cell
    # a cell writes only its own fields and its own points' keep, and the second pass reads the fields the first
    # has finished
    step = (n_cells + runs - 1) // runs
    for run in numba.prange(runs):
        first, last = run * step, min((run + 1) * step, n_cells)
        _settle_cells(first, last, order, bounds, xyz, rank, image_id, views, tol, keep, height, frame_a, frame_b,
                      settled)
    for run in numba.prange(runs):
        for c in range(run * step, min((run + 1) * step, n_cells)):
            if settled[c] or frame_a[c] < 0:
                continue
            row, col = cell_keys[c] // cols, cell_keys[c] % cols
            second = False
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    if second or (dr == 0 and dc == 0) or not 0 <= col + dc < cols:
                        continue
                    near = (row + dr) * cols + col + dc
                    j = np.searchsorted(cell_keys, near)
                    if j >= n_cells or cell_keys[j] != near or not abs(height[j] - height[c]) <= tol:
                        continue
                    second = ((frame_a[j] >= 0 and frame_a[j] != frame_a[c])
                              or (frame_b[j] >= 0 and frame_b[j] != frame_a[c]))
            if not second:
                for p in range(bounds[c], bounds[c + 1]):
                    keep[order[p]] = False
    return keep


def dense_cloud(frames: Sequence[FrameGeometry], load: FrameLoader, tie_xyz: np.ndarray, ground_height_m: float,
                config: DenseConfig | None = None, client=None,
                progress: Callable[[int, int], None] | None = None) -> DenseCloud:
    """The dense cloud of an adjusted block (module docstring).

    Args:
        frames: the adjusted frames (poses and the IO that holds for each).
        load: image id -> (8-bit frame for matching, frame values for the cloud's attribute), full resolution;
            called on the workers (it must pickle for a Dask client).
        tie_xyz: the adjusted tie points (N, 3) world metres: the disparity search of each pair.
        ground_height_m: a typical ground height (metres) for the neighbours' overlap.
        config: matching and fusion settings.
        client: a Dask client (one task per reference frame), or ``None`` to run here.
        progress: called with (frames done, frames) as references complete.

    Returns:
        the fused :class:`DenseCloud` (empty when no pair could be matched).
    """
    config = config or DenseConfig()
    frames = list(frames)
    scale = matching_scale(frames, config.max_image_pixels)
    neighbours = select_neighbours(frames, ground_height_m, config)
    planner = _PairPlanner(frames, tie_xyz, scale, config)
    by_id = {f.image_id: f for f in frames}
    centres = np.array([f.C[:2] for f in frames], dtype=float)
    plans: dict[int, list[PairPlan]] = {}
    results: list[tuple[int, ReferencePoints]] = []
    if client is None:
        for k, (r, others) in enumerate(neighbours.items()):
            ps = plans[r] = planner.plans(r, others)
            results.append((r, reference_points(by_id[r], [by_id[p.other] for p in ps], ps, load, scale, centres,
                                                config, ground_height_m)))
            if progress:
                progress(k + 1, len(neighbours))
    else:
        # lazy: distributed is slow to import; only the Dask path needs it
        from distributed import as_completed

        # each reference is handed to the workers as soon as its pairs are planned: the planning of a city's
        # 3,400 pairs (rectification and tie points' disparities) took seconds while the workers waited
        futures = {}
        for r, others in neighbours.items():
            ps = plans[r] = planner.plans(r, others)
            futures[client.submit(reference_points, by_id[r], [by_id[p.other] for p in ps], ps, load, scale,
                                  centres, config, ground_height_m, pure=False)] = r
        for k, fut in enumerate(as_completed(futures)):
            results.append((futures[fut], fut.result()))
            fut.release()
            if progress:
                progress(k + 1, len(futures))
    results.sort(key=lambda t: t[0])
    if not results:
        results = [(0, ReferencePoints.empty())]
    image_id = np.repeat(np.array([i for i, _ in results], dtype=np.int32),
                         np.array([len(r.offset) for _, r in results], dtype=np.int64))
    # one field at a time, each reference's part released as it is copied: the parts and the whole cloud are
    # never all held at once (benchmarks/RESULTS.md, "Dense surface: the cloud's memory")
    fields = {name: [getattr(r, name) for _, r in results] for name in ("offset", "value", "views", "rank")}
    origins = [r.origin for _, r in results]
    del results
    xyz = _gathered(fields.pop("offset"), origins)
    rank = _gathered(fields.pop("rank"))
    views = _gathered(fields.pop("views"))
    gsd = float(np.median([(f.C[2] - ground_height_m) / (f.camera.f * scale) for f in frames]))
    keep = confirmed(xyz, rank, image_id, gsd, config.fill_agreement_gsd * gsd, views)
    n_pairs = sum(len(p) for p in plans.values())
    stats = {"frames": len(frames), "references": len(plans), "pairs": n_pairs,
             "pairs_left_out": sum(len(v) for v in neighbours.values()) - n_pairs,
             "points": int(keep.sum()), "unconfirmed": int(len(keep) - keep.sum()), "scale": scale}
    xyz, rank, image_id, views = (_kept(a, keep) for a in (xyz, rank, image_id, views))
    value = _kept(_gathered(fields.pop("value")), keep)
    stats["two_view_points"] = int(np.count_nonzero(views == 2))
    return DenseCloud(xyz=xyz, value=value, views=views, image_id=image_id, gsd_m=gsd, stats=stats, rank=rank)


def _gathered(parts: list[np.ndarray], origins: list[np.ndarray] | None = None) -> np.ndarray:
    """The ``parts`` (arrays of one dtype and trailing shape) concatenated, each part dropped from the list as it
    is copied (the caller holds no other reference): the whole and all the parts are never held at once. With
    ``origins`` (one (3,) float64 per part), the parts are float32 offsets from them and the whole is
    ``origin + offset`` in float64.

    The parts a Dask client received are a few megabytes each, which the C allocator keeps in its heap once freed
    rather than giving back: every 64 MB copied, the freed pages are handed back (:func:`_release_freed_memory`),
    or the process would hold the parts' pages and the whole at once (a city's 178 million points: 4 GB more at
    the peak; ``benchmarks/RESULTS.md``, "City scale with the dense surface: the flow's memory")."""
    total = sum(len(p) for p in parts)
    out = np.empty((total, *parts[0].shape[1:]), dtype=parts[0].dtype if origins is None else np.float64)
    parts.reverse()
    if origins is not None:
        origins = origins[::-1]
    at, since = 0, 0
    while parts:
        part = parts.pop()
        if origins is None:
            out[at:at + len(part)] = part
        else:
            _add_origin(np.asarray(origins.pop(), dtype=np.float64), part, out[at:at + len(part)])
        at += len(part)
        since += part.nbytes
        del part
        if since >= 64 << 20:
            _release_freed_memory()
            since = 0
    _release_freed_memory()
    return out


@numba.njit(cache=True, parallel=True)
def _add_origin(origin: np.ndarray, offset: np.ndarray, out: np.ndarray) -> None:
    """``out = origin + offset`` (``np.add``'s values) on numba's threads: the flow's process gathers a city's
    cloud while the workers are idle, and most of the time is the kernel's first touch of the new pages."""
    for i in numba.prange(offset.shape[0]):
        for k in range(3):
            out[i, k] = origin[k] + np.float64(offset[i, k])


def _release_freed_memory() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim``; nothing where there is none)."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _libc() -> ctypes.CDLL | None:
    try:
        lib = ctypes.CDLL("libc.so.6")
        lib.malloc_trim.argtypes = [ctypes.c_size_t]
        return lib
    except (OSError, AttributeError):  # not glibc (macOS, musl): freed memory is the allocator's business
        return None


_LIBC = _libc()


def _kept(values: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``values[keep]`` written over ``values`` itself (which is then no longer valid): the kept rows moved to the
    front in order and the array shrunk, without a second copy of a cloud-sized array."""
    if not len(values) or not (values.flags.c_contiguous and values.flags.owndata):
        return values[keep]
    n = _move_kept(values.reshape(len(values), -1), keep)
    values.resize((n, *values.shape[1:]), refcheck=False)
    return values


@numba.njit(cache=True)
def _move_kept(rows: np.ndarray, keep: np.ndarray) -> int:
    j = 0
    for i in range(rows.shape[0]):
        if keep[i]:
            if j != i:
                rows[j] = rows[i]
            j += 1
    return j


def cell_views(cloud: DenseCloud, dsm: Dsm, measured: np.ndarray) -> np.ndarray:
    """Per cell of ``dsm`` (the cloud's DSM, or its cells before the filling), the most views that agree on a point
    of the cloud in it (uint8, the DSM's shape; 0 where the cell is not ``measured``): 2 where the cell's height
    stands on one pair that no third view could check, 3 or more where it was checked. :func:`views_of_cells` of
    :func:`own_views`."""
    return views_of_cells(own_views(cloud, dsm), measured)


def own_views(cloud: DenseCloud, dsm: Dsm) -> np.ndarray:
    """Per cell of ``dsm``'s grid, the most views of the cloud's points in it (uint8; 0: no point)."""
    rows, cols = dsm.shape
    return _most_views(np.ascontiguousarray(cloud.xyz, dtype=np.float64), np.asarray(cloud.views, dtype=np.uint8),
                       float(dsm.west), float(dsm.north), float(dsm.cell_m), rows, cols).reshape(rows, cols)


def views_of_cells(own: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """:func:`cell_views` from the cells' own views (:func:`own_views`) on the ``measured`` cells (0 elsewhere); a
    measured cell without a point of its own (a mask wider than :meth:`Dsm.measured`) takes the most of its 3 x 3
    neighbourhood's."""
    return np.where(measured, np.where(own > 0, own, maximum_filter(own, size=3)), 0).astype(np.uint8)


@numba.njit(cache=True)
def _most_views(xyz: np.ndarray, views: np.ndarray, west: float, north: float, cell: float, rows: int,
                cols: int) -> np.ndarray:
    """:func:`cell_views` before the neighbourhood: per cell (flat, row-major) the most views of its own points."""
    out = np.zeros(rows * cols, dtype=np.uint8)
    for i in range(xyz.shape[0]):
        c = int(np.floor((xyz[i, 0] - west) / cell))
        r = int(np.floor((north - xyz[i, 1]) / cell))
        if 0 <= c < cols and 0 <= r < rows and views[i] > out[r * cols + c]:
            out[r * cols + c] = views[i]
    return out
