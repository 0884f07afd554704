"""Orthomosaic: the block's frames resampled onto a north-up grid in the flight's projected CRS.

Output grid
-----------
North-up, square pixels of ``gsd_m`` metres; pixel ``(row, col)`` is centred on
``E = west + (col + 0.5) gsd``, ``N = north - (row + 0.5) gsd`` (GDAL "pixel is area"). Written as a
Cloud-Optimized GeoTIFF (deflate, internal tiles, overviews) with the flight's CRS, its transform and a
nodata value; written atomically (:func:`aerocal.io.atomic_path`). The tiles make the overview levels
(:func:`overview_factors`); the grid then reaches east and south of the bounds, by nodata pixels, to a whole
number of the coarsest level's pixels.

Per output pixel
----------------
1. Its ground point ``X = (E, N, h)`` with ``h`` bilinear in the DSM (:class:`aerocal.products.dsm.Dsm`).
2. For every candidate frame: ``uv = camera_i.project(R_cw (X - C))`` through the FULL camera model
   (Brown distortion, affinity, skew) with that frame's IO: ``LinearThermalModel.camera_at(camera, T_i)``
   when a linear thermal model is given; for the similarity/polynomial models (which map measured
   pixels to the reference camera) the measured position is found by inverting the correction by
   fixed-point iteration (6 steps; it converges because the corrections change slowly across the image).
3. Frame choice: the most nadir view, i.e. the smallest distance of ``uv`` to the frame's principal
   point. Seams are feathered: a frame whose distance exceeds the best one by ``delta`` pixels gets
   weight ``1 - delta / (2 feather_px)`` (clipped to [0, 1]); as ``delta`` grows by up to 2 px per
   output pixel across a seam, weights fall to 0 over about ``feather_px`` pixels from it. Every weight
   also tapers to ~0 over ``feather_px`` pixels inside the frame's border, so a frame edge never shows.
4. The value is the weighted mean of the frames' values, each resampled bilinearly (``cv2.remap``,
   ``INTER_LINEAR``) from the ORIGINAL radiometry (16-bit thermal DN stay DN; output dtype = input
   dtype). Pixels no frame sees, or without a DSM height, are nodata.

Occlusions are not modelled (this is an orthomosaic on the DSM, not a true orthophoto): at the
narrow fields of view of thermal frames from hundreds of metres the hidden ground is a few metres
beside tall buildings.

Parallelism: the grid is cut into tiles of ``tile_px``; each tile is one task (on a Dask
``distributed.Client`` when one is passed, serially otherwise) that receives only the frames whose
footprint (the image border cast onto planes at the lowest and highest DSM heights under the frame) touches it,
their pixels and the DSM window under the tile. Serial and Dask runs give identical bytes (the same
function, frames summed in image-id order). Tiles run along a Hilbert curve over the grid, and each process keeps
the frames it decoded last (:func:`frame_pixels`): a frame is decoded about once per process, not once per tile
that touches it, and only the part of it a tile reads is converted for resampling.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextlib
import dataclasses
import shutil
import tempfile
import threading
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import rasterio
import rasterio.shutil
from rasterio.enums import Resampling
from rasterio.transform import from_origin

from aerocal import tables
from aerocal.camera import Camera, LinearThermalModel, ThermalModel, correct_measurements
from aerocal.geometry import matrix_from_quat_wxyz
from aerocal.ingest.pixels import ImageReadError, read_raw
from aerocal.io import atomic_path
from aerocal.products.dsm import DEFLATE_LEVEL, Dsm, cog_overview_factors
from aerocal.products.kernels import (
    NO_PIXEL,
    add_weighted,
    frame_view,
    halve,
    score_bounds,
    tile_heights,
    weighed_box,
    weighted_mean,
)

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class MosaicConfig:
    """Orthomosaic settings. Lengths in metres, sizes in output pixels.

    ``gsd_m`` None = the block's median GSD (flying height above the DSM's median / focal length).
    ``bounds`` None = the union of the frames' footprints at the DSM's median height. The grid covers the bounds
    (its corner on whole multiples of the pixel size) and reaches beyond them east and south, by nodata pixels
    fewer than the coarsest overview's factor, to a whole number of that overview's pixels (:func:`overview_factors`).
    ``nodata`` None = the dtype's maximum for uint16 (65535, i.e. 655.35 K, never a thermal value) and 0 for
    uint8 (valid pixels are then clipped to 1..255).
    """

    gsd_m: float | None = None
    bounds: tuple[float, float, float, float] | None = None  #: (west, south, east, north)
    tile_px: int = 256  #: tile (task and GeoTIFF block) size; a multiple of 16
    feather_px: float = 8.0  #: seam and frame-border feathering width
    nodata: int | None = None
    cog: bool = True  #: Cloud-Optimized GeoTIFF (else a tiled GeoTIFF with internal overviews)
    overview_resampling: str = "average"

    def __post_init__(self) -> None:
        if self.gsd_m is not None and not self.gsd_m > 0:
            raise ValueError(f"MosaicConfig.gsd_m must be positive, got {self.gsd_m}")
        if self.tile_px < 16 or self.tile_px % 16:
            raise ValueError(f"MosaicConfig.tile_px must be a multiple of 16 (>= 16), got {self.tile_px}")
        if self.feather_px < 0:
            raise ValueError(f"MosaicConfig.feather_px must be >= 0, got {self.feather_px}")


@dataclass(frozen=True)
class FrameGeometry:
    """One adjusted frame: ``R_cw`` world-to-camera (3, 3), projection centre ``C`` (3,) world metres, and
    the camera (IO in pixels) that holds for this frame.

    ``thermal_model`` / ``temperature`` are set only for models that correct measurements rather than the
    IO (similarity, polynomial): ``camera`` is then the reference camera and :meth:`project` undoes the
    correction to find where the frame really recorded a ground point.
    """

    image_id: int
    camera: Camera
    R_cw: np.ndarray
    C: np.ndarray
    thermal_model: ThermalModel | None = None
    temperature: float | None = None
    #: a frame read out row by row while the camera moves: the projection centre's displacement (world metres) per
    #: unit of ``row / height - 0.5`` (velocity x readout; ``C`` is the centre when the middle row is exposed)
    motion: np.ndarray | None = None

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> recorded pixels (..., 2) (top-left-corner convention); NaN behind."""
        X = np.asarray(X, dtype=float)
        C = np.asarray(self.C, dtype=float)
        p = (X - C) @ np.asarray(self.R_cw).T
        uv = self.camera.project(p)
        if self.motion is not None:
            motion = np.asarray(self.motion, dtype=float)
            for _ in range(3):  # the row each point is read on, by fixed-point iteration
                frac = uv[..., 1:2] / self.camera.height - 0.5
                uv = self.camera.project((X - C - frac * motion) @ np.asarray(self.R_cw).T)
        if self.thermal_model is None:
            return uv

        raw = uv.copy()
        for _ in range(6):  # correct(raw) = uv, the correction is close to the identity
            raw = raw + (uv - correct_measurements(self.camera, raw, self.temperature, self.thermal_model))
        return raw

    def ground_footprint(self, heights: Sequence[float], samples_per_edge: int = 8) -> np.ndarray:
        """The image border cast onto horizontal planes at ``heights`` (metres): (M, 2) E, N points."""
        cam = self.camera
        t = np.linspace(0.0, 1.0, samples_per_edge, endpoint=False)
        w, h = float(cam.width), float(cam.height)
        border = np.concatenate([
            np.column_stack([t * w, np.zeros_like(t)]), np.column_stack([np.full_like(t, w), t * h]),
            np.column_stack([w - t * w, np.full_like(t, h)]), np.column_stack([np.zeros_like(t), h - t * h]),
        ])
        if self.thermal_model is not None:
            border = correct_measurements(cam, border, self.temperature, self.thermal_model)
        d = np.column_stack([cam.unproject(border), np.ones(len(border))]) @ np.asarray(self.R_cw)
        out = []
        for z in heights:
            down = d[:, 2] < -1e-9
            s = (float(z) - self.C[2]) / np.where(down, d[:, 2], -1.0)
            out.append(np.asarray(self.C)[:2] + s[down, None] * d[down, :2])
        return np.vstack(out) if out else np.zeros((0, 2))


def frames_from_poses(
    poses,
    camera: Camera | Mapping[int, Camera],
    temperatures: Mapping[int, float] | None = None,
    thermal_model: ThermalModel | None = None,
    motion: Mapping[int, np.ndarray] | None = None,
    turn: Mapping[int, np.ndarray] | None = None,
) -> list[FrameGeometry]:
    """Frame geometries from a ``poses`` table (world-to-camera quaternions, projection centres).

    ``camera`` is one camera for the block or one per image id. With ``thermal_model`` every image id needs
    a temperature (degC) in ``temperatures``: a :class:`LinearThermalModel` gives the frame the IO
    ``camera_at(camera, T_i)``; the other models are applied to measurements in :meth:`FrameGeometry.project`.
    ``motion``: per image id the rolling readout's displacement of the projection centre
    (:attr:`FrameGeometry.motion`); ``turn``: per image id a rotation (3, 3) about the camera's own axes applied to
    its adjusted attitude (a thermal rotation of the image about the principal point: the adjusted pose is the
    camera's at the certificate's reference temperature).

    Raises:
        ValueError: with ``thermal_model``, an image id without a finite temperature in ``temperatures``.
    """
    poses = tables.validate(poses, "poses")
    ids = poses.column("image_id").to_numpy()
    q = np.column_stack([poses.column(c).to_numpy() for c in ("qw", "qx", "qy", "qz")])
    C = np.column_stack([poses.column(c).to_numpy() for c in ("X", "Y", "Z")])
    R = matrix_from_quat_wxyz(q / np.linalg.norm(q, axis=1, keepdims=True)).reshape(-1, 3, 3)
    frames = []
    for i, iid in enumerate(ids.tolist()):
        cam = camera[iid] if isinstance(camera, Mapping) else camera
        model, temp = None, None
        if thermal_model is not None:
            if temperatures is None or iid not in temperatures or not np.isfinite(temperatures[iid]):
                raise ValueError(f"frames_from_poses: image {iid} has no sensor temperature; the thermal "
                                 "model needs one per image (images.temperature_c)")
            temp = float(temperatures[iid])
            if isinstance(thermal_model, LinearThermalModel):
                cam = thermal_model.camera_at(cam, temp)
            else:
                model = thermal_model
        R_i = R[i] if turn is None or iid not in turn else np.asarray(turn[iid]) @ R[i]
        m = None if motion is None or iid not in motion else np.asarray(motion[iid], dtype=float)
        frames.append(FrameGeometry(image_id=int(iid), camera=cam, R_cw=R_i, C=C[i], thermal_model=model,
                                    temperature=temp, motion=m))
    return frames


def block_gsd(frames: Sequence[FrameGeometry], ground_height_m: float) -> float:
    """Median ground sampling distance (metres): (centre height - ground height) / focal length (px)."""
    g = [(f.C[2] - ground_height_m) / f.camera.f for f in frames]
    return float(np.median(g))


def read_frame(path: str | Path) -> np.ndarray:
    """A frame's original pixels as ingest reads them (:func:`aerocal.ingest.read_raw`): the 16-bit counts
    of FLIR radiometric JPEGs and DJI R-JPEGs (not their 8-bit palette previews), 16-bit TIFF as stored,
    other JPEGs as RGB. Raises ``ValueError`` naming the file."""
    try:
        return read_raw(path)
    except ImageReadError as exc:
        raise ValueError(str(exc)) from exc


class FrameCache:
    """The frames a process read last, up to ``max_bytes`` (their arrays' sizes summed), kept read-only and the
    least recently used dropped first; one per process, module level, so that tasks a Dask worker runs one after
    another share it. ``clear`` releases them: a step's frames are not kept beyond it (a long-lived process would
    hold them, and a frame rewritten at the same path would read as it was)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._kept: collections.OrderedDict[object, tuple[np.ndarray, ...]] = collections.OrderedDict()
        self._reading: dict[object, threading.Event] = {}
        self._lock = threading.Lock()

    def get(self, key: object, read: Callable[[], tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
        """The arrays kept under ``key``, else ``read()``'s, kept (read-only) before they are returned. Safe to
        call from several threads: ``read`` runs outside the lock, once for threads that miss the same key at
        once (the others wait for it: the threads of a mosaic render neighbouring tiles, which need the same
        frames at the same moment, and decoded most frames twice); a thread whose reader failed reads again
        itself (and meets the same error)."""
        while True:
            with self._lock:
                if key in self._kept:
                    self._kept.move_to_end(key)
                    return self._kept[key]
                pending = self._reading.get(key)
                if pending is None:
                    pending = self._reading[key] = threading.Event()
                    break
            pending.wait()
        try:
            arrays = read()
            for a in arrays:
                a.flags.writeable = False
            with self._lock:
                self._kept[key] = arrays
                while sum(a.nbytes for v in self._kept.values() for a in v) > self.max_bytes and len(self._kept) > 1:
                    self._kept.popitem(last=False)
        finally:
            with self._lock:
                del self._reading[key]
            pending.set()
        return arrays

    def __len__(self) -> int:
        return len(self._kept)

    def clear(self) -> None:
        with self._lock:
            self._kept.clear()


#: the decoded frames each process keeps (:func:`frame_pixels`): tiles are rendered in an order that keeps
#: neighbours together (:func:`_hilbert_order`), so the frames a tile needs are mostly those the last tiles read;
#: 768 MiB hold about 27 frames of 3600 x 2700 RGB, or every frame of a 640 x 512 thermal block of 1,000
_decoded = FrameCache(768 * 2**20)


def frame_pixels(path: str | Path) -> np.ndarray:
    """:func:`read_frame` through this process's :class:`FrameCache`: each tile that touches a frame decoded it
    again, and a visible block's mosaic was decode-bound (benchmarks/RESULTS.md, "Orthomosaic of large visible
    frames against the decode-and-resample limit")."""
    return _decoded.get(str(path), lambda: (read_frame(path),))[0]


def forget_frames() -> None:
    """Release the frames :func:`frame_pixels` keeps in this process (module level: run on every Dask worker at
    the end of a mosaic)."""
    _decoded.clear()


def _hilbert_order(rows: int, cols: int) -> np.ndarray:
    """Indices of a ``rows`` x ``cols`` grid (row-major) in the order of a Hilbert curve over it: consecutive cells
    are neighbours, and any run of them stays compact, so tiles rendered in this order share their frames."""
    n = 1 << max(int(np.ceil(np.log2(max(rows, cols, 1)))), 0)
    r, c = np.divmod(np.arange(rows * cols), cols)
    x, y = c.copy(), r.copy()
    d = np.zeros(rows * cols, dtype=np.int64)
    s = n // 2
    while s > 0:
        rx = (x & s) > 0
        ry = (y & s) > 0
        d += s * s * ((3 * rx) ^ ry)
        # rotate the quadrant so the curve's pieces join
        flip = ~ry & rx
        x = np.where(flip, s - 1 - x, x)
        y = np.where(flip, s - 1 - y, y)
        x, y = np.where(~ry, y, x), np.where(~ry, x, y)
        s //= 2
    return np.argsort(d, kind="stable")


@dataclass(frozen=True)
class TileSpec:
    """One tile of the output grid: pixel offsets and size, and the grid's origin and pixel size."""

    row0: int
    col0: int
    rows: int
    cols: int
    west: float
    north: float
    gsd_m: float

    def bounds(self) -> tuple[float, float, float, float]:
        w = self.west + self.col0 * self.gsd_m
        n = self.north - self.row0 * self.gsd_m
        return (w, n - self.rows * self.gsd_m, w + self.cols * self.gsd_m, n)


def render_tile(
    tile: TileSpec, frames: Sequence[FrameGeometry], pixels: Sequence[np.ndarray | str | Path], dsm: Dsm,
    feather_px: float, nodata: int, dtype: str, bands: int,
) -> tuple[TileSpec, np.ndarray]:
    """Compute one tile: (bands, rows, cols) array of ``dtype``; nodata where no frame sees the ground.

    Raises:
        ValueError: a frame's pixels are not of its camera's width and height; give the frame's original pixels.
    """
    cv2.setNumThreads(1)
    shape = (tile.rows, tile.cols)
    out = np.full((bands,) + shape, nodata, dtype=dtype)
    if not frames:
        return tile, out
    w, _, _, n = tile.bounds()
    e = w + (np.arange(tile.cols) + 0.5) * tile.gsd_m
    nn = n - (np.arange(tile.rows) + 0.5) * tile.gsd_m
    H = np.empty(shape)
    tile_heights(dsm.heights, float(dsm.west), float(dsm.north), float(dsm.cell_m), e, nn, H)
    width = max(2.0 * feather_px, 1e-9)
    kept = _may_be_seen(frames, tile, H, width)
    maps, scores, tapers = [], [], []
    for _, fr in kept:
        map_u, map_v = np.empty(shape, np.float32), np.empty(shape, np.float32)
        score, taper = np.empty(shape), np.empty(shape)
        if fr.thermal_model is None:
            frame_view(e, nn, H, np.asarray(fr.R_cw, dtype=float), np.asarray(fr.C, dtype=float),
                       fr.camera.params(), float(fr.camera.width), float(fr.camera.height), float(feather_px),
                       map_u, map_v, score, taper,
                       np.zeros(3) if fr.motion is None else np.asarray(fr.motion, dtype=float))
        else:
            E, N = np.meshgrid(e, nn)
            _frame_view_numpy(fr, np.stack([E, N, H], axis=-1), feather_px, map_u, map_v, score, taper)
        maps.append((map_u, map_v))
        scores.append(score)
        tapers.append(taper)
    if not kept:
        return tile, out
    best = scores[0].copy()
    for score in scores[1:]:
        np.minimum(best, score, out=best)
    if not np.isfinite(best).any():
        return tile, out
    acc = np.zeros((bands,) + shape)
    wsum = np.zeros(shape)
    for k, (index, fr) in enumerate(kept):
        weighed, u0, u1, v0, v1, r0, r1, c0, c1 = weighed_box(*maps[k], scores[k], best, tapers[k], width)
        if not weighed:
            continue  # never decoded for this tile
        img = pixels[index]
        if not isinstance(img, np.ndarray):
            img = frame_pixels(img)
        cam = fr.camera
        if img.shape[:2] != (cam.height, cam.width):
            raise ValueError(f"image {fr.image_id}: pixels are {img.shape[1]}x{img.shape[0]}, its camera says "
                             f"{cam.width}x{cam.height}; give the frame's original pixels")
        # resampled and added where the frame weighs only: in a thermal block most frames of a tile weigh on part
        # of it (benchmarks/RESULTS.md, "Orthomosaic: a frame resampled where it weighs")
        part = (slice(r0, r1), slice(c0, c1))
        values = _resampled(img, maps[k][0][part], maps[k][1][part], u0, u1, v0, v1).reshape((r1 - r0, c1 - c0, -1))
        add_weighted(values, scores[k][part], best[part], tapers[k][part], width, acc[:, r0:r1, c0:c1], wsum[part])
    info = np.iinfo(dtype)  # uint8 or uint16 (build_mosaic)
    weighted_mean(acc, wsum, float(info.min), float(info.max), float(nodata), out)
    return tile, out


def _may_be_seen(frames: Sequence[FrameGeometry], tile: TileSpec, heights: np.ndarray, width: float
                 ) -> list[tuple[int, FrameGeometry]]:
    """(index, frame) of the ``frames`` that may carry weight somewhere in ``tile`` (``heights``: its pixels'
    DSM heights; ``width``: the seam's feathering width, px). A frame is left out when the bounds on the scores
    (:func:`aerocal.products.kernels.score_bounds`) show it scores at least ``width`` worse than a frame that
    sees the whole tile, at every pixel: its weight would be 0 everywhere, so the tile's values are unchanged.
    Frames with a readout's motion or a thermal model of measurements are always kept.

    Why: each candidate's projection is a full tile's pass through the camera model, and most candidates of a
    block with much overlap carry no weight (benchmarks/RESULTS.md, "Orthomosaic of large visible frames against
    the decode-and-resample limit")."""
    finite = heights[np.isfinite(heights)]
    indexed = list(enumerate(frames))
    if finite.size == 0:
        return indexed
    w, s, e, n = tile.bounds()
    box = np.array([[w, s, float(finite.min())], [e, n, float(finite.max())]])
    bounds = []
    for _, fr in indexed:
        if fr.thermal_model is not None or (fr.motion is not None and np.any(fr.motion)):
            bounds.append((0.0, np.inf, False))
        else:
            bounds.append(score_bounds(box, np.asarray(fr.R_cw, dtype=float), np.asarray(fr.C, dtype=float),
                                       fr.camera.params(), float(fr.camera.width), float(fr.camera.height)))
    ceiling = min((high for _, high, whole in bounds if whole), default=np.inf)
    return [(k, fr) for (k, fr), (low, _, _) in zip(indexed, bounds, strict=True) if not low >= ceiling + width]


def _resampled(img: np.ndarray, map_u: np.ndarray, map_v: np.ndarray, u_min: float, u_max: float, v_min: float,
               v_max: float) -> np.ndarray:
    """``img`` resampled bilinearly at (``map_u``, ``map_v``) (OpenCV's pixel convention), as float32, exact at the
    positions within (``u_min``..``u_max``, ``v_min``..``v_max``); elsewhere any finite value.

    Only the part of the frame those positions reach is converted to float32 (with the pixel beyond each side
    bilinear interpolation reads): a tile reads a tile-sized part of a frame, and converting the whole frame per
    tile took most of a visible block's mosaic time (benchmarks/RESULTS.md, "Orthomosaic of large visible frames
    against the decode-and-resample limit")."""
    h, w = img.shape[:2]
    c0 = int(np.clip(np.floor(u_min) - 1, 0, w - 1))
    c1 = int(np.clip(np.floor(u_max) + 3, c0 + 1, w))
    r0 = int(np.clip(np.floor(v_min) - 1, 0, h - 1))
    r1 = int(np.clip(np.floor(v_max) + 3, r0 + 1, h))
    crop = img[r0:r1, c0:c1].astype(np.float32)
    # BORDER_REPLICATE at the crop's edge is the frame's own edge or a pixel no position within the box reads
    return cv2.remap(crop, map_u - np.float32(c0), map_v - np.float32(r0), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def _frame_view_numpy(fr: FrameGeometry, X: np.ndarray, feather_px: float, map_u: np.ndarray, map_v: np.ndarray,
                      score: np.ndarray, taper: np.ndarray) -> None:
    """:func:`aerocal.products.kernels.frame_view` for the frames whose thermal model corrects measurements
    (:meth:`FrameGeometry.project` inverts it), with numpy: the same outputs from the ground points ``X``."""
    uv = fr.project(X)
    cam = fr.camera
    ok = np.isfinite(X[..., 2]) & np.all(np.isfinite(uv), axis=-1) & cam.in_image(uv)
    border = np.minimum.reduce([uv[..., 0], cam.width - uv[..., 0], uv[..., 1], cam.height - uv[..., 1]])
    score[...] = np.where(ok, np.hypot(uv[..., 0] - cam.cx, uv[..., 1] - cam.cy), np.inf)
    taper[...] = np.where(ok, np.clip(border / max(feather_px, 1e-9), 1e-6, 1.0), 0.0)
    uv = np.nan_to_num(uv, nan=NO_PIXEL + 0.5).astype(np.float32)
    # OpenCV puts the centre of the first pixel at (0, 0): ours minus 0.5
    map_u[...] = uv[..., 0] - np.float32(0.5)
    map_v[...] = uv[..., 1] - np.float32(0.5)


@dataclass(frozen=True)
class MosaicResult:
    """What :func:`build_mosaic` wrote: file, grid and coverage."""

    path: Path
    crs: str
    transform: tuple[float, ...]  #: GDAL geotransform order as rasterio's Affine (a, b, c, d, e, f)
    width: int
    height: int
    gsd_m: float
    nodata: int
    dtype: str
    bands: int
    tiles: int
    tiles_with_data: int
    coverage: float  #: fraction of pixels with data

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["path"] = str(self.path)
        d["transform"] = list(self.transform)
        return d


def _footprint_box(frame: FrameGeometry, zmin: float, zmax: float) -> tuple[float, float, float, float]:
    pts = frame.ground_footprint([zmin, zmax])
    if len(pts) == 0:
        return (np.inf, np.inf, -np.inf, -np.inf)
    return (pts[:, 0].min(), pts[:, 1].min(), pts[:, 0].max(), pts[:, 1].max())


def _frame_bboxes(frames: Sequence[FrameGeometry], zmin: float, zmax: float) -> np.ndarray:
    """(west, south, east, north) of every frame's footprint cast onto planes at ``zmin`` and ``zmax``."""
    return np.asarray([_footprint_box(fr, zmin, zmax) for fr in frames], dtype=float)


def _frame_bboxes_on(frames: Sequence[FrameGeometry], dsm: Dsm, start: float, rounds: int = 5) -> np.ndarray:
    """Every frame's footprint box over the heights of the DSM under it.

    Starts from the footprint on a plane at ``start``; each round casts the footprint onto the lowest and
    highest DSM heights inside the current box, until the box stops growing. A frame then only reaches the
    tiles it can see: a plane at the DSM's global extremes would hand a tile every frame that sees a
    deep pit or a tall spike anywhere in the block.
    """
    boxes = []
    for fr in frames:
        box = _footprint_box(fr, start, start)
        for _ in range(rounds):
            if not np.isfinite(box).all():
                break
            h = dsm.window(box, margin_cells=1).heights
            if not np.isfinite(h).any():
                break
            new = _footprint_box(fr, float(np.nanmin(h)), float(np.nanmax(h)))
            grown = (min(box[0], new[0]), min(box[1], new[1]), max(box[2], new[2]), max(box[3], new[3]))
            if grown == box:
                break
            box = grown
        boxes.append(box)
    return np.asarray(boxes, dtype=float)


def build_mosaic(
    frames: Sequence[FrameGeometry],
    images: Mapping[int, np.ndarray | str | Path],
    dsm: Dsm,
    out_path: str | Path,
    config: MosaicConfig | None = None,
    client=None,
    progress: Progress | None = None,
    threads: int = 1,
) -> MosaicResult:
    """Build the orthomosaic of ``frames`` over ``dsm`` and write it to ``out_path`` (see module docstring).

    ``images`` maps image id -> original pixels (array) or a file path (read by :func:`read_frame` where
    the tile is computed). ``client``: a ``distributed.Client`` (tiles run on its workers), or None: the tiles
    run in this process, on ``threads`` threads (the tile kernels, OpenCV's resampling and JPEG decoding release
    the GIL; one OpenCV thread each while they run, the process's own count restored after). Nothing is shipped
    between processes and the threads share one frame cache: on 40 visible frames of 9.5 MP, two threads took
    9.5 s and a local cluster of two worker processes 9.6 s in the same run, each within 3x of its
    decode-and-resample limit (``benchmarks/RESULTS.md``, "Orthomosaic of large visible frames against the
    decode-and-resample limit"; thermal blocks not measured apart).
    ``progress(done, total)`` is called after each tile is written.

    Raises:
        ValueError: ``images`` has no pixels for a frame; ``frames`` is empty; the output grid is empty; the frames are
            neither uint8 nor uint16; a frame's pixels are not of its camera's size (:func:`render_tile`).
    """
    config = config or MosaicConfig()
    out_path = Path(out_path)
    frames = sorted(frames, key=lambda f: f.image_id)
    missing = [f.image_id for f in frames if f.image_id not in images]
    if missing:
        raise ValueError(f"build_mosaic: no pixels for image id(s) {missing[:10]}; pass every frame's image")
    if not frames:
        raise ValueError("build_mosaic: no frames")
    zmed = float(np.nanmedian(dsm.heights))
    gsd = config.gsd_m or block_gsd(frames, zmed)
    boxes = _frame_bboxes_on(frames, dsm, zmed)
    if config.bounds is not None:
        w, s, e, n = config.bounds
    else:
        mid = _frame_bboxes(frames, zmed, zmed)
        ok = np.isfinite(mid).all(axis=1)
        w, s = mid[ok, 0].min(), mid[ok, 1].min()
        e, n = mid[ok, 2].max(), mid[ok, 3].max()
        dw, ds, de, dn = dsm.bounds()
        w, s, e, n = max(w, dw), max(s, ds), min(e, de), min(n, dn)
    west = np.floor(w / gsd) * gsd
    north = np.ceil(n / gsd) * gsd
    width = int(np.ceil((e - west) / gsd))
    height = int(np.ceil((north - s) / gsd))
    if width <= 0 or height <= 0:
        raise ValueError(f"build_mosaic: empty output grid for bounds {(w, s, e, n)}")
    # where the tiles make the overviews, the grid grows east and south (nodata) to a multiple of the coarsest
    # level's factor: each level then halves the one before exactly, as GDAL reads an overview's pixel size
    while True:
        factors = overview_factors(width, height, config)
        step = factors[-1] if factors else 1
        if width % step == 0 and height % step == 0:
            break
        width, height = -(-width // step) * step, -(-height // step) * step

    # data type and bands from the first frame (read through the cache, emptied first: a frame rewritten at the
    # same path since an earlier mosaic in this process is read again)
    forget_frames()
    first = images[frames[0].image_id]
    sample = first if isinstance(first, np.ndarray) else frame_pixels(first)
    dtype = str(sample.dtype)
    bands = 1 if sample.ndim == 2 else int(sample.shape[2])
    if dtype not in ("uint8", "uint16"):
        raise ValueError(f"build_mosaic: frames of dtype {dtype} are not supported; give uint8 or uint16 pixels")
    nodata = config.nodata if config.nodata is not None else (65535 if dtype == "uint16" else 0)

    grid = [TileSpec(r0, c0, min(config.tile_px, height - r0), min(config.tile_px, width - c0),
                     float(west), float(north), float(gsd))
            for r0 in range(0, height, config.tile_px) for c0 in range(0, width, config.tile_px)]
    # rendered along a Hilbert curve: the tiles a worker renders one after another share their frames, which
    # it then decodes once (frame_pixels)
    order = _hilbert_order(-(-height // config.tile_px), -(-width // config.tile_px))
    tiles = [grid[k] for k in order]

    def members(tile: TileSpec) -> list[int]:
        tw, ts, te, tn = tile.bounds()
        hit = (boxes[:, 0] <= te) & (boxes[:, 2] >= tw) & (boxes[:, 1] <= tn) & (boxes[:, 3] >= ts)
        return np.nonzero(hit)[0].tolist()

    transform = from_origin(west, north, gsd, gsd)
    profile = {
        "driver": "GTiff", "width": width, "height": height, "count": bands, "dtype": dtype, "crs": dsm.crs,
        "transform": transform, "nodata": nodata, "tiled": True, "blockxsize": config.tile_px,
        "blockysize": config.tile_px, "compress": "deflate", "predictor": 2, "BIGTIFF": "IF_SAFER",
    }
    # the working file is written by this process while the workers render, and read once by _finalise:
    # uncompressed, as the levels are (zstd at level 1 cost this process 2.0 s of writing on a 9280 x 7360 RGB
    # mosaic on one core, uncompressed 0.7-0.9 s; the file on disk is then bands x bytes x pixels, 205 MB there)
    work_profile = {k: v for k, v in profile.items() if k not in ("compress", "predictor")}
    total = len(tiles)
    with_data = 0
    valid_px = 0
    tmpdir = Path(tempfile.mkdtemp(prefix=".tmp-mosaic.", dir=out_path.parent if out_path.parent.exists()
                                   else None))
    opencv_threads = cv2.getNumThreads()  # render_tile sets one: this process's own count comes back after
    try:
        work = tmpdir / "work.tif"
        levels = [tmpdir / f"overview_{f}.tif" for f in factors]
        with contextlib.ExitStack() as files:
            dst = files.enter_context(rasterio.open(work, "w", **work_profile))
            # each level a file of its own, uncompressed (a tile's part of a level is a fraction of a block, and
            # a block written in parts is compressed once per part): the COG is copied from them and the
            # working file together (_finalise)
            plain = {k: v for k, v in profile.items() if k not in ("compress", "predictor")}
            dst_levels = [files.enter_context(rasterio.open(
                path, "w", **(plain | {"width": -(-width // f), "height": -(-height // f)})))
                for f, path in zip(factors, levels, strict=True)]
            done = 0
            for tile, arr, pyramid in _run_tiles(tiles, members, frames, images, dsm, config, nodata, dtype, bands,
                                                 client, threads, len(factors)):
                dst.write(arr, window=rasterio.windows.Window(tile.col0, tile.row0, tile.cols, tile.rows))
                for f, level, part in zip(factors, dst_levels, pyramid, strict=True):
                    level.write(part, window=rasterio.windows.Window(tile.col0 // f, tile.row0 // f,
                                                                      part.shape[2], part.shape[1]))
                n_valid = int(np.count_nonzero(arr[0] != nodata))
                valid_px += n_valid
                with_data += n_valid > 0
                done += 1
                if progress:
                    progress(done, total)
        _finalise(work, out_path, config, profile, dict(zip(factors, levels, strict=True)))
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
        forget_frames()  # this process's frames (the serial tiles, the first frame's sample)
        cv2.setNumThreads(opencv_threads)
    return MosaicResult(
        path=out_path, crs=dsm.crs, transform=tuple(transform)[:6], width=width, height=height, gsd_m=float(gsd),
        nodata=int(nodata), dtype=dtype, bands=bands, tiles=total, tiles_with_data=with_data,
        coverage=valid_px / float(width * height),
    )


def _run_tiles(tiles, members, frames, images, dsm, config, nodata, dtype, bands, client, threads=1, levels=0):
    """Yield (tile, array, its first ``levels`` overview levels) as tiles complete (:func:`render_tile_pyramid`):
    in this process (on ``threads`` threads, in ``tiles``' order), or on the Dask client (in ``tiles``' order, which
    the scheduler keeps for tasks submitted one after another). A frame given as a path is decoded where the tile
    is rendered, once per process while it is in use (:func:`frame_pixels`)."""
    args = (config.feather_px, nodata, dtype, bands)
    if client is None:
        def one(tile: TileSpec) -> tuple[TileSpec, np.ndarray, list[np.ndarray]]:
            idx = members(tile)
            return render_tile_pyramid(levels, tile, [frames[k] for k in idx],
                                       [images[frames[k].image_id] for k in idx], dsm.window(tile.bounds()), *args)

        if threads <= 1:
            yield from map(one, tiles)
            return
        # a few tiles ahead of the writer per thread, not all of them: a finished tile waits in memory until the
        # tiles before it are written
        with concurrent.futures.ThreadPoolExecutor(threads) as pool:
            pending: collections.deque = collections.deque()
            for tile in tiles:
                pending.append(pool.submit(one, tile))
                if len(pending) >= 4 * threads:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        return

    # lazy: distributed is slow to import; only the Dask path needs it
    from distributed import as_completed

    arrays = {f.image_id: images[f.image_id] for f in frames if isinstance(images[f.image_id], np.ndarray)}
    scattered = client.scatter(arrays) if arrays else {}
    # each worker renders one run of the curve, so that it decodes the frames of its part of the block and not
    # every frame the other workers read too; an idle worker still takes tiles from a busy one (loose restriction).
    # A task renders TILES_PER_TASK tiles that follow one another on the curve: they share frames, and the
    # scheduler's and the transfers' cost per task is paid once for them
    workers = sorted(client.scheduler_info()["workers"])
    runs = np.array_split(np.arange(len(tiles)), max(len(workers), 1))
    home = {int(i): [w] for w, run in zip(workers, runs, strict=False) for i in run}
    futures = []
    for start in range(0, len(tiles), TILES_PER_TASK):
        jobs = []
        for tile in tiles[start:start + TILES_PER_TASK]:
            idx = members(tile)
            pix = [scattered[frames[k].image_id] if frames[k].image_id in scattered
                   else str(images[frames[k].image_id]) for k in idx]
            jobs.append((tile, [frames[k] for k in idx], pix, dsm.window(tile.bounds())))
        futures.append(client.submit(_render_tiles, levels, jobs, *args, pure=False, workers=home.get(start),
                                     allow_other_workers=True))
    try:
        for fut in as_completed(futures):
            yield from fut.result()
    finally:
        for fut in futures:
            fut.release()
        client.run(forget_frames, on_error="ignore")  # a worker lost on the way has nothing to release


#: tiles one Dask task renders (:func:`_run_tiles`): a task per tile cost the flow's process (the scheduler, the
#: submitting, the results) twice the CPU of eight (benchmarks/RESULTS.md, "Orthomosaic: a Dask task for eight tiles")
TILES_PER_TASK = 8


def _render_tiles(levels: int, jobs: Sequence[tuple], feather_px: float, nodata: int, dtype: str, bands: int
                  ) -> list[tuple[TileSpec, np.ndarray, list[np.ndarray]]]:
    """:func:`render_tile_pyramid` of each (tile, frames, pixels, DSM window) in ``jobs``, in order."""
    return [render_tile_pyramid(levels, tile, frames, pixels, dsm, feather_px, nodata, dtype, bands)
            for tile, frames, pixels, dsm in jobs]


def overview_factors(width: int, height: int, config: MosaicConfig) -> list[int]:
    """The overview levels (decimation factors) the tiles compute for a ``width`` x ``height`` mosaic, or none
    where GDAL is left to make them from the finished mosaic.

    The levels are GDAL's: for a COG, halving until the coarsest level fits in one block (``config.tile_px``); for
    a tiled GeoTIFF, 2 to 32 while the shorter side keeps at least 64 pixels. The tiles compute them (average of
    their valid pixels, :func:`aerocal.products.kernels.halve`) when every factor divides ``config.tile_px`` (each
    tile's part of a level is then made of its own pixels alone) and the resampling is "average"; otherwise none.

    Why: GDAL's COG driver made the overviews of a 9267 x 7352 RGB mosaic after the last tile, on one core, in
    more than a third of its copy (benchmarks/RESULTS.md, "Orthomosaic: the overview levels made by the tiles")."""
    factors = _gdal_factors(width, height, config)
    if config.overview_resampling != "average" or any(config.tile_px % f for f in factors):
        return []
    return factors


def _gdal_factors(width: int, height: int, config: MosaicConfig) -> list[int]:
    """The overview levels GDAL makes of a ``width`` x ``height`` mosaic (:func:`overview_factors`)."""
    if config.cog:
        return cog_overview_factors(width, height, config.tile_px)
    factors, f = [], 2
    while f <= 32 and min(width, height) // f >= 64:
        factors.append(f)
        f *= 2
    return factors


def render_tile_pyramid(levels: int, tile: TileSpec, frames: Sequence[FrameGeometry],
                        pixels: Sequence[np.ndarray | str | Path], dsm: Dsm, feather_px: float, nodata: int,
                        dtype: str, bands: int) -> tuple[TileSpec, np.ndarray, list[np.ndarray]]:
    """:func:`render_tile` and the tile's first ``levels`` overview levels, each half the size of the one before
    (rounded up): the average of its valid pixels (:func:`halve`)."""
    tile, arr = render_tile(tile, frames, pixels, dsm, feather_px, nodata, dtype, bands)
    hi = np.iinfo(arr.dtype).max
    pyramid, level = [], arr
    for _ in range(levels):
        half = np.empty((level.shape[0], -(-level.shape[1] // 2), -(-level.shape[2] // 2)), dtype=level.dtype)
        halve(level, nodata, hi, half)
        pyramid.append(half)
        level = half
    return tile, arr, pyramid


def _finalise(work: Path, out_path: Path, config: MosaicConfig, profile: dict, levels: Mapping[int, Path]) -> None:
    """Copy the working GeoTIFF to ``out_path`` as a COG (or tiled GeoTIFF with overviews), atomically. ``levels``:
    the overview levels the tiles made (factor -> file, :func:`overview_factors`); where there are none, GDAL makes
    them from the working file.

    GDAL compresses with every core (``NUM_THREADS``): the workers are done by now. Deflate at the DSM's level 1,
    not GDAL's 6: on a 9280 x 7360 RGB mosaic the copy took 1.0 s at level 1, 1.8 s at 3 and 4.3 s at 6, for
    files of 90, 86 and 84 MB (benchmarks/RESULTS.md, "Orthomosaic: a frame's view of a tile in vector
    instructions")."""
    resampling = Resampling[config.overview_resampling]
    source = _with_overviews(work, levels) if levels else work
    with atomic_path(out_path) as tmp:
        if config.cog:
            rasterio.shutil.copy(source, tmp, driver="COG", COMPRESS="DEFLATE", LEVEL=DEFLATE_LEVEL, PREDICTOR="YES",
                                 BLOCKSIZE=config.tile_px, OVERVIEW_RESAMPLING=config.overview_resampling.upper(),
                                 BIGTIFF="IF_SAFER", NUM_THREADS="ALL_CPUS")
        else:
            if not levels:
                with rasterio.open(work, "r+") as src:
                    factors = _gdal_factors(src.width, src.height, config)
                    if factors:
                        src.build_overviews(factors, resampling)
            rasterio.shutil.copy(source, tmp, driver="GTiff", TILED="YES", COMPRESS="DEFLATE", ZLEVEL=DEFLATE_LEVEL,
                                 PREDICTOR=2, BLOCKXSIZE=config.tile_px, BLOCKYSIZE=config.tile_px,
                                 COPY_SRC_OVERVIEWS="YES", NUM_THREADS="ALL_CPUS")


def _with_overviews(work: Path, levels: Mapping[int, Path]) -> Path:
    """A GDAL virtual raster (VRT) beside ``work`` that is ``work`` with ``levels`` (factor -> file, finest first) as
    its overviews, which GDAL's COG and GeoTIFF copies then take instead of making their own."""
    vrt = work.with_suffix(".vrt")
    rasterio.shutil.copy(work, vrt, driver="VRT")
    tree = ET.parse(vrt)
    for band in tree.getroot().iter("VRTRasterBand"):
        for path in levels.values():
            overview = ET.SubElement(band, "Overview")
            ET.SubElement(overview, "SourceFilename", relativeToVRT="0").text = str(path)
            ET.SubElement(overview, "SourceBand").text = band.get("band")
    tree.write(vrt)
    return vrt


def write_temperature_raster(
    counts_path: str | Path,
    out_path: str | Path,
    to_celsius: Callable[[np.ndarray], np.ndarray],
) -> Path:
    """A float32 GeoTIFF of temperatures (degC) from a radiometric counts orthomosaic, block by block.

    ``to_celsius`` converts raw counts to degC (e.g. :func:`aerocal.ingest.flir.raw_to_celsius` with the
    flight's camera information). Nodata cells of the counts stay NaN; the grid, CRS and tiling are the
    orthomosaic's, so memory is bounded by one block whatever the area. Written atomically."""
    out_path = Path(out_path)
    with rasterio.open(counts_path) as src:
        profile = src.profile.copy()
        profile.update(count=1, dtype="float32", nodata=float("nan"), predictor=3)
        nodata = src.nodata
        with atomic_path(out_path) as tmp, rasterio.open(tmp, "w", **profile) as dst:
            for _, window in src.block_windows(1):
                raw = src.read(1, window=window)
                t = np.asarray(to_celsius(raw), dtype=np.float32)
                if nodata is not None:
                    t[raw == nodata] = np.nan
                dst.write(t, 1, window=window)
            dst.update_tags(1, units="degC", quantity="object temperature")
    return out_path
