"""Orthomosaic of large visible frames on a Dask cluster, against the decode-and-resample limit of the same frames.

Frames: the shared seneca JPEGs (1620 x 1215) enlarged to ``--scale`` times their size (2.2: 3564 x 2673, about
the 3600 x 2700 of seneca's full-resolution original) and written as JPEG (quality 92), so that decoding one costs
what a survey camera's frame costs. Geometry: a nadir block of ``--strips`` x ``--per-strip`` frames over a flat
surface, 75 % forward and 60 % side overlap, the output at the frames' ground sampling distance (3 cm).

Baseline measured in the same run, the limit of any orthomosaic of these frames on these cores: each frame decoded
once, and an output the size of its footprint resampled from it once (``cv2.remap``, bilinear), one task per frame,
measured the way each mosaic then runs: on ``--workers`` threads of this process (the product's path without a
Dask scheduler) and as tasks on a local Dask cluster of as many workers (the path of a run given a scheduler). Two
workers on two cores need not run twice as fast as one: the limit is measured, not divided; the run prints the
speed-up. Each mosaic's time is printed as a ratio against its own limit, and the same mosaic on one thread beside.

    python -m benchmarks.mosaic_bench [--scale 2.2] [--strips 5] [--per-strip 8] [--workers 2]

Target: the mosaic within 3x of the decode-and-resample limit.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from aerocal.camera import Camera
from aerocal.matching.cluster import local_client
from aerocal.products.dsm import Dsm
from aerocal.products.mosaic import FrameGeometry, MosaicConfig, build_mosaic, read_frame
from benchmarks.common import peak_rss_mb, record

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
#: world-to-camera rotation of a nadir frame: x east, y south, z down
NADIR = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
GSD_M = 0.03
HEIGHT_M = 100.0


def write_frames(out: Path, scale: float, n: int) -> list[Path]:
    """``n`` seneca JPEGs resized to ``scale`` times 1620 x 1215 (most of them are that size), written as JPEG
    to ``out``."""
    size = (round(1620 * scale), round(1215 * scale))
    sources = sorted((DATA / "seneca" / "images").glob("*.[jJ][pP][gG]"))
    paths = []
    for k in range(n):
        img = cv2.imread(str(sources[k % len(sources)]))
        big = cv2.resize(img, size, interpolation=cv2.INTER_CUBIC)
        path = out / f"frame_{k:03d}.jpg"
        cv2.imwrite(str(path), big, [cv2.IMWRITE_JPEG_QUALITY, 92])
        paths.append(path)
    return paths


def nadir_block(camera: Camera, strips: int, per_strip: int) -> list[FrameGeometry]:
    """A nadir block at ``HEIGHT_M`` above the ground: 75 % forward, 60 % side overlap."""
    along = 0.25 * camera.height * GSD_M
    across = 0.40 * camera.width * GSD_M
    frames = []
    for s in range(strips):
        for k in range(per_strip):
            C = np.array([s * across, k * along, HEIGHT_M])
            frames.append(FrameGeometry(image_id=len(frames), camera=camera, R_cw=NADIR, C=C))
    return frames


def decode_and_resample(path: Path, width: int, height: int, seed: int) -> tuple[float, float]:
    """Seconds to decode one frame, and to resample an output the size of its footprint from it (bilinear, at
    positions a fraction of a pixel off its grid)."""
    t0 = time.perf_counter()
    img = read_frame(path)
    t1 = time.perf_counter()
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    u += rng.random(dtype=np.float32)
    v += rng.random(dtype=np.float32)
    t2 = time.perf_counter()
    cv2.remap(img, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return t1 - t0, time.perf_counter() - t2


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=2.2)
    parser.add_argument("--strips", type=int, default=5)
    parser.add_argument("--per-strip", type=int, default=8)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="mosaic-bench-") as tmp:
        work = Path(tmp)
        paths = write_frames(work, args.scale, args.strips * args.per_strip)
        h, w = read_frame(paths[0]).shape[:2]
        camera = Camera(width=w, height=h, f=HEIGHT_M / GSD_M, cx=w / 2, cy=h / 2)
        frames = nadir_block(camera, args.strips, args.per_strip)
        E = np.array([f.C[0] for f in frames])
        N = np.array([f.C[1] for f in frames])
        cell = 1.0
        west, north = E.min() - w * GSD_M, N.max() + h * GSD_M
        rows = int((north - (N.min() - h * GSD_M)) / cell) + 1
        cols = int((E.max() + w * GSD_M - west) / cell) + 1
        dsm = Dsm(heights=np.zeros((rows, cols), np.float32), west=west, north=north, cell_m=cell,
                  crs="EPSG:32618", distance_m=np.zeros((rows, cols), np.float32))
        n = len(paths)
        # the product's path without a scheduler: the limit and the mosaic on threads of this process
        opencv_threads = cv2.getNumThreads()
        cv2.setNumThreads(1)  # one OpenCV thread per task, as the mosaic's tiles run
        t0 = time.perf_counter()
        with concurrent.futures.ThreadPoolExecutor(args.workers) as pool:
            list(pool.map(decode_and_resample, paths, [w] * n, [h] * n, range(n)))
        thread_limit = time.perf_counter() - t0
        cv2.setNumThreads(opencv_threads)
        t0 = time.perf_counter()
        build_mosaic(frames, dict(enumerate(paths)), dsm, work / "ortho_threads.tif", MosaicConfig(gsd_m=GSD_M),
                     threads=args.workers)
        threads_s = time.perf_counter() - t0
        with local_client(args.workers) as client:
            # the limit, on the same workers: every frame decoded once and resampled once, one task per frame
            client.run(cv2.setNumThreads, 1)
            t0 = time.perf_counter()
            parts = client.gather(client.map(decode_and_resample, paths, [w] * n, [h] * n, range(n)))
            limit = time.perf_counter() - t0
            decode_s, resample_s = (float(sum(p[k] for p in parts)) for k in (0, 1))
            t0 = time.perf_counter()
            result = build_mosaic(frames, dict(enumerate(paths)), dsm, work / "ortho.tif",
                                  MosaicConfig(gsd_m=GSD_M), client=client)
            mosaic_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        build_mosaic(frames, dict(enumerate(paths)), dsm, work / "ortho_serial.tif", MosaicConfig(gsd_m=GSD_M))
        serial_s = time.perf_counter() - t0
    ratio = mosaic_s / limit
    thread_ratio = threads_s / thread_limit
    lines = [
        "| frames | output | decode once / resample once (summed over the tasks) | path | limit: the same tasks "
        "run the same way (baseline) | mosaic | ratio | target |",
        "|---|---|---|---|---|---|---|---|",
        f"| {len(frames)} of {w} x {h} (seneca x {args.scale:g}, JPEG) | {result.width} x {result.height} px, "
        f"{result.tiles} tiles | {decode_s:.1f} s / {resample_s:.1f} s | {args.workers} threads in this process "
        f"(without a scheduler) | {thread_limit:.1f} s | {threads_s:.1f} s | {thread_ratio:.2f} | <= 3: "
        f"{'met' if thread_ratio <= 3 else 'not met'} |",
        f"| | | | a local Dask cluster of {args.workers} workers (a run given a scheduler) | {limit:.1f} s | "
        f"{mosaic_s:.1f} s | {ratio:.2f} | <= 3: {'met' if ratio <= 3 else 'not met'} |",
        "",
        f"- the same mosaic on one thread: {serial_s:.1f} s",
        f"- the limit's tasks summed {decode_s + resample_s:.1f} s in {limit:.1f} s of wall time on {args.workers} "
        f"workers: {(decode_s + resample_s) / limit:.2f}x one core; {thread_limit:.1f} s on {args.workers} threads",
        f"- peak memory {peak_rss_mb():.0f} MB (this process; the Dask workers apart)",
    ]
    record("Orthomosaic of large visible frames against the decode-and-resample limit", lines)


if __name__ == "__main__":
    main()
