"""The flight report: one self-contained HTML file whose images decode, and summary.json with the numbers."""

import base64
import json
import re

import cv2
import numpy as np

from aerocal.assess import accuracy_ratio, bin_residuals, compare_dems
from aerocal.camera import Camera, LinearThermalModel
from aerocal.dsm import Dsm
from aerocal.report import (
    CertificateTable,
    block_figure,
    dem_difference_figure,
    image_residual_figure,
    temperature_io_figure,
    write_report,
)


def _inputs(seed: int):
    rng = np.random.default_rng(seed)
    centres = np.column_stack([np.repeat([0.0, 100.0, 200.0], 3), np.tile([0.0, 80.0, 160.0], 3)]) + 686000
    footprints = [c + np.array([[-60, -45], [60, -45], [60, 45], [-60, 45]]) for c in centres]
    pts = rng.uniform(686000, 686200, (12, 2))
    res = rng.normal(0, 0.1, (12, 3))
    xy = rng.uniform([0, 0], [640, 480], (3000, 2))
    r = 0.3 * (xy - [320, 240]) / 320 + rng.normal(0, 0.2, (3000, 2))
    ref = Dsm(heights=np.full((60, 80), 50.0, np.float32), west=686000, north=4929060, cell_m=1.0, crs="EPSG:32632")
    test = Dsm(heights=(ref.heights + 0.4 + rng.normal(0, 0.2, ref.shape)).astype(np.float32), west=686000,
               north=4929060, cell_m=1.0, crs="EPSG:32632")
    return centres, footprints, pts, res, xy, r, ref, test


def test_report_is_one_html_file_with_decodable_images_and_a_summary(tmp_path):
    seed = 9
    centres, footprints, pts, res, xy, r, ref, test = _inputs(seed)
    cam = Camera.from_mm(640, 480, focal_mm=39.2, pixel_size_um=23.5)
    model = LinearThermalModel(t0=20.0, df_dt=0.21)
    temps = np.linspace(14, 24, 20)
    f = cam.f + 0.21 * (temps - 20) + np.random.default_rng(seed).normal(0, 0.05, 20)
    diff = compare_dems(test, ref, transects=[((686010.0, 4929030.0), (686070.0, 4929030.0))])
    ratio = accuracy_ratio(res, np.array([0.1, 0.1, 0.1]))
    figures = [
        block_figure(centres, footprints, pts, res, ids=[f"CHK{i}" for i in range(12)]),
        image_residual_figure(bin_residuals(xy, r, 640, 480)),
        temperature_io_figure(temps, f, np.full(20, cam.cx), np.full(20, cam.cy), model=model, camera=cam),
        dem_difference_figure(diff),
    ]
    cert = CertificateTable.from_values("NEC TS9260 #0912034 v3", {"f": cam.f, "cx": cam.cx, "k1": -0.08},
                                        {"f": 0.4, "cx": 0.3, "k1": 0.002}, info={"valid": "12-24 degC"})
    summary = {"dem_difference": diff.to_dict(), "achieved_vs_predicted": ratio.to_dict(), "images": 9}
    path = write_report(tmp_path / "run", summary, figures, certificate=cert, title="Flight 2016-03-14")
    assert path.name == "report.html" and sorted(p.name for p in path.parent.iterdir()) == [
        "report.html", "summary.json"], "one HTML file (and the machine summary), nothing else"
    text = path.read_text()
    srcs = re.findall(r'<img[^>]*\ssrc="([^"]*)"', text)
    assert len(srcs) == len(figures) == text.count("<img")
    for src in srcs:
        assert src.startswith("data:image/png;base64,"), f"not embedded: {src[:40]}"
        img = cv2.imdecode(np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 300
        assert img.std() > 10, "the figure has content"
    assert "http://" not in text and "https://" not in text, "self-contained: no external resources"
    assert "NEC TS9260 #0912034 v3" in text and "k1" in text
    assert ratio.verdict in text
    data = json.loads((path.parent / "summary.json").read_text())
    assert data["summary"]["dem_difference"]["mean_m"] == diff.mean
    assert abs(data["figures"]["dem_difference"]["mean_m"] - 0.4) < 0.02
    assert abs(data["figures"]["temperature_io"]["fitted_slope_px_per_degC"]["f"] - 0.21) < 0.02
    assert len(data["figures"]["block"]["points"]) == 12 and data["figures"]["block"]["exaggeration"] > 1
    assert data["certificate"]["parameters"][0] == {"name": "f", "value": cam.f, "sigma": 0.4, "unit": "px"}


def test_report_refuses_duplicate_figure_names_and_writes_nothing(tmp_path):
    centres, footprints, pts, res, *_ = _inputs(1)
    fig = block_figure(centres, footprints, pts, res)
    try:
        write_report(tmp_path / "run", {}, [fig, fig])
    except ValueError as exc:
        assert "unique" in str(exc)
    else:
        raise AssertionError("duplicate figure names accepted")
    assert not (tmp_path / "run").exists()


# ------------------------------------------------------------------ figures of a processed flight
def test_thermal_io_of_a_similarity_model_matches_the_linear_drift_it_was_fitted_to():
    """A similarity model fitted (Daakir's way) to measurements drifting by a linear IO model gives, as its
    equivalent focal length and principal point, the linear model's IO at every temperature."""
    from aerocal.camera import SimilarityThermalModel
    from aerocal.report import io_at_temperatures

    cam = Camera(640, 480, f=1668.0, cx=321.0, cy=238.5)
    linear = LinearThermalModel(t0=20.0, df_dt=0.21, dcx_dt=-0.05, dcy_dt=0.08)
    temps = (10.0, 20.0, 30.0)
    u, v = np.meshgrid(np.linspace(0, 640, 12), np.linspace(0, 480, 9))
    ref = np.column_stack([u.ravel(), v.ravel()])
    fits = []
    for t in temps:  # where the camera at t sees the grid the reference camera sees at ref
        c_t = linear.camera_at(cam, t)
        seen = c_t.normalised_to_pixels((ref - [cam.cx, cam.cy]) / cam.f)
        fits.append(SimilarityThermalModel.fit_one(seen, ref, (320.0, 240.0)))
    sim = SimilarityThermalModel(temps, *(tuple(x) for x in zip(*fits, strict=True)), centre=(320.0, 240.0))
    at = np.array([12.0, 20.0, 27.5])
    got, want = io_at_temperatures(cam, sim, at), io_at_temperatures(cam, linear, at)
    for name in ("f", "cx", "cy"):
        np.testing.assert_allclose(got[name], want[name], atol=0.01, err_msg=name)
    assert want["f"][0] == cam.f + 0.21 * (12.0 - 20.0)
    assert (io_at_temperatures(cam, None, at)["f"] == cam.f).all(), "no thermal model: constant IO"


def test_temperature_figure_without_a_thermal_model_draws_the_constant_io_and_says_so():
    from aerocal.report import FigureSkipped, temperature_io_for_flight

    cam = Camera(640, 480, f=1668.0, cx=321.0, cy=238.5)
    temps = {1: 18.2, 2: 18.6, 3: None, 4: 19.0}
    fig = temperature_io_for_flight(cam, None, temps)
    assert "no thermal model" in fig.caption and "18.2 to 19.0 degC" in fig.caption
    assert fig.numbers["image_id"] == [1, 2, 4] and fig.numbers["f_px"] == [1668.0] * 3
    assert fig.numbers["thermal_model"] is False and fig.numbers["model"] is None
    img = cv2.imdecode(np.frombuffer(fig.png, np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.std() > 10

    model = LinearThermalModel(t0=20.0, df_dt=0.21, valid_range=(19.0, 30.0))
    fig = temperature_io_for_flight(cam, model, temps, valid_range=model.valid_range)
    assert fig.numbers["f_px"] == [cam.f + 0.21 * (t - 20.0) for t in (18.2, 18.6, 19.0)]
    assert "leave the model's valid range" in fig.caption
    assert abs(fig.numbers["fitted_slope_px_per_degC"]["f"] - 0.21) < 1e-9
    try:
        temperature_io_for_flight(cam, None, {1: None})
    except FigureSkipped as why:
        assert "no image of the flight records a sensor temperature" in str(why)
    else:
        raise AssertionError("a flight without temperatures got a temperature figure")


def test_dem_difference_for_a_flight_compares_inside_the_reference_and_on_measured_cells():
    from aerocal.report import FigureSkipped, dem_difference_for_flight

    seed = 4
    rng = np.random.default_rng(seed)
    heights = (50.0 + rng.normal(0, 0.05, (60, 80))).astype(np.float32)
    dsm = Dsm(heights=heights + np.float32(0.4), west=686000, north=4929060, cell_m=1.0, crs="EPSG:32632")
    # the reference covers the western half only and is 1.0 m higher on its northern 10 rows
    ref_h = heights[:, :40].copy()
    ref_h[:10] += 1.0
    ref = Dsm(heights=ref_h, west=686000, north=4929060, cell_m=1.0, crs="EPSG:32632")
    ties = np.array([[686010.5, 4929030.5], [686030.5, 4929020.5], [686075.5, 4929020.5]])
    fig = dem_difference_for_flight(dsm, ref, ties, measured_within_m=2.0)
    n = fig.numbers
    assert n["n"] == 60 * 40, "only cells inside the reference are compared (no edge extension)"
    assert abs(n["mean_m"] - (0.4 - 10 / 60)) < 0.01, f"seed {seed}: mean {n['mean_m']}"
    assert abs(n["median_m"] - 0.4) < 0.01, f"seed {seed}: median {n['median_m']}"
    m = n["measured_cells"]
    assert m["n"] == 2 * 13, f"two tie points inside the reference, 13 cells each within 2 m: {m}"
    assert abs(m["mean_m"] - 0.4) < 0.01 and "within 2 m" in m["selection"]
    assert "NMAD" in fig.caption and str(n["n"]) in fig.caption
    for other, why in ((Dsm(heights=ref_h, west=686000, north=4929060, cell_m=1.0, crs="EPSG:32633"), "EPSG:32633"),
                       (Dsm(heights=ref_h, west=690000, north=4929060, cell_m=1.0, crs="EPSG:32632"), "no heights")):
        try:
            dem_difference_for_flight(dsm, other)
        except FigureSkipped as exc:
            assert why in str(exc), str(exc)
        else:
            raise AssertionError(f"compared against an unusable reference ({why})")


def test_binned_residuals_survive_the_assessment_json_and_missing_figures_become_notes(tmp_path):
    from aerocal.assess import BinnedResiduals
    from aerocal.report import FigureSkipped, image_residuals_from_assessment

    *_, xy, r, _, _ = _inputs(2)
    binned = bin_residuals(xy[:40], r[:40], 640, 480)  # few points: some bins stay empty
    assert (binned.count == 0).any()
    back = BinnedResiduals.from_dict(json.loads(json.dumps(binned.to_dict())))
    np.testing.assert_array_equal(back.count, binned.count)
    np.testing.assert_allclose(back.mean, binned.mean)
    fig = image_residuals_from_assessment({"reprojection": {"n": 40, "rms_px": 0.5, "binned": binned.to_dict()}})
    assert fig.numbers["count"] == binned.count.tolist() and "RMS 0.5 px over 40" in fig.caption
    try:
        image_residuals_from_assessment({"reprojection": {"binned": None}})
    except FigureSkipped as why:
        note = str(why)
    else:
        raise AssertionError("no binned residuals, yet a figure")
    path = write_report(tmp_path, {"flight": "f"}, [fig], notes=[note])
    assert note in path.read_text() and "Figures not drawn" in path.read_text()
    assert json.loads((tmp_path / "summary.json").read_text())["notes"] == [note]
