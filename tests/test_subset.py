"""Calibration-subset selection from recorded poses and ground control (no truth used)."""

from __future__ import annotations

import dataclasses

from tolerance import assert_within_sigma

from aerocal.adjust import AdjustConfig, adjust, select_images
from aerocal.calibrate.subset import SubsetConfig, propose_subset
from aerocal.simulate import get_preset, simulate_flight


def test_subset_prefers_transversal_strip_and_its_prediction_is_honest():
    spec = get_preset("conte-calibration")
    spec = spec.replace(plan=dataclasses.replace(spec.plan, images_per_strip=12), n_gcp=11)
    sim = simulate_flight(spec, seed=5)
    s = spec.sensors
    acfg = AdjustConfig(
        gnss_sigma_m=(s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m),
        free=("f", "cx", "cy", "k1", "k2", "p1", "p2"),
    )
    prop = propose_subset(
        sim.images,
        sim.camera_nominal,
        sim.gcps,
        SubsetConfig(adjust=acfg, tie_sigma_px=s.tie_sigma_px, max_images=44),
    )
    print("\n".join(prop.reasons))
    assert prop.transversal, f"seed 5: the chosen subset has no transversal strip: {prop.reasons}"
    assert len(prop.image_ids) <= 44 and len(prop.gcp_ids) >= 1
    no_t = [c for c in prop.candidates if not c["transversal"] and c["n_images"] == len(prop.image_ids) - 12]
    assert all(c["score"] > prop.score for c in no_t), (
        "a transversal strip should improve the predicted sigma"
    )
    # the adjustment on the chosen subset reaches about the predicted precision
    res = adjust(
        select_images(sim.images, prop.image_ids),
        select_images(sim.observations, prop.image_ids),
        sim.camera_nominal,
        acfg,
        sim.gcps,
        select_images(sim.gcp_observations, prop.image_ids),
    )
    for n in ("f", "cx", "cy"):
        ratio = res.sigmas[n] / prop.predicted_sigmas[n]
        print(
            f"{n}: predicted {prop.predicted_sigmas[n]:.3f} px, adjustment {res.sigmas[n]:.3f} px, "
            f"ratio {ratio:.2f}"
        )
        assert 0.5 < ratio < 2.0, f"seed 5: {n} predicted sigma off by {ratio:.2f}"
    err = res.camera.f - spec.camera_true.f
    assert_within_sigma(err, res.sigmas["f"], 3, 0.002 * spec.camera_true.f, "seed 5: f (px)")
