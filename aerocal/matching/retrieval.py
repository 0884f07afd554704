"""Which pairs to match when nothing recorded says where the frames look: a coarse match of each image's
strongest keypoints.

A flight without GNSS/IMU records (old survey archives, cameras that write no position) has no footprints to
predict overlap from, so every pair is a candidate; matching all ``n (n - 1) / 2`` pairs with every keypoint costs
a descriptor product of ``8000 x 8000`` per pair, most of them between frames that do not overlap. Here each
image's strongest keypoints (``RetrievalConfig.strongest``, the head of the ``keypoints`` table, which keeps an
image's keypoints strongest first) are matched against every other image's with the nearest-neighbour and mutual
tests of the full match and a stricter ratio (:func:`aerocal.matching.verify.match_descriptors`, exact): a product
of ``1024 x 1024`` per pair, 1/61 of the full one. Frames that overlap share many of their strongest points;
frames that do not share few, by chance (among 1024 candidates the second-nearest lies farther than among 8000,
so Lowe's 0.8 lets more chance matches through than in the full match: the coarse ratio is 0.7).

A pair goes on to the full match when its coarse matches reach ``min_matches``; when it is among an image's
``neighbours`` best-scoring pairs (no image is left without candidates however weak its texture, if it shares
anything); or when the two frames are within ``sequence_window`` of each other in capture order (consecutive
frames of a strip overlap by design).

This is the retrieval step of OpenSfM (``matching_bow_neighbors``: a bag of words over the strongest features)
and COLMAP (vocabulary-tree matching) reduced to what a flight of up to a few hundred frames needs: no
vocabulary is trained, and the coarse match is exact on the descriptors the full match uses. Measured on real
flights against the exhaustive match: ``benchmarks/RESULTS.md``, "Pairs without GNSS".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from aerocal.matching.config import MatchConfig
from aerocal.matching.features import image_features
from aerocal.matching.verify import match_descriptors


@dataclass(frozen=True)
class RetrievalConfig:
    """How candidate pairs are retrieved from the images' strongest keypoints.

    Attributes
    ----------
    strongest:
        Keypoints per image in the coarse match: the strongest by SIFT response (default 1024). Fewer make
        the coarse match cheaper and its scores noisier.
    ratio:
        Lowe's ratio test of the coarse match, both directions (default 0.7).
    min_matches:
        Coarse mutual ratio-test matches that send a pair to the full match (default 5). The defaults were
        chosen on the real copr flight against its exhaustive match (``benchmarks/RESULTS.md``, "Pairs without
        GNSS").
    neighbours:
        Each image keeps its this many best-scoring pairs whatever their scores, where they score at least
        one coarse match (default 5), so that a frame of weak texture still has candidates.
    sequence_window:
        Frames within this many places of each other in capture order are always paired (default 1: each
        frame with the next); 0 = none.
    """

    strongest: int = 1024
    ratio: float = 0.7
    min_matches: int = 5
    neighbours: int = 5
    sequence_window: int = 1

    def __post_init__(self) -> None:
        if self.strongest < 16:
            raise ValueError(f"RetrievalConfig.strongest must be 16 or more, got {self.strongest}")
        if not 0.0 < self.ratio <= 1.0:
            raise ValueError(f"RetrievalConfig.ratio must be in (0, 1], got {self.ratio}")
        if self.min_matches < 1:
            raise ValueError(f"RetrievalConfig.min_matches must be 1 or more, got {self.min_matches}")
        if self.neighbours < 0 or self.sequence_window < 0:
            raise ValueError(f"RetrievalConfig.neighbours and sequence_window must be 0 or more, got "
                             f"{self.neighbours} and {self.sequence_window}")


@dataclass(frozen=True)
class RetrievedPairs:
    """The pairs a coarse match chose, with what it measured.

    Attributes
    ----------
    pairs:
        (P, 2) int64 image ids, ``pairs[:, 0] < pairs[:, 1]``, in increasing order: the pairs to match in full.
    candidates:
        (C, 2) int64: every pair scored (all pairs of the images), same order convention.
    scores:
        (C,) int64: coarse matches of each candidate pair.
    """

    pairs: np.ndarray
    candidates: np.ndarray
    scores: np.ndarray

    @property
    def fraction(self) -> float:
        """Share of the candidate pairs kept (0..1; 1 for fewer than two images)."""
        return len(self.pairs) / len(self.candidates) if len(self.candidates) else 1.0


def retrieve_pairs(keypoints: pa.Table, order: np.ndarray | None = None, config: RetrievalConfig | None = None,
                   match: MatchConfig | None = None) -> RetrievedPairs:
    """Candidate pairs of the images of a ``keypoints`` table, scored by a coarse match of their strongest keypoints.

    Args:
        keypoints: the ``keypoints`` table (:func:`aerocal.matching.extract_features`), each image's keypoints
            strongest first.
        order: image ids in capture order (for ``config.sequence_window``); ``None``: the table's image ids
            in increasing order.
        config: :class:`RetrievalConfig` (default).
        match: the full match's :class:`MatchConfig`; its ``mutual`` test is used, with ``config.ratio`` and
            always the exact matcher (default :class:`MatchConfig`).

    Returns:
        :class:`RetrievedPairs`. An image without keypoints scores 0 with every other one; it is paired only by
        capture order.

    Raises:
        SchemaError, ValueError: as :func:`aerocal.matching.verify.image_features`.
    """
    config = config or RetrievalConfig()
    mcfg = match or MatchConfig()
    coarse = MatchConfig(ratio=config.ratio, mutual=mcfg.mutual, matcher="exact")
    feats = image_features(keypoints)
    ids = np.array(sorted(feats), dtype=np.int64) if order is None else np.asarray(order, dtype=np.int64)
    n = len(ids)
    a, b = np.triu_indices(n, k=1)
    heads = [feats[int(i)][2][: config.strongest] if int(i) in feats else np.zeros((0, 128), np.uint8) for i in ids]
    scores = np.array([len(match_descriptors(heads[i], heads[j], coarse)) for i, j in zip(a, b, strict=True)],
                      dtype=np.int64)
    keep = scores >= config.min_matches
    if config.sequence_window:
        keep |= (b - a) <= config.sequence_window
    if config.neighbours and n > 1:
        full = np.full((n, n), -1, dtype=np.int64)
        full[a, b] = full[b, a] = scores
        np.fill_diagonal(full, -1)
        k = min(config.neighbours, n - 1)
        best = np.argpartition(-full, k - 1, axis=1)[:, :k]  # each image's k best-scoring partners
        chosen = np.zeros((n, n), dtype=bool)
        chosen[np.repeat(np.arange(n), k), best.ravel()] = True
        chosen |= chosen.T
        keep |= chosen[a, b] & (scores > 0)
    lo, hi = np.minimum(ids[a], ids[b]), np.maximum(ids[a], ids[b])
    candidates = np.stack([lo, hi], axis=1)
    sort = np.lexsort((candidates[:, 1], candidates[:, 0]))
    candidates, scores, keep = candidates[sort], scores[sort], keep[sort]
    return RetrievedPairs(pairs=candidates[keep], candidates=candidates, scores=scores)
