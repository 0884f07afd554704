"""Rendered, matched flights through the `aerocal` commands: the diagnosis names the effect hidden in the pixels
or in the recorded exterior orientation, and nothing when none is hidden.

Each flight is made and processed as a user would, one command after the other:
``aerocal simulate PRESET --mode images`` (thermal 640 x 480 frames ray-cast through the true camera, with
every hidden effect acting on the pixels or on the recorded GNSS/IMU), ``aerocal db upgrade``,
``aerocal certificates import cameras.txt`` (the camera's lab calibration, written as a COLMAP cameras.txt),
``aerocal process --certificate ID`` (matching, orientation, the block with IO fixed, mosaic, diagnosis) and
``aerocal diagnose RUN --json``. With the IO known, what the diagnosis sees is what the matched-image path and
the hidden effect leave in the block: the signatures of matching (correlated, non-white errors, mismatches)
must not pass for an effect.

Flights are small (16 central frames of ``conte-calibration`` and of the warming ``conte-city``, 12 for the
effect-free ones) and run two at a time, as two terminals would (the machine has two cores). Sizes are
realistic: a 0.3 s GNSS time lag, a 30 ms rolling-shutter readout, a 0.2 deg mounting tilt, a focal drift of
0.5 px/degC (0.03 % of f per degC).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

AEROCAL = str(Path(sys.executable).with_name("aerocal"))
N_IMAGES = 16  # frames of a flight with a hidden effect
N_EFFECT_FREE = 12  # frames of an effect-free flight (what matters there is the matched path, not power)
EFFECT_FREE = [("conte-calibration", seed) for seed in (21, 22, 23)] + [("conte-city", seed) for seed in (21, 22, 23)]
HIDDEN = [
    ("conte-city", 24, "thermal_focal", (0.5,)),
    ("conte-calibration", 25, "rolling_shutter", (0.03,)),
    ("conte-city", 26, "boresight", (0.2, -0.1, 0.0)),
    ("conte-calibration", 11, "gnss_time_offset", (0.3,)),
]


@pytest.fixture(scope="module")
def prefect_api():
    """A temporary Prefect server the flights' processes report to (its URL in their environment)."""
    from prefect.settings import PREFECT_API_URL
    from prefect_harness import prefect_harness

    with prefect_harness():
        yield PREFECT_API_URL.value()


def _run(args: list[str], env: dict, cwd: Path) -> str:
    done = subprocess.run([AEROCAL, *args], env=env, cwd=cwd, capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, f"aerocal {' '.join(args)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
    return done.stdout


def _flight(work: Path, api: str, preset: str, seed: int, effect: str | None = None) -> tuple[dict, Path]:
    """Simulate, import the lab certificate, process and diagnose one flight; its diagnosis and folder."""
    name = f"{preset}-{seed}" + (f"-{effect.split('=')[0]}" if effect else "")
    here = work / name
    here.mkdir(parents=True)
    env = {**os.environ, "PREFECT_API_URL": api, "COLUMNS": "250"}
    db = f"sqlite:///{here / 'aerocal.db'}"
    args = ["simulate", preset, "--out", "flight", "--seed", str(seed), "--mode", "images",
            "--max-images", str(N_IMAGES if effect else N_EFFECT_FREE)]
    _run(args + (["--effect", effect] if effect else []), env, here)
    cam = json.loads((here / "flight" / "truth.json").read_text())["camera_true"]
    (here / "cameras.txt").write_text(
        f"# the camera's lab calibration\n1 FULL_OPENCV {cam['width']} {cam['height']} {cam['f']} {cam['f']} "
        f"{cam['cx']} {cam['cy']} {cam['k1']} {cam['k2']} {cam['p1']} {cam['p2']} {cam['k3']} 0 0 0\n")
    identity = json.loads((here / "flight" / "camera.json").read_text())["identity"]
    _run(["db", "upgrade", "--database-url", db], env, here)
    imported = _run(["certificates", "import", "cameras.txt", "--make", identity["make"], "--model",
                     identity["model"], "--serial", identity["serial"], "--lens", identity["lens"],
                     "--database-url", db], env, here)
    cert_id = imported.split("stored certificate ")[1].split(":")[0]
    _run(["process", "flight", "--certificate", cert_id, "--out", "run", "--database-url", db,
          "--artifacts", "artifacts"], env, here)
    out = _run(["diagnose", "run", "--json"], env, here)
    return json.JSONDecoder().raw_decode(out[out.index("{"):])[0], here


def _named(diagnosis: dict) -> list[str]:
    return [e["name"] for e in diagnosis["effects"]]


@pytest.fixture(scope="module")
def rendered(tmp_path_factory, prefect_api):
    """Every flight of EFFECT_FREE and HIDDEN, made and diagnosed: {(preset, seed, effect): (diagnosis, folder)}."""
    work = tmp_path_factory.mktemp("rendered")
    jobs = [(p, s, None) for p, s in EFFECT_FREE] + [
        (p, s, f"{name}={','.join(str(v) for v in value)}") for p, s, name, value in HIDDEN]
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(lambda job: _flight(work, prefect_api, *job), jobs))
    return dict(zip(jobs, results, strict=True))


@pytest.mark.slow
@pytest.mark.timeout(1500)  # the ten flights are made in this test's setup: ~9 min on the idle 2-core machine
def test_rendered_flights_name_the_hidden_effect_and_nothing_else(rendered):
    by_job = {job: d for job, (d, _) in rendered.items()}
    for job, d in by_job.items():
        print(job, "->", d["summary"])

    # effect-free: at most one alarm over the six flights (two presets, three seeds each)
    alarms = {f"{p} seed {s}": d["summary"] for (p, s, e), d in by_job.items() if e is None and d["effects"]}
    assert len(alarms) <= 1, f"effect-free rendered flights with a named effect: {alarms}"

    # hidden: each is the only effect named, its magnitude within 25 %
    for preset, seed, name, value in HIDDEN:
        d = next(d for (p, s, e), d in by_job.items() if p == preset and s == seed and e)
        assert _named(d) == [name], f"{preset} seed {seed}: hid {name} {value}, named {d['summary']}"
        found = np.atleast_1d(d["effects"][0]["magnitude"])
        truth = np.asarray(value, dtype=float)
        assert np.linalg.norm(found - truth) <= 0.25 * np.linalg.norm(truth), (
            f"{preset} seed {seed}: {name} {found} against the hidden {truth}")


@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_a_rendered_flat_block_without_gcps_keeps_the_nominal_focal_length(rendered, prefect_api, tmp_path):
    """The frames of an effect-free flight, as a survey with consumer GNSS/IMU and no ground control would
    hand them over (no GCP files; flight.json declares 3/5 m and 2/2/5 deg): the self-calibration does not
    free a focal length the flat, GCP-free block cannot determine, keeps the nominal one and says why."""
    import shutil

    preset, seed = EFFECT_FREE[0]
    _, source = rendered[(preset, seed, None)]
    flight = tmp_path / "flight"
    shutil.copytree(source / "flight", flight, symlinks=True)
    for name in ("gcp_list.txt", "gcps.csv"):
        (flight / name).unlink()
    meta = json.loads((flight / "flight.json").read_text())
    meta.update(gnss_sigma_m=[3.0, 5.0], imu_sigma_deg=[2.0, 2.0, 5.0])
    (flight / "flight.json").write_text(json.dumps(meta, indent=1))
    env = {**os.environ, "PREFECT_API_URL": prefect_api, "COLUMNS": "250"}
    _run(["process", "flight", "--certificate", "none", "--out", "run", "--database-url",
          f"sqlite:///{tmp_path / 'aerocal.db'}", "--artifacts", "artifacts"], env, tmp_path)
    from aerocal.certificate import Certificate

    cert = Certificate.from_json((tmp_path / "run" / "calibration_certificate.json").read_text())
    nominal = json.loads((flight / "camera.json").read_text())["camera"]["f"]
    assert "f" not in cert.estimated and cert.camera.f == nominal, f"{preset} seed {seed}: {cert.render_text()}"
    assert "f not determined by this block" in cert.significance["f"].dropped, cert.significance
