"""Diagnose a flight folder: read its tables and declared sensor sigmas, adjust, diagnose."""

from __future__ import annotations

import json
from pathlib import Path

from aerocal import tables
from aerocal.adjust import AdjustConfig, corrected_to_t0
from aerocal.camera import Camera
from aerocal.diagnose.engine import DiagnoseConfig, Diagnosis, diagnose
from aerocal.diagnose.io_uncertainty import IOUncertainty
from aerocal.formats import import_certificate

#: the interior orientation a baseline self-calibrates when no certificate fixes it
SELF_CALIBRATED = ("f", "cx", "cy", "k1", "k2", "p1", "p2")


class DiagnoseInputError(ValueError):
    """A flight folder lacks what the diagnosis needs; the message names the file and the fix."""


def _read(folder: Path, kind: str, required: bool = True):
    path = folder / "observations" / f"{kind}.parquet"
    if not path.exists():
        if required:
            raise DiagnoseInputError(f"{path} is missing; run matching (or simulate in observations mode) first")
        return None
    try:
        return tables.read(path, kind)
    except tables.SchemaError as exc:
        raise DiagnoseInputError(str(exc)) from exc


def diagnose_folder(folder: str | Path, certificate: str | Path | None = None,
                    config: DiagnoseConfig | None = None) -> Diagnosis:
    folder = Path(folder)
    if not folder.is_dir():
        raise DiagnoseInputError(f"{folder} is not a folder; give a processed flight folder")
    images = _read(folder, "images")
    observations = _read(folder, "observations")
    gcps = _read(folder, "gcps", required=False)
    gcp_obs = _read(folder, "gcp_observations", required=False)
    meta_path = folder / "flight.json"
    meta = json.loads(meta_path.read_text()) if meta_path.exists() else {}
    h, v = meta.get("gnss_sigma_m", [0.10, 0.15])
    imu = meta.get("imu_sigma_deg")
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
        # the certificate's model is diagnosed: its linear thermal correction applied, as aerocal process's block
        # adjustment applies it, so a thermal effect named is what that model leaves
        observations = corrected_to_t0(images, observations, camera, cert.linear_thermal)
        gcp_obs = corrected_to_t0(images, gcp_obs, camera, cert.linear_thermal)
    else:
        cam_path = folder / "camera.json"
        if not cam_path.exists():
            raise DiagnoseInputError(f"{cam_path} is missing; give --certificate or the camera's nominal values")
        camera, free = Camera.from_dict(json.loads(cam_path.read_text())["camera"]), SELF_CALIBRATED
    adjust_config = AdjustConfig(free=free, gnss_sigma_m=(h, h, v),
                                 attitude_sigma_deg=tuple(imu) if imu else None)
    config = config or DiagnoseConfig(reference_temperature=t0)
    return diagnose(images, observations, camera, adjust_config, gcps, gcp_obs, config, io)


def read_run_diagnosis(folder: str | Path) -> dict | None:
    """The diagnosis a processing run stored (``diagnosis.json`` of a run folder), or None."""
    path = Path(folder) / "diagnosis.json"
    if not path.is_file() or (Path(folder) / "observations").is_dir():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DiagnoseInputError(f"{path}: not valid JSON ({exc}); re-run the diagnose step") from exc
