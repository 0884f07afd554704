"""A password given with --database-url reaches neither Prefect's stored flow-run parameters, nor the run's
record in aerocal's database, nor what the command prints.

The flow runs against a real PostgreSQL database (trust authentication: the password is accepted and not
checked, so the test can give one) and fails early on purpose (an observations-mode folder without
camera.json), which is enough: Prefect records a flow run's parameters when it is created.
"""

from __future__ import annotations

import json

from typer.testing import CliRunner

pytest_plugins = ["conftest_storage"]

PASSWORD = "s3cret-Pw-9431"


def test_a_database_password_is_never_a_flow_parameter(prefect_server, tmp_path, request):
    from conftest_storage import create_postgres_database
    from sqlalchemy.engine import make_url

    from aerocal.cli import app
    from aerocal.simulate import simulate_flight, write_flight

    url = make_url(create_postgres_database(request.config, "secret")).set(password=PASSWORD)
    url_text = url.render_as_string(hide_password=False)
    sim = simulate_flight("conte-calibration", seed=4, max_images=6)
    flight = write_flight(sim, tmp_path / "flight", mode="observations")
    (flight / "camera.json").unlink()  # the flow fails in its ingest step, after its run was recorded

    res = CliRunner().invoke(app, ["process", str(flight), "--database-url", url_text, "--artifacts",
                                   str(tmp_path / "art"), "--out", str(tmp_path / "run")])
    assert res.exit_code == 2 and "camera.json is missing" in " ".join(res.output.split()), res.output
    assert PASSWORD not in res.output

    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs()
    assert runs, "the flow run was not recorded"
    stored = json.dumps([r.parameters for r in runs], default=str)
    assert PASSWORD not in stored and "aerocal-secret-" in stored, stored

    import sqlalchemy as sa

    engine = sa.create_engine(url)
    try:
        with engine.connect() as conn:
            rows = conn.execute(sa.text("SELECT configuration, error FROM runs")).all()
    finally:
        engine.dispose()
    assert rows and PASSWORD not in json.dumps([list(r) for r in rows], default=str)
