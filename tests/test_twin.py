"""The flight's twin: white-noise simulation explains a white-noise block; a block with per-frame focal jitter
is told apart from it, the cause named, the simulation extended and the gap closed."""

import numpy as np
import pyarrow as pa

from aerocal.adjust import AdjustConfig
from aerocal.diagnose.model import fit_baseline
from aerocal.simulate import PRESETS, simulate_flight
from aerocal.twin import compare

SPEC = PRESETS["conte-calibration"]
CONFIG = AdjustConfig(free=(), gnss_sigma_m=(0.10, 0.10, 0.15))


def _block(seed: int, jitter: float):
    sim = simulate_flight(SPEC, seed=seed)
    obs = sim.observations
    if jitter:
        rng = np.random.default_rng(seed)
        o = obs.to_pydict()
        img = np.asarray(o["image_id"])
        scale = 1.0 + rng.normal(0.0, jitter, img.max() + 1)[img]  # each frame's focal length jitters
        cam = SPEC.camera_true
        obs = obs.set_column(2, "x", pa.array(cam.cx + (np.asarray(o["x"]) - cam.cx) * scale))
        obs = obs.set_column(3, "y", pa.array(cam.cy + (np.asarray(o["y"]) - cam.cy) * scale))
    return fit_baseline(sim.images, obs, SPEC.camera_true, CONFIG, sim.gcps, sim.gcp_observations)


def test_a_white_noise_block_is_explained_by_its_twin():
    seed = 61
    c = compare(_block(seed, 0.0), n_twins=5)
    assert not c.differs, f"seed {seed}: {c.summary()}"
    assert "explains it" in c.summary()


def test_per_frame_focal_jitter_is_named_and_the_extended_twin_closes_the_gap():
    seed = 62
    jitter = 4e-4  # ~0.7 px at the corners of a 640x480 frame; 3.83e-4 RMS as drawn for this seed's 44 frames
    c = compare(_block(seed, jitter), n_twins=5)
    assert "per_image_scale" in c.differs, f"seed {seed}: {c.summary()}"
    ext = c.extended["per-image focal jitter"]
    assert abs(ext["jitter"] - 3.83e-4) < 0.3 * 3.83e-4, f"seed {seed}: {ext}"
    assert 0.7 < ext["gap_closed"]["per_image_scale"] < 1.4, f"seed {seed}: {ext}"


def test_an_extension_beyond_any_lens_is_not_named_as_the_cause():
    seed = 63
    jitter = 1e-2  # 1 % of f per frame: no lens does this; the per-image scale must come from elsewhere
    c = compare(_block(seed, jitter), n_twins=3)
    ext = c.extended["per-image focal jitter"]
    assert ext["jitter"] > 2e-3 and ext["plausible"] is False, f"seed {seed}: {ext}"
    assert "beyond any lens" in c.summary() and "not the cause" in c.summary(), f"seed {seed}: {c.summary()}"
