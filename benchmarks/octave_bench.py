"""SIFT on visible frames from octave 0 against OpenCV's upsampled octave -1: detection time and verified matches.

Baseline measured in the same run: the same frames detected as OpenCV does, the octave -1 it upsamples searched
too (the default for frames of these sizes). Both settings keep the default cap of 8000
keypoints. Pairs are each frame with the next two in capture order, verified as ``aerocal process`` verifies
them (fundamental matrix, MAGSAC++, 1 px).

    python -m benchmarks.octave_bench [--flights seneca copr] [--frames 12]

Read with: what a pair's verified inliers and their Sampson RMS say of the tie points the adjustment gets.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from aerocal.ingest import ingest_folder
from aerocal.matching import FeatureConfig, MatchConfig
from aerocal.matching.features import detect
from aerocal.matching.verify import match_descriptors, verify
from aerocal.pipeline.match_step import frame_loader
from benchmarks.common import peak_rss_mb, record

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FOLDERS = {"seneca": DATA / "seneca" / "images", "copr": DATA / "copr"}


def flight_rows(name: str, n_frames: int) -> list[str]:
    images = ingest_folder(FOLDERS[name]).images
    order = np.argsort(images.column("name").to_pylist())[:n_frames]
    loader = frame_loader(images.column("path").to_pylist())
    frames = [loader(images.column("path")[int(k)].as_py()) for k in order]
    settings = {"octave -1 (OpenCV's and the default below 12 MP, baseline)": FeatureConfig(),
                "octave 0": FeatureConfig(fine_octave_max_pixels=0)}
    rows, base = [], None
    for label, config in settings.items():
        t0 = time.perf_counter()
        feats = [detect(f, config) for f in frames]
        seconds = (time.perf_counter() - t0) / len(frames)
        inliers, rms = [], []
        for i in range(len(frames)):
            for j in (i + 1, i + 2):
                if j >= len(frames):
                    continue
                m = match_descriptors(feats[i][1], feats[j][1], MatchConfig())
                if len(m) < MatchConfig().min_matches:
                    inliers.append(0)
                    continue
                ok, _, r = verify(feats[i][0][m[:, 0], :2].astype(float), feats[j][0][m[:, 1], :2].astype(float))
                inliers.append(int(ok.sum()))
                if np.isfinite(r):
                    rms.append(r)
        base = base or (seconds, sum(inliers))
        rows.append(f"| {name} ({len(frames)} frames of {frames[0].shape[1]} x {frames[0].shape[0]}) | {label} | "
                    f"{seconds:.2f} s ({seconds / base[0]:.2f}) | {np.mean([len(f[0]) for f in feats]):.0f} | "
                    f"{sum(inliers)} ({sum(inliers) / max(base[1], 1):.2f}) in {len(inliers)} pairs | "
                    f"{np.median(rms):.3f} px |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flights", nargs="+", default=["seneca", "copr"])
    parser.add_argument("--frames", type=int, default=12)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    lines = ["| flight | detected from | detection per frame (ratio) | keypoints per frame | verified inliers "
             "(ratio) | median Sampson RMS of a pair's inliers |", "|---|---|---|---|---|---|"]
    for name in args.flights:
        lines += flight_rows(name, args.frames)
    lines += ["", f"- peak memory {peak_rss_mb():.0f} MB; one thread"]
    record("SIFT from octave 0 on visible frames", lines)


if __name__ == "__main__":
    main()
