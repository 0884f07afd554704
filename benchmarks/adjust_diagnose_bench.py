"""Full-block adjustment and diagnosis at city scale (observations mode).

Targets: the ~800-image fixed-IO adjustment of conte-city in under 30 s; the diagnosis (every
hypothesis scored) in under 60 s. Baseline measured in the same run: the self-calibrating adjustment
of the same block (IO free), so the ratio shows what fixing IO saves.

    python -m benchmarks.adjust_diagnose_bench
"""

from __future__ import annotations

import time

from aerocal.adjust import AdjustConfig, adjust
from aerocal.diagnose.engine import DiagnoseConfig, diagnose_baseline
from aerocal.diagnose.model import fit_baseline
from aerocal.simulate import simulate_flight
from benchmarks.common import peak_rss_mb, record


def main() -> None:
    sim = simulate_flight("conte-city", seed=1, effects={"thermal_focal": 0.2})
    s = sim.spec.sensors
    priors = dict(gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
                  attitude_sigma_deg=s.imu_sigma_deg)
    n_obs = sim.observations.num_rows
    rows = []
    t0 = time.perf_counter()
    fixed = adjust(sim.images, sim.observations, sim.spec.camera_true, AdjustConfig(free=(), **priors),
                   sim.gcps, sim.gcp_observations)
    t_fixed = time.perf_counter() - t0
    rows.append(("full-block adjustment, IO fixed", t_fixed, fixed.iterations))
    t0 = time.perf_counter()
    free = adjust(sim.images, sim.observations, sim.spec.camera_nominal,
                  AdjustConfig(free=("f", "cx", "cy", "k1", "k2", "p1", "p2"), **priors), sim.gcps,
                  sim.gcp_observations)
    t_free = time.perf_counter() - t0
    rows.append(("baseline: self-calibrating adjustment", t_free, free.iterations))
    t0 = time.perf_counter()
    base = fit_baseline(sim.images, sim.observations, sim.spec.camera_true, AdjustConfig(free=(), **priors),
                        sim.gcps, sim.gcp_observations)
    t_base = time.perf_counter() - t0
    d = diagnose_baseline(base, DiagnoseConfig(reference_temperature=s.reference_temperature_c, twins=0))
    t_diag = time.perf_counter() - t0
    t0 = time.perf_counter()
    twin_cfg = DiagnoseConfig(reference_temperature=s.reference_temperature_c)
    with_twin = diagnose_baseline(base, twin_cfg)
    t_twin = time.perf_counter() - t0 + t_base
    lines = [f"conte-city: {sim.images.num_rows} images, {n_obs} tie observations, hidden thermal_focal=0.2 "
             "px/degC", "", "| step | time | iterations |", "|---|---|---|"]
    lines += [f"| {name} | {t:.1f} s | {it} |" for name, t, it in rows]
    lines += [
        f"| diagnosis (baseline adjustment + all hypotheses + extension) | {t_diag:.1f} s | |",
        f"| diagnosis with the flight's twin ({twin_cfg.twins} twins) | {t_twin:.1f} s | |",
        "",
        f"- twin: {with_twin.twin.get('summary')}",
        f"- ratio fixed / self-calibrating: {t_fixed / t_free:.2f}",
        f"- targets: fixed-IO adjustment < 30 s: {'met' if t_fixed < 30 else 'not met'}; "
        f"diagnosis < 60 s: {'met' if t_diag < 60 else 'not met'}; with the twin < 60 s: "
        f"{'met' if t_twin < 60 else 'not met'}",
        f"- diagnosis verdict: {d.summary()}",
        f"- peak memory: {peak_rss_mb():.0f} MB",
    ]
    record("Adjustment and diagnosis, conte-city", lines)


if __name__ == "__main__":
    main()
