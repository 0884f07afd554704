"""Ray-casting renderer: images of a simulated scene seen through a simulated exposure.

Every pixel is integrated from ``supersample x supersample`` sub-pixel rays (a box filter over the pixel
area, so edges are anti-aliased and target centroids are exact), each ray given by ``exposure.rays`` (all
geometric effects live there: distortion, refraction, rolling shutter...) and intersected with the
scene's DSM. Then optics and sensor act on the image: vignetting, Gaussian optical blur, sensor noise
(the NETD in kelvin for thermal frames).

Pixel convention: origin at the top-left corner of the top-left pixel, x right, y down; the centre of
pixel ``(row, col)`` is ``(col + 0.5, row + 0.5)``.

Ray-DSM intersection (:func:`intersect_dsm`)
--------------------------------------------
The DSM surface is bilinear between cell centres. Vectorised over rays; Python loops only over march
steps, and rays that have hit leave the active set at every step:

1. each ray starts where it descends through the DSM's maximum height and must hit before it passes
   below the minimum (the surface is continuous, edges extended);
2. empty space is skipped with conservative maximum grids (blocks of 16 and 4 cells, each block holding
   the maximum over itself and its neighbours): a ray advances as far as it provably stays above;
3. then it marches one DSM patch (the square between four cell centres) per step, in the order the ray
   crosses them (a 2D DDA, Amanatides & Woo 1987). Along the ray, the bilinear patch is a quadratic in
   the ray parameter, so the first crossing inside a patch is the smallest root of that quadratic in
   the patch's interval: exact, nothing thin is stepped over, and no iterative refinement is needed
   (the height error of a hit is ~1e-9 m, measured in tests/test_raycast.py).

Rays that point upwards from above the DSM, or leave the grid's extent (plus one cell) without hitting,
see the sky: a frame that looks past the edge of the scene shows the sky there, which a flight plan
should avoid (keep footprints inside the scene).

Acceleration (``RenderConfig.accelerate``, on by default)
---------------------------------------------------------
Sub-pixel rays vary smoothly across a pixel, so ``exposure.rays`` is evaluated at pixel centres (with a
one-pixel border) and the sub-pixel rays are interpolated bilinearly; a sample of them is compared with
``exposure.rays`` in every batch and the batch falls back to exact rays if they differ by more than
1e-4 px (or 0.1 mm of origin). Pixel-centre rays are traced fully; where a pixel and its 8 neighbours
hit coherently (no step in distance, hits less than a cell apart horizontally, so no DSM feature fits
between them unseen) its sub-pixel rays are intersected exactly starting 0.3 cell before their
interpolated distance; all other sub-pixel rays are traced fully. Over a flat block and over a city alike
this more than halved a frame's time against tracing every sub-pixel ray
(``benchmarks/history/engine_measurements.md``; a frame's current time: ``benchmarks/RESULTS.md``,
"Simulator"); the two images differ by < 1e-3 K on 99.9 % of the pixels (tests/test_raycast.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import cv2
import numpy as np

from aerocal.camera import Camera
from aerocal.simulate.raycast_kernels import coherent_hits, march, subpixel_rays
from aerocal.simulate.scene import SKY_KELVIN, SKY_RGB, Scene


class ExposureLike(Protocol):
    """What the renderer needs of an exposure (``aerocal.simulate.exposure.Exposure`` provides it)."""

    camera: Camera

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) -> ray origins (N, 3) and unit directions (N, 3), world E, N, Up metres."""
        ...

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> pixels (N, 2), NaN behind the camera."""
        ...


@dataclass(frozen=True)
class RenderConfig:
    """How a frame is rendered. Lengths in metres, temperatures in kelvin, image values in DN."""

    modality: Literal["thermal", "rgb"] = "thermal"
    supersample: int = 3  #: sub-pixel rays per pixel along each axis (3 -> 3 x 3, box-filtered)
    netd_k: float = 0.06  #: thermal sensor noise, 1 sigma, kelvin (added after blur); 0 = noiseless
    dn_per_kelvin: float = 100.0  #: thermal DN = round(dn_per_kelvin * T) (radiometric 0.01 K counts)
    rgb_noise_dn: float = 1.5  #: RGB sensor noise, 1 sigma, DN of 0-255
    vignetting: float = 0.0  #: relative signal fall-off at the image corner, ``1 - v (r / r_corner)^2``
    blur_sigma_px: float = 0.5  #: Gaussian optical blur, pixels; 0 = none
    chunk_rays: int = 1 << 17  #: sub-pixel rays traced per batch (bounds memory; ~150 MB per million)
    accelerate: bool = True  #: derive sub-pixel rays and hits from pixel-centre rays where exact enough

    def __post_init__(self) -> None:
        if self.modality not in ("thermal", "rgb"):
            raise ValueError(f"RenderConfig.modality must be 'thermal' or 'rgb', got {self.modality!r}")
        if int(self.supersample) < 1:
            raise ValueError(f"RenderConfig.supersample must be >= 1, got {self.supersample}")
        if self.netd_k < 0 or self.rgb_noise_dn < 0 or self.blur_sigma_px < 0:
            raise ValueError("RenderConfig: netd_k, rgb_noise_dn and blur_sigma_px must be >= 0")


# ============================================================================================ intersection
@dataclass(frozen=True)
class RayHits:
    """Result of :func:`intersect_dsm` for N rays."""

    points: np.ndarray  #: (N, 3) hit points, world metres; NaN where the ray sees the sky
    t: np.ndarray  #: (N,) distance from the ray origin to the hit, metres; inf for the sky
    hit: np.ndarray  #: (N,) bool


_LEVELS = (16, 4)  # block sizes (cells) of the empty-space-skipping grids, coarse to fine
#: the grids :func:`aerocal.simulate.raycast_kernels.march` is given when empty-space skipping is off
_NO_GRID = np.zeros((1, 1), dtype=np.float32)


def _padded_dsm(scene: Scene) -> np.ndarray:
    """The DSM with one edge-replicated cell on each side, flattened (cached on the scene)."""
    cache = getattr(scene, "_render_padded_dsm", None)
    if cache is None:
        cache = np.pad(scene.dsm, 1, mode="edge").reshape(-1)
        object.__setattr__(scene, "_render_padded_dsm", cache)  # a cache on the frozen scene (derived data)
    return cache


def _max_grids(scene: Scene) -> list[tuple[int, np.ndarray]]:
    """Per level: (block size b, float32 grid bounding the bilinear surface over each block of b x b
    patches and its 8 neighbouring blocks). Patch (r, c) is the square between the centres of cells
    (r, c) and (r + 1, c + 1); the surface inside it is at most the maximum of its four corners. A ray
    point in block B that moves at most b cells horizontally stays inside B's 3 x 3 neighbourhood."""
    cache = getattr(scene, "_render_max_grids", None)
    if cache is not None:
        return cache
    rows, cols = scene.shape
    padded = np.pad(scene.dsm, ((0, 1), (0, 1)), mode="edge")
    patch_max = np.maximum(np.maximum(padded[:-1, :-1], padded[:-1, 1:]),
                           np.maximum(padded[1:, :-1], padded[1:, 1:]))
    out = []
    for b in _LEVELS:
        pr, pc = -(-rows // b) * b, -(-cols // b) * b
        grid = np.pad(patch_max, ((0, pr - rows), (0, pc - cols)), mode="edge")
        blocks = grid.reshape(pr // b, b, pc // b, b).max(axis=(1, 3))
        dil = cv2.dilate(blocks, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
        out.append((b, dil.astype(np.float32) + np.float32(1e-3)))
    object.__setattr__(scene, "_render_max_grids", out)  # a cache on the frozen scene (derived data)
    return out


def intersect_dsm(
    scene: Scene, origins: np.ndarray, directions: np.ndarray, t_start: np.ndarray | None = None,
    skip_empty: bool = True,
) -> RayHits:
    """First intersection of rays with the scene's DSM (bilinear surface), vectorised over rays.

    ``origins`` (N, 3) and unit ``directions`` (N, 3) are world E, N, Up metres. A ray that starts below
    the surface hits at its start; a ray that leaves the grid's extent (plus one cell) without hitting
    does not hit (``hit`` False, ``t`` inf).

    ``t_start`` (N,) optionally starts each ray that far from its origin (metres), the caller vouching
    that the ray is above the surface before it; ``skip_empty=False`` turns the max-grid skipping off
    (for rays started just above their hit).
    """
    o = np.asarray(origins, dtype=float)
    d = np.asarray(directions, dtype=float)
    n_rays = len(d)
    cell = scene.config.cell_m
    rows, cols = scene.shape
    zmin, zmax = scene.height_range
    zmin -= 1e-3
    zmax += 1e-3
    # rays in grid units: col(t) = c0 + t dc, row(t) = r0 + t dr (cells), z(t) = z0 + t dz, t in metres
    c0, r0 = scene.grid_coords(o[:, 0], o[:, 1])
    dc = d[:, 0] / cell
    dr = -d[:, 1] / cell
    z0 = o[:, 2]
    dz = d[:, 2]
    t_first = np.zeros(n_rays) if t_start is None else np.maximum(np.asarray(t_start, dtype=float), 0.0)

    t_hit = np.full(n_rays, np.inf)
    z_first = z0 + t_first * dz
    low = np.nonzero(z_first <= zmax)[0]
    tl = t_first[low]
    under = z_first[low] - scene.height_at_grid(c0[low] + tl * dc[low], r0[low] + tl * dr[low]) <= 0
    below = low[under]  # starts under the surface
    t_hit[below] = t_first[below]
    down = dz < -1e-12
    start_ok = np.ones(n_rays, dtype=bool)
    start_ok[below] = False
    cand = np.nonzero(start_ok & (down | (z_first <= zmax)))[0]  # the others point up from above: sky
    if len(cand) == 0:
        return _hits(o, d, t_hit)
    c0, r0, z0, dc, dr, dz, down = c0[cand], r0[cand], z0[cand], dc[cand], dr[cand], dz[cand], down[cand]
    t_first, z_first = t_first[cand], z_first[cand]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(down & (z_first > zmax), (zmax - z0) / dz, t_first)
        t_end = np.where(down, (zmin - z0) / dz, np.inf)
        t_end = np.where(~down & (dz > 0), (zmax - z0) / np.where(dz > 0, dz, 1.0), t_end)
        t_end = np.minimum(t_end, _t_leave_grid(c0, r0, dc, dr, rows, cols))
    h_len = np.maximum(np.hypot(dc, dr), 1e-12)  # cells per metre, horizontally
    levels = _max_grids(scene) if skip_empty else []
    grids = tuple(g for _, g in levels) or (_NO_GRID, _NO_GRID)
    blocks = np.array([b for b, _ in levels] or [1, 1], dtype=np.int64)
    result = march(_padded_dsm(scene), rows, cols, c0, r0, z0, dc, dr, dz, down, t, t_end, h_len, float(cell),
                   grids, blocks, len(levels))
    t_hit[cand] = result
    return _hits(o, d, t_hit)


def _t_leave_grid(c0, r0, dc, dr, rows: int, cols: int) -> np.ndarray:
    """Ray parameter (metres) where a ray leaves the grid's extent (plus one cell) horizontally."""
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = np.where(dc > 0, (cols + 1 - c0) / dc, np.where(dc < 0, (-2 - c0) / dc, np.inf))
        tr = np.where(dr > 0, (rows + 1 - r0) / dr, np.where(dr < 0, (-2 - r0) / dr, np.inf))
    return np.maximum(np.minimum(tc, tr), 0.0)


def _hits(o: np.ndarray, d: np.ndarray, t: np.ndarray) -> RayHits:
    hit = np.isfinite(t)
    pts = o + np.where(hit, t, np.nan)[:, None] * d
    return RayHits(points=pts, t=t, hit=hit)


def _trace_rows(
    scene: Scene, exposure: ExposureLike, row0: int, row1: int, ss: int, accelerate: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel rays of image rows [row0, row1) and their DSM hits: (origins, directions, t), ordered
    (row, sub-row, col, sub-col); t is inf for the sky.

    With ``accelerate`` the exposure is asked only for the rays of pixel centres (with a one-pixel
    border): sub-pixel rays are interpolated from them (checked against ``exposure.rays`` on a sample of
    sub-pixels; the chunk falls back to exact rays beyond 1e-4 px or 0.1 mm), and where the pixel-centre
    hits of a pixel and its 8 neighbours are coherent (no depth step, hits less than a cell apart, so
    nothing can stand between them) each sub-pixel ray is intersected starting just before its
    interpolated distance; every other sub-pixel ray is traced from the top.
    """
    cam = exposure.camera
    width = int(cam.width)
    offs = (np.arange(ss) + 0.5) / ss
    u = (np.arange(width)[:, None] + offs[None, :]).reshape(-1)
    v = (np.arange(row0, row1)[:, None] + offs[None, :]).reshape(-1)
    uu, vv = np.meshgrid(u, v)
    uv = np.column_stack([uu.reshape(-1), vv.reshape(-1)])
    if not accelerate:
        o, d = exposure.rays(uv)
        return o, d, intersect_dsm(scene, o, d).t

    # pixel-centre rays on a grid with a one-pixel border: anchor (i, j) is pixel (row0 - 1 + i, j - 1)
    ua = np.arange(-1, width + 1) + 0.5
    va = np.arange(row0 - 1, row1 + 1) + 0.5
    ga, gb = np.meshgrid(ua, va)
    oa, da = exposure.rays(np.column_stack([ga.reshape(-1), gb.reshape(-1)]))
    anchors = intersect_dsm(scene, oa, da)
    shape_a = (len(va), len(ua))
    # sub-pixel rays interpolated from the anchors, checked against the exposure's own on a sample
    o, d = subpixel_rays(oa.reshape(shape_a + (3,)), da.reshape(shape_a + (3,)), ss)
    check = np.linspace(0, len(uv) - 1, 64).astype(np.int64)
    oc, dc = exposure.rays(uv[check])
    angle_px = np.linalg.norm(dc - d[check], axis=1).max() * float(cam.f)
    if angle_px > 1e-4 or np.abs(oc - o[check]).max() > 1e-4:
        o, d = exposure.rays(uv)
    # coherent pixels' sub-pixel rays intersected near their interpolated distance, the rest from the top
    cfg = scene.config
    top_n = cfg.origin_n + scene.shape[0] * cfg.cell_m
    t, todo = coherent_hits(_padded_dsm(scene), scene.shape[0], scene.shape[1], float(cfg.origin_e), float(top_n),
                            float(cfg.cell_m), o, d, anchors.t.reshape(shape_a),
                            np.ascontiguousarray(anchors.points.reshape(shape_a + (3,))[..., :2]), ss)
    rest = np.nonzero(todo)[0]
    if len(rest):
        t[rest] = intersect_dsm(scene, o[rest], d[rest]).t
    return o, d, t


def render_radiance(scene: Scene, exposure: ExposureLike, config: RenderConfig) -> np.ndarray:
    """The noiseless, unblurred signal: (H, W) kelvin (thermal) or (H, W, 3) reflectance 0-255 (RGB),
    each pixel the mean of its sub-pixel rays."""
    cam = exposure.camera
    width, height = int(cam.width), int(cam.height)
    ss = int(config.supersample)
    thermal = config.modality == "thermal"
    out = np.empty((height, width) if thermal else (height, width, 3), dtype=np.float64)
    rows_per_chunk = max(1, int(config.chunk_rays) // (width * ss * ss))
    f_px = float(cam.f)
    for row0 in range(0, height, rows_per_chunk):
        row1 = min(row0 + rows_per_chunk, height)
        o, d, t = _trace_rows(scene, exposure, row0, row1, ss, config.accelerate)
        hit = np.isfinite(t)
        th = np.where(hit, t, 0.0)
        footprint = th / (f_px * ss)  # ground spacing of the sub-samples, metres
        e = o[:, 0] + th * d[:, 0]
        n = o[:, 1] + th * d[:, 1]
        nr = row1 - row0
        if thermal:
            vals = scene.thermal_at(e, n, footprint)
            vals[~hit] = SKY_KELVIN
            out[row0:row1] = vals.reshape(nr, ss, width, ss).mean(axis=(1, 3))
        else:
            vals = scene.rgb_at(e, n, footprint)
            vals[~hit] = SKY_RGB
            out[row0:row1] = vals.reshape(nr, ss, width, ss, 3).mean(axis=(1, 3))
    return out


def vignetting_factor(camera: Camera, strength: float) -> np.ndarray:
    """(H, W) multiplicative fall-off ``1 - strength (r / r_corner)^2``, r from the principal point."""
    u = np.arange(camera.width) + 0.5 - camera.cx
    v = np.arange(camera.height) + 0.5 - camera.cy
    r2 = u[None, :] ** 2 + v[:, None] ** 2
    corner = max(camera.cx, camera.width - camera.cx) ** 2 + max(camera.cy, camera.height - camera.cy) ** 2
    return 1.0 - strength * r2 / corner


def render_frame(
    scene: Scene, exposure: ExposureLike, config: RenderConfig, rng: np.random.Generator
) -> np.ndarray:
    """Render one frame: (H, W) uint16 thermal DN (= round(dn_per_kelvin * T) with noise at the NETD),
    or (H, W, 3) uint8 RGB. Only ``exposure.rays`` and ``exposure.camera`` (size, focal length) are used.
    """
    img = render_radiance(scene, exposure, config)
    if config.vignetting:
        fall = vignetting_factor(exposure.camera, config.vignetting)
        img = img * (fall if img.ndim == 2 else fall[..., None])
    if config.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigmaX=config.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
    if config.modality == "thermal":
        if config.netd_k > 0:
            img = img + rng.normal(0.0, config.netd_k, img.shape)
        return np.clip(np.rint(img * config.dn_per_kelvin), 0, 65535).astype(np.uint16)
    if config.rgb_noise_dn > 0:
        img = img + rng.normal(0.0, config.rgb_noise_dn, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
