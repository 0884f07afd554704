"""How an ``aerocal`` command's help is written: its docstring, registered by :func:`command`.

A command's docstring is its help: a first line that says what it does (the line ``aerocal --help`` and
``aerocal GROUP --help`` list beside its name, at most :data:`FIRST_LINE_MAX` characters so that it fits an
80-column terminal), then paragraphs, then one or more ``Example: aerocal ...`` lines that run as written.
Docstrings are wrapped at 120 columns in the source; rich prints a later paragraph's line breaks as they are,
which at another terminal width wraps raggedly, so :func:`reflow` joins each paragraph into one line
(``Example:`` lines and ``* `` items stay lines of their own) and the terminal wraps it.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any, TypeVar

import typer

#: longest first line of a command's help (characters): the listing beside the longest command name fits
#: in 80 columns
FIRST_LINE_MAX = 60

#: the lines of a help paragraph that start a line of their own
LINE_STARTS = ("Example:", "* ")

Function = TypeVar("Function", bound=Callable[..., Any])


def reflow(doc: str) -> str:
    """``doc`` with each paragraph joined into one line, except :data:`LINE_STARTS` lines."""
    paragraphs = []
    for block in inspect.cleandoc(doc).split("\n\n"):
        lines: list[str] = []
        for line in block.splitlines():
            if lines and not line.startswith(LINE_STARTS):
                lines[-1] += " " + line.strip()
            else:
                lines.append(line.strip())
        paragraphs.append("\n".join(lines))
    return "\n\n".join(paragraphs)


def command(app: typer.Typer, name: str, **settings: Any) -> Callable[[Function], Function]:
    """Register the decorated function as command ``name`` of ``app``, its reflowed docstring as its help
    (``settings``: further arguments of :meth:`typer.Typer.command`, e.g. ``rich_help_panel``)."""

    def register(function: Function) -> Function:
        app.command(name, help=reflow(function.__doc__ or ""), **settings)(function)
        return function

    return register
