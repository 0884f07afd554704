"""The flight and campaign repository.

A flight is registered once per name (re-registering updates its fields: ingest may learn the image
count and temperature range later). A campaign is a named set of flights with an optional cron
schedule for its recurring processing. Functions add and change rows in the caller's session; the
caller commits.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from datetime import date, datetime

import sqlalchemy as sa
from sqlalchemy.orm import Session

from storage.cameras import CameraIdentity, get_or_create_camera
from storage.errors import NotFoundError
from storage.models import Camera, Campaign, Flight


def register_flight(
    session: Session,
    name: str,
    flight_date: date | datetime | str,
    camera: CameraIdentity | Camera | str,
    crs: str | None = None,
    n_images: int = 0,
    bbox: Sequence[float] | None = None,
    area: str | None = None,
    temperature_range: Sequence[float] | None = None,
) -> Flight:
    """Insert or update the flight called ``name``.

    Args:
        flight_date: the (UTC) date of the flight; ISO text is accepted.
        camera: the camera identity (registered if new).
        crs: the flight's projected CRS, e.g. ``"EPSG:32632"``.
        bbox: ``(min_x, min_y, max_x, max_y)`` of the footprint in ``crs`` (metres).
        area: a name for the area flown (e.g. ``"Seneca"``).
        temperature_range: ``(min, max)`` sensor temperature in degC over the flight.
    """
    if isinstance(flight_date, datetime):
        day = flight_date.date()
    elif isinstance(flight_date, date):
        day = flight_date
    else:
        day = date.fromisoformat(str(flight_date)[:10])
    stored_camera = camera if isinstance(camera, Camera) else get_or_create_camera(session, camera)
    flight = session.scalars(sa.select(Flight).where(Flight.name == name)).one_or_none()
    if flight is None:
        flight = Flight(name=name, date=day, camera_id=stored_camera.id, n_images=int(n_images))
        session.add(flight)
    flight.date, flight.camera_id, flight.n_images = day, stored_camera.id, int(n_images)
    flight.crs, flight.area = crs, area
    if bbox is not None:
        if len(bbox) != 4 or bbox[0] > bbox[2] or bbox[1] > bbox[3]:
            raise ValueError(f"flight {name}: bbox must be (min_x, min_y, max_x, max_y), got {list(bbox)}")
        flight.bbox_min_x, flight.bbox_min_y, flight.bbox_max_x, flight.bbox_max_y = (float(v) for v in bbox)
    if temperature_range is not None:
        lo, hi = (float(v) for v in temperature_range)
        flight.temperature_min, flight.temperature_max = min(lo, hi), max(lo, hi)
    session.flush()
    return flight


def get_flight(session: Session, name: str) -> Flight:
    """The flight called ``name``; :class:`NotFoundError` when there is none."""
    flight = session.scalars(sa.select(Flight).where(Flight.name == name)).one_or_none()
    if flight is None:
        raise NotFoundError(f"flight {name!r} not found; register it first")
    return flight


def list_flights(session: Session, camera: CameraIdentity | str | None = None) -> list[Flight]:
    """Flights by date, optionally of one camera."""
    query = sa.select(Flight).order_by(Flight.date, Flight.name)
    if camera is not None:
        identity = CameraIdentity.coerce(camera)
        query = query.join(Camera).where(
            Camera.make == identity.make,
            Camera.model == identity.model,
            Camera.serial == identity.serial,
            Camera.lens == identity.lens,
        )
    return list(session.scalars(query))


def create_campaign(
    session: Session,
    name: str,
    cron: str | None = None,
    flights: Iterable[Flight | str] = (),
    description: str | None = None,
) -> Campaign:
    """Insert or update the campaign called ``name`` and add ``flights`` (objects or names) to it.

    ``cron`` is a five-field cron expression in UTC (e.g. ``"0 3 * * *"``), or ``None`` for on demand.
    """
    if cron is not None and len(cron.split()) != 5:
        raise ValueError(
            f"campaign {name}: cron {cron!r} must have five fields (minute hour day month weekday)"
        )
    campaign = session.scalars(sa.select(Campaign).where(Campaign.name == name)).one_or_none()
    if campaign is None:
        campaign = Campaign(name=name)
        session.add(campaign)
    campaign.cron, campaign.description = cron, description
    add_flights_to_campaign(session, campaign, flights)
    return campaign


def add_flights_to_campaign(session: Session, campaign: Campaign, flights: Iterable[Flight | str]) -> None:
    """Add ``flights`` (objects or names) to ``campaign``; flights already in it are skipped."""
    for flight in flights:
        stored = get_flight(session, flight) if isinstance(flight, str) else flight
        if stored not in campaign.flights:
            campaign.flights.append(stored)
    session.flush()


def get_campaign(session: Session, name: str) -> Campaign:
    """The campaign called ``name``; :class:`NotFoundError` when there is none."""
    campaign = session.scalars(sa.select(Campaign).where(Campaign.name == name)).one_or_none()
    if campaign is None:
        raise NotFoundError(f"campaign {name!r} not found; create it first")
    return campaign
