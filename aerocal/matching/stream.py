"""Detection and matching as one stream of tasks on a Dask cluster.

:func:`aerocal.matching.extract_features` followed by :func:`aerocal.matching.match_pairs_detailed` runs in
two phases: every image's features come back to the caller, are assembled into the ``keypoints`` table,
split again per image and sent back to the cluster before the first pair is matched, and the workers idle
while the last images finish. Here a pair's matching task depends on the detection tasks of its two images
and starts as soon as both are done; each image's features are sent to the caller once (for the table) and
dropped from the cluster when the last pair that needs them is matched, so the workers hold the features of
the images in flight, not of the whole flight. On a rendered city flight the stream was slightly faster than
the two phases (``benchmarks/history/engine_measurements.md``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pyarrow as pa

from aerocal.matching.cluster import Progress
from aerocal.matching.config import FeatureConfig, MatchConfig
from aerocal.matching.features import (
    _detect_image_task,
    _image_items,
    detects_tiles,
    extract_features,
    keypoints_table,
)
from aerocal.matching.verify import (
    MatchResult,
    _batches,
    _match_batch,
    match_pairs_detailed,
    match_result,
    normalise_pairs,
)


def _match_detected(pairs: np.ndarray, detected: dict[int, tuple], config: MatchConfig):
    """:func:`aerocal.matching.verify._match_batch` on detection results ``{image_id: (image_id, (kp, desc))}``;
    keypoint ids number each image's keypoints 0..N-1, as :func:`keypoints_table` does."""
    features = {i: (np.arange(len(kp), dtype=np.int32), kp[:, :2].astype(np.float64), desc)
                for i, (_, (kp, desc)) in detected.items()}
    return _match_batch(pairs, features, config)


def detect_and_match(
    images,
    loader: Callable[[object], np.ndarray],
    pairs,
    features: FeatureConfig | None = None,
    match: MatchConfig | None = None,
    client: object | None = None,
    progress: Progress | None = None,
) -> tuple[pa.Table, MatchResult]:
    """The ``keypoints`` table and the verified matches of ``pairs``, detection and matching streamed on ``client``.

    The same tables as :func:`extract_features` then :func:`match_pairs_detailed`: a pair's matching task starts
    as soon as its two images are detected. Without a client, or when ``features.granularity`` chooses tiles
    (few large images), the two phases run one after the other.

    Args:
        images: an ``images`` table (its ``image_id`` and ``path`` columns), a sequence of ``(image_id, source)``
            pairs, or a sequence of sources (numbered 0..n-1), as for :func:`extract_features`.
        loader: ``loader(source) -> uint8 image`` (2-D, or BGR converted to grey); it runs on the workers, so it
            must be picklable.
        pairs: (P, 2) image ids; order within a pair, duplicates and self-pairs do not matter
            (:func:`aerocal.matching.verify.normalise_pairs`). An image absent from ``images`` has no features.
        features: detection (default :class:`FeatureConfig`).
        match: matching and verification (default :class:`MatchConfig`).
        client: a ``distributed.Client``, or ``None`` to run in this process.
        progress: optional ``progress(done, total)`` callback; it counts images detected plus pairs matched.

    Returns:
        ``(keypoints, result)``: the ``keypoints`` table (images in the order given, keypoints strongest first)
        and the :class:`MatchResult` (verified matches and one :data:`PAIR_STATS` row per normalised pair).

    Raises:
        ValueError: an ``images`` table row without a ``path``, or a loaded image that is not 2-D 8-bit.
    """
    fcfg = features or FeatureConfig()
    mcfg = match or MatchConfig()
    items = _image_items(images)
    pairs = normalise_pairs(pairs)
    if client is None or detects_tiles(len(items), fcfg, client) or not items:
        n = len(items)
        kp = extract_features(images, loader, fcfg, client, None if progress is None else
                              (lambda d, t: progress(d * n // max(t, 1), n + len(pairs))))
        return kp, match_pairs_detailed(pairs, kp, mcfg, client, None if progress is None else
                                        (lambda d, t: progress(n + d, n + t)))

    # lazy: distributed is slow to import; only the Dask path needs it
    from distributed import as_completed

    detected = {i: client.submit(_detect_image_task, i, s, loader, fcfg, pure=False)  # type: ignore[attr-defined]
                for i, s in items}
    batches = _batches(pairs, mcfg.pairs_per_task)
    users = {i: 0 for i in detected}  # batches still to run that need the image's features
    batch_images = []
    for b in batches:
        ids = [int(i) for i in np.unique(b) if int(i) in detected]
        batch_images.append(ids)
        for i in ids:
            users[i] += 1
    matched = [client.submit(_match_detected, b, {i: detected[i] for i in ids}, mcfg, pure=False)  # type: ignore[attr-defined]
               for b, ids in zip(batches, batch_images, strict=True)]
    kind = {f.key: ("image", i) for i, f in detected.items()} | {f.key: ("batch", k) for k, f in enumerate(matched)}
    total, done = len(items) + len(pairs), 0
    found: dict[int, tuple] = {}
    results: list = [None] * len(batches)
    try:
        for fut in as_completed([*detected.values(), *matched]):
            what, k = kind[fut.key]
            if what == "image":
                found[k] = fut.result()[1]
                done += 1
                if users[k] == 0:
                    detected.pop(k).release()
            else:
                results[k] = fut.result()
                done += len(batches[k])
                for i in batch_images[k]:
                    users[i] -= 1
                    if users[i] == 0 and i in found:
                        detected.pop(i).release()
                fut.release()
            if progress is not None:
                progress(done, total)
    finally:
        for fut in [*detected.values(), *matched]:
            fut.release()
    kp = keypoints_table([(i, *found[i]) for i, _ in items])
    return kp, match_result(pairs, results)
