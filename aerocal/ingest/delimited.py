"""Line-oriented text sidecars (CSV with a header, whitespace lists): reading them safely.

Common rules of the EO and GCP files:

* UTF-8 (a BOM is ignored; undecodable bytes are replaced and reported once);
* ``# key: value`` comment lines set directives (``# crs: EPSG:32632``, ``# attitude: dji_gimbal``);
  other lines starting with ``#`` and blank lines are ignored;
* line numbers in messages are 1-based lines of the file, counted at ``\n`` (as ``grep -n`` counts them).
"""

from __future__ import annotations

import csv
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from aerocal.ingest.problems import ProblemLog

MAX_TEXT_BYTES = 64 * 1024 * 1024
_DIRECTIVE = re.compile(r"^#\s*([A-Za-z_][\w\-]*)\s*:\s*(.*?)\s*$")


@dataclass
class TextLines:
    """The content lines of a sidecar file and its ``# key: value`` directives (key -> (value, line))."""

    path: Path
    lines: list[tuple[int, str]] = field(default_factory=list)
    directives: dict[str, tuple[str, int]] = field(default_factory=dict)


def read_text_lines(path: Path, problems: ProblemLog) -> TextLines | None:
    """Content lines of ``path`` (comments and blanks removed); ``None`` with an error if unreadable."""
    try:
        size = path.stat().st_size
        if size > MAX_TEXT_BYTES:
            problems.error(
                path, f"file is {size} bytes; text sidecars larger than {MAX_TEXT_BYTES} are not read"
            )
            return None
        raw = path.read_bytes()
    except OSError as exc:
        problems.error(path, f"cannot be read ({exc.strerror or exc}); ignored")
        return None
    if b"\x00" in raw[:4096]:
        problems.error(path, "is a binary file, not text; ignored")
        return None
    text = raw.decode("utf-8", errors="replace")
    if "\ufffd" in text:
        problems.warning(path, "contains bytes that are not UTF-8; they were replaced")
    text = text.lstrip("\ufeff")
    out = TextLines(path)
    # lines are counted at "\n" (as grep -n, wc -l and editors do), trailing "\r" dropped ("\r\r\n" occurs);
    # a file with no "\n" at all but "\r" uses classic Mac line ends
    raw_lines = text.split("\n") if "\n" in text or "\r" not in text else text.split("\r")
    for number, line in enumerate((ln.rstrip("\r") for ln in raw_lines), start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            m = _DIRECTIVE.match(stripped)
            if m:
                out.directives.setdefault(m.group(1).lower(), (m.group(2), number))
            continue
        out.lines.append((number, line))
    return out


def split_csv(line: str) -> list[str]:
    """Fields of one CSV line (quotes honoured), stripped."""
    try:
        return [f.strip() for f in next(csv.reader([line], skipinitialspace=True))]
    except (csv.Error, StopIteration):
        return [f.strip() for f in line.split(",")]


def split_whitespace(line: str) -> list[str]:
    return line.split()


def normalise_header(names: list[str]) -> list[str]:
    """Header names lower-cased, blanks and dashes as underscores (``"Point Name"`` -> ``"point_name"``)."""
    return [re.sub(r"[\s\-]+", "_", n.strip().lower()) for n in names]


def find_column(header: list[str], aliases: tuple[str, ...]) -> int | None:
    """Index of the first header name among ``aliases``, or ``None``."""
    for alias in aliases:
        if alias in header:
            return header.index(alias)
    return None


def keyed_rows(
    text: TextLines,
    n_cols: int,
    key_col: int,
    problems: ProblemLog,
    seen: Mapping[str, object],
    key_label: str,
    key_field: str,
    count_field: str,
    repeat_prefix: str = "",
) -> Iterator[tuple[int, list[str], str]]:
    """Data rows (line, fields, key) of a CSV with a header, keyed by column ``key_col``.

    A row whose field count differs from the header's, whose key is empty, or whose key is already in
    ``seen`` (the caller's records, each with a ``line``; checked when the row is reached) is reported
    by file, line and field and skipped.
    """
    path = text.path
    for line, raw in text.lines[1:]:
        fields = split_csv(raw)
        if len(fields) != n_cols:
            problems.error(path, f"has {len(fields)} fields, the header has {n_cols}; row ignored", count_field,
                           line)
            continue
        key = fields[key_col]
        if not key:
            problems.error(path, f"{key_label} is empty; row ignored", key_field, line)
            continue
        if key in seen:
            previous = seen[key].line  # type: ignore[attr-defined]
            problems.error(path, f"{repeat_prefix}{key} repeats line {previous}; row ignored", key_field, line)
            continue
        yield line, fields, key
