"""Initial orientation of a block: from the recorded GNSS/IMU, or by incremental SfM where none exist.

* With a recorded position and attitude for every image, the initial poses are those records and the
  tie points are intersected from them (:func:`orient_from_priors`); the bundle adjustment refines both.
* Without them (e.g. the copr images, which carry no GNSS), :func:`orient_incremental` hands our own
  keypoints and verified matches to COLMAP's incremental mapper (pycolmap 4.x) and reads the
  reconstruction back as aerocal tables; :func:`georeference` then moves it into the flight's CRS by a
  7-parameter similarity estimated on the ground-control points triangulated in the model.

Poses follow aerocal's convention (world-to-camera quaternions, scalar first, projection centres);
pixels are COLMAP's own convention, so keypoints go to COLMAP unchanged.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pycolmap

from aerocal import tables
from aerocal.adjust.control import (
    ControlScreeningConfig,
    heights_unknown,
    intersect_gcp,
    misfit_covariance,
    plan_only,
    screen_points,
)
from aerocal.camera import Camera, to_pycolmap
from aerocal.geometry import (
    R_cw_to_opk,
    Similarity,
    attitude_to_R_cw,
    estimate_similarity,
)
from aerocal.poses import has_priors, poses_arrays, poses_table


class OrientationError(RuntimeError):
    """The block could not be oriented; the message says what was missing and what to try."""


#: COLMAP models the mapper's camera can be seeded as: f, cx, cy, k1; f_x, f_y, cx, cy; or the whole Brown model
#: (:func:`aerocal.camera.to_pycolmap`)
COLMAP_SEED_MODELS = ("SIMPLE_RADIAL", "PINHOLE", "FULL_OPENCV")


@dataclass(frozen=True)
class IncrementalConfig:
    """Options of the incremental mapper (documented defaults)."""

    min_model_size: int = 3  # smallest reconstruction kept
    refine_intrinsics: bool = False  # keep the starting camera: flat nadir blocks do not determine it
    multiple_models: bool = False  # one model; images that do not join it stay unregistered
    camera_model: str = "SIMPLE_RADIAL"  # COLMAP model seeded from the starting camera (COLMAP_SEED_MODELS)

    def __post_init__(self) -> None:
        if self.min_model_size < 2:
            raise ValueError(f"IncrementalConfig.min_model_size must be 2 or more images, got {self.min_model_size}")
        if self.camera_model not in COLMAP_SEED_MODELS:
            raise ValueError(f"IncrementalConfig.camera_model must be one of {', '.join(COLMAP_SEED_MODELS)}, got "
                             f"{self.camera_model!r}")


def orient_from_priors(images: pa.Table) -> pa.Table:
    """Initial poses from the recorded GNSS/IMU (the adjustment refines them).

    Raises:
        OrientationError: an image lacks a recorded position or attitude; use :func:`orient_incremental`.
    """
    if not has_priors(images):
        raise OrientationError("some images lack a recorded position or attitude; use orient_incremental")
    im = images.to_pydict()
    R = np.stack([attitude_to_R_cw(c, r, p, y) for c, r, p, y in
                  zip(im["attitude_convention"], im["roll"], im["pitch"], im["yaw"], strict=True)])
    C = np.column_stack([im["gnss_x"], im["gnss_y"], im["gnss_z"]]).astype(float)
    return poses_table(np.asarray(im["image_id"]), R, C, tables.crs_of(images))


def images_with_poses(images: pa.Table, poses: pa.Table) -> pa.Table:
    """The images that have a pose, their exterior orientation taken from ``poses``.

    For blocks oriented by SfM: ``gnss_x/y/z`` become the oriented projection centres (flight CRS,
    metres) and the attitude omega-phi-kappa degrees (``attitude_convention = "opk"``), so every later
    step reads one images table. These are starting values, not measurements: the adjustment of such a
    block must run without GNSS and attitude observations (``gnss_sigma_m=None``,
    ``attitude_sigma_deg=None``). Images without a pose (not registered) are left out.
    """
    ids, R, C = poses_arrays(poses)
    where = {int(k): i for i, k in enumerate(ids)}
    image_ids = images.column("image_id").to_numpy(zero_copy_only=False)
    keep = np.flatnonzero([int(i) in where for i in image_ids])
    out = images.take(pa.array(keep, pa.int64()))
    rows = np.array([where[int(i)] for i in image_ids[keep]], dtype=np.int64).reshape(-1)
    opk = np.array([R_cw_to_opk(R[k]) for k in rows]).reshape(-1, 3)
    cols = {
        "gnss_x": C[rows, 0], "gnss_y": C[rows, 1], "gnss_z": C[rows, 2],
        "roll": opk[:, 0], "pitch": opk[:, 1], "yaw": opk[:, 2],
    }
    for name, values in cols.items():
        out = out.set_column(out.schema.get_field_index(name), out.schema.field(name),
                             pa.array(values, pa.float64()))
    conv = out.schema.get_field_index("attitude_convention")
    return out.set_column(conv, out.schema.field(conv), pa.array(["opk"] * out.num_rows, pa.string()))


def _colmap_camera(camera: Camera, model: str):
    if model == "SIMPLE_RADIAL":
        params = [camera.f, camera.cx, camera.cy, camera.k1]
    elif model == "PINHOLE":
        params = [camera.f + camera.b1, camera.f, camera.cx, camera.cy]
    else:
        return to_pycolmap(camera, drop_skew=True)
    return pycolmap.Camera(model=model, width=camera.width, height=camera.height, params=params)


def orient_incremental(
    images: pa.Table,
    keypoints: pa.Table,
    matches: pa.Table,
    camera: Camera,
    config: IncrementalConfig | None = None,
    workdir: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[pa.Table, pa.Table, pa.Table]:
    """Incremental SfM on our keypoints and verified matches: (poses, points, observations) in the
    reconstruction's own frame (arbitrary datum; see :func:`georeference`).

    ``observations`` holds the registered measurements of the reconstruction's tracks (track ids are
    COLMAP's point ids).

    Raises:
        OrientationError: incremental mapping finds no initial pair; check the matches, or give GNSS/IMU priors.
    """
    config = config or IncrementalConfig()
    pycolmap.logging.minloglevel = 2  # COLMAP's own progress lines: our callback reports progress
    keypoints = tables.validate(keypoints, "keypoints", source="keypoints")
    matches = tables.validate(matches, "matches", source="matches")
    tmp = tempfile.TemporaryDirectory(prefix="aerocal-sfm-") if workdir is None else None
    work = Path(tmp.name if tmp else workdir)
    work.mkdir(parents=True, exist_ok=True)
    try:
        db_path = work / "database.db"
        if db_path.exists():
            db_path.unlink()
        db = pycolmap.Database.open(str(db_path))
        cam_id = db.write_camera(_colmap_camera(camera, config.camera_model))
        names = dict(zip(images.column("image_id").to_pylist(), images.column("name").to_pylist(), strict=True))
        kp = keypoints.to_pydict()
        kp_img = np.asarray(kp["image_id"])
        kp_id = np.asarray(kp["keypoint_id"])
        kp_xy = np.column_stack([kp["x"], kp["y"]]).astype(np.float32)
        colmap_id: dict[int, int] = {}
        row_of: dict[int, np.ndarray] = {}  # our keypoint id -> row in COLMAP's keypoint list, per image
        for image_id in names:
            sel = np.flatnonzero(kp_img == image_id)
            iid = db.write_image(pycolmap.Image(name=str(names[image_id]), camera_id=cam_id))
            colmap_id[image_id] = iid
            db.write_keypoints(iid, kp_xy[sel])
            lut = np.full(int(kp_id[sel].max()) + 1 if len(sel) else 1, -1, dtype=np.int64)
            lut[kp_id[sel]] = np.arange(len(sel))
            row_of[image_id] = lut
        m = matches.to_pydict()
        a, b = np.asarray(m["image_id1"]), np.asarray(m["image_id2"])
        ka, kb = np.asarray(m["keypoint_id1"]), np.asarray(m["keypoint_id2"])
        pairs = np.unique(np.column_stack([a, b]), axis=0) if len(a) else np.zeros((0, 2), int)
        for i1, i2 in pairs:
            sel = (a == i1) & (b == i2)
            mm = np.column_stack([row_of[i1][ka[sel]], row_of[i2][kb[sel]]]).astype(np.uint32)
            c1, c2 = colmap_id[i1], colmap_id[i2]
            if c1 > c2:
                c1, c2, mm = c2, c1, mm[:, ::-1].copy()
            db.write_matches(c1, c2, mm)
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.UNCALIBRATED
            tvg.inlier_matches = mm
            db.write_two_view_geometry(c1, c2, tvg)
        db.close()
        opts = pycolmap.IncrementalPipelineOptions()
        opts.min_model_size = config.min_model_size
        opts.multiple_models = config.multiple_models
        opts.ba_refine_focal_length = config.refine_intrinsics
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = config.refine_intrinsics
        n_total = len(names)
        registered = [0]

        def on_image() -> None:
            registered[0] += 1
            if progress:
                progress(min(registered[0], n_total), n_total)

        recs = pycolmap.incremental_mapping(str(db_path), str(work), str(work / "sparse"), options=opts,
                                            next_image_callback=on_image)
    finally:
        if tmp:
            tmp.cleanup()
    if not recs:
        raise OrientationError(
            f"incremental mapping found no initial pair among {len(names)} images ({len(pairs)} matched pairs); "
            "check the matches, or give GNSS/IMU priors")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    ours = {v: k for k, v in colmap_id.items()}
    ids, Rs, Cs = [], [], []
    obs_img, obs_trk, obs_xy = [], [], []
    for iid, image in rec.images.items():
        if not image.has_pose:
            continue
        T = image.cam_from_world()
        R = np.asarray(T.rotation.matrix())
        ids.append(ours[iid])
        Rs.append(R)
        Cs.append(-R.T @ np.asarray(T.translation))
        for p2d in image.points2D:
            if p2d.has_point3D():
                obs_img.append(ours[iid])
                obs_trk.append(p2d.point3D_id)
                obs_xy.append(np.asarray(p2d.xy))
    pts = rec.points3D
    pid = np.array(list(pts.keys()), dtype=np.int64)
    xyz = np.array([pts[k].xyz for k in pid]).reshape(-1, 3)
    err = np.array([pts[k].error for k in pid])
    n_obs = np.array([pts[k].track.length() for k in pid], dtype=np.int32)
    order = np.argsort(ids)
    poses = poses_table(np.asarray(ids)[order], np.stack(Rs)[order], np.stack(Cs)[order])
    points = tables.from_columns("points", {"track_id": pid, "X": xyz[:, 0], "Y": xyz[:, 1], "Z": xyz[:, 2],
                                            "n_obs": n_obs, "error": err})
    xy = np.asarray(obs_xy).reshape(-1, 2)
    observations = tables.from_columns("observations", {
        "image_id": np.asarray(obs_img, dtype=np.int32), "track_id": np.asarray(obs_trk, dtype=np.int64),
        "x": xy[:, 0], "y": xy[:, 1], "sigma": np.full(len(xy), 0.5, np.float32)})
    return poses, points, observations


def georeference(poses: pa.Table, camera: Camera, gcps: pa.Table, gcp_observations: pa.Table,
                 crs: str | None = None, screening: ControlScreeningConfig | None = None,
                 ) -> tuple[pa.Table, Similarity]:
    """Move a reconstruction into the flight CRS by a similarity on the intersected control points.

    The similarity is fitted on the points that pass the data snooping of
    :func:`aerocal.adjust.control.screen_points` (each point against the similarity of the others): a
    control point with wrong coordinates or a wrong label would otherwise tilt and shift the whole block.

    Raises:
        OrientationError: fewer than 3 control points are seen in at least 2 oriented images; add ground control or
            GNSS.
        ValueError: the intersected control points are collinear (:func:`aerocal.geometry.estimate_similarity`).
    """
    config = screening or ControlScreeningConfig()
    ids, R, C = poses_arrays(poses)
    index = {int(k): i for i, k in enumerate(ids)}
    g = gcps.to_pydict()
    go = gcp_observations.to_pydict()
    go_gid = np.asarray(go["gcp_id"], dtype=object)
    go_img = np.asarray(go["image_id"], dtype=np.int64)
    hits, world, survey = [], [], []
    for k, gid in enumerate(g["gcp_id"]):
        if g["role"][k] != "control":
            continue
        rows = np.flatnonzero((go_gid == gid) & np.isin(go_img, list(index)))
        if len(rows) < 2:
            continue
        pk = np.array([index[int(i)] for i in go_img[rows]])
        uv = np.column_stack([np.asarray(go["x"])[rows], np.asarray(go["y"])[rows]])
        hit = intersect_gcp(camera, R[pk], C[pk], uv, np.asarray(go["sigma"], float)[rows], go_img[rows],
                            config.measurement_limit_px)
        if hit is None:
            continue
        hits.append(hit)
        world.append([g["X"][k], g["Y"][k], g["Z"][k]])
        survey.append([g["sigma_x"][k], g["sigma_y"][k], g["sigma_z"][k]])
    if len(hits) < 3:
        raise OrientationError(
            f"georeferencing needs at least 3 control points seen in 2 oriented images, found {len(hits)}; "
            "add ground control or GNSS")
    model, world = np.stack([h.xyz for h in hits]), np.asarray(world)
    first = estimate_similarity(model, world)
    cov = misfit_covariance(hits, np.asarray(survey), camera.f, config, scale=first.scale,
                            heights_unknown=heights_unknown(world))
    tested = plan_only(first.apply(model), world) if heights_unknown(world) else first.apply(model)
    keep = screen_points(world, tested, cov, "similarity", config)[0]
    if keep.sum() < 3:
        keep[:] = True
    sim = estimate_similarity(model[keep], world[keep])
    C_w = sim.apply(C)
    R_w = np.einsum("nij,jk->nik", R, sim.R.T)  # R_cw' = R_cw S^T: p_cam = R (S^T (X - t) / s - ...)
    return poses_table(ids, R_w, C_w, crs or tables.crs_of(gcps)), sim
