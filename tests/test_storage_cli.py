"""The storage command line (`aerocal db|certificates|runs ...`), on SQLite and PostgreSQL."""

from __future__ import annotations

import json
import sys
import types
from pathlib import Path

import pytest
from typer.testing import CliRunner

import aerocal
from flows.cli.certificates import certificates_app
from flows.cli.database import db_app
from flows.cli.runs import runs_app
from storage.certificates import issue_certificate, select_certificate
from storage.database import connect
from storage.runs import finish_run, record_timing, start_run

pytest_plugins = ["conftest_storage"]  # fixtures: storage_url, storage_db, unique, ...

WIDE = {"COLUMNS": "250"}  # rich tables do not fold ids at this width


def invoke(app, *args: str):
    return CliRunner().invoke(app, list(args), env=WIDE)


def test_db_commands_upgrade_show_and_downgrade(empty_database_url):
    url = ("--database-url", empty_database_url)
    result = invoke(db_app, "current", *url)
    assert result.exit_code == 0 and "empty (head is 0003)" in result.output
    result = invoke(db_app, "upgrade", *url)
    assert result.exit_code == 0, result.output
    assert "empty -> 0003" in result.output
    assert "0003 (head)" in invoke(db_app, "current", *url).output
    result = invoke(db_app, "downgrade", "base", "--yes", *url)
    assert result.exit_code == 0 and "0003 -> empty" in result.output


def test_commands_on_an_unmigrated_database_say_to_upgrade(empty_database_url):
    result = invoke(certificates_app, "list", "--database-url", empty_database_url)
    assert result.exit_code == 1
    assert "run `aerocal db upgrade`" in result.output
    assert len(result.output.strip().splitlines()) == 1
    if empty_database_url.startswith("sqlite:///"):  # a reading command never creates the file
        assert not Path(empty_database_url.removeprefix("sqlite:///")).exists()


@pytest.mark.parametrize("app_args", [(db_app, "current"), (certificates_app, "list"), (runs_app, "list")])
def test_bad_urls_fail_with_one_masked_line(app_args):
    app, command = app_args
    for url, shown in (
        ("nosuchdb://x", "nosuchdb://x"),
        ("postgresql+psycopg://user:secret@127.0.0.1:1/x", "postgresql+psycopg://user:***@127.0.0.1:1/x"),
    ):
        result = invoke(app, command, "--database-url", url)
        assert result.exit_code == 1
        assert shown in result.output and "secret" not in result.output
        assert len(result.output.strip().splitlines()) == 1, result.output


def test_import_list_show_and_export_json(make_certificate, storage_url, unique, tmp_path):
    url = ("--database-url", storage_url)
    serial = f"cli-{unique}"
    docs = [make_certificate(serial, "2016-03-14"), make_certificate(serial, "2017-04-02", f=1670.5)]
    for i, doc in enumerate(docs):
        path = tmp_path / f"cert{i}.json"
        path.write_text(json.dumps(doc))
        result = invoke(certificates_app, "import", str(path), *url)
        assert result.exit_code == 0, result.output
        assert f"stored certificate {doc['id']}: NEC TS9260 s/n {serial} version {i + 1}" in result.output
    assert f"supersedes {docs[0]['id']}" in result.output

    listing = invoke(certificates_app, "list", "--camera", serial, *url)
    assert listing.exit_code == 0, listing.output
    assert docs[0]["id"] in listing.output and docs[1]["id"] in listing.output
    assert "2 (latest)" in listing.output
    assert "no certificates" in invoke(certificates_app, "list", "--camera", f"none-{unique}", *url).output

    shown = invoke(certificates_app, "show", docs[1]["id"][:12], *url)
    assert shown.exit_code == 0, shown.output
    assert f"NEC TS9260 s/n {serial}" in shown.output and "1670.5" in shown.output
    assert "as written" in shown.output  # no overdispersion recorded: the sigmas are not said to be calibrated
    as_json = json.loads(invoke(certificates_app, "show", docs[1]["id"], "--json", *url).output)
    assert (as_json["version"], as_json["supersedes"]) == (2, docs[0]["id"])

    out = tmp_path / "exported.json"
    result = invoke(certificates_app, "export", docs[1]["id"], "--format", "json", "--out", str(out), *url)
    assert result.exit_code == 0, result.output
    exported = json.loads(out.read_text())
    assert exported == as_json
    assert exported["model"]["params"] == docs[1]["model"]["params"]


def test_foreign_formats_go_through_aerocal_formats(
    make_certificate, storage_url, unique, tmp_path, monkeypatch
):
    calls = []

    class Imported:
        def to_dict(self):
            doc = make_certificate("unknown", "2018-07-01")
            doc["camera"] = {"make": "unknown", "model": "unknown", "serial": "unknown", "lens": "unknown"}
            return doc

    def export_certificate(doc, fmt, path):
        calls.append(("export", doc["id"], fmt, str(path)))
        path.write_text("%YAML:1.0\n")

    def import_certificate(path, fmt=None, identity=None):
        calls.append(("import", str(path), fmt, identity))
        return Imported()

    fake = types.SimpleNamespace(export_certificate=export_certificate, import_certificate=import_certificate)
    monkeypatch.setitem(sys.modules, "aerocal.formats", fake)
    monkeypatch.setattr(aerocal, "formats", fake, raising=False)
    url = ("--database-url", storage_url)
    yaml_file = tmp_path / "camera.yaml"
    yaml_file.write_text("%YAML:1.0\n")
    # a foreign file without camera identity is refused: a certificate must name its camera
    refused = invoke(certificates_app, "import", str(yaml_file), *url)
    assert refused.exit_code == 2
    expected = "the file does not name the camera's make, model, serial; pass --make, --model, --serial"
    assert f"{yaml_file}: {expected}" in refused.output
    result = invoke(
        certificates_app,
        "import",
        str(yaml_file),
        "--format",
        "opencv",
        "--make",
        "FLIR",
        "--model",
        "Vue Pro R",
        "--serial",
        f"cli-{unique}",
        *url,
    )
    assert result.exit_code == 0, result.output
    assert f"FLIR Vue Pro R s/n cli-{unique} version 1" in result.output
    _, path, fmt, identity = calls[-1]
    assert (path, fmt, identity.serial) == (str(yaml_file), "opencv", f"cli-{unique}")
    cert_id = result.output.split("stored certificate ")[1].split(":")[0]
    out = tmp_path / "out.yaml"
    result = invoke(certificates_app, "export", cert_id, "--format", "opencv", "--out", str(out), *url)
    assert result.exit_code == 0, result.output
    assert calls[-1] == ("export", cert_id, "opencv", str(out))


def test_user_errors_are_one_line_with_the_file_and_the_fix(make_certificate, storage_url, unique, tmp_path):
    url = ("--database-url", storage_url)
    broken = tmp_path / "broken.json"
    broken.write_text('{\n  "schema": "aerocal.certificate/1",\n  "id": oops\n}\n')
    result = invoke(certificates_app, "import", str(broken), *url)
    assert result.exit_code == 2
    assert f"{broken}: line 3 column" in result.output and "not valid JSON" in result.output
    no_serial = make_certificate(f"x-{unique}")
    del no_serial["camera"]["serial"]
    path = tmp_path / "no_serial.json"
    path.write_text(json.dumps(no_serial))
    result = invoke(certificates_app, "import", str(path), *url)
    assert result.exit_code == 2 and f"{path}: the file does not name the camera's serial; pass --serial" in (
        result.output
    )
    assert len(result.output.strip().splitlines()) == 1, result.output
    result = invoke(certificates_app, "show", f"nothing{unique}", *url)
    assert (
        result.exit_code == 1
        and "not found" in result.output
        and "aerocal certificates list" in result.output
    )
    result = invoke(runs_app, "show", f"nothing-{unique}", *url)
    assert result.exit_code == 1 and "not found" in result.output
    result = invoke(certificates_app, "import", str(tmp_path / "absent.json"), *url)
    assert result.exit_code == 2 and "absent.json: no such file" in result.output


def test_runs_list_and_show_provenance(make_certificate, storage_url, unique):
    serial = f"runs-{unique}"
    run_id = f"flow-{unique}"
    db = connect(storage_url)
    try:
        with db.session() as session:
            cert = issue_certificate(session, make_certificate(serial, "2016-03-14"))
            start_run(session, run_id, "process_flight", configuration={"tile_size": 1024})
            select_certificate(session, f"NEC|TS9260|{serial}", "2017-05-02", (19.0, 23.0), run_id=run_id)
            record_timing(session, run_id, "match", 3.25)
            finish_run(session, run_id)
            session.commit()
    finally:
        db.dispose()
    url = ("--database-url", storage_url)
    listing = invoke(runs_app, "list", "--kind", "process_flight", *url)
    assert listing.exit_code == 0 and run_id in listing.output and cert.id in listing.output
    shown = invoke(runs_app, "show", run_id, *url)
    assert shown.exit_code == 0, shown.output
    assert cert.id in shown.output and "newest applicable certificate" in shown.output
    assert "tile_size" in shown.output and "3.25" in shown.output
    prov = json.loads(invoke(runs_app, "show", run_id, "--json", *url).output)
    assert prov["certificate"]["id"] == cert.id and prov["timings"] == {"match": 3.25}


def test_every_command_has_help_with_an_example():
    for app, commands in (
        (db_app, ("upgrade", "downgrade", "current")),
        (certificates_app, ("list", "show", "export", "import")),
        (runs_app, ("list", "show")),
    ):
        for command in commands:
            result = invoke(app, command, "--help")
            assert result.exit_code == 0 and "Example: aerocal" in result.output, (command, result.output)


def test_db_upgrade_does_not_make_folders_at_the_filesystem_root(tmp_path):
    missing = Path("/") / f"aerocal-no-such-folder-{tmp_path.name}"
    result = invoke(db_app, "upgrade", "--database-url", f"sqlite:///{missing / 'x.db'}")
    assert result.exit_code == 1 and f"folder {missing} does not exist" in result.output, result.output
    assert not missing.exists()
    # one new folder inside an existing one is made, as for the documented data folder
    result = invoke(db_app, "upgrade", "--database-url", f"sqlite:///{tmp_path / 'new' / 'x.db'}")
    assert result.exit_code == 0 and (tmp_path / "new" / "x.db").is_file(), result.output
