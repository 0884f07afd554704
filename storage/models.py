"""The relational model of aerocal: cameras, certificates, flights, campaigns, runs, artifacts, lineage.

SQLAlchemy 2.0 typed declarative mapping with portable types only, so that SQLite and PostgreSQL hold
the same schema: JSON documents in ``sqlalchemy.JSON``, times in :class:`UTCDateTime` (timezone-aware,
always returned in UTC, also on SQLite, which has no timezone type), dates as ``DATE``.

The schema itself is created and changed only by the Alembic migrations in ``storage/migrations``;
``Base.metadata`` describes the head revision (a test checks that the two agree).

Certificates are immutable: changing or deleting a stored one raises
:class:`~storage.errors.ImmutableCertificateError` in the ORM (at assignment and at flush), and the
database refuses ``UPDATE`` and ``DELETE`` on the table with a trigger, so raw SQL cannot either.
"""

from __future__ import annotations

import copy
from datetime import UTC, date, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy import (
    JSON,
    BigInteger,
    CheckConstraint,
    Column,
    Date,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    MetaData,
    String,
    Table,
    Text,
    TypeDecorator,
    UniqueConstraint,
    event,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship

from aerocal.certificates.identity import CameraIdentity
from storage.errors import ImmutableCertificateError

#: Constraint names follow one pattern, so migrations (and SQLite batch mode) can refer to them.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

#: Roles of an artifact in a run.
ARTIFACT_ROLES = ("input", "output")

#: Statuses a run goes through.
RUN_STATUSES = ("running", "completed", "failed", "cancelled")


def utcnow() -> datetime:
    """The current time, timezone-aware UTC."""
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator):
    """A timezone-aware timestamp stored in UTC and always returned as an aware UTC ``datetime``.

    Naive datetimes are refused (their timezone is unknown). PostgreSQL stores ``timestamptz``; SQLite
    stores the UTC wall time as text, so ordering by the column is chronological on both.
    """

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect: sa.Dialect) -> datetime | None:
        if value is None:
            return None
        if not isinstance(value, datetime):
            raise TypeError(f"expected a datetime, got {type(value).__name__}")
        if value.tzinfo is None or value.utcoffset() is None:
            raise ValueError(f"naive datetime {value.isoformat()}: give a timezone-aware (UTC) time")
        return value.astimezone(UTC)

    def process_result_value(self, value: datetime | None, dialect: sa.Dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value.astimezone(UTC)


class Base(DeclarativeBase):
    """Declarative base of every aerocal table."""

    metadata = MetaData(naming_convention=NAMING_CONVENTION)
    type_annotation_map = {datetime: UTCDateTime(), date: Date(), dict[str, Any]: JSON()}


campaign_flights = Table(
    "campaign_flights",
    Base.metadata,
    Column("campaign_id", ForeignKey("campaigns.id", ondelete="CASCADE"), primary_key=True),
    Column("flight_id", ForeignKey("flights.id", ondelete="CASCADE"), primary_key=True),
)


class Camera(Base):
    """One physical camera: make, model, serial number and lens (``"unknown"`` when not recorded)."""

    __tablename__ = "cameras"
    __table_args__ = (UniqueConstraint("make", "model", "serial", "lens"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    make: Mapped[str] = mapped_column(String(128))
    model: Mapped[str] = mapped_column(String(128))
    serial: Mapped[str] = mapped_column(String(128))
    lens: Mapped[str] = mapped_column(String(128), default="unknown")
    created: Mapped[datetime] = mapped_column(default=utcnow)

    certificates: Mapped[list[Certificate]] = relationship(
        back_populates="camera", order_by="Certificate.version", viewonly=True
    )

    @property
    def identity(self) -> CameraIdentity:
        """The camera's identity (make, model, serial, lens)."""
        return CameraIdentity(self.make, self.model, self.serial, self.lens)

    @property
    def label(self) -> str:
        """Human-readable identity, e.g. ``NEC TS9260 s/n 123``
        (:attr:`aerocal.certificates.identity.CameraIdentity.label`: a camera without a recorded serial number
        says its certificates may serve several bodies of the model)."""
        return self.identity.label


class Certificate(Base):
    """A stored calibration certificate: the full JSON document plus the columns selection needs.

    Attributes:
        id: the document's id (uuid4 hex).
        version: 1, 2, ... per camera, in the order the certificates were issued.
        supersedes: id of the camera's previous certificate (``None`` for version 1).
        issued: when the certificate was issued (UTC).
        calibration_date: date of the data the calibration was computed from (``conditions.date``,
            else the issue date); a certificate applies to flights on or after this date.
        temperature_min, temperature_max: temperature range (degC) the certificate was determined
            over: ``thermal.valid_range`` when it has a thermal model, else
            ``conditions.temperature_range``; ``None`` when not recorded.
        thermal_kind: kind of thermal IO model (``"linear"``), ``None`` for a constant IO.
        model_kind: camera model kind (``"brown"``).
        sigma0: a-posteriori standard deviation of unit weight of the calibration adjustment.
        reprojection_rms_px: RMS reprojection error of the calibration, pixels.
        status: ``"accepted"`` or ``"rejected"`` (the document's ``review.status``; a certificate without
            a review is accepted); a rejected certificate is on record but never selected for a flight.
    """

    __tablename__ = "certificates"
    __table_args__ = (
        UniqueConstraint("camera_id", "version"),
        UniqueConstraint("supersedes"),
        CheckConstraint("version >= 1", name="version_positive"),
        Index("ix_certificates_camera_date", "camera_id", "calibration_date"),
    )

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    camera_id: Mapped[int] = mapped_column(ForeignKey("cameras.id"))
    version: Mapped[int] = mapped_column(Integer)
    supersedes: Mapped[str | None] = mapped_column(ForeignKey("certificates.id"))
    issued: Mapped[datetime] = mapped_column()
    calibration_date: Mapped[date] = mapped_column()
    temperature_min: Mapped[float | None] = mapped_column(Float)
    temperature_max: Mapped[float | None] = mapped_column(Float)
    thermal_kind: Mapped[str | None] = mapped_column(String(32))
    model_kind: Mapped[str] = mapped_column(String(32))
    sigma0: Mapped[float | None] = mapped_column(Float)
    reprojection_rms_px: Mapped[float | None] = mapped_column(Float)
    stored: Mapped[datetime] = mapped_column(default=utcnow)
    _document: Mapped[dict[str, Any]] = mapped_column("document", JSON)
    status: Mapped[str] = mapped_column(String(16), default="accepted", server_default="accepted")

    camera: Mapped[Camera] = relationship(back_populates="certificates", lazy="joined")

    @property
    def document(self) -> dict[str, Any]:
        """A deep copy of the certificate document (editing the copy never touches the stored record)."""
        return copy.deepcopy(self._document)

    @property
    def temperature_range(self) -> tuple[float, float] | None:
        """``(min, max)`` in degC, or ``None`` when not recorded."""
        if self.temperature_min is None or self.temperature_max is None:
            return None
        return (self.temperature_min, self.temperature_max)


class Flight(Base):
    """A flight: one camera, one date, one area, in one projected CRS.

    ``bbox_*`` are the footprint's bounds in ``crs`` (metres); ``temperature_min/max`` the sensor
    temperature range (degC) over the flight when recorded.
    """

    __tablename__ = "flights"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(256), unique=True)
    date: Mapped[date] = mapped_column()
    camera_id: Mapped[int] = mapped_column(ForeignKey("cameras.id"), index=True)
    area: Mapped[str | None] = mapped_column(String(256))
    crs: Mapped[str | None] = mapped_column(String(256))
    bbox_min_x: Mapped[float | None] = mapped_column(Float)
    bbox_min_y: Mapped[float | None] = mapped_column(Float)
    bbox_max_x: Mapped[float | None] = mapped_column(Float)
    bbox_max_y: Mapped[float | None] = mapped_column(Float)
    n_images: Mapped[int] = mapped_column(Integer, default=0)
    temperature_min: Mapped[float | None] = mapped_column(Float)
    temperature_max: Mapped[float | None] = mapped_column(Float)
    created: Mapped[datetime] = mapped_column(default=utcnow)

    camera: Mapped[Camera] = relationship(lazy="joined")
    campaigns: Mapped[list[Campaign]] = relationship(secondary=campaign_flights, back_populates="flights")

    @property
    def temperature_range(self) -> tuple[float, float] | None:
        """``(min, max)`` sensor temperature over the flight in degC, or ``None``."""
        if self.temperature_min is None or self.temperature_max is None:
            return None
        return (self.temperature_min, self.temperature_max)


class Campaign(Base):
    """A named set of flights, optionally processed on a cron schedule (e.g. ``"0 3 * * *"``)."""

    __tablename__ = "campaigns"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(256), unique=True)
    cron: Mapped[str | None] = mapped_column(String(128))
    description: Mapped[str | None] = mapped_column(Text)
    created: Mapped[datetime] = mapped_column(default=utcnow)

    flights: Mapped[list[Flight]] = relationship(
        secondary=campaign_flights, back_populates="campaigns", order_by="Flight.date"
    )


class Run(Base):
    """One flow run (its id is the Prefect flow-run id) and what it ran with.

    Attributes:
        configuration: the full configuration the run used (JSON).
        timings: seconds spent per step, ``{step: seconds}``.
        certificate_id, certificate_reason: the certificate the run used and why it was chosen.
        runner: ``"host:pid:start"`` of the process running it (:func:`storage.runs.reap_dead_runs`).
    """

    __tablename__ = "runs"
    __table_args__ = (CheckConstraint(f"status IN {RUN_STATUSES!r}", name="status_known"),)

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    kind: Mapped[str] = mapped_column(String(64), index=True)
    status: Mapped[str] = mapped_column(String(16), default="running")
    configuration: Mapped[dict[str, Any]] = mapped_column(default=dict)
    code_version: Mapped[str | None] = mapped_column(String(128))
    started: Mapped[datetime] = mapped_column(default=utcnow, index=True)
    ended: Mapped[datetime | None] = mapped_column()
    timings: Mapped[dict[str, Any]] = mapped_column(default=dict)
    flight_id: Mapped[int | None] = mapped_column(ForeignKey("flights.id"), index=True)
    campaign_id: Mapped[int | None] = mapped_column(ForeignKey("campaigns.id"))
    certificate_id: Mapped[str | None] = mapped_column(ForeignKey("certificates.id"))
    certificate_reason: Mapped[str | None] = mapped_column(Text)
    error: Mapped[str | None] = mapped_column(Text)
    runner: Mapped[str | None] = mapped_column(String(128))

    flight: Mapped[Flight | None] = relationship()
    campaign: Mapped[Campaign | None] = relationship()
    certificate: Mapped[Certificate | None] = relationship()


class Artifact(Base):
    """A content-addressed file: one row per distinct content (sha256).

    Attributes:
        uri: where the content lives (``file://`` URI under the artifact store's root).
        kind: what it is (a table kind of :mod:`aerocal.tables`, ``"image"``, ``"report"``, ...).
        schema_name: the schema its content follows (e.g. ``"aerocal.tables/observations"``), if any.
        producing_run_id: the run that first produced this content.
    """

    __tablename__ = "artifacts"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    sha256: Mapped[str] = mapped_column(String(64), unique=True)
    uri: Mapped[str] = mapped_column(String(2048))
    kind: Mapped[str] = mapped_column(String(64), index=True)
    schema_name: Mapped[str | None] = mapped_column(String(128))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    producing_run_id: Mapped[str | None] = mapped_column(ForeignKey("runs.id"), index=True)
    created: Mapped[datetime] = mapped_column(default=utcnow)


class RunArtifact(Base):
    """An artifact a run read (``role="input"``) or wrote (``role="output"``)."""

    __tablename__ = "run_artifacts"
    __table_args__ = (CheckConstraint(f"role IN {ARTIFACT_ROLES!r}", name="role_known"),)

    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), primary_key=True)
    artifact_id: Mapped[int] = mapped_column(ForeignKey("artifacts.id"), primary_key=True, index=True)
    role: Mapped[str] = mapped_column(String(16), primary_key=True)

    artifact: Mapped[Artifact] = relationship(lazy="joined")


class LineageEdge(Base):
    """Within ``run_id``, ``output_artifact_id`` was derived from ``input_artifact_id``."""

    __tablename__ = "lineage_edges"
    __table_args__ = (UniqueConstraint("run_id", "input_artifact_id", "output_artifact_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"))
    input_artifact_id: Mapped[int] = mapped_column(ForeignKey("artifacts.id"), index=True)
    output_artifact_id: Mapped[int] = mapped_column(ForeignKey("artifacts.id"), index=True)


# ----------------------------------------------------------------------------- certificate immutability
_IMMUTABLE_MESSAGE = "certificates are immutable: issue a new certificate that supersedes this one"

#: Triggers that make the database itself refuse UPDATE/DELETE of certificates (same text as migration 0001).
SQLITE_IMMUTABLE_TRIGGERS = (
    f"""CREATE TRIGGER certificates_no_update BEFORE UPDATE ON certificates
        BEGIN SELECT RAISE(ABORT, '{_IMMUTABLE_MESSAGE}'); END""",
    f"""CREATE TRIGGER certificates_no_delete BEFORE DELETE ON certificates
        BEGIN SELECT RAISE(ABORT, '{_IMMUTABLE_MESSAGE}'); END""",
)
POSTGRESQL_IMMUTABLE_TRIGGERS = (
    f"""CREATE FUNCTION aerocal_certificates_immutable() RETURNS trigger LANGUAGE plpgsql AS $$
        BEGIN RAISE EXCEPTION '{_IMMUTABLE_MESSAGE}'; END; $$""",
    """CREATE TRIGGER certificates_immutable BEFORE UPDATE OR DELETE ON certificates
        FOR EACH ROW EXECUTE FUNCTION aerocal_certificates_immutable()""",
)

for _ddl in SQLITE_IMMUTABLE_TRIGGERS:
    event.listen(Certificate.__table__, "after_create", sa.DDL(_ddl).execute_if(dialect="sqlite"))
for _ddl in POSTGRESQL_IMMUTABLE_TRIGGERS:
    event.listen(Certificate.__table__, "after_create", sa.DDL(_ddl).execute_if(dialect="postgresql"))
event.listen(
    Certificate.__table__,
    "after_drop",
    sa.DDL("DROP FUNCTION IF EXISTS aerocal_certificates_immutable()").execute_if(dialect="postgresql"),
)


def _refuse_change(attribute: str):
    def listener(target: Certificate, value: object, oldvalue: object, initiator: object) -> None:
        if sa.inspect(target).has_identity:
            raise ImmutableCertificateError(
                f"certificate {target.id} (version {target.version}) cannot change {attribute!r}: "
                f"{_IMMUTABLE_MESSAGE}"
            )

    return listener


for _name, _column_property in Certificate.__mapper__.column_attrs.items():
    event.listen(getattr(Certificate, _name), "set", _refuse_change(_name.lstrip("_")))


@event.listens_for(Session, "before_flush")
def _refuse_certificate_changes(session: Session, _flush_context: object, _instances: object) -> None:
    for obj in session.deleted:
        if isinstance(obj, Certificate):
            raise ImmutableCertificateError(f"certificate {obj.id} cannot be deleted: {_IMMUTABLE_MESSAGE}")
    for obj in session.dirty:
        if isinstance(obj, Certificate) and session.is_modified(obj, include_collections=False):
            raise ImmutableCertificateError(f"certificate {obj.id} cannot be modified: {_IMMUTABLE_MESSAGE}")
