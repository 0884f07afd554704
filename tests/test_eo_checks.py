"""The recorded GNSS offset is tested against control GCPs before a self-calibration, and subtracted when named."""

import dataclasses

import numpy as np
from tolerance import assert_within_sigma

from aerocal.adjust import AdjustConfig
from aerocal.calibrate.eo_checks import correct_gnss_offset
from aerocal.simulate import PRESETS, simulate_flight

SPEC = PRESETS["conte-calibration"]
CONFIG = AdjustConfig(gnss_sigma_m=(0.10, 0.10, 0.15))  # f, cx, cy, k1..k3, p1, p2 free, as a calibration


def test_a_horizontal_gnss_offset_is_found_and_subtracted():
    seed = 41
    hidden = np.array([2.0, -1.6, 0.0])
    sim = simulate_flight(SPEC, seed=seed, effects={"gnss_bias": tuple(hidden)})
    out = correct_gnss_offset(sim.images, sim.observations, SPEC.camera_nominal, CONFIG, sim.gcps,
                              sim.gcp_observations)
    assert out.offset_m is not None, f"seed {seed}: {out.notes}"
    err = np.abs(np.asarray(out.offset_m[:2]) - hidden[:2])
    assert_within_sigma(err, out.sigma_m[:2], 3, 0.5, f"seed {seed}: GNSS offset E, N (m)")
    moved = sim.images.column("gnss_x").to_numpy() - out.images.column("gnss_x").to_numpy()
    assert np.allclose(moved, out.offset_m[0]) and "subtracted" in out.notes[0]


def test_without_control_the_offset_is_not_testable():
    seed = 42
    spec = SPEC.replace(n_gcp=0, n_check=0, sensors=dataclasses.replace(SPEC.sensors, gnss_sigma_h_m=2.0))
    sim = simulate_flight(spec, seed=seed)
    out = correct_gnss_offset(sim.images, sim.observations, spec.camera_nominal, CONFIG, sim.gcps,
                              sim.gcp_observations)
    assert out.offset_m is None and out.images is sim.images
    assert "not testable: 0 control GCPs" in out.notes[0], out.notes



def test_a_gnss_time_lag_is_found_and_removed_without_control():
    """A camera clock 0.3 s off the receiver's (small drones: tenths of a second) moves every position along
    its track; strips flown both ways determine it without GCPs."""
    seed = 43
    spec = SPEC.replace(n_gcp=0, n_check=0)
    lag = 0.3
    sim = simulate_flight(spec, seed=seed, effects={"gnss_time_offset": lag})
    out = correct_gnss_offset(sim.images, sim.observations, spec.camera_nominal, CONFIG, sim.gcps,
                              sim.gcp_observations)
    assert out.time_offset_s is not None, f"seed {seed}: {out.notes}"
    assert abs(out.time_offset_s - lag) < max(3 * out.time_sigma_s, 0.25 * lag), (
        f"seed {seed}: {out.time_offset_s} +- {out.time_sigma_s}")
    assert any("GNSS time lag" in n and "removed" in n for n in out.notes), out.notes
    # and an effect-free flight keeps its positions
    clean = simulate_flight(spec, seed=seed)
    kept = correct_gnss_offset(clean.images, clean.observations, spec.camera_nominal, CONFIG, clean.gcps,
                               clean.gcp_observations)
    assert kept.time_offset_s is None and kept.images is clean.images, f"seed {seed}: {kept.notes}"


def test_a_rolling_shutter_readout_is_not_removed_as_a_gnss_time_lag():
    """A frame read out row by row (33 ms, rows from the nose) while the aircraft flies displaces its rows along
    the track, the other way on strips flown back. Through the pipeline's calibration, a time lag tested alone
    had mimicked it: +51 +- 14 ms "removed" (3 m along each track) from a flight with no lag. With the readout
    tested beside it, the readout is named, the lag is not removed, and a real lag with the readout still is."""
    from aerocal.pipeline import process
    from aerocal.simulate import as_dataset

    seed = 101
    effects = {"thermal_focal": 0.2, "rolling_shutter": 0.033}
    sim = simulate_flight(SPEC, seed=seed, effects=effects)
    review = process(as_dataset(sim), calibrate_only=True).json("certificate")["review"]
    lag_notes = [n for n in review["notes"] if n.startswith("GNSS time lag")]
    assert lag_notes and "removed" not in lag_notes[0], f"seed {seed}: {review['notes']}"
    assert "rolling_shutter 0.03" in lag_notes[0], f"seed {seed}: {lag_notes}"
    lag = 0.3
    both = simulate_flight(SPEC, seed=seed, effects={**effects, "gnss_time_offset": lag})
    out = correct_gnss_offset(both.images, both.observations, SPEC.camera_nominal, CONFIG, both.gcps,
                              both.gcp_observations)
    assert out.time_offset_s is not None, f"seed {seed}: {out.notes}"
    assert abs(out.time_offset_s - lag) < max(3 * out.time_sigma_s, 0.1 * lag), (
        f"seed {seed}: {out.time_offset_s} +- {out.time_sigma_s}; {out.notes}")


def test_a_principal_point_error_is_not_removed_as_a_gnss_time_lag():
    """A nominal camera whose principal point is 0.8 px off (a metric camera's 5 um): each footprint moves along
    its own track as a lag would, opposite on strips flown the other way. With the nominal camera's tolerances
    taken into the test, the block step keeps the recorded positions; held exact, it removed a lag of
    -1.57 +- 0.22 ms (7 sigma, 11 cm along each track) on this seed."""
    from aerocal.pipeline import process
    from aerocal.simulate import as_dataset

    seed = 1
    sim = simulate_flight("mitishita-block", seed=seed)  # true cy 0.83 px from the nominal one, no lag
    run = process(as_dataset(sim), certificate="nominal")
    notes = [n for n in run.summary.recorded_eo_corrections if "time lag" in n]
    assert notes and "removed" not in notes[0], f"seed {seed}: {notes}"
    assert run.json("adjustment")["recorded_eo_corrections"]["time_offset_s"] is None
