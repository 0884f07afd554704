"""The flight simulator: presets reproduce the seeds' figures, effects move points as their formulas say."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from aerocal import effects as fx
from aerocal import tables
from aerocal.cli import app
from aerocal.simulate import PRESETS, simulate_flight, write_flight
from aerocal.simulate.exposure import Exposure
from aerocal.simulate.flight_plan import overlaps
from aerocal.simulate.sensors import TemperatureCurve
from aerocal.simulate.simulator import recorded_R_cw, spec_summary

DT = 10.0  # degC above the reference temperature for thermal effects


def quiet(name: str, temperature_offset: float = 0.0, **sensor_kw):
    """A preset with noise-free GNSS/IMU and a constant sensor temperature."""
    spec = PRESETS[name]
    t = spec.sensors.reference_temperature_c + temperature_offset
    sensors = dataclasses.replace(
        spec.sensors, gnss_sigma_h_m=0.0, gnss_sigma_v_m=0.0, imu_sigma_deg=(0.0, 0.0, 0.0),
        temperature=TemperatureCurve(start_c=t, equilibrium_c=t, noise_c=0.0), **sensor_kw,
    )
    return spec.replace(sensors=sensors)


def grid_pixels(cam, n=9):
    u, v = np.meshgrid(np.linspace(0, cam.width, n), np.linspace(0, cam.height, n))
    return np.column_stack([u.ravel(), v.ravel()])


def ground_points(ex: Exposure, uv, z):
    o, d = ex.rays(uv)
    s = (z - o[:, 2]) / d[:, 2]
    return o + s[:, None] * d


def recorded_exposure(sim, i):
    """Frame i as the recorded GNSS/IMU describe it (true IO)."""
    im = sim.images
    R = recorded_R_cw(im)[i]
    C = np.array([im.column(c)[i].as_py() for c in ("gnss_x", "gnss_y", "gnss_z")])
    ex = sim.exposures[i]
    return Exposure(ex.image_id, ex.camera, R, C, ex.velocity)


# ------------------------------------------------------------------------------------------ presets
def test_conte_city_reproduces_the_paper_figures():
    sim = simulate_flight("conte-city", seed=1)
    gsd = sim.trajectory.gsd_m
    fwd, side = overlaps(sim.trajectory, sim.spec.camera_nominal, sim.spec.plan.height_agl_m)
    n = sim.images.num_rows
    assert abs(gsd - 0.5) / 0.5 < 0.03, f"GSD {gsd:.3f} m"
    assert abs(fwd - 0.60) < 0.05 and abs(side - 0.20) < 0.05, f"overlaps {fwd:.2f}/{side:.2f}"
    assert abs(n - 800) / 800 < 0.10, f"{n} frames"
    assert sim.trajectory.transversal.any(), "one transversal strip"
    per_image = np.bincount(sim.tie.image_id)[1:]
    assert np.median(per_image) > 300, "enough tie points per frame"


def test_conte_calibration_subset_shape():
    sim = simulate_flight("conte-calibration", seed=2)
    s = spec_summary(sim)
    assert s["images"] == 44 and s["strips"] == 5 and s["gcps"] == 11
    assert int(sim.trajectory.transversal.sum()) == 12
    gcp_seen = set(sim.gcp_observations.column("gcp_id").to_pylist())
    assert sum(g.startswith("GCP") for g in gcp_seen) == 11, "every control point is measured in some image"


def test_mitishita_gsd_and_focal_error_moves_heights_by_75_cm():
    sim = simulate_flight(quiet("mitishita-block"), seed=3)
    assert abs(sim.trajectory.gsd_m - 0.15) / 0.15 < 0.03
    # forward-intersect noise-free tie points with the true EO and a focal length 0.030 mm too long
    wrong_df = 0.030 / sim.spec.camera_true.pixel_size_mm
    tie = sim.tie
    z_true, z_wrong = [], []
    for track in np.unique(tie.point_id)[:400]:
        sel = np.flatnonzero(tie.point_id == track)
        if len(sel) < 3:
            continue
        for df, out in ((0.0, z_true), (wrong_df, z_wrong)):
            A, b = [], []
            for k in sel:
                ex = sim.exposures[tie.image_id[k] - 1]
                cam = ex.camera.replace(f=ex.camera.f + df)
                xy = cam.unproject(tie.uv_true[k][None])[0]
                d = ex.R_cw.T @ np.array([xy[0], xy[1], 1.0])
                d /= np.linalg.norm(d)
                P = np.eye(3) - np.outer(d, d)
                A.append(P)
                b.append(P @ ex.C)
            out.append(np.linalg.solve(np.sum(A, axis=0), np.sum(b, axis=0))[2])
    dz = np.array(z_wrong) - np.array(z_true)
    expected = sim.spec.plan.height_agl_m * 0.030 / sim.spec.camera_true.focal_mm
    assert abs(abs(np.mean(dz)) - 0.75) / 0.75 < 0.05, f"mean height change {np.mean(dz):.3f} m"
    assert abs(np.mean(dz) + expected) < 0.02, "a longer focal length puts the points lower"


# ------------------------------------------------------------------------------------------ effects
def _interior_displacement(preset, effect, value, temperature_offset=0.0, frame=20):
    base = simulate_flight(quiet(preset, temperature_offset), seed=5)
    eff = simulate_flight(quiet(preset, temperature_offset), seed=5, effects={effect: value})
    ex0, ex1 = base.exposures[frame], eff.exposures[frame]
    uv = grid_pixels(ex0.camera)
    X = ground_points(ex0, uv, base.spec.scene.terrain_mean_m)
    return ex0, uv, ex1.project(X) - uv


def test_thermal_focal_displacement():
    slope = 0.5e-3 / PRESETS["conte-city"].camera_true.pixel_size_mm  # 0.5 um/degC in px/degC
    ex0, uv, d = _interior_displacement("conte-calibration", "thermal_focal", slope, DT)
    df = slope * DT
    assert df == pytest.approx(0.2, abs=0.02), "NOTES: 0.2 px for 10 degC on the 640x480 thermal camera"
    expected = df * ex0.camera.pixels_to_normalised(uv)
    assert np.abs(d - expected).max() < 0.05 * np.abs(expected).max()


def test_thermal_principal_point_displacement():
    _, _, d = _interior_displacement("conte-calibration", "thermal_principal_point", (0.05, -0.03), DT)
    assert np.allclose(d, [0.5, -0.3], rtol=0.05, atol=0.01)


def test_thermal_rotation_turns_the_image_about_the_principal_point():
    # Daakir 2019's bound, 0.02 px/degC at the corner, over 10 degC: the corners move 0.2 px tangentially
    ex0, uv, d = _interior_displacement("daakir-uav", "thermal_rotation", 0.02, DT)
    rel = uv - [ex0.camera.cx, ex0.camera.cy]
    r = np.hypot(rel[:, 0], rel[:, 1])
    tangential = (rel[:, 0] * d[:, 1] - rel[:, 1] * d[:, 0]) / np.maximum(r, 1e-9)
    radial = (rel[:, 0] * d[:, 0] + rel[:, 1] * d[:, 1]) / np.maximum(r, 1e-9)
    assert tangential[np.argmax(r)] == pytest.approx(0.2, rel=0.05)
    assert np.allclose(tangential, 0.2 * r / r.max(), atol=0.01) and np.abs(radial).max() < 0.01


def test_affinity_skew_and_k3_displacement():
    ex0, uv, d = _interior_displacement("conte-calibration", "affinity_skew", (0.6, 0.25))
    xn = ex0.camera.pixels_to_normalised(uv)
    expected = np.column_stack([0.6 * xn[:, 0] + 0.25 * xn[:, 1], np.zeros(len(xn))])
    assert np.abs(d - expected).max() < 0.05 * np.abs(expected).max()
    ex0, uv, d = _interior_displacement("conte-calibration", "radial_k3", 0.05)
    xy = ex0.camera.unproject(uv)
    expected = 0.05 * ex0.camera.param_jacobian(xy)[:, :, 5]
    assert np.abs(d - expected).max() < 0.05 * np.abs(expected).max()


def test_refraction_displacement_on_the_ultracam():
    ex0, uv, d = _interior_displacement("mitishita-block", "refraction", "on")
    r = np.linalg.norm(uv - [ex0.camera.cx, ex0.camera.cy], axis=1)
    k = fx.bertram_refraction_k(float(ex0.C[2]), PRESETS["mitishita-block"].scene.terrain_mean_m)
    expected = fx.refraction_displacement_px(r, ex0.camera.f, k)
    corner = np.argmax(r)
    assert 0.25 < expected[corner] < 0.5, "NOTES: ~0.4 px at the corner of the UltraCam at 2500 m"
    measured = np.linalg.norm(d, axis=1)
    assert abs(measured[corner] - expected[corner]) < 0.05 * expected[corner]


def test_rolling_shutter_displacement():
    readout = 0.033
    base = simulate_flight(quiet("conte-calibration"), seed=5)
    eff = simulate_flight(quiet("conte-calibration"), seed=5, effects={"rolling_shutter": readout})
    ex0, ex1 = base.exposures[3], eff.exposures[3]
    cam = ex0.camera
    top = np.column_stack([np.linspace(50, 590, 5), np.full(5, 0.5)])
    bottom = np.column_stack([np.linspace(50, 590, 5), np.full(5, cam.height - 0.5)])
    z = base.spec.scene.terrain_mean_m
    d_top = ex1.project(ground_points(ex0, top, z)) - top
    d_bottom = ex1.project(ground_points(ex0, bottom, z)) - bottom
    stretch = np.linalg.norm(d_bottom - d_top, axis=1).mean()
    gsd = (ex0.C[2] - z) / cam.f
    expected = fx.rolling_shutter_shift_px(base.spec.plan.speed_m_s, readout, gsd) * (cam.height - 1) / cam.height
    assert abs(stretch - expected) < 0.05 * expected, f"{stretch:.3f} vs {expected:.3f} px"


@pytest.mark.parametrize(
    "effect, value, metres",
    [("lever_arm", (1.0, 0.0, 0.0), 1.0), ("gnss_bias", (1.0, -0.5, 0.0), np.hypot(1.0, 0.5)),
     ("gnss_time_offset", 0.1, 60.0 * 0.1)],
)
def test_position_effects_shift_the_image_by_offset_over_gsd(effect, value, metres):
    sim = simulate_flight(quiet("conte-calibration"), seed=6, effects={effect: value})
    i = 10
    ex, rec = sim.exposures[i], recorded_exposure(sim, i)
    c = np.array([[ex.camera.cx, ex.camera.cy]])
    X = ground_points(ex, c, sim.spec.scene.terrain_mean_m)
    shift = np.linalg.norm(rec.project(X) - c)
    depth = ex.R_cw[2] @ (X[0] - ex.C)
    expected = metres * ex.camera.f / depth
    assert abs(shift - expected) < 0.05 * expected, f"{effect}: {shift:.3f} vs {expected:.3f} px"


def test_boresight_shift_at_the_principal_point():
    sim = simulate_flight(quiet("conte-calibration"), seed=6, effects={"boresight": (0.01, 0.0, 0.0)})
    ex, rec = sim.exposures[7], recorded_exposure(sim, 7)
    c = np.array([[ex.camera.cx, ex.camera.cy]])
    X = ground_points(ex, c, sim.spec.scene.terrain_mean_m)
    shift = np.linalg.norm(rec.project(X) - c)
    expected = fx.boresight_shift_px(ex.camera.f, 0.01)
    assert expected == pytest.approx(0.29, abs=0.01)
    assert abs(shift - expected) < 0.05 * expected


def test_exposure_rays_and_projection_are_inverse_with_every_effect():
    sim = simulate_flight("conte-calibration", seed=8, effects={
        "rolling_shutter": 0.03, "refraction": "on", "thermal_focal": 0.1, "affinity_skew": (0.5, 0.2),
        "radial_k3": 0.02})
    ex = sim.exposures[5]
    uv = grid_pixels(ex.camera, 15)
    o, d = ex.rays(uv)
    X = o + 800.0 * d
    assert np.abs(ex.project(X) - uv).max() < 1e-8


def test_effect_free_observations_have_the_stated_noise():
    sim = simulate_flight("conte-calibration", seed=9)
    resid = sim.tie.uv - sim.tie.uv_true
    assert np.std(resid) == pytest.approx(sim.spec.sensors.tie_sigma_px, rel=0.05)


def test_same_seed_same_flight_other_seed_other_flight():
    a = simulate_flight("conte-calibration", seed=4, max_images=12)
    b = simulate_flight("conte-calibration", seed=4, max_images=12)
    c = simulate_flight("conte-calibration", seed=5, max_images=12)
    assert a.observations.equals(b.observations)
    assert not a.observations.equals(c.observations)
    assert a.images.num_rows == 12


# ------------------------------------------------------------------------------------------ files, CLI
def test_write_flight_folder_is_complete_and_valid(tmp_path):
    sim = simulate_flight("conte-calibration", seed=1, effects={"thermal_focal": 0.05}, max_images=20)
    out = write_flight(sim, tmp_path / "flight")
    for kind in ("images", "observations", "gcps", "gcp_observations"):
        t = tables.read(out / "observations" / f"{kind}.parquet", kind)
        assert tables.crs_of(t) == "EPSG:32632"
    truth = json.loads((out / "truth.json").read_text())
    assert truth["effects"] == {"thermal_focal": [0.05]}
    eo = [line for line in (out / "eo.csv").read_text().splitlines() if not line.startswith("#")]
    assert eo[0] == "image,lat,lon,alt,roll,pitch,yaw,temperature" and len(eo) == 21
    camera = json.loads((out / "camera.json").read_text())
    assert camera["identity"]["model"] == "TS9260" and "k1" in camera["camera"]
    assert pq.read_table(out / "truth" / "poses.parquet").num_rows == 20
    assert not list(tmp_path.glob(".tmp-*"))


def test_interrupted_write_leaves_nothing(tmp_path, monkeypatch):
    sim = simulate_flight("conte-calibration", seed=1, max_images=8)
    import aerocal.simulate.simulator as simulator

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(simulator, "write_json_atomic", boom)
    with pytest.raises(KeyboardInterrupt):
        write_flight(sim, tmp_path / "flight")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "args, message",
    [(["conte-x"], "valid presets: conte-calibration, conte-city, daakir-calibration, daakir-uav, "
                   "mitishita-block, seneca"),
     (["conte-calibration", "--effect", "foo=1"], "valid effects: thermal_focal"),
     (["conte-calibration", "--effect", "boresight=0.1"], "boresight takes 3"),
     (["conte-calibration", "--effect", "thermal_focal=abc"], "thermal_focal takes 1"),
     (["conte-calibration", "--effect", "refraction=maybe"], "refraction=on"),
     (["conte-calibration", "--mode", "video"], "valid modes: observations, images")],
)
def test_bad_input_gives_one_clear_line_and_writes_nothing(tmp_path, args, message):
    out = tmp_path / "flight"
    result = CliRunner().invoke(app, ["simulate", *args, "--out", str(out)])
    assert result.exit_code != 0
    text = " ".join(result.output.split())
    assert message in text, result.output
    assert not out.exists()


def test_cli_simulate_writes_a_flight(tmp_path):
    out = tmp_path / "flight"
    result = CliRunner().invoke(app, ["simulate", "conte-calibration", "--out", str(out), "--seed", "3",
                                      "--max-images", "10", "--effect", "boresight=0.01,0,0", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["images"] == 10 and summary["effects"] == {"boresight": [0.01, 0.0, 0.0]}
    assert (out / "truth.json").exists()


SENECA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "seneca" / "images"


def test_seneca_preset_flies_the_real_stations_and_temperatures():
    if not SENECA.is_dir():
        pytest.skip(f"measured data not found at {SENECA} (../shared/data beside the repository)")
    sim = simulate_flight("seneca", seed=2)
    t = sim.images.column("temperature_c").to_numpy()
    assert sim.images.num_rows == 166, "the 1800x1350 frames (the first, smaller frame is left out)"
    assert t[0] == 37.0 and t[-1] == 23.0 and np.all(np.diff(t) <= 0), "the camera cooled from 37 to 23 degC"
    assert sim.crs == "EPSG:32617"
    assert len(np.unique(sim.trajectory.strip)) >= 20, "strips as ingest found them"
    assert np.median(np.bincount(sim.tie.image_id)[1:]) > 300
    gsd = sim.trajectory.gsd_m
    assert 0.04 < gsd < 0.07, f"GSD {gsd:.3f} m at ~70 m with a 4.3 mm lens"


def test_measured_preset_with_a_missing_folder_names_it(tmp_path):
    result = CliRunner().invoke(app, ["simulate", "seneca", "--source", str(tmp_path / "nothing"),
                                      "--out", str(tmp_path / "f")])
    assert result.exit_code != 0 and "nothing is not a folder" in " ".join(result.output.split())
