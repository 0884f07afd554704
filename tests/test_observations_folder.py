"""An observations-mode flight folder is read one way: `aerocal ingest` and `aerocal process` both judge the
tables processing uses and the files beside them (eo.csv, GCP files), which must agree with the tables."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from aerocal.cli import app
from aerocal.ingest.sidecars import AGREEMENT_M

SEED = 3


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("obs") / "flight"
    result = CliRunner().invoke(app, ["simulate", "mitishita-block", "--out", str(out), "--seed", str(SEED)])
    assert result.exit_code == 0, result.output
    return out


def _spoil(folder: Path, dst: Path, shift_m: float) -> tuple[int, str]:
    """A copy of ``folder`` whose eo.csv has alt=abc on its fifth image and whose gcps.csv moves GCP01 east by
    ``shift_m``; the eo.csv line spoiled and the image's name."""
    shutil.copytree(folder, dst)
    lines = (dst / "eo.csv").read_text().splitlines()
    header = next(k for k, line in enumerate(lines) if line.startswith("image,"))
    row = header + 5
    cells = lines[row].split(",")
    cells[lines[header].split(",").index("alt")] = "abc"
    lines[row] = ",".join(cells)
    (dst / "eo.csv").write_text("\n".join(lines) + "\n")
    gcps = (dst / "gcps.csv").read_text()
    moved = re.sub(r"^GCP01,([-0-9.]+),", lambda m: f"GCP01,{float(m.group(1)) + shift_m:.4f},", gcps, flags=re.M)
    assert moved != gcps
    (dst / "gcps.csv").write_text(moved)
    return row + 1, cells[0]


def test_a_simulated_observations_folder_ingests_clean(folder):
    result = CliRunner().invoke(app, ["ingest", str(folder)], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "observations (processed from observations/*.parquet)" in result.output
    assert "[error" not in result.output and "stop `aerocal process`" not in result.output


def test_files_that_contradict_the_tables_stop_ingest_and_process_alike(folder, tmp_path):
    spoiled = tmp_path / "spoiled"
    line, image = _spoil(folder, spoiled, 1000.0)
    env = {"COLUMNS": "300"}
    ingest = CliRunner().invoke(app, ["ingest", str(spoiled)], env=env)
    assert ingest.exit_code == 2, ingest.output
    # the unreadable cell is an error as in an image-mode ingest; the moved GCP contradicts the table and stops
    assert re.search(rf"eo\.csv:{line}: alt: alt 'abc' is not a number.*\[error\]", ingest.output), ingest.output
    assert re.search(r"gcps\.csv:\d+: coordinates: GCP01 lies 1000\.00 m horizontally.*\[error, stops processing\]",
                     ingest.output), ingest.output
    assert "1 problem(s) stop `aerocal process`" in ingest.output

    db = tmp_path / "store.db"
    process = CliRunner().invoke(app, ["process", str(spoiled), "--database-url", f"sqlite:///{db}"], env=env)
    assert process.exit_code == 2, process.output
    assert "GCP01 lies 1000.00 m" in process.output, process.output
    assert "nothing was processed or stored" in process.output
    assert not db.exists(), "a run stopped by bad input created the store"


def test_a_gcp_moved_within_the_files_precision_is_agreement(folder, tmp_path):
    """Below :data:`AGREEMENT_M` a file and its table agree (the files round to 1e-4 m); the alt=abc stays an
    error that does not stop processing."""
    spoiled = tmp_path / "spoiled"
    _spoil(folder, spoiled, AGREEMENT_M / 2)
    result = CliRunner().invoke(app, ["ingest", str(spoiled)], env={"COLUMNS": "300"})
    assert result.exit_code == 2 and "GCP01" not in result.output and "stop `aerocal process`" not in result.output, (
        result.output)
