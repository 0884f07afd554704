"""Content-addressed steps that resume: cache keys, step records, and the run's bookkeeping.

Every step of a flow run goes through :func:`run_step`:

1. its **cache key** is the SHA-256 of the step name, the SHA-256 of each input artifact (by input name)
   and the step's configuration as JSON (:func:`cache_key`), plus :data:`STEP_FORMAT` and the version of
   the code that computes steps (:func:`code_version`: a step computed by other code is computed again, since
   the cache cannot tell whether the change matters; a diagnosis cached before a fix had been reused
   silently);
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
import dataclasses
import functools
import hashlib
import io
import json
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import sqlalchemy as sa

from storage.artifacts import ArtifactStore
from storage.database import Database, connect
from storage.errors import CorruptArtifactError, NotFoundError
from storage.models import Artifact
from storage.provenance import record_lineage
from storage.runs import record_timing, to_json

#: version of the cache-key recipe and step-record layout; changing it invalidates every record
STEP_FORMAT = "aerocal.step/1"

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


# ------------------------------------------------------------------------------------------- outputs
@dataclass
class TableOutput:
    """An Arrow table of an :mod:`aerocal.tables` kind, stored as Parquet."""

    table: pa.Table
    kind: str


@dataclass
class JsonOutput:
    """A JSON document (any value :func:`storage.runs.to_json` converts), stored as ``.json``."""

    value: Any
    kind: str


@dataclass
class FileOutput:
    """A file written by the step (GeoTIFF, HTML, ...), copied into the store; a ``temporary`` file (and
    its folder, when left empty) is removed once stored."""

    path: Path
    kind: str
    temporary: bool = False


@dataclass
class ArrayOutput:
    """A numpy array, stored as ``.npy``."""

    array: np.ndarray
    kind: str


Output = TableOutput | JsonOutput | FileOutput | ArrayOutput


@dataclass
class StepResult:
    """What a step produced: output name -> SHA-256, whether it was reused and which run computed it."""

    step: str
    key: str
    outputs: dict[str, str]
    reused: bool
    computed_by: str
    seconds: float
    extra: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, name: str) -> str:
        return self.outputs[name]


class StepInputs:
    """Read access to a step's input artifacts by name (each read verified against its SHA-256)."""

    def __init__(self, ctx: StepContext, inputs: Mapping[str, str]) -> None:
        self.ctx, self.shas = ctx, dict(inputs)

    def _artifact(self, name: str) -> Artifact:
        if name not in self.shas:
            raise KeyError(f"step input {name!r} not given; inputs are {sorted(self.shas)}")
        with self.ctx.database.session() as session:
            return self.ctx.store.get(session, self.shas[name])

    def has(self, name: str) -> bool:
        return name in self.shas

    def table(self, name: str, kind: str | None = None) -> pa.Table:
        art = self._artifact(name)
        return self.ctx.store.read_table(art, kind or art.kind)

    def json(self, name: str) -> Any:
        return json.loads(self.ctx.store.read_bytes(self._artifact(name)))

    def array(self, name: str) -> np.ndarray:
        return np.load(io.BytesIO(self.ctx.store.read_bytes(self._artifact(name))), allow_pickle=False)

    def path(self, name: str) -> Path:
        return self.ctx.store.verify(self._artifact(name))


# ---------------------------------------------------------------------------------------- cache key
def configuration_json(config: Any) -> Any:
    """A configuration (dataclass, mapping, scalar) as plain JSON types, for keys and run records."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    return to_json(config)


#: the packages whose code computes step outputs (the engine and the step wrappers), for :func:`code_version`
CODE_PACKAGES = ("aerocal", "tasks")


@functools.cache
def code_version() -> str:
    """SHA-256 (hex) of the source of :data:`CODE_PACKAGES`: every ``.py`` file's path (relative to the project
    root) and bytes, in path order. Read once per process (about 200 files, a few milliseconds)."""
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for package in CODE_PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode() + b"\0")
            digest.update(path.read_bytes())
    return digest.hexdigest()


def cache_key(step: str, inputs: Mapping[str, str], config: Any = None) -> str:
    """SHA-256 (hex) of the step name, its inputs' SHA-256 by name, its configuration as JSON and the code
    version (:func:`code_version`)."""
    doc = {
        "format": STEP_FORMAT,
        "code": code_version(),
        "step": step,
        "inputs": dict(sorted(inputs.items())),
        "config": configuration_json(config),
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


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


def _put(store: ArtifactStore, session, out: Output, run_id: str) -> Artifact:
    if isinstance(out, TableOutput):
        return store.put_table(session, out.table, out.kind, run_id=run_id)
    if isinstance(out, JsonOutput):
        data = json.dumps(configuration_json(out.value), sort_keys=True, indent=1).encode()
        return store.put_bytes(session, data, out.kind, "json", run_id=run_id)
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


#: set by :func:`interrupt_handler` when Ctrl-C arrives, checked at every step boundary (:func:`run_step`)
_INTERRUPTED = threading.Event()


def interrupt_handler(signum: int, frame: object) -> None:
    """SIGINT: note it, then raise KeyboardInterrupt as Python's default handler does.

    A KeyboardInterrupt raised while Python runs a finalizer or a weakref callback (SQLAlchemy's, at garbage
    collection) is printed as "Exception ignored in ..." and lost: the run went on to the end and exited 0
    (Ctrl-C 0.1 s into an ``aerocal process`` run, 2 times in 2). The note makes the next step boundary raise it
    again."""
    _INTERRUPTED.set()
    raise KeyboardInterrupt


@contextlib.contextmanager
def interrupts_noted() -> Iterator[None]:
    """:func:`interrupt_handler` as the SIGINT handler for the block (main thread only; elsewhere the block
    runs as it is), the previous handler restored after it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _INTERRUPTED.clear()
    previous = signal.signal(signal.SIGINT, interrupt_handler)
    previous_hook = sys.unraisablehook

    def quiet_lost_interrupt(unraisable: object) -> None:
        # the lost KeyboardInterrupt is raised again at the next step boundary: no "Exception ignored" traceback
        if not (_INTERRUPTED.is_set() and unraisable.exc_type is KeyboardInterrupt):  # type: ignore[attr-defined]
            previous_hook(unraisable)  # type: ignore[arg-type]

    sys.unraisablehook = quiet_lost_interrupt
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = previous_hook
        _INTERRUPTED.clear()  # a later run in this process (a served flow) starts without it


def check_interrupted() -> None:
    """Raise KeyboardInterrupt if Ctrl-C arrived (:func:`interrupt_handler`) and was swallowed since."""
    if _INTERRUPTED.is_set():
        raise KeyboardInterrupt


def run_step(
    ctx: StepContext,
    step: str,
    inputs: Mapping[str, str],
    config: Any,
    compute: Callable[[StepInputs], Mapping[str, Output]],
) -> StepResult:
    """Reuse the completed ``step`` for these inputs and configuration, or compute and record it.

    ``inputs``: input name -> SHA-256 of a stored artifact. ``compute(inputs)`` returns output name ->
    output; it runs only when no intact step record exists (see the module docstring). An output named
    ``_extra`` (a :class:`JsonOutput`) is not stored as an artifact: its value goes into the step record
    and comes back as :attr:`StepResult.extra` (small figures such as counts).
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
    produced = compute(StepInputs(ctx, inputs))
    seconds = time.perf_counter() - t0
    extra = {}
    if "_extra" in produced:
        produced = dict(produced)
        extra = configuration_json(produced.pop("_extra").value)
    with db.session() as session:
        arts = {name: _put(store, session, out, ctx.run_id) for name, out in produced.items()}
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


def skip_step(ctx: StepContext, step: str, reason: str) -> StepResult:
    """Record that ``step`` does not apply to this flight (e.g. matching in observations mode)."""
    with ctx.database.session() as session:
        record_timing(session, ctx.run_id, f"{step} (skipped: {reason})", 0.0)
        session.commit()
    return StepResult(step, "", {}, False, ctx.run_id, 0.0, {"skipped": reason})
