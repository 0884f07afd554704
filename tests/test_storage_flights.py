"""Flights, campaigns and runs repositories, on SQLite and PostgreSQL."""

from __future__ import annotations

import dataclasses
from datetime import date
from pathlib import Path

import numpy as np
import pytest

from storage.cameras import CameraIdentity
from storage.errors import NotFoundError
from storage.flights import create_campaign, get_campaign, list_flights, register_flight
from storage.runs import finish_run, get_run, list_runs, start_run

pytest_plugins = ["conftest_storage"]  # fixtures: storage_url, storage_db, unique


@dataclasses.dataclass(frozen=True)
class _Config:
    tile_px: int = 1024
    ratio: float = 0.8
    out: Path = Path("/data/out")
    weights: np.ndarray = dataclasses.field(default_factory=lambda: np.array([1.0, 0.5]))


def test_campaign_groups_flights_of_a_camera_with_a_schedule(storage_db, unique):
    camera = CameraIdentity("DJI", "H20T", f"1ZN-{unique}")
    with storage_db.session() as session:
        for name, day in ((f"forest-1-{unique}", "2021-06-02"), (f"forest-2-{unique}", "2021-06-09")):
            register_flight(
                session,
                name,
                day,
                camera,
                crs="EPSG:32633",
                n_images=120,
                bbox=(400000, 5500000, 400800, 5500600),
                area="forest",
            )
        # re-registering updates in place (ingest learns the image count later)
        register_flight(session, f"forest-2-{unique}", "2021-06-09", camera, crs="EPSG:32633", n_images=131)
        create_campaign(
            session,
            f"forest-{unique}",
            cron="0 3 * * 1",
            flights=[f"forest-1-{unique}", f"forest-2-{unique}"],
        )
        create_campaign(session, f"forest-{unique}", cron="0 3 * * 1", flights=[f"forest-1-{unique}"])
        session.commit()
    with storage_db.session() as session:
        campaign = get_campaign(session, f"forest-{unique}")
        assert campaign.cron == "0 3 * * 1"
        assert [f.name for f in campaign.flights] == [f"forest-1-{unique}", f"forest-2-{unique}"]
        flights = list_flights(session, camera)
        assert [(f.date, f.n_images) for f in flights] == [(date(2021, 6, 2), 120), (date(2021, 6, 9), 131)]
        assert flights[0].camera.label == f"DJI H20T s/n 1ZN-{unique}"
        with pytest.raises(ValueError, match="five fields"):
            create_campaign(session, f"bad-{unique}", cron="daily")
        with pytest.raises(NotFoundError, match="register it first"):
            create_campaign(session, f"other-{unique}", flights=[f"nowhere-{unique}"])


def test_runs_record_their_full_configuration_and_can_be_retried(storage_db, unique):
    run_id = f"run-{unique}"
    with storage_db.session() as session:
        run = start_run(
            session, run_id, "calibrate_camera", configuration=_Config(), code_version="aerocal 0.1.0"
        )
        finish_run(session, run_id, status="failed", error="adjustment diverged")
        session.commit()
        assert run.configuration == {"tile_px": 1024, "ratio": 0.8, "out": "/data/out", "weights": [1.0, 0.5]}
        start_run(session, run_id, "calibrate_camera", configuration={"tile_px": 512})  # the retry
        session.commit()
    with storage_db.session() as session:
        run = get_run(session, run_id)
        assert (run.status, run.error, run.ended, run.configuration) == (
            "running",
            None,
            None,
            {"tile_px": 512},
        )
        assert run.code_version.startswith("aerocal")
        assert run_id in [r.id for r in list_runs(session, kind="calibrate_camera", status="running")]
        with pytest.raises(ValueError, match="completed, failed, cancelled"):
            finish_run(session, run_id, status="done")
