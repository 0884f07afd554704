"""Writing an ingest result to a folder, and reading it back, with nothing partial ever trusted.

Layout of ``out_dir``::

    images.parquet, gcps.parquet, gcp_observations.parquet   (aerocal.tables schemas, via tables.write)
    extra.parquet                                            (per-image metadata outside the schema)
    ingest.json                                              (manifest: CRS, sha256 of each table, problems,
                                                              sources, configuration)

Every file is written atomically (temporary file, fsync, rename). The manifest is removed first and
written last: a folder whose manifest is missing or whose tables do not match the hashes it lists is an
interrupted write, and :func:`read_ingest` refuses it with a message naming the file.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from aerocal import tables
from aerocal.ingest.folder import IngestResult
from aerocal.ingest.problems import Problem
from aerocal.io import atomic_path, write_json_atomic

MANIFEST = "ingest.json"
TABLE_FILES = {
    "images": "images.parquet",
    "gcps": "gcps.parquet",
    "gcp_observations": "gcp_observations.parquet",
}
EXTRA_FILE = "extra.parquet"
FORMAT_VERSION = 1


class IngestOutputError(ValueError):
    """An ingest folder is incomplete or inconsistent; the message names the file."""


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_ingest(result: IngestResult, out_dir: str | Path) -> Path:
    """Write an ingest result to ``out_dir``: the tables, then the manifest (layout in the module docstring).

    The manifest is removed first and written last, every file atomically: a folder whose write was
    interrupted has no manifest, and :func:`read_ingest` refuses it.

    Args:
        result: what :func:`aerocal.ingest.folder.ingest_folder` returned.
        out_dir: the folder (created with its parents when missing); files of an earlier write are replaced.

    Returns:
        The path of the manifest, ``out_dir/ingest.json``.

    Raises:
        SchemaError: a table of ``result`` does not match its :mod:`aerocal.tables` schema.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    manifest = out / MANIFEST
    if manifest.exists():
        manifest.unlink()
    hashes: dict[str, str] = {}
    for kind, name in TABLE_FILES.items():
        path = tables.write(getattr(result, kind), out / name, kind)
        hashes[name] = _sha256(path)
    with atomic_path(out / EXTRA_FILE) as tmp:
        pq.write_table(result.extra, tmp)
    hashes[EXTRA_FILE] = _sha256(out / EXTRA_FILE)
    doc = {
        "format": "aerocal.ingest",
        "version": FORMAT_VERSION,
        "crs": result.crs,
        "files": hashes,
        "counts": {
            "images": result.images.num_rows,
            "skipped_images": len(result.skipped_images),
            "gcps": result.gcps.num_rows,
            "gcp_observations": result.gcp_observations.num_rows,
        },
        "skipped_images": result.skipped_images,
        "sources": result.sources,
        "camera_identity": dataclasses.asdict(result.camera_identity) if result.camera_identity else None,
        "camera": result.camera.to_dict() if result.camera else None,
        "problems": [dataclasses.asdict(p) for p in result.problems],
        "config": dataclasses.asdict(result.config),
    }
    return write_json_atomic(manifest, doc)


def read_ingest(out_dir: str | Path) -> dict[str, object]:
    """Read a folder written by :func:`write_ingest`, refusing an incomplete or altered one.

    Args:
        out_dir: the folder.

    Returns:
        ``{"images", "gcps", "gcp_observations", "extra": tables, "crs": str | None, "problems": list[Problem],
        "manifest": dict}``: the three :mod:`aerocal.tables` tables (validated), the per-image metadata outside
        the schema, the flight's CRS (``None`` when ingest found none), the problems ingest recorded and the
        manifest as read.

    Raises:
        IngestOutputError: the manifest is missing or unreadable, or a file it lists is missing or differs from
            its sha256; the message names the file.
        SchemaError: a table file is not readable Parquet or does not match its schema.
    """
    out = Path(out_dir)
    manifest_path = out / MANIFEST
    if not manifest_path.is_file():
        raise IngestOutputError(
            f"{manifest_path}: missing; the ingest output is incomplete (write interrupted?)"
        )
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise IngestOutputError(f"{manifest_path}: unreadable manifest ({exc})") from exc
    for name, digest in manifest.get("files", {}).items():
        path = out / name
        if not path.is_file():
            raise IngestOutputError(f"{path}: listed in {MANIFEST} but missing")
        if _sha256(path) != digest:
            raise IngestOutputError(
                f"{path}: content differs from the sha256 in {MANIFEST}; rewrite the output"
            )
    data: dict[str, object] = {kind: tables.read(out / name, kind) for kind, name in TABLE_FILES.items()}
    extra: pa.Table = pq.read_table(out / EXTRA_FILE)
    data["extra"] = extra
    data["crs"] = manifest.get("crs")
    data["problems"] = [Problem(**p) for p in manifest.get("problems", [])]
    data["manifest"] = manifest
    return data
