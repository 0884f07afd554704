"""Alembic environment of aerocal's database (run by :mod:`storage.migrations`, no alembic.ini needed).

The connection comes from ``config.attributes["connection"]`` (set by :func:`storage.migrations.upgrade`
and friends); when Alembic is run from its own command line instead, the URL comes from the
``sqlalchemy.url`` option or :func:`storage.database.database_url`. SQLite migrations run in batch mode
(copy-and-move), which is how SQLite alters tables.
"""

from __future__ import annotations

from alembic import context

from storage.database import connect
from storage.models import Base

config = context.config
target_metadata = Base.metadata


def _run(connection) -> None:
    context.configure(
        connection=connection,
        target_metadata=target_metadata,
        render_as_batch=connection.dialect.name == "sqlite",
        compare_type=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_offline() -> None:
    """Emit the SQL to stdout (``alembic upgrade --sql``)."""
    context.configure(
        url=config.get_main_option("sqlalchemy.url"),
        target_metadata=target_metadata,
        literal_binds=True,
        render_as_batch=True,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    db = connect(config.get_main_option("sqlalchemy.url") or None)
    try:
        with db.engine.begin() as conn:
            _run(conn)
    finally:
        db.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
