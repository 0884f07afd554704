"""The camera repository: one row per physical camera (make, model, serial number, lens).

The identity is :class:`aerocal.certificates.identity.CameraIdentity`, the class ingest, certificates and the
exchange formats use (re-exported here). The four ``cameras`` columns hold its parts as its ``key`` writes
them: ``"unknown"`` for a lens not recorded (a value, not NULL, so that the unique constraint on the four
fields holds on every database). Make, model and serial must be known:
a certificate of "some camera" must never be selected for another one, so :func:`stored_identity` refuses an
identity without them. A camera that records no serial number is identified by make, model, lens and frame
size, with the serial ``"no-serial WxH"`` (:data:`aerocal.certificates.identity.NO_SERIAL`): its certificates may be
shared by several bodies of the model, which its label says.
"""

from __future__ import annotations

import sqlalchemy as sa
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.orm import Session

from aerocal.certificates.identity import UNKNOWN, CameraIdentity
from storage.errors import NotFoundError
from storage.models import Camera, utcnow

__all__ = [
    "UNKNOWN",
    "CameraIdentity",
    "find_camera",
    "get_camera",
    "get_or_create_camera",
    "list_cameras",
    "stored_identity",
]


def stored_identity(camera: CameraIdentity | Camera | object) -> CameraIdentity:
    """The identity of ``camera`` (an identity, a stored :class:`Camera`, a mapping or ``"make|model|serial"``
    / ``"make|model|serial|lens"``: :meth:`CameraIdentity.coerce`), checked for the database.

    Raises ``ValueError`` when make, model or serial is unknown.
    """
    identity = CameraIdentity.coerce(camera)
    if identity.missing:
        raise ValueError(
            f"camera identity {identity.key!r} lacks {', '.join(identity.missing)}: give make, model and serial "
            "number"
        )
    return identity


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
    identity = stored_identity(camera)
    query = sa.select(Camera).where(_where(identity))
    if lock:
        query = query.with_for_update()
    return session.scalars(query).one_or_none()


def get_camera(session: Session, camera: CameraIdentity | str) -> Camera:
    """The stored camera with this identity; :class:`NotFoundError` when there is none."""
    found = find_camera(session, camera)
    if found is None:
        raise NotFoundError(f"camera {stored_identity(camera)} is not in the database")
    return found


def get_or_create_camera(session: Session, camera: CameraIdentity | str, lock: bool = False) -> Camera:
    """The stored camera with this identity, inserting it when new (safe against concurrent inserts).

    The insert is ``INSERT ... ON CONFLICT DO NOTHING`` (PostgreSQL and SQLite), so two processes
    registering the same camera at once end with one row. ``lock`` as in :func:`find_camera`.
    """
    identity = stored_identity(camera)
    found = find_camera(session, identity, lock=lock)
    if found is not None:
        return found
    dialect = session.get_bind().dialect.name
    values = identity.as_dict()
    insert = {"postgresql": postgresql.insert, "sqlite": sqlite.insert}.get(dialect)
    if insert is not None:
        session.execute(insert(Camera).values(**values, created=utcnow()).on_conflict_do_nothing())
    else:  # pragma: no cover - only SQLite and PostgreSQL are supported
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
