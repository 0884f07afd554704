"""Self-calibration under the decision rule (engine level; the product path is in test_no_confident_wrong_answer)."""

import dataclasses

import numpy as np

from aerocal.adjust import AdjustConfig
from aerocal.calibration import CalibrationConfig, self_calibrate
from aerocal.decision import fighting_radial_term, radial_cancellation
from aerocal.simulate import PRESETS, simulate_flight
from aerocal.simulate.sensors import TemperatureCurve

SPEC = PRESETS["conte-calibration"]
CONFIG = AdjustConfig(gnss_sigma_m=(0.10, 0.10, 0.15), thermal=("f",), adaptive=True)


def test_a_calibration_from_input_with_errors_is_rejected():
    """One bad input cell must not become the camera's certificate for every later flight."""
    seed = 43
    sim = simulate_flight(SPEC, seed=seed, max_images=20)
    error = "eo.csv:7: alt 'abc' is not a number [error]"
    cal = self_calibrate(sim.images, sim.observations, SPEC.camera_nominal, sim.gcps, sim.gcp_observations,
                         config=CalibrationConfig(null_draws=0), adjust_config=CONFIG, input_errors=(error,))
    assert cal.review.status == "rejected" and error in cal.review.problems[-1], cal.review


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
    assert abs(cal.result.thermal_slopes["df/dT"] - 1.5) < 4 * cal.result.thermal_sigmas["df/dT"]
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


def test_radial_terms_that_cancel_each_other_are_told_from_a_lens():
    """The simulated conte lens (k1 -0.08, k2 0.12 at 16 degrees) has terms that barely interact; the k2 / k3
    pair a rendered city calibration block took (k3 -202 against k2, each moving the corners by 4 % of their
    radius where the lens moves them by 0.5 %) cancels itself, and the near-singular k3 is the one named."""
    lens = SPEC.camera_true
    assert 1.0 <= radial_cancellation(lens) < 1.3
    assert radial_cancellation(SPEC.camera_nominal) == 1.0
    r2 = (lens.corner_radius / lens.f) ** 2
    fought = lens.replace(k3=-201.8, k2=lens.k2 + 201.8 * r2)
    assert radial_cancellation(fought) > 10.0
    names = ["f", "cx", "cy", "k1", "k2", "k3"]
    corr = np.eye(6)
    corr[4, 5] = corr[5, 4] = -0.97
    name, why = fighting_radial_term(names, corr, fought, corr_limit=0.95)
    assert name == "k3" and "k3 -201.8 is nearly collinear with k2 (|corr| 0.970" in why, why
    assert fighting_radial_term(names, corr, lens, corr_limit=0.95) == (None, "")  # a lens: no fight
    corr[4, 5] = corr[5, 4] = -0.5
    assert fighting_radial_term(names, corr, fought, corr_limit=0.95) == (None, "")  # separable: the t decides


def test_a_lens_whose_radial_terms_cancel_keeps_them_when_held_out_images_confirm_them():
    """A narrow-field lens whose k2 and k3 undo each other (+1.5 % and -1.9 % of the corner radius alone,
    -0.9 % together): the pair is nearly collinear and cancels, so the self-calibration asks held-out strips;
    they confirm k3, it is kept with the reason, and the lens's profile is recovered."""
    seed = 46
    lens = SPEC.camera_true.replace(k2=4.5, k3=-100.0)
    spec = SPEC.replace(camera_true=lens)
    sim = simulate_flight(spec, seed=seed)
    cal = self_calibrate(sim.images, sim.observations, spec.camera_nominal, sim.gcps, sim.gcp_observations,
                         config=CalibrationConfig(null_draws=0),
                         adjust_config=dataclasses.replace(CONFIG, thermal=()))
    notes = " | ".join(cal.review.notes)
    print(f"seed {seed}: {cal.result.camera}; {notes}")
    assert "k3" in cal.held_out, f"seed {seed}: the held-out test was not asked: {notes}"
    assert "k3 kept" in notes and "cancel each other" in notes, f"seed {seed}: {notes}"
    got = cal.result.camera
    r = np.linspace(0.0, got.corner_radius / got.f, 50)
    profile = [c.f * r * (c.k1 * r**2 + c.k2 * r**4 + c.k3 * r**6) for c in (got, lens)]
    assert np.max(np.abs(profile[0] - profile[1])) < 0.5, f"seed {seed}: radial profile off by > 0.5 px"
