"""How the adjustment's cost grows with the block: 800, 3200 and 12,800 images (observations mode).

The conte-city flight plan over a larger area, ``max_images`` frames of it (the most compact set). Each
block is simulated once in a process of its own and kept as Parquet under ``--work`` (a 12,509-image
simulation peaked at 7.4 GB), then adjusted in a fresh process that reads the tables, IO fixed (the
production case) and, up to ``--self-cal-max`` images, self-calibrating (f, cx, cy, k1, k2, k3, p1, p2),
so that each peak memory is the adjustment's own.

Run: ``python -m benchmarks.adjust_scaling_bench [--sizes 800,3200,12800,25600] [--repeat 3] [--work DIR]``. This is
the single adjustment in one process (~0.6 kB per observation: 25,600 images, 12.4 M observations, took
7.2 GB with the tables); simulating the 25,600-image block once takes ~10 min and peaks at 16.6 GB. The partitioned
adjustment (``benchmarks/partition_bench.py``) spreads the observations over the Dask workers.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import city_spec, in_fresh_process, load_adjustment_kernels, peak_rss_mb, record

TABLES = ("images", "observations", "gcps", "gcp_observations")
TARGET_SECONDS, TARGET_MB, TARGET_EXPONENT = 300.0, 6144.0, 1.15  # 12,800 images, IO fixed; growth


def _simulate(n: int, folder: str, queue) -> None:
    import pyarrow.parquet as pq

    from aerocal.simulate import simulate_flight

    t0 = time.perf_counter()
    sim = simulate_flight(city_spec(n), seed=0, max_images=n)
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    for name in TABLES:
        pq.write_table(getattr(sim, name), out / f"{name}.parquet")
    (out / "done.json").write_text(json.dumps({"images": sim.images.num_rows, "seconds": time.perf_counter() - t0,
                                               "peak_mb": peak_rss_mb()}))
    queue.put(None)


def _adjust(folder: str, mode: str, queue) -> None:
    import pyarrow.parquet as pq

    from aerocal.adjust import AdjustConfig, adjust, adjust_fixed_io
    from aerocal.simulate.presets import PRESETS

    t = {name: pq.read_table(Path(folder) / f"{name}.parquet") for name in TABLES}
    spec = PRESETS["conte-city"]
    s = spec.sensors
    cfg = AdjustConfig(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m))
    load_adjustment_kernels()
    before = peak_rss_mb()
    t0 = time.perf_counter()
    if mode == "fixed":
        res = adjust_fixed_io(t["images"], t["observations"], spec.camera_true, cfg, t["gcps"], t["gcp_observations"])
    else:
        res = adjust(t["images"], t["observations"], spec.camera_nominal, cfg, t["gcps"], t["gcp_observations"])
    queue.put({"images": t["images"].num_rows, "observations": t["observations"].num_rows,
               "seconds": time.perf_counter() - t0, "iterations": res.iterations, "sigma0": res.sigma0,
               "peak_mb": peak_rss_mb(), "tables_mb": before})


def add_work_argument(ap: argparse.ArgumentParser) -> None:
    """``--work``: where the simulated blocks are kept, shared by the adjustment benchmarks."""
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "aerocal-adjust-scaling",
                    help="where the simulated blocks are kept (reused by later runs of every adjustment benchmark)")


def block(n: int, work: Path) -> Path:
    """The simulated n-image block's folder under ``work``, simulated first if it is not there."""
    folder = work / f"conte-city-{n}"
    if not (folder / "done.json").exists():
        print(f"simulating {n} images into {folder} ...", flush=True)
        in_fresh_process(_simulate, n, str(folder))
    return folder


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="800,3200,12800,25600", help="block sizes (images), comma-separated")
    ap.add_argument("--self-cal-max", type=int, default=3200, help="self-calibrate blocks up to this size")
    ap.add_argument("--repeat", type=int, default=1,
                    help="fixed-IO runs per size, each in a fresh process; the median time is reported (this VM's "
                         "run-to-run spread is 10-20 %%, and the growth exponent rests on the smallest block's time)")
    add_work_argument(ap)
    args = ap.parse_args(argv)
    sizes = [int(v) for v in args.sizes.split(",")]
    lines = ["| images | observations | IO fixed | iterations | peak memory (tables alone) | self-calibrating | "
             "iterations | peak memory |", "|---|---|---|---|---|---|---|---|"]
    fixed = []
    for n in sizes:
        folder = block(n, args.work)
        runs = [in_fresh_process(_adjust, str(folder), "fixed") for _ in range(max(1, args.repeat))]
        times = sorted(r["seconds"] for r in runs)
        fx = dict(runs[0], seconds=float(np.median(times)), peak_mb=max(r["peak_mb"] for r in runs))
        fixed.append(fx)
        sc = in_fresh_process(_adjust, str(folder), "self") if n <= args.self_cal_max else None
        selfcal = (f"{sc['seconds']:.1f} s | {sc['iterations']} | {sc['peak_mb']:.0f} MB" if sc
                   else "not run | | ")
        spread = f" ({', '.join(f'{t:.1f}' for t in times)})" if len(times) > 1 else ""
        lines.append(f"| {fx['images']} | {fx['observations']} | {fx['seconds']:.1f} s{spread} | {fx['iterations']} | "
                     f"{fx['peak_mb']:.0f} MB ({fx['tables_mb']:.0f} MB) | {selfcal} |")
        print(lines[-1], flush=True)
    lines.append("")
    for a, b in zip(fixed, fixed[1:], strict=False):
        e = math.log(b["seconds"] / a["seconds"]) / math.log(b["images"] / a["images"])
        lines.append(f"- fixed-IO time grows as images^{e:.2f} from {a['images']} to {b['images']} images")
    if len(fixed) >= 2:
        a, b = fixed[0], fixed[-1]
        e = math.log(b["seconds"] / a["seconds"]) / math.log(b["images"] / a["images"])
        lines.append(f"- overall images^{e:.2f} from {a['images']} to {b['images']} (target <= images^"
                     f"{TARGET_EXPONENT}): {'met' if e <= TARGET_EXPONENT else 'not met'}")
    big = [fx for fx in fixed if 12000 <= fx["images"] <= 13600]
    if big:
        fx = big[0]
        ok = fx["seconds"] <= TARGET_SECONDS and fx["peak_mb"] <= TARGET_MB
        lines.append(f"- target, {fx['images']} images IO fixed in <= {TARGET_SECONDS / 60:.0f} min and <= "
                     f"{TARGET_MB / 1024:.0f} GB: {'met' if ok else 'not met'} ({fx['seconds']:.0f} s, "
                     f"{fx['peak_mb']:.0f} MB)")
    record("Adjustment scaling, observations mode (conte-city plan)", lines)


if __name__ == "__main__":
    main()
