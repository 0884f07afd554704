"""The artifact disk filling up in the middle of `aerocal process`: a small filesystem (tmpfs) as the artifact store
(mounting it needs root, as CI runs). The run stops with one line that says the disk is full and what to do, no
artifact is registered without its whole file, the run is recorded as failed, and once there is room the same
command resumes and completes."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

AEROCAL = str(Path(sys.executable).with_name("aerocal"))


@pytest.fixture
def small_disk(tmp_path):
    """A 1.5 MB tmpfs mounted in ``tmp_path`` (unmounted after the test). Where this process may not mount one
    (not root, or no tmpfs) the test fails and says so: a full disk is a case the product must be held to."""
    mount = tmp_path / "small"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1536k", "tmpfs", str(mount)], capture_output=True,
                          text=True)
    if done.returncode != 0:
        pytest.fail(f"cannot mount a small tmpfs here ({done.stderr.strip() or done.returncode}): the disk-full "
                    "case needs one; run the tests as a user who may mount a tmpfs (root in CI)", pytrace=False)
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def test_a_full_artifact_disk_stops_the_run_in_one_line_and_registers_nothing_half_written(small_disk, tmp_path):
    from prefect_harness import prefect_harness

    from aerocal.simulate import simulate_flight, write_flight
    from storage.artifacts import ArtifactStore
    from storage.database import connect
    from storage.models import Artifact, Run

    seed = 61
    folder = write_flight(simulate_flight("conte-calibration", seed=seed, max_images=24), tmp_path / "flight",
                          mode="observations")
    db = f"sqlite:///{tmp_path / 'aerocal.db'}"
    with prefect_harness():
        from prefect.settings import PREFECT_API_URL

        env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "COLUMNS": "200"}

        def process(artifacts: Path) -> subprocess.CompletedProcess:
            return subprocess.run([AEROCAL, "process", str(folder), "--certificate", "none", "--out",
                                   str(tmp_path / "run"), "--database-url", db, "--artifacts", str(artifacts)],
                                  capture_output=True, text=True, env=env, timeout=900)

        full = process(small_disk)
        said = [line for line in (full.stdout + full.stderr).splitlines()
                if line.strip() and not line.startswith("processing ")]
        assert full.returncode == 1, f"seed {seed}: exit {full.returncode}\n{full.stdout}\n{full.stderr}"
        assert len(said) == 1 and "No space left on device" in said[0] and "--artifacts" in said[0], said
        # every artifact registered has its whole file, and the run is recorded as failed
        store, database = ArtifactStore(small_disk), connect(db)
        try:
            with database.session() as session:
                stored = session.query(Artifact).all()
                for artifact in stored:
                    store.verify(artifact)  # raises on a missing or partial file
                statuses = [r.status for r in session.query(Run).all()]
        finally:
            database.dispose()
        assert stored and statuses == ["failed"], statuses
        # room again (the same files on a larger disk): the same command resumes and completes
        roomy = tmp_path / "roomy"
        subprocess.run(["cp", "-a", f"{small_disk}/.", str(roomy)], check=True)
        again = process(roomy)
    assert again.returncode == 0, f"seed {seed}: {again.stdout}\n{again.stderr}"
    assert json.loads((tmp_path / "run" / "run.json").read_text())["certificate_id"]
