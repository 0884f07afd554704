"""Database URLs, engines and sessions for SQLite and PostgreSQL.

The database is chosen by :func:`database_url`: the environment variable ``AEROCAL_DATABASE_URL`` when
set, else a SQLite file ``$XDG_DATA_HOME/aerocal/aerocal.db`` (``~/.local/share/aerocal/aerocal.db``).
PostgreSQL is reached through psycopg 3 (``postgresql+psycopg://USER:PASSWORD@HOST:PORT/DB``; plain
``postgresql://`` and ``postgres://`` URLs are read as that).

SQLite connections are configured for several processes sharing one file: foreign keys on, WAL journal,
a busy timeout, and explicit ``BEGIN`` statements so that every transaction takes the write lock up
front (``BEGIN IMMEDIATE``) and savepoints work (the pysqlite driver's own transaction handling is
switched off, as SQLAlchemy's documentation recommends for this). A deferred transaction that reads and
then writes while another process has committed fails at once with "database is locked" in WAL mode
(its snapshot is stale; the busy timeout does not apply), so on SQLite writers queue instead: one
process writes at a time, each waiting up to the busy timeout. Concurrent flights belong on PostgreSQL.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import URL, Engine, make_url
from sqlalchemy.orm import Session, sessionmaker

from storage.errors import DatabaseBusyError, DatabaseUnreachableError, DatabaseURLError, StorageError

#: Environment variable that names the database.
URL_ENV = "AEROCAL_DATABASE_URL"

#: Execution option read by the SQLite ``begin`` hook: ``"IMMEDIATE"`` (default) or ``"DEFERRED"``.
SQLITE_BEGIN_OPTION = "aerocal_sqlite_begin"

_URL_HELP = (
    "use sqlite:///PATH or postgresql+psycopg://USER:PASSWORD@HOST:PORT/DB (or set AEROCAL_DATABASE_URL)"
)


@dataclass(frozen=True)
class DatabaseOptions:
    """How engines are built.

    Attributes:
        sqlite_busy_timeout_s: seconds a SQLite connection waits for another process's write lock
            before failing with "database is locked" (default 30 s).
        sqlite_wal: use the write-ahead-log journal on SQLite files, so readers never block the
            writer (default on).
        connect_timeout_s: seconds to wait for a PostgreSQL server to answer (default 5 s).
        check: open one connection in :func:`connect` so that a bad URL or an unreachable server
            fails there, with a clear message, instead of at the first query (default on).
        echo: log every SQL statement (default off).
    """

    sqlite_busy_timeout_s: float = 30.0
    sqlite_wal: bool = True
    connect_timeout_s: float = 5.0
    check: bool = True
    echo: bool = False


@dataclass
class Database:
    """An engine and its session factory for one database URL.

    ``sessionmaker`` makes sessions with ``expire_on_commit=False``: records returned by the
    repositories stay readable after the session commits.
    """

    url: URL
    engine: Engine
    sessionmaker: sessionmaker[Session] = field(repr=False)

    @property
    def masked_url(self) -> str:
        """The URL with its password replaced by ``***`` (safe to print)."""
        return mask_url(self.url)

    @property
    def dialect(self) -> str:
        """``"sqlite"`` or ``"postgresql"``."""
        return self.engine.dialect.name

    def session(self) -> Session:
        """A new session (use it as a context manager)."""
        return self.sessionmaker()

    def dispose(self) -> None:
        """Close every pooled connection."""
        self.engine.dispose()

    def __enter__(self) -> Database:
        """``with connect(url) as db:``: the pooled connections are closed when the block ends, however."""
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.dispose()


def default_sqlite_path() -> Path:
    """``$XDG_DATA_HOME/aerocal/aerocal.db``, with ``XDG_DATA_HOME`` defaulting to ``~/.local/share``."""
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base).expanduser() / "aerocal" / "aerocal.db"


def database_url() -> str:
    """The database URL: ``$AEROCAL_DATABASE_URL`` if set and not empty, else the default SQLite file."""
    env = os.environ.get(URL_ENV, "").strip()
    if env:
        return env
    return f"sqlite:///{default_sqlite_path()}"


_PASSWORD_IN_URL = re.compile(r"(?P<head>[a-zA-Z][\w+.-]*://[^:/@\s]*:)(?P<pw>[^@\s]*)@")


def mask_url(url: str | URL) -> str:
    """Render ``url`` with its password replaced by ``***`` (also for strings SQLAlchemy cannot parse)."""
    if isinstance(url, URL):
        return url.render_as_string(hide_password=True)
    try:
        return make_url(url).render_as_string(hide_password=True)
    except Exception:  # unparseable: mask anything between "user:" and "@"
        return _PASSWORD_IN_URL.sub(lambda m: f"{m['head']}***@", str(url))


def normalise_url(url: str | URL | None) -> URL:
    """Parse ``url`` (default :func:`database_url`) and map plain PostgreSQL URLs to the psycopg 3 driver.

    Raises :class:`DatabaseURLError` naming the (masked) URL when it cannot be parsed.
    """
    raw = database_url() if url is None else url
    if isinstance(raw, URL):
        parsed = raw
    else:
        try:
            parsed = make_url(str(raw).strip())
        except Exception:
            raise DatabaseURLError(
                f"database URL {mask_url(str(raw))!s} cannot be parsed; {_URL_HELP}"
            ) from None
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername="postgresql+psycopg")
    return parsed


def _one_line(text: str, secret: str | None) -> str:
    line = " ".join(str(text).split())
    if secret:
        line = line.replace(secret, "***")
    return line


def connect(url: str | URL | None = None, options: DatabaseOptions | None = None) -> Database:
    """Build the engine and session factory for ``url`` (default :func:`database_url`).

    A SQLite file's folder is created when missing if it is the documented data folder or one new
    folder inside an existing one (not at the filesystem root); otherwise that is an error naming it.
    With ``options.check`` (default) one connection is opened at once, so that a bad URL or an
    unreachable server raises here.

    Raises:
        DatabaseURLError: the URL cannot be parsed, names an unknown database kind, or needs a driver
            that is not installed. The message shows the URL with the password masked.
        DatabaseUnreachableError: the server does not answer, refuses the login, or the SQLite file
            cannot be opened.
    """
    options = options or DatabaseOptions()
    parsed = normalise_url(url)
    masked = mask_url(parsed)
    backend = parsed.get_backend_name()
    kwargs: dict[str, object] = {"echo": options.echo}
    if backend == "sqlite":
        kwargs["connect_args"] = {"timeout": options.sqlite_busy_timeout_s}
        database = parsed.database or ""
        if database and database != ":memory:" and not database.startswith("file:"):
            folder = Path(database).expanduser().parent
            default = folder == default_sqlite_path().parent
            at_root = folder.parent == Path(folder.anchor)
            if not folder.exists() and not default and (at_root or not folder.parent.is_dir()):
                # only the documented data folder, or one new folder inside an existing one, is created:
                # a mistyped path must not make folders at the filesystem root
                raise DatabaseURLError(
                    f"database URL {masked}: folder {folder} does not exist; create it or choose another path"
                )
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise DatabaseURLError(
                    f"database URL {masked}: cannot create folder {Path(database).parent} ({exc.strerror}); "
                    "choose a writable path"
                ) from None
    elif backend == "postgresql":
        kwargs["connect_args"] = {
            "connect_timeout": max(1, int(round(options.connect_timeout_s))),
            "application_name": "aerocal",
        }
        kwargs["pool_pre_ping"] = True
    try:
        engine = sa.create_engine(parsed, **kwargs)
    except sa.exc.NoSuchModuleError:
        raise DatabaseURLError(
            f"database URL {masked}: unknown database kind {parsed.drivername!r}; {_URL_HELP}"
        ) from None
    except ImportError as exc:
        raise DatabaseURLError(
            f"database URL {masked}: the driver for {parsed.drivername!r} is not installed ({exc.name}); "
            "use postgresql+psycopg:// for PostgreSQL"
        ) from None
    except (sa.exc.ArgumentError, TypeError, ValueError) as exc:
        raise DatabaseURLError(
            f"database URL {masked} is not valid ({_one_line(str(exc), parsed.password)}); {_URL_HELP}"
        ) from None
    if engine.dialect.name == "sqlite":
        _configure_sqlite(engine, options, parsed)
    db = Database(url=parsed, engine=engine, sessionmaker=sessionmaker(bind=engine, expire_on_commit=False))
    if options.check:
        check_connection(db)
    return db


def check_connection(db: Database) -> None:
    """Open and close one connection; raise :class:`DatabaseUnreachableError` with the cause and the fix."""
    try:
        with db.engine.connect() as conn:
            conn.exec_driver_sql("SELECT 1")
    except sa.exc.DBAPIError as exc:
        reason = _one_line(str(exc.orig) if exc.orig is not None else str(exc), db.url.password)
        if db.dialect == "sqlite":
            fix = "check that the file's folder exists and is writable"
        else:
            fix = (
                "check that the server runs, that host, port, user and database are right "
                "(create the database with `createdb`), or set AEROCAL_DATABASE_URL"
            )
        db.dispose()
        raise DatabaseUnreachableError(
            f"cannot connect to database {db.masked_url}: {reason}; {fix}"
        ) from None


def _configure_sqlite(engine: Engine, options: DatabaseOptions, url: URL) -> None:
    busy_ms = int(options.sqlite_busy_timeout_s * 1000)
    database = url.database or ""
    is_file = bool(database) and database != ":memory:" and "mode=memory" not in database

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, _record) -> None:
        # Let SQLAlchemy emit BEGIN itself (see _on_begin); pysqlite's implicit transactions
        # would otherwise defer BEGIN and break BEGIN IMMEDIATE and SAVEPOINT.
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        try:
            cursor.execute(f"PRAGMA busy_timeout = {busy_ms}")
            cursor.execute("PRAGMA foreign_keys = ON")
            if is_file and options.sqlite_wal:
                cursor.execute("PRAGMA journal_mode = WAL")
                cursor.execute("PRAGMA synchronous = NORMAL")
        finally:
            cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: sa.Connection) -> None:
        mode = conn.get_execution_options().get(SQLITE_BEGIN_OPTION, "IMMEDIATE")
        if mode not in ("DEFERRED", "IMMEDIATE", "EXCLUSIVE"):
            raise StorageError(
                f"{SQLITE_BEGIN_OPTION} must be DEFERRED, IMMEDIATE or EXCLUSIVE, not {mode!r}"
            )
        conn.exec_driver_sql(f"BEGIN {mode}")

    @event.listens_for(engine, "handle_error")
    def _on_error(context) -> None:
        if "database is locked" in str(context.original_exception):
            raise DatabaseBusyError(
                f"the SQLite store {database or ':memory:'} stayed locked by another process for longer than "
                f"{options.sqlite_busy_timeout_s:g} s: SQLite lets one process write at a time; run flights "
                "one after another on it, or give flights processed at once a PostgreSQL store "
                "(--database-url postgresql+psycopg://USER@HOST/DB); the same command then resumes"
            ) from context.sqlalchemy_exception


def begin_write(session: Session) -> None:
    """Start ``session``'s transaction as a writer.

    On SQLite this is ``BEGIN IMMEDIATE``: the write lock is taken now, so a read-then-write sequence
    (read the latest version, write the next one) cannot be overtaken by another process. Elsewhere it
    is an ordinary ``BEGIN`` (PostgreSQL code takes row locks with ``SELECT ... FOR UPDATE``).

    The session must not be inside a transaction already; commit or roll back first.
    """
    if session.in_transaction():
        raise StorageError("begin_write needs a session with no open transaction; commit or roll back first")
    bind = session.get_bind()
    if bind.dialect.name == "sqlite":
        session.connection(execution_options={SQLITE_BEGIN_OPTION: "IMMEDIATE"})
    else:
        session.connection()
