"""Shared plumbing of the benchmarks: timing, peak memory, and appending results to RESULTS.md."""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import resource
import sys
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "RESULTS.md"


def machine() -> str:
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    return (f"{platform.node()} {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC, load average {load} at the end (above 2 means "
            "other jobs shared the cores)")


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@contextmanager
def timed(rows: list, label: str):
    t0 = time.perf_counter()
    yield
    rows.append((label, time.perf_counter() - t0, peak_rss_mb()))


def best_of(fn: Callable[[], object], repeat: int = 3) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def in_fresh_process(target: Callable, *args):
    """``target(*args, queue)`` run in a spawned process (its own peak memory); returns what it put on the queue."""
    import multiprocessing as mp
    import queue as queues

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=target, args=(*args, q))
    p.start()
    while True:  # a child that fails puts nothing: say so instead of waiting for ever
        try:
            out = q.get(timeout=5.0)
            break
        except queues.Empty:
            if not p.is_alive():
                raise RuntimeError(f"{getattr(target, '__name__', target)}{args} ended with exit code {p.exitcode} "
                                   "and no result (its traceback is above)") from None
    p.join()
    return out


def load_adjustment_kernels() -> float:
    """Load the adjustment's compiled loops (numba; compiled on a fresh install, then cached on disk) with a
    fixed-IO adjustment of an 8-image flight, so that a benchmark's timing is of the adjustment; returns the
    seconds it took (a one-off per process, reported beside the timings)."""
    from aerocal.adjust import AdjustConfig, adjust_fixed_io
    from aerocal.simulate import simulate_flight

    sim = simulate_flight("conte-calibration", seed=0, max_images=8)
    t0 = time.perf_counter()
    adjust_fixed_io(sim.images, sim.observations, sim.spec.camera_true, AdjustConfig(gnss_sigma_m=(0.1, 0.1, 0.15)),
                    sim.gcps, sim.gcp_observations)
    return time.perf_counter() - t0


CITY_FRAMES = 818  # frames of conte-city


def city_spec(n: int):
    """The conte-city preset, or for ``n`` above its 818 frames the same flight plan over a larger area
    (pass ``max_images=n`` to the simulation to keep the ``n`` most compact frames)."""
    import dataclasses

    from aerocal.simulate.presets import PRESETS

    spec = PRESETS["conte-city"]
    if n <= CITY_FRAMES:
        return spec
    k = 1.2 * (n / CITY_FRAMES) ** 0.5  # strips lose frames at the area's edges: plan more, keep the n most compact
    w, h = spec.area_m
    return dataclasses.replace(spec, name=f"conte-city-{n}", area_m=(w * k, h * k))


def record(title: str, lines: list[str]) -> None:
    """Print ``lines`` and append them under ``title`` with the machine and exact command to RESULTS.md."""
    command = " ".join(getattr(sys, "orig_argv", sys.argv))
    block = [f"## {title}", "", f"- machine: {machine()}", f"- command: `{command}`", "", *lines, ""]
    print("\n".join(block))
    with RESULTS.open("a") as fh:
        fh.write("\n".join(block) + "\n")


def flight_document(folder: Path) -> dict:
    """A flight folder's ``flight.json`` with the folder's path under ``folder`` (what the match step reads)."""
    return json.loads((folder / "flight.json").read_text()) | {"folder": str(folder)}
