"""The flight report: one self-contained HTML file whose images decode, and summary.json with the numbers.

The report of a processed flight is built from a small simulated flight's real step outputs (the engine's
adjustment, DSM, assessment and diagnosis of the flight, as the pipeline's steps make them) and read as a
person reads it: every section there, the check-point table's numbers the adjustment's, no machine key, repr,
``None`` or ``nan`` on the page.
"""

import base64
import fnmatch
import importlib.resources
import json
import re
import tomllib
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pytest

from aerocal.assess import accuracy_ratio, bin_residuals, compare_dems
from aerocal.camera import Camera, LinearThermalModel
from aerocal.products.dsm import Dsm
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


# ------------------------------------------------------------------ the report of a processed flight
SEED = 5


class _Page(HTMLParser):
    """What a reader sees of a page: the visible text (no style), section ids, headings, figure ids, image
    sources and the rows of every table with an id."""

    def __init__(self) -> None:
        super().__init__()
        self.text: list[str] = []
        self.sections: list[str] = []
        self.headings: list[str] = []
        self.figures: list[str] = []
        self.srcs: list[str] = []
        self.tables: dict[str, list[list[str]]] = {}
        self._hidden = 0
        self._heading = None
        self._table = None
        self._row = None
        self._cell = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag in ("style", "script", "title"):
            self._hidden += 1
        elif tag == "section":
            self.sections.append(a.get("id") or "")
        elif tag == "h2":
            self._heading = []
        elif tag == "figure":
            self.figures.append(a.get("id") or "")
        elif tag == "img":
            self.srcs.append(a.get("src") or "")
        elif tag == "table" and a.get("id"):
            self._table = self.tables.setdefault(a["id"], [])
        elif tag == "tr" and self._table is not None:
            self._row = []
        elif tag in ("td", "th") and self._row is not None:
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("style", "script", "title"):
            self._hidden -= 1
        elif tag == "h2" and self._heading is not None:
            self.headings.append("".join(self._heading).strip())
            self._heading = None
        elif tag in ("td", "th") and self._cell is not None:
            self._row.append("".join(self._cell).strip())
            self._cell = None
        elif tag == "tr" and self._row is not None:
            self._table.append(self._row)
            self._row = None
        elif tag == "table":
            self._table = None

    def handle_data(self, data):
        if self._hidden:
            return
        self.text.append(data)
        for part in (self._heading, self._cell):
            if part is not None:
                part.append(data)

    def visible(self) -> str:
        return " ".join(" ".join(self.text).split())


def _read(path) -> _Page:
    page = _Page()
    page.feed(Path(path).read_text())
    return page


@pytest.fixture(scope="module")
def processed_flight(tmp_path_factory):
    """A 16-image thermal calibration flight in observations mode, processed by the engine as the pipeline's
    steps do (fixed-IO adjustment with check points, DSM from the tie points, assessment, diagnosis), with
    the reference DSM the simulator writes beside it."""
    from aerocal.adjust import AdjustConfig, adjust_fixed_io
    from aerocal.assess import reprojection_stats
    from aerocal.certificates.document import CameraIdentity, Certificate, Conditions, Quality
    from aerocal.diagnose.engine import DiagnoseConfig, diagnose
    from aerocal.products.dsm import dsm_from_points, write_dsm
    from aerocal.simulate import simulate_flight, write_flight

    sim = simulate_flight("conte-calibration", seed=SEED, max_images=16)
    folder = write_flight(sim, tmp_path_factory.mktemp("flights") / "flight-r", mode="observations")
    images, obs, gcps, gobs = sim.images, sim.observations, sim.gcps, sim.gcp_observations
    camera = sim.spec.camera_true
    temps = [t for t in images.column("temperature_c").to_pylist() if t is not None]
    cert = Certificate(
        identity=CameraIdentity.from_camera_id(images.column("camera_id")[0].as_py()), camera=camera,
        sigmas={"f": 0.41, "cx": 0.3, "cy": 0.28, "k1": 0.002}, estimated=("f", "cx", "cy", "k1"),
        conditions=Conditions(date="2016-03-14", temperature_range=(min(temps), max(temps)), n_images=16,
                              strips=3, transversal_strip=True, n_gcp=6, priors={"gnss_position_m": 0.05}),
        quality=Quality(sigma0=1.02, reprojection_rms_px=0.31, dof=4000, overdispersion=16.0),
    )
    res = adjust_fixed_io(images, obs, camera, AdjustConfig(), gcps, gobs, None)
    adjustment = {**res.summary(), "converged": res.converged, "iterations": res.iterations,
                  "check_ids": list(res.check_ids), "check_errors_m": np.asarray(res.check_errors).tolist(),
                  "check_sigma_m": np.asarray(res.check_sigma).tolist(), "control_ids": list(res.control_ids),
                  "control_errors_m": np.asarray(res.control_errors).tolist(), "recorded_eo_corrections": None}
    ground = float(np.median(res.points.column("Z").to_numpy()))
    gsd = (float(np.median(res.poses.column("Z").to_numpy())) - ground) / camera.f
    dsm = write_dsm(dsm_from_points(res.points, sim.crs, gsd_m=gsd), folder.parent / "dsm.tif")
    ok = np.isfinite(res.residuals).all(axis=1)
    e, s = np.asarray(res.check_errors, float), np.asarray(res.check_sigma, float)
    measured = np.isfinite(e).all(axis=1) & (s > 0).all(axis=1)  # as the assess step: points with a prediction
    assessment = {"check_points": accuracy_ratio(e[measured], s[measured]).to_dict(),
                  "reprojection": reprojection_stats(obs.filter(pa.array(ok)), res.residuals[ok], images).to_dict()}
    diag = diagnose(images, obs, camera, AdjustConfig(free=(), thermal=(), adaptive=False), gcps, gobs,
                    DiagnoseConfig(twins=0, null_draws=0))
    diagnosis = {**diag.to_dict(), "summary": diag.summary()}
    flight = {"name": "flight-r", "folder": str(folder), "mode": "observations", "crs": sim.crs,
              "date": "2016-03-14", "n_images": images.num_rows, "temperature_range": [min(temps), max(temps)],
              "skipped_images": [], "facts": {}}
    mosaic = {"gsd_m": gsd, "ground_height_m": ground, "dsm_cell_m": 1.0, "frames": 0}
    return {"flight": flight, "images": images, "certificate": cert, "adjustment": adjustment, "poses": res.poses,
            "points": res.points, "dsm": dsm, "mosaic": mosaic, "assessment": assessment, "diagnosis": diagnosis,
            "gcps": gcps, "reference_dsm": folder / "reference" / "dsm.tif"}


def _write(flight, out, **kwargs):
    from aerocal.report.flight_report import write_flight_report

    f = flight
    return write_flight_report(out, f["flight"], f["images"], f["certificate"], f["adjustment"], f["poses"],
                               f["points"], f["dsm"], f["mosaic"], f["assessment"], f["diagnosis"], f["gcps"],
                               **{"reference_dsm": f["reference_dsm"], **kwargs})


#: what a machine key, a repr or a missing value looks like on a page
RAW_KEY = re.compile(r"\b[a-z][a-z0-9]*(?:_[a-z0-9]+)+\b")
DANGLING = re.compile(r"(?:^|\s)[-–](?:\s|$)")


def _reader_problems(text: str) -> list[str]:
    found = [f"raw key {k!r}" for k in RAW_KEY.findall(text)]
    found += [f"{w!r}" for w in ("None", "nan", "NaN", "inf") if re.search(rf"\b{w}\b", text)]
    found += [f"{c!r}" for c in ("{", "}", "[", "]", "+-", "()") if c in text]
    found += ["dangling dash" for _ in DANGLING.findall(text)]
    return found


def test_flight_report_reads_as_a_report(processed_flight, tmp_path):
    from aerocal.report.flight_report import SECTIONS

    steps = {"ingest": 0.8, "adjust": 1.6, "mosaic": 11.1, "diagnose": 11.5, "report": 2.0}
    doc = _write(processed_flight, tmp_path / "run", step_seconds=steps)
    run = tmp_path / "run"
    assert sorted(p.name for p in run.iterdir()) == ["report.html", "summary.json"]
    page = _read(run / "report.html")
    text = page.visible()

    # every section, in order, with its heading
    assert page.sections == [i for i, _ in SECTIONS]
    assert page.headings == [h for _, h in SECTIONS]
    # every figure drawn (the flight has a reference DSM), each an embedded PNG with content
    assert set(page.figures) == {"overview", "tie_points", "distortion", "temperature_io", "block",
                                 "image_residuals", "dem_difference", "surface"}, page.figures
    assert len(page.srcs) == len(page.figures)
    for src in page.srcs:
        assert src.startswith("data:image/png;base64,"), src[:40]
        img = cv2.imdecode(np.frombuffer(base64.b64decode(src.split(",", 1)[1]), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[1] > 300 and img.std() > 10
    # the check-point table holds the adjustment's errors (metres, to the millimetre) and RMSE
    adj = processed_flight["adjustment"]
    table = page.tables["check-points"]
    header, rows, total = table[0], table[1:-1], table[-1]
    col = {name: header.index(name) for name in ("Error E (m)", "Error N (m)", "Error Up (m)")}
    assert [r[0] for r in rows] == adj["check_ids"], f"seed {SEED}: {adj['check_ids']}"
    measured = 0
    for row, err in zip(rows, adj["check_errors_m"], strict=True):
        if np.isfinite(err).all():
            assert [float(row[col[c]]) for c in col] == [round(v, 3) for v in err], (row, err)
            measured += 1
        else:  # seen in one image: no intersection, said in words
            assert [row[col[c]] for c in col] == ["not measured"] * 3 and row[0] in text, row
    assert measured >= 3, f"seed {SEED}: {measured} check points measured"
    assert total[0] == "RMSE" and [float(total[col[c]]) for c in col] == [round(v, 3) for v in adj["check_rmse_m"]]
    assert [r[0] for r in page.tables["control-points"][1:-1]] == adj["control_ids"]
    # words a person reads, no machine key, repr or missing value anywhere on the page
    assert _reader_problems(text) == [], _reader_problems(text)
    assert "Focal length f" in text and "Prior standard deviation: GNSS position 0.0500 m" in text
    assert "Strips 3, with a transversal strip" in text
    assert "Sigmas calibrated: formal x 4, the square root of the block's measured overdispersion 16" in text
    assert "Step times were not given" not in text and "Total of the steps above 27.0 s" in text
    assert "No orthomosaic: the flight holds no image pixels" in text
    # summary.json keeps the machine keys and the figures' numbers
    saved = json.loads((run / "summary.json").read_text())
    assert saved == json.loads(json.dumps(doc))
    assert saved["summary"]["check_rmse_m"] == adj["check_rmse_m"]
    assert saved["summary"]["dsm_minus_reference_m"]["mean_m"] == saved["figures"]["dem_difference"]["mean_m"]
    assert saved["notes"] == [] and saved["step_seconds"] == steps
    overview = saved["figures"]["overview"]
    assert overview["check_points"] == len(adj["check_ids"]) and overview["control_points"] == len(adj["control_ids"])
    assert overview["overlap_max"] >= 4, f"seed {SEED}: a calibration block sees its centre from many images"


def test_a_report_without_figures_keeps_every_caption_and_number(processed_flight, tmp_path):
    """``ReportStepConfig(figures=False)``: the same page and summary.json, each figure's caption and numbers
    without its picture."""
    from aerocal.report.figures import figures_drawn

    _write(processed_flight, tmp_path / "drawn")
    with figures_drawn(False):
        _write(processed_flight, tmp_path / "text")
    drawn, text = _read(tmp_path / "drawn" / "report.html"), _read(tmp_path / "text" / "report.html")
    assert len(drawn.srcs) == len(drawn.figures) == 8 and not text.srcs, (len(drawn.srcs), len(text.srcs))
    # the pages differ only in the second they were written
    stamp = re.compile(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d \(UTC\)")
    assert len(stamp.findall(text.visible())) == 1
    assert text.figures == drawn.figures and stamp.sub("", text.visible()) == stamp.sub("", drawn.visible())
    a, b = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("drawn", "text"))
    a.pop("created_utc"), b.pop("created_utc")
    assert a == b


def test_flight_report_says_why_a_figure_is_missing(processed_flight, tmp_path):
    """Without a reference DSM, check points or step times the page says so in words where they would be."""
    from aerocal.adjust.control import ControlScreening, GcpVerdict

    f = dict(processed_flight)
    adj = dict(f["adjustment"])
    adj.update(check_ids=[], check_errors_m=[], check_sigma_m=[], check_rmse_m=None)
    f["adjustment"] = adj
    f["reference_dsm"] = None
    f["assessment"] = {"check_points": {"n": 0, "verdict": "fewer than 2 check points: accuracy not assessed"}}
    gid = f["gcps"].column("gcp_id")[0].as_py()
    screening = ControlScreening(f["gcps"], pa.table({}), [
        GcpVerdict(gid, "control", "demoted", 5, [12.0, -3.0, 0.4], 410.0, 11.3, [], "15 m off in plan"),
        GcpVerdict("CHK99", "check", "not tested", 1, None, None, None, [], "seen in one image"),
    ], "gnss", ["heights of 0.0 read as unknown"]).to_dict()
    doc = _write(f, tmp_path, control_screening=screening)
    text = _read(tmp_path / "report.html").visible()
    assert _reader_problems(text) == [], _reader_problems(text)
    assert "the flight folder has no reference DSM (reference/dsm.tif" in text
    assert "The flight has no check point: the accuracy of its products is not measured" in text
    assert "Reprojection residuals over the image: not drawn, the assessment holds no binned residuals" in text
    assert "Step times were not given to the report" in text
    assert f"{gid} control demoted 5 12.000 -3.000 0.400 15 m off in plan" in text
    assert "CHK99 check not tested 1 not tested not tested not tested seen in one image" in text
    assert "Heights of 0.0 read as unknown." in text
    assert len(doc["notes"]) == 2 and "dsm_minus_reference_m" not in doc["summary"]


def test_an_unreadable_reference_dsm_is_a_figure_left_out_with_the_file_and_the_fix(processed_flight, tmp_path):
    """The reference DSM is the user's file: one that is not a GeoTIFF, or has no CRS, leaves its figure out with
    a sentence naming the file and what to do, and the report (the run's last step) is still written."""
    import rasterio
    from rasterio.transform import from_origin

    f = dict(processed_flight)
    broken = tmp_path / "broken.tif"
    broken.write_bytes(b"not a GeoTIFF at all")
    f["reference_dsm"] = broken
    _write(f, tmp_path / "a")
    text = _read(tmp_path / "a" / "report.html").visible()
    assert f"DSM minus reference: not drawn, {broken}: not a readable GeoTIFF" in text
    no_crs = tmp_path / "no_crs.tif"
    with rasterio.open(no_crs, "w", driver="GTiff", width=4, height=4, count=1, dtype="float32",
                       transform=from_origin(0, 4, 1, 1)) as ds:
        ds.write(np.zeros((1, 4, 4), np.float32))
    f["reference_dsm"] = no_crs
    doc = _write(f, tmp_path / "b")
    text = _read(tmp_path / "b" / "report.html").visible()
    assert "the raster has no CRS; assign the flight's CRS" in text
    assert "dsm_minus_reference_m" not in doc["summary"]


def test_overlap_counts_cover_each_footprint_once():
    """One nadir frame over flat ground sees a rectangle of w H / f by h H / f metres: that many cells count 1,
    none 2; two frames a footprint apart along E count 2 nowhere either, half a footprint apart on half of
    it."""
    from aerocal.geometry import nadir_R_cw
    from aerocal.products.mosaic import FrameGeometry
    from aerocal.report import overlap_counts

    cam = Camera(640, 480, f=1600.0, cx=320.0, cy=240.0)
    H = 400.0
    width_m, height_m = 640 * H / 1600.0, 480 * H / 1600.0
    one = FrameGeometry(1, cam, nadir_R_cw(0.0), np.array([1000.0, 2000.0, H + 50.0]))
    counts, (w, e, s, n) = overlap_counts([one], ground_height_m=50.0, cells=200)
    cell = (e - w) / counts.shape[1]
    assert counts.max() == 1
    assert abs((counts == 1).sum() * cell**2 / (width_m * height_m) - 1) < 0.03
    along = [FrameGeometry(i, cam, nadir_R_cw(0.0), np.array([1000.0 + k, 2000.0, H + 50.0]))
             for i, k in ((1, 0.0), (2, 0.5 * width_m))]
    counts, (w, e, s, n) = overlap_counts(along, ground_height_m=50.0, cells=200)
    cell = (e - w) / counts.shape[1]
    assert abs((counts == 2).sum() * cell**2 / (0.5 * width_m * height_m) - 1) < 0.05


def test_templates_ship_in_the_package():
    """The templates load from the installed package's folder, and pyproject's package-data ships each."""
    from aerocal.report.html import environment

    folder = importlib.resources.files("aerocal.report") / "templates"
    names = sorted(p.name for p in folder.iterdir() if p.name.endswith(".j2"))
    assert {"flight_report.html.j2", "report.html.j2", "base.html.j2"} <= set(names)
    template = environment().get_template("flight_report.html.j2")
    assert Path(template.filename).resolve() == Path(str(folder / "flight_report.html.j2")).resolve()
    pyproject = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    patterns = pyproject["tool"]["setuptools"]["package-data"]["aerocal.report"]
    assert all(any(fnmatch.fnmatch(f"templates/{n}", p) for p in patterns) for n in names), (names, patterns)
    deps = [d.split(">")[0].split("=")[0].strip().lower() for d in pyproject["project"]["dependencies"]]
    assert "jinja2" in deps


def test_effects_the_block_cannot_tell_apart_are_one_sentence_naming_each_and_applying_none():
    from aerocal.report.wording import diagnosis_sentences

    group = {"effects": ["rolling_shutter", "affinity_skew", "boresight"], "conditional": "each within 2 sigma of "
             "zero given the others", "separated_by": "strips flown at different ground speeds"}
    text = " ".join(diagnosis_sentences({"effects": [], "hypotheses": [], "pairs": [group]}))
    assert re.search(r"A rolling.*, an? affin.* and a boresight.* cannot tell them apart", text, re.I), text
    assert "none is named nor applied" in text and "Strips flown at different ground speeds." in text, text
    pair = dict(group, effects=["rolling_shutter", "affinity_skew"])
    assert "neither is named nor applied" in " ".join(diagnosis_sentences({"effects": [], "pairs": [pair]}))


def test_the_laser_figure_draws_each_frames_ranges_and_carries_the_medians():
    from aerocal.report.figures import laser_range_figure

    doc = {"verdict": "DISAGREES with the laser range finder: ...", "median_m": 11.1,
           "images": {"2": [64.5, 76.1], "4": [65.8, 80.0], "16": [97.4, 127.0]},
           "fitted": {"median_m": 6.6, "images": {"1": [67.7, 70.0], "3": [65.3, 71.2]}}}
    fig = laser_range_figure(doc)
    assert fig.name == "laser_range" and fig.png.startswith(b"\x89PNG") and fig.caption.startswith("DISAGREES")
    assert fig.numbers == {"held_out_median_m": 11.1, "fitted_median_m": 6.6}
    decoded = cv2.imdecode(np.frombuffer(fig.png, np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None and decoded.shape[1] > 600, "a figure a browser shows"


def test_the_laser_figure_of_fitted_frames_no_surface_met_says_not_measured():
    """On the tie points' surface no fitted frame's axis may meet a measured cell: its median is null in the run's
    JSON, and the report is made all the same (h20t_forest with --surface tie-points)."""
    from aerocal.report.figures import laser_range_figure

    doc = {"verdict": "agrees with the laser range finder (...)", "median_m": -0.3,
           "images": {"2": [93.5, 93.2], "4": [94.0, 93.6]},
           "fitted": {"median_m": None, "n": 0, "unmatched": 21, "images": {}}}
    fig = laser_range_figure(doc)
    assert fig.numbers == {"held_out_median_m": -0.3, "fitted_median_m": None}


def test_a_large_grid_is_drawn_from_block_means_and_a_city_dsm_figure_stays_small():
    """A map is drawn from means of blocks of cells (NaN cells left out), never from every cell of a city's DSM:
    its figure comes out as the same small image whatever the grid's size."""
    from aerocal.products.dsm import Dsm
    from aerocal.report.figures import MAX_DRAWN_CELLS, drawing_step, drawn, surface_figure

    grid = np.arange(35, dtype=np.float32).reshape(5, 7)
    grid[0, 0] = np.nan
    means = drawn(grid, 3)
    assert means.shape == (2, 3)
    assert means[0, 0] == pytest.approx(np.nanmean(grid[:3, :3]))
    assert means[1, 2] == pytest.approx(np.mean(grid[3:, 6:]))  # the last, partial block
    assert np.isnan(drawn(np.full((4, 4), np.nan, np.float32), 2)).all()
    assert drawing_step((7909, 9610)) == -(-9610 // MAX_DRAWN_CELLS) and drawing_step((300, 200)) == 1

    rows, cols = 4 * MAX_DRAWN_CELLS, 3 * MAX_DRAWN_CELLS
    heights = np.add.outer(np.linspace(0, 50, rows), np.linspace(0, 30, cols)).astype(np.float32)
    dsm = Dsm(heights=heights, west=0.0, north=float(rows), cell_m=1.0, crs="EPSG:32633")
    measured = np.ones(heights.shape, dtype=bool)
    measured[:, : cols // 2] = False
    fig = surface_figure(dsm, measured)
    assert "drawn as blocks of 4 x 4 cells" in fig.caption and fig.numbers["measured_fraction"] == 0.5
