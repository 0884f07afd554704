"""The ``aerocal diagnose`` command: the systematic effects a block's model misses.

It runs the engine alone (never Prefect, SQLAlchemy or the flows); the diagnosis takes about 1 s to import
and is imported inside the command.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from flows.cli.console import console
from flows.cli.errors import user_errors


def diagnose(
    flight: Path = typer.Argument(
        ..., help="A run folder of 'aerocal process' (shows its diagnosis), or a flight folder with "
        "observations/*.parquet (diagnoses it now).",
    ),
    certificate: Path | None = typer.Option(
        None, "--certificate", help="Certificate file (aerocal JSON, OpenCV YAML, COLMAP, OpenSfM, Metashape): IO "
        "fixed from it.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (effects, gain, hypotheses)."),
) -> None:
    """Name the systematic effects a block's model misses.

    Tests each candidate effect (hypothesis, statistic, adjusted p, estimate with sigma) and gives the gain
    on check points of modelling the ones found. Without --certificate the baseline self-calibrates f, cx,
    cy, k1, k2, p1, p2 from camera.json.

    Example: aerocal diagnose runs/2016-03-14 --json

    Example: aerocal diagnose flight --certificate camera.json
    """
    # lazy: the diagnosis engine costs ~1.2 s CPU at start-up; --help must not pay it
    from aerocal.diagnose.run import read_run_diagnosis
    from aerocal.pipeline.diagnose_step import diagnose_folder

    with user_errors():
        stored = read_run_diagnosis(flight) if certificate is None else None
    if stored is not None:  # a processing run's folder: show the diagnosis it made
        if as_json:
            console.print_json(json.dumps(stored))
        else:
            console.print(f"[bold]verdict:[/bold] {stored.get('summary')}")
            for note in stored.get("notes", []):
                console.print(f"note: {note}")
        return
    with user_errors():
        result = diagnose_folder(flight, certificate)
    if as_json:
        console.print_json(json.dumps(result.to_dict()))
        return
    table = Table(title=f"diagnosis of {flight}")
    for col in ("hypothesis", "round", "statistic", "p (adjusted)", "estimate", "sigma", "units"):
        table.add_column(col)
    for h in result.hypotheses:
        table.add_row(h.name, str(h.round), f"{h.statistic:.1f}", f"{h.p_adjusted:.2g}",
                      ", ".join(f"{v:.4g}" for v in h.estimate), ", ".join(f"{v:.2g}" for v in h.sigma), h.units)
    console.print(table)
    console.print(f"[bold]verdict:[/bold] {result.summary()}")
    if result.gain:
        g = result.gain
        console.print(f"gain on check points: RMSE {g.before:.3f} m -> {g.after:.3f} m (x{g.ratio:.2f})")
    for note in result.notes:
        console.print(f"note: {note}")
