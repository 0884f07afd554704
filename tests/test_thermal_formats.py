"""Real thermal files as they come off the camera: FLIR radiometric JPEG (FFF) and the DJI R-JPEG family.

The FLIR samples (``../shared/data/flir_samples``, sources and licences in its README) are read to the
exact 16-bit frame and to temperatures within 0.1 degC of ``flyr`` 5.1, the reference reader; the two
DJI Zenmuse files flyr cannot read (little-endian FFF) are checked against the raw range ExifTool gives
and an independent Planck evaluation. Files written by the project's own FFF writer, in both byte orders
and both payloads, read back exactly.
"""

from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from aerocal.ingest import read_raw
from aerocal.ingest.camera_catalogue import lookup, nominal_camera
from aerocal.ingest.flir import FlirCameraInfo, FlirFormatError, raw_to_celsius, read_flir
from aerocal.ingest.jpeg import parse_jpeg
from aerocal.ingest.metadata import read_image_metadata
from aerocal.ingest.metadata_writer import (
    dji_xmp_packet,
    exif_block,
    fff_file,
    flir_app1_segments,
    jpeg_with_flir,
    jpeg_with_metadata,
)
from aerocal.ingest.pixels import read_temperature_c

SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "data" / "flir_samples"
HANDHELD = {  # file -> (raw width, height, payload)
    "fff_flir_e40.jpg": (160, 120, "raw"),
    "fff_flir_e60_moving_car.jpg": (320, 240, "raw"),
    "fff_flir_t640.jpg": (640, 480, "png"),
    "fff_flir_ax8.jpg": (80, 60, "png"),
    "fff_flir_b60_aqua_tower.jpg": (180, 180, "png"),
    "fff_flir_example_embedded_rgb.jpg": (240, 320, "png"),
}
#: DJI Zenmuse XT family: raw range from ExifTool's RawThermalImage, and the README's own Planck evaluation
#: (emissivity and reflection corrected, no atmosphere): min..max degC
ZENMUSE = {"fff_dji_xt2.jpg": ((3233, 6859), (22.7, 80.6)), "fff_dji_xtr.jpg": ((3051, 4630), (17.1, 58.6))}
DJI_RJPEG = {  # file -> (raw width, height, APPn marker that holds it)
    "dji_rjpeg_m2ea.jpg": (640, 512, 0xE3),
    "dji_rjpeg_m30t.jpg": (640, 512, 0xE3),
    "dji_rjpeg_h30t.jpg": (1280, 1024, 0xE3),
    "dji_rjpeg_xts.jpg": (640, 512, 0xE4),
}


def _thermogram(name: str):
    return read_flir(parse_jpeg((SAMPLES / name).read_bytes()))


def test_the_shared_samples_are_there():
    assert SAMPLES.is_dir(), f"{SAMPLES} is missing: the FLIR samples are part of the measured data"
    assert {*HANDHELD, *ZENMUSE, *DJI_RJPEG} <= {p.name for p in SAMPLES.glob("*.jpg")}


@pytest.mark.parametrize("name", sorted(HANDHELD))
def test_flir_handheld_files_match_the_reference_reader(name):
    import flyr
    w, h, payload = HANDHELD[name]
    t = _thermogram(name)
    assert t.raw.dtype == np.uint16 and t.raw.shape == (h, w) and t.payload == payload
    ref = flyr.unpack(str(SAMPLES / name))
    ref_raw = ref._FlyrThermogram__thermal  # flyr keeps the counts private
    assert np.array_equal(t.raw, ref_raw.astype(np.uint16)), "raw frame differs from flyr's"
    ours, theirs = t.celsius(), ref.celsius
    assert np.nanmax(np.abs(ours - theirs)) < 0.1, f"{name}: up to {np.nanmax(np.abs(ours - theirs)):.3f} degC off"


@pytest.mark.parametrize("name", sorted(ZENMUSE))
def test_dji_zenmuse_fff_is_little_endian_and_read_whole(name):
    (raw_lo, raw_hi), (t_lo, t_hi) = ZENMUSE[name]
    t = _thermogram(name)
    assert t.byte_order == "<" and t.creator == "ATAU_RBFO" and t.payload == "raw"
    assert t.raw.shape == (512, 640) and (int(t.raw.min()), int(t.raw.max())) == (raw_lo, raw_hi)
    # without the air path the temperatures are the README's independent evaluation
    no_air = raw_to_celsius(t.raw, dataclasses.replace(t.info, object_distance_m=0.0))
    assert abs(np.nanmin(no_air) - t_lo) < 0.15 and abs(np.nanmax(no_air) - t_hi) < 0.15
    # with the recorded 20 m of warm air the scene reads a little colder at the low end, warmer at the top
    full = t.celsius()
    assert np.all(np.isfinite(full)) and np.nanmin(full) < np.nanmin(no_air) < np.nanmax(no_air) < np.nanmax(full)


def test_flir_metadata_identity_and_temperature_provenance():
    meta, problems = read_image_metadata(SAMPLES / "fff_dji_xt2.jpg")
    assert meta.raw_format == "flir-fff" and (meta.width, meta.height, meta.bit_depth) == (640, 512, 16)
    assert meta.extra["flir_planck_r1"] == pytest.approx(17096.453) and meta.extra["flir_planck_o"] == -267
    # XMP FLIR:CentralTemperature is a scene temperature: kept as such, never the sensor temperature
    assert meta.extra["flir_central_temperature_scene_c"] == 34.0 and meta.temperature_c is None
    meta, _ = read_image_metadata(SAMPLES / "fff_flir_t640.jpg")
    assert (meta.make, meta.model, meta.serial) == ("FLIR Systems AB", "FLIR T640", "55908724")
    assert read_raw(SAMPLES / "fff_flir_t640.jpg").shape == (480, 640)


@pytest.mark.parametrize("name", sorted(DJI_RJPEG))
def test_dji_rjpeg_family_reads_counts_only(name):
    w, h, marker = DJI_RJPEG[name]
    meta, problems = read_image_metadata(SAMPLES / name)
    assert meta is not None and meta.raw_format == "dji-rjpeg" and (meta.width, meta.height) == (w, h)
    raw = read_raw(SAMPLES / name)
    assert raw.dtype == np.uint16 and raw.shape == (h, w)
    jpeg = parse_jpeg((SAMPLES / name).read_bytes())
    expected = np.frombuffer(b"".join(jpeg.app(marker)), "<u2").reshape(h, w)
    assert np.array_equal(raw, expected)
    assert read_temperature_c(SAMPLES / name) is None  # DJI's conversion is in its SDK only
    # the H20T's undocumented APP4 floats are not read on other models (they hold 0 or 1e28 there)
    assert not [k for k in meta.extra if k.startswith("dji_app4")]
    assert meta.serial is None  # these files record "0"
    if name == "dji_rjpeg_xts.jpg":  # its preview is cut; the raw frame before it is whole
        assert [p.field for p in problems] == ["EOI"]


def _info(**kw) -> FlirCameraInfo:
    base = dict(
        emissivity=0.95, object_distance_m=35.0, reflected_temperature_k=290.0, atmospheric_temperature_k=285.0,
        window_temperature_k=290.0, window_transmission=1.0, relative_humidity=0.6, planck_r1=17096.453,
        planck_b=1428.0, planck_f=1.0, planck_o=-267.0, planck_r2=0.046582, atm_alpha1=0.006569,
        atm_alpha2=0.01262, atm_beta1=-0.002276, atm_beta2=-0.00667, atm_x=1.9, camera_model="Test core",
    )
    return FlirCameraInfo(**{**base, **kw})


def _flir_jpeg(raw: np.ndarray, info: FlirCameraInfo, byte_order="<", payload="raw", make="DJI", model="XT2",
               focal_mm=13.0, xmp: dict | None = None) -> bytes:
    buf = io.BytesIO()
    Image.fromarray((raw >> 6).astype(np.uint8)).save(buf, "JPEG")
    exif = exif_block(make=make, model=model, focal_mm=focal_mm, gps=(47.1, 8.2, 560.0))
    packet = dji_xmp_packet(xmp) if xmp else None
    return jpeg_with_flir(jpeg_with_metadata(buf.getvalue(), exif, packet), fff_file(raw, info, byte_order, payload))


@pytest.mark.parametrize("byte_order", ["<", ">"])
@pytest.mark.parametrize("payload", ["raw", "png"])
def test_written_fff_reads_back_exactly(byte_order, payload):
    seed = 20261125
    rng = np.random.default_rng(seed)
    raw = rng.integers(2500, 9000, (96, 128)).astype(np.uint16)
    info = _info()
    t = read_flir(parse_jpeg(_flir_jpeg(raw, info, byte_order, payload)))
    assert np.array_equal(t.raw, raw), f"seed {seed}"
    assert t.byte_order == byte_order and t.payload == payload
    for f in dataclasses.fields(info):  # stored as float32 and read back
        want, got = getattr(info, f.name), getattr(t.info, f.name)
        assert got == (want if isinstance(want, str) else pytest.approx(np.float32(want))), f.name
    assert np.allclose(t.celsius(), raw_to_celsius(raw, info))


def test_a_flir_file_missing_a_segment_is_an_error_not_a_palette_picture(tmp_path):
    from aerocal.ingest.metadata_writer import _segment

    raw = np.full((64, 80), 5000, np.uint16)
    segs = flir_app1_segments(fff_file(raw, _info()), chunk=4000)
    assert len(segs) > 2
    buf = io.BytesIO()
    Image.fromarray((raw >> 6).astype(np.uint8)).save(buf, "JPEG")
    base = jpeg_with_metadata(buf.getvalue(), exif_block(make="DJI", model="XT2"))
    broken = base[:2] + b"".join(_segment(0xE1, s) for k, s in enumerate(segs) if k != 1) + base[2:]
    (tmp_path / "a.jpg").write_bytes(broken)
    meta, problems = read_image_metadata(tmp_path / "a.jpg")
    assert meta is None and problems[0].severity == "error" and problems[0].field == "FLIR"
    assert f"segment(s) 1 of {len(segs)} missing" in problems[0].message and "palette" in problems[0].message
    with pytest.raises(FlirFormatError):
        read_flir(parse_jpeg(broken))


def test_catalogue_builds_the_nominal_camera_and_says_from_what():
    h20t = nominal_camera("DJI", "ZH20T", 640, 512)
    assert h20t.camera.f == pytest.approx(13.5 / 0.012) and "fixed lens" in h20t.focal_source
    xt2 = nominal_camera("DJI", "XT2", 640, 512, exif_focal_mm=13.0)
    assert xt2.camera.f == pytest.approx(13.0 / 0.017) and xt2.focal_source == "EXIF FocalLength"
    none = nominal_camera("DJI", "FLIR", 640, 512)  # Zenmuse XT without a focal length: not guessed
    assert none.camera is None and "interchangeable lenses" in none.reason
    fov = nominal_camera("DJI", "FLIR", 640, 512, field_of_view_deg=45.0)
    assert fov.camera.f == pytest.approx(320 / np.tan(np.radians(22.5)))
    assert lookup("DJI", "XT2", 336, 256).pixel_pitch_um == 17.0
    assert nominal_camera("Acme", "Thermo 1", 640, 512).camera is None


def test_three_independent_problems_in_one_report_and_process_stops_with_it(tmp_path):
    """Ingest reports every problem at once and exits 2; process stops before any work with the same
    report, no traceback, nothing stored."""
    from typer.testing import CliRunner

    from aerocal.cli import app

    flight = tmp_path / "flight"
    (flight / "images").mkdir(parents=True)
    rng = np.random.default_rng(7)
    for k in range(3):
        raw = rng.integers(3000, 6000, (48, 64)).astype(np.uint16)
        xmp = {"RelativeAltitude": 50.0, "GimbalRollDegree": 0.0, "GimbalPitchDegree": -90.0,
               "GimbalYawDegree": 0.0, "AbsoluteAltitude": 610.0}
        (flight / "images" / f"IMG_{k}.jpg").write_bytes(_flir_jpeg(raw, _info(), model="Thermo 1", make="Acme",
                                                                    xmp=xmp))
    good = (flight / "images" / "IMG_2.jpg").read_bytes()
    (flight / "images" / "IMG_2.jpg").write_bytes(good[: len(good) // 3])  # 1: a cut file
    (flight / "flight.json").write_text('{"height_agl_m": "fifty"}')  # 2: a bad value
    # 3: no camera.json and a camera the catalogue does not know
    runner = CliRunner()
    res = runner.invoke(app, ["ingest", str(flight)])
    out = " ".join(res.output.split())
    assert res.exit_code == 2, res.output
    assert "IMG_2.jpg" in out and "height_agl_m = 'fifty'" in out and "camera.json" in out, res.output
    assert "stops processing" in out and "Traceback" not in res.output
    db = tmp_path / "store.db"
    res = runner.invoke(app, ["process", str(flight), "--database-url", f"sqlite:///{db}",
                              "--artifacts", str(tmp_path / "art")])
    out = " ".join(res.output.split())
    assert res.exit_code == 2, res.output
    assert "cannot be processed" in out and "camera.json" in out and "IMG_2.jpg" in out and "fifty" in out
    assert "Traceback" not in res.output
    assert not db.exists() and not (tmp_path / "art").exists() and not (tmp_path / "flight-processed").exists()


def test_strip_headings_come_from_the_rotation_not_the_gimbal_yaw():
    """Near nadir a gimbal's yaw and roll trade against each other: the simulator's recorded yaws of a
    nadir XT2 survey scatter over +-180 deg, the image's heading on the ground does not."""
    from aerocal.geometry import R_cw_to_dji_gimbal
    from aerocal.ingest.folder import image_heading
    from aerocal.ingest.strips import angle_difference, circular_median
    from aerocal.simulate import get_preset, simulate_flight
    from aerocal.simulate.simulator import recorded_R_cw

    seed = 3
    sim = simulate_flight(get_preset("xt2-survey"), seed=seed)
    strips = np.asarray(sim.trajectory.strip)
    # the gimbal angles the rendered files record (aerocal.simulate.rendered_frames writes these)
    gimbal = np.array([R_cw_to_dji_gimbal(R) for R in recorded_R_cw(sim.images)])
    head = np.array([image_heading("dji_gimbal", r, p, y) for r, p, y in gimbal])
    yaw_spreads = []
    for k in np.unique(strips[strips >= 0]):
        h = head[strips == k]
        # within the recorded attitude's noise (1-2 deg, 3 sigma)
        assert angle_difference(h, circular_median(h)).max() < 10.0, f"seed {seed}, strip {k}: {h}"
        yaw = gimbal[strips == k, 2]
        yaw_spreads.append(float(angle_difference(yaw, circular_median(yaw)).max()))
    assert max(yaw_spreads) > 45.0, f"seed {seed}: recorded yaw spreads {yaw_spreads} (the point of the test)"


def test_frames_without_radiometric_calibration_say_so_in_words(tmp_path):
    """A folder of 16-bit TIFF counts gives no temperature raster, and the reason a user reads is that the frames
    carry no radiometric calibration, not a JPEG parser's complaint."""
    from aerocal.ingest.flir import common_camera_info

    frame = tmp_path / "IMG_0001.tif"
    tifffile.imwrite(frame, np.full((8, 8), 30000, dtype=np.uint16))
    info, why = common_camera_info([frame])
    assert info is None and "carry no radiometric calibration" in why and "IMG_0001.tif" in why, why
