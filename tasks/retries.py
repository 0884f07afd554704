"""Which failures a Prefect task retries: transient I/O and database trouble, never deterministic errors.

A retry helps when a file system hiccups, a database is briefly locked or unreachable, or a Dask worker
dies; it cannot help a wrong input (bad table, singular adjustment, missing file), which fails the same
way every time and should reach the user at once.
"""

from __future__ import annotations

from typing import Any

import sqlalchemy.exc

from storage.errors import DatabaseUnreachableError

#: retries of every step task, and the delays between them (seconds)
TASK_RETRIES = 2
TASK_RETRY_DELAYS_S = [2.0, 10.0]


def is_transient(exc: BaseException | None) -> bool:
    """True for failures a retry can cure: OS-level I/O errors, database operational errors (locked,
    connection lost), an unreachable database, a lost Dask worker."""
    if exc is None:
        return False
    if isinstance(exc, FileNotFoundError | IsADirectoryError | NotADirectoryError | PermissionError):
        return False  # a missing or forbidden file stays so
    if isinstance(exc, OSError | TimeoutError | ConnectionError | DatabaseUnreachableError):
        return True
    if isinstance(exc, sqlalchemy.exc.OperationalError | sqlalchemy.exc.InterfaceError):
        return True
    return type(exc).__name__ in {"KilledWorker", "CommClosedError"}


def retry_condition(task: Any, task_run: Any, state: Any) -> bool:
    """Prefect ``retry_condition_fn``: retry only transient failures (see :func:`is_transient`)."""
    try:
        state.result()
    except BaseException as exc:  # the state's own exception is what we classify
        return is_transient(exc)
    return False
