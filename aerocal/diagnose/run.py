"""Diagnose a flight's tables outside a processing run (``aerocal diagnose``), and read a run's stored diagnosis.

The folder is read by the pipeline's flight reader (:func:`aerocal.pipeline.diagnose_step.diagnose_folder`), as
``aerocal process`` reads it."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa

from aerocal.adjust import AdjustConfig, corrected_to_t0
from aerocal.camera import Camera
from aerocal.diagnose.engine import DiagnoseConfig, Diagnosis, diagnose
from aerocal.diagnose.io_uncertainty import IOUncertainty
from aerocal.formats import import_certificate

#: the interior orientation a baseline self-calibrates when no certificate fixes it
SELF_CALIBRATED = ("f", "cx", "cy", "k1", "k2", "p1", "p2")


class DiagnoseInputError(ValueError):
    """A flight folder lacks what the diagnosis needs; the message names the file and the fix."""


def diagnose_tables(images: pa.Table, observations: pa.Table, gcps: pa.Table | None, gcp_obs: pa.Table | None,
                    metadata: dict, camera: Camera | None, certificate: str | Path | None = None,
                    config: DiagnoseConfig | None = None) -> Diagnosis:
    """Diagnose a flight's measured block as ``aerocal diagnose`` does, outside a processing run.

    Args:
        images, observations, gcps, gcp_obs: the flight's tables (:mod:`aerocal.tables`; the GCP tables may be
            ``None``).
        metadata: the flight's ``flight.json`` (``gnss_sigma_m`` [horizontal, vertical] metres, default 0.10 /
            0.15; ``imu_sigma_deg``, default: attitudes not observed).
        camera: the nominal camera (camera.json), self-calibrated in f, cx, cy, k1, k2, p1, p2 by the baseline
            when no ``certificate`` is given.
        certificate: a certificate file in any format :func:`aerocal.formats.import_certificate` reads; its IO is
            fixed and its linear thermal correction applied to the measurements, as ``aerocal process``'s block
            adjustment applies it, so that a thermal effect named is what that model leaves.

    Raises:
        DiagnoseInputError: neither a camera nor a certificate, or a certificate file that does not read.
    """
    h, v = metadata.get("gnss_sigma_m") or [0.10, 0.15]
    imu = metadata.get("imu_sigma_deg")
    t0 = None
    io = None
    if certificate is not None:
        try:
            cert = import_certificate(certificate)
        except (OSError, ValueError) as exc:
            raise DiagnoseInputError(f"{certificate}: {exc}") from exc
        camera, free = cert.camera, ()
        io = IOUncertainty.from_certificate(cert)
        if cert.thermal is not None:
            t0 = getattr(cert.thermal.model, "t0", None)
        observations = corrected_to_t0(images, observations, camera, cert.linear_thermal)
        gcp_obs = corrected_to_t0(images, gcp_obs, camera, cert.linear_thermal)
    elif camera is None:
        raise DiagnoseInputError("no camera: give --certificate or the camera's nominal values in camera.json")
    else:
        free = SELF_CALIBRATED
    adjust_config = AdjustConfig(free=free, gnss_sigma_m=(h, h, v),
                                 attitude_sigma_deg=tuple(imu) if imu else None)
    config = config or DiagnoseConfig(reference_temperature=t0)
    return diagnose(images, observations, camera, adjust_config, gcps, gcp_obs, config, io)


def read_run_diagnosis(folder: str | Path) -> dict | None:
    """The diagnosis a processing run stored (``diagnosis.json`` of a run folder), or None.

    Raises:
        DiagnoseInputError: ``diagnosis.json`` is not valid JSON; re-run the diagnose step.
    """
    path = Path(folder) / "diagnosis.json"
    if not path.is_file() or (Path(folder) / "observations").is_dir():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DiagnoseInputError(f"{path}: not valid JSON ({exc}); re-run the diagnose step") from exc
