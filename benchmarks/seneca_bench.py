"""seneca (real), end to end through the pipeline of ``aerocal process``, measured.

Data: ``../shared/data/seneca/images``, 166 of the 167 nadir JPEGs of a senseFly Swinglet CAM (Canon
PowerShot ELPH 300 HS, 1800x1350) whose camera cooled from 37 to 23 degC; GNSS and autopilot attitude in
the senseFly XMP, camera temperature in the Canon maker notes. The first image (IMG_0446) is 1620x1215,
another size than the rest: it is left out, as in ``studies/seneca.py``.

The flight folder is built in a temporary directory, the images are not copied:

* ``images/``: symbolic links to the shared JPEGs;
* ``camera.json``: the camera identity from the EXIF make and model (the camera records no serial
  number; it is built into the airframe, so the serial is that of the senseFly frame in the XMP,
  ``SC-05-110``: the store refuses an identity without a serial), and the nominal camera: width and
  height of the images, the EXIF focal length (4.3 mm) over the pixel pitch of the 1/2.3" sensor
  (6.17 mm / 1800 px = 3.43 um; EXIF carries no focal-plane resolution), principal point at the centre;
* ``flight.json``: no GCPs, so the terrain height for candidate pairs comes from ``height_agl_m``: the
  mean GNSS height minus the take-off ground (GNSS height minus senseFly's height above take-off, median
  over the images); consumer GNSS and autopilot attitude sigmas (``gnss_sigma_m`` 2.5 m horizontal, 5 m
  vertical; ``imu_sigma_deg`` 5/5/10 deg), the values of ``studies/seneca.py``.

Then :func:`aerocal.pipeline.process` (the code of ``aerocal process FLIGHT_DIR OUT_DIR``, here without
Prefect or a database) runs with its default configuration but for the SIFT cap (:data:`MAX_FEATURES`) and
``certificate="none"`` (self-calibration), a local Dask cluster of 2 workers per step that needs one; the
tables the report and ``--rediagnose`` read are kept in ``kept/`` of the work folder. Recorded: time per
step and wall time, peak memory of this process and of its children (the Dask workers), images registered,
tie points per image, reprojection RMS and sigma0 of the calibration and of the block adjustment,
blunders rejected, the certificate's f, cx, cy with sigmas and the thermal slope,
the diagnosis. Figure: ``benchmarks/output/seneca_tie_points.png`` (tie points per image over the image
order, sensor temperature on a twin axis); the per-image numbers in ``seneca_per_image.csv`` beside it.

Run: ``python -m benchmarks.seneca_bench`` (``--quick``: strips 0, 2 and 4 only, ~30 images).
``--work DIR --rediagnose`` times the diagnosis (with the flight's twin) again on the run kept in ``DIR``:
the diagnose step's own engine call on the step's own inputs (the observations the block adjustment kept, its
poses and points, the certificate it used), so that a change of the diagnosis is measured without matching
and calibrating again (the step cache keys on inputs and configuration, not code).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import resource
import shutil
import tempfile
import time
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.adjust import AdjustConfig, scale_tie_sigma, screened_rows
from aerocal.camera import Camera
from aerocal.certificates.document import Certificate
from aerocal.diagnose.engine import DiagnoseConfig, diagnose
from aerocal.diagnose.io_uncertainty import IOUncertainty
from aerocal.ingest import ingest_folder
from aerocal.io import write_json_atomic
from aerocal.matching import FeatureConfig
from aerocal.pipeline import process
from aerocal.pipeline.config import MatchStepConfig, ProcessConfig
from aerocal.report.wording import recorded_eo_text
from benchmarks.common import peak_rss_mb, record

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT.parent / "shared" / "data" / "seneca" / "images"
OUTPUT = Path(__file__).resolve().parent / "output"
QUICK_STRIPS = (0, 2, 4)
#: SIFT keypoints per image (the default is 8000). Exact matching costs grow with the product of the two
#: images' keypoints: on seneca pairs (linear stretch, one core) 0.59 s per pair at 8000 and 0.09 s at 4000
#: for 52 % of the verified matches, so the 2276 candidate footprint pairs need about 11 minutes of two
#: workers at 8000 and under 2 at 4000 (estimated from those per-pair times; the whole match step, SIFT
#: included, took 428 s at 4000 with the test suite sharing the cores). 4000 keypoints still give
#: hundreds of matches per neighbouring pair.
MAX_FEATURES = 4000
#: an image with fewer tie points than this in the block adjustment is named in the results
WEAK_TIE_POINTS = 50


def children_peak_mb() -> float:
    """Peak resident memory of the largest terminated child process so far (Dask workers), MB."""
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0


def build_flight(work: Path, quick: bool = False) -> tuple[Path, dict]:
    """The flight folder ``work/seneca`` as a user hands it to ``aerocal process``: links to the seneca images
    and nothing else (the images of :data:`QUICK_STRIPS` only when ``quick``). The nominal camera, the flying
    height and the GNSS sigmas are what ingest reads from the images (EXIF FocalPlaneXResolution, senseFly
    Height, consumer-grade GNSS); returned with what was left out: ``(folder, facts)``."""
    names = sorted(p.name for p in IMAGES.iterdir() if p.suffix.lower() == ".jpg")
    if quick:
        whole = ingest_folder(IMAGES).images
        strip = np.array([-1 if s is None else s for s in whole.column("strip").to_pylist()])
        names = sorted(np.asarray(whole.column("name").to_pylist())[np.isin(strip, QUICK_STRIPS)].tolist())
    folder = work / "seneca"
    shutil.rmtree(folder, ignore_errors=True)  # links of an unfinished run
    (folder / "images").mkdir(parents=True)
    for name in names:
        os.symlink(IMAGES / name, folder / "images" / name)
    res = ingest_folder(folder)
    if res.blocking or res.camera is None or res.height_agl_m is None:
        raise SystemExit(f"{folder}: ingest says processing would stop: {[str(p) for p in res.blocking]}")
    left_out = [f"{p.file.rsplit('/', 1)[-1]} ({p.message.split(':', 1)[1].split(',')[0].strip()})"
                for p in res.problems if p.field == "width" and p.message.startswith("left out")]
    return folder, {"left_out": left_out, "images": res.images.num_rows, "camera": res.camera,
                    "camera_source": res.camera_source, "height_agl_m": res.height_agl_m,
                    "height_source": res.flight_facts.get("height_agl_m", ""), "gnss_sigma_m": res.gnss_sigma_m}


def _stats(values: np.ndarray) -> str:
    values = np.asarray(values)
    if values.size == 0:
        return "none"
    return f"{int(values.min())} / {float(np.median(values)):.0f} / {int(values.max())}"


def _rejected(selection: list[str]) -> str:
    for s in selection or []:
        m = re.match(r"rejected (\d+) of (\d+)", s)
        if m:
            return f"{m.group(1)} of {m.group(2)}"
    return "none (no robust pass)"


def tie_point_figure(names: list[str], per_image: np.ndarray, used: np.ndarray, temperature: np.ndarray,
                     path: Path) -> Path:
    """Bars of tie points per image (matched and used by the block adjustment) over the image order, the
    sensor temperature on a twin axis."""
    matplotlib.use("Agg")

    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(12, 4.5))
    ax.bar(x, per_image, width=0.9, color="0.75", label="tie points matched (tracks seen)")
    ax.bar(x, used, width=0.5, color="tab:blue", label="used by the block adjustment")
    ax.set_xlabel("image (flight order)")
    ax.set_ylabel("tie points per image")
    step = max(1, len(names) // 20)
    ax.set_xticks(x[::step], [n.rsplit(".", 1)[0] for n in names[::step]], rotation=60, fontsize=7)
    ax.set_xlim(-1, len(names))
    tw = ax.twinx()
    tw.plot(x, temperature, color="tab:red", lw=1.5, label="sensor temperature")
    tw.set_ylabel("sensor temperature (degC)", color="tab:red")
    tw.tick_params(axis="y", colors="tab:red")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = tw.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)
    ax.set_title("seneca: tie points per image (aerocal process)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


#: what :func:`keep` writes: name -> (step, output, kind); kind ``None`` for arrays and JSON
KEPT = {
    "images": ("ingest", "images", "images"),
    "observations": ("match", "observations", "observations"),
    "gcps": ("control", "gcps", "gcps"),
    "gcp_observations": ("control", "gcp_observations", "gcp_observations"),
    "calibration": ("calibrate", "calibration", None),
    "adjustment": ("adjust", "adjustment", None),
    "residuals": ("adjust", "residuals", None),
    "obs_weight": ("adjust", "obs_weight", None),
    "poses": ("adjust", "poses", "poses"),
    "points": ("adjust", "points", "points"),
}


def keep(run, work: Path) -> None:
    """Write the run's tables the report and ``--rediagnose`` read to ``work/kept`` (Parquet, .npy, JSON)."""
    folder = work / "kept"
    for name, (step, output, kind) in KEPT.items():
        values = run.runner.inputs({name: run.steps[step][output]})
        if kind is not None:
            tables.write(values.table(name), folder / f"{name}.parquet", kind)
        elif name in ("residuals", "obs_weight"):
            folder.mkdir(parents=True, exist_ok=True)
            np.save(folder / f"{name}.npy", values.array(name), allow_pickle=False)
        else:
            write_json_atomic(folder / f"{name}.json", values.json(name))


def read_kept(work: Path) -> dict:
    """What :func:`keep` wrote, by name."""
    folder, out = work / "kept", {}
    for name, (_, _, kind) in KEPT.items():
        if kind is not None:
            out[name] = tables.read(folder / f"{name}.parquet", kind)
        elif (folder / f"{name}.npy").is_file():
            out[name] = np.load(folder / f"{name}.npy", allow_pickle=False)
        else:
            out[name] = json.loads((folder / f"{name}.json").read_text())
    return out


def rediagnose(work: Path) -> list[str]:
    """The diagnose step of the run kept in ``work`` done again by this code, timed: result lines."""
    measured_path = work / "measured.json"
    if not measured_path.is_file():
        raise SystemExit(f"{measured_path} not found: run the benchmark with --work {work} first")
    summary = json.loads(measured_path.read_text())["summary"]
    cert = Certificate.from_dict(json.loads((Path(summary["out_dir"]) / "certificate.json").read_text()))
    kept = read_kept(work)
    images, gcps, gcp_obs, obs = kept["images"], kept["gcps"], kept["gcp_observations"], kept["observations"]
    weight, residuals, adjustment = kept["obs_weight"], kept["residuals"], kept["adjustment"]
    poses, points = kept["poses"], kept["points"]
    flight = json.loads((work / "seneca" / "flight.json").read_text())
    h, v = flight["gnss_sigma_m"]
    config = AdjustConfig(free=(), gnss_sigma_m=(h, h, v), attitude_sigma_deg=tuple(flight["imu_sigma_deg"]))
    # as aerocal.pipeline.diagnose_step: the block adjustment's screening and tie-point sigma, least squares
    scale = float(adjustment.get("tie_sigma_scale", 1.0))
    keep = screened_rows(obs, residuals, weight, scale, config.reject_chi2)
    obs = scale_tie_sigma(obs.take(pa.array(keep, pa.int64())), scale)
    config = dataclasses.replace(config, robust_loss="none", adaptive=False)
    dcfg = DiagnoseConfig()
    t0 = time.perf_counter()
    result = diagnose(images, obs, cert.camera, config, gcps, gcp_obs, dcfg, IOUncertainty.from_certificate(cert),
                      (poses, points))
    seconds = time.perf_counter() - t0
    twin = result.twin
    lines = [
        f"- the diagnose step's engine call on the kept run's inputs: {obs.num_rows} tie observations, "
        f"{images.num_rows} images, certificate {cert.camera.f:.2f} px, {dcfg.twins} twins (seed {dcfg.seed})",
        f"- time {seconds:.1f} s; peak memory of this process {peak_rss_mb():.0f} MB "
        f"(target of the city-scale work: 60 s)",
        f"- baseline sigma0 {result.sigma0_before:.3f}; named: {result.summary()}",
        f"- twin: {twin.get('summary')}",
    ]
    if twin.get("extended"):
        lines += ["", "| extension | size | bound | plausible | gaps closed |", "|---|---|---|---|---|"]
        for name, ext in twin["extended"].items():
            closed = ", ".join(f"{k} {100 * g:.0f} %" for k, g in ext["gap_closed"].items())
            lines.append(f"| {name} | {ext['physical']:.3g} {ext['unit']} | {ext['bound']:.3g} | "
                         f"{ext['plausible']} | {closed} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help=f"strips {QUICK_STRIPS} only")
    ap.add_argument("--work", type=Path, default=None,
                    help="keep the flight folder, store and run output here (default: a temporary folder, "
                    "removed at the end); given again, the measured run found there is reported again")
    ap.add_argument("--max-pairs-per-image", default="none",
                    help="the match step's cap on each image's candidate pairs (MatchStepConfig; 'none': every pair)")
    ap.add_argument("--rediagnose", action="store_true",
                    help="time the diagnosis again on the run kept in --work (see the module docstring)")
    args = ap.parse_args(argv)
    if args.rediagnose:
        if args.work is None:
            raise SystemExit("--rediagnose needs --work DIR, the folder of a kept run")
        record("seneca (real), diagnosis with the flight's twin", rediagnose(args.work.resolve()))
        return
    if not IMAGES.is_dir():
        raise SystemExit(f"{IMAGES} not found: the seneca images are needed")
    work = args.work.resolve() if args.work else Path(tempfile.mkdtemp(prefix="aerocal-seneca-"))
    work.mkdir(parents=True, exist_ok=True)
    measured_path = work / "measured.json"
    done = False
    try:
        if measured_path.exists():
            measured = json.loads(measured_path.read_text())
        else:
            folder, built = build_flight(work, args.quick)
            t0 = time.perf_counter()
            cap = None if args.max_pairs_per_image.lower() == "none" else int(args.max_pairs_per_image)
            config = ProcessConfig(match=MatchStepConfig(features=FeatureConfig(max_features=MAX_FEATURES),
                                                         max_pairs_per_image=cap))
            run = process(folder, config, certificate="none", out_dir=work / "run")
            summary = run.summary.to_json()
            keep(run, work)
            measured = {"summary": summary, "wall_s": time.perf_counter() - t0, "peak_main_mb": peak_rss_mb(),
                        "peak_children_mb": children_peak_mb(),
                        "built": {**built, "camera": built["camera"].to_dict()}}
            measured_path.write_text(json.dumps(measured, indent=1, default=str))
        summary, wall, built = measured["summary"], measured["wall_s"], measured["built"]
        built["camera"] = Camera.from_dict(built["camera"])
        peak_main, peak_children = measured["peak_main_mb"], measured["peak_children_mb"]

        run_dir = Path(summary["out_dir"])
        adj = json.loads((run_dir / "adjustment.json").read_text())
        # the calibration's own certificate (with its review), not the nominal camera a rejected one leaves
        cert = Certificate.from_dict(json.loads((run_dir / "calibration_certificate.json").read_text()))
        steps = summary["steps"]
        kept = read_kept(work)
        images, obs, cal = kept["images"], kept["observations"], kept["calibration"]
        residuals, poses = kept["residuals"], kept["poses"]

        order = np.argsort(images.column("time").to_numpy(), kind="stable")
        ids = images.column("image_id").to_numpy()[order]
        names = np.asarray(images.column("name").to_pylist())[order].tolist()
        temps = images.column("temperature_c").to_numpy(zero_copy_only=False).astype(float)[order]
        oid = obs.column("image_id").to_numpy()
        track = obs.column("track_id").to_numpy()
        n_max = int(max(ids.max(), oid.max())) + 1
        per_image = np.bincount(oid, minlength=n_max)[ids]
        used_rows = np.isfinite(np.asarray(residuals, dtype=float).reshape(len(oid), -1)).all(axis=1)
        used = np.bincount(oid[used_rows], minlength=n_max)[ids]
        _, track_len = np.unique(track, return_counts=True)
        _, track_len_used = np.unique(track[used_rows], return_counts=True)
        posed = np.isin(ids, poses.column("image_id").to_numpy())
        registered = int(np.sum(posed & (used > 0)))
        weak = [f"{n} ({u})" for n, u in zip(names, used, strict=True) if u < WEAK_TIE_POINTS]
        stem = "seneca_quick" if args.quick else "seneca"
        fig = tie_point_figure(names, per_image, used, temps, OUTPUT / f"{stem}_tie_points.png")
        table = OUTPUT / f"{stem}_per_image.csv"
        table.write_text("name,temperature_c,tie_points_matched,tie_points_used,posed\n" + "".join(
            f"{n},{t:g},{a},{b},{int(p)}\n"
            for n, t, a, b, p in zip(names, temps, per_image, used, posed, strict=True)))

        ca = cal["adjustment"]
        sub = cal["subset"]
        orient = steps["orient"].get("extra", {})
        match = steps["match"].get("extra", {})
        lines = [
            f"seneca (real): {built['images']} JPEGs {built['camera'].width}x{built['camera'].height} "
            f"of a Canon PowerShot ELPH 300 HS, temperature {np.nanmin(temps):.0f}-{np.nanmax(temps):.0f} degC"
            + (f", strips {QUICK_STRIPS} only" if args.quick else "")
            + f"; left out (another size): {', '.join(built['left_out']) or 'none'}; no GCPs",
            f"- nothing hand-written: nominal camera f {built['camera'].f:.1f} px ({built['camera_source']}); "
            f"flying height {built['height_agl_m']:.1f} m ({built['height_source']}); GNSS sigma "
            f"{built['gnss_sigma_m']} m, attitude not used",
            f"- `aerocal.pipeline.process`, default configuration but SIFT capped at {MAX_FEATURES} keypoints per "
            f"image, candidate pairs per image {args.max_pairs_per_image}, certificate `none` (self-calibration), "
            "local Dask cluster of 2 workers, full-size images",
            "",
            "| step | status | time |",
            "|---|---|---|",
        ]
        for step, info in steps.items():
            secs = info.get("seconds")
            lines.append(f"| {step} | {info.get('status')} | "
                         + (f"{secs:.1f} s |" if secs is not None else f"{info.get('reason', '')} |"))
        lines += [
            f"| **total (wall, flow start to report)** | | **{wall:.1f} s** |",
            "",
            f"- peak memory: main process {peak_main:.0f} MB, largest child (Dask worker) {peak_children:.0f} MB",
            f"- matching: {match.get('pairs', '?')} candidate pairs, {obs.num_rows} observations, "
            f"{len(track_len)} tracks (length min/median/max {_stats(track_len)})",
            f"- images registered (posed by the block adjustment with tie points): {registered} of "
            f"{images.num_rows}; orient: {orient.get('method')}, images without observations "
            f"{orient.get('images_without_observations')}",
            f"- images with fewer than {WEAK_TIE_POINTS} tie points used (held by their GNSS/attitude priors): "
            f"{len(weak)}{': ' + ', '.join(weak) if weak else ''}",
            f"- tie points (tracks) per image, min / median / max: matched {_stats(per_image)}, used by the "
            f"block adjustment {_stats(used)}; tracks used {len(track_len_used)} (length min/median/max "
            f"{_stats(track_len_used)})",
            f"- calibration sub-block: {len(sub['image_ids'])} images ({'; '.join(sub.get('reasons', [])[:2])})",
            f"- calibration: reprojection RMS {ca['reprojection_rms_px']:.3f} px, sigma0 {ca['sigma0']:.3f}, "
            f"dof {ca['dof']}, blunders rejected {_rejected(ca.get('selection'))}",
            f"- block adjustment (fixed IO): reprojection RMS {adj['reprojection_rms_px']:.3f} px, sigma0 "
            f"{adj['sigma0']:.3f}, dof {adj['dof']}, converged {adj.get('converged')} in {adj.get('iterations')} "
            f"iterations, blunders rejected {_rejected(adj.get('selection'))}",
            f"- certificate: f {cert.camera.f:.2f} +- {cert.sigmas.get('f', float('nan')):.2f} px, cx "
            f"{cert.camera.cx:.2f} +- {cert.sigmas.get('cx', float('nan')):.2f} px, cy {cert.camera.cy:.2f} +- "
            f"{cert.sigmas.get('cy', float('nan')):.2f} px; estimated {', '.join(cert.estimated)}",
        ]
        if cert.thermal is not None:
            m = cert.thermal.model
            lines.append(f"- thermal slope: df/dT {m.df_dt:.4f} +- {cert.thermal.sigmas.get('df_dt', float('nan')):.4f}"
                         f" px/degC (T0 {m.t0:.1f} degC)")
        else:
            dropped = [s for s in ca.get("selection") or [] if s.startswith("dropped df/dT")]
            lines.append(f"- thermal slope: not in the certificate ({dropped[0] if dropped else 'not estimated'})")
        review = cert.review.to_dict() if cert.review is not None else {}
        lines += [
            f"- selection (calibration): {'; '.join(ca.get('selection') or []) or 'none'}",
            f"- review: {review.get('status')}; overdispersion {cal.get('overdispersion', 1.0):.1f}; "
            f"{'; '.join(review.get('problems', []) + review.get('notes', []))}",
            f"- certificate used by the block: {summary.get('certificate_reason')}",
            f"- diagnosis: {summary.get('diagnosis')}",
            f"- recorded EO checks: {recorded_eo_text(summary.get('recorded_eo') or {})}",
            f"- figure: `{fig.relative_to(ROOT)}`; per image: `{table.relative_to(ROOT)}`",
        ]
        record("seneca (real), end to end" + (" (quick)" if args.quick else ""), lines)
        done = True
    finally:
        if done and args.work is None:
            shutil.rmtree(work, ignore_errors=True)
        else:
            print(f"work folder kept: {work} (report it again with --work {work})")


if __name__ == "__main__":
    main()
