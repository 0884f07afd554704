"""Pairs without GNSS: the pairs a coarse match retrieves against matching every pair, on real flights.

Baseline measured in the same run: every pair matched in full (what a flight without position records had before
retrieval). For each flight: detection once, then the exhaustive match, the coarse match
(:func:`aerocal.matching.retrieval.retrieve_pairs`, default settings) and the full match of the pairs it keeps;
what the retrieved pairs lose is read against the exhaustive match's verified pairs.

    python -m benchmarks.retrieval_bench [--flights copr h20t_forest]

Target: the retrieved pairs keep >= 98 % of the exhaustive match's verified inliers, in at most half its time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from aerocal.ingest import ingest_folder
from aerocal.matching import FeatureConfig, MatchConfig, exhaustive_pairs, extract_features, match_pairs_detailed
from aerocal.matching.cluster import local_client
from aerocal.matching.retrieval import RetrievalConfig, retrieve_pairs
from aerocal.pipeline.match_step import capture_order, frame_loader
from benchmarks.common import peak_rss_mb, record

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def flight_rows(name: str) -> list[str]:
    images = ingest_folder(DATA / name).images
    loader = frame_loader(images.column("path").to_pylist())
    with local_client(2) as client:
        t0 = time.perf_counter()
        kp = extract_features(images, loader, FeatureConfig(), client)
        t1 = time.perf_counter()
        every = exhaustive_pairs(images.column("image_id").to_numpy())
        full = match_pairs_detailed(every, kp, MatchConfig(), client).pair_stats
        t2 = time.perf_counter()
        got = retrieve_pairs(kp, capture_order(images), RetrievalConfig())
        t3 = time.perf_counter()
        match_pairs_detailed(got.pairs, kp, MatchConfig(), client)
        t4 = time.perf_counter()
    a, b = full.column("image_id1").to_numpy(), full.column("image_id2").to_numpy()
    inliers, verified = full.column("n_inliers").to_numpy(), full.column("verified").to_numpy()
    kept = {(int(i), int(j)) for i, j in got.pairs}
    keep = np.array([(int(i), int(j)) in kept for i, j in zip(a, b, strict=True)])
    lost = verified & ~keep
    share = inliers[verified & keep].sum() / max(inliers[verified].sum(), 1)
    largest = ", ".join(str(int(v)) for v in sorted(inliers[lost])[-5:]) or "-"
    exhaustive_s, retrieved_s = t2 - t1, (t3 - t2) + (t4 - t3)
    met = share >= 0.98 and retrieved_s <= 0.5 * exhaustive_s
    return [
        f"| {name} ({images.num_rows} frames) | {t1 - t0:.1f} s | {len(every)} pairs, {verified.sum()} verified: "
        f"{exhaustive_s:.1f} s | {t3 - t2:.1f} s + {len(got.pairs)} pairs: {t4 - t3:.1f} s | "
        f"{retrieved_s / exhaustive_s:.2f} | {lost.sum()} (inliers {largest}) | "
        f"{share:.2%} | {'met' if met else 'not met'} |",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flights", nargs="+", default=["copr", "h20t_forest"])
    args = parser.parse_args()
    lines = ["| flight | detection | exhaustive match (baseline) | coarse match + retrieved pairs | time ratio | "
             "verified pairs lost (largest inlier counts) | verified inliers kept | target |",
             "|---|---|---|---|---|---|---|---|"]
    for name in args.flights:
        lines += flight_rows(name)
    lines += ["", f"- peak memory {peak_rss_mb():.0f} MB (this process; the Dask workers apart)",
              f"- settings: {RetrievalConfig()}",
              "- target: >= 98 % of the verified inliers in at most half the exhaustive match's time"]
    record("Pairs without GNSS: a coarse match's pairs against every pair (real frames)", lines)


if __name__ == "__main__":
    main()
