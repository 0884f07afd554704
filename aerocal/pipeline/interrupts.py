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
from collections.abc import Callable, Iterator
from typing import Any

#: set by :func:`interrupt_handler` when Ctrl-C arrives, checked at every step boundary (:func:`check_interrupted`)
_INTERRUPTED = threading.Event()
#: set when Ctrl-C ended the last :func:`interrupts_noted` block: the hook stays quiet while the interrupt unwinds
_ENDED_BY_INTERRUPT = threading.Event()


def interrupt_handler(signum: int, frame: object) -> None:
    """SIGINT: note it, then raise KeyboardInterrupt as Python's default handler does.

    A KeyboardInterrupt raised while Python runs a finalizer or a weakref callback (SQLAlchemy's, at garbage
    collection) is printed as "Exception ignored in ..." and lost: the run went on to the end and exited 0.
    The note makes the next step boundary raise it again."""
    _INTERRUPTED.set()
    raise KeyboardInterrupt


class _QuietAfterInterrupt:
    """The unraisable hook inside :func:`interrupts_noted`, and after a block Ctrl-C ended.

    Inside the block a KeyboardInterrupt lost in a finalizer is quiet (it is raised again at the next step
    boundary). Once Ctrl-C has arrived, any exception raised in a finalizer is quiet too: an object the interrupt
    left half built fails in its own ``__del__`` when it is collected, possibly after the block, as the process
    exits (llvmlite's pass manager, interrupted while numba compiled a kernel on a first run, printed
    "AttributeError: ... no attribute '_as_parameter_'" after "interrupted"). Anything else goes to ``wrapped``.
    """

    def __init__(self, wrapped: Callable[[Any], object]) -> None:
        self.wrapped = wrapped

    def __call__(self, unraisable: Any) -> None:
        if not _INTERRUPTED.is_set() and not _ENDED_BY_INTERRUPT.is_set():
            self.wrapped(unraisable)


@contextlib.contextmanager
def interrupts_noted() -> Iterator[None]:
    """:func:`interrupt_handler` as the SIGINT handler for the block (main thread only; elsewhere the block
    runs as it is), the previous handler restored after it. Exceptions in finalizers after Ctrl-C are quiet
    (:class:`_QuietAfterInterrupt`) until the next block starts.

    Raises:
        KeyboardInterrupt: the block raised another exception after a Ctrl-C (a library's error for the interrupt); that
            exception is its cause. Other exceptions of the block pass through unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _INTERRUPTED.clear()
    _ENDED_BY_INTERRUPT.clear()
    previous = signal.signal(signal.SIGINT, interrupt_handler)
    hook = sys.unraisablehook
    previous_hook = hook.wrapped if isinstance(hook, _QuietAfterInterrupt) else hook
    sys.unraisablehook = _QuietAfterInterrupt(previous_hook)
    ended_by_interrupt = False
    try:
        yield
    except KeyboardInterrupt:
        ended_by_interrupt = True
        raise
    except Exception as exc:
        # Ctrl-C landing inside a library's own bookkeeping can come out as that library's error (Prefect's
        # "Task run is not set" for a Ctrl-C early in a run): still the user's interrupt
        if _INTERRUPTED.is_set():
            ended_by_interrupt = True
            raise KeyboardInterrupt from exc
        raise
    finally:
        signal.signal(signal.SIGINT, previous)
        if ended_by_interrupt or _INTERRUPTED.is_set():
            # the quiet hook stays: what the interrupt left half built is collected later, as the process exits
            _ENDED_BY_INTERRUPT.set()
        else:
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
