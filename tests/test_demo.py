"""The demo flow on a reduced flight: simulated, processed with every step, products that open."""

from __future__ import annotations

import json
import os

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


def test_demo_flow_makes_every_product(prefect_server, tmp_path, monkeypatch):
    from aerocal.certificate import Certificate
    from flows.demo import DemoConfig, demo
    from storage.certificates import get_certificate
    from storage.database import connect

    monkeypatch.delenv("AEROCAL_DATABASE_URL", raising=False)
    monkeypatch.delenv("AEROCAL_ARTIFACT_ROOT", raising=False)
    out = tmp_path / "demo"
    summary = demo(out, DemoConfig(max_images=30, frames=5))

    # everything under the output folder, Prefect's home included
    assert (out / "aerocal.db").is_file() and (out / "artifacts").is_dir()
    assert os.environ["PREFECT_HOME"] == str((out / "prefect").resolve())
    statuses = {k: v["status"] for k, v in summary["steps"].items()}
    assert all(statuses[s] == "computed" for s in ("ingest", "calibrate", "adjust", "mosaic", "report")), (
        statuses
    )

    with rasterio.open(summary["files"]["orthomosaic"]) as ds:
        assert ds.crs.to_string() == summary["simulated"]["crs"]
        band = ds.read(1)
        coverage = float(np.mean(band != ds.nodata))
    assert coverage > 0.2, f"orthomosaic covers {coverage:.0%} of its grid"
    mosaic = json.loads((out / "run" / "summary.json").read_text())["summary"]
    assert mosaic["mosaic_frames"] == 5
    html = (out / "run" / "report.html").read_text()
    assert "Flight report" in html and "data:image/png;base64" in html

    cert = Certificate.from_json((out / "run" / "certificate.json").read_text())
    db = connect(f"sqlite:///{out / 'aerocal.db'}")
    with db.session() as session:
        stored = get_certificate(session, cert.id)
        assert stored.camera.model == "TS9260"
    db.dispose()
    # the focal length is determined to a fraction of a pixel from 16 frames with GCPs
    assert cert.sigmas["f"] < 2.0, cert.sigmas
    assert isinstance(summary["diagnosis"], str) and summary["diagnosis"]
    # the demo's hidden effect (a 10 ms rolling-shutter readout) is named, never told to the flow
    assert summary["diagnosis"].startswith("rolling_shutter"), summary["diagnosis"]
