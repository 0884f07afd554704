"""Which image pairs to match: footprint overlap predicted from GNSS/IMU, or all / sequential pairs.

A city flight has hundreds of frames; matching all n (n - 1) / 2 pairs costs hours and adds wrong
matches between unrelated images. The recorded exterior orientation predicts each image's footprint on
a horizontal ground plane; only pairs whose footprints overlap are matched.

Footprint: the four image corners (pixels, aerocal convention) are turned into viewing rays with the
camera model, rotated into the world frame with the recorded attitude (``R_cw`` world-to-camera, see
:mod:`aerocal.geometry`) and intersected with the plane ``Z = terrain_height`` (world frame: projected
CRS, E, N, Up, metres). Candidates come from a KD-tree on footprint centres (pairs whose bounding
circles meet), then the exact overlap area of the two convex quadrilaterals (Sutherland-Hodgman
clipping, vectorised over all candidate pairs), so the cost is O(n log n + candidates).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import pyarrow as pa
from scipy.spatial import cKDTree

from aerocal.camera import Camera
from aerocal.geometry import attitude_to_R_cw

#: Rays that miss the ground, or meet it farther than this many flying heights away (horizontally),
#: are clamped to that distance, so that near-horizontal corners of oblique views stay finite.
MAX_RANGE_HEIGHTS = 10.0


# ----------------------------------------------------------------------------- poses from the images table
def _columns(images) -> dict[str, np.ndarray]:
    if isinstance(images, pa.Table):
        return {
            name: np.asarray(images.column(name).to_pylist(), dtype=object) for name in images.column_names
        }
    return {k: np.asarray(v) for k, v in images.items()}


def prior_poses(images) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Recorded poses ``(image_id, R_cw, C)`` of an ``images`` table or a mapping of columns.

    Args:
        images: an ``images`` table (:mod:`aerocal.tables`) or a mapping of column name -> values. The mapping
            may hold ``R_cw`` (N, 3, 3) and ``C`` (N, 3) directly, or the ``images`` columns ``gnss_x, gnss_y,
            gnss_z`` (metres, flight CRS), ``roll, pitch, yaw`` (degrees) and ``attitude_convention``. ``image_id``
            is optional.

    Returns:
        ``(image_id (N,) int64, R_cw (N, 3, 3), C (N, 3))``: world-to-camera rotations (:mod:`aerocal.geometry`)
        and projection centres (E, N, Up metres in the flight CRS; from the ``images`` columns, the recorded GNSS
        positions). ``image_id`` defaults to 0..N-1.

    Raises:
        ValueError: a needed column is missing; images lack a position or attitude (the message names them); an
            unknown ``attitude_convention``.
    """
    cols = _columns(images)
    if "R_cw" in cols and "C" in cols:
        R = np.asarray(cols["R_cw"], dtype=float).reshape(-1, 3, 3)
        C = np.asarray(cols["C"], dtype=float).reshape(-1, 3)
    else:
        need = ["gnss_x", "gnss_y", "gnss_z", "roll", "pitch", "yaw", "attitude_convention"]
        missing = [k for k in need if k not in cols]
        if missing:
            raise ValueError(f"footprints need image columns {need}; missing {missing}")
        n = len(cols["gnss_x"])
        vals = {k: np.array([np.nan if v is None else v for v in cols[k]], dtype=float) for k in need[:-1]}
        conv = cols["attitude_convention"]
        bad = ~np.isfinite(np.column_stack([vals[k] for k in need[:-1]])).all(axis=1)
        bad |= np.array([c is None or c == "" for c in conv])
        if bad.any():
            names = cols.get("name", cols.get("image_id", np.arange(n)))
            raise ValueError(
                f"{int(bad.sum())} image(s) lack a GNSS position or attitude (e.g. "
                f"{[str(v) for v in np.asarray(names)[bad][:5]]}): fill gnss_x/y/z, roll/pitch/yaw and "
                "attitude_convention, or use exhaustive_pairs/sequential_pairs"
            )
        C = np.column_stack([vals["gnss_x"], vals["gnss_y"], vals["gnss_z"]])
        R = np.stack([
            attitude_to_R_cw(str(c), r, p, y)
            for c, r, p, y in zip(conv, vals["roll"], vals["pitch"], vals["yaw"], strict=True)
        ]) if n else np.zeros((0, 3, 3))
    ids = np.asarray(cols["image_id"], dtype=np.int64) if "image_id" in cols else np.arange(len(C))
    return ids, R, C


def _cameras_for(images, camera: Camera | Mapping[str, Camera], n: int) -> list[Camera]:
    if isinstance(camera, Camera):
        return [camera] * n
    cols = _columns(images)
    if "camera_id" not in cols:
        raise ValueError("a mapping of cameras needs a camera_id column in the images")
    out = []
    for cid in cols["camera_id"]:
        if cid not in camera:
            raise ValueError(f"images.camera_id {cid!r} has no camera; known: {sorted(camera)}")
        out.append(camera[cid])
    return out


# ----------------------------------------------------------------------------- footprints
def footprints(
    R_cw: np.ndarray,
    C: np.ndarray,
    cameras: Camera | Sequence[Camera],
    terrain_height: float | np.ndarray,
) -> np.ndarray:
    """Ground footprints: the four image corners of each camera on the plane ``Z = terrain_height``.

    Each corner's viewing ray (camera model) is rotated into the world frame and intersected with the plane.
    Rays that miss the ground, or meet it farther than :data:`MAX_RANGE_HEIGHTS` flying heights away
    (horizontally), are clamped to that distance, so that near-horizontal corners of oblique views stay finite.

    Args:
        R_cw: world-to-camera rotations (N, 3, 3).
        C: projection centres (N, 3), E, N, Up metres in the flight CRS.
        cameras: one :class:`~aerocal.camera.Camera` for every image, or one per image.
        terrain_height: height of the ground plane, one height or one per image (metres, same datum as ``C``).

    Returns:
        float array (N, 4, 2): E, N (metres) of each image's corners on the plane; vertices counter-clockwise
        (seen from above).

    Raises:
        ValueError: a camera at or below its terrain height; the usual cause is a height in another reference
            (take-off-relative vs ellipsoidal).
    """
    R = np.asarray(R_cw, dtype=float).reshape(-1, 3, 3)
    C = np.asarray(C, dtype=float).reshape(-1, 3)
    n = len(C)
    cams = [cameras] * n if isinstance(cameras, Camera) else list(cameras)
    h = np.broadcast_to(np.asarray(terrain_height, dtype=float), (n,))
    above = C[:, 2] - h
    if n and not (above > 0).all():
        k = np.nonzero(~(above > 0))[0]
        raise ValueError(
            f"{len(k)} camera(s) at or below the terrain height (e.g. index {k[:5].tolist()}: Z "
            f"{C[k[0], 2]:.2f} m vs terrain {h[k[0]]:.2f} m); check the height reference of gnss_z "
            "and terrain_height"
        )
    rays = np.empty((n, 4, 3))
    for cam in {id(c): c for c in cams}.values():  # one unprojection per distinct camera
        sel = np.array([c is cam for c in cams])
        rays[sel] = cam.rays(cam.corners())
    d = np.einsum("nji,nkj->nki", R, rays)  # world directions: R_cw^T r
    max_range = MAX_RANGE_HEIGHTS * above
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (h - C[:, 2])[:, None] / d[..., 2]
    horiz = np.linalg.norm(d[..., :2], axis=-1)
    reach = t * horiz
    clamp = ~(d[..., 2] < 0) | ~(reach <= max_range[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        unit = d[..., :2] / horiz[..., None]
    unit = np.where(np.isfinite(unit), unit, 0.0)
    pts = C[:, None, :2] + np.where(
        clamp[..., None], unit * max_range[:, None, None], t[..., None] * d[..., :2]
    )
    return _ccw(pts)


def _signed_area(poly: np.ndarray) -> np.ndarray:
    x, y = poly[..., 0], poly[..., 1]
    return 0.5 * np.sum(x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y, axis=-1)


def _ccw(poly: np.ndarray) -> np.ndarray:
    """Reverse the vertex order of clockwise polygons."""
    flip = _signed_area(poly) < 0
    out = poly.copy()
    out[flip] = out[flip, ::-1]
    return out


def convex_overlap_area(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Area of the intersection of convex counter-clockwise polygons ``a[i]`` and ``b[i]``, for P pairs at once.

    Sutherland-Hodgman clipping of ``a`` by each edge of ``b``, vectorised over the P pairs. Vertices that fall
    outside are replaced by a copy of the previous kept vertex, so every polygon keeps a fixed number of
    (possibly repeated) vertices, which changes neither its shape nor its area; the vertex count doubles per
    clipping edge (4 -> 64 for quads). Written here because shapely is not a dependency; checked against
    ``scipy.spatial.ConvexHull`` volumes of the intersection points in tests/test_matching.py.

    Args:
        a: P convex polygons (P, M, 2), vertices counter-clockwise (e.g. :func:`footprints`, E, N metres).
        b: P convex polygons (P, K, 2), vertices counter-clockwise; ``b[i]`` clips ``a[i]``.

    Returns:
        float array (P,): the intersection areas, in the square of the coordinates' unit (m^2 for footprints);
        0 where the polygons do not meet.
    """
    poly = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    P = len(poly)
    if P == 0:
        return np.zeros(0)
    empty = np.zeros(P, dtype=bool)
    for k in range(b.shape[1]):
        p0 = b[:, k][:, None, :]
        edge = (b[:, (k + 1) % b.shape[1]] - b[:, k])[:, None, :]
        s = edge[..., 0] * (poly[..., 1] - p0[..., 1]) - edge[..., 1] * (poly[..., 0] - p0[..., 0])
        nxt = np.roll(poly, -1, axis=1)
        s_n = np.roll(s, -1, axis=1)
        inside, inside_n = s >= 0, s_n >= 0
        crosses = inside != inside_n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(crosses, s / (s - s_n), 0.0)
        inter = poly + t[..., None] * (nxt - poly)
        M = poly.shape[1]
        cand = np.stack([inter, nxt], axis=2).reshape(P, 2 * M, 2)
        valid = np.stack([crosses, inside_n], axis=2).reshape(P, 2 * M)
        idx = np.where(valid, np.arange(2 * M), -1)
        idx = np.maximum.accumulate(idx, axis=1)
        last = idx[:, -1:]
        idx = np.where(idx < 0, last, idx)
        empty |= last[:, 0] < 0
        idx = np.maximum(idx, 0)
        poly = np.take_along_axis(cand, idx[..., None], axis=1)
    area = _signed_area(poly)
    area[empty] = 0.0
    return np.maximum(area, 0.0)


def candidate_pairs_from_footprints(
    images,
    camera: Camera | Mapping[str, Camera],
    terrain_height: float | np.ndarray,
    min_overlap: float = 0.1,
    max_pairs_per_image: int | None = None,
    return_overlap: bool = False,
):
    """Image pairs whose predicted ground footprints overlap.

    Parameters
    ----------
    images:
        An ``images`` table or a mapping of its columns (see :func:`prior_poses`).
    camera:
        The camera, or a mapping ``camera_id -> Camera`` for multi-camera flights.
    terrain_height:
        Height of the ground plane (metres, the datum of ``gnss_z``), one value or one per image.
    min_overlap:
        Keep pairs whose overlap area is at least this fraction of the smaller footprint (default 0.1).
    max_pairs_per_image:
        If given, each image keeps only its pairs of largest overlap (a pair stays if either image
        keeps it).
    return_overlap:
        Also return the overlap fraction of every pair.

    Returns int64 (P, 2) image ids with ``id1 < id2`` sorted (and the (P,) overlaps if asked).

    Raises:
        ValueError: ``min_overlap`` is outside [0, 1]; a mapping of cameras without an images ``camera_id`` column, or a
            camera_id it has no camera for; and as :func:`prior_poses` and :func:`footprints` (images without a position
            or attitude, a camera at or below the terrain height).
    """
    if not 0.0 <= min_overlap <= 1.0:
        raise ValueError(f"min_overlap must be a fraction in [0, 1], got {min_overlap}")
    ids, R, C = prior_poses(images)
    n = len(ids)
    fp = footprints(R, C, _cameras_for(images, camera, n), terrain_height)
    centre = fp.mean(axis=1)
    radius = np.linalg.norm(fp - centre[:, None, :], axis=-1).max(axis=1)
    if n < 2:
        pairs, frac = np.zeros((0, 2), dtype=np.int64), np.zeros(0)
    else:
        tree = cKDTree(centre)
        near = tree.query_ball_point(centre, radius + radius.max(), return_sorted=False)
        counts = np.fromiter((len(v) for v in near), dtype=np.int64, count=n)
        i = np.repeat(np.arange(n), counts)
        j = np.fromiter((x for v in near for x in v), dtype=np.int64, count=int(counts.sum()))
        keep = (j > i) & (np.linalg.norm(centre[i] - centre[j], axis=1) <= radius[i] + radius[j])
        i, j = i[keep], j[keep]
        area = np.abs(_signed_area(fp))
        inter = convex_overlap_area(fp[i], fp[j])
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = inter / np.minimum(area[i], area[j])
        ok = frac >= max(min_overlap, 1e-12)
        i, j, frac = i[ok], j[ok], frac[ok]
        if max_pairs_per_image is not None:
            sel = _top_k_per_image(i, j, frac, n, max_pairs_per_image)
            i, j, frac = i[sel], j[sel], frac[sel]
        pairs = np.sort(np.column_stack([ids[i], ids[j]]), axis=1)
        order = np.lexsort((pairs[:, 1], pairs[:, 0]))
        pairs, frac = pairs[order], frac[order]
    return (pairs, frac) if return_overlap else pairs


def _top_k_per_image(i: np.ndarray, j: np.ndarray, score: np.ndarray, n: int, k: int) -> np.ndarray:
    """Mask of pairs that are among the ``k`` best (by ``score``) of image i or of image j."""
    e = len(i)
    node = np.concatenate([i, j])
    s = np.concatenate([score, score])
    edge = np.concatenate([np.arange(e), np.arange(e)])
    order = np.lexsort((-s, node))
    node_sorted = node[order]
    start = np.searchsorted(node_sorted, np.arange(n))
    rank = np.arange(len(order)) - start[node_sorted]
    keep = np.zeros(e, dtype=bool)
    keep[edge[order][rank < k]] = True
    return keep


def exhaustive_pairs(ids: int | Sequence[int] | np.ndarray) -> np.ndarray:
    """All pairs of a set of images.

    Args:
        ids: image ids (repeated ids count once), or an int n for the ids 0..n-1.

    Returns:
        int64 array (P, 2), P = n (n - 1) / 2 over the n distinct ids: every pair once with ``id1 < id2``, rows
        sorted by ``id1``, then ``id2``.
    """
    ids = np.arange(ids) if isinstance(ids, int | np.integer) else np.unique(np.asarray(ids, dtype=np.int64))
    i, j = np.triu_indices(len(ids), k=1)
    return np.column_stack([ids[i], ids[j]]).astype(np.int64)


def sequential_pairs(ids: int | Sequence[int] | np.ndarray, window: int = 3) -> np.ndarray:
    """Each image with its next ``window`` images in the order given (a sliding window; flight order).

    Args:
        ids: image ids in flight order, or an int n for the ids 0..n-1. The order is kept and repeated ids are
            not merged (a repeated id can pair an image with itself).
        window: how many following images each image is paired with (default 3); ``<= 0`` gives no pair.

    Returns:
        int64 array (P, 2): every pair once, its two ids in increasing order, rows sorted by the first id, then
        the second.
    """
    ids = np.arange(ids) if isinstance(ids, int | np.integer) else np.asarray(ids, dtype=np.int64)
    n = len(ids)
    out = [np.column_stack([ids[: n - d], ids[d:]]) for d in range(1, min(window, n - 1) + 1)]
    if not out:
        return np.zeros((0, 2), dtype=np.int64)
    p = np.sort(np.concatenate(out), axis=1)
    return np.unique(p, axis=0).astype(np.int64)
