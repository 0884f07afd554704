"""A digital terrain model (DTM) from a DSM: the ground under buildings and trees.

:func:`dtm_from_dsm` is the progressive morphological filter of Zhang et al. (2003, IEEE TGRS 41(4)), the ground
filter PDAL (``filters.pmf``) and OpenDroneMap's DTM inherit, on the gridded surface rather than on the points:
grey openings with windows doubling from 2 cells up to ``max_window_m`` remove what stands above the ground and is
smaller than the window; a cell whose height drops by more than the window's threshold (``initial_m`` plus
``slope`` times the growth of the window, at most ``max_m``) is not ground. The ground cells' heights are
interpolated (linear on their Delaunay triangulation, :func:`aerocal.products.dsm.fill_holes`) under the rest.

The filter needs ground between the objects: where under ``min_ground_fraction`` of the measured cells remain
ground (a block of roofs, a closed canopy), there is no DTM and the reason says so.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from aerocal.products.dsm import Dsm, fill_holes


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

    def __post_init__(self) -> None:
        if not self.max_window_m > 0 or not self.slope >= 0 or not 0 < self.initial_m <= self.max_m:
            raise ValueError("GroundFilterConfig: need max_window_m > 0, slope >= 0 and 0 < initial_m <= max_m, got "
                             f"{self.max_window_m}, {self.slope}, {self.initial_m}, {self.max_m}")
        if not 0 <= self.min_ground_fraction < 1:
            raise ValueError("GroundFilterConfig.min_ground_fraction must be in [0, 1), got "
                             f"{self.min_ground_fraction}")


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
        a :class:`Terrain`; its DTM is on the DSM's grid, with heights where the DSM has them.
    """
    config = config or GroundFilterConfig()
    has = np.isfinite(dsm.heights)
    measured = has if measured is None else (measured & has)
    surface = np.where(has, dsm.heights, np.nanmax(dsm.heights) if has.any() else 0.0).astype(np.float64)
    ground = measured.copy()
    cell = dsm.cell_m
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
        return Terrain(None, ground, f"no DTM: {share:.0%} of the measured cells are ground (at least "
                                     f"{config.min_ground_fraction:.0%} needed: roofs or canopy close the ground)")
    heights = fill_holes(np.where(ground, dsm.heights, np.nan), ground)
    heights = np.where(has, heights, np.nan).astype(np.float32)
    dtm = replace(dsm, heights=heights, counts=None, distance_m=None, stats={"ground_fraction": share})
    return Terrain(dtm, ground, f"DTM from {share:.0%} of the measured cells (progressive morphological filter, "
                                f"windows up to {config.max_window_m:g} m)")
