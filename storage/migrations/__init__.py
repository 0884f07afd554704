"""Schema migrations of aerocal's database (Alembic, configured here: no alembic.ini needed).

>>> upgrade("sqlite:////tmp/aerocal.db")          # empty database -> head
>>> current("sqlite:////tmp/aerocal.db")
'0001'
>>> downgrade("sqlite:////tmp/aerocal.db", "base")  # back to an empty schema

Every function takes a database URL (``None``: :func:`storage.database.database_url`) or an already
connected :class:`~storage.database.Database`. Each migration command runs in one transaction on
PostgreSQL and on SQLite (whose DDL is transactional with the connection setup of
:mod:`storage.database`), so a failed migration leaves the schema as it was.
"""

from __future__ import annotations

from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy.engine import URL

from storage.database import Database, connect
from storage.errors import SchemaOutOfDateError, StorageError

MIGRATIONS_DIR = Path(__file__).resolve().parent


def alembic_config(url: str | URL | None = None) -> Config:
    """An Alembic configuration pointing at the migrations shipped in this package."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    if url is not None:
        # ConfigParser interpolation: a literal '%' (URL-encoded passwords) must be doubled.
        text = url.render_as_string(hide_password=False) if isinstance(url, URL) else str(url)
        cfg.set_main_option("sqlalchemy.url", text.replace("%", "%%"))
    return cfg


def head() -> str:
    """The newest revision the code knows."""
    revision = ScriptDirectory.from_config(alembic_config()).get_current_head()
    if revision is None:  # pragma: no cover - the package always ships revisions
        raise StorageError(f"no migrations found in {MIGRATIONS_DIR}")
    return revision


def _run(url: str | URL | Database | None, fn, revision: str) -> None:
    db = url if isinstance(url, Database) else connect(url)
    try:
        cfg = alembic_config()
        with db.engine.begin() as conn:
            cfg.attributes["connection"] = conn
            try:
                fn(cfg, revision)
            except command.util.CommandError as exc:
                raise StorageError(
                    f"database {db.masked_url}: {exc}; known revisions: base, {', '.join(_revisions())}, head"
                ) from None
    finally:
        if not isinstance(url, Database):
            db.dispose()


def _revisions() -> list[str]:
    script = ScriptDirectory.from_config(alembic_config())
    return [rev.revision for rev in reversed(list(script.walk_revisions()))]


def upgrade(url: str | URL | Database | None = None, revision: str = "head") -> None:
    """Migrate the database at ``url`` up to ``revision`` (default: the newest)."""
    _run(url, command.upgrade, revision)


def downgrade(url: str | URL | Database | None, revision: str) -> None:
    """Migrate the database at ``url`` down to ``revision`` (``"base"``: drop every aerocal table)."""
    _run(url, command.downgrade, revision)


def current(url: str | URL | Database | None = None) -> str | None:
    """The revision the database is at, ``None`` for an empty (never migrated) database."""
    db = url if isinstance(url, Database) else connect(url)
    try:
        with db.engine.connect() as conn:
            return MigrationContext.configure(conn).get_current_revision()
    finally:
        if not isinstance(url, Database):
            db.dispose()


def require_current(db: Database) -> None:
    """Raise :class:`SchemaOutOfDateError` unless the database is at :func:`head`."""
    found = current(db)
    expected = head()
    if found != expected:
        state = "empty (no aerocal tables)" if found is None else f"at revision {found}"
        raise SchemaOutOfDateError(
            f"database {db.masked_url} is {state}, this aerocal needs revision {expected}; "
            "run `aerocal db upgrade`"
        )
