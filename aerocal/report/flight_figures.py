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
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import rasterio
from pyproj import CRS
from rasterio.enums import Resampling

from aerocal.assess import BinnedResiduals, DemDifference, compare_dems
from aerocal.camera import Camera
from aerocal.products.dsm import distance_to_data
from aerocal.products.mosaic import FrameGeometry
from aerocal.report.figures import (
    Figure,
    dem_difference_figure,
    distortion_figure,
    image_residual_figure,
    io_at_temperatures,
    overview_figure,
    temperature_io_figure,
    tie_point_figure,
)

#: the overview's ground grid has at most this many cells along its longer side
OVERVIEW_CELLS = 160
#: the orthomosaic thumbnail of the overview has at most this many pixels along its longer side
THUMBNAIL_PX = 900

#: DSM cells at most this far (metres) from a cell holding a tie point count as measured, not interpolated
MEASURED_WITHIN_M = 2.0


class FigureSkipped(Exception):
    """A figure the flight's data cannot support; the message is the sentence the report shows instead."""


def image_residuals_from_assessment(assessment: Mapping) -> Figure:
    """Mean reprojection residual per image region, from an assessment's ``reprojection`` statistics.

    Args:
        assessment: the assessment document; its ``reprojection`` entry
            (:meth:`aerocal.assess.ReprojectionStats.to_dict`) gives the ``binned`` grid drawn, and ``rms_px``
            (pixels) and ``n`` for the caption.

    Returns:
        :class:`~aerocal.report.figures.Figure` ``"image_residuals"``
        (:func:`~aerocal.report.figures.image_residual_figure`), its caption adding the overall reprojection RMS
        and the number of observations when ``rms_px`` is given.

    Raises:
        FigureSkipped: the assessment holds no binned residuals, or every bin is empty (no image size or no
            observations).
        ValueError: the grid's ``bins`` disagree with the shape of its counts.
    """
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

    Without a thermal model the constant IO is drawn over the flight's temperatures and the caption says that
    the certificate assumes no drift. A model that only corrects measurements is drawn as its equivalent focal
    length and principal point (:func:`~aerocal.report.figures.io_at_temperatures`).

    Args:
        camera: the certificate's camera (IO at the thermal model's reference temperature; pixels).
        model: its thermal model, or ``None``.
        temperatures: image id -> sensor temperature (degC, ``None`` when not recorded; NaN counts as not
            recorded).
        valid_range: the model's valid temperatures (degC); the caption says when the flight leaves them (the
            model is then extrapolated).

    Returns:
        :class:`~aerocal.report.figures.Figure` ``"temperature_io"``
        (:func:`~aerocal.report.figures.temperature_io_figure`); its ``numbers`` add ``image_id``,
        ``temperature_range_c``, ``valid_range_c`` and ``thermal_model`` (whether there is one).

    Raises:
        FigureSkipped: no image of the flight records a sensor temperature.
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
    """Cells of ``dsm`` whose centres lie inside the grid of ``reference`` (both :class:`aerocal.products.dsm.Dsm`)."""
    w, s, e, n = reference.bounds()
    east, north = dsm.centre_axes()
    return ((north >= s) & (north <= n))[:, None] & ((east >= w) & (east <= e))[None, :]


def _near_tie_points(dsm, tie_points_en: np.ndarray, within_m: float) -> np.ndarray:
    """Cells of ``dsm`` within ``within_m`` metres of a cell that holds a tie point (E, N metres)."""
    col, row = dsm.grid_coords(tie_points_en[:, 0], tie_points_en[:, 1])
    c, r = np.rint(col).astype(int), np.rint(row).astype(int)
    rows, cols = dsm.shape
    ok = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
    has = np.zeros(dsm.shape, dtype=bool)
    has[r[ok], c[ok]] = True
    if not has.any():
        return has
    return distance_to_data(has) * dsm.cell_m <= within_m


def _same_crs(a: str, b: str) -> bool:
    return CRS.from_user_input(a) == CRS.from_user_input(b)


@dataclasses.dataclass(frozen=True)
class DemComparison:
    """A flight's DSM against a reference surface (:func:`compare_to_reference`), before it is drawn: the
    comparison on the DSM's cells inside the reference (``whole``), on its measured cells (``measured``, ``None``
    without a selection of them), and how the caption names the reference and the measured cells."""

    whole: DemDifference
    measured: DemDifference | None
    reference_name: str
    cell_m: float


def compare_to_reference(
    dsm, reference, tie_points_en: np.ndarray | None = None, measured_within_m: float = MEASURED_WITHIN_M,
    reference_name: str = "the reference DSM", measured: np.ndarray | None = None,
) -> DemComparison:
    """The numbers of :func:`dem_difference_for_flight` without its drawing (arguments and errors the same): no
    Matplotlib, so it may run on another thread while figures are drawn."""
    if not _same_crs(dsm.crs, reference.crs):
        raise FigureSkipped(f"DSM minus reference: not drawn, {reference_name} is in {reference.crs} and the "
                            f"flight's DSM in {dsm.crs}; warp the reference to the flight's CRS (gdalwarp -t_srs).")
    inside = _inside(dsm, reference)
    diff = compare_dems(dsm, reference, mask=inside, selection=f"cells inside {reference_name}")
    if diff.n == 0:
        raise FigureSkipped(f"DSM minus reference: not drawn, {reference_name} has no heights under the "
                            "flight's DSM.")
    near = None
    if measured is not None:
        near, sel = measured, "measured by the dense cloud"
    elif tie_points_en is not None and len(tie_points_en):
        near = _near_tie_points(dsm, np.asarray(tie_points_en, dtype=float), measured_within_m)
        sel = f"within {measured_within_m:g} m of a tie point"
    return DemComparison(diff, None if near is None else diff.within(near, sel), reference_name, dsm.cell_m)


def dem_difference_drawn(comparison: DemComparison) -> Figure:
    """The figure of a :class:`DemComparison` (:func:`dem_difference_for_flight`'s return)."""
    diff, m = comparison.whole, comparison.measured
    fig = dem_difference_figure(diff)
    caption = (f"The flight's DSM minus {comparison.reference_name} on {diff.n} cells of {comparison.cell_m:.3g} m: "
               f"mean {diff.mean:.3g} m, median {diff.median:.3g} m, NMAD {diff.nmad:.3g} m.")
    if m is not None:
        fig.numbers["measured_cells"] = {k: v for k, v in m.to_dict().items()
                                         if k in ("n", "mean_m", "std_m", "median_m", "nmad_m", "rmse_m",
                                                  "selection")}
        if m.n:
            caption += (f" On the {m.n} cells {m.selection} (measured heights, the rest is interpolated): mean "
                        f"{m.mean:.3g} m, NMAD {m.nmad:.3g} m.")
    return dataclasses.replace(fig, caption=caption)


def dem_difference_for_flight(
    dsm, reference, tie_points_en: np.ndarray | None = None, measured_within_m: float = MEASURED_WITHIN_M,
    reference_name: str = "the reference DSM", measured: np.ndarray | None = None,
) -> Figure:
    """The flight's DSM minus a reference surface, map and histogram, on the DSM's cells inside the reference grid.

    Args:
        dsm: the flight's DSM (:class:`aerocal.products.dsm.Dsm`, heights in metres).
        reference: the reference surface (:class:`aerocal.products.dsm.Dsm`), in the DSM's CRS.
        tie_points_en: the adjusted tie points (N, 2+), E, N metres. With them the numbers add ``measured_cells``:
            the same statistics on the cells within ``measured_within_m`` of a tie point, where the DSM's heights
            are measured rather than interpolated.
        measured_within_m: metres from a DSM cell holding a tie point (default :data:`MEASURED_WITHIN_M`, 2 m).
        reference_name: how the caption and the skip messages name the reference (default "the reference DSM").
        measured: bool (the DSM's shape), the cells a dense cloud measured; when given it replaces the tie points
            as the selection of ``measured_cells``.

    Returns:
        :class:`~aerocal.report.figures.Figure` ``"dem_difference"`` (tested minus reference); its caption gives
        the number of cells, the cell size, mean, median and NMAD (metres), and those of the measured cells when
        there are any; ``numbers`` are the :class:`aerocal.assess.DemDifference`'s ``to_dict()``, plus
        ``measured_cells`` (``n``, ``mean_m``, ``std_m``, ``median_m``, ``nmad_m``, ``rmse_m``, ``selection``).

    Raises:
        FigureSkipped: the reference is in another CRS (the message says how to warp it), or it has no heights
            under the flight's DSM.
    """
    return dem_difference_drawn(compare_to_reference(dsm, reference, tie_points_en, measured_within_m,
                                                     reference_name, measured))


def overlap_counts(
    frames: Sequence[FrameGeometry], dsm=None, ground_height_m: float | None = None,
    cells: int = OVERVIEW_CELLS,
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """How many frames see each ground cell, on a grid over the frames' footprints.

    The grid covers the frames' footprints on the plane at the ground height with at most ``cells`` cells along
    its longer side; every cell centre is lifted to the DSM's height there (the ground height where the DSM is
    empty or absent) and projected into every frame with its interior orientation and distortion: a cell
    counts for a frame when it lands inside it.

    Args:
        frames: the adjusted frames (:class:`aerocal.products.mosaic.FrameGeometry`), at least one.
        dsm: the flight's DSM (:class:`aerocal.products.dsm.Dsm`), or ``None``.
        ground_height_m: the ground plane's height, metres (default: the DSM's median height; 0 without a DSM).
        cells: the most cells along the grid's longer side (default :data:`OVERVIEW_CELLS`, 160).

    Returns:
        ``(counts, (west, east, south, north))``: int32 counts (rows, cols), row 0 north, and the grid's extent,
        metres of the flight's CRS.

    Raises:
        ValueError: ``frames`` is empty.
    """
    if ground_height_m is None:
        ground_height_m = float(np.nanmedian(dsm.heights)) if dsm is not None else 0.0
    prints = np.vstack([f.ground_footprint([ground_height_m]) for f in frames])
    w, s = prints.min(axis=0)
    e, n = prints.max(axis=0)
    cell = max(e - w, n - s, 1e-6) / cells
    cols, rows = max(int(np.ceil((e - w) / cell)), 1), max(int(np.ceil((n - s) / cell)), 1)
    east = w + (np.arange(cols) + 0.5) * cell
    north = n - (np.arange(rows) + 0.5) * cell
    E, N = np.meshgrid(east, north)
    Z = np.full(E.shape, float(ground_height_m))
    if dsm is not None:
        z = dsm.height_at(E, N)
        col, row = dsm.grid_coords(E, N)
        on = (col >= -0.5) & (col <= dsm.shape[1] - 0.5) & (row >= -0.5) & (row <= dsm.shape[0] - 0.5)
        Z = np.where(on & np.isfinite(z), z, Z)
    X = np.column_stack([E.ravel(), N.ravel(), Z.ravel()])
    counts = np.zeros(len(X), dtype=np.int32)
    for f in frames:
        counts += f.camera.in_image(f.project(X)).astype(np.int32)
    return counts.reshape(E.shape), (float(w), float(w + cols * cell), float(n - rows * cell), float(n))


def mosaic_thumbnail(path: str | Path, max_px: int = THUMBNAIL_PX) -> tuple[np.ndarray, tuple[float, ...]]:
    """The orthomosaic's first band, averaged down to at most ``max_px`` pixels along its longer side and
    stretched to 0..1 between its 2nd and 98th percentiles (NaN where it has no data), with its extent
    ``(west, east, south, north)`` metres."""
    with rasterio.open(path) as ds:
        k = max(ds.width, ds.height) / max_px
        shape = (max(int(ds.height / k), 1), max(int(ds.width / k), 1)) if k > 1 else (ds.height, ds.width)
        band = ds.read(1, out_shape=shape, resampling=Resampling.average, masked=True).astype(float)
        west, south, east, north = ds.bounds
    grey = band.filled(np.nan)
    valid = grey[np.isfinite(grey)]
    if valid.size:
        lo, hi = np.percentile(valid, [2, 98])
        grey = np.clip((grey - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return grey, (west, east, south, north)


def overview_for_flight(
    frames: Sequence[FrameGeometry], dsm=None, ground_height_m: float | None = None,
    orthomosaic: str | Path | None = None, control: Sequence[tuple[str, float, float]] = (),
    check: Sequence[tuple[str, float, float]] = (), no_mosaic_reason: str = "",
) -> Figure:
    """The overview map: orthomosaic thumbnail (when ``orthomosaic`` is a GeoTIFF), image-overlap counts
    (:func:`overlap_counts`), camera centres, control and check points ((id, E, N) metres). Without an
    orthomosaic the caption says why (``no_mosaic_reason``, a sentence).

    Raises:
        FigureSkipped: ``frames`` is empty (the adjustment holds no oriented image).
    """
    if not len(frames):
        raise FigureSkipped("Overview map: not drawn, the adjustment holds no oriented image.")
    counts, extent = overlap_counts(frames, dsm, ground_height_m)
    mosaic, mosaic_extent = (None, None) if orthomosaic is None else mosaic_thumbnail(orthomosaic)
    centres = np.array([f.C[:2] for f in frames], dtype=float)
    seen = counts[counts > 0]
    caption = (f"{len(frames)} camera centres (dots) over the number of images that see each "
               f"ground cell (colour; median {np.median(seen):.0f}, at most {counts.max()}; red: seen by one "
               "image only, where nothing on the ground can be triangulated).")
    if len(control) or len(check):
        caption += f" Triangles: {len(control)} control points; circles: {len(check)} check points."
    if mosaic is not None:
        caption += " Background: the orthomosaic."
    elif no_mosaic_reason:
        caption += " " + no_mosaic_reason
    return overview_figure(centres, counts, extent, mosaic, mosaic_extent, control, check,
                           title="Overview: camera centres, image overlap and ground control", caption=caption)


def tie_points_for_flight(points, centres_en: np.ndarray | None = None) -> Figure:
    """Tie-point coverage from the adjusted ``points`` table (X, Y metres, ``n_obs``, ``error`` px).

    Raises:
        FigureSkipped: ``points`` is ``None`` or empty, or no point records how many images measured it (``n_obs``).
    """
    if points is None or points.num_rows == 0:
        raise FigureSkipped("Tie points: not drawn, the adjustment holds no tie point.")
    en = np.column_stack([points.column("X").to_numpy(), points.column("Y").to_numpy()])
    n_obs = points.column("n_obs").to_numpy(zero_copy_only=False).astype(float)
    if not np.isfinite(n_obs).any():
        raise FigureSkipped("Tie points: not drawn, the adjusted points do not record how many images "
                            "measured them.")
    n_obs = np.nan_to_num(n_obs, nan=2.0)
    caption = (f"{len(en)} adjusted tie points coloured by how many images measured each (median "
               f"{np.median(n_obs):.0f}); gaps are ground the matching found nothing on, and points seen by two "
               "images only are the weakest.")
    fig = tie_point_figure(en, n_obs, centres_en, title="Tie-point coverage", caption=caption)
    err = points.column("error").to_numpy(zero_copy_only=False).astype(float)
    if np.isfinite(err).any():
        fig.numbers["mean_reprojection_error_px"] = float(np.nanmean(err))
    return fig


def distortion_for_camera(camera: Camera) -> Figure:
    """The lens distortion of a certificate's camera (:func:`aerocal.report.figures.distortion_figure`)."""
    fig = distortion_figure(camera, title="Lens distortion of the certificate's camera")
    n = fig.numbers
    terms = [name for name in ("k1", "k2", "k3", "p1", "p2", "b1", "b2") if getattr(camera, name) != 0.0]
    if not terms:
        caption = ("The certificate's camera has no distortion term: an ideal pinhole, every arrow has "
                   "zero length.")
    else:
        caption = (f"How far the lens model ({', '.join(terms)}) moves each pixel from where an ideal "
                   f"pinhole camera with the same focal length and principal point would put it: at most "
                   f"{n['max_displacement_px']:.3g} px over the frame (arrows drawn x{n['exaggeration']:g}); "
                   "right, the displacement along the line from the principal point (+) out to the farthest corner, "
                   "positive outwards; the dotted line is half the shorter image side.")
    return dataclasses.replace(fig, caption=caption)
