"""The report step: the self-contained HTML report and its ``summary.json`` (:func:`aerocal.report.write_report`):
the block with check-point residuals, reprojection residuals over the image, the IO each image was adjusted
with against its sensor temperature, the DSM minus a reference surface (when the flight folder holds one,
:data:`aerocal.pipeline.dataset.REFERENCE_DSM`) and the certificate."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from aerocal.certificate import Certificate
from aerocal.dsm import read_dsm
from aerocal.ingest.problems import name_list
from aerocal.pipeline.config import ReportStepConfig
from aerocal.pipeline.dataset import REFERENCE_DSM
from aerocal.pipeline.mosaic_step import reference_dsm_path
from aerocal.pipeline.runner import FileOutput, Runner, StepInputs, StepResult
from aerocal.report.figures import block_figure
from aerocal.report.flight import (
    FigureSkipped,
    dem_difference_for_flight,
    image_residuals_from_assessment,
    temperature_io_for_flight,
)
from aerocal.report.html import CertificateTable, write_report


def _thermal(cert: Certificate):
    return None if cert.thermal is None else cert.thermal.model


def _skipped_text(names: list[str]) -> str:
    """``"none"`` or ``"3: a.jpg, b.jpg, c.jpg (see the ingest errors)"``."""
    return f"{len(names)}: {name_list(names)} (see the ingest errors)" if names else "none"


def _check_point_block(poses, adj: dict, gcps):
    """The block figure: camera centres and the check-point residuals of the adjustment."""
    centres = np.column_stack([poses.column("X").to_numpy(), poses.column("Y").to_numpy()])
    ids = adj.get("check_ids") or []
    if not ids:
        return block_figure(centres)
    where = {
        g: (x, y)
        for g, x, y in zip(
            gcps.column("gcp_id").to_pylist(),
            gcps.column("X").to_pylist(),
            gcps.column("Y").to_pylist(),
            strict=True,
        )
    }
    en = np.array([where[i] for i in ids], dtype=float)
    errs = np.asarray(adj["check_errors_m"], dtype=float).reshape(-1, 3)
    return block_figure(centres, points_en=en, residuals=errs, ids=ids)


def _screening_text(screening: dict) -> str:
    """One line of what the ground-control screening found (:mod:`aerocal.adjust.control`)."""
    if screening.get("datum") == "none":
        return "; ".join(screening.get("notes") or []) or "none"
    verdicts = screening.get("verdicts") or []
    kept = sum(v["status"] == "kept" for v in verdicts)
    untested = sum(v["status"] == "not tested" for v in verdicts)
    head = f"{kept} point(s) consistent with the block, {len(screening.get('demoted') or [])} demoted, " \
           f"{untested} not testable"
    return "; ".join([head] + list(screening.get("lines") or []))


def report_step(
    runner: Runner,
    ingest: StepResult,
    certificate: str,
    adjusted: StepResult,
    mosaic: StepResult,
    assessment: StepResult,
    diagnosis: StepResult,
    config: ReportStepConfig | None = None,
) -> StepResult:
    """Outputs ``report`` (self-contained HTML) and ``report_summary`` (its numbers as JSON).

    Inputs beyond the step outputs: the flight folder's reference DSM (:data:`REFERENCE_DSM`), when it
    exists, is stored as an artifact (kind ``reference-dsm``) and keys the step by its content; without
    one the report says that the DSM was not compared.
    """
    config = config or ReportStepConfig()
    inputs = {
        "flight": ingest["flight"],
        "images": ingest["images"],
        "certificate": certificate,
        "adjustment": adjusted["adjustment"],
        "poses": adjusted["poses"],
        "points": adjusted["points"],
        "dsm": mosaic["dsm"],
        "mosaic": mosaic["mosaic"],
        "assessment": assessment["assessment"],
        "diagnosis": diagnosis["diagnosis"],
        "gcps": ingest["gcps"],
    }
    if "control_screening" in ingest.outputs:
        inputs["control_screening"] = ingest["control_screening"]
    reference = reference_dsm_path(runner.inputs({"flight": ingest["flight"]}).json("flight"))
    if reference is not None:
        inputs["reference_dsm"] = runner.put(FileOutput(reference, "reference-dsm"))

    def compute(inp: StepInputs) -> dict:
        flight, adj, assess = inp.json("flight"), inp.json("adjustment"), inp.json("assessment")
        diag, mos = inp.json("diagnosis"), inp.json("mosaic")
        cert = Certificate.from_dict(inp.json("certificate"))
        images = inp.table("images")
        cp = assess.get("check_points", {})
        review = cert.review.notes[0] if cert.review is not None and cert.review.notes and not cert.estimated \
            else (cert.review.summary() if cert.review is not None else "not reviewed (made elsewhere)")
        summary = {
            "flight": flight["name"],
            "mode": flight["mode"],
            "images": flight["n_images"],
            "images_skipped_at_ingest": _skipped_text(flight.get("skipped_images") or []),
            "crs": flight["crs"],
            "date": flight["date"],
            "temperature_c": flight.get("temperature_range"),
            "flight_facts": "; ".join(f"{k}: {v}" for k, v in (flight.get("facts") or {}).items()) or None,
            "temperature_raster": mos.get("temperature"),
            "certificate": f"{cert.id} (version {cert.version})",
            "certificate_review": review,
            "thermal_model": cert.thermal.kind if cert.thermal is not None else None,
            "adjustment": "converged" if adj.get("converged", True) else (
                f"NOT converged in {adj.get('iterations')} iterations: sigma0, residuals and products describe an "
                "unfinished solution"),
            "sigma0": adj["sigma0"],
            "reprojection_rms_px": adj["reprojection_rms_px"],
            "check_rmse_m": adj.get("check_rmse_m"),
            "rho": cp.get("rho"),
            "verdict": cp.get("verdict"),
            "diagnosis": diag.get("summary"),
            "recorded_eo_checks": recorded_eo_text(diag.get("recorded_eo") or {}),
            "recorded_eo_corrections": "; ".join((adj.get("recorded_eo_corrections") or {}).get("notes") or [])
                                       or "none tested",
            "twin": (diag.get("twin") or {}).get("summary", "not made"),
            "gsd_m": mos.get("gsd_m"),
            "mosaic_frames": mos.get("frames"),
            "ground_control": _screening_text(inp.json("control_screening"))
                              if inp.has("control_screening") else "not screened",
        }
        figs = [_check_point_block(inp.table("poses"), adj, inp.table("gcps"))]
        notes: list[str] = []
        temps = dict(
            zip(
                images.column("image_id").to_pylist(),
                images.column("temperature_c").to_pylist(),
                strict=True,
            )
        )

        def dem_difference():
            if not inp.has("reference_dsm"):
                raise FigureSkipped(
                    f"DSM minus reference: not drawn, the flight folder has no reference DSM "
                    f"({REFERENCE_DSM.as_posix()}, a GeoTIFF of surface heights in the flight's CRS)."
                )
            points = inp.table("points")
            tie_en = np.column_stack([points.column("X").to_numpy(), points.column("Y").to_numpy()])
            return dem_difference_for_flight(
                read_dsm(inp.path("dsm")),
                read_dsm(inp.path("reference_dsm")),
                tie_en,
                config.measured_within_m,
                f"the reference DSM ({REFERENCE_DSM.as_posix()})",
            )

        builders = (
            lambda: image_residuals_from_assessment(assess),
            lambda: temperature_io_for_flight(
                cert.camera,
                _thermal(cert),
                temps,
                None if cert.thermal is None else cert.thermal.valid_range,
            ),
            dem_difference,
        )
        for build in builders:
            try:
                figs.append(build())
            except FigureSkipped as why:
                notes.append(str(why))
        dem = next((f.numbers for f in figs if f.name == "dem_difference"), None)
        if dem is not None:
            summary["dsm_minus_reference_m"] = {
                k: dem[k] for k in ("n", "mean_m", "median_m", "nmad_m", "rmse_m")
            }
        summary.update(config.extra)
        table = CertificateTable.from_values(
            f"Certificate {cert.id[:8]} (version {cert.version})",
            {n: getattr(cert.camera, n) for n in cert.estimated} or {"f": cert.camera.f},
            dict(cert.sigmas),
            info={"camera": cert.identity.key, "conditions": cert.conditions.to_dict()},
        )
        work = Path(tempfile.mkdtemp(prefix="aerocal-report-"))
        html = write_report(
            work, summary, figs, table, config.title or f"Flight report: {flight['name']}", notes=notes
        )
        return {
            "report": FileOutput(html, "report", temporary=True),
            "report_summary": FileOutput(work / "summary.json", "report-summary", temporary=True),
        }

    return runner.run("report", inputs, config, compute)


def recorded_eo_text(checks: dict) -> str:
    """One line per recorded-EO check of a diagnosis (``Diagnosis.recorded_eo``): estimate +- sigma, status."""
    parts = []
    for name, c in checks.items():
        if "estimate" in c:
            est = ", ".join(f"{v:.3g}" for v in c["estimate"])
            sig = ", ".join("?" if v is None else f"{v:.2g}" for v in c["sigma"])
            parts.append(f"{name} {est} +- {sig} {c['units']} ({c['status']})")
        else:
            parts.append(f"{name}: {c['status']}")
    return "; ".join(parts) or "no GNSS/IMU observations: not checked"
