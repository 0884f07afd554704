"""A scheduled campaign as it runs over a city: eight flights of two cameras processed four at a time, each an
`aerocal process` of its own, against one PostgreSQL certificate store. Every certificate version of a camera is
distinct and in order, each superseding the one before; no run is left running; every run's certificate is one
it made itself or one another flight had stored before it ended (chosen once the flight was matched, so
possibly stored after the run started). The same on a SQLite store (four flights at once): SQLite lets one
process write at a time, so the runs queue for the write lock instead of failing with "database is locked"."""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

pytest_plugins = ["conftest_storage"]

AEROCAL = str(Path(sys.executable).with_name("aerocal"))
#: (preset, seed) of the campaign's flights: two cameras (NEC TS9260, IGN CamLight), four flights each
FLIGHTS = [("conte-calibration", 71), ("daakir-calibration", 72), ("conte-calibration", 73),
           ("daakir-calibration", 74), ("conte-calibration", 75), ("daakir-calibration", 76),
           ("conte-calibration", 77), ("daakir-calibration", 78)]


def test_eight_flights_of_two_cameras_four_at_a_time_share_one_store(request, tmp_path):
    from conftest_storage import create_postgres_database

    from storage.migrations import upgrade

    url = create_postgres_database(request.config, "campaign")
    upgrade(url)
    _check_campaign(url, FLIGHTS, tmp_path)


def test_four_flights_at_once_queue_for_a_sqlite_store(tmp_path):
    """Four processes on one SQLite file: every transaction takes the write lock up front, so none fails on a
    stale read snapshot (before, two of four runs stopped within 10 s on "database is locked")."""
    _check_campaign(f"sqlite:///{tmp_path / 'store.db'}", FLIGHTS[:4], tmp_path)


def _check_campaign(url: str, flights: list[tuple[str, int]], tmp_path: Path) -> None:
    from prefect_harness import prefect_harness

    from aerocal.simulate import simulate_flight, write_flight
    from storage.database import connect
    from storage.models import Certificate, Run

    folders = [write_flight(simulate_flight(preset, seed=seed, max_images=10), tmp_path / f"{preset}-{seed}",
                            mode="observations") for preset, seed in flights]
    with prefect_harness():
        from prefect.settings import PREFECT_API_URL

        env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "COLUMNS": "200"}

        def run(folder: Path) -> subprocess.CompletedProcess:
            return subprocess.run([AEROCAL, "process", str(folder), "--out", str(folder) + "-run", "--database-url",
                                   url, "--artifacts", str(tmp_path / "art"), "--no-figures"], capture_output=True,
                                  text=True, env=env, timeout=1200)

        with ThreadPoolExecutor(max_workers=4) as pool:
            done = list(pool.map(run, folders))
    for (preset, seed), d in zip(flights, done, strict=True):
        assert d.returncode == 0, f"{preset} seed {seed}: exit {d.returncode}\n{d.stdout[-3000:]}\n{d.stderr[-3000:]}"
    db = connect(url)
    try:
        with db.session() as session:
            runs = session.query(Run).all()
            certificates = session.query(Certificate).all()
            by_camera: dict[int, list] = {}
            for c in certificates:
                by_camera.setdefault(c.camera_id, []).append(c)
            chosen = {r.id: (r.ended, r.certificate_id, r.status) for r in runs}
            made_by = {c.id: c.document.get("provenance", {}).get("flow_run") for c in certificates}
            issued = {c.id: c.stored for c in certificates}
    finally:
        db.dispose()
    assert len(by_camera) == 2, {k: [c.version for c in v] for k, v in by_camera.items()}
    for versions in by_camera.values():
        versions.sort(key=lambda c: c.version)
        assert [c.version for c in versions] == list(range(1, len(versions) + 1))
        assert [c.supersedes for c in versions] == [None] + [c.id for c in versions[:-1]]
    assert len(runs) == len(flights) and {s for _, _, s in chosen.values()} == {"completed"}, chosen
    for run_id, (ended, cert_id, _) in chosen.items():
        assert cert_id is not None, run_id
        # its own certificate, or one another run had stored before this one ended
        assert made_by.get(cert_id) == run_id or (made_by.get(cert_id) in chosen and issued[cert_id] <= ended), (
            run_id, cert_id, made_by, issued)
    # the later flights reused what the first ones stored (with `--certificate auto`), as a campaign should; four
    # flights started at once all choose before any of them has stored a certificate
    if len(flights) > 4:
        reused = [run_id for run_id, (_, cert_id, _) in chosen.items() if made_by.get(cert_id) != run_id]
        assert reused, {k: [c.version for c in v] for k, v in by_camera.items()}
