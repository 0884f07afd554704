"""Campaigns: two flights of one camera share one certificate; a campaign's cron schedule becomes a
Prefect deployment."""

from __future__ import annotations

import pytest

SEEDS = (3, 4)
CRON = "0 3 * * *"


@pytest.fixture(scope="module")
def campaign(tmp_path_factory, prefect_server):
    """Two 16-image flights of the NEC TS9260 (different seeds, same day) in campaign "seneca" with a cron
    schedule, in a fresh SQLite database."""
    from aerocal.simulate import simulate_flight, write_flight
    from flows.campaign import add_flights

    root = tmp_path_factory.mktemp("campaign")
    dirs = []
    for i, seed in enumerate(SEEDS):
        sim = simulate_flight("conte-calibration", seed=seed, effects={"thermal_focal": 0.06}, max_images=16)
        dirs.append(write_flight(sim, root / f"flight-{i + 1}", mode="observations"))
    url, art = f"sqlite:///{root / 'aerocal.db'}", str(root / "artifacts")
    names = add_flights("seneca", dirs, cron=CRON, database_url=url, artifact_root=art)
    assert names == ["flight-1", "flight-2"]
    return {"root": root, "url": url, "artifacts": art}


def test_second_flight_reuses_the_first_flights_certificate(campaign):
    from flows.campaign import run_campaign
    from storage.database import connect
    from storage.provenance import provenance

    result = run_campaign("seneca", str(campaign["root"] / "runs"), campaign["url"], campaign["artifacts"])
    first, second = result.runs
    assert first.flight == "flight-1" and second.flight == "flight-2"
    assert "calibrate" in first.steps and "calibrate" not in second.steps, (first.steps, second.steps)
    assert second.certificate_id == first.certificate_id
    db = connect(campaign["url"])
    with db.session() as session:
        prov1 = provenance(session, first.run_id).to_dict()
        prov2 = provenance(session, second.run_id).to_dict()
    db.dispose()
    assert "self-calibration" in prov1["certificate"]["reason"]
    assert prov2["certificate"]["id"] == first.certificate_id
    assert "newest applicable certificate" in prov2["certificate"]["reason"], prov2["certificate"]["reason"]
    # the certificate document the second run adjusted with is an input of its adjustment step
    assert first.outputs["certificate"] == second.outputs["certificate"]
    assert (campaign["root"] / "runs" / "flight-2" / "report.html").is_file()


def test_campaign_schedule_becomes_a_deployment(campaign):
    from prefect.client.orchestration import get_client

    from flows.campaign import campaign_deployment_name, register_campaign_deployments

    deployments = register_campaign_deployments(campaign["url"], campaign["artifacts"])
    assert len(deployments) == 1
    with get_client(sync_client=True) as client:
        dep = client.read_deployment_by_name(f"run-campaign/{campaign_deployment_name('seneca')}")
    assert dep.parameters["campaign"] == "seneca"
    assert dep.entrypoint == "flows.campaign.run_campaign"
    assert dep.parameters["database_url"] == campaign["url"]
    crons = [s.schedule.cron for s in dep.schedules]
    assert crons == [CRON], crons
    assert all(s.active for s in dep.schedules)
