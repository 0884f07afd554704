"""A Prefect server for flow tests: started once per test process and shared by every module that asks for one.

``prefect_test_harness`` starts a server subprocess for each ``with`` block (12 to 20 s on a loaded 2-core
machine) and stops it at the end; seventeen test modules asked for one, so a ``make test`` process started up to
nine. Here the first module of a process starts one (with its own SQLite database, as the harness does) and
every module then runs against it inside the harness's settings for as long as its ``with`` block lasts: the API
URL, the database, no analytics and no heartbeats; on leaving, the logs and events are drained, as the harness
does, so that nothing of one module reaches the next. The server stops at the end of the session
(``tests/conftest.py``).
"""

from __future__ import annotations

import atexit
import contextlib
import inspect
import shutil
import tempfile
from pathlib import Path

_SERVER = None
_DATABASE_URL: str | None = None


def _shared_server():
    global _SERVER, _DATABASE_URL
    from prefect.server.api.server import SubprocessASGIServer
    from prefect.settings import (
        PREFECT_SERVER_ANALYTICS_ENABLED,
        PREFECT_SERVER_DATABASE_CONNECTION_URL,
        temporary_settings,
    )
    from prefect.testing.utilities import _find_available_port

    if _SERVER is None or not _SERVER.running:
        home = tempfile.mkdtemp(prefix="aerocal-prefect-tests-")
        atexit.register(shutil.rmtree, home, True)
        _DATABASE_URL = "sqlite+aiosqlite:///" + str(Path(home) / "prefect-test.db")
        with temporary_settings({PREFECT_SERVER_DATABASE_CONNECTION_URL: _DATABASE_URL,
                                 PREFECT_SERVER_ANALYTICS_ENABLED: False}):
            server = SubprocessASGIServer(port=_find_available_port())
            server.start(timeout=180)  # a loaded 2-core machine starts it slowly
        _SERVER = server
    return _SERVER


def stop_shared_server() -> None:
    """Stop the shared server (at the end of the test session, while pytest's streams still take its last log)."""
    if _SERVER is not None and _SERVER.running:
        _SERVER.stop()


def _drain() -> None:
    """What the harness does on leaving: the log and event workers emptied, nothing carried to the next module."""
    from prefect.events.worker import EventsWorker
    from prefect.logging.handlers import APILogWorker
    from prefect.utilities.asyncutils import run_coro_as_sync

    async def drain_workers():
        try:
            result = APILogWorker.instance().drain()
            if inspect.isawaitable(result):
                await result
        except RuntimeError:  # never started
            pass
        result = EventsWorker.drain_all()
        if inspect.isawaitable(result):
            await result

    run_coro_as_sync(drain_workers())


@contextlib.contextmanager
def prefect_harness():
    import prefect.context
    from prefect.server.api.server import SubprocessASGIServer
    from prefect.server.database.dependencies import temporary_database_interface
    from prefect.settings import (
        PREFECT_API_URL,
        PREFECT_FLOWS_HEARTBEAT_FREQUENCY,
        PREFECT_SERVER_ANALYTICS_ENABLED,
        PREFECT_SERVER_DATABASE_CONNECTION_URL,
        temporary_settings,
    )

    server = _shared_server()
    prior = SubprocessASGIServer._instances.get(None)
    # code that asks for the default server during a flow run finds this one instead of starting another
    SubprocessASGIServer._instances[None] = server
    try:
        with contextlib.ExitStack() as stack:
            stack.enter_context(temporary_database_interface())
            stack.enter_context(temporary_settings({PREFECT_SERVER_DATABASE_CONNECTION_URL: _DATABASE_URL,
                                                    PREFECT_SERVER_ANALYTICS_ENABLED: False,
                                                    PREFECT_API_URL: server.api_url,
                                                    PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}))
            stack.enter_context(prefect.context._temporary_global_settings_context(
                prefect.context.get_settings_context()))
            try:
                yield
            finally:
                _drain()
    finally:
        if prior is not None:
            SubprocessASGIServer._instances[None] = prior
        else:
            SubprocessASGIServer._instances.pop(None, None)
