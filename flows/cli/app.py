"""The ``aerocal`` command tree: every command and group, the help panel each is listed under, in order.

Panels of ``aerocal --help``:

* :data:`FLIGHTS` -- ``ingest``, ``match``, ``process``, ``calibrate``, ``report`` (:mod:`flows.cli.flights`);
* :data:`CAMPAIGNS` -- ``campaign`` (add, run, list), ``serve`` (:mod:`flows.cli.campaigns`);
* :data:`STORAGE` -- ``init``, ``db`` (:mod:`flows.cli.database`), ``certificates``
  (:mod:`flows.cli.certificates`), ``runs`` (:mod:`flows.cli.runs`);
* :data:`SIMULATION` -- ``simulate``, ``demo`` (:mod:`flows.cli.simulation`), ``diagnose``
  (:mod:`flows.cli.diagnosis`).

Importing this module imports every command module but neither Prefect, SQLAlchemy, the flows nor the
engine's heavy modules: each command imports what it needs when it runs.
"""

from __future__ import annotations

import typer

from flows.cli import campaigns, certificates, database, diagnosis, flights, runs, simulation
from flows.cli.help_text import command

FLIGHTS = "Process flights"
CAMPAIGNS = "Campaigns and schedules"
STORAGE = "Certificates and storage"
SIMULATION = "Simulation and diagnosis"

app = typer.Typer(
    help="aerocal: photogrammetry for cameras whose interior orientation is not stable.\n\n"
    "Thermal and heating cameras: calibration certificates, block adjustment, orthomosaics and a diagnosis "
    "of the systematic effects a block's model misses. `aerocal COMMAND --help` explains a command, with "
    "examples.\n\n"
    "Example: aerocal demo --out demo-output",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)

for name, function in (
    ("ingest", flights.ingest),
    ("match", flights.match),
    ("process", flights.process),
    ("calibrate", flights.calibrate),
    ("report", flights.report),
):
    command(app, name, rich_help_panel=FLIGHTS)(function)

app.add_typer(campaigns.campaign_app, name="campaign", rich_help_panel=CAMPAIGNS)
command(app, "serve", rich_help_panel=CAMPAIGNS)(campaigns.serve)

command(app, "init", rich_help_panel=STORAGE)(database.init)
app.add_typer(database.db_app, name="db", rich_help_panel=STORAGE)
app.add_typer(certificates.certificates_app, name="certificates", rich_help_panel=STORAGE)
app.add_typer(runs.runs_app, name="runs", rich_help_panel=STORAGE)

command(app, "simulate", rich_help_panel=SIMULATION)(simulation.simulate)
command(app, "diagnose", rich_help_panel=SIMULATION)(diagnosis.diagnose)
command(app, "demo", rich_help_panel=SIMULATION)(simulation.demo)
