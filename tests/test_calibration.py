"""Self-calibration under the decision rule (engine level; the product path is in test_no_confident_wrong_answer)."""

import dataclasses

import pytest
from tolerance import assert_within_sigma

from aerocal.adjust import AdjustConfig
from aerocal.calibrate.self_calibration import CalibrationConfig, self_calibrate
from aerocal.certificates.review import DecisionConfig
from aerocal.simulate import PRESETS, simulate_flight
from aerocal.simulate.sensors import TemperatureCurve

SPEC = PRESETS["conte-calibration"]
CONFIG = AdjustConfig(gnss_sigma_m=(0.10, 0.10, 0.15), thermal=("f",), adaptive=True)


def test_a_calibration_from_input_with_errors_is_rejected():
    """One bad input cell must not become the camera's certificate for every later flight; the fit never saw the
    skipped item, so the flight it was made on may use it (``usable_on_its_flight``)."""
    seed = 43
    sim = simulate_flight(SPEC, seed=seed, max_images=20)
    error = "eo.csv:7: alt 'abc' is not a number [error]"
    cal = self_calibrate(sim.images, sim.observations, SPEC.camera_nominal, sim.gcps, sim.gcp_observations,
                         config=CalibrationConfig(null_draws=0), adjust_config=CONFIG, input_errors=(error,))
    assert cal.review.status == "rejected" and error in cal.review.problems[-1], cal.review
    assert len(cal.review.problems) == 1 and cal.usable_on_its_flight, cal.review


def test_an_overdispersion_that_could_not_be_measured_is_said(monkeypatch):
    """When the block's null cannot be fitted, the formal sigmas are used as they are, and the review says so
    with the reason (they were several times too small on real blocks)."""
    import aerocal.calibrate.self_calibration as calibration

    def failing(*args, **kwargs):
        raise ValueError("no tie point left after thinning")

    monkeypatch.setattr(calibration, "fit_baseline", failing)
    seed = 44
    sim = simulate_flight(SPEC, seed=seed, max_images=20)
    cfg = dataclasses.replace(CONFIG, thermal=(), adaptive=False)
    cal = self_calibrate(sim.images, sim.observations, SPEC.camera_nominal, sim.gcps, sim.gcp_observations,
                         config=CalibrationConfig(null_draws=5), adjust_config=cfg)
    said = [n for n in cal.review.notes if "overdispersion could not be measured" in n]
    assert said and "no tie point left after thinning" in said[0], (seed, cal.review.notes)
    assert cal.overdispersion == 1.0, seed


def test_a_thermal_slope_is_certified_only_with_a_held_out_gain():
    """A focal drift of 1.5 px/degC while the camera warms by 12 degC predicts held-out strips better and is
    kept; on the same flight without a drift the slope is not certified."""
    seed = 44
    spec = SPEC.replace(sensors=dataclasses.replace(SPEC.sensors, temperature=TemperatureCurve(10.0, 30.0, 600.0)))
    warm = simulate_flight(spec, seed=seed, effects={"thermal_focal": (1.5,)})
    cal = self_calibrate(warm.images, warm.observations, spec.camera_nominal, warm.gcps, warm.gcp_observations,
                         adjust_config=CONFIG)
    h = cal.held_out.get("df/dT")
    assert h is not None and h.beyond(2.0), f"seed {seed}: {h and h.describe()}"
    assert "df/dT" in cal.result.thermal_slopes, f"seed {seed}: {cal.review.notes}"
    # bounded: a slope kept for its held-out gain is known to 20 % of itself
    assert_within_sigma(cal.result.thermal_slopes["df/dT"] - 1.5, cal.result.thermal_sigmas["df/dT"], 4, 0.3,
                        f"seed {seed}: df/dT (px/degC)")
    still = simulate_flight(spec, seed=seed)
    cal = self_calibrate(still.images, still.observations, spec.camera_nominal, still.gcps, still.gcp_observations,
                         adjust_config=CONFIG)
    assert not cal.result.thermal_slopes, f"seed {seed}: {cal.result.thermal_slopes} {cal.review.notes}"


def test_a_slope_no_lens_has_is_dropped_not_the_whole_certificate():
    """A focal drift of 5 px/degC (0.3 % of f per degC, beyond any lens) that predicts held-out strips better
    is a signal of another cause: the slope goes, the constant IO is certified."""
    seed = 45
    spec = SPEC.replace(sensors=dataclasses.replace(SPEC.sensors, temperature=TemperatureCurve(10.0, 30.0, 600.0)))
    sim = simulate_flight(spec, seed=seed, effects={"thermal_focal": (5.0,)})
    cal = self_calibrate(sim.images, sim.observations, spec.camera_nominal, sim.gcps, sim.gcp_observations,
                         config=CalibrationConfig(null_draws=0), adjust_config=CONFIG)
    assert not cal.result.thermal_slopes, f"seed {seed}: {cal.review.notes}"
    assert any("no lens drifts that fast" in n for n in cal.review.notes), cal.review.notes
    assert cal.review.status == "accepted", f"seed {seed}: {cal.review.problems}"



def _off_centre_flight(n_strips: int, seed: int):
    """An xt2-survey flight (2 / 5 m GNSS, no GCPs) whose lens sits 15 px (3 % of the side) below the frame's
    centre, and the self-calibration's settings with f, cx, cy, k1, k2 free."""
    spec = PRESETS["xt2-survey"]
    true = dataclasses.replace(spec.camera_true, cy=spec.camera_nominal.cy + 15.0)
    spec = dataclasses.replace(spec, camera_true=true, plan=dataclasses.replace(spec.plan, n_strips=n_strips),
                               sensors=dataclasses.replace(spec.sensors, gnss_sigma_h_m=2.0, gnss_sigma_v_m=5.0))
    sim = simulate_flight(spec, seed=seed)
    cfg = AdjustConfig(free=("f", "cx", "cy", "k1", "k2"), gnss_sigma_m=(2.0, 2.0, 5.0), adaptive=True)
    return spec, sim, cfg


@pytest.mark.parametrize("seed", [61])
def test_a_principal_point_the_prediction_holds_is_freed_when_held_out_images_refute_the_centre(seed):
    """Two strips, and a determinability threshold strict enough (0.2 % of the side) that the geometry's prediction
    holds cx and cy at the centre: the k-fold over the block shows that freed they predict images the fit did not
    use better, so they are freed, and cy is the true one."""
    spec, sim, cfg = _off_centre_flight(2, seed)
    strict = CalibrationConfig(null_draws=0, decision=DecisionConfig(determined_principal_point=0.002))
    cal = self_calibrate(sim.images, sim.observations, spec.camera_nominal, sim.gcps, sim.gcp_observations,
                         height_agl_m=spec.plan.height_agl_m, config=strict, adjust_config=cfg)
    text = "\n".join(cal.review.notes)
    print(f"seed {seed}:", text)
    assert "cx, cy freed although the geometry's prediction held them" in text, f"seed {seed}: {text}"
    assert not {"cx", "cy"} & set(cal.held_at_nominal), cal.held_at_nominal
    cy, sigma = cal.result.camera.cy, cal.result.sigmas["cy"]
    assert abs(cy - spec.camera_true.cy) <= min(3.0 * sigma, 2.0) + 0.5, f"seed {seed}: cy {cy} +- {sigma}"
    assert cal.held_out["cy"].beyond(2.0), cal.held_out


@pytest.mark.parametrize("seed", [61])
def test_a_principal_point_held_out_images_do_not_support_stays_held(seed):
    """One strip of 8 frames cannot tell the principal point from the poses: held by the prediction; freed, it
    predicts the held-out frames no better than 2 standard errors, or (the lens is 15 px off) marginally better with
    a calibrated sigma the decision rule rejects, so it stays at the centre and the review says which."""
    spec, sim, cfg = _off_centre_flight(1, seed)
    cal = self_calibrate(sim.images, sim.observations, spec.camera_nominal, sim.gcps, sim.gcp_observations,
                         height_agl_m=spec.plan.height_agl_m, config=CalibrationConfig(null_draws=0),
                         adjust_config=cfg)
    text = "\n".join(cal.review.notes)
    print(f"seed {seed}:", text)
    assert {"cx", "cy"} <= set(cal.held_at_nominal), f"seed {seed}: {cal.held_at_nominal}"
    why = [n for n in cal.review.notes if n.startswith("cx, cy held at the nominal all the same: freed, they")]
    assert len(why) == 1, text
    assert ("do not predict held-out images better" in why[0]
            or "cy not determined by this block: calibrated sigma" in why[0]), why[0]
