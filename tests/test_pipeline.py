"""The flight pipeline in the engine (:mod:`aerocal.pipeline`), as a notebook user runs it: no Prefect server,
no database, the same answers as the platform's run of the same flight."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio

ROOT = Path(__file__).resolve().parents[1]
SEED = 11
#: the focal slope hidden in the flight (px/degC)
SLOPE = 0.06


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    from aerocal.simulate import simulate_flight, write_flight

    sim = simulate_flight("conte-calibration", seed=SEED, effects={"thermal_focal": SLOPE}, max_images=20)
    folder = write_flight(sim, tmp_path_factory.mktemp("flights") / "flight-b", mode="observations")
    return sim, folder


def test_process_runs_a_flight_in_a_fresh_interpreter_without_prefect_or_a_database(simulated, tmp_path):
    """``aerocal.pipeline.process`` on a folder, in a new Python: it writes the products and imports neither
    Prefect nor SQLAlchemy nor Dask's distributed scheduler."""
    sim, folder = simulated
    code = f"""
import json, sys
from aerocal.pipeline import process
run = process({str(folder)!r}, certificate="none", out_dir={str(tmp_path / 'run')!r})
heavy = sorted(m for m in ("prefect", "sqlalchemy", "distributed", "storage", "tasks", "flows") if m in sys.modules)
print(json.dumps({{"heavy": heavy, "reason": run.summary.certificate_reason, "files": run.files}}))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=600,
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["heavy"] == [], f"the pipeline imported {result['heavy']}"
    assert result["reason"].startswith("made by this flight's self-calibration"), result["reason"]
    files = result["files"]
    for name in ("report", "dsm", "certificate", "diagnosis", "poses", "points"):
        assert Path(files[name]).is_file(), name
    with rasterio.open(files["dsm"]) as ds:
        heights = ds.read(1, masked=True)
        assert ds.crs is not None and heights.count() > 100
    cert = json.loads(Path(files["certificate"]).read_text())
    # f at the reference temperature, within 4 sigma of the truth it was simulated with
    from aerocal.certificates.document import Certificate

    parsed = Certificate.from_dict(cert)
    true_f = sim.spec.camera_true.f
    t0 = sim.spec.sensors.reference_temperature_c
    model = parsed.thermal.model if parsed.thermal is not None else None
    f_at_ref = parsed.camera.f + (model.df_dt * (t0 - model.t0) if model is not None else 0.0)
    sigma = parsed.sigmas["f"]
    assert sigma <= 0.01 * true_f, f"seed {SEED}: sigma of f {sigma:.2f} px beyond the review's 1 % bound"
    assert abs(f_at_ref - true_f) < 4 * sigma + (abs(SLOPE) * 3 if model is None else 0.0), \
        f"seed {SEED}: f {f_at_ref:.2f} +- {sigma:.2f} px, true {true_f:.2f} px"


def test_a_dataset_in_memory_gives_the_folder_answer_and_a_store_is_reused(simulated):
    """The simulated flight as tables in memory (no folder written) gives the same adjustment as its folder, and
    a second flight with the same in-memory certificate store reuses the certificate the first one issued."""
    from aerocal.pipeline import MemoryCertificates, process
    from aerocal.simulate import as_dataset

    sim, folder = simulated
    store = MemoryCertificates()
    from_folder = process(folder, certificate="none", certificates=store)
    in_memory = process(as_dataset(sim, name=folder.name), certificates=store)
    assert len(store.documents) == 1
    assert in_memory.summary.certificate_id == from_folder.summary.certificate_id
    assert in_memory.summary.certificate_reason.startswith("newest applicable certificate"), \
        in_memory.summary.certificate_reason
    assert "calibrate" not in in_memory.steps and in_memory.steps["match"].skipped
    # each step's figures are those its type declares (aerocal.pipeline.figures), here as a reader finds them
    from aerocal.pipeline.figures import FIGURES

    for name, step in from_folder.steps.items():
        if name in FIGURES and not step.skipped:
            declared = FIGURES[name]
            assert declared.__required_keys__ <= set(step.extra) <= set(declared.__annotations__), (name, step.extra)
    assert from_folder.steps["orient"].extra["method"] == "priors" and from_folder.steps["control"].extra["datum"]
    a, b = from_folder.table("poses"), in_memory.table("poses")
    for col in ("X", "Y", "Z"):
        np.testing.assert_allclose(a.column(col).to_numpy(), b.column(col).to_numpy(), atol=1e-6)
    assert in_memory.json("assessment")["check_points"] == from_folder.json("assessment")["check_points"]
    # the dataset in memory has no folder: no frames to mosaic, no reference DSM; the report says so
    assert in_memory.json("mosaic")["frames"] == 0


def test_a_step_asked_again_is_reused_by_the_local_runner(simulated):
    from aerocal.pipeline import LocalRunner, process

    _, folder = simulated
    runner = LocalRunner()
    first = process(folder, certificate="none", runner=runner)
    second = process(folder, certificate="none", runner=runner)
    assert all(not r.reused for r in first.steps.values())
    assert {name for name, r in second.steps.items() if not r.skipped and not r.reused} == set()
    assert second.outputs == first.outputs


def test_a_bad_dataset_is_named(tmp_path):
    from aerocal.pipeline import FlightInputError, process

    (tmp_path / "empty").mkdir()
    with pytest.raises(FlightInputError, match="holds no files"):
        process(tmp_path / "empty")
    with pytest.raises(FlightInputError, match="is not a folder"):
        process(tmp_path / "missing")
