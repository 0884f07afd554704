"""Commands that process flights: ``ingest``, ``match``, ``process``, ``calibrate``, ``report``.

The functions here are registered as commands by :mod:`flows.cli.app`. Prefect, the flows, the tasks and
the engine's ingest are imported inside the commands, not here: ``aerocal --help`` imports this module, and
Prefect alone takes about 1 s to import (the engine's ingest 1 s); :func:`flows.environment.quiet_prefect`
sets Prefect's environment first.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console
from rich.table import Table

from flows.cli.console import console, err_console, print_key_values, run_status
from flows.cli.errors import BAD_INPUT, FAILED, CommandInputError, fail, flow_errors, user_errors
from flows.cli.options import ARTIFACT_ROOT_OPTION, DASK_OPTION, DATABASE_URL_OPTION
from flows.environment import conceal_password, quiet_prefect

if TYPE_CHECKING:  # the CLI's start-up imports no engine module (see the module docstring)
    from aerocal.ingest.problems import Problem
    from aerocal.pipeline import ProcessConfig
    from aerocal.pipeline.findings import Finding
    from aerocal.pipeline.summary import RunSummary

#: ingest problems the run summary prints (errors first); `aerocal ingest` lists them all
INGEST_LINES = 10

#: files of a run folder that `aerocal report` points to, when present
REPORT_FILES = ("report.html", "orthomosaic.tif", "dsm.tif", "certificate.json", "provenance.json")


def require_folder(folder: Path, what: str = "a flight folder (images/ or observations/)") -> None:
    """Refuse (exit 2) before any server starts when ``folder`` is not a folder."""
    if not folder.is_dir():
        fail(f"{folder} is not a folder; give {what}", BAD_INPUT)


def default_run_dir(flight_dir: Path, out: Path | None) -> Path:
    """The run folder of a flight: ``out``, else ``FLIGHT_DIR-processed`` beside the flight folder."""
    return (out or flight_dir.with_name(flight_dir.name + "-processed")).resolve()


def print_steps(summary: RunSummary) -> None:
    """The steps of a run: status (and why a step was skipped or reused), seconds, who computed it."""
    table = Table(title=f"run {summary.run_id} of {summary.flight}")
    for col in ("step", "status", "seconds", "computed by"):
        table.add_column(col)
    for name, step in summary.steps.items():
        table.add_row(
            name,
            step.status.value + (f" ({step.reason})" if step.reason else ""),
            f"{step.seconds:.2f}",
            step.computed_by or "",
        )
    console.print(table)


def print_run(summary: RunSummary) -> None:
    """A processing run's summary: steps, ingest problems, ground control, certificate, accuracy, diagnosis,
    recorded-EO checks, the twin's verdict and the files written."""
    print_steps(summary)
    skipped = summary.images_skipped_at_ingest
    if skipped:
        # lazy: aerocal.ingest costs ~1.3 s CPU at start-up (OpenCV, Pillow, SciPy); --help must not pay it
        from aerocal.ingest.problems import name_list

        console.print(f"[yellow]{len(skipped)} image(s) skipped at ingest[/yellow]: {name_list(list(skipped))} "
                      "(`aerocal ingest FOLDER` says why)")
    problems = summary.ingest_problems
    errors = [p for p in problems if p.endswith("[error]")]
    warnings = [p for p in problems if p.endswith("[warning]")]
    shown = errors[:INGEST_LINES] + warnings[: max(0, INGEST_LINES - len(errors))]
    if shown:
        console.print(f"[yellow]ingest found {len(errors)} error(s) and {len(warnings)} warning(s)[/yellow] that did "
                      "not stop processing (a certificate from input with errors is stored as rejected):")
        for line in shown:
            console.print(f"  {line}", markup=False, highlight=False)
        if len(problems) > len(shown):
            console.print(f"  ... and {len(problems) - len(shown)} more: `aerocal ingest FOLDER` lists them all")
    for key, text in summary.flight_facts.items():
        if not text.startswith(("flight.json", "/")):  # inferred from the images: say so
            console.print(f"{key}: {text}")
    control = summary.ground_control
    if control.demoted:
        console.print(f"[yellow]ground control demoted[/yellow] (neither control nor check point): "
                      f"{', '.join(control.demoted)}")
    for line in control.lines:
        console.print(f"ground control: {line}")
    console.print(f"certificate: {summary.certificate_id} ({summary.certificate_reason})")
    if summary.adjustment_converged is False:
        console.print(f"[yellow]the block adjustment did not converge[/yellow] ({summary.adjustment_iterations} "
                      "iterations): its sigma0, residuals, products and diagnosis describe an unfinished solution")
    print_loop(summary)
    if summary.recorded_eo:
        # lazy: aerocal.report loads matplotlib, rasterio and Jinja2 (about 1 s); --help must not pay them
        from aerocal.report.wording import recorded_eo_text

        console.print("recorded EO checks: " + recorded_eo_text(summary.recorded_eo))
    if summary.recorded_eo_corrections:
        console.print("recorded positions in the block adjustment: " + "; ".join(summary.recorded_eo_corrections))
    if summary.twin:
        console.print(f"twin (what the simulation gets wrong): {summary.twin}")
    print_surface(summary)
    for name, path in summary.files.items():
        console.print(f"{name:>13}: {path}")


def print_surface(summary: RunSummary) -> None:
    """The surface the products stand on and its check against an independent measurement (a laser range finder,
    the recorded flying height), in yellow when they disagree."""
    if summary.surface:
        colour = "yellow" if "DISAGREES" in summary.surface else "default"
        console.print(f"[{colour}]surface[/{colour}]: {summary.surface}", highlight=False)


def print_loop(summary: RunSummary) -> None:
    """What a run found and how its block changed, as ``aerocal process`` and ``aerocal demo`` print it: the check
    points' accuracy, the findings applied, the diagnosis, and the block before and after its extension."""
    acc = summary.accuracy or {}
    if acc.get("rho"):
        rho = ", ".join(f"{k} {v:.2f}" for k, v in acc["rho"].items() if v is not None)
        console.print(f"check points: rho {rho} -> {acc.get('verdict')}")
    if summary.findings:
        console.print("found and applied:", highlight=False)
        for f in summary.findings:
            console.print(f"  {finding_text(f)}", markup=False, highlight=False)
    if summary.diagnosis:
        console.print(f"diagnosis: {summary.diagnosis}", markup=False, highlight=False)
    for line in summary.certificate_terms:
        console.print(f"certificate term: {line}", markup=False, highlight=False)
    if summary.model_extension:
        for line in extension_lines(summary.model_extension):
            console.print(f"  {line}", markup=False, highlight=False)
        console.print(f"diagnosis of the extended block: {summary.diagnosis_after_extension}", markup=False,
                      highlight=False)


def finding_text(finding: Finding) -> str:
    """A finding of the run in one line, with where it went and its evidence."""
    values = ", ".join(f"{v:.4g}" for v in finding.values)
    sigmas = ", ".join("?" if v is None else f"{v:.2g}" for v in finding.sigmas)
    return (f"{finding.name} = {values} +- {sigmas} {finding.units} (by the {finding.found_by}; "
            f"{finding.applied}; {finding.evidence})")


def extension_lines(extension: dict[str, Any]) -> list[str]:
    """The block before and after its extension by the diagnosis, a line per figure that changed."""
    b, a = extension.get("before") or {}, extension.get("after") or {}
    lines = []
    if b.get("sigma0") is not None and a.get("sigma0") is not None:
        lines.append(f"sigma0 {b['sigma0']:.3f} -> {a['sigma0']:.3f}")
    cb, ca = b.get("check_points") or {}, a.get("check_points") or {}
    if cb.get("rmse_m") and ca.get("rmse_m"):
        axes = [k for k in cb["rmse_m"] if cb["rmse_m"][k] is not None and ca["rmse_m"].get(k) is not None]
        rmse = ", ".join(f"{k} {cb['rmse_m'][k]:.3g} -> {ca['rmse_m'][k]:.3g}" for k in axes)
        worse = [k for k in axes if ca["rmse_m"][k] > cb["rmse_m"][k]]
        # a gain overall need not be one on every axis: an axis that got worse is said, not left to be noticed
        lines.append(f"check points RMSE (m): {rmse}" + (f" (worse in {', '.join(worse)})" if worse else ""))
    if b.get("twin") != a.get("twin"):
        lines.append(f"twin: {a.get('twin')}")
    if b.get("certificate_id") != a.get("certificate_id"):
        lines.append(f"certificate {b.get('certificate_id')} -> {a.get('certificate_id')}")
    lines.extend(extension.get("agreement") or [])
    return lines


def print_problems(problems: list[Problem], out: Console, warnings: bool = True, limit: int = 50) -> None:
    """Every error of ingest's ``problems`` (:class:`aerocal.ingest.problems.Problem`; those that stop processing
    first), then warnings up to ``limit`` lines in all."""
    ordered = [p for p in problems if p.stops_processing]
    ordered += [p for p in problems if p.severity == "error" and not p.stops_processing]
    notes = [p for p in problems if p.severity != "error" and not p.stops_processing]
    shown = notes[: max(0, limit - len(ordered))] if warnings else []
    for p in ordered + shown:
        out.print(str(p), markup=False)
    rest = len(notes) - len(shown)
    if warnings and rest > 0:
        out.print(f"... and {rest} more warnings (aerocal ingest FOLDER --out DIR writes them all)")


def print_ingest_report(folder: Path, rows: list[tuple[str, str]], problems: list[Problem],
                        written: Path | None = None) -> None:
    """What ``aerocal ingest`` says of a folder: the summary ``rows``, every problem, where the tables were
    ``written``, and how many problems stop ``aerocal process``; exit 2 when any problem is an error."""
    table = Table(title=f"ingest of {folder}", show_header=False)
    for item, value in rows:
        table.add_row(item, value)
    console.print(table)
    print_problems(problems, console)
    if written is not None:
        console.print(f"tables written to {written}")
    blocking = [p for p in problems if p.stops_processing]
    if blocking:
        err_console.print(
            f"[red]{len(blocking)} problem(s) stop `aerocal process`[/red] (marked 'stops processing'); "
            "fix them and ingest again",
            markup=True,
        )
    if any(p.severity == "error" for p in problems):
        raise typer.Exit(BAD_INPUT)


def stop_if_not_processable(flight_dir: Path) -> None:
    """Run ingest's checks on a flight (those of ``aerocal ingest``) before any server starts; on a blocking
    problem print them and exit 2 (bad input)."""
    # lazy: aerocal.pipeline costs ~1.4 s CPU at start-up; --help must not pay it
    from aerocal.pipeline.dataset import FolderDataset, IngestStepConfig, sidecar_blockers

    if (flight_dir / "observations" / "observations.parquet").is_file():
        with user_errors():
            # the files beside the tables; a missing table or camera.json is the flow's own one-line error
            blocking = sidecar_blockers(flight_dir)
        if blocking:
            err_console.print(f"[red]error:[/red] {flight_dir} cannot be processed: {len(blocking)} problem(s) stop "
                              "processing (nothing was processed or stored):", markup=True)
            for p in blocking[:20]:
                err_console.print(str(p), markup=False)
            raise typer.Exit(BAD_INPUT)
        return
    with user_errors():
        with console.status(f"checking {flight_dir} ..."):
            result = FolderDataset(flight_dir).ingest(IngestStepConfig())
    if result.blocking:
        err_console.print(
            f"[red]error:[/red] {flight_dir} cannot be processed: {len(result.blocking)} problem(s) stop "
            f"processing ({len(result.errors)} error(s) in all; nothing was processed or stored):",
            markup=True,
        )
        print_problems(result.problems, err_console, warnings=False)
        raise typer.Exit(BAD_INPUT)


def ingest(
    folder: Path = typer.Argument(..., help="Flight folder or folder of images."),
    gcp: list[Path] = typer.Option([], "--gcp", help="GCP file (ODM gcp_list.txt or CSV); repeatable."),
    eo: Path | None = typer.Option(None, "--eo", help="Exterior-orientation CSV (default: eo.csv)."),
    crs: str | None = typer.Option(None, "--crs", help="Projected CRS, e.g. EPSG:32632 (default: UTM zone)."),
    out: Path | None = typer.Option(None, "--out", help="Write the ingested tables to this folder."),
) -> None:
    """Check a flight folder; list every problem by file and line.

    Reads the images, their metadata, the exterior orientation and the ground control, and prints a summary
    and every problem by file and line. Exit code 0 when nothing is wrong (warnings only), 2 when there are
    errors: skipped images or rows, and problems that stop `aerocal process` (each names the file, the field
    and the fix).

    Example: aerocal ingest flights/2016-03-14 --gcp flights/2016-03-14/gcp_list.txt --out ingested
    """
    # lazy: aerocal.ingest and aerocal.pipeline cost ~1.4 s CPU at start-up; --help must not pay it
    from aerocal.ingest import summary_rows, write_ingest
    from aerocal.pipeline.dataset import FolderDataset, IngestStepConfig

    if not folder.exists():
        fail(f"{folder}: no such folder; give a flight folder or a folder of images", BAD_INPUT)
    if (folder / "observations" / "observations.parquet").is_file():
        _ingest_observations_folder(folder)
        return
    with user_errors():
        with console.status(f"ingesting {folder} ..."):
            # the reader `aerocal process` uses, with the files given here
            result = FolderDataset(folder).ingest(IngestStepConfig(gcp_file=tuple(gcp) or None, eo_file=eo,
                                                                   crs=crs))
        if out is not None:
            write_ingest(result, out)
    print_ingest_report(folder, summary_rows(result), result.problems, out)


def _ingest_observations_folder(folder: Path) -> None:
    """``aerocal ingest`` of an observations-mode folder: what processing reads of it, and the files beside its
    tables that disagree with them; exit 2 when anything stops processing."""
    # lazy: aerocal.pipeline costs ~1.4 s CPU at start-up; --help must not pay it
    from aerocal.pipeline.dataset import observations_report

    with user_errors():
        rows, problems = observations_report(folder)
    print_ingest_report(folder, rows, problems)


def match(
    folder: Path = typer.Argument(..., help="Flight folder with images/ (and eo.csv, gcp files, camera.json)."),
    out: Path | None = typer.Option(None, "--out", help="Folder for the tables (default: FOLDER/observations)."),
    dask: str | None = DASK_OPTION,
    workers: int = typer.Option(2, "--workers", help="Local Dask workers when --dask is not given."),
) -> None:
    """Match a flight's images into tie-point observations.

    Enhances and matches the frames (tile-parallel SIFT on Dask) and writes the images, observations, gcps
    and gcp_observations tables; the folder can then be processed in observations mode.

    Example: aerocal match flights/2016-03-14 --workers 2

    Example: aerocal match flights/2016-03-14 --dask tcp://scheduler:8786
    """
    if not folder.is_dir():
        fail(f"{folder}: no such folder; give a flight folder with images/", BAD_INPUT)
    quiet_prefect()
    with user_errors():
        # lazy: aerocal.pipeline costs ~1.4 s CPU at start-up; --help must not pay it
        from aerocal import tables
        from aerocal.camera import Camera
        from aerocal.io import write_json_atomic
        from aerocal.matching.cluster import ExecutionConfig
        from aerocal.pipeline.config import MatchStepConfig
        from aerocal.pipeline.dataset import FlightInputError, FolderDataset, IngestStepConfig
        from aerocal.pipeline.ingest_step import flight_summary
        from aerocal.pipeline.match_step import match_images, pairs_from

        # the flight as `aerocal process` reads it: the same images, camera (camera.json, else the nominal camera
        # from the files) and flying height
        dataset = FolderDataset(folder)
        read = dataset.read_images(IngestStepConfig())
        images, gcps = read.tables["images"], read.tables["gcps"]
        if images.num_rows == 0:
            raise FlightInputError(f"{folder}: no image could be ingested; run `aerocal ingest {folder}` to see why")
        flight = flight_summary(images, read.metadata, read.crs, dataset.name, read.mode, str(dataset.folder))
        with console.status(f"matching {images.num_rows} images ..."):
            kp, matches, obs, n_pairs = match_images(
                images, Camera.from_dict(read.camera["camera"]), gcps, flight, MatchStepConfig(),
                ExecutionConfig(dask, workers)
            )
        target = out or folder / "observations"
        for kind, tab in (
            ("images", images),
            ("observations", obs),
            ("gcps", gcps),
            ("gcp_observations", read.tables["gcp_observations"]),
            ("keypoints", kp),
            ("matches", matches),
        ):
            tables.write(tab, target / f"{kind}.parquet", kind)
        camera_json = folder / "camera.json"
        if out is None and not camera_json.exists():
            # observations mode reads the camera from camera.json: the one ingest found in the files, with its source
            write_json_atomic(camera_json, read.camera)
            console.print(f"camera.json written ({read.camera.get('source')}): check it before processing")
    console.print(
        f"{images.num_rows} images, {n_pairs} candidate pairs (from {pairs_from(images, MatchStepConfig())}), "
        f"{matches.num_rows} verified matches, "
        f"{obs.num_rows} observations of {len(set(obs.column('track_id').to_pylist()))} tracks"
    )
    console.print(f"tables written to {target}")


def process(
    flight_dir: Path = typer.Argument(..., help="Flight folder (images/ or observations/, eo.csv, gcp files)."),
    certificate: str = typer.Option(
        "auto", "--certificate",
        help="auto (stored certificate that applies, else self-calibrate), none (always self-calibrate), nominal "
        "(the camera.json camera as given, e.g. a metric camera's laboratory calibration) or a certificate id.",
    ),
    out: Path | None = typer.Option(None, "--out", help="Run folder (default: FLIGHT_DIR-processed)."),
    dask: str | None = DASK_OPTION,
    database_url: str | None = DATABASE_URL_OPTION,
    artifact_root: Path | None = ARTIFACT_ROOT_OPTION,
    surface: str = typer.Option(
        "dense", "--surface",
        help="dense (the surface matched in the frames: cloud.laz, DSM and DTM at the ground sample distance; "
        "the orthomosaic stands on it) or tie-points (the tie points' DSM only: minutes sooner on a large flight, "
        "an orthomosaic whose roofs and walls lean).",
    ),
    figures: bool = typer.Option(
        True, "--figures/--no-figures",
        help="Draw the report's figures (default). --no-figures writes the same report page and summary.json, every "
        "caption and number, without pictures: seconds sooner per run, for batch runs whose reports are read by "
        "programs.",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the run summary as JSON."),
) -> None:
    """Process a flight end to end and record the run.

    Ingest, match, orient, calibrate or reuse a stored certificate, adjust, mosaic, assess, diagnose and
    write the report. A re-run after a crash or Ctrl-C resumes after the last completed step.

    Example: aerocal process flights/2016-03-14 --certificate auto --out runs/2016-03-14
    """
    with user_errors():
        config = run_config(surface, figures)
    require_folder(flight_dir)
    stop_if_not_processable(flight_dir)
    quiet_prefect()
    run_dir = default_run_dir(flight_dir, out)
    with flow_errors(run_dir):
        # lazy: flows.process imports Prefect (~2.9 s CPU at start-up); --help must not pay it
        from flows.process import process_flight

        with run_status(f"processing {flight_dir}"):
            summary = process_flight(
                flight_dir,
                out,
                certificate,
                config,
                conceal_password(database_url),
                str(artifact_root) if artifact_root else None,
                dask,
            )
    if as_json:
        console.print_json(json.dumps(summary.to_json(), default=str))
    else:
        print_run(summary)


SURFACES = ("dense", "tie-points")


def run_config(surface: str, figures: bool = True) -> ProcessConfig | None:
    """The process configuration ``--surface`` and ``--figures/--no-figures`` ask for: ``None`` (the defaults)
    for ``dense`` with figures; the products step without the dense surface for ``tie-points``; the report
    without pictures for ``--no-figures``.

    Raises:
        CommandInputError: ``surface`` is neither ``dense`` nor ``tie-points``.
    """
    if surface not in SURFACES:
        raise CommandInputError(f"--surface {surface}: unknown; give one of {', '.join(SURFACES)}")
    if surface == "dense" and figures:
        return None
    # lazy: aerocal.pipeline loads the engine (OpenCV, SciPy, pyarrow); --help must not pay it
    from aerocal.pipeline import ProcessConfig

    cfg = ProcessConfig()
    if surface == "tie-points":
        cfg = dataclasses.replace(cfg, mosaic=dataclasses.replace(cfg.mosaic, dense=None))
    if not figures:
        cfg = dataclasses.replace(cfg, report=dataclasses.replace(cfg.report, figures=False))
    return cfg


def subset_config(subset: str) -> dict[str, Any]:
    """The calibration settings ``--subset`` asks for: ``{}`` for auto, else the image ids or names listed
    one per line in the file ``subset`` (``#`` starts a comment)."""
    if subset == "auto":
        return {}
    path = Path(subset)
    if not path.is_file():
        raise CommandInputError(
            f"--subset {subset}: no such file; give auto or a file of image names or ids, one per line"
        )
    items = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        text = line.split("#", 1)[0].strip()
        if text:
            items.append((n, text))
    if not items:
        raise CommandInputError(f"{path}: no image names or ids; write one per line")
    if all(t.isdigit() for _, t in items):
        return {"subset_images": tuple(int(t) for _, t in items)}
    bad = [(n, t) for n, t in items if t.isdigit()]
    if bad:
        raise CommandInputError(
            f"{path}:{bad[0][0]}: {bad[0][1]!r} is an id among image names; use names or ids, not both"
        )
    return {"subset_names": tuple(t for _, t in items)}


def calibrate(
    flight_dir: Path = typer.Argument(..., help="A calibration flight folder."),
    subset: str = typer.Option(
        "auto", "--subset",
        help="auto (sub-block chosen by predicted IO precision) or a FILE of image names or ids, one per line.",
    ),
    out: Path | None = typer.Option(None, "--out", help="Run folder (default: FLIGHT_DIR-processed)."),
    dask: str | None = DASK_OPTION,
    database_url: str | None = DATABASE_URL_OPTION,
    artifact_root: Path | None = ARTIFACT_ROOT_OPTION,
) -> None:
    """Calibrate a camera from a flight; store the certificate.

    Self-calibrates on a sub-block, stores the certificate and prints it: parameters, sigmas, significance,
    dropped parameters, correlations above 0.9. Exit code 1 when the review rejects the calibration (it is
    stored, marked rejected, and never used).

    Example: aerocal calibrate flights/calibration --subset auto --out runs/calibration

    Example: aerocal calibrate flights/calibration --subset subset.txt
    """
    with user_errors():
        settings = subset_config(subset)
    require_folder(flight_dir)
    quiet_prefect()
    with flow_errors(default_run_dir(flight_dir, out)):
        # lazy: flows.process imports Prefect (~2.9 s CPU at start-up); --help must not pay it
        from aerocal.certificates.document import Certificate
        from aerocal.pipeline import ProcessConfig
        from flows.process import calibrate_camera

        cfg = ProcessConfig()
        cfg = dataclasses.replace(cfg, calibration=dataclasses.replace(cfg.calibration, **settings))
        with run_status(f"calibrating from {flight_dir}"):
            summary = calibrate_camera(
                flight_dir, out, cfg, conceal_password(database_url), str(artifact_root) if artifact_root else None,
                dask,
            )
        cert = Certificate.from_json(Path(summary.files["calibration_certificate"]).read_text())
    console.print(cert.render_text(correlation_threshold=0.9))
    console.print(f"stored: {summary.certificate_id} ({summary.certificate_reason})")
    console.print(f"certificate file: {summary.files['calibration_certificate']}")
    if cert.status != "accepted":
        console.print("[bold red]the calibration was REJECTED[/]: it is on record but will never be used; "
                      "see the review above")
        raise typer.Exit(FAILED)


def report(
    run_dir: Path = typer.Argument(..., help="Run folder written by `aerocal process`."),
    as_json: bool = typer.Option(False, "--json", help="Print the report's numbers as JSON."),
) -> None:
    """Show a processed flight's key figures and its files.

    Reads the run folder's summary.json (written with report.html by `aerocal process`).

    Example: aerocal report runs/2016-03-14

    Example: aerocal report runs/2016-03-14 --json
    """
    path = run_dir / "summary.json"
    if not path.is_file():
        fail(f"{path}: no such file; give a run folder written by `aerocal process` (or re-run it)", BAD_INPUT)
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        fail(f"{path}:{exc.lineno}: not valid JSON ({exc.msg}); re-run `aerocal process` to rewrite it", BAD_INPUT)
    if as_json:
        console.print_json(json.dumps(doc))
        return
    print_key_values(doc.get("title", f"report of {run_dir}"), doc.get("summary", {}))
    for name in REPORT_FILES:
        if (run_dir / name).exists():
            console.print(f"{name:>16}: {(run_dir / name).resolve()}")
