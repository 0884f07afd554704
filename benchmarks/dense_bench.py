"""Dense surface, measured: the rendered ``conte-city`` flight (640x480 thermal frames, GSD 0.5 m), true poses.

1. Time and peak memory of :func:`aerocal.products.dense.dense_cloud` on the N frames nearest the block centre
   (default all 818) on the pipeline's local Dask cluster of 2 single-threaded workers; baseline in the same
   run: gridding the tie points (the surface the products stood on before).
2. The dense DSM (1 GSD cells) and the tie-point DSM against the simulator's true surface: median, NMAD,
   completeness (measured cells over the cells that two and three frames see, and that two frames see with the point
   hidden from neither).

Targets (issue "A dense surface"): the dense step <= 120 s and <= 4 GB per worker on 2 cores for the 818 frames.

Run: ``python -m benchmarks.dense_bench`` (``--frames N``; ``--serial``: the dense cloud timed in this process too).
"""

from __future__ import annotations

import argparse
import functools
import resource
import time

import numpy as np

from aerocal.assess import compare_dems, view_counts
from aerocal.enhance import EnhanceConfig, grey, stretch_params
from aerocal.ingest import read_raw
from aerocal.matching.cluster import local_client
from aerocal.pipeline.config import MosaicStepConfig
from aerocal.pipeline.mosaic_step import dense_frame, forget_dense_frames
from aerocal.products.dense import DenseConfig, cell_views, dense_cloud
from aerocal.products.dsm import dsm_from_points
from aerocal.products.mosaic import frames_from_poses
from aerocal.products.terrain import dtm_from_dsm
from aerocal.simulate import simulate_flight
from aerocal.simulate.raycast import intersect_dsm
from aerocal.simulate.simulator import true_poses
from benchmarks.city_bench import CITY_FRAMES, rendered_flight
from benchmarks.common import city_spec, peak_rss_mb, record


def _worker_peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=CITY_FRAMES)
    ap.add_argument("--serial", action="store_true", help="also time the dense cloud in this process, no cluster")
    args = ap.parse_args()
    folder = rendered_flight()
    sim = simulate_flight(city_spec(CITY_FRAMES), seed=0)
    names = dict(zip(sim.images.column("image_id").to_pylist(), sim.images.column("name").to_pylist(), strict=True))
    frames = frames_from_poses(true_poses(sim), {e.image_id: e.camera for e in sim.exposures})
    centre = np.median([f.C[:2] for f in frames], axis=0)
    frames = sorted(frames, key=lambda f: float(np.hypot(*(f.C[:2] - centre))))[:args.frames]
    paths = {f.image_id: str(folder / "images" / names[f.image_id]) for f in frames}
    tie = np.asarray(sim.tie.points, dtype=float)
    ground = float(np.median(tie[:, 2]))

    t0 = time.perf_counter()
    sparse = dsm_from_points(tie, sim.crs, gsd_m=sim.trajectory.gsd_m)
    t_sparse = time.perf_counter() - t0

    ecfg = EnhanceConfig()
    params = stretch_params(list(paths.values()), percent=ecfg.percent, loader=lambda p: grey(read_raw(p)))
    load = functools.partial(dense_frame, paths=paths, params=params, config=ecfg)
    t_serial = None
    if args.serial:
        dense_cloud(frames[:4], load, tie, ground, DenseConfig())  # the compiled kernels loaded, as on the workers
        t0 = time.perf_counter()
        dense_cloud(frames, load, tie, ground, DenseConfig())
        t_serial = time.perf_counter() - t0
        forget_dense_frames()
        print(f"dense cloud in this process: {t_serial:.1f} s", flush=True)
    with local_client(n_workers=2) as client:  # the pipeline's cluster: one OpenCV thread per worker
        t0 = time.perf_counter()
        cloud = dense_cloud(frames, load, tie, ground, DenseConfig(), client)
        t_dense = time.perf_counter() - t0
        print(f"dense cloud: {t_dense:.1f} s", flush=True)
        worker_mb = max(client.run(_worker_peak_mb).values())
    t0 = time.perf_counter()
    dsm = dsm_from_points(cloud.xyz, sim.crs, gsd_m=cloud.gsd_m, config=MosaicStepConfig().dense_dsm)
    t_grid = time.perf_counter() - t0
    grid_peak_mb = peak_rss_mb()  # the product's part: the dense step and its gridding, before the comparison
    print(f"dense {t_dense:.1f} s, {len(cloud.xyz)} points; gridding {t_grid:.1f} s", flush=True)
    measured = dsm.measured()
    t0 = time.perf_counter()
    terrain = dtm_from_dsm(dsm, measured)
    t_dtm = time.perf_counter() - t0
    print(f"DTM {t_dtm:.1f} s: {terrain.note}", flush=True)
    cells_views = cell_views(cloud, dsm, measured)
    # completeness on 200,000 cells drawn at random (every cell into every frame would take longer than the step)
    rng = np.random.default_rng(0)
    flat = rng.choice(measured.size, size=min(200_000, measured.size), replace=False)
    E, N = dsm.cell_centres()
    e, n = E.ravel()[flat], N.ravel()[flat]
    X = np.stack([e, n, sim.scene.height_at(e, n)], axis=-1)
    views = view_counts(frames, X)
    unhidden = view_counts(frames, X, lambda o, d: intersect_dsm(sim.scene, o, d).t, tolerance_m=0.25 * dsm.cell_m)
    rows = [float(np.count_nonzero(measured.ravel()[flat] & (v >= k)) / max(np.count_nonzero(v >= k), 1))
            for v, k in ((views, 2), (views, 3), (unhidden, 2))]
    seen = np.zeros(measured.shape, dtype=bool)
    seen.ravel()[flat[views >= 2]] = True
    d = compare_dems(dsm, sim.scene.height_at, mask=measured & seen, selection="measured")
    checked = compare_dems(dsm, sim.scene.height_at, mask=measured & seen & (cells_views >= 3), selection="checked")
    one_pair = compare_dems(dsm, sim.scene.height_at, mask=measured & seen & (cells_views == 2), selection="one pair")
    sp = compare_dems(sparse, sim.scene.height_at, mask=np.isfinite(sparse.heights), selection="all cells")
    gsd = cloud.gsd_m
    lines = [
        f"{len(frames)} frames nearest the block centre, true poses; local Dask cluster of 2 workers.", "",
        "| what | value |", "|---|---|",
        f"| dense cloud ({cloud.stats['pairs']} pairs, {len(cloud.xyz)} points) | {t_dense:.1f} s "
        f"(target <= 120 s for 818 frames) |",
        *([f"| the same in this process, no cluster | {t_serial:.1f} s |"] if t_serial is not None else []),
        f"| peak memory | largest worker {worker_mb:.0f} MB (target <= 4096 MB); this process {grid_peak_mb:.0f} MB "
        f"through the gridding, {peak_rss_mb():.0f} MB with the comparison against the true surface (every cell) |",
        f"| gridding the dense cloud (1 GSD cells, {dsm.shape[1]} x {dsm.shape[0]}) | {t_grid:.1f} s |",
        f"| baseline: gridding the tie points ({len(tie)} points) | {t_sparse:.1f} s |",
        f"| dense DSM - true surface, measured cells (of 200,000 drawn) | median {d.median:.3f} m, NMAD {d.nmad:.3f} m "
        f"({d.nmad / gsd:.2f} GSD), n {d.n} |",
        f"| the same, cells three views or more checked / cells of one pair (views band 3 / 2) | NMAD "
        f"{checked.nmad / gsd:.2f} GSD, n {checked.n} / NMAD {one_pair.nmad / gsd:.2f} GSD, n {one_pair.n} |",
        f"| dense DSM completeness | {rows[0]:.1%} of the cells two frames see, {rows[1]:.1%} of those three see, "
        f"{rows[2]:.1%} of those two frames see with the point hidden from neither |",
        f"| DTM from the dense DSM ({terrain.note}) | {t_dtm:.1f} s |",
        f"| tie-point DSM - true surface, all cells | median {sp.median:.3f} m, NMAD {sp.nmad:.3f} m "
        f"({sp.nmad / gsd:.2f} GSD), n {sp.n} |",
    ]
    record("Dense surface: rendered conte-city", lines)


if __name__ == "__main__":
    main()
