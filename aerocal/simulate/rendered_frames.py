"""Rendered frames of a simulated flight (``aerocal simulate --mode images``).

Each frame is ray-cast through its true :class:`~aerocal.simulate.exposure.Exposure` (every effect on)
into the scene with the ground-control targets painted in, and written with the metadata a real camera
records (EXIF, DJI-style XMP with the *recorded* GNSS/IMU values).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
from collections.abc import Callable
from pathlib import Path

import numpy as np

from aerocal.geometry import R_cw_to_dji_gimbal
from aerocal.simulate.image_files import FrameMetadata, write_flir_rjpeg, write_frame, zenmuse_xt2_camera_info
from aerocal.simulate.raycast import RenderConfig, render_frame
from aerocal.simulate.sensors import recorded_R_cw

#: target disc radius in ground sampling distances (a 2.5 px radius disc is located to ~0.05 px)
TARGET_RADIUS_GSD = 2.5


def target_scene(sim):
    """The flight's scene with a signalised target at every ground control and check point."""
    radius = TARGET_RADIUS_GSD * sim.trajectory.gsd_m
    return sim.scene.place_targets(sim.gcp_true[:, :2], radius)


def render_flight_images(sim, out_dir: str | Path, config: RenderConfig | None = None,
                         progress: Callable[[int, int], None] | None = None) -> list[Path]:
    """Render every frame of ``sim`` into ``out_dir`` (TIFF for thermal, JPEG for RGB, FLIR radiometric JPEG
    for a spec whose ``file_format`` is ``"flir-rjpeg"``: RelativeAltitude above the mean terrain in XMP)."""
    config = config or RenderConfig(modality=sim.spec.modality)
    scene = target_scene(sim)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    im = sim.images.to_pydict()
    R_rec = recorded_R_cw(sim.images)
    ident = sim.spec.identity
    paths = []
    rng = np.random.default_rng(np.random.SeedSequence([sim.seed, 7919]))
    n = len(sim.exposures)
    for i, ex in enumerate(sim.exposures):
        img = render_frame(scene, ex, config, rng)
        roll, pitch, yaw = R_cw_to_dji_gimbal(R_rec[i])
        t = im["time"][i]
        meta = FrameMetadata(
            make=ident["make"], model=ident["model"], serial=ident["serial"],
            time=t if isinstance(t, dt.datetime) else dt.datetime.fromisoformat(str(t)),
            gps_latitude=im["lat"][i], gps_longitude=im["lon"][i], absolute_altitude=im["alt"][i],
            gimbal_roll_deg=roll, gimbal_pitch_deg=pitch, gimbal_yaw_deg=yaw,
        )
        if sim.spec.file_format == "flir-rjpeg":
            info = zenmuse_xt2_camera_info(object_distance_m=sim.spec.plan.height_agl_m)
            cam = sim.spec.camera_nominal
            focal_mm = cam.f * cam.pixel_size_mm if cam.pixel_size_mm else None
            meta = dataclasses.replace(meta, extra_xmp={
                "RelativeAltitude": float(im["alt"][i] - sim.spec.scene.terrain_mean_m)})
            paths.append(write_flir_rjpeg(out / im["name"][i], img, meta, info, config.dn_per_kelvin, focal_mm))
        else:
            paths.append(write_frame(out / im["name"][i], img, meta))
        if progress:
            progress(i + 1, n)
    return paths
