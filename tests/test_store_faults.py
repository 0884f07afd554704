"""The certificate store's PostgreSQL server dropping the run's connections midway, as a restarted server or a
database administrator's ``pg_terminate_backend`` does: `aerocal process` goes on with new connections, and the
store holds the run completed with its certificate, nothing half-written."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import sqlalchemy as sa

pytest_plugins = ["conftest_storage"]

AEROCAL = str(Path(sys.executable).with_name("aerocal"))


def _terminate(url: str) -> int:
    """Terminate every connection `aerocal` holds to the database of ``url``; how many were."""
    from conftest_storage import require_postgres

    name = sa.engine.make_url(url).database
    admin = sa.create_engine(require_postgres(), isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as conn:
            rows = conn.execute(sa.text("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = :d "
                                        "AND application_name = 'aerocal'"), {"d": name}).all()
    finally:
        admin.dispose()
    return sum(bool(r[0]) for r in rows)


def test_connections_dropped_during_a_run_are_replaced_and_the_run_is_stored_whole(request, tmp_path):
    from conftest_storage import create_postgres_database
    from prefect_harness import prefect_harness

    from aerocal.simulate import simulate_flight, write_flight
    from storage.migrations import upgrade

    url = create_postgres_database(request.config, "dropped")
    upgrade(url)
    seed = 52
    folder = write_flight(simulate_flight("conte-calibration", seed=seed, max_images=24), tmp_path / "flight",
                          mode="observations")
    with prefect_harness():
        from prefect.settings import PREFECT_API_URL

        env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "COLUMNS": "200", "PYTHONUNBUFFERED": "1"}
        args = [AEROCAL, "process", str(folder), "--certificate", "none", "--out", str(tmp_path / "run"),
                "--database-url", url, "--artifacts", str(tmp_path / "art")]
        run = subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        lines, dropped = [], {}
        for line in run.stdout:
            lines.append(line)
            for step in ("calibrate", "diagnose"):  # twice: after the run is recorded, and again later
                if line.rstrip().endswith(f"flight: {step}") and step not in dropped:
                    dropped[step] = _terminate(url)
        code = run.wait(timeout=900)
    output = "".join(lines)
    assert dropped.get("calibrate", 0) >= 1, (dropped, output)  # the run held a connection, and lost it
    assert code == 0, f"seed {seed}: exit {code} after {dropped} connections were dropped:\n{output}"
    summary = json.loads((tmp_path / "run" / "run.json").read_text())
    listed = subprocess.run([AEROCAL, "runs", "show", summary["run_id"], "--database-url", url, "--json"],
                            capture_output=True, text=True, env=env, timeout=120)
    assert listed.returncode == 0, listed.stdout + listed.stderr
    shown = json.loads(listed.stdout)
    assert shown["status"] == "completed" and shown["ended"] and not shown["error"], shown
    assert shown["certificate"]["id"] == summary["certificate_id"], shown  # the certificate it made, stored
