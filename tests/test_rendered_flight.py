"""Rendered simulated frames: the geometry of the pixels is the geometry of the observations."""

import numpy as np
import pytest
import tifffile

from aerocal.simulate import simulate_flight, write_flight
from aerocal.simulate.raycast import RenderConfig, render_frame
from aerocal.simulate.rendered_frames import target_scene
from aerocal.targets import locate_targets

# every effect of the catalogue that acts on pixels, in three renders (the exterior-orientation effects
# change only what is recorded, not the pixels)
EFFECTS = [
    {},
    {"thermal_focal": 0.3, "thermal_principal_point": (0.3, -0.2), "affinity_skew": (1.5, 0.8), "radial_k3": 0.3},
    {"rolling_shutter": 0.03, "refraction": "on"},
]


@pytest.mark.parametrize("effects", EFFECTS, ids=lambda e: ",".join(e) or "none")
def test_rendered_targets_sit_at_their_analytic_projection(effects):
    seed = 21
    sim = simulate_flight("conte-calibration", seed=seed, effects=effects)
    scene = target_scene(sim)
    config = RenderConfig(modality="thermal", supersample=3, netd_k=0.0, blur_sigma_px=0.5)
    rng = np.random.default_rng(seed)
    errors = []
    # the frames that see the most targets
    counts = np.bincount(sim.gcp_observations.column("image_id").to_numpy(), minlength=len(sim.exposures) + 1)
    for image_id in np.argsort(counts)[::-1][:1]:
        ex = sim.exposures[image_id - 1]
        uv = ex.project(scene.target_points())
        inside = ex.camera.in_image(uv, margin=12)
        if not inside.any():
            continue
        img = render_frame(scene, ex, config, rng)
        found = locate_targets(img, uv[inside], window_px=9)
        ok = np.isfinite(found).all(axis=1)
        errors.append(np.linalg.norm(found[ok] - uv[inside][ok], axis=1))
    err = np.concatenate(errors)
    assert len(err) >= 3, f"seed {seed}: too few targets located ({len(err)})"
    assert np.max(err) < 0.1, f"seed {seed}, effects {effects}: target errors up to {np.max(err):.3f} px"


def test_images_mode_writes_frames_a_reader_can_open(tmp_path):
    sim = simulate_flight("conte-calibration", seed=2, max_images=3)
    out = write_flight(sim, tmp_path / "flight", mode="images")
    frames = sorted((out / "images").glob("*.tif"))
    assert [f.name for f in frames] == ["IMG_0001.tif", "IMG_0002.tif", "IMG_0003.tif"]
    img = tifffile.imread(frames[0])
    assert img.dtype == np.uint16 and img.shape == (480, 640)
    kelvin = img / 100.0
    assert 260 < np.median(kelvin) < 320 and img.std() > 50, "thermal DN = 100 K with real contrast"
    assert not (out / "observations" / "observations.parquet").exists(), "images mode hands over pixels only"
