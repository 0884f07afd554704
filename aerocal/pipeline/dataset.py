"""Where a flight's inputs come from: a folder on disk or tables in memory (the idea of OpenSfM's DataSet).

A :class:`FlightDataset` gives the ingest step everything processing reads of a flight: the images, image
observations (observations mode), ground control and its image measurements as :mod:`aerocal.tables`
tables, the camera document (identity and nominal camera), the flight's metadata, and a *manifest*: what
identifies its content, so that a changed input re-runs ingest and everything after it.

* :class:`FolderDataset`: a flight folder, in one of two kinds:

  - **observations mode** (``observations/observations.parquet`` exists, as the simulator writes it): the
    image measurements are given; ``camera.json`` and ``flight.json`` say the rest; frames in ``images/``,
    if any, are used for the mosaic only;
  - **image mode**: :func:`aerocal.ingest.ingest_folder` reads images, metadata, EO and GCP files; the
    enhance + match step then measures the tie points.

* :class:`MemoryDataset`: the tables and documents themselves (a simulated flight, a notebook's tables);
  nothing is read from disk, and there are no frames (the mosaic step makes the DSM only). A simulated
  flight is one: :func:`aerocal.simulate.simulator.as_dataset`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any, Protocol

import pyarrow as pa

from aerocal import tables
from aerocal.camera import Camera
from aerocal.certificates.document import validate_camera
from aerocal.certificates.identity import CameraIdentity
from aerocal.ingest import IngestResult, ingest_folder
from aerocal.ingest.inferred import certificate_identity
from aerocal.ingest.problems import Problem, ProblemLog
from aerocal.ingest.sidecars import sidecar_problems
from aerocal.io import file_sha256
from aerocal.matching.ground import flying_height
from aerocal.pipeline.runner import table_sha256
from aerocal.pipeline.summary import FlightMode
from aerocal.poses import has_priors

#: stem of the simulator's truth files and folder, which processing never reads (nor hashes)
TRUTH_STEM = "truth"

#: the tables of an observations-mode flight, in ``observations/<kind>.parquet``
OBSERVATION_TABLES = ("images", "observations", "gcps", "gcp_observations")

#: a reference surface for the DSM (e.g. a LiDAR DSM) in the flight folder: a single-band north-up GeoTIFF
#: of heights in metres, in the flight's CRS
REFERENCE_DSM = Path("reference") / "dsm.tif"


class FlightInputError(ValueError):
    """A flight's input lacks what processing needs; the message names the file, the field and the fix."""


@dataclass(frozen=True)
class IngestStepConfig:
    """The ingest step's settings (the configuration a dataset is read with): ``gcp_file`` (a path, or a tuple of
    them when the coordinates and the image measurements are in separate files) / ``eo_file`` override the
    folder's own files, ``crs`` the automatic UTM zone (image mode only); ``flight_name`` defaults
    to the folder's (or dataset's) name. ``None`` everywhere: the folder decides. A value given is a non-empty
    string (a path may be a :class:`~pathlib.Path`); whether the files exist and the CRS is a projected one is
    ingest's to judge, which reports them as problems of the flight (:func:`aerocal.ingest.ingest_folder`)."""

    gcp_file: str | tuple[str, ...] | None = None
    eo_file: str | None = None
    crs: str | None = None
    flight_name: str | None = None

    def __post_init__(self) -> None:
        if isinstance(self.gcp_file, list | tuple):  # several GCP files (``aerocal ingest --gcp A --gcp B``)
            files = tuple(self.gcp_file)
            if not files or not all(isinstance(f, str | PurePath) and str(f).strip() for f in files):
                raise ValueError(f"IngestStepConfig.gcp_file must be None, a non-empty path or a non-empty tuple "
                                 f"of them, got {self.gcp_file!r}")
            object.__setattr__(self, "gcp_file", files if len(files) > 1 else files[0])
        for name in ("gcp_file", "eo_file", "crs", "flight_name"):
            value = getattr(self, name)
            if name == "gcp_file" and isinstance(value, tuple):
                continue
            paths = (str, PurePath) if name.endswith("_file") else (str,)
            if value is not None and not (isinstance(value, paths) and str(value).strip()):
                what = "a non-empty path" if name.endswith("_file") else "a non-empty string"
                raise ValueError(f"IngestStepConfig.{name} must be None or {what}, got {value!r}")


@dataclass
class IngestedFlight:
    """What a dataset holds, read: the tables by kind (``images``, ``gcps``, ``gcp_observations`` and, in
    observations mode, ``observations``), the camera document (``identity``, ``camera`` and ``source``), the
    flight's metadata as its ``flight.json`` says it (plan, sigmas, height above ground), its CRS, the
    :class:`FlightMode` (its string value is accepted and held as the member), ingest's problems (one line
    each), the images left out and the flight facts ingest inferred."""

    tables: dict[str, pa.Table]
    camera: dict[str, Any]
    metadata: dict[str, Any]
    crs: str | None
    mode: FlightMode
    problems: list[str] = field(default_factory=list)
    skipped_images: list[str] = field(default_factory=list)
    facts: dict[str, str] | None = None

    def __post_init__(self) -> None:
        self.mode = FlightMode(self.mode)


class FlightDataset(Protocol):
    """A flight's inputs (see the module docstring)."""

    #: the flight's name (the folder's name by default)
    name: str
    #: the folder frames and the reference DSM are found in, or ``None`` (a dataset in memory)
    folder: Path | None

    @property
    def observations_mode(self) -> bool:
        """True when the image measurements are given (no matching)."""
        ...

    def manifest(self) -> dict[str, Any]:
        """What identifies the dataset's content (a changed input changes it)."""
        ...

    def read(self, settings: IngestStepConfig) -> IngestedFlight:
        """Read everything; raises :class:`FlightInputError` naming what is wrong."""
        ...


def observations_mode(flight_dir: str | Path) -> bool:
    """True when the folder holds measured image observations (``observations/observations.parquet``)."""
    return (Path(flight_dir) / "observations" / "observations.parquet").is_file()


def observations_report(folder: str | Path) -> tuple[list[tuple[str, str]], list[Problem]]:
    """What ``aerocal ingest`` says of an observations-mode folder: the same reading as processing
    (:meth:`FolderDataset.read`): its tables (rows per table, CRS) and the problems of the files beside them
    (:func:`aerocal.ingest.sidecars.sidecar_problems`); a table that cannot be read is a problem that stops
    processing. Returns (summary rows, problems)."""
    folder = Path(folder)
    rows: list[tuple[str, str]] = [("mode", "observations (processed from observations/*.parquet)")]
    found = ProblemLog()
    tabs = {}
    for kind in OBSERVATION_TABLES:
        path = folder / "observations" / f"{kind}.parquet"
        try:
            tabs[kind] = tables.read(path, kind)
            rows.append((f"{kind} rows", str(tabs[kind].num_rows)))
        except (OSError, ValueError, pa.ArrowException) as exc:
            found.blocker(path, f"cannot be read ({exc}); write the table again (`aerocal match`)")
    if not (folder / "camera.json").is_file():
        found.blocker(folder / "camera.json", "missing; write the camera identity and nominal model there")
    if "images" in tabs and "gcps" in tabs:
        crs = (tabs["images"].schema.metadata or {}).get(b"aerocal.crs", b"").decode() or None
        rows.append(("CRS", crs or "-"))
        found.extend(sidecar_problems(folder, tabs["images"], tabs["gcps"], crs))
    return rows, found.as_list()


def sidecar_blockers(folder: str | Path) -> list[Problem]:
    """The problems that stop processing among the files beside an observations-mode folder's tables
    (:func:`aerocal.ingest.sidecars.sidecar_problems`); none when its images or gcps table cannot be read (the
    reader of the flight says that)."""
    folder = Path(folder)
    try:
        images = tables.read(folder / "observations" / "images.parquet", "images")
        gcps = tables.read(folder / "observations" / "gcps.parquet", "gcps")
    except (OSError, ValueError, pa.ArrowException):
        return []
    crs = (images.schema.metadata or {}).get(b"aerocal.crs", b"").decode() or None
    return [p for p in sidecar_problems(folder, images, gcps, crs) if p.stops_processing]


def blocking_report(result) -> str:
    """The message of a flight that cannot be processed: every blocking problem of ingest, one per line."""
    lines = [f"{result.sources.get('images', 'flight')}: cannot be processed ({len(result.blocking)} problem(s); "
             "`aerocal ingest FOLDER` shows the whole report):"]
    lines += [f"  - {p}" for p in result.blocking]
    return "\n".join(lines)


def camera_document(path: Path) -> dict:
    """An observations-mode ``camera.json``, checked as a certificate's camera is (finite, plausible values).

    Raises:
        FlightInputError: ``path`` is not valid JSON (the message names the line), or its ``camera`` is missing or not a
            valid camera.
    """
    try:
        doc = json.loads(path.read_text())
        validate_camera(Camera.from_dict(doc["camera"]))
    except json.JSONDecodeError as exc:
        raise FlightInputError(f"{path}:{exc.lineno}: not valid JSON ({exc.msg}); fix the file there") from None
    except (KeyError, TypeError, ValueError, OverflowError) as exc:
        raise FlightInputError(f"{path}: 'camera' is not a valid camera ({exc}); fix the file") from None
    return doc


def with_shared_identity(cam_doc: dict) -> dict:
    """A camera document whose identity records no serial gets the serial-less identity an image-mode flight of
    that camera gets (``no-serial WxH``, :func:`aerocal.ingest.inferred.certificate_identity`): a thermal camera
    that writes no serial into its files must still be processable, and its certificate found again."""
    ident = cam_doc.get("identity") or {}
    serial = str(ident.get("serial") or "") if isinstance(ident, dict) else ""
    if not isinstance(ident, dict) or serial.strip().lower() not in ("", "unknown") \
            or not isinstance(cam_doc.get("camera"), dict):
        return cam_doc
    given = CameraIdentity.from_parts(ident.get("make"), ident.get("model"), "", ident.get("lens"))
    shared = certificate_identity([], given, Camera.from_dict(cam_doc["camera"]))
    if shared is None:
        return cam_doc
    return {**cam_doc, "identity": shared.as_dict()}


class FolderDataset:
    """A flight folder (observations mode or image mode; see the module docstring)."""

    def __init__(self, folder: str | Path, name: str | None = None) -> None:
        self.folder = Path(folder).resolve()
        if not self.folder.is_dir():
            raise FlightInputError(f"{self.folder} is not a folder; give a flight folder (images/ or "
                                   "observations/, eo.csv, gcp files, camera.json)")
        self.name = name or self.folder.name

    def __repr__(self) -> str:
        return f"FolderDataset({str(self.folder)!r})"

    @property
    def observations_mode(self) -> bool:
        return observations_mode(self.folder)

    def manifest(self) -> dict[str, Any]:
        """Every file of the folder (relative path -> SHA-256 and size), truth and hidden files left out.

        Raises:
            FlightInputError: the folder holds no files.
        """
        files = {}
        for p in sorted(self.folder.rglob("*")):
            rel = p.relative_to(self.folder)
            hidden = any(part.startswith(".") for part in rel.parts)
            if not p.is_file() or hidden or rel.parts[0].split(".")[0] == TRUTH_STEM:
                continue
            files[rel.as_posix()] = {"sha256": file_sha256(p), "size": p.stat().st_size}
        if not files:
            raise FlightInputError(f"{self.folder} holds no files; give a flight folder")
        mode = FlightMode.OBSERVATIONS if self.observations_mode else FlightMode.IMAGES
        return {"schema": "aerocal.flight-manifest/1", "mode": mode.value,
                "files": files}

    def read(self, settings: IngestStepConfig) -> IngestedFlight:
        return self._read_observations() if self.observations_mode else self.read_images(settings)

    def _read_observations(self) -> IngestedFlight:
        meta_path, cam_path = self.folder / "flight.json", self.folder / "camera.json"
        meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
        tabs = {}
        for kind in OBSERVATION_TABLES:
            path = self.folder / "observations" / f"{kind}.parquet"
            if not path.exists():
                raise FlightInputError(f"{path} is missing; an observations-mode flight needs "
                                       f"{', '.join(OBSERVATION_TABLES)}")
            tabs[kind] = tables.read(path, kind)
        if not cam_path.exists():
            raise FlightInputError(f"{cam_path} is missing; write the camera identity and nominal model there")
        cam_doc = with_shared_identity(camera_document(cam_path))
        crs = (tabs["images"].schema.metadata or {}).get(b"aerocal.crs", b"").decode() or meta.get("crs")
        found = sidecar_problems(self.folder, tabs["images"], tabs["gcps"], crs)
        blocking = [p for p in found if p.stops_processing]
        if blocking:
            lines = [f"{self.folder}: cannot be processed ({len(blocking)} problem(s); `aerocal ingest FOLDER` "
                     "shows the whole report):"] + [f"  - {p}" for p in blocking[:20]]
            if len(blocking) > 20:
                lines.append(f"  ... and {len(blocking) - 20} more")
            raise FlightInputError("\n".join(lines))
        return IngestedFlight(tabs, cam_doc, meta, crs, FlightMode.OBSERVATIONS, [str(p) for p in found])

    def ingest(self, settings: IngestStepConfig) -> IngestResult:
        """Ingest's whole report of the folder's images (:func:`aerocal.ingest.ingest_folder` with the files and
        CRS of ``settings``): the tables and every problem, those that stop processing included, raising none of
        them. ``aerocal ingest`` prints it; :meth:`read_images` stops on its blocking problems."""
        gcp = list(settings.gcp_file) if isinstance(settings.gcp_file, tuple) else settings.gcp_file
        return ingest_folder(self.folder, gcp_file=gcp, eo_file=settings.eo_file, crs=settings.crs)

    def read_images(self, settings: IngestStepConfig) -> IngestedFlight:
        """The folder's images as image mode reads them (also where it holds observation tables: ``aerocal
        match`` makes them again), the tables, camera and flight metadata ingest gives the pipeline.

        Raises:
            FlightInputError: ingest finds problems that stop processing (the message is their report), or the flying
                height is needed and cannot be measured (:func:`measured_flying_height`).
        """
        res = self.ingest(settings)
        if res.blocking:
            raise FlightInputError(blocking_report(res))
        cam_doc = {"identity": CameraIdentity.coerce(res.camera_identity).as_dict(),
                   "camera": res.camera.to_dict(), "source": res.camera_source}
        tabs = {"images": res.images, "gcps": res.gcps, "gcp_observations": res.gcp_observations}
        # flight.json as ingest checked it, with what the images tell where it is silent
        facts = dict(res.flight_facts)
        height = res.height_agl_m
        if height is None and res.gcps.num_rows == 0 and has_priors(res.images):
            height, facts["height_agl_m"] = measured_flying_height(self.folder, res.images, res.camera)
        meta = {**res.plan, "height_agl_m": height,
                "gnss_sigma_m": None if res.gnss_sigma_m is None else list(res.gnss_sigma_m)}
        return IngestedFlight(tabs, cam_doc, meta, res.crs, FlightMode.IMAGES, [str(p) for p in res.problems],
                              list(res.skipped_images), facts)


def measured_flying_height(folder: Path, images: pa.Table, camera: Camera) -> tuple[float, str]:
    """The flying height (m) of a flight that records none, measured from its tie points
    (:func:`aerocal.matching.ground.flying_height` on the enhanced frames matching uses), and its source;
    raises :class:`FlightInputError` naming the fix where the images do not give it."""
    # import cycle: aerocal.pipeline.match_step (the pipeline's frame reader) imports this module
    from aerocal.pipeline.match_step import frame_loader

    paths = images.column("path").to_pylist()
    step = max(1, len(paths) // 40)  # the flight's stretch from 40 frames at most: a few seconds on any flight
    measured = flying_height(images, camera, frame_loader(paths[::step]))
    if measured.height_m is None:
        raise FlightInputError(
            f"{folder}: flying height unknown: no GCPs, no height_agl_m in flight.json, no height above ground in "
            f"the images, and {measured.source}. Fix: write {folder / 'flight.json'} with {{\"height_agl_m\": H}} "
            "(metres above ground), or add ground control")
    return measured.height_m, f"{measured.height_m:.1f} m {measured.source}"


@dataclass
class MemoryDataset:
    """A flight given as tables (observations mode): ``images``, ``observations``, ``gcps`` and
    ``gcp_observations`` (:mod:`aerocal.tables` kinds), the camera document (``{"identity": {make, model,
    serial, lens}, "camera": Camera.to_dict()}``) and the flight's metadata as a ``flight.json`` would hold it
    (``height_agl_m``, ``gnss_sigma_m`` [horizontal, vertical], ``imu_sigma_deg``, ``start_time``, ``crs``)."""

    name: str
    images: pa.Table
    observations: pa.Table
    gcps: pa.Table
    gcp_observations: pa.Table
    camera: dict[str, Any]
    metadata: dict[str, Any] = field(default_factory=dict)
    crs: str | None = None
    folder: Path | None = None

    @property
    def observations_mode(self) -> bool:
        return True

    def manifest(self) -> dict[str, Any]:
        """SHA-256 of each table (:func:`aerocal.pipeline.runner.table_sha256`) and the documents."""
        return {
            "schema": "aerocal.memory-manifest/1",
            "mode": FlightMode.OBSERVATIONS.value,
            "tables": {kind: table_sha256(getattr(self, kind), kind) for kind in OBSERVATION_TABLES},
            "camera": self.camera,
            "metadata": self.metadata,
            "crs": self.crs,
        }

    def read(self, settings: IngestStepConfig) -> IngestedFlight:
        """Validate the tables and the camera document and return them as the pipeline reads a flight.

        Raises:
            FlightInputError: a table does not match its :mod:`aerocal.tables` schema, or ``camera['camera']`` is
                missing or not a valid camera; the message names the dataset.
        """
        tabs = {}
        for kind in OBSERVATION_TABLES:
            try:
                tabs[kind] = tables.validate(getattr(self, kind), kind)
            except ValueError as exc:
                raise FlightInputError(f"dataset {self.name}: table {kind!r} is not valid ({exc})") from None
        try:
            validate_camera(Camera.from_dict(self.camera["camera"]))
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise FlightInputError(f"dataset {self.name}: 'camera' is not a valid camera ({exc})") from None
        crs = self.crs or (self.images.schema.metadata or {}).get(b"aerocal.crs", b"").decode() \
            or self.metadata.get("crs")
        return IngestedFlight(tabs, with_shared_identity(dict(self.camera)), dict(self.metadata), crs,
                              FlightMode.OBSERVATIONS)


def dataset_of(flight: str | Path | FlightDataset) -> FlightDataset:
    """A dataset for a folder path, or the dataset itself."""
    return FolderDataset(flight) if isinstance(flight, str | Path) else flight
