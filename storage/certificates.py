"""The certificate store: issuing immutable, versioned certificates and selecting the one a flight uses.

A certificate document is validated whole by the engine's schema (:mod:`aerocal.certificates.schema`, through
:meth:`aerocal.certificates.document.Certificate.from_dict`) and stored unchanged apart from the fields the store owns:
``id`` (kept, or a new uuid4 hex when absent), ``issued`` (kept, or now when absent), ``version`` and
``supersedes``. The columns selection needs are indexed from the engine certificate (:func:`index_fields`).

Versions are consecutive per camera from 1, assigned under a lock: ``BEGIN IMMEDIATE`` on SQLite, a
``SELECT ... FOR UPDATE`` of the camera row on PostgreSQL, with the unique constraint
(camera_id, version) as the last guard and a retry when two writers still collide.

Which stored certificate a flight uses is decided by the engine's rules
(:func:`aerocal.certificates.selection.choose_certificate`: same camera, date and temperature coverage, age,
pins, rejected ones never chosen); :func:`select_certificate` queries the candidates and records the choice.
"""

from __future__ import annotations

import json
import random
import time
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import date, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from aerocal.certificates.document import Certificate as EngineCertificate
from aerocal.certificates.document import CertificateError
from aerocal.certificates.review import STATUSES
from aerocal.certificates.schema import SCHEMA
from aerocal.certificates.selection import Candidate, SelectionRules, choose_certificate, flight_day
from aerocal.certificates.selection import NoCertificateError as NoApplicableCertificate
from aerocal.certificates.selection import coverage as candidate_coverage
from storage.cameras import CameraIdentity, find_camera, get_or_create_camera, stored_identity
from storage.database import begin_write
from storage.errors import (
    CertificateDocumentError,
    NoStoredCertificateError,
    NotFoundError,
    StorageError,
)
from storage.models import Camera, Certificate, utcnow
from storage.runs import record_certificate

#: Schema family of certificate documents and the major version this code reads.
SCHEMA_FAMILY, _, _major = SCHEMA.partition("/")
SCHEMA_VERSION = int(_major)

#: review verdicts a stored certificate can carry (``aerocal.certificates.review.STATUSES``)
CERTIFICATE_STATUSES = STATUSES

__all__ = [
    "CERTIFICATE_STATUSES",
    "SCHEMA_FAMILY",
    "SCHEMA_VERSION",
    "IndexedFields",
    "SelectionRules",
    "candidate",
    "coverage",
    "get_certificate",
    "index_fields",
    "issue_certificate",
    "latest_certificate",
    "list_certificates",
    "select_certificate",
    "supersession_chain",
]


@dataclass(frozen=True)
class IndexedFields:
    """What the store indexes of a certificate document (see :func:`index_fields`)."""

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


# --------------------------------------------------------------------------------------- documents
def _json_default(obj: object) -> object:
    # numpy scalars and arrays without importing numpy here
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, datetime | date):
        return obj.isoformat()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _plain_document(document: Mapping[str, Any]) -> dict[str, Any]:
    """The document as plain JSON types, with the fields the store owns filled in: a missing ``id`` becomes a
    new uuid4 hex, a missing ``issued`` now; ``version`` and ``supersedes`` are assigned when it is stored."""
    if not isinstance(document, Mapping):
        raise CertificateDocumentError(
            f"a certificate document must be a JSON object, got {type(document).__name__}"
        )
    raw_id = document.get("id")
    where = f"certificate {raw_id}" if isinstance(raw_id, str) and raw_id else "certificate"
    try:
        plain = json.loads(json.dumps(document, default=_json_default))
    except (TypeError, ValueError) as exc:
        raise CertificateDocumentError(f"{where}: not JSON serialisable ({exc})") from None
    if not plain.get("id"):
        plain["id"] = uuid.uuid4().hex
    if not plain.get("issued"):
        plain["issued"] = utcnow().isoformat().replace("+00:00", "Z")
    plain["version"] = plain["supersedes"] = None
    return plain


def _indexed(certificate: EngineCertificate) -> IndexedFields:
    facts = Candidate.of(certificate)
    return IndexedFields(
        id=certificate.id,
        camera=stored_identity(certificate.identity),
        issued=certificate.issued,
        calibration_date=facts.calibration_date,
        temperature_range=facts.temperature_range,
        thermal_kind=facts.thermal_kind,
        model_kind="brown",
        sigma0=certificate.quality.sigma0,
        reprojection_rms_px=certificate.quality.reprojection_rms_px,
        status=facts.status,
    )


def _validated(document: Mapping[str, Any]) -> tuple[IndexedFields, dict[str, Any]]:
    """The indexed fields and the plain document to store; :class:`CertificateDocumentError` names the
    certificate, the field, what was expected and found, and the fix."""
    plain = _plain_document(document)
    where = f"certificate {plain['id']}"
    try:
        certificate = EngineCertificate.from_dict(plain)
    except CertificateError as exc:
        raise CertificateDocumentError(f"{where}: {exc}") from None
    try:
        fields = _indexed(certificate)
    except ValueError as exc:  # make, model or serial unknown
        raise CertificateDocumentError(f"{where}: camera: {exc}") from None
    return fields, plain


def index_fields(document: Mapping[str, Any]) -> IndexedFields:
    """Validate a certificate document with the engine's schema and read the fields the store indexes;
    :class:`CertificateDocumentError` names the field. A missing ``id`` becomes a new uuid4 hex, a missing
    ``issued`` now; the camera must name make, model and serial."""
    return _validated(document)[0]


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
        CertificateDocumentError: the document does not pass the certificate schema (the message names the
            field, what was expected and found, and the fix), its camera lacks make, model or serial, or a
            certificate with this id is already stored.
        StorageError: the version could not be assigned after ``max_attempts`` collisions.
    """
    fields, plain = _validated(document)
    where = f"certificate {fields.id}"
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
            stored_document["version"] = version
            stored_document["supersedes"] = latest.id if latest is not None else None
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
        identity = stored_identity(camera)
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
def candidate(certificate: Certificate, camera: CameraIdentity | None = None) -> Candidate:
    """What the selection rules read of a stored certificate (the row is the candidate's ``item``); ``camera``
    is its camera's identity when the caller has it already."""
    problems: tuple[str, ...] = ()
    if certificate.status != "accepted":
        problems = tuple((certificate.document.get("review") or {}).get("problems") or ())
    return Candidate(
        id=certificate.id,
        camera=camera or certificate.camera.identity,
        calibration_date=certificate.calibration_date,
        temperature_range=certificate.temperature_range,
        thermal_kind=certificate.thermal_kind,
        version=certificate.version,
        issued=certificate.issued,
        status=certificate.status,
        problems=problems,
        item=certificate,
    )


def coverage(certificate: Certificate, rules: SelectionRules | None = None) -> tuple[float, float] | None:
    """Temperature range (degC) the stored certificate covers under ``rules``, ``None`` when it records none
    (:func:`aerocal.certificates.selection.coverage`)."""
    return candidate_coverage(candidate(certificate), rules)


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
    """The stored certificate a flight of ``camera`` on ``flight_date`` should use, and why.

    The candidates are the camera's stored certificates (or, with ``pin``, the certificate with that id or
    unique prefix, of any camera); the choice is :func:`aerocal.certificates.selection.choose_certificate`'s:
    same camera identity, calibrated on or before the flight date and at most ``max_age_days`` before it,
    temperature coverage containing ``temperature_range`` (the flight's sensor temperatures ``(min, max)`` in
    degC, or ``None`` when unknown), never a rejected one; the newest by calibration date (then version)
    wins. A pin's broken rules are noted in the reason, not refused; it must belong to the same camera.

    With ``run_id`` the choice and reason are recorded on that run (not committed).

    Raises:
        NoStoredCertificateError: nothing applies; the message says what is missing, e.g.
            ``camera NEC TS9260 s/n 123: newest certificate 2016-03-14 covers 18-24 degC; flight
            spans 12-19 degC; ...``.
    """
    identity = stored_identity(camera)
    day = flight_day(flight_date)
    if pin is not None:
        try:
            pinned = get_certificate(session, pin)
        except NotFoundError as exc:
            raise NoStoredCertificateError(f"camera {identity}: pinned {exc}") from None
        candidates, pin = [candidate(pinned)], pinned.id
    else:  # the camera's certificates: its identity is the flight's
        candidates = [candidate(row, identity) for row in _certificates_of(session, identity)]
    try:
        chosen, reason = choose_certificate(
            candidates, identity, day, temperature_range, rules=rules, pin=pin, max_age_days=max_age_days
        )
    except NoApplicableCertificate as exc:
        raise NoStoredCertificateError(str(exc)) from None
    if run_id is not None:
        record_certificate(session, run_id, chosen, reason)
    return chosen, reason


def _certificates_of(session: Session, identity: CameraIdentity) -> list[Certificate]:
    """The camera's stored certificates, newest calibration (then version) first."""
    stored_camera = find_camera(session, identity)
    if stored_camera is None:
        return []
    return list(
        session.scalars(
            sa.select(Certificate)
            .where(Certificate.camera_id == stored_camera.id)
            .order_by(Certificate.calibration_date.desc(), Certificate.version.desc())
        )
    )


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
