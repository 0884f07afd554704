"""SIFT keypoints and descriptors, detected on image tiles, serially or on a Dask cluster.

Coordinates are returned in full-image pixels in the aerocal convention: origin at the top-left
*corner* of the top-left pixel (OpenCV puts the centre of that pixel at (0, 0), so 0.5 is added to
OpenCV's keypoint positions). ``scale`` is the keypoint's Gaussian scale sigma in pixels (OpenCV's
``size`` is twice it); ``orientation`` is OpenCV's angle in radians, clockwise from the x axis (y is
down).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import cv2
import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.matching.cluster import Progress, n_workers, run_all, single_threaded_opencv
from aerocal.matching.config import FeatureConfig

#: Columns of a detection result before the cap: x, y, scale, orientation, response.
_N_COLS = 5


def _sift(config: FeatureConfig):
    # The cap is also applied per tile, before descriptors are computed (OpenCV keeps the strongest
    # responses, ties included): a tile's owned keypoints among the image's strongest are among the
    # tile's strongest, so the per-image cap in merge_tiles sees them all, and descriptors of keypoints
    # that would be dropped are never computed.
    return cv2.SIFT_create(
        config.max_features, config.n_octave_layers, config.contrast_threshold, config.edge_threshold, config.sigma,
        cv2.CV_8U, config.precise_upscale,
    )


def tile_boxes(width: int, height: int, config: FeatureConfig) -> np.ndarray:
    """Tiles of an image and the core each one owns, for SIFT detected tile by tile.

    The cores partition the image; tile origins are multiples of ``tile_size - tile_overlap``. ``tile_size=0``
    gives one tile, the whole image.

    Args:
        width, height: the image's size, pixels.
        config: ``tile_size`` and ``tile_overlap`` (pixels); an image side no longer than ``tile_size`` is one
            tile along that side.

    Returns:
        int64 array (T, 8), one row per tile, left to right then top to bottom: tile ``x0, y0, x1, y1`` then core
        ``cx0, cy0, cx1, cy1`` (pixels, half-open, full-image coordinates with the origin at the top-left
        corner). The last tile along a side ends at the image border; a core reaches the image border where its
        tile does, and stops about half the overlap inside the tile elsewhere.
    """

    def axis(n: int) -> list[tuple[int, int, int, int]]:
        if not config.tile_size or n <= config.tile_size:
            return [(0, n, 0, n)]
        step = config.tile_size - config.tile_overlap
        starts = list(range(0, max(n - config.tile_overlap, 1), step))
        spans = [(s, min(s + config.tile_size, n)) for s in starts]  # the last start is >= n - tile_size
        half = config.tile_overlap // 2
        out = []
        for k, (s, e) in enumerate(spans):
            core0 = 0 if k == 0 else s + half
            core1 = n if k == len(spans) - 1 else spans[k + 1][0] + half
            out.append((s, e, core0, core1))
        return out

    boxes = [
        (xs, ys, xe, ye, cx0, cy0, cx1, cy1)
        for (ys, ye, cy0, cy1) in axis(int(height))
        for (xs, xe, cx0, cx1) in axis(int(width))
    ]
    return np.array(boxes, dtype=np.int64)


def reduction(width: int, height: int, config: FeatureConfig) -> int:
    """By how much a frame is reduced before OpenCV's SIFT sees it: 1, or 2 for a frame of more than
    ``config.fine_octave_max_pixels`` pixels (detected from octave 0: :class:`FeatureConfig`)."""
    return 2 if width * height > config.fine_octave_max_pixels else 1


def detect_tile(img8: np.ndarray, box: np.ndarray, config: FeatureConfig) -> tuple[np.ndarray, np.ndarray]:
    """SIFT on one tile of ``img8``; keeps the keypoints inside the tile's core.

    A frame :func:`reduction` reduces is detected on the tile reduced twice by area averaging (its odd last row
    or column left out), the keypoints scaled back to the frame's pixels.

    Returns ``(kp, desc)``: ``kp`` float64 (N, 5) x, y (full-image pixels, aerocal convention), scale,
    orientation (radians), response; ``desc`` uint8 (N, 128).
    """
    single_threaded_opencv()
    x0, y0, x1, y1, cx0, cy0, cx1, cy1 = (int(v) for v in box)
    r = reduction(img8.shape[1], img8.shape[0], config)
    tile = np.ascontiguousarray(img8[y0 : y1 - (y1 - y0) % r, x0 : x1 - (x1 - x0) % r])
    if r > 1:
        tile = cv2.resize(tile, (tile.shape[1] // r, tile.shape[0] // r), interpolation=cv2.INTER_AREA)
    kps, desc = _sift(config).detectAndCompute(tile, None)
    if not kps:
        return np.zeros((0, _N_COLS)), np.zeros((0, 128), dtype=np.uint8)
    kp = np.array([(k.pt[0], k.pt[1], k.size, k.angle, k.response) for k in kps], dtype=np.float64)
    # OpenCV's pixel centres to the tile's corner convention, then the reduced tile's pixels to the frame's
    kp[:, 0] = (kp[:, 0] + 0.5) * r + x0
    kp[:, 1] = (kp[:, 1] + 0.5) * r + y0
    kp[:, 2] *= 0.5 * r  # OpenCV size = 2 sigma
    kp[:, 3] = np.radians(kp[:, 3])
    own = (kp[:, 0] >= cx0) & (kp[:, 0] < cx1) & (kp[:, 1] >= cy0) & (kp[:, 1] < cy1)
    return kp[own], np.asarray(desc, dtype=np.uint8)[own]


def merge_tiles(
    results: Sequence[tuple[np.ndarray, np.ndarray]], config: FeatureConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Join tile results, order them by decreasing response and apply the per-image cap.

    The order is total (ties broken by y, x, scale, orientation), so the result does not depend on
    the order tiles finished in or on OpenCV's threading.
    """
    kp = np.concatenate([r[0] for r in results]) if results else np.zeros((0, _N_COLS))
    desc = np.concatenate([r[1] for r in results]) if results else np.zeros((0, 128), np.uint8)
    order = np.lexsort((kp[:, 3], kp[:, 2], kp[:, 0], kp[:, 1], -kp[:, 4]))
    if config.max_features:
        order = order[: config.max_features]
    return kp[order, :4].astype(np.float32), np.ascontiguousarray(desc[order])


def detect(img8: np.ndarray, config: FeatureConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of an 8-bit image, detected tile by tile (:func:`tile_boxes`).

    Args:
        img8: the image, uint8 (H, W); (H, W, 3) BGR and (H, W, 4) BGRA are converted to grey.
        config: detection and tiling (default :class:`FeatureConfig`).

    Returns:
        ``(keypoints, descriptors)``: float32 (N, 4) ``[x, y, scale, orientation]``, x, y in full-image pixels
        (aerocal convention, see the module docstring: origin at the top-left corner of the top-left pixel, y
        down), scale the Gaussian sigma in pixels, orientation in radians clockwise from the x axis; strongest
        response first (ties broken by y, x, scale, orientation), at most ``config.max_features`` (0: no cap);
        and uint8 (N, 128) SIFT descriptors in the same order.

    Raises:
        ValueError: the image is not 2-D 8-bit (after the grey conversion); convert it with
            :func:`aerocal.enhance.enhance` or :func:`aerocal.enhance.to_uint8`.
    """
    config = config or FeatureConfig()
    img8 = _check_image(img8)
    boxes = tile_boxes(img8.shape[1], img8.shape[0], config)
    return merge_tiles([detect_tile(img8, b, config) for b in boxes], config)


def _check_image(img: np.ndarray, name: object = "image") -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a, cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if a.ndim != 2 or a.dtype != np.uint8:
        raise ValueError(
            f"{name}: SIFT needs a 2-D 8-bit image, got shape {a.shape} dtype {a.dtype}; "
            "convert it with aerocal.enhance.enhance or aerocal.enhance.to_uint8"
        )
    return a


# ----------------------------------------------------------------------------- tasks
def _detect_image_task(image_id: int, source: object, loader: Callable, config: FeatureConfig):
    single_threaded_opencv()
    img = _check_image(loader(source), source)
    boxes = tile_boxes(img.shape[1], img.shape[0], config)
    return image_id, merge_tiles([detect_tile(img, b, config) for b in boxes], config)


def _load_task(source: object, loader: Callable) -> np.ndarray:
    single_threaded_opencv()
    return _check_image(loader(source), source)


def _shape_task(img: np.ndarray) -> tuple[int, int]:
    return int(img.shape[1]), int(img.shape[0])


def _image_items(images) -> list[tuple[int, object]]:
    """``(image_id, source)`` pairs from an images table (``path``) or a sequence of pairs/sources."""
    if isinstance(images, pa.Table):
        ids = images.column("image_id").to_pylist()
        paths = images.column("path").to_pylist()
        missing = [i for i, p in zip(ids, paths, strict=True) if p is None]
        if missing:
            raise ValueError(f"images table: image_id(s) {missing[:5]} have no path; fill images.path")
        return list(zip(ids, paths, strict=True))
    items = []
    for k, item in enumerate(images):
        if isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], int | np.integer):
            items.append((int(item[0]), item[1]))
        else:
            items.append((k, item))
    return items


def keypoints_table(features: Sequence[tuple[int, np.ndarray, np.ndarray]]) -> pa.Table:
    """The ``keypoints`` table of per-image detections.

    Args:
        features: ``(image_id, keypoints, descriptors)`` triples, as :func:`detect` gives them: keypoints (N, 4)
            ``[x, y, scale, orientation]`` (pixels with the origin at the top-left corner; radians), descriptors
            uint8 (N, 128). Give each image once.

    Returns:
        The ``keypoints`` table (:mod:`aerocal.tables`), images and keypoints in the order given; ``keypoint_id``
        numbers each image's keypoints 0..N-1 in that order. Empty when ``features`` is.

    Raises:
        ValueError: keypoints or descriptors that cannot be reshaped to (N, 4) and (N, 128).
    """
    ids, kpids, kps, descs = [], [], [], []
    for image_id, kp, desc in features:
        n = len(kp)
        ids.append(np.full(n, image_id, dtype=np.int32))
        kpids.append(np.arange(n, dtype=np.int32))
        kps.append(np.asarray(kp, dtype=np.float32).reshape(n, 4))
        descs.append(np.asarray(desc, dtype=np.uint8).reshape(n, 128))
    if not kps:
        return tables.empty("keypoints")
    kp = np.concatenate(kps)
    desc = pa.FixedSizeListArray.from_arrays(pa.array(np.concatenate(descs).ravel(), pa.uint8()), 128)
    return tables.from_columns("keypoints", {
        "image_id": np.concatenate(ids), "keypoint_id": np.concatenate(kpids),
        "x": kp[:, 0], "y": kp[:, 1], "scale": kp[:, 2], "orientation": kp[:, 3], "descriptor": desc,
    })


def detects_tiles(n_images: int, config: FeatureConfig, client: object | None) -> bool:
    """Whether the cluster's unit of work is a tile (``config.granularity``; ``"auto"``: fewer than two images
    per worker, tiled), not an image; never without a cluster."""
    return client is not None and (
        config.granularity == "tile"
        or (config.granularity == "auto" and n_images < 2 * n_workers(client) and config.tile_size > 0)
    )


def extract_features(
    images,
    loader: Callable[[object], np.ndarray],
    config: FeatureConfig | None = None,
    client: object | None = None,
    progress: Progress | None = None,
) -> pa.Table:
    """Detect SIFT features on every image, on a Dask cluster when ``client`` is given.

    Parameters
    ----------
    images:
        An ``images`` table (its ``image_id`` and ``path`` columns are used), a sequence of
        ``(image_id, source)`` pairs, or a sequence of sources (numbered 0..n-1).
    loader:
        ``loader(source) -> uint8 image`` (2-D, or BGR which is converted to grey), e.g. a reader
        followed by :func:`aerocal.enhance.enhance`. It runs on the workers, so it must be picklable
        (a module-level function or a ``functools.partial`` of one).
    config:
        :class:`FeatureConfig`; its ``granularity`` chooses images or tiles as the unit of work.
    client:
        A ``distributed.Client`` (e.g. from :func:`aerocal.matching.local_client`), or ``None`` to
        run in this process.
    progress:
        Optional ``progress(done, total)`` callback, called as images (or tiles) finish.

    Returns the ``keypoints`` table, images in the order given, keypoints strongest first. The result
    is identical with and without a cluster.
    """
    config = config or FeatureConfig()
    items = _image_items(images)
    if not items:
        return tables.empty("keypoints")
    if not detects_tiles(len(items), config, client):
        results = run_all(_detect_image_task, [(i, s, loader, config) for i, s in items], client, progress)
        return keypoints_table([(i, kp, desc) for i, (kp, desc) in results])

    # one task per tile; each image is loaded once on a worker and shared with the tile tasks
    loaded = [client.submit(_load_task, s, loader, pure=False) for _, s in items]  # type: ignore[attr-defined]
    shapes = client.gather([client.submit(_shape_task, f) for f in loaded])  # type: ignore[attr-defined]
    tasks, owner = [], []
    for k, (fut, (w, h)) in enumerate(zip(loaded, shapes, strict=True)):
        for box in tile_boxes(w, h, config):
            tasks.append((fut, box, config))
            owner.append(k)
    tile_results = run_all(detect_tile, tasks, client, progress)
    del loaded
    per_image: list[list] = [[] for _ in items]
    for k, res in zip(owner, tile_results, strict=True):
        per_image[k].append(res)
    merged = [merge_tiles(r, config) for r in per_image]
    return keypoints_table([(i, kp, desc) for (i, _), (kp, desc) in zip(items, merged, strict=True)])


def image_features(keypoints: pa.Table) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Split a ``keypoints`` table per image, for matching.

    Args:
        keypoints: the ``keypoints`` table (:mod:`aerocal.tables`), every keypoint with its descriptor.

    Returns:
        ``{image_id: (keypoint_id (N,), xy (N, 2) float64, desc (N, 128) uint8)}``, image ids in increasing order,
        each image's rows in increasing ``keypoint_id``; ``xy`` in pixels with the origin at the top-left corner.

    Raises:
        SchemaError: the table does not match the ``keypoints`` schema.
        ValueError: keypoints without a descriptor.
    """
    kp = tables.validate(keypoints, "keypoints")
    image_id = kp.column("image_id").to_numpy()
    kp_id = kp.column("keypoint_id").to_numpy()
    xy = np.stack([kp.column("x").to_numpy(), kp.column("y").to_numpy()], axis=1).astype(np.float64)
    desc_col = kp.column("descriptor").combine_chunks()
    if desc_col.null_count:
        raise ValueError(f"keypoints table has {desc_col.null_count} keypoint(s) without a descriptor")
    desc = desc_col.flatten().to_numpy(zero_copy_only=False).reshape(-1, 128)
    order = np.lexsort((kp_id, image_id))
    image_id, kp_id, xy, desc = image_id[order], kp_id[order], xy[order], desc[order]
    ids, starts = np.unique(image_id, return_index=True)
    ends = np.append(starts[1:], len(image_id)) if len(starts) else starts
    return {int(i): (kp_id[s:e], xy[s:e], desc[s:e]) for i, s, e in zip(ids, starts, ends, strict=True)}
