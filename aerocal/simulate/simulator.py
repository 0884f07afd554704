"""Simulate a flight: scene, plan, sensors, hidden effects, and what the aircraft and camera recorded.

:func:`simulate_flight` builds everything in memory (:class:`SimulatedFlight`); :func:`write_flight`
writes a flight folder that the processing pipeline reads like a real one::

    flight/
      images/IMG_0001.tif ...     rendered frames (images mode only)
      observations/*.parquet      images, observations, gcps, gcp_observations (observations mode)
      eo.csv                      recorded GNSS/IMU and sensor temperature
      gcps.csv, gcp_list.txt      surveyed ground control (OpenDroneMap format for the latter)
      camera.json                 camera identity and the manufacturer's nominal camera
      flight.json                 plan metadata a pilot would hand over (no truth)
      truth.json, truth/          the true parameters and effects: read by tests and studies only

Processing code never reads ``truth.json`` or ``truth/``.
"""

from __future__ import annotations

import datetime as dt
import math
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.camera import Camera
from aerocal.effects import bertram_refraction_k, image_rotation, normalise_effects, thermal_rotation_angle
from aerocal.geometry import (
    R_cw_to_dji_gimbal,
    R_cw_to_opk,
    projected_to_lonlat,
)
from aerocal.io import write_json_atomic
from aerocal.pipeline.dataset import MemoryDataset
from aerocal.poses import poses_table
from aerocal.products.dsm import Dsm, write_dsm
from aerocal.simulate.exposure import Exposure
from aerocal.simulate.flight_plan import Trajectory, footprint_m, overlaps, plan_flight
from aerocal.simulate.measured import trajectory
from aerocal.simulate.observations import Measurements, observe_points, place_control, sample_surface_points
from aerocal.simulate.presets import FlightSpec, get_preset
from aerocal.simulate.rendered_frames import render_flight_images
from aerocal.simulate.scene import SceneConfig, make_scene
from aerocal.simulate.sensors import recorded_exterior, recorded_R_cw

MODES = ("observations", "images")


class SimulationError(ValueError):
    """Bad simulation input (mode, size, output folder); the message names it and the fix."""


@dataclass
class SimulatedFlight:
    """A simulated flight in memory: what was recorded (tables) and what was true (``truth``)."""

    spec: FlightSpec
    seed: int
    effects: dict[str, tuple[float, ...]]
    crs: str
    scene: object
    bounds: tuple[float, float, float, float]
    trajectory: Trajectory
    exposures: list[Exposure]
    temperature_true: np.ndarray
    images: pa.Table
    observations: pa.Table
    gcps: pa.Table
    gcp_observations: pa.Table
    tie: Measurements
    gcp_true: np.ndarray
    truth: dict = field(default_factory=dict)

    @property
    def camera_nominal(self) -> Camera:
        return self.spec.camera_nominal


def _true_camera(spec: FlightSpec, effects: dict[str, tuple[float, ...]], temperature: float) -> Camera:
    cam = spec.camera_true
    dt_c = temperature - spec.sensors.reference_temperature_c
    f, cx, cy = cam.f, cam.cx, cam.cy
    if "thermal_focal" in effects:
        f += effects["thermal_focal"][0] * dt_c
    if "thermal_principal_point" in effects:
        cx += effects["thermal_principal_point"][0] * dt_c
        cy += effects["thermal_principal_point"][1] * dt_c
    b1, b2 = cam.b1, cam.b2
    if "affinity_skew" in effects:
        b1 += effects["affinity_skew"][0]
        b2 += effects["affinity_skew"][1]
    k3 = cam.k3 + (effects["radial_k3"][0] if "radial_k3" in effects else 0.0)
    return cam.replace(f=f, cx=cx, cy=cy, b1=b1, b2=b2, k3=k3)


def _make_scene(spec: FlightSpec, margin_m: float, seed: int):
    s = spec.scene
    width = spec.area_m[0] + 2 * margin_m
    height = spec.area_m[1] + 2 * margin_m
    cfg = SceneConfig(
        width_m=width, height_m=height, cell_m=s.cell_m, origin_e=s.origin_e, origin_n=s.origin_n, crs=s.crs,
        terrain_relief_m=s.terrain_relief_m, terrain_mean_m=s.terrain_mean_m,
        building_density=s.building_density, building_height_m=s.building_height_m,
        vegetation_density=s.vegetation_density, flat=s.flat,
    )
    scene = make_scene(cfg, seed=seed)
    bounds = (s.origin_e + margin_m, s.origin_n + margin_m,
              s.origin_e + margin_m + spec.area_m[0], s.origin_n + margin_m + spec.area_m[1])
    return scene, bounds


def _select_compact(traj: Trajectory, n: int) -> np.ndarray:
    """The ``n`` stations nearest to the block centre, in time order: a compact sub-block."""
    centre = np.median(traj.C[:, :2], axis=0)
    d = np.linalg.norm(traj.C[:, :2] - centre, axis=1)
    return np.sort(np.argsort(d, kind="stable")[:n])


def simulate_flight(
    preset: str | FlightSpec,
    seed: int = 0,
    effects: dict[str, object] | None = None,
    max_images: int | None = None,
    source: str | None = None,
) -> SimulatedFlight:
    """Simulate ``preset`` with hidden ``effects``.

    Args:
        preset: a preset's name (:data:`aerocal.simulate.presets.PRESETS`) or a :class:`FlightSpec`.
        seed: of every random draw (scene, trajectory, sensor noise, measurements): the same seed, the same flight.
        effects: ``{name: magnitude}`` in the catalogue's units (:mod:`aerocal.effects`), acting on the
            measurements and the recorded exterior orientation; processing is never told them.
        max_images: keep the frames nearest the block centre (at least 2); ``None``: every frame.
        source: the image folder of a measured preset (``seneca``).

    Returns:
        :class:`SimulatedFlight`: the tables a flight folder holds, the true exposures and camera, the scene.

    Raises:
        PresetError: an unknown preset. EffectError: an unknown effect or a magnitude of the wrong shape.
        SimulationError: ``max_images`` below 2.
    """
    spec = get_preset(preset, source) if isinstance(preset, str) else preset
    fx = normalise_effects(effects)
    if max_images is not None and max_images < 2:
        raise SimulationError(f"--max-images must be at least 2, got {max_images}")
    seeds = np.random.SeedSequence(seed).spawn(6)
    rng_plan, rng_sens, rng_tie, rng_gcp, rng_temp = (np.random.default_rng(s) for s in seeds[1:])

    _, across, along = footprint_m(spec.camera_nominal, spec.plan.height_agl_m)
    margin = 0.75 * math.hypot(across, along) + 50.0
    scene, bounds = _make_scene(spec, margin, seed=int(seeds[0].generate_state(1)[0]))
    terrain = spec.scene.terrain_mean_m
    if "stations" in spec.extra:  # a measured flight: its recorded stations are the truth

        traj = trajectory(spec.extra["stations"])
    else:
        traj = plan_flight(spec.plan, spec.camera_nominal, bounds, terrain, rng_plan)
    selected = np.arange(len(traj))
    if max_images is not None and max_images < len(traj):
        selected = _select_compact(traj, max_images)
        traj = traj.subset(selected)
    N = len(traj)

    t_true = spec.sensors.temperature.true_at(traj.time_s)
    t_rec = spec.sensors.temperature.recorded_at(traj.time_s, rng_temp)
    if "stations" in spec.extra:  # the camera's own readings (integer degC) stand for the truth and the record
        t_true = np.asarray(spec.extra["stations"]["temperature"], dtype=float)[selected]
        t_rec = t_true.copy()
    readout = fx["rolling_shutter"][0] if "rolling_shutter" in fx else 0.0
    refr = fx.get("refraction", (0.0,))[0]
    exposures = []
    for i in range(N):
        k = bertram_refraction_k(float(traj.C[i, 2]), terrain) if refr else 0.0
        R_cw = traj.R_cw[i]
        if "thermal_rotation" in fx:  # the image turns about the principal point: the camera about its axis
            dt_c = float(t_true[i]) - spec.sensors.reference_temperature_c
            theta = thermal_rotation_angle(fx["thermal_rotation"][0], dt_c, spec.camera_true.corner_radius)
            R_cw = image_rotation(theta) @ R_cw
        exposures.append(Exposure(
            image_id=i + 1, camera=_true_camera(spec, fx, float(t_true[i])), R_cw=R_cw, C=traj.C[i],
            velocity=traj.velocity[i], readout_s=readout, refraction_k=k,
        ))

    pos_rec, R_rec = recorded_exterior(traj.C, traj.R_cw, traj.velocity, spec.sensors, fx, rng_sens)

    # tie points: enough surface points for ~points_per_image measurements per frame
    cover = (traj.C[:, 0].min() - across, traj.C[:, 1].min() - across,
             traj.C[:, 0].max() + across, traj.C[:, 1].max() + across)
    cover_area = (cover[2] - cover[0]) * (cover[3] - cover[1])
    n_points = int(spec.points_per_image * cover_area / (across * along))
    pts = sample_surface_points(scene, cover, n_points, rng_tie)
    radius = 0.75 * math.hypot(across, along)
    tie = observe_points(exposures, pts, spec.sensors.tie_sigma_px, rng_tie, radius)
    # re-number tracks 0..T-1
    used, track = np.unique(tie.point_id, return_inverse=True)
    tie = Measurements(tie.image_id, track.astype(np.int64), tie.uv, tie.uv_true, tie.points[used])

    # ground control inside the imaged part of the area
    gb = (max(bounds[0], cover[0] + across), max(bounds[1], cover[1] + across),
          min(bounds[2], cover[2] - across), min(bounds[3], cover[3] - across))
    ctrl = place_control(scene, gb, spec.n_gcp, rng_gcp)
    check = place_control(scene, gb, spec.n_check, rng_gcp, inset=0.15, avoid=ctrl)
    gcp_true = np.vstack([ctrl, check])
    roles = ["control"] * len(ctrl) + ["check"] * len(check)
    names = [f"GCP{i + 1:02d}" for i in range(len(ctrl))] + [f"CHK{i + 1:02d}" for i in range(len(check))]
    sxy, sz = spec.sensors.gcp_survey_sigma_m
    surveyed = gcp_true + np.column_stack([rng_gcp.normal(0, sxy, (len(gcp_true), 2)),
                                           rng_gcp.normal(0, sz, len(gcp_true))])
    gcp_meas = observe_points(exposures, gcp_true, spec.sensors.gcp_sigma_px, rng_gcp, radius, margin_px=5.0,
                              min_views=1)

    crs = spec.scene.crs
    start = dt.datetime.fromisoformat(spec.start_time)
    times = [start + dt.timedelta(seconds=float(t)) for t in traj.time_s]
    lon, lat = projected_to_lonlat(pos_rec[:, 0], pos_rec[:, 1], crs)
    opk = np.array([R_cw_to_opk(R) for R in R_rec])
    ident = spec.identity
    camera_id = "|".join(ident[k] for k in ("make", "model", "serial", "lens"))
    ext = "jpg" if spec.modality != "thermal" or spec.file_format == "flir-rjpeg" else "tif"
    images = tables.from_columns("images", {
        "image_id": np.arange(1, N + 1, dtype=np.int32),
        "name": [f"IMG_{i + 1:04d}.{ext}" for i in range(N)],
        "time": times,
        "camera_id": [camera_id] * N,
        "width": np.full(N, spec.camera_nominal.width, np.int32),
        "height": np.full(N, spec.camera_nominal.height, np.int32),
        "bit_depth": np.full(N, 16 if spec.modality == "thermal" else 8, np.int8),
        "lat": np.asarray(lat), "lon": np.asarray(lon), "alt": pos_rec[:, 2],
        "gnss_x": pos_rec[:, 0], "gnss_y": pos_rec[:, 1], "gnss_z": pos_rec[:, 2],
        "roll": opk[:, 0], "pitch": opk[:, 1], "yaw": opk[:, 2],
        "attitude_convention": ["opk"] * N,
        "temperature_c": t_rec,
        "strip": traj.strip.astype(np.int32),
    }, crs=crs)
    observations = tables.from_columns("observations", {
        "image_id": tie.image_id, "track_id": tie.point_id, "x": tie.uv[:, 0], "y": tie.uv[:, 1],
        "sigma": np.full(len(tie.image_id), spec.sensors.tie_sigma_px, np.float32),
    }, crs=crs)
    gcps = tables.from_columns("gcps", {
        "gcp_id": names, "X": surveyed[:, 0], "Y": surveyed[:, 1], "Z": surveyed[:, 2],
        "sigma_x": np.full(len(names), sxy), "sigma_y": np.full(len(names), sxy), "sigma_z": np.full(len(names), sz),
        "role": roles,
    }, crs=crs)
    gcp_obs = tables.from_columns("gcp_observations", {
        "gcp_id": [names[i] for i in gcp_meas.point_id], "image_id": gcp_meas.image_id,
        "x": gcp_meas.uv[:, 0], "y": gcp_meas.uv[:, 1],
        "sigma": np.full(len(gcp_meas.image_id), spec.sensors.gcp_sigma_px, np.float32),
    }, crs=crs)

    truth = {
        "preset": spec.name,
        "seed": seed,
        "effects": {k: list(v) for k, v in fx.items()},
        "crs": crs,
        "camera_true": spec.camera_true.to_dict(),
        "camera_nominal": spec.camera_nominal.to_dict(),
        "reference_temperature_c": spec.sensors.reference_temperature_c,
        "temperature_true_c": t_true.tolist(),
        "rolling_shutter_readout_s": readout,
        "refraction_k": [ex.refraction_k for ex in exposures],
        "gsd_m": traj.gsd_m,
        "height_agl_m": spec.plan.height_agl_m,
        "bounds": list(bounds),
        "gcps_true": {n: p.tolist() for n, p in zip(names, gcp_true, strict=True)},
        "n_tracks": len(tie.points),
        "n_observations": len(tie.image_id),
    }
    return SimulatedFlight(
        spec=spec, seed=seed, effects=fx, crs=crs, scene=scene, bounds=bounds, trajectory=traj,
        exposures=exposures, temperature_true=t_true, images=images, observations=observations, gcps=gcps,
        gcp_observations=gcp_obs, tie=tie, gcp_true=gcp_true, truth=truth,
    )


def true_poses(sim: SimulatedFlight) -> pa.Table:
    """The true poses as a ``poses`` table (world-to-camera quaternion and projection centre)."""
    return poses_table(np.array([ex.image_id for ex in sim.exposures]), np.stack([ex.R_cw for ex in sim.exposures]),
                       np.stack([ex.C for ex in sim.exposures]), sim.crs)


# ----------------------------------------------------------------------------------- writing
def _eo_csv(sim: SimulatedFlight) -> str:
    im = sim.images
    lines = ["# recorded GNSS/IMU exterior orientation and sensor temperature",
             "# crs: EPSG:4326", "# attitude: dji_gimbal",
             "image,lat,lon,alt,roll,pitch,yaw,temperature"]
    R = recorded_R_cw(im)
    cols = {n: im.column(n).to_pylist() for n in ("name", "lat", "lon", "alt", "temperature_c")}
    for i in range(im.num_rows):
        roll, pitch, yaw = R_cw_to_dji_gimbal(R[i])
        lines.append(
            f"{cols['name'][i]},{cols['lat'][i]:.12f},{cols['lon'][i]:.12f},{cols['alt'][i]:.4f},"
            f"{roll:.9f},{pitch:.9f},{yaw:.9f},{cols['temperature_c'][i]:.3f}"
        )
    return "\n".join(lines) + "\n"


def _gcp_files(sim: SimulatedFlight) -> tuple[str, str]:
    g = sim.gcps.to_pydict()
    csv = [f"# crs: {sim.crs}", "id,X,Y,Z,sigma_xy,sigma_z,role"]
    for i, gid in enumerate(g["gcp_id"]):
        csv.append(f"{gid},{g['X'][i]:.4f},{g['Y'][i]:.4f},{g['Z'][i]:.4f},{g['sigma_x'][i]:.4f},"
                   f"{g['sigma_z'][i]:.4f},{g['role'][i]}")
    coords = {gid: (g["X"][i], g["Y"][i], g["Z"][i]) for i, gid in enumerate(g["gcp_id"])}
    names = dict(zip(sim.images.column("image_id").to_pylist(), sim.images.column("name").to_pylist(),
                     strict=True))
    obs = sim.gcp_observations.to_pydict()
    # OpenDroneMap pixel coordinates put the centre of the top-left pixel at (0, 0): ours minus 0.5
    odm = [sim.crs]
    for gid, iid, x, y in zip(obs["gcp_id"], obs["image_id"], obs["x"], obs["y"], strict=True):
        X, Y, Z = coords[gid]
        odm.append(f"{X:.4f} {Y:.4f} {Z:.4f} {x - 0.5:.3f} {y - 0.5:.3f} {names[iid]} {gid}")
    return "\n".join(csv) + "\n", "\n".join(odm) + "\n"


def _write_reference_dsm(sim: SimulatedFlight, path: Path) -> None:
    """The scene's surface over the flight (plus 50 cells) as a reference DSM, as a city's LiDAR survey
    would supply it (``reference/dsm.tif``: what the flight report compares its DSM with)."""
    scene = sim.scene
    west, _, _, north = scene.bounds()
    surface = Dsm(heights=scene.dsm, west=west, north=north, cell_m=scene.config.cell_m, crs=sim.crs)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_dsm(surface.window(sim.bounds, margin_cells=50), path)


def as_dataset(sim: SimulatedFlight, name: str | None = None) -> MemoryDataset:
    """The flight as a dataset :func:`aerocal.pipeline.process` runs on in memory.

    It holds what :func:`write_flight` would write in observations mode, without writing it.

    Args:
        sim: the flight (:func:`simulate_flight`).
        name: the dataset's name (default: the preset's, ``sim.spec.name``).

    Returns:
        :class:`aerocal.pipeline.dataset.MemoryDataset`: the ``images``, ``observations``, ``gcps`` and
        ``gcp_observations`` tables, the camera document (:func:`camera_document`), the flight's metadata
        (:func:`flight_metadata` in observations mode) and its CRS; none of the truth.
    """
    return MemoryDataset(name or sim.spec.name, sim.images, sim.observations, sim.gcps, sim.gcp_observations,
                         camera_document(sim), flight_metadata(sim, "observations"), sim.crs)


def camera_document(sim: SimulatedFlight) -> dict:
    """The flight's ``camera.json``: the camera identity and the manufacturer's nominal camera."""
    return {"identity": dict(sim.spec.identity), "camera": sim.spec.camera_nominal.to_dict()}


def flight_metadata(sim: SimulatedFlight, mode: str) -> dict:
    """The flight's ``flight.json``: what a pilot would hand over (plan, sensor sigmas; no truth)."""
    return {
        "name": sim.spec.name, "description": sim.spec.description, "crs": sim.crs, "mode": mode,
        "modality": sim.spec.modality, "n_images": sim.images.num_rows,
        "height_agl_m": sim.spec.plan.height_agl_m, "start_time": sim.spec.start_time,
        "gnss_sigma_m": [sim.spec.sensors.gnss_sigma_h_m, sim.spec.sensors.gnss_sigma_v_m],
        "imu_sigma_deg": list(sim.spec.sensors.imu_sigma_deg),
        "tie_sigma_px": sim.spec.sensors.tie_sigma_px,
    }


def write_flight(sim: SimulatedFlight, out_dir: str | Path, mode: str = "observations",
                 progress=None, as_recorded: bool = False) -> Path:
    """Write the flight folder atomically: everything goes to a temporary sibling, renamed at the end.

    Args:
        sim: the flight (:func:`simulate_flight`).
        out_dir: the folder to write; it must not exist, or be empty.
        mode: ``"observations"`` (the measurement tables under ``observations/``, nothing to match) or
            ``"images"`` (rendered frames under ``images/`` with eo.csv, the GCP files, camera.json and
            flight.json).
        progress: ``progress(done, total)`` per rendered frame.
        as_recorded: (images mode only) the folder as it comes off the aircraft: ``images/`` with the metadata
            the camera records, and no sidecar file (no eo.csv, GCP files, camera.json, flight.json,
            observations/).

    Returns:
        The folder written. The truth (``truth.json``, ``truth/``) and the reference DSM are written beside the
        flight as always; processing never reads them.

    Raises:
        SimulationError: an unknown mode, ``as_recorded`` with observations, or an ``out_dir`` that is not empty."""
    if as_recorded and mode != "images":
        raise SimulationError("as_recorded needs mode 'images': an observations-mode flight is its sidecar files")
    if mode not in MODES:
        raise SimulationError(f"unknown mode {mode!r}; valid modes: {', '.join(MODES)}")
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise SimulationError(f"output folder {out} exists and is not empty; choose a new --out or remove it")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".tmp-{out.name}.", dir=out.parent))
    try:
        if as_recorded:
            render_flight_images(sim, tmp / "images", progress=progress)
            return _finish_flight(sim, tmp, out)
        obs_dir = tmp / "observations"
        tables.write(sim.images, obs_dir / "images.parquet", "images")
        if mode == "observations":
            tables.write(sim.observations, obs_dir / "observations.parquet", "observations")
        tables.write(sim.gcps, obs_dir / "gcps.parquet", "gcps")
        tables.write(sim.gcp_observations, obs_dir / "gcp_observations.parquet", "gcp_observations")
        (tmp / "eo.csv").write_text(_eo_csv(sim))
        if sim.gcps.num_rows:  # a flight without ground control has no GCP files (an empty one is an error)
            gcsv, odm = _gcp_files(sim)
            (tmp / "gcps.csv").write_text(gcsv)
            (tmp / "gcp_list.txt").write_text(odm)
        write_json_atomic(tmp / "camera.json", camera_document(sim))
        write_json_atomic(tmp / "flight.json", flight_metadata(sim, mode))
        if mode == "images":
            render_flight_images(sim, tmp / "images", progress=progress)
        return _finish_flight(sim, tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _finish_flight(sim: SimulatedFlight, tmp: Path, out: Path) -> Path:
    """Write the reference DSM and the truth into ``tmp`` and rename it to ``out``."""
    _write_reference_dsm(sim, tmp / "reference" / "dsm.tif")
    tables.write(true_poses(sim), tmp / "truth" / "poses.parquet", "poses")
    pts = sim.tie.points
    tables.write(tables.from_columns("points", {
        "track_id": np.arange(len(pts), dtype=np.int64), "X": pts[:, 0], "Y": pts[:, 1], "Z": pts[:, 2],
    }, crs=sim.crs), tmp / "truth" / "points.parquet", "points")
    write_json_atomic(tmp / "truth.json", sim.truth)
    if out.exists():
        out.rmdir()
    tmp.rename(out)
    return out


def spec_summary(sim: SimulatedFlight) -> dict:
    """Figures a user checks after simulating (for the CLI)."""
    fwd, side = overlaps(sim.trajectory, sim.spec.camera_nominal, sim.spec.plan.height_agl_m)
    t = sim.images.column("temperature_c").to_numpy()
    obs_per_image = np.bincount(sim.tie.image_id)[1:]
    return {
        "preset": sim.spec.name, "images": sim.images.num_rows,
        "strips": int(len(np.unique(sim.trajectory.strip))),
        "gsd_m": round(sim.trajectory.gsd_m, 4), "forward_overlap": round(fwd, 3), "side_overlap": round(side, 3),
        "tracks": int(len(sim.tie.points)), "observations": int(len(sim.tie.image_id)),
        "observations_per_image": float(np.mean(obs_per_image)) if len(obs_per_image) else 0.0,
        "gcps": int(sum(r == "control" for r in sim.gcps.column("role").to_pylist())),
        "check_points": int(sum(r == "check" for r in sim.gcps.column("role").to_pylist())),
        "temperature_c": [float(np.min(t)), float(np.max(t))],
        "ground_speed_m_s": [round(float(v), 1) for v in np.unique(np.round(
            np.linalg.norm(sim.trajectory.velocity[:, :2], axis=1), 1))],
        "effects": {k: list(v) for k, v in sim.effects.items()},
        "crs": sim.crs,
    }

