"""Where a flight's products step spends its time and memory: the flight processed end to end
(:func:`aerocal.pipeline.process`, self-calibrated, a local Dask cluster where the step uses one), the parts of the
products step (dense cloud, its gridding, the LAZ, the filling, the DTM, the DSM files, the comparison with the
reference surface, the orthomosaic) timed, with this process's resident memory before, at the peak within and
after each part, and the largest Dask worker's.

A profile, not a target: the memory says which part holds the peak. Each part's span (from its first call's start to
its last call's end, seconds after the first part started) shows which parts ran side by side: the step writes the
LAZ while it fills the DSM's holes and goes on, and the DSMs' files and differences while it filters the DTM and
rectifies the orthomosaic. Parts that ran side by side overlap in time, and their memory columns come from one
sampler, so read their peaks together.

Run: ``python -m benchmarks.products_profile FOLDER`` (the rendered city: ``benchmarks/data/conte-city-images-s0``,
made by ``python -m benchmarks.city_bench``).
"""

from __future__ import annotations

import argparse
import functools
import resource
import tempfile
import threading
import time
from pathlib import Path

import aerocal.pipeline.mosaic_step as mosaic_step
import aerocal.products.dense as dense
from benchmarks.common import record

#: the parts of the products step, by the name the mosaic step (or the dense cloud) calls them
PARTS = {
    mosaic_step: ("dense_cloud", "cells_from_points", "own_views", "write_laz", "filled", "views_of_cells",
                  "dtm_from_dsm", "write_dsm", "difference_to", "build_mosaic", "dsm_from_points",
                  "temperature_output"),
    dense: ("_gathered", "confirmed", "_kept"),
}


class Memory:
    """This process's resident memory and its children's largest, sampled every 50 ms in a thread."""

    def __init__(self) -> None:
        import psutil

        self._me = psutil.Process()
        self.peak = self.now()
        self.workers_peak = 0.0
        threading.Thread(target=self._sample, daemon=True).start()

    def now(self) -> float:
        return self._me.memory_info().rss / 2**20

    def _sample(self) -> None:
        k = 0
        while True:
            self.peak = max(self.peak, self.now())
            k += 1
            if k % 10 == 0:  # the workers twice a second
                try:
                    kids = [c.memory_info().rss / 2**20 for c in self._me.children(recursive=True)]
                except Exception:  # a worker that ended between the listing and the reading
                    kids = []
                self.workers_peak = max([self.workers_peak, *kids])
            time.sleep(0.05)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="a flight folder with images/")
    args = ap.parse_args(argv)
    memory = Memory()
    rows: list[list] = []  # [part, calls, seconds, before, peak, after, first start, last end] as first called
    index: dict[str, list] = {}
    origin: list[float] = []  # when the first part started

    def wrap(module, name: str) -> None:
        fn = getattr(module, name)

        @functools.wraps(fn)
        def timed(*a, **k):
            outer_peak = memory.peak
            before = memory.peak = memory.now()
            t0 = time.perf_counter()
            if not origin:
                origin.append(t0)
            try:
                return fn(*a, **k)
            finally:
                end = time.perf_counter()
                seconds, peak = end - t0, memory.peak
                row = index.get(name)
                if row is None:
                    row = index[name] = [name, 0, 0.0, before, 0.0, 0.0, t0 - origin[0], 0.0]
                    rows.append(row)
                row[7] = end - origin[0]
                row[1] += 1
                row[2] += seconds
                row[4] = max(row[4], peak)
                row[5] = memory.now()
                memory.peak = max(outer_peak, peak)  # a part inside another keeps the outer one's peak

        setattr(module, name, timed)

    for module, names in PARTS.items():
        for name in names:
            wrap(module, name)

    from aerocal.matching.cluster import ExecutionConfig
    from aerocal.pipeline import process

    with tempfile.TemporaryDirectory(prefix="products-profile-") as out:
        t0 = time.perf_counter()
        run = process(args.folder, certificate="none", out_dir=Path(out) / "run", execution=ExecutionConfig(None))
        total = time.perf_counter() - t0
        mosaic = run.json("mosaic")
    steps = ", ".join(f"{k} {v.seconds:.1f} s" for k, v in run.summary.steps.items() if v.seconds)
    dense_doc = mosaic.get("dense") or {}
    lines = [
        f"flight {args.folder.name}: whole run {total:.1f} s ({steps})",
        f"dense cloud: {dense_doc.get('points', 0):,} points in {dense_doc.get('pairs', 0)} pairs of "
        f"{dense_doc.get('frames', 0)} frames; DSM {mosaic.get('dsm_shape')} cells",
        "",
        "| part of the products step | calls | seconds | span (s after the first part's start) | memory before | "
        "peak within | after |",
        "|---|---|---|---|---|---|---|",
        *[f"| {name} | {calls} | {seconds:.1f} | {first:.1f}-{last:.1f} | {before:.0f} MB | {peak:.0f} MB | "
          f"{after:.0f} MB |" for name, calls, seconds, before, peak, after, first, last in rows],
        "",
        f"- peak memory: this process {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB, the "
        f"largest Dask worker {memory.workers_peak:.0f} MB",
        "- the dense cloud's parts (`_gathered`, `confirmed`, `_kept`) run inside `dense_cloud`; the rest of "
        "`dense_cloud` is the pairs' matching (on the Dask workers where a cluster runs it)",
    ]
    record("Products step, part by part", lines)


if __name__ == "__main__":
    main()
