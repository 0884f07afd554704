"""Capture times in UTC from camera clocks that rarely say which time zone they keep.

EXIF ``DateTimeOriginal`` is the camera clock's local time, without a zone. The offset to UTC is taken,
per image, from the first of:

1. a tag that states it: EXIF ``OffsetTimeOriginal``, or an XMP date with a zone (DJI ``xmp:CreateDate``)
   that shows the same clock reading;
2. (``IngestConfig.time_zone_from_gnss``) a UTC time the GNSS receiver recorded in the same image (EXIF
   GPS date/time stamp, senseFly ``UTCTime``): the flight's median difference between camera clock and
   GNSS UTC, rounded to 15 minutes (time zones are whole quarter hours). On ``seneca`` the camera clock
   reads 4 h 0 min 34 s behind GNSS UTC: the zone is UTC-04:00 (EDT), and the remaining 34 s are the
   camera clock's own error, reported but not corrected (DateTimeOriginal stays the time source);
3. otherwise UTC is assumed.

Cases 2 and 3 are reported once per flight, not once per image.
"""

from __future__ import annotations

import datetime as dt

import numpy as np

from aerocal.ingest.metadata import ImageMetadata
from aerocal.ingest.problems import ProblemLog, name_list

QUARTER_HOUR_S = 900.0
MAX_ZONE_S = 14 * 3600.0


def _format_offset(seconds: float) -> str:
    sign = "-" if seconds < 0 else "+"
    s = int(round(abs(seconds)))
    return f"{sign}{s // 3600:02d}:{(s % 3600) // 60:02d}"


def resolve_utc_times(
    metas: list[ImageMetadata], where: str, problems: ProblemLog, use_gnss: bool = True
) -> list[dt.datetime | None]:
    """UTC capture time (timezone-aware) per image, ``None`` where the image has no capture time."""
    out: list[dt.datetime | None] = [None] * len(metas)
    timed = [i for i, m in enumerate(metas) if m.local_time is not None]
    if not timed:
        if metas:
            problems.warning(
                where, f"no capture time in any of the {len(metas)} images; time is null", "time"
            )
        return out
    # a flight-wide zone from GNSS UTC where the camera states none
    zone_s: float | None = None
    residual_s: float | None = None
    source = None
    if use_gnss:
        diffs = [
            (metas[i].local_time - metas[i].gnss_utc).total_seconds()  # type: ignore[operator]
            for i in timed
            if metas[i].utc_offset is None and metas[i].gnss_utc is not None
        ]
        if diffs:
            median = float(np.median(diffs))
            zone = round(median / QUARTER_HOUR_S) * QUARTER_HOUR_S
            if abs(zone) <= MAX_ZONE_S:
                zone_s, residual_s = zone, median - zone
                source = next(metas[i].gnss_utc_source for i in timed if metas[i].gnss_utc is not None)
    assumed: list[str] = []
    from_gnss: list[str] = []
    for i in timed:
        m = metas[i]
        local = m.local_time
        assert local is not None
        if m.utc_offset is not None:
            utc = local - m.utc_offset
        elif zone_s is not None:
            utc = local - dt.timedelta(seconds=zone_s)
            from_gnss.append(m.name)
        else:
            utc = local
            assumed.append(m.name)
        out[i] = utc.replace(tzinfo=dt.UTC)
    if from_gnss:
        assert zone_s is not None and residual_s is not None
        problems.warning(
            where,
            f"DateTimeOriginal of {len(from_gnss)} image(s) carries no time zone; "
            f"zone UTC{_format_offset(zone_s)} "
            f"taken from the GNSS UTC time ({source}); the camera clock differs from GNSS UTC by a further "
            f"{residual_s:+.0f} s (not corrected)",
            "time",
        )
    if assumed:
        problems.warning(
            where,
            f"DateTimeOriginal of {len(assumed)} image(s) carries no time zone (no OffsetTimeOriginal) "
            "and no GNSS "
            f"UTC time: assumed to be UTC ({name_list(assumed)})",
            "time",
        )
    missing = [m.name for i, m in enumerate(metas) if m.local_time is None]
    if missing:
        problems.warning(where, f"{len(missing)} image(s) have no capture time: {name_list(missing)}", "time")
    return out
