"""How the adjustment's cost grows with the block: 50, 200, 800 and 3200 images (observations mode).

``conte-city`` (818 frames) gives the 50- and 200-image blocks (the frames nearest the centre) and the
800-image block; the 3200-image block is the same flight plan over four times the area. Each block is
adjusted twice, IO fixed (the production case) and self-calibrating (f, cx, cy, k1, k2, k3, p1, p2), each
in a fresh process so that its peak memory is its own.

Run: ``python -m benchmarks.adjust_scaling_bench [--sizes 50,200,800,3200]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import multiprocessing as mp
import resource
import time

from aerocal.adjust import AdjustConfig, adjust, adjust_fixed_io
from aerocal.simulate import simulate_flight
from aerocal.simulate.presets import PRESETS
from benchmarks.common import record

FULL = 818  # frames of conte-city


def _spec(n: int):
    spec = PRESETS["conte-city"]
    if n <= FULL:
        return spec, (n if n < FULL else None)
    k = (n / FULL) ** 0.5
    w, h = spec.area_m
    return dataclasses.replace(spec, name=f"conte-city-x{n / FULL:.0f}", area_m=(w * k, h * k)), None


def _case(n: int, mode: str, queue) -> None:
    spec, max_images = _spec(n)
    sim = simulate_flight(spec, seed=0, max_images=max_images)
    s = sim.spec.sensors
    cfg = AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m))
    t0 = time.perf_counter()
    if mode == "fixed":
        res = adjust_fixed_io(sim.images, sim.observations, sim.spec.camera_true, cfg, sim.gcps, sim.gcp_observations)
    else:
        res = adjust(sim.images, sim.observations, sim.camera_nominal, cfg, sim.gcps, sim.gcp_observations)
    secs = time.perf_counter() - t0
    queue.put({"images": sim.images.num_rows, "observations": sim.observations.num_rows, "seconds": secs,
               "iterations": res.iterations, "sigma0": res.sigma0,
               "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0})


def run_case(n: int, mode: str) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=_case, args=(n, mode, q))
    p.start()
    out = q.get()
    p.join()
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="50,200,800,3200", help="block sizes (images), comma-separated")
    args = ap.parse_args(argv)
    sizes = [int(v) for v in args.sizes.split(",")]
    lines = ["| images | observations | IO fixed | iterations | peak memory | self-calibrating | iterations | "
             "peak memory | ratio fixed / self-cal |", "|---|---|---|---|---|---|---|---|---|"]
    rows = []
    for n in sizes:
        fx, sc = run_case(n, "fixed"), run_case(n, "self")
        rows.append((fx, sc))
        lines.append(f"| {fx['images']} | {fx['observations']} | {fx['seconds']:.1f} s | {fx['iterations']} | "
                     f"{fx['peak_mb']:.0f} MB | {sc['seconds']:.1f} s | {sc['iterations']} | {sc['peak_mb']:.0f} MB | "
                     f"{fx['seconds'] / sc['seconds']:.2f} |")
        print(lines[-1], flush=True)
    if len(rows) >= 2:
        (a, _), (b, _) = rows[0], rows[-1]

        expo = math.log(b["seconds"] / a["seconds"]) / math.log(b["images"] / a["images"])
        lines += ["", f"- fixed-IO time grows as images^{expo:.2f} from {a['images']} to {b['images']} images"]
    eight = [fx for fx, _ in rows if 700 < fx["images"] < 900]
    if eight:
        lines.append(f"- target: the ~800-image fixed-IO adjustment in < 30 s: "
                     f"{'met' if eight[0]['seconds'] < 30 else 'not met'} ({eight[0]['seconds']:.1f} s)")
    record("Adjustment scaling, observations mode (conte-city plan)", lines)


if __name__ == "__main__":
    main()
