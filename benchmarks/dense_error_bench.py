"""Where the dense DSM's error lives: its cells against the simulator's true surface, split by the relief within
each cell, on the rendered block of ``tests/test_dense.py`` (12 thermal frames of ``conte-calibration``, GSD
0.51 m, true poses and camera) at several seeds, with the default matching settings and variations of them.

Relief classes, from the true surface sampled at the cell centre and at 8 points half a cell away: *flat* where it
varies by less than 0.05 GSD, *sloped* up to 0.5 GSD, *edges* beyond (a roof's or a tree's rim crosses the cell).
The figures are the test's (NMAD of the measured cells two frames see, in GSD; the DSM gridded as the products
step grids it), per class, and what the same cells give against the true surface's median over 5 x 5 points of
each cell (the reference gridded as the DSM is); completeness of the cells two frames see, and of those two frames
see with the point hidden from neither (the simulator's surface ray-cast from each projection centre); beside them,
the cells without a point within 1.5 cells of one, which the DSM's mask called measured before
:meth:`aerocal.products.dsm.Dsm.measured`.

Run: ``python -m benchmarks.dense_error_bench`` (``--seeds 3 4 5``; ``--vary block_size=5 keep_frames=6 ...``:
each a :class:`aerocal.products.dense.DenseConfig` field and value, run beside the defaults).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from aerocal.assess import view_counts
from aerocal.enhance import enhance, stretch_params
from aerocal.pipeline.config import MosaicStepConfig
from aerocal.products.dense import DenseConfig, dense_cloud
from aerocal.products.dsm import dsm_from_points
from aerocal.products.mosaic import frames_from_poses, read_frame
from aerocal.simulate import simulate_flight
from aerocal.simulate.raycast import RenderConfig, intersect_dsm
from aerocal.simulate.rendered_frames import render_flight_images
from aerocal.simulate.simulator import true_poses
from benchmarks.common import record

#: relief within a cell (GSD) that separates flat from sloped cells, and sloped cells from edges
FLAT_GSD, EDGE_GSD = 0.05, 0.5


def _nmad(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else float("nan")


def _block(seed: int, folder: Path):
    sim = simulate_flight("conte-calibration", seed=seed, max_images=12)
    render_flight_images(sim, folder, config=RenderConfig(modality="thermal", supersample=2))
    names = dict(zip(sim.images.column("image_id").to_pylist(), sim.images.column("name").to_pylist(), strict=True))
    raws = {i: read_frame(folder / n) for i, n in names.items()}
    frames = frames_from_poses(true_poses(sim), {e.image_id: e.camera for e in sim.exposures})
    params = stretch_params(list(raws.values()))
    return sim, frames, (lambda i: (enhance(raws[i], params), raws[i].astype(np.float32)))


def _classes(sim, E: np.ndarray, N: np.ndarray, gsd: float) -> tuple[np.ndarray, np.ndarray]:
    """(relief within each cell (m), the true surface's median over 5 x 5 points of the cell (m))."""
    centre = sim.scene.height_at(E, N)
    h = 0.5 * gsd
    relief = np.zeros_like(centre)
    for de, dn in ((h, 0), (-h, 0), (0, h), (0, -h), (h, h), (-h, -h), (h, -h), (-h, h)):
        relief = np.maximum(relief, np.abs(sim.scene.height_at(E + de, N + dn) - centre))
    offs = ((np.arange(5) + 0.5) / 5 - 0.5) * gsd
    cell_median = np.median(np.stack([sim.scene.height_at(E + a, N + b) for a in offs for b in offs]), axis=0)
    return relief, cell_median


def _row(seed: int, label: str, sim, frames, load, config: DenseConfig) -> str:
    tie = np.asarray(sim.tie.points, dtype=float)
    t0 = time.perf_counter()
    cloud = dense_cloud(frames, load, tie, float(np.median(tie[:, 2])), config)
    seconds = time.perf_counter() - t0
    gsd = cloud.gsd_m
    dsm = dsm_from_points(cloud.xyz, sim.crs, gsd_m=gsd, config=MosaicStepConfig().dense_dsm)
    E, N = dsm.cell_centres()
    truth = sim.scene.height_at(E, N)
    seen = view_counts(frames, np.stack([E, N, truth], axis=-1)) >= 2
    visible = view_counts(frames, np.stack([E, N, truth], axis=-1), lambda o, d: intersect_dsm(sim.scene, o, d).t,
                          tolerance_m=0.25 * dsm.cell_m) >= 2
    measured = dsm.measured() & seen
    # the cells a hole's rim adds when a cell within 1.5 cells of a point counts as measured (the mask before)
    rim = (dsm.distance_m <= 1.5 * dsm.cell_m) & ~dsm.measured() & seen & np.isfinite(dsm.heights)
    relief, cell_median = _classes(sim, E, N, gsd)
    diff = (dsm.heights - truth)[measured] / gsd
    rel = relief[measured] / gsd
    flat, edge = rel < FLAT_GSD, rel >= EDGE_GSD
    sloped = ~flat & ~edge
    gridded = (dsm.heights - cell_median)[measured] / gsd
    share = [f"{np.mean(c):.0%}" for c in (flat, sloped, edge)]
    return (f"| {seed} | {label} | {seconds:.1f} s | {_nmad(diff):.2f} ({np.median(diff):+.2f}) | "
            f"{_nmad(diff[flat]):.2f} / {_nmad(diff[sloped]):.2f} / {_nmad(diff[edge]):.2f} ({' / '.join(share)}) | "
            f"{np.mean(edge & (diff > 2)):.1%} / {np.mean(edge & (diff < -2)):.1%} | "
            f"{np.mean(flat & (np.abs(diff) > 2)) / max(np.mean(flat), 1e-12):.1%} | {_nmad(gridded):.2f} | "
            f"{np.count_nonzero(measured) / max(np.count_nonzero(seen), 1):.1%} | "
            f"{np.count_nonzero(dsm.measured() & visible) / max(np.count_nonzero(visible), 1):.1%} | "
            f"{_nmad((dsm.heights - truth)[rim] / gsd):.1f} "
            f"({np.count_nonzero(rim) / max(np.count_nonzero(seen), 1):.1%}) |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5])
    ap.add_argument("--vary", nargs="*", default=["block_size=5", "block_size=9", "keep_frames=6",
                                                  "agreement_px=0.35"])
    args = ap.parse_args()
    base = DenseConfig()
    variants = [("defaults", base)]
    for item in args.vary:
        name, value = item.split("=")
        variants.append((item, dataclasses.replace(base, **{name: type(getattr(base, name))(value)})))
    lines = [
        "| seed | settings | dense cloud | NMAD, all measured cells (median), GSD | NMAD flat / sloped / edges "
        "(share of the cells) | edge cells > +2 / < -2 GSD (of all) | flat cells beyond 2 GSD | NMAD against the "
        "cell-median truth | completeness (cells two frames see) | completeness (cells two frames see, hidden "
        "from neither) | the rim of the holes, within 1.5 cells of a "
        "point: NMAD, GSD (share of the cells two frames see) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as tmp:
            sim, frames, load = _block(seed, Path(tmp))
            for label, config in variants:
                lines.append(_row(seed, label, sim, frames, load, config))
                print(lines[-1], flush=True)
    record("Dense surface: where its error lives", lines)


if __name__ == "__main__":
    main()
