"""Commands that simulate: ``aerocal simulate`` (a flight folder with its truth beside it) and
``aerocal demo`` (a simulated thermal flight processed end to end).

``simulate`` runs the engine alone: it never imports Prefect, SQLAlchemy or the flows. The simulator takes
about 0.6 s to import and is imported inside the command; ``demo`` imports the flows (Prefect: about 1 s)
only after :func:`flows.environment.demo_environment` has put Prefect's home under ``--out``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import typer

from flows.cli.console import console, print_key_values, progress, run_status
from flows.cli.errors import BAD_INPUT, fail, user_errors
from flows.cli.flights import print_loop, print_surface
from flows.environment import demo_environment


def simulate(
    preset: str = typer.Argument(
        ..., help="Flight preset: conte-city, conte-calibration, daakir-uav, daakir-calibration, mitishita-block, "
        "xt2-survey (FLIR R-JPEG), seneca (stations read from real images).",
    ),
    out: Path = typer.Option(..., "--out", help="Flight folder to write (must not exist or be empty)."),
    seed: int = typer.Option(0, help="Random seed; the same seed gives the same flight."),
    mode: str = typer.Option(
        "observations", help="observations (image measurements, fast) or images (rendered frames)."
    ),
    effect: list[str] = typer.Option(
        [], "--effect", help="Hidden effect NAME=VALUE, repeatable, e.g. thermal_focal=0.075 or boresight=0.01,0,0."
    ),
    max_images: int | None = typer.Option(
        None, "--max-images", help="Keep only the N frames nearest the block centre."
    ),
    as_recorded: bool = typer.Option(
        False, "--as-recorded", help="Images mode: write only the images, as they come off the aircraft (no "
        "camera.json, flight.json, eo.csv or GCP files).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
    source: Path | None = typer.Option(
        None, "--source", help="Image folder of a measured preset (seneca); default ../shared/data/seneca/images."
    ),
    wind: str | None = typer.Option(
        None, "--wind", help="Wind EAST,NORTH in m/s, e.g. 9,4: the preset's speed is then the airspeed, strips "
        "against the wind are slower over the ground and the aircraft crabs into a cross wind.",
    ),
) -> None:
    """Simulate a flight and write its flight folder.

    The truth (camera, orientations, hidden effects) is written beside it, for tests and studies only:
    processing never reads it. With --as-recorded only the images are written, as they come off the aircraft.

    Example: aerocal simulate conte-calibration --out flight --seed 3 --effect thermal_focal=0.05

    Example: aerocal simulate xt2-survey --mode images --as-recorded --max-images 12 --out xt2
    """
    # lazy: the simulator costs ~1.5 s CPU at start-up; --help must not pay it
    from aerocal.effects import parse_effect
    from aerocal.simulate import MODES, SimulationError, get_preset, simulate_flight, write_flight
    from aerocal.simulate.simulator import spec_summary

    with user_errors():
        spec = get_preset(preset, source)
        if wind is not None:
            spec = spec.flown(wind_vector(wind))
        if mode not in MODES:
            raise SimulationError(f"unknown mode {mode!r}; valid modes: {', '.join(MODES)}")
        effects = dict(parse_effect(e) for e in effect)
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            fail(f"output folder {out} exists and is not empty; choose a new --out or remove it", BAD_INPUT)
        sim = simulate_flight(spec, seed=seed, effects=effects, max_images=max_images)
        with progress(f"writing {mode}", sim.images.num_rows if mode == "images" else 0) as advance:
            write_flight(sim, out, mode=mode, progress=advance, as_recorded=as_recorded)
    summary = spec_summary(sim)
    summary["out"] = str(out)
    if as_json:
        console.print_json(json.dumps(summary))
    else:
        print_key_values(f"simulated {preset} (seed {seed})", summary)


def wind_vector(text: str) -> tuple[float, float]:
    """``--wind EAST,NORTH`` (m/s) as a pair of finite numbers; a clear error otherwise."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 2 or not all(math.isfinite(v) for v in values):
        fail(f"--wind {text!r}: give the wind as EAST,NORTH in m/s, e.g. --wind 9,4", BAD_INPUT)
    return values  # type: ignore[return-value]


def demo(
    out: Path = typer.Option(Path("demo-output"), "--out", help="Folder for everything the demo writes."),
    seed: int = typer.Option(7, help="Random seed of the simulated flight."),
) -> None:
    """Simulate a thermal flight and process it end to end.

    The flight has one hidden effect (a 10 ms rolling-shutter readout), which processing is not told:
    it self-calibrates and stores the certificate, adjusts, assesses and diagnoses the block, and where the
    diagnosis names an effect that predicts images the fit did not use, adjusts the block again with it and
    writes it into a new version of the camera's certificate; then mosaics and writes an HTML report, in about
    two minutes.
    Everything goes under --out (SQLite database, artifacts, Prefect's home) unless AEROCAL_DATABASE_URL or
    AEROCAL_ARTIFACT_ROOT are set.

    Example: aerocal demo --out demo-output
    """
    demo_environment(out)  # before Prefect is imported: its home goes under --out
    with user_errors():
        # lazy: flows.demo imports Prefect (~2.7 s CPU at start-up); --help must not pay it
        from flows.demo import DemoConfig
        from flows.demo import demo as demo_flow

        with run_status("simulating and processing the demo flight (about a minute)"):
            summary = demo_flow(out, DemoConfig(seed=seed))
    run = summary.run
    print_key_values(f"demo: simulated thermal flight (hidden, and not told to processing: {summary.hidden})",
                     summary.simulated)
    steps = ", ".join(f"{k} {v.status.value}" for k, v in run.steps.items())
    console.print(f"steps: {steps}")
    console.print(f"certificate: {run.certificate_id} ({run.certificate_reason})")
    print_loop(run)
    print_surface(run)
    console.print(f"flight folder: {summary.flight_dir}")
    for name, path in run.files.items():
        console.print(f"{name:>13}: {path}")
    for key, value in run.storage.items():
        console.print(f"{key:>13}: {value}")
