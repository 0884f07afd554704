"""The ingest step: a flight dataset read into tables, the camera document and the flight's summary."""

from __future__ import annotations

import datetime as dt
from typing import Any

import numpy as np
import pyarrow as pa

from aerocal.pipeline.dataset import FlightDataset, IngestStepConfig
from aerocal.pipeline.runner import JsonOutput, Runner, StepInputs, StepResult, TableOutput
from aerocal.pipeline.summary import FlightMode


def flight_summary(images: pa.Table, meta: dict, crs: str | None, name: str, mode: FlightMode | str,
                   folder: str | None) -> dict[str, Any]:
    """The flight's summary (the ``flight`` document every later step reads): name, folder (``None`` for a
    dataset in memory), mode (the :class:`FlightMode`'s value), CRS, date (of the first image, else the plan's
    start, else today), image count, sensor temperature range (degC), bounding box of the GNSS positions
    (E min, N min, E max, N max in the CRS) and the declared sigmas and height above ground (metres)."""
    times = [t for t in images.column("time").to_pylist() if t is not None]
    start = meta.get("start_time")
    if times:
        day = min(times).date().isoformat()
    elif start:
        day = str(start)[:10]
    else:
        day = dt.date.today().isoformat()
    temps = np.array([t for t in images.column("temperature_c").to_pylist() if t is not None], dtype=float)
    xy = np.column_stack([images.column("gnss_x").to_numpy(zero_copy_only=False),
                          images.column("gnss_y").to_numpy(zero_copy_only=False)]).astype(float)
    ok = np.isfinite(xy).all(axis=1)
    return {
        "name": name,
        "folder": folder,
        "mode": FlightMode(mode).value,
        "crs": crs,
        "date": day,
        "n_images": images.num_rows,
        "temperature_range": [float(temps.min()), float(temps.max())] if temps.size else None,
        "bbox": [float(v) for v in (*xy[ok].min(axis=0), *xy[ok].max(axis=0))] if ok.any() else None,
        "gnss_sigma_m": meta.get("gnss_sigma_m"),
        "imu_sigma_deg": meta.get("imu_sigma_deg"),
        "tie_sigma_px": meta.get("tie_sigma_px"),
        "height_agl_m": meta.get("height_agl_m"),
        "description": meta.get("description"),
    }


def ingest_step(runner: Runner, dataset: FlightDataset, manifest: str,
                config: IngestStepConfig | None = None) -> StepResult:
    """Read the dataset (``manifest``: the reference of its manifest, which keys the step).

    Outputs: the ``images``, ``gcps``, ``gcp_observations`` and (observations mode) ``observations`` tables,
    ``camera`` (identity, nominal camera, its source) and ``flight`` (:func:`flight_summary` with ingest's
    ``problems``, ``skipped_images`` and ``facts``)."""
    config = config or IngestStepConfig()
    name = config.flight_name or dataset.name

    def compute(inp: StepInputs) -> dict:
        read = dataset.read(config)
        out: dict[str, Any] = {kind: TableOutput(tab, kind) for kind, tab in read.tables.items()}
        out["camera"] = JsonOutput(read.camera, "camera")
        folder = None if dataset.folder is None else str(dataset.folder)
        summary = flight_summary(read.tables["images"], read.metadata, read.crs, name, read.mode, folder)
        summary["problems"] = read.problems
        summary["skipped_images"] = read.skipped_images
        if read.facts is not None:
            summary["facts"] = read.facts
        out["flight"] = JsonOutput(summary, "flight")
        return out

    return runner.run("ingest", {"manifest": manifest}, config, compute)
