"""Problems found while ingesting a flight: one line each, naming the file, the line and the field.

Severity ``"error"`` means the item (an image, a row of a text file, a whole sidecar file) was skipped;
``"warning"`` means it was kept with a caveat the message states. An error with ``stops_processing``
is one that ``aerocal process`` cannot go past (no nominal camera, no flying height, ...): process
checks for them before any work and stops with the same report.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

SEVERITIES = ("error", "warning")


@dataclass(frozen=True)
class Problem:
    """One problem: ``file`` (name or path), 1-based ``line`` and ``field`` where there are any."""

    file: str
    line: int | None
    field: str | None
    message: str
    severity: str = "warning"
    stops_processing: bool = False

    def __post_init__(self) -> None:
        if self.severity not in SEVERITIES:
            raise ValueError(f"problem severity {self.severity!r} unknown; valid: {', '.join(SEVERITIES)}")

    def __str__(self) -> str:
        where = self.file if self.line is None else f"{self.file}:{self.line}"
        what = f" {self.field}:" if self.field else ""
        tag = "error, stops processing" if self.stops_processing else self.severity
        return f"{where}:{what} {self.message} [{tag}]"


class ProblemLog:
    """An ordered, duplicate-free collection of :class:`Problem`."""

    def __init__(self) -> None:
        self._items: list[Problem] = []
        self._seen: set[Problem] = set()

    def add(self, problem: Problem) -> None:
        if problem not in self._seen:
            self._seen.add(problem)
            self._items.append(problem)

    def error(
        self, file: str | Path, message: str, field: str | None = None, line: int | None = None
    ) -> None:
        self.add(Problem(str(file), line, field, message, "error"))

    def blocker(self, file: str | Path, message: str, field: str | None = None, line: int | None = None) -> None:
        """An error that ``aerocal process`` cannot go past; ``message`` names the fix."""
        self.add(Problem(str(file), line, field, message, "error", stops_processing=True))

    def warning(
        self, file: str | Path, message: str, field: str | None = None, line: int | None = None
    ) -> None:
        self.add(Problem(str(file), line, field, message, "warning"))

    def extend(self, problems: Iterable[Problem]) -> None:
        for p in problems:
            self.add(p)

    def __iter__(self) -> Iterator[Problem]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def as_list(self) -> list[Problem]:
        return list(self._items)


def name_list(names: list[str], limit: int = 5) -> str:
    """``"a, b, c and 4 more"``: a short list of names for messages that summarise many items."""
    if len(names) <= limit:
        return ", ".join(names)
    return f"{', '.join(names[:limit])} and {len(names) - limit} more"
