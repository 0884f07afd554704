"""pycolmap's own pipeline vs aerocal on the same rendered frames: time, registered images, check points.

Both pipelines run in this process, one after the other, on the same frames, GCPs and machine:

* **COLMAP** (pycolmap, CPU, its defaults): every 16-bit frame is converted to an 8-bit PNG with a
  plain per-frame min-max linear stretch (what a user feeding COLMAP would do; COLMAP reads 8-bit
  images); ``extract_features`` (SIFT) with one shared SIMPLE_RADIAL camera seeded from the nominal
  camera of ``camera.json`` (f, cx, cy, k1 = 0; COLMAP refines f and k1, its default); the recorded GNSS
  positions written into the database as pose priors and ``match_spatial``; ``incremental_mapping``
  (its local and global bundle adjustments). The largest model is georeferenced on the control GCPs
  triangulated in it (:func:`aerocal.orient.georeference`, 7-parameter similarity) and the check
  points are triangulated from their image measurements with COLMAP's refined camera.
* **aerocal**: ingest, ``aerocal.pipeline.match_step.match_images`` (enhance, SIFT on a local Dask cluster of 2 workers,
  footprint pairs, verification, tracks), ``orient_from_priors``, then the adjustments of
  ``process_flight``: self-calibration on the calibration sub-block (the whole block up to 44 images)
  and the full-block adjustment with that IO fixed, GNSS/IMU priors and control GCPs weighted, Huber
  loss with blunder screening, the block's tie tracks thinned as the flow does for matched flights (the
  others intersected afterwards). Check-point errors come from the block adjustment.

The one departure from COLMAP's defaults is the spatial matcher's ``max_distance``: its default, 100 m,
keeps only the next frame of a strip on this flight (frames ~98 m apart at 850 m, strips ~280 m apart);
it is set to the ground diagonal of a frame's footprint (``--spatial-max-distance`` overrides it).

Datum of COLMAP's model (``--datum``): ``gcps`` (the control GCPs, at least 3 seen in 2 registered
images), ``gnss`` (similarity on the registered images' recorded GNSS positions and whatever control
GCPs the model holds, weighted by their sigmas: COLMAP's ``model_aligner`` on GNSS), ``auto`` (default:
``gcps`` when at least 3 control GCPs are in the model, else ``gnss``). Sub-blocks of the frames nearest
the centre hold few control GCPs (2 in the central 100 frames).

Two departures from COLMAP's defaults can be asked for, to tell where its result comes from:
``--colmap-input wallis`` feeds it aerocal's enhanced 8-bit frames instead of the min-max stretch, and
``--colmap-fixed-camera`` holds the nominal camera fixed in its mapping.

Run: ``python -m benchmarks.colmap_bench [--frames N] [--source DIR]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from aerocal import tables
from aerocal.adjust import adjust, adjust_fixed_io, select_images
from aerocal.assess import point_residuals, triangulate_gcps
from aerocal.calibrate.subset import SubsetConfig, propose_subset
from aerocal.camera import Camera, LinearThermalModel, from_pycolmap
from aerocal.enhance import EnhanceConfig, enhance, stretch_params
from aerocal.geometry import estimate_similarity
from aerocal.ingest import ingest_folder, read_raw
from aerocal.orient import georeference, orient_from_priors
from aerocal.pipeline.config import ProcessConfig, with_flight_sigmas
from aerocal.pipeline.match_step import match_images, terrain_height
from aerocal.poses import poses_arrays, poses_table
from aerocal.products.mosaic import frames_from_poses
from benchmarks.city_bench import rendered_flight, scratch_folder, subset_folder
from benchmarks.common import flight_document, record

AXES = ("E", "N", "Up")


@dataclass
class PipelineRun:
    """What one pipeline produced on the flight: stage times (s), counts and check-point errors (m)."""

    name: str
    stages: dict[str, float] = field(default_factory=dict)
    n_images: int = 0
    registered: int = 0
    tie_points: int = 0
    observations: int = 0
    check_ids: list[str] = field(default_factory=list)
    check_errors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    notes: list[str] = field(default_factory=list)

    @property
    def total(self) -> float:
        return float(sum(self.stages.values()))

    def set_checks(self, ids, errors) -> None:
        """Keep the check points that were triangulated (finite errors, metres, E N Up)."""
        e = np.asarray(errors, dtype=float).reshape(-1, 3)
        ok = np.isfinite(e).all(axis=1)
        self.check_ids, self.check_errors = [i for i, k in zip(ids, ok, strict=True) if k], e[ok]

    def rmse(self, ids: list[str] | None = None) -> np.ndarray:
        """Check-point RMSE per axis (E, N, Up; metres) over ``ids`` (default: every triangulated one)."""
        keep = [k for k, i in enumerate(self.check_ids) if ids is None or i in ids]
        e = self.check_errors[keep]
        e = e[np.isfinite(e).all(axis=1)]
        return np.sqrt(np.mean(e**2, axis=0)) if len(e) else np.full(3, np.nan)


class _Stopwatch:
    def __init__(self, run: PipelineRun) -> None:
        self.run = run

    def __call__(self, stage: str):
        run = self.run

        class _Stage:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                run.stages[stage] = run.stages.get(stage, 0.0) + time.perf_counter() - self.t0
                print(f"  {run.name}: {stage} {run.stages[stage]:.1f} s", flush=True)

        return _Stage()


# ----------------------------------------------------------------------------------------- COLMAP
def pycolmap_version() -> str:
    return str(pycolmap.__version__)


def frames_to_png(paths: list[str], out: Path, method: str = "none") -> list[str]:
    """Each frame as an 8-bit PNG in ``out``; the PNG names.

    ``method`` is :class:`aerocal.enhance.EnhanceConfig`'s: ``"none"`` (default) a plain per-frame
    min-max linear stretch, what a user feeding COLMAP would do; ``"wallis"`` aerocal's own enhancement
    (dataset-wide 2 % stretch and Wallis filter), to tell the conversion's share from COLMAP's.
    """
    config = EnhanceConfig(method=method)
    params = None if method == "none" else stretch_params(paths, percent=config.percent, loader=read_raw)
    out.mkdir(parents=True, exist_ok=True)
    names = []
    for p in paths:
        name = Path(p).stem + ".png"
        cv2.imwrite(str(out / name), enhance(read_raw(p), params, config))
        names.append(name)
    return names


def footprint_diagonal_m(images, camera, gcps, flight: dict) -> float:
    """Ground diagonal of a frame's footprint (metres) at the terrain height the matcher also uses."""
    z = images.column("gnss_z").to_numpy(zero_copy_only=False).astype(float)
    height = float(np.nanmean(z)) - terrain_height(images, gcps, flight)
    return height * float(np.hypot(camera.width, camera.height)) / camera.f


def _apply_similarity(poses, sim, crs):
    ids, R, C = poses_arrays(poses)
    return poses_table(ids, np.einsum("nij,jk->nik", R, sim.R.T), sim.apply(C), crs)


def georeference_colmap(local_poses, camera, images, gcps, gobs, datum: str, gnss_sigma: tuple[float, float]):
    """COLMAP's model in the flight CRS: (poses, similarity, sentence saying how)."""
    crs = tables.crs_of(gcps) or tables.crs_of(images)
    g = gcps.to_pydict()
    control = {gid: k for k, gid in enumerate(g["gcp_id"]) if g["role"][k] == "control"}
    in_model = triangulate_gcps(frames_from_poses(local_poses, camera), gobs)
    ctrl = [gid for gid in in_model if gid in control]
    if datum == "auto":
        datum = "gcps" if len(ctrl) >= 3 else "gnss"
    if datum == "gcps":
        poses, sim = georeference(local_poses, camera, gcps, gobs, crs)
        return poses, sim, f"similarity on {len(ctrl)} control GCPs triangulated in the model"
    ids = local_poses.column("image_id").to_numpy()
    C_model = np.column_stack([local_poses.column(c).to_numpy() for c in ("X", "Y", "Z")])
    im = images.to_pydict()
    where = {int(i): k for k, i in enumerate(im["image_id"])}
    C_gnss = np.array([[im[c][where[int(i)]] for c in ("gnss_x", "gnss_y", "gnss_z")] for i in ids], float)
    src = [C_model] + [in_model[gid][None] for gid in ctrl]
    dst = [C_gnss] + [np.array([[g["X"][control[gid]], g["Y"][control[gid]], g["Z"][control[gid]]]])
                      for gid in ctrl]
    s_gnss = float(np.hypot(*gnss_sigma) / np.sqrt(2.0))
    s_gcp = [float(np.sqrt((2 * g["sigma_x"][control[gid]] ** 2 + g["sigma_z"][control[gid]] ** 2) / 3))
             for gid in ctrl]
    w = np.concatenate([np.full(len(C_model), s_gnss**-2), np.asarray(s_gcp, float) ** -2])
    sim = estimate_similarity(np.vstack(src), np.vstack(dst), weights=w)
    return (_apply_similarity(local_poses, sim, crs), sim,
            f"similarity on the recorded GNSS positions of {len(ids)} registered images and {len(ctrl)} "
            "control GCPs triangulated in the model, weighted by their sigmas (fewer than 3 control GCPs "
            "in the model)")


def run_colmap(folder: Path, work: Path, datum: str = "auto", max_distance: float | None = None,
               refine_camera: bool = True, conversion: str = "none") -> PipelineRun:
    """pycolmap's pipeline on the flight's frames (module docstring).

    ``conversion``: how the 16-bit frames become 8-bit PNGs (:func:`frames_to_png`).
    ``refine_camera=False`` departs from COLMAP's defaults: the nominal camera is held fixed in mapping
    and bundle adjustment (what aerocal's notes recommend for flat nadir thermal blocks).
    """
    pycolmap.logging.minloglevel = 2
    run = PipelineRun("COLMAP" if refine_camera else "COLMAP (camera fixed)")
    clock = _Stopwatch(run)
    # the flight's records (not part of COLMAP's pipeline: the image list, GNSS and GCPs it is given)
    res = ingest_folder(folder)
    images, gcps, gobs = res.images, res.gcps, res.gcp_observations
    flight = flight_document(folder)
    nominal = Camera.from_dict(json.loads((folder / "camera.json").read_text())["camera"])
    run.n_images = images.num_rows
    if max_distance is None:
        max_distance = footprint_diagonal_m(images, nominal, gcps, flight)
    png = work / "colmap-png"
    db_path = work / "colmap.db"
    with clock("8-bit conversion"):
        names = frames_to_png(images.column("path").to_pylist(), png, conversion)
    with clock("features (SIFT)"):
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        reader.camera_params = f"{nominal.f},{nominal.cx},{nominal.cy},0"
        pycolmap.extract_features(str(db_path), str(png), image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, device=pycolmap.Device.cpu)
    gnss_sigma = tuple(float(v) for v in (flight.get("gnss_sigma_m") or (1.0, 1.0)))
    with clock("matching (spatial)"):
        im = images.to_pydict()
        xyz = {Path(n).stem: (x, y, z) for n, x, y, z in zip(im["name"], im["gnss_x"], im["gnss_y"], im["gnss_z"],
                                                               strict=True)}
        db = pycolmap.Database.open(str(db_path))
        cov = np.diag([gnss_sigma[0] ** 2, gnss_sigma[0] ** 2, gnss_sigma[-1] ** 2])
        for image in db.read_all_images():
            prior = pycolmap.PosePrior()
            prior.corr_data_id = pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, image.camera_id),
                                                 image.image_id)
            prior.position = np.asarray(xyz[Path(image.name).stem], dtype=float)
            prior.position_covariance = cov
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
            db.write_pose_prior(prior)
        db.close()
        pairing = pycolmap.SpatialPairingOptions()
        pairing.max_distance = float(max_distance)
        pycolmap.match_spatial(str(db_path), pairing_options=pairing, device=pycolmap.Device.cpu)
    db = pycolmap.Database.open(str(db_path))
    n_pairs = db.num_matched_image_pairs()
    n_verified = sum(len(g.inlier_matches) > 0 for g in db.read_two_view_geometries()[1])
    n_keypoints = db.num_keypoints()
    db.close()
    with clock("incremental mapping + BA"):
        (work / "colmap-sparse").mkdir(exist_ok=True)
        opts = pycolmap.IncrementalPipelineOptions()
        if not refine_camera:
            opts.ba_refine_focal_length = opts.ba_refine_extra_params = False
            opts.mapper.abs_pose_refine_focal_length = opts.mapper.abs_pose_refine_extra_params = False
        recs = pycolmap.incremental_mapping(str(db_path), str(png), str(work / "colmap-sparse"), options=opts)
    sizes = sorted((r.num_reg_images() for r in recs.values()), reverse=True)
    run.notes += [
        f"{n_keypoints} SIFT keypoints; spatial pairs within {max_distance:.0f} m (at most "
        f"{pairing.max_num_neighbors} neighbours): {n_pairs} matched, {n_verified} with a verified geometry",
        f"{len(recs)} model(s), registered images per model: {sizes}",
    ]
    if not recs:
        run.notes.append("incremental mapping built no model")
        return run
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    run.registered = rec.num_reg_images()
    run.tie_points = rec.num_points3D()
    run.observations = int(sum(p.track.length() for p in rec.points3D.values()))
    cam = from_pycolmap(next(iter(rec.cameras.values())), nominal.pixel_size_mm)
    rec.update_point_3d_errors()
    run.notes.append(f"COLMAP's refined camera: f {cam.f:.2f} px (nominal {nominal.f:.2f}), k1 {cam.k1:.5f}; "
                     f"mean reprojection error {rec.compute_mean_reprojection_error():.3f} px")
    with clock("georeference + check points"):
        by_stem = {Path(n).stem: int(i) for n, i in zip(im["name"], im["image_id"], strict=True)}
        ids, Rs, Cs = [], [], []
        for image in rec.images.values():
            if not image.has_pose:
                continue
            T = image.cam_from_world()
            R = np.asarray(T.rotation.matrix())
            ids.append(by_stem[Path(image.name).stem])
            Rs.append(R)
            Cs.append(-R.T @ np.asarray(T.translation))
        order = np.argsort(ids)
        local = poses_table(np.asarray(ids)[order], np.stack(Rs)[order], np.stack(Cs)[order])
        try:
            poses, sim, how = georeference_colmap(local, cam, images, gcps, gobs, datum, gnss_sigma)
        except Exception as exc:  # too few control points for the datum asked
            run.notes.append(f"not georeferenced: {exc}")
            return run
        xyz_chk = triangulate_gcps(frames_from_poses(poses, cam), gobs)
        pr = point_residuals(xyz_chk, gcps, role="check")
    run.set_checks(pr.ids, pr.residuals)
    ctrl = np.asarray(point_residuals(xyz_chk, gcps, role="control").residuals).reshape(-1, 3)
    fit = (f"control-point RMSE after it {np.round(np.sqrt(np.mean(ctrl**2, axis=0)), 3).tolist()} m"
           if len(ctrl) else "no control GCP in the model")
    gnss = np.column_stack([images.column(c).to_numpy(zero_copy_only=False) for c in ("gnss_x", "gnss_y", "gnss_z")])
    row = {int(i): k for k, i in enumerate(im["image_id"])}
    C_geo = np.column_stack([poses.column(c).to_numpy() for c in ("X", "Y", "Z")])
    d = C_geo - gnss[[row[int(i)] for i in poses.column("image_id").to_numpy()]]
    run.notes.append(f"datum: {how}; scale {sim.scale:.3f}; {fit}; georeferenced projection centres minus "
                     f"recorded GNSS, RMS E/N/Up {np.round(np.sqrt(np.mean(d**2, axis=0)), 2).tolist()} m")
    return run


# ---------------------------------------------------------------------------------------- aerocal
def run_aerocal(folder: Path) -> PipelineRun:
    """aerocal's pipeline steps up to the full-block adjustment (:mod:`aerocal.pipeline`), with its defaults."""
    run = PipelineRun("aerocal")
    clock = _Stopwatch(run)
    config = ProcessConfig()
    with clock("ingest"):
        res = ingest_folder(folder)
        images, gcps, gobs, camera = res.images, res.gcps, res.gcp_observations, res.camera
        flight = flight_document(folder)
    run.n_images = images.num_rows
    with clock("enhance + match (Dask, 2 workers)"):
        kp, matches, obs, n_pairs = match_images(images, camera, gcps, flight, config.match)
    with clock("orient (GNSS/IMU)"):
        orient_from_priors(images)
    cal_cfg = with_flight_sigmas(config.calibration.adjust, flight)
    blk_cfg = with_flight_sigmas(config.block.adjust, flight)
    cal_cfg = dataclasses.replace(cal_cfg, robust_loss=config.matched_robust_loss)
    blk_cfg = dataclasses.replace(blk_cfg, robust_loss=config.matched_robust_loss,
                                  tie_thinning=config.matched_tie_thinning)
    with clock("self-calibration (sub-block)"):
        if images.num_rows <= config.calibration.whole_flight_max_images:
            ids = images.column("image_id").to_pylist()
            why = f"the whole block ({len(ids)} images)"
        else:
            scfg = dataclasses.replace(SubsetConfig(), height_agl_m=float(flight["height_agl_m"]))
            ids = propose_subset(images, camera, gcps, scfg).image_ids
            why = f"a sub-block of {len(ids)} images"
        cal = adjust(select_images(images, ids), select_images(obs, ids), camera, cal_cfg, gcps,
                     select_images(gobs, ids))
    with clock("block adjustment (fixed IO)"):
        thermal = cal.thermal if isinstance(cal.thermal, LinearThermalModel) else None
        blk = adjust_fixed_io(images, obs, cal.camera, blk_cfg, gcps, gobs, thermal)
    run.registered = blk.poses.num_rows
    run.tie_points = blk.points.num_rows
    run.observations = int(np.isfinite(blk.residuals).all(axis=1).sum())
    run.set_checks(blk.check_ids, blk.check_errors)
    per_image = np.bincount(obs.column("image_id").to_numpy().astype(int),
                            minlength=int(images.column("image_id").to_numpy().max()) + 1)
    seen = int(np.sum(per_image[images.column("image_id").to_numpy().astype(int)] > 0))
    run.notes += [
        f"{kp.num_rows} SIFT keypoints; {n_pairs} footprint pairs, {matches.num_rows} verified matches",
        f"{seen} of {images.num_rows} images hold tie observations; poses from the recorded GNSS/IMU",
        f"self-calibration on {why}: f {cal.camera.f:.2f} px, sigma0 {cal.sigma0:.3f}"
        + (f", df/dT {thermal.df_dt:.3f} px/degC" if thermal else ""),
        f"block: sigma0 {blk.sigma0:.3f}, reprojection RMS {blk.reprojection_rms:.3f} px, "
        f"rho {np.round(blk.rho, 2).tolist()}; {'; '.join(blk.selection) or 'no blunders screened'}",
    ]
    return run


# ----------------------------------------------------------------------------------------- report
def _fmt(v: np.ndarray) -> str:
    return " / ".join("n/a" if not np.isfinite(x) else f"{x:.3f}" for x in v)


def comparison(colmap: PipelineRun, ours: PipelineRun) -> list[str]:
    """Markdown lines: stage times, totals, counts, check-point RMSE and the ratios."""
    lines = ["| pipeline | stage | time |", "|---|---|---|"]
    for run in (colmap, ours):
        lines += [f"| {run.name} | {s} | {t:.1f} s |" for s, t in run.stages.items()]
        lines.append(f"| **{run.name}** | **total** | **{run.total:.1f} s** |")
    common = sorted(set(colmap.check_ids) & set(ours.check_ids))
    lines += ["", "| | COLMAP | aerocal |", "|---|---|---|",
              f"| registered images | {colmap.registered} of {colmap.n_images} | {ours.registered} of "
              f"{ours.n_images} |",
              f"| tie points (observations) | {colmap.tie_points} ({colmap.observations}) | {ours.tie_points} "
              f"({ours.observations}) |",
              f"| check points triangulated | {len(colmap.check_ids)} | {len(ours.check_ids)} |",
              f"| check RMSE E / N / Up, own points (m) | {_fmt(colmap.rmse())} | {_fmt(ours.rmse())} |",
              f"| check RMSE E / N / Up, the {len(common)} common points (m) | {_fmt(colmap.rmse(common))} | "
              f"{_fmt(ours.rmse(common))} |", ""]
    ratio = colmap.rmse(common) / ours.rmse(common) if common else np.full(3, np.nan)
    lines += [f"- time ratio COLMAP / aerocal: {colmap.total / ours.total:.2f}x (target >= 3x)",
              f"- accuracy ratio COLMAP RMSE / aerocal RMSE (common check points), E / N / Up: {_fmt(ratio)} "
              "(target >= 1: aerocal at least as accurate)", ""]
    for run in (colmap, ours):
        lines += [f"- {run.name}: {n}" for n in run.notes]
    return lines + [""]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=None, help="only the N frames nearest the block centre")
    ap.add_argument("--source", type=Path, default=None,
                    help="a rendered flight folder (default: conte-city seed 0, rendered on first use)")
    ap.add_argument("--datum", choices=("auto", "gcps", "gnss"), default="auto",
                    help="how COLMAP's model is georeferenced (module docstring)")
    ap.add_argument("--spatial-max-distance", type=float, default=None,
                    help="COLMAP's spatial matching radius, metres (default: a footprint's ground diagonal)")
    ap.add_argument("--colmap-input", choices=("none", "wallis"), default="none",
                    help="8-bit frames COLMAP reads: none = per-frame min-max stretch (default), "
                         "wallis = aerocal's enhancement (a departure, to isolate the conversion's share)")
    ap.add_argument("--colmap-fixed-camera", action="store_true",
                    help="hold the nominal camera fixed in COLMAP's mapping (a departure from its defaults)")
    args = ap.parse_args(argv)
    with scratch_folder("work-colmap-") as work:
        full = args.source or rendered_flight()
        folder = subset_folder(full, args.frames, work) if args.frames else full
        n = len(list((folder / "images").iterdir()))
        t0 = time.perf_counter()
        colmap = run_colmap(folder, work, args.datum, args.spatial_max_distance,
                            refine_camera=not args.colmap_fixed_camera, conversion=args.colmap_input)
        ours = run_aerocal(folder)
        wall = time.perf_counter() - t0
        lines = [f"{full.name}: {n} frames 640x480 16-bit thermal"
                 + (f" ({n} nearest the centre)" if args.frames else "")
                 + "; both pipelines in this run, one after the other, 2 cores each (COLMAP's threads, "
                 "aerocal's 2 Dask workers)", "",
                 *comparison(colmap, ours),
                 f"- COLMAP {pycolmap_version()}: pycolmap defaults, CPU SIFT; frames converted to 8-bit PNG "
                 + ("by a per-frame min-max stretch" if args.colmap_input == "none" else
                    "by aerocal's enhancement (dataset-wide 2 % stretch + Wallis)")
                 + " (timed); one shared SIMPLE_RADIAL camera seeded from camera.json, "
                 + ("held fixed" if args.colmap_fixed_camera else "refined by COLMAP")
                 + "; GNSS positions as pose priors for spatial matching only (mapping ignores "
                 "them, its default); the flight's records (image list, GNSS, GCPs) read untimed",
                 f"- benchmark wall time {wall:.0f} s", ""]
        record("COLMAP comparison: pycolmap's pipeline vs aerocal on rendered conte-city frames", lines)


if __name__ == "__main__":
    main()
