"""The nominal camera of any camera from what its files say, and the flying height from any autopilot that
records one: a flight straight off the aircraft needs no hand-written ``camera.json`` or ``flight.json``.

Judged against what a user would otherwise write by hand: the seneca benchmark's camera (EXIF focal length
over a 6.17 mm wide 1/2.3-inch sensor), copr's (a 22.2 mm wide Canon APS-C sensor), and the camera a rendered
flight was simulated with.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image
from PIL.ExifTags import Base

from aerocal.ingest import ingest_folder
from aerocal.ingest.camera_catalogue import nominal_camera, sensor_width
from aerocal.ingest.inferred import infer_camera, infer_gnss_sigma, infer_height_agl
from aerocal.ingest.metadata import read_image_metadata
from aerocal.ingest.metadata_writer import exif_block, jpeg_with_metadata

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
AEROCAL = str(Path(sys.executable).with_name("aerocal"))


def _metas(folder: Path, n: int = 4) -> list:
    metas = [read_image_metadata(p)[0] for p in sorted(folder.glob("*.[jJ][pP][gG]"))[:n]]
    assert all(m is not None for m in metas), folder
    return metas


@pytest.mark.parametrize(("name", "focal_mm", "sensor_mm"), [("seneca", 4.3, 6.17), ("copr", 30.0, 22.2)])
def test_a_real_camera_outside_the_catalogue_gets_its_focal_length_from_its_exif(name, focal_mm, sensor_mm):
    metas = _metas(DATA / name / "images")
    camera, reason = infer_camera(metas)
    width = max(m.width for m in metas if (m.width, m.height) == (camera.width, camera.height))
    by_hand = focal_mm / (sensor_mm / width)  # what a user writes into camera.json from the sensor's data sheet
    assert camera is not None, reason
    assert camera.f == pytest.approx(by_hand, rel=0.01), reason
    assert "FocalPlaneXResolution" in reason and f"stored width {width} px" in reason, reason
    assert (camera.cx, camera.cy) == (camera.width / 2, camera.height / 2)


def test_the_pixel_pitch_scales_with_the_width_the_image_is_stored_at(tmp_path):
    """A camera that records its 4000-pixel sensor (FocalPlaneXResolution in pixels per centimetre) and an
    image resized to 1000 pixels: the stored pixels are 4 times the sensor's."""
    buf = io.BytesIO()
    Image.fromarray(np.zeros((750, 1000, 3), np.uint8)).save(buf, "JPEG")
    pitch_mm = 0.0015  # 1.5 um
    exif = exif_block(make="Acme", model="Survey One", focal_mm=8.8, exif_extra=[
        (Base.FocalPlaneXResolution, 5, [10.0 / pitch_mm]), (Base.FocalPlaneResolutionUnit, 3, [3]),
        (Base.ExifImageWidth, 4, [4000])])
    (tmp_path / "a.jpg").write_bytes(jpeg_with_metadata(buf.getvalue(), exif))
    meta, problems = read_image_metadata(tmp_path / "a.jpg")
    assert meta.extra["exif_pixel_pitch_mm"] == pytest.approx(4 * pitch_mm, rel=1e-6), problems
    camera, reason = infer_camera([meta])
    assert camera.f == pytest.approx(8.8 / (4 * pitch_mm), rel=1e-6) and camera.pixel_size_mm == pytest.approx(0.006)


def test_the_35mm_equivalent_and_the_sensor_table_when_the_pitch_is_not_recorded():
    # FocalLengthIn35mmFilm over the 36 mm long side of 35 mm film
    nominal = nominal_camera("Acme", "Survey One", 4000, 3000, exif_focal_mm=8.8, focal_35mm=24.0)
    assert nominal.camera.f == pytest.approx(24.0 / 36.0 * 4000) and "FocalLengthIn35mmFilm 24 mm" in nominal.reason
    assert nominal.camera.pixel_size_mm == pytest.approx(8.8 / nominal.camera.f)
    # a camera of the sensor-width table recording only its focal length (a portrait frame: the long side)
    assert sensor_width("DJI", "FC6310").width_mm == 13.2
    nominal = nominal_camera("DJI", "FC6310", 3648, 5472, exif_focal_mm=8.8)
    assert nominal.camera.f == pytest.approx(8.8 / (13.2 / 5472)) and "1-inch sensor" in nominal.reason
    # nothing to go by: no camera, and the reason names what is missing
    nominal = nominal_camera("Acme", "Survey One", 4000, 3000, exif_focal_mm=8.8)
    assert nominal.camera is None and "FocalPlaneXResolution" in nominal.reason, nominal.reason
    nominal = nominal_camera("Acme", "Survey One", 4000, 3000)
    assert nominal.camera is None and "no focal length" in nominal.reason, nominal.reason
    # a thermal camera of the catalogue keeps the maker's pitch over its rounded 35 mm equivalent
    h20t = nominal_camera("DJI", "ZH20T", 640, 512, exif_focal_mm=13.5, focal_35mm=58.0)
    assert h20t.camera.f == pytest.approx(13.5 / 0.012)


def test_the_sensefly_height_above_takeoff_is_the_flying_height():
    metas = _metas(DATA / "seneca" / "images", 6)
    height = infer_height_agl(metas)
    expected = np.median([m.extra["sensefly_height_above_takeoff_m"] for m in metas])
    assert height.value == pytest.approx(expected) and "senseFly XMP Height" in height.source
    assert 40 < height.value < 120, height  # the Swinglet flew at about 70 m


@pytest.mark.parametrize("recorded", ["focal_plane", "35mm"])
def test_a_rendered_flight_written_as_jpegs_gives_the_simulated_focal_length(tmp_path, recorded):
    """``aerocal simulate`` frames rewritten as a camera aerocal does not know would write them (8-bit JPEGs
    with EXIF focal length and FocalPlaneXResolution, or with FocalLengthIn35mmFilm only) and no camera.json:
    ``aerocal ingest`` finds nothing that stops processing, and the nominal camera is the simulated one."""
    done = subprocess.run([AEROCAL, "simulate", "conte-calibration", "--out", str(tmp_path / "sim"), "--seed", "3",
                           "--mode", "images", "--max-images", "4"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    sim = tmp_path / "sim"
    nominal = json.loads((sim / "camera.json").read_text())["camera"]
    flight = tmp_path / "flight"
    (flight / "images").mkdir(parents=True)
    for name in ("eo.csv", "gcp_list.txt", "flight.json"):
        text = (sim / name).read_text().replace(".tif", ".jpg")
        (flight / name).write_text(text)
    focal_mm = nominal["f"] * nominal["pixel_size_mm"]
    for tif in sorted((sim / "images").glob("*.tif")):
        counts = tifffile.imread(tif).astype(float)
        lo, hi = np.percentile(counts, (1, 99))
        grey = np.clip((counts - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
        buf = io.BytesIO()
        Image.fromarray(grey).save(buf, "JPEG", quality=95)
        extra = ([(Base.FocalPlaneXResolution, 5, [25.4 / nominal["pixel_size_mm"]]),
                  (Base.FocalPlaneResolutionUnit, 3, [2])] if recorded == "focal_plane" else
                 [(Base.FocalLengthIn35mmFilm, 3, [round(nominal["f"] * 36.0 / nominal["width"])])])
        exif = exif_block(make="Acme", model="Thermal One", serial="7", focal_mm=focal_mm if recorded ==
                          "focal_plane" else None, exif_extra=extra)
        (flight / "images" / tif.with_suffix(".jpg").name).write_bytes(jpeg_with_metadata(buf.getvalue(), exif))
    done = subprocess.run([AEROCAL, "ingest", str(flight)], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "COLUMNS": "200"})
    assert "stops processing" not in done.stdout, done.stdout
    result = ingest_folder(flight)
    assert result.camera.f == pytest.approx(nominal["f"], rel=0.01), result.camera_source
    assert ("FocalPlaneXResolution" if recorded == "focal_plane" else "FocalLengthIn35mmFilm") in \
        result.camera_source, result.camera_source
    shutil.rmtree(sim)


def test_gnss_sigmas_from_the_pix4d_camera_namespace_else_consumer_grade(tmp_path):
    """A camera writing Pix4D's XMP layout (MicaSense, Parrot Sequoia) records its GNSS accuracy; a position
    recorded without one is consumer grade, said so."""
    buf = io.BytesIO()
    Image.fromarray(np.zeros((64, 80, 3), np.uint8)).save(buf, "JPEG")
    packet = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
              '<rdf:Description rdf:about="" xmlns:Camera="http://pix4d.com/camera/1.0/" '
              'Camera:GPSXYAccuracy="0.031" Camera:GPSZAccuracy="0.052"/></rdf:RDF></x:xmpmeta>')
    metas = []
    for k, xmp in enumerate([packet, packet, None]):
        exif = exif_block(make="Acme", model="Multi", gps=(47.0 + 1e-4 * k, 8.0, 500.0))
        (tmp_path / f"{k}.jpg").write_bytes(jpeg_with_metadata(buf.getvalue(), exif, xmp))
        metas.append(read_image_metadata(tmp_path / f"{k}.jpg")[0])
    assert metas[0].extra["xmp_gps_xy_accuracy_m"] == 0.031
    sigma = infer_gnss_sigma(metas)
    assert sigma.value == (0.031, 0.052) and "GPSXYAccuracy" in sigma.source, sigma
    sigma = infer_gnss_sigma(metas[2:])
    assert sigma.value == (2.0, 5.0) and "exif:gps" in sigma.source and "consumer-grade" in sigma.source, sigma


def test_a_parrot_image_gives_its_camera_attitude_and_height_above_ground(tmp_path):
    """Parrot's XMP layout: the camera's attitude as gimbal angles (pitch -90 straight down), the position in EXIF
    GPS, the height above ground in Pix4D's Camera:AboveGroundAltitude."""
    buf = io.BytesIO()
    Image.fromarray(np.zeros((64, 80, 3), np.uint8)).save(buf, "JPEG")
    packet = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
              '<rdf:Description rdf:about="" xmlns:drone-parrot="http://www.parrot.com/drone-parrot/1.0/" '
              'xmlns:Camera="http://pix4d.com/camera/1.0/" drone-parrot:CameraRollDegree="-0.32" '
              'drone-parrot:CameraPitchDegree="-89.5" drone-parrot:CameraYawDegree="176.3" '
              'Camera:AboveGroundAltitude="60.4"/></rdf:RDF></x:xmpmeta>')
    exif = exif_block(make="Parrot", model="ANAFI", gps=(47.0, 8.0, 520.0))
    (tmp_path / "p.jpg").write_bytes(jpeg_with_metadata(buf.getvalue(), exif, packet))
    meta, problems = read_image_metadata(tmp_path / "p.jpg")
    pose = meta.pose
    assert (pose.source, pose.convention) == ("xmp:drone-parrot", "dji_gimbal"), problems
    assert (pose.roll, pose.pitch, pose.yaw) == (-0.32, -89.5, 176.3) and pose.lat == pytest.approx(47.0)
    height = infer_height_agl([meta])
    assert height.value == 60.4 and "AboveGroundAltitude" in height.source, height
    assert infer_gnss_sigma([meta]).value == (2.0, 5.0)  # a position recorded without an accuracy
