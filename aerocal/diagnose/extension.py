"""The model terms a diagnosis adds to a block, and how each reaches a flight's tables and its certificate.

An effect that passes the decision rule (:mod:`aerocal.diagnose.engine`: determined, significant against the
block's own null, and a gain on images the fit did not use) becomes part of the block's model. This module holds
the named effects as data (:class:`ModelTerm`) and applies them:

* **camera terms** belong to the camera and go into its next certificate (:func:`extend_certificate`):
  ``affinity_skew`` and ``radial_k3`` are parameters of the Brown model (b1, b2, k3), ``thermal_focal`` and
  ``thermal_principal_point`` slopes of the certificate's linear thermal model; a ``rolling_shutter`` readout and a
  ``thermal_rotation`` have no Brown parameter and correct the image measurements at the adjusted geometry
  (Daakir 2019's way: the measurements, not the pixels), wherever the certificate is used
  (:func:`measurement_terms`, :func:`remove_image_terms`);
* **block terms** belong to this flight's records (:func:`apply_block_terms`): ``gnss_bias``,
  ``gnss_time_offset`` and ``lever_arm`` correct the recorded positions, ``boresight`` the recorded attitudes,
  ``refraction`` the image measurements.

The corrections are the diagnosis's own signatures (:func:`aerocal.diagnose.hypotheses.signature`) evaluated at
the adjusted poses and points, so that what is removed from the data is exactly what was estimated.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import uuid
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from aerocal.camera import Camera, LinearThermalModel
from aerocal.certificates.document import CameraTerm, Certificate, ParameterSignificance, ThermalCalibration
from aerocal.certificates.schema import CAMERA_TERMS
from aerocal.diagnose import hypotheses as hyp
from aerocal.diagnose.model import image_strips, image_times_s, point_geometry
from aerocal.effects import CATALOGUE, bertram_refraction_k, image_rotation, thermal_rotation_angle
from aerocal.geometry import R_cw_to_body_rpy, R_cw_to_dji_gimbal, R_cw_to_opk, attitude_to_R_cw, small_rotation
from aerocal.poses import poses_arrays

#: terms of the records of one flight (not of its camera)
BLOCK_TERMS = ("gnss_bias", "gnss_time_offset", "lever_arm", "boresight", "refraction")
#: camera terms with no parameter in the Brown or linear thermal model: applied to the measurements
MEASUREMENT_TERMS = ("rolling_shutter", "thermal_rotation")
#: image-side terms whose correction :func:`remove_image_terms` makes
IMAGE_TERMS = ("rolling_shutter", "thermal_rotation", "refraction", "affinity_skew", "radial_k3", "thermal_focal",
               "thermal_principal_point")


@dataclass(frozen=True)
class ModelTerm:
    """One named effect as a term of the block's model: its catalogue ``name``, ``values`` and ``sigmas`` (in the
    catalogue's units), and the ``evidence`` that it predicts data the fit did not use, in words."""

    name: str
    values: tuple[float, ...]
    sigmas: tuple[float, ...]
    evidence: str = ""
    reference_temperature: float | None = None  # degC, of a thermal term (its slopes are relative to it)

    def __post_init__(self) -> None:
        if self.name not in CATALOGUE:
            raise ValueError(f"model term {self.name!r} is not an effect of the catalogue; valid: "
                             f"{', '.join(CATALOGUE)}")
        object.__setattr__(self, "values", tuple(float(v) for v in self.values))
        object.__setattr__(self, "sigmas", tuple(float(v) for v in self.sigmas))
        if len(self.values) != CATALOGUE[self.name].size or len(self.sigmas) != len(self.values):
            raise ValueError(f"model term {self.name}: {CATALOGUE[self.name].size} value(s) and as many sigmas "
                             f"expected, got {len(self.values)} and {len(self.sigmas)}")

    @property
    def units(self) -> str:
        return CATALOGUE[self.name].units

    @property
    def belongs_to_camera(self) -> bool:
        return self.name in CAMERA_TERMS

    def text(self) -> str:
        """``"rolling_shutter 0.0101 +- 0.00025 s"``."""
        values = ", ".join(f"{v:.4g}" for v in self.values)
        sigmas = ", ".join(f"{v:.2g}" for v in self.sigmas)
        return f"{self.name} {values} +- {sigmas} {self.units}"

    def to_dict(self) -> dict:
        return {"name": self.name, "values": list(self.values), "sigmas": list(self.sigmas), "units": self.units,
                "evidence": self.evidence, "reference_temperature": self.reference_temperature}

    @classmethod
    def from_dict(cls, d: dict) -> ModelTerm:
        return cls(d["name"], tuple(d["values"]), tuple(d["sigmas"]), d.get("evidence") or "",
                   d.get("reference_temperature"))


def terms_of_diagnosis(doc: dict) -> tuple[ModelTerm, ...]:
    """The model terms of a diagnosis document (:meth:`aerocal.diagnose.engine.Diagnosis.to_dict`): its named
    effects of the catalogue, each with its held-out evidence (IO offsets per strip, a symptom, are named but have
    no term)."""
    out = []
    t_ref = doc.get("reference_temperature")
    for e in doc.get("effects") or []:
        if e["name"] not in CATALOGUE:  # per-strip IO: a symptom the block's model has no term for
            continue
        values = e["magnitude"] if isinstance(e["magnitude"], list) else [e["magnitude"]]
        sigmas = e["sigma"] if isinstance(e["sigma"], list) else [e["sigma"]]
        thermal = CATALOGUE[e["name"]].depends_on == ("temperature",)
        out.append(ModelTerm(e["name"], tuple(values), tuple(sigmas), evidence_text(e), t_ref if thermal else None))
    return tuple(out)


def evidence_text(effect: dict) -> str:
    """The evidence of a named effect (a diagnosis document's entry) in words: its gain on held-out images and on
    the check points."""
    parts = []
    held = effect.get("held_out") or {}
    if held.get("gain") is not None:
        parts.append(f"held-out gain {100 * held['gain']:+.2f} +- {100 * (held.get('sigma') or 0):.2f} % on "
                     f"{held.get('n_images')} images ({held.get('units')})")
    check = effect.get("check_points") or {}
    if check.get("gain") is not None:
        parts.append(f"check points {100 * check['gain']:+.1f} +- {100 * (check.get('sigma') or 0):.1f} % of their "
                     "squared error")
    excess = max((effect.get("fold_dispersion") or {}).get("excess") or [1.0])
    if excess > 1.0:
        parts.append(f"its folds' estimates scatter {excess ** 0.5:.1f}x their formal sigmas: its sigma widened so")
    return "; ".join(parts) or "named by the diagnosis"


# ----------------------------------------------------------------------------------------- geometry of tables
@dataclass(frozen=True)
class TableGeometry:
    """What the signatures need of a table of image measurements at an adjusted block: per measurement its image's
    index into ``R``/``C`` (-1 where the image has no pose) and (xn, pc, duv_dpc); per posed image its
    :class:`~aerocal.diagnose.hypotheses.Context` (temperatures, velocities, refraction constants)."""

    image: np.ndarray
    xn: np.ndarray
    pc: np.ndarray
    duv_dpc: np.ndarray
    R: np.ndarray
    strip: np.ndarray
    ctx: hyp.Context


def table_geometry(images: pa.Table, image_id: np.ndarray, uv: np.ndarray, X: np.ndarray, camera: Camera,
                   poses: pa.Table, points_z: float, t_ref: float) -> TableGeometry:
    """:class:`TableGeometry` of measurements ``uv`` (M, 2) in images ``image_id`` (M,) of points ``X`` (M, 3,
    world metres; NaN where unknown: the point is then put on the measured ray at the image's median depth of
    the others, or at the height ``points_z``), at the adjusted ``poses``; temperatures relative to ``t_ref``."""
    ids, R, C = poses_arrays(poses)
    origin = C.mean(axis=0) if len(C) else np.zeros(3)
    C = C - origin
    pos = {int(v): k for k, v in enumerate(ids)}
    img = np.array([pos.get(int(i), -1) for i in image_id], dtype=np.int64)
    ok = img >= 0
    Xl = np.asarray(X, dtype=float) - origin
    missing = ok & ~np.isfinite(Xl).all(axis=1)
    if missing.any():
        rays = camera.unproject(np.asarray(uv, dtype=float)[missing])
        d_cam = np.column_stack([rays, np.ones(len(rays))])
        i = img[missing]
        d = np.einsum("mba,mb->ma", R[i], d_cam)  # R^T d: the ray in the world frame
        depth = _median_depths(R, C, img, Xl, ok & ~missing, len(ids))
        fallback = (C[i, 2] - (points_z - origin[2])) / np.maximum(-d[:, 2], 1e-6)
        scale = np.where(np.isfinite(depth[i]), depth[i], fallback)
        Xl[missing] = C[i] + d * scale[:, None]
    gi = np.where(ok, img, 0)
    xn, pc, duv = point_geometry(camera.params(), np.zeros(3), R, C, gi, np.nan_to_num(Xl))
    meta = _image_rows(images, ids)
    T = meta["temperature"]
    dT = np.where(np.isfinite(T), T - t_ref, 0.0)
    V = hyp.velocities(C, meta["time"], meta["strip"])
    K = np.array([bertram_refraction_k(float(c + origin[2]), points_z) for c in C[:, 2]])
    ctx = hyp.Context(dT=dT, t_ref=float(t_ref), velocity=V, refraction_k=K, strips=np.zeros(0, np.int64))
    return TableGeometry(img, xn, pc, duv, R, meta["strip"], ctx)


def _median_depths(R: np.ndarray, C: np.ndarray, img: np.ndarray, X: np.ndarray, known: np.ndarray,
                   n: int) -> np.ndarray:
    """Per image the median depth (metres along the optical axis) of its measurements of known points."""
    out = np.full(n, np.nan)
    if not known.any():
        return out
    i = img[known]
    z = np.einsum("mb,mb->m", R[i, 2], X[known] - C[i])
    order = np.argsort(i, kind="stable")
    i, z = i[order], z[order]
    starts = np.flatnonzero(np.r_[True, np.diff(i) != 0])
    for a, b in zip(starts, np.r_[starts[1:], len(i)], strict=True):
        out[i[a]] = float(np.median(z[a:b]))
    return out


def _image_rows(images: pa.Table, ids: np.ndarray) -> dict[str, np.ndarray]:
    """Temperature, time (s) and strip of each image of ``ids``, from the images table."""
    rows = {int(v): k for k, v in enumerate(images.column("image_id").to_numpy())}
    at = np.array([rows[int(v)] for v in ids], dtype=np.int64)
    T = images.column("temperature_c").to_numpy(zero_copy_only=False).astype(float)[at]
    secs = image_times_s(images)
    t = (secs if secs is not None else np.arange(images.num_rows, dtype=float))[at]
    return {"temperature": T, "time": t, "strip": image_strips(images)[at]}


# ----------------------------------------------------------------------------------------- corrections
def remove_image_terms(terms: tuple[ModelTerm, ...], images: pa.Table, observations: pa.Table | None,
                       gcp_observations: pa.Table | None, gcps: pa.Table | None, camera: Camera, poses: pa.Table,
                       points: pa.Table, t_ref: float) -> tuple[pa.Table | None, pa.Table | None]:
    """The tie and GCP measurements with the image-side ``terms`` removed (:data:`IMAGE_TERMS`; others ignored),
    each at the adjusted ``poses`` and ``points`` (GCPs at their surveyed positions), ``camera`` the IO at
    ``t_ref`` (degC). Measurements of images without a pose are returned as they were."""
    image_terms = [t for t in terms if t.name in IMAGE_TERMS]
    if not image_terms:
        return observations, gcp_observations
    p = points.to_pydict() if points is not None else {"track_id": [], "X": [], "Y": [], "Z": []}
    z = float(np.median(p["Z"])) if len(p["Z"]) else 0.0
    out = []
    if observations is not None and observations.num_rows:
        pos = {int(t): k for k, t in enumerate(p["track_id"])}
        P = np.column_stack([p["X"], p["Y"], p["Z"]]) if len(p["X"]) else np.zeros((0, 3))
        at = np.array([pos.get(int(t), -1) for t in observations.column("track_id").to_numpy()], dtype=np.int64)
        X = np.where((at >= 0)[:, None], P[np.maximum(at, 0)] if len(P) else np.nan, np.nan)
        out.append(_corrected(image_terms, images, observations, X, camera, poses, z, t_ref))
    else:
        out.append(observations)
    if gcp_observations is not None and gcp_observations.num_rows:
        X = np.full((gcp_observations.num_rows, 3), np.nan)
        if gcps is not None and gcps.num_rows:
            g = gcps.to_pydict()
            where = {gid: k for k, gid in enumerate(g["gcp_id"])}
            for r, gid in enumerate(gcp_observations.column("gcp_id").to_pylist()):
                if gid in where:
                    k = where[gid]
                    X[r] = (g["X"][k], g["Y"][k], g["Z"][k])
        out.append(_corrected(image_terms, images, gcp_observations, X, camera, poses, z, t_ref))
    else:
        out.append(gcp_observations)
    return out[0], out[1]


def _corrected(terms: list[ModelTerm], images: pa.Table, table: pa.Table, X: np.ndarray, camera: Camera,
               poses: pa.Table, points_z: float, t_ref: float) -> pa.Table:
    uv = np.column_stack([table.column("x").to_numpy(), table.column("y").to_numpy()]).astype(float)
    geo = table_geometry(images, table.column("image_id").to_numpy(), uv, X, camera, poses, points_z, t_ref)
    ok = geo.image >= 0
    shift = np.zeros_like(uv)
    gi = np.where(ok, geo.image, 0)
    for term in terms:
        ctx = geo.ctx
        if term.reference_temperature is not None:  # a thermal term is relative to its own reference temperature
            ctx = dataclasses.replace(ctx, dT=ctx.dT + (ctx.t_ref - term.reference_temperature))
        J = hyp.signature(term.name, camera, geo.R, geo.strip, ctx, gi, geo.xn, geo.pc, geo.duv_dpc)
        shift += np.einsum("mak,k->ma", J, np.asarray(term.values))
    shift[~ok] = 0.0
    shift = np.nan_to_num(shift)
    new = uv - shift
    out = table.set_column(table.schema.get_field_index("x"), table.schema.field("x"), pa.array(new[:, 0]))
    return out.set_column(out.schema.get_field_index("y"), out.schema.field("y"), pa.array(new[:, 1]))


def apply_block_terms(terms: tuple[ModelTerm, ...], images: pa.Table, poses: pa.Table) -> pa.Table:
    """``images`` with the record terms of ``terms`` removed from the recorded positions (``gnss_bias``: a constant
    offset; ``gnss_time_offset``: each position moved back along its track by the adjusted velocity times the lag;
    ``lever_arm``: the antenna offset turned by the adjusted attitude) and the recorded attitudes (``boresight``:
    ``R_rec <- Rot(boresight) R_rec``, written back in each image's convention). Images without a pose keep their
    records where a term needs the adjusted geometry."""
    record = [t for t in terms if t.name in ("gnss_bias", "gnss_time_offset", "lever_arm", "boresight")]
    if not record:
        return images
    ids, R, C = poses_arrays(poses)
    at = {int(v): k for k, v in enumerate(ids)}
    img_ids = images.column("image_id").to_numpy()
    rows = np.array([at.get(int(v), -1) for v in img_ids], dtype=np.int64)
    posed = rows >= 0
    meta = _image_rows(images.filter(pa.array(posed)), ids[rows[posed]]) if posed.any() else None
    G = np.column_stack([images.column(c).to_numpy(zero_copy_only=False).astype(float)
                         for c in ("gnss_x", "gnss_y", "gnss_z")])
    for term in record:
        v = np.asarray(term.values, dtype=float)
        if term.name == "gnss_bias":
            G -= v
        elif term.name == "gnss_time_offset" and meta is not None:
            Cp = C[rows[posed]]
            V = hyp.velocities(Cp - Cp.mean(axis=0), meta["time"], meta["strip"])
            G[posed] -= V * v[0]
        elif term.name == "lever_arm" and posed.any():
            G[posed] -= np.einsum("nji,j->ni", R[rows[posed]], v)
    out = images
    for k, name in enumerate(("gnss_x", "gnss_y", "gnss_z")):
        i = out.schema.get_field_index(name)
        out = out.set_column(i, out.schema.field(i), pa.array(G[:, k], out.schema.field(i).type))
    for term in record:
        if term.name == "boresight":
            out = turn_recorded_attitudes(out, small_rotation(np.radians(np.asarray(term.values, dtype=float))))
    return out


def turn_recorded_attitudes(images: pa.Table, B: np.ndarray) -> pa.Table:
    """``images`` with every recorded attitude turned about the camera axes by ``B`` (3, 3):
    ``R_rec <- B R_rec`` (the convention of ``boresight``, :mod:`aerocal.effects`), written back in each image's
    angle convention; images without a recorded attitude keep none."""
    conv = images.column("attitude_convention").to_pylist()
    att = np.column_stack([images.column(c).to_numpy(zero_copy_only=False).astype(float)
                           for c in ("roll", "pitch", "yaw")])
    for k in range(len(conv)):
        if conv[k] is None or not np.isfinite(att[k]).all():
            continue
        att[k] = _angles(conv[k], B @ attitude_to_R_cw(conv[k], *att[k]))
    out = images
    for k, name in enumerate(("roll", "pitch", "yaw")):
        i = out.schema.get_field_index(name)
        out = out.set_column(i, out.schema.field(i), pa.array(att[:, k], out.schema.field(i).type))
    return out


def _angles(convention: str, R: np.ndarray) -> tuple[float, float, float]:
    """The angles of rotation ``R`` (world-to-camera) in ``convention`` (:data:`aerocal.geometry.CONVENTIONS`)."""
    inverse = {"opk": R_cw_to_opk, "dji_gimbal": R_cw_to_dji_gimbal, "body_rpy": R_cw_to_body_rpy}
    return inverse[convention](R)


# ----------------------------------------------------------------------------------------- certificates
def measurement_terms(cert: Certificate) -> tuple[ModelTerm, ...]:
    """The camera terms of ``cert`` applied to the measurements (:data:`MEASUREMENT_TERMS`: a readout, a thermal
    rotation), as model terms."""
    return tuple(ModelTerm(name, t.values, t.sigmas, t.evidence, t.reference_temperature)
                 for name, t in cert.terms.items() if t.applied == "measurements" and name in MEASUREMENT_TERMS)


def frame_terms(cert: Certificate, images: pa.Table, poses: pa.Table) -> tuple[dict[int, np.ndarray] | None,
                                                                            dict[int, np.ndarray] | None]:
    """What the certificate's measurement terms make of each adjusted frame, for the products that project the
    ground into the frames (:func:`aerocal.products.mosaic.frames_from_poses`): per image id the readout's
    displacement of the projection centre (velocity from the adjusted neighbours x readout; ``motion``) and the
    thermal rotation about the camera axis (``turn``); None where the certificate has no such term."""
    terms = {t.name: t for t in measurement_terms(cert)}
    if not terms:
        return None, None
    ids, R, C = poses_arrays(poses)
    meta = _image_rows(images, ids)
    motion = turn = None
    if "rolling_shutter" in terms:
        V = hyp.velocities(C - C.mean(axis=0), meta["time"], meta["strip"])
        motion = {int(i): V[k] * terms["rolling_shutter"].values[0] for k, i in enumerate(ids)}
    if "thermal_rotation" in terms:
        t = terms["thermal_rotation"]
        dT = np.nan_to_num(meta["temperature"] - (t.reference_temperature or 0.0))
        theta = thermal_rotation_angle(t.values[0], dT, cert.camera.corner_radius)
        turn = {int(i): image_rotation(float(a)) for i, a in zip(ids, theta, strict=True)}
    return motion, turn


def extend_certificate(cert: Certificate, terms: tuple[ModelTerm, ...], flight: str,
                       t_ref: float | None = None) -> Certificate:
    """A new certificate (unnumbered: the store numbers it) of ``cert``'s camera with the camera ``terms`` found on
    ``flight`` added: b1, b2 and k3 to the Brown model (their sigmas recorded), the slopes to its linear thermal
    model (made at ``t_ref`` where it has none), a readout or a thermal rotation as terms applied to the
    measurements; every term in ``effects`` with its evidence and the flights that support it (a term the
    certificate already holds: the sum, the new sigma, and both flights). ``cert`` itself is unchanged."""
    camera_terms = [t for t in terms if t.belongs_to_camera]
    if not camera_terms:
        return cert
    cam = cert.camera
    sigmas = dict(cert.sigmas)
    estimated = list(cert.estimated)
    thermal = cert.thermal
    records = dict(cert.terms)
    notes = []
    for t in camera_terms:
        v = t.values
        applied = "measurements" if t.name in MEASUREMENT_TERMS else "model"
        if t.name == "affinity_skew":
            cam = cam.replace(b1=cam.b1 + v[0], b2=cam.b2 + v[1])
            for name, s in zip(("b1", "b2"), t.sigmas, strict=True):
                sigmas[name] = s
                if name not in estimated:
                    estimated.append(name)
        elif t.name == "radial_k3":
            cam = cam.replace(k3=cam.k3 + v[0])
            sigmas["k3"] = t.sigmas[0]
            if "k3" not in estimated:
                estimated.append("k3")
        elif t.name in ("thermal_focal", "thermal_principal_point"):
            thermal = _add_slopes(thermal, t, cert, t_ref)
        old = records.get(t.name)
        values = tuple(np.add(old.values, v)) if old is not None and applied == "measurements" else v
        flights = (*old.flights, flight) if old is not None else (flight,)
        records[t.name] = CameraTerm(values, t.sigmas, t.units, applied, flights, t.evidence,
                                     t.reference_temperature)
        notes.append(f"{t.text()} added from the diagnosis of flight {flight} ({t.evidence})")
    review = cert.review.merged(notes=notes) if cert.review is not None else None
    # a parameter the self-calibration dropped (k3 correlated with k2, b1 and b2 without gain) and the diagnosis
    # then found is estimated now: its significance is the diagnosis's, no longer a drop
    significance = dict(cert.significance)
    for name in set(estimated) - set(cert.estimated):
        value, sigma = float(getattr(cam, name)), float(sigmas[name])
        t = value / sigma if sigma > 0 else float("inf")
        significance[name] = ParameterSignificance(t=t, significant=bool(abs(t) > 1.96))
    return dataclasses.replace(cert, camera=cam, sigmas=sigmas, estimated=tuple(estimated), thermal=thermal,
                               terms=records, review=review, significance=significance, id=_new_id(), issued=_now(),
                               version=None, supersedes=None)


def _add_slopes(thermal: ThermalCalibration | None, term: ModelTerm, cert: Certificate,
                t_ref: float | None) -> ThermalCalibration | None:
    model = cert.linear_thermal
    if thermal is not None and model is None:
        raise ValueError(f"certificate {cert.id} holds a {thermal.kind} thermal model; a linear slope is not added "
                         "to it")
    if model is None:
        if t_ref is None:
            raise ValueError("a thermal slope needs the reference temperature it was estimated at")
        model = LinearThermalModel(t0=float(t_ref))
    s = dict(thermal.sigmas) if thermal is not None else {}
    if term.name == "thermal_focal":
        model = dataclasses.replace(model, df_dt=model.df_dt + term.values[0])
        s["df_dt"] = term.sigmas[0]
    else:
        model = dataclasses.replace(model, dcx_dt=model.dcx_dt + term.values[0], dcy_dt=model.dcy_dt + term.values[1])
        s["dcx_dt"], s["dcy_dt"] = term.sigmas
    return ThermalCalibration(model, s)


def _new_id() -> str:
    return uuid.uuid4().hex


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)
