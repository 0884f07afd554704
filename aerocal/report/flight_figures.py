"""The figures of a processed flight, built from what its steps stored.

Each builder takes plain step outputs (the assessment JSON, the certificate's camera and thermal model,
the images' sensor temperatures, the DSM and a reference surface) and returns a
:class:`~aerocal.report.figures.Figure` whose caption says what is drawn and whose ``numbers`` carry
the values for ``summary.json``. A figure the flight's data cannot support raises :class:`FigureSkipped`
with the sentence the report shows in its place (:func:`aerocal.report.html.write_report` ``notes``).

Units and frames: pixels with the origin at the top-left corner of the frame; temperatures degC; world
E, N, Up metres in the flight's projected CRS; differences are always *tested minus reference*.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from aerocal.report.figures import (
    Figure,
    dem_difference_figure,
    image_residual_figure,
    io_at_temperatures,
    temperature_io_figure,
)

#: DSM cells at most this far (metres) from a cell holding a tie point count as measured, not interpolated
MEASURED_WITHIN_M = 2.0


class FigureSkipped(Exception):
    """A figure the flight's data cannot support; the message is the sentence the report shows instead."""


def image_residuals_from_assessment(assessment: Mapping) -> Figure:
    """Mean reprojection residual per image region from an assessment's ``reprojection`` statistics
    (:meth:`aerocal.assess.ReprojectionStats.to_dict`, whose ``binned`` grid it draws)."""
    from aerocal.assess import BinnedResiduals

    rep = assessment.get("reprojection") or {}
    binned = rep.get("binned")
    if not binned or not np.asarray(binned.get("count", []), dtype=float).sum():
        raise FigureSkipped("Reprojection residuals over the image: not drawn, the assessment holds no "
                            "binned residuals (no image size or no observations).")
    fig = image_residual_figure(BinnedResiduals.from_dict(binned))
    rms = rep.get("rms_px")
    if rms is not None:
        fig = dataclasses.replace(fig, caption=f"{fig.caption} Overall reprojection RMS {rms:.3g} px over "
                                  f"{rep.get('n')} observations.")
    return fig


def temperature_io_for_flight(
    camera, model, temperatures: Mapping[int, float | None], valid_range: tuple[float, float] | None = None,
) -> Figure:
    """Focal length and principal point each image was adjusted with, against its sensor temperature.

    ``camera``: the certificate's camera (IO at the thermal model's reference temperature); ``model``:
    its thermal model or ``None``; ``temperatures``: image id -> sensor temperature (degC, ``None`` when
    not recorded); ``valid_range``: the model's valid temperatures (degC). Without a thermal model the
    constant IO is drawn over the flight's temperatures and the caption says that the certificate assumes
    no drift.
    """
    ids = [int(i) for i, t in temperatures.items() if t is not None and np.isfinite(t)]
    t = np.array([float(temperatures[i]) for i in ids], dtype=float)
    if not t.size:
        raise FigureSkipped("Interior orientation against sensor temperature: not drawn, no image of the "
                            "flight records a sensor temperature.")
    io = io_at_temperatures(camera, model, t)
    lo, hi = float(t.min()), float(t.max())
    if model is None:
        caption = (f"The certificate has no thermal model: every image was adjusted with the same focal "
                   f"length and principal point, drawn flat over the flight's sensor temperatures "
                   f"{lo:.1f} to {hi:.1f} degC. The flat line is the certificate's statement that the "
                   "interior orientation does not drift with temperature.")
    else:
        kind = model.to_dict().get("kind", "thermal")
        caption = (f"Focal length and principal point each image was adjusted with: the certificate's {kind} "
                   "thermal model (line) at the image's sensor temperature (points).")
        if not hasattr(model, "camera_at"):
            caption += (" The model corrects image measurements; shown is its equivalent scale and shift of "
                        "the frame as focal length and principal point.")
        if valid_range is not None and (lo < valid_range[0] or hi > valid_range[1]):
            caption += (f" The flight's temperatures {lo:.1f} to {hi:.1f} degC leave the model's valid range "
                        f"{valid_range[0]:.1f} to {valid_range[1]:.1f} degC: the model is extrapolated there.")
    fig = temperature_io_figure(t, io["f"], io["cx"], io["cy"], model=model, camera=camera, caption=caption)
    fig.numbers.update({
        "image_id": ids, "temperature_range_c": [lo, hi],
        "valid_range_c": None if valid_range is None else [float(v) for v in valid_range],
        "thermal_model": model is not None,
    })
    return fig


def _inside(dsm, reference) -> np.ndarray:
    """Cells of ``dsm`` whose centres lie inside the grid of ``reference`` (both :class:`aerocal.dsm.Dsm`)."""
    E, N = dsm.cell_centres()
    w, s, e, n = reference.bounds()
    return (E >= w) & (E <= e) & (N >= s) & (N <= n)


def _near_tie_points(dsm, tie_points_en: np.ndarray, within_m: float) -> np.ndarray:
    """Cells of ``dsm`` within ``within_m`` metres of a cell that holds a tie point (E, N metres)."""
    from scipy import ndimage

    col, row = dsm.grid_coords(tie_points_en[:, 0], tie_points_en[:, 1])
    c, r = np.rint(col).astype(int), np.rint(row).astype(int)
    rows, cols = dsm.shape
    ok = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
    has = np.zeros(dsm.shape, dtype=bool)
    has[r[ok], c[ok]] = True
    if not has.any():
        return has
    return ndimage.distance_transform_edt(~has) * dsm.cell_m <= within_m


def _same_crs(a: str, b: str) -> bool:
    from pyproj import CRS

    return CRS.from_user_input(a) == CRS.from_user_input(b)


def dem_difference_for_flight(
    dsm, reference, tie_points_en: np.ndarray | None = None, measured_within_m: float = MEASURED_WITHIN_M,
    reference_name: str = "the reference DSM",
) -> Figure:
    """The flight's DSM minus a reference surface (both :class:`aerocal.dsm.Dsm`), map and histogram, on
    the DSM's cells inside the reference grid. With the adjusted tie points (``tie_points_en`` (N, 2+) E, N
    metres) the numbers add ``measured_cells``: the same statistics on the cells within
    ``measured_within_m`` of a tie point, where the DSM's heights are measured rather than interpolated."""
    from aerocal.assess import compare_dems

    if not _same_crs(dsm.crs, reference.crs):
        raise FigureSkipped(f"DSM minus reference: not drawn, {reference_name} is in {reference.crs} and the "
                            f"flight's DSM in {dsm.crs}; warp the reference to the flight's CRS (gdalwarp -t_srs).")
    inside = _inside(dsm, reference)
    diff = compare_dems(dsm, reference, mask=inside, selection=f"cells inside {reference_name}")
    if diff.n == 0:
        raise FigureSkipped(f"DSM minus reference: not drawn, {reference_name} has no heights under the "
                            "flight's DSM.")
    fig = dem_difference_figure(diff)
    caption = (f"The flight's DSM minus {reference_name} on {diff.n} cells of {dsm.cell_m:.3g} m: mean "
               f"{diff.mean:.3g} m, median {diff.median:.3g} m, NMAD {diff.nmad:.3g} m.")
    if tie_points_en is not None and len(tie_points_en):
        near = _near_tie_points(dsm, np.asarray(tie_points_en, dtype=float), measured_within_m)
        sel = f"within {measured_within_m:g} m of a tie point"
        m = compare_dems(dsm, reference, mask=inside & near, selection=sel)
        fig.numbers["measured_cells"] = {k: v for k, v in m.to_dict().items()
                                         if k in ("n", "mean_m", "std_m", "median_m", "nmad_m", "rmse_m",
                                                  "selection")}
        if m.n:
            caption += (f" On the {m.n} cells {sel} (measured heights, the rest is interpolated): mean "
                        f"{m.mean:.3g} m, NMAD {m.nmad:.3g} m.")
    return dataclasses.replace(fig, caption=caption)
