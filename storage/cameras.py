"""Camera identities and the camera repository.

A camera is identified by make, model, serial number and lens, as in
:class:`aerocal.certificate.CameraIdentity`. The lens is ``"unknown"`` when not recorded (a value, not
NULL, so that the unique constraint on the four fields holds on every database; an empty lens is read
as ``"unknown"``). Make, model and serial must be known: a certificate of "some camera" must never be
selected for another one, so an identity without them is refused. A camera that records no serial number
is identified by make, model, lens and frame size, with the serial ``"no-serial WxH"``
(:data:`aerocal.ingest.inferred.NO_SERIAL`): its certificates may be shared by several bodies of the model,
which :attr:`CameraIdentity.shared_body` and its text say. The textual form used by the Arrow
``images`` table is ``"make|model|serial|lens"``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.orm import Session

from aerocal.ingest.camera_identity import is_shared_identity
from storage.errors import CertificateDocumentError, NotFoundError
from storage.models import Camera

_FIELDS = ("make", "model", "serial", "lens")

#: The value of an identity part that was not recorded.
UNKNOWN = "unknown"


@dataclass(frozen=True)
class CameraIdentity:
    """Make, model, serial number and lens of one camera (surrounding whitespace is stripped).

    Raises ``ValueError`` when make, model or serial is empty or ``"unknown"``.
    """

    make: str
    model: str
    serial: str
    lens: str = UNKNOWN

    def __post_init__(self) -> None:
        for name in _FIELDS:
            value = getattr(self, name)
            value = "" if value is None else str(value).strip()
            if name == "lens" and not value:
                value = UNKNOWN
            object.__setattr__(self, name, value)
        missing = [name for name in _FIELDS[:3] if getattr(self, name).lower() in ("", UNKNOWN)]
        if missing:
            raise ValueError(
                f"camera identity {self.key!r} lacks {', '.join(missing)}: give make, model and serial number"
            )

    @classmethod
    def parse(cls, text: str) -> CameraIdentity:
        """From ``"make|model|serial"`` or ``"make|model|serial|lens"`` (the ``images.camera_id`` form)."""
        parts = str(text).split("|")
        if len(parts) not in (3, 4):
            raise ValueError(f"camera {text!r}: expected 'make|model|serial' or 'make|model|serial|lens'")
        return cls(*parts)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, object], where: str = "camera") -> CameraIdentity:
        """From a dict with keys make, model, serial and optionally lens (a certificate's ``camera``)."""
        if not isinstance(mapping, Mapping):
            raise CertificateDocumentError(f"{where} must be an object with make, model, serial, lens")
        values = {}
        for name in _FIELDS:
            value = mapping.get(name)
            if value is not None and not isinstance(value, str | int):
                raise CertificateDocumentError(f"{where}.{name} must be a string, got {type(value).__name__}")
            values[name] = "" if value is None else str(value)
        try:
            return cls(**values)
        except ValueError as exc:
            raise CertificateDocumentError(f"{where}: {exc}") from None

    @classmethod
    def coerce(cls, value: CameraIdentity | Camera | Mapping[str, object] | str) -> CameraIdentity:
        """From an identity, a stored :class:`Camera`, a mapping or ``"make|model|serial|lens"``."""
        if isinstance(value, CameraIdentity):
            return value
        if isinstance(value, Camera):
            return cls(value.make, value.model, value.serial, value.lens)
        if isinstance(value, Mapping):
            return cls.from_mapping(value)
        return cls.parse(value)

    @property
    def key(self) -> str:
        """``"make|model|serial|lens"``."""
        return "|".join((self.make, self.model, self.serial, self.lens))

    def as_dict(self) -> dict[str, str]:
        """``{"make", "model", "serial", "lens"}``."""
        return {name: getattr(self, name) for name in _FIELDS}

    @property
    def shared_body(self) -> bool:
        """True for a camera that records no serial number, identified by make, model, lens and frame size
        (serial ``"no-serial WxH"``): its certificates may be shared by several bodies of that model."""
        return is_shared_identity(self.serial)

    def __str__(self) -> str:
        if self.shared_body:
            text = f"{self.make} {self.model} ({self.serial}: any body of this model; no serial recorded)"
            return text if self.lens == UNKNOWN else f"{text} lens {self.lens}"
        text = f"{self.make} {self.model} s/n {self.serial}"
        return text if self.lens == UNKNOWN else f"{text} lens {self.lens}"


def _where(identity: CameraIdentity) -> sa.ColumnElement[bool]:
    return sa.and_(
        Camera.make == identity.make,
        Camera.model == identity.model,
        Camera.serial == identity.serial,
        Camera.lens == identity.lens,
    )


def find_camera(session: Session, camera: CameraIdentity | str, lock: bool = False) -> Camera | None:
    """The stored camera with this identity, or ``None``.

    With ``lock`` the row is locked until the transaction ends (``SELECT ... FOR UPDATE`` on
    PostgreSQL; SQLite has no row locks, use :func:`storage.database.begin_write` there).
    """
    identity = CameraIdentity.coerce(camera)
    query = sa.select(Camera).where(_where(identity))
    if lock:
        query = query.with_for_update()
    return session.scalars(query).one_or_none()


def get_camera(session: Session, camera: CameraIdentity | str) -> Camera:
    """The stored camera with this identity; :class:`NotFoundError` when there is none."""
    found = find_camera(session, camera)
    if found is None:
        raise NotFoundError(f"camera {CameraIdentity.coerce(camera)} is not in the database")
    return found


def get_or_create_camera(session: Session, camera: CameraIdentity | str, lock: bool = False) -> Camera:
    """The stored camera with this identity, inserting it when new (safe against concurrent inserts).

    The insert is ``INSERT ... ON CONFLICT DO NOTHING`` (PostgreSQL and SQLite), so two processes
    registering the same camera at once end with one row. ``lock`` as in :func:`find_camera`.
    """
    identity = CameraIdentity.coerce(camera)
    found = find_camera(session, identity, lock=lock)
    if found is not None:
        return found
    dialect = session.get_bind().dialect.name
    values = identity.as_dict()
    if dialect == "postgresql":
        from sqlalchemy.dialects.postgresql import insert
    elif dialect == "sqlite":
        from sqlalchemy.dialects.sqlite import insert
    else:  # pragma: no cover - only SQLite and PostgreSQL are supported
        insert = None
    if insert is not None:
        from storage.models import utcnow

        session.execute(insert(Camera).values(**values, created=utcnow()).on_conflict_do_nothing())
    else:  # pragma: no cover
        with session.begin_nested():
            session.add(Camera(**values))
    found = find_camera(session, identity, lock=lock)
    assert found is not None
    return found


def list_cameras(session: Session) -> list[Camera]:
    """Every stored camera, by make, model, serial, lens."""
    return list(
        session.scalars(sa.select(Camera).order_by(Camera.make, Camera.model, Camera.serial, Camera.lens))
    )
