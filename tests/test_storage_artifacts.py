"""Artifact store: content addressing, verification, crash safety, lineage and provenance, on both engines."""

from __future__ import annotations

import hashlib
import multiprocessing
import os
import random
import signal

import numpy as np
import pytest
import sqlalchemy as sa

from aerocal import tables
from storage.artifacts import ArtifactStore
from storage.errors import CorruptArtifactError, NotFoundError
from storage.models import Artifact, Run
from storage.provenance import ancestors, provenance, record_lineage
from storage.runs import start_run

pytest_plugins = ["conftest_storage"]  # fixtures: storage_url, storage_db, unique, ...

SEED = 20160314


def _observations(seed: int, n: int = 500):
    rng = np.random.default_rng(seed)
    return tables.from_columns(
        "observations",
        {
            "image_id": rng.integers(0, 40, n),
            "track_id": np.arange(n),
            "x": rng.uniform(0, 640, n),
            "y": rng.uniform(0, 480, n),
            "sigma": np.full(n, 0.3),
        },
        crs="EPSG:32632",
    )


def test_table_round_trip_is_content_addressed_and_verified(storage_db, unique, tmp_path):
    store = ArtifactStore(tmp_path / "artifacts")
    table = _observations(int(unique, 16))
    with storage_db.session() as session:
        start_run(session, f"run-{unique}", "test")
        first = store.put_table(session, table, "observations", run_id=f"run-{unique}")
        again = store.put_table(session, table, "observations", run_id=f"run-{unique}")
        session.commit()
        assert again.id == first.id  # same content, one row, one file
        path = store.path_for(first.sha256, "parquet")
        assert path == tmp_path / "artifacts" / first.sha256[:2] / f"{first.sha256}.parquet"
        assert first.uri == path.as_uri()
        assert hashlib.sha256(path.read_bytes()).hexdigest() == first.sha256
        assert first.size_bytes == path.stat().st_size
        assert (first.kind, first.schema_name, first.producing_run_id) == (
            "observations",
            "aerocal.tables/observations",
            f"run-{unique}",
        )
        back = store.read_table(first)
    assert back.equals(tables.validate(table, "observations"))
    assert tables.crs_of(back) == "EPSG:32632"
    assert len(list((tmp_path / "artifacts").rglob("*.parquet"))) == 1


def test_corrupt_or_missing_artifacts_are_never_used(storage_db, unique, tmp_path):
    store = ArtifactStore(tmp_path / "artifacts")
    data = random.Random(f"{SEED}-{unique}").randbytes(10_000)
    with storage_db.session() as session:
        artifact = store.put_bytes(session, data, "report", "bin")
        session.commit()
        path = store.locate(artifact)
        damaged = bytearray(data)
        damaged[1234] ^= 0xFF  # one flipped byte, same size
        path.write_bytes(bytes(damaged))
        for read in (store.read_bytes, store.verify):
            with pytest.raises(CorruptArtifactError) as err:
                read(artifact)
            assert artifact.uri in str(err.value) and "corrupt" in str(err.value)
        path.unlink()
        with pytest.raises(CorruptArtifactError, match="is missing"):
            store.read_bytes(artifact)
        # storing the content again repairs the file
        repaired = store.put_bytes(session, data, "report", "bin")
        assert repaired.id == artifact.id
        assert store.read_bytes(repaired) == data


# -------------------------------------------------------------------------------- crash safety
def _write_and_get_killed(url: str, root: str, run_id: str, seed: str, size: int, stage: str, ready) -> None:
    """Worker (spawned process): start storing an artifact and hang at ``stage`` until killed."""
    import time

    import storage.artifacts as artifacts
    from storage.database import connect

    def hang() -> None:
        ready.set()
        time.sleep(600)

    if stage == "mid-write":  # after the first 1 MiB chunk reached the temporary file
        chunks = artifacts._chunks

        def slow_chunks(data):
            for i, chunk in enumerate(chunks(data)):
                if i == 1:
                    hang()
                yield chunk

        artifacts._chunks = slow_chunks
    elif stage == "before-rename":  # the temporary file is complete, fsync is about to run
        os.fsync = lambda fd: hang()
    elif stage == "before-commit":  # the file is in place, the row not yet inserted
        register = artifacts.ArtifactStore._register

        def slow_register(self, session, *args, **kwargs):
            hang()
            return register(self, session, *args, **kwargs)

        artifacts.ArtifactStore._register = slow_register
    db = connect(url)
    store = artifacts.ArtifactStore(root)
    data = random.Random(seed).randbytes(size)
    with db.session() as session:
        start_run(session, run_id, "test")  # an open transaction holding a new row
        store.put_bytes(session, data, "report", "bin", run_id=run_id)
        session.commit()


@pytest.mark.parametrize("stage", ["mid-write", "before-rename", "before-commit"])
def test_a_writer_killed_mid_artifact_leaves_nothing_half_written(storage_url, unique, tmp_path, stage):
    size = 3 * 2**20 + 17
    seed = f"{SEED}-{unique}"  # content unique to this test: the PostgreSQL database is shared by the session
    data = random.Random(seed).randbytes(size)
    sha = hashlib.sha256(data).hexdigest()
    root = tmp_path / "artifacts"
    run_id = f"killed-{unique}"
    ctx = multiprocessing.get_context("spawn")
    ready = ctx.Event()
    proc = ctx.Process(
        target=_write_and_get_killed, args=(storage_url, str(root), run_id, seed, size, stage, ready)
    )
    proc.start()
    try:
        assert ready.wait(timeout=60), (
            f"writer never reached {stage} (exit code {proc.exitcode}, seed {seed})"
        )
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.join(timeout=30)
    assert proc.exitcode == -signal.SIGKILL
    store = ArtifactStore(root)
    final = store.path_for(sha, "bin")
    if stage == "before-commit":
        # the rename is atomic: whatever is visible under the final name is the whole content
        assert hashlib.sha256(final.read_bytes()).hexdigest() == sha
    else:
        assert not final.exists(), f"partial artifact visible under its final name at stage {stage}"
        leftovers = store.temporaries()
        assert len(leftovers) == 1 and leftovers[0].stat().st_size <= size
    from storage.database import connect

    db = connect(storage_url)
    try:
        with db.session() as session:
            assert session.scalars(sa.select(Artifact).where(Artifact.sha256 == sha)).first() is None
            assert session.get(Run, run_id) is None  # the killed transaction left nothing
            # the next write stores it (or adopts the complete file) and it reads back verified
            start_run(session, run_id, "test")
            artifact = store.put_bytes(session, data, "report", "bin", run_id=run_id)
            session.commit()
            assert store.read_bytes(artifact) == data
            assert [a.id for a in provenance(session, run_id).outputs] == [artifact.id]
    finally:
        db.dispose()
    removed = store.sweep_temporaries(older_than_s=0)
    assert store.temporaries() == [] and all(not p.exists() for p in removed)


# ---------------------------------------------------------------------------------- provenance
def test_lineage_and_provenance_across_two_runs(storage_db, unique, tmp_path):
    store = ArtifactStore(tmp_path / "artifacts")
    with storage_db.session() as session:
        match_run, adjust_run = f"match-{unique}", f"adjust-{unique}"
        start_run(session, match_run, "match", configuration={"ratio": 0.8})
        images = store.put_bytes(session, b"images table " + unique.encode(), "images", "parquet")
        observations = store.put_table(
            session, _observations(int(unique, 16)), "observations", run_id=match_run
        )
        assert record_lineage(session, match_run, [images], [observations]) == 1
        assert record_lineage(session, match_run, [images.id], [observations.id]) == 0  # idempotent
        start_run(session, adjust_run, "adjust")
        poses = store.put_bytes(session, b"poses " + unique.encode(), "poses", "parquet", run_id=adjust_run)
        points = store.put_bytes(
            session, b"points " + unique.encode(), "points", "parquet", run_id=adjust_run
        )
        assert record_lineage(session, adjust_run, [observations, images], [poses, points]) == 4
        session.commit()
        prov = provenance(session, adjust_run)
        assert [a.id for a in prov.inputs] == sorted([observations.id, images.id])
        assert [a.id for a in prov.outputs] == sorted([poses.id, points.id])
        assert len(prov.edges) == 4
        assert prov.to_dict()["outputs"][0]["sha256"] in (poses.sha256, points.sha256)
        first = provenance(session, match_run)
        assert [a.id for a in first.inputs] == [images.id]
        assert [a.id for a in first.outputs] == [observations.id]
        assert first.configuration == {"ratio": 0.8}
        assert {a.id for a in ancestors(session, points)} == {observations.id, images.id}
        with pytest.raises(NotFoundError, match="artifact id"):
            record_lineage(session, adjust_run, [10**9], [poses])
