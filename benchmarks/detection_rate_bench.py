"""How often the product names a hidden effect, and how often it names something on effect-free flights.

One hidden-effect case run on many seeds through :func:`aerocal.pipeline.process` (observations mode, the
product's own calibration, no truth handed over): per effect, the share of seeds on which it is named, the
share named within 25 % of its size, the estimates' mean and spread, and any other effect named; then the same
flight plan without effects on as many seeds, and what was named there. A single seed says whether a case can be
found; this says how often, which is what a test bound or an acceptance criterion must be set against.

Run: ``python -m benchmarks.detection_rate_bench [--preset xt2-survey] [--wind 2.5,1]
[--effect rolling_shutter=0.03 --effect gnss_time_offset=0.3] [--seeds 11] [--free 8] [--strips 6]``
(``--strips``: the preset's plan with this many strips, the area widened by as many strip spacings: the rate
against the block's size).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from aerocal.pipeline import RunSummary
from benchmarks.common import record


def _named(summary: RunSummary) -> dict[str, list[float]]:
    return {f.name: [float(v) for v in f.values] for f in summary.findings}


def with_strips(spec, n_strips: int):
    """``spec`` flown with ``n_strips`` strips: the planned area widened across the strips by the spacing the
    side overlap gives (the footprint's across-track width at the flying height x (1 - side overlap))."""
    plan = spec.plan
    across = spec.camera_nominal.height if plan.direction == "ew" else spec.camera_nominal.width
    spacing = across / spec.camera_nominal.f * plan.height_agl_m * (1.0 - plan.side_overlap)
    extra = spacing * (n_strips - plan.n_strips)
    ew, ns = spec.area_m
    area = (ew, ns + extra) if plan.direction == "ew" else (ew + extra, ns)
    return spec.replace(plan=dataclasses.replace(plan, n_strips=n_strips), area_m=area)


def main(argv: list[str] | None = None) -> None:
    from aerocal.effects import parse_effect
    from aerocal.pipeline import process
    from aerocal.pipeline.config import ProcessConfig
    from aerocal.simulate import simulate_flight
    from aerocal.simulate.presets import PRESETS
    from aerocal.simulate.simulator import as_dataset

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="xt2-survey")
    ap.add_argument("--wind", default="2.5,1", help="wind E,N in m/s")
    ap.add_argument("--effect", action="append", default=None, help="NAME=VALUE[,VALUE], repeatable")
    ap.add_argument("--seeds", type=int, default=11, help="flights with the effects (seeds 101, 102, ...)")
    ap.add_argument("--free", type=int, default=8, help="effect-free flights (seeds 201, 202, ...)")
    ap.add_argument("--strips", type=int, default=0, help="strips of the plan (0: the preset's)")
    args = ap.parse_args(argv)
    effects = dict(parse_effect(text) for text in (args.effect or ["rolling_shutter=0.03", "gnss_time_offset=0.3"]))
    wind = tuple(float(v) for v in args.wind.split(","))
    spec = PRESETS[args.preset].flown(wind)
    if args.strips:
        spec = with_strips(spec, args.strips)

    def run(seed: int, hidden: dict) -> tuple[dict[str, list[float]], float]:
        t0 = time.perf_counter()
        summary = process(as_dataset(simulate_flight(spec, seed=seed, effects=hidden)), ProcessConfig()).summary
        return _named(summary), time.perf_counter() - t0

    with_effects = {}
    for seed in range(101, 101 + args.seeds):
        with_effects[seed], took = run(seed, effects)
        print(f"seed {seed} ({took:.0f} s): {with_effects[seed]}", flush=True)
    free = {}
    for seed in range(201, 201 + args.free):
        free[seed], took = run(seed, {})
        print(f"effect-free seed {seed} ({took:.0f} s): {free[seed]}", flush=True)

    n = len(with_effects)
    size = f"{spec.plan.n_strips} strips of {spec.plan.images_per_strip} images"
    lines = [f"{args.preset} ({size}) in a wind {wind} m/s, observations mode, the product's own calibration; hidden: "
             f"{', '.join(f'{k} {v}' for k, v in effects.items())}; seeds 101-{100 + n}", "",
             "| effect | named | within 25 % | estimates mean +- std | hidden |", "|---|---|---|---|---|"]
    for name, value in effects.items():
        est = np.array([found[name][0] for found in with_effects.values() if name in found])
        close = np.sum(np.abs(est - value[0]) <= 0.25 * abs(value[0])) if len(est) else 0
        spread = f"{est.mean():.4g} +- {est.std(ddof=1) if len(est) > 1 else 0.0:.2g}" if len(est) else "-"
        lines.append(f"| {name} | {len(est)} of {n} | {close} of {n} | {spread} | {value[0]} |")
    others = {seed: sorted(set(found) - set(effects)) for seed, found in with_effects.items()
              if set(found) - set(effects)}
    false = {seed: found for seed, found in free.items() if found}
    lines += ["", f"- other effects named beside the hidden ones: {others or 'none'}",
              f"- effect-free seeds 201-{200 + len(free)}: {len(false)} of {len(free)} named anything"
              + (f" ({false})" if false else "")]
    record(f"Detection rate: {', '.join(effects)} hidden in {args.preset}", lines)


if __name__ == "__main__":
    main()
