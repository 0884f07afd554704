"""Database URLs, engines and migrations, on SQLite and PostgreSQL."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext

from storage import migrations
from storage.database import (
    DatabaseOptions,
    DatabaseUnreachableError,
    DatabaseURLError,
    connect,
    database_url,
    mask_url,
)
from storage.errors import DatabaseBusyError, SchemaOutOfDateError, StorageError
from storage.models import Base, Run

pytest_plugins = ["conftest_storage"]  # fixtures: storage_url, storage_db, unique, ...

AEROCAL_TABLES = {
    "cameras",
    "certificates",
    "flights",
    "campaigns",
    "campaign_flights",
    "runs",
    "artifacts",
    "run_artifacts",
    "lineage_edges",
}


def test_default_url_is_a_sqlite_file_under_xdg_data_home(monkeypatch, tmp_path):
    monkeypatch.delenv("AEROCAL_DATABASE_URL", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert database_url() == f"sqlite:///{tmp_path / 'data' / 'aerocal' / 'aerocal.db'}"
    monkeypatch.setenv("AEROCAL_DATABASE_URL", "postgresql+psycopg://u@db.example/aerocal")
    assert database_url() == "postgresql+psycopg://u@db.example/aerocal"


def test_connect_creates_the_sqlite_folder_with_wal_and_foreign_keys(monkeypatch, tmp_path):
    monkeypatch.delenv("AEROCAL_DATABASE_URL", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    db = connect()
    try:
        assert (tmp_path / "xdg" / "aerocal").is_dir()
        with db.engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
            assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() == 30000
    finally:
        db.dispose()


def test_a_sqlite_writer_queues_behind_another_and_says_what_sqlite_cannot_do(tmp_path):
    """Every SQLite transaction takes the write lock when it begins: a process that reads, then writes, can
    no longer be overtaken between the two (in WAL mode that failed at once with "database is locked",
    whatever the busy timeout). A writer that waits longer than its timeout is told why and what to use."""
    url = f"sqlite:///{tmp_path / 'store.db'}"
    migrations.upgrade(url)
    first = connect(url)
    second = connect(url, DatabaseOptions(sqlite_busy_timeout_s=0.3))
    started = datetime(2026, 1, 1, tzinfo=UTC)
    try:
        with first.session() as holder:
            assert holder.query(Run).count() == 0  # the read takes the write lock
            with second.session() as other, pytest.raises(DatabaseBusyError) as caught:
                other.add(Run(id="waiting", kind="process_flight", status="running", started=started))
                other.commit()
            message = str(caught.value)
            assert str(tmp_path / "store.db") in message and "one process write at a time" in message
            assert "PostgreSQL" in message and "0.3 s" in message
            holder.add(Run(id="holder", kind="process_flight", status="running", started=started))
            holder.commit()
        with second.session() as other:  # the lock released, the same write goes through
            other.add(Run(id="waiting", kind="process_flight", status="running", started=started))
            other.commit()
            assert {r.id for r in other.query(Run)} == {"holder", "waiting"}
    finally:
        first.dispose()
        second.dispose()


def test_unknown_database_kind_is_one_clear_line():
    with pytest.raises(DatabaseURLError) as err:
        connect("nosuchdb://x")
    message = str(err.value)
    assert "nosuchdb://x" in message and "unknown database kind" in message
    assert "postgresql+psycopg://" in message  # the fix
    assert "\n" not in message


def test_unreachable_server_message_masks_the_password():
    url = "postgresql+psycopg://user:secret@127.0.0.1:1/x"
    with pytest.raises(DatabaseUnreachableError) as err:
        connect(url)
    message = str(err.value)
    assert "postgresql+psycopg://user:***@127.0.0.1:1/x" in message
    assert "secret" not in message
    assert "\n" not in message
    assert "check that the server runs" in message
    assert err.value.__cause__ is None and err.value.__suppress_context__  # no chained driver text


@pytest.mark.parametrize(
    ("url", "shown"),
    [
        ("postgresql+psycopg://u:p%40ss@h/db", "postgresql+psycopg://u:***@h/db"),
        ("not a url://u:topsecret@host", "not a url://u:***@host"),
    ],
)
def test_mask_url_hides_passwords_even_in_unparseable_urls(url, shown):
    assert mask_url(url) == shown


def test_plain_postgresql_urls_use_psycopg3():
    with pytest.raises(DatabaseUnreachableError) as err:
        connect("postgresql://user:pw@127.0.0.1:1/x")
    assert "postgresql+psycopg://user:***@127.0.0.1:1/x" in str(err.value)


def test_migrations_upgrade_from_empty_to_head_and_back_to_base(empty_database_url):
    assert migrations.current(empty_database_url) is None
    migrations.upgrade(empty_database_url)
    assert migrations.current(empty_database_url) == migrations.head() == "0003"
    engine = sa.create_engine(empty_database_url)
    try:
        assert AEROCAL_TABLES <= set(sa.inspect(engine).get_table_names())
        with engine.connect() as conn:
            # the schema the migrations built is the one the models describe
            diff = compare_metadata(
                MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata
            )
        assert diff == [], f"migrations and models disagree: {diff}"
        migrations.downgrade(empty_database_url, "base")
        assert migrations.current(empty_database_url) is None
        left = set(sa.inspect(engine).get_table_names()) & AEROCAL_TABLES
        assert left == set(), f"tables left after downgrade to base: {sorted(left)}"
        if engine.dialect.name == "postgresql":
            with engine.connect() as conn:
                functions = conn.exec_driver_sql(
                    "SELECT count(*) FROM pg_proc WHERE proname = 'aerocal_certificates_immutable'"
                ).scalar()
            assert functions == 0
        migrations.upgrade(empty_database_url)  # and up again
        assert migrations.current(empty_database_url) == "0003"
    finally:
        engine.dispose()


def test_unknown_revision_names_the_known_ones(empty_database_url):
    with pytest.raises(StorageError) as err:
        migrations.upgrade(empty_database_url, "9999")
    assert "9999" in str(err.value) and "0001" in str(err.value)


def test_require_current_tells_to_upgrade(empty_database_url):
    db = connect(empty_database_url)
    try:
        with pytest.raises(SchemaOutOfDateError, match="run `aerocal db upgrade`"):
            migrations.require_current(db)
    finally:
        db.dispose()


def test_times_come_back_timezone_aware_in_utc(storage_db, unique):
    started = datetime(2017, 5, 2, 11, 30, 15, 250000, tzinfo=timezone(timedelta(hours=2)))
    with storage_db.session() as session:
        session.add(Run(id=f"tz-{unique}", kind="test", configuration={}, timings={}, started=started))
        session.commit()
    with storage_db.session() as session:
        run = session.get(Run, f"tz-{unique}")
        assert run.started.tzinfo is not None
        assert run.started.utcoffset() == timedelta(0)
        assert run.started == started  # same instant
        assert run.started.hour == 9


def test_naive_datetimes_are_refused(storage_db, unique):
    with storage_db.session() as session:
        session.add(
            Run(
                id=f"naive-{unique}",
                kind="test",
                configuration={},
                timings={},
                started=datetime(2017, 5, 2, 11, 30),
            )
        )
        with pytest.raises(sa.exc.StatementError, match="naive datetime"):
            session.flush()
        session.rollback()
