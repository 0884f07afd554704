"""Descriptor matching on real frames: the exact matcher against OpenCV's brute-force matcher and FLANN.

Baselines measured in the same run, on the same descriptor sets, one thread: OpenCV's ``BFMatcher.knnMatch``
(k = 2, both directions, the same ratio test and mutual check), FLANN (``matcher="flann"``) and the exact
matcher as numpy wrote it before its scan became one compiled pass (:func:`numpy_exact`, kept here as it was).
Pairs are the footprint pairs of the flight's recorded positions and attitudes (as ``aerocal process`` matches
them), or consecutive frames where the records are missing; the first ``--pairs`` of them.

    python -m benchmarks.descriptor_bench [--flights h20t_forest copr] [--pairs 60]

Target: the same matches as the brute-force definition (OpenCV's), faster than either OpenCV matcher.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from aerocal.camera import Camera
from aerocal.matching import FeatureConfig, MatchConfig, extract_features
from aerocal.matching.pairs import candidate_pairs_from_footprints
from aerocal.matching.verify import match_descriptors
from aerocal.pipeline.dataset import FolderDataset, IngestStepConfig
from aerocal.pipeline.match_step import frame_loader, terrain_height
from aerocal.poses import has_priors
from benchmarks.common import peak_rss_mb, record

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def numpy_exact(desc1: np.ndarray, desc2: np.ndarray, ratio: float) -> np.ndarray:
    """The exact matcher before 2026-12-06 (numpy passes over one distance matrix), for the same data."""
    a, b = desc1.astype(np.float32), desc2.astype(np.float32)
    d = a @ b.T
    d *= -2.0
    d += np.einsum("ij,ij->i", a, a)[:, None]
    d += np.einsum("ij,ij->i", b, b)[None, :]
    np.maximum(d, 0.0, out=d)
    r, r2 = np.arange(len(a)), np.float32(ratio * ratio)
    j1 = d.argmin(axis=1)
    best = d[r, j1]
    d[r, j1] = np.inf
    second = d.min(axis=1)
    d[r, j1] = best
    q = np.nonzero(best < r2 * second)[0]
    q = q[best[q] <= d.min(axis=0)[j1[q]]]
    q = q[np.bincount(j1[q], minlength=len(b))[j1[q]] == 1]
    d[q, j1[q]] = np.inf
    q = q[best[q] < r2 * d.min(axis=0)[j1[q]]]
    return np.stack([q, j1[q]], axis=1)


def opencv_bf(desc1: np.ndarray, desc2: np.ndarray, ratio: float) -> np.ndarray:
    """OpenCV's brute-force matcher, k = 2 both ways, the ratio test both ways and the mutual check."""
    bf = cv2.BFMatcher(cv2.NORM_L2)
    a, b = desc1.astype(np.float32), desc2.astype(np.float32)

    def nn(x, y):
        out = np.full(len(x), -1)
        for m in bf.knnMatch(x, y, k=2):
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                out[m[0].queryIdx] = m[0].trainIdx
        return out

    ab, ba = nn(a, b), nn(b, a)
    q = np.nonzero(ab >= 0)[0]
    q = q[ba[ab[q]] == q]
    return np.stack([q, ab[q]], axis=1)


def flight_rows(name: str, n_pairs: int) -> list[str]:
    flight = FolderDataset(DATA / name).read(IngestStepConfig())
    images = flight.tables["images"]
    camera = Camera.from_dict(flight.camera["camera"])
    if has_priors(images):
        pairs = candidate_pairs_from_footprints(images, camera, terrain_height(images, flight.tables.get("gcps"),
                                                                              flight.metadata))[:n_pairs]
    else:  # frames without records: consecutive frames
        order = images.column("image_id").to_numpy()
        pairs = np.stack([order[:-1], order[1:]], axis=1)[:n_pairs]
    kp = extract_features(images, frame_loader(images.column("path").to_pylist()), FeatureConfig(), None)
    ids, desc = kp.column("image_id").to_numpy(), kp.column("descriptor").to_pylist()
    sets = {int(i): np.asarray([d for k, d in zip(ids, desc, strict=True) if k == i], np.uint8)
            for i in np.unique(pairs)}
    config = MatchConfig()
    methods = {"OpenCV BFMatcher (baseline)": lambda a, b: opencv_bf(a, b, config.ratio),
               "FLANN": lambda a, b: match_descriptors(a, b, MatchConfig(matcher="flann")),
               "exact, numpy passes (before)": lambda a, b: numpy_exact(a, b, config.ratio),
               "exact, one compiled pass": lambda a, b: match_descriptors(a, b, config)}
    match_descriptors(sets[int(pairs[0][0])][:10], sets[int(pairs[0][1])][:10], config)  # compiled before timing
    seconds, found = {}, {}
    for label, fn in methods.items():
        t0 = time.perf_counter()
        found[label] = [set(map(tuple, fn(sets[int(i)], sets[int(j)]).tolist())) for i, j in pairs]
        seconds[label] = time.perf_counter() - t0
    base = "OpenCV BFMatcher (baseline)"
    n_desc = np.mean([len(s) for s in sets.values()])
    rows = []
    for label in methods:
        same = sum(len(f & g) for f, g in zip(found[label], found[base], strict=True))
        total = sum(len(g) for g in found[base])
        rows.append(f"| {name} ({len(pairs)} pairs, {n_desc:.0f} descriptors per frame) | {label} | "
                    f"{1e3 * seconds[label] / len(pairs):.0f} ms | {seconds[label] / seconds[base]:.2f} | "
                    f"{sum(len(f) for f in found[label])} | {same / max(total, 1):.2%} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flights", nargs="+", default=["h20t_forest", "copr"])
    parser.add_argument("--pairs", type=int, default=60)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    lines = ["| flight | matcher | time per pair | ratio to the baseline | matches | of the baseline's matches |",
             "|---|---|---|---|---|---|"]
    for name in args.flights:
        lines += flight_rows(name, args.pairs)
    lines += ["", f"- peak memory {peak_rss_mb():.0f} MB; one thread (OMP_NUM_THREADS=1 for numpy's BLAS)",
              "- target: the baseline's matches, in less time than either OpenCV matcher"]
    record("Descriptor matching in one pass", lines)


if __name__ == "__main__":
    main()
