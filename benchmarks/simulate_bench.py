"""Simulator benchmarks: observations for conte-city, one rendered 640x480 thermal frame.

Targets: conte-city observations in under 30 s; one 640x480 thermal frame in under 0.5 s on one core.
Baseline measured in the same run: the raw cost of projecting the same observations without the
simulator's bookkeeping (one vectorised Exposure.project per frame), so the ratio shows the overhead.

    python -m benchmarks.simulate_bench
"""

from __future__ import annotations

import time

import numpy as np

from aerocal.simulate import simulate_flight
from aerocal.simulate.raycast import RenderConfig, render_frame
from benchmarks.common import best_of, peak_rss_mb, record


def main() -> None:
    t0 = time.perf_counter()
    sim = simulate_flight("conte-city", seed=1)
    t_city = time.perf_counter() - t0
    n_obs = len(sim.tie.image_id)

    # baseline: projecting every tie point of every frame once, nothing else
    pts = sim.tie.points
    def project_all():
        for ex in sim.exposures:
            sel = sim.tie.point_id[sim.tie.image_id == ex.image_id]
            ex.project(pts[sel])
    t_base = best_of(project_all, repeat=1)

    lines = [
        "| what | value |", "|---|---|",
        f"| conte-city simulation (scene, plan, {sim.images.num_rows} frames, {n_obs} observations) | {t_city:.2f} s |",
        f"| baseline: projection of the same observations only | {t_base:.2f} s |",
        f"| ratio simulation / baseline | {t_city / t_base:.1f} |",
        f"| target | < 30 s: {'met' if t_city < 30 else 'not met'} |",
    ]
    small = simulate_flight("conte-calibration", seed=1, max_images=2)
    ex = small.exposures[0]
    rng = np.random.default_rng(0)
    t_frame = best_of(lambda: render_frame(small.scene, ex, RenderConfig(), rng), repeat=3)
    lines.append(f"| one rendered 640x480 thermal frame (default supersampling) | {t_frame:.3f} s "
                 f"(target < 0.5 s: {'met' if t_frame < 0.5 else 'not met'}) |")
    # baseline: the same frame with every sub-pixel ray traced from the top (no derivation from pixel centres)
    t_exact = best_of(lambda: render_frame(small.scene, ex, RenderConfig(accelerate=False), rng), repeat=2)
    lines.append(f"| baseline: the same frame, every sub-pixel ray traced | {t_exact:.3f} s |")
    lines.append(f"| ratio frame / baseline | {t_frame / t_exact:.2f} |")
    lines.append(f"| peak memory | {peak_rss_mb():.0f} MB |")
    record("Simulator", lines)


if __name__ == "__main__":
    main()
