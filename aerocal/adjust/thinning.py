"""Tie-point thinning: the adjustment's tie tracks, a few per cell of a grid over every image.

Matched frames hold far more tie points than the orientation needs: about a thousand observations per
image on the rendered conte-city flight (``benchmarks/RESULTS.md``, "Tie-point thinning: adjustments with
every track and thinned, same run"), where the precision of the poses and of the check points is set by
the GCPs, the GNSS and the geometry of the rays long before. The adjustment's cost grows with the
observations, so it spends most of its time on tie points that add nothing. This is what Metashape's
"tie point limit" and MicMac's ``Schnaps``/``Ratafia`` reduction do; aerocal's form of it:

* every image is cut into ``grid`` cells (columns x rows over the frame);
* in each cell of each image, the ``per_cell`` tracks with the most rays are chosen (more rays: better
  intersection geometry and a blunder that is found, not absorbed); ties are broken by a seeded random
  order, not by track id (which follows the order of detection: top of the frame first);
* a track chosen in any image is kept whole, with all its observations.

So every image keeps tie points in every part of the frame where it had any, and tracks shared by many
images are preferred. The flow thins the block adjustment only: a self-calibration from thinned tracks of
the real seneca sub-block lost the focal length's temperature slope (``benchmarks/RESULTS.md``, the notes of
"City scale: conte-city rendered, end to end" of 2026-11-22).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa


@dataclass(frozen=True)
class ThinningConfig:
    """How tie tracks are thinned (:func:`thin_tracks`).

    * ``grid``: cells across and down each frame (default 8 x 6, cells of 80 x 80 px on a 640 x 480
      thermal frame).
    * ``per_cell``: tracks chosen per cell of each image (default 4); 0 = no thinning.
    * ``seed``: of the random order that breaks ties between tracks of the same length (default 0).
    """

    grid: tuple[int, int] = (8, 6)
    per_cell: int = 4
    seed: int = 0

    def __post_init__(self) -> None:
        if self.per_cell < 0 or min(self.grid) < 1:
            raise ValueError(f"ThinningConfig: per_cell must be >= 0 and grid >= (1, 1), got {self}")


def thin_tracks(observations: pa.Table, width: int, height: int, config: ThinningConfig | None = None) -> np.ndarray:
    """Sorted row indices of ``observations`` (an observations table) that belong to the kept tracks.

    ``width`` and ``height`` are the frame's size in pixels; ``x``, ``y`` are pixels from the top-left
    corner (``x`` right, ``y`` down). Rows of every track are either all kept or all left out.
    """
    config = config or ThinningConfig()
    n = observations.num_rows
    if config.per_cell == 0 or n == 0:
        return np.arange(n)
    track = observations.column("track_id").to_numpy().astype(np.int64)
    image = observations.column("image_id").to_numpy().astype(np.int64)
    x = observations.column("x").to_numpy(zero_copy_only=False).astype(float)
    y = observations.column("y").to_numpy(zero_copy_only=False).astype(float)
    gx, gy = config.grid
    col = np.clip((x * gx / width).astype(np.int64), 0, gx - 1)
    row = np.clip((y * gy / height).astype(np.int64), 0, gy - 1)
    _, image_index = np.unique(image, return_inverse=True)
    cell = (image_index * gy + row) * gx + col
    tracks, track_index = np.unique(track, return_inverse=True)
    length = np.bincount(track_index)[track_index]
    tiebreak = np.random.default_rng(config.seed).permutation(len(tracks))[track_index]
    order = np.lexsort((tiebreak, -length, cell))
    c = cell[order]
    start = np.flatnonzero(np.r_[True, c[1:] != c[:-1]])
    rank = np.arange(n) - np.repeat(start, np.diff(np.r_[start, n]))
    chosen = np.zeros(len(tracks), dtype=bool)
    chosen[track_index[order[rank < config.per_cell]]] = True
    return np.flatnonzero(chosen[track_index])
