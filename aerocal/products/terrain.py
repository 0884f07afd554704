"""A digital terrain model (DTM) from a DSM: the ground under buildings and trees.

:func:`dtm_from_dsm` is the progressive morphological filter of Zhang et al. (2003, IEEE TGRS 41(4)), the ground
filter PDAL (``filters.pmf``) and OpenDroneMap's DTM inherit, on the gridded surface rather than on the points:
grey openings with windows doubling from 2 cells up to ``max_window_m`` remove what stands above the ground and is
smaller than the window; a cell whose height drops by more than the window's threshold (``initial_m`` plus
``slope`` times the growth of the window, at most ``max_m``) is not ground. The ground cells' heights are
interpolated (linear on their Delaunay triangulation, :func:`aerocal.products.dsm.fill_holes`) under the rest.
The filter runs on blocks of the DSM's cells about ``cell_m`` wide (the median of each block's measured heights),
and the DTM is interpolated back onto the DSM's cells.

The filter needs ground between the objects: where under ``min_ground_fraction`` of the measured cells remain
ground (a block of roofs, a closed canopy), there is no DTM and the reason says so.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np
from scipy import ndimage

from aerocal.products.dsm import Dsm, fill_holes, median_in_place


@dataclass(frozen=True)
class GroundFilterConfig:
    """Parameters of the progressive morphological filter (lengths in metres).

    Defaults for built-up areas at decimetre to metre cells: windows up to 60 m open the largest buildings of a city
    block; the thresholds follow a 30 % terrain slope from 0.5 m, at most 3 m (a storey).
    """

    max_window_m: float = 60.0  #: the largest object (building, tree group) the filter removes, metres
    slope: float = 0.3  #: terrain slope the thresholds allow, metres per metre
    initial_m: float = 0.5  #: threshold of the smallest window, metres
    max_m: float = 3.0  #: the largest threshold, metres
    min_ground_fraction: float = 0.1  #: below this share of ground cells there is no DTM
    #: the filter runs on cells of about this size (a whole number of the DSM's cells, each the median of its measured
    #: heights) and its DTM is interpolated back onto the DSM's cells: the ground varies over metres, not over a
    #: ground sample, and the openings' and the interpolation's cost grows with the cells (a city's 0.5 m DSM holds
    #: 76 M of them); 0: the DSM's own cells
    cell_m: float = 2.0

    def __post_init__(self) -> None:
        if not self.max_window_m > 0 or not self.slope >= 0 or not 0 < self.initial_m <= self.max_m:
            raise ValueError("GroundFilterConfig: need max_window_m > 0, slope >= 0 and 0 < initial_m <= max_m, got "
                             f"{self.max_window_m}, {self.slope}, {self.initial_m}, {self.max_m}")
        if not 0 <= self.min_ground_fraction < 1:
            raise ValueError("GroundFilterConfig.min_ground_fraction must be in [0, 1), got "
                             f"{self.min_ground_fraction}")
        if not self.cell_m >= 0:
            raise ValueError(f"GroundFilterConfig.cell_m must be 0 or more, got {self.cell_m}")


@dataclass(frozen=True)
class Terrain:
    """What :func:`dtm_from_dsm` found: the DTM (``None`` when the block has too little ground), the ground cells
    (bool, the DSM's shape) and one sentence on what was done or why not."""

    dtm: Dsm | None
    ground: np.ndarray
    note: str


def dtm_from_dsm(dsm: Dsm, measured: np.ndarray | None = None, config: GroundFilterConfig | None = None) -> Terrain:
    """The DTM under ``dsm`` (module docstring).

    Args:
        dsm: the surface (heights in metres, NaN outside the data).
        measured: bool (the DSM's shape), the cells with a measured height; ground is only chosen among them
            (``None``: every cell with a height).
        config: the filter's parameters.

    Returns:
        a :class:`Terrain`; its DTM is on the DSM's grid, with heights where the DSM has them. Where the filter
        ran on coarser cells (``config.cell_m``), a DSM cell is ground when its block is and its height lies
        within ``config.initial_m`` above the DTM.
    """
    config = config or GroundFilterConfig()
    has = np.isfinite(dsm.heights)
    measured = has if measured is None else (measured & has)
    k = max(1, int(round(config.cell_m / dsm.cell_m))) if config.cell_m > 0 else 1
    if k == 1:
        filled, ground, share, note = _filter(dsm.heights, measured, dsm.cell_m, config)
        if filled is None:
            return Terrain(None, ground, note)
    else:
        coarse = _block_medians(np.ascontiguousarray(dsm.heights, dtype=np.float32), measured, k)
        filled, coarse_ground, share, note = _filter(coarse, np.isfinite(coarse), dsm.cell_m * k, config)
        rows, cols = dsm.shape
        block_ground = np.repeat(np.repeat(coarse_ground, k, axis=0), k, axis=1)[:rows, :cols]
        if filled is None:
            return Terrain(None, measured & block_ground, note)
        # cell centres at integers on both grids: cv2's linear resize is that interpolation, edges extended
        filled = cv2.resize(filled.astype(np.float32), (filled.shape[1] * k, filled.shape[0] * k),
                            interpolation=cv2.INTER_LINEAR)[:rows, :cols]
        with np.errstate(invalid="ignore"):
            ground = measured & block_ground & (dsm.heights - filled <= config.initial_m)
        note += f" on {dsm.cell_m * k:.3g} m cells"
    heights = np.where(has, filled, np.nan).astype(np.float32)
    dtm = replace(dsm, heights=heights, counts=None, distance_m=None, stats={"ground_fraction": share})
    return Terrain(dtm, ground, note)


def _filter(heights: np.ndarray, measured: np.ndarray, cell: float,
            config: GroundFilterConfig) -> tuple[np.ndarray | None, np.ndarray, float, str]:
    """The progressive morphological filter on a grid of ``cell`` metres: (the ground's heights interpolated on
    every cell, or ``None`` with too little ground; the ground cells; their share of the measured cells; the
    sentence that says what was done or why not)."""
    has = np.isfinite(heights)
    surface = np.where(has, heights, np.nanmax(heights) if has.any() else 0.0).astype(np.float64)
    ground = measured.copy()
    largest = 2 * int(np.ceil(config.max_window_m / cell / 2)) + 1  # cells, odd
    windows = [w for w in (2 ** k + 1 for k in range(1, 16)) if w < largest] + [largest]
    previous = None
    for window in windows:
        opened = ndimage.grey_opening(surface, size=(window, window), mode="nearest")
        grown = 0.0 if previous is None else (window - previous) * cell
        threshold = min(config.initial_m + config.slope * grown, config.max_m)
        ground &= (surface - opened) <= threshold
        surface = opened
        previous = window
    share = float(np.count_nonzero(ground) / max(np.count_nonzero(measured), 1))
    if share < config.min_ground_fraction or np.count_nonzero(ground) < 3:
        return None, ground, share, (f"no DTM: {share:.0%} of the measured cells are ground (at least "
                                     f"{config.min_ground_fraction:.0%} needed: roofs or canopy close the ground)")
    filled = fill_holes(np.where(ground, heights, np.nan), ground)
    return filled, ground, share, (f"DTM from {share:.0%} of the measured cells (progressive morphological "
                                   f"filter, windows up to {config.max_window_m:g} m)")


def _block_medians(heights: np.ndarray, measured: np.ndarray, k: int) -> np.ndarray:
    """The median of the measured heights in each ``k`` x ``k`` block of cells (float32, ceil(rows / k) x
    ceil(cols / k); NaN where a block has none)."""
    rows, cols = heights.shape
    return _block_medians_kernel(heights, np.ascontiguousarray(measured), k, -(-rows // k), -(-cols // k))


@numba.njit(cache=True, nogil=True)
def _block_medians_kernel(heights: np.ndarray, measured: np.ndarray, k: int, out_rows: int,
                          out_cols: int) -> np.ndarray:
    rows, cols = heights.shape
    out = np.full((out_rows, out_cols), np.nan, dtype=np.float32)
    buf = np.empty(k * k, dtype=np.float64)
    for R in range(out_rows):
        for C in range(out_cols):
            n = 0
            for r in range(R * k, min(R * k + k, rows)):
                for c in range(C * k, min(C * k + k, cols)):
                    if measured[r, c] and np.isfinite(heights[r, c]):
                        buf[n] = heights[r, c]
                        n += 1
            if n:
                out[R, C] = median_in_place(buf[:n])
    return out
