"""Ctrl-C during a run is never lost: it is noted when it arrives and raised again at the next step boundary.

A KeyboardInterrupt raised while Python runs a finalizer or a weakref callback (SQLAlchemy's, at garbage
collection) is printed as "Exception ignored in ..." and lost: the run went on to the end and exited 0
(reproduced with a Ctrl-C early in an ``aerocal process`` run). Runners call :func:`check_interrupted` before
every step.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator

#: set by :func:`interrupt_handler` when Ctrl-C arrives, checked at every step boundary (:func:`check_interrupted`)
_INTERRUPTED = threading.Event()


def interrupt_handler(signum: int, frame: object) -> None:
    """SIGINT: note it, then raise KeyboardInterrupt as Python's default handler does.

    A KeyboardInterrupt raised while Python runs a finalizer or a weakref callback (SQLAlchemy's, at garbage
    collection) is printed as "Exception ignored in ..." and lost: the run went on to the end and exited 0.
    The note makes the next step boundary raise it again."""
    _INTERRUPTED.set()
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupts_noted() -> Iterator[None]:
    """:func:`interrupt_handler` as the SIGINT handler for the block (main thread only; elsewhere the block
    runs as it is), the previous handler restored after it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _INTERRUPTED.clear()
    previous = signal.signal(signal.SIGINT, interrupt_handler)
    previous_hook = sys.unraisablehook

    def quiet_lost_interrupt(unraisable: object) -> None:
        # the lost KeyboardInterrupt is raised again at the next step boundary: no "Exception ignored" traceback
        if not (_INTERRUPTED.is_set() and unraisable.exc_type is KeyboardInterrupt):  # type: ignore[attr-defined]
            previous_hook(unraisable)  # type: ignore[arg-type]

    sys.unraisablehook = quiet_lost_interrupt
    try:
        yield
    except Exception as exc:
        # Ctrl-C landing inside a library's own bookkeeping can come out as that library's error (Prefect's
        # "Task run is not set" for a Ctrl-C early in a run): still the user's interrupt
        if _INTERRUPTED.is_set():
            raise KeyboardInterrupt from exc
        raise
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook
        _INTERRUPTED.clear()  # a later run in this process (a served flow) starts without it


def check_interrupted() -> None:
    """Raise KeyboardInterrupt if Ctrl-C arrived (:func:`interrupt_handler`) and was swallowed since."""
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt




def was_interrupted() -> bool:
    """Whether Ctrl-C arrived (:func:`interrupt_handler`) in the current :func:`interrupts_noted` block: an error
    raised after it is the interrupt's doing."""
    return _INTERRUPTED.is_set()
