"""Calibration steps: calibration sub-block, self-calibration -> certificate, and certificate choice.

* :func:`calibrate_step` (cached): the sub-block (:func:`aerocal.subset.propose_subset`, or the whole
  flight when it is no larger than ``SubsetConfig.max_images``, or the image ids given), a bundle
  adjustment with IO free and adaptive parameter selection (:func:`aerocal.adjust.adjust`), and the
  certificate document built from it (:func:`certificate_from_adjustment`).
* :func:`issue_step`: store that certificate (once: a re-run that reuses the step finds it by id).
* :func:`select_step`: ask the store for the certificate that applies to the flight
  (:func:`storage.certificates.select_certificate`); never cached, since the answer depends on what the
  store holds now.

Both record the certificate the run uses and why (:func:`storage.runs.record_certificate`) and store the
certificate document as an artifact (kind ``certificate``), the input of the block adjustment.
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from prefect import task

from aerocal.adjust import AdjustConfig, AdjustmentResult, adjust, select_images
from aerocal.camera import PARAM_NAMES, Camera, LinearThermalModel
from aerocal.certificate import (
    CameraIdentity,
    Certificate,
    Conditions,
    Correlation,
    ParameterSignificance,
    Provenance,
    Quality,
    ThermalCalibration,
)
from storage.certificates import get_certificate, issue_certificate, select_certificate
from storage.errors import NoCertificateError, NotFoundError
from storage.runs import record_certificate
from tasks.resume import JsonOutput, StepContext, StepInputs, StepResult, run_step
from tasks.retries import TASK_RETRIES, TASK_RETRY_DELAYS_S, retry_condition

#: adjustment names of thermal slopes -> certificate names (pixels per degC)
SLOPE_NAMES = {"df/dT": "df_dt", "dcx/dT": "dcx_dt", "dcy/dT": "dcy_dt"}


@dataclass(frozen=True)
class CalibrationStepConfig:
    """Self-calibration settings.

    * ``adjust``: the self-calibrating adjustment (default: f, cx, cy, k1..k3, p1, p2 free, a focal-length
      temperature slope, adaptive selection dropping insignificant or |r| > 0.95 parameters).
    * ``subset``: :class:`aerocal.subset.SubsetConfig` for :func:`~aerocal.subset.propose_subset`
      (default its defaults).
    * ``whole_flight_max_images``: a flight of at most this many images (44, Conte 2018's sub-block
      size) is calibrated whole, with no sub-block search.
    * ``subset_images``: image ids of the sub-block, chosen by hand (``None``: propose one);
      ``subset_names``: the same by image name.
    """

    adjust: AdjustConfig = field(default_factory=lambda: AdjustConfig(thermal=("f",), adaptive=True))
    subset: Any = None
    whole_flight_max_images: int = 44
    subset_images: tuple[int, ...] | None = None
    subset_names: tuple[str, ...] | None = None


def _t_from_reason(name: str, reason: str) -> float:
    m = re.search(rf"t\({re.escape(name)}\) = ([-\d.eE+]+)", reason) or re.search(
        r"\bt = ([-\d.eE+]+)", reason
    )
    return float(m.group(1)) if m else 0.0


def certificate_from_adjustment(
    cal: AdjustmentResult,
    identity: CameraIdentity,
    images: Any,
    gcp_observations: Any,
    flight: dict,
    run_id: str | None,
    inputs: dict[str, str],
    gcps: Any = None,
    transversal: bool | None = None,
) -> Certificate:
    """The certificate of a self-calibration: IO and sigmas, correlations, significance (with the reason
    each dropped parameter was dropped), the thermal model over the sub-block's temperature range, the
    conditions (date, images, strips, GCPs, priors) and quality figures."""
    io_names = [n for n in cal.names if n in PARAM_NAMES]
    names = [SLOPE_NAMES.get(n, n) for n in cal.names]
    significance: dict[str, ParameterSignificance] = {}
    for n, t in zip(cal.names, np.asarray(cal.t_values, dtype=float), strict=True):
        significance[SLOPE_NAMES.get(n, n)] = ParameterSignificance(
            float(t) if np.isfinite(t) else 0.0, bool(cal.significant.get(n, False))
        )
    for reason in cal.selection:
        m = re.match(r"dropped (\S+):", reason)
        if m:
            n = m.group(1)
            why = reason[m.end() :].strip()  # the text after "dropped NAME:"
            significance[SLOPE_NAMES.get(n, n)] = ParameterSignificance(_t_from_reason(n, reason), False, why)
    temps = np.array([t for t in images.column("temperature_c").to_pylist() if t is not None], dtype=float)
    trange = (float(temps.min()), float(temps.max())) if temps.size else None
    thermal = None
    if isinstance(cal.thermal, LinearThermalModel) and trange is not None:
        model = dataclasses.replace(cal.thermal, valid_range=trange)
        thermal = ThermalCalibration(
            model, {SLOPE_NAMES.get(k, k): float(v) for k, v in cal.thermal_sigmas.items()}
        )
    if thermal is None:  # a slope dropped as insignificant leaves no thermal model to attach it to
        significance = {n: s for n, s in significance.items() if n not in SLOPE_NAMES.values()}
    cfg = cal.config
    priors = {}
    if cfg.gnss_sigma_m is not None:
        priors["gnss_position_m"] = float(max(cfg.gnss_sigma_m))
    if cfg.attitude_sigma_deg is not None:
        priors["imu_attitude_deg"] = float(max(cfg.attitude_sigma_deg))
    gcp_ids = set(gcp_observations.column("gcp_id").to_pylist()) if gcp_observations is not None else set()
    if gcps is not None:  # only control points enter the adjustment; check points are held out
        roles = dict(zip(gcps.column("gcp_id").to_pylist(), gcps.column("role").to_pylist(), strict=True))
        gcp_ids = {g for g in gcp_ids if roles.get(g) == "control"}
    return Certificate(
        identity=identity,
        camera=cal.camera,
        sigmas={n: float(cal.sigmas[n]) for n in io_names},
        estimated=tuple(io_names),
        correlation=Correlation(tuple(names), np.asarray(cal.correlation, dtype=float)),
        significance=significance,
        thermal=thermal,
        conditions=Conditions(
            date=flight.get("date"),
            temperature_range=trange,
            n_images=images.num_rows,
            strips=len(set(images.column("strip").to_pylist())),
            transversal_strip=transversal,
            n_gcp=len(gcp_ids) if cfg.use_gcps else 0,
            priors=priors,
            images=tuple(images.column("name").to_pylist()),
        ),
        quality=Quality(float(cal.sigma0), float(cal.reprojection_rms), int(cal.dof)),
        provenance=Provenance(flow_run=run_id, inputs=inputs),
    )


def calibrate_step(
    ctx: StepContext,
    ingest: StepResult,
    observations: str,
    config: CalibrationStepConfig | None = None,
    adjust_config: AdjustConfig | None = None,
) -> StepResult:
    """Choose the calibration sub-block, self-calibrate on it and build the certificate document.

    Outputs: ``certificate`` (the document, not yet stored), ``calibration`` (the adjustment's summary,
    the sub-block and why it was chosen). ``adjust_config`` overrides ``config.adjust`` (e.g. with the
    flight's declared GNSS sigmas).
    """
    config = config or CalibrationStepConfig()
    acfg = adjust_config or config.adjust
    inputs = {
        "images": ingest["images"],
        "observations": observations,
        "gcps": ingest["gcps"],
        "gcp_observations": ingest["gcp_observations"],
        "camera": ingest["camera"],
        "flight": ingest["flight"],
    }

    def compute(inp: StepInputs) -> dict:
        images, obs = inp.table("images"), inp.table("observations")
        gcps, gobs = inp.table("gcps"), inp.table("gcp_observations")
        cam_doc, flight = inp.json("camera"), inp.json("flight")
        camera = Camera.from_dict(cam_doc["camera"])
        subset_info: dict[str, Any]
        transversal = None
        if config.subset_names is not None:
            by_name = dict(
                zip(images.column("name").to_pylist(), images.column("image_id").to_pylist(), strict=True)
            )
            unknown = [n for n in config.subset_names if n not in by_name]
            if unknown:
                raise ValueError(
                    f"calibration sub-block: images {unknown[:5]} are not in the flight; give names "
                    "of the flight's images"
                )
            ids = [int(by_name[n]) for n in config.subset_names]
            subset_info = {"image_ids": ids, "reasons": ["sub-block given by the user (image names)"]}
        elif config.subset_images is not None:
            ids = [int(i) for i in config.subset_images]
            subset_info = {"image_ids": ids, "reasons": ["sub-block given by the user"]}
        elif images.num_rows <= config.whole_flight_max_images:
            ids = images.column("image_id").to_pylist()
            subset_info = {
                "image_ids": ids,
                "reasons": [
                    f"the flight has {images.num_rows} images, no more than whole_flight_max_images = "
                    f"{config.whole_flight_max_images}: it is calibrated whole"
                ],
            }
        else:
            from aerocal.subset import SubsetConfig, propose_subset

            scfg = config.subset or SubsetConfig()
            if scfg.height_agl_m is None and flight.get("height_agl_m"):
                scfg = dataclasses.replace(scfg, height_agl_m=float(flight["height_agl_m"]))
            prop = propose_subset(images, camera, gcps, scfg)
            ids, transversal = prop.image_ids, prop.transversal
            subset_info = {
                "image_ids": ids,
                "strips": prop.strips,
                "transversal": prop.transversal,
                "gcp_ids": prop.gcp_ids,
                "predicted_sigmas": prop.predicted_sigmas,
                "score": prop.score,
                "reasons": prop.reasons,
            }
        known = set(images.column("image_id").to_pylist())
        missing = sorted(set(ids) - known)
        if missing:
            raise ValueError(
                f"calibration sub-block: image ids {missing[:5]} are not in the flight; "
                "give ids of the images table"
            )
        sub_images = select_images(images, ids)
        sub_gobs = select_images(gobs, ids)
        run_cfg = acfg
        temps = sub_images.column("temperature_c").to_numpy(zero_copy_only=False).astype(float)
        if acfg.thermal and not np.isfinite(temps).all():
            # a temperature slope cannot be estimated without every image's sensor temperature
            run_cfg = dataclasses.replace(acfg, thermal=())
            subset_info["thermal"] = (
                f"thermal slopes {list(acfg.thermal)} not estimated: {int(np.sum(~np.isfinite(temps)))} of "
                f"{len(temps)} sub-block images have no sensor temperature"
            )
        cal = adjust(sub_images, select_images(obs, ids), camera, run_cfg, gcps, sub_gobs)
        identity = CameraIdentity(
            **{
                k: str(cam_doc.get("identity", {}).get(k) or "unknown")
                for k in ("make", "model", "serial", "lens")
            }
        )
        cert = certificate_from_adjustment(
            cal,
            identity,
            sub_images,
            sub_gobs,
            flight,
            ctx.run_id,
            dict(inp.shas),
            transversal=transversal,
            gcps=gcps,
        )
        return {
            "certificate": JsonOutput(cert.to_dict(), "certificate"),
            "calibration": JsonOutput(
                {
                    "subset": subset_info,
                    "adjustment": cal.summary(),
                    "high_correlations": cert.correlation.high_pairs(0.9),
                },
                "calibration",
            ),
            "_extra": JsonOutput({"certificate_id": cert.id}, "extra"),
        }

    return run_step(ctx, "calibrate", inputs, {"config": config, "adjust": acfg}, compute)


def _store_document(ctx: StepContext, session, document: dict) -> str:
    import json

    data = json.dumps(document, sort_keys=True, indent=1).encode()
    return ctx.store.put_bytes(session, data, "certificate", "json", run_id=ctx.run_id).sha256


def issue_step(ctx: StepContext, calibration: StepResult) -> tuple[str, str, str]:
    """Store the calibration's certificate (once) and record it as the run's certificate.

    Returns (certificate id, SHA-256 of the stored document artifact, reason).
    """
    import json

    with ctx.database.session() as session:
        art = ctx.store.get(session, calibration["certificate"])
        document = json.loads(ctx.store.read_bytes(art))
        try:
            stored = get_certificate(session, document["id"])
            reason = f"made by this flight's self-calibration (run {calibration.computed_by}), issued before"
        except NotFoundError:
            stored = issue_certificate(session, document)
            reason = "made by this flight's self-calibration"
        reason += f"; version {stored.version} of camera {stored.camera.make} {stored.camera.model}"
        sha = _store_document(ctx, session, stored.document)
        record_certificate(session, ctx.run_id, stored.id, reason)
        session.commit()
        return stored.id, sha, reason


def select_step(
    ctx: StepContext, ingest: StepResult, pin: str | None = None, max_age_days: float | None = None
) -> tuple[str, str, str] | None:
    """The stored certificate that applies to the flight (or the one pinned by id), recorded on the run;
    ``None`` when no stored certificate qualifies (unless pinned: then the store's error propagates)."""
    import json

    with ctx.database.session() as session:
        cam_doc = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["camera"])))
        flight = json.loads(ctx.store.read_bytes(ctx.store.get(session, ingest["flight"])))
        identity = CameraIdentity(
            **{
                k: str(cam_doc.get("identity", {}).get(k) or "unknown")
                for k in ("make", "model", "serial", "lens")
            }
        )
        try:
            cert, reason = select_certificate(
                session,
                identity.key,
                flight["date"],
                flight.get("temperature_range"),
                max_age_days=max_age_days,
                pin=pin,
                run_id=ctx.run_id,
            )
        except NoCertificateError:
            if pin:
                raise
            return None
        sha = _store_document(ctx, session, cert.document)
        record_certificate(session, ctx.run_id, cert.id, reason)
        session.commit()
        return cert.id, sha, reason


_RETRY = {
    "retries": TASK_RETRIES,
    "retry_delay_seconds": TASK_RETRY_DELAYS_S,
    "retry_condition_fn": retry_condition,
}

calibrate_task = task(calibrate_step, name="self-calibrate", **_RETRY)
issue_task = task(issue_step, name="issue-certificate", **_RETRY)
select_task = task(select_step, name="select-certificate", **_RETRY)
