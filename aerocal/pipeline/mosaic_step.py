"""The products step: a DSM gridded from the adjusted tie points (:func:`aerocal.products.dsm.dsm_from_points`, GeoTIFF)
and, when frames with pixels exist (``images/`` of the flight folder), the orthomosaic in the flight's CRS from
their original radiometry (:func:`aerocal.products.mosaic.build_mosaic`, tiles on a Dask client), with a temperature
raster for FLIR radiometric frames. A flight without frames gets the DSM only."""

from __future__ import annotations

import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa

from aerocal.certificates.document import Certificate
from aerocal.diagnose.extension import frame_terms
from aerocal.ingest.flir import common_camera_info, raw_to_celsius
from aerocal.io import file_sha256
from aerocal.matching import ExecutionConfig
from aerocal.pipeline.config import MosaicStepConfig
from aerocal.pipeline.dataset import REFERENCE_DSM
from aerocal.pipeline.progress import step_progress
from aerocal.pipeline.runner import FileOutput, JsonOutput, Runner, StepInputs, StepResult
from aerocal.products.dsm import DsmConfig, dsm_from_points, write_dsm
from aerocal.products.mosaic import MosaicConfig, build_mosaic, frames_from_poses, write_temperature_raster


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
        out: dict[str, Any] = {"dsm": FileOutput(write_dsm(dsm, work / "dsm.tif"), "dsm", temporary=True)}
        info: dict[str, Any] = {"gsd_m": gsd, "ground_height_m": ground, "dsm_cell_m": dsm.cell_m,
                                "dsm_shape": list(dsm.heights.shape), "frames": 0}
        paths = frame_paths(flight, images)
        if paths:
            thermal = None if cert.thermal is None else cert.thermal.model
            temps = {int(k): float(v) for k, v in zip(images.column("image_id").to_pylist(),
                                                      images.column("temperature_c").to_pylist(), strict=True)
                     if v is not None}
            sel = poses.filter(np.isin(poses.column("image_id").to_numpy(), list(paths)))
            motion, turn = frame_terms(cert, images, poses)  # the certificate's readout and thermal rotation
            frames = frames_from_poses(sel, cert.camera, temps if thermal is not None else None, thermal, motion,
                                       turn)
            megapixels = len(frames) * cert.camera.width * cert.camera.height / 1e6
            serial = megapixels <= config.serial_max_megapixels
            with (execution or ExecutionConfig()).client(serial) as client:
                res = build_mosaic(frames, paths, dsm, work / "orthomosaic.tif", config.mosaic or MosaicConfig(),
                                   client, step_progress("mosaic"))
            out["orthomosaic"] = FileOutput(res.path, "orthomosaic", temporary=True)
            info.update({k: v for k, v in res.to_dict().items() if k != "path"})
            if res.dtype == "uint16":
                out.update(temperature_output(paths.values(), res.path, work, info))
            info["frames"] = len(frames)
        out["mosaic"] = JsonOutput(info, "mosaic")
        return out

    frames = runner.inputs({"flight": ingest["flight"], "images": ingest["images"]})
    frames_key = {str(i): file_sha256(p) for i, p in sorted(frame_paths(frames.json("flight"),
                                                                         frames.table("images")).items())}
    return runner.run("mosaic", inputs, {"config": config, "frames": frames_key}, compute)
