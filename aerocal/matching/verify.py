"""Descriptor matching (exact or FLANN nearest neighbours, ratio test, mutual check) and RANSAC geometric verification.

Image coordinates are aerocal pixels (origin at the top-left corner of the top-left pixel); the
fundamental matrices and homographies estimated here refer to that convention. Pairs are matched in
batches, one batch per Dask task.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.matching.cluster import Progress, run_all, single_threaded_opencv
from aerocal.matching.config import MatchConfig
from aerocal.matching.features import image_features

#: Per-pair statistics of :func:`match_pairs_detailed`. ``rms_px`` is the RMS Sampson distance of the
#: inliers to the fundamental matrix (or their RMS transfer error under the homography), pixels.
PAIR_STATS = pa.schema(
    [
        pa.field("image_id1", pa.int32(), nullable=False),
        pa.field("image_id2", pa.int32(), nullable=False),
        pa.field("n_putative", pa.int32(), nullable=False),
        pa.field("n_inliers", pa.int32(), nullable=False),
        pa.field("rms_px", pa.float64()),
        pa.field("verified", pa.bool_(), nullable=False),
    ]
)

Features = tuple[np.ndarray, np.ndarray, np.ndarray]  # keypoint_id (N,), xy (N, 2), descriptors (N, 128)


@dataclass(frozen=True)
class MatchResult:
    """Verified matches (``matches`` table, inliers only) and one row of :data:`PAIR_STATS` per pair."""

    matches: pa.Table
    pair_stats: pa.Table


# ----------------------------------------------------------------------------- descriptor matching
class _IndexCache:
    """FLANN KD-tree forests of the images of one batch, each built once with a fixed seed."""

    def __init__(self, config: MatchConfig) -> None:
        self.config = config
        self._cache: dict[int, object] = {}

    def get(self, image_id: int, desc: np.ndarray):
        if image_id not in self._cache:
            cv2.setRNGSeed(self.config.seed)  # FLANN draws its split dimensions from OpenCV's RNG
            params = {"algorithm": 1, "trees": self.config.flann_trees}  # 1 = FLANN_INDEX_KDTREE
            self._cache[image_id] = cv2.flann_Index(np.ascontiguousarray(desc, dtype=np.float32), params)
        return self._cache[image_id]


def _knn2(index, query: np.ndarray, checks: int) -> tuple[np.ndarray, np.ndarray]:
    idx, dist = index.knnSearch(np.ascontiguousarray(query, dtype=np.float32), 2, params={"checks": checks})
    return idx.astype(np.int64), dist.astype(np.float64)  # squared L2 distances


def _ratio_nn(idx: np.ndarray, dist: np.ndarray, ratio: float) -> np.ndarray:
    """Nearest neighbour of each query, or -1 where Lowe's ratio test fails."""
    ok = dist[:, 0] < (ratio * ratio) * dist[:, 1]
    return np.where(ok, idx[:, 0], -1)


#: Largest block of the distance matrix (query rows x train columns) formed at once, cells: 4096 x 4096 float32
#: cells are 64 MB. Bigger sets are matched in row blocks of one product, both directions from each block.
EXACT_MAX_CELLS = 4096 * 4096


@numba.njit(cache=True)
def _scan_block(dot: np.ndarray, na: np.ndarray, nb: np.ndarray, start: int, idx: np.ndarray, d1: np.ndarray,
                d2: np.ndarray, c1: np.ndarray, c2: np.ndarray) -> None:
    """One pass over a block of the product ``a @ b.T`` (rows ``start:start + len(dot)`` of ``a``): each cell's
    squared distance ``|a|^2 + |b|^2 - 2 a.b`` (float32, clipped at 0), each row's nearest column ``idx`` (the
    first on a tie) with its nearest two distances ``d1``, ``d2``, and each column's nearest two over the rows seen
    so far ``c1``, ``c2`` (updated in place; equal where two rows tie for a column's nearest).

    Numpy needed seven passes over each block for the same (an argmin and a minimum per direction, the masks of
    ties and of the nearest); with one, the matrix product is most of the matching's time
    (``benchmarks/RESULTS.md``, "Descriptor matching in one pass", against OpenCV's matchers)."""
    two, zero = np.float32(2.0), np.float32(0.0)
    for r in range(dot.shape[0]):
        ai = na[start + r]
        r1, r2, best = np.float32(np.inf), np.float32(np.inf), 0
        row = dot[r]
        for j in range(dot.shape[1]):
            v = max((ai - two * row[j]) + nb[j], zero)
            if v < r1:
                r2, r1, best = r1, v, j
            elif v < r2:
                r2 = v
            c2[j] = min(c2[j], max(c1[j], v))
            c1[j] = min(c1[j], v)
        idx[start + r], d1[start + r], d2[start + r] = best, r1, r2


def _nearest_two(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, ...]:
    """Both directions from one distance matrix, formed in row blocks of ``a`` (float32 rows): for every row of
    ``a`` the index of its nearest row of ``b`` and the squared distances to the nearest two; for every row of
    ``b`` the squared distances to its nearest two rows of ``a`` (equal when two rows tie for the nearest).

    SIFT's uint8 descriptors make every product and distance an integer below 2^24 (128 x 255^2), exact in
    float32: the matches are those of the definition, ties included (a test)."""
    na, nb = np.einsum("ij,ij->i", a, a), np.einsum("ij,ij->i", b, b)
    n, m = len(a), len(b)
    idx, d1, d2 = np.zeros(n, np.int64), np.zeros(n, np.float32), np.zeros(n, np.float32)
    c1, c2 = np.full(m, np.inf, np.float32), np.full(m, np.inf, np.float32)
    step = max(1, EXACT_MAX_CELLS // max(m, 1))
    for s in range(0, n, step):
        _scan_block(a[s : s + step] @ b.T, na, nb, s, idx, d1, d2, c1, c2)
    return idx, d1, d2, c1, c2


def _exact_matches(desc1: np.ndarray, desc2: np.ndarray, ratio: float, mutual: bool) -> np.ndarray:
    """Exact nearest neighbours, ratio test (and the mutual check with the reverse ratio test): (M, 2).

    Both directions come from one distance matrix, one pass over each of its row blocks
    (:func:`_nearest_two`). Written for this project on numpy's BLAS, faster than OpenCV's
    ``BFMatcher.knnMatch`` and FLANN (see :class:`MatchConfig`; ``benchmarks/history/engine_measurements.md``).
    """
    a = np.ascontiguousarray(desc1, dtype=np.float32)
    b = np.ascontiguousarray(desc2, dtype=np.float32)
    if not len(a) or not len(b):
        return np.zeros((0, 2), np.int64)
    j1, best, second, col_best, col_second = _nearest_two(a, b)
    r2 = np.float32(ratio * ratio)
    q = np.nonzero(best < r2 * second)[0]
    if mutual:
        # q is the nearest row of its nearest column (a tie leaves that column's two smallest equal, and the
        # reverse ratio test then fails), and that column passes the ratio test too
        j = j1[q]
        q = q[(best[q] <= col_best[j]) & (col_best[j] < r2 * col_second[j])]
    return np.stack([q, j1[q]], axis=1).astype(np.int64)


def match_descriptors(
    desc1: np.ndarray, desc2: np.ndarray, config: MatchConfig | None = None, index1=None, index2=None
) -> np.ndarray:
    """Putative matches between two descriptor sets: nearest neighbours, ratio test and mutual check.

    Nearest neighbours by ``config.matcher``: exact (brute force on BLAS) or FLANN randomised KD-trees; Lowe's
    ratio test and, with ``config.mutual``, the mutual check with the ratio test in the reverse direction too.

    Args:
        desc1, desc2: the descriptor sets (N1, 128) and (N2, 128) (SIFT, uint8).
        config: ``matcher``, ``ratio``, ``mutual`` and the FLANN settings (default :class:`MatchConfig`).
        index1, index2: prebuilt ``cv2.flann_Index`` of ``desc1`` and ``desc2`` (``matcher="flann"`` only;
            ``None``: built here, OpenCV's generator seeded with ``config.seed``). The exact matcher ignores them.

    Returns:
        int64 array (M, 2) of row indices into ``desc1`` and ``desc2``, in increasing ``desc1`` row; empty when
        either set has fewer than 2 descriptors.
    """
    config = config or MatchConfig()
    if len(desc1) < 2 or len(desc2) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    if config.matcher == "exact":
        return _exact_matches(desc1, desc2, config.ratio, config.mutual)
    cache = _IndexCache(config)
    index2 = index2 if index2 is not None else cache.get(2, desc2)
    nn12 = _ratio_nn(*_knn2(index2, desc1, config.flann_checks), config.ratio)
    q = np.nonzero(nn12 >= 0)[0]
    if config.mutual:
        index1 = index1 if index1 is not None else cache.get(1, desc1)
        nn21 = _ratio_nn(*_knn2(index1, desc2, config.flann_checks), config.ratio)
        q = q[nn21[nn12[q]] == q]
    return np.stack([q, nn12[q]], axis=1).astype(np.int64)


# ----------------------------------------------------------------------------- geometric verification
def sampson_distance(F: np.ndarray, xy1: np.ndarray, xy2: np.ndarray) -> np.ndarray:
    """Sampson distance of correspondences ``xy1 <-> xy2`` to the epipolar constraint ``x2^T F x1 = 0``.

    The first-order approximation of the geometric (reprojection) error:
    ``|x2^T F x1| / sqrt((F x1)_1^2 + (F x1)_2^2 + (F^T x2)_1^2 + (F^T x2)_2^2)``.

    Args:
        F: the fundamental matrix (3, 3) from the first image to the second, in pixel coordinates (origin at the
            top-left corner of the top-left pixel).
        xy1, xy2: corresponding points (N, 2), pixels, in the first and the second image.

    Returns:
        float array (N,): the distances, pixels; inf or NaN where the denominator is zero.
    """
    x1 = np.column_stack([xy1, np.ones(len(xy1))])
    x2 = np.column_stack([xy2, np.ones(len(xy2))])
    Fx1 = x1 @ F.T
    Ftx2 = x2 @ F
    e = np.sum(x2 * Fx1, axis=1)
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.abs(e) / np.sqrt(den)


def transfer_error(H: np.ndarray, xy1: np.ndarray, xy2: np.ndarray) -> np.ndarray:
    """Distance (pixels) between ``xy2`` and ``H`` applied to ``xy1``."""
    p = np.column_stack([xy1, np.ones(len(xy1))]) @ H.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.linalg.norm(p[:, :2] / p[:, 2:3] - xy2, axis=1)


def verify(xy1: np.ndarray, xy2: np.ndarray, config: MatchConfig | None = None):
    """Geometric verification of putative correspondences by RANSAC (OpenCV USAC MAGSAC++).

    Args:
        xy1, xy2: putative correspondences (N, 2), pixels (origin at the top-left corner of the top-left pixel),
            in the first and the second image.
        config: ``geometry`` (fundamental matrix or homography), ``ransac_threshold`` (pixels),
            ``ransac_confidence``, ``ransac_max_iters`` and ``min_matches`` (default :class:`MatchConfig`).

    Returns:
        ``(inlier_mask (N,) bool, model 3x3 or None, rms_px)``: ``model`` is the fundamental matrix
        (``x2^T F x1 = 0``) or the homography (``x2 ~ H x1``); ``rms_px`` is the RMS Sampson distance
        (fundamental) or transfer error (homography) of the inliers, pixels, NaN without a model. There is no
        model (mask all False) with fewer than ``max(config.min_matches, 8)`` correspondences, when OpenCV asserts
        on a degenerate sample, or when no correspondence is an inlier. The number of inliers is not checked
        against ``min_matches`` here.
    """
    config = config or MatchConfig()
    n = len(xy1)
    none = np.zeros(n, dtype=bool), None, float("nan")
    if n < max(config.min_matches, 8):
        return none
    p1 = np.ascontiguousarray(xy1, dtype=np.float64)
    p2 = np.ascontiguousarray(xy2, dtype=np.float64)
    try:
        if config.geometry == "fundamental":
            model, mask = cv2.findFundamentalMat(
                p1, p2, cv2.USAC_MAGSAC, config.ransac_threshold, config.ransac_confidence,
                config.ransac_max_iters,
            )
        else:
            model, mask = cv2.findHomography(
                p1, p2, cv2.USAC_MAGSAC, config.ransac_threshold, maxIters=config.ransac_max_iters,
                confidence=config.ransac_confidence,
            )
    except cv2.error:  # USAC asserts on some degenerate samples (`!model.empty()`): no model, not verified
        return none
    if model is None or mask is None or model.shape != (3, 3):
        return none
    inl = mask.ravel().astype(bool)
    if not inl.any():
        return none
    err = (sampson_distance if config.geometry == "fundamental" else transfer_error)(model, p1[inl], p2[inl])
    return inl, model, float(np.sqrt(np.mean(err**2)))


# ----------------------------------------------------------------------------- batches of pairs
def _match_batch(pairs: np.ndarray, features: dict[int, Features], config: MatchConfig):
    """Match and verify a batch of pairs; returns (matches (M, 4) int64, stats (B, 4) float64)."""
    single_threaded_opencv()
    cache = _IndexCache(config)
    empty = (np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 128), np.uint8))
    out, stats = [], np.zeros((len(pairs), 4))
    for k, (i, j) in enumerate(pairs):
        id1, xy1, d1 = features.get(int(i), empty)
        id2, xy2, d2 = features.get(int(j), empty)
        m = np.zeros((0, 2), dtype=np.int64)
        if len(d1) >= 2 and len(d2) >= 2:
            if config.matcher == "flann":
                m = match_descriptors(d1, d2, config, cache.get(int(i), d1), cache.get(int(j), d2))
            else:
                m = match_descriptors(d1, d2, config)
        inl, _, rms = verify(xy1[m[:, 0]], xy2[m[:, 1]], config)
        ok = bool(inl.sum() >= config.min_matches)
        stats[k] = (len(m), inl.sum(), rms, ok)
        if ok:
            m = m[inl]
            out.append(np.column_stack([np.full(len(m), i), np.full(len(m), j), id1[m[:, 0]], id2[m[:, 1]]]))
    matches = np.concatenate(out).astype(np.int64) if out else np.zeros((0, 4), dtype=np.int64)
    return matches, stats


def normalise_pairs(pairs) -> np.ndarray:
    """Pairs as a sorted, duplicate-free int64 array (P, 2) with ``id1 < id2``; self-pairs dropped."""
    p = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    p = np.sort(p, axis=1)
    p = p[p[:, 0] != p[:, 1]]
    return np.unique(p, axis=0) if len(p) else p


def _batches(pairs: np.ndarray, size: int) -> list[np.ndarray]:
    return [pairs[s : s + size] for s in range(0, len(pairs), size)]


def match_pairs_detailed(
    pairs,
    keypoints: pa.Table,
    config: MatchConfig | None = None,
    client: object | None = None,
    progress: Progress | None = None,
) -> MatchResult:
    """Match and verify image pairs; the verified matches and per-pair statistics.

    Parameters
    ----------
    pairs:
        (P, 2) image ids (order within a pair and duplicates do not matter; see
        :func:`normalise_pairs`). An image absent from ``keypoints`` has no features.
    keypoints:
        The ``keypoints`` table with descriptors (:func:`aerocal.matching.extract_features`).
    config:
        :class:`MatchConfig`.
    client:
        A ``distributed.Client``: batches of ``config.pairs_per_task`` pairs run as tasks, each
        image's features are sent to the cluster once. ``None`` runs here. Results are identical.
    progress:
        Optional ``progress(done_pairs, total_pairs)`` callback.
    """
    config = config or MatchConfig()
    pairs = normalise_pairs(pairs)
    feats = image_features(keypoints)
    batches = _batches(pairs, config.pairs_per_task)
    source: dict = feats
    if client is not None:  # send each image's features to the cluster once
        used = [int(i) for i in np.unique(pairs) if int(i) in feats]
        scattered = client.scatter([feats[i] for i in used])  # type: ignore[attr-defined]
        source = dict(zip(used, scattered, strict=True))
    args = [(b, {int(i): source[int(i)] for i in np.unique(b) if int(i) in source}, config) for b in batches]
    return match_result(pairs, run_all(_match_batch, args, client, progress, weights=[len(b) for b in batches]))


def match_result(pairs: np.ndarray, results: list) -> MatchResult:
    """The :class:`MatchResult` of normalised ``pairs`` from the ``(matches, stats)`` of their batches
    (:func:`_match_batch`), batches in the order of the pairs."""
    matches = np.concatenate([r[0] for r in results]) if results else np.zeros((0, 4), np.int64)
    stats = np.concatenate([r[1] for r in results]) if results else np.zeros((0, 4))
    table = tables.from_columns("matches", {
        "image_id1": matches[:, 0], "image_id2": matches[:, 1],
        "keypoint_id1": matches[:, 2], "keypoint_id2": matches[:, 3],
    })
    pair_stats = pa.Table.from_arrays(
        [
            pa.array(pairs[:, 0], pa.int32()), pa.array(pairs[:, 1], pa.int32()),
            pa.array(stats[:, 0].astype(np.int32)), pa.array(stats[:, 1].astype(np.int32)),
            pa.array(stats[:, 2], pa.float64(), from_pandas=True), pa.array(stats[:, 3].astype(bool)),
        ],
        schema=PAIR_STATS,
    )
    return MatchResult(table, pair_stats)


def match_pairs(
    pairs,
    keypoints: pa.Table,
    config: MatchConfig | None = None,
    client: object | None = None,
    progress: Progress | None = None,
) -> pa.Table:
    """The ``matches`` table (verified inliers only) of ``pairs``; see :func:`match_pairs_detailed`.

    Args:
        pairs: (P, 2) image ids; order within a pair, duplicates and self-pairs do not matter
            (:func:`normalise_pairs`). An image absent from ``keypoints`` has no features.
        keypoints: the ``keypoints`` table with descriptors (:func:`aerocal.matching.extract_features`).
        config: matching and verification (default :class:`MatchConfig`).
        client: a ``distributed.Client``: batches of ``config.pairs_per_task`` pairs run as tasks, each image's
            features are sent to the cluster once. ``None`` runs here. Results are identical.
        progress: optional ``progress(done_pairs, total_pairs)`` callback.

    Returns:
        The ``matches`` table: the inliers of every verified pair (at least ``config.min_matches`` inliers), with
        ``image_id1 < image_id2``, pairs in increasing order.

    Raises:
        SchemaError: ``keypoints`` does not match its :mod:`aerocal.tables` schema.
        ValueError: keypoints without a descriptor.
    """
    return match_pairs_detailed(pairs, keypoints, config, client, progress).matches


def pair_summary(pair_stats: pa.Table) -> dict[str, float]:
    """Totals of a :data:`PAIR_STATS` table.

    Args:
        pair_stats: the per-pair statistics (:attr:`MatchResult.pair_stats`).

    Returns:
        ``{"pairs", "verified_pairs", "inliers", "putative", "rms_px"}``: the pairs tried and those verified; the
        inliers and the putative matches summed over the verified pairs only; the pooled inlier RMS (pixels) of
        the verified pairs (their ``rms_px`` weighted by inliers), NaN when no pair is verified.
    """
    n_inl = pair_stats.column("n_inliers").to_numpy()
    rms = pair_stats.column("rms_px").to_numpy(zero_copy_only=False)
    ok = pair_stats.column("verified").to_numpy(zero_copy_only=False).astype(bool)
    pooled = float(np.sqrt(np.sum(n_inl[ok] * rms[ok] ** 2) / n_inl[ok].sum())) if ok.any() else float("nan")
    return {
        "pairs": int(len(ok)),
        "verified_pairs": int(ok.sum()),
        "inliers": int(n_inl[ok].sum()),
        "putative": int(pair_stats.column("n_putative").to_numpy()[ok].sum()),
        "rms_px": pooled,
    }
