"""Every effect of the catalogue hidden in rendered frames, and effect-free rendered flights: what the product names.

Each flight is ``conte-calibration`` in a wind of (9, 4) m/s, 16 central frames (12 for the effect-free ones, as in
``tests/test_rendered_discovery.py``), ray-cast through the true camera with the effect acting on the pixels or on
the recorded GNSS/IMU, written as files and processed by :func:`aerocal.pipeline.process` from the folder with the
product's own calibration. Effects a self-calibration on the same frames absorbs (a boresight about the camera's x
and y axes) use the certificate of an effect-free flight of the camera. Thermal effects are hidden in a flight whose
camera warms from 10 to ~23 degC. Sizes are those a user meets: 0.1-0.3 % of f for image terms, tenths of a second
and of a metre for the recorded EO.

Not swept here, with the reason: ``refraction`` (0.36 px at the corners of a 17,000-pixel UltraCam frame at 1,000 m:
nothing at 640 px and 300 m; tests/test_model_loop.py finds it in observations) and ``lever_arm`` (a 5 cm arm is
tested on the 40-image daakir-uav corridor in observations; its 3 cm GSD frames take minutes each to render).

Reported per flight: what was hidden, what the run found (name, values, sigmas, who found it), the relative error
along the truth, what else it named, and the run's time; then the hit rate and the false-naming rate over the
effect-free seeds.

    python -m benchmarks.rendered_sweep_bench [--nulls N] [--skip-effects] [--effects NAME ...]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from aerocal.pipeline import ProcessConfig, process
from aerocal.pipeline.certificates import MemoryCertificates
from aerocal.simulate import PRESETS, simulate_flight, write_flight
from aerocal.simulate.sensors import TemperatureCurve
from benchmarks.common import peak_rss_mb, record

WIND = (9.0, 4.0)
N_IMAGES = 16
N_EFFECT_FREE = 12
#: (effect, values, seed, warming camera, with a certificate from an effect-free flight)
SWEEP = [
    ("rolling_shutter", (0.03,), 501, False, False),
    ("affinity_skew", (5.0, 0.0), 502, False, False),
    ("radial_k3", (20.0,), 503, False, False),
    ("thermal_focal", (0.3,), 504, True, False),
    ("thermal_principal_point", (0.08, -0.06), 505, True, False),
    ("thermal_rotation", (0.05,), 506, True, False),
    ("gnss_time_offset", (0.3,), 507, False, False),
    ("gnss_bias", (0.4, -0.3, 0.0), 508, False, False),
    ("boresight", (0.2, -0.1, 0.0), 509, False, True),
]
NULL_SEEDS = range(601, 699)


def spec(warming: bool):
    return PRESETS["conte-calibration"].flown(
        WIND, TemperatureCurve(start_c=10.0, equilibrium_c=30.0, tau_s=400.0) if warming else None)


def flight(work: Path, seed: int, effects: dict, warming: bool, n: int, store: MemoryCertificates):
    """The run's summary and its time; a run that fails is a finding: its summary says so (``failed``)."""
    sim = simulate_flight(spec(warming), seed=seed, effects=effects, max_images=n)
    folder = work / f"{seed}-{'-'.join(effects) or 'none'}"
    write_flight(sim, folder, mode="images")
    t0 = time.perf_counter()
    try:
        summary = process(folder, ProcessConfig(), certificates=store).summary.to_json()
    except Exception as exc:  # every failure of a run is what this benchmark reports
        summary = {"failed": f"{type(exc).__name__}: {exc}"}
    return summary, time.perf_counter() - t0


def _row(line: str) -> str:
    print(line, flush=True)  # as it comes: a sweep stopped midway keeps what it measured
    return line


def _findings(summary: dict) -> str:  # the run summary as JSON (run.json)
    if "failed" in summary:
        return f"the run failed ({summary['failed']})"
    return "; ".join(f"{f['name']} {', '.join(f'{v:.4g}' for v in f['values'])} ({f['found_by']})"
                     for f in summary.get("findings") or []) or "nothing"


def along(estimate, truth) -> float:
    truth = np.asarray(truth, dtype=float)
    u = truth / np.linalg.norm(truth)
    return abs(float(np.asarray(estimate, dtype=float) @ u) - np.linalg.norm(truth)) / np.linalg.norm(truth)


def effects(work: Path, only: list[str] | None = None) -> None:
    lines = ["| hidden | found | error along the truth | named besides | time |", "|---|---|---|---|---|"]
    hits = 0
    sweep = [case for case in SWEEP if not only or case[0] in only]
    for name, value, seed, warming, certified in sweep:
        store = MemoryCertificates()
        if certified:
            flight(work, seed + 1000, {}, warming, N_EFFECT_FREE, store)
        s, took = flight(work, seed, {name: value}, warming, N_IMAGES, store)
        f = next((f for f in s.get("findings") or [] if f["name"] == name), None)
        err = along(f["values"], value) if f is not None else None
        others = [g["name"] for g in s.get("findings") or [] if g["name"] != name]
        hit = err is not None and err < 0.25 and not others
        hits += hit
        lines.append(_row(f"| {name} {', '.join(str(v) for v in value)} (seed {seed}) | {_findings(s)} | "
                          f"{'-' if err is None else f'{err:.0%}'} | {', '.join(others) or '-'} | {took:.0f} s |"))
    lines += ["", f"- found within 25 % with nothing else named: {hits} of {len(sweep)}",
              f"- peak memory {peak_rss_mb():.0f} MB"]
    record("Every catalogue effect hidden in rendered conte-calibration frames (16, wind 9,4)", lines)


def nulls(work: Path, n: int) -> None:
    lines = ["| seed | named | time |", "|---|---|---|"]
    named = 0
    for seed in list(NULL_SEEDS)[:n]:
        s, took = flight(work, seed, {}, seed % 2 == 0, N_EFFECT_FREE, MemoryCertificates())
        named += bool(s.get("findings")) or "failed" in s
        lines.append(_row(f"| {seed} | {_findings(s)} | {took:.0f} s |"))
    lines += ["", f"- effect-free flights that named something (or failed): {named} of {n}",
              f"- peak memory {peak_rss_mb():.0f} MB"]
    record(f"Effect-free rendered conte-calibration flights ({N_EFFECT_FREE} frames, wind 9,4)", lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nulls", type=int, default=8, help="effect-free seeds (default 8)")
    parser.add_argument("--skip-effects", action="store_true")
    parser.add_argument("--effects", nargs="*", metavar="NAME", help="only these effects of the sweep")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="aerocal-rendered-sweep-"))
    if args.nulls:
        nulls(work, args.nulls)
    if not args.skip_effects:
        effects(work, args.effects)


if __name__ == "__main__":
    main()
