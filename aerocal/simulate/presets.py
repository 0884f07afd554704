"""Flight presets from the seed papers and the measured data.

Each preset is a :class:`FlightSpec`: the camera (true and nominal), the flight plan, the scene, the
sensors and the ground control. Figures come from ``shared/reference/*.csv``; where the papers'
figures disagree with each other the choice is stated in the preset's ``notes``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from aerocal.camera import Camera
from aerocal.simulate.flight_plan import FlightPlanConfig
from aerocal.simulate.sensors import SensorConfig, TemperatureCurve


@dataclass(frozen=True)
class SceneSpec:
    """Scene parameters (passed to :class:`aerocal.simulate.scene.SceneConfig`); extent from the plan."""

    cell_m: float = 1.0
    terrain_relief_m: float = 20.0
    terrain_mean_m: float = 50.0
    building_density: float = 0.25
    building_height_m: tuple[float, float] = (6.0, 30.0)
    vegetation_density: float = 0.1
    flat: bool = False
    origin_e: float = 686_000.0  # south-west corner of the scene, UTM metres
    origin_n: float = 4_929_000.0
    crs: str = "EPSG:32632"  # UTM 32N (Bologna)


@dataclass(frozen=True)
class FlightSpec:
    """Everything that defines a simulated flight except the seed and the hidden effects."""

    name: str
    description: str
    identity: dict[str, str]  # make, model, serial, lens
    camera_true: Camera  # the true IO at ``sensors.reference_temperature_c``
    camera_nominal: Camera  # what the manufacturer states (what processing starts from)
    plan: FlightPlanConfig
    area_m: tuple[float, float]  # (east-west, north-south) extent of the planned area
    scene: SceneSpec
    sensors: SensorConfig
    n_gcp: int = 0  # control points
    n_check: int = 0  # check points
    modality: str = "thermal"  # "thermal" (16-bit TIFF) or "rgb" (8-bit JPEG)
    #: image files in images mode: "" (by modality: TIFF or JPEG) or "flir-rjpeg" (FLIR radiometric JPEG
    #: as a DJI Zenmuse XT/XT2 writes it, thermal only)
    file_format: str = ""
    points_per_image: int = 400  # tie points per image in observations mode
    start_time: str = "2016-03-14T23:30:00+00:00"
    notes: str = ""
    extra: dict = field(default_factory=dict)

    def replace(self, **kw) -> FlightSpec:
        return dataclasses.replace(self, **kw)

    def flown(self, wind_m_s: tuple[float, float] | None = None,
              temperature: TemperatureCurve | None = None) -> FlightSpec:
        """This flight in a wind (east, north; m/s: the aircraft crabs and its ground speed changes with the
        heading) and/or with another sensor temperature curve (a camera warming or cooling in flight)."""
        spec = self
        if wind_m_s is not None:
            spec = spec.replace(plan=dataclasses.replace(spec.plan, wind_m_s=tuple(float(w) for w in wind_m_s)))
        if temperature is not None:
            spec = spec.replace(sensors=dataclasses.replace(spec.sensors, temperature=temperature))
        return spec


def _conte_camera(true: bool) -> Camera:
    nominal = Camera.from_mm(640, 480, focal_mm=39.2, pixel_size_um=23.5)
    if not true:
        return nominal
    # a germanium lens calibrated in the lab: focal and principal point off the nominal values,
    # visible radial distortion and a little decentring
    return nominal.replace(f=nominal.f + 6.0, cx=322.7, cy=237.9, k1=-0.08, k2=0.12, p1=2e-4, p2=-1.5e-4)


CONTE_IDENTITY = {"make": "NEC", "model": "TS9260", "serial": "0912034", "lens": "39.2mm Ge"}

PRESETS: dict[str, FlightSpec] = {}


def _register(spec: FlightSpec) -> FlightSpec:
    PRESETS[spec.name] = spec
    return spec


_register(FlightSpec(
    name="conte-city",
    description="Conte 2018 city flight: NEC TS9260 640x480 thermal, f 39.2 mm, 850 m, GSD 0.5 m, "
                "60/20 % overlap, one transversal strip, ~800 frames",
    identity=CONTE_IDENTITY,
    camera_true=_conte_camera(True),
    camera_nominal=_conte_camera(False),
    plan=FlightPlanConfig(height_agl_m=850.0, forward_overlap=0.60, side_overlap=0.20, speed_m_s=60.0,
                          direction="ew", transversal_strips=1, turn_time_s=90.0, attitude_jitter_deg=1.0),
    area_m=(4700.0, 3400.0),
    scene=SceneSpec(cell_m=2.0, terrain_relief_m=15.0, building_density=0.3),
    sensors=SensorConfig(gnss_sigma_h_m=0.10, gnss_sigma_v_m=0.15, tie_sigma_px=0.5, gcp_sigma_px=1.0,
                         gcp_survey_sigma_m=(0.25, 0.25),
                         temperature=TemperatureCurve(start_c=12.0, equilibrium_c=22.0, tau_s=1500.0),
                         reference_temperature_c=20.0),
    n_gcp=11, n_check=50,
    points_per_image=500,
    notes="The paper's 10 km2, 60/20 % minimum overlap and ~800 frames are not consistent with each other "
          "at 0.5 m GSD with a 640x480 frame (its average base of 60 m means ~75 % forward overlap). "
          "This preset keeps the overlaps and the frame count, so its area is ~16 km2.",
))

_register(FlightSpec(
    name="conte-calibration",
    description="Conte 2018 calibration subset: 44 images in 4 parallel strips of 8 and a transversal "
                "strip of 12, ~0.5 km2, 11 GCPs",
    identity=CONTE_IDENTITY,
    camera_true=_conte_camera(True),
    camera_nominal=_conte_camera(False),
    plan=FlightPlanConfig(height_agl_m=850.0, forward_overlap=0.60, side_overlap=0.20, speed_m_s=60.0,
                          direction="ew", n_strips=4, images_per_strip=8, transversal_strips=1,
                          transversal_images=12, turn_time_s=90.0, attitude_jitter_deg=1.0),
    area_m=(700.0, 800.0),
    scene=SceneSpec(cell_m=1.0, terrain_relief_m=10.0, building_density=0.3),
    sensors=SensorConfig(gnss_sigma_h_m=0.10, gnss_sigma_v_m=0.15, tie_sigma_px=0.5, gcp_sigma_px=0.5,
                         gcp_survey_sigma_m=(0.05, 0.05),
                         temperature=TemperatureCurve(start_c=18.0, equilibrium_c=22.0, tau_s=1500.0),
                         reference_temperature_c=20.0),
    n_gcp=11, n_check=12,
    points_per_image=400,
))

_register(FlightSpec(
    name="daakir-uav",
    description="Daakir 2019 UAV road corridor: CamLight 5120x3840, 6.4 um, 35 mm, 70 m, 2 strips along "
                "500 m, 75/75 %, sensor 22.7 -> 28.8 degC, 10 GCPs (RTK 1 cm)",
    identity={"make": "IGN", "model": "CamLight", "serial": "CL-03", "lens": "35mm"},
    camera_true=Camera.from_mm(5120, 3840, focal_mm=35.0, pixel_size_um=6.4).replace(
        f=5489.0, cx=2528.5, cy=1931.6, k1=-0.02, k2=0.01),
    camera_nominal=Camera.from_mm(5120, 3840, focal_mm=35.0, pixel_size_um=6.4),
    plan=FlightPlanConfig(height_agl_m=70.0, forward_overlap=0.75, side_overlap=0.75, speed_m_s=1.2,
                          direction="ew", n_strips=2, images_per_strip=39, extend_images=0, turn_time_s=60.0,
                          attitude_jitter_deg=1.5, height_jitter_m=0.5),
    area_m=(480.0, 60.0),
    scene=SceneSpec(cell_m=0.25, terrain_relief_m=3.0, building_density=0.02, building_height_m=(3.0, 8.0),
                    vegetation_density=0.2, origin_e=650_000.0, origin_n=5_400_000.0, crs="EPSG:32631"),
    sensors=SensorConfig(gnss_sigma_h_m=0.03, gnss_sigma_v_m=0.05, tie_sigma_px=0.3, gcp_sigma_px=0.3,
                         gcp_survey_sigma_m=(0.01, 0.01),
                         temperature=TemperatureCurve.linear_between(22.7, 28.8, 860.0, noise_c=0.05),
                         reference_temperature_c=22.7),
    n_gcp=10, n_check=10,
    modality="rgb",
    points_per_image=600,
    start_time="2017-06-20T10:00:00+00:00",
))

_register(FlightSpec(
    name="daakir-calibration",
    description="Calibration block for the Daakir 2019 CamLight: 44 convergent frames (4 strips of 8 and a "
                "transversal strip of 12, attitude spread 25 deg) at 30 m over a built-up 80 x 80 m field, "
                "20 GCPs (5 mm), target-quality measurements (0.15 px), sensor temperature held at a plateau",
    identity=PRESETS["daakir-uav"].identity,
    camera_true=PRESETS["daakir-uav"].camera_true,
    camera_nominal=PRESETS["daakir-uav"].camera_nominal,
    plan=FlightPlanConfig(height_agl_m=30.0, forward_overlap=0.75, side_overlap=0.60, speed_m_s=3.0,
                          direction="ew", n_strips=4, images_per_strip=8, extend_images=0, transversal_strips=1,
                          transversal_images=12, turn_time_s=30.0, attitude_jitter_deg=25.0, height_jitter_m=1.0),
    area_m=(80.0, 80.0),
    scene=SceneSpec(cell_m=0.25, terrain_relief_m=5.0, building_density=0.3, building_height_m=(6.0, 30.0),
                    vegetation_density=0.2, origin_e=650_000.0, origin_n=5_400_000.0, crs="EPSG:32631"),
    sensors=SensorConfig(gnss_sigma_h_m=0.03, gnss_sigma_v_m=0.05, tie_sigma_px=0.15, gcp_sigma_px=0.15,
                         gcp_survey_sigma_m=(0.005, 0.005),
                         temperature=TemperatureCurve(start_c=27.5, equilibrium_c=27.5),
                         reference_temperature_c=PRESETS["daakir-uav"].sensors.reference_temperature_c),
    n_gcp=20, n_check=6,
    modality="rgb",
    points_per_image=700,
    start_time="2017-06-19T10:00:00+00:00",
    notes="Daakir calibrated on a terrestrial field (43 convergent and rotated images, 28 GCPs at 0.5 mm, "
          "GSD 0.5-1.5 mm; moving-camera reprojection 0.16-0.2 px). The simulator flies aerial blocks, so the "
          "convergence comes from a 25 deg attitude spread over a low block with 6-30 m buildings: a "
          "nadir block at constant height cannot separate the focal length from the flying height. "
          "Same camera truth and reference temperature as daakir-uav; to calibrate at T degC set "
          "sensors.temperature to TemperatureCurve(T, T) (a plateau).",
))

_register(FlightSpec(
    name="mitishita-block",
    description="Mitishita: UltraCam Xp 17310x11310, 6 um, 100.5 mm, 2500 m, GSD 0.15 m, 6 strips in four "
                "directions, 80/60 %, POS AV GNSS/IMU, 30 signalised points",
    identity={"make": "Vexcel", "model": "UltraCam Xp", "serial": "UCXp-1", "lens": "100.5mm"},
    camera_true=Camera.from_mm(17310, 11310, focal_mm=100.534, pixel_size_um=6.0).replace(
        cx=17310 / 2 - 0.118 / 0.006, cy=11310 / 2 + 0.005 / 0.006),
    camera_nominal=Camera.from_mm(17310, 11310, focal_mm=100.5, pixel_size_um=6.0).replace(
        cx=17310 / 2 - 0.120 / 0.006, cy=11310 / 2),
    plan=FlightPlanConfig(height_agl_m=2500.0, forward_overlap=0.80, side_overlap=0.60, speed_m_s=70.0,
                          direction="ns", n_strips=3, images_per_strip=12, extend_images=0, cross_block=True,
                          turn_time_s=180.0, attitude_jitter_deg=0.5, height_jitter_m=5.0),
    area_m=(3700.0, 3700.0),
    scene=SceneSpec(cell_m=4.0, terrain_relief_m=40.0, terrain_mean_m=900.0, building_density=0.15,
                    origin_e=670_000.0, origin_n=7_180_000.0, crs="EPSG:32722"),
    sensors=SensorConfig(gnss_sigma_h_m=0.10, gnss_sigma_v_m=0.10,
                         imu_sigma_deg=(30 / 3600, 30 / 3600, 30 / 3600),
                         tie_sigma_px=0.5, gcp_sigma_px=0.5, gcp_survey_sigma_m=(0.02, 0.02),
                         temperature=TemperatureCurve(start_c=20.0, equilibrium_c=20.0),
                         reference_temperature_c=20.0),
    n_gcp=1, n_check=29,
    modality="rgb",
    points_per_image=300,
    start_time="2003-09-02T13:00:00+00:00",
    notes="Camera truth: the in-situ calibrated focal length 100.534 mm (nominal 100.500 mm) and principal "
          "point of the paper's first sub-block.",
))


_register(FlightSpec(
    name="xt2-survey",
    description="DJI Zenmuse XT2 (FLIR Tau 2, 640x512, 17 um, 13 mm) nadir survey at 60 m over a village, "
                "3 strips, 80/70 %, consumer GNSS (no RTK), no ground control, FLIR radiometric JPEGs as they "
                "come off the drone (no serial number, no camera.json, no flight.json with --as-recorded)",
    identity={"make": "DJI", "model": "XT2", "serial": "", "lens": ""},
    camera_true=Camera.from_mm(640, 512, focal_mm=13.0, pixel_size_um=17.0).replace(
        f=13.0 / 0.017 * 1.004, cx=323.1, cy=254.2, k1=-0.05, k2=0.03),
    camera_nominal=Camera.from_mm(640, 512, focal_mm=13.0, pixel_size_um=17.0),
    plan=FlightPlanConfig(height_agl_m=60.0, forward_overlap=0.80, side_overlap=0.70, speed_m_s=5.0,
                          direction="ew", n_strips=3, images_per_strip=8, extend_images=0, turn_time_s=20.0,
                          attitude_jitter_deg=1.0, height_jitter_m=0.5),
    area_m=(160.0, 100.0),
    scene=SceneSpec(cell_m=0.25, terrain_relief_m=3.0, building_density=0.25, building_height_m=(4.0, 12.0),
                    vegetation_density=0.2, origin_e=500_000.0, origin_n=5_300_000.0, crs="EPSG:32633"),
    sensors=SensorConfig(gnss_sigma_h_m=1.5, gnss_sigma_v_m=3.0, imu_sigma_deg=(1.0, 1.0, 2.0), tie_sigma_px=0.5,
                         temperature=TemperatureCurve(start_c=30.0, equilibrium_c=35.0, tau_s=600.0),
                         reference_temperature_c=30.0),
    modality="thermal",
    file_format="flir-rjpeg",
    points_per_image=400,
    start_time="2024-07-02T21:30:00+00:00",
    notes="The XT2 records no core temperature, so the sensor temperature of this flight is not in its files.",
))


class PresetError(ValueError):
    """An unknown preset; the message lists the valid names."""


#: presets built on demand from measured data (name -> builder taking an optional source folder)
MEASURED = ("seneca",)


def preset_names() -> list[str]:
    return sorted([*PRESETS, *MEASURED])


def get_preset(name: str, source: str | None = None) -> FlightSpec:
    """A flight specification by preset name.

    Args:
        name: a preset of :data:`PRESETS`, or a measured preset (:data:`MEASURED`: ``seneca``).
        source: the image folder of a measured preset (``seneca``; default: its folder in a development checkout,
            ``shared/data/seneca/images`` beside the repository); unused by the other presets.

    Returns:
        :class:`FlightSpec`: the preset of :data:`PRESETS` itself, or for a measured preset one built on every
        call from the stations, attitudes and temperatures its images record.

    Raises:
        PresetError: an unknown name (the message lists the valid ones), or a measured preset whose images are
            missing or lack GNSS positions.
    """
    if name == "seneca":
        # import cycle: aerocal.simulate.measured builds its FlightSpec from the classes of this module
        from aerocal.simulate.measured import MeasuredFlightError, seneca_spec

        try:
            return seneca_spec(source)
        except MeasuredFlightError as exc:
            raise PresetError(str(exc)) from exc
    if name not in PRESETS:
        raise PresetError(f"unknown preset {name!r}; valid presets: {', '.join(preset_names())}")
    return PRESETS[name]
