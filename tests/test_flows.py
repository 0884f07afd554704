"""End to end: a small simulated thermal flight through ``process_flight`` under a Prefect test server.

Checks what a user would: the certificate is stored and the run names it with the reason, every output
artifact is registered with lineage back to the flight's manifest, the provenance is complete, the run
folder's files open, the report shows every figure with its numbers in summary.json, and a crashed run
resumes without recomputing its completed steps.
"""

from __future__ import annotations

import json
from html.parser import HTMLParser

import pytest
import rasterio

pytest_plugins = ["conftest_storage"]

SEED = 3


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A 20-image thermal calibration flight in observations mode with a hidden focal-length slope, and
    beside it a reference DSM (as a LiDAR survey would give): the scene's surface over the flight."""
    from aerocal.pipeline.dataset import REFERENCE_DSM
    from aerocal.simulate import simulate_flight, write_flight

    sim = simulate_flight("conte-calibration", seed=SEED, effects={"thermal_focal": 0.06}, max_images=20)
    folder = write_flight(sim, tmp_path_factory.mktemp("flights") / "flight-a", mode="observations")
    assert (folder / REFERENCE_DSM).is_file(), "the simulator writes the scene's surface as the reference"
    return folder


def _json(ctx_store, session, sha):
    return json.loads(ctx_store.read_bytes(ctx_store.get(session, sha)))


def test_process_flight_end_to_end(prefect_server, flight, storage_url, tmp_path):
    from aerocal.certificates.document import Certificate
    from flows.process import process_flight
    from storage.certificates import get_certificate
    from storage.database import connect
    from storage.provenance import ancestors, provenance
    from storage.runs import get_run

    out = tmp_path / "run"
    summary = process_flight(
        flight, out, "none", database_url=storage_url, artifact_root=str(tmp_path / "art")
    )

    computed = {k for k, v in summary.steps.items() if v.status == "computed"}
    assert {"ingest", "orient", "calibrate", "adjust", "mosaic", "assess", "diagnose", "report"} <= computed
    assert summary.steps["match"].status == "skipped", summary.steps["match"]
    db = connect(storage_url)
    with db.session() as session:
        run = get_run(session, summary.run_id)
        assert run.status == "completed", run.error
        cert = get_certificate(session, summary.certificate_id)
        assert cert.camera.model == "TS9260" and cert.version >= 1
        assert "self-calibration" in summary.certificate_reason
        prov = provenance(session, summary.run_id).to_dict()
        # inputs: the flight's manifest; outputs: every step output; certificate with reason; configuration
        input_kinds = {a["kind"] for a in prov["inputs"]}
        assert "flight-manifest" in input_kinds, input_kinds
        out_shas = {a["sha256"] for a in prov["outputs"]}
        missing = {n for n, sha in summary.outputs.items() if sha not in out_shas and n != "certificate"}
        assert not missing, f"outputs not recorded on the run: {missing}"
        assert prov["certificate"]["id"] == summary.certificate_id
        assert "self-calibration" in prov["certificate"]["reason"]
        conf = prov["configuration"]
        assert conf["certificate"] == "none"
        assert conf["process"]["calibration"]["adjust"]["adaptive"] is True
        # the flight declares its GNSS sigmas; the effective configuration records them
        declared = json.loads((flight / "flight.json").read_text())["gnss_sigma_m"]
        assert conf["effective"]["block_adjust"]["gnss_sigma_m"][2] == pytest.approx(declared[1])
        for step in ("ingest", "orient", "calibrate", "adjust", "mosaic", "assess", "diagnose", "report"):
            assert step in prov["timings"], f"no timing for {step}: {prov['timings']}"
        # lineage: the orthomosaic side (DSM) and the report descend from the flight's manifest
        from storage.artifacts import ArtifactStore

        store = ArtifactStore(tmp_path / "art")
        for name in ("dsm", "report", "poses", "diagnosis"):
            kinds = {a.kind for a in ancestors(session, store.get(session, summary.outputs[name]))}
            assert "flight-manifest" in kinds, f"{name} has no lineage to the flight: {kinds}"
        adjustment = _json(store, session, summary.outputs["adjustment"])
    db.dispose()

    # the run folder: report, DSM in the flight CRS, certificate, provenance
    files = summary.files
    assert "<html" in (out / "report.html").read_text()[:200].lower()
    check_report_shows_every_figure(out)
    with rasterio.open(files["dsm"]) as ds:
        assert ds.crs.to_epsg() == 32632
        assert ds.read(1).size > 100
    stored = Certificate.from_json((out / "certificate.json").read_text())
    assert stored.id == summary.certificate_id
    # conditions count the control points the calibration used (check points are held out)
    from aerocal import tables

    gcps = tables.read(flight / "observations" / "gcps.parquet", "gcps")
    seen = set(tables.read(flight / "observations" / "gcp_observations.parquet", "gcp_observations")
               .column("gcp_id").to_pylist())
    control = {g for g, r in zip(gcps.column("gcp_id").to_pylist(), gcps.column("role").to_pylist(),
                                 strict=True) if r == "control"}
    assert stored.conditions.n_gcp == len(control & seen)
    assert stored.conditions.n_images == 20
    dropped = {n: s.dropped for n, s in stored.significance.items() if s.dropped}
    assert all(not why.startswith("dropped") for why in dropped.values()), dropped
    assert json.loads((out / "provenance.json").read_text())["run_id"] == summary.run_id

    # the adjusted block is as good as its noise: sigma0 near 1 and check points inside a loose bound
    assert 0.7 < adjustment["sigma0"] < 1.4, adjustment["sigma0"]
    rho = summary.accuracy["rho"]
    assert all(r is not None and r < 2.5 for r in rho.values()), f"seed {SEED}: rho {rho}"
    assert isinstance(summary.diagnosis, str) and summary.diagnosis


class _Report(HTMLParser):
    """The ``<img>`` sources and ``<figure>`` ids of a report."""

    def __init__(self) -> None:
        super().__init__()
        self.srcs: list[str] = []
        self.figures: list[str] = []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.srcs.append(a.get("src") or "")
        elif tag == "figure":
            self.figures.append(a.get("id") or "")


def check_report_shows_every_figure(run_dir):
    """What a reader of the run folder's report checks: every image it references opens as a PNG, the
    four figures are there (the flight has a reference DSM), and summary.json carries their numbers:
    the DSM difference, the binned residual grid of the assessment, the IO the certificate gives each
    image at its temperature. ``aerocal report`` prints the run folder's key figures."""
    import base64
    import io

    import numpy as np
    from PIL import Image
    from typer.testing import CliRunner

    from aerocal.certificates.document import Certificate
    from aerocal.cli import app
    from aerocal.report import io_at_temperatures

    text = (run_dir / "report.html").read_text()
    parsed = _Report()
    parsed.feed(text)
    assert len(parsed.srcs) == text.count("<img") >= 4, parsed.srcs
    for src in parsed.srcs:
        if src.startswith("data:"):
            assert src.startswith("data:image/png;base64,"), src[:40]
            data = base64.b64decode(src.split(",", 1)[1])
        else:
            assert (run_dir / src).is_file(), f"the report references {src}, which is not in {run_dir}"
            data = (run_dir / src).read_bytes()
        with Image.open(io.BytesIO(data)) as img:
            assert img.format == "PNG"
            img.load()
            assert img.width > 300 and img.height > 200, img.size
            assert np.asarray(img.convert("L")).std() > 10, "the figure has content"
    kinds = {"block", "image_residuals", "temperature_io", "dem_difference"}
    assert kinds <= set(parsed.figures), parsed.figures
    assert "Figures not drawn" not in text

    doc = json.loads((run_dir / "summary.json").read_text())
    assert doc["notes"] == [] and kinds <= set(doc["figures"])
    dem = doc["figures"]["dem_difference"]
    assert doc["summary"]["dsm_minus_reference_m"]["mean_m"] == dem["mean_m"]
    measured = dem["measured_cells"]
    rmse_u = doc["summary"]["check_rmse_m"][2]
    print(f"DSM minus reference: all {dem['n']} cells mean {dem['mean_m']:.3f} m NMAD {dem['nmad_m']:.3f} m; "
          f"{measured['n']} measured cells mean {measured['mean_m']:.3f} m NMAD {measured['nmad_m']:.3f} m; "
          f"check points RMSE Up {rmse_u:.3f} m")
    # where the DSM is measured its offset from the reference is the block's height error, which the check
    # points measure (plus the tie-point DSM's own ~0.1 m, aerocal.products.dsm); interpolation across roofs and
    # trees spreads the differences elsewhere (aerocal.products.dsm): the measured cells scatter less than all
    assert abs(measured["mean_m"]) < 2.0 * rmse_u + 0.1, f"seed {SEED}: {measured}, check RMSE Up {rmse_u}"
    assert measured["nmad_m"] < dem["nmad_m"], f"seed {SEED}: measured {measured}, all cells {dem}"
    assert measured["n"] > 0.02 * dem["n"], f"seed {SEED}: few measured cells {measured['n']} of {dem['n']}"

    binned = doc["figures"]["image_residuals"]
    stored = json.loads((run_dir / "assessment.json").read_text())["reprojection"]
    assert binned["bins"] == [6, 8] and binned["count"] == stored["binned"]["count"]
    assert binned["mean_px"] == stored["binned"]["mean_px"]
    assert sum(map(sum, binned["count"])) == stored["n"] > 1000
    worst = max(np.hypot(*c) for row in binned["mean_px"] for c in row if c[0] is not None)
    print(f"binned residuals: {stored['n']} observations, largest bin mean {worst:.3f} px, "
          f"RMS {stored['rms_px']:.3f} px")

    cert = Certificate.from_json((run_dir / "certificate.json").read_text())
    tio = doc["figures"]["temperature_io"]
    model = None if cert.thermal is None else cert.thermal.model
    expected = io_at_temperatures(cert.camera, model, tio["temperature_c"])
    assert len(tio["temperature_c"]) == 20 and tio["thermal_model"] == (model is not None)
    if model is None:  # the flat line and the sentence that explains it
        assert "The certificate has no thermal model" in text and len(set(tio["f_px"])) == 1
    np.testing.assert_allclose(tio["f_px"], expected["f"], rtol=1e-12)
    np.testing.assert_allclose(tio["cy_px"], expected["cy"], rtol=1e-12)
    print(f"certificate thermal model: {None if model is None else model.to_dict()}; f over the flight "
          f"{min(tio['f_px']):.3f}-{max(tio['f_px']):.3f} px at {min(tio['temperature_c']):.2f}-"
          f"{max(tio['temperature_c']):.2f} degC")

    result = CliRunner().invoke(app, ["report", str(run_dir)])
    assert result.exit_code == 0, result.output
    assert "dsm_minus_reference_m" in result.output and "report.html" in result.output


def test_crashed_run_resumes_after_the_last_completed_step(prefect_server, flight, tmp_path, monkeypatch):
    import aerocal.pipeline.adjust_step
    from flows.process import process_flight
    from storage.database import connect
    from storage.runs import list_runs

    url, art = f"sqlite:///{tmp_path / 'aerocal.db'}", str(tmp_path / "art")

    def crash(*args, **kwargs):
        raise RuntimeError("power cut during the block adjustment")

    monkeypatch.setattr(aerocal.pipeline.adjust_step, "adjust_fixed_io", crash)
    with pytest.raises(RuntimeError, match="power cut"):
        process_flight(flight, tmp_path / "run", "none", database_url=url, artifact_root=art)
    monkeypatch.undo()

    db = connect(url)
    with db.session() as session:
        (first,) = list_runs(session, kind="process_flight")
        assert first.status == "failed" and "power cut" in first.error
        assert {"ingest", "orient", "calibrate"} <= set(first.timings), first.timings
        assert "adjust" not in first.timings
        first_id = first.id

    summary = process_flight(flight, tmp_path / "run", "none", database_url=url, artifact_root=art)
    steps = summary.steps
    for step in ("ingest", "orient", "calibrate"):
        assert steps[step].status == "reused", (step, steps[step])
        assert steps[step].computed_by == first_id
    assert steps["adjust"].status == "computed"
    with db.session() as session:
        runs = {r.id: r for r in list_runs(session, kind="process_flight")}
        second = runs[summary.run_id]
        assert second.status == "completed"
        assert "ingest (reused)" in second.timings and "ingest" not in second.timings
        assert "calibrate (reused)" in second.timings and "adjust" in second.timings
        # the certificate made before the crash is the one the resumed run uses
        assert second.certificate_id == summary.certificate_id
    db.dispose()


def test_image_mode_flight_is_matched_on_dask_and_the_step_resumes(tmp_path, monkeypatch):
    """Rendered frames (no observations given): ingest reads them, enhance + match run tile-parallel SIFT on
    a local Dask cluster, and the tracks tie every frame; a second call reuses the stored step, and a call by
    other code computes it again."""
    import numpy as np

    from aerocal.pipeline import FolderDataset
    from aerocal.pipeline.config import MatchStepConfig
    from aerocal.pipeline.ingest_step import ingest_step
    from aerocal.pipeline.match_step import match_step
    from aerocal.pipeline.runner import JsonOutput
    from aerocal.simulate import simulate_flight, write_flight
    from storage.migrations import upgrade
    from storage.runs import start_run
    from storage.steps import StepContext
    from tasks.runner import StoreRunner

    sim = simulate_flight("conte-calibration", seed=5, max_images=4)
    folder = write_flight(sim, tmp_path / "flight", mode="images")
    url = f"sqlite:///{tmp_path / 'aerocal.db'}"
    upgrade(url)
    ctx = StepContext(url, str(tmp_path / "art"), "run-images")
    with ctx.database.session() as session:
        start_run(session, ctx.run_id, "test")
        session.commit()
    runner, dataset = StoreRunner(ctx, prefect_tasks=False), FolderDataset(folder)
    ing = ingest_step(runner, dataset, runner.put(JsonOutput(dataset.manifest(), "flight-manifest")))
    matched = match_step(runner, ing, MatchStepConfig(serial_max_megapixels=0.0))
    assert not matched.reused
    with ctx.database.session() as session:
        obs = ctx.store.read_table(ctx.store.get(session, matched["observations"]), "observations")
        images = ctx.store.read_table(ctx.store.get(session, ing["images"]), "images")
    assert images.num_rows == 4
    ids = images.column("image_id").to_numpy()
    per_image = np.bincount(obs.column("image_id").to_numpy(), minlength=ids.max() + 1)[ids]
    assert per_image.min() > 100, f"observations per image {per_image.tolist()}"
    track_len = np.bincount(obs.column("track_id").to_numpy())
    assert track_len[track_len > 0].min() >= 2
    again = match_step(runner, ing, MatchStepConfig(serial_max_megapixels=0.0))
    assert again.reused and again.outputs == matched.outputs
    from aerocal.pipeline import runner as runner_module

    monkeypatch.setattr(runner_module, "source_digest", lambda: "another version of the code")
    other = match_step(runner, ing, MatchStepConfig(serial_max_megapixels=0.0))
    assert not other.reused, "a step cached by other code was reused"


def test_large_flight_calibrates_on_the_proposed_sub_block(flight, tmp_path):
    """A flight larger than ``whole_flight_max_images`` calibrates on the sub-block that
    :func:`aerocal.calibrate.subset.propose_subset` predicts best; the certificate's conditions describe it."""
    from aerocal.calibrate.self_calibration import CalibrationConfig
    from aerocal.calibrate.subset import SubsetConfig
    from aerocal.certificates.document import Certificate
    from aerocal.pipeline import FolderDataset
    from aerocal.pipeline.calibrate_step import calibrate_step
    from aerocal.pipeline.ingest_step import ingest_step
    from aerocal.pipeline.runner import JsonOutput
    from storage.migrations import upgrade
    from storage.runs import start_run
    from storage.steps import StepContext
    from tasks.runner import StoreRunner

    url = f"sqlite:///{tmp_path / 'aerocal.db'}"
    upgrade(url)
    ctx = StepContext(url, str(tmp_path / "art"), "run-subset")
    with ctx.database.session() as session:
        start_run(session, ctx.run_id, "test")
        session.commit()
    runner, dataset = StoreRunner(ctx, prefect_tasks=False), FolderDataset(flight)
    ing = ingest_step(runner, dataset, runner.put(JsonOutput(dataset.manifest(), "flight-manifest")))
    config = CalibrationConfig(
        whole_flight_max_images=10, subset=SubsetConfig(strip_counts=(2, 3), images_per_strip=(3, 4))
    )
    cal = calibrate_step(runner, ing, ing["observations"], config)
    with ctx.database.session() as session:
        doc = json.loads(ctx.store.read_bytes(ctx.store.get(session, cal["calibration"])))
        cert_art = ctx.store.get(session, cal["certificate"])
        cert = Certificate.from_dict(json.loads(ctx.store.read_bytes(cert_art)))
    subset = doc["subset"]
    assert 10 <= len(subset["image_ids"]) < 20, subset
    assert "candidates scored" in subset["reasons"][0]
    assert cert.conditions.n_images == len(subset["image_ids"])
    assert cert.conditions.transversal_strip == subset["transversal"]
    assert cert.sigmas["f"] < 3.0, cert.sigmas
