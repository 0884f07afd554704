"""Where a flow keeps things and how Prefect runs: database, artifact store, Prefect home and settings.

This module does not import Prefect: :func:`quiet_prefect` must set Prefect's environment before Prefect
is first imported (its settings are read then).

* Database: ``database_url`` argument, else ``$AEROCAL_DATABASE_URL``, else the SQLite file of
  :func:`storage.database.database_url`; migrated to the newest schema on first use.
* Artifacts: ``artifact_root`` argument, else ``$AEROCAL_ARTIFACT_ROOT``, else ``artifacts/`` beside a
  SQLite database file the user chose, else :func:`storage.artifacts.default_artifact_root`.
* Prefect: with ``PREFECT_API_URL`` unset, the first flow run starts Prefect's temporary local server
  (SQLite under ``PREFECT_HOME``); with it set (e.g. the compose file's Prefect server backed by
  PostgreSQL), flow runs are recorded there.
* Dask: a ``LocalCluster`` per step that needs one, or the scheduler at ``--dask ADDRESS``.
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass
from pathlib import Path

#: environment that keeps Prefect local and quiet unless the user set otherwise
PREFECT_DEFAULTS = {
    "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
    "DO_NOT_TRACK": "1",
    "PREFECT_LOGGING_LEVEL": "WARNING",
    "PREFECT_UI_ENABLED": "false",
    "DASK_LOGGING__DISTRIBUTED": "warning",  # Dask's per-worker INFO lines drown the progress otherwise
    # Prefect waits 20 s for its temporary server; a busy 2-core machine has taken longer to start it
    "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "180",
    # a failed step is one line on the console (the command's own message); the traceback goes to Prefect's
    # API log and the run folder's aerocal-error.log, not 40-80 lines on the terminal
    "PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL": "CRITICAL",
    "PREFECT_LOGGING_HANDLERS_CONSOLE_FLOW_RUNS_LEVEL": "CRITICAL",
    "PREFECT_LOGGING_HANDLERS_CONSOLE_TASK_RUNS_LEVEL": "CRITICAL",
}


def quiet_prefect(home: str | Path | None = None) -> None:
    """Set Prefect's analytics off and logging to warnings (unless already set); with ``home``, put
    ``PREFECT_HOME`` (Prefect's profiles and its temporary server's database) there. Call before Prefect
    is imported."""
    for key, value in PREFECT_DEFAULTS.items():
        os.environ.setdefault(key, value)
    if home is not None:
        Path(home).mkdir(parents=True, exist_ok=True)
        os.environ["PREFECT_HOME"] = str(Path(home).resolve())


@dataclass(frozen=True)
class StorageLocation:
    """The database URL and the artifact root a flow run uses."""

    database_url: str
    artifact_root: str

    def describe(self) -> dict[str, str]:
        # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
        from storage.database import mask_url

        return {"database": mask_url(self.database_url), "artifacts": self.artifact_root}


_migrated: set[str] = set()


#: passwords of database URLs given on the command line, by reference (this process only)
_PASSWORDS: dict[str, str] = {}
_SECRET_PREFIX = "aerocal-secret-"


def conceal_password(url: str | None) -> str | None:
    """``url`` with its password replaced by a reference that only this process can resolve
    (:func:`reveal_password`). Flow parameters are recorded by Prefect's server, so a password must never be
    one: the commands pass the concealed URL and :func:`resolve_storage` resolves it."""
    if not url:
        return url
    # lazy: SQLAlchemy costs ~0.15-0.5 s CPU at start-up; --help must not pay it
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        parsed = make_url(url)
    except ArgumentError:
        return url  # not a URL: resolve_storage's own error names it
    if not parsed.password or str(parsed.password).startswith(_SECRET_PREFIX):
        return url

    token = _SECRET_PREFIX + secrets.token_hex(8)
    _PASSWORDS[token] = str(parsed.password)
    return parsed.set(password=token).render_as_string(hide_password=False)


def reveal_password(url: str | None) -> str | None:
    """The URL :func:`conceal_password` concealed; raises ``ValueError`` when its password is not known here."""
    if not url or _SECRET_PREFIX not in url:
        return url
    # lazy: SQLAlchemy costs ~0.15-0.5 s CPU at start-up; --help must not pay it
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    token = str(parsed.password or "")
    if token not in _PASSWORDS:
        raise ValueError(
            "the database URL's password was given to another process; set AEROCAL_DATABASE_URL in this "
            "process's environment instead"
        )
    return parsed.set(password=_PASSWORDS[token]).render_as_string(hide_password=False)


def resolve_storage(
    database_url: str | None = None, artifact_root: str | Path | None = None, migrate: bool = True
) -> StorageLocation:
    """The storage a flow uses (see the module docstring); the database is migrated to the newest schema
    once per process."""
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage.artifacts import default_artifact_root
    from storage.database import database_url as default_url
    from storage.migrations import upgrade

    url = reveal_password(database_url) or default_url()
    if artifact_root:
        root = str(Path(artifact_root).resolve())
    else:
        root = str(_artifacts_beside(url) or default_artifact_root())
    if migrate and url not in _migrated:
        upgrade(url)
        _migrated.add(url)
    return StorageLocation(url, root)


def _artifacts_beside(url: str) -> Path | None:
    """``artifacts/`` beside a SQLite database file the user chose (not the default one), when
    ``$AEROCAL_ARTIFACT_ROOT`` is unset: the step cache follows the store the user named instead of going
    to the home data folder."""
    if os.environ.get("AEROCAL_ARTIFACT_ROOT", "").strip():
        return None
    # lazy: storage and SQLAlchemy cost ~0.5 s CPU at start-up; --help must not pay them
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    from storage.database import default_sqlite_path

    try:
        parsed = make_url(url)
    except ArgumentError:
        return None
    path = parsed.database or ""
    if parsed.get_backend_name() != "sqlite" or not path or path == ":memory:" or path.startswith("file:"):
        return None
    folder = Path(path).expanduser().resolve().parent
    return None if folder == default_sqlite_path().resolve().parent else folder / "artifacts"


def demo_environment(out: str | Path) -> dict[str, str]:
    """Database, artifact root and Prefect home of a demo writing to ``out`` (environment wins for the first
    two). Sets ``PREFECT_HOME``; call before Prefect is imported for it to take effect."""
    out = Path(out).resolve()
    quiet_prefect(out / "prefect")
    return {
        "database_url": os.environ.get("AEROCAL_DATABASE_URL") or f"sqlite:///{out / 'aerocal.db'}",
        "artifact_root": os.environ.get("AEROCAL_ARTIFACT_ROOT") or str(out / "artifacts"),
    }
