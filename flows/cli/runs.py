"""Commands for processing runs: the ``aerocal runs`` group (``list``, ``show``).

The store (:mod:`storage.runs`, :mod:`storage.provenance`; SQLAlchemy: about 0.2 s to import) is imported
inside the commands.
"""

from __future__ import annotations

import json

import typer
from rich.table import Table

from flows.cli.console import console, err_console
from flows.cli.database import open_database
from flows.cli.errors import user_errors
from flows.cli.help_text import command
from flows.cli.options import DATABASE_URL_OPTION

runs_app = typer.Typer(
    help="Processing runs and their provenance: list, show.\n\n"
    "Every `aerocal process`, `calibrate` and `campaign run` records a run: its inputs, the certificate it "
    "used and why, its configuration, timings and outputs.\n\n"
    "Example: aerocal runs list",
    no_args_is_help=True,
)


@command(runs_app, "list")
def runs_list(
    limit: int = typer.Option(50, "--limit", min=1, help="Show at most this many runs, newest first."),
    kind: str | None = typer.Option(None, "--kind", help="Only runs of this kind (e.g. process_flight)."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """List processing runs, newest first.

    A run whose process is gone (killed) is recorded as failed here, and said.

    Example: aerocal runs list

    Example: aerocal runs list --kind process_flight --limit 10
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage.runs import list_runs, reap_dead_runs

    with user_errors():
        with open_database(database_url) as db:
            with db.session() as session:
                # a run whose process is gone is not "running": recorded as failed, and said
                dead = [f"run {r.id}: {r.error}" for r in reap_dead_runs(session)]
                session.commit()
                rows = list_runs(session, limit=limit, kind=kind)
                flights = {row.id: row.flight.name if row.flight else "-" for row in rows}
    for line in dead:
        err_console.print(line)
    if not rows:
        console.print("no runs")
        return
    table = Table(title=f"{len(rows)} run(s)")
    for column in ("run", "kind", "status", "started", "seconds", "flight", "certificate"):
        table.add_column(column, no_wrap=column in ("status", "started"), overflow="fold")
    for row in rows:
        seconds = (row.ended - row.started).total_seconds() if row.ended else None
        table.add_row(
            row.id,
            row.kind,
            row.status,
            row.started.strftime("%Y-%m-%d %H:%M:%S"),
            "-" if seconds is None else f"{seconds:.1f}",
            flights[row.id],
            row.certificate_id or "-",
        )
    console.print(table)


@command(runs_app, "show")
def runs_show(
    run_id: str = typer.Argument(..., metavar="RUN_ID", help="Run id (as `aerocal runs list` shows it)."),
    as_json: bool = typer.Option(False, "--json", help="Print the provenance as JSON."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Show a run's inputs, certificate, timings and outputs.

    Its provenance: also why that certificate, the configuration, the code version and the run's status.

    Example: aerocal runs show 0d9f6c1e-5b7a-4f4e-9d55-2b1f0c8e7a31

    Example: aerocal runs show 0d9f6c1e-5b7a-4f4e-9d55-2b1f0c8e7a31 --json
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage.provenance import provenance

    with user_errors():
        with open_database(database_url) as db:
            with db.session() as session:
                prov = provenance(session, run_id)
    if as_json:
        console.print_json(json.dumps(prov.to_dict()))
        return
    summary = Table(title=f"run {prov.run_id}", show_header=False)
    summary.add_column("field", no_wrap=True)
    summary.add_column("value", overflow="fold")
    cert = prov.certificate
    for key, value in (
        ("kind", prov.kind),
        ("status", prov.status + (f" ({prov.error})" if prov.error else "")),
        ("started", prov.started.isoformat()),
        ("ended", prov.ended.isoformat() if prov.ended else "-"),
        ("code version", prov.code_version or "-"),
        ("flight", prov.flight or "-"),
        ("certificate", f"{cert.id} v{cert.version} ({cert.camera})" if cert
         else "the nominal camera (no stored certificate)" if prov.certificate_reason else "-"),
        ("why", prov.certificate_reason or "-"),
        ("configuration", json.dumps(prov.configuration, sort_keys=True)),
    ):
        summary.add_row(key, value)
    console.print(summary)
    if prov.timings:
        timings = Table(title="timings")
        timings.add_column("step")
        timings.add_column("seconds", justify="right")
        for step, seconds in prov.timings.items():
            timings.add_row(step, f"{seconds:.2f}")
        console.print(timings)
    for title, items in (("inputs", prov.inputs), ("outputs", prov.outputs)):
        if not items:
            continue
        table = Table(title=title)
        for column in ("id", "kind", "bytes", "sha256", "uri"):
            table.add_column(column, overflow="fold")
        for item in items:
            table.add_row(str(item.id), item.kind, str(item.size_bytes), item.sha256[:16], item.uri)
        console.print(table)
