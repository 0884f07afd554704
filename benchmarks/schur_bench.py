"""The reduced camera system of one Levenberg-Marquardt iteration: general sparse products against the
observations' blocks (:func:`aerocal.adjust.solver.schur_complement` without and with ``blocks``).

Blocks: ``conte-city`` in observations mode, 200 and 818 images, IO fixed (the block adjustment) and
self-calibrating (f, cx, cy, k1, k2, p1, p2: the calibration). Both paths run on the same Jacobian in
the same process, alternately, best of three; the ratio is sparse time over structured time.

Run: ``python -m benchmarks.schur_bench [--sizes 200,818]``.
"""

from __future__ import annotations

import argparse

import numpy as np

from aerocal.adjust import AdjustConfig
from aerocal.adjust.bundle import initial_state
from aerocal.adjust.problem import build_block
from aerocal.adjust.solver import BundleProblem, schur_complement
from aerocal.simulate import simulate_flight
from benchmarks.common import best_of, record


def case(n: int, free: tuple[str, ...]) -> dict:
    sim = simulate_flight("conte-city", seed=0, max_images=n if n < 818 else None)
    cfg = AdjustConfig(free=free, gnss_sigma_m=(0.1, 0.1, 0.15))
    blk = build_block(sim.images, sim.observations, sim.gcps, sim.gcp_observations, cfg)
    blk, st = initial_state(blk, sim.camera_nominal)
    prob = BundleProblem(blk, cfg, 0.0)
    _, _, _, r, Jc, Jp, Hpp = prob.residuals(st, jac=True)
    sparse = best_of(lambda: schur_complement(Jc, Jp, Hpp, r, 1e-3))
    structured = best_of(lambda: schur_complement(Jc, Jp, Hpp, r, 1e-3, prob.blocks))
    count = np.bincount(prob.blocks.point)
    return {"images": blk.n_images, "observations": len(prob.blocks.point), "pairs": int(count @ count),
            "free": len(free), "sparse": sparse, "structured": structured}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="200,818")
    args = ap.parse_args(argv)
    lines = ["| images | observations | observation pairs | free IO | sparse products | structured | ratio |",
             "|---|---|---|---|---|---|---|"]
    for n in (int(v) for v in args.sizes.split(",")):
        for free in ((), ("f", "cx", "cy", "k1", "k2", "p1", "p2")):
            c = case(n, free)
            lines.append(f"| {c['images']} | {c['observations']} | {c['pairs']} | {c['free']} | "
                         f"{c['sparse']:.3f} s | {c['structured']:.3f} s | {c['sparse'] / c['structured']:.2f}x |")
            print(lines[-1], flush=True)
    record("Reduced camera system: sparse products vs the observations' blocks", lines)


if __name__ == "__main__":
    main()
