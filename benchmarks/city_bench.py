"""City scale, measured: a rendered ``conte-city`` flight (818 frames, 640x480, 16-bit thermal).

1. End to end: every step of ``process_flight`` (ingest, enhance + match on a local Dask cluster of 2
   workers, orient, calibration sub-block + self-calibration, full-block adjustment with fixed IO, DSM +
   orthomosaic, assessment, diagnosis, report) with its time; peak memory of the flow process and of the
   Dask workers; check-point accuracy against its prediction (rho per axis).
2. Matching, Dask 1 vs 2 workers: features and verified matches of a 150-frame sub-block.
3. Candidate pairs, footprints vs exhaustive, on a 100-frame sub-block: time ratio and recall (verified
   matches found, and pairs holding at least 15 verified matches in the exhaustive run that the footprint
   pairs also hold).
4. Orthomosaic of the whole flight, Dask 1 vs 2 workers, from the end-to-end run's poses and DSM.
5. End to end on a cluster of separate processes (a ``dask scheduler`` and two ``dask worker`` processes,
   as ``aerocal process --dask ADDRESS`` uses one) against the local cluster of part 1, same run: time per
   step and the largest pose difference.

The rendered flight is cached in ``benchmarks/data/`` (rendering the 818 frames takes ~13 min on one core;
``--images 3200``: the same plan over a larger area, rendered in ~2 h on one core shared with other jobs).

Run: ``python -m benchmarks.city_bench`` (``--frames N``: only the N frames nearest the block centre;
``--parts e2e,matching``: only those parts).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio

from aerocal import tables
from aerocal.camera import Camera
from aerocal.certificates.document import Certificate
from aerocal.ingest import ingest_folder
from aerocal.io import write_json_atomic
from aerocal.matching import (
    FeatureConfig,
    MatchConfig,
    candidate_pairs_from_footprints,
    exhaustive_pairs,
    extract_features,
    local_client,
    match_pairs_detailed,
)
from aerocal.matching.cluster import ExecutionConfig
from aerocal.pipeline import process
from aerocal.pipeline.config import MatchStepConfig
from aerocal.pipeline.match_step import frame_loader, match_images
from aerocal.products.dsm import read_dsm
from aerocal.products.mosaic import build_mosaic, frames_from_poses
from aerocal.simulate import simulate_flight, write_flight
from benchmarks.common import CITY_FRAMES, city_spec, peak_rss_mb, record

DATA = Path(__file__).resolve().parent / "data"


def children_peak_mb() -> float:
    """Peak resident memory of the largest terminated child process so far (Dask workers), MB."""
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


def rendered_flight(images: int = CITY_FRAMES, seed: int = 0) -> Path:
    """The rendered conte-city flight folder (``images`` > 818: the same plan over a larger area, see
    :func:`benchmarks.common.city_spec`), simulated and rendered on first use (~1 s per frame on one core)."""
    spec = city_spec(images)
    out = DATA / f"{spec.name}-images-s{seed}"
    if (out / "flight.json").exists():
        return out
    sim = simulate_flight(spec, seed=seed, max_images=images if images > CITY_FRAMES else None)
    t0 = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if done % 50 == 0 or done == total:
            print(f"rendered {done}/{total} frames ({time.perf_counter() - t0:.0f} s)", flush=True)

    return write_flight(sim, out, mode="images", progress=progress)


@contextlib.contextmanager
def scratch_folder(prefix: str):
    """A temporary folder beside the cached frames (so hard links to them work), removed on exit."""
    DATA.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=prefix, dir=DATA))
    try:
        yield work
    finally:
        shutil.rmtree(work, ignore_errors=True)


def subset_folder(folder: Path, n: int, work: Path) -> Path:
    """A flight folder of the ``n`` frames nearest the block centre (hard links to the cached frames)."""
    res = ingest_folder(folder)
    im = res.images
    x, y = im.column("gnss_x").to_numpy(), im.column("gnss_y").to_numpy()
    d = np.hypot(x - np.median(x), y - np.median(y))
    keep = set(np.asarray(im.column("name").to_pylist())[np.argsort(d)[:n]])
    out = work / f"{folder.name}-{n}"
    (out / "images").mkdir(parents=True)
    for f in (folder / "images").iterdir():
        if f.name in keep:
            try:
                os.link(f, out / "images" / f.name)  # same file system: no copy
            except OSError:
                shutil.copy(f, out / "images" / f.name)
    for f in folder.iterdir():
        if f.suffix in (".csv", ".txt"):  # EO and GCP measurement rows of the kept frames only
            lines = f.read_text().splitlines(keepends=True)
            names = [next((w for w in line.replace(",", " ").split() if w.startswith("IMG_")), None)
                     for line in lines]
            f_out = "".join(line for line, name in zip(lines, names, strict=True) if name is None or name in keep)
            (out / f.name).write_text(f_out)
        elif f.is_file():
            shutil.copy(f, out / f.name)
    if (folder / "reference").is_dir():
        shutil.copytree(folder / "reference", out / "reference")
    return out


def end_to_end(folder: Path, work: Path, dask_address: str | None = None) -> tuple[dict, float]:
    """The run summary of the whole flight through :func:`aerocal.pipeline.process` (``run.json`` written
    beside the products), and its seconds; on the Dask scheduler ``dask_address`` when given."""
    t0 = time.perf_counter()
    run = process(folder, certificate="none", out_dir=work / "run", execution=ExecutionConfig(dask_address))
    seconds = time.perf_counter() - t0
    summary = run.summary.to_json()
    write_json_atomic(work / "run" / "run.json", summary)
    return summary, seconds


def matching_workers(folder: Path, workers: int) -> tuple[float, float, int, int]:
    """(features s, matches s, keypoints, verified matches) of the flight with a ``workers`` cluster."""
    res = ingest_folder(folder)
    cam = Camera.from_dict(json.loads((folder / "camera.json").read_text())["camera"])
    flight = json.loads((folder / "flight.json").read_text()) | {"folder": str(folder)}
    t0 = time.perf_counter()
    with local_client(n_workers=workers):
        pass  # cluster start-up is not part of the measurement below
    t1 = time.perf_counter()
    kp, matches, _, _ = match_images(res.images, cam, res.gcps, flight, MatchStepConfig(),
                                       ExecutionConfig(local_workers=workers))
    total = time.perf_counter() - t1
    return t1 - t0, total, kp.num_rows, matches.num_rows


def pairs_recall(folder: Path) -> dict:
    """Footprint vs exhaustive candidate pairs on the flight: time and recall of verified matches."""

    res = ingest_folder(folder)
    images = res.images
    cam = Camera.from_dict(json.loads((folder / "camera.json").read_text())["camera"])
    loader = frame_loader(images.column("path").to_pylist())
    terrain = float(np.mean(res.gcps.column("Z").to_numpy()))
    out = {}
    with local_client(n_workers=2) as client:
        kp = extract_features(images, loader, FeatureConfig(), client)
        for name, pairs in (
            ("footprints", candidate_pairs_from_footprints(images, cam, terrain)),
            ("exhaustive", exhaustive_pairs(images.column("image_id").to_numpy())),
        ):
            t0 = time.perf_counter()
            det = match_pairs_detailed(pairs, kp, MatchConfig(), client)
            m = det.matches.to_pydict()
            counts: dict[tuple[int, int], int] = {}
            for a, b in zip(m["image_id1"], m["image_id2"], strict=True):
                counts[(a, b)] = counts.get((a, b), 0) + 1
            out[name] = {"seconds": time.perf_counter() - t0, "pairs": len(pairs), "matches": len(m["image_id1"]),
                         "good_pairs": {p for p, c in counts.items() if c >= 15}}
    fp, ex = out["footprints"], out["exhaustive"]
    recall = len(fp["good_pairs"] & ex["good_pairs"]) / max(1, len(ex["good_pairs"]))
    return {"footprints": fp, "exhaustive": ex, "pair_recall": recall,
            "match_recall": fp["matches"] / max(1, ex["matches"])}


def mosaic_workers(run_dir: Path, folder: Path, workers: int, work: Path) -> float:
    """Seconds to mosaic the whole flight from the run's poses and DSM with a ``workers`` cluster."""
    cert = Certificate.from_dict(json.loads((run_dir / "certificate.json").read_text()))
    dsm = read_dsm(run_dir / "dsm.tif")
    poses = tables.read(run_dir / "poses.parquet", "poses")

    images = ingest_folder(folder).images  # the same image ids as the run's ingest
    paths = dict(zip(images.column("image_id").to_pylist(), images.column("path").to_pylist(), strict=True))
    frames = frames_from_poses(poses, cert.camera)
    with local_client(n_workers=workers) as client:
        t0 = time.perf_counter()
        build_mosaic(frames, paths, dsm, work / f"mosaic-{workers}.tif", None, client)
        return time.perf_counter() - t0


def separate_processes(folder: Path, work: Path, local: dict, local_wall: float) -> list[str]:
    """Part 5: the flight end to end on a scheduler and two worker processes, against the local run."""
    import pyarrow.parquet as pq

    from benchmarks.process_cluster import process_cluster

    (work / "cluster").mkdir()
    with process_cluster(work / "cluster", n_workers=2) as cluster:
        remote, wall = end_to_end(folder, work / "remote", cluster.address)
    a, b = (pq.read_table(Path(s["out_dir"]) / "poses.parquet").sort_by("image_id") for s in (local, remote))
    xyz = [np.column_stack([t.column(c).to_numpy() for c in ("X", "Y", "Z")]) for t in (a, b)]
    lines = ["### End to end, separate worker processes against the local cluster (same run)", "",
             "| step | local cluster | 2 worker processes |", "|---|---|---|"]
    for step, info in local["steps"].items():
        other = remote["steps"].get(step, {})
        lines.append(f"| {step} | {info.get('seconds', float('nan')):.1f} s | "
                     f"{other.get('seconds', float('nan')):.1f} s |")
    same = a.column("image_id").to_pylist() == b.column("image_id").to_pylist()
    diff = f"{float(np.abs(xyz[0] - xyz[1]).max()):.1e} m" if same else "the oriented frames differ"
    lines += [f"| **total** | **{local_wall:.1f} s** | **{wall:.1f} s** |", "",
              f"- ratio separate / local: {wall / local_wall:.2f}; largest pose difference: {diff}", ""]
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=None, help="only the N frames nearest the block centre")
    ap.add_argument("--images", type=int, default=CITY_FRAMES,
                    help="render conte-city's plan over a larger area and keep this many frames (default 818: "
                         "the preset itself; 3200 took ~2 h on one core shared with other jobs; cached)")
    ap.add_argument("--source", type=Path, default=None,
                    help="a rendered flight folder (default: conte-city seed 0, rendered on first use)")
    ap.add_argument("--parts", default="e2e,matching,pairs,mosaic,cluster",
                    help="comma-separated parts to run: e2e, matching, pairs, mosaic, cluster (mosaic and cluster "
                         "need e2e)")
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    for part in ("mosaic", "cluster"):
        if part in parts and "e2e" not in parts:
            ap.error(f"--parts {part} needs e2e (it is compared with the end-to-end run)")
    with scratch_folder("work-") as work:
        full = args.source or rendered_flight(args.images)
        folder = subset_folder(full, args.frames, work) if args.frames else full
        n = len(list((folder / "images").iterdir()))
        lines = [f"{full.name}: rendered, {n} frames 640x480 16-bit thermal"
                 + (f" ({n} nearest the centre)" if args.frames else ""), ""]

        if "e2e" not in parts:
            summary, wall = None, 0.0
        else:
            summary, wall = end_to_end(folder, work)
        if summary is not None:
            peak_flow, peak_workers = peak_rss_mb(), children_peak_mb()
            lines += ["### End to end (`process_flight`, local Dask cluster of 2 workers, SQLite)", "",
                      "| step | status | time |", "|---|---|---|"]
            for step, info in summary["steps"].items():
                lines.append(f"| {step} | {info.get('status')} | {info.get('seconds', float('nan')):.1f} s |")
            run_dir = Path(summary["out_dir"])
            adj = json.loads((run_dir / "adjustment.json").read_text())
            mosaic = summary["steps"]["mosaic"]
            with rasterio.open(run_dir / "dsm.tif") as d, rasterio.open(run_dir / "orthomosaic.tif") as o:
                grids = (f"- DSM: {d.height} x {d.width} cells of {d.res[0]:.2f} m; orthomosaic {o.height} x "
                         f"{o.width} px of {o.res[0]:.3f} m")
            lines += [
                f"| **total (wall, flow start to report)** | | **{wall:.1f} s** |", "",
                f"- peak memory: flow process {peak_flow:.0f} MB, largest Dask worker {peak_workers:.0f} MB",
                f"- target: the whole flight in < 10 min: {'met' if wall < 600 else 'not met'}",
                f"- block: sigma0 {adj['sigma0']:.3f}, reprojection RMS {adj['reprojection_rms_px']:.3f} px, check "
                f"RMSE {np.round(adj['check_rmse_m'], 3).tolist()} m, rho {np.round(adj['rho'], 2).tolist()}",
                f"- selection: {'; '.join(adj.get('selection') or []) or 'none'}",
                f"- matching (features + matches): {summary['steps']['match'].get('seconds', float('nan')):.1f} s "
                f"(target < 180 s for 800 frames)",
                f"- DSM + orthomosaic: {mosaic.get('seconds', float('nan')):.1f} s (target < 120 s)",
                grids,
                f"- diagnosis: {json.loads((run_dir / 'diagnosis.json').read_text()).get('summary')}",
                "",
            ]

        if "matching" in parts:
            sub = subset_folder(full, 150, work) if n > 150 else folder
            rows = {w: matching_workers(sub, w) for w in (1, 2)}
            lines += ["### Matching, Dask 1 vs 2 workers (150 frames nearest the centre)", "",
                      "| workers | features + matches | keypoints | verified matches |", "|---|---|---|---|"]
            for w, (_, secs, nk, nm) in rows.items():
                lines.append(f"| {w} | {secs:.1f} s | {nk} | {nm} |")
            lines += ["", f"- speed-up 2 vs 1 workers: {rows[1][1] / rows[2][1]:.2f}x", ""]

        if "pairs" in parts:
            small = subset_folder(full, 100, work) if n > 100 else folder
            pr = pairs_recall(small)
            fp, ex = pr["footprints"], pr["exhaustive"]
            lines += ["### Candidate pairs, footprints vs exhaustive (100 frames nearest the centre)", "",
                      "| pairs from | pairs | matching time | verified matches | pairs with >= 15 matches |",
                      "|---|---|---|---|---|",
                      f"| footprints | {fp['pairs']} | {fp['seconds']:.1f} s | {fp['matches']} | "
                      f"{len(fp['good_pairs'])} |",
                      f"| exhaustive | {ex['pairs']} | {ex['seconds']:.1f} s | {ex['matches']} | "
                      f"{len(ex['good_pairs'])} |",
                      "",
                      f"- time ratio exhaustive / footprints: {ex['seconds'] / fp['seconds']:.1f}x",
                      f"- recall of the footprint pairs: {pr['pair_recall']:.3f} of the well-matched pairs, "
                      f"{pr['match_recall']:.3f} of the verified matches", ""]

        if "mosaic" in parts:
            mos = {w: mosaic_workers(run_dir, folder, w, work) for w in (1, 2)}
            lines += ["### Orthomosaic of the whole flight, Dask 1 vs 2 workers", "",
                      "| workers | time |", "|---|---|"] + [f"| {w} | {s:.1f} s |" for w, s in mos.items()]
            lines += ["", f"- speed-up 2 vs 1 workers: {mos[1] / mos[2]:.2f}x", ""]

        if "cluster" in parts:
            lines += separate_processes(folder, work, summary, wall)
        record("City scale: conte-city rendered, end to end", lines)


if __name__ == "__main__":
    main()
