"""Commands for the database: ``aerocal init`` and the ``aerocal db`` group (``upgrade``, ``downgrade``,
``current``), and :func:`open_database`, which the certificate and run commands connect through.

SQLAlchemy and the storage layer take about 0.2 s to import: they are imported inside the commands, so that
``aerocal --help`` does not pay for them.
"""

from __future__ import annotations

import os
from pathlib import Path

import typer

from flows.cli.console import console
from flows.cli.errors import fail, user_errors
from flows.cli.help_text import command
from flows.cli.options import ARTIFACT_ROOT_OPTION, DATABASE_URL_OPTION
from flows.environment import resolve_storage

db_app = typer.Typer(
    help="Database schema migrations: upgrade, downgrade, current.\n\n"
    "The database holds cameras, certificates, flights, campaigns and runs: SQLite (a file) or PostgreSQL, "
    "given by --database-url or $AEROCAL_DATABASE_URL.\n\n"
    "Example: aerocal db current",
    no_args_is_help=True,
)


def open_database(url: str | None, migrated: bool = True):  # -> storage.database.Database
    """Connect to the database at ``url`` (default: :func:`storage.database.database_url`); use it as
    ``with open_database(url) as db:`` so that its connections are closed when the command ends.

    With ``migrated``, the database must exist at the newest schema. A command that only reads never creates
    a SQLite file (a mistyped path, or no database configured yet, is said, not made).
    """
    # lazy: storage and SQLAlchemy cost ~0.5 s CPU at start-up; --help must not pay them
    from sqlalchemy.engine import make_url

    from storage.database import connect, database_url
    from storage.errors import DatabaseURLError
    from storage.migrations import require_current

    if migrated:
        parsed = make_url(url or database_url())
        path = parsed.database or ""
        if parsed.get_backend_name() == "sqlite" and path and path != ":memory:" and not path.startswith("file:") \
                and not Path(path).expanduser().exists():
            raise DatabaseURLError(
                f"no database at {path}: run `aerocal db upgrade` (or `aerocal init`) to create it, or give the "
                "right --database-url / AEROCAL_DATABASE_URL"
            )
    db = connect(url)
    if migrated:
        try:
            require_current(db)
        except BaseException:
            db.dispose()
            raise
    return db


def init(
    database_url: str | None = DATABASE_URL_OPTION,
    artifact_root: Path | None = ARTIFACT_ROOT_OPTION,
) -> None:
    """Create the database; show where everything is kept.

    Creates or migrates the database to the newest schema and prints where the database, the artifact store
    and the Prefect API are.

    Example: aerocal init

    Example: aerocal init --database-url postgresql://aerocal@localhost/aerocal --artifacts /data/artifacts
    """
    with user_errors():
        where = resolve_storage(database_url, artifact_root)
    for key, value in where.describe().items():
        console.print(f"{key:>10}: {value}")
    api = os.environ.get("PREFECT_API_URL")
    console.print(f"{'prefect':>10}: {api or 'temporary local server per command (PREFECT_API_URL unset)'}")


@command(db_app, "upgrade")
def db_upgrade(
    revision: str = typer.Option("head", "--revision", help="Revision to migrate to."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Create the database or migrate its schema up to a revision.

    The revision is the newest one unless --revision says otherwise.

    Example: aerocal db upgrade

    Example: aerocal db upgrade --database-url postgresql+psycopg://aerocal@localhost/aerocal
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage import migrations

    with user_errors():
        with open_database(database_url, migrated=False) as db:
            before = migrations.current(db)
            migrations.upgrade(db, revision)
            after = migrations.current(db)
    console.print(f"database {db.masked_url}: {before or 'empty'} -> {after or 'empty'}")


@command(db_app, "downgrade")
def db_downgrade(
    revision: str = typer.Argument(..., help="Revision to migrate down to; 'base' drops every aerocal table."),
    yes: bool = typer.Option(False, "--yes", help="Do not ask for confirmation."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Migrate the schema down to a revision; dropped data is lost.

    Asks for confirmation unless --yes is given.

    Example: aerocal db downgrade base --yes --database-url sqlite:///scratch.db
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage import migrations

    with user_errors():
        with open_database(database_url, migrated=False) as db:
            before = migrations.current(db)
            if not yes and not typer.confirm(f"migrate {db.masked_url} from {before} down to {revision}?"):
                fail("downgrade cancelled; pass --yes to skip the question")
            migrations.downgrade(db, revision)
            after = migrations.current(db)
    console.print(f"database {db.masked_url}: {before or 'empty'} -> {after or 'empty'}")


@command(db_app, "current")
def db_current(database_url: str | None = DATABASE_URL_OPTION) -> None:
    """Show the database's schema revision and the newest known.

    Example: aerocal db current

    Example: aerocal db current --database-url sqlite:///aerocal.db
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage import migrations

    with user_errors():
        with open_database(database_url, migrated=False) as db:
            revision = migrations.current(db)
        head = migrations.head()
    if revision is None:
        console.print(f"database {db.masked_url}: empty (head is {head}); run `aerocal db upgrade`")
    elif revision == head:
        console.print(f"database {db.masked_url}: {revision} (head)")
    else:
        console.print(f"database {db.masked_url}: {revision} (head is {head}); run `aerocal db upgrade`")
