"""Campaigns: several flights of one camera, processed together or on a cron schedule.

* :func:`add_flights` registers flight folders (ingested once, so that date, camera, CRS and temperature
  range are known) and adds them to a campaign with an optional cron schedule (UTC).
* :func:`run_campaign` (flow) processes the campaign's flights in date order with
  ``certificate="auto"``: the first flight of a camera without an applicable certificate self-calibrates
  and issues one, the following flights reuse it (their runs record it and why).
* :func:`register_campaign_deployments` registers one Prefect deployment of :func:`run_campaign` per
  campaign with a cron schedule and returns at once; :func:`serve_campaigns` then serves them
  (blocking), so scheduled processing runs unattended.

The folder of each flight is kept as a small JSON artifact per campaign (kind ``campaign-folders``,
``schema_name`` ``aerocal.campaign/<name>``, newest wins), since the flights table stores no paths.
"""

from __future__ import annotations

import dataclasses
import json
import os
import uuid
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from prefect import flow, serve
from prefect.client.schemas.schedules import CronSchedule
from prefect.deployments.runner import EntrypointType
from sqlalchemy.engine import make_url

from aerocal.pipeline import FolderDataset, ProcessConfig, RunSummary
from aerocal.pipeline.certificates import identity_of
from aerocal.pipeline.ingest_step import ingest_step
from aerocal.pipeline.runner import JsonOutput
from flows.environment import resolve_storage
from flows.process import FlowInputError, process_flight
from storage.flights import create_campaign, get_campaign, register_flight
from storage.models import Artifact, Campaign
from storage.runs import finish_run, start_run
from storage.steps import StepContext
from tasks.runner import StoreRunner

FOLDERS_KIND = "campaign-folders"


def _folders_schema(name: str) -> str:
    return f"aerocal.campaign/{name}"


def campaign_folders(ctx_or_location: Any, name: str) -> dict[str, str]:
    """Flight name -> folder of the campaign ``name`` (empty when none were added)."""
    ctx = (
        ctx_or_location
        if isinstance(ctx_or_location, StepContext)
        else StepContext(ctx_or_location.database_url, ctx_or_location.artifact_root, "")
    )
    with ctx.database.session() as session:
        row = session.scalars(
            sa.select(Artifact)
            .where(Artifact.kind == FOLDERS_KIND, Artifact.schema_name == _folders_schema(name))
            .order_by(Artifact.id.desc())
            .limit(1)
        ).first()
        return json.loads(ctx.store.read_bytes(row)) if row is not None else {}


def add_flights(
    name: str,
    flight_dirs: list[str | Path],
    cron: str | None = None,
    description: str | None = None,
    database_url: str | None = None,
    artifact_root: str | None = None,
) -> list[str]:
    """Register ``flight_dirs`` (ingesting each: a later processing run reuses that step) and add them to
    campaign ``name`` (created if new; ``cron`` a five-field UTC expression, ``None`` keeps the current
    one). Returns the flight names."""
    where = resolve_storage(database_url, artifact_root)
    if cron is not None:
        try:
            CronSchedule(cron=cron)
        except ValueError:
            raise FlowInputError(
                f"cron {cron!r} is not a valid cron expression; give five fields, e.g. "
                "'0 3 * * *' (03:00 UTC daily)"
            ) from None
    ctx = StepContext(where.database_url, where.artifact_root, uuid.uuid4().hex)
    with ctx.database.session() as session:
        start_run(
            session,
            ctx.run_id,
            "campaign_add",
            configuration={"campaign": name, "cron": cron, "flights": [str(d) for d in flight_dirs]},
        )
        session.commit()
    folders = campaign_folders(ctx, name)
    names = []
    try:
        for d in flight_dirs:
            folder = Path(d).resolve()
            if not folder.is_dir():
                raise FlowInputError(f"{folder} is not a folder; give flight folders")
            runner, dataset = StoreRunner(ctx, prefect_tasks=False), FolderDataset(folder)
            ing = ingest_step(runner, dataset, runner.put(JsonOutput(dataset.manifest(), "flight-manifest")))
            docs = runner.inputs({"flight": ing["flight"], "camera": ing["camera"]})
            flight, key = docs.json("flight"), identity_of(docs.json("camera")).key
            with ctx.database.session() as session:
                register_flight(
                    session,
                    flight["name"],
                    flight["date"],
                    key,
                    crs=flight.get("crs"),
                    n_images=flight["n_images"],
                    bbox=flight.get("bbox"),
                    temperature_range=flight.get("temperature_range"),
                )
                session.commit()
            folders[flight["name"]] = str(folder)
            names.append(flight["name"])
        with ctx.database.session() as session:
            try:
                existing = get_campaign(session, name)
                cron = cron if cron is not None else existing.cron
                description = description if description is not None else existing.description
            except LookupError:
                pass
            create_campaign(session, name, cron=cron, flights=names, description=description)
            data = json.dumps(folders, sort_keys=True, indent=1).encode()
            ctx.store.put_bytes(
                session, data, FOLDERS_KIND, "json", schema_name=_folders_schema(name), run_id=ctx.run_id
            )
            finish_run(session, ctx.run_id, "completed")
            session.commit()
    except BaseException as exc:
        with ctx.database.session() as session:
            finish_run(session, ctx.run_id, "failed", error=f"{type(exc).__name__}: {exc}")
            session.commit()
        raise
    return names


def list_campaigns(database_url: str | None = None) -> list[dict[str, Any]]:
    """Every campaign: name, cron, description and its flights (name, date, images)."""
    where = resolve_storage(database_url)
    ctx = StepContext(where.database_url, where.artifact_root, "")
    with ctx.database.session() as session:
        rows = session.scalars(sa.select(Campaign).order_by(Campaign.name)).all()
        return [
            {
                "name": c.name,
                "cron": c.cron,
                "description": c.description,
                "flights": [
                    {"name": f.name, "date": f.date.isoformat(), "images": f.n_images}
                    for f in sorted(c.flights, key=lambda f: (f.date, f.name))
                ],
            }
            for c in rows
        ]


@dataclasses.dataclass(frozen=True)
class CampaignRun:
    """A campaign processed: its name and the flights' run summaries in date order."""

    campaign: str
    runs: tuple[RunSummary, ...]


@flow(name="run-campaign", validate_parameters=False)
def run_campaign(
    campaign: str,
    out_dir: str | None = None,
    database_url: str | None = None,
    artifact_root: str | None = None,
    dask_address: str | None = None,
    config: ProcessConfig | None = None,
) -> CampaignRun:
    """Process every flight of ``campaign`` in date order, one ``process_flight`` sub-flow each, with the
    certificate chosen automatically (made once per camera, then reused). Run folders go to
    ``out_dir/<flight name>`` (default: beside each flight folder)."""
    where = resolve_storage(database_url, artifact_root)
    with StepContext(where.database_url, where.artifact_root, "").database.session() as session:
        try:
            camp = get_campaign(session, campaign)
        except LookupError:
            raise FlowInputError(
                f"campaign {campaign!r} does not exist; create it with "
                "`aerocal campaign add NAME FLIGHT_DIR...`"
            ) from None
        flights = sorted(camp.flights, key=lambda f: (f.date, f.name))
        names = [f.name for f in flights]
    folders = campaign_folders(where, campaign)
    missing = [n for n in names if n not in folders]
    if missing:
        raise FlowInputError(
            f"campaign {campaign!r}: no folder known for flights {missing}; add them with "
            "`aerocal campaign add`"
        )
    runs = []
    for name in names:
        out = Path(out_dir) / name if out_dir else None
        runs.append(
            process_flight(
                folders[name],
                out,
                "auto",
                config,
                database_url,  # as given (concealed or None): sub-flow parameters are stored too
                where.artifact_root,
                dask_address,
                campaign,
            )
        )
    return CampaignRun(campaign, tuple(runs))


def campaign_deployment_name(campaign: str) -> str:
    """Name of the deployment of :func:`run_campaign` for ``campaign``."""
    return f"campaign-{campaign}"


def register_campaign_deployments(
    database_url: str | None = None,
    artifact_root: str | None = None,
    out_dir: str | None = None,
    dask_address: str | None = None,
) -> list[Any]:
    """Register one scheduled deployment of :func:`run_campaign` per campaign with a cron schedule and
    return the ``RunnerDeployment`` objects (nothing runs until they are served)."""
    where = resolve_storage(database_url, artifact_root)
    # deployment parameters are stored by Prefect's server: a URL with a password goes to the environment the
    # served runs inherit (AEROCAL_DATABASE_URL), never into the parameters
    stored_url: str | None = where.database_url
    if make_url(where.database_url).password:
        os.environ["AEROCAL_DATABASE_URL"] = where.database_url
        stored_url = None
    deployments = []
    for camp in list_campaigns(where.database_url):
        if not camp["cron"]:
            continue
        dep = run_campaign.to_deployment(
            name=campaign_deployment_name(camp["name"]),
            cron=camp["cron"],
            parameters={
                "campaign": camp["name"],
                "out_dir": out_dir,
                "database_url": stored_url,
                "artifact_root": where.artifact_root,
                "dask_address": dask_address,
            },
            description=f"Scheduled processing of campaign {camp['name']} ({len(camp['flights'])} flights)",
            tags=["aerocal", "campaign"],
            # by module, not file path: the served process imports the installed package from any folder
            entrypoint_type=EntrypointType.MODULE_PATH,
        )
        dep.apply()
        deployments.append(dep)
    return deployments


def serve_campaigns(
    database_url: str | None = None,
    artifact_root: str | None = None,
    out_dir: str | None = None,
    dask_address: str | None = None,
) -> None:
    """Register the campaigns' deployments and serve them until interrupted (blocks)."""
    deployments = register_campaign_deployments(database_url, artifact_root, out_dir, dask_address)
    if not deployments:
        raise FlowInputError(
            "no campaign has a cron schedule; add one with "
            "`aerocal campaign add NAME FLIGHT_DIR... --cron '0 3 * * *'`"
        )
    serve(*deployments)
