"""The recorded GNSS offset is tested against control GCPs before a self-calibration, and subtracted when named."""

import dataclasses

import numpy as np

from aerocal.adjust import AdjustConfig
from aerocal.eo_checks import correct_gnss_offset
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
    assert np.all(err < 3 * np.asarray(out.sigma_m[:2])), f"seed {seed}: {out.offset_m} +- {out.sigma_m}"
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

