"""Grouping the frames of a flight into strips (flight lines) from positions and headings.

The rule (all thresholds in :class:`StripConfig`):

1. Frames are taken in flight order (capture time; file name when a time is missing). A *step* joins
   two consecutive frames; its *course* is the direction of travel (degrees clockwise from grid north)
   and its *length* the distance in metres in the projected CRS.
2. Steps shorter than ``min_step_fraction`` times the flight's median step are hovering or turning on
   the spot and belong to no strip; a candidate strip whose median step is shorter than
   ``min_strip_step_fraction`` times the flight's median step is a slow transition (a multirotor side-
   stepping between lines while it yaws round, ``h20t_forest`` frames 19-21), not a strip.
3. A strip grows step by step while the next step's course stays within ``course_tolerance_deg`` of the
   strip's mean course so far and its length stays within a factor ``spacing_ratio`` of the strip's
   median step (a gap of one missed frame, about twice the spacing, is tolerated; a turn, a change of
   speed regime or a jump is not). A step that fails starts a new candidate strip. Consecutive
   candidates that share a frame and agree in mean course and spacing are joined again (GNSS noise early
   in a line can make one step fail against the mean of the first two).
4. Where a heading is recorded (gimbal or aircraft yaw), frames at either end of a strip whose heading
   differs from the strip's median heading by more than ``heading_tolerance_deg`` are trimmed: they were
   taken while the aircraft was already turning. Headings are not used for the course itself because
   a fixed-wing aircraft crabs in wind (``seneca``: headings 24-76 deg on lines whose course is 44-70 deg).
5. A candidate with at least ``min_frames`` frames is a strip; strips are numbered 0, 1, 2, ... in flight
   order. Frames in no strip get -1 (turns, approach, hover). A frame shared by two strips (a sharp turn
   exactly at a frame) stays with the earlier strip.

On the measured data this finds 2 strips with the turn between them on ``h20t_forest`` and the
lawn-mower legs of ``seneca`` in both directions plus its cross strips (see ``tests/test_ingest_real.py``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StripConfig:
    """Thresholds of the strip rule above.

    * ``course_tolerance_deg`` (25): largest difference between a step's course and the strip's mean course,
      widened to 3 standard deviations of the flight's own course noise up to ``max_course_tolerance_deg``
      (60): noisy GNSS on short steps must not cut strips, a 90 or 180 deg turn still ends one.
    * ``spacing_ratio`` (2.5): a step may be at most this factor longer or shorter than the strip's median,
      widened (up to ``max_spacing_ratio``, 5) so that a step 3 robust standard deviations short of the
      flight's median still passes where GNSS noise is a large part of the step.
    * ``min_step_fraction`` (0.3): steps shorter than this fraction of the flight's median step are turns.
    * ``min_strip_step_fraction`` (0.75): a strip's median step must be at least this fraction of the
      flight's median step (measured: 0.93-0.97 on ``seneca``'s slowest lines, 0.64 in the turn of
      ``h20t_forest``).
    * ``heading_tolerance_deg`` (45): end frames whose heading differs more from the strip's are trimmed.
    * ``min_frames`` (3): fewest frames a strip may have.
    """

    course_tolerance_deg: float = 25.0
    max_course_tolerance_deg: float = 60.0
    spacing_ratio: float = 2.5
    max_spacing_ratio: float = 5.0
    min_step_fraction: float = 0.3
    min_strip_step_fraction: float = 0.75
    heading_tolerance_deg: float = 45.0
    min_frames: int = 3

    def __post_init__(self) -> None:
        if not 0 < self.course_tolerance_deg < 180:
            raise ValueError(
                f"StripConfig.course_tolerance_deg must be in (0, 180), got {self.course_tolerance_deg}"
            )
        if not self.spacing_ratio > 1:
            raise ValueError(f"StripConfig.spacing_ratio must be > 1, got {self.spacing_ratio}")
        if not 0 <= self.min_step_fraction < 1:
            raise ValueError(f"StripConfig.min_step_fraction must be in [0, 1), got {self.min_step_fraction}")
        if not 0 < self.heading_tolerance_deg <= 180:
            raise ValueError(
                f"StripConfig.heading_tolerance_deg must be in (0, 180], got {self.heading_tolerance_deg}"
            )
        if not 0 <= self.min_strip_step_fraction < 1:
            raise ValueError(
                f"StripConfig.min_strip_step_fraction must be in [0, 1), got {self.min_strip_step_fraction}"
            )
        if self.min_frames < 2:
            raise ValueError(f"StripConfig.min_frames must be >= 2, got {self.min_frames}")


def angle_difference(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Absolute difference of angles in degrees, in [0, 180]."""
    d = (np.asarray(a, dtype=float) - np.asarray(b, dtype=float) + 180.0) % 360.0 - 180.0
    return np.abs(d)


def circular_mean(angles_deg: np.ndarray) -> float:
    """Mean direction (degrees in [0, 360)) of angles in degrees."""
    r = np.radians(np.asarray(angles_deg, dtype=float))
    return float(np.degrees(np.arctan2(np.sin(r).sum(), np.cos(r).sum())) % 360.0)


def find_strips(
    x: np.ndarray, y: np.ndarray, heading: np.ndarray | None = None, config: StripConfig | None = None
) -> np.ndarray:
    """Strip number of every frame, by the rule of the module docstring (thresholds in :class:`StripConfig`).

    Args:
        x, y: positions (N,), metres in a projected CRS, in flight order, all finite (drop frames without a
            position before calling).
        heading: degrees clockwise from north per frame, NaN where unknown; ``None``: no end frame is trimmed by
            heading.
        config: the thresholds (default :class:`StripConfig`); ``course_tolerance_deg`` and ``spacing_ratio`` are
            widened to the flight's own course and step noise.

    Returns:
        int32 array (N,), in flight order: strips numbered 0, 1, 2, ... in flight order, -1 for frames in no strip
        (turns, approach, hover); all -1 with fewer than ``config.min_frames`` frames or when no frame moves.
    """
    cfg = config or StripConfig()
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    n = len(x)
    strip = np.full(n, -1, dtype=np.int32)
    if n < cfg.min_frames:
        return strip
    dx, dy = np.diff(x), np.diff(y)
    length = np.hypot(dx, dy)
    course = np.degrees(np.arctan2(dx, dy)) % 360.0
    moving = length[length > 0]
    if moving.size == 0:
        return strip
    scale = float(np.median(moving))
    usable = length >= cfg.min_step_fraction * scale
    tolerance = _course_tolerance(course, usable, cfg)
    cfg = dataclasses.replace(cfg, course_tolerance_deg=tolerance,
                              spacing_ratio=_spacing_ratio(length[usable], cfg))

    segments: list[tuple[int, int]] = []  # (first frame, last frame) inclusive
    i = 0
    n_steps = n - 1
    while i < n_steps:
        if not usable[i]:
            i += 1
            continue
        j = i + 1
        while j < n_steps and usable[j]:
            seg = slice(i, j)
            if angle_difference(course[j], circular_mean(course[seg])) > cfg.course_tolerance_deg:
                break
            med = float(np.median(length[seg]))
            if not med / cfg.spacing_ratio <= length[j] <= med * cfg.spacing_ratio:
                break
            j += 1
        segments.append((i, j))  # steps i..j-1 join frames i..j
        i = j
    segments = _merge_noise_splits(segments, course, length, cfg)

    head = None if heading is None else np.asarray(heading, dtype=float)
    number = 0
    for first, last in segments:
        if first > 0 and strip[first] >= 0:  # shared with the previous strip
            first += 1
        if head is not None:
            first, last = _trim_by_heading(head, first, last, cfg.heading_tolerance_deg)
        if last - first + 1 < cfg.min_frames:
            continue
        if np.median(length[first:last]) < cfg.min_strip_step_fraction * scale:
            continue
        strip[first : last + 1] = number
        number += 1
    return strip


def _course_tolerance(course: np.ndarray, usable: np.ndarray, cfg: StripConfig) -> float:
    """``course_tolerance_deg``, widened to 3 standard deviations of the flight's course noise where that is
    larger (at most ``max_course_tolerance_deg``, so that a turn stays a turn).

    The noise is measured on the flight itself, from the change of course between consecutive usable steps
    (robust: turns are outliers): consumer GNSS (1.5-3 m) on a low flight's 5-10 m steps turns single-step
    courses by 15-30 deg, so a fixed 25 deg cut a rendered XT2 survey's strips into pieces."""
    ok = usable[1:] & usable[:-1]
    if ok.sum() < 4:
        return cfg.course_tolerance_deg
    change = angle_difference(course[1:][ok], course[:-1][ok])
    sigma = 1.4826 * float(np.median(change)) / np.sqrt(2.0)
    return float(np.clip(3.0 * sigma, cfg.course_tolerance_deg, cfg.max_course_tolerance_deg))


def _spacing_ratio(steps: np.ndarray, cfg: StripConfig) -> float:
    """``spacing_ratio``, widened where the flight's step lengths are noisy: a step 3 robust standard
    deviations short must still pass (at most ``max_spacing_ratio``)."""
    if steps.size < 4:
        return cfg.spacing_ratio
    med = float(np.median(steps))
    rel = 1.4826 * float(np.median(np.abs(steps - med))) / med
    if 3.0 * rel >= 1.0 - 1.0 / cfg.max_spacing_ratio:
        return cfg.max_spacing_ratio
    return float(np.clip(1.0 / (1.0 - 3.0 * rel), cfg.spacing_ratio, cfg.max_spacing_ratio))


def _merge_noise_splits(
    segments: list[tuple[int, int]], course: np.ndarray, length: np.ndarray, cfg: StripConfig
) -> list[tuple[int, int]]:
    """Join consecutive candidates that share a frame and agree in mean course and spacing.

    Greedy growth compares each step with the mean of the few steps before it, so GNSS noise early in a
    line can split it; a real turn gives candidates whose courses differ and are never joined.
    """
    out: list[tuple[int, int]] = []
    for first, last in segments:
        if out and out[-1][1] == first:
            p_first, p_last = out[-1]
            steps = length[p_first:last]
            med = float(np.median(steps))
            same_course = (
                angle_difference(circular_mean(course[p_first:p_last]), circular_mean(course[first:last]))
                <= cfg.course_tolerance_deg
            )
            regular = bool(np.all((steps >= med / cfg.spacing_ratio) & (steps <= med * cfg.spacing_ratio)))
            if same_course and regular:
                out[-1] = (p_first, last)
                continue
        out.append((first, last))
    return out


def circular_median(angles_deg: np.ndarray) -> float:
    """The sample angle (degrees) with the least total angular distance to the others (a circular median)."""
    a = np.asarray(angles_deg, dtype=float)
    return float(a[np.argmin(angle_difference(a[:, None], a[None, :]).sum(axis=1))])


def _trim_by_heading(head: np.ndarray, first: int, last: int, tolerance: float) -> tuple[int, int]:
    known = np.isfinite(head[first : last + 1])
    if known.sum() < 2:
        return first, last
    ref = circular_median(head[first : last + 1][known])  # robust to the turn frames being trimmed
    while first <= last and np.isfinite(head[first]) and angle_difference(head[first], ref) > tolerance:
        first += 1
    while last >= first and np.isfinite(head[last]) and angle_difference(head[last], ref) > tolerance:
        last -= 1
    return first, last
