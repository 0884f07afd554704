"""The content-addressed artifact store.

Every artifact (a Parquet table, an image, a report, an orthomosaic) is stored once per content under
``<root>/<sha[:2]>/<sha>.<ext>`` where ``sha`` is the SHA-256 of its bytes, and registered in the
``artifacts`` table with its kind, schema, size and producing run.

Safety:

* Files are written with :func:`aerocal.io.atomic_path` (temporary file in the same folder, fsync,
  rename): a process killed while writing leaves at most a ``.tmp-*`` file, never a partial file under
  the final name. The database row is added only after the file is in place, so a killed writer also
  leaves no row; writing the same content again stores it. :meth:`ArtifactStore.sweep_temporaries`
  removes old temporary files.
* Every read checks the SHA-256: a missing or altered file raises
  :class:`~storage.errors.CorruptArtifactError` naming the URI, and is never used. Writing the same
  content again repairs it.
* A file left without a row (the writer died between rename and commit) is verified and adopted by
  the next write of that content.

The root is ``$AEROCAL_ARTIFACT_ROOT``, else ``$XDG_DATA_HOME/aerocal/artifacts``
(``~/.local/share/aerocal/artifacts``).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import time
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import unquote, urlparse

import pyarrow as pa
import pyarrow.parquet as pq
import sqlalchemy as sa
from sqlalchemy.orm import Session

from aerocal import tables
from aerocal.io import atomic_path
from storage.database import begin_write
from storage.errors import CorruptArtifactError, NotFoundError, StorageError
from storage.models import Artifact
from storage.provenance import link_run_artifact

ROOT_ENV = "AEROCAL_ARTIFACT_ROOT"

#: Bytes per read/write when hashing and copying files.
CHUNK_BYTES = 1 << 20


def default_artifact_root() -> Path:
    """``$AEROCAL_ARTIFACT_ROOT``, else ``$XDG_DATA_HOME/aerocal/artifacts``."""
    env = os.environ.get(ROOT_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base).expanduser() / "aerocal" / "artifacts"


def sha256_file(path: str | Path) -> tuple[str, int]:
    """SHA-256 hex digest and size in bytes of a file, read in chunks."""
    digest = hashlib.sha256()
    size = 0
    with open(path, "rb") as fh:
        while chunk := fh.read(CHUNK_BYTES):
            digest.update(chunk)
            size += len(chunk)
    return digest.hexdigest(), size


def table_schema_name(kind: str) -> str:
    """Schema name recorded for an Arrow table of ``kind`` (``"aerocal.tables/<kind>"``)."""
    return f"aerocal.tables/{kind}"


def _uri_path(uri: str) -> Path | None:
    parsed = urlparse(uri)
    if parsed.scheme != "file":
        return None
    return Path(unquote(parsed.path))


def _chunks(data: bytes | memoryview) -> Iterator[memoryview]:
    view = memoryview(data)
    for start in range(0, len(view), CHUNK_BYTES):
        yield view[start : start + CHUNK_BYTES]


class ArtifactStore:
    """Content-addressed files under ``root``, registered in the database.

    The ``put_*`` methods add or reuse the ``Artifact`` row in the caller's session (flushed, not
    committed) and, with ``run_id``, record the artifact as an output of that run.
    """

    def __init__(self, root: str | Path | None = None) -> None:
        self.root = (
            Path(root).expanduser().resolve() if root is not None else default_artifact_root().resolve()
        )

    def __repr__(self) -> str:
        return f"ArtifactStore({str(self.root)!r})"

    # ------------------------------------------------------------------------------------ locations
    def path_for(self, sha256: str, ext: str) -> Path:
        """Where content with this hash and extension lives: ``<root>/<sha[:2]>/<sha>.<ext>``."""
        ext = ext.lstrip(".")
        if ext and not ext.replace(".", "").replace("_", "").replace("-", "").isalnum():
            raise StorageError(f"artifact extension {ext!r} must be letters and digits, e.g. 'parquet'")
        if len(sha256) != 64 or any(c not in "0123456789abcdef" for c in sha256):
            raise StorageError(f"not a SHA-256 hex digest: {sha256!r}")
        name = f"{sha256}.{ext}" if ext else sha256
        return self.root / sha256[:2] / name

    def locate(self, artifact: Artifact) -> Path:
        """The file of ``artifact``: its URI's path, or the same name under this store's root when the
        URI points elsewhere (a moved store). Not verified; see :meth:`verify`."""
        path = _uri_path(artifact.uri)
        if path is None:
            raise StorageError(f"artifact {artifact.uri}: only file:// URIs are supported")
        if not path.exists():
            here = self.root / artifact.sha256[:2] / path.name
            if here.exists():
                return here
        return path

    # ---------------------------------------------------------------------------------------- write
    def _holds(self, path: Path, sha256: str, size: int) -> bool:
        """Whether ``path`` exists with exactly this content."""
        try:
            if path.stat().st_size != size:
                return False
        except OSError:
            return False
        return sha256_file(path)[0] == sha256

    def _register(
        self,
        session: Session,
        sha256: str,
        size: int,
        path: Path,
        kind: str,
        schema_name: str | None,
        run_id: str | None,
    ) -> Artifact:
        uri = path.as_uri()
        if not session.in_transaction():
            begin_write(
                session
            )  # SQLite: take the write lock before reading, so the insert cannot be overtaken
        artifact = session.scalars(sa.select(Artifact).where(Artifact.sha256 == sha256)).one_or_none()
        if artifact is None:
            try:
                with session.begin_nested():
                    artifact = Artifact(
                        sha256=sha256,
                        uri=uri,
                        kind=kind,
                        schema_name=schema_name,
                        size_bytes=size,
                        producing_run_id=run_id,
                    )
                    session.add(artifact)
            except sa.exc.IntegrityError:  # another writer registered the same content just now
                artifact = session.scalars(sa.select(Artifact).where(Artifact.sha256 == sha256)).one()
        elif artifact.uri != uri:
            old = _uri_path(artifact.uri)
            if old is None or not self._holds(old, sha256, size):
                artifact.uri = uri  # the recorded copy is gone or damaged: point at the good one
        if run_id is not None:
            link_run_artifact(session, run_id, artifact, "output")
        session.flush()
        return artifact

    @contextlib.contextmanager
    def _writing(self, size: int) -> Iterator[None]:
        """Around the write of an artifact file: a full disk is a :class:`StorageError` that names the folder and
        the fix (the temporary file is already gone, :func:`aerocal.io.atomic_path`, and nothing is registered)."""
        try:
            yield
        except OSError as exc:
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            raise StorageError(
                f"{self.root}: {exc.strerror} while storing {size} bytes (artifact store); free space on that disk "
                "or give another artifact folder (--artifacts, AEROCAL_ARTIFACT_ROOT, with the files already there "
                "copied over), then run the same command again: it resumes after its last completed step"
            ) from None

    def put_bytes(
        self,
        session: Session,
        data: bytes,
        kind: str,
        ext: str,
        schema_name: str | None = None,
        run_id: str | None = None,
    ) -> Artifact:
        """Store ``data`` (once per content) and return its registered :class:`Artifact`.

        Args:
            kind: what it is (``"observations"``, ``"image"``, ``"report"``, ...).
            ext: file extension without the dot (``"parquet"``, ``"json"``, ``"tif"``).
            schema_name: the schema the content follows, if any.
            run_id: the run producing it (recorded as producer for new content, and as run output).
        """
        sha = hashlib.sha256(data).hexdigest()
        final = self.path_for(sha, ext)
        if not self._holds(final, sha, len(data)):
            with self._writing(len(data)), atomic_path(final) as tmp:
                with open(tmp, "wb") as fh:
                    for chunk in _chunks(data):
                        fh.write(chunk)
                tmp.chmod(0o644)
        return self._register(session, sha, len(data), final, kind, schema_name, run_id)

    def put_file(
        self,
        session: Session,
        source: str | Path,
        kind: str,
        ext: str | None = None,
        schema_name: str | None = None,
        run_id: str | None = None,
    ) -> Artifact:
        """Copy the file ``source`` into the store (``ext`` defaults to its suffix); see :meth:`put_bytes`."""
        source = Path(source)
        try:
            sha, size = sha256_file(source)
        except OSError as exc:
            raise StorageError(f"{source}: cannot read ({exc.strerror}); check the path") from None
        final = self.path_for(sha, source.suffix if ext is None else ext)
        if not self._holds(final, sha, size):
            with self._writing(size), atomic_path(final) as tmp:
                digest = hashlib.sha256()
                with open(source, "rb") as src, open(tmp, "wb") as dst:
                    while chunk := src.read(CHUNK_BYTES):
                        digest.update(chunk)
                        dst.write(chunk)
                if digest.hexdigest() != sha:
                    raise StorageError(f"{source} changed while it was being stored; store it again")
                tmp.chmod(0o644)
        return self._register(session, sha, size, final, kind, schema_name, run_id)

    def put_table(self, session: Session, table: pa.Table, kind: str, run_id: str | None = None) -> Artifact:
        """Validate an Arrow table against :mod:`aerocal.tables` and store it as Parquet."""
        table = tables.validate(table, kind)
        meta = dict(table.schema.metadata or {})
        meta[tables.KIND_KEY] = kind.encode()
        table = table.replace_schema_metadata(meta)
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink)
        return self.put_bytes(
            session,
            sink.getvalue().to_pybytes(),
            kind,
            "parquet",
            schema_name=table_schema_name(kind),
            run_id=run_id,
        )

    # ----------------------------------------------------------------------------------------- read
    def get(self, session: Session, artifact_id: int | str) -> Artifact:
        """The artifact with this integer id or SHA-256; :class:`NotFoundError` when unknown."""
        if isinstance(artifact_id, int) or str(artifact_id).isdigit():
            found = session.get(Artifact, int(artifact_id))
        else:
            found = session.scalars(
                sa.select(Artifact).where(Artifact.sha256 == str(artifact_id))
            ).one_or_none()
        if found is None:
            raise NotFoundError(f"artifact {artifact_id!r} not found")
        return found

    def verify(self, artifact: Artifact) -> Path:
        """Check the file's size and SHA-256 and return its path; :class:`CorruptArtifactError` otherwise."""
        path = self.locate(artifact)
        if not path.exists():
            raise CorruptArtifactError(
                f"artifact {artifact.uri} is missing (sha256 {artifact.sha256}); "
                "re-run the step that produced it"
            )
        sha, size = sha256_file(path)
        self._check(artifact, sha, size)
        return path

    def _check(self, artifact: Artifact, sha: str, size: int) -> None:
        if sha != artifact.sha256 or size != artifact.size_bytes:
            raise CorruptArtifactError(
                f"artifact {artifact.uri} is corrupt: sha256 {sha} ({size} bytes) differs from the recorded "
                f"{artifact.sha256} ({artifact.size_bytes} bytes); re-run the step that produced it"
            )

    def read_bytes(self, artifact: Artifact) -> bytes:
        """The artifact's content, verified against its SHA-256."""
        path = self.locate(artifact)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise CorruptArtifactError(
                f"artifact {artifact.uri} is missing (sha256 {artifact.sha256}); "
                "re-run the step that produced it"
            ) from None
        self._check(artifact, hashlib.sha256(data).hexdigest(), len(data))
        return data

    def read_table(self, artifact: Artifact, kind: str | None = None) -> pa.Table:
        """A stored Arrow table, verified and validated against ``kind`` (default: the artifact's kind)."""
        data = self.read_bytes(artifact)
        try:
            table = pq.read_table(pa.BufferReader(data))
        except (OSError, pa.ArrowInvalid) as exc:
            raise CorruptArtifactError(
                f"artifact {artifact.uri}: not a readable Parquet file ({exc})"
            ) from None
        return tables.validate(table, kind or artifact.kind, source=artifact.uri)

    # ------------------------------------------------------------------------------------- cleanup
    def temporaries(self) -> list[Path]:
        """Temporary files left by interrupted writes (``.tmp-*`` in the store's folders)."""
        if not self.root.exists():
            return []
        return sorted(self.root.glob("*/.tmp-*"))

    def sweep_temporaries(self, older_than_s: float = 3600.0) -> list[Path]:
        """Delete temporary files older than ``older_than_s`` seconds (default one hour; a younger one
        may belong to a write in progress) and return them."""
        now = time.time()
        removed = []
        for path in self.temporaries():
            try:
                if now - path.stat().st_mtime >= older_than_s:
                    path.unlink()
                    removed.append(path)
            except FileNotFoundError:
                continue
        return removed
