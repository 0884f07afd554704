"""Which cells of a grid the frames of a block can see: the union of their footprints.

A filled DSM holds a height in every cell of its grid, the rectangle around its cloud. Where the block's frames
see no ground at all (the corners of a grid that a cross strip stretches, a block's ragged ends) that height is
extrapolated from the nearest measured cells, tens of metres off: such a cell is not the flight's to describe,
and the products leave it without a height, as OpenDroneMap crops its elevation models to the cloud's boundary.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from aerocal.products.dsm import Dsm
from aerocal.products.mosaic import FrameGeometry

#: fractional bits of the polygon vertices handed to OpenCV (a sixteenth of a cell)
SHIFT = 4


def seen_cells(frames: Sequence[FrameGeometry], grid: Dsm, height_m: float) -> np.ndarray:
    """bool (rows, cols): the cells of ``grid`` whose centre lies inside the footprint of at least one frame on the
    horizontal plane at ``height_m`` (metres; the image border cast as :meth:`FrameGeometry.ground_footprint` casts
    it, the convex hull of that border filled by OpenCV at a sixteenth of a cell).

    A frame looking down sees a point above that plane only inside its footprint on it, so with the plane at the
    lowest height of the surface the union holds every cell a frame can see. A border ray that points above the
    horizon is left out of its footprint, which then covers less than the frame sees: the caller keeps the cells
    that hold points whatever this says."""
    rows, cols = grid.shape
    mask = np.zeros((rows, cols), dtype=np.uint8)
    limit = 1e7  # cells: a ray a hair below the horizon meets the plane far away; int32 holds 16 times this
    for frame in frames:
        xy = frame.ground_footprint([height_m])
        if len(xy) < 3:
            continue
        col, row = grid.grid_coords(xy[:, 0], xy[:, 1])
        pts = np.clip(np.column_stack([col, row]), -limit, limit) * (1 << SHIFT)
        hull = cv2.convexHull(np.round(pts).astype(np.int32))
        cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=SHIFT)
    return mask.view(bool)
