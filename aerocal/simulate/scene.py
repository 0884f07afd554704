"""Simulated scenes: a digital surface model with surface classes, thermal and RGB-like textures and targets.

Frames and grids
----------------
* World frame: the scene's projected CRS (``SceneConfig.crs``), easting E, northing N, height Up, metres.
* Grids (``Scene.dsm``, ``Scene.ground``, ``Scene.classes`` and the texture bases) have ``rows`` from north
  to south and ``cols`` from west to east, one value per cell of ``cell_m`` metres. Cell ``(row, col)`` is
  centred on ``E = origin_e + (col + 0.5) cell_m``, ``N = origin_n + height_m - (row + 0.5) cell_m``.
* Heights (:meth:`Scene.height_at`) are bilinear between cell centres; outside the grid the edge values are
  extended. (The renderer shows the sky beyond the grid's extent.)

Textures
--------
The texture of a point is the sum of a gridded base and a procedural detail:

* the base is stored at the cell size: per-class temperatures (roofs 285-300 K per building, the two sides
  of a gable roof differing, streets ~291 K, field parcels ~284-292 K, vegetation ~283 K, water ~279 K),
  class boundaries Gaussian-blurred by ``edge_blur_m``, plus seeded noise at scales from one cell to
  64 cells so that SIFT finds features everywhere;
* finer detail (octaves of 1/2, 1/4 and 1/8 cell) is hash-based value noise evaluated at the query
  points, so memory does not grow with the rendering's resolution: a scene stores 16 bytes per cell
  (160 MB for 4 km x 2.5 km at 1 m cells; several times that at its peak while generating it:
  ``benchmarks/history/engine_measurements.md``). Octaves finer than the footprint of a rendering sample
  are faded out (a band limit, so supersampled renderings do not alias);
* signalised targets (:meth:`Scene.place_targets`) are analytic: a hot/bright disc on a cold/dark
  square, edges anti-aliased over the sample footprint, so the centroid of a rendered target is exact.

Sensor noise is not part of the scene: the renderer adds it at the camera's NETD.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from aerocal.simulate.noise_kernels import detail

#: Surface classes stored in :attr:`Scene.classes` (uint8).
CLASS_GROUND = 0  # open ground, fields and streets
CLASS_ROOF = 1
CLASS_VEGETATION = 2
CLASS_WATER = 3
CLASS_NAMES: dict[int, str] = {
    CLASS_GROUND: "ground", CLASS_ROOF: "roof", CLASS_VEGETATION: "vegetation", CLASS_WATER: "water",
}

#: Temperatures (K) and colours of what is not on the ground: a clear sky, and the target paint.
SKY_KELVIN = 230.0
SKY_RGB = (170.0, 200.0, 235.0)


@dataclass(frozen=True)
class SceneConfig:
    """Size, position and content of a simulated scene. Lengths in metres, temperatures in kelvin."""

    width_m: float = 2000.0  #: extent east
    height_m: float = 1500.0  #: extent north
    cell_m: float = 1.0  #: DSM and texture-base cell size
    origin_e: float = 500000.0  #: easting of the south-west corner
    origin_n: float = 4_900_000.0  #: northing of the south-west corner
    crs: str = "EPSG:32632"
    terrain_relief_m: float = 20.0  #: peak-to-peak height of the smooth terrain
    terrain_mean_m: float = 50.0  #: mean terrain height
    building_density: float = 0.25  #: fraction of the area covered by buildings (city); 0 for fields
    building_height_m: tuple[float, float] = (6.0, 30.0)  #: eave heights drawn uniformly in this range
    gable_fraction: float = 0.4  #: fraction of buildings with a gable roof (the rest are flat)
    vegetation_density: float = 0.1  #: fraction of the area under tree crowns
    tree_height_m: tuple[float, float] = (4.0, 15.0)
    tree_radius_m: tuple[float, float] = (2.0, 6.0)
    water_density: float = 0.02  #: fraction of the area under ponds (flat water surfaces)
    flat: bool = False  #: a flat block: DSM constant at terrain_mean_m (no relief, buildings or trees)
    edge_blur_m: float = 2.0  #: Gaussian sigma blurring thermal class boundaries
    rgb_edge_blur_m: float = 0.5  #: the same for the RGB texture
    texture_k: float = 0.35  #: amplitude (K) of each octave of thermal texture noise
    texture_rgb: float = 9.0  #: amplitude (digital numbers, 0-255) of each octave of RGB texture noise
    detail_octaves: tuple[float, ...] = (0.5, 0.25, 0.125)  #: sub-cell value-noise lattice spacings, in cells
    target_hot_k: float = 315.0  #: target disc temperature
    target_cold_k: float = 275.0  #: target background-square temperature
    target_bright: float = 245.0  #: target disc reflectance (0-255)
    target_dark: float = 25.0  #: target square reflectance (0-255)
    target_square_ratio: float = 3.0  #: half-side of the target square / disc radius

    def __post_init__(self) -> None:
        for name in ("width_m", "height_m", "cell_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SceneConfig.{name} must be positive, got {getattr(self, name)}")
        for name in ("building_density", "vegetation_density", "water_density"):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                raise ValueError(f"SceneConfig.{name} must be in [0, 1), got {v}")
        if self.target_square_ratio <= 1.0:
            raise ValueError(f"SceneConfig.target_square_ratio must exceed 1, got {self.target_square_ratio}")

    @property
    def shape(self) -> tuple[int, int]:
        """Grid shape (rows north->south, cols west->east)."""
        return int(round(self.height_m / self.cell_m)), int(round(self.width_m / self.cell_m))


@dataclass(frozen=True, eq=False)
class Scene:
    """A simulated scene: surface heights, classes and textures (see the module docstring for frames).

    Build one with :func:`make_scene`. Arrays are shared between a scene and the copies
    :meth:`place_targets` makes; do not modify them in place.
    """

    config: SceneConfig
    seed: int
    dsm: np.ndarray  #: float32 (rows, cols), surface height (terrain + buildings + trees), metres
    ground: np.ndarray  #: float32 (rows, cols), terrain height without buildings and trees, metres
    classes: np.ndarray  #: uint8 (rows, cols), CLASS_* codes
    thermal_base: np.ndarray  #: float32 (rows, cols), kelvin, blurred class temperatures + gridded noise
    rgb_base: np.ndarray  #: uint8 (rows, cols, 3), reflectance 0-255
    targets_en: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  #: (M, 2) target centres E, N
    targets_radius: np.ndarray = field(default_factory=lambda: np.zeros(0))  #: (M,) disc radii, metres
    target_index: np.ndarray | None = None  #: int32 (rows, cols): target whose square covers a cell, or -1

    # ------------------------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int]:
        return self.dsm.shape  # type: ignore[return-value]

    def bounds(self) -> tuple[float, float, float, float]:
        """(e_min, n_min, e_max, n_max) of the grid, metres."""
        c = self.config
        rows, cols = self.shape
        return (c.origin_e, c.origin_n, c.origin_e + cols * c.cell_m, c.origin_n + rows * c.cell_m)

    @property
    def height_range(self) -> tuple[float, float]:
        """(min, max) of the DSM, metres."""
        return float(self.dsm.min()), float(self.dsm.max())

    def grid_coords(self, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World E, N (metres) -> fractional grid (col, row) with cell centres at integers."""
        c = self.config
        rows = self.shape[0]
        col = (np.asarray(e, dtype=float) - c.origin_e) / c.cell_m - 0.5
        row = (c.origin_n + rows * c.cell_m - np.asarray(n, dtype=float)) / c.cell_m - 0.5
        return col, row

    def cell_centres(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer grid indices -> world E, N of the cell centres, metres."""
        c = self.config
        e = c.origin_e + (np.asarray(cols, dtype=float) + 0.5) * c.cell_m
        n = c.origin_n + (self.shape[0] - np.asarray(rows, dtype=float) - 0.5) * c.cell_m
        return e, n

    def height_at(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Surface (DSM) height at world E, N arrays, metres, bilinear between cell centres."""
        col, row = self.grid_coords(e, n)
        return _bilinear(self.dsm, col, row)

    def height_at_grid(self, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """Surface height at fractional grid coordinates (see :meth:`grid_coords`), metres."""
        return _bilinear(self.dsm, col, row)

    def ground_height_at(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Terrain height without buildings and trees at world E, N arrays, metres (bilinear)."""
        col, row = self.grid_coords(e, n)
        return _bilinear(self.ground, col, row)

    def class_at(self, e: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Surface class (CLASS_* codes) of the cell holding each E, N point (edge cells outside)."""
        col, row = self.grid_coords(e, n)
        r, c = _nearest_index(self.classes.shape, col, row)
        return self.classes[r, c]

    def open_ground_positions(
        self, count: int, rng: np.random.Generator, clearance_m: float = 8.0, margin_m: float = 50.0,
        min_spacing_m: float = 0.0,
    ) -> np.ndarray:
        """``count`` random (E, N) positions on open ground (no roof, tree or water within ``clearance_m``,
        at least ``margin_m`` inside the scene, at least ``min_spacing_m`` apart), e.g. where ground
        control points are surveyed. (count, 2), metres.

        Raises:
            ValueError: fewer than ``count`` positions qualify; lower ``clearance_m`` or ``min_spacing_m``.
        """
        c = self.config
        blocked = self.classes != CLASS_GROUND
        k = max(1, int(np.ceil(clearance_m / c.cell_m)))
        yy, xx = np.mgrid[-k:k + 1, -k:k + 1]
        blocked = ndimage.binary_dilation(blocked, structure=(xx**2 + yy**2) <= k * k)
        m = int(np.ceil(margin_m / c.cell_m))
        blocked[:m], blocked[-m:], blocked[:, :m], blocked[:, -m:] = True, True, True, True
        rows, cols = np.nonzero(~blocked)
        order = rng.permutation(len(rows))
        e, n = self.cell_centres(rows[order], cols[order])
        if min_spacing_m > 0:
            keep: list[int] = []
            for i in range(len(e)):  # greedy thinning; stops as soon as ``count`` are found
                if not keep or np.min(np.hypot(e[keep] - e[i], n[keep] - n[i])) >= min_spacing_m:
                    keep.append(i)
                    if len(keep) == count:
                        break
            e, n = e[keep], n[keep]
        if len(e) < count:
            raise ValueError(f"only {len(e)} open-ground positions for {count} requested; lower clearance_m "
                             "or min_spacing_m")
        return np.column_stack([e[:count], n[:count]])

    # ------------------------------------------------------------------------------------ textures
    def thermal_at(self, e: np.ndarray, n: np.ndarray, footprint_m: np.ndarray | float = 0.0) -> np.ndarray:
        """Surface temperature (kelvin, float64) at world E, N arrays.

        ``footprint_m`` (scalar or per point) is the ground size of a rendering sample: detail octaves
        finer than it are faded out and target edges are anti-aliased over it (0 = point sampling).
        """
        col, row = self.grid_coords(e, n)
        t = _bilinear(self.thermal_base, col, row).astype(float)
        t += self.config.texture_k * self._detail(e, n, footprint_m)
        c = self.config
        return self._paint_targets(e, n, col, row, t, c.target_hot_k, c.target_cold_k, footprint_m)

    def rgb_at(self, e: np.ndarray, n: np.ndarray, footprint_m: np.ndarray | float = 0.0) -> np.ndarray:
        """Reflectance (N, 3), float in the 0-255 range, at world E, N arrays (``footprint_m`` as in
        :meth:`thermal_at`)."""
        col, row = self.grid_coords(e, n)
        rgb = _bilinear(self.rgb_base, col, row)
        rgb += (self.config.texture_rgb * self._detail(e, n, footprint_m))[..., None]
        c = self.config
        out = np.empty_like(rgb)
        for k in range(3):
            out[..., k] = self._paint_targets(
                e, n, col, row, rgb[..., k], c.target_bright, c.target_dark, footprint_m
            )
        return np.clip(out, 0.0, 255.0)

    def _detail(self, e: np.ndarray, n: np.ndarray, footprint_m: np.ndarray | float) -> np.ndarray:
        """Sub-cell value noise in [-1, 1] per octave, summed, band-limited by the footprint."""
        c = self.config
        e = np.asarray(e, dtype=float) - c.origin_e
        n = np.asarray(n, dtype=float) - c.origin_n
        e, n, fp = np.broadcast_arrays(e, n, np.asarray(footprint_m, dtype=float))
        spacings = np.array([octave * c.cell_m for octave in c.detail_octaves], dtype=float)
        salts = np.array([self.seed * 7919 + k for k in range(len(spacings))], dtype=np.int64)
        # each octave weighted 1 for footprints up to half its spacing, faded out by a whole spacing
        out = detail(np.ravel(e), np.ravel(n), np.ravel(fp), spacings, salts)
        return out.reshape(e.shape)

    def _paint_targets(self, e, n, col, row, values, disc_value, square_value, footprint_m):
        if self.target_index is None or len(self.targets_radius) == 0:
            return values
        r, cidx = _nearest_index(self.target_index.shape, col, row)
        tid = self.target_index[r, cidx]
        sel = np.nonzero(tid >= 0)[0] if tid.ndim else (np.array([0]) if tid >= 0 else np.zeros(0, int))
        if len(sel) == 0:
            return values
        values = np.array(values, dtype=float, copy=True)
        flat_vals = values.reshape(-1)
        ee = np.broadcast_to(np.asarray(e, dtype=float), values.shape).reshape(-1)[sel]
        nn = np.broadcast_to(np.asarray(n, dtype=float), values.shape).reshape(-1)[sel]
        ids = tid.reshape(-1)[sel]
        fp = np.broadcast_to(np.asarray(footprint_m, dtype=float), values.shape).reshape(-1)[sel]
        width = np.maximum(fp, 1e-6)
        dx = ee - self.targets_en[ids, 0]
        dy = nn - self.targets_en[ids, 1]
        radius = self.targets_radius[ids]
        half = radius * self.config.target_square_ratio
        disc = np.clip(0.5 + (radius - np.hypot(dx, dy)) / width, 0.0, 1.0)
        square = np.clip(0.5 + (half - np.maximum(np.abs(dx), np.abs(dy))) / width, 0.0, 1.0)
        under = flat_vals[sel]
        flat_vals[sel] = disc * disc_value + (1 - disc) * (square * square_value + (1 - square) * under)
        return values

    # ------------------------------------------------------------------------------------ targets
    def place_targets(self, positions: np.ndarray, radius_m: float | np.ndarray) -> Scene:
        """A copy of the scene with signalised targets painted at ``positions`` (M, 2: E, N, metres).

        Each target is a disc of ``radius_m`` (hot in the thermal texture, bright in RGB) on a square of
        half-side ``target_square_ratio * radius_m`` (cold / dark), axis-aligned with E and N. The DSM is
        not changed: a target lies on the surface at ``height_at(e, n)``. Targets already placed are
        kept; squares must not overlap.

        Raises:
            ValueError: ``positions`` is not (M, 2); a radius is not positive; a target lies outside the scene's bounds;
                the squares of two targets (new or already placed) overlap.
        """
        pos = np.atleast_2d(np.asarray(positions, dtype=float))
        if pos.shape[1] != 2:
            raise ValueError(f"place_targets: positions must be (M, 2) E, N, got shape {pos.shape}")
        radius = np.broadcast_to(np.asarray(radius_m, dtype=float), (len(pos),)).copy()
        if np.any(radius <= 0):
            raise ValueError("place_targets: radius_m must be positive")
        en = np.vstack([self.targets_en, pos])
        rad = np.concatenate([self.targets_radius, radius])
        half = rad * self.config.target_square_ratio
        e0, n0, e1, n1 = self.bounds()
        outside = (pos[:, 0] < e0) | (pos[:, 0] > e1) | (pos[:, 1] < n0) | (pos[:, 1] > n1)
        if np.any(outside):
            raise ValueError(f"place_targets: target(s) {np.nonzero(outside)[0].tolist()} outside the scene "
                             f"bounds {self.bounds()}")
        d = np.maximum(np.abs(en[:, None, 0] - en[None, :, 0]), np.abs(en[:, None, 1] - en[None, :, 1]))
        np.fill_diagonal(d, np.inf)
        clash = d < (half[:, None] + half[None, :])
        if np.any(clash):
            i, j = np.argwhere(clash)[0]
            raise ValueError(f"place_targets: the squares of targets {i} and {j} overlap; move them apart")
        index = np.full(self.shape, -1, dtype=np.int32)
        cell = self.config.cell_m
        for k in range(len(en)):  # one slice per target (tens to hundreds of targets)
            col, row = self.grid_coords(en[k, 0], en[k, 1])
            m = half[k] / cell + 1.0
            r0, r1 = max(int(np.floor(row - m)), 0), min(int(np.ceil(row + m)) + 1, self.shape[0])
            c0, c1 = max(int(np.floor(col - m)), 0), min(int(np.ceil(col + m)) + 1, self.shape[1])
            index[r0:r1, c0:c1] = k
        return dataclasses.replace(self, targets_en=en, targets_radius=rad, target_index=index)

    def target_points(self) -> np.ndarray:
        """Target centres on the surface, (M, 3) E, N, height (metres)."""
        if len(self.targets_en) == 0:
            return np.zeros((0, 3))
        h = self.height_at(self.targets_en[:, 0], self.targets_en[:, 1])
        return np.column_stack([self.targets_en, h])


# ============================================================================================ sampling
def _bilinear(grid: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a (rows, cols) or (rows, cols, channels) grid at fractional (col, row),
    cell centres at integers, edges extended. Float64 result of shape ``col.shape`` (+ channels);
    integer grids are interpolated in floating point."""
    rows, cols = grid.shape[:2]
    col = np.clip(np.asarray(col, dtype=float), 0.0, cols - 1.0)
    row = np.clip(np.asarray(row, dtype=float), 0.0, rows - 1.0)
    c0 = np.minimum(col.astype(np.int64), max(cols - 2, 0))
    r0 = np.minimum(row.astype(np.int64), max(rows - 2, 0))
    fc = col - c0
    fr = row - r0
    flat = grid.reshape((rows * cols,) + grid.shape[2:])
    if grid.ndim == 3:
        fc = fc[..., None]
        fr = fr[..., None]
    i00 = r0 * cols + c0
    dc = 1 if cols > 1 else 0
    dr = cols if rows > 1 else 0
    as_float = np.float32 if flat.dtype.kind in "iub" else None
    v00 = flat[i00].astype(as_float or flat.dtype, copy=False)
    v01 = flat[i00 + dc].astype(as_float or flat.dtype, copy=False)
    v10 = flat[i00 + dr].astype(as_float or flat.dtype, copy=False)
    v11 = flat[i00 + dr + dc].astype(as_float or flat.dtype, copy=False)
    top = v00 + fc * (v01 - v00)
    bottom = v10 + fc * (v11 - v10)
    return top + fr * (bottom - top)


def _nearest_index(shape: tuple[int, int], col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = shape
    r = np.clip(np.rint(np.asarray(row, dtype=float)), 0, rows - 1).astype(np.int64)
    c = np.clip(np.rint(np.asarray(col, dtype=float)), 0, cols - 1).astype(np.int64)
    return r, c


# ============================================================================================ generation
def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], scale_cells: float) -> np.ndarray:
    """Zero-mean, unit-std noise with features of ``scale_cells`` cells (cubic upsampling of a coarse
    grid)."""
    rows, cols = shape
    cr = max(int(np.ceil(rows / scale_cells)) + 3, 4)
    cc = max(int(np.ceil(cols / scale_cells)) + 3, 4)
    coarse = rng.standard_normal((cr, cc)).astype(np.float32)
    big = cv2.resize(coarse, (int(round(cc * scale_cells)), int(round(cr * scale_cells))),
                     interpolation=cv2.INTER_CUBIC)
    r0 = int(rng.integers(0, max(big.shape[0] - rows, 0) + 1))
    c0 = int(rng.integers(0, max(big.shape[1] - cols, 0) + 1))
    out = big[r0:r0 + rows, c0:c0 + cols]
    return (out - out.mean()) / max(float(out.std()), 1e-6)


def _terrain(cfg: SceneConfig, rng: np.random.Generator) -> np.ndarray:
    """Smooth terrain: a sum of seeded sinusoids (wavelengths 300-2500 m) and smoothed noise, scaled to
    ``terrain_relief_m`` peak to peak around ``terrain_mean_m``. Sinusoids are separable
    (sin(a + b) = sin a cos b + cos a sin b), so the grid costs a few outer products."""
    rows, cols = cfg.shape
    if cfg.flat or cfg.terrain_relief_m == 0:
        return np.full((rows, cols), cfg.terrain_mean_m, dtype=np.float32)
    x = (np.arange(cols) + 0.5) * cfg.cell_m
    y = (rows - np.arange(rows) - 0.5) * cfg.cell_m
    z = np.zeros((rows, cols), dtype=np.float32)
    for _ in range(6):
        wavelength = rng.uniform(300.0, 2500.0)
        theta = rng.uniform(0.0, np.pi)
        k = 2.0 * np.pi / wavelength
        a = k * np.cos(theta) * x + rng.uniform(0.0, 2.0 * np.pi)
        b = k * np.sin(theta) * y
        amp = rng.uniform(0.5, 1.0)
        z += (amp * (np.outer(np.cos(b), np.sin(a)) + np.outer(np.sin(b), np.cos(a)))).astype(np.float32)
    z += 0.3 * _smooth_noise(rng, (rows, cols), 150.0 / cfg.cell_m)
    z -= z.min()
    z *= cfg.terrain_relief_m / max(float(z.max()), 1e-6)
    z += cfg.terrain_mean_m - float(z.mean())
    return z.astype(np.float32)


def _axis_partition(rng: np.random.Generator, n_cells: int, block: tuple[float, float],
                    street: tuple[float, float]) -> np.ndarray:
    """A 1D street pattern: True where a cell lies on a street, blocks of ``block`` cells between."""
    mask = np.zeros(n_cells, dtype=bool)
    pos = rng.uniform(0.0, block[1])
    while pos < n_cells:
        w = rng.uniform(*street)
        mask[int(pos):int(pos + w) + 1] = True
        pos += w + rng.uniform(*block)
    return mask


def _parcels(rng: np.random.Generator, shape: tuple[int, int], size_cells: tuple[float, float]) -> np.ndarray:
    """Irregular rectangular parcels: (rows, cols) int parcel ids from random splits along both axes."""
    rows, cols = shape
    edges_c = np.cumsum(rng.uniform(*size_cells, size=int(cols / size_cells[0]) + 2))
    edges_r = np.cumsum(rng.uniform(*size_cells, size=int(rows / size_cells[0]) + 2))
    ic = np.searchsorted(edges_c, np.arange(cols))
    ir = np.searchsorted(edges_r, np.arange(rows))
    return ir[:, None] * (len(edges_c) + 1) + ic[None, :]


def _buildings(cfg: SceneConfig, rng: np.random.Generator, ground: np.ndarray, street: np.ndarray):
    """Rasterise random rectangular buildings (flat or gable roofs) off the streets.

    Returns (roof height grid with NaN off buildings, roof temperature grid, label grid, roof colour grid).
    """
    rows, cols = ground.shape
    cell = cfg.cell_m
    target_cells = cfg.building_density * rows * cols
    label = np.zeros((rows, cols), dtype=np.int32)
    params: list[np.ndarray] = []
    n_total = 0
    for _ in range(6):  # add batches until the covered fraction reaches the density
        covered = np.count_nonzero(label)
        if covered >= target_cells * 0.97:
            break
        mean_area = (22.0 / cell) ** 2
        n_new = int((target_cells - covered) / mean_area * 1.3) + 1
        w = rng.uniform(8.0, 40.0, n_new) / cell
        h = rng.uniform(8.0, 40.0, n_new) / cell
        c0 = rng.uniform(0, cols, n_new)
        r0 = rng.uniform(0, rows, n_new)
        x0 = np.clip(c0, 0, cols).astype(int)
        x1 = np.clip(c0 + w, 0, cols).astype(int)
        y0 = np.clip(r0, 0, rows).astype(int)
        y1 = np.clip(r0 + h, 0, rows).astype(int)
        for k in range(n_new):  # one slice assignment per building (thousands, ~1 us each)
            label[y0[k]:y1[k], x0[k]:x1[k]] = n_total + k + 1
        label[street] = 0
        params.append(np.column_stack([x0, x1, y0, y1]))
        n_total += n_new
    p = np.vstack(params) if params else np.zeros((0, 4), dtype=int)
    nb = len(p)
    eave = rng.uniform(*cfg.building_height_m, nb + 1)
    gable = rng.uniform(size=nb + 1) < cfg.gable_fraction
    ridge_along_e = rng.uniform(size=nb + 1) < 0.5
    pitch = np.tan(np.radians(rng.uniform(25.0, 45.0, nb + 1)))
    roof_t = rng.uniform(285.0, 300.0, nb + 1)
    side_dt = rng.uniform(0.5, 2.5, nb + 1)
    palette = np.array([[150, 70, 55], [120, 120, 125], [80, 80, 85], [170, 160, 150], [95, 60, 50]], float)
    colour = palette[rng.integers(0, len(palette), nb + 1)] + rng.normal(0, 8, (nb + 1, 3))
    rr, cc = np.nonzero(label)
    ids = label[rr, cc]
    x0, x1, y0, y1 = (np.concatenate([[0], p[:, i]]) for i in range(4))
    base = np.zeros(nb + 1)
    centre_r = np.clip(((y0 + y1) // 2), 0, rows - 1)
    centre_c = np.clip(((x0 + x1) // 2), 0, cols - 1)
    base[1:] = ground[centre_r[1:], centre_c[1:]]
    # distance (cells) to the ridge line, and the side of the ridge, per roof cell
    along_e = ridge_along_e[ids]
    mid = np.where(along_e, (y0[ids] + y1[ids]) / 2.0, (x0[ids] + x1[ids]) / 2.0)
    pos = np.where(along_e, rr + 0.5, cc + 0.5)
    halfw = np.where(along_e, (y1[ids] - y0[ids]) / 2.0, (x1[ids] - x0[ids]) / 2.0)
    d = np.abs(pos - mid)
    rise = np.where(gable[ids], pitch[ids] * np.maximum(halfw - d, 0.0) * cell, 0.0)
    roof_h = np.full((rows, cols), np.nan, dtype=np.float32)
    roof_h[rr, cc] = base[ids] + eave[ids] + rise
    side = np.where(pos > mid, 1.0, -1.0)
    temp = np.zeros((rows, cols), dtype=np.float32)
    temp[rr, cc] = roof_t[ids] + np.where(gable[ids], side * side_dt[ids], 0.0)
    rgb = np.zeros((rows, cols, 3), dtype=np.float32)
    shade = np.where(gable[ids], 1.0 + 0.12 * side, 1.0)
    rgb[rr, cc] = colour[ids] * shade[:, None]
    return roof_h, temp, label, rgb


def _trees(
    cfg: SceneConfig, rng: np.random.Generator, shape: tuple[int, int], free: np.ndarray
) -> np.ndarray:
    """Tree crowns (domes) rasterised with ``np.maximum.at``; heights above ground, 0 off the crowns."""
    rows, cols = shape
    veg = np.zeros(rows * cols, dtype=np.float32)
    if cfg.vegetation_density <= 0:
        return veg.reshape(shape)
    cell = cfg.cell_m
    r_min, r_max = cfg.tree_radius_m
    mean_area = np.pi * ((r_min + r_max) / 2.0) ** 2
    free_frac = max(float(free.mean()), 1e-3)
    density = min(cfg.vegetation_density / free_frac, 0.95)
    count = int(-np.log(1.0 - density) * rows * cols * cell * cell / mean_area)
    # clustered: half the trees near others (rows along streets, woods), half scattered
    centres = np.column_stack([rng.uniform(0, rows, count), rng.uniform(0, cols, count)])
    half = count // 2
    if half and count - half:
        parent = half + rng.integers(0, count - half, half)
        centres[:half] = centres[parent] + rng.normal(0, 8.0 / cell, (half, 2))
    radius_cells = np.clip(np.rint(rng.uniform(r_min, r_max, count) / cell), 1, None).astype(int)
    height = rng.uniform(*cfg.tree_height_m, count)
    for rc in np.unique(radius_cells):
        sel = np.nonzero(radius_cells == rc)[0]
        dy, dx = np.mgrid[-rc:rc + 1, -rc:rc + 1]
        d2 = (dx**2 + dy**2) / float(rc * rc)
        inside = d2 <= 1.0
        dy, dx, profile = dy[inside], dx[inside], np.sqrt(np.clip(1.0 - d2[inside], 0.0, 1.0))
        ty = np.rint(centres[sel, 0]).astype(int)[:, None] + dy[None, :]
        tx = np.rint(centres[sel, 1]).astype(int)[:, None] + dx[None, :]
        ok = (ty >= 0) & (ty < rows) & (tx >= 0) & (tx < cols)
        vals = (height[sel, None] * (0.45 + 0.55 * profile[None, :])).astype(np.float32)
        np.maximum.at(veg, (ty * cols + tx)[ok], vals[ok])
    veg = veg.reshape(shape)
    veg[~free] = 0.0
    return veg


def make_scene(config: SceneConfig, seed: int) -> Scene:
    """Generate a scene from ``config``; the same seed gives the same scene.

    A scene stores 16 bytes per cell, 160 MB for 4 km x 2.5 km at 1 m cells (DSM, terrain, thermal base
    float32; classes uint8; RGB base 3 x uint8), with a peak of several times that while generating (its time
    and peak: ``benchmarks/history/engine_measurements.md``; a whole flight's simulation, scene included:
    ``benchmarks/RESULTS.md``, "Simulator").
    """
    cfg = config
    rng = np.random.default_rng(seed)
    rows, cols = cfg.shape
    cell = cfg.cell_m
    ground = _terrain(cfg, rng)
    classes = np.zeros((rows, cols), dtype=np.uint8)

    # streets: a grid in a city, a few roads in the fields
    if cfg.building_density > 0:
        blocks, widths = (60.0 / cell, 160.0 / cell), (8.0 / cell, 16.0 / cell)
    else:
        blocks, widths = (400.0 / cell, 900.0 / cell), (5.0 / cell, 7.0 / cell)
    street = (_axis_partition(rng, rows, blocks, widths)[:, None]
              | _axis_partition(rng, cols, blocks, widths)[None, :])

    # ponds: the lowest values of a smooth noise field; flat water surface at the pond's lowest ground
    water = np.zeros((rows, cols), dtype=bool)
    if cfg.water_density > 0:
        field_ = _smooth_noise(rng, (rows, cols), 120.0 / cell)
        water = field_ < np.quantile(field_[:: 7, :: 7], cfg.water_density)
        water &= ~street
        if not cfg.flat:
            lab, n_lab = ndimage.label(water)
            if n_lab:
                ids = lab[water]
                level = np.full(n_lab + 1, np.inf, dtype=np.float32)
                np.minimum.at(level, ids, ground[water])
                ground[water] = level[ids]

    # ground temperatures and colours: field parcels, warmer streets
    parcel_id = _parcels(rng, (rows, cols), (40.0 / cell, 140.0 / cell))
    n_parcels = int(parcel_id.max()) + 1
    parcel_t = rng.uniform(284.0, 292.0, n_parcels).astype(np.float32)
    parcel_rgb = np.array([[110, 130, 70], [140, 130, 90], [90, 115, 60], [160, 145, 110], [120, 100, 70]],
                          float)[rng.integers(0, 5, n_parcels)] + rng.normal(0, 10, (n_parcels, 3))
    therm = parcel_t[parcel_id]
    rgb = parcel_rgb[parcel_id].astype(np.float32)
    del parcel_id
    therm[street] = 291.0
    rgb[street] = (105.0, 105.0, 110.0)

    dsm = ground.copy()
    if cfg.building_density > 0 and not cfg.flat:
        roof_h, roof_t, label, roof_rgb = _buildings(cfg, rng, ground, street | water)
        on_roof = label > 0
        del label
        dsm[on_roof] = roof_h[on_roof]
        therm[on_roof] = roof_t[on_roof]
        rgb[on_roof] = roof_rgb[on_roof]
        classes[on_roof] = CLASS_ROOF
        del roof_h, roof_t, roof_rgb
    else:
        on_roof = np.zeros((rows, cols), dtype=bool)

    veg = _trees(cfg, rng, (rows, cols), ~(on_roof | street | water))
    on_veg = veg > 0
    classes[on_veg] = CLASS_VEGETATION
    therm[on_veg] = 282.0 + 0.15 * veg[on_veg]
    rgb[on_veg] = np.array([50.0, 85.0, 40.0]) + 4.0 * veg[on_veg][:, None]
    if not cfg.flat:
        dsm += veg
    classes[water] = CLASS_WATER
    therm[water] = 279.0
    rgb[water] = (40.0, 60.0, 80.0)

    # blur class edges, add gridded texture noise from one cell to 64 cells
    sigma = cfg.edge_blur_m / cell
    if sigma > 0:
        therm = cv2.GaussianBlur(therm, (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REFLECT)
    if cfg.rgb_edge_blur_m > 0:
        rgb = cv2.GaussianBlur(rgb, (0, 0), sigmaX=cfg.rgb_edge_blur_m / cell, borderType=cv2.BORDER_REFLECT)
    lum = np.zeros((rows, cols), dtype=np.float32)
    for scale in (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0):
        noise = (rng.standard_normal((rows, cols)).astype(np.float32) if scale == 1.0
                 else _smooth_noise(rng, (rows, cols), scale))
        lum += noise
    lum *= 1.0 / np.sqrt(7.0)
    therm += cfg.texture_k * 2.0 * lum
    rgb += (cfg.texture_rgb * 2.0 * lum)[..., None]
    rgb_u8 = np.clip(np.rint(rgb), 0, 255).astype(np.uint8)
    del rgb, lum
    return Scene(
        config=cfg, seed=int(seed), dsm=dsm.astype(np.float32), ground=ground.astype(np.float32),
        classes=classes, thermal_base=therm.astype(np.float32), rgb_base=rgb_u8,
    )
