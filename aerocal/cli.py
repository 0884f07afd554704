"""The ``aerocal`` command line.

Engine commands (``simulate``, ...) live here. Platform commands (``db``, ``certificates``, ``runs``,
``process``, ``campaign``, ``serve``) live in :mod:`flows` and are imported lazily, only when invoked,
so that the engine never imports Prefect or SQLAlchemy (this module is the one exception allowed to
import ``flows``).

Every error a user can cause is one line naming what is wrong and the fix, with a non-zero exit code.
"""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import click
import typer
from rich.console import Console
from rich.table import Table
from typer.core import TyperGroup

console = Console()
err_console = Console(stderr=True)

#: platform command groups: name -> (module, typer app attribute, one-line help)
LAZY_GROUPS: dict[str, tuple[str, str, str]] = {
    "db": ("flows.commands_storage", "db_app", "Database migrations: upgrade, downgrade, current."),
    "certificates": ("flows.commands_storage", "certificates_app",
                     "Calibration certificates: list, show, export, import."),
    "runs": ("flows.commands_storage", "runs_app", "Processing runs and their provenance."),
    "init": ("flows.commands", "init_app", "Create the database and show where things live."),
    "process": ("flows.commands", "process_app", "Process a flight end to end."),
    "calibrate": ("flows.commands", "calibrate_app", "Calibrate a camera and store the certificate."),
    "campaign": ("flows.commands", "campaign_app", "Campaigns of flights: add, run, list."),
    "serve": ("flows.commands", "serve_app", "Serve the campaigns' scheduled deployments (blocks)."),
    "ingest": ("flows.commands", "ingest_app", "Ingest a flight folder and summarise what was found."),
    "match": ("flows.commands", "match_app", "Match a flight's images into tie-point observations."),
    "report": ("flows.commands", "report_app", "Show the report of a processed flight."),
}


class LazyGroup(TyperGroup):
    """A click group that imports platform sub-commands only when they are used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(set(super().list_commands(ctx)) | set(LAZY_GROUPS))

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name in LAZY_GROUPS:
            module, attr, help_text = LAZY_GROUPS[name]
            try:
                sub = getattr(importlib.import_module(module), attr)
            except (ImportError, AttributeError) as exc:
                return click.Command(name, help=help_text, callback=_unavailable(name, exc))
            cmd = typer.main.get_command(sub)
            cmd.help = cmd.help or help_text
            return cmd
        return super().get_command(ctx, name)


def _unavailable(name: str, exc: Exception):
    def run() -> None:
        err_console.print(f"[red]error:[/red] the '{name}' commands are not available in this installation "
                          f"({exc}); install aerocal with its platform dependencies: pip install -e .")
        raise SystemExit(2)

    return run


app = typer.Typer(
    cls=LazyGroup,
    help="aerocal: photogrammetry for cameras whose interior orientation is not stable.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def fail(message: str, code: int = 2) -> None:
    """Print one error line and exit non-zero."""
    err_console.print(f"[red]error:[/red] {message}", highlight=False, soft_wrap=True)
    raise typer.Exit(code)


@app.command()
def simulate(
    preset: str = typer.Argument(..., help="Flight preset: conte-city, conte-calibration, daakir-uav, "
                                            "daakir-calibration, mitishita-block, xt2-survey (FLIR R-JPEG), "
                                            "seneca (stations read "
                                            "from real images)."),
    out: Path = typer.Option(..., "--out", help="Flight folder to write (must not exist or be empty)."),
    seed: int = typer.Option(0, help="Random seed; the same seed gives the same flight."),
    mode: str = typer.Option("observations", help="observations (image measurements, fast) or images "
                                                  "(rendered frames)."),
    effect: list[str] = typer.Option([], "--effect", help="Hidden effect NAME=VALUE, repeatable, e.g. "
                                                          "thermal_focal=0.075 or boresight=0.01,0,0."),
    max_images: int | None = typer.Option(None, "--max-images", help="Keep only the N frames nearest the "
                                                                      "block centre."),
    as_recorded: bool = typer.Option(False, "--as-recorded", help="Images mode: write only the images, as "
                                                                   "they come off the aircraft (no camera.json, "
                                                                   "flight.json, eo.csv or GCP files)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
    source: Path | None = typer.Option(None, "--source", help="Image folder of a measured preset (seneca); "
                                                              "default ../shared/data/seneca/images."),
) -> None:
    """Simulate a flight and write a flight folder (with the truth beside it, for tests and studies only).

    Example: aerocal simulate conte-calibration --out flight --seed 3 --effect thermal_focal=0.05

    Example: aerocal simulate xt2-survey --mode images --as-recorded --out xt2  (FLIR R-JPEGs only)
    """
    from aerocal.effects import EffectError, parse_effect
    from aerocal.simulate import (
        MODES,
        PresetError,
        SimulationError,
        get_preset,
        simulate_flight,
        write_flight,
    )
    from aerocal.simulate.simulator import spec_summary

    try:
        spec = get_preset(preset, source)
        if mode not in MODES:
            raise SimulationError(f"unknown mode {mode!r}; valid modes: {', '.join(MODES)}")
        effects = dict(parse_effect(e) for e in effect)
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise SimulationError(f"output folder {out} exists and is not empty; choose a new --out or remove it")
        sim = simulate_flight(spec, seed=seed, effects=effects, max_images=max_images)
        with _progress(f"writing {mode}", sim.images.num_rows if mode == "images" else 0) as advance:
            write_flight(sim, out, mode=mode, progress=advance, as_recorded=as_recorded)
    except (PresetError, EffectError, SimulationError) as exc:
        fail(str(exc))
    summary = spec_summary(sim)
    summary["out"] = str(out)
    if as_json:
        console.print_json(json.dumps(summary))
    else:
        _print_summary(f"simulated {preset} (seed {seed})", summary)


class _progress:
    """A rich progress bar for ``total`` steps (no bar when total is 0); yields an ``advance(done, total)``."""

    def __init__(self, label: str, total: int) -> None:
        self.label, self.total = label, total

    def __enter__(self):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

        if not self.total:
            return lambda done, total: None
        self.bar = Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                            TimeRemainingColumn(), console=err_console, transient=True)
        self.bar.__enter__()
        task = self.bar.add_task(self.label, total=self.total)
        return lambda done, total: self.bar.update(task, completed=done, total=total)

    def __exit__(self, *exc) -> None:
        if self.total:
            self.bar.__exit__(*exc)


def _print_summary(title: str, summary: dict) -> None:
    table = Table(title=title, show_header=False)
    for key, value in summary.items():
        table.add_row(key, json.dumps(value) if isinstance(value, list | dict) else str(value))
    console.print(table)


@app.command()
def diagnose(
    flight: Path = typer.Argument(..., help="A run folder of 'aerocal process' (shows its diagnosis), or a flight "
                                            "folder with observations/*.parquet (diagnoses it now)."),
    certificate: Path | None = typer.Option(None, "--certificate", help="Certificate file (aerocal JSON, "
                                            "OpenCV YAML, COLMAP, OpenSfM, Metashape): IO fixed from it."),
    as_json: bool = typer.Option(False, "--json", help="Print one JSON object (effects, gain, hypotheses)."),
) -> None:
    """Name the systematic effects the block's model misses, with magnitudes and the gain on check points.

    Without --certificate the baseline self-calibrates f, cx, cy, k1, k2, p1, p2 from camera.json.

    Examples: aerocal diagnose runs/2016-03-14 --json; aerocal diagnose flight --certificate cam.json
    """
    from aerocal.diagnose.run import DiagnoseInputError, diagnose_folder, read_run_diagnosis

    try:
        stored = read_run_diagnosis(flight) if certificate is None else None
    except DiagnoseInputError as exc:
        fail(str(exc))
    if stored is not None:  # a processing run's folder: show the diagnosis it made
        if as_json:
            console.print_json(json.dumps(stored))
        else:
            console.print(f"[bold]verdict:[/bold] {stored.get('summary')}")
            for note in stored.get("notes", []):
                console.print(f"note: {note}")
        return
    try:
        result = diagnose_folder(flight, certificate)
    except DiagnoseInputError as exc:
        fail(str(exc))
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


@app.command()
def demo(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Folder for everything the demo writes."),
    seed: int = typer.Option(7, help="Random seed of the simulated flight."),
) -> None:
    """Simulate a small thermal flight with one hidden effect and process it end to end: self-calibration
    with the certificate stored, adjustment, orthomosaic, assessment, diagnosis and an HTML report.

    Everything goes under --out (SQLite database, artifacts, Prefect's home) unless AEROCAL_DATABASE_URL
    or AEROCAL_ARTIFACT_ROOT are set.

    Example: aerocal demo --out demo-output
    """
    from flows.environment import demo_environment

    demo_environment(out)  # before Prefect is imported: its home goes under --out
    from flows.demo import DemoConfig
    from flows.demo import demo as demo_flow
    from flows.flight import FlowInputError

    try:
        with console.status("simulating and processing the demo flight (about a minute) ..."):
            summary = demo_flow(out, DemoConfig(seed=seed))
    except (FlowInputError, OSError) as exc:
        fail(str(exc))
    _print_summary("demo: simulated thermal flight (one hidden effect: thermal_focal)", summary["simulated"])
    steps = ", ".join(f"{k} {v['status']}" for k, v in summary["steps"].items())
    console.print(f"steps: {steps}")
    console.print(f"certificate: {summary['certificate_id']} ({summary['certificate_reason']})")
    acc = summary.get("accuracy") or {}
    if acc.get("rho"):
        rho = ", ".join(f"{k} {v:.2f}" for k, v in acc["rho"].items() if v is not None)
        console.print(f"check points: rho {rho} -> {acc.get('verdict')}")
    console.print(f"[bold]diagnosis:[/bold] {summary.get('diagnosis')}")
    console.print(f"flight folder: {summary['flight_dir']}")
    for name, path in summary["files"].items():
        console.print(f"{name:>13}: {path}")
    for key, value in summary["storage"].items():
        console.print(f"{key:>13}: {value}")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
