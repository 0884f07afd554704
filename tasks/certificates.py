"""The platform's certificate store for the flight pipeline: the database (:mod:`storage.certificates`).

:class:`DatabaseCertificates` is the :class:`aerocal.pipeline.certificates.CertificateStore` that
``flows.process`` hands to :func:`aerocal.pipeline.process`: choosing goes through
:func:`storage.certificates.select_certificate` (the engine's rules over the stored rows), issuing through
:func:`storage.certificates.issue_certificate` (versions assigned under a lock); the run's row records the choice
(:class:`tasks.run_records.RunRecorder`).
"""

from __future__ import annotations

from aerocal.pipeline.certificates import Issued
from storage.certificates import get_certificate, issue_certificate, select_certificate
from storage.errors import NotFoundError
from storage.steps import StepContext


def _issued(stored, before: bool) -> Issued:
    return Issued(stored.id, stored.version, stored.status, stored.document,
                  f"{stored.camera.make} {stored.camera.model}", before)


class DatabaseCertificates:
    """The certificates of the database at ``ctx.database_url``."""

    def __init__(self, ctx: StepContext) -> None:
        self.ctx = ctx

    def choose(self, camera, flight_date, temperature_range, *, pin=None, max_age_days=None):
        with self.ctx.database.session() as session:
            cert, reason = select_certificate(session, camera.key, flight_date, temperature_range,
                                              max_age_days=max_age_days, pin=pin)
            return cert.document, reason

    def issue(self, document):
        with self.ctx.database.session() as session:
            try:
                return _issued(get_certificate(session, document["id"]), True)
            except NotFoundError:
                return _issued(issue_certificate(session, document), False)
