"""``aerocal match`` and ``aerocal diagnose`` read a flight folder as ``aerocal process`` does: the same images,
the same camera (camera.json, else the nominal camera ingest finds in the files) and the same flying height."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from aerocal import tables
from aerocal.simulate import simulate_flight, write_flight

SEED = 4


def test_match_writes_the_tables_and_the_camera_it_found_then_the_folder_is_diagnosed(tmp_path):
    from aerocal.cli import app

    folder = write_flight(simulate_flight("conte-calibration", seed=SEED, max_images=6), tmp_path / "flight",
                          mode="images")
    (folder / "camera.json").unlink()  # a user's folder of frames: the camera comes from the files
    cli = CliRunner()

    early = cli.invoke(app, ["diagnose", str(folder), "--json"])
    assert early.exit_code == 2 and "aerocal match" in " ".join(early.output.split()), early.output

    result = cli.invoke(app, ["match", str(folder), "--workers", "0"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, f"seed {SEED}: {result.output}"
    obs = tables.read(folder / "observations" / "observations.parquet", "observations")
    images = tables.read(folder / "observations" / "images.parquet", "images")
    assert images.num_rows == 6 and obs.num_rows > 1000, f"seed {SEED}: {images.num_rows} images, {obs.num_rows}"
    assert set(obs.column("image_id").to_pylist()) == set(images.column("image_id").to_pylist())
    camera = json.loads((folder / "camera.json").read_text())
    assert "catalogue" in camera["source"] and camera["camera"]["width"] == 640, camera
    assert "camera.json written" in result.output, result.output

    # the folder is now an observations-mode flight that the diagnosis reads as process would
    diagnosed = cli.invoke(app, ["diagnose", str(folder), "--json"])
    assert diagnosed.exit_code == 0, diagnosed.output
    assert "hypotheses" in json.loads(diagnosed.output)
