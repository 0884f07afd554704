"""The exterior orientation a sensor recorded for one image, before any checking or projection."""

from __future__ import annotations

from dataclasses import dataclass, field

from aerocal.ingest.numbers import describe_bad_number, to_float


@dataclass
class RecordedPose:
    """Position (WGS84 degrees, metres) and attitude (degrees, in ``convention``) as read from metadata.

    ``alt_reference`` says what the height is measured from, as far as the source documents it;
    ``extra`` holds fields that are not part of the ``images`` table (speeds, laser range, ...);
    ``notes`` lists (field, message) for values that were present but unusable.
    """

    source: str
    lat: float | None = None
    lon: float | None = None
    alt: float | None = None
    alt_reference: str | None = None
    roll: float | None = None
    pitch: float | None = None
    yaw: float | None = None
    convention: str | None = None
    utc_time: str | None = None
    extra: dict[str, float | str] = field(default_factory=dict)
    notes: list[tuple[str, str]] = field(default_factory=list)

    def number(self, fields: dict[str, str], key: str) -> float | None:
        """The number stored under ``key`` in ``fields`` (an XMP dict); a bad value is noted and None."""
        raw = fields.get(key)
        if raw is None:
            return None
        value = to_float(raw)
        if value is None:
            self.notes.append((key, f"{describe_bad_number(raw)}; ignored"))
        return value
