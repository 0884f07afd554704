"""Fixtures of the storage tests: every test runs on SQLite (a temporary file) and on PostgreSQL.

PostgreSQL: the server at 127.0.0.1:5432 (trust authentication, user ``postgres`` or ``root``), or the
administrative URL in ``AEROCAL_TEST_POSTGRES_URL``. One database with a unique name is created per
test session (migrated once) and dropped at the end; tests that need an empty database get their own.
When the server cannot be reached the PostgreSQL half of the tests is skipped, or fails when the
environment variable ``CI`` is set (CI must test both engines).

Fixtures:

* ``empty_database_url`` -- URL of an empty database (never migrated).
* ``storage_url`` -- URL of a database migrated to head (SQLite: fresh per test; PostgreSQL: shared by
  the session, so tests use their own camera serials and run ids, see ``unique``).
* ``storage_db`` -- a connected :class:`storage.database.Database` on ``storage_url``.
* ``unique`` -- a short random suffix for names that must not collide within the session.
* ``make_certificate`` -- :func:`certificate_document`, a factory of valid certificate documents.

Test modules load them with ``pytest_plugins = ["conftest_storage"]``.

The state is kept at module level, so importing these fixtures into several test modules still
creates one PostgreSQL database per session.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator

import pytest
import sqlalchemy as sa
from sqlalchemy.engine import URL, make_url

ADMIN_URL_ENV = "AEROCAL_TEST_POSTGRES_URL"
_CANDIDATES = (
    "postgresql+psycopg://postgres@127.0.0.1:5432/postgres",
    "postgresql+psycopg://root@127.0.0.1:5432/postgres",
)
ENGINES = ("sqlite", "postgresql")

_state: dict[str, object] = {}


def _admin_url() -> URL | None:
    """A working administrative PostgreSQL URL (cached), or ``None`` with the reason in ``_state``."""
    if "admin" in _state:
        return _state["admin"]  # type: ignore[return-value]
    candidates = [os.environ[ADMIN_URL_ENV]] if os.environ.get(ADMIN_URL_ENV) else list(_CANDIDATES)
    reasons = []
    for text in candidates:
        url = make_url(text)
        if url.drivername in ("postgresql", "postgres"):
            url = url.set(drivername="postgresql+psycopg")
        engine = sa.create_engine(url, isolation_level="AUTOCOMMIT", connect_args={"connect_timeout": 3})
        try:
            with engine.connect() as conn:
                conn.exec_driver_sql("SELECT 1")
            _state["admin"] = url
            return url
        except sa.exc.DBAPIError as exc:
            reasons.append(f"{url.render_as_string(hide_password=True)}: {' '.join(str(exc.orig).split())}")
        finally:
            engine.dispose()
    _state["admin"] = None
    _state["admin_error"] = "; ".join(reasons)
    return None


def require_postgres() -> URL:
    """The administrative URL; skip (or fail under CI) when no PostgreSQL server answers."""
    url = _admin_url()
    if url is None:
        message = (
            f"postgres server not reachable ({_state.get('admin_error')}); "
            f"start PostgreSQL on 127.0.0.1:5432 or set {ADMIN_URL_ENV}"
        )
        if os.environ.get("CI"):
            pytest.fail(f"{message} -- CI is set, so the PostgreSQL storage tests must run", pytrace=False)
        pytest.skip(message)  # postgres unreachable outside CI only
    return url


def create_postgres_database(config: pytest.Config, purpose: str) -> str:
    """Create a database with a unique name, dropped when the session ends; return its URL."""
    admin = require_postgres()
    name = f"aerocal_test_{purpose}_{os.getpid()}_{secrets.token_hex(4)}"
    engine = sa.create_engine(admin, isolation_level="AUTOCOMMIT")
    try:
        with engine.connect() as conn:
            conn.exec_driver_sql(f'CREATE DATABASE "{name}"')
    finally:
        engine.dispose()

    def drop() -> None:
        dropper = sa.create_engine(admin, isolation_level="AUTOCOMMIT")
        try:
            with dropper.connect() as conn:
                conn.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        finally:
            dropper.dispose()

    config.add_cleanup(drop)
    return admin.set(database=name).render_as_string(hide_password=False)


@pytest.fixture(params=ENGINES)
def empty_database_url(request: pytest.FixtureRequest, tmp_path) -> str:
    """URL of an empty database (SQLite file in tmp_path, or a new PostgreSQL database)."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'empty.db'}"
    return create_postgres_database(request.config, "empty")


@pytest.fixture(params=ENGINES)
def storage_url(request: pytest.FixtureRequest, tmp_path) -> str:
    """URL of a database at the head revision."""
    from storage.migrations import upgrade

    if request.param == "sqlite":
        url = f"sqlite:///{tmp_path / 'aerocal.db'}"
        upgrade(url)
        return url
    if "session_db" not in _state:
        url = create_postgres_database(request.config, "session")
        upgrade(url)
        _state["session_db"] = url
    return _state["session_db"]  # type: ignore[return-value]


@pytest.fixture
def storage_db(storage_url: str) -> Iterator[object]:
    """A connected :class:`storage.database.Database` on ``storage_url``, disposed after the test."""
    from storage.database import connect

    db = connect(storage_url)
    try:
        yield db
    finally:
        db.dispose()


@pytest.fixture
def unique() -> str:
    """A random suffix (8 hex digits) for camera serials, run ids and flight names."""
    return secrets.token_hex(4)


def certificate_document(
    serial: str,
    calibration_date: str = "2016-03-14",
    temperature_range: tuple[float, float] | None = (21.0, 21.0),
    thermal_range: tuple[float, float] | None = None,
    make: str = "NEC",
    model: str = "TS9260",
    issued: str | None = None,
    f: float = 1668.0,
) -> dict:
    """A certificate document of schema ``aerocal.certificate/1`` for a 640x480 thermal camera.

    ``temperature_range`` is the calibration flight's sensor temperature range (degC);
    ``thermal_range`` adds a linear thermal model valid over that range.
    """
    names = ["f", "cx", "cy", "k1"]
    thermal = None
    if thermal_range is not None:
        thermal = {
            "kind": "linear",
            "t0": 20.0,
            "df_dt": 0.21,
            "dcx_dt": 0.0,
            "dcy_dt": 0.0,
            "valid_range": list(thermal_range),
            "sigmas": {"df_dt": 0.02},
        }
    return {
        "schema": "aerocal.certificate/1",
        "id": secrets.token_hex(16),
        "camera": {"make": make, "model": model, "serial": serial, "lens": "unknown"},
        "version": None,
        "supersedes": None,
        "issued": issued or f"{calibration_date}T18:00:00Z",
        "model": {
            "kind": "brown",
            "width": 640,
            "height": 480,
            "pixel_size_mm": 0.0235,
            "params": {
                "f": f,
                "cx": 320.4,
                "cy": 240.7,
                "k1": -0.012,
                "k2": 0.0,
                "k3": 0.0,
                "p1": 0.0,
                "p2": 0.0,
                "b1": 0.0,
                "b2": 0.0,
            },
        },
        "sigmas": {"f": 0.8, "cx": 0.5, "cy": 0.5, "k1": 0.001},
        "estimated": names,
        "correlation": {
            "names": names,
            "matrix": [[1.0 if i == j else 0.1 for j in range(4)] for i in range(4)],
        },
        "significance": {},
        "thermal": thermal,
        "conditions": {
            "date": calibration_date,
            "temperature_range": None if temperature_range is None else list(temperature_range),
            "n_images": 44,
            "strips": 5,
            "transversal_strip": True,
            "n_gcp": 4,
            "priors": {},
            "images": [],
        },
        "quality": {"sigma0": 0.93, "reprojection_rms_px": 0.41, "dof": 5120},
        "provenance": {"flow_run": None, "code_version": "test", "inputs": {}},
    }


@pytest.fixture
def make_certificate():
    """The :func:`certificate_document` factory (a fixture, so test modules need not import this module)."""
    return certificate_document
