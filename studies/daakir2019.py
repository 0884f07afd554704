"""Daakir et al. 2019, UAV corridor: the thermal correction's gain on the GCPs, simulated.

The paper (``../shared/seeds/000_bcf8ed96d49b6c76.txt``, Sec. 5.2, Tables 14-16): a CamLight (5120x3840,
6.4 um, 35 mm) flies 77 images in two strips along a 500 m road at 70 m while its sensor warms from 22.7
to 28.8 degC; 10 GCPs (RTK, 1 cm) along the road. The camera was pre-calibrated on a terrestrial field at
34.2-36 degC, once from the original and once from the thermally corrected observations. The block is a
*relative* orientation ("the relative result was moved to the coordinate system of GCPs with a
7-parameter 3D similarity transformation and no bundle block adjustment was followed", Sec. 5); the tie
points and GCP image measurements are corrected, not the pixels. GCP residuals after the similarity:
mean 21.4 mm (original) -> 15.5 mm (corrected), "an accuracy improvement of a factor of ~1.4".

The thermal model is Eq. 2, a 4-parameter similarity of the image with temperature: translation
u(T), v(T) ("the variation of the translation corresponds to the deviation of the principal point"),
scale k(T) (the focal length) and rotation theta(T) ("less than 0.02 px/degC"). Simulated as the
catalogue's ``thermal_focal`` (0.075 px/degC, Sec. 4.2.3), ``thermal_principal_point`` (the slopes of
Table 8's principal point against temperature, -0.05 / +0.27 px/degC) and ``thermal_rotation`` (0.02
px/degC at the image corner).

Columns of the table:

* today's model (the set-up the project simulated before this study): a focal-only drift; the block adjusted with GNSS
  (3/5 cm) and IMU priors, IO fixed at the camera's 22.7 degC calibration; the correction a focal slope
  calibrated separately; residuals of all 20 ground points after the similarity.
* extended model: the Eq. 2 field hidden; the paper's workflow: relative orientation from the tie points
  alone (the recorded positions at 5 m only fix the datum; no attitude observations), "original" = the
  pre-calibration at 35.1 degC from the original observations, "corrected" = the pre-calibration from
  observations corrected to the reference temperature and the same Eq. 2 correction (slopes as
  calibrated separately, truth + noise) applied to the corridor's tie points and GCP measurements;
  residuals of the 10 GCPs after the similarity. The same with today's focal-only correction, and with
  a focal-only hidden drift, separate what the field and the correction add; a principal-point drift
  three times Table 8's measures what the paper's gain would take.
* the size of the thermal deformation itself: the same runs without survey and with little image noise.

The same corridor is also run as a user of aerocal runs it (:func:`product_runs`, section "Through the
product"): a calibration flight through :func:`aerocal.pipeline.process` (``calibrate_only=True``) issues
certificates into one :class:`aerocal.pipeline.MemoryCertificates` store: the CamLight's convergent
calibration block (``daakir-calibration``) with the Eq. 2 field, the sensor warming linearly over
22.7-45.5 degC (the corridor's start to Table 8's warmest), once with ``ProcessConfig()`` (the calibration
frees a focal slope only) and once with the principal point's slopes freed (``thermal=("f", "cx", "cy")``).
The corridor itself, calibrated the same way, determines no slope (predicted sigma of df/dT 0.08 px/degC on
24 images): its certificates are recorded, not used. The corridor (every GCP a check point) is then
processed with each certificate pinned, with and without ``block.thermal_correction``, as flown (GNSS/IMU
sigmas of the flight) and as the paper's relative orientation (``use_flight_sigmas=False``, GNSS 5 m, no
attitude), also noise-free; the residuals of the 10 GCPs from ``adjustment.check_errors_m`` after the
similarity, the certificates' slopes against the truth, and what the diagnosis step named.

Run: ``python -m studies.daakir2019`` (five seeds and one product seed on the whole corridor; ``--quick``: one
seed, a 24-image corridor). Writes ``studies/output/daakir2019.md`` (``daakir2019_quick.md``, whose header gives the
run's time) and a PNG.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.compute as pc

from aerocal.adjust import AdjustConfig, run_strategy
from aerocal.camera import LinearThermalModel
from aerocal.certificates.selection import NoCertificateError
from aerocal.geometry import estimate_similarity
from aerocal.pipeline import MemoryCertificates, ProcessConfig, process
from aerocal.simulate import as_dataset, get_preset, simulate_flight
from aerocal.simulate.presets import FlightSpec
from aerocal.simulate.sensors import TemperatureCurve
from studies.papers import (
    PRODUCT,
    as_checks,
    certificate_row,
    gnss_priors,
    pyplot,
    save_png,
    stats,
    study_parser,
    write_study,
)

PRESET = "daakir-uav"
#: focal drift (px/degC, Sec. 4.2.3: 0.07-0.08) and the uncertainty of its separate calibration (px/degC)
DAAKIR_SLOPE = 0.075
DAAKIR_CAL_SIGMA = 0.005
#: principal-point drift (px/degC): least-squares slopes of Table 8 (moving-camera bundle adjustments at
#: 27.6, 39.3 and 45.5 degC); their separate calibration's uncertainty (px/degC)
PP_SLOPE = (-0.05, 0.27)
PP_CAL_SIGMA = 0.02
#: image rotation (px/degC at the image corner): the paper's bound, "less than 0.02 px/degC"
ROTATION_SLOPE = 0.02
#: the terrestrial pre-calibration's temperature (degC, Table 14: 34.2-36)
PRECALIBRATION_C = 35.1
#: the recorded positions' weight in the relative orientation (m): fixes the datum, not the shape
RELATIVE_DATUM_SIGMA_M = 5.0
#: paper, Table 16 (mm): original and corrected GCP residuals after the 7-parameter similarity
PAPER = {"original": {"mean": 21.4, "std": 11.0, "min": 5.9, "max": 39.6},
         "corrected": {"mean": 15.5, "std": 6.6, "min": 5.9, "max": 24.9}}

FOCAL_FIELD = {"thermal_focal": DAAKIR_SLOPE}
EQ2_FIELD = {"thermal_focal": DAAKIR_SLOPE, "thermal_principal_point": PP_SLOPE,
             "thermal_rotation": ROTATION_SLOPE}
#: what the paper's gain would take: the principal-point drift three times Table 8's
PP_FACTOR = 3.0
EQ2_LARGER_PP = {**EQ2_FIELD, "thermal_principal_point": tuple(PP_FACTOR * v for v in PP_SLOPE)}


@dataclass(frozen=True)
class StudyConfig:
    """What the study runs (defaults: the full study)."""

    quick: bool = False
    seeds: tuple[int, ...] = (1, 2, 3, 4, 5)
    images: int | None = None  # None = the whole corridor (78 images)
    points_per_image: int | None = None  # None = the preset's 600 tie points per image
    #: seeds run through the product (:func:`product_runs`: 16 process runs per seed)
    product_seeds: tuple[int, ...] = (1,)

    @staticmethod
    def for_quick() -> StudyConfig:
        return StudyConfig(quick=True, seeds=(1,), images=24, points_per_image=200, product_seeds=(1,))

    def spec(self, quiet: bool = False) -> FlightSpec:
        """The corridor's preset, thinned to ``points_per_image``, noise-free with ``quiet``."""
        spec = get_preset(PRESET)
        if self.points_per_image:
            spec = spec.replace(points_per_image=self.points_per_image)
        return noise_free(spec) if quiet else spec



def noise_free(spec: FlightSpec) -> FlightSpec:
    """``spec`` without survey noise and with little image noise: what is left is the thermal deformation."""
    return spec.replace(sensors=dataclasses.replace(spec.sensors, gcp_survey_sigma_m=(0.0, 0.0),
                                                    gcp_sigma_px=0.05, tie_sigma_px=0.1))


def similarity_residuals(sim, camera, config: AdjustConfig, thermal: LinearThermalModel | None,
                         control_only: bool) -> np.ndarray:
    """Ground-point residuals (m) after a 7-parameter similarity of the adjusted block onto the survey.

    The points are kept out of the adjustment and intersected afterwards; ``control_only``: the paper's 10
    GCPs, otherwise every ground point of the preset (today's set-up).
    """
    g = sim.gcps
    go = sim.gcp_observations
    if control_only:
        g = g.filter(pc.equal(g.column("role"), "control"))
        go = go.filter(pc.is_in(go.column("gcp_id"), value_set=g.column("gcp_id")))
    g = as_checks(g)
    res = run_strategy("fixed", sim.images, sim.observations, camera, config, g, go, thermal=thermal).block
    names = g.column("gcp_id").to_pylist()
    surveyed = np.column_stack([g.column(c).to_numpy() for c in ("X", "Y", "Z")])
    dst = surveyed[[names.index(n) for n in res.check_ids]]
    return after_similarity(dst + res.check_errors, dst)


def after_similarity(computed: np.ndarray, surveyed: np.ndarray) -> np.ndarray:
    """Distances (m) of ``computed`` points (K, 3) from ``surveyed`` after the 7-parameter similarity of the first
    onto the second (points with a non-finite coordinate left out)."""
    ok = np.isfinite(computed).all(axis=1)
    s7 = estimate_similarity(computed[ok], surveyed[ok])
    return np.linalg.norm(s7.apply(computed[ok]) - surveyed[ok], axis=1)


def _relative_config() -> AdjustConfig:
    return AdjustConfig(gnss_sigma_m=(RELATIVE_DATUM_SIGMA_M,) * 3, attitude_sigma_deg=None)


def calibrated_models(t0: float, rng: np.random.Generator, field: dict | None = None
                      ) -> dict[str, LinearThermalModel]:
    """The thermal models of the hidden ``field`` (default: Eq. 2) as a separate (test-field) calibration
    gives them: truth + calibration noise. "focal": today's focal-only model; "eq2": focal and principal
    point (the rotation needs no model: each image's kappa takes it)."""
    field = EQ2_FIELD if field is None else field
    df = field.get("thermal_focal", 0.0) + rng.normal(0.0, DAAKIR_CAL_SIGMA)
    dcx, dcy = (s + rng.normal(0.0, PP_CAL_SIGMA) for s in field.get("thermal_principal_point", (0.0, 0.0)))
    return {"focal": LinearThermalModel(t0=t0, df_dt=df),
            "eq2": LinearThermalModel(t0=t0, df_dt=df, dcx_dt=dcx, dcy_dt=dcy)}


def precalibration(camera, truth: LinearThermalModel, model: LinearThermalModel | None):
    """The terrestrial pre-calibration at ``PRECALIBRATION_C`` degC, from observations corrected to the
    model's reference temperature with ``model`` (``None``: the original observations).

    ``camera`` holds the true IO at ``truth.t0``; what is not corrected stays at the pre-calibration's
    temperature: ``IO = IO(t0) + (truth slopes - model slopes) (T_precal - t0)``.
    """
    dt = PRECALIBRATION_C - truth.t0
    m = model or LinearThermalModel(t0=truth.t0)
    return camera.replace(f=camera.f + (truth.df_dt - m.df_dt) * dt, cx=camera.cx + (truth.dcx_dt - m.dcx_dt) * dt,
                          cy=camera.cy + (truth.dcy_dt - m.dcy_dt) * dt)


# ----------------------------------------------------------------------------- runs
def today(cfg: StudyConfig) -> dict:
    """Today's set-up: focal-only drift, GNSS/IMU-weighted block, IO at 22.7 degC, all 20 ground points."""
    rows = {"original": [], "corrected": []}
    for seed in cfg.seeds:
        sim = simulate_flight(cfg.spec(), seed=seed, effects=FOCAL_FIELD, max_images=cfg.images)
        t0 = sim.spec.sensors.reference_temperature_c
        model = calibrated_models(t0, np.random.default_rng(seed), FOCAL_FIELD)["focal"]
        for label, th in (("original", None), ("corrected", model)):
            config = gnss_priors(sim, attitude_sigma_deg=sim.spec.sensors.imu_sigma_deg)
            rows[label].append(similarity_residuals(sim, sim.spec.camera_true, config, th, False))
        print(f"  today seed {seed}: {np.mean(rows['original'][-1]) * 1000:.2f} -> "
              f"{np.mean(rows['corrected'][-1]) * 1000:.2f} mm", flush=True)
    return {k: {**stats(np.concatenate(v)), "per_seed_mean": [float(np.mean(x)) for x in v]}
            for k, v in rows.items()}


def paper_workflow(cfg: StudyConfig, field: dict, quiet: bool) -> dict:
    """The paper's workflow on a corridor with the hidden ``field``: residuals of the 10 GCPs (m).

    original: the pre-calibration at 35.1 degC from the original observations; corrected: the
    pre-calibration from observations corrected with the focal-only or the Eq. 2 model
    (:func:`precalibration`), and the same model applied to the corridor's tie points and GCP measurements.
    """
    spec = cfg.spec(quiet)
    rows = {"original": [], "corrected, focal-only model": [], "corrected, Eq. 2 model": []}
    for seed in cfg.seeds:
        sim = simulate_flight(spec, seed=seed, effects=field, max_images=cfg.images)
        t0 = sim.spec.sensors.reference_temperature_c
        truth = LinearThermalModel(t0=t0, df_dt=field.get("thermal_focal", 0.0),
                                   dcx_dt=field.get("thermal_principal_point", (0.0, 0.0))[0],
                                   dcy_dt=field.get("thermal_principal_point", (0.0, 0.0))[1])
        models = calibrated_models(t0, np.random.default_rng(seed), field)
        conf = _relative_config()
        cam = sim.spec.camera_true
        rows["original"].append(similarity_residuals(sim, precalibration(cam, truth, None), conf, None, True))
        for label, key in (("corrected, focal-only model", "focal"), ("corrected, Eq. 2 model", "eq2")):
            rows[label].append(similarity_residuals(sim, precalibration(cam, truth, models[key]), conf,
                                                    models[key], True))
        print(f"  paper workflow, {'+'.join(field)}{' (noise-free)' if quiet else ''}, seed {seed}: "
              + ", ".join(f"{k} {np.mean(v[-1]) * 1000:.2f}" for k, v in rows.items()) + " mm", flush=True)
    return {k: {**stats(np.concatenate(v)), "per_seed_mean": [float(np.mean(x)) for x in v]}
            for k, v in rows.items()}


# ----------------------------------------------------------------------------- through the product
#: the calibration flight: the CamLight's calibration block (preset ``daakir-calibration``: 44 convergent
#: frames, 20 GCPs) flown while the sensor warms linearly from the corridor's start to Table 8's warmest
#: temperature (degC), so that its certificate's thermal model covers the corridor and Table 8's range
CALIBRATION_PRESET = "daakir-calibration"
CALIBRATION_RANGE_C = (22.7, 45.5)
#: the certificates: the product's default calibration (``ProcessConfig()``: a focal-length slope only) and
#: one whose calibration also frees the principal point's slopes (Eq. 2's translation)
CERTIFICATES = {"focal-only": None, "Eq. 2": ("f", "cx", "cy")}
#: the corridor's block -> (relative orientation, noise-free corridor): as a user runs it (the flight's GNSS
#: 3/5 cm and IMU sigmas), the paper's relative orientation (GNSS at 5 m, no attitude:
#: ``use_flight_sigmas=False``), and the same without survey noise and with little image noise (what is left
#: is the thermal deformation the product's correction can remove)
BLOCKS = {"as flown": (False, False), "relative": (True, False), "relative, noise-free": (True, True)}


def product_config(thermal: tuple[str, ...] | None = None, correction: bool = True,
                   relative: bool = False) -> ProcessConfig:
    """The product's configuration: :data:`studies.papers.PRODUCT` unless the calibration's thermal slopes
    (``thermal``), the block's thermal correction (``correction``) or a relative orientation (``relative``) are
    asked for. The diagnosis's extension of the block is off: the study compares what each certificate's own
    correction does (with the focal-only certificate the extension adds the principal point's drift the diagnosis
    finds)."""
    config = dataclasses.replace(PRODUCT, extend=False)
    if thermal is not None:
        cal = config.calibration
        config = dataclasses.replace(config, calibration=dataclasses.replace(
            cal, adjust=dataclasses.replace(cal.adjust, thermal=tuple(thermal))))
    block = dataclasses.replace(config.block, thermal_correction=correction)
    if relative:
        block = dataclasses.replace(block, adjust=_relative_config())
        config = dataclasses.replace(config, use_flight_sigmas=False)
    return dataclasses.replace(config, block=block)


def calibration_flight(seed: int, field: dict | None = None, spec: FlightSpec | None = None,
                       max_images: int | None = None):
    """The calibration block of ``seed`` (``spec``, default :data:`CALIBRATION_PRESET`) with the hidden
    ``field`` (default Eq. 2), the sensor warming linearly over :data:`CALIBRATION_RANGE_C` from the first
    frame to the last (of the ``max_images`` simulated)."""
    spec = spec or get_preset(CALIBRATION_PRESET)
    times = simulate_flight(spec, seed=100 + seed, max_images=max_images).images.column("time").to_numpy()
    times = times.astype("datetime64[ms]")
    seconds = float((times.max() - times.min()) / np.timedelta64(1, "s"))
    start = float((times.min() - np.datetime64(spec.start_time[:19])) / np.timedelta64(1, "s"))
    lo, hi = CALIBRATION_RANGE_C
    rate, tau = (hi - lo) / max(seconds, 1.0), 1e7  # tau >> the flight: the exponential is a straight line
    t_start = lo - rate * start
    curve = TemperatureCurve(start_c=t_start, equilibrium_c=t_start + rate * tau, tau_s=tau, noise_c=0.05)
    spec = spec.replace(sensors=dataclasses.replace(spec.sensors, temperature=curve))
    return simulate_flight(spec, seed=100 + seed, effects=EQ2_FIELD if field is None else field,
                           max_images=max_images)


def _certificate_row(run) -> dict:
    """The certificate a calibration flight issued: IO, thermal slopes +- their sigmas (px/degC), review."""
    cert = run.json("certificate")
    params = cert["model"]["params"]
    thermal = cert.get("thermal") or {}
    sig = thermal.get("sigmas") or {}
    slopes = {k: [float(thermal[k]), float(sig.get(k, float("nan")))] for k in ("df_dt", "dcx_dt", "dcy_dt")
              if thermal.get(k) not in (None, 0.0)}
    cal = run.json("calibration")
    return {**certificate_row(run), "cx": float(params["cx"]), "cy": float(params["cy"]), "t0": thermal.get("t0"),
            "valid_range": thermal.get("valid_range"), "slopes": slopes,
            "overdispersion": float(cal.get("overdispersion") or 1.0),
            "selection": list((cal.get("adjustment") or {}).get("selection") or [])}


def product_residuals(sim, run) -> np.ndarray:
    """Residuals (m) of the paper's 10 GCPs (the preset's control points, given to the product as check
    points) after a 7-parameter similarity of their computed onto their surveyed coordinates."""
    adj = run.json("adjustment")
    g = sim.gcps
    names = [str(n) for n in g.column("gcp_id").to_pylist()]
    roles = g.column("role").to_pylist()
    surveyed = np.column_stack([g.column(c).to_numpy() for c in ("X", "Y", "Z")])
    err = np.asarray(adj["check_errors_m"], dtype=float).reshape(-1, 3)
    rows = [(k, names.index(str(n))) for k, n in enumerate(adj["check_ids"]) if roles[names.index(str(n))] == "control"]
    dst = surveyed[[j for _, j in rows]]
    return after_similarity(dst + err[[k for k, _ in rows]], dst)


def _corridor_row(sim, run) -> dict:
    """A corridor run: the GCP residuals after the similarity, what the diagnosis named, the block's state."""
    adj = run.json("adjustment")
    diag = run.json("diagnosis")
    res = product_residuals(sim, run)
    return {**stats(res), "n": int(len(res)), "thermal_correction": bool(adj.get("thermal_correction")),
            "converged": bool(adj.get("converged", True)), "reason": run.summary.certificate_reason,
            "diagnosis": run.summary.diagnosis,
            "effects": {e["name"]: {"magnitude": [float(v) for v in np.ravel(e["magnitude"])],
                                    "sigma": [float(v) for v in np.ravel(e["sigma"])], "units": e.get("units"),
                                    "alternatives": list(e.get("alternatives") or [])}
                        for e in diag.get("effects") or []},
            "recorded_eo": (adj.get("recorded_eo_corrections") or {}).get("notes") or []}


def product_runs(cfg: StudyConfig, seed: int, log=print) -> dict:
    """The corridor as a user of aerocal runs it: a calibration flight through
    :func:`aerocal.pipeline.process` (``calibrate_only``) issues a certificate into one store
    (:class:`aerocal.pipeline.MemoryCertificates`), once with the default configuration (a focal slope) and
    once with the principal point's slopes freed; the corridor (its GCPs all check points) is processed with
    each certificate pinned, with and without the certificate's thermal correction, as flown and as the
    paper's relative orientation; the diagnosis step runs on every corridor block."""
    t_start = time.perf_counter()
    store = MemoryCertificates()
    cal = calibration_flight(seed)
    temps = cal.images.column("temperature_c").to_numpy()
    out: dict = {"calibration_range_c": [float(temps.min()), float(temps.max())], "certificates": {},
                 "corridor": {}}
    for name, thermal in CERTIFICATES.items():
        t = time.perf_counter()
        run = process(as_dataset(cal, f"daakir-calibration {name}"), product_config(thermal), certificates=store,
                      calibrate_only=True)
        row = out["certificates"][name] = {**_certificate_row(run), "seconds": time.perf_counter() - t}
        log(f"  seed {seed} aerocal process, calibration flight ({name}): f {row['f']:.2f} px, slopes "
            + ", ".join(f"{k} {v[0]:+.4f} +- {v[1]:.4f}" for k, v in row["slopes"].items())
            + f" ({row['status']}, {row['seconds']:.0f} s)")
    # the corridor itself as the calibration flight (same warming): what a nadir two-strip block determines
    corridor_cal = calibration_flight(seed, spec=cfg.spec(), max_images=cfg.images)
    out["corridor as calibration flight"] = {}
    for name, thermal in CERTIFICATES.items():
        run = process(as_dataset(corridor_cal, f"daakir-corridor-calibration {name}"), product_config(thermal),
                      calibrate_only=True)  # its own store: these certificates are not used for the corridor
        row = out["corridor as calibration flight"][name] = _certificate_row(run)
        log(f"  seed {seed} aerocal process, the corridor as calibration flight ({name}): f {row['f']:.2f} px, "
            f"slopes {row['slopes'] or 'none'} ({row['status']})")
    flights = {}
    for quiet in (False, True):
        sim = simulate_flight(cfg.spec(quiet), seed=seed, effects=EQ2_FIELD, max_images=cfg.images)
        ds = as_dataset(sim, "daakir-corridor")
        ds.gcps = as_checks(sim.gcps)  # every GCP a check point: none enters the block's datum
        flights[quiet] = (sim, ds)
    for name, cert in out["certificates"].items():
        for block, (relative, quiet) in BLOCKS.items():
            sim, ds = flights[quiet]
            for correction in (True, False):
                key = f"{name} | {block} | {'corrected' if correction else 'original'}"
                t = time.perf_counter()
                try:
                    run = process(ds, product_config(correction=correction, relative=relative),
                                  certificate=cert["certificate"], certificates=store)
                except NoCertificateError as exc:
                    out["corridor"][key] = {"refused": str(exc)}
                    log(f"  seed {seed} aerocal process, corridor {key}: refused ({exc})")
                    continue
                row = out["corridor"][key] = {**_corridor_row(sim, run), "seconds": time.perf_counter() - t}
                log(f"  seed {seed} aerocal process, corridor {key}: {row['mean'] * 1000:.2f} mm "
                    f"({row['seconds']:.0f} s); diagnosis: {row['diagnosis']}")
    out["seconds"] = time.perf_counter() - t_start
    return out


def run(quick: bool = False) -> dict:
    """All numbers of the study (plain JSON types)."""
    cfg = StudyConfig.for_quick() if quick else StudyConfig()
    t0 = time.perf_counter()
    print("Daakir 2019: today's set-up", flush=True)
    out = {"quick": quick, "seeds": list(cfg.seeds), "images": cfg.images, "today": today(cfg)}
    print("Daakir 2019: the paper's workflow", flush=True)
    out["workflow"] = {
        "eq2": paper_workflow(cfg, EQ2_FIELD, quiet=False),
        "eq2 noise-free": paper_workflow(cfg, EQ2_FIELD, quiet=True),
        "focal noise-free": paper_workflow(cfg, FOCAL_FIELD, quiet=True),
    }
    if not quick:  # the focal-only field under the survey noise, and what a larger drift would give
        out["workflow"]["focal"] = paper_workflow(cfg, FOCAL_FIELD, quiet=False)
        out["workflow"]["eq2 larger pp"] = paper_workflow(cfg, EQ2_LARGER_PP, quiet=False)
    print("Daakir 2019: through the product (aerocal.pipeline.process)", flush=True)
    out["product"] = {str(seed): product_runs(cfg, seed) for seed in cfg.product_seeds}
    out["seconds"] = time.perf_counter() - t0
    return out


# ----------------------------------------------------------------------------- report
def gain(a: dict, b: dict) -> float:
    return a["mean"] / b["mean"]


def needed_thermal_mm() -> float:
    """The thermal part of the paper's original residual (mm) if the corrected one is its floor."""
    return float(np.sqrt(PAPER["original"]["mean"] ** 2 - PAPER["corrected"]["mean"] ** 2))


def markdown(result: dict) -> str:
    t = result["today"]
    w = result["workflow"]
    e, qn, qf = w["eq2"], w["eq2 noise-free"], w["focal noise-free"]
    orig, corr, corr_f = "original", "corrected, Eq. 2 model", "corrected, focal-only model"
    p_gain = PAPER["original"]["mean"] / PAPER["corrected"]["mean"]
    n_img = "the whole corridor (78 images)" if result["images"] is None else f"{result['images']} images"
    need = needed_thermal_mm()
    floor = e[corr]["mean"] * 1000
    thermal = qn[orig]["mean"] * 1000
    predicted = np.sqrt(floor**2 + thermal**2) / floor
    L = [f"## Daakir 2019, UAV corridor: GCP residuals after a 7-parameter similarity"
         f"{' (quick)' if result['quick'] else ''}", "",
         f"Generated by `python -m studies.daakir2019`{' --quick' if result['quick'] else ''}; seeds "
         f"{result['seeds']}, {n_img}; {result['seconds']:.0f} s. Paper: Table 16 "
         "(`../shared/reference/daakir2019_results.csv`).", "",
         "| GCP residual (mm) | paper, original -> corrected | our simulation, today's model | "
         "our simulation, extended model |", "|---|---|---:|---:|"]
    for k in ("mean", "std", "min", "max"):
        L.append(f"| {k} | {PAPER['original'][k]} -> {PAPER['corrected'][k]} | "
                 f"{t['original'][k] * 1000:.1f} -> {t['corrected'][k] * 1000:.1f} | "
                 f"{e[orig][k] * 1000:.1f} -> {e[corr][k] * 1000:.1f} |")
    L.append(f"| gain in the mean | {p_gain:.2f}x | {gain(t['original'], t['corrected']):.2f}x | "
             f"{gain(e[orig], e[corr]):.2f}x |")
    L += ["",
          "Today's model: focal-only drift 0.075 px/degC, block with GNSS 3/5 cm and IMU priors, IO at "
          "22.7 degC, focal-only correction, all 20 ground points. Extended model: the Eq. 2 field (focal "
          f"{DAAKIR_SLOPE}, principal point {PP_SLOPE[0]:+.2f} / {PP_SLOPE[1]:+.2f}, rotation "
          f"{ROTATION_SLOPE} px/degC at the corner), the paper's workflow (relative orientation, "
          f"pre-calibration at {PRECALIBRATION_C} degC, Eq. 2 correction of the tie points and GCP "
          "measurements), its 10 GCPs.", "",
          "### The gain, hidden field by correction (paper's workflow; mean residual in mm, gain)", "",
          "| hidden field | original | corrected, focal-only model | corrected, Eq. 2 model |",
          "|---|---:|---:|---:|"]
    rows = (("focal only, with survey noise", "focal"), ("Eq. 2, with survey noise", "eq2"),
            (f"Eq. 2 with {PP_FACTOR:.0f}x Table 8's principal-point drift, with survey noise", "eq2 larger pp"),
            ("focal only, noise-free", "focal noise-free"), ("Eq. 2, noise-free", "eq2 noise-free"))
    for lab, key in rows:
        if key not in w:
            continue
        d = w[key]
        cells = [f"{d[orig]['mean'] * 1000:.2f}"]
        for k in (corr_f, corr):
            cells.append(f"{d[k]['mean'] * 1000:.2f} ({gain(d[orig], d[k]):.2f}x)")
        L.append(f"| {lab} | {' | '.join(cells)} |")
    def seeds(d: dict) -> str:
        return " / ".join(f"{v * 1000:.1f}" for v in d.get("per_seed_mean", [])) or "not recorded"

    dt_pre = PRECALIBRATION_C - get_preset(PRESET).sensors.reference_temperature_c
    draws = []
    for seed in result["seeds"]:
        m = calibrated_models(0.0, np.random.default_rng(seed))["eq2"]
        draws.append(f"({m.dcx_dt - PP_SLOPE[0]:+.3f}, {m.dcy_dt - PP_SLOPE[1]:+.3f})")
    full_better = gain(qn[orig], qn[corr]) > gain(qn[orig], qn[corr_f])

    a_, b_ = e[orig].get("per_seed_mean", []), e[corr].get("per_seed_mean", [])
    n_close = sum(x / y >= 0.8 * 1.4 for x, y in zip(a_, b_, strict=True))

    def per_seed_gains(d: dict) -> str:
        a, b = d[orig].get("per_seed_mean", []), d[corr].get("per_seed_mean", [])
        return ", ".join(f"{x / y:.2f}x" for x, y in zip(a, b, strict=True))
    L += ["",
          "### Every row explained", "",
          f"* **Today's model, gain {gain(t['original'], t['corrected']):.2f}x.** A focal drift on a "
          "nadir corridor held by GNSS (3/5 cm) and IMU priors moves the block by a height offset and a "
          "scale, which the similarity removes; what is left is the survey noise of the points (1 cm per "
          "coordinate) and the block's noise, which the correction does not touch.",
          f"* **The paper's workflow, noise-free: the thermal deformation itself.** Without GNSS and IMU "
          f"weights, IO errors bend the corridor instead of shifting it. A focal-only drift leaves "
          f"{qf[orig]['mean'] * 1000:.2f} mm after the similarity, {qf[corr_f]['mean'] * 1000:.2f} mm "
          f"corrected ({gain(qf[orig], qf[corr_f]):.2f}x, {(qf[orig]['mean'] - qf[corr_f]['mean']) * 1000:+.2f} "
          "mm): next to nothing to gain, as today. The Eq. 2 field, with "
          f"the pre-calibration {dt_pre:.1f} degC warmer than the flight's start (its IO off by "
          f"{DAAKIR_SLOPE * dt_pre:+.2f} px in f and {PP_SLOPE[0] * dt_pre:+.2f} / {PP_SLOPE[1] * dt_pre:+.2f} "
          f"px in the principal point, plus the drift in flight), leaves {thermal:.2f} mm (per seed "
          f"{seeds(qn[orig])}); the Eq. 2 correction {qn[corr]['mean'] * 1000:.2f} mm "
          f"({gain(qn[orig], qn[corr]):.2f}x; per seed {seeds(qn[corr])}), today's focal-only correction "
          f"{qn[corr_f]['mean'] * 1000:.2f} mm ({gain(qn[orig], qn[corr_f]):.2f}x). "
          + ("The hypothesis holds: the gain needs the principal-point terms of the paper's field; a "
             "focal-only correction removes nothing that bends the corridor."
             if full_better else
             "The Eq. 2 correction does not beat the focal-only one here: its own principal-point "
             "calibration error does as much harm as the drift it removes."),
          f"* **What bends the corridor is the principal point.** With a focal-only hidden drift, the Eq. 2 "
          f"correction's calibration error alone (principal-point slope errors per seed {', '.join(draws)} "
          f"px/degC, sigma {PP_CAL_SIGMA}, times the {dt_pre:.1f} degC between pre-calibration and flight) "
          f"leaves {qf[corr]['mean'] * 1000:.2f} mm (per seed {seeds(qf[corr])}) against "
          f"{qf[orig]['mean'] * 1000:.2f} mm without it: a few tenths of a pixel of principal point bend a "
          "two-strip corridor by millimetres, and how much depends on the flight (per-seed spread). The "
          "paper's own principal-point slopes are the parameter it found \"reproducible but not "
          "repeatable\".",
          f"* **Extended column (with the survey noise).** The Eq. 2 correction takes the residual mean "
          f"from {e[orig]['mean'] * 1000:.1f} to {e[corr]['mean'] * 1000:.1f} mm, "
          f"{gain(e[orig], e[corr]):.2f}x pooled over the seeds (focal-only correction: "
          f"{gain(e[orig], e[corr_f]):.2f}x); per seed {per_seed_gains(e) or 'not recorded'}. A "
          f"{thermal:.1f} mm deformation added in quadrature to a {floor:.1f} mm floor predicts "
          f"{predicted:.2f}x.",
          f"* **Min / max / std.** Paper: max 39.6 -> 24.9 mm, std 11.0 -> 6.6 mm (a few GCPs carried most of "
          f"its thermal error); simulation: max {e[orig]['max'] * 1000:.1f} -> {e[corr]['max'] * 1000:.1f} mm, "
          f"std {e[orig]['std'] * 1000:.1f} -> {e[corr]['std'] * 1000:.1f} mm, the survey noise's spread.",
          "",
          "### Why the paper's 1.4x is not reached: the measured reason", "",
          f"If the paper's corrected residual (15.5 mm) is its noise floor, its original 21.4 mm holds a "
          f"thermal part of sqrt(21.4^2 - 15.5^2) = {need:.1f} mm. The drift rates the paper measured "
          "(focal 0.07-0.08 px/degC, Table 8's principal point, rotation < 0.02 px/degC) deform this "
          f"corridor by {thermal:.1f} mm after the similarity on average, {need / max(thermal, 1e-9):.1f} "
          f"times too little; under the GCPs' 1 cm survey noise the correction then gains "
          f"{gain(e[orig], e[corr]):.2f}x. The deformation depends strongly on the simulated flight (per "
          f"seed {seeds(qn[orig])} mm with the same drift and pre-calibration; a seed draws the scene, the "
          f"trajectory's jitter, the GCP layout and the tie points): {n_close} of {len(result['seeds'])} "
          "seeds reach a gain of 1.12x (1.4x less 20 %) or more under the survey noise. The paper's "
          "set-up can give its 1.4x on one flight, not as the expected gain; the paper measured one "
          "flight. "
          "The image rotation adds nothing here, exactly: a rotation of the image about the principal "
          "point is a rotation of the camera about its axis (that is how the simulator applies it), which "
          "each image's free kappa takes in a relative orientation (the diagnosis does not test it without "
          "attitude observations)."]
    if "eq2 larger pp" in w:
        x = w["eq2 larger pp"]
        L.append(f"With the principal-point drift {PP_FACTOR:.0f} times Table 8's "
                 f"({PP_FACTOR * PP_SLOPE[0]:+.2f} / {PP_FACTOR * PP_SLOPE[1]:+.2f} px/degC) the gain is "
                 f"{gain(x[orig], x[corr]):.2f}x ({x[orig]['mean'] * 1000:.1f} -> {x[corr]['mean'] * 1000:.1f} "
                 f"mm): the paper's 1.4x lies between Table 8's drift ({gain(e[orig], e[corr]):.2f}x) and three "
                 "times it.")
    L += ["",
          "What would settle it: the principal-point drift on the flight day (Table 8's slopes come from "
          "another day, and the paper finds the translation \"reproducible but not repeatable\"), the "
          "camera temperature during the terrestrial pre-calibration against the flight's, and the noise "
          "floor of the paper's GCPs (its corrected residual, 15.5 mm, is that floor only if the correction "
          "removed all the thermal error).", ""]
    if result.get("product"):
        L += product_markdown(result)
    return "\n".join(L)


# ----------------------------------------------------------------------------- report: through the product
TRUE_SLOPES = {"df_dt": DAAKIR_SLOPE, "dcx_dt": PP_SLOPE[0], "dcy_dt": PP_SLOPE[1]}


def product_summary(result: dict) -> dict:
    """The product runs over the seeds: per corridor row the pooled residual statistics (m) of original and
    corrected and their gain; per certificate the slopes' estimates, sigmas and z against the truth."""
    per_seed = list(result["product"].values())
    rows: dict = {}
    for name in CERTIFICATES:
        for block in BLOCKS:
            pair = {}
            for label in ("original", "corrected"):
                runs = [p["corridor"].get(f"{name} | {block} | {label}", {}) for p in per_seed]
                done = [r for r in runs if "mean" in r]
                pair[label] = ({k: float(np.mean([r[k] for r in done])) for k in ("mean", "std")}
                               | {"min": min(r["min"] for r in done), "max": max(r["max"] for r in done),
                                  "per_seed_mean": [r["mean"] for r in done]} if done else None)
                pair[f"{label} refused"] = [r["refused"] for r in runs if "refused" in r]
            if pair["original"] and pair["corrected"]:
                pair["gain"] = gain(pair["original"], pair["corrected"])
            rows[f"{name} | {block}"] = pair
    certs: dict = {}
    for name in CERTIFICATES:
        cs = [p["certificates"][name] for p in per_seed]
        slopes = {}
        for k, truth in TRUE_SLOPES.items():
            vals = [c["slopes"][k] for c in cs if k in c["slopes"]]
            slopes[k] = {"values": [v[0] for v in vals], "sigmas": [v[1] for v in vals],
                         "z": [(v[0] - truth) / v[1] for v in vals], "missing": len(cs) - len(vals)}
        ref = get_preset(CALIBRATION_PRESET)
        f_err = [c["f"] - (ref.camera_true.f + DAAKIR_SLOPE * (c["t0"] - ref.sensors.reference_temperature_c))
                 for c in cs if c.get("t0") is not None]
        certs[name] = {"slopes": slopes, "status": [c["status"] for c in cs], "problems": [p for c in cs
                       for p in c["problems"]], "overdispersion": [c["overdispersion"] for c in cs],
                       "f": [c["f"] for c in cs], "f_err": f_err, "t0": [c["t0"] for c in cs]}
    return {"rows": rows, "certificates": certs}


def _named(result: dict, key: str) -> dict[str, list]:
    """The effects the diagnosis named on a corridor row, over the seeds: name -> [(magnitude, sigma), ...]."""
    out: dict[str, list] = {}
    for p in result["product"].values():
        for name, e in (p["corridor"].get(key, {}).get("effects") or {}).items():
            out.setdefault(name, []).append((e["magnitude"], e["sigma"], e.get("alternatives") or []))
    return out


def _effects_text(named: dict[str, list]) -> str:
    if not named:
        return "nothing"
    parts = []
    for name, draws in named.items():
        vals = "; ".join(" / ".join(f"{m:+.3f}" for m in mag) + " +- " + " / ".join(f"{x:.3f}" for x in sig)
                         for mag, sig, _ in draws)
        alt = sorted({a for _, _, alts in draws for a in alts})
        parts.append(f"`{name}` {vals}" + (f" (or {', '.join(alt)}: not separable)" if alt else ""))
    return ", ".join(parts)


def product_markdown(result: dict) -> list[str]:
    """The corridor through ``aerocal.pipeline.process``: the certificates, the gain, the diagnosis."""
    summ = product_summary(result)
    rows, certs = summ["rows"], summ["certificates"]
    per_seed = list(result["product"].values())
    lo = min(p["calibration_range_c"][0] for p in per_seed)
    hi = max(p["calibration_range_c"][1] for p in per_seed)
    t, e, qn = result["today"], result["workflow"]["eq2"], result["workflow"]["eq2 noise-free"]
    orig, corr = "original", "corrected, Eq. 2 model"
    p_gain = PAPER["original"]["mean"] / PAPER["corrected"]["mean"]
    seconds = sum(p["seconds"] for p in per_seed)

    def slope_cell(c: dict, k: str) -> str:
        s = c["slopes"][k]
        if not s["values"]:
            return "not in the certificate"
        return "; ".join(f"{v:+.4f} +- {x:.4f} ({z:+.1f} sigma)" for v, x, z in zip(s["values"], s["sigmas"], s["z"],
                                                                                       strict=True))

    L = ["### Through the product (`aerocal.pipeline.process`)", "",
         f"The corridor as a user of aerocal runs it ({seconds:.0f} s): a calibration flight (preset "
         f"`{CALIBRATION_PRESET}`, the CamLight's 44-frame convergent block, the Eq. 2 field hidden, the sensor "
         f"warming linearly over {lo:.1f}-{hi:.1f} degC: the corridor's start to Table 8's warmest) processed with "
         "`calibrate_only=True` into one certificate store, once with the default configuration (`ProcessConfig()`: "
         "the calibration frees a focal-length slope only) and once with `CalibrationConfig.adjust.thermal = "
         "(\"f\", \"cx\", \"cy\")` (Eq. 2's translation). The corridor (the same flight as the engine's "
         "columns, every GCP a check point) is processed with each certificate pinned, with the certificate's "
         "thermal correction (`block.thermal_correction`, the default) and without; as flown (the flight's GNSS "
         "3/5 cm and IMU sigmas) and as the paper's relative orientation (GNSS 5 m, no attitude, "
         "`use_flight_sigmas=False`). Residuals of the paper's 10 GCPs from `adjustment.check_errors_m` after a "
         "7-parameter similarity.", "",
         "| certificate (calibration flight) | f at its t0 (px), error | df/dT (px/degC) | dcx/dT | dcy/dT | review |",
         "|---|---|---|---|---|---|",
         f"| simulated truth | - | {DAAKIR_SLOPE:+.4f} | {PP_SLOPE[0]:+.4f} | {PP_SLOPE[1]:+.4f} | - |"]
    for name, c in certs.items():
        fcell = "; ".join(f"{f:.2f} ({err:+.2f})" for f, err in zip(c["f"], c["f_err"], strict=True))
        L.append(f"| aerocal, {name} | {fcell} | {slope_cell(c, 'df_dt')} | {slope_cell(c, 'dcx_dt')} | "
                 f"{slope_cell(c, 'dcy_dt')} | {', '.join(sorted(set(c['status'])))} |")

    def pair(key: str, k: str) -> str:
        r = rows[key]
        if not (r["original"] and r["corrected"]):
            return "refused: " + "; ".join(r["original refused"] + r["corrected refused"])
        return f"{r['original'][k] * 1000:.1f} -> {r['corrected'][k] * 1000:.1f}"

    L += ["", "| GCP residual (mm), original -> corrected | paper | engine, today's model | engine, extended model | "
          "aerocal process, focal-only certificate | aerocal process, Eq. 2 certificate |",
          "|---|---|---:|---:|---:|---:|"]
    for k in ("mean", "std", "min", "max"):
        L.append(f"| {k} | {PAPER['original'][k]} -> {PAPER['corrected'][k]} | "
                 f"{t['original'][k] * 1000:.1f} -> {t['corrected'][k] * 1000:.1f} | "
                 f"{e[orig][k] * 1000:.1f} -> {e[corr][k] * 1000:.1f} | "
                 f"{pair('focal-only | relative', k)} | {pair('Eq. 2 | relative', k)} |")

    def g(key: str) -> str:
        return f"{rows[key]['gain']:.2f}x" if "gain" in rows[key] else "-"
    L.append(f"| gain in the mean | {p_gain:.2f}x | {gain(t['original'], t['corrected']):.2f}x | "
             f"{gain(e[orig], e[corr]):.2f}x | {g('focal-only | relative')} | {g('Eq. 2 | relative')} |")
    L += ["", "The product's columns: the relative orientation (the paper's workflow). By block, mean residual "
          "original -> corrected (mm) and gain:", "",
          "| block | focal-only certificate | Eq. 2 certificate | engine, extended model |", "|---|---:|---:|---:|"]
    engine = {"relative": e, "relative, noise-free": qn}
    for block in BLOCKS:
        cells = [f"{pair(f'{n} | {block}', 'mean')} ({g(f'{n} | {block}')})" for n in CERTIFICATES]
        en = engine.get(block)
        cells.append(f"{en[orig]['mean'] * 1000:.1f} -> {en[corr]['mean'] * 1000:.1f} ({gain(en[orig], en[corr]):.2f}x)"
                     if en else "-")
        L.append(f"| {block} | {' | '.join(cells)} |")
    L += ["", *product_explain(result, summ)]
    return L


def product_explain(result: dict, summ: dict) -> list[str]:
    """Sentences from the product runs' numbers: the certificates, the gain, the diagnosis."""
    rows, certs = summ["rows"], summ["certificates"]
    e, qn = result["workflow"]["eq2"], result["workflow"]["eq2 noise-free"]
    orig, corr = "original", "corrected, Eq. 2 model"
    out = []
    # the certificates against the truth
    sent = []
    for name, c in certs.items():
        got = {k: s for k, s in c["slopes"].items() if s["values"]}
        within = [k for k, s in got.items() if all(abs(z) <= 3 for z in s["z"])]
        outside = [k for k in got if k not in within]
        missing = [k for k, s in c["slopes"].items() if not s["values"]]
        phi = float(np.mean(c["overdispersion"]))
        f_err = ", ".join(f"{x:+.2f}" for x in c["f_err"])
        sent.append(
            f"the {name} certificate ({', '.join(sorted(set(c['status'])))}"
            + (f"; problems: {'; '.join(c['problems'])}" if c["problems"] else "") + ") holds "
            + (", ".join(_slope_name(k) for k in got) or "no thermal slope")
            + (f", within 3 sigma of the simulated slope: {', '.join(map(_slope_name, within))}" if within else "")
            + (f", beyond 3 sigma: {', '.join(map(_slope_name, outside))}" if outside else "")
            + (f"; {', '.join(map(_slope_name, missing))} not in its model" if missing else "")
            + f"; its f at its reference temperature is off by {f_err} px"
            + (f" (its calibration measured the formal statistics {phi:.1f}x too optimistic on the block, on its "
               f"own model with its thermal slopes, and raised its significance bar by {np.sqrt(phi):.1f}x: what "
               "the model lacks; the sigmas quoted are the formal ones)" if phi > 1.0 else
               " (its calibration measured no overdispersion on its own model, thermal slopes included)"))
    text = "; ".join(sent)
    out.append("**The certificates.** " + text[:1].upper() + text[1:] + ".")
    cc = result["product"][next(iter(result["product"]))].get("corridor as calibration flight") or {}
    if cc:
        out.append("**The corridor itself as the calibration flight** (the same warming over its images, the "
                   "same two configurations): " + "; ".join(
                       f"{name}: {c['status']}, slopes "
                       + (", ".join(f"{_slope_name(k)} {v[0]:+.3f} +- {v[1]:.3f}" for k, v in c["slopes"].items())
                          or "none (constant IO)")
                       + "".join(f"; {x}" for x in c["selection"] if "/dT" in x and "dropped" in x)
                       for name, c in cc.items()) + ".")
    # the gain
    fr, er = rows["focal-only | relative"], rows["Eq. 2 | relative"]
    fa, ea = rows["focal-only | as flown"], rows["Eq. 2 | as flown"]
    fq, eq = rows["focal-only | relative, noise-free"], rows["Eq. 2 | relative, noise-free"]
    if all("gain" in r for r in (fr, er, fa, ea, fq, eq)):
        mm = 1000.0
        out.append(
            f"**The gain.** Through the product the thermal correction takes the mean GCP residual after the "
            f"similarity from {er['original']['mean'] * mm:.2f} to {er['corrected']['mean'] * mm:.2f} mm with the "
            f"Eq. 2 certificate ({er['gain']:.3f}x) and from {fr['original']['mean'] * mm:.2f} to "
            f"{fr['corrected']['mean'] * mm:.2f} mm with the focal-only one ({fr['gain']:.3f}x) in the relative "
            f"orientation; as flown, {ea['gain']:.3f}x and {fa['gain']:.3f}x (paper: "
            f"{PAPER['original']['mean'] / PAPER['corrected']['mean']:.2f}x; engine, extended model: "
            f"{gain(e[orig], e[corr]):.2f}x). Without the survey noise the thermal deformation the product's "
            f"original block keeps is {eq['original']['mean'] * mm:.2f} mm ({fq['original']['mean'] * mm:.2f} mm "
            f"with the focal-only certificate), {eq['corrected']['mean'] * mm:.2f} mm after the Eq. 2 correction "
            f"({eq['gain']:.2f}x) and {fq['corrected']['mean'] * mm:.2f} mm after the focal-only one "
            f"({fq['gain']:.2f}x); the engine's paper workflow keeps {qn[orig]['mean'] * mm:.2f} mm "
            f"(pre-calibration at {PRECALIBRATION_C} degC), the product's original block uses the certificate's IO "
            f"at its reference temperature {np.mean(certs['Eq. 2']['t0']):.1f} degC. Added in quadrature to the "
            f"survey floor ({er['corrected']['mean'] * mm:.1f} mm) that deformation predicts "
            f"{np.hypot(er['corrected']['mean'], eq['original']['mean']) / er['corrected']['mean']:.3f}x.")
    else:
        out.append("**The gain.** Not measured: a corridor run was refused (see the table).")
    # the diagnosis
    d_rows = []
    for name in CERTIFICATES:
        for label in ("original", "corrected"):
            named = _effects_text(_named(result, f"{name} | relative | {label}"))
            d_rows.append(f"{name} certificate, {label} (relative): {named}")
    named_eq2 = _named(result, "Eq. 2 | relative | corrected")
    same = all(_same_effects(_named(result, f"{n} | relative | original"),
                             _named(result, f"{n} | relative | corrected")) for n in CERTIFICATES)
    pp = named_eq2.get("thermal_principal_point")
    cert_pp = certs["Eq. 2"]["slopes"]
    again = (f" With the Eq. 2 certificate, whose thermal model holds dcx/dT, dcy/dT = "
             f"{np.mean(cert_pp['dcx_dt']['values']):+.3f} / {np.mean(cert_pp['dcy_dt']['values']):+.3f} px/degC and "
             "whose correction the block applied, the diagnosis still names a principal-point drift: the diagnosis "
             "step adjusts with the certificate's IO at its reference temperature and no thermal correction."
             if pp and cert_pp["dcx_dt"]["values"] else "")
    if same:
        again += " It names the same effects, with the same sizes, with the correction on and off."
    z = []
    for key, truth in (("focal-only | relative | original", PP_SLOPE), ("Eq. 2 | relative | corrected", PP_SLOPE)):
        for mag, sig, _ in _named(result, key).get("thermal_principal_point", []):
            z.append(max(abs(m - tr) / x for m, tr, x in zip(mag, truth, sig, strict=True)))
    if z:
        again += (f" Its principal-point slopes lie within {max(z):.1f} sigma of the simulated drift.")
    unsimulated = sorted({n for p in result["product"].values() for r in p["corridor"].values()
                          for n in r.get("effects") or {}} - set(EQ2_FIELD))
    if unsimulated:
        again += f" Named but not simulated: {', '.join(unsimulated)}."
    out.append("**What the diagnosis named** (simulated: focal "
               f"{DAAKIR_SLOPE}, principal point {PP_SLOPE[0]:+.2f} / {PP_SLOPE[1]:+.2f}, rotation {ROTATION_SLOPE} "
               "px/degC): " + "; ".join(d_rows) + "." + again)
    return [x for p in out for x in (p, "")]


def _same_effects(a: dict[str, list], b: dict[str, list]) -> bool:
    """Whether two diagnoses named the same effects with sizes equal to 0.1 % of their sigmas."""
    if set(a) != set(b):
        return False
    return all(len(a[k]) == len(b[k]) and all(np.allclose(ma, mb, rtol=0.0, atol=1e-3 * max(map(abs, sa), default=1.0))
                                              for (ma, sa, _), (mb, _, _) in zip(a[k], b[k], strict=True)) for k in a)


def _slope_name(key: str) -> str:
    return {"df_dt": "df/dT", "dcx_dt": "dcx/dT", "dcy_dt": "dcy/dT"}.get(key, key)


def figure(result: dict, path: Path) -> None:
    plt = pyplot()
    t, e = result["today"], result["workflow"]["eq2"]
    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    x = np.arange(2)
    ax.bar(x - 0.25, [PAPER["original"]["mean"], PAPER["corrected"]["mean"]], width=0.25, label="paper")
    ax.bar(x, [t["original"]["mean"] * 1000, t["corrected"]["mean"] * 1000], width=0.25,
           label="simulation, today's model")
    ax.bar(x + 0.25, [e["original"]["mean"] * 1000, e["corrected, Eq. 2 model"]["mean"] * 1000], width=0.25,
           label="simulation, extended model")
    ax.set_xticks(x, ["original", "corrected"])
    ax.set_ylabel("GCP residual mean after similarity (mm)")
    ax.set_title("Daakir 2019 UAV corridor", fontsize=9)
    ax.legend(fontsize=7)
    save_png(fig, path)


def main(argv: list[str] | None = None) -> Path:
    ap = study_parser(__doc__, "one seed, a 24-image corridor (~160 s)")
    args = ap.parse_args(argv)
    md = write_study("daakir2019", run(quick=args.quick), markdown, figure, args.out, args.quick)
    print(f"wrote {md}")
    return md


if __name__ == "__main__":
    main()
