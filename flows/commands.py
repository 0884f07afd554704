"""Platform commands of the ``aerocal`` CLI: init, process, calibrate, campaign, serve, ingest, match, report.

Each is a typer app registered lazily by :mod:`aerocal.cli` (a one-command app becomes a plain command).
Prefect, SQLAlchemy and the flows are imported only inside the commands, after
:func:`flows.environment.quiet_prefect` has set Prefect's environment. Every error a user can cause is one
line naming what is wrong and the fix, with exit code 1.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NoReturn

import typer
from rich.console import Console
from rich.table import Table

console = Console(highlight=False, soft_wrap=True)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)

_URL_HELP = "Database URL (default: $AEROCAL_DATABASE_URL, else ~/.local/share/aerocal/aerocal.db)."
_ART_HELP = "Artifact store folder (default: $AEROCAL_ARTIFACT_ROOT, else ~/.local/share/aerocal/artifacts)."
_DASK_HELP = "Address of a Dask scheduler (e.g. tcp://scheduler:8786); default: a local cluster per step."


#: exit code of a command refused because of its input (1: it failed; 130: interrupted)
BAD_INPUT = 2


def _fail(message: str, code: int = 1) -> NoReturn:
    err_console.print(f"[red]error:[/red] {' '.join(str(message).split())}", markup=True, soft_wrap=True)
    raise typer.Exit(code)


@contextlib.contextmanager
def _user_errors() -> Iterator[None]:
    """Turn the errors a user can cause into one line: exit code 2 for bad input (a flight folder, file or
    argument that is wrong or missing), 1 for what failed (the database, an adjustment that cannot go on)."""
    _prefect_ready()  # the error classes live in modules that import Prefect: its environment first
    from flows.flight import FlowInputError
    from storage.errors import StorageError
    from tasks.flight import FlightInputError

    try:
        yield
    except StorageError as exc:
        _fail(str(exc))
    except (FlowInputError, FlightInputError) as exc:
        _fail(str(exc), BAD_INPUT)
    except OSError as exc:
        _fail(f"{exc.filename or ''}: {exc.strerror or exc}; check the path", BAD_INPUT)
    except (ValueError, LookupError) as exc:  # CertificateError, AdjustmentError, ...
        _fail(str(exc))


def conceal_password(url: str | None) -> str | None:
    """The URL with its password replaced by a reference only this process resolves: flow parameters are
    stored by Prefect's server, a password must not be (:func:`flows.environment.conceal_password`)."""
    from flows.environment import conceal_password as conceal

    return conceal(url)


@contextlib.contextmanager
def _flow_errors(out_dir: Path) -> Iterator[None]:
    """Around a flow run: the user's errors as one line (exit 1), Ctrl-C as one line saying what is kept and
    how to resume (exit 130), and a defect as one line naming the run folder's traceback file (exit 1)."""
    from flows.flight import FAILURE_LOG
    from tasks.resume import interrupts_noted

    try:
        with _user_errors(), interrupts_noted():
            yield
    except typer.Exit:
        raise
    except KeyboardInterrupt:
        err_console.print("[yellow]interrupted[/yellow]: the steps completed so far are kept in the store; run "
                          "the same command again to resume after the last of them (the run is recorded as "
                          "cancelled)", markup=True)
        raise typer.Exit(130) from None
    except Exception as exc:  # a defect, not the user's input: one line here, the traceback in the run folder
        _fail(f"{type(exc).__name__}: {exc} (the full traceback is in {out_dir / FAILURE_LOG})")


def _prefect_ready() -> None:
    from flows.environment import quiet_prefect

    quiet_prefect()


def _require_folder(folder: Path, what: str = "a flight folder (images/ or observations/)") -> None:
    """Fail before any server starts when the folder does not exist."""
    if not folder.is_dir():
        _fail(f"{folder} is not a folder; give {what}", BAD_INPUT)


def _print_steps(summary: dict[str, Any]) -> None:
    table = Table(title=f"run {summary['run_id']} of {summary['flight']}")
    for col in ("step", "status", "seconds", "computed by"):
        table.add_column(col)
    for name, step in summary["steps"].items():
        table.add_row(
            name,
            step["status"] + (f" ({step['reason']})" if step.get("reason") else ""),
            f"{step.get('seconds', 0):.2f}",
            step.get("computed_by", "") or "",
        )
    console.print(table)


#: ingest problems the run summary prints (errors first); `aerocal ingest` lists them all
INGEST_LINES = 10


def _print_run(summary: dict[str, Any]) -> None:
    _print_steps(summary)
    skipped = summary.get("images_skipped_at_ingest") or []
    if skipped:
        from aerocal.ingest.problems import name_list

        console.print(f"[yellow]{len(skipped)} image(s) skipped at ingest[/yellow]: {name_list(skipped)} "
                      "(`aerocal ingest FOLDER` says why)")
    problems = summary.get("ingest_problems") or []
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
    for key, text in (summary.get("flight_facts") or {}).items():
        if not text.startswith(("flight.json", "/")):  # inferred from the images: say so
            console.print(f"{key}: {text}")
    control = summary.get("ground_control") or {}
    if control.get("demoted"):
        console.print(f"[yellow]ground control demoted[/yellow] (neither control nor check point): "
                      f"{', '.join(control['demoted'])}")
    for line in control.get("lines") or []:
        console.print(f"ground control: {line}")
    console.print(f"certificate: {summary['certificate_id']} ({summary['certificate_reason']})")
    if summary.get("adjustment_converged") is False:
        console.print(f"[yellow]the block adjustment did not converge[/yellow] ({summary.get('adjustment_iterations')} "
                      "iterations): its sigma0, residuals, products and diagnosis describe an unfinished solution")
    acc = summary.get("accuracy") or {}
    if acc.get("rho"):
        rho = ", ".join(f"{k} {v:.2f}" for k, v in acc["rho"].items() if v is not None)
        console.print(f"check points: rho {rho} -> {acc.get('verdict')}")
    if summary.get("diagnosis"):
        console.print(f"diagnosis: {summary['diagnosis']}")
    if summary.get("recorded_eo"):
        from tasks.products import recorded_eo_text

        console.print("recorded EO checks: " + recorded_eo_text(summary["recorded_eo"]))
    if summary.get("recorded_eo_corrections"):
        console.print("recorded positions in the block adjustment: " + "; ".join(summary["recorded_eo_corrections"]))
    if summary.get("twin"):
        console.print(f"twin (what the simulation gets wrong): {summary['twin']}")
    for name, path in summary.get("files", {}).items():
        console.print(f"{name:>13}: {path}")


# ------------------------------------------------------------------------------------------------ init
init_app = typer.Typer(help="Create the database (run migrations) and show where things live.")


@init_app.command("init")
def init(
    database_url: str | None = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False),
    artifact_root: Path | None = typer.Option(None, "--artifacts", help=_ART_HELP, show_default=False),
) -> None:
    """Create or migrate the database and print where the database, artifacts and Prefect API are.

    Example: aerocal init --database-url postgresql://aerocal@localhost/aerocal
    """
    import os

    with _user_errors():
        from flows.environment import resolve_storage

        where = resolve_storage(database_url, artifact_root)
    for key, value in where.describe().items():
        console.print(f"{key:>10}: {value}")
    api = os.environ.get("PREFECT_API_URL")
    console.print(f"{'prefect':>10}: {api or 'temporary local server per command (PREFECT_API_URL unset)'}")


# --------------------------------------------------------------------------------------------- process
process_app = typer.Typer(help="Process a flight end to end.")


@process_app.command("process")
def process(
    flight_dir: Path = typer.Argument(
        ..., help="Flight folder (images/ or observations/, eo.csv, gcp files)."
    ),
    certificate: str = typer.Option(
        "auto",
        "--certificate",
        help="auto (stored certificate that applies, else "
        "self-calibrate), none (always self-calibrate) or a certificate id.",
    ),
    out: Path | None = typer.Option(None, "--out", help="Run folder (default: FLIGHT_DIR-processed)."),
    dask: str | None = typer.Option(None, "--dask", help=_DASK_HELP),
    database_url: str | None = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False),
    artifact_root: Path | None = typer.Option(None, "--artifacts", help=_ART_HELP, show_default=False),
    as_json: bool = typer.Option(False, "--json", help="Print the run summary as JSON."),
) -> None:
    """Ingest, match, orient, calibrate or reuse a certificate, adjust, mosaic, assess, diagnose, report.

    A re-run after a crash resumes after the last completed step.

    Example: aerocal process flights/2016-03-14 --certificate auto --out runs/2016-03-14
    """
    _require_folder(flight_dir)
    _stop_if_not_processable(flight_dir)
    _prefect_ready()
    run_dir = (out or flight_dir.with_name(flight_dir.name + "-processed")).resolve()
    with _flow_errors(run_dir):
        from flows.flight import process_flight

        with console.status(f"processing {flight_dir} ..."):
            summary = process_flight(
                flight_dir,
                out,
                certificate,
                None,
                conceal_password(database_url),
                str(artifact_root) if artifact_root else None,
                dask,
            )
    if as_json:
        console.print_json(json.dumps(summary, default=str))
    else:
        _print_run(summary)


def _print_problems(result: Any, out: Console, warnings: bool = True, limit: int = 50) -> None:
    """Every error (blocking ones first), then warnings up to ``limit`` lines in all."""
    ordered = result.blocking + [p for p in result.errors if not p.stops_processing]
    if warnings:
        ordered += result.warnings[: max(0, limit - len(ordered))]
    for p in ordered:
        out.print(str(p), markup=False)
    rest = len(result.warnings) - len([p for p in ordered if p.severity == "warning"])
    if warnings and rest > 0:
        out.print(f"... and {rest} more warnings (aerocal ingest FOLDER --out DIR writes them all)")


def _stop_if_not_processable(flight_dir: Path) -> None:
    """Run ingest's checks on an image-mode flight before any server starts; on a blocking problem print
    ingest's errors and exit 2 (bad input)."""
    from aerocal.ingest import ingest_folder

    if (flight_dir / "observations" / "observations.parquet").is_file():
        return
    with _user_errors():
        with console.status(f"checking {flight_dir} ..."):
            result = ingest_folder(flight_dir)
    if result.blocking:
        err_console.print(
            f"[red]error:[/red] {flight_dir} cannot be processed: {len(result.blocking)} problem(s) stop "
            f"processing ({len(result.errors)} error(s) in all; nothing was processed or stored):",
            markup=True,
        )
        _print_problems(result, err_console, warnings=False)
        raise typer.Exit(2)


# ------------------------------------------------------------------------------------------- calibrate
calibrate_app = typer.Typer(help="Calibrate a camera from a flight and store the certificate.")


def _subset_config(subset: str) -> dict[str, Any]:
    from flows.flight import FlowInputError

    if subset == "auto":
        return {}
    path = Path(subset)
    if not path.is_file():
        raise FlowInputError(
            f"--subset {subset}: no such file; give auto or a file of image names or ids, one per line"
        )
    items = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        text = line.split("#", 1)[0].strip()
        if text:
            items.append((n, text))
    if not items:
        raise FlowInputError(f"{path}: no image names or ids; write one per line")
    if all(t.isdigit() for _, t in items):
        return {"subset_images": tuple(int(t) for _, t in items)}
    bad = [(n, t) for n, t in items if t.isdigit()]
    if bad:
        raise FlowInputError(
            f"{path}:{bad[0][0]}: {bad[0][1]!r} is an id among image names; use names or ids, not both"
        )
    return {"subset_names": tuple(t for _, t in items)}


@calibrate_app.command("calibrate")
def calibrate(
    flight_dir: Path = typer.Argument(..., help="A calibration flight folder."),
    subset: str = typer.Option(
        "auto",
        "--subset",
        help="auto (sub-block chosen by predicted IO precision) or "
        "a FILE of image names or ids, one per line.",
    ),
    out: Path | None = typer.Option(None, "--out", help="Run folder (default: FLIGHT_DIR-processed)."),
    dask: str | None = typer.Option(None, "--dask", help=_DASK_HELP),
    database_url: str | None = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False),
    artifact_root: Path | None = typer.Option(None, "--artifacts", help=_ART_HELP, show_default=False),
) -> None:
    """Self-calibrate on a sub-block, store the certificate and print it (parameters, sigmas, significance,
    dropped parameters, correlations above 0.9).

    Example: aerocal calibrate flights/calibration --subset subset.txt
    """
    import dataclasses

    with _user_errors():
        subset_config = _subset_config(subset)
    _require_folder(flight_dir)
    _prefect_ready()
    with _flow_errors((out or flight_dir.with_name(flight_dir.name + "-processed")).resolve()):
        from aerocal.certificate import Certificate
        from flows.config import ProcessConfig
        from flows.flight import calibrate_camera

        cfg = ProcessConfig()
        cfg.calibration = dataclasses.replace(cfg.calibration, **subset_config)
        with console.status(f"calibrating from {flight_dir} ..."):
            summary = calibrate_camera(
                flight_dir, out, cfg, conceal_password(database_url), str(artifact_root) if artifact_root else None,
                dask,
            )
        cert = Certificate.from_json(Path(summary["files"]["calibration_certificate"]).read_text())
    console.print(cert.render_text(correlation_threshold=0.9))
    console.print(f"stored: {summary['certificate_id']} ({summary['certificate_reason']})")
    console.print(f"certificate file: {summary['files']['calibration_certificate']}")
    if cert.status != "accepted":
        console.print("[bold red]the calibration was REJECTED[/]: it is on record but will never be used; "
                      "see the review above")
        raise typer.Exit(1)


# -------------------------------------------------------------------------------------------- campaign
campaign_app = typer.Typer(
    help="Campaigns: several flights of one camera, on demand or on a schedule.", no_args_is_help=True
)


@campaign_app.command("add")
def campaign_add(
    name: str = typer.Argument(..., help="Campaign name (created if new)."),
    flight_dirs: list[Path] = typer.Argument(..., help="Flight folders to add."),
    cron: str | None = typer.Option(
        None, "--cron", help="Five-field cron schedule in UTC, e.g. '0 3 * * *'."
    ),
    description: str | None = typer.Option(None, "--description", help="What the campaign is for."),
    database_url: str | None = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False),
    artifact_root: Path | None = typer.Option(None, "--artifacts", help=_ART_HELP, show_default=False),
) -> None:
    """Register flight folders and add them to a campaign.

    Example: aerocal campaign add seneca-2016 flights/0314 flights/0315 --cron '0 3 * * *'
    """
    _prefect_ready()
    with _user_errors():
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


@campaign_app.command("run")
def campaign_run(
    name: str = typer.Argument(..., help="Campaign name."),
    out: Path | None = typer.Option(None, "--out", help="Folder for the run folders (one per flight)."),
    dask: str | None = typer.Option(None, "--dask", help=_DASK_HELP),
    database_url: str | None = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False),
    artifact_root: Path | None = typer.Option(None, "--artifacts", help=_ART_HELP, show_default=False),
) -> None:
    """Process every flight of a campaign now (certificate made once per camera, then reused).

    Example: aerocal campaign run seneca-2016 --out runs/seneca-2016
    """
    _prefect_ready()
    with _user_errors():
        from flows.campaign import run_campaign

        with console.status(f"processing campaign {name} ..."):
            result = run_campaign(
                name,
                str(out) if out else None,
                conceal_password(database_url),
                str(artifact_root) if artifact_root else None,
                dask,
            )
    for summary in result["runs"]:
        _print_run(summary)


@campaign_app.command("list")
def campaign_list(
    database_url: str | None = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False),
) -> None:
    """List campaigns with their schedules and flights.

    Example: aerocal campaign list
    """
    with _user_errors():
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


# ----------------------------------------------------------------------------------------------- serve
serve_app = typer.Typer(help="Serve the campaigns' scheduled deployments (blocks).")


@serve_app.command("serve")
def serve(
    out: Path | None = typer.Option(None, "--out", help="Folder for the run folders of scheduled runs."),
    dask: str | None = typer.Option(None, "--dask", help=_DASK_HELP),
    database_url: str | None = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False),
    artifact_root: Path | None = typer.Option(None, "--artifacts", help=_ART_HELP, show_default=False),
    wait: float = typer.Option(
        0.0,
        "--wait",
        help="When no campaign has a schedule yet, look again every "
        "WAIT seconds instead of failing (0: fail).",
    ),
) -> None:
    """Register one Prefect deployment per scheduled campaign and run them on their cron schedules until
    interrupted. Campaigns added later are picked up at the next start. Set PREFECT_API_URL to a Prefect
    server for the schedules to persist.

    Example: PREFECT_API_URL=http://prefect:4200/api aerocal serve --out /data/runs --wait 60
    """
    import time

    _prefect_ready()
    with _user_errors():
        from flows.campaign import list_campaigns, serve_campaigns

        while wait > 0 and not any(c["cron"] for c in list_campaigns(database_url)):
            err_console.print(f"no scheduled campaign yet; looking again in {wait:g} s")
            time.sleep(wait)
        serve_campaigns(
            database_url, str(artifact_root) if artifact_root else None, str(out) if out else None, dask
        )


# ---------------------------------------------------------------------------------------------- ingest
ingest_app = typer.Typer(help="Ingest a flight folder and summarise what was found.")


@ingest_app.command("ingest")
def ingest(
    folder: Path = typer.Argument(..., help="Flight folder or folder of images."),
    gcp: list[Path] = typer.Option([], "--gcp", help="GCP file (ODM gcp_list.txt or CSV); repeatable."),
    eo: Path | None = typer.Option(None, "--eo", help="Exterior-orientation CSV (default: eo.csv)."),
    crs: str | None = typer.Option(None, "--crs", help="Projected CRS, e.g. EPSG:32632 (default: UTM zone)."),
    out: Path | None = typer.Option(None, "--out", help="Write the ingested tables to this folder."),
) -> None:
    """Read images, metadata, EO and ground control; print a summary and every problem by file and line.

    Exit code 0 when nothing is wrong (warnings only), 2 when there are errors: skipped images or rows, and
    problems that stop `aerocal process` (each names the file, the field and the fix).

    Example: aerocal ingest flights/0314 --gcp gcp_list.txt --eo eo.csv
    """
    from aerocal.ingest import ingest_folder, summary_rows, write_ingest

    if not folder.exists():
        _fail(f"{folder}: no such folder; give a flight folder or a folder of images", BAD_INPUT)
    with _user_errors():
        with console.status(f"ingesting {folder} ..."):
            result = ingest_folder(folder, gcp_file=list(gcp) or None, eo_file=eo, crs=crs)
        if out is not None:
            write_ingest(result, out)
    table = Table(title=f"ingest of {folder}", show_header=False)
    for item, value in summary_rows(result):
        table.add_row(item, value)
    console.print(table)
    _print_problems(result, console)
    if out is not None:
        console.print(f"tables written to {out}")
    if result.blocking:
        err_console.print(
            f"[red]{len(result.blocking)} problem(s) stop `aerocal process`[/red] (marked 'stops processing'); "
            "fix them and ingest again",
            markup=True,
        )
    if result.errors:
        raise typer.Exit(2)


# ----------------------------------------------------------------------------------------------- match
match_app = typer.Typer(help="Match a flight's images into tie-point observations.")


@match_app.command("match")
def match(
    folder: Path = typer.Argument(
        ..., help="Flight folder with images/ (and eo.csv, gcp files, camera.json)."
    ),
    out: Path | None = typer.Option(
        None, "--out", help="Folder for the tables (default: FOLDER/observations)."
    ),
    dask: str | None = typer.Option(None, "--dask", help=_DASK_HELP),
    workers: int = typer.Option(2, "--workers", help="Local Dask workers when --dask is not given."),
) -> None:
    """Enhance and match the frames (tile-parallel SIFT on Dask), write images, observations, gcps and
    gcp_observations tables; the folder can then be processed in observations mode.

    Example: aerocal match flights/0314 --dask tcp://scheduler:8786
    """
    from aerocal import tables
    from aerocal.ingest import ingest_folder

    if not folder.is_dir():
        _fail(f"{folder}: no such folder; give a flight folder with images/", BAD_INPUT)
    with _user_errors():
        from tasks.flight import FlightInputError, MatchStepConfig, match_images

        res = ingest_folder(folder)
        if res.images.num_rows == 0:
            raise FlightInputError(
                f"{folder}: no image could be ingested; run `aerocal ingest {folder}` to see why"
            )
        if res.camera is None:
            raise FlightInputError(
                f"{folder / 'camera.json'} is missing; matching needs the camera's nominal "
                "model (width, height, f, cx, cy in pixels) there"
            )
        meta_path = folder / "flight.json"
        meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
        meta["folder"] = str(folder)
        with console.status(f"matching {res.images.num_rows} images ..."):
            kp, matches, obs, n_pairs = match_images(
                res.images, res.camera, res.gcps, meta, MatchStepConfig(dask_workers=workers), dask
            )
        target = out or folder / "observations"
        for kind, tab in (
            ("images", res.images),
            ("observations", obs),
            ("gcps", res.gcps),
            ("gcp_observations", res.gcp_observations),
            ("keypoints", kp),
            ("matches", matches),
        ):
            tables.write(tab, target / f"{kind}.parquet", kind)
    console.print(
        f"{res.images.num_rows} images, {n_pairs} candidate pairs, {matches.num_rows} verified matches, "
        f"{obs.num_rows} observations of {len(set(obs.column('track_id').to_pylist()))} tracks"
    )
    console.print(f"tables written to {target}")


# ---------------------------------------------------------------------------------------------- report
report_app = typer.Typer(help="Show the report of a processed flight.")


@report_app.command("report")
def report(
    run_dir: Path = typer.Argument(..., help="Run folder written by `aerocal process`."),
    as_json: bool = typer.Option(False, "--json", help="Print the report's numbers as JSON."),
) -> None:
    """Print the key figures of a run folder's report and where its files are.

    Example: aerocal report runs/2016-03-14
    """
    path = run_dir / "summary.json"
    if not path.is_file():
        _fail(f"{path}: no such file; give a run folder written by `aerocal process` (or re-run it)", BAD_INPUT)
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        _fail(f"{path}:{exc.lineno}: not valid JSON ({exc.msg}); re-run `aerocal process` to rewrite it", BAD_INPUT)
    if as_json:
        console.print_json(json.dumps(doc))
        return
    table = Table(title=doc.get("title", f"report of {run_dir}"), show_header=False)
    for key, value in doc.get("summary", {}).items():
        table.add_row(key, json.dumps(value) if isinstance(value, list | dict) else str(value))
    console.print(table)
    for name in ("report.html", "orthomosaic.tif", "dsm.tif", "certificate.json", "provenance.json"):
        if (run_dir / name).exists():
            console.print(f"{name:>16}: {(run_dir / name).resolve()}")
