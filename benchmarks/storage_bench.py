"""Storage at scale, on SQLite and PostgreSQL: 100,000 per-image artifact records and 1,000 certificates.

aerocal keeps image metadata in Parquet artifacts, not in database rows; what the database holds per
image is its content-addressed artifact record (sha256, URI, kind, producing run) and lineage. So the
"100,000 image records" are 100,000 artifact rows with lineage edges to one run, inserted in batches,
then looked up by hash, listed by kind and traced by provenance. Baseline in the same run: the same
rows through a plain ``executemany`` of SQL INSERTs on the same engine, so the ratio shows the ORM's cost.

    python -m benchmarks.storage_bench [--images 100000] [--certificates 1000]
"""

from __future__ import annotations

import argparse
import hashlib
import secrets
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import sqlalchemy as sa

from aerocal.certificates.document import CameraIdentity, Certificate, Conditions
from aerocal.simulate.presets import PRESETS
from benchmarks.common import record
from storage.certificates import issue_certificate, select_certificate
from storage.database import connect
from storage.migrations import upgrade
from storage.models import Artifact, RunArtifact
from storage.provenance import provenance
from storage.runs import start_run

POSTGRES_ADMIN = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"


def _postgres_url() -> tuple[str, str] | None:
    name = f"aerocal_bench_{secrets.token_hex(4)}"
    try:
        admin = sa.create_engine(POSTGRES_ADMIN, isolation_level="AUTOCOMMIT")
        with admin.connect() as conn:
            conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
        admin.dispose()
    except sa.exc.OperationalError:
        return None
    return POSTGRES_ADMIN.rsplit("/", 1)[0] + "/" + name, name


def _drop_postgres(name: str) -> None:
    admin = sa.create_engine(POSTGRES_ADMIN, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
    admin.dispose()


def _certificate(serial: int, k: int) -> dict:
    cam = PRESETS["conte-calibration"].camera_true.replace(f=1670.0 + 0.01 * k)
    return Certificate(CameraIdentity("NEC", "TS9260", f"{serial:05d}", "39.2mm Ge"), cam,
                       conditions=Conditions(date="2016-03-14", temperature_range=(15.0, 25.0))).to_dict()


def bench(url: str, n_images: int, n_certs: int) -> list[tuple[str, float, int]]:
    upgrade(url)
    db = connect(url)
    rows = []
    with db.session() as s:
        start_run(s, "bench-run", "process_flight")
        s.commit()
        hashes = [hashlib.sha256(f"img{i}".encode()).hexdigest() for i in range(n_images)]
        t0 = time.perf_counter()
        for lo in range(0, n_images, 5000):
            s.add_all([Artifact(sha256=h, uri=f"file:///a/{h[:2]}/{h}.jpg", kind="image", schema_name=None,
                                size_bytes=1_000_000, producing_run_id=None) for h in hashes[lo:lo + 5000]])
            s.flush()
        s.commit()
        rows.append(("insert image artifact records (ORM, batches of 5000)", time.perf_counter() - t0, n_images))
        ids = [a for (a,) in s.execute(sa.select(Artifact.id).where(Artifact.kind == "image"))]
        t0 = time.perf_counter()
        s.execute(sa.insert(RunArtifact), [{"run_id": "bench-run", "artifact_id": a, "role": "input"} for a in ids])
        s.commit()
        rows.append(("record lineage: every image as an input of one run", time.perf_counter() - t0, n_images))
        t0 = time.perf_counter()
        for h in hashes[:: max(1, n_images // 1000)]:
            s.execute(sa.select(Artifact).where(Artifact.sha256 == h)).scalar_one()
        n_lookups = len(hashes[:: max(1, n_images // 1000)])
        rows.append(("look up an artifact by sha256 (each)", (time.perf_counter() - t0) / n_lookups, n_lookups))
        t0 = time.perf_counter()
        n = s.execute(sa.select(sa.func.count()).select_from(Artifact).where(Artifact.kind == "image")).scalar()
        rows.append(("count artifacts of a kind", time.perf_counter() - t0, n))
        t0 = time.perf_counter()
        prov = provenance(s, "bench-run")
        rows.append(("provenance of the run (all its inputs)", time.perf_counter() - t0, len(prov.inputs)))
    now = datetime.now(UTC)
    with db.engine.begin() as conn:  # baseline: plain executemany of the same rows
        h2 = [hashlib.sha256(f"raw{i}".encode()).hexdigest() for i in range(n_images)]
        t0 = time.perf_counter()
        conn.execute(sa.insert(Artifact.__table__), [
            {"sha256": h, "uri": f"file:///a/{h}.jpg", "kind": "image-raw", "size_bytes": 1, "created": now}
            for h in h2])
        rows.append(("baseline: executemany of the same rows (Core)", time.perf_counter() - t0, n_images))
    with db.session() as s:
        t0 = time.perf_counter()
        n_cams = min(50, n_certs)
        for k in range(n_certs):
            issue_certificate(s, _certificate(k % n_cams, k))
        rows.append((f"issue certificates ({n_cams} cameras, versioned)", time.perf_counter() - t0, n_certs))
        t0 = time.perf_counter()
        for k in range(100):
            camera = {"make": "NEC", "model": "TS9260", "serial": f"{k % n_cams:05d}", "lens": "39.2mm Ge"}
            select_certificate(s, camera, "2017-03-08", (16.0, 20.0))
        rows.append(("select the certificate for a flight (each)", (time.perf_counter() - t0) / 100, 100))
    db.dispose()
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--images", type=int, default=100_000)
    p.add_argument("--certificates", type=int, default=1000)
    a = p.parse_args(argv)
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        engines = [("SQLite", f"sqlite:///{Path(tmp) / 'bench.db'}", None)]
        pg = _postgres_url()
        if pg:
            engines.append(("PostgreSQL", pg[0], pg[1]))
        for label, url, name in engines:
            try:
                rows = bench(url, a.images, a.certificates)
            finally:
                if name:
                    _drop_postgres(name)
            lines += [f"### {label}", "", "| operation | time | count |", "|---|---|---|"]
            for what, t, n in rows:
                lines.append(f"| {what} | {t * 1000:.2f} ms | {n} |" if t < 1 else f"| {what} | {t:.2f} s | {n} |")
            orm = next(t for w, t, _ in rows if w.startswith("insert image"))
            core = next(t for w, t, _ in rows if w.startswith("baseline"))
            lines += ["", f"ratio ORM / Core insert: {orm / core:.2f}", ""]
        if not pg:
            lines.append("PostgreSQL at 127.0.0.1:5432 not reachable: not measured")
    record(f"Storage: {a.images} image records, {a.certificates} certificates", lines)


if __name__ == "__main__":
    main()
