"""Commands for calibration certificates: the ``aerocal certificates`` group (``list``, ``show``, ``export``,
``import``).

Foreign certificate formats (OpenCV, COLMAP, OpenSfM, Metashape) go through :mod:`aerocal.formats`, and the
store through :mod:`storage.certificates` (SQLAlchemy: about 0.2 s to import); both are imported inside the
commands, only when used.
"""

from __future__ import annotations

import json
from enum import StrEnum
from pathlib import Path
from typing import Any

import typer
from rich.table import Table

from flows.cli.console import console
from flows.cli.database import open_database
from flows.cli.errors import BAD_INPUT, fail, user_errors
from flows.cli.help_text import command
from flows.cli.options import DATABASE_URL_OPTION

certificates_app = typer.Typer(
    help="Calibration certificates: list, show, export, import.\n\n"
    "A certificate is an immutable, versioned camera calibration (interior orientation with sigmas, its "
    "coverage and provenance); `aerocal process --certificate auto` uses the newest one that applies.\n\n"
    "Example: aerocal certificates list",
    no_args_is_help=True,
)


class ExportFormat(StrEnum):
    """Formats a certificate exports to (json: the lossless aerocal certificate document)."""

    json = "json"
    opencv = "opencv"
    colmap = "colmap"
    opensfm = "opensfm"
    metashape = "metashape"


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


@command(certificates_app, "list")
def certificates_list(
    camera: str | None = typer.Option(
        None, "--camera", help="Only cameras whose make, model, serial or lens contain all these words."
    ),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """List stored certificates by camera and version.

    Example: aerocal certificates list

    Example: aerocal certificates list --camera "TS9260 123"
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage.certificates import list_certificates

    with user_errors():
        with open_database(database_url) as db:
            with db.session() as session:
                rows = list_certificates(session, camera)
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


@command(certificates_app, "show")
def certificates_show(
    certificate_id: str = typer.Argument(..., metavar="ID", help="Certificate id (or a unique prefix)."),
    as_json: bool = typer.Option(False, "--json", help="Print the full certificate document as JSON."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Show a certificate: parameters, sigmas, quality, provenance.

    Also its camera, version, review and coverage (dates, temperatures, images, strips, GCPs).

    Example: aerocal certificates show 3f2a9c

    Example: aerocal certificates show 3f2a9c --json
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up), the engine numpy; --help must not pay it
    from aerocal.certificates.document import Quality
    from storage.certificates import get_certificate

    with user_errors():
        with open_database(database_url) as db:
            with db.session() as session:
                cert = get_certificate(session, certificate_id)
                doc = cert.document
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
        ("sigmas", Quality(overdispersion=quality.get("overdispersion")).sigmas_text()),
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


@command(certificates_app, "export")
def certificates_export(
    certificate_id: str = typer.Argument(..., metavar="ID", help="Certificate id (or a unique prefix)."),
    fmt: ExportFormat = typer.Option(ExportFormat.json, "--format", help="File format to write."),
    out: Path = typer.Option(..., "--out", help="File to write (replaced atomically)."),
    database_url: str | None = DATABASE_URL_OPTION,
) -> None:
    """Write a certificate to a file, in any supported format.

    As the lossless aerocal JSON document, or in OpenCV, COLMAP, OpenSfM or Metashape's format.

    Example: aerocal certificates export 3f2a9c --out camera.json

    Example: aerocal certificates export 3f2a9c --format opencv --out camera.yaml
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU), aerocal.io numpy (~0.07 s); --help must not pay them
    from aerocal.io import write_json_atomic
    from storage.certificates import get_certificate

    with user_errors():
        with open_database(database_url) as db:
            with db.session() as session:
                cert = get_certificate(session, certificate_id)
                doc = cert.document
    with user_errors(out):
        if fmt is ExportFormat.json:
            write_json_atomic(out, doc)
        else:
            _formats_module().export_certificate(doc, fmt.value, out)
    console.print(f"certificate {cert.id} (v{cert.version}, {cert.camera.label}) -> {out} ({fmt.value})")
    if fmt.value == "metashape" and "rolling_shutter" in (doc.get("effects") or {}):
        console.print("  a Metashape cameras XML (File > Import > Import Cameras): its sensor's rolling-shutter "
                      "flag is on; the readout is in a comment (Metashape has no field for it)")


def _formats_module():  # -> the aerocal.formats module
    try:
        # lazy: aerocal.formats costs ~0.4 s CPU at start-up; --help must not pay it
        from aerocal import formats
    except ImportError as exc:
        fail(f"certificate formats are not available in this installation ({exc}); use --format json")
    return formats


def _read_document(path: Path, fmt: str | None, identity: dict[str, str]) -> dict[str, Any]:
    """The certificate document in ``path``: aerocal JSON directly, other formats via aerocal.formats.

    ``identity`` (make, model, serial, lens given on the command line) replaces what the file says.
    """
    # lazy: aerocal.certificates.document costs ~0.2 s CPU at start-up (numpy, pydantic); --help must not pay it
    from aerocal.certificates.document import CameraIdentity, Certificate

    doc: Any = None
    if fmt == "json" or (fmt is None and path.suffix.lower() == ".json"):
        doc = json.loads(path.read_text(encoding="utf-8"))
        is_ours = isinstance(doc, dict) and str(doc.get("schema", "")).startswith("aerocal.certificate/")
        if fmt == "json" and not is_ours:
            raise ValueError("not an aerocal certificate document (no 'schema': 'aerocal.certificate/1')")
        if not is_ours:
            doc = None  # another tool's JSON (OpenSfM cameras.json)
    if doc is None:
        formats = _formats_module()
        kwargs: dict[str, Any] = {"identity": CameraIdentity(**identity)} if identity else {}
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
    Certificate.from_dict(doc)  # the whole document, strictly (the store checks only what it indexes)
    return doc


@command(certificates_app, "import")
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
    """Store a certificate file as its camera's next version.

    Foreign formats do not record the camera: name it with --make, --model and --serial.

    Example: aerocal certificates import camera.json

    Example: aerocal certificates import camera.yaml --make NEC --model TS9260 --serial 123
    """
    # lazy: storage imports SQLAlchemy (~0.5 s CPU at start-up); --help must not pay it
    from storage.certificates import issue_certificate

    identity = {k: v for k, v in (("make", make), ("model", model), ("serial", serial), ("lens", lens)) if v}
    if not file.is_file():
        fail(f"{file}: no such file; check the path", BAD_INPUT)
    with user_errors(file):
        doc = _read_document(file, fmt.value if fmt else None, identity)
        with open_database(database_url) as db:
            with db.session() as session:
                cert = issue_certificate(session, doc)
    superseded = f", supersedes {cert.supersedes}" if cert.supersedes else ""
    console.print(f"stored certificate {cert.id}: {cert.camera.label} version {cert.version}{superseded}")
