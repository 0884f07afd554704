"""The dense cloud as a LAZ file (ASPRS LAS 1.4, point format 6, LAZ-compressed with lazrs) that point-cloud
viewers and GIS open: coordinates in the flight's projected CRS (an OGC WKT record), millimetre resolution, the
frame value at each point (a radiometric frame's counts, else its grey level) in ``intensity``, and two extra
dimensions: ``views`` (frames that agree on the point) and, for radiometric frames, ``temperature`` (degC)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import laspy
import numpy as np
import pyproj

from aerocal.io import atomic_path
from aerocal.products.dense import DenseCloud

#: coordinate resolution of the LAZ file, metres (far below any ground sample distance the block reaches)
SCALE_M = 0.001


def write_laz(cloud: DenseCloud, path: str | Path, crs: str,
              temperature: Callable[[np.ndarray], np.ndarray] | None = None, chunk: int = 2_000_000) -> Path:
    """Write ``cloud`` to ``path`` atomically (nothing half-written under its name), in chunks of ``chunk``
    points (memory bounded by the chunk, not the cloud).

    Args:
        cloud: the fused dense cloud (:class:`aerocal.products.dense.DenseCloud`).
        path: the ``.laz`` file to write.
        crs: the flight's projected CRS (anything :class:`pyproj.CRS` reads: ``"EPSG:32632"``, WKT).
        temperature: counts (float array) -> degC for radiometric frames, or ``None`` (no ``temperature``).
        chunk: points per write.

    Returns:
        ``path``.

    Raises:
        ValueError: the cloud is empty or ``crs`` is not a CRS.
    """
    path = Path(path)
    n = len(cloud.xyz)
    if not n:
        raise ValueError(f"write_laz: the dense cloud for {path} has no points")
    try:
        proj = pyproj.CRS.from_user_input(crs)
    except pyproj.exceptions.CRSError as exc:
        raise ValueError(f"write_laz: {crs!r} is not a coordinate reference system ({exc})") from exc
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, SCALE_M)
    header.offsets = np.floor(cloud.xyz.min(axis=0))
    header.add_extra_dim(laspy.ExtraBytesParams(name="views", type=np.uint8,
                                                description="frames agreeing on the point"))
    if temperature is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name="temperature", type=np.float32,
                                                    description="object temperature, degC"))
    header.add_crs(proj)
    with atomic_path(path) as tmp, laspy.open(tmp, mode="w", header=header, do_compress=True) as writer:
        for start in range(0, n, chunk):
            sl = slice(start, min(n, start + chunk))
            pts = laspy.ScaleAwarePointRecord.zeros(sl.stop - sl.start, header=header)
            pts.x, pts.y, pts.z = cloud.xyz[sl, 0], cloud.xyz[sl, 1], cloud.xyz[sl, 2]
            pts.intensity = np.clip(np.rint(cloud.value[sl]), 0, 65535).astype(np.uint16)
            pts.views = cloud.views[sl]
            if temperature is not None:
                pts.temperature = np.asarray(temperature(cloud.value[sl].astype(float)), dtype=np.float32)
            writer.write_points(pts)
    return path
