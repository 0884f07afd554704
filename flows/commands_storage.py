"""Command-line groups of the storage layer: ``aerocal db``, ``aerocal certificates``, ``aerocal runs``.

Every command takes ``--database-url`` (default ``$AEROCAL_DATABASE_URL``, else the SQLite file under
``~/.local/share/aerocal``). Errors are one line naming what is wrong and the fix, with exit code 1.
Foreign certificate formats (OpenCV, COLMAP, OpenSfM, Metashape) go through :mod:`aerocal.formats`,
imported only when such a format is used.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from enum import StrEnum
from pathlib import Path
from typing import Any, NoReturn

import typer
from rich.console import Console
from rich.table import Table

console = Console(highlight=False, soft_wrap=True)
err_console = Console(stderr=True, highlight=False, soft_wrap=True)

_URL_HELP = "Database URL (default: $AEROCAL_DATABASE_URL, else ~/.local/share/aerocal/aerocal.db)."
DATABASE_URL_OPTION = typer.Option(None, "--database-url", help=_URL_HELP, show_default=False)

db_app = typer.Typer(help="Database migrations: upgrade, downgrade, current.", no_args_is_help=True)
certificates_app = typer.Typer(
    help="Calibration certificates: list, show, export, import.", no_args_is_help=True
)
runs_app = typer.Typer(help="Processing runs and their provenance.", no_args_is_help=True)


class ExportFormat(StrEnum):
    """Formats a certificate exports to (json: the lossless aerocal certificate document)."""

    json = "json"
    opencv = "opencv"
    colmap = "colmap"
    opensfm = "opensfm"
    metashape = "metashape"


#: exit code of a command refused because of its input (1: it failed)
BAD_INPUT = 2


def _fail(message: str, code: int = 1) -> NoReturn:
    err_console.print(f"[red]error:[/red] {' '.join(str(message).split())}", markup=True, soft_wrap=True)
    raise typer.Exit(code)


@contextlib.contextmanager
def _user_errors(source: str | None = None) -> Iterator[None]:
    """Turn the errors a user can cause into one line: exit code 2 for bad input (the file ``source``, an
    argument), 1 for what failed (the database)."""
    from storage.errors import StorageError

    where = f"{source}: " if source else ""
    try:
        yield
    except StorageError as exc:
        _fail(f"{where}{exc}" if source and source not in str(exc) else str(exc))
    except json.JSONDecodeError as exc:
        _fail(f"{where}line {exc.lineno} column {exc.colno}: not valid JSON ({exc.msg}); fix the file there",
              BAD_INPUT)
    except OSError as exc:
        name = exc.filename or source or ""
        _fail(f"{name}: {exc.strerror or exc}; check the path", BAD_INPUT)
    except ValueError as exc:  # includes aerocal's FormatError and CertificateError
        message = str(exc)
        _fail(message if source is None or source in message else f"{where}{message}", BAD_INPUT)


def _open(url: str | None, migrated: bool = True):  # -> storage.database.Database
    """Connect; with ``migrated``, the database must exist at the newest schema. A command that only reads
    never creates a SQLite file (a mistyped path, or no database configured yet, is said, not made)."""
    from sqlalchemy.engine import make_url

    from storage.database import connect, database_url
    from storage.errors import DatabaseURLError
    from storage.migrations import require_current

    if migrated:
        parsed = make_url(url or database_url())
        path = parsed.database or ""
        if parsed.get_backend_name() == "sqlite" and path and path != ":memory:" and not path.startswith("file:") \
                and not Path(path).expanduser().exists():
            raise DatabaseURLError(
                f"no database at {path}: run `aerocal db upgrade` (or `aerocal init`) to create it, or give the "
                "right --database-url / AEROCAL_DATABASE_URL"
            )
    db = connect(url)
    if migrated:
        require_current(db)
    return db


# ------------------------------------------------------------------------------------------ db
@db_app.command("upgrade")
def db_upgrade(
    revision: str = typer.Option("head", "--revision", help="Revision to migrate to."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Create or migrate the database schema up to REVISION (default: the newest).

    Example: aerocal db upgrade --database-url postgresql+psycopg://aerocal@localhost/aerocal
    """
    from storage import migrations

    with _user_errors():
        db = _open(database_url, migrated=False)
        try:
            before = migrations.current(db)
            migrations.upgrade(db, revision)
            after = migrations.current(db)
        finally:
            db.dispose()
    console.print(f"database {db.masked_url}: {before or 'empty'} -> {after or 'empty'}")


@db_app.command("downgrade")
def db_downgrade(
    revision: str = typer.Argument(
        ..., help="Revision to migrate down to; 'base' drops every aerocal table."
    ),
    yes: bool = typer.Option(False, "--yes", help="Do not ask for confirmation."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Migrate the database schema down to REVISION (data in dropped tables is lost).

    Example: aerocal db downgrade base --yes
    """
    from storage import migrations

    with _user_errors():
        db = _open(database_url, migrated=False)
        try:
            before = migrations.current(db)
            if not yes and not typer.confirm(f"migrate {db.masked_url} from {before} down to {revision}?"):
                _fail("downgrade cancelled; pass --yes to skip the question")
            migrations.downgrade(db, revision)
            after = migrations.current(db)
        finally:
            db.dispose()
    console.print(f"database {db.masked_url}: {before or 'empty'} -> {after or 'empty'}")


@db_app.command("current")
def db_current(database_url: str | None = DATABASE_URL_OPTION) -> None:
    """Show the schema revision of the database and the newest one this aerocal knows.

    Example: aerocal db current
    """
    from storage import migrations

    with _user_errors():
        db = _open(database_url, migrated=False)
        try:
            revision = migrations.current(db)
        finally:
            db.dispose()
        head = migrations.head()
    if revision is None:
        console.print(f"database {db.masked_url}: empty (head is {head}); run `aerocal db upgrade`")
    elif revision == head:
        console.print(f"database {db.masked_url}: {revision} (head)")
    else:
        console.print(f"database {db.masked_url}: {revision} (head is {head}); run `aerocal db upgrade`")


# -------------------------------------------------------------------------------- certificates
def _fmt(value: Any, spec: str = ".4g") -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return format(value, spec)
    return str(value)


def _range_text(rng: Any) -> str:
    if not rng:
        return "-"
    return f"{rng[0]:g}..{rng[1]:g}"


@certificates_app.command("list")
def certificates_list(
    camera: str | None = typer.Option(
        None, "--camera", help="Only cameras whose make, model, serial or lens contain all these words."
    ),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """List stored certificates by camera and version.

    Example: aerocal certificates list --camera "TS9260 123"
    """
    from storage.certificates import list_certificates

    with _user_errors():
        db = _open(database_url)
        try:
            with db.session() as session:
                rows = list_certificates(session, camera)
        finally:
            db.dispose()
    if not rows:
        console.print("no certificates" + (f" for cameras matching {camera!r}" if camera else ""))
        return
    superseded = {row.supersedes for row in rows if row.supersedes}
    table = Table(title=f"{len(rows)} certificate(s)")
    for column in ("id", "camera", "v", "status", "calibrated", "issued", "degC", "thermal", "sigma0", "rms px"):
        table.add_column(column, no_wrap=column != "camera", overflow="fold")
    for row in rows:
        version = f"{row.version}" + ("" if row.id in superseded else " (latest)")
        table.add_row(
            row.id,
            row.camera.label,
            version,
            row.status if row.status == "accepted" else f"[red]{row.status}[/]",
            str(row.calibration_date),
            row.issued.strftime("%Y-%m-%d %H:%M"),
            _range_text(row.temperature_range),
            row.thermal_kind or "-",
            _fmt(row.sigma0, ".3f"),
            _fmt(row.reprojection_rms_px, ".3f"),
        )
    console.print(table)


@certificates_app.command("show")
def certificates_show(
    certificate_id: str = typer.Argument(..., metavar="ID", help="Certificate id (or a unique prefix)."),
    as_json: bool = typer.Option(False, "--json", help="Print the full certificate document as JSON."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Show one certificate: camera, version, coverage, parameters with sigmas, quality, provenance.

    Example: aerocal certificates show 3f2a9c --json
    """
    from storage.certificates import get_certificate

    with _user_errors():
        db = _open(database_url)
        try:
            with db.session() as session:
                cert = get_certificate(session, certificate_id)
                doc = cert.document
        finally:
            db.dispose()
    if as_json:
        console.print_json(json.dumps(doc))
        return
    summary = Table(title=f"certificate {cert.id}", show_header=False)
    summary.add_column("field", no_wrap=True)
    summary.add_column("value", overflow="fold")
    conditions = doc.get("conditions") or {}
    quality = doc.get("quality") or {}
    provenance = doc.get("provenance") or {}
    thermal = doc.get("thermal")
    for key, value in (
        ("camera", cert.camera.label),
        ("version", f"{cert.version}" + (f" (supersedes {cert.supersedes})" if cert.supersedes else "")),
        ("review", cert.status + "".join(f"\n  problem: {p}" for p in (doc.get("review") or {}).get("problems", []))
         + "".join(f"\n  note: {n}" for n in (doc.get("review") or {}).get("notes", []))),
        ("issued", cert.issued.isoformat()),
        ("calibrated", str(cert.calibration_date)),
        ("temperatures degC", _range_text(cert.temperature_range)),
        ("model", cert.model_kind),
        ("thermal model", "none (constant IO)" if not thermal else thermal.get("kind", "?")),
        (
            "images / strips / GCPs",
            " / ".join(_fmt(conditions.get(k)) for k in ("n_images", "strips", "n_gcp")),
        ),
        ("sigma0", _fmt(quality.get("sigma0"))),
        ("reprojection RMS px", _fmt(quality.get("reprojection_rms_px"))),
        ("flow run", _fmt(provenance.get("flow_run"))),
        ("code version", _fmt(provenance.get("code_version"))),
    ):
        summary.add_row(key, value)
    console.print(summary)
    params = ((doc.get("model") or {}).get("params")) or {}
    sigmas = doc.get("sigmas") or {}
    estimated = set(doc.get("estimated") or [])
    if params:
        table = Table(title="interior orientation (pixels; k, p dimensionless)")
        for column in ("parameter", "value", "sigma", "estimated"):
            table.add_column(column, justify="right" if column in ("value", "sigma") else "left")
        for name, value in params.items():
            table.add_row(
                name, _fmt(value, ".6g"), _fmt(sigmas.get(name), ".3g"), "yes" if name in estimated else ""
            )
        console.print(table)


def _write_json(path: Path, doc: dict[str, Any]) -> None:
    from aerocal.io import write_json_atomic

    write_json_atomic(path, doc)


@certificates_app.command("export")
def certificates_export(
    certificate_id: str = typer.Argument(..., metavar="ID", help="Certificate id (or a unique prefix)."),
    fmt: ExportFormat = typer.Option(ExportFormat.json, "--format", help="File format to write."),
    out: Path = typer.Option(..., "--out", help="File to write (replaced atomically)."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Write a stored certificate to a file, as aerocal JSON or in another tool's format.

    Example: aerocal certificates export 3f2a9c --format opencv --out camera.yaml
    """
    from storage.certificates import get_certificate

    with _user_errors():
        db = _open(database_url)
        try:
            with db.session() as session:
                cert = get_certificate(session, certificate_id)
                doc = cert.document
        finally:
            db.dispose()
    with _user_errors(str(out)):
        if fmt is ExportFormat.json:
            _write_json(out, doc)
        else:
            formats = _formats_module()
            formats.export_certificate(doc, fmt.value, out)
    console.print(f"certificate {cert.id} (v{cert.version}, {cert.camera.label}) -> {out} ({fmt.value})")


def _formats_module():  # -> the aerocal.formats module
    try:
        from aerocal import formats
    except ImportError as exc:
        _fail(f"certificate formats are not available in this installation ({exc}); use --format json")
    return formats


def _read_document(path: Path, fmt: str | None, identity: dict[str, str]) -> dict[str, Any]:
    """The certificate document in ``path``: aerocal JSON directly, other formats via aerocal.formats.

    ``identity`` (make, model, serial, lens given on the command line) replaces what the file says.
    """
    doc: Any = None
    if fmt == "json" or (fmt is None and path.suffix.lower() == ".json"):
        doc = json.loads(path.read_text(encoding="utf-8"))
        is_ours = isinstance(doc, dict) and str(doc.get("schema", "")).startswith("aerocal.certificate")
        if fmt == "json" and not is_ours:
            raise ValueError("not an aerocal certificate document (no 'schema': 'aerocal.certificate/1')")
        if not is_ours:
            doc = None  # another tool's JSON (OpenSfM cameras.json)
    if doc is None:
        formats = _formats_module()
        kwargs: dict[str, Any] = {}
        if identity:
            from aerocal.certificate import CameraIdentity as EngineIdentity

            kwargs["identity"] = EngineIdentity(**identity)
        imported = formats.import_certificate(path, fmt, **kwargs)
        doc = imported.to_dict() if hasattr(imported, "to_dict") else dict(imported)
    if identity:
        doc["camera"] = {**dict(doc.get("camera") or {}), **identity}
    camera = doc.get("camera") if isinstance(doc.get("camera"), dict) else {}
    missing = [
        k for k in ("make", "model", "serial") if str(camera.get(k) or "").strip().lower() in ("", "unknown")
    ]
    if missing:
        options = ", ".join(f"--{k}" for k in missing)
        raise ValueError(f"the file does not name the camera's {', '.join(missing)}; pass {options}")
    _validate_strictly(doc)
    return doc


def _validate_strictly(doc: dict[str, Any]) -> None:
    """Validate the whole document with :mod:`aerocal.certificate` (the store checks only what it indexes)."""
    try:
        from aerocal.certificate import Certificate
    except ImportError:  # the store's own checks still apply
        return
    Certificate.from_dict(doc)


@certificates_app.command("import")
def certificates_import(
    file: Path = typer.Argument(
        ...,
        help="Certificate file: aerocal JSON, OpenCV YAML, COLMAP cameras.txt, OpenSfM cameras.json "
        "or Metashape XML.",
    ),
    fmt: ExportFormat | None = typer.Option(None, "--format", help="File format (default: from the file)."),
    make: str | None = typer.Option(None, "--make", help="Camera make (foreign formats do not record it)."),
    model: str | None = typer.Option(None, "--model", help="Camera model."),
    serial: str | None = typer.Option(None, "--serial", help="Camera serial number."),
    lens: str | None = typer.Option(None, "--lens", help="Lens (default: unknown)."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Store a certificate from a file as the next version for its camera.

    Example: aerocal certificates import camera.yaml --make NEC --model TS9260 --serial 123
    """
    from storage.certificates import issue_certificate

    identity = {k: v for k, v in (("make", make), ("model", model), ("serial", serial), ("lens", lens)) if v}
    if not file.is_file():
        _fail(f"{file}: no such file; check the path", BAD_INPUT)
    with _user_errors(str(file)):
        doc = _read_document(file, fmt.value if fmt else None, identity)
        db = _open(database_url)
        try:
            with db.session() as session:
                cert = issue_certificate(session, doc)
        finally:
            db.dispose()
    superseded = f", supersedes {cert.supersedes}" if cert.supersedes else ""
    console.print(f"stored certificate {cert.id}: {cert.camera.label} version {cert.version}{superseded}")


# ---------------------------------------------------------------------------------------- runs
@runs_app.command("list")
def runs_list(
    limit: int = typer.Option(50, "--limit", min=1, help="Show at most this many runs, newest first."),
    kind: str | None = typer.Option(None, "--kind", help="Only runs of this kind (e.g. process_flight)."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """List flow runs, newest first.

    Example: aerocal runs list --kind process_flight --limit 10
    """
    from storage.runs import list_runs, reap_dead_runs

    with _user_errors():
        db = _open(database_url)
        try:
            with db.session() as session:
                # a run whose process is gone is not "running": recorded as failed, and said
                dead = [f"run {r.id}: {r.error}" for r in reap_dead_runs(session)]
                session.commit()
                rows = list_runs(session, limit=limit, kind=kind)
                flights = {row.id: row.flight.name if row.flight else "-" for row in rows}
        finally:
            db.dispose()
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
            _fmt(seconds, ".1f"),
            flights[row.id],
            row.certificate_id or "-",
        )
    console.print(table)


@runs_app.command("show")
def runs_show(
    run_id: str = typer.Argument(..., metavar="RUN_ID", help="Flow-run id."),
    as_json: bool = typer.Option(False, "--json", help="Print the provenance as JSON."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Show a run's provenance: inputs, certificate and why, configuration, timings, outputs.

    Example: aerocal runs show 0d9f6c1e-5b7a-4f4e-9d55-2b1f0c8e7a31
    """
    from storage.provenance import provenance

    with _user_errors():
        db = _open(database_url)
        try:
            with db.session() as session:
                prov = provenance(session, run_id)
        finally:
            db.dispose()
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
        ("certificate", f"{cert.id} v{cert.version} ({cert.camera})" if cert else "-"),
        ("why", (cert.reason or "-") if cert else "-"),
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
