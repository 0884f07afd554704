"""Content-addressed steps that resume: step records in the artifact store, and the run's bookkeeping.

Every step of a flow run goes through :func:`run_step`:

1. its **cache key** is the SHA-256 of the step name, the SHA-256 of each input artifact (by input name)
   and the step's configuration as JSON, plus the key recipe and the version of the code that computes steps
   (:func:`aerocal.pipeline.runner.cache_key`: a step computed by other code is computed again, since the
   cache cannot tell whether the change matters; a diagnosis cached before a fix had been reused silently);
2. the database is asked for a **step record** registered for (step name, cache key): a small JSON
   artifact of kind ``"step"`` whose ``schema_name`` is ``aerocal.step/<step>/<cache key>`` and whose
   content lists the step's output artifacts (name -> SHA-256) and the run that computed them;
3. when a record exists and every output it names is present and intact (SHA-256 verified), the step is
   **reused**: its outputs are linked to the current run with lineage, the timing is recorded as
   ``"<step> (reused)"``, nothing is computed;
4. otherwise the step computes, its outputs go to the artifact store (Parquet tables validated against
   :mod:`aerocal.tables`, files), lineage input -> output is recorded, then the step record, the timing
   and a commit: a crash loses at most the step in progress.

Why on top of storage rather than Prefect's result cache (``cache_key_fn`` / ``persist_result``):
Prefect's cache lives in Prefect's result storage and its own database, which a flight re-run from the CLI
on another machine, a different Prefect server, or Prefect's temporary local server (whose database is
thrown away) does not see; and a cache hit there records nothing in aerocal's provenance. The step record
lives beside the artifacts and the runs in aerocal's database, is keyed by the content hashes that
provenance already stores, survives a change of Prefect server, is verified against the artifacts' hashes
before use (a corrupt artifact means recompute, never a silent reuse), and leaves in the new run a trace
of what was reused and which run computed it. Prefect still gives retries, logging, the UI and
scheduling.

A step record is an artifact (not a table of its own) so that the storage schema needs no migration;
the lookup uses the indexed ``kind`` column and the ``schema_name`` column.
"""

from __future__ import annotations

import contextlib
import functools
import io
import json
import shutil
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import sqlalchemy as sa

from aerocal.io import atomic_path
from aerocal.pipeline.interrupts import check_interrupted
from aerocal.pipeline.runner import (
    EXTRA,
    STEP_FORMAT,
    ArrayOutput,
    Compute,
    FileOutput,
    JsonOutput,
    Output,
    StepResult,
    TableOutput,
    cache_key,
    configuration_json,
    json_bytes,
)
from storage.artifacts import ArtifactStore
from storage.database import Database, connect
from storage.errors import CorruptArtifactError, NotFoundError
from storage.models import Artifact
from storage.provenance import record_lineage
from storage.runs import record_timing

#: kind of the artifacts that record a completed step
STEP_KIND = "step"


@dataclass(frozen=True)
class StepContext:
    """Where a run keeps its records: database URL, artifact root and the run id (the flow-run id).

    Plain strings only, so that a context travels to Prefect tasks and Dask workers unchanged.
    """

    database_url: str
    artifact_root: str
    run_id: str

    @property
    def database(self) -> Database:
        return _database(self.database_url)

    @property
    def store(self) -> ArtifactStore:
        return ArtifactStore(Path(self.artifact_root))


@functools.lru_cache(maxsize=8)
def _database(url: str) -> Database:
    """One engine per URL and process (engines pool connections; building one per step would not)."""
    return connect(url)


class StoredInputs:
    """Read access to a step's input artifacts by name (each read verified against its SHA-256): the
    :class:`aerocal.pipeline.runner.StepInputs` of the platform."""

    def __init__(self, ctx: StepContext, inputs: Mapping[str, str]) -> None:
        self.ctx, self.refs = ctx, dict(inputs)

    def _artifact(self, name: str) -> Artifact:
        if name not in self.refs:
            raise KeyError(f"step input {name!r} not given; inputs are {sorted(self.refs)}")
        with self.ctx.database.session() as session:
            return self.ctx.store.get(session, self.refs[name])

    def has(self, name: str) -> bool:
        return name in self.refs

    def table(self, name: str, kind: str | None = None) -> pa.Table:
        art = self._artifact(name)
        return self.ctx.store.read_table(art, kind or art.kind)

    def json(self, name: str) -> Any:
        return json.loads(self.ctx.store.read_bytes(self._artifact(name)))

    def array(self, name: str) -> np.ndarray:
        return np.load(io.BytesIO(self.ctx.store.read_bytes(self._artifact(name))), allow_pickle=False)

    def path(self, name: str) -> Path:
        return self.ctx.store.verify(self._artifact(name))


def record_schema(step: str, key: str) -> str:
    """``schema_name`` of the step record of ``step`` with cache ``key``."""
    return f"aerocal.step/{step}/{key}"


def find_step_record(ctx: StepContext, step: str, key: str) -> dict[str, Any] | None:
    """The record of a completed ``step`` with cache ``key`` whose outputs are all intact, else ``None``."""
    db, store = ctx.database, ctx.store
    with db.session() as session:
        rows = session.scalars(
            sa.select(Artifact)
            .where(Artifact.kind == STEP_KIND, Artifact.schema_name == record_schema(step, key))
            .order_by(Artifact.id.desc())
        ).all()
        for row in rows:
            try:
                record = json.loads(store.read_bytes(row))
                for sha in record["outputs"].values():
                    store.verify(store.get(session, sha))
            except (CorruptArtifactError, NotFoundError, KeyError, ValueError):
                continue  # damaged or incomplete: recompute (writing the same content repairs it)
            record["record_sha256"] = row.sha256
            return record
    return None


def put_output(store: ArtifactStore, session, out: Output, run_id: str) -> Artifact:
    """Store a step's output as an artifact of its kind (Parquet, JSON, ``.npy`` or the file itself)."""
    if isinstance(out, TableOutput):
        return store.put_table(session, out.table, out.kind, run_id=run_id)
    if isinstance(out, JsonOutput):
        return store.put_bytes(session, json_bytes(out.value), out.kind, "json", run_id=run_id)
    if isinstance(out, ArrayOutput):
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(out.array), allow_pickle=False)
        return store.put_bytes(session, buf.getvalue(), out.kind, "npy", run_id=run_id)
    if isinstance(out, FileOutput):
        art = store.put_file(session, out.path, out.kind, run_id=run_id)
        if out.temporary:
            Path(out.path).unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                Path(out.path).parent.rmdir()
        return art
    raise TypeError(
        f"step output of type {type(out).__name__}; use TableOutput, JsonOutput, FileOutput or ArrayOutput"
    )


def run_step(
    ctx: StepContext,
    step: str,
    inputs: Mapping[str, str],
    config: Any,
    compute: Compute,
) -> StepResult:
    """Reuse the completed ``step`` for these inputs and configuration, or compute and record it.

    ``inputs``: input name -> SHA-256 of a stored artifact. ``compute(inputs)`` returns output name ->
    output; it runs only when no intact step record exists (see the module docstring). An output named
    ``_extra`` (a :class:`~aerocal.pipeline.runner.JsonOutput`) is not stored as an artifact: its value goes
    into the step record and comes back as :attr:`StepResult.extra` (small figures such as counts).
    """
    check_interrupted()
    key = cache_key(step, inputs, config)
    db, store = ctx.database, ctx.store
    t0 = time.perf_counter()
    record = find_step_record(ctx, step, key)
    if record is not None:
        with db.session() as session:
            outs = [store.get(session, sha) for sha in record["outputs"].values()]
            ins = [store.get(session, sha) for sha in inputs.values()]
            in_ids = {a.id for a in ins}
            rec = store.get(session, record["record_sha256"])
            record_lineage(session, ctx.run_id, ins, [a for a in outs if a.id not in in_ids] + [rec])
            seconds = time.perf_counter() - t0
            record_timing(session, ctx.run_id, f"{step} (reused)", seconds)
            session.commit()
        return StepResult(
            step, key, dict(record["outputs"]), True, record["run_id"], seconds, dict(record.get("extra", {}))
        )
    produced = compute(StoredInputs(ctx, inputs))
    seconds = time.perf_counter() - t0
    extra = {}
    if EXTRA in produced:
        produced = dict(produced)
        extra = configuration_json(produced.pop(EXTRA).value)
    with db.session() as session:
        arts = {name: put_output(store, session, out, ctx.run_id) for name, out in produced.items()}
        outputs = {name: a.sha256 for name, a in arts.items()}
        doc = {
            "format": STEP_FORMAT,
            "step": step,
            "key": key,
            "inputs": dict(sorted(inputs.items())),
            "outputs": outputs,
            "run_id": ctx.run_id,
            "seconds": round(seconds, 3),
            "extra": extra,
        }
        rec = store.put_bytes(
            session,
            json.dumps(doc, sort_keys=True).encode(),
            STEP_KIND,
            "json",
            schema_name=record_schema(step, key),
            run_id=ctx.run_id,
        )
        ins = [store.get(session, sha) for sha in inputs.values()]
        in_ids = {a.id for a in ins}
        record_lineage(session, ctx.run_id, ins, [a for a in arts.values() if a.id not in in_ids] + [rec])
        record_timing(session, ctx.run_id, step, seconds)
        session.commit()
    return StepResult(step, key, outputs, False, ctx.run_id, seconds, extra)


def record_skip(ctx: StepContext, step: str, reason: str) -> StepResult:
    """Record that ``step`` does not apply to this flight (e.g. matching in observations mode)."""
    with ctx.database.session() as session:
        record_timing(session, ctx.run_id, f"{step} (skipped: {reason})", 0.0)
        session.commit()
    return StepResult(step, "", {}, False, ctx.run_id, 0.0, {"skipped": reason})


def export_artifact(ctx: StepContext, sha: str, target: Path) -> Path:
    """Copy a stored artifact (verified) to ``target`` (atomically)."""
    with ctx.database.session() as session:
        src = ctx.store.verify(ctx.store.get(session, sha))
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp:
        shutil.copyfile(src, tmp)
    return target


def put_value(ctx: StepContext, output: Output) -> str:
    """Store a value no step computed (a manifest, a certificate document, a reference DSM) with the run; its
    SHA-256."""
    with ctx.database.session() as session:
        art = put_output(ctx.store, session, output, ctx.run_id)
        session.commit()
        return art.sha256
