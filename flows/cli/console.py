"""Where the ``aerocal`` commands print: the two consoles, the progress bar, a run's status and the key-value
table.

Results go to standard output (:data:`console`), errors and progress to standard error (:data:`err_console`),
so that ``aerocal ... --json > file`` holds the JSON alone. Neither console highlights numbers or wraps long
lines of paths and ids (``soft_wrap``): a line copied from the terminal is the line printed.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn
from rich.table import Table

console = Console(highlight=False, soft_wrap=True)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)


@contextmanager
def progress(label: str, total: int) -> Iterator[Callable[[int, int], None]]:
    """A transient progress bar on standard error for ``total`` steps, yielding ``advance(done, total)``;
    no bar when ``total`` is 0 (``advance`` then does nothing)."""
    if not total:
        yield lambda done, total: None
        return
    bar = Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                   TimeRemainingColumn(), console=err_console, transient=True)
    with bar:
        task = bar.add_task(label, total=total)
        yield lambda done, total: bar.update(task, completed=done, total=total)


@contextmanager
def run_status(label: str) -> Iterator[None]:
    """What a flight's run shows while it goes (:mod:`aerocal.pipeline.progress`).

    On a terminal: a status line with ``label``, the step running and its work done (``match 412/4236``).
    Otherwise (a log file, a scheduled job, a pipe): a line on standard error as each step starts, and one when
    a step's counted work is complete, so that a log says where a run was when it stopped."""
    # lazy: importing aerocal.pipeline (every step) costs 1.5 s (measured); `aerocal --help` must not pay it
    from aerocal.pipeline.progress import reporting_to

    if console.is_terminal:
        with console.status(f"{label} ...") as status:

            def show(step: str, done: int, total: int) -> None:
                status.update(f"{label}: {step}" + (f" {done}/{total}" if total else "") + " ...")

            with reporting_to(show):
                yield
        return

    def log(step: str, done: int, total: int) -> None:
        if not total:
            err_console.print(f"{label}: {step}", markup=False)
        elif done >= total:
            err_console.print(f"{label}: {step} {done}/{total} done", markup=False)

    with reporting_to(log):
        yield


def print_key_values(title: str, values: dict[str, Any]) -> None:
    """One two-column table: each key beside its value (lists and mappings as JSON)."""
    table = Table(title=title, show_header=False)
    for key, value in values.items():
        table.add_row(str(key), json.dumps(value) if isinstance(value, list | dict) else str(value))
    console.print(table)
