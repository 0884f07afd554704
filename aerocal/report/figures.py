"""Report figures: PNG images (matplotlib, Agg canvas, no pyplot state) with the numbers they show.

Every function takes plain arrays or :mod:`aerocal.assess` results and returns a :class:`Figure`:
the PNG bytes, a title, a caption and ``numbers`` (JSON-ready) that ``summary.json`` carries for
machines. World coordinates are E, N metres of the flight's CRS; image coordinates pixels (origin at
the top-left corner, y down, so image plots have y pointing down).
"""

from __future__ import annotations

import io
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.figure import Figure as MplFigure
from matplotlib.patches import Rectangle


@dataclass
class Figure:
    """A rendered figure and the numbers behind it."""

    name: str  #: identifier (file-name safe), the key in summary.json
    title: str
    png: bytes = field(repr=False)
    caption: str = ""
    numbers: dict = field(default_factory=dict)


def _canvas(width_in: float = 7.0, height_in: float = 5.0):
    fig = MplFigure(figsize=(width_in, height_in), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


#: whether :func:`_png` renders (:func:`figures_drawn`); a report of text and numbers only sets it False
_DRAWN: ContextVar[bool] = ContextVar("aerocal_figures_drawn", default=True)


@contextmanager
def figures_drawn(drawn: bool) -> Iterator[None]:
    """Inside the block, figures are rendered to PNG (``drawn``, the default) or not: each :class:`Figure` then
    holds its title, caption and numbers with empty ``png`` bytes, and the page shows the caption alone."""
    token = _DRAWN.set(bool(drawn))
    try:
        yield
    finally:
        _DRAWN.reset(token)


def _png(fig) -> bytes:
    """The figure as PNG bytes at 100 dpi (empty inside ``figures_drawn(False)``), at zlib's fastest level: the
    default level 6 costs a report more time than the few per cent of file size it saves
    (``benchmarks/RESULTS.md``, "The test suite's time: the matching's scan")."""
    if not _DRAWN.get():
        return b""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, pil_kwargs={"compress_level": 1})
    return buf.getvalue()


def _nice(x: float) -> float:
    """A round number (1, 2, 5 x 10^k) close to ``x``."""
    if not x > 0 or not np.isfinite(x):
        return 1.0
    k = np.floor(np.log10(x))
    m = x / 10**k
    return float((1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * 10**k)


def _f(v) -> float | None:
    """``v`` as a finite float, or ``None`` (a figure not measured: ``None`` or NaN in the run's JSON)."""
    if v is None:
        return None
    v = float(v)
    return v if np.isfinite(v) else None


def block_figure(
    centres: np.ndarray,
    footprints: Sequence[np.ndarray] = (),
    points_en: np.ndarray | None = None,
    residuals: np.ndarray | None = None,
    ids: Sequence[str] | None = None,
    exaggeration: float | None = None,
    title: str = "Block and check-point residuals",
) -> Figure:
    """The block seen from above: camera centres, footprints and residual vectors with a scale arrow.

    Residuals are exaggerated (default: the largest residual drawn as 8 % of the block's size, the factor
    rounded to 1, 2 or 5 x 10^k); the scale arrow has a round length near the largest residual.

    Args:
        centres: camera centres (N, 2+), E, N metres in the flight CRS.
        footprints: image footprints on the ground, each an (M, 2) polygon of E, N metres (default: none).
        points_en: where the residuals are drawn (K, 2+), E, N metres; nothing is drawn without ``residuals``.
        residuals: residual vectors (K, 2+), metres; their E, N components are drawn (the caption calls them
            check-point residuals, estimated minus surveyed).
        ids: the K points' names in ``numbers`` (default "0".."K-1").
        exaggeration: the factor the residuals are drawn at (default: automatic, above).
        title: the figure's title.

    Returns:
        :class:`Figure` ``"block"``; ``numbers`` hold ``n_images`` and, with residuals, ``exaggeration``,
        ``scale_arrow_m`` and ``points`` (``id``, ``E``, ``N``, ``dE_m``, ``dN_m``).
    """
    fig = _canvas(7.0, 6.0)
    ax = fig.add_subplot()
    c = np.asarray(centres, dtype=float)
    for fp in footprints:
        p = np.asarray(fp, dtype=float)
        ax.fill(p[:, 0], p[:, 1], facecolor="tab:blue", alpha=0.06, edgecolor="tab:blue", linewidth=0.6)
    ax.plot(c[:, 0], c[:, 1], "k^", markersize=5, label="camera centres")
    numbers: dict = {"n_images": int(len(c))}
    if points_en is not None and residuals is not None and len(points_en):
        p = np.asarray(points_en, dtype=float)
        r = np.asarray(residuals, dtype=float)[:, :2]
        extent = max(np.ptp(np.vstack([c[:, :2], p[:, :2]]), axis=0).max(), 1.0)
        biggest = max(float(np.max(np.hypot(r[:, 0], r[:, 1]))), 1e-9)
        k = exaggeration or _nice(0.08 * extent / biggest)
        ax.quiver(p[:, 0], p[:, 1], r[:, 0] * k, r[:, 1] * k, angles="xy", scale_units="xy", scale=1.0,
                  color="tab:red", width=0.004, label=f"residuals x{k:g}")
        ax.plot(p[:, 0], p[:, 1], "o", mfc="none", mec="tab:red", markersize=5)
        ref = _nice(biggest)
        x0, y0 = c[:, 0].min(), c[:, 1].min() - 0.06 * extent
        ax.annotate("", xy=(x0 + ref * k, y0), xytext=(x0, y0),
                    arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 1.5})
        ax.text(x0, y0 - 0.02 * extent, f"{ref:g} m", color="tab:red", va="top")
        ax.plot([x0], [y0 - 0.07 * extent], alpha=0.0)  # keep the scale arrow and its label inside the axes
        numbers.update({"exaggeration": k, "scale_arrow_m": ref, "points": [
            {"id": ids[i] if ids is not None else str(i), "E": float(p[i, 0]), "N": float(p[i, 1]),
             "dE_m": _f(r[i, 0]), "dN_m": _f(r[i, 1])} for i in range(len(p))]})
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("E (m)")
    ax.set_ylabel("N (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=30)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title)
    return Figure("block", title, _png(fig), "Camera centres and footprints; red arrows are check-point "
                  "residuals (estimated minus surveyed), exaggerated, with a scale arrow.", numbers)


def image_residual_figure(binned, exaggeration: float | None = None,
                          title: str = "Reprojection residuals over the image") -> Figure:
    """Mean residual vectors per bin over the image frame, exaggerated, with a scale arrow.

    Args:
        binned: an :class:`aerocal.assess.BinnedResiduals`: the mean reprojection residual (pixels) per bin of
            the image (origin at the top-left corner, y down, drawn with y down); empty bins are not drawn.
        exaggeration: the factor the vectors are drawn at (default: the largest drawn as 0.8 of a bin's shorter
            side, the factor rounded to 1, 2 or 5 x 10^k).
        title: the figure's title.

    Returns:
        :class:`Figure` ``"image_residuals"``; ``numbers`` hold ``exaggeration``, ``scale_arrow_px`` and the
        binned grid (:meth:`aerocal.assess.BinnedResiduals.to_dict`).
    """
    fig = _canvas(7.0, 5.6)
    ax = fig.add_subplot()
    x, y = binned.centres()
    m = binned.mean
    has = binned.count > 0
    length = np.hypot(m[..., 0], m[..., 1])
    biggest = max(float(length[has].max()) if has.any() else 0.0, 1e-9)
    cell = min(binned.width / m.shape[1], binned.height / m.shape[0])
    k = exaggeration or _nice(0.8 * cell / biggest)
    ax.quiver(x[has], y[has], m[..., 0][has] * k, m[..., 1][has] * k, angles="xy", scale_units="xy", scale=1.0,
              color="tab:red", width=0.005)
    ax.add_patch(_rect(binned.width, binned.height))
    ref = _nice(biggest)
    ax.annotate("", xy=(0.05 * binned.width + ref * k, -0.06 * binned.height),
                xytext=(0.05 * binned.width, -0.06 * binned.height),
                arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 1.5}, annotation_clip=False)
    ax.text(0.05 * binned.width, -0.09 * binned.height, f"{ref:g} px (x{k:g})", color="tab:red")
    ax.set_xlim(-0.05 * binned.width, 1.05 * binned.width)
    ax.set_ylim(1.05 * binned.height, -0.14 * binned.height)  # y down, as in the image
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title(title)
    return Figure("image_residuals", title, _png(fig), "Mean reprojection residual per image region "
                  "(exaggerated); a pattern means the camera model misses something.",
                  {"exaggeration": k, "scale_arrow_px": ref, **binned.to_dict()})


def _rect(w: float, h: float):
    return Rectangle((0, 0), w, h, fill=False, edgecolor="0.4")


def io_at_temperatures(camera, model, temperatures) -> dict[str, np.ndarray]:
    """Focal length and principal point (pixels) that a thermal IO ``model`` gives ``camera`` at temperatures.

    ``model=None`` (a certificate without a thermal model) gives the constant IO of ``camera``. A model
    with ``camera_at`` (:class:`~aerocal.camera.LinearThermalModel`) is evaluated exactly; a model that
    only corrects measurements (``correct(uv, T)``: similarity, polynomial) is summarised by the
    equivalent IO: the scale ``s`` and shift ``a`` of the least-squares fit ``correct(p, T) = a + s p`` over
    a grid of pixels ``p`` of the frame give ``f(T) = f / s`` and ``(cx, cy)(T) = ((cx, cy) - a) / s``.

    Args:
        camera: the IO at the model's reference temperature (:class:`aerocal.camera.Camera`, pixels).
        model: the thermal model (with ``camera_at``, or with ``correct(uv, T)`` only), or ``None``.
        temperatures: sensor temperatures, degC (one value or a 1-D array).

    Returns:
        ``{"f", "cx", "cy"}``: float arrays, pixels, one value per temperature.
    """
    t = np.atleast_1d(np.asarray(temperatures, dtype=float))
    out = {n: np.full(t.shape, float(getattr(camera, n))) for n in ("f", "cx", "cy")}
    if model is None:
        return out
    if hasattr(model, "camera_at"):
        for i, x in enumerate(t):
            c = model.camera_at(camera, x)
            out["f"][i], out["cx"][i], out["cy"][i] = c.f, c.cx, c.cy
        return out
    u, v = np.meshgrid(np.linspace(0.0, camera.width, 9), np.linspace(0.0, camera.height, 7))
    uv = np.column_stack([u.ravel(), v.ravel()])
    design = np.zeros((2 * len(uv), 3))
    design[0::2, 0] = 1.0
    design[1::2, 1] = 1.0
    design[0::2, 2] = uv[:, 0]
    design[1::2, 2] = uv[:, 1]
    for i, x in enumerate(t):
        ax_, ay_, s = np.linalg.lstsq(design, np.asarray(model.correct(uv, x), dtype=float).ravel(), rcond=None)[0]
        out["f"][i], out["cx"][i], out["cy"][i] = camera.f / s, (camera.cx - ax_) / s, (camera.cy - ay_) / s
    return out


def temperature_io_figure(
    temperatures: np.ndarray, f: np.ndarray, cx: np.ndarray, cy: np.ndarray,
    model=None, camera=None, title: str = "Interior orientation against sensor temperature",
    caption: str | None = None,
) -> Figure:
    """Per-image focal length and principal point (pixels) against sensor temperature (degC).

    With a ``camera`` (IO at the model's reference temperature) the certificate's line is drawn too over the
    images' temperatures: the thermal ``model`` (:func:`io_at_temperatures`), or, with ``model=None``, the
    constant IO of a certificate without a thermal model.

    Args:
        temperatures: each image's sensor temperature (N,), degC.
        f, cx, cy: each image's focal length and principal point (N,), pixels.
        model: the certificate's thermal model, or ``None``.
        camera: the certificate's camera (IO at the model's reference temperature); ``None``: no line.
        title: the figure's title.
        caption: the caption (default: a sentence saying what is drawn).

    Returns:
        :class:`Figure` ``"temperature_io"``; ``numbers`` hold ``temperature_c``, ``f_px``, ``cx_px``, ``cy_px``,
        ``fitted_slope_px_per_degC`` (the least-squares slope of each series that has two finite points at
        different temperatures) and ``model`` (its ``to_dict()``, or ``None``).
    """
    t = np.asarray(temperatures, dtype=float)
    series = {"f": np.asarray(f, dtype=float), "cx": np.asarray(cx, dtype=float), "cy": np.asarray(cy, dtype=float)}
    fig = _canvas(7.0, 7.0)
    axes = fig.subplots(3, 1, sharex=True)
    numbers: dict = {"temperature_c": t.tolist()}
    slopes = {}
    line = None
    if camera is not None and np.isfinite(t).any():
        tt = np.linspace(np.nanmin(t), np.nanmax(t), 20)
        line = (tt, io_at_temperatures(camera, model, tt),
                "thermal model" if model is not None else "certificate: constant IO (no thermal model)")
    for ax, (name, v) in zip(axes, series.items(), strict=True):
        ax.plot(t, v, "o", markersize=4, label="per image")
        ok = np.isfinite(t) & np.isfinite(v)
        if ok.sum() >= 2 and np.ptp(t[ok]) > 0:
            slopes[name] = float(np.polyfit(t[ok], v[ok], 1)[0])
        if line is not None:
            ax.plot(line[0], line[1][name], "-", color="tab:orange", label=line[2])
        ax.set_ylabel(f"{name} (px)")
        ax.ticklabel_format(axis="y", useOffset=False, style="plain")
        ax.grid(alpha=0.3)
        numbers[f"{name}_px"] = [_f(x) for x in v]
    axes[0].legend(fontsize=8)
    axes[-1].set_xlabel("sensor temperature (degC)")
    axes[0].set_title(title)
    numbers["fitted_slope_px_per_degC"] = slopes
    numbers["model"] = model.to_dict() if model is not None else None
    return Figure("temperature_io", title, _png(fig), caption or "Focal length and principal point against "
                  "the sensor temperature of each image.", numbers)


#: a map is drawn from at most this many cells along its longer side (means of blocks of cells): a figure shows
#: about a thousand pixels across, and drawing every cell of a city's dense DSM (7909 x 9610) held the report
#: step for minutes and gigabytes
MAX_DRAWN_CELLS = 1200


def drawn(grid: np.ndarray, step: int) -> np.ndarray:
    """``grid`` (rows, cols) as a map draws it: the mean of each block of ``step`` x ``step`` cells, NaN cells left
    out, NaN where a block has none (float32); ``grid`` itself when ``step`` is 1."""
    if step <= 1:
        return grid
    rows, cols = grid.shape
    R, C = -(-rows // step), -(-cols // step)
    total = np.zeros((R, C))
    count = np.zeros((R, C))
    for r0 in range(0, rows, step * 64):  # bands of block rows: a city's grid is not copied whole
        band = np.asarray(grid[r0:r0 + step * 64], dtype=np.float32)
        br = -(-band.shape[0] // step)
        padded = np.full((br * step, C * step), np.nan, dtype=np.float32)
        padded[:band.shape[0], :cols] = band
        blocks = padded.reshape(br, step, C, step)
        ok = np.isfinite(blocks)
        total[r0 // step:r0 // step + br] = np.where(ok, blocks, 0.0).sum(axis=(1, 3), dtype=np.float64)
        count[r0 // step:r0 // step + br] = ok.sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).astype(np.float32)


def drawing_step(shape: tuple[int, ...]) -> int:
    """Cells per side of the blocks a grid of ``shape`` is drawn from (:data:`MAX_DRAWN_CELLS`)."""
    return max(1, -(-max(shape[:2]) // MAX_DRAWN_CELLS))


def dem_difference_figure(diff, title: str = "DSM minus reference") -> Figure:
    """Map and histogram of an :class:`aerocal.assess.DemDifference` (tested minus reference).

    Args:
        diff: the difference (metres, on the tested DEM's grid, E, N in the flight CRS); its transects are drawn
            on the map.
        title: the figure's title.

    Returns:
        :class:`Figure` ``"dem_difference"``: the map (colours symmetric about 0 out to ``|median| + 3 NMAD``, at
        least 0.1 m) and the histogram with the mean and the median; ``numbers`` are ``diff.to_dict()``.
    """
    fig = _canvas(10.0, 4.6)
    ax_map, ax_hist = fig.subplots(1, 2, width_ratios=[1.3, 1.0])
    d = drawn(diff.difference, drawing_step(diff.difference.shape))
    lim = max(abs(diff.median) + 3 * (diff.nmad if np.isfinite(diff.nmad) else 1.0), 0.1)
    w, s, e, n = diff.extent
    im = ax_map.imshow(d, cmap="RdBu_r", vmin=-lim, vmax=lim, extent=(w, e, s, n), interpolation="nearest")
    fig.colorbar(im, ax=ax_map, label="difference (m)", shrink=0.8)
    for t in diff.transects:
        ax_map.plot([t["start"][0], t["end"][0]], [t["start"][1], t["end"][1]], "k-", lw=1)
    ax_map.set_xlabel("E (m)")
    ax_map.set_ylabel("N (m)")
    ax_map.ticklabel_format(useOffset=False, style="plain")
    ax_map.tick_params(axis="x", labelrotation=30)
    edges, counts = diff.histogram_edges, diff.histogram_counts
    ax_hist.bar(0.5 * (edges[:-1] + edges[1:]), counts, width=np.diff(edges), color="0.5")
    ax_hist.axvline(diff.mean, color="tab:red", label=f"mean {diff.mean:.2f} m")
    ax_hist.axvline(diff.median, color="tab:blue", ls="--", label=f"median {diff.median:.2f} m")
    ax_hist.set_xlabel("difference (m)")
    ax_hist.set_ylabel("cells")
    ax_hist.legend(fontsize=8)
    ax_hist.set_title(f"NMAD {diff.nmad:.2f} m, n {diff.n}")
    fig.suptitle(title)
    return Figure("dem_difference", title, _png(fig), f"Tested DSM minus reference ({diff.selection}).",
                  diff.to_dict())


def hillshade(heights: np.ndarray, cell_m: float, azimuth_deg: float = 315.0, altitude_deg: float = 45.0
              ) -> np.ndarray:
    """Hillshade (0 dark to 1 lit) of a height grid (rows north to south, ``cell_m`` metres), lit from
    ``azimuth_deg`` (clockwise from north) at ``altitude_deg`` above the horizon, as GDAL's ``gdaldem hillshade``
    computes it (Horn's gradient); NaN where a height or a neighbour's is missing."""
    z = np.asarray(heights, dtype=float)
    p = np.pad(z, 1, mode="edge")
    dzdx = ((p[:-2, 2:] + 2 * p[1:-1, 2:] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[1:-1, :-2] + p[2:, :-2])) / (8 * cell_m)
    dzdy = ((p[2:, :-2] + 2 * p[2:, 1:-1] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[:-2, 1:-1] + p[:-2, 2:])) / (8 * cell_m)
    slope = np.arctan(np.hypot(dzdx, dzdy))
    aspect = np.arctan2(dzdy, -dzdx)
    zen, az = np.radians(90.0 - altitude_deg), np.radians(360.0 - azimuth_deg + 90.0)
    return np.clip(np.cos(zen) * np.cos(slope) + np.sin(zen) * np.sin(slope) * np.cos(az - aspect), 0.0, 1.0)


def surface_figure(dsm, measured: np.ndarray | None, title: str = "Surface model") -> Figure:
    """The DSM as a hillshade beside its heights, the filled cells tinted.

    Args:
        dsm: the flight's DSM (:class:`aerocal.products.dsm.Dsm`).
        measured: bool (the DSM's shape), the cells with a measured height (the dense cloud's), or ``None`` (a
            tie-point DSM: every cell is drawn alike).
        title: the figure's title.

    Returns:
        :class:`Figure` ``"surface"``; ``numbers``: the cell size (m), the height range (m) and the measured
        fraction.
    """
    fig = _canvas(10.0, 4.6)
    ax_shade, ax_height = fig.subplots(1, 2)
    west, south, east, north = dsm.bounds()
    extent = (west, east, south, north)
    step = drawing_step(dsm.shape)
    heights = drawn(dsm.heights, step)
    shade = hillshade(heights, dsm.cell_m * step)
    ax_shade.imshow(shade, cmap="gray", vmin=0, vmax=1, extent=extent, interpolation="nearest")
    if measured is not None and not measured.all():
        tint = np.zeros(heights.shape + (4,), dtype=np.float32)
        tint[(drawn(measured, step) < 0.5) & np.isfinite(heights)] = (1.0, 0.55, 0.0, 0.45)
        ax_shade.imshow(tint, extent=extent, interpolation="nearest")
    ax_shade.set_title("hillshade" + (", filled cells in orange" if measured is not None else ""))
    finite = dsm.heights[np.isfinite(dsm.heights)]
    lo, hi = np.percentile(finite, [1, 99]) if finite.size else (0.0, 1.0)
    del finite
    im = ax_height.imshow(heights, cmap="terrain", vmin=lo, vmax=max(hi, lo + 0.1), extent=extent,
                          interpolation="nearest")
    fig.colorbar(im, ax=ax_height, label="height (m)", shrink=0.8)
    ax_height.set_title("heights")
    for ax in (ax_shade, ax_height):
        ax.set_xlabel("E (m)")
        ax.ticklabel_format(useOffset=False, style="plain")
        ax.tick_params(axis="x", labelrotation=30)
    ax_shade.set_ylabel("N (m)")
    fig.suptitle(title)
    frac = None if measured is None else float(np.mean(measured[np.isfinite(dsm.heights)]))
    caption = (f"The DSM, {dsm.shape[1]} x {dsm.shape[0]} cells of {dsm.cell_m:.3g} m"
               + (f" (drawn as blocks of {step} x {step} cells)" if step > 1 else "")
               + ("." if frac is None else f"; {100 * frac:.0f} % of its cells are measured by the dense cloud, "
                  "the rest filled by interpolation (band 2 of dsm.tif)."))
    return Figure("surface", title, _png(fig), caption,
                  {"cell_m": _f(dsm.cell_m), "height_range_m": [_f(lo), _f(hi)], "measured_fraction": frac})


def laser_range_figure(laser: Mapping) -> Figure:
    """Per frame, the range along the camera's axis to the surface against the laser's, the frames no fit used
    apart from those whose range observed the block.

    Args:
        laser: the products step's ``laser_range`` document (:func:`aerocal.pipeline.mosaic_step.laser_output`):
            ``images`` (image id -> [laser m, surface m]) of the held-out frames, ``fitted["images"]`` of the
            others, ``verdict``.

    Returns:
        :class:`Figure` ``"laser_range"``; ``numbers``: the held-out and fitted medians (m).
    """
    fig = _canvas(9.0, 4.2)
    ax_range, ax_diff = fig.subplots(1, 2)
    groups = (("no fit used it", laser.get("images") or {}, "o", "tab:blue"),
              ("observed the block", (laser.get("fitted") or {}).get("images") or {}, "s", "tab:orange"))
    for label, images, marker, colour in groups:
        if not images:
            continue
        ids = np.array([int(k) for k in images])
        pairs = np.array(list(images.values()), dtype=float)
        order = np.argsort(ids)
        ax_range.plot(ids[order], pairs[order, 0], marker, mfc="none", color=colour, label=f"laser, {label}")
        ax_range.plot(ids[order], pairs[order, 1], marker, color=colour, label=f"surface, {label}")
        ax_diff.plot(ids[order], pairs[order, 1] - pairs[order, 0], marker, color=colour, label=label)
    ax_range.set_xlabel("image id")
    ax_range.set_ylabel("range along the camera's axis (m)")
    ax_range.legend(fontsize=7)
    ax_diff.axhline(0.0, color="k", lw=0.8)
    ax_diff.set_xlabel("image id")
    ax_diff.set_ylabel("surface minus laser (m)")
    ax_diff.legend(fontsize=7)
    fig.suptitle("Surface against the laser range finder")
    fitted = laser.get("fitted") or {}
    return Figure("laser_range", "Surface against the laser range finder", _png(fig), str(laser.get("verdict", "")),
                  {"held_out_median_m": _f(laser.get("median_m")), "fitted_median_m": _f(fitted.get("median_m"))})


def overview_figure(
    centres_en: np.ndarray,
    overlap: np.ndarray | None = None,
    overlap_extent: tuple[float, float, float, float] | None = None,
    mosaic: np.ndarray | None = None,
    mosaic_extent: tuple[float, float, float, float] | None = None,
    control: Sequence[tuple[str, float, float]] = (),
    check: Sequence[tuple[str, float, float]] = (),
    title: str = "Overview",
    caption: str = "",
) -> Figure:
    """The flight seen from above: orthomosaic thumbnail, image overlap, camera centres and ground control.

    Args:
        centres_en: camera centres (N, 2+), E, N metres in the flight CRS.
        overlap: the number of images that see each ground cell, (rows, cols) counts, row 0 north; cells of 0
            are left blank and cells seen by one image only are red.
        overlap_extent: ``(west, east, south, north)`` metres of ``overlap``; it is drawn only with both.
        mosaic: the orthomosaic thumbnail, (H, W) grey values, NaN where empty.
        mosaic_extent: ``(west, east, south, north)`` metres of ``mosaic``; it is drawn only with both.
        control: control points (triangles) as ``(id, E, N)``.
        check: check points (circles) as ``(id, E, N)``.
        title: the figure's title.
        caption: the caption.

    Returns:
        :class:`Figure` ``"overview"``; ``numbers`` hold ``n_images``, ``control_points`` and ``check_points``,
        with a mosaic ``mosaic_extent_m``, and with overlap ``overlap_extent_m``, ``overlap_median`` and
        ``overlap_fraction_below_3`` (over the cells seen at all) and ``overlap_max``.
    """
    fig = _canvas(8.0, 6.6)
    ax = fig.add_subplot()
    c = np.asarray(centres_en, dtype=float)
    numbers: dict = {"n_images": int(len(c))}
    if mosaic is not None and mosaic_extent is not None:
        ax.imshow(np.ma.masked_invalid(mosaic), cmap="gray", extent=mosaic_extent, interpolation="bilinear",
                  zorder=0)
        numbers["mosaic_extent_m"] = [float(v) for v in mosaic_extent]
    if overlap is not None and overlap_extent is not None:
        top = max(int(overlap.max()), 1)
        steps = [1, 2, 3, 4, 5, 6, 9, 12, 16, 20, 30, 50, 100]
        bounds = [b for b in steps if b <= top] + [top + 1]
        bounds = sorted(set(bounds))
        base = colormaps["viridis"].resampled(max(len(bounds) - 2, 1))
        colours = ["#d62728"] + [base(i) for i in range(len(bounds) - 2)]  # one image only: red
        cmap = ListedColormap(colours[: len(bounds) - 1])
        shown = np.ma.masked_where(overlap <= 0, overlap)
        im = ax.imshow(shown, cmap=cmap, norm=BoundaryNorm(bounds, cmap.N), extent=overlap_extent,
                       interpolation="nearest", alpha=0.45 if mosaic is not None else 0.8, zorder=1)
        cb = fig.colorbar(im, ax=ax, shrink=0.8, label="images seeing the ground")
        cb.set_ticks([0.5 * (a + b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)])
        cb.set_ticklabels([str(a) if b - a == 1 else f"{a}-{b - 1}" for a, b in zip(bounds[:-1], bounds[1:],
                                                                                    strict=True)])
        seen = overlap[overlap > 0]
        numbers.update({"overlap_extent_m": [float(v) for v in overlap_extent],
                        "overlap_median": float(np.median(seen)) if seen.size else 0.0,
                        "overlap_max": int(overlap.max()),
                        "overlap_fraction_below_3": float(np.mean(seen < 3)) if seen.size else 0.0})
    ax.plot(c[:, 0], c[:, 1], "k.", markersize=4, label="camera centres", zorder=3)
    for points, marker, colour, label in ((control, "^", "tab:blue", "control points"),
                                          (check, "o", "tab:orange", "check points")):
        if not len(points):
            continue
        e = np.array([p[1] for p in points], dtype=float)
        n = np.array([p[2] for p in points], dtype=float)
        ax.plot(e, n, marker, mfc=colour, mec="k", markersize=8, linestyle="none", label=label, zorder=4)
        for name, x, y in points:
            ax.annotate(str(name), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, zorder=5,
                        bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.7})
    numbers.update({"control_points": len(control), "check_points": len(check)})
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("E (m)")
    ax.set_ylabel("N (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=30)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    ax.set_title(title)
    return Figure("overview", title, _png(fig), caption, numbers)


def tie_point_figure(
    points_en: np.ndarray, n_obs: np.ndarray, centres_en: np.ndarray | None = None,
    title: str = "Tie points", caption: str = "",
) -> Figure:
    """Tie points coloured by the number of images that measured each, beside the histogram of that number.

    Args:
        points_en: tie points (N, 2+), E, N metres in the flight CRS.
        n_obs: the number of images that measured each point (N,).
        centres_en: camera centres (M, 2+), E, N metres, drawn too when given.
        title: the figure's title.
        caption: the caption.

    Returns:
        :class:`Figure` ``"tie_points"``; ``numbers`` hold ``n_points``, ``images_per_point_median``,
        ``images_per_point_mean`` and ``images_per_point_counts`` (images per point -> number of points).
    """
    p = np.asarray(points_en, dtype=float)
    k = np.asarray(n_obs, dtype=float)
    fig = _canvas(10.0, 5.0)
    ax, ax_h = fig.subplots(1, 2, width_ratios=[1.6, 1.0])
    order = np.argsort(k)  # the best-seen points on top
    hi = max(float(np.percentile(k, 98)), 3.0)
    sc = ax.scatter(p[order, 0], p[order, 1], c=k[order], s=2, cmap="viridis", vmin=2, vmax=hi,
                    rasterized=True)
    fig.colorbar(sc, ax=ax, shrink=0.8, label="images measuring the point")
    if centres_en is not None and len(centres_en):
        c = np.asarray(centres_en, dtype=float)
        ax.plot(c[:, 0], c[:, 1], "k.", markersize=3, label="camera centres")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("E (m)")
    ax.set_ylabel("N (m)")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=30)
    top = int(k.max())
    ax_h.hist(k, bins=np.arange(1.5, top + 1.5, 1.0 if top < 40 else max(top // 30, 1)), color="0.5")
    ax_h.set_xlabel("images measuring the point")
    ax_h.set_ylabel("tie points")
    fig.suptitle(title)
    numbers = {"n_points": int(len(p)), "images_per_point_median": float(np.median(k)),
               "images_per_point_mean": float(np.mean(k)),
               "images_per_point_counts": {str(int(v)): int(n) for v, n in zip(*np.unique(k, return_counts=True),
                                                                               strict=True)}}
    return Figure("tie_points", title, _png(fig), caption, numbers)


def distortion_displacement(camera, uv: np.ndarray) -> np.ndarray:
    """How far (pixels, (N, 2)) the lens model moves each ideal pixel ``uv`` (N, 2): the recorded pixel of
    the ray that an ideal pinhole with the same f, cx, cy would put at ``uv``, minus ``uv``. Radial (k1..k3),
    tangential (p1, p2) and affinity/skew (b1, b2) together."""
    uv = np.asarray(uv, dtype=float)
    xy = np.stack([(uv[..., 0] - camera.cx) / camera.f, (uv[..., 1] - camera.cy) / camera.f], axis=-1)
    return camera.normalised_to_pixels(camera.distort(xy)) - uv


def distortion_figure(camera, title: str = "Lens distortion", caption: str = "") -> Figure:
    """The certificate's distortion: displacement vectors over the frame and a radial profile.

    Left, the displacement (:func:`distortion_displacement`) of a grid of pixels over the frame (exaggerated,
    with a scale arrow; the principal point marked); right, the displacement's length against the distance from
    the principal point (pixels), along +x out to the distance of the farthest corner, positive outwards.

    Args:
        camera: the camera (:class:`aerocal.camera.Camera`, pixels with the origin at the top-left corner).
        title: the figure's title.
        caption: the caption.

    Returns:
        :class:`Figure` ``"distortion"``; ``numbers`` hold ``max_displacement_px`` (over the grid),
        ``corner_displacement_px`` (at the four corners), ``exaggeration`` and ``scale_arrow_px``.
    """
    w, h = float(camera.width), float(camera.height)
    u, v = np.meshgrid(np.linspace(0.0, w, 13), np.linspace(0.0, h, 10))
    uv = np.column_stack([u.ravel(), v.ravel()])
    d = distortion_displacement(camera, uv)
    length = np.hypot(d[:, 0], d[:, 1])
    biggest = max(float(length.max()), 1e-9)
    fig = _canvas(10.0, 4.6)
    ax, ax_r = fig.subplots(1, 2, width_ratios=[1.3, 1.0])
    k = _nice(0.09 * max(w, h) / biggest)
    ax.quiver(uv[:, 0], uv[:, 1], d[:, 0] * k, d[:, 1] * k, angles="xy", scale_units="xy", scale=1.0,
              color="tab:purple", width=0.004)
    ax.add_patch(_rect(w, h))
    ax.plot([camera.cx], [camera.cy], "k+", markersize=10)
    ref = _nice(biggest)
    ax.annotate("", xy=(0.05 * w + ref * k, -0.06 * h), xytext=(0.05 * w, -0.06 * h),
                arrowprops={"arrowstyle": "->", "color": "tab:purple", "lw": 1.5}, annotation_clip=False)
    ax.text(0.05 * w, -0.09 * h, f"{ref:g} px (drawn x{k:g})", color="tab:purple")
    ax.set_xlim(-0.08 * w, 1.08 * w)
    ax.set_ylim(1.08 * h, -0.16 * h)
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    ax.set_title("displacement over the frame")
    corner = float(np.hypot(max(camera.cx, w - camera.cx), max(camera.cy, h - camera.cy)))
    r = np.linspace(0.0, corner, 60)
    radial = distortion_displacement(camera, np.column_stack([camera.cx + r, np.full_like(r, camera.cy)]))
    rd = np.hypot(radial[:, 0], radial[:, 1]) * np.sign(radial[:, 0] + 1e-300)
    ax_r.plot(r, rd, "-", color="tab:purple", label="along +x from the principal point")
    ax_r.axhline(0.0, color="0.6", lw=0.8)
    ax_r.axvline(min(w, h) / 2, color="0.6", ls=":", lw=0.8)
    ax_r.set_xlabel("distance from the principal point (px)")
    ax_r.set_ylabel("displacement (px, + outwards)")
    ax_r.grid(alpha=0.3)
    ax_r.legend(fontsize=8)
    ax_r.set_title("radial profile")
    fig.suptitle(title)
    corners = distortion_displacement(camera, camera.corners())
    numbers = {"max_displacement_px": biggest,
               "corner_displacement_px": [_f(np.hypot(x, y)) for x, y in corners],
               "exaggeration": k, "scale_arrow_px": ref}
    return Figure("distortion", title, _png(fig), caption, numbers)
