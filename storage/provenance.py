"""Lineage between artifacts and the provenance of a run.

Within a run, every output artifact is derived from the run's input artifacts: :func:`record_lineage`
stores the run's inputs and outputs and an edge input -> output for each pair. :func:`provenance`
answers "what made this?": the run's inputs, the certificate it used and why, its configuration, code
version, timings and outputs. :func:`ancestors` follows edges across runs back to the raw inputs.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from datetime import date, datetime
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from storage.errors import NotFoundError
from storage.models import Artifact, LineageEdge, Run, RunArtifact


@dataclass(frozen=True)
class ArtifactInfo:
    """One artifact as provenance reports it."""

    id: int
    sha256: str
    uri: str
    kind: str
    schema_name: str | None
    size_bytes: int
    producing_run_id: str | None

    @classmethod
    def of(cls, artifact: Artifact) -> ArtifactInfo:
        return cls(
            artifact.id,
            artifact.sha256,
            artifact.uri,
            artifact.kind,
            artifact.schema_name,
            artifact.size_bytes,
            artifact.producing_run_id,
        )


@dataclass(frozen=True)
class CertificateInfo:
    """The certificate a run used and why it was chosen."""

    id: str
    version: int
    camera: str
    calibration_date: date
    reason: str | None


@dataclass(frozen=True)
class Provenance:
    """Everything recorded about one run; :meth:`to_dict` gives a JSON-ready form."""

    run_id: str
    kind: str
    status: str
    started: datetime
    ended: datetime | None
    code_version: str | None
    configuration: dict[str, Any]
    timings: dict[str, float]
    flight: str | None
    certificate: CertificateInfo | None
    inputs: list[ArtifactInfo] = field(default_factory=list)
    outputs: list[ArtifactInfo] = field(default_factory=list)
    edges: list[tuple[int, int]] = field(default_factory=list)
    error: str | None = None
    #: why the run used its certificate, or the nominal camera (then ``certificate`` is ``None``)
    certificate_reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types (times and dates as ISO-8601 text)."""

        def plain(value: Any) -> Any:
            if isinstance(value, datetime | date):
                return value.isoformat()
            if isinstance(value, dict):
                return {k: plain(v) for k, v in value.items()}
            if isinstance(value, list | tuple):
                return [plain(v) for v in value]
            return value

        return plain(asdict(self))


def _artifact_ids(session: Session, artifacts: Iterable[Artifact | int], what: str) -> list[int]:
    ids = []
    for item in artifacts:
        ids.append(item.id if isinstance(item, Artifact) else int(item))
    unique = list(dict.fromkeys(ids))
    if unique:
        found = set(session.scalars(sa.select(Artifact.id).where(Artifact.id.in_(unique))))
        missing = [i for i in unique if i not in found]
        if missing:
            raise NotFoundError(
                f"{what} artifact id(s) {missing} not found; store them before recording lineage"
            )
    return unique


def link_run_artifact(session: Session, run_id: str, artifact: Artifact | int, role: str) -> None:
    """Record that run ``run_id`` read (``role="input"``) or wrote (``"output"``) an artifact (idempotent)."""
    artifact_id = artifact.id if isinstance(artifact, Artifact) else int(artifact)
    if session.get(RunArtifact, (str(run_id), artifact_id, role)) is None:
        session.add(RunArtifact(run_id=str(run_id), artifact_id=artifact_id, role=role))
        session.flush()


def record_lineage(
    session: Session, run_id: str, inputs: Iterable[Artifact | int], outputs: Iterable[Artifact | int]
) -> int:
    """Record that run ``run_id`` derived every artifact of ``outputs`` from those of ``inputs``.

    Stores the run's inputs and outputs and one edge per (input, output) pair; recording the same
    lineage again adds nothing. Returns the number of new edges. Does not commit.
    """
    run = session.get(Run, str(run_id))
    if run is None:
        raise NotFoundError(f"run {run_id!r} not found; start it before recording lineage")
    input_ids = _artifact_ids(session, inputs, "input")
    output_ids = _artifact_ids(session, outputs, "output")
    for artifact_id in input_ids:
        link_run_artifact(session, run.id, artifact_id, "input")
    for artifact_id in output_ids:
        link_run_artifact(session, run.id, artifact_id, "output")
    existing = set(
        session.execute(
            sa.select(LineageEdge.input_artifact_id, LineageEdge.output_artifact_id).where(
                LineageEdge.run_id == run.id
            )
        ).tuples()
    )
    new = [
        LineageEdge(run_id=run.id, input_artifact_id=i, output_artifact_id=o)
        for i in input_ids
        for o in output_ids
        if i != o and (i, o) not in existing
    ]
    session.add_all(new)
    session.flush()
    return len(new)


def provenance(session: Session, run_id: str) -> Provenance:
    """Inputs, certificate (and reason), configuration, code version, timings and outputs of a run."""
    run = session.get(Run, str(run_id))
    if run is None:
        raise NotFoundError(f"run {run_id!r} not found; list them with `aerocal runs list`")
    links = list(
        session.scalars(
            sa.select(RunArtifact).where(RunArtifact.run_id == run.id).order_by(RunArtifact.artifact_id)
        )
    )
    inputs = [ArtifactInfo.of(link.artifact) for link in links if link.role == "input"]
    outputs = [ArtifactInfo.of(link.artifact) for link in links if link.role == "output"]
    listed = {a.id for a in outputs}
    for artifact in session.scalars(
        sa.select(Artifact).where(Artifact.producing_run_id == run.id).order_by(Artifact.id)
    ):
        if artifact.id not in listed:
            outputs.append(ArtifactInfo.of(artifact))
    edges = sorted(
        session.execute(
            sa.select(LineageEdge.input_artifact_id, LineageEdge.output_artifact_id).where(
                LineageEdge.run_id == run.id
            )
        ).tuples()
    )
    certificate = None
    if run.certificate is not None:
        cert = run.certificate
        certificate = CertificateInfo(
            cert.id, cert.version, cert.camera.label, cert.calibration_date, run.certificate_reason
        )
    return Provenance(
        run_id=run.id,
        kind=run.kind,
        status=run.status,
        started=run.started,
        ended=run.ended,
        code_version=run.code_version,
        configuration=dict(run.configuration or {}),
        timings={k: float(v) for k, v in (run.timings or {}).items()},
        flight=run.flight.name if run.flight is not None else None,
        certificate=certificate,
        inputs=inputs,
        outputs=outputs,
        edges=[(int(i), int(o)) for i, o in edges],
        error=run.error,
        certificate_reason=run.certificate_reason,
    )


def ancestors(session: Session, artifact: Artifact | int) -> list[ArtifactInfo]:
    """Every artifact ``artifact`` was derived from, across runs (breadth-first, nearest first)."""
    start = artifact.id if isinstance(artifact, Artifact) else int(artifact)
    seen: dict[int, None] = {}
    frontier = [start]
    while frontier:
        parents = session.scalars(
            sa.select(LineageEdge.input_artifact_id)
            .where(LineageEdge.output_artifact_id.in_(frontier))
            .distinct()
        )
        frontier = [p for p in parents if p not in seen and p != start]
        seen.update(dict.fromkeys(frontier))
    if not seen:
        return []
    rows = {a.id: a for a in session.scalars(sa.select(Artifact).where(Artifact.id.in_(list(seen))))}
    return [ArtifactInfo.of(rows[i]) for i in seen]
