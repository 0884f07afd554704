"""Reading numbers from metadata text, and the plausibility ranges ingest checks them against.

A value that is not a number, not finite, or outside its physical range is never passed on: it becomes
``None`` and the caller reports it by file and field.
"""

from __future__ import annotations

import math

#: field -> (low, high) inclusive, units in the name; angles in degrees
PLAUSIBLE_RANGES: dict[str, tuple[float, float]] = {
    "lat": (-90.0, 90.0),
    "lon": (-180.0, 180.0),
    "roll": (-180.0, 180.0),
    "pitch": (-180.0, 180.0),
    "yaw": (-360.0, 360.0),
}


def to_float(text: object) -> float | None:
    """``float(text)`` for numeric text (``"+51.36"``, ``"1e3"``); ``None`` if not a finite number."""
    if isinstance(text, bool):
        return None
    if isinstance(text, int | float):
        value = float(text)
    elif isinstance(text, str):
        s = text.strip()
        if not s or len(s) > 64:
            return None
        try:
            value = float(s)
        except ValueError:
            return None
    else:
        return None
    return value if math.isfinite(value) else None


def describe_bad_number(text: object) -> str:
    """Why :func:`to_float` refused ``text``, for a message."""
    if isinstance(text, str):
        s = text.strip()
        if not s:
            return "is empty"
        try:
            value = float(s)
        except ValueError:
            return f"{s[:40]!r} is not a number"
        if not math.isfinite(value):
            return f"{s!r} is not a finite number"
        return f"{s[:40]!r} is too long"
    if isinstance(text, float) and not math.isfinite(text):
        return f"{text} is not a finite number"
    return f"{text!r} is not a number"


def in_range(value: float | None, low: float, high: float) -> bool:
    return value is not None and math.isfinite(value) and low <= value <= high
