"""The products step. When the flight has frames with pixels (``images/`` of the flight folder): the dense surface
matched in them (:mod:`aerocal.products.dense`; ``cloud.laz``), its DSM at one ground sample per cell with the
measured cells in band 2, the DTM filtered from it, and the tie points' DSM beside it (``sparse_dsm``); without
frames, the DSM gridded from the adjusted tie points (:func:`aerocal.products.dsm.dsm_from_points`, GeoTIFF).
Then, on that surface, the orthomosaic in the flight's CRS from the frames' original radiometry
(:func:`aerocal.products.mosaic.build_mosaic`, tiles on a Dask client), with a temperature raster for FLIR
radiometric frames. A flight without frames gets the DSM only. Where the frames record a laser range along the
camera's axis, the surface is checked against it (:mod:`aerocal.products.range_check`)."""

from __future__ import annotations

import functools
import tempfile
import time
from collections.abc import Iterable, Mapping
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from aerocal.adjust.laser import fitted_lasers
from aerocal.assess import compare_dems
from aerocal.certificates.document import Certificate
from aerocal.diagnose.extension import frame_terms
from aerocal.enhance import EnhanceConfig, StretchParams, enhance, grey, stretch_params
from aerocal.ingest import read_raw
from aerocal.ingest.flir import common_camera_info, raw_to_celsius
from aerocal.io import file_sha256
from aerocal.matching import ExecutionConfig
from aerocal.pipeline.config import MosaicStepConfig
from aerocal.pipeline.dataset import REFERENCE_DSM
from aerocal.pipeline.progress import step_progress
from aerocal.pipeline.runner import FileOutput, JsonOutput, Runner, StepInputs, StepResult
from aerocal.products.coverage import seen_cells
from aerocal.products.dense import dense_cloud, own_views, views_of_cells
from aerocal.products.dsm import Dsm, DsmConfig, cells_from_points, dsm_from_points, filled, read_dsm, write_dsm
from aerocal.products.mosaic import (
    FrameCache,
    FrameGeometry,
    MosaicConfig,
    build_mosaic,
    frames_from_poses,
    write_temperature_raster,
)
from aerocal.products.pointcloud import write_laz
from aerocal.products.range_check import flying_height_check, laser_range_check
from aerocal.products.terrain import dtm_from_dsm
from aerocal.report import wording


def frame_paths(flight: dict, images: pa.Table) -> dict[int, Path]:
    """Image id -> frame file for the frames that exist: the ``path`` column, else ``images/<name>`` of the
    flight folder (rendered frames beside an observations-mode flight); none for a flight without a folder."""
    folder = Path(flight["folder"]) if flight.get("folder") else None
    out = {}
    for iid, name, path in zip(images.column("image_id").to_pylist(), images.column("name").to_pylist(),
                               images.column("path").to_pylist(), strict=True):
        for cand in (Path(path) if path else None, folder / "images" / name if folder and name else None):
            if cand is not None and cand.is_file():
                out[int(iid)] = cand
                break
    return out


def reference_dsm_path(flight: dict) -> Path | None:
    """The flight folder's reference DSM (:data:`aerocal.pipeline.dataset.REFERENCE_DSM`), or ``None``."""
    if not flight.get("folder"):
        return None
    path = Path(flight["folder"]) / REFERENCE_DSM
    return path if path.is_file() else None


def flight_gsd(poses: pa.Table, points: pa.Table, camera_f_px: float) -> tuple[float, float]:
    """(ground sample distance in metres, ground height in metres): the median camera height above the median
    tie-point height over the focal length in pixels (GSD = H p / c)."""
    ground = float(np.median(points.column("Z").to_numpy()))
    height = float(np.median(poses.column("Z").to_numpy())) - ground
    return height / camera_f_px, ground


def temperature_output(paths: Iterable[Path], counts_path: Path, work: Path, info: dict[str, Any]) -> dict:
    """``temperature`` (float32 degC GeoTIFF on the orthomosaic's grid) when every frame is a FLIR
    radiometric JPEG with one temperature scale; ``info["temperature"]`` says what was done and why."""
    flir, why = common_camera_info(list(paths))
    if flir is None:
        info["temperature"] = f"no temperature raster: {why}"
        return {}
    path = write_temperature_raster(counts_path, work / "temperature.tif", lambda raw: raw_to_celsius(raw, flir))
    info["temperature"] = (
        f"temperature.tif: object temperature (degC) from the counts mosaic, emissivity {flir.emissivity:g}, "
        f"object distance {flir.object_distance_m:g} m, as the camera recorded them ({why})"
    )
    return {"temperature": FileOutput(path, "temperature", temporary=True)}


def frames_of(images: pa.Table, poses: pa.Table, cert: Certificate, paths: Mapping[int, Path]
              ) -> list[FrameGeometry]:
    """The adjusted frames that have pixels, with what the certificate holds for each: its IO (at the frame's
    temperature under a thermal model), the readout's motion and the thermal rotation."""
    thermal = None if cert.thermal is None else cert.thermal.model
    temps = {int(k): float(v) for k, v in zip(images.column("image_id").to_pylist(),
                                              images.column("temperature_c").to_pylist(), strict=True)
             if v is not None}
    sel = poses.filter(np.isin(poses.column("image_id").to_numpy(), list(paths)))
    motion, turn = frame_terms(cert, images, poses)  # the certificate's readout and thermal rotation
    return frames_from_poses(sel, cert.camera, temps if thermal is not None else None, thermal, motion, turn)


#: the enhanced frames each process keeps (:func:`dense_frame`): a reference and its neighbours are the next
#: references' neighbours too (150 rendered city frames were loaded 624 times)
_dense_frames = FrameCache(512 * 2**20)


def dense_frame(image_id: int, paths: Mapping[int, str], params: StretchParams,
                config: EnhanceConfig) -> tuple[np.ndarray, np.ndarray]:
    """(8-bit frame for dense matching, grey frame values) of one image, enhanced as for tie-point matching
    (module level: it runs on Dask workers), through this process's :class:`~aerocal.products.mosaic.FrameCache`
    (read-only)."""

    def read() -> tuple[np.ndarray, np.ndarray]:
        raw = read_raw(paths[image_id])
        return enhance(raw, params, config), grey(raw).astype(np.float32)

    return _dense_frames.get((str(paths[image_id]), params, config), read)  # type: ignore[return-value]


def forget_dense_frames() -> None:
    """Release the frames :func:`dense_frame` keeps in this process (module level: run on every Dask worker when
    the dense surface is done)."""
    _dense_frames.clear()


def difference_to(dsm: Dsm, reference: Path, measured: np.ndarray) -> dict[str, Any]:
    """The DSM minus a reference surface on its measured cells: n, mean, median, NMAD and RMSE (metres),
    completeness (measured cells over the cells inside the reference); a reference that cannot be read gives
    ``{"error": why}`` (the report says the same)."""
    try:
        ref = read_dsm(reference)
    except ValueError as exc:
        return {"error": str(exc)}
    inside = np.zeros(dsm.shape, dtype=bool)
    for rows, e, n in dsm.centre_blocks():  # a block of rows at a time: a city's dense DSM has 76 M cells
        inside[rows] = np.isfinite(ref.heights_on(e, n))
    diff = compare_dems(dsm, ref, mask=measured & inside, selection="measured cells")
    return {"n": diff.n, "mean_m": diff.mean, "median_m": diff.median, "nmad_m": diff.nmad, "rmse_m": diff.rmse,
            "completeness": float(np.count_nonzero(measured & inside) / max(np.count_nonzero(inside), 1))}


def dense_surface(flight: dict, frames: list[FrameGeometry], points: pa.Table, cert: Certificate,
                  paths: Mapping[int, Path], ground: float, config: MosaicStepConfig,
                  execution: ExecutionConfig | None, work: Path, info: dict[str, Any], background: Executor
                  ) -> tuple[Dsm, np.ndarray, np.ndarray, Future[Path]] | None:
    """The dense cloud of the adjusted frames (:func:`aerocal.products.dense.dense_cloud`), its DSM at about one
    ground sample per cell, where that DSM is measured (:meth:`Dsm.measured`: the cells holding points; the rest
    is filled), the views that agree on each measured cell (:func:`aerocal.products.dense.cell_views`), and the
    cloud's LAZ file (``cloud.laz`` in ``work``) being written on ``background``: the future of its path, which
    the caller awaits before the step ends (nothing else reads the file). ``info["dense"]`` records what was
    matched. ``None`` when no point survives the fusion (frames without texture): the products then stand on the
    tie points, and ``info["surface"]`` says why.

    ``frames`` are those the orthomosaic rectifies (:func:`frames_of`): the certificate's IO at each frame's
    temperature, its readout and thermal rotation.

    Raises:
        ValueError: ``config.dense`` is ``None``.
    """
    ecfg = EnhanceConfig()
    names = {i: str(p) for i, p in paths.items()}
    params = stretch_params(list(names.values()), percent=ecfg.percent, loader=lambda p: grey(read_raw(p)))
    load = functools.partial(dense_frame, paths=names, params=params, config=ecfg)
    tie = np.column_stack([points.column(c).to_numpy() for c in ("X", "Y", "Z")])
    dcfg = config.dense
    if dcfg is None:
        raise ValueError("dense_surface: MosaicStepConfig.dense is None (the tie points' surface was asked for)")
    serial = len(frames) * cert.camera.width * cert.camera.height / 1e6 <= config.serial_max_megapixels
    start = time.perf_counter()
    with (execution or ExecutionConfig()).client(serial) as client:
        try:
            cloud = dense_cloud(frames, load, tie, ground, dcfg, client, step_progress("dense surface"))
        finally:
            forget_dense_frames()
            if client is not None:
                client.run(forget_dense_frames, on_error="ignore")
    seconds = time.perf_counter() - start
    if len(cloud.xyz) < 3:
        info["surface"] = (f"tie points: dense matching found no surface in {len(frames)} frames (no pair with "
                           "texture that two other views agree on)")
        return None
    # the cloud's cells first; the cloud is written and released before the holes are filled (a city's cloud is
    # 10^8 points, and the filling's triangulation and distance transforms need the memory)
    cells = cells_from_points(cloud.xyz, flight["crs"], gsd_m=cloud.gsd_m, config=config.dense_dsm)
    own = own_views(cloud, cells)
    flir, _ = common_camera_info(list(paths.values()))
    temperature = None if flir is None else functools.partial(raw_to_celsius, info=flir)
    stats, gsd, median_views = dict(cloud.stats), cloud.gsd_m, float(np.median(cloud.views))
    # the LAZ is written on a thread while the holes are filled and the rest of the step goes on: lazrs's compression
    # and the products' compiled loops release the GIL, so they share the cores (benchmarks/RESULTS.md, "Products
    # step: the LAZ, the DSMs' files and the DTM side by side"); the thread drops the cloud once it is written
    laz = background.submit(write_laz, cloud, work / "cloud.laz", flight["crs"], temperature)
    del cloud
    dsm = filled(cells, config.dense_dsm)
    del cells
    measured = dsm.measured()
    # no height where no frame sees the ground (aerocal.products.coverage): there the filling extrapolates. The
    # plane is the surface's lowest but for a thousandth of its cells: a few points tens of metres below the ground
    # (the demo's lowest lies 95 m under its 0.1st percentile) would widen every footprint by a tenth of its size
    low = float(np.percentile(dsm.heights[measured], 0.1))
    seen = seen_cells(frames, dsm, low) | measured
    dsm = replace(dsm, heights=np.where(seen, dsm.heights, np.float32(np.nan)))
    views = views_of_cells(own, measured)
    info["surface"] = "dense"
    info["dense"] = {**stats, "seconds": round(seconds, 1), "gsd_m": gsd, "dsm_cell_m": dsm.cell_m,
                     "measured_fraction": float(np.count_nonzero(measured) / np.count_nonzero(seen)),
                     "two_view_fraction": float(np.count_nonzero(views == 2) / max(np.count_nonzero(measured), 1)),
                     "median_views": median_views, "temperature": flir is not None}
    return dsm, measured, views, laz


def dense_files(dsm: Dsm, measured: np.ndarray, views: np.ndarray, sparse: Dsm, reference: Path | None,
                work: Path) -> tuple[dict[str, FileOutput], dict[str, Any]]:
    """The dense DSM's file (band 2 its measured cells, band 3 the views that agree on them) and the tie points'
    DSM beside it (outputs ``dsm`` and ``sparse_dsm``), and, when the flight has a reference surface, both DSMs'
    differences to it (``sparse_minus_reference_m``, ``dense_minus_reference_m``: :func:`difference_to`)."""
    out = {"dsm": FileOutput(write_dsm(dsm, work / "dsm.tif", measured, views), "dsm", temporary=True),
           "sparse_dsm": FileOutput(write_dsm(sparse, work / "sparse_dsm.tif"), "dsm", temporary=True)}
    info: dict[str, Any] = {}
    if reference is not None:
        info["sparse_minus_reference_m"] = difference_to(sparse, reference, sparse.distance_m == 0)
        info["dense_minus_reference_m"] = difference_to(dsm, reference, measured)
    return out, info


def laser_output(images: pa.Table, frames: list[FrameGeometry], dsm: Dsm, measured: np.ndarray,
                 gsd: float) -> dict[str, Any] | None:
    """The surface against the frames' laser ranges (:mod:`aerocal.products.range_check`), judged on the ranges no
    adjustment used (:func:`aerocal.adjust.laser.fitted_lasers` keeps every second one out of the fits), with the
    figures of the fitted ones beside (``fitted``); ``None`` when no frame records a range."""
    ids = np.asarray(images.column("image_id").to_pylist(), dtype=np.int64)
    ranges = np.array([np.nan if r is None else r for r in images.column("laser_range_m").to_pylist()], float)
    if not np.isfinite(ranges).any():
        return None
    fitted = np.isfinite(fitted_lasers(ids, ranges))
    held = {int(i): float(r) for i, r, f in zip(ids, ranges, fitted, strict=True) if np.isfinite(r) and not f}
    used = {int(i): float(r) for i, r, f in zip(ids, ranges, fitted, strict=True) if f}
    check = laser_range_check(frames, held, dsm, measured)
    if check is None:
        return None
    doc = check.to_json(gsd)
    doc["verdict"] += " (frames whose range no adjustment used; the others' ranges observe the block's depth)"
    fit = laser_range_check(frames, used, dsm, measured)
    if fit is not None:
        doc["fitted"] = fit.to_json(gsd)
    return doc


def surface_text(info: Mapping[str, Any]) -> str:
    """The products step's surface in a sentence (``info``: its ``mosaic`` document): what the DSM stands on and,
    where the frames record laser ranges, whether it agrees with them."""
    dense = info.get("dense")
    if info.get("surface") == "dense" and dense:
        text = (f"dense: {dense['points']:,} points matched in {dense['pairs']} pairs of {dense['frames']} frames, "
                f"{100 * dense['measured_fraction']:.0f} % of the DSM measured"
                + wording.two_view_text(dense))
    else:
        text = str(info.get("surface") or "tie points")
    height = info.get("flying_height")
    if height:
        text += (f"; flying height above the {height['ground']} {height['from_surface_m']:.1f} m against "
                 f"{height['recorded_m']:.1f} m recorded ({100 * height['relative']:+.1f} %)")
    laser = info.get("laser_range")
    return text + (f"; {laser['verdict']}" if laser else "")


def mosaic_step(runner: Runner, ingest: StepResult, adjusted: StepResult, certificate: str,
                config: MosaicStepConfig | None = None, execution: ExecutionConfig | None = None) -> StepResult:
    """Outputs: ``dsm`` (GeoTIFF, float32 metres), ``orthomosaic`` (GeoTIFF/COG, when frames exist),
    ``temperature`` (FLIR frames) and ``mosaic`` (grid, GSD, coverage, frames used). The frames' SHA-256 key
    the step too: a frame added to ``images/`` or rendered again re-runs it."""
    config = config or MosaicStepConfig()
    inputs = {"images": ingest["images"], "flight": ingest["flight"], "poses": adjusted["poses"],
              "points": adjusted["points"], "certificate": certificate}

    def compute(inp: StepInputs) -> dict:
        flight, images, poses = inp.json("flight"), inp.table("images"), inp.table("poses")
        points = inp.table("points")
        cert = Certificate.from_dict(inp.json("certificate"))
        gsd, ground = flight_gsd(poses, points, cert.camera.f)
        work = Path(tempfile.mkdtemp(prefix="aerocal-mosaic-"))
        dsm = dsm_from_points(points, flight["crs"], gsd_m=gsd, config=config.dsm or DsmConfig())
        info: dict[str, Any] = {"gsd_m": gsd, "ground_height_m": ground, "frames": 0,
                                "surface": "tie points: the flight has no frames (images/) to match densely"}
        out: dict[str, Any] = {}
        paths = frame_paths(flight, images)
        frames = frames_of(images, poses, cert, paths) if paths else []
        reference = reference_dsm_path(flight)
        # the files no later part reads (the LAZ, the DSMs' GeoTIFFs and their differences to the reference) are
        # written on threads while the DTM is filtered and the orthomosaic rectified: GDAL's and lazrs's writing,
        # numpy's reductions and the products' compiled loops release the GIL, so they share the cores
        # (benchmarks/RESULTS.md, "Products step, part by part", 2026-12-07 16:15); leaving
        # this block waits for them, a failure's too
        with ThreadPoolExecutor(2, thread_name_prefix="aerocal-products") as background:
            dense = (dense_surface(flight, frames, points, cert, paths, ground, config, execution, work, info,
                                   background)
                     if paths and config.dense is not None else None)
            if paths and config.dense is None:
                info["surface"] = "tie points: the dense surface was not asked for (--surface tie-points)"
            files = laz = None
            if dense is not None:
                sparse = dsm
                dsm, measured, views, laz = dense
                files = background.submit(dense_files, dsm, measured, views, sparse, reference, work)
                terrain = dtm_from_dsm(dsm, measured, config.ground_filter)
                info["dtm"] = terrain.note
                if terrain.dtm is not None:
                    # band 2: where the ground itself was measured (a measured cell the filter took for ground); the
                    # rest is interpolated, under buildings and trees and out to the grid's corners
                    out["dtm"] = FileOutput(write_dsm(terrain.dtm, work / "dtm.tif", terrain.ground), "dsm",
                                            temporary=True)
                recorded = flight.get("height_agl_m")
                source = str((flight.get("facts") or {}).get("height_agl_m", ""))
                # against the ground (a DTM: over a forest the DSM is the canopy); a height measured on this block's
                # tie points would judge itself
                if recorded and terrain.dtm is not None and "tie points" not in source:
                    check = flying_height_check(frames, terrain.dtm, float(recorded))
                    if check is not None:
                        info["flying_height"] = {**check, "ground": "DTM", "source": source or "flight.json"}
                del terrain
            else:
                measured = views = None
                out["dsm"] = FileOutput(write_dsm(dsm, work / "dsm.tif"), "dsm", temporary=True)
            if paths:
                laser = laser_output(images, frames, dsm, dsm.distance_m == 0 if measured is None else measured,
                                     gsd)
                if laser is not None:
                    info["laser_range"] = laser
            info.update({"dsm_cell_m": dsm.cell_m, "dsm_shape": list(dsm.heights.shape)})
            if paths:
                run = execution or ExecutionConfig()
                # on the run's Dask scheduler when it has one; without one, on threads in this process, one per local
                # worker the run would start (no local cluster: build_mosaic's docstring)
                with run.client(serial=run.dask_address is None) as client:
                    res = build_mosaic(frames, paths, dsm, work / "orthomosaic.tif", config.mosaic or MosaicConfig(),
                                       client, step_progress("mosaic"), threads=max(1, run.local_workers))
                out["orthomosaic"] = FileOutput(res.path, "orthomosaic", temporary=True)
                info.update({k: v for k, v in res.to_dict().items() if k != "path"})
                if res.dtype == "uint16":
                    out.update(temperature_output(paths.values(), res.path, work, info))
                info["frames"] = len(frames)
            if files is not None:
                files_out, differences = files.result()
                out.update(files_out)
                info.update(differences)
            if laz is not None:
                out["cloud"] = FileOutput(laz.result(), "cloud", temporary=True)
        out["mosaic"] = JsonOutput(info, "mosaic")
        return out

    frames = runner.inputs({"flight": ingest["flight"], "images": ingest["images"]})
    frames_key = {str(i): file_sha256(p) for i, p in sorted(frame_paths(frames.json("flight"),
                                                                         frames.table("images")).items())}
    return runner.run("mosaic", inputs, {"config": config, "frames": frames_key}, compute)
