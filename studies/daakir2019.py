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

Run: ``python -m studies.daakir2019`` (five seeds, 698 s on 2 shared cores; ``--quick``: one seed, a 24-image corridor,
< 90 s). Writes ``studies/output/daakir2019.md`` (``daakir2019_quick.md``) and a PNG.
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
from aerocal.geometry import estimate_similarity
from aerocal.simulate import get_preset, simulate_flight
from aerocal.simulate.presets import FlightSpec
from studies.papers import as_checks, gnss_priors, pyplot, save_png, stats, study_parser, write_study

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

    @staticmethod
    def for_quick() -> StudyConfig:
        return StudyConfig(quick=True, seeds=(1,), images=24, points_per_image=200)

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
    src = dst + res.check_errors
    ok = np.isfinite(src).all(axis=1)
    s7 = estimate_similarity(src[ok], dst[ok])
    return np.linalg.norm(s7.apply(src[ok]) - dst[ok], axis=1)


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
    return "\n".join(L)


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
    ap = study_parser(__doc__, "one seed, a 24-image corridor (< 90 s)")
    args = ap.parse_args(argv)
    md = write_study("daakir2019", run(quick=args.quick), markdown, figure, args.out, args.quick)
    print(f"wrote {md}")
    return md


if __name__ == "__main__":
    main()
