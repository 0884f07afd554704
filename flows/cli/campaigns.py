"""Commands for campaigns of flights: the ``aerocal campaign`` group (``add``, ``run``, ``list``) and
``aerocal serve``.

:mod:`flows.campaign` imports Prefect (about 1 s): it is imported inside the commands, after
:func:`flows.environment.quiet_prefect` has set Prefect's environment, so that help stays fast.
"""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.table import Table

from flows.cli.console import console, err_console, run_status
from flows.cli.errors import user_errors
from flows.cli.flights import print_run
from flows.cli.help_text import command
from flows.cli.options import ARTIFACT_ROOT_OPTION, DASK_OPTION, DATABASE_URL_OPTION
from flows.environment import conceal_password, quiet_prefect

campaign_app = typer.Typer(
    help="Campaigns of flights: add, run, list.\n\n"
    "A campaign is several flights of one camera, processed on demand (`aerocal campaign run`) or on a cron "
    "schedule (`aerocal serve`); the certificate is made once per camera, then reused.\n\n"
    "Example: aerocal campaign list",
    no_args_is_help=True,
)


@command(campaign_app, "add")
def campaign_add(
    name: str = typer.Argument(..., help="Campaign name (created if new)."),
    flight_dirs: list[Path] = typer.Argument(..., help="Flight folders to add."),
    cron: str | None = typer.Option(None, "--cron", help="Five-field cron schedule in UTC, e.g. '0 3 * * *'."),
    description: str | None = typer.Option(None, "--description", help="What the campaign is for."),
    database_url: str | None = DATABASE_URL_OPTION,
    artifact_root: Path | None = ARTIFACT_ROOT_OPTION,
) -> None:
    """Register flight folders and add them to a campaign.

    The campaign is created if new; with --cron, `aerocal serve` runs it on that schedule.

    Example: aerocal campaign add seneca-2016 flights/2016-03-14 flights/2016-03-15 --cron '0 3 * * *'
    """
    quiet_prefect()
    with user_errors():
        # lazy: flows.campaign imports Prefect (~2.9 s CPU at start-up); --help must not pay it
        from flows.campaign import add_flights

        names = add_flights(
            name,
            list(flight_dirs),
            cron,
            description,
            database_url,
            str(artifact_root) if artifact_root else None,
        )
    console.print(f"campaign {name}: added {', '.join(names)}" + (f" (schedule {cron} UTC)" if cron else ""))


@command(campaign_app, "run")
def campaign_run(
    name: str = typer.Argument(..., help="Campaign name."),
    out: Path | None = typer.Option(None, "--out", help="Folder for the run folders (one per flight)."),
    dask: str | None = DASK_OPTION,
    database_url: str | None = DATABASE_URL_OPTION,
    artifact_root: Path | None = ARTIFACT_ROOT_OPTION,
) -> None:
    """Process every flight of a campaign now.

    The certificate is made once per camera, then reused for the campaign's other flights.

    Example: aerocal campaign run seneca-2016 --out runs/seneca-2016
    """
    quiet_prefect()
    with user_errors():
        # lazy: flows.campaign imports Prefect (~2.9 s CPU at start-up); --help must not pay it
        from flows.campaign import run_campaign

        with run_status(f"processing campaign {name}"):
            result = run_campaign(
                name,
                str(out) if out else None,
                conceal_password(database_url),
                str(artifact_root) if artifact_root else None,
                dask,
            )
    for summary in result.runs:
        print_run(summary)


@command(campaign_app, "list")
def campaign_list(database_url: str | None = DATABASE_URL_OPTION) -> None:
    """List campaigns with their schedules and flights.

    Example: aerocal campaign list
    """
    quiet_prefect()
    with user_errors():
        # lazy: flows.campaign imports Prefect (~2.9 s CPU at start-up); --help must not pay it
        from flows.campaign import list_campaigns

        rows = list_campaigns(database_url)
    table = Table(title="campaigns")
    for col in ("name", "schedule (UTC)", "flights"):
        table.add_column(col)
    for c in rows:
        table.add_row(
            c["name"],
            c["cron"] or "on demand",
            ", ".join(f"{f['name']} ({f['date']})" for f in c["flights"]) or "-",
        )
    console.print(table)


def serve(
    out: Path | None = typer.Option(None, "--out", help="Folder for the run folders of scheduled runs."),
    dask: str | None = DASK_OPTION,
    database_url: str | None = DATABASE_URL_OPTION,
    artifact_root: Path | None = ARTIFACT_ROOT_OPTION,
    wait: float = typer.Option(
        0.0, "--wait",
        help="When no campaign has a schedule yet, look again every WAIT seconds instead of failing (0: fail).",
    ),
) -> None:
    """Run the scheduled campaigns on their cron schedules.

    Registers one Prefect deployment per scheduled campaign and runs them until interrupted. Campaigns added
    later are picked up at the next start. Set PREFECT_API_URL to a Prefect server for the schedules to
    persist.

    Example: aerocal serve --out runs --wait 60

    Example: PREFECT_API_URL=http://prefect:4200/api aerocal serve --out /data/runs --wait 60
    """
    quiet_prefect()
    with user_errors():
        # lazy: flows.campaign imports Prefect (~2.9 s CPU at start-up); --help must not pay it
        from flows.campaign import list_campaigns, serve_campaigns

        while wait > 0 and not any(c["cron"] for c in list_campaigns(database_url)):
            err_console.print(f"no scheduled campaign yet; looking again in {wait:g} s")
            time.sleep(wait)
        serve_campaigns(
            database_url, str(artifact_root) if artifact_root else None, str(out) if out else None, dask
        )
