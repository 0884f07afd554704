"""How an ``aerocal`` command ends when something goes wrong: the exit codes, the one error line, and the
two blocks every command wraps its work in (:func:`user_errors`, and :func:`flow_errors` around a flow run).

Exit codes (every command):

* 0 -- done;
* :data:`FAILED` (1) -- the command could not do its work: the database is unreachable or out of date, an
  adjustment cannot go on, a calibration was rejected, a defect (its traceback in the run folder);
* :data:`BAD_INPUT` (2) -- refused because of what the user gave: a folder, file or argument that is wrong or
  missing; nothing was processed or stored;
* :data:`INTERRUPTED` (130) -- stopped by Ctrl-C (SIGINT), as a shell reports ``128 + SIGINT``.

Every error is one line on standard error, ``error: WHAT IS WRONG; THE FIX``, without a traceback.
"""

from __future__ import annotations

import contextlib
import errno
import json
from collections.abc import Iterator
from pathlib import Path
from typing import NoReturn

import typer
from rich.text import Text

from flows.cli.console import err_console

FAILED = 1
BAD_INPUT = 2
INTERRUPTED = 130

#: The errors below are named by module and class and compared by name along the raised error's class
#: hierarchy, so that this module imports none of them just to be ready for an error: ``flows.process``
#: imports Prefect (about 1 s), the pipeline and the simulator take 0.6 s, the diagnosis 1 s, and
#: ``storage.errors`` 0.3 s (it imports the engine's certificate schema); ``aerocal --help`` would pay for
#: them. ``tests/test_cli_help.py`` checks that each still exists.

#: errors of the storage layer (exit code :data:`FAILED`): the database URL, an unreachable server, an
#: out-of-date schema, a certificate or run not found, a certificate already stored
STORAGE_ERRORS: frozenset[tuple[str, str]] = frozenset({("storage.errors", "StorageError")})

#: errors that mean the user's input is wrong (exit code :data:`BAD_INPUT`)
INPUT_ERRORS: frozenset[tuple[str, str]] = frozenset({
    ("aerocal.pipeline.dataset", "FlightInputError"),
    ("aerocal.effects", "EffectError"),
    ("aerocal.simulate.presets", "PresetError"),
    ("aerocal.simulate.simulator", "SimulationError"),
    ("aerocal.simulate.measured", "MeasuredFlightError"),
    ("aerocal.diagnose.run", "DiagnoseInputError"),
})

#: what an interrupted command says unless its block says more (:func:`flow_errors` says how to resume)
INTERRUPTED_NOTE = "stopped by Ctrl-C before the command finished"

#: what an interrupted flow run says: its completed steps are kept and the same command resumes
RESUME_NOTE = ("the steps completed so far are kept in the store; run the same command again to resume after "
               "the last of them (the run is recorded as cancelled)")


class CommandInputError(ValueError):
    """A command's own check of its arguments failed (exit code :data:`BAD_INPUT`); the message names the
    argument or file (with its line) and the fix."""


def fail(message: object, code: int = FAILED) -> NoReturn:
    """Print ``error: MESSAGE`` as one line on standard error (whitespace runs become one space; brackets are
    printed as they are, never read as markup) and exit with ``code``."""
    err_console.print(Text.assemble(("error:", "red"), " ", " ".join(str(message).split())))
    raise typer.Exit(code)


def raised_as(exc: BaseException, names: frozenset[tuple[str, str]]) -> bool:
    """Whether ``exc`` is an instance of one of the classes ``names`` (module, class name)."""
    return any((cls.__module__, cls.__qualname__) in names for cls in type(exc).__mro__)


def is_input_error(exc: BaseException) -> bool:
    """Whether ``exc`` says the user's input is wrong: a :class:`CommandInputError` or one of
    :data:`INPUT_ERRORS` (or a subclass of either)."""
    return isinstance(exc, CommandInputError) or raised_as(exc, INPUT_ERRORS)


@contextlib.contextmanager
def user_errors(source: str | Path | None = None, interrupted: str = INTERRUPTED_NOTE) -> Iterator[None]:
    """Turn the errors a user can cause into one line and an exit code.

    ``source`` is the file the block reads (or writes) for the user: a malformed value or JSON in it is bad
    input, said with its name. Without ``source`` a ``ValueError`` or ``LookupError`` is bad input only when
    :func:`is_input_error` says so (a certificate or an adjustment that cannot be used is a failure).

    * Ctrl-C -> ``interrupted`` (yellow), exit :data:`INTERRUPTED`;
    * invalid JSON -> its line and column, :data:`BAD_INPUT`;
    * ``OSError`` (no such file, permission) -> the path and "check the path", :data:`BAD_INPUT`; a full disk
      -> the path and "free space", :data:`FAILED`;
    * one of :data:`STORAGE_ERRORS` -> the message, :data:`FAILED`;
    * ``ValueError`` / ``LookupError`` -> the message, :data:`BAD_INPUT` or :data:`FAILED` as above.

    Anything else is a defect and keeps its traceback.
    """
    where = str(source) if source is not None else None

    def located(message: str) -> str:
        return message if where is None or where in message else f"{where}: {message}"

    try:
        yield
    except KeyboardInterrupt:
        err_console.print(Text.assemble(("interrupted", "yellow"), f": {interrupted}"))
        raise typer.Exit(INTERRUPTED) from None
    except json.JSONDecodeError as exc:
        fail(located(f"line {exc.lineno} column {exc.colno}: not valid JSON ({exc.msg}); fix the file there"),
             BAD_INPUT)
    except OSError as exc:
        name = exc.filename or where
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):  # not the user's input: the disk written to is full
            reason = f"{exc.strerror}; free space on that disk or write elsewhere, then run the command again"
            fail(f"{name}: {reason}" if name else reason, FAILED)
        reason = f"{exc.strerror or exc}; check the path"
        fail(f"{name}: {reason}" if name else reason, BAD_INPUT)
    except Exception as exc:
        if raised_as(exc, STORAGE_ERRORS):  # before ValueError: a certificate document's error is both
            fail(located(str(exc)))
        if isinstance(exc, ValueError | LookupError):
            fail(located(str(exc)), BAD_INPUT if where is not None or is_input_error(exc) else FAILED)
        raise


@contextlib.contextmanager
def flow_errors(run_dir: Path) -> Iterator[None]:
    """Around a flow run that writes ``run_dir``: the user's errors as :func:`user_errors` says, Ctrl-C as one
    line saying what is kept and how to resume (exit :data:`INTERRUPTED`), and a defect as one line naming
    the run folder's traceback file (exit :data:`FAILED`). Call after :func:`flows.environment.quiet_prefect`:
    this imports Prefect."""
    # lazy: flows.process imports Prefect (about 1 s), only around a flow run
    from aerocal.pipeline.interrupts import interrupts_noted
    from flows.process import FAILURE_LOG

    try:
        with user_errors(interrupted=RESUME_NOTE), interrupts_noted():
            yield
    except typer.Exit:
        raise
    except Exception as exc:  # a defect, not the user's input: one line here, the traceback in the run folder
        fail(f"{type(exc).__name__}: {exc} (the full traceback is in {run_dir / FAILURE_LOG})")
