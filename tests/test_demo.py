"""`aerocal demo` as a user runs it: the flight simulated, processed with every step, what it prints, products that
open."""

from __future__ import annotations

import json
import os

import laspy
import numpy as np
import pytest
import rasterio


@pytest.fixture
def isolated_prefect_env(monkeypatch):
    """The demo points PREFECT_HOME under its output and sets Prefect's quiet defaults: restore them after."""
    from flows.environment import PREFECT_DEFAULTS

    for key in ("PREFECT_HOME", *PREFECT_DEFAULTS):
        monkeypatch.setenv(key, os.environ.get(key, "unset"))
        if os.environ[key] == "unset":
            monkeypatch.delenv(key)


@pytest.fixture
def prefect_server(isolated_prefect_env):
    from prefect_harness import prefect_harness

    with prefect_harness():
        yield


def test_the_demo_as_a_user_runs_it_finds_the_hidden_readout_and_extends_the_model(prefect_server, tmp_path,
                                                                                    monkeypatch):
    """``aerocal demo`` with its defaults (the 44-image flight and its 8 rendered frames, as `make demo` runs it): the
    hidden 10 ms readout is not told to processing; the diagnosis names it within 25 %, the block is adjusted again
    with it, the check points improve, the readout goes into version 2 of the camera's certificate and the extended
    block's diagnosis names nothing; the command says so."""
    from typer.testing import CliRunner

    from aerocal.certificates.document import Certificate
    from aerocal.cli import app
    from aerocal.pipeline import RunSummary
    from flows.demo import DemoConfig
    from storage.certificates import get_certificate
    from storage.database import connect

    monkeypatch.delenv("AEROCAL_DATABASE_URL", raising=False)
    monkeypatch.delenv("AEROCAL_ARTIFACT_ROOT", raising=False)
    out = tmp_path / "demo"
    config = DemoConfig()  # what the command runs
    done = CliRunner().invoke(app, ["demo", "--out", str(out)], env={"COLUMNS": "250"})
    assert done.exit_code == 0, done.output
    printed = " ".join(done.output.split())
    assert "not told to processing: rolling_shutter = 0.01 s" in printed, printed[:2000]
    assert "found and applied: rolling_shutter = " in printed and "(by the diagnosis;" in printed, printed
    assert "diagnosis of the extended block: no systematic effect found" in printed, printed
    assert "surface: dense: " in printed and "% of the DSM measured" in printed, printed
    summary = RunSummary.from_json(json.loads((out / "run" / "run.json").read_text()))

    # everything under the output folder, Prefect's home included
    assert (out / "aerocal.db").is_file() and (out / "artifacts").is_dir()
    assert os.environ["PREFECT_HOME"] == str((out / "prefect").resolve())
    statuses = summary.step_status()
    assert all(statuses[s] == "computed" for s in ("ingest", "calibrate", "adjust", "diagnose", "extend",
                                                   "recalibrate", "adjust_extended", "mosaic", "report")), statuses

    # the readout, found by the diagnosis with a gain on held-out images, within 25 % of the hidden 10 ms
    found = summary.finding("rolling_shutter")
    assert found and found.found_by == "diagnosis", f"seed {config.seed}: {summary.findings}"
    assert abs(found.values[0] - 0.010) < 0.0025, f"seed {config.seed}: {found}"
    assert "held-out gain +" in found.evidence, found
    ext = summary.model_extension
    before, after = ext["before"]["check_points"], ext["after"]["check_points"]
    rmse = [float(np.sqrt(sum(v**2 for v in c["rmse_m"].values()))) for c in (before, after)]
    assert rmse[1] < rmse[0], f"seed {config.seed}: check points {rmse[0]:.3f} m before, {rmse[1]:.3f} m after"
    assert summary.diagnosis_after_extension == "no systematic effect found", summary.diagnosis_after_extension

    # the products come from the extended block
    with rasterio.open(summary.files["orthomosaic"]) as ds:
        assert ds.crs.to_string() == json.loads((out / "flight" / "flight.json").read_text())["crs"]
        band = ds.read(1)
        coverage = float(np.mean(band != ds.nodata))
    assert coverage > 0.2, f"orthomosaic covers {coverage:.0%} of its grid"
    # ... on the dense surface matched in the frames: a LAZ cloud a viewer opens, a DSM whose band 2 flags its
    # filled cells, and the dense and tie-point DSMs against the flight's reference surface side by side
    las = laspy.read(summary.files["cloud"])
    assert las.header.point_count > 100_000 and las.header.parse_crs().to_string() == ds.crs.to_string()
    views = np.asarray(las.views)
    assert views.min() >= 2 and np.mean(views >= 3) > 0.5, np.bincount(views)
    with rasterio.open(summary.files["dsm"]) as dsm:
        measured = dsm.read(2, masked=True).compressed()
        assert dsm.descriptions == ("height", "measured", "views") and 0.3 < measured.mean() < 1.0, measured.mean()
        cell_views = dsm.read(3, masked=True).compressed()
        assert set(np.unique(cell_views[measured == 1]).tolist()) <= set(range(2, 8))
        # a cell flagged measured is one the cloud's points fall in; every other height is interpolated
        col, row = ~dsm.transform * (np.asarray(las.x), np.asarray(las.y))
        row, col = np.floor(row).astype(np.int64), np.floor(col).astype(np.int64)
        inside = (row >= 0) & (row < dsm.height) & (col >= 0) & (col < dsm.width)
        holds = np.zeros((dsm.height, dsm.width), dtype=bool)
        holds[row[inside], col[inside]] = True
        flagged = dsm.read(2) == 1
        assert np.mean(flagged == holds) > 0.999, (int(np.count_nonzero(flagged & ~holds)),
                                                   int(np.count_nonzero(holds & ~flagged)))
    # a height only where the frames see the ground: the DSM's cells with a height lie under the orthomosaic (the
    # grid around the cloud has corners no frame saw, where the filling extrapolates). Measured: 93.5 % of the grid
    # with a height, 99.15 % of those under the orthomosaic, the rest a band a few cells wide along its edge (the
    # footprints are cast on a plane below the surface)
    with rasterio.open(summary.files["dsm"]) as dsm, rasterio.open(summary.files["orthomosaic"]) as ortho:
        has = dsm.read(1) != dsm.nodata
        rows, cols = np.nonzero(has)
        x, y = dsm.transform * (cols + 0.5, rows + 0.5)
        ocol, orow = ~ortho.transform * (x, y)
        orow, ocol = np.floor(orow).astype(np.int64), np.floor(ocol).astype(np.int64)
        within = (orow >= 0) & (orow < ortho.height) & (ocol >= 0) & (ocol < ortho.width)
        under = np.zeros(len(rows), dtype=bool)
        under[within] = ortho.read(1)[orow[within], ocol[within]] != ortho.nodata
        print(f"dsm.tif: {has.mean():.1%} of its grid with a height, {np.mean(under):.2%} of those under the "
              "orthomosaic")
        assert np.mean(under) > 0.985 and has.mean() < 0.98, (has.mean(), np.mean(under))
    with rasterio.open(summary.files["dsm"]) as dsm, rasterio.open(summary.files["dtm"]) as dtm:
        assert dtm.crs == dsm.crs and dtm.transform == dsm.transform
        above = (dsm.read(1, masked=True) - dtm.read(1, masked=True)).compressed()
        # the DTM's band 2: the ground measured, a part of the DSM's measured cells on which the DTM is the surface
        assert dtm.descriptions[:2] == ("height", "measured")
        ground = dtm.read(2) == 1
        assert 0.1 < ground.mean() < 0.9 and not np.any(ground & (dsm.read(2) != 1)), ground.mean()
        on_ground = (dsm.read(1) - dtm.read(1))[ground]
        assert abs(np.median(on_ground)) < 0.3 and np.percentile(np.abs(on_ground), 95) < 3.0, (
            np.percentile(on_ground, [5, 50, 95]))
    # the ground under the city: the buildings (measured: 90th percentile 20.7 m) gone, the ground kept
    assert np.percentile(above, 90) > 5.0 and abs(np.median(above)) < 0.5, np.percentile(above, [5, 50, 90])
    report = json.loads((out / "run" / "summary.json").read_text())["summary"]
    # the dense surface of the extended block (its frames read out row by row, as the certificate now says) against
    # the simulated scene: measured: median 0.3 m (0.6 GSD), NMAD 0.68 m; the tie points' NMAD 1.82 m
    dense, sparse = report["dense_minus_reference_m"], report["sparse_minus_reference_m"]
    gsd = report["gsd_m"]
    assert abs(dense["median_m"]) < gsd and dense["nmad_m"] < 2 * gsd, dense
    assert dense["nmad_m"] < 0.6 * sparse["nmad_m"] and dense["completeness"] > 10 * sparse["completeness"], (
        dense, sparse)
    assert report["mosaic_frames"] == config.frames and "rolling_shutter" in report["model_extension"]
    html = (out / "run" / "report.html").read_text()
    assert "Flight report" in html and "data:image/png;base64" in html and "The model extended by the diagnosis" in html
    assert "Dense DSM minus reference" in html and "Tie-point DSM minus reference" in html
    assert "measured by the dense cloud" in html

    # the camera's certificate: version 2 carries the readout, with the flight that found it
    cert = Certificate.from_json((out / "run" / "certificate.json").read_text())
    db = connect(f"sqlite:///{out / 'aerocal.db'}")
    with db.session() as session:
        stored = get_certificate(session, cert.id)
        assert stored.camera.model == "TS9260" and stored.version == 2
    db.dispose()
    term = cert.terms["rolling_shutter"]
    assert term.applied == "measurements" and abs(term.values[0] - 0.010) < 0.0025 and term.flights, term
    assert cert.sigmas["f"] < 2.0, cert.sigmas
