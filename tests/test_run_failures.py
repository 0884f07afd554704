"""A run that fails or is interrupted, as a user meets it at the terminal: one line, not a Prefect traceback;
the run folder holds a run.json that says so and how to resume, the traceback in aerocal-error.log; the
database records the run as failed or cancelled, never as running."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

AEROCAL = str(Path(sys.executable).with_name("aerocal"))
SEED = 4


def _flight(root: Path, n: int) -> Path:
    from aerocal.simulate import simulate_flight, write_flight

    return write_flight(simulate_flight("conte-calibration", seed=SEED, max_images=n), root, mode="observations")


def _statuses(db: Path) -> list[str]:
    if not db.exists():
        return []
    with sqlite3.connect(db) as conn:
        try:
            return [r[0] for r in conn.execute("SELECT status FROM runs")]
        except sqlite3.OperationalError:  # the schema is being created
            return []


def test_a_failing_run_is_one_line_and_leaves_a_run_json_that_says_so(tmp_path):
    flight = _flight(tmp_path / "flight", 6)
    camera = (flight / "camera.json").read_bytes()
    (flight / "camera.json").unlink()
    db = tmp_path / "a.db"
    done = subprocess.run([AEROCAL, "process", str(flight), "--database-url", f"sqlite:///{db}", "--artifacts",
                           str(tmp_path / "art"), "--out", str(tmp_path / "run")],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    # not a terminal: the steps started are logged on stderr, then the failure is one line
    progress = f"processing {flight}: "
    steps = [line[len(progress):] for line in done.stderr.splitlines() if line.startswith(progress)]
    lines = [line for line in (done.stdout + done.stderr).splitlines() if line.strip() and
             not line.startswith(progress)]
    assert done.returncode == 2, f"seed {SEED}: {done.stdout}\n{done.stderr}"  # bad input
    assert len(lines) == 1 and "camera.json is missing" in lines[0], lines
    assert steps == ["ingest"], steps
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["status"] == "failed" and "camera.json is missing" in run["error"] and "again" in run["resume"]
    assert "Traceback" in (tmp_path / "run" / "aerocal-error.log").read_text()
    assert _statuses(db) == ["failed"]
    # the input mended, the same command completes in the same folder: no stale error log beside its outputs
    (flight / "camera.json").write_bytes(camera)
    again = subprocess.run([AEROCAL, "process", str(flight), "--database-url", f"sqlite:///{db}", "--artifacts",
                            str(tmp_path / "art"), "--out", str(tmp_path / "run")],
                           capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert again.returncode == 0, f"seed {SEED}: {again.stdout}\n{again.stderr}"
    assert json.loads((tmp_path / "run" / "run.json").read_text())["run_id"] != run.get("run_id")
    assert not (tmp_path / "run" / "aerocal-error.log").exists(), "a failed run's log was left beside a completed run"
    assert _statuses(db) == ["failed", "completed"]


@pytest.mark.parametrize("delay_s", [1.0, 0.1])
def test_ctrl_c_stops_the_run_says_how_to_resume_and_records_it_cancelled(tmp_path, delay_s):
    """Ctrl-C inside a step, and 0.1 s into the run (a KeyboardInterrupt raised in a garbage-collection callback
    had been printed as "Exception ignored" and lost: the run went on and exited 0)."""
    # the whole 44-image flight: 20 images ran through in about 2 s once the diagnosis's twins got cheaper,
    # and the interrupt could land after the run had finished
    flight = _flight(tmp_path / "flight", 44)
    db = tmp_path / "a.db"
    proc = subprocess.Popen([AEROCAL, "process", str(flight), "--database-url", f"sqlite:///{db}", "--artifacts",
                             str(tmp_path / "art"), "--out", str(tmp_path / "run")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            env={**os.environ, "COLUMNS": "200"})
    deadline = time.monotonic() + 300
    while "running" not in _statuses(db) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert proc.poll() is None, f"the run ended before it could be interrupted: {proc.communicate()}"
    time.sleep(delay_s)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    print(f"exited {time.monotonic() - t0:.1f} s after Ctrl-C")
    assert proc.returncode == 130, f"{out}\n{err}"
    assert "interrupted" in err and "run the same command again to resume" in " ".join(err.split()), err
    assert "Traceback" not in out + err
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["status"] == "cancelled"
    assert _statuses(db) == ["cancelled"]


def test_a_killed_run_is_not_listed_as_running(tmp_path):
    """kill -9 leaves no chance to record anything: the next `aerocal runs list` finds the run's process gone
    and records it as failed, with how to resume."""
    flight = _flight(tmp_path / "flight", 20)
    db = tmp_path / "a.db"
    url = f"sqlite:///{db}"
    proc = subprocess.Popen([AEROCAL, "process", str(flight), "--database-url", url, "--artifacts",
                             str(tmp_path / "art"), "--out", str(tmp_path / "run")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=tmp_path,
                            start_new_session=True)
    deadline = time.monotonic() + 300
    while "running" not in _statuses(db) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert proc.poll() is None, "the run ended before it could be killed"
    # the run and its children (Prefect's temporary server, which would otherwise outlive the test)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=60)
    assert _statuses(db) == ["running"]  # nothing could record the end
    listed = subprocess.run([AEROCAL, "runs", "list", "--database-url", url], capture_output=True, text=True,
                            timeout=120, env={**os.environ, "COLUMNS": "250"})
    assert listed.returncode == 0, listed.stderr
    assert "ended without recording an end" in " ".join(listed.stderr.split()), listed.stderr
    assert "running" not in listed.stdout and "failed" in listed.stdout, listed.stdout
    assert _statuses(db) == ["failed"]


def test_a_run_interrupted_inside_a_database_transaction_is_still_recorded(tmp_path, monkeypatch):
    """Ctrl-C landing while a step holds SQLite's write lock (its session left open in the interrupted frame):
    the run folder says "cancelled" and how to resume, and the database records it, without waiting out the
    busy timeout (30 s) for a lock the interrupted run itself holds."""
    from sqlalchemy import text

    import flows.process as fp

    def interrupted_in_a_transaction(*args, runner, **kwargs):
        session = runner.ctx.database.session()
        session.execute(text("SELECT 1"))  # BEGIN IMMEDIATE: the write lock, held while this frame lives
        raise KeyboardInterrupt

    monkeypatch.setattr(fp, "process", interrupted_in_a_transaction)
    flight = _flight(tmp_path / "flight", 6)
    db = tmp_path / "a.db"
    with pytest.raises(KeyboardInterrupt):  # not the database's "locked" error of the wait
        fp._run_flow("process_flight", flight, tmp_path / "run", "auto", None, f"sqlite:///{db}",
                     str(tmp_path / "art"), None, None, calibrate_only=False)
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["status"] == "cancelled" and "run the same command again" in run["resume"], run
    assert _statuses(db) == ["cancelled"]


class _HalfBuilt:
    """An object Ctrl-C interrupts in its constructor, whose finalizer then fails (llvmlite's pass manager when
    the interrupt landed while numba compiled a kernel on a run's first call)."""

    def __init__(self) -> None:
        import signal as _signal

        from aerocal.pipeline.interrupts import interrupt_handler

        interrupt_handler(_signal.SIGINT, None)  # Ctrl-C arrives here
        self.handle = 1

    def __del__(self) -> None:
        self.handle  # noqa: B018 -- AttributeError: the constructor never got this far


def test_a_finalizer_failing_after_ctrl_c_prints_nothing_and_others_still_print(monkeypatch):
    """After Ctrl-C, what it left half built may fail in its finalizer, inside the run's block or later, as
    the process exits: quiet. Without Ctrl-C the same failure reaches the hook that was there before."""
    import gc

    from aerocal.pipeline.interrupts import interrupts_noted

    seen: list[type[BaseException]] = []
    monkeypatch.setattr(sys, "unraisablehook", lambda u: seen.append(u.exc_type))
    held: list[object] = []
    with pytest.raises(KeyboardInterrupt), interrupts_noted():
        try:
            _HalfBuilt()
        except KeyboardInterrupt as exc:
            held.append(exc)  # its traceback keeps the half-built object until after the block
            raise
    held.clear()
    gc.collect()
    assert seen == []

    class _Failing:
        def __del__(self) -> None:
            raise AttributeError("a defect in a finalizer")

    with interrupts_noted():
        _Failing()
        gc.collect()
    assert seen == [AttributeError]
    _Failing()
    gc.collect()
    assert seen == [AttributeError, AttributeError]
