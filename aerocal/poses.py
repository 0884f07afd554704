"""The ``poses`` table and arrays: image ids, world-to-camera rotations ``R_cw`` (N, 3, 3) and projection
centres ``C`` (N, 3) in the block's world frame (metres).

The table stores the rotations as unit quaternions, scalar first (``qw, qx, qy, qz``), the centres as
``X, Y, Z`` (schema ``poses`` of :mod:`aerocal.tables`).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.geometry import matrix_from_quat_wxyz, quat_wxyz_from_matrix


def poses_table(image_ids: np.ndarray, R_cw: np.ndarray, C: np.ndarray, crs: str | None = None) -> pa.Table:
    """The ``poses`` table of ``R_cw`` (N, 3, 3) and ``C`` (N, 3), in ``crs`` when given."""
    q = quat_wxyz_from_matrix(R_cw)
    return tables.from_columns("poses", {
        "image_id": np.asarray(image_ids, dtype=np.int32), "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2],
        "qz": q[:, 3], "X": C[:, 0], "Y": C[:, 1], "Z": C[:, 2]}, crs=crs)


def poses_arrays(poses: pa.Table) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image ids, R_cw (N, 3, 3), C (N, 3)) of a poses table."""
    p = poses.to_pydict()
    q = np.column_stack([p["qw"], p["qx"], p["qy"], p["qz"]])
    return (np.asarray(p["image_id"]), matrix_from_quat_wxyz(q).reshape(-1, 3, 3),
            np.column_stack([p["X"], p["Y"], p["Z"]]))


def has_priors(images: pa.Table) -> bool:
    """True when every image has a recorded position and attitude."""
    cols = ("gnss_x", "gnss_y", "gnss_z", "roll", "pitch", "yaw", "attitude_convention")
    return all(images.column(c).null_count == 0 for c in cols) and images.num_rows > 0
