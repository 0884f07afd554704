"""Ingest a flight: a folder of images (or a list of image files) plus its sidecar files.

A *flight folder* keeps its images in ``images/`` and beside it, all optional::

    eo.csv          exterior orientation overriding the image metadata (see aerocal.ingest.eo_csv)
    gcp_list.txt    OpenDroneMap ground control list (see aerocal.ingest.gcp_odm)
    gcps.csv        GCP coordinates with sigmas and roles (see aerocal.ingest.gcp_csv)
    camera.json     camera identity and nominal camera (see aerocal.ingest.camera_json); without it,
                    the nominal camera comes from the camera catalogue (aerocal.ingest.camera_catalogue)
    flight.json     the flight plan: height_agl_m, gnss_sigma_m [h, v], imu_sigma_deg, ...; without it the
                    flying height and GNSS sigmas are inferred from the images (aerocal.ingest.inferred)
    (the simulator's ground-truth file is never read by ingest or any processing code)

A plain folder of images is also accepted (its sidecars are looked for in the folder itself).
Explicit ``gcp_file``/``eo_file``/``crs`` arguments win over what is found.

Order of work: list and read every image (metadata only, no pixel decoding); drop duplicates; apply the
EO CSV; fill the camera identity; resolve UTC times; choose the flight CRS (the ``crs`` argument, else the
UTM zone of the images' median position, else the ground control's CRS); project positions; find
strips; read and check ground control; infer what the sidecars do not give (nominal camera, identity,
flying height, GNSS sigmas); build the tables; check that processing can run (:mod:`aerocal.ingest.
readiness`). Problems never stop ingest: each names its file (and line and field), and the result carries
them all; those that ``aerocal process`` cannot go past are marked ``stops_processing``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.camera import Camera
from aerocal.certificates.identity import CameraIdentity
from aerocal.geometry import CONVENTIONS, attitude_to_R_cw, lonlat_to_projected, utm_crs_for
from aerocal.ingest.camera_json import UNKNOWN_CAMERA_ID, read_camera_json
from aerocal.ingest.capture_time import resolve_utc_times
from aerocal.ingest.config import IngestConfig
from aerocal.ingest.crs_strings import CrsTextError, crs_kind, normalise_crs
from aerocal.ingest.dji import APP4_FLOAT_OFFSETS, app4_field_name
from aerocal.ingest.eo_csv import EoFile, read_eo_csv
from aerocal.ingest.gcp import ImageFrame, build_gcp_tables, read_gcp_file
from aerocal.ingest.gcp_records import GcpFile
from aerocal.ingest.inferred import certificate_identity, infer_camera, infer_gnss_sigma, infer_height_agl
from aerocal.ingest.metadata import ImageMetadata, read_image_metadata, sniff_container
from aerocal.ingest.problems import Problem, ProblemLog, name_list
from aerocal.ingest.readiness import check_processable, read_flight_json
from aerocal.ingest.strips import find_strips

#: extensions of image formats ingest does not read; such files are reported, not silently ignored
OTHER_IMAGE_EXTENSIONS = (
    ".png",
    ".bmp",
    ".gif",
    ".dng",
    ".raw",
    ".cr2",
    ".nef",
    ".arw",
    ".heic",
    ".webp",
    ".jp2",
)
EO_NAME, GCP_LIST_NAME, GCP_CSV_NAME, CAMERA_JSON_NAME = "eo.csv", "gcp_list.txt", "gcps.csv", "camera.json"
FLIGHT_JSON_NAME = "flight.json"


@dataclass
class IngestResult:
    """Everything ingest produced for one flight.

    * ``images``: table of schema :data:`aerocal.tables.IMAGES` (CRS in its metadata);
    * ``gcps``, ``gcp_observations``: tables of schemas ``GCPS`` and ``GCP_OBSERVATIONS``;
    * ``extra``: per-image metadata not in the schema (``image_id``, ``name`` and one column per field:
      speeds, laser range, relative altitude, undocumented DJI APP4 floats, provenance of each value);
    * ``crs``: the flight's projected CRS (``None`` if nothing in the flight is georeferenced);
    * ``problems``: everything found wrong, by file, line and field;
    * ``camera``, ``camera_identity``: the nominal camera of ``camera.json`` if there is one;
    * ``skipped_images``: image files that could not be ingested (each has an error in ``problems``);
    * ``sources``: the sidecar files that were read;
    * ``camera_source``: where the nominal camera came from (``camera.json`` or the catalogue, with values);
    * ``height_agl_m``, ``gnss_sigma_m`` (horizontal, vertical): the flight's flying height and GNSS
      sigmas, from ``flight.json`` or inferred from the images, ``None`` where unknown; ``flight_facts``:
      one sentence per fact on where it came from;
    * ``plan``: the other ``flight.json`` fields (name, description, imu_sigma_deg, tie_sigma_px, ...).
    """

    images: pa.Table
    gcps: pa.Table
    gcp_observations: pa.Table
    extra: pa.Table
    crs: str | None
    problems: list[Problem]
    camera: Camera | None = None
    camera_identity: CameraIdentity | None = None
    skipped_images: list[str] = field(default_factory=list)
    sources: dict[str, str] = field(default_factory=dict)
    config: IngestConfig = field(default_factory=IngestConfig)
    camera_source: str | None = None
    height_agl_m: float | None = None
    gnss_sigma_m: tuple[float, float] | None = None
    flight_facts: dict[str, str] = field(default_factory=dict)
    plan: dict = field(default_factory=dict)

    @property
    def blocking(self) -> list[Problem]:
        """The errors ``aerocal process`` cannot go past."""
        return [p for p in self.problems if p.stops_processing]

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "error"]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == "warning"]


# ---------------------------------------------------------------------------- discovery
@dataclass
class _Inputs:
    label: str
    images: list[Path]
    sidecar_dir: Path | None
    folder_files: set[str]


def _discover(
    path_or_list: str | Path | Sequence[str | Path], cfg: IngestConfig, problems: ProblemLog
) -> _Inputs:
    exts = tuple(e.lower() for e in cfg.image_extensions)
    if isinstance(path_or_list, str | Path):
        root = Path(path_or_list)
        if not root.exists():
            problems.error(root, "does not exist; nothing ingested")
            return _Inputs(str(root), [], None, set())
        if root.is_file():
            return _Inputs(str(root), [root], None, {root.name})
        image_dir = root / "images" if (root / "images").is_dir() else root
        try:
            entries = sorted((p for p in image_dir.iterdir() if p.is_file()), key=lambda p: p.name)
        except OSError as exc:
            problems.error(image_dir, f"cannot be listed ({exc.strerror or exc}); nothing ingested")
            return _Inputs(str(root), [], root, set())
        images: list[Path] = []
        for p in entries:
            if p.name.startswith("."):
                continue
            ext = p.suffix.lower()
            if ext in exts:
                images.append(p)
            elif ext in OTHER_IMAGE_EXTENSIONS:
                if _sniff(p) is not None:
                    images.append(p)
                else:
                    problems.error(
                        p, f"image format {ext} is not supported (JPEG, TIFF, DJI R-JPEG are); skipped"
                    )
        if not images:
            problems.error(image_dir, f"holds no image files ({', '.join(exts)}); nothing ingested")
        return _Inputs(str(root), images, root, {p.name for p in entries})
    paths: list[Path] = []
    for item in path_or_list:
        p = Path(item)
        if not p.is_file():
            problems.error(p, "does not exist or is not a file; skipped")
            continue
        paths.append(p)
    paths.sort(key=lambda p: p.name)
    label = str(paths[0].parent) if paths else "<no images>"
    return _Inputs(label, paths, None, {p.name for p in paths})


def _sniff(path: Path) -> str | None:
    try:
        with open(path, "rb") as fh:
            return sniff_container(fh.read(8))
    except OSError:
        return None


def _sidecar(
    explicit: str | Path | None, sidecar_dir: Path | None, name: str, problems: ProblemLog
) -> Path | None:
    if explicit is not None:
        p = Path(explicit)
        if not p.is_file():
            problems.error(p, "does not exist or is not a file; not used")
            return None
        return p
    if sidecar_dir is not None and (sidecar_dir / name).is_file():
        return sidecar_dir / name
    return None


# ---------------------------------------------------------------------------- main entry
def ingest_folder(
    path_or_list: str | Path | Sequence[str | Path],
    gcp_file: str | Path | Sequence[str | Path] | None = None,
    eo_file: str | Path | None = None,
    crs: str | None = None,
    config: IngestConfig | None = None,
) -> IngestResult:
    """Ingest a flight folder, a folder of images or a list of image files; never raises on bad data.

    Args:
        path_or_list: a flight folder (``images/`` beside eo.csv, GCP files, camera.json, flight.json), a folder
            of images, or image files.
        gcp_file: an ODM ``gcp_list.txt`` or a GCP CSV, or several (a CSV of coordinates and roles plus a
            ``gcp_list.txt`` of image measurements); default: ``gcp_list.txt`` and ``gcps.csv`` beside ``images/``.
        eo_file: an EO CSV (default ``eo.csv``): positions and attitudes that replace or complete the images' own.
        crs: the flight's projected CRS (default: the UTM zone of the images' median position); also the CRS of
            EO/GCP CSVs that carry no ``# crs:`` line.
        config: what ingest accepts (default :class:`aerocal.ingest.config.IngestConfig`).

    Returns:
        :class:`IngestResult`: the ``images``, ``gcps`` and ``gcp_observations`` tables in the flight CRS
        (metres), the camera identity and its nominal camera with the source of each number, the flight's
        facts, and ``problems``: everything found wrong by file, line and field, those that stop processing
        marked (``blocking``). Bad data never raises: it is a problem in the result.
    """
    cfg = config or IngestConfig()
    problems = ProblemLog()
    inputs = _discover(path_or_list, cfg, problems)
    where = inputs.label
    sources: dict[str, str] = {"images": where}

    user_crs = None
    if crs is not None:
        try:
            norm = normalise_crs(str(crs))
            if crs_kind(norm) != "projected":
                problems.error(
                    where,
                    f"crs {crs!r} is not a projected CRS in metres; chosen automatically instead",
                    "crs",
                )
            else:
                user_crs = norm
        except CrsTextError as exc:
            problems.error(where, f"crs argument: {exc}; chosen automatically instead", "crs")

    # images
    metas: list[ImageMetadata] = []
    skipped: list[str] = []
    for path in inputs.images:
        try:
            meta, found = read_image_metadata(path, cfg)
        except Exception as exc:  # a defect in a reader must not stop the flight; it is reported by file
            why = f"unexpected failure while reading ({type(exc).__name__}: {exc}); skipped"
            meta, found = None, [Problem(str(path), None, None, why, "error")]
        problems.extend(found)
        if meta is None:
            skipped.append(path.name)
        else:
            metas.append(meta)
    metas = _drop_duplicates(metas, problems, skipped)

    # sidecars
    eo_path = _sidecar(eo_file, inputs.sidecar_dir, EO_NAME, problems)
    camera_json = _sidecar(None, inputs.sidecar_dir, CAMERA_JSON_NAME, problems)
    if gcp_file is None:
        gcp_paths = [
            p
            for p in (_sidecar(None, inputs.sidecar_dir, n, problems) for n in (GCP_CSV_NAME, GCP_LIST_NAME))
            if p is not None
        ]
    else:
        items = [gcp_file] if isinstance(gcp_file, str | Path) else list(gcp_file)
        gcp_paths = [p for p in (_sidecar(i, None, "", problems) for i in items) if p is not None]

    identity, camera = (None, None)
    if camera_json is not None:
        identity, camera = _guarded(problems, camera_json, read_camera_json, camera_json, problems) or (
            None,
            None,
        )
        sources["camera_json"] = str(camera_json)
    flight_json = _sidecar(None, inputs.sidecar_dir, FLIGHT_JSON_NAME, problems)
    plan: dict = {}
    if flight_json is not None:
        plan = _guarded(problems, flight_json, read_flight_json, flight_json, problems) or {}
        sources["flight_json"] = str(flight_json)
        if user_crs is None and plan.get("crs"):
            user_crs = plan["crs"]  # the flight's own CRS, checked by read_flight_json
    if eo_path is not None:
        sources["eo"] = str(eo_path)
        eo = _guarded(problems, eo_path, read_eo_csv, eo_path, problems, user_crs, cfg.eo_default_attitude)
        if eo is not None:
            _apply_eo(eo, metas, problems, set(skipped))
    gcp_files: list[GcpFile] = []
    for p in gcp_paths:
        f = _guarded(problems, p, read_gcp_file, p, problems, cfg, user_crs)
        if f is not None:
            gcp_files.append(f)
    if gcp_paths:
        sources["gcp"] = ";".join(str(p) for p in gcp_paths)

    facts: dict[str, str] = {}
    if camera is not None:
        camera_source = f"{camera_json}"
    elif camera_json is not None and any(p.file == str(camera_json) and p.severity == "error" for p in problems):
        # the user's own file is broken: never replaced by the catalogue's guess
        camera_source = f"{camera_json} gives no valid camera (see its error above); fix it or remove it"
    else:
        camera, camera_source = infer_camera(metas)
        facts["camera"] = camera_source
    metas = _leave_out_other_sizes(metas, camera, problems, skipped)
    camera_ids = _camera_ids(metas, identity, camera, camera_json, problems)
    identity = certificate_identity(metas, identity, camera)
    height = plan.get("height_agl_m")
    facts["height_agl_m"] = f"{FLIGHT_JSON_NAME} height_agl_m"
    if height is None:
        guess = infer_height_agl(metas)
        height, facts["height_agl_m"] = guess.value, guess.source
    gnss = plan.get("gnss_sigma_m")
    facts["gnss_sigma_m"] = f"{FLIGHT_JSON_NAME} gnss_sigma_m"
    if gnss is None:
        guess = infer_gnss_sigma(metas)
        gnss, facts["gnss_sigma_m"] = guess.value, guess.source
    times = resolve_utc_times(metas, where, problems, cfg.time_zone_from_gnss)
    _flight_warnings(metas, where, problems)

    flight_crs = user_crs or _choose_crs(metas, gcp_files, where, problems)
    x, y = _project(metas, flight_crs)
    strip = _strips(metas, x, y, times, cfg)

    frames = {m.name: ImageFrame(i + 1, m.width, m.height) for i, m in enumerate(metas)}
    built = None
    if gcp_files and flight_crs is not None:
        built = _guarded(
            problems,
            gcp_files[0].path,
            build_gcp_tables,
            gcp_files,
            frames,
            flight_crs,
            problems,
            cfg,
            inputs.folder_files,
        )
    if built is not None:
        gcps, gcp_obs = built
    else:
        gcps, gcp_obs = tables.empty("gcps"), tables.empty("gcp_observations")
        if gcp_files and flight_crs is None:
            problems.error(gcp_files[0].path, "no flight CRS could be chosen; ground control not used", "crs")

    images = _images_table(metas, camera_ids, times, x, y, strip, flight_crs)
    extra = _extra_table(metas)
    if flight_crs is not None:
        gcps, gcp_obs = tables.with_crs(gcps, flight_crs), tables.with_crs(gcp_obs, flight_crs)
    _temperature_notes(metas, where, problems)
    eo_errors = [p for p in problems if eo_path is not None and p.file == str(eo_path) and p.severity == "error"
                 and not p.stops_processing]
    check_processable(
        problems, where, images, gcps, camera, camera_source, identity, height, inputs.sidecar_dir, skipped,
        eo_errors,
    )
    return IngestResult(
        images=images,
        gcps=gcps,
        gcp_observations=gcp_obs,
        extra=extra,
        crs=flight_crs,
        problems=problems.as_list(),
        camera=camera,
        camera_identity=identity,
        skipped_images=skipped,
        sources=sources,
        config=cfg,
        camera_source=camera_source if camera is not None else None,
        height_agl_m=None if height is None else float(height),
        gnss_sigma_m=None if gnss is None else (float(gnss[0]), float(gnss[-1])),
        flight_facts=facts,
        plan=plan,
    )


def _temperature_notes(metas: list[ImageMetadata], where: str, problems: ProblemLog) -> None:
    """Say where the sensor temperature came from, or that it is unknown, for radiometric thermal flights."""
    thermal = [m for m in metas if m.raw_format is not None]
    if not thermal or any(m.temperature_c is not None for m in thermal):
        return
    scene = [m for m in thermal if "flir_central_temperature_scene_c" in m.extra]
    note = (
        f"; XMP FLIR:CentralTemperature ({len(scene)} images) is the scene's temperature at the frame "
        "centre, not the sensor's, and is not used as one"
        if scene
        else ""
    )
    problems.warning(
        where,
        f"sensor (core) temperature unknown for {len(thermal)} radiometric thermal image(s): "
        f"{', '.join(sorted({m.raw_format or '' for m in thermal}))} record no documented one{note}; give it per image "
        "in eo.csv (temperature_c) to model thermal drift",
        "temperature_c",
    )


# ---------------------------------------------------------------------------- steps
def _guarded(problems: ProblemLog, path: Path, fn, *args):
    """``fn(*args)``; an unexpected exception (a defect, not bad data) is reported against ``path``."""
    try:
        return fn(*args)
    except Exception as exc:  # a defect in a reader must not stop the flight; it is reported by file
        problems.error(path, f"unexpected failure while reading ({type(exc).__name__}: {exc}); not used")
        return None


def _drop_duplicates(
    metas: list[ImageMetadata], problems: ProblemLog, skipped: list[str]
) -> list[ImageMetadata]:
    """Of files with the same content, the one with the shortest name is kept (``IMG_0006.tif`` over its
    copy ``IMG_0006 (1).tif``: the sidecars name the original; keeping the copy lost its EO row and GCP
    measurements); the order of the others is kept."""
    by_hash: dict[str, ImageMetadata] = {}
    by_name: dict[str, ImageMetadata] = {}
    out = []
    rank = {id(m): k for k, m in enumerate(metas)}
    preferred = sorted(metas, key=lambda m: (len(Path(m.name).stem), rank[id(m)]))
    for m in preferred:
        if m.sha256 in by_hash:
            problems.error(
                m.path, f"has the same content as {by_hash[m.sha256].path}; duplicate skipped", "sha256"
            )
            skipped.append(m.name)
            continue
        if m.name in by_name:
            problems.error(m.path, f"has the same file name as {by_name[m.name].path}; skipped", "name")
            skipped.append(m.name)
            continue
        by_hash[m.sha256] = by_name[m.name] = m
        out.append(m)
    return sorted(out, key=lambda m: rank[id(m)])


def _apply_eo(eo: EoFile, metas: list[ImageMetadata], problems: ProblemLog, skipped: set[str] = frozenset()) -> None:
    """Put the EO file's positions, attitudes and temperatures on the images. A row of an image that was
    skipped (its own error says why) is a warning, not a second error: its image is gone, not the row wrong."""
    exact = {m.name: m for m in metas}
    lower = {m.name.lower(): m for m in metas}
    stem = {Path(m.name).stem.lower(): m for m in metas}
    covered: set[str] = set()
    for name, rec in eo.records.items():
        m = exact.get(name) or lower.get(name.lower()) or stem.get(Path(name).stem.lower())
        if m is None:
            if name in skipped or Path(name).name in skipped:
                problems.warning(eo.path, f"image {name} was skipped (see its error); its row is not used", "image",
                                 rec.line)
            else:
                problems.error(
                    eo.path, f"image {name} is not among the ingested images; row ignored", "image", rec.line
                )
            continue
        covered.add(m.name)
        pose = m.pose
        if rec.lat is not None and rec.lon is not None:
            pose.lat, pose.lon, pose.alt = rec.lat, rec.lon, rec.z
            pose.source = f"eo_csv:{eo.path.name}"
            pose.alt_reference = f"as given in {eo.path.name}"
            if crs_kind(eo.crs) == "projected":
                m.extra["eo_crs"] = eo.crs
                m.extra["eo_x"], m.extra["eo_y"] = float(rec.x), float(rec.y)  # type: ignore[arg-type]
        if rec.angles is not None and eo.convention is not None:
            pose.roll, pose.pitch, pose.yaw = rec.angles
            pose.convention = eo.convention
            m.extra["attitude_source"] = f"eo_csv:{eo.path.name}"
        if rec.temperature_c is not None:
            m.temperature_c, m.temperature_source = rec.temperature_c, f"eo_csv:{eo.path.name}"
    missing = [m.name for m in metas if m.name not in covered]
    if missing and eo.records:
        own = [m for m in metas if m.name in set(missing) and m.pose.lat is not None]
        why = (f"{len(own)} of them would keep their own metadata's position (another source and vertical "
               "reference)" if own else "they would have no position")
        problems.blocker(
            eo.path,
            f"{len(missing)} ingested image(s) have no row: {name_list(missing)}; {why}. Fix: add their rows, "
            "or move those images out of the flight",
            "image",
        )


def _leave_out_other_sizes(
    metas: list[ImageMetadata], camera: Camera | None, problems: ProblemLog, skipped: list[str]
) -> list[ImageMetadata]:
    """The images whose frame has the nominal camera's size; the others are left out with a warning each
    (added to ``skipped``): a frame of another size is another camera or a resized copy, and one camera model
    cannot hold both. When no image has the camera's size, all are kept (the camera is then wrong, and
    :func:`~aerocal.ingest.readiness.check_processable` says so)."""
    if camera is None:
        return metas
    size = (camera.width, camera.height)
    keep = [m for m in metas if (m.width, m.height) == size]
    if not keep or len(keep) == len(metas):
        return metas
    for m in metas:
        if (m.width, m.height) != size:
            problems.warning(
                m.path,
                f"left out: its frame is {m.width}x{m.height}, not the {size[0]}x{size[1]} of the flight's nominal "
                f"camera ({len(keep)} images); another camera or a resized copy cannot share that camera's "
                "model. Fix: process it in a folder of its own, or restore the original frame",
                "width",
            )
            skipped.append(m.name)
    return keep


def _camera_ids(
    metas: list[ImageMetadata],
    identity: CameraIdentity | None,
    camera: Camera | None,
    camera_json: Path | None,
    problems: ProblemLog,
) -> list[str]:
    ids: list[str] = []
    known: dict[tuple[int, int], set[str]] = {}
    for m in metas:
        ident = CameraIdentity.from_parts(m.make, m.model, m.serial, m.lens)
        if ident.is_known:
            known.setdefault((m.width, m.height), set()).add(ident.camera_id)
    for m in metas:
        ident = CameraIdentity.from_parts(m.make, m.model, m.serial, m.lens)
        if ident.is_known:
            if (
                identity is not None
                and identity.is_known
                and (ident.make, ident.model) != (identity.make, identity.model)
            ):
                problems.warning(
                    m.path,
                    f"camera {ident.camera_id} differs from {CAMERA_JSON_NAME} ({identity.camera_id}); "
                    "the image's own identity is used",
                    "camera_id",
                )
            ids.append(ident.camera_id)
        elif identity is not None and identity.is_known:
            ids.append(identity.camera_id)
        elif len(known.get((m.width, m.height), ())) == 1:
            cid = next(iter(known[(m.width, m.height)]))
            problems.warning(
                m.path, f"no camera identity; assumed to be the flight's {cid} (same image size)", "camera_id"
            )
            ids.append(cid)
        else:
            problems.warning(
                m.path, f"no camera identity; camera_id set to {UNKNOWN_CAMERA_ID!r}", "camera_id"
            )
            ids.append(UNKNOWN_CAMERA_ID)
    if camera is not None and camera_json is not None:
        sizes = sorted({(m.width, m.height) for m in metas})
        if sizes and (camera.width, camera.height) not in sizes:
            problems.warning(
                camera_json,
                f"nominal camera is {camera.width}x{camera.height} but the images are "
                f"{', '.join(f'{w}x{h}' for w, h in sizes)}",
                "camera",
            )
    return ids


def _flight_warnings(metas: list[ImageMetadata], where: str, problems: ProblemLog) -> None:
    """Warnings about the whole flight, given once instead of once per image."""
    if not metas:
        return
    n = len(metas)
    no_pos = [m.name for m in metas if m.pose.lat is None]
    if len(no_pos) == n:
        problems.warning(
            where,
            f"no image carries a GNSS position ({n} images): positions and attitude are null; orientation "
            "must come from structure from motion and ground control",
            "gnss",
        )
    elif no_pos:
        problems.warning(
            where, f"{len(no_pos)} of {n} images have no GNSS position: {name_list(no_pos)}", "gnss"
        )
    no_att = [m.name for m in metas if m.pose.convention is None]
    if no_att and len(no_pos) < n:
        problems.warning(
            where, f"{len(no_att)} of {n} images have no recorded attitude: {name_list(no_att)}", "attitude"
        )
    no_temp = [m.name for m in metas if m.temperature_c is None]
    if no_temp and len(no_temp) < n:
        problems.warning(
            where,
            f"{len(no_temp)} of {n} images have no camera temperature: {name_list(no_temp)}",
            "temperature_c",
        )
    dji_alt = [m for m in metas if m.pose.source == "xmp:drone-dji" and m.pose.alt is not None]
    if dji_alt:
        problems.warning(
            where,
            f"alt of {len(dji_alt)} image(s) is DJI AbsoluteAltitude, whose vertical reference (ellipsoidal "
            "or mean sea level) DJI does not document for every model and mode: "
            "check before using heights as "
            "priors (dji_relative_altitude_m is in extra)",
            "alt",
        )
    app4 = [m for m in metas if any(app4_field_name(o) in m.extra for o in APP4_FLOAT_OFFSETS)]
    if app4:
        ranges = []
        for off in APP4_FLOAT_OFFSETS:
            vals = [float(m.extra[app4_field_name(off)]) for m in app4 if app4_field_name(off) in m.extra]
            if vals:
                ranges.append(f"byte {off}: {vals[0]:.1f} -> {vals[-1]:.1f}")
        used = [m for m in app4 if (m.temperature_source or "").startswith("dji:APP4")]
        use = (
            f"used as temperature_c on request ({len(used)} images)"
            if used
            else "not used as the sensor temperature (IngestConfig.dji_app4_temperature opts in)"
        )
        problems.warning(
            where,
            f"DJI APP4 floats that read as internal temperatures in degC ({'; '.join(ranges)}) are "
            f"UNDOCUMENTED by DJI; stored in extra as dji_app4_f<byte>_undocumented, {use}",
            "APP4",
        )


def _choose_crs(
    metas: list[ImageMetadata], gcp_files: list[GcpFile], where: str, problems: ProblemLog
) -> str | None:
    lon = np.array([m.pose.lon for m in metas if m.pose.lon is not None], dtype=float)
    lat = np.array([m.pose.lat for m in metas if m.pose.lat is not None], dtype=float)
    if lon.size:
        try:
            return utm_crs_for(float(np.median(lon)), float(np.median(lat)))
        except ValueError as exc:
            problems.warning(
                where, f"images' median position: {exc}; flight CRS from ground control instead", "crs"
            )
    for f in gcp_files:
        kind = crs_kind(f.crs)
        if kind == "projected":
            return f.crs
        if kind == "geographic" and f.points:
            glon = float(np.median([p.x for p in f.points.values()]))
            glat = float(np.median([p.y for p in f.points.values()]))
            try:
                return utm_crs_for(glon, glat)
            except ValueError:
                continue
    return None


def _project(metas: list[ImageMetadata], crs: str | None) -> tuple[np.ndarray, np.ndarray]:
    n = len(metas)
    x = np.full(n, np.nan)
    y = np.full(n, np.nan)
    if crs is None:
        return x, y
    idx = [i for i, m in enumerate(metas) if m.pose.lat is not None and m.pose.lon is not None]
    if idx:
        lon = np.array([metas[i].pose.lon for i in idx], dtype=float)
        lat = np.array([metas[i].pose.lat for i in idx], dtype=float)
        px, py = lonlat_to_projected(lon, lat, crs)
        x[idx], y[idx] = np.asarray(px, dtype=float), np.asarray(py, dtype=float)
    for i, m in enumerate(metas):  # EO given in the flight CRS: keep its coordinates exactly
        if m.extra.get("eo_crs") == crs and str(m.pose.source).startswith("eo_csv"):
            x[i], y[i] = float(m.extra["eo_x"]), float(m.extra["eo_y"])
    bad = ~np.isfinite(x) | ~np.isfinite(y)
    x[bad] = y[bad] = np.nan
    return x, y


def _strips(metas, x, y, times, cfg: IngestConfig) -> np.ndarray:
    n = len(metas)
    strip = np.full(n, -2, dtype=np.int32)  # -2: no position (null in the table)
    pos = np.flatnonzero(np.isfinite(x) & np.isfinite(y))
    if pos.size == 0:
        return strip
    if all(times[i] is not None for i in pos):
        order = sorted(pos, key=lambda i: (times[i], metas[i].name))
    else:
        order = sorted(pos, key=lambda i: metas[i].name)
    order = np.asarray(order)
    heading = np.array([image_heading(metas[i].pose.convention, metas[i].pose.roll, metas[i].pose.pitch,
                                      metas[i].pose.yaw) for i in order], dtype=float)
    strip[order] = find_strips(x[order], y[order], heading, cfg.strips)
    return strip


def image_heading(convention: str | None, roll: float | None, pitch: float | None, yaw: float | None) -> float:
    """Azimuth (degrees clockwise from grid north) of the image's "up" direction on the ground, from the
    recorded attitude; NaN without one.

    Taken from the rotation, not from the yaw angle: near nadir a gimbal's yaw and roll trade against each
    other (gimbal lock), so the yaw of a camera tilted 1 degree off nadir can read anything while the image's
    orientation on the ground is well defined. A camera looking near the horizon uses its viewing direction.
    """
    if convention not in CONVENTIONS or None in (roll, pitch, yaw):
        return float("nan")
    R = attitude_to_R_cw(convention, float(roll), float(pitch), float(yaw))  # type: ignore[arg-type]
    v = -R[1, :]  # the camera's -y axis (image up) in the world frame (E, N, up)
    if np.hypot(v[0], v[1]) < 0.2:
        v = R[2, :]  # viewing direction
    return float(np.degrees(np.arctan2(v[0], v[1])) % 360.0)


def laser_range(extra: dict) -> float | None:
    """The range (metres) a laser range finder on the camera's axis measured for an image, from its recorded
    metadata (DJI XMP ``LRFTargetDistance``, kept only with ``LRFStatus`` "Normal" where the status is written), or
    ``None``."""
    value = extra.get("dji_lrf_target_distance_m")
    status = extra.get("dji_lrf_status")
    if value is None or not math.isfinite(float(value)) or float(value) <= 0 or status not in (None, "Normal"):
        return None
    return float(value)


def _images_table(metas, camera_ids, times, x, y, strip, crs) -> pa.Table:
    def col(values):
        return [None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v for v in values]

    columns = {
        "image_id": list(range(1, len(metas) + 1)),
        "name": [m.name for m in metas],
        "path": [str(m.path.resolve()) for m in metas],
        "sha256": [m.sha256 for m in metas],
        "time": times,
        "camera_id": camera_ids,
        "width": [m.width for m in metas],
        "height": [m.height for m in metas],
        "bit_depth": [m.bit_depth for m in metas],
        "lat": col(m.pose.lat for m in metas),
        "lon": col(m.pose.lon for m in metas),
        "alt": col(m.pose.alt for m in metas),
        "gnss_x": col(x.tolist()),
        "gnss_y": col(y.tolist()),
        "gnss_z": col(m.pose.alt if np.isfinite(x[i]) else None for i, m in enumerate(metas)),
        "roll": col(m.pose.roll for m in metas),
        "pitch": col(m.pose.pitch for m in metas),
        "yaw": col(m.pose.yaw for m in metas),
        "attitude_convention": [m.pose.convention for m in metas],
        "temperature_c": col(m.temperature_c for m in metas),
        "strip": [None if s == -2 else int(s) for s in strip.tolist()],
        "laser_range_m": [laser_range(m.pose.extra) for m in metas],
    }
    table = tables.from_columns("images", columns)
    return tables.with_crs(table, crs) if crs else table


def _extra_table(metas: list[ImageMetadata]) -> pa.Table:
    rows = []
    for m in metas:
        row = dict(m.extra)
        row["position_source"] = m.pose.source
        if m.pose.alt_reference:
            row["alt_reference"] = m.pose.alt_reference
        if m.temperature_source:
            row["temperature_source"] = m.temperature_source
        row["container"] = m.container + ("/r-jpeg raw thermal" if m.raw_thermal else "")
        rows.append(row)
    keys = sorted({k for r in rows for k in r})
    arrays = [
        pa.array(list(range(1, len(metas) + 1)), type=pa.int32()),
        pa.array([m.name for m in metas], type=pa.string()),
    ]
    names = ["image_id", "name"]
    for k in keys:
        values = [r.get(k) for r in rows]
        numeric = all(v is None or (isinstance(v, int | float) and not isinstance(v, bool)) for v in values)
        if numeric:
            arrays.append(pa.array([None if v is None else float(v) for v in values], type=pa.float64()))
        else:
            arrays.append(pa.array([None if v is None else str(v) for v in values], type=pa.string()))
        names.append(k)
    return pa.Table.from_arrays(arrays, names=names)
