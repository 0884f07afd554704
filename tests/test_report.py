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
    srcs = re.findall(r"<img[^>]*\ssrc='([^']*)'", text)
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
