"""What the platform records of a flight run as the pipeline goes: the flight, the settings in effect, the
certificate and why (:class:`aerocal.pipeline.process.RunRecorder` over the ``runs`` and ``flights`` rows)."""

from __future__ import annotations

from typing import Any

from aerocal.pipeline.config import Adjustments
from storage.flights import register_flight
from storage.runs import get_run, record_certificate
from storage.steps import StepContext


class RunRecorder:
    """Records on the run ``ctx.run_id``; ``configuration`` is the run's configuration record (the process
    configuration, the certificate asked for, folders, Dask address) to which the effective adjustment
    settings are added."""

    def __init__(self, ctx: StepContext, configuration: dict[str, Any]) -> None:
        self.ctx, self.base = ctx, dict(configuration)

    def flight_ingested(self, flight, camera) -> None:
        with self.ctx.database.session() as session:
            row = register_flight(session, flight["name"], flight["date"], camera.key, crs=flight.get("crs"),
                                  n_images=flight["n_images"], bbox=flight.get("bbox"),
                                  temperature_range=flight.get("temperature_range"))
            get_run(session, self.ctx.run_id).flight = row
            session.commit()

    def configuration(self, adjustments: Adjustments) -> None:
        with self.ctx.database.session() as session:
            get_run(session, self.ctx.run_id).configuration = {**self.base, "effective": adjustments.to_json()}
            session.commit()

    def certificate(self, certificate_id, reason) -> None:
        with self.ctx.database.session() as session:
            record_certificate(session, self.ctx.run_id, certificate_id, reason)
            session.commit()
