"""Where a flight's certificate comes from: a certificate store, the flight's own self-calibration, or the
nominal camera.

:class:`CertificateStore` is what the pipeline asks of a store: the certificate that applies to a flight
(:func:`aerocal.certificates.selection.choose_certificate`'s rules) and issuing a new one.
:class:`MemoryCertificates` keeps them in a list (a notebook, a study, a test); the
platform's store is the database (``tasks.certificates.DatabaseCertificates``).

Before a stored certificate is reused it is reviewed against this flight's nominal camera
(:func:`aerocal.certificates.review.review_camera`: image size, f within its band, principal point, distortion, thermal
slopes); one that fails is not used, and the reason says why. A certificate whose review rejected it is
stored as rejected, and the flight goes on with the nominal camera (:func:`nominal_certificate`).
"""

from __future__ import annotations

import datetime as dt
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from aerocal.camera import Camera
from aerocal.certificates.document import Certificate, ParameterSignificance, Provenance
from aerocal.certificates.identity import CameraIdentity
from aerocal.certificates.review import NOMINAL_PARAMETERS, Review, nominal_sigma, review_camera
from aerocal.certificates.selection import NoCertificateError, choose_certificate
from aerocal.diagnose.extension import ModelTerm, extend_certificate


@dataclass(frozen=True)
class Issued:
    """A certificate as the store holds it: id, version per camera, status (``accepted`` / ``rejected``), the
    stored document (with its version), the camera's make and model, and whether it was stored before this call."""

    id: str
    version: int
    status: str
    document: dict[str, Any]
    camera_label: str
    issued_before: bool = False


class CertificateStore(Protocol):
    """What the pipeline asks of a certificate store (see the module docstring)."""

    def choose(self, camera: CameraIdentity, flight_date: str, temperature_range: Sequence[float] | None, *,
               pin: str | None = None, max_age_days: float | None = None) -> tuple[dict[str, Any], str]:
        """The document of the certificate that applies and why; raises :class:`NoCertificateError`."""
        ...

    def issue(self, document: dict[str, Any]) -> Issued:
        """Store a new certificate (once: a document whose id is stored already comes back as stored)."""
        ...

@dataclass
class MemoryCertificates:
    """A certificate store in memory: the certificates issued (documents with their versions)."""

    documents: list[dict[str, Any]] = field(default_factory=list)

    def certificates(self) -> list[Certificate]:
        return [Certificate.from_dict(d) for d in self.documents]

    def choose(self, camera, flight_date, temperature_range, *, pin=None, max_age_days=None):
        chosen, reason = choose_certificate(self.certificates(), camera, flight_date, temperature_range, pin=pin,
                                            max_age_days=max_age_days)
        return next(d for d in self.documents if d["id"] == chosen.id), reason

    def issue(self, document):
        for stored in self.documents:
            if stored["id"] == document["id"]:
                return self._issued(stored, True)
        cert = Certificate.from_dict(document)
        same = [d for d in self.documents if Certificate.from_dict(d).identity == cert.identity]
        latest = max(same, key=lambda d: d.get("version") or 0, default=None)
        stored = {**document, "version": (latest.get("version") or 0) + 1 if latest else 1,
                  "supersedes": latest["id"] if latest else None}
        self.documents.append(stored)
        return self._issued(stored, False)

    @staticmethod
    def _issued(document: dict, before: bool) -> Issued:
        cert = Certificate.from_dict(document)
        status = cert.review.status if cert.review is not None else "accepted"
        return Issued(cert.id, int(document.get("version") or 1), status, document,
                      f"{cert.identity.make} {cert.identity.model}", before)


def identity_of(cam_doc: dict) -> CameraIdentity:
    """The camera identity of an ingested camera document ("unknown" for a missing part)."""
    return CameraIdentity.from_mapping(cam_doc.get("identity") or {})


def nominal_certificate(cam_doc: dict, run_id: str, why: str) -> dict:
    """A certificate document of the flight's nominal camera (nothing estimated, each nominal value with its own
    uncertainty for the diagnosis), for the block adjustment of a flight whose own calibration was rejected or
    not made; kept with the run, never issued to the store."""
    camera = Camera.from_dict(cam_doc["camera"])
    source = cam_doc.get("source") or "camera.json"
    held = {n: ParameterSignificance(0.0, False, "nominal value, not calibrated", prior_sigma=nominal_sigma(n, camera))
            for n in NOMINAL_PARAMETERS}
    cert = Certificate(identity=identity_of(cam_doc), camera=camera, significance=held,
                       provenance=Provenance(flow_run=run_id),
                       review=Review(notes=(f"the nominal camera of the flight ({source}): {why}",)))
    return cert.to_dict()


def choose_stored(store: CertificateStore, cam_doc: dict, flight: dict, pin: str | None,
                  max_age_days: float | None) -> tuple[dict | None, str]:
    """The stored certificate that applies to the flight (or the one pinned by id), reviewed against the
    flight's nominal camera, as ``(document, reason)``; ``(None, why)`` when none qualifies (with a pin the
    store's :class:`NoCertificateError` propagates, and so does a failed review).

    Raises:
        NoCertificateError: with ``pin``: the pinned certificate does not apply to the flight (from the store), or its
            review against the flight's nominal camera fails.
    """
    try:
        document, reason = store.choose(identity_of(cam_doc), flight["date"], flight.get("temperature_range"),
                                        pin=pin, max_age_days=max_age_days)
    except NoCertificateError as exc:
        if pin:
            raise
        return None, f"no stored certificate applies ({exc})"
    parsed = Certificate.from_dict(document)
    slopes = {}
    if parsed.thermal is not None:
        slopes = {k: getattr(parsed.thermal.model, k, None) for k in ("df_dt", "dcx_dt", "dcy_dt")}
    review = review_camera(parsed.camera, Camera.from_dict(cam_doc["camera"]), dict(parsed.sigmas), slopes)
    if not review.accepted:
        why = f"stored certificate {parsed.id} not reused: {'; '.join(review.problems)}"
        if pin:
            raise NoCertificateError(f"pinned {why}")
        return None, why
    return document, reason


def issue_calibration(store: CertificateStore, document: dict, cam_doc: dict, run_id: str,
                      computed_by: str, usable_here: bool = False) -> tuple[str, dict, str]:
    """Issue the flight's own certificate (once) and say which document the block adjustment uses:
    ``(certificate id, document, reason)``. A certificate its review rejected is stored as rejected (never
    selected for a flight) and the block uses the nominal camera; the reason says so. ``usable_here``: only the
    flight's input errors rejected it (:attr:`aerocal.calibrate.self_calibration.Calibration.usable_on_its_flight`:
    the items they name never reached the fit), so this flight's block uses it all the same: a lens model made on
    the flight's own data is closer to its camera than the nominal one, and later flights still never select it."""
    stored = store.issue(document)
    reason = ("made by this flight's self-calibration" + (f" (run {computed_by}), issued before"
                                                           if stored.issued_before else "")
              + f"; version {stored.version} of camera {stored.camera_label}")
    return _used(stored, cam_doc, run_id, reason, f"this flight's calibration {stored.id} was rejected", usable_here)


def _used(stored: Issued, cam_doc: dict, run_id: str, reason: str, rejected: str,
          usable_here: bool = False) -> tuple[str, dict, str]:
    """``(certificate id, document the block uses, reason)`` for a certificate just issued: its own document when
    the store accepted it, or when it was rejected for the flight's input errors alone (``usable_here``); else the
    nominal camera (:func:`nominal_certificate`, with ``rejected`` as its reason). The review's problems are added
    to ``reason``."""
    if stored.status == "accepted":
        return stored.id, stored.document, reason
    problems = "; ".join((stored.document.get("review") or {}).get("problems") or [])
    if usable_here:
        return stored.id, stored.document, (
            f"{reason}, stored as REJECTED for later flights ({problems}); this flight's block uses it: its fit "
            "passed the review and the items in error were skipped before it")
    reason += f", stored as REJECTED ({problems}): the block uses the nominal camera instead"
    return stored.id, nominal_certificate(cam_doc, run_id, rejected), reason


def extended_certificate(document: dict, terms: dict, flight: dict) -> dict:
    """The document of ``document``'s certificate (a calibration of this flight, made on its measurements with
    the named image terms removed) with the camera terms of ``terms`` (the extension step's ``terms`` document)
    added (:func:`aerocal.diagnose.extension.extend_certificate`)."""
    camera = tuple(ModelTerm.from_dict(t) for t in terms["terms"] if t["name"] in terms["camera_terms"])
    cert = extend_certificate(Certificate.from_dict(document), camera, flight.get("name") or "unnamed flight",
                              terms.get("reference_temperature"))
    return cert.to_dict()


def issue_extension(store: CertificateStore, document: dict, cam_doc: dict, run_id: str, previous: str,
                    terms: dict, usable_here: bool = False) -> tuple[str, dict, str]:
    """Issue the certificate extended by the flight's camera terms as the camera's next version and say which
    document the extended block uses: ``(certificate id, document, reason)``; ``previous`` is why the block used
    the certificate it had. Rejected (the review of a re-calibration failed), it is stored as such and the block
    uses the nominal camera, as :func:`issue_calibration` does (``usable_here`` as there)."""
    stored = store.issue(document)
    reason = (f"version {stored.version} of camera {stored.camera_label}, extended by this flight's diagnosis with "
              f"{', '.join(terms['camera_terms'])} (before: {previous})")
    return _used(stored, cam_doc, run_id, reason, f"the extended certificate {stored.id} was rejected", usable_here)


#: a remainder (or a second flight's value) within this many of the combined sigmas agrees with the certificate
AGREEMENT_SIGMAS = 2.0


def term_agreement(store: CertificateStore, cam_doc: dict, flight: dict, terms: dict,
                   in_use: dict | None = None) -> list[str]:
    """How the camera terms this flight found compare with the same terms in the certificate the store holds for
    the camera (the one that applies to this flight; none: nothing to compare): per term, agreement within
    :data:`AGREEMENT_SIGMAS` of the combined sigma, or the difference in sigmas, with the flights each came from.
    A term the certificate the block used (``in_use``) already applied is left out: what this flight found of it
    is a remainder on top of it, which :func:`certificate_term_remainders` judges."""
    try:
        document, _ = store.choose(identity_of(cam_doc), flight["date"], flight.get("temperature_range"))
    except (NoCertificateError, ValueError):
        return []
    stored = Certificate.from_dict(document)
    applied = set(Certificate.from_dict(in_use).terms) if in_use is not None else set()
    out = []
    for t in terms["terms"]:
        old = stored.terms.get(t["name"])
        if t["name"] not in terms["camera_terms"] or old is None or t["name"] in applied:
            continue
        a, b = np.asarray(t["values"], float), np.asarray(old.values, float)
        s = np.sqrt(np.asarray(t["sigmas"], float) ** 2 + np.asarray(old.sigmas, float) ** 2)
        z = float(np.max(np.abs(a - b) / np.maximum(s, 1e-300)))
        verdict = "agrees with" if z <= AGREEMENT_SIGMAS else f"differs by {z:.1f} sigma from"
        out.append(f"{t['name']} {', '.join(f'{v:.4g}' for v in a)} {t['units']} on this flight {verdict} "
                   f"{', '.join(f'{v:.4g}' for v in b)} +- {', '.join(f'{v:.2g}' for v in old.sigmas)} of certificate "
                   f"{stored.id} (flights {', '.join(old.flights)})" + (f", within {z:.1f} sigma"
                                                                         if z <= AGREEMENT_SIGMAS else ""))
    return out


def _floats(values) -> np.ndarray:
    """A JSON list of numbers as floats, null (a sigma not determined) as NaN."""
    return np.array([np.nan if v is None else float(v) for v in np.atleast_1d(values)], dtype=float)


def certificate_term_remainders(certificate: dict, diagnosis: dict) -> list[str]:
    """What this flight says of each camera term of the certificate its block used (a readout, an affinity, k3,
    thermal slopes): the block applied the term, so the diagnosis's estimate of the same hypothesis is the term's
    remainder on this flight. Named by the diagnosis, its named size; else its first-round estimate given nothing
    else (named or not: a remainder too small to name still says whether the certificate holds), its sigma
    calibrated by the block's overdispersion. Per term one sentence: the certificate's value and sigma, the
    remainder, and whether it is zero within :data:`AGREEMENT_SIGMAS` of the combined sigma (the remainder's and
    the certificate's own); a term the diagnosis did not test on this block is said to be untested.

    Why: a later flight is the certificate's only check on data its fit did not use, and a remainder too small to
    name is no reason to be silent about it (a rendered XT2 readout certified 2 % short, with a sigma a quarter
    of its error: ``benchmarks/RESULTS.md``, the XT2 loop of 2026-12-05)."""
    cert = Certificate.from_dict(certificate)
    if not cert.terms:
        return []
    named = {e["name"]: (e["magnitude"], e["sigma"]) for e in diagnosis.get("effects") or []}
    first = {h["name"]: h for h in diagnosis.get("hypotheses") or [] if h.get("round") == 1}
    phi = max(1.0, float(diagnosis.get("overdispersion") or 1.0))
    out = []
    for name, term in cert.terms.items():
        held = (f"{name} of certificate {cert.id} ({', '.join(f'{v:.4g}' for v in term.values)} +- "
                f"{', '.join(f'{v:.2g}' for v in term.sigmas)} {term.units}, flights {', '.join(term.flights)})")
        if name in named:
            r, s = (_floats(x) for x in named[name])
            how = "named on this flight"
        elif name in first and first[name].get("estimate") and np.all(np.isfinite(_floats(first[name]["sigma"]))):
            r = _floats(first[name]["estimate"])
            s = _floats(first[name]["sigma"]) * np.sqrt(phi)
            how = "not named"
        else:
            out.append(f"{held}: not tested on this flight")
            continue
        if r.shape != (len(term.values),):
            continue
        z = float(np.max(np.abs(r) / np.maximum(np.hypot(s, np.asarray(term.sigmas, dtype=float)), 1e-300)))
        verdict = (f"holds on this flight (within {z:.1f} sigma)" if z <= AGREEMENT_SIGMAS
                   else f"does not hold on this flight: off by {z:.1f} of the combined sigmas")
        out.append(f"{held} {verdict}; the remainder here {', '.join(f'{v:+.3g}' for v in r)} +- "
                   f"{', '.join(f'{v:.2g}' for v in s)} {term.units} ({how})")
    return out


def new_run_id() -> str:
    """A run id for a run outside the platform: the time (UTC) and a short random suffix."""
    return f"{dt.datetime.now(dt.UTC):%Y%m%dT%H%M%S}-{uuid.uuid4().hex[:8]}"
