"""The partitioned adjustment against the single one on the same block (observations mode, IO fixed).

The blocks of :mod:`benchmarks.adjust_scaling_bench` (conte-city plan, simulated once and kept as Parquet).
Each run is a fresh process: the single adjustment (:func:`aerocal.adjust.solver.solve`), then the
partitioned one (:mod:`aerocal.adjust.partition`) in 2, 4, ... sub-blocks held by the workers of a local
2-worker Dask cluster, or with ``--processes N`` by a cluster of separate processes (a ``dask scheduler`` and
N ``dask worker`` processes, :mod:`benchmarks.process_cluster`). Printed: time (the cluster's start apart),
peak memory of the caller's process and of the largest worker, and the largest differences of poses and check
points between the two solutions.

Run: ``python -m benchmarks.partition_bench [--sizes 800,3200] [--parts 2,4] [--processes 4] [--work DIR]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

from benchmarks.adjust_scaling_bench import TABLES, add_work_argument, block
from benchmarks.common import in_fresh_process, load_adjustment_kernels, peak_rss_mb, record
from benchmarks.process_cluster import process_cluster


def _adjust(folder: str, parts: int, processes: int, queue) -> None:
    import numpy as np
    import pyarrow.parquet as pq

    from aerocal.adjust import AdjustConfig, adjust_fixed_io
    from aerocal.adjust.partition import PartitionedSolver
    from aerocal.simulate.presets import PRESETS

    t = {name: pq.read_table(Path(folder) / f"{name}.parquet") for name in TABLES}
    spec = PRESETS["conte-city"]
    s = spec.sensors
    cfg = AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m))
    n = t["images"].num_rows

    def run(solver=None) -> tuple:
        t0 = time.perf_counter()
        res = adjust_fixed_io(t["images"], t["observations"], spec.camera_true, cfg, t["gcps"],
                              t["gcp_observations"], solver=solver)
        xyz = np.column_stack([res.poses.column(c).to_numpy() for c in ("X", "Y", "Z")])
        return time.perf_counter() - t0, res, xyz

    out = {"images": n, "observations": t["observations"].num_rows, "parts": parts}
    load_adjustment_kernels()
    if parts <= 1:
        seconds, res, xyz = run()
        out.update(seconds=seconds, peak_mb=peak_rss_mb(), worker_mb=0.0, start_s=0.0)
    else:
        t0 = time.perf_counter()
        with _cluster(processes) as client:
            client.run(load_adjustment_kernels)
            start = time.perf_counter() - t0
            workers = len(client.scheduler_info()["workers"])
            solver = PartitionedSolver(min_images=1, max_images=-(-n // parts), n_workers=workers, client=client)
            seconds, res, xyz = run(solver)
            worker = max(client.run(peak_rss_mb).values())
            out.update(seconds=seconds, peak_mb=peak_rss_mb(), worker_mb=worker, start_s=start,
                       boundary=solver.runs[-1]["boundary_images"], workers=workers)
    out.update(iterations=res.iterations, sigma0=res.sigma0, xyz=xyz, check=np.asarray(res.check_errors, float))
    queue.put(out)


@contextmanager
def _cluster(processes: int):
    """A client of the product's local 2-worker cluster (``processes`` 0) or of ``processes`` separate worker
    processes."""
    from distributed import Client

    from aerocal.matching.cluster import local_client

    if processes <= 0:
        with local_client(n_workers=2) as client:
            yield client
        return
    with tempfile.TemporaryDirectory(prefix="aerocal-cluster-") as work, \
            process_cluster(Path(work), n_workers=processes) as running, Client(running.address) as client:
        yield client


def main(argv: list[str] | None = None) -> None:
    import numpy as np

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="800,3200", help="block sizes (images), comma-separated")
    ap.add_argument("--parts", default="2,4", help="sub-block counts, comma-separated")
    ap.add_argument("--single-max", type=int, default=3200,
                    help="run the single adjustment (and the differences) up to this size; beyond, see "
                         "adjust_scaling_bench")
    ap.add_argument("--processes", type=int, default=0,
                    help="run the sub-blocks on a cluster of this many separate worker processes (default: the "
                         "product's local 2-worker cluster)")
    add_work_argument(ap)
    args = ap.parse_args(argv)
    lines = ["| images | observations | solve | sub-blocks (boundary images) | time | ratio to single | "
             "peak memory caller / largest worker | max pose difference | max check-point difference |",
             "|---|---|---|---|---|---|---|---|---|"]
    for n in (int(v) for v in args.sizes.split(",")):
        folder = str(block(n, args.work))
        single = in_fresh_process(_adjust, folder, 1, 0) if n <= args.single_max else None
        if single is not None:
            lines.append(f"| {single['images']} | {single['observations']} | single | - | {single['seconds']:.1f} s "
                         f"({single['iterations']} it.) | 1.00 | {single['peak_mb']:.0f} MB | - | - |")
            print(lines[-1], flush=True)
        for k in (int(v) for v in args.parts.split(",")):
            p = in_fresh_process(_adjust, folder, k, args.processes)
            if single is not None:
                dpos = f"{float(np.abs(p['xyz'] - single['xyz']).max()):.1e} m"
                ok = np.isfinite(single["check"])
                dchk = f"{float(np.abs(p['check'][ok] - single['check'][ok]).max()):.1e} m" if ok.any() else "-"
                ratio = f"{p['seconds'] / single['seconds']:.2f}"
            else:
                dpos = dchk = ratio = "single not run"
            kind = (f"{p['workers']} worker processes" if args.processes > 0 else "2 local Dask workers")
            lines.append(f"| {p['images']} | {p['observations']} | partitioned, {kind} "
                         f"(+{p['start_s']:.1f} s cluster start and kernel load) | {k} ({p['boundary']}) | "
                         f"{p['seconds']:.1f} s ({p['iterations']} it.) | "
                         f"{ratio} | {p['peak_mb']:.0f} / {p['worker_mb']:.0f} MB | {dpos} | {dchk} |")
            print(lines[-1], flush=True)
    record("Partitioned adjustment against the single one (conte-city plan, IO fixed)", lines)


if __name__ == "__main__":
    main()
