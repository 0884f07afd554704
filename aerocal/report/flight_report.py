"""The report of one processed flight, written for a person: :func:`write_flight_report`.

It takes the flight's step outputs as plain data (the ingest's flight summary and images table, the
certificate, the adjustment's summary, poses and points, the DSM, the mosaic's and the assessment's
summaries, the diagnosis, the ground control and its screening) and writes two files into ``out_dir``:

* ``report.html``: one self-contained page (figures embedded as PNG) rendered from the Jinja2 template
  ``templates/flight_report.html.j2``: the overview map (orthomosaic thumbnail, camera centres, how many
  images see each ground cell, control and check points), tie-point coverage, the calibration (parameters
  with sigmas, thermal model, distortion plot, the conditions it was made under, the interior orientation
  against temperature), the ground control and check points (errors E, N, Up metres), the reprojection
  residuals over the image, the DSM against a reference surface, what the diagnosis found and the step
  times. Where a figure cannot be drawn the page says why in its place.
* ``summary.json``: the same numbers for machines (:func:`aerocal.report.html.machine_summary`), its
  ``summary`` keys unchanged (``check_rmse_m``, ``dsm_minus_reference_m``, ...).

Frames and units: E, N, Up metres in the flight's projected CRS; errors are estimated minus surveyed;
pixels with the origin at the top-left corner of the frame; temperatures degC; times seconds.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa

from aerocal.certificates.document import Certificate
from aerocal.io import write_json_atomic, write_text_atomic
from aerocal.products.dsm import read_dsm, read_dsm_and_measured
from aerocal.products.mosaic import frames_from_poses
from aerocal.report import wording
from aerocal.report.figures import Figure, block_figure, laser_range_figure, surface_figure
from aerocal.report.flight_figures import (
    MEASURED_WITHIN_M,
    DemComparison,
    FigureSkipped,
    compare_to_reference,
    dem_difference_drawn,
    distortion_for_camera,
    image_residuals_from_assessment,
    overview_for_flight,
    temperature_io_for_flight,
    tie_points_for_flight,
)
from aerocal.report.html import REPORT_NAME, SUMMARY_NAME, CertificateTable, machine_summary, render

#: where a flight folder keeps its reference surface, as the report names it when there is none

#: what a ground point's error cells say when the block could not intersect it (seen in one image)
NOT_MEASURED = "not measured"

#: the sections of the page, in order: (id, heading)
SECTIONS: tuple[tuple[str, str], ...] = (
    ("summary", "Summary"),
    ("overview", "Overview"),
    ("tie-points", "Tie points"),
    ("calibration", "Camera calibration"),
    ("ground-control", "Ground control and check points"),
    ("residuals", "Reprojection residuals"),
    ("surface", "Surface model"),
    ("diagnosis", "Diagnosis"),
    ("steps", "Processing steps"),
)


def write_flight_report(
    out_dir: str | Path,
    flight: Mapping,
    images: pa.Table,
    certificate: Certificate,
    adjustment: Mapping,
    poses: pa.Table,
    points: pa.Table,
    dsm: str | Path | None,
    mosaic: Mapping,
    assessment: Mapping,
    diagnosis: Mapping,
    gcps: pa.Table,
    control_screening: Mapping | None = None,
    reference_dsm: str | Path | None = None,
    orthomosaic: str | Path | None = None,
    title: str | None = None,
    extra: Mapping | None = None,
    measured_within_m: float = MEASURED_WITHIN_M,
    step_seconds: Mapping[str, float] | None = None,
    reference_dsm_name: str = "reference/dsm.tif",
    extension: Mapping | None = None,
    certificate_terms: Sequence[str] = (),
) -> dict:
    """Write ``out_dir/report.html`` and ``out_dir/summary.json`` for a processed flight.

    A figure the flight's data cannot support is replaced on the page, and in ``summary.json``'s ``notes``, by
    the sentence saying why (:class:`~aerocal.report.flight_figures.FigureSkipped`).

    Args:
        out_dir: the folder written (created with its parents when missing).
        flight: the ingest's flight summary: ``name``, ``mode``, ``n_images``, ``crs`` and ``date`` (required),
            ``temperature_range``, ``facts``, ``skipped_images``.
        images: the ``images`` table (:mod:`aerocal.tables`); its ``temperature_c`` (degC) per image.
        certificate: the calibration certificate the flight used (camera, thermal model, sigmas, conditions).
        adjustment: the fixed-IO adjustment's summary: ``sigma0`` and ``reprojection_rms_px`` (required),
            ``check_ids``, ``check_errors_m`` (E, N, Up metres, estimated minus surveyed; required with
            ``check_ids``), ``control_ids``, ...
        poses: the adjusted ``poses`` table (projection centres E, N, Up metres in the flight's CRS).
        points: the adjusted ``points`` table.
        dsm: the DSM GeoTIFF, or ``None``.
        mosaic: the mosaic step's JSON document (``frames``, ``ground_height_m``, ``gsd_m``, ``temperature``).
        assessment: the assessment step's JSON document.
        diagnosis: the diagnosis step's JSON document.
        gcps: the ``gcps`` table.
        control_screening: the ground-control screening's JSON document, or ``None`` (not screened).
        reference_dsm: a reference surface GeoTIFF (heights in metres, the flight's CRS), or ``None``.
        orthomosaic: the orthomosaic GeoTIFF, or ``None``.
        title: the page's title (default "Flight report: <name>").
        extra: key figures added to the summary.
        measured_within_m: DSM cells this close to a tie point (metres) count as measured (default
            :data:`~aerocal.report.flight_figures.MEASURED_WITHIN_M`).
        step_seconds: step name -> wall time (seconds), shown when given.
        reference_dsm_name: how the page names the reference surface (default ``"reference/dsm.tif"``).
        extension: the record of the block's extension by its diagnosis
            (:func:`aerocal.pipeline.extend_step.extension_record`): the terms applied and the block before and
            after (``adjustment``, ``assessment`` and ``diagnosis`` are then the extended block's).
        certificate_terms: whether each camera term of the stored certificate the block used holds on this flight,
            one sentence each (:func:`aerocal.pipeline.certificates.certificate_term_remainders`).

    Returns:
        The summary document, what ``summary.json`` holds (:func:`aerocal.report.html.machine_summary`, plus
        ``step_seconds`` when given).

    Raises:
        KeyError: a required key of ``flight`` or ``adjustment`` is missing, or a check id is absent from ``gcps``.
        ValueError: ``dsm`` or ``reference_dsm`` is not a readable north-up GeoTIFF with a CRS.
    """
    out_dir = Path(out_dir)
    cert = certificate
    title = title or f"Flight report: {flight['name']}"
    thermal = None if cert.thermal is None else cert.thermal.model
    temps = dict(zip(images.column("image_id").to_pylist(), images.column("temperature_c").to_pylist(),
                     strict=True))
    summary = flight_summary(flight, cert, adjustment, assessment, diagnosis, mosaic, control_screening)

    figures: dict[str, Figure] = {}
    skipped: dict[str, str] = {}

    def attempt(name: str, build: Callable[[], Figure]) -> None:
        try:
            figures[name] = build()
        except FigureSkipped as why:
            skipped[name] = str(why)

    # the DSM is read and compared with the reference on a thread of its own (numpy and GDAL, which release the
    # GIL) while this one draws the figures that do not need it: on a city's dense DSM (82 million cells) the two
    # took 13.2 of the report's 24.3 s under a profiler, on one core while the other waited; the step went from
    # 22.0 to 12.6 s (benchmarks/RESULTS.md, "Report: the DSM read once, its difference formed once" and "Report:
    # the DSM read and compared beside the figures"). Matplotlib stays on this thread.
    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="report-dsm") as pool:
        surface_read = pool.submit(read_dsm_and_measured, dsm) if dsm is not None else None

        def compared() -> DemComparison:  # on the pool's thread, after the read
            if reference_dsm is None:
                raise FigureSkipped(f"DSM minus reference: not drawn, the flight folder has no reference DSM "
                                    f"({reference_dsm_name}, a GeoTIFF of surface heights in the flight's CRS).")
            if surface_read is None:
                raise FigureSkipped("DSM minus reference: not drawn, the flight has no DSM.")
            try:
                reference = read_dsm(reference_dsm)
            except ValueError as exc:  # the user's file: a figure left out with why, not a run lost at its end
                raise FigureSkipped(f"DSM minus reference: not drawn, {exc}") from exc
            grid, cells = surface_read.result()
            tie_en = np.column_stack([points.column("X").to_numpy(), points.column("Y").to_numpy()])
            return compare_to_reference(grid, reference, tie_en, measured_within_m,
                                        f"the reference DSM ({reference_dsm_name})", cells)

        comparison = pool.submit(compared)
        frames = _frames(poses, cert, temps, thermal)
        control, check = _ground_points(adjustment, gcps)
        centres = np.column_stack([poses.column("X").to_numpy(), poses.column("Y").to_numpy()])
        attempt("tie_points", lambda: tie_points_for_flight(points, centres))
        attempt("distortion", lambda: distortion_for_camera(cert.camera))
        attempt("temperature_io", lambda: temperature_io_for_flight(
            cert.camera, thermal, temps, None if cert.thermal is None else cert.thermal.valid_range))
        attempt("block", lambda: check_point_block(poses, adjustment, gcps, frames, mosaic.get("ground_height_m")))
        attempt("image_residuals", lambda: image_residuals_from_assessment(assessment))

        dsm_grid, measured = surface_read.result() if surface_read is not None else (None, None)
        no_mosaic = ("No orthomosaic: " + (
            "the flight holds no image pixels (observations only)." if not mosaic.get("frames")
            else "its file was not given to the report."))
        attempt("overview", lambda: overview_for_flight(
            frames, dsm_grid, mosaic.get("ground_height_m"), orthomosaic, control, check, no_mosaic))

        def surface() -> Figure:
            if dsm_grid is None:
                raise FigureSkipped("Surface model: not drawn, the flight has no DSM.")
            return surface_figure(dsm_grid, measured)

        attempt("surface", surface)
        attempt("dem_difference", lambda: dem_difference_drawn(comparison.result()))
    if "dem_difference" in figures:
        dem = figures["dem_difference"].numbers
        summary["dsm_minus_reference_m"] = {k: dem[k] for k in ("n", "mean_m", "median_m", "nmad_m", "rmse_m")}
    for key in ("dense_minus_reference_m", "sparse_minus_reference_m"):  # the products step's, measured cells
        if mosaic.get(key) and "error" not in mosaic[key]:
            summary[key] = mosaic[key]
    if mosaic.get("flying_height"):
        summary["flying_height_m"] = mosaic["flying_height"]
    if mosaic.get("laser_range"):
        laser_doc = mosaic["laser_range"]
        summary["surface_minus_laser_range_m"] = {
            k: ({kk: vv for kk, vv in v.items() if kk != "images"} if k == "fitted" else v)
            for k, v in laser_doc.items() if k != "images"}
        attempt("laser_range", lambda: laser_range_figure(laser_doc))
    if extension is not None:
        summary["model_extension"] = extension.get("named")
    if certificate_terms:
        summary["certificate_terms"] = list(certificate_terms)
    summary.update(extra or {})

    table = CertificateTable.from_values(
        f"Certificate {cert.id[:8]} (version {cert.version})",
        {n: getattr(cert.camera, n) for n in cert.estimated} or {"f": cert.camera.f},
        dict(cert.sigmas),
        info={"camera": cert.identity.key, "conditions": cert.conditions.to_dict()},
    )
    order = ("block", "image_residuals", "temperature_io", "dem_difference", "laser_range", "overview", "tie_points",
             "distortion")
    drawn = [figures[n] for n in order if n in figures]
    notes = [skipped[n] for n in order if n in skipped]
    doc = machine_summary(title, summary, drawn, notes, table)
    if step_seconds:
        doc["step_seconds"] = {str(k): float(v) for k, v in step_seconds.items()}

    context = {
        "title": title,
        "created_utc": doc["created_utc"].replace("T", " ").replace("+00:00", ""),
        "summary_name": SUMMARY_NAME,
        "sections": SECTIONS,
        "subtitle": _subtitle(flight, cert),
        "verdict": _verdict(assessment),
        "key_figures": _summary_rows(summary, flight, cert, adjustment, extra or {}),
        "figures": {n: _figure_view(f) for n, f in figures.items()},
        "skipped": skipped,
        "tie_points": _tie_point_rows(adjustment, points, assessment),
        "certificate": _certificate_view(cert),
        "certificate_terms": list(certificate_terms),
        "control": _control_view(adjustment, gcps),
        "check": _check_view(adjustment, gcps, assessment),
        "screening": _screening_view(control_screening),
        "surface": _surface_rows(mosaic, dsm_grid),
        "diagnosis": _diagnosis_view(diagnosis),
        "extension": wording.extension_view(extension) if extension is not None else None,
        "steps": wording.step_rows(step_seconds) if step_seconds else [],
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_dir / SUMMARY_NAME, doc)
    write_text_atomic(out_dir / REPORT_NAME, render("flight_report.html.j2", context))
    return doc


# ------------------------------------------------------------------------------ the summary for machines
def flight_summary(flight: Mapping, cert: Certificate, adjustment: Mapping, assessment: Mapping,
                   diagnosis: Mapping, mosaic: Mapping, control_screening: Mapping | None) -> dict:
    """The key figures of a processed flight under their machine keys (``summary.json``'s ``summary``)."""
    cp = assessment.get("check_points", {})
    adj = adjustment
    return {
        "flight": flight["name"],
        "mode": flight["mode"],
        "images": flight["n_images"],
        "images_skipped_at_ingest": wording.skipped_images_text(flight.get("skipped_images") or []),
        "crs": flight["crs"],
        "date": flight["date"],
        "temperature_c": flight.get("temperature_range"),
        "flight_facts": "; ".join(f"{k}: {v}" for k, v in (flight.get("facts") or {}).items()) or None,
        "temperature_raster": mosaic.get("temperature"),
        "certificate": f"{cert.id} ({_version(cert)})",
        "certificate_review": wording.review_text(cert),
        "thermal_model": cert.thermal.kind if cert.thermal is not None else None,
        "adjustment": "converged" if adj.get("converged", True) else (
            f"NOT converged in {adj.get('iterations')} iterations: sigma0, residuals and products describe an "
            "unfinished solution"),
        "sigma0": adj["sigma0"],
        "reprojection_rms_px": adj["reprojection_rms_px"],
        "check_rmse_m": adj.get("check_rmse_m"),
        "rho": cp.get("rho"),
        "verdict": cp.get("verdict"),
        "diagnosis": diagnosis.get("summary"),
        "recorded_eo_checks": wording.recorded_eo_text(diagnosis.get("recorded_eo") or {}),
        "recorded_eo_corrections": "; ".join((adj.get("recorded_eo_corrections") or {}).get("notes") or [])
                                   or "none tested",
        "twin": (diagnosis.get("twin") or {}).get("summary", "not made"),
        "gsd_m": mosaic.get("gsd_m"),
        "mosaic_frames": mosaic.get("frames"),
        "ground_control": wording.screening_text(control_screening) if control_screening is not None
                          else "not screened",
    }


# ------------------------------------------------------------------------------ figures from the steps
def check_point_block(poses: pa.Table, adjustment: Mapping, gcps: pa.Table, frames=(),
                      ground_height_m: float | None = None) -> Figure:
    """The block figure: camera centres, the frames' footprints on the ground plane at ``ground_height_m``
    (when both are given) and the check-point residuals of the adjustment (E, N metres)."""
    centres = np.column_stack([poses.column("X").to_numpy(), poses.column("Y").to_numpy()])
    prints = [f.ground_footprint([ground_height_m]) for f in frames] if ground_height_m is not None else []
    ids = adjustment.get("check_ids") or []
    if not ids:
        fig = block_figure(centres, prints)
        return dataclasses.replace(fig, caption="Camera centres and footprints. The flight has no check point: "
                                                "no residual is drawn.")
    where = _positions(gcps)
    en = np.array([where[i][:2] for i in ids], dtype=float)
    errs = np.asarray(adjustment["check_errors_m"], dtype=float).reshape(-1, 3)
    return block_figure(centres, prints, points_en=en, residuals=errs, ids=ids)


def _frames(poses: pa.Table, cert: Certificate, temps: Mapping, thermal) -> list:
    """The adjusted frames with the certificate's IO (its thermal model at each image's temperature when
    every image has one, else the reference IO: the overlap map does not see the difference)."""
    known = {int(k): float(v) for k, v in temps.items() if v is not None and np.isfinite(v)}
    ids = poses.column("image_id").to_pylist()
    if thermal is not None and all(int(i) in known for i in ids):
        return frames_from_poses(poses, cert.camera, known, thermal)
    return frames_from_poses(poses, cert.camera)


def _positions(gcps: pa.Table) -> dict[str, tuple[float, float, float]]:
    return {g: (x, y, z) for g, x, y, z in zip(*(gcps.column(c).to_pylist() for c in ("gcp_id", "X", "Y", "Z")),
                                                strict=True)}


def _ground_points(adjustment: Mapping, gcps: pa.Table) -> tuple[list, list]:
    """(id, E, N) of the control and the check points the adjustment used (the GCP table's roles when the
    adjustment does not list them)."""
    where = _positions(gcps)
    roles = dict(zip(gcps.column("gcp_id").to_pylist(), gcps.column("role").to_pylist(), strict=True))
    out = []
    for role, key in (("control", "control_ids"), ("check", "check_ids")):
        ids = adjustment.get(key)
        if ids is None:
            ids = [g for g, r in roles.items() if r == role]
        out.append([(g, where[g][0], where[g][1]) for g in ids if g in where])
    return out[0], out[1]


# ------------------------------------------------------------------------------ views for the template
def _figure_view(fig: Figure) -> dict:
    return {"name": fig.name, "title": fig.title, "caption": fig.caption, "png": fig.png}


def _version(cert: Certificate) -> str:
    return "unversioned" if cert.version is None else f"version {cert.version}"


def _subtitle(flight: Mapping, cert: Certificate) -> str:
    parts = [str(flight["name"])]
    if flight.get("date"):
        parts.append(str(flight["date"]))
    parts.append(f"{flight['n_images']} images")
    parts.append(f"camera {cert.identity.label}")
    parts.append(str(flight["crs"]))
    return ", ".join(parts)


def _summary_rows(summary: Mapping, flight: Mapping, cert: Certificate, adjustment: Mapping,
                  extra: Mapping) -> list[tuple[str, str]]:
    """The key figures a reader looks at first, in words; the details are in the sections below."""
    say = wording.say
    skipped = flight.get("skipped_images") or []
    images = f"{flight['n_images']}" + (f" ({summary['images_skipped_at_ingest']} skipped at ingest)" if skipped
                                        else ", none skipped at ingest")
    mode = {"observations": "measured image coordinates (no image matching)",
            "images": "images (features matched)"}.get(str(flight["mode"]), str(flight["mode"]))
    rows = [("Flight", str(flight["name"])), ("Date", say(flight.get("date"))), ("Images", images),
            ("Input", mode), ("Coordinate reference system", str(flight["crs"])),
            ("Sensor temperature", say(flight.get("temperature_range"), "degC"))]
    if flight.get("facts"):
        rows.append(("Facts read from the images", "; ".join(f"{wording.humanise(k)[0]}: {v}"
                                                             for k, v in flight["facts"].items())))
    rows.append(("Calibration certificate", f"{cert.id[:8]} ({_version(cert)}) of {cert.identity.label}, "
                                            f"{summary['certificate_review']}"))
    rows.append(("Thermal model", "none" if cert.thermal is None else f"{cert.thermal.kind}"))
    rows.append(("Bundle adjustment", summary["adjustment"]))
    rows.append(("Sigma naught", wording.number(summary.get("sigma0"), 3)))
    rows.append(("Reprojection error (RMS)", say(summary.get("reprojection_rms_px"), "px")))
    if adjustment.get("check_ids"):
        rows.append(("Check-point error (RMSE)", say(summary.get("check_rmse_m"), "m")))
        if summary.get("rho"):
            rows.append(("Achieved over predicted accuracy",
                         "; ".join(f"{a} {wording.number(v, 3)}" for a, v in summary["rho"].items())))
    else:
        rows.append(("Check-point error (RMSE)", "no check point: not measured"))
    rows.append(("Ground control", summary["ground_control"]))
    rows.append(("Diagnosis", wording.name_effects(summary.get("diagnosis") or "not made").replace("+-", "±")))
    rows.append(("Ground sampling distance", say(summary.get("gsd_m"), "m")))
    rows.append(("Frames in the orthomosaic", say(summary.get("mosaic_frames") or 0)))
    dem = summary.get("dsm_minus_reference_m")
    if dem:
        fx = wording.fixed
        rows.append(("DSM minus reference", f"mean {fx(dem['mean_m'])} m, median {fx(dem['median_m'])} m, "
                                            f"NMAD {fx(dem['nmad_m'])} m over {dem['n']} cells"))
    else:
        rows.append(("DSM minus reference", "not compared (no reference surface)"))
    rows.extend(wording.key_figures(extra))
    return rows


def _verdict(assessment: Mapping) -> str:
    cp = assessment.get("check_points") or {}
    verdict = cp.get("verdict")
    if not verdict:
        return ""
    rho = cp.get("rho") or {}
    ratios = ", ".join(f"{a} {wording.number(v, 3)}" for a, v in rho.items() if v is not None)
    text = f"Check points: {verdict}"
    if ratios:
        text += f" (achieved over predicted accuracy {ratios})"
    return text + "."


def _tie_point_rows(adjustment: Mapping, points: pa.Table, assessment: Mapping) -> list[tuple[str, str]]:
    rows = [("Adjusted tie points", wording.number(points.num_rows))]
    if points.num_rows:
        n_obs = points.column("n_obs").to_numpy(zero_copy_only=False).astype(float)
        if np.isfinite(n_obs).any():
            rows.append(("Images measuring a point", f"median {float(np.nanmedian(n_obs)):.0f}, "
                                                     f"mean {float(np.nanmean(n_obs)):.1f}"))
    rep = assessment.get("reprojection") or {}
    if rep.get("n"):
        rows.append(("Image measurements", wording.number(rep["n"])))
    rows.append(("Reprojection error (RMS)", wording.with_unit(wording.number(adjustment.get(
        "reprojection_rms_px"), 3), "px")))
    rows.append(("Sigma naught", wording.number(adjustment.get("sigma0"), 3)))
    return rows


def _certificate_view(cert: Certificate) -> dict:
    cam = cert.camera
    size = f"{cam.width} x {cam.height} px"
    if cam.pixel_size_mm is not None:
        size += f", pixel {wording.number(cam.pixel_size_mm * 1000, 3)} um, focal length " \
                f"{wording.number(cam.focal_mm, 5)} mm"
    q = cert.quality
    quality = [("Sigma naught", wording.number(q.sigma0, 3)),
               ("Reprojection error (RMS)", wording.with_unit(wording.number(q.reprojection_rms_px, 3), "px")),
               ("Degrees of freedom", wording.number(q.dof))]
    if q.overdispersion is not None:
        quality.append(("Sigmas", q.sigmas_text()))
    pairs = cert.correlation.high_pairs(0.9)
    return {
        "id": cert.id,
        "version": _version(cert),
        "camera": cert.identity.label,
        "issued": cert.issued.strftime("%Y-%m-%d %H:%M UTC"),
        "status": cert.status,
        "size": size,
        "review": wording.review_text(cert),
        "parameters": wording.parameter_rows(cert),
        "thermal": wording.thermal_sentence(cert),
        "conditions": wording.conditions_rows(cert.conditions),
        "quality": quality,
        "correlations": ", ".join(f"{a} with {b} ({r:+.2f})" for a, b, r in pairs),
    }


def _control_view(adjustment: Mapping, gcps: pa.Table) -> dict:
    ids = list(adjustment.get("control_ids") or [])
    errs = np.asarray(adjustment.get("control_errors_m") or np.zeros((0, 3)), dtype=float).reshape(-1, 3)
    return _point_table(ids, errs, None, _positions(gcps))


def _check_view(adjustment: Mapping, gcps: pa.Table, assessment: Mapping) -> dict:
    ids = list(adjustment.get("check_ids") or [])
    errs = np.asarray(adjustment.get("check_errors_m") or np.zeros((0, 3)), dtype=float).reshape(-1, 3)
    sig = adjustment.get("check_sigma_m")
    sig = None if sig is None else np.asarray(sig, dtype=float).reshape(-1, 3) if len(sig) else None
    view = _point_table(ids, errs, sig, _positions(gcps))
    rmse = adjustment.get("check_rmse_m")
    if ids and rmse is not None:
        view["rmse"] = [wording.fixed(v) for v in rmse]
    return view


def _point_table(ids: list, errs: np.ndarray, sigmas: np.ndarray | None, where: Mapping) -> dict:
    rows = []
    for k, g in enumerate(ids):
        e = errs[k]
        measured = bool(np.isfinite(e).all())
        row = {"id": str(g), "position": [wording.fixed(v, 2) for v in where.get(g, (None, None, None))],
               "error": [wording.fixed(v) for v in e] if measured else [NOT_MEASURED] * 3,
               "total": wording.fixed(float(np.linalg.norm(e))) if measured else NOT_MEASURED}
        if sigmas is not None and k < len(sigmas):
            row["sigma"] = [wording.fixed(v) if measured else NOT_MEASURED for v in sigmas[k]]
        rows.append(row)
    ok = np.isfinite(errs).all(axis=1)
    rmse = [wording.fixed(float(np.sqrt(np.mean(errs[ok, i] ** 2)))) for i in range(3)] if ok.any() else \
        [NOT_MEASURED] * 3
    unmeasured = [str(g) for g, m in zip(ids, ok, strict=True) if not m]
    return {"rows": rows, "has_sigma": sigmas is not None and len(rows) > 0, "rmse": rmse,
            "unmeasured": ", ".join(unmeasured)}


def _screening_view(screening: Mapping | None) -> dict:
    if screening is None:
        return {"sentences": ["The ground control was not screened against the block."], "rows": []}
    sentences = [wording.sentence(s) for s in wording.screening_parts(screening)]
    datum = {"gnss": "the recorded GNSS positions", "control": "the other control points",
             "none": "nothing (no datum to test against)"}.get(str(screening.get("datum")), "an unknown datum")
    sentences.insert(0, f"Each ground point was intersected from the block and compared with its survey, the "
                        f"block placed by {datum}.")
    rows = []
    for v in screening.get("verdicts") or []:
        misfit = v.get("misfit_m")
        rows.append({"id": str(v.get("gcp_id")), "role": str(v.get("role") or wording.MISSING),
                     "status": str(v.get("status") or wording.MISSING), "rays": wording.number(v.get("n_rays")),
                     "misfit": [wording.fixed(x) for x in misfit] if misfit else ["not tested"] * 3,
                     "reason": str(v.get("reason") or "")})
    return {"sentences": sentences, "rows": rows}


def _surface_rows(mosaic: Mapping, dsm) -> list[tuple[str, str]]:
    rows = [("Ground sampling distance", wording.with_unit(wording.number(mosaic.get("gsd_m"), 3), "m"))]
    if mosaic.get("ground_height_m") is not None:
        rows.append(("Median ground height", wording.with_unit(wording.number(mosaic["ground_height_m"], 5),
                                                                "m")))
    if dsm is not None:
        rows.append(("DSM cell", wording.with_unit(wording.number(dsm.cell_m, 3), "m")))
        rows.append(("DSM size", f"{dsm.shape[1]} x {dsm.shape[0]} cells, "
                                 f"{100 * float(np.mean(np.isfinite(dsm.heights))):.0f} % with a height"))
    dense = mosaic.get("dense")
    if dense:
        rows.append(("Surface", f"dense: {wording.number(dense['points'])} points matched in "
                                f"{wording.number(dense['pairs'])} pairs of {wording.number(dense['frames'])} "
                                f"frames (cloud.laz), {100 * dense['measured_fraction']:.0f} % of the DSM measured"
                                f"{wording.two_view_text(dense)}, the rest filled (band 2 of dsm.tif)"))
        if mosaic.get("dtm"):
            rows.append(("Terrain", str(mosaic["dtm"]) + (" (dtm.tif)" if mosaic["dtm"].startswith("DTM") else "")))
    else:
        rows.append(("Surface", str(mosaic.get("surface") or "the adjusted tie points")))
    for key, name in (("dense_minus_reference_m", "Dense DSM minus reference"),
                      ("sparse_minus_reference_m", "Tie-point DSM minus reference")):
        d = mosaic.get(key)
        if d and "error" not in d:
            rows.append((name, f"measured cells: mean {d['mean_m']:.2f} m, NMAD {d['nmad_m']:.2f} m, "
                               f"RMSE {d['rmse_m']:.2f} m, {100 * d['completeness']:.0f} % of the cells"))
    height = mosaic.get("flying_height")
    if height:
        rows.append(("Flying height from the surface",
                     f"{height['from_surface_m']:.1f} m above the {height['ground']} under the cameras (median of "
                     f"{height['frames']} frames), against {height['recorded_m']:.1f} m recorded "
                     f"({height['source']}): {height['difference_m']:+.1f} m, {100 * height['relative']:+.1f} %"))
    laser = mosaic.get("laser_range")
    if laser:
        fitted = laser.get("fitted")
        rows.append(("Surface against the laser range finder", str(laser["verdict"]) + (
            f"; on the {fitted['n']} frames whose range the adjustment used: median {fitted['median_m']:+.2f} m"
            if fitted and fitted.get("n") else "")))
    rows.append(("Frames in the orthomosaic", wording.number(mosaic.get("frames") or 0)))
    if mosaic.get("temperature"):
        rows.append(("Temperature raster", str(mosaic["temperature"])))
    return rows


def _diagnosis_view(diagnosis: Mapping) -> dict:
    twin = diagnosis.get("twin") or {}
    return {
        "sentences": wording.diagnosis_sentences(diagnosis),
        "recorded_eo": wording.recorded_eo_rows(diagnosis.get("recorded_eo") or {}),
        "twin": wording.twin_view(twin),
    }
