"""The certificate store: issuing immutable, versioned certificates and selecting the one a flight uses.

A certificate document (produced by ``aerocal.certificate``) is a JSON object of schema
``aerocal.certificate/1``; this module reads only the fields it indexes (camera, id, issued, model kind,
thermal model, conditions, quality) and stores the whole document unchanged apart from the three fields
the store owns: ``id`` (kept, or a new uuid4 hex when absent), ``version`` and ``supersedes``.

Versions are consecutive per camera from 1, assigned under a lock: ``BEGIN IMMEDIATE`` on SQLite, a
``SELECT ... FOR UPDATE`` of the camera row on PostgreSQL, with the unique constraint
(camera_id, version) as the last guard and a retry when two writers still collide.

Temperature coverage
--------------------
A certificate covers the temperatures it was determined over: ``thermal.valid_range`` when it has a
thermal model (widened by :attr:`SelectionRules.thermal_tolerance_c`, default 0 degC: the model is
not extrapolated), else ``conditions.temperature_range`` widened by
:attr:`SelectionRules.temperature_tolerance_c` (default 3 degC) on each side. A constant-IO
certificate made at 30 degC therefore does not cover a flight at 10 degC. A certificate that records
no temperatures covers any flight temperature (``accept_unrecorded_temperature``), and a flight that
records none is not checked; the selection reason says so in both cases.

Dates
-----
A certificate applies to flights on or after its calibration date: ``conditions.date`` (the date of
the data it was computed from), or the issue date when the document has none. Using the date of the
data rather than the issue time lets a certificate computed today from a 2016 flight serve a 2017
flight of the same camera. ``max_age_days`` limits the days between calibration and flight.
"""

from __future__ import annotations

import json
import math
import random
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, date, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from storage.cameras import CameraIdentity, find_camera, get_or_create_camera
from storage.database import begin_write
from storage.errors import (
    CertificateDocumentError,
    NoCertificateError,
    NotFoundError,
    StorageError,
)
from storage.models import Camera, Certificate, utcnow
from storage.runs import record_certificate

#: Schema family of certificate documents and the major version this code reads.
SCHEMA_FAMILY = "aerocal.certificate"
SCHEMA_VERSION = 1


@dataclass(frozen=True)
class SelectionRules:
    """How :func:`select_certificate` decides whether a certificate covers a flight's temperatures.

    Attributes:
        temperature_tolerance_c: degC added on each side of a constant-IO certificate's calibration
            temperature range (default 3 degC: about the spread of sensor temperature within one
            calibration flight).
        thermal_tolerance_c: degC added on each side of a thermal model's ``valid_range`` (default 0:
            a fitted dIO/dT is not extrapolated).
        accept_unrecorded_temperature: whether a certificate recording no temperatures covers any
            flight temperature (default True; the reason then says the temperature was not checked).
    """

    temperature_tolerance_c: float = 3.0
    thermal_tolerance_c: float = 0.0
    accept_unrecorded_temperature: bool = True


@dataclass(frozen=True)
class IndexedFields:
    """What the store reads from a certificate document (see :func:`index_fields`)."""

    id: str
    camera: CameraIdentity
    issued: datetime
    calibration_date: date
    temperature_range: tuple[float, float] | None
    thermal_kind: str | None
    model_kind: str
    sigma0: float | None
    reprojection_rms_px: float | None
    status: str = "accepted"


#: review verdicts a stored certificate can carry (``aerocal.decision.STATUSES``)
CERTIFICATE_STATUSES = ("accepted", "rejected")


# --------------------------------------------------------------------------------------- documents
def _parse_time(value: object, where: str) -> datetime:
    if not isinstance(value, str):
        raise CertificateDocumentError(f"{where} must be an ISO-8601 UTC time like 2016-03-14T10:00:00Z")
    try:
        parsed = datetime.fromisoformat(value.strip())
    except ValueError:
        raise CertificateDocumentError(
            f"{where} {value!r} is not an ISO-8601 time; write it like 2016-03-14T10:00:00Z"
        ) from None
    if parsed.tzinfo is None:  # documented: times without offset are UTC
        parsed = parsed.replace(tzinfo=UTC)
    return parsed.astimezone(UTC)


def _parse_date(value: object, where: str) -> date:
    if isinstance(value, datetime):
        return value.astimezone(UTC).date() if value.tzinfo else value.date()
    if isinstance(value, date):
        return value
    if isinstance(value, str):
        try:
            return date.fromisoformat(value.strip()[:10])
        except ValueError:
            pass
    raise CertificateDocumentError(f"{where} {value!r} is not a date; write it as YYYY-MM-DD")


def _number(value: object, where: str) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise CertificateDocumentError(f"{where} must be a number or null, got {value!r}")
    return float(value)


def _range(value: object, where: str) -> tuple[float, float] | None:
    if value is None:
        return None
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
        raise CertificateDocumentError(f"{where} must be [min, max] in degC or null, got {value!r}")
    lo, hi = (_number(v, where) for v in value)
    if lo is None or hi is None:
        return None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise CertificateDocumentError(f"{where} must be finite with min <= max, got {list(value)}")
    return (lo, hi)


def _section(document: Mapping[str, Any], name: str, where: str, required: bool = False) -> Mapping[str, Any]:
    value = document.get(name)
    if value is None and not required:
        return {}
    if not isinstance(value, Mapping):
        raise CertificateDocumentError(f"{where}: field {name!r} must be an object")
    return value


def index_fields(document: Mapping[str, Any]) -> IndexedFields:
    """Validate and read the fields the store indexes; :class:`CertificateDocumentError` names the field.

    A missing ``id`` becomes a new uuid4 hex; a missing ``issued`` becomes now; times without an
    offset are read as UTC.
    """
    if not isinstance(document, Mapping):
        raise CertificateDocumentError("a certificate document must be a JSON object")
    raw_id = document.get("id")
    if raw_id is not None and (not isinstance(raw_id, str) or not raw_id.strip() or len(raw_id) > 64):
        raise CertificateDocumentError(
            f"certificate id must be a non-empty string of at most 64 characters, got {raw_id!r}"
        )
    cert_id = raw_id.strip() if raw_id else uuid.uuid4().hex
    where = f"certificate {cert_id}"
    schema = document.get("schema")
    if not isinstance(schema, str) or not schema.startswith(SCHEMA_FAMILY + "/"):
        raise CertificateDocumentError(
            f"{where}: field 'schema' is {schema!r}, expected '{SCHEMA_FAMILY}/{SCHEMA_VERSION}'"
        )
    major = schema.split("/", 1)[1].split(".")[0]
    if major != str(SCHEMA_VERSION):
        raise CertificateDocumentError(
            f"{where}: schema {schema!r} is not readable by this aerocal ({SCHEMA_FAMILY}/{SCHEMA_VERSION}); "
            "upgrade aerocal"
        )
    camera = CameraIdentity.from_mapping(
        _section(document, "camera", where, required=True), f"{where}: camera"
    )
    issued = _parse_time(document["issued"], f"{where}: issued") if document.get("issued") else utcnow()
    model = _section(document, "model", where, required=True)
    model_kind = model.get("kind")
    if not isinstance(model_kind, str) or not model_kind:
        raise CertificateDocumentError(f"{where}: model.kind must name the camera model (e.g. 'brown')")
    conditions = _section(document, "conditions", where)
    calibration_date = (
        _parse_date(conditions["date"], f"{where}: conditions.date")
        if conditions.get("date")
        else issued.date()
    )
    condition_range = _range(conditions.get("temperature_range"), f"{where}: conditions.temperature_range")
    thermal = _section(document, "thermal", where)
    thermal_kind = None
    temperature_range = condition_range
    if thermal:
        thermal_kind = thermal.get("kind")
        if not isinstance(thermal_kind, str) or not thermal_kind:
            raise CertificateDocumentError(
                f"{where}: thermal.kind must name the thermal model (e.g. 'linear')"
            )
        valid = _range(thermal.get("valid_range"), f"{where}: thermal.valid_range")
        temperature_range = valid if valid is not None else condition_range
    quality = _section(document, "quality", where)
    review = _section(document, "review", where)
    status = review.get("status", "accepted") if review else "accepted"
    if status not in CERTIFICATE_STATUSES:
        raise CertificateDocumentError(
            f"{where}: review.status is {status!r}; write one of {', '.join(CERTIFICATE_STATUSES)}"
        )
    return IndexedFields(
        id=cert_id,
        camera=camera,
        issued=issued,
        calibration_date=calibration_date,
        temperature_range=temperature_range,
        thermal_kind=thermal_kind,
        model_kind=model_kind,
        sigma0=_number(quality.get("sigma0"), f"{where}: quality.sigma0"),
        reprojection_rms_px=_number(
            quality.get("reprojection_rms_px"), f"{where}: quality.reprojection_rms_px"
        ),
        status=status,
    )


def _json_default(obj: object) -> object:
    # numpy scalars and arrays without importing numpy here
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, datetime | date):
        return obj.isoformat()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _first_non_finite(obj: object, path: str = "") -> str | None:
    if isinstance(obj, float) and not math.isfinite(obj):
        return path or "(document)"
    if isinstance(obj, Mapping):
        for key, value in obj.items():
            found = _first_non_finite(value, f"{path}.{key}" if path else str(key))
            if found:
                return found
    elif isinstance(obj, list | tuple):
        for i, value in enumerate(obj):
            found = _first_non_finite(value, f"{path}[{i}]")
            if found:
                return found
    return None


def _plain_json(document: Mapping[str, Any], where: str) -> dict[str, Any]:
    """The document as plain JSON types; NaN and infinities are refused (PostgreSQL JSON rejects them)."""
    try:
        text = json.dumps(document, default=_json_default)
    except TypeError as exc:
        raise CertificateDocumentError(f"{where}: not JSON serialisable ({exc})") from None
    plain = json.loads(text)
    bad = _first_non_finite(plain)
    if bad:
        raise CertificateDocumentError(
            f"{where}: field {bad} is NaN or infinite; store null for a value that was not estimated"
        )
    return plain


# ----------------------------------------------------------------------------------------- issuing
def _retryable(exc: sa.exc.DBAPIError) -> bool:
    if isinstance(exc, sa.exc.IntegrityError):
        return True
    sqlstate = getattr(exc.orig, "sqlstate", None)
    if sqlstate in ("40001", "40P01", "55P03"):  # serialization failure, deadlock, lock not available
        return True
    return "database is locked" in str(exc.orig) or "database is busy" in str(exc.orig)


def issue_certificate(session: Session, document: Mapping[str, Any], max_attempts: int = 20) -> Certificate:
    """Store ``document`` as the next certificate of its camera and return the stored record.

    Assigns ``version`` (previous + 1, or 1) and ``supersedes`` (id of the camera's latest
    certificate) under a lock, so concurrent issuers for one camera get distinct consecutive versions.
    The camera is registered if new. The certificate is committed when this returns: issuing runs in
    a transaction of its own, and any transaction open on ``session`` is committed first.

    Raises:
        CertificateDocumentError: a field the store indexes is missing or malformed, the document
            holds NaN, or a certificate with this id is already stored.
        StorageError: the version could not be assigned after ``max_attempts`` collisions.
    """
    fields = index_fields(document)
    where = f"certificate {fields.id}"
    plain = _plain_json(document, where)
    if session.in_transaction():
        session.commit()
    last_error: Exception | None = None
    for attempt in range(max_attempts):
        try:
            begin_write(session)
            existing = session.get(Certificate, fields.id)
            if existing is not None:
                raise CertificateDocumentError(
                    f"{where} is already stored (version {existing.version} of camera "
                    f"{existing.camera.label}); certificates are immutable, "
                    "issue a new document with a new id"
                )
            camera = get_or_create_camera(session, fields.camera, lock=True)
            latest = session.scalars(
                sa.select(Certificate)
                .where(Certificate.camera_id == camera.id)
                .order_by(Certificate.version.desc())
                .limit(1)
            ).first()
            version = latest.version + 1 if latest is not None else 1
            stored_document = dict(plain)
            stored_document["id"] = fields.id
            stored_document["version"] = version
            stored_document["supersedes"] = latest.id if latest is not None else None
            if not stored_document.get("issued"):
                stored_document["issued"] = fields.issued.isoformat().replace("+00:00", "Z")
            lo, hi = fields.temperature_range if fields.temperature_range else (None, None)
            record = Certificate(
                id=fields.id,
                camera_id=camera.id,
                version=version,
                supersedes=stored_document["supersedes"],
                issued=fields.issued,
                calibration_date=fields.calibration_date,
                temperature_min=lo,
                temperature_max=hi,
                thermal_kind=fields.thermal_kind,
                model_kind=fields.model_kind,
                sigma0=fields.sigma0,
                reprojection_rms_px=fields.reprojection_rms_px,
                _document=stored_document,
                status=fields.status,
            )
            record.camera = camera
            session.add(record)
            session.commit()
            return record
        except sa.exc.DBAPIError as exc:
            session.rollback()
            if not _retryable(exc):
                raise
            last_error = exc
            # back off before retrying; the jitter is unseeded on purpose: it must differ between processes
            time.sleep(random.uniform(0.005, 0.02) * (1 + attempt))
        except BaseException:
            session.rollback()
            raise
    raise StorageError(
        f"{where}: could not assign a version for camera {fields.camera} after {max_attempts} attempts "
        f"({' '.join(str(last_error).split())[:200]}); retry later"
    )


# -------------------------------------------------------------------------------------- retrieving
def get_certificate(session: Session, certificate_id: str) -> Certificate:
    """The certificate with this id, or with this unique id prefix (at least 4 characters)."""
    key = str(certificate_id).strip()
    found = session.get(Certificate, key)
    if found is not None:
        return found
    if len(key) >= 4:
        matches = list(session.scalars(sa.select(Certificate).where(Certificate.id.startswith(key)).limit(3)))
        if len(matches) == 1:
            return matches[0]
        if len(matches) > 1:
            raise NotFoundError(f"certificate id prefix {key!r} is ambiguous; give more characters")
    raise NotFoundError(f"certificate {key!r} not found; list them with `aerocal certificates list`")


def list_certificates(session: Session, camera: CameraIdentity | str | None = None) -> list[Certificate]:
    """Stored certificates by camera and version.

    ``camera`` is an identity (exact match), a ``"make|model|serial|lens"`` text (exact), or free
    text whose words must all occur in make, model, serial or lens (case-insensitive).
    """
    query = sa.select(Certificate).join(Camera)
    if isinstance(camera, CameraIdentity) or (isinstance(camera, str) and "|" in camera):
        identity = CameraIdentity.coerce(camera)
        query = query.where(
            Camera.make == identity.make,
            Camera.model == identity.model,
            Camera.serial == identity.serial,
            Camera.lens == identity.lens,
        )
    elif camera:
        text = Camera.make + " " + Camera.model + " " + Camera.serial + " " + Camera.lens
        for word in str(camera).split():
            query = query.where(sa.func.lower(text).contains(word.lower(), autoescape=True))
    query = query.order_by(Camera.make, Camera.model, Camera.serial, Camera.lens, Certificate.version)
    return list(session.scalars(query))


def latest_certificate(session: Session, camera: CameraIdentity | str) -> Certificate | None:
    """The camera's highest-version certificate, or ``None``."""
    stored = find_camera(session, camera)
    if stored is None:
        return None
    return session.scalars(
        sa.select(Certificate)
        .where(Certificate.camera_id == stored.id)
        .order_by(Certificate.version.desc())
        .limit(1)
    ).first()


# --------------------------------------------------------------------------------------- selection
def coverage(certificate: Certificate, rules: SelectionRules | None = None) -> tuple[float, float] | None:
    """Temperature range (degC) the certificate covers under ``rules``, ``None`` when it records none."""
    rules = rules or SelectionRules()
    recorded = certificate.temperature_range
    if recorded is None:
        return None
    tol = rules.thermal_tolerance_c if certificate.thermal_kind else rules.temperature_tolerance_c
    return (recorded[0] - tol, recorded[1] + tol)


def _coverage_basis(certificate: Certificate, rules: SelectionRules) -> str:
    recorded = certificate.temperature_range
    if recorded is None:
        return "records no temperatures"
    if certificate.thermal_kind:
        tol = f" +/- {rules.thermal_tolerance_c:g}" if rules.thermal_tolerance_c else ""
        return f"{certificate.thermal_kind} thermal model valid {_span(recorded)}{tol}"
    return f"constant IO calibrated at {_span(recorded)} +/- {rules.temperature_tolerance_c:g}"


def _span(rng: tuple[float, float]) -> str:
    return f"{rng[0]:g}-{rng[1]:g} degC"


def _flight_date(value: date | datetime | str) -> date:
    try:
        return _parse_date(value, "flight date")
    except CertificateDocumentError as exc:
        raise ValueError(str(exc)) from None


def _flight_range(value: Sequence[float] | None) -> tuple[float, float] | None:
    if value is None:
        return None
    lo, hi = (float(v) for v in value)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"flight temperature range must be finite, got {list(value)}")
    return (min(lo, hi), max(lo, hi))


def _problems(
    cert: Certificate,
    flight_date: date,
    flight_range: tuple[float, float] | None,
    max_age_days: float | None,
    rules: SelectionRules,
) -> list[str]:
    """Why ``cert`` does not apply to the flight (empty when it does)."""
    problems = []
    if cert.status != "accepted":
        why = "; ".join((cert.document.get("review") or {}).get("problems") or []) or "no reason recorded"
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
    cert: Certificate,
    n_applicable: int,
    n_total: int,
    flight_date: date,
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


def select_certificate(
    session: Session,
    camera: CameraIdentity | Camera | Mapping[str, object] | str,
    flight_date: date | datetime | str,
    temperature_range: Sequence[float] | None,
    max_age_days: float | None = None,
    pin: str | None = None,
    rules: SelectionRules | None = None,
    run_id: str | None = None,
) -> tuple[Certificate, str]:
    """The certificate a flight of ``camera`` on ``flight_date`` should use, and why.

    Candidates are the certificates of the same camera identity (make, model, serial, lens) that
    were calibrated on or before the flight date, at most ``max_age_days`` before it, and whose
    temperature coverage (see the module docstring) contains ``temperature_range`` (the flight's
    sensor temperatures ``(min, max)`` in degC, or ``None`` when unknown). The newest candidate by
    calibration date (then version) wins.

    ``pin`` selects a certificate by id (or unique prefix) instead; it must belong to the same camera.
    Rules it breaks are noted in the reason, not refused: a pin is a deliberate choice.

    With ``run_id`` the choice and reason are recorded on that run (not committed).

    Raises:
        NoCertificateError: nothing applies; the message says what is missing, e.g.
            ``camera NEC TS9260 s/n 123: newest certificate 2016-03-14 covers 18-24 degC; flight
            spans 12-19 degC; ...``.
    """
    rules = rules or SelectionRules()
    identity = CameraIdentity.coerce(camera)
    day = _flight_date(flight_date)
    flight_range = _flight_range(temperature_range)
    if pin is not None:
        try:
            chosen = get_certificate(session, pin)
        except NotFoundError as exc:
            raise NoCertificateError(f"camera {identity}: pinned {exc}") from None
        if CameraIdentity.coerce(chosen.camera) != identity:
            raise NoCertificateError(
                f"camera {identity}: pinned certificate {chosen.id} belongs to camera {chosen.camera.label}; "
                "pin a certificate of this camera"
            )
        if chosen.status != "accepted":
            raise NoCertificateError(
                f"camera {identity}: pinned certificate {chosen.id} "
                + _problems(chosen, day, None, None, rules)[0]
                + "; a rejected certificate is never used: pin an accepted one or calibrate on this flight"
            )
        problems = _problems(chosen, day, flight_range, max_age_days, rules)
        reason = f"pinned by id: v{chosen.version} {chosen.id} calibrated {chosen.calibration_date}"
        if problems:
            reason += "; note: it " + "; it ".join(problems)
    else:
        chosen, reason = _select_newest(session, identity, day, flight_range, max_age_days, rules)
    if run_id is not None:
        record_certificate(session, run_id, chosen, reason)
    return chosen, reason


def _select_newest(
    session: Session,
    identity: CameraIdentity,
    day: date,
    flight_range: tuple[float, float] | None,
    max_age_days: float | None,
    rules: SelectionRules,
) -> tuple[Certificate, str]:
    stored_camera = find_camera(session, identity)
    certificates: list[Certificate] = []
    if stored_camera is not None:
        certificates = list(
            session.scalars(
                sa.select(Certificate)
                .where(Certificate.camera_id == stored_camera.id)
                .order_by(Certificate.calibration_date.desc(), Certificate.version.desc())
            )
        )
    fix = "calibrate the camera on this flight, import a certificate, or pin one"
    if not certificates:
        raise NoCertificateError(f"camera {identity}: no certificate is stored for this camera; {fix}")
    verdicts = [(cert, _problems(cert, day, flight_range, max_age_days, rules)) for cert in certificates]
    applicable = [cert for cert, problems in verdicts if not problems]
    if applicable:
        chosen = applicable[0]
        return chosen, _describe_choice(
            chosen, len(applicable), len(certificates), day, flight_range, max_age_days, rules
        )
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


def supersession_chain(session: Session, certificate: Certificate | str) -> list[Certificate]:
    """The certificate and every one it supersedes, newest first."""
    current = get_certificate(session, certificate) if isinstance(certificate, str) else certificate
    chain = [current]
    while current.supersedes is not None:
        current = session.get(Certificate, current.supersedes)
        if current is None:  # pragma: no cover - foreign key guarantees it
            break
        chain.append(current)
    return chain
