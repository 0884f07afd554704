"""The run repository: one row per flow run, with its configuration, code version, timings and certificate.

These functions add and change rows in the caller's session; the caller commits (a flow commits at the
end of each step, so a crash loses at most the step in progress).
"""

from __future__ import annotations

import functools
import json
import os
import socket
import subprocess
from datetime import datetime
from importlib import metadata
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from aerocal.io import plain_json
from storage.errors import NotFoundError, StorageError
from storage.models import RUN_STATUSES, Campaign, Certificate, Flight, Run, utcnow


@functools.lru_cache(maxsize=1)
def current_code_version() -> str:
    """``aerocal <version>`` plus the git commit (``+g<hash>``, ``-dirty``) when run from a checkout."""
    try:
        version = metadata.version("aerocal")
    except metadata.PackageNotFoundError:
        version = "unknown"
    repo = Path(__file__).resolve().parents[1]
    try:
        out = subprocess.run(
            ["git", "-C", str(repo), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return f"aerocal {version}"
    commit = out.stdout.strip() if out.returncode == 0 else ""
    return f"aerocal {version}+g{commit}" if commit else f"aerocal {version}"


def to_json(value: Any) -> Any:
    """``value`` as plain JSON types (:func:`aerocal.io.plain_json`); a value of another type raises
    :class:`StorageError` naming it."""
    try:
        return plain_json(value)
    except TypeError as exc:
        raise StorageError(f"configuration {exc}") from None


def get_run(session: Session, run_id: str) -> Run:
    """The run with this id; :class:`NotFoundError` when there is none."""
    run = session.get(Run, str(run_id))
    if run is None:
        raise NotFoundError(f"run {run_id!r} not found; list them with `aerocal runs list`")
    return run


def _flight_id(session: Session, flight: Flight | int | str | None) -> int | None:
    if flight is None or isinstance(flight, int):
        return flight
    if isinstance(flight, Flight):
        return flight.id
    found = session.scalars(sa.select(Flight.id).where(Flight.name == flight)).first()
    if found is None:
        raise NotFoundError(f"flight {flight!r} not found; register it first")
    return found


def _campaign_id(session: Session, campaign: Campaign | int | str | None) -> int | None:
    if campaign is None or isinstance(campaign, int):
        return campaign
    if isinstance(campaign, Campaign):
        return campaign.id
    found = session.scalars(sa.select(Campaign.id).where(Campaign.name == campaign)).first()
    if found is None:
        raise NotFoundError(f"campaign {campaign!r} not found; create it first")
    return found


def start_run(
    session: Session,
    run_id: str,
    kind: str,
    configuration: Any = None,
    code_version: str | None = None,
    flight: Flight | int | str | None = None,
    campaign: Campaign | int | str | None = None,
    started: datetime | None = None,
) -> Run:
    """Record that run ``run_id`` (the flow-run id) of ``kind`` (e.g. ``"process_flight"``) started.

    ``configuration`` (a dataclass or mapping) is stored in full as JSON; ``code_version`` defaults
    to :func:`current_code_version`. Starting a run id that exists again (a retried flow run) marks it
    running again and replaces its configuration; its timings, artifacts and lineage are kept.
    """
    config = to_json(configuration) if configuration is not None else {}
    if not isinstance(config, dict):
        config = {"value": config}
    run = session.get(Run, str(run_id))
    version = code_version or current_code_version()
    runner = this_runner()
    if run is None:
        run = Run(
            id=str(run_id),
            kind=kind,
            status="running",
            configuration=config,
            code_version=version,
            started=started or utcnow(),
            timings={},
            runner=runner,
        )
        session.add(run)
    else:
        run.kind, run.status, run.configuration, run.code_version = kind, "running", config, version
        run.ended, run.error, run.runner = None, None, runner
    if flight is not None:
        run.flight_id = _flight_id(session, flight)
    if campaign is not None:
        run.campaign_id = _campaign_id(session, campaign)
    session.flush()
    return run


def finish_run(
    session: Session,
    run_id: str,
    status: str = "completed",
    error: str | None = None,
    ended: datetime | None = None,
) -> Run:
    """Record the end of a run: ``status`` is ``completed``, ``failed`` or ``cancelled``."""
    if status not in RUN_STATUSES or status == "running":
        raise ValueError(f"run status {status!r}: use one of completed, failed, cancelled")
    run = get_run(session, run_id)
    run.status, run.error, run.ended = status, error, ended or utcnow()
    session.flush()
    return run


def record_timing(session: Session, run_id: str, step: str, seconds: float) -> None:
    """Record that ``step`` of the run took ``seconds`` (wall time); a repeated step is overwritten."""
    run = get_run(session, run_id)
    run.timings = {
        **(run.timings or {}),
        str(step): float(seconds),
    }  # reassign: plain JSON is not mutation-tracked
    session.flush()


def record_certificate(session: Session, run_id: str, certificate: Certificate | str | None, reason: str) -> None:
    """Record the certificate the run uses and why it was chosen (``None``: the flight's nominal camera, which is
    no stored certificate; the reason says so)."""
    run = get_run(session, run_id)
    if isinstance(certificate, str):
        found = session.get(Certificate, certificate)
        if found is None:
            raise NotFoundError(f"certificate {certificate!r} not found")
        certificate = found
    run.certificate_id = None if certificate is None else certificate.id
    run.certificate_reason = reason
    session.flush()


def _process_start(pid: int) -> str | None:
    """The start time of process ``pid`` in clock ticks since boot (Linux ``/proc``), or ``None``."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]  # field 22 of proc(5), after the command name


def this_runner() -> str:
    """``"host:pid:start"`` of this process."""
    pid = os.getpid()
    return f"{socket.gethostname()}:{pid}:{_process_start(pid) or ''}"


def runner_alive(runner: str | None) -> bool | None:
    """Whether the process ``runner`` names is alive: ``None`` when that cannot be told (no runner recorded,
    or another host)."""
    if not runner:
        return None
    host, _, rest = runner.partition(":")
    pid_text, _, start = rest.partition(":")
    if host != socket.gethostname() or not pid_text.isdigit():
        return None
    now = _process_start(int(pid_text))
    if now is None:
        return False
    return not start or now == start  # a reused pid has another start time


def reap_dead_runs(session: Session) -> list[Run]:
    """Record as failed every run still marked running whose process on this host is gone (killed, crashed,
    the machine restarted), with the reason and how to resume; returns them."""
    dead = []
    for run in session.scalars(sa.select(Run).where(Run.status == "running")):
        if runner_alive(run.runner) is False:
            finish_run(session, run.id, "failed", error=(
                "the process running it ended without recording an end (killed or crashed); its completed "
                "steps are kept: run the same command again to resume"))
            dead.append(run)
    return dead


def list_runs(
    session: Session, limit: int = 50, kind: str | None = None, status: str | None = None
) -> list[Run]:
    """The newest runs first, optionally of one ``kind`` or ``status``."""
    query = sa.select(Run).order_by(Run.started.desc(), Run.id)
    if kind:
        query = query.where(Run.kind == kind)
    if status:
        query = query.where(Run.status == status)
    return list(session.scalars(query.limit(limit)))


def configuration_text(run: Run) -> str:
    """The run's configuration as indented JSON."""
    return json.dumps(run.configuration, indent=2, sort_keys=True)
