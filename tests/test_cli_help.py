"""The command tree as a newcomer sees it: `aerocal --help` names every command and group with its one line,
`aerocal GROUP --help` every sub-command, each command's help ends with examples that parse, help never
imports Prefect, and every command ends an error the same way (one line, exit codes 1, 2 and 130)."""

from __future__ import annotations

import importlib
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import typer
from typer.core import TyperGroup
from typer.testing import CliRunner

from aerocal.cli import app
from flows.cli.errors import (
    BAD_INPUT,
    FAILED,
    INPUT_ERRORS,
    INTERRUPTED,
    STORAGE_ERRORS,
    CommandInputError,
    flow_errors,
    user_errors,
)
from flows.cli.help_text import FIRST_LINE_MAX, reflow
from storage.errors import NotFoundError

ROOT = typer.main.get_command(app)

#: what `aerocal --help` must list: every command and group, the sub-commands of each group
COMMANDS = ("ingest", "match", "process", "calibrate", "report", "serve", "init", "simulate", "diagnose", "demo")
GROUPS = {
    "campaign": ("add", "run", "list"),
    "db": ("upgrade", "downgrade", "current"),
    "certificates": ("list", "show", "export", "import"),
    "runs": ("list", "show"),
}
PANELS = ("Process flights", "Campaigns and schedules", "Certificates and storage", "Simulation and diagnosis")

#: modules help must not import: Prefect, SQLAlchemy, the flows, the storage layer (its errors included)
HEAVY = ("prefect", "sqlalchemy", "flows.process", "flows.campaign", "flows.demo", "storage.errors", "storage.database")

#: every command of the tree by its path, e.g. ("certificates", "export")
LEAVES = [(name,) for name in COMMANDS] + [(group, sub) for group, subs in GROUPS.items() for sub in subs]


def _help(*path: str, columns: int = 80) -> str:
    result = CliRunner().invoke(app, [*path, "--help"], env={"COLUMNS": str(columns)})
    assert result.exit_code == 0, result.output
    return result.output


def _command(*path: str) -> typer.core.TyperCommand | TyperGroup:
    cmd = ROOT
    for name in path:
        assert isinstance(cmd, TyperGroup)
        cmd = cmd.commands[name]
    return cmd


def _first_line(cmd: typer.core.TyperCommand | TyperGroup) -> str:
    return (cmd.help or "").split("\n\n")[0]


def _listed(output: str, name: str, line: str) -> bool:
    """Whether ``output`` has a row ``name   line`` (one terminal line, inside a rich panel)."""
    return re.search(rf"^\W*{re.escape(name)} +{re.escape(line)} *\W*$", output, re.MULTILINE) is not None


def test_the_tree_holds_every_command_and_group():
    assert set(ROOT.commands) == set(COMMANDS) | set(GROUPS)
    for group, subs in GROUPS.items():
        assert tuple(_command(group).commands) == subs


@pytest.mark.parametrize("path", [(name,) for name in (*COMMANDS, *GROUPS)] + LEAVES[len(COMMANDS):])
def test_every_first_line_is_one_short_line(path):
    line = _first_line(_command(*path))
    assert line and "\n" not in line and len(line) <= FIRST_LINE_MAX, (path, line)
    assert line.endswith("."), line


def test_top_level_help_lists_every_command_and_group_with_its_line_in_a_panel():
    output = _help()
    for name in (*COMMANDS, *GROUPS):
        assert _listed(output, name, _first_line(_command(name))), (name, output)
    for panel in PANELS:
        assert f" {panel} " in output, output
    assert "Commands" not in output  # no command left outside a panel


@pytest.mark.parametrize("group", GROUPS)
def test_each_groups_help_lists_its_commands_with_their_line(group):
    output = _help(group)
    assert _first_line(_command(group)) in output
    for sub in GROUPS[group]:
        assert _listed(output, sub, _first_line(_command(group, sub))), (group, sub, output)


def _examples(cmd: typer.core.TyperCommand | TyperGroup) -> list[str]:
    return [line.removeprefix("Example:").strip() for line in (cmd.help or "").splitlines()
            if line.startswith("Example:")]


@pytest.mark.parametrize("path", LEAVES + [(group,) for group in GROUPS] + [()])
def test_every_help_ends_with_examples_that_parse(path):
    """Each example runs the command whose help it is in, and click accepts its arguments and options."""
    cmd = _command(*path)
    last = (cmd.help or "").split("\n\n")[-1].splitlines()
    assert last and all(line.startswith("Example: ") for line in last), (path, cmd.help)
    assert "Example: aerocal" in " ".join(_help(*path, columns=200).split()) or path == ("serve",)
    for example in _examples(cmd):
        words = shlex.split(example)
        while re.fullmatch(r"[A-Z_]+=\S+", words[0]):  # an environment setting before the command
            words.pop(0)
        assert words.pop(0) == "aerocal", example
        assert tuple(words[: len(path)]) == path, (path, example)
        target = ROOT
        while isinstance(target, TyperGroup):
            name = words.pop(0)
            target = target.commands[name]
        target.make_context(name, words)  # raises a UsageError on an unknown option or a bad value


def test_help_imports_neither_prefect_nor_sqlalchemy():
    """Every help page, and `aerocal simulate` itself, in a fresh interpreter."""
    pages = [[], *[[name] for name in (*COMMANDS, *GROUPS)], *[list(path) for path in LEAVES[len(COMMANDS):]]]
    script = f"""
import json, sys
HEAVY = {HEAVY!r}
from aerocal.cli import app
for page in {pages!r}:
    try:
        app(page + ["--help"])
    except SystemExit as exit:
        assert exit.code == 0, (page, exit.code)
print(json.dumps(sorted(m for m in HEAVY if m in sys.modules)))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == [], done.stdout[-500:]


def test_simulate_imports_neither_prefect_nor_the_storage_layer(tmp_path):
    script = f"""
import json, sys
HEAVY = {HEAVY!r}
from aerocal.cli import app
try:
    app(["simulate", "conte-calibration", "--out", {str(tmp_path / "flight")!r}, "--max-images", "6"])
except SystemExit as exit:
    assert exit.code == 0, exit.code
print(json.dumps(sorted(m for m in HEAVY if m in sys.modules)))
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "COLUMNS": "200"})
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout.splitlines()[-1]) == [], done.stdout[-500:]
    assert (tmp_path / "flight" / "camera.json").is_file()


def test_the_input_errors_named_by_the_handler_exist():
    for module, name in sorted(INPUT_ERRORS | STORAGE_ERRORS):
        cls = getattr(importlib.import_module(module), name, None)
        assert isinstance(cls, type) and issubclass(cls, Exception), f"{module}.{name} is gone; update errors.py"


def _exit_of(block, raised: BaseException) -> int:
    with pytest.raises(typer.Exit) as stopped:
        with block:
            raise raised
    return stopped.value.exit_code


def test_user_errors_gives_every_command_the_same_exit_codes(tmp_path, capsys):
    class FlightTrouble(ValueError):  # not named as an input error: a failure
        pass

    assert _exit_of(user_errors(), NotFoundError("certificate 3f2a9c not found")) == FAILED
    assert _exit_of(user_errors(), FlightTrouble("the adjustment did not converge")) == FAILED
    assert _exit_of(user_errors(), CommandInputError("--subset x: no such file")) == BAD_INPUT
    assert _exit_of(user_errors("cam.yaml"), FlightTrouble("k1 is not a number")) == BAD_INPUT
    assert _exit_of(user_errors(), FileNotFoundError(2, "No such file or directory", "a.json")) == BAD_INPUT
    assert _exit_of(user_errors("b.json"), json.JSONDecodeError("Expecting value", '{\n "a": x}', 8)) == BAD_INPUT
    assert _exit_of(user_errors(), KeyboardInterrupt()) == INTERRUPTED
    lines = capsys.readouterr().err.splitlines()
    assert lines[:6] == [
        "error: certificate 3f2a9c not found",
        "error: the adjustment did not converge",
        "error: --subset x: no such file",
        "error: cam.yaml: k1 is not a number",
        "error: a.json: No such file or directory; check the path",
        "error: b.json: line 2 column 7: not valid JSON (Expecting value); fix the file there",
    ]
    assert lines[6].startswith("interrupted: ")
    with pytest.raises(RuntimeError):  # a defect keeps its traceback
        with user_errors():
            raise RuntimeError("a defect")


def test_error_lines_print_brackets_as_they_are(capsys):
    assert _exit_of(user_errors(), ValueError("image [3] of [bold]strip[/bold] 2")) == FAILED
    assert capsys.readouterr().err == "error: image [3] of [bold]strip[/bold] 2\n"


def test_a_defect_in_a_flow_run_is_one_line_naming_the_traceback_file(tmp_path, capsys):
    assert _exit_of(flow_errors(tmp_path), ZeroDivisionError("division by zero")) == FAILED
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "ZeroDivisionError: division by zero" in err and str(tmp_path) in err
    assert _exit_of(flow_errors(tmp_path), KeyboardInterrupt()) == INTERRUPTED
    assert "run the same command again to resume" in capsys.readouterr().err


def test_reflow_joins_paragraph_lines_and_keeps_examples_apart():
    doc = """First line.

    A paragraph wrapped
    in the source.

    Example: aerocal a
    Example: aerocal b
    """
    assert reflow(doc) == "First line.\n\nA paragraph wrapped in the source.\n\nExample: aerocal a\nExample: aerocal b"


def test_the_console_script_is_the_tree():
    from flows.cli.app import app as tree

    assert app is tree
    scripts = Path(__file__).resolve().parents[1] / "pyproject.toml"
    assert 'aerocal = "aerocal.cli:app"' in scripts.read_text()
