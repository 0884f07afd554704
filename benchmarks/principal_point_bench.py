"""How often the self-calibration frees a principal point the geometry's prediction held, with the lens at the
frame's centre and 15 px (3 % of the side) below it.

Two strips of the xt2-survey preset (2 / 5 m GNSS, no GCPs), f, cx, cy, k1, k2 asked for, and a determinability
threshold of 0.2 % of the side, strict enough that the prediction holds cx and cy; the k-fold over the block then
decides (:func:`aerocal.calibrate.self_calibration.self_calibrate`). Per offset: the seeds on which cy was freed, its
estimate, and the held-out gain that freed it.

Run: ``python -m benchmarks.principal_point_bench [--seeds 8]``
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from aerocal.adjust import AdjustConfig
from aerocal.calibrate.self_calibration import CalibrationConfig, self_calibrate
from aerocal.certificates.review import DecisionConfig
from aerocal.simulate import PRESETS, simulate_flight
from benchmarks.common import record

OFFSETS_PX = (0.0, 15.0)


def main(seeds: int = 8) -> None:
    base = PRESETS["xt2-survey"]
    nominal = base.camera_nominal
    lines = ["| offset of cy (px) | seed | freed | cy estimated (true) | held-out gain of cx, cy free |",
             "|---|---|---|---|---|"]
    summary = []
    t0 = time.perf_counter()
    for off in OFFSETS_PX:
        true = dataclasses.replace(base.camera_true, cx=nominal.cx, cy=nominal.cy + off)
        spec = dataclasses.replace(base, camera_true=true, plan=dataclasses.replace(base.plan, n_strips=2),
                                   sensors=dataclasses.replace(base.sensors, gnss_sigma_h_m=2.0, gnss_sigma_v_m=5.0))
        cfg = AdjustConfig(free=("f", "cx", "cy", "k1", "k2"), gnss_sigma_m=(2.0, 2.0, 5.0), adaptive=True)
        strict = CalibrationConfig(null_draws=0, decision=DecisionConfig(determined_principal_point=0.002))
        freed = 0
        for seed in range(301, 301 + seeds):
            sim = simulate_flight(spec, seed=seed)
            cal = self_calibrate(sim.images, sim.observations, nominal, sim.gcps, sim.gcp_observations,
                                 height_agl_m=spec.plan.height_agl_m, config=strict, adjust_config=cfg)
            is_freed = "cy" not in cal.held_at_nominal
            freed += is_freed
            h = cal.held_out.get("cy")
            gain = f"{100 * h.gain:+.2f} +- {100 * h.sigma:.2f} %" if h is not None else "(not tested)"
            lines.append(f"| {off:g} | {seed} | {'yes' if is_freed else 'no'} | {cal.result.camera.cy:.2f} "
                         f"({true.cy:g}) | {gain} |")
        summary.append(f"- cy {off:g} px off the centre: freed on {freed} of {seeds} seeds")
    lines += ["", *summary, f"- wall time {time.perf_counter() - t0:.0f} s"]
    record("Principal point freed on held-out frames: simulated two-strip blocks", lines)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    main(parser.parse_args().seeds)
