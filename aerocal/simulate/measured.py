"""A preset whose flight is read from real images: the plan, attitudes, times and sensor temperatures.

``seneca``: the senseFly Swinglet CAM flight over Ohio farm fields (../shared/data/seneca), a Canon
PowerShot ELPH 300 HS whose temperature fell from 37 to 23 degC. Its recorded positions, autopilot
attitudes, times, strips and temperatures become the *true* stations of a simulated flight over a
synthetic field scene, so that the simulation can be compared with what the real images show.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from aerocal.camera import Camera
from aerocal.geometry import attitude_to_R_cw
from aerocal.ingest import ingest_folder
from aerocal.simulate.flight_plan import FlightPlanConfig, Trajectory, footprint_m
from aerocal.simulate.presets import FlightSpec, SceneSpec
from aerocal.simulate.sensors import SensorConfig, TemperatureCurve

#: where the measured images live in a development checkout (../shared beside the repository)
DEFAULT_SENECA = Path(__file__).resolve().parents[3] / "shared" / "data" / "seneca" / "images"

# Canon PowerShot ELPH 300 HS: f 4.3 mm, 1/2.3" sensor 6.17 mm wide; the images are halved to 1800 px
SENECA_PIXEL_UM = 6.17 / 1800 * 1000.0
SENECA_FLYING_HEIGHT_M = 70.0


class MeasuredFlightError(ValueError):
    """The images a measured preset reads are missing or unusable; the message names the folder."""


def stations_from_images(folder: str | Path) -> dict:
    """True stations (from the recorded EO) of a real flight: positions, rotations, times, strips, temperatures.

    Raises:
        MeasuredFlightError: ``folder`` is not a folder, or some of its images lack a GNSS position.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise MeasuredFlightError(f"{folder} is not a folder of images; give --source with the seneca images")
    res = ingest_folder(folder)
    im = res.images
    width = im.column("width").to_numpy()
    keep = width == np.median(width)  # the first frame is smaller (1620 px): not the same camera geometry
    d = {k: np.asarray(im.column(k).to_pylist(), dtype=object)[keep] for k in im.schema.names}
    C = np.column_stack([d["gnss_x"], d["gnss_y"], d["gnss_z"]]).astype(float)
    if not np.isfinite(C).all():
        raise MeasuredFlightError(f"{folder}: some images lack GNSS positions; a measured preset needs all of them")
    R = np.stack([attitude_to_R_cw(c, r, p, y) for c, r, p, y in zip(d["attitude_convention"], d["roll"],
                                                                     d["pitch"], d["yaw"], strict=True)])
    t = np.array([(x - d["time"][0]).total_seconds() for x in d["time"]])
    strip = d["strip"].astype(np.int32)
    V = np.zeros_like(C)
    V[1:-1] = (C[2:] - C[:-2]) / (t[2:] - t[:-2])[:, None]
    V[0], V[-1] = V[1], V[-2]
    return {"C": C, "R": R, "time_s": t, "strip": strip, "velocity": V, "crs": res.crs,
            "temperature": d["temperature_c"].astype(float), "start": d["time"][0],
            "width": int(np.median(width)), "height": int(np.median(im.column("height").to_numpy()))}


def fit_temperature_curve(t: np.ndarray, temperature: np.ndarray) -> TemperatureCurve:
    """Exponential relaxation fitted to recorded temperatures (grid search on tau, linear in the rest)."""
    best = None
    for tau in np.geomspace(30.0, 3000.0, 200):
        e = np.exp(-t / tau)
        A = np.column_stack([np.ones_like(e), e])  # T = Teq + (Ts - Teq) e
        coef, *_ = np.linalg.lstsq(A, temperature, rcond=None)
        err = float(np.sum((A @ coef - temperature) ** 2))
        if best is None or err < best[0]:
            best = (err, tau, coef)
    _, tau, (teq, amp) = best
    return TemperatureCurve(start_c=float(teq + amp), equilibrium_c=float(teq), tau_s=float(tau), noise_c=0.0,
                            quantum_c=1.0)


def trajectory(stations: dict) -> Trajectory:
    C = stations["C"]
    heading = np.degrees(np.arctan2(stations["velocity"][:, 0], stations["velocity"][:, 1])) % 360.0
    return Trajectory(time_s=stations["time_s"], C=C, R_cw=stations["R"], velocity=stations["velocity"],
                      heading_deg=heading, strip=stations["strip"], transversal=np.zeros(len(C), bool),
                      gsd_m=SENECA_FLYING_HEIGHT_M / seneca_camera(False).f, base_m=float("nan"),
                      spacing_m=float("nan"))


def seneca_camera(true: bool) -> Camera:
    nominal = Camera.from_mm(1800, 1350, focal_mm=4.3, pixel_size_um=SENECA_PIXEL_UM)
    if not true:
        return nominal
    # a compact zoom at its wide end: barrel distortion, principal point off centre
    return nominal.replace(f=nominal.f * 1.012, cx=903.1, cy=671.4, k1=-0.09, k2=0.04, p1=3e-4, p2=-2e-4)


def seneca_spec(source: str | Path | None = None):
    """The ``seneca`` FlightSpec (stations in ``extra["stations"]``)."""
    st = stations_from_images(source or DEFAULT_SENECA)
    ground = float(np.median(st["C"][:, 2])) - SENECA_FLYING_HEIGHT_M
    lo = st["C"][:, :2].min(axis=0)
    hi = st["C"][:, :2].max(axis=0)
    _, across, along = footprint_m(seneca_camera(False), SENECA_FLYING_HEIGHT_M)
    margin = 0.75 * float(np.hypot(across, along)) + 50.0  # as simulate_flight pads the planned area
    curve = fit_temperature_curve(st["time_s"], st["temperature"])
    return FlightSpec(
        name="seneca",
        description="senseFly Swinglet CAM over Ohio farm fields, Canon ELPH 300 HS (1800x1350 halved), ~70 m, "
                    "stations, attitudes and temperatures (37 -> 23 degC) read from the real images",
        identity={"make": "Canon", "model": "Canon PowerShot ELPH 300 HS", "serial": "unknown", "lens": "4.3mm"},
        camera_true=seneca_camera(True), camera_nominal=seneca_camera(False),
        plan=FlightPlanConfig(height_agl_m=SENECA_FLYING_HEIGHT_M, speed_m_s=float(
            np.median(np.linalg.norm(st["velocity"], axis=1)))),
        area_m=(float(hi[0] - lo[0]), float(hi[1] - lo[1])),
        scene=SceneSpec(cell_m=0.5, terrain_relief_m=3.0, terrain_mean_m=ground, building_density=0.0,
                        vegetation_density=0.05, origin_e=float(lo[0]) - margin, origin_n=float(lo[1]) - margin,
                        crs=st["crs"]),
        sensors=SensorConfig(gnss_sigma_h_m=2.0, gnss_sigma_v_m=4.0, imu_sigma_deg=(1.0, 1.0, 2.0),
                             tie_sigma_px=0.5, gcp_sigma_px=0.5, gcp_survey_sigma_m=(0.02, 0.03),
                             temperature=curve, reference_temperature_c=23.0),
        n_gcp=0, n_check=10, modality="rgb", points_per_image=500,
        start_time=st["start"].isoformat(),
        extra={"stations": st},
        notes="Consumer GNSS (2 m / 4 m) and autopilot attitude (1-2 deg) sigmas are assumptions, not "
              "measurements; the scene is synthetic fields, not the real ones.",
    )
