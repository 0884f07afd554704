"""How far a flight's run has got: the step running and, for the long ones, its work done.

One listener per process, set with :func:`reporting_to` by whoever shows it (the ``aerocal`` commands put it on
their status line). :func:`aerocal.pipeline.process` announces every step as it starts, ``listener(step, 0, 0)``;
steps with countable work report ``listener(step, done, total)`` as it goes (the match step: images detected
plus pairs matched; the mosaic step: orthomosaic tiles). Calls come from the thread that runs the step (a
Prefect task's thread on the platform). Without a listener nothing is reported and nothing else changes.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator

Listener = Callable[[str, int, int], None]

_lock = threading.Lock()
_listener: Listener | None = None


@contextlib.contextmanager
def reporting_to(listener: Listener) -> Iterator[None]:
    """Send the steps' progress to ``listener(step, done, total)`` inside the ``with`` block (the previous
    listener, if any, is restored after it)."""
    global _listener
    with _lock:
        previous, _listener = _listener, listener
    try:
        yield
    finally:
        with _lock:
            _listener = previous


def step_started(step: str) -> None:
    """Announce that ``step`` starts (its inputs are checked and, unless reused, it is computed)."""
    listener = _listener
    if listener is not None:
        listener(step, 0, 0)


def step_progress(step: str) -> Callable[[int, int], None] | None:
    """A ``progress(done, total)`` callback for ``step``'s countable work, or ``None`` when nobody listens (the
    engine's functions then skip their reporting)."""
    listener = _listener
    if listener is None:
        return None
    return lambda done, total: listener(step, done, total)
