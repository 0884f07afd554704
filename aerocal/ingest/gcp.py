"""Ground control: read GCP files, check them against the ingested images, build the Arrow tables.

Checks, each reported by file and line:

* a GCP measured twice in one image (the second measurement is ignored);
* one target carrying two labels: two different GCPs measured within ``IngestConfig.gcp_label_conflict_px``
  of each other in the same image (``copr`` IMG_0031: gcp00 and gcp04, 16 m apart on the ground, at the
  same pixel); both measurements are dropped (or kept with a warning, ``gcp_label_conflict="keep"``);
* heights that are all 0.0: unknown, not sea level; kept with a warning (``unknown_height_sigma_z_m``
  turns them into planimetric control);
* labels of ``gcp_list.txt`` missing from the coordinate list ``gcps.csv``, and coordinates that disagree
  between the two by more than ``gcp_coordinate_tolerance_m`` (beyond ``gcp_conflict_stop_m`` this stops
  processing: one of the files is wrong);
* pixels outside the image, images not in the folder, coordinates that cannot be transformed.

Coordinates are transformed to the flight CRS with pyproj (horizontal only: heights pass unchanged).
When a coordinate list (CSV) and ``gcp_list.txt`` are both given, the CSV's coordinates, sigmas and roles
win and ``gcp_list.txt`` supplies the image measurements.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from aerocal import tables
from aerocal.geometry import transformer
from aerocal.ingest.config import IngestConfig
from aerocal.ingest.delimited import read_text_lines
from aerocal.ingest.gcp_csv import looks_like_gcp_csv, read_gcp_csv
from aerocal.ingest.gcp_odm import read_odm_gcp_list
from aerocal.ingest.gcp_records import GcpCoordinate, GcpFile, GcpMeasurement
from aerocal.ingest.problems import ProblemLog, name_list


@dataclass(frozen=True)
class ImageFrame:
    """What GCP checks need about an ingested image: its id and size in pixels."""

    image_id: int
    width: int
    height: int


def read_gcp_file(
    path: str | Path, problems: ProblemLog, config: IngestConfig | None = None, crs: str | None = None
) -> GcpFile | None:
    """Read an ODM ``gcp_list.txt`` or a GCP CSV, telling them apart by the first content line."""
    path = Path(path)
    peek = read_text_lines(path, ProblemLog())
    if peek is not None and peek.lines and looks_like_gcp_csv(peek.lines[0][1]):
        return read_gcp_csv(path, problems, crs=crs)
    return read_odm_gcp_list(path, problems, config)


def build_gcp_tables(
    files: list[GcpFile],
    images: dict[str, ImageFrame],
    flight_crs: str,
    problems: ProblemLog,
    config: IngestConfig | None = None,
    folder_files: set[str] | None = None,
) -> tuple[pa.Table, pa.Table]:
    """The ``gcps`` and ``gcp_observations`` tables (flight CRS, aerocal pixels) from parsed GCP files.

    ``images`` maps image names to their ids and sizes; ``folder_files`` are all file names found in the
    image folder (to tell "not in the folder" from "skipped because unreadable").
    """
    cfg = config or IngestConfig()
    csv_files = [f for f in files if f.kind == "csv"]
    ordered = csv_files + [f for f in files if f.kind != "csv"]
    chosen: dict[str, tuple[GcpCoordinate, GcpFile]] = {}
    others: list[tuple[GcpCoordinate, GcpFile]] = []
    for f in ordered:
        for gid, point in f.points.items():
            if gid in chosen:
                others.append((point, f))
                continue
            if f.kind != "csv" and csv_files:
                lists = ", ".join(c.path.name for c in csv_files)
                problems.warning(
                    f.path,
                    f"label {gid} is not in the coordinate list {lists}; its coordinates from "
                    f"{f.path.name} are used with the default role and sigmas",
                    "label",
                    point.line,
                )
            chosen[gid] = (point, f)

    # transform to the flight CRS
    ids = sorted(chosen)
    xyz = np.full((len(ids), 3), np.nan)
    for k, gid in enumerate(ids):
        xyz[k] = to_flight_crs(chosen[gid][0], chosen[gid][1].crs, flight_crs)
    usable = np.all(np.isfinite(xyz), axis=1)
    for k in np.flatnonzero(~usable):
        point, f = chosen[ids[k]]
        problems.error(
            f.path,
            f"{ids[k]} cannot be transformed from {f.crs} to {flight_crs}; GCP ignored",
            "X/Y",
            point.line,
        )
    flight_xyz = {gid: xyz[k] for k, gid in enumerate(ids) if usable[k]}
    for point, f in others:
        ref_point, ref_file = chosen[point.gcp_id]
        if point.gcp_id not in flight_xyz:
            continue
        other = to_flight_crs(point, f.crs, flight_crs)
        d = float(np.linalg.norm(other - flight_xyz[point.gcp_id]))
        if not np.isfinite(d) or d > cfg.gcp_conflict_stop_m:
            # two files disagree by more than any survey: one of them is wrong, and only the user knows which
            problems.blocker(
                f.path,
                f"{point.gcp_id} lies {d:.3f} m from its coordinates in {ref_file.path.name} line "
                f"{ref_point.line}: one of the two is wrong. Fix: correct it, or remove the point from one "
                "file",
                "X/Y/Z",
                point.line,
            )
        elif d > cfg.gcp_coordinate_tolerance_m:
            problems.warning(
                f.path,
                f"{point.gcp_id} lies {d:.3f} m from its coordinates in {ref_file.path.name} line "
                f"{ref_point.line}; those are used",
                "X/Y/Z",
                point.line,
            )

    # heights that are all zero
    unknown_files = {id(f) for f in files if f.heights_unknown}
    for f in files:
        if not f.heights_unknown or f.heights_absent or not any(chosen[g][1] is f for g in flight_xyz):
            continue
        span = f"lines {f.first_data_line}-{f.last_data_line}" if f.first_data_line else "every line"
        what = (
            f"sigma_z set to {cfg.unknown_height_sigma_z_m} m (planimetric control)"
            if cfg.unknown_height_sigma_z_m is not None
            else "kept at 0.0 with their sigma_z: use them for planimetry only or set "
            "IngestConfig.unknown_height_sigma_z_m"
        )
        problems.warning(
            f.path,
            f"every GCP height is 0.0 ({span}): heights are unknown, not sea level; {what}",
            "Z",
            f.first_data_line,
        )

    observations = _check_measurements(files, images, flight_xyz, problems, cfg, folder_files or set())

    gcp_rows = {k: [] for k in ("gcp_id", "X", "Y", "Z", "sigma_x", "sigma_y", "sigma_z", "role")}
    for gid in sorted(flight_xyz):
        point, f = chosen[gid]
        sxy = point.sigma_xy if point.sigma_xy is not None else cfg.gcp_sigma_xy_m
        sz = point.sigma_z if point.sigma_z is not None else cfg.gcp_sigma_z_m
        if id(f) in unknown_files and cfg.unknown_height_sigma_z_m is not None:
            sz = cfg.unknown_height_sigma_z_m
        X, Y, Z = flight_xyz[gid]
        for key, value in zip(
            gcp_rows, (gid, X, Y, Z, sxy, sxy, sz, point.role or cfg.gcp_default_role), strict=True
        ):
            gcp_rows[key].append(value)
    gcps = tables.from_columns("gcps", gcp_rows, crs=flight_crs)
    obs_rows = {
        "gcp_id": [m.gcp_id for m in observations],
        "image_id": [images[m.image].image_id for m in observations],
        "x": [m.x for m in observations],
        "y": [m.y for m in observations],
        "sigma": [cfg.gcp_pixel_sigma_px] * len(observations),
    }
    obs = tables.from_columns("gcp_observations", obs_rows, crs=flight_crs)

    observed = {m.gcp_id for m in observations}
    unobserved = [g for g in sorted(flight_xyz) if g not in observed]
    if unobserved and observations:
        where = next((f.path for f in files if f.kind != "csv"), files[0].path)
        problems.warning(
            where,
            f"{len(unobserved)} GCP(s) have no usable image measurement: {name_list(unobserved)}",
            "gcp_id",
        )
    elif flight_xyz and not observations:
        problems.warning(
            files[0].path, "no image measurement of any GCP: ground control has coordinates only", "gcp_id"
        )
    return gcps, obs


def to_flight_crs(point: GcpCoordinate, src: str, dst: str) -> np.ndarray:
    """``point``'s X, Y, Z (metres) in ``dst`` from its file's CRS ``src`` (heights are kept as they are); NaN
    where the transformation fails."""
    if src == dst:
        return np.array([point.x, point.y, point.z], dtype=float)
    try:
        x, y = transformer(src, dst).transform(point.x, point.y)
    except Exception:  # pyproj raises ProjError subclasses or returns inf depending on the case
        return np.full(3, np.nan)
    return np.array([x, y, point.z], dtype=float)


def _check_measurements(
    files: list[GcpFile],
    images: dict[str, ImageFrame],
    flight_xyz: dict[str, np.ndarray],
    problems: ProblemLog,
    cfg: IngestConfig,
    folder_files: set[str],
) -> list[GcpMeasurement]:
    kept: list[GcpMeasurement] = []
    seen: dict[tuple[str, str], GcpMeasurement] = {}
    for f in files:
        for m in f.measurements:
            if m.gcp_id not in flight_xyz:
                continue  # its coordinates were reported
            frame = images.get(m.image)
            if frame is None:
                if m.image in folder_files:  # the image's own problem says why: one, not one per line
                    problems.warning(m.file, f"image {m.image} was not ingested (skipped or left out: see its own "
                                     f"problem); measurement of {m.gcp_id} ignored", "image", m.line)
                else:
                    problems.error(m.file, f"image {m.image} is not in the image folder; measurement of {m.gcp_id} "
                                   "ignored", "image", m.line)
                continue
            if not (0.0 <= m.x <= frame.width and 0.0 <= m.y <= frame.height):
                problems.error(
                    m.file,
                    f"pixel ({m.x:.1f}, {m.y:.1f}) of {m.gcp_id} lies outside {m.image} "
                    f"({frame.width}x{frame.height}); measurement ignored",
                    "px/py",
                    m.line,
                )
                continue
            key = (m.gcp_id, m.image)
            if key in seen:
                problems.error(
                    m.file,
                    f"{m.gcp_id} is measured twice in {m.image} (line {seen[key].line} and here); "
                    "this one ignored",
                    "label",
                    m.line,
                )
                continue
            seen[key] = m
            kept.append(m)

    drop: set[int] = set()
    by_image: dict[str, list[int]] = {}
    for k, m in enumerate(kept):
        by_image.setdefault(m.image, []).append(k)
    for image, idx in by_image.items():
        if len(idx) < 2:
            continue
        uv = np.array([[kept[k].x, kept[k].y] for k in idx])
        dist = np.linalg.norm(uv[:, None, :] - uv[None, :, :], axis=2)
        close = np.argwhere(np.triu(dist < cfg.gcp_label_conflict_px, k=1))
        for a, b in close:
            ma, mb = kept[idx[a]], kept[idx[b]]
            if ma.gcp_id == mb.gcp_id:
                continue
            first, second = sorted((ma, mb), key=lambda m: (str(m.file), m.line))
            ground = float(np.linalg.norm(flight_xyz[ma.gcp_id][:2] - flight_xyz[mb.gcp_id][:2]))
            action = "both measurements dropped" if cfg.gcp_label_conflict == "drop" else "both kept"
            message = (
                f"{image}: one target carries two labels, {first.gcp_id} (line {first.line}) and "
                f"{second.gcp_id} (line {second.line}), {dist[a, b]:.1f} px apart in the image but "
                f"{ground:.1f} m apart on the "
                f"ground; {action}"
            )
            if cfg.gcp_label_conflict == "drop":
                problems.error(second.file, message, "label", second.line)
                drop.update((idx[a], idx[b]))
            else:
                problems.warning(second.file, message, "label", second.line)
    return [m for k, m in enumerate(kept) if k not in drop]
