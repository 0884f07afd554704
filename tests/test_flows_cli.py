"""The platform commands of the CLI: help with an example, one-line errors naming the fix, init and report."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

COMMANDS = (
    "init",
    "process",
    "calibrate",
    "campaign add",
    "campaign run",
    "campaign list",
    "serve",
    "ingest",
    "match",
    "report",
    "demo",
)


@pytest.fixture
def run():
    from aerocal.cli import app

    runner = CliRunner()

    def invoke(*args: str):
        return runner.invoke(app, list(args))

    return invoke


@pytest.mark.parametrize("command", COMMANDS)
def test_every_platform_command_has_help_with_an_example(run, command):
    result = run(*command.split(), "--help")
    assert result.exit_code == 0, result.output
    assert "Example: aerocal" in " ".join(result.output.split()) or "Example:" in result.output, result.output


def test_top_level_help_lists_the_platform_commands(run):
    result = run("--help")
    assert result.exit_code == 0
    for name in ("init", "process", "calibrate", "campaign", "serve", "ingest", "match", "report", "demo"):
        assert name in result.output


def test_process_of_a_missing_folder_is_one_line_naming_it(run, tmp_path):
    missing = tmp_path / "no-such-flight"
    result = run("process", str(missing), "--database-url", f"sqlite:///{tmp_path / 'a.db'}")
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "no-such-flight" in lines[0] and "give a flight folder" in lines[0], (
        result.output
    )


def test_an_unknown_surface_is_one_line_naming_the_ones_there_are(run, tmp_path):
    result = run("process", str(tmp_path), "--surface", "lidar", "--database-url", f"sqlite:///{tmp_path / 'a.db'}")
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--surface lidar" in lines[0] and "dense, tie-points" in lines[0], result.output


def test_calibrate_subset_file_errors_name_the_file_and_line(run, tmp_path):
    subset = tmp_path / "subset.txt"
    subset.write_text("IMG_0001.tif\n12\n")
    flight = tmp_path / "flight"
    flight.mkdir()
    result = run(
        "calibrate", str(flight), "--subset", str(subset), "--database-url", f"sqlite:///{tmp_path / 'a.db'}"
    )
    assert result.exit_code == 2
    assert f"{subset}:2" in " ".join(result.output.split()), result.output


def test_init_creates_the_database_at_the_newest_schema(run, tmp_path):
    from storage.migrations import current, head

    url = f"sqlite:///{tmp_path / 'new.db'}"
    result = run("init", "--database-url", url, "--artifacts", str(tmp_path / "art"))
    assert result.exit_code == 0, result.output
    assert str(tmp_path / "new.db") in result.output and str(tmp_path / "art") in result.output
    assert current(url) == head()


def test_campaign_list_and_bad_cron(run, tmp_path):
    url = f"sqlite:///{tmp_path / 'c.db'}"
    result = run("campaign", "list", "--database-url", url)
    assert result.exit_code == 0 and "campaigns" in result.output
    flight = tmp_path / "flight"
    flight.mkdir()
    result = run("campaign", "add", "c1", str(flight), "--cron", "every night", "--database-url", url)
    assert result.exit_code == 2
    assert "cron 'every night'" in result.output and "five fields" in result.output, result.output


def test_report_prints_a_run_folders_figures(run, tmp_path):
    from aerocal.report.html import write_report

    write_report(tmp_path, {"flight": "flight-a", "sigma0": 1.02})
    result = run("report", str(tmp_path))
    assert result.exit_code == 0, result.output
    assert "flight-a" in result.output and "1.02" in result.output and "report.html" in result.output
    result = run("report", str(tmp_path / "nothing"))
    assert result.exit_code == 2 and "summary.json" in result.output


def test_the_step_cache_follows_a_sqlite_store_the_user_named(tmp_path, monkeypatch):
    from flows.environment import resolve_storage

    monkeypatch.delenv("AEROCAL_ARTIFACT_ROOT", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "home-data"))
    where = resolve_storage(f"sqlite:///{tmp_path / 'store' / 'a.db'}", migrate=False)
    assert where.artifact_root == str(tmp_path / "store" / "artifacts")
    default = resolve_storage(None, migrate=False)  # the documented data folder keeps its own
    assert default.artifact_root == str(tmp_path / "home-data" / "aerocal" / "artifacts")
