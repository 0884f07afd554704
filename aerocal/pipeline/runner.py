"""How a step of the flight pipeline runs: its outputs, its result, and the runner that computes or reuses it.

A step (``aerocal.pipeline.*_step``) names its inputs (input name -> *reference* of a value the runner holds),
its configuration, and a ``compute(inputs)`` function returning output name -> :data:`Output`. The runner
decides whether to compute: :class:`LocalRunner` keeps every value in memory (a notebook, a study, a test; no
Prefect, no database), the platform's runner (``tasks.runner.StoreRunner``) keys each step by the content of
its inputs, its configuration and the code (:func:`cache_key`), stores the outputs in the artifact store with
their lineage, reuses a completed step, and runs each step as a Prefect task. The steps do not know which.

References are the SHA-256 of the values: of the stored artifact for the platform, of the value's content
for :class:`LocalRunner` (:func:`table_sha256` for a table). Values read back are the same types in both:
Arrow tables, plain JSON (dicts, lists, strings, numbers: what :func:`configuration_json` makes of a value),
numpy arrays, file paths.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import datetime as dt
import functools
import hashlib
import io
import json
import shutil
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from aerocal.io import atomic_path, file_sha256, plain_json
from aerocal.pipeline.interrupts import check_interrupted
from aerocal.pipeline.summary import StepRecord, StepStatus

if TYPE_CHECKING:  # the figures' module makes its outputs with this one's JsonOutput
    from aerocal.pipeline.figures import StepFigures

#: version of the cache-key recipe; changing it invalidates every stored step
STEP_FORMAT = "aerocal.step/1"


# ------------------------------------------------------------------------------------------- outputs
@dataclass
class TableOutput:
    """An Arrow table of an :mod:`aerocal.tables` kind (the platform stores it as Parquet, validated)."""

    table: pa.Table
    kind: str


@dataclass
class JsonOutput:
    """A JSON document: any value :func:`configuration_json` turns into plain JSON."""

    value: Any
    kind: str


@dataclass
class FileOutput:
    """A file the step wrote (GeoTIFF, HTML, ...); a ``temporary`` file (and its folder, when left empty) is
    removed once the runner has kept it."""

    path: Path
    kind: str
    temporary: bool = False


@dataclass
class ArrayOutput:
    """A numpy array (stored as ``.npy``)."""

    array: np.ndarray
    kind: str


Output = TableOutput | JsonOutput | FileOutput | ArrayOutput

#: the output name whose value is not an artifact but small figures kept with the step (:attr:`StepResult.extra`)
EXTRA = "_extra"


@dataclass
class StepResult:
    """What a step produced: output name -> reference, whether it was reused, which run computed it, how long
    it took (seconds) and its small figures (``extra``: counts, the method used, ``skipped`` and why; the step's
    type of :mod:`aerocal.pipeline.figures`)."""

    step: str
    key: str
    outputs: dict[str, str]
    reused: bool
    computed_by: str
    seconds: float
    extra: StepFigures | dict = field(default_factory=dict)  # {} for a step without figures

    def __getitem__(self, name: str) -> str:
        return self.outputs[name]

    @property
    def skipped(self) -> bool:
        return "skipped" in self.extra

    def with_outputs(self, **outputs: str) -> StepResult:
        """The same result with some outputs replaced (e.g. the screened ground control for later steps)."""
        return dataclasses.replace(self, outputs={**self.outputs, **outputs})

    def record(self) -> StepRecord:
        """What a run records of the step (:class:`~aerocal.pipeline.summary.StepRecord`)."""
        if self.skipped:
            return StepRecord(StepStatus.SKIPPED, reason=self.extra["skipped"])
        return StepRecord(StepStatus.REUSED if self.reused else StepStatus.COMPUTED, seconds=self.seconds,
                          computed_by=self.computed_by, key=self.key, outputs=dict(self.outputs),
                          extra=dict(self.extra))


class StepInputs(Protocol):
    """Read access to a step's inputs by name, as :class:`Runner` gives it to ``compute``."""

    refs: dict[str, str]

    def has(self, name: str) -> bool: ...
    def table(self, name: str) -> pa.Table: ...
    def json(self, name: str) -> Any: ...
    def array(self, name: str) -> np.ndarray: ...
    def path(self, name: str) -> Path: ...


Compute = Callable[[StepInputs], Mapping[str, Output]]


class Runner(Protocol):
    """Computes or reuses steps and holds their values (see the module docstring)."""

    run_id: str

    def run(self, step: str, inputs: Mapping[str, str], config: Any, compute: Compute) -> StepResult:
        """Reuse the step for these inputs and configuration, or compute it; outputs kept by reference."""
        ...

    def skip(self, step: str, reason: str) -> StepResult:
        """Record that ``step`` does not apply to this flight (e.g. matching in observations mode)."""
        ...

    def put(self, output: Output) -> str:
        """Keep a value that no step computed (a manifest, a certificate document); its reference."""
        ...

    def inputs(self, refs: Mapping[str, str]) -> StepInputs:
        """Read access to values by name (outside a step: e.g. the flight summary for the flow's record)."""
        ...

    def export(self, ref: str, target: Path) -> Path:
        """Write the value of ``ref`` to ``target`` (atomically) and return ``target``."""
        ...


# ---------------------------------------------------------------------------------------- cache key
def configuration_json(config: Any) -> Any:
    """A configuration (dataclass, mapping, scalar, array) as plain JSON types, for keys and run records."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        config = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    return plain_json(config)


#: the packages whose code computes step outputs, for :func:`source_digest`
CODE_PACKAGES = ("aerocal", "tasks")


@functools.cache
def source_digest() -> str:
    """SHA-256 (hex) of the source of :data:`CODE_PACKAGES`: every ``.py`` file's path (relative to the project
    root) and bytes, in path order (about 200 files, a few milliseconds, read once per process). A step
    computed by other code is computed again: the cache cannot tell whether the change matters (a diagnosis
    cached before a fix had been reused silently)."""
    root = Path(__file__).resolve().parents[2]
    digest = hashlib.sha256()
    for package in CODE_PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode() + b"\0")
            digest.update(path.read_bytes())
    return digest.hexdigest()


def cache_key(step: str, inputs: Mapping[str, str], config: Any = None) -> str:
    """SHA-256 (hex) of the step name, its inputs' references by name, its configuration as JSON, the key
    recipe (:data:`STEP_FORMAT`) and the code version (:func:`source_digest`)."""
    doc = {
        "format": STEP_FORMAT,
        "code": source_digest(),
        "step": step,
        "inputs": dict(sorted(inputs.items())),
        "config": configuration_json(config),
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def json_bytes(value: Any) -> bytes:
    """The bytes a JSON output is kept as (sorted keys, one space indent)."""
    return json.dumps(configuration_json(value), sort_keys=True, indent=1).encode()


def table_sha256(table: pa.Table, kind: str) -> str:
    """SHA-256 (hex) of a table's kind, schema (with its metadata) and the bytes of every column's buffers,
    without writing it anywhere (memory speed; a Parquet file of it would hash differently)."""
    digest = hashlib.sha256(kind.encode() + b"\0" + table.schema.serialize().to_pybytes())
    for column in table.columns:
        for chunk in column.chunks:
            for buf in chunk.buffers():
                digest.update(b"\0" if buf is None else memoryview(buf))
    return digest.hexdigest()


# ------------------------------------------------------------------------------------- local runner
class _MemoryInputs:
    """:class:`StepInputs` over a :class:`LocalRunner`'s values."""

    def __init__(self, runner: LocalRunner, refs: Mapping[str, str]) -> None:
        self.runner, self.refs = runner, dict(refs)

    def _value(self, name: str) -> Any:
        if name not in self.refs:
            raise KeyError(f"step input {name!r} not given; inputs are {sorted(self.refs)}")
        return self.runner.values[self.refs[name]]

    def has(self, name: str) -> bool:
        return name in self.refs

    def table(self, name: str) -> pa.Table:
        return self._value(name)

    def json(self, name: str) -> Any:
        return copy.deepcopy(self._value(name))

    def array(self, name: str) -> np.ndarray:
        return self._value(name).copy()

    def path(self, name: str) -> Path:
        return Path(self._value(name))


class LocalRunner:
    """Runs every step in this process and keeps its values in memory; a step asked again with the same inputs
    and configuration is reused (within this runner). Files a step writes are kept in ``workdir`` (default: a
    new temporary folder). References are SHA-256 (hex) of the content: of a JSON document's bytes, a file's
bytes, an array's ``.npy`` bytes, and of a table's kind, schema and Arrow buffers (:func:`table_sha256`)."""

    def __init__(self, run_id: str | None = None, workdir: Path | None = None) -> None:
        self.run_id = run_id or f"local-{dt.datetime.now(dt.UTC):%Y%m%dT%H%M%S}"
        self.workdir = Path(workdir) if workdir else Path(tempfile.mkdtemp(prefix="aerocal-run-"))
        self.values: dict[str, Any] = {}
        self.results: dict[str, StepResult] = {}
        self.timings: dict[str, float] = {}

    def put(self, output: Output) -> str:
        """Keep the value of ``output`` and return its reference (the SHA-256 of its content).

        Raises:
            TypeError: ``output`` is not a TableOutput, JsonOutput, FileOutput or ArrayOutput.
        """
        if isinstance(output, TableOutput):
            value: Any = output.table
            ref = table_sha256(value, output.kind)
        elif isinstance(output, JsonOutput):
            data = json_bytes(output.value)
            value, ref = json.loads(data), hashlib.sha256(data).hexdigest()  # the types a stored document has
        elif isinstance(output, ArrayOutput):
            buf = io.BytesIO()
            value = np.ascontiguousarray(output.array)
            np.save(buf, value, allow_pickle=False)
            ref = hashlib.sha256(buf.getvalue()).hexdigest()
        elif isinstance(output, FileOutput):
            ref = file_sha256(output.path)
            value = self.workdir / ref[:16] / Path(output.path).name
            value.parent.mkdir(parents=True, exist_ok=True)
            if output.temporary:
                shutil.move(output.path, value)
                with contextlib.suppress(OSError):  # the step's folder still holds other files
                    Path(output.path).parent.rmdir()
            else:
                shutil.copyfile(output.path, value)
        else:
            raise TypeError(f"step output of type {type(output).__name__}; use TableOutput, JsonOutput, "
                            "FileOutput or ArrayOutput")
        self.values[ref] = value
        return ref

    def inputs(self, refs: Mapping[str, str]) -> StepInputs:
        return _MemoryInputs(self, refs)

    def run(self, step: str, inputs: Mapping[str, str], config: Any, compute: Compute) -> StepResult:
        check_interrupted()
        key = cache_key(step, inputs, config)
        if key in self.results:
            self.timings[f"{step} (reused)"] = 0.0
            return dataclasses.replace(self.results[key], reused=True, seconds=0.0)
        t0 = time.perf_counter()
        produced = dict(compute(self.inputs(inputs)))
        extra = configuration_json(produced.pop(EXTRA).value) if EXTRA in produced else {}
        outputs = {name: self.put(out) for name, out in produced.items()}
        seconds = time.perf_counter() - t0
        self.timings[step] = seconds
        result = StepResult(step, key, outputs, False, self.run_id, seconds, extra)
        self.results[key] = result
        return result

    def skip(self, step: str, reason: str) -> StepResult:
        self.timings[f"{step} (skipped: {reason})"] = 0.0
        return StepResult(step, "", {}, False, self.run_id, 0.0, {"skipped": reason})

    def export(self, ref: str, target: Path) -> Path:
        value = self.values[ref]
        target = Path(target)
        target.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            if isinstance(value, Path):
                shutil.copyfile(value, tmp)
            elif isinstance(value, pa.Table):
                pq.write_table(value, tmp)
            elif isinstance(value, np.ndarray):
                with open(tmp, "wb") as fh:
                    np.save(fh, value, allow_pickle=False)
            else:
                Path(tmp).write_bytes(json_bytes(value))
        return target
