"""Which certificate applies to a flight: the selection rules, pure Python over a list of candidates.

:func:`choose_certificate` takes the certificates a store holds (:class:`aerocal.certificates.document.Certificate`
objects, or :class:`Candidate` records of what the rules read, e.g. built from database rows), the flight's
camera, date and sensor temperature range, and returns the one to use with the reason, or raises
:class:`NoCertificateError` saying why none applies. The database store (:mod:`storage.certificates`) and an
in-memory store both call it; no SQL here.

Camera
------
Only certificates of the same camera identity (make, model, serial, lens; :class:`CameraIdentity`) apply.

Dates
-----
A certificate applies to flights on or after its calibration date: ``conditions.date`` (the date of the data
it was computed from), or the issue date when the document has none
(:attr:`aerocal.certificates.document.Certificate.calibration_date`). Using the date of the data rather than the issue
time lets a certificate computed today from a 2016 flight serve a 2017 flight of the same camera.
``max_age_days`` limits the days between calibration and flight.

Temperature coverage
--------------------
A certificate covers the temperatures it was determined over: ``thermal.valid_range`` when it has a thermal
model (widened by :attr:`SelectionRules.thermal_tolerance_c`, default 0 degC: the model is not extrapolated),
else ``conditions.temperature_range`` widened by :attr:`SelectionRules.temperature_tolerance_c` (default
3 degC) on each side. A constant-IO certificate made at 30 degC therefore does not cover a flight at 10 degC.
A certificate that records no temperatures covers any flight temperature
(:attr:`SelectionRules.accept_unrecorded_temperature`), and a flight that records none is not checked; the
reason says so in both cases.

Review
------
A certificate whose review rejected it is on record but never chosen, not even when pinned.

Choice
------
The newest applicable certificate by calibration date (then version, then issue time) wins. A pin (an id or a
unique id prefix of at least 4 characters) chooses a certificate instead; it must belong to the camera and
not be rejected; the other rules it breaks are noted in the reason, not refused: a pin is a deliberate choice.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from aerocal.certificates.document import Certificate
from aerocal.certificates.identity import CameraIdentity
from aerocal.certificates.review import ACCEPTED

#: how many leading characters of an id a pin must give at least when it is not a whole id
MIN_PIN_PREFIX = 4


@dataclass(frozen=True)
class SelectionRules:
    """How :func:`choose_certificate` decides whether a certificate covers a flight's temperatures.

    Attributes:
        temperature_tolerance_c: degC added on each side of a constant-IO certificate's calibration
            temperature range (default 3 degC: about the spread of sensor temperature within one
            calibration flight).
        thermal_tolerance_c: degC added on each side of a thermal model's ``valid_range`` (default 0:
            a fitted dIO/dT is not extrapolated).
        accept_unrecorded_temperature: whether a certificate recording no temperatures covers any
            flight temperature (default True; the reason then says the temperature was not checked).

    Tolerances are finite and 0 or more: a negative one would narrow the range a certificate was determined
    over, refusing flights it covers.
    """

    temperature_tolerance_c: float = 3.0
    thermal_tolerance_c: float = 0.0
    accept_unrecorded_temperature: bool = True

    def __post_init__(self) -> None:
        for name in ("temperature_tolerance_c", "thermal_tolerance_c"):
            value = getattr(self, name)
            if not 0.0 <= value < math.inf:
                raise ValueError(f"SelectionRules.{name} must be finite degC of 0 or more (a negative tolerance "
                                 f"would narrow the range a certificate was determined over), got {value!r}")
        if not isinstance(self.accept_unrecorded_temperature, bool):
            raise ValueError(f"SelectionRules.accept_unrecorded_temperature must be True or False, got "
                             f"{self.accept_unrecorded_temperature!r}")


class NoCertificateError(LookupError):
    """No certificate applies to a flight; the message says what is missing and how to fix it."""


@dataclass(frozen=True)
class Candidate:
    """What the selection rules read of one certificate, and the ``item`` returned when it is chosen.

    ``temperature_range`` (degC) is the range the certificate was determined over: its thermal model's valid
    range where it has one, else the calibration images' range (``None``: not recorded); ``thermal_kind`` is
    the thermal model's kind (``None``: constant IO); ``problems`` are its review's reasons for rejecting it;
    ``item`` is what :func:`choose_certificate` returns when it is chosen (``None``: the candidate itself).
    """

    id: str
    camera: CameraIdentity
    calibration_date: dt.date
    temperature_range: tuple[float, float] | None
    thermal_kind: str | None = None
    version: int | None = None
    issued: dt.datetime | None = None
    status: str = ACCEPTED
    problems: tuple[str, ...] = ()
    item: Any = None

    @classmethod
    def of(cls, certificate: Certificate, status: str | None = None, item: Any = None) -> Candidate:
        """The candidate of an engine certificate; ``status`` overrides its review's verdict (a store may keep
        the status apart), ``item`` what to return when chosen (default: the certificate)."""
        review = certificate.review
        return cls(
            id=certificate.id,
            camera=certificate.identity,
            calibration_date=certificate.calibration_date,
            temperature_range=certificate.valid_temperature_range,
            thermal_kind=None if certificate.thermal is None else certificate.thermal.kind,
            version=certificate.version,
            issued=certificate.issued,
            status=status or certificate.status,
            problems=() if review is None else tuple(review.problems),
            item=certificate if item is None else item,
        )

    @property
    def accepted(self) -> bool:
        return self.status == ACCEPTED

    @property
    def result(self) -> Any:
        """What choosing this candidate returns: its ``item``, or the candidate itself when it has none."""
        return self if self.item is None else self.item


def _candidate(value: Candidate | Certificate) -> Candidate:
    if isinstance(value, Candidate):
        return value
    if isinstance(value, Certificate):
        return Candidate.of(value)
    raise TypeError(f"expected a Certificate or a Candidate, got {type(value).__name__}")


# ----------------------------------------------------------------------------------- the flight's facts
def flight_day(value: dt.date | dt.datetime | str) -> dt.date:
    """The flight's date from a date, a datetime (its UTC date when aware) or ISO text (the first 10
    characters, so ``"2017-05-02T10:00:00Z"`` reads as 2017-05-02); ``ValueError`` naming the value otherwise.

    Raises:
        ValueError: ``value`` is neither a date, a datetime nor text starting with an ISO date (YYYY-MM-DD).
    """
    if isinstance(value, dt.datetime):
        return value.astimezone(dt.UTC).date() if value.tzinfo else value.date()
    if isinstance(value, dt.date):
        return value
    if isinstance(value, str):
        try:
            return dt.date.fromisoformat(value.strip()[:10])
        except ValueError:
            pass
    raise ValueError(f"flight date {value!r} is not a date; write it as YYYY-MM-DD")


def flight_temperatures(value: Sequence[float] | None) -> tuple[float, float] | None:
    """``(min, max)`` degC of the flight's sensor temperatures (either order given), or ``None``.

    Raises:
        ValueError: a temperature of ``value`` is not a finite number.
    """
    if value is None:
        return None
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"flight temperature range must be finite, got {list(value)}")
    return (min(lo, hi), max(lo, hi))


# ----------------------------------------------------------------------------------- the rules
def coverage(candidate: Candidate | Certificate, rules: SelectionRules | None = None) -> tuple[float, float] | None:
    """Temperature range (degC) the certificate covers under ``rules``, ``None`` when it records none."""
    candidate = _candidate(candidate)
    rules = rules or SelectionRules()
    recorded = candidate.temperature_range
    if recorded is None:
        return None
    tol = rules.thermal_tolerance_c if candidate.thermal_kind else rules.temperature_tolerance_c
    return (recorded[0] - tol, recorded[1] + tol)


def _coverage_basis(candidate: Candidate, rules: SelectionRules) -> str:
    recorded = candidate.temperature_range
    if recorded is None:
        return "records no temperatures"
    if candidate.thermal_kind:
        tol = f" +/- {rules.thermal_tolerance_c:g}" if rules.thermal_tolerance_c else ""
        return f"{candidate.thermal_kind} thermal model valid {_span(recorded)}{tol}"
    return f"constant IO calibrated at {_span(recorded)} +/- {rules.temperature_tolerance_c:g}"


def _span(rng: tuple[float, float]) -> str:
    return f"{rng[0]:g}-{rng[1]:g} degC"


def problems_with(
    candidate: Candidate | Certificate,
    flight_date: dt.date,
    flight_range: tuple[float, float] | None,
    max_age_days: float | None = None,
    rules: SelectionRules | None = None,
) -> list[str]:
    """Why the certificate does not apply to the flight, one clause each (empty when it does)."""
    cert = _candidate(candidate)
    rules = rules or SelectionRules()
    problems = []
    if not cert.accepted:
        why = "; ".join(cert.problems) or "no reason recorded"
        problems.append(f"was rejected by its review ({why})")
    if cert.calibration_date > flight_date:
        problems.append(f"was calibrated after the flight of {flight_date}")
    else:
        age = (flight_date - cert.calibration_date).days
        if max_age_days is not None and age > max_age_days:
            problems.append(
                f"is {age} days older than the flight of {flight_date}; the limit is {max_age_days:g} days"
            )
    covered = coverage(cert, rules)
    if flight_range is not None:
        if covered is None:
            if not rules.accept_unrecorded_temperature:
                problems.append(f"records no temperatures; flight spans {_span(flight_range)}")
        elif flight_range[0] < covered[0] or flight_range[1] > covered[1]:
            problems.append(f"covers {_span(covered)}; flight spans {_span(flight_range)}")
    return problems


def _describe_choice(
    cert: Candidate,
    n_applicable: int,
    n_total: int,
    flight_date: dt.date,
    flight_range: tuple[float, float] | None,
    max_age_days: float | None,
    rules: SelectionRules,
) -> str:
    age = (flight_date - cert.calibration_date).days
    limit = f" (limit {max_age_days:g})" if max_age_days is not None else ""
    covered = coverage(cert, rules)
    if flight_range is None:
        temperature = "flight records no temperatures, not checked"
    elif covered is None:
        temperature = f"certificate records no temperatures, flight {_span(flight_range)} not checked"
    else:
        temperature = (
            f"covers {_span(covered)} ({_coverage_basis(cert, rules)}) >= flight {_span(flight_range)}"
        )
    return (
        f"newest applicable certificate ({n_applicable} of {n_total} for camera {cert.camera.label}): "
        f"v{cert.version} {cert.id} calibrated {cert.calibration_date}, {age} days before the flight{limit}; "
        f"{temperature}"
    )


def _newest_first(candidates: Iterable[Candidate]) -> list[Candidate]:
    oldest = dt.datetime.min.replace(tzinfo=dt.UTC)
    return sorted(candidates, key=lambda c: (c.calibration_date, c.version or 0, c.issued or oldest), reverse=True)


def _pinned(candidates: list[Candidate], pin: str, identity: CameraIdentity) -> Candidate:
    key = str(pin).strip()
    matches = [c for c in candidates if c.id == key]
    if not matches and len(key) >= MIN_PIN_PREFIX:
        matches = [c for c in candidates if c.id.startswith(key)]
    if not matches:
        raise NoCertificateError(
            f"camera {identity}: pinned certificate {key!r} not found among the {len(candidates)} certificates "
            "given; pin the id of one of them"
        )
    if len(matches) > 1:
        raise NoCertificateError(f"camera {identity}: pinned certificate id prefix {key!r} is ambiguous; "
                                 "give more characters")
    return matches[0]


def choose_certificate(
    candidates: Iterable[Candidate | Certificate],
    camera: CameraIdentity | str | object,
    flight_date: dt.date | dt.datetime | str,
    temperature_range: Sequence[float] | None,
    *,
    rules: SelectionRules | None = None,
    pin: str | None = None,
    max_age_days: float | None = None,
) -> tuple[Any, str]:
    """The certificate a flight of ``camera`` on ``flight_date`` should use, and why (see the module docstring).

    Args:
        candidates: the certificates to choose from (any camera: the others are passed over), as engine
            :class:`~aerocal.certificates.document.Certificate` objects (their review gives the status) or
            :class:`Candidate` records.
        camera: the flight's camera identity (or its key ``"make|model|serial|lens"``).
        flight_date: the flight's date (a date, datetime or ISO text).
        temperature_range: the flight's sensor temperatures ``(min, max)`` in degC, or ``None`` when unknown.
        rules: the temperature coverage rules (default :class:`SelectionRules`).
        pin: a certificate id (or unique prefix) to use instead of the newest applicable one.
        max_age_days: the most days a certificate may be calibrated before the flight.

    Returns:
        ``(item, reason)``: the chosen candidate's ``item`` (the certificate itself for a certificate given)
        and one line saying why it was chosen.

    Raises:
        NoCertificateError: nothing applies; the message says what is missing, e.g. ``camera NEC TS9260 s/n
            123: newest certificate 2016-03-14 covers 18-24 degC; flight spans 12-19 degC; ...``.
        ValueError: the flight date or temperature range cannot be read.
    """
    rules = rules or SelectionRules()
    identity = CameraIdentity.coerce(camera)
    day = flight_day(flight_date)
    flight_range = flight_temperatures(temperature_range)
    pool = [_candidate(c) for c in candidates]
    if pin is not None:
        chosen = _pinned(pool, pin, identity)
        if chosen.camera != identity:
            raise NoCertificateError(
                f"camera {identity}: pinned certificate {chosen.id} belongs to camera {chosen.camera.label}; "
                "pin a certificate of this camera"
            )
        if not chosen.accepted:
            raise NoCertificateError(
                f"camera {identity}: pinned certificate {chosen.id} "
                + problems_with(chosen, day, None, None, rules)[0]
                + "; a rejected certificate is never used: pin an accepted one or calibrate on this flight"
            )
        problems = problems_with(chosen, day, flight_range, max_age_days, rules)
        reason = f"pinned by id: v{chosen.version} {chosen.id} calibrated {chosen.calibration_date}"
        if problems:
            reason += "; note: it " + "; it ".join(problems)
        return chosen.result, reason
    certificates = _newest_first(c for c in pool if c.camera == identity)
    fix = "calibrate the camera on this flight, import a certificate, or pin one"
    if not certificates:
        raise NoCertificateError(f"camera {identity}: no certificate is stored for this camera; {fix}")
    verdicts = [(cert, problems_with(cert, day, flight_range, max_age_days, rules)) for cert in certificates]
    applicable = [cert for cert, problems in verdicts if not problems]
    if applicable:
        chosen = applicable[0]
        reason = _describe_choice(chosen, len(applicable), len(certificates), day, flight_range, max_age_days, rules)
        return chosen.result, reason
    before = [(cert, problems) for cert, problems in verdicts if cert.calibration_date <= day]
    if before:
        cert, problems = before[0]
        what = f"newest certificate {cert.calibration_date} " + "; it ".join(problems)
    else:
        cert, problems = verdicts[-1]
        what = f"oldest certificate {cert.calibration_date} " + "; it ".join(problems)
    count = f"{len(certificates)} certificate{'s' if len(certificates) > 1 else ''} checked"
    if flight_range is not None and len(certificates) > 1:
        spans = [span for span in (coverage(c, rules) for c in certificates) if span is not None]
        if spans:
            widest = max(spans, key=lambda s: s[1] - s[0])
            count += f"; widest temperature coverage of any certificate: {_span(widest)}"
    raise NoCertificateError(f"camera {identity}: {what} ({count}); {fix}")


__all__ = [
    "MIN_PIN_PREFIX",
    "Candidate",
    "NoCertificateError",
    "SelectionRules",
    "choose_certificate",
    "coverage",
    "flight_day",
    "flight_temperatures",
    "problems_with",
]
