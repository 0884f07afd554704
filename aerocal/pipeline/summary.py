"""What a processing run hands on: :class:`RunSummary`, the record the CLI prints, ``run.json`` holds and the
database keeps, with named fields instead of a dictionary read key by key.

A run's documents (the diagnosis, the assessment, the extension record, the recorded-EO checks) are JSON documents
written by their steps and read by the report; the summary carries the parts a reader looks at first and refers
to the rest by file. :meth:`RunSummary.to_json` is the form written to disk and stored;
:meth:`RunSummary.from_json` reads it back (``aerocal`` reads a ``run.json`` written by an earlier version the
same way: a field it does not know is ignored, a field it misses takes its default).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from aerocal.pipeline.findings import Finding

if TYPE_CHECKING:
    from aerocal.pipeline.figures import StepFigures


class FlightMode(StrEnum):
    """Where a flight's image measurements come from."""

    IMAGES = "images"  #: matched from its frames
    OBSERVATIONS = "observations"  #: given as tables (``observations/*.parquet``), nothing matched


class StepStatus(StrEnum):
    """What became of a step in a run."""

    COMPUTED = "computed"  #: computed by this run
    REUSED = "reused"  #: its outputs were in the store under the same key (an earlier run, or a resumed one)
    SKIPPED = "skipped"  #: not run, and :attr:`StepRecord.reason` says why (e.g. matching in observations mode)


@dataclass(frozen=True)
class StepRecord:
    """One step of a run: its ``status``, wall time in ``seconds``, the run that ``computed_by`` it, its cache
    ``key``, its ``outputs`` (output name -> artifact reference), its small figures (``extra``: counts, the method
    used; the step's type of :mod:`aerocal.pipeline.figures`) and, when skipped, the ``reason``."""

    status: StepStatus
    seconds: float = 0.0
    computed_by: str | None = None
    key: str | None = None
    outputs: dict[str, str] = field(default_factory=dict)
    extra: StepFigures | dict = field(default_factory=dict)
    reason: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "status", StepStatus(self.status))
        if self.seconds < 0:
            raise ValueError(f"step seconds {self.seconds} < 0")
        if self.status is StepStatus.SKIPPED and not self.reason:
            raise ValueError("a skipped step needs its reason")

    def to_json(self) -> dict[str, Any]:
        if self.status is StepStatus.SKIPPED:
            return {"status": self.status.value, "reason": self.reason}
        doc = {"status": self.status.value, "computed_by": self.computed_by, "seconds": round(self.seconds, 3),
               "key": self.key, "outputs": dict(self.outputs)}
        if self.extra:
            doc["extra"] = self.extra
        return doc

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> StepRecord:
        return cls(status=doc["status"], seconds=float(doc.get("seconds") or 0.0),
                   computed_by=doc.get("computed_by"), key=doc.get("key"), outputs=dict(doc.get("outputs") or {}),
                   extra=dict(doc.get("extra") or {}), reason=doc.get("reason"))


@dataclass(frozen=True)
class GroundControlSummary:
    """The screened ground control: the ``datum`` it gave the block (words), the points ``demoted`` (neither
    control nor check point) and a line per finding of the screening."""

    datum: str | None = None
    demoted: tuple[str, ...] = ()
    lines: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {"datum": self.datum, "demoted": list(self.demoted), "lines": list(self.lines)}

    @classmethod
    def from_json(cls, doc: dict[str, Any] | None) -> GroundControlSummary:
        doc = doc or {}
        return cls(doc.get("datum"), tuple(doc.get("demoted") or ()), tuple(doc.get("lines") or ()))


@dataclass(frozen=True)
class RunSummary:
    """A processing run at a glance.

    Fields: ``run_id``; ``flight`` (its name) and ``mode`` (:class:`FlightMode`; its string value is accepted and
    held as the member, and ``run.json`` holds the value); ``certificate_id``
    (``None``: the nominal camera) and ``certificate_reason`` (why, in words); the ``steps`` in the order they ran;
    what ingest left out or complained of (``images_skipped_at_ingest``, ``ingest_problems`` as
    ``"... [error]"`` / ``"... [warning]"`` lines) and what it inferred (``flight_facts``: name -> words with their
    source); the screened ``ground_control``; ``outputs`` (name -> artifact reference) and ``files`` (name -> path
    written under ``out_dir``); ``storage`` (where the platform stored the run; empty in memory).

    After a block adjustment (not on a calibration-only run): ``findings`` (every catalogue effect the run found and
    where it went), ``diagnosis`` (what the diagnosis named, in words), ``diagnosis_after_extension`` (the extended
    block's, where the block was extended), ``model_extension`` (the ``extension.json`` document: the block before
    and after, the terms and their gain), ``recorded_eo`` (the diagnosis's recorded-EO checks, a document),
    ``recorded_eo_corrections`` (what the first adjustment removed from the recorded positions, in words), ``twin``
    (what the simulation gets wrong, in words), ``certificate_terms`` (whether each camera term of the stored
    certificate the block used holds on this flight, one sentence each:
    :func:`aerocal.pipeline.certificates.certificate_term_remainders`), ``accuracy`` (the check points' assessment
    document, ``None`` without check points), ``adjustment_converged`` and ``adjustment_iterations``, and the
    ``surface`` the products stand on, in words (dense or the tie points and why; against the frames' laser ranges
    where they record them).
    """

    run_id: str
    flight: str
    mode: FlightMode
    certificate_id: str | None
    certificate_reason: str
    steps: dict[str, StepRecord] = field(default_factory=dict)
    images_skipped_at_ingest: tuple[str, ...] = ()
    ingest_problems: tuple[str, ...] = ()
    flight_facts: dict[str, str] = field(default_factory=dict)
    ground_control: GroundControlSummary = field(default_factory=GroundControlSummary)
    out_dir: str | None = None
    outputs: dict[str, str] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    storage: dict[str, str] = field(default_factory=dict)
    findings: tuple[Finding, ...] = ()
    diagnosis: str | None = None
    diagnosis_after_extension: str | None = None
    model_extension: dict[str, Any] | None = None
    recorded_eo: dict[str, Any] | None = None
    recorded_eo_corrections: tuple[str, ...] = ()
    twin: str | None = None
    certificate_terms: tuple[str, ...] = ()
    accuracy: dict[str, Any] | None = None
    adjustment_converged: bool | None = None
    adjustment_iterations: int | None = None
    surface: str | None = None

    def __post_init__(self) -> None:
        if not self.run_id:
            raise ValueError("a run summary needs its run id")
        try:
            object.__setattr__(self, "mode", FlightMode(self.mode))
        except ValueError:
            raise ValueError(f"a run summary's mode is one of {', '.join(FlightMode)}, got {self.mode!r}") from None
        for name, step in self.steps.items():
            if not isinstance(step, StepRecord):
                raise TypeError(f"step {name!r}: {type(step).__name__}, not a StepRecord")

    def finding(self, name: str) -> Finding | None:
        """The run's finding of the catalogue effect ``name``, ``None`` when it found none."""
        return next((f for f in self.findings if f.name == name), None)

    def step_status(self) -> dict[str, StepStatus]:
        """Step name -> what became of it."""
        return {name: step.status for name, step in self.steps.items()}

    def with_files(self, **files: str) -> RunSummary:
        """The same summary with more files written (e.g. ``run.json`` and ``provenance.json`` by the platform)."""
        return dataclasses.replace(self, files={**self.files, **files})

    def to_json(self) -> dict[str, Any]:
        """The summary as plain JSON (``run.json``, the database, ``aerocal process --json``)."""
        doc: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "mode":
                value = value.value
            elif f.name == "steps":
                value = {k: v.to_json() for k, v in value.items()}
            elif f.name == "ground_control":
                value = value.to_json()
            elif f.name == "findings":
                value = [x.to_dict() for x in value]
            elif isinstance(value, tuple):
                value = list(value)
            doc[f.name] = value
        return doc

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> RunSummary:
        """A summary from :meth:`to_json`'s form; unknown keys are ignored, missing ones take their defaults."""
        known = {f.name for f in dataclasses.fields(cls)}
        kw = {k: v for k, v in doc.items() if k in known}
        kw["steps"] = {k: StepRecord.from_json(v) for k, v in (doc.get("steps") or {}).items()}
        kw["ground_control"] = GroundControlSummary.from_json(doc.get("ground_control"))
        kw["findings"] = tuple(Finding.from_dict(f) for f in doc.get("findings") or ())
        for name in ("images_skipped_at_ingest", "ingest_problems", "recorded_eo_corrections", "certificate_terms"):
            kw[name] = tuple(doc.get(name) or ())
        for name in ("flight_facts", "outputs", "files", "storage"):
            kw[name] = dict(doc.get(name) or {})
        return cls(**kw)
