"""Bad input through `aerocal process`: one clear report naming the file, the line and the field, exit code 2,
no traceback, and nothing stored or changed (the certificate store is compared before and after).

The flight is three FLIR radiometric JPEGs of a DJI Zenmuse XT2 (640 x 512, written by the project's FFF
writer) with GNSS and gimbal attitude in EXIF/XMP; each case breaks one thing.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from aerocal.cli import app
from aerocal.ingest.metadata_writer import dji_xmp_packet, exif_block, fff_file, jpeg_with_flir, jpeg_with_metadata
from aerocal.simulate.image_files import zenmuse_xt2_camera_info

SEED = 11


def _flight(root: Path) -> Path:
    rng = np.random.default_rng(SEED)
    images = root / "images"
    images.mkdir(parents=True)
    info = zenmuse_xt2_camera_info(60.0)
    for k in range(3):
        raw = rng.integers(3000, 6000, (512, 640)).astype(np.uint16)
        buf = io.BytesIO()
        Image.fromarray((raw >> 5).astype(np.uint8)).save(buf, "JPEG")
        exif = exif_block(make="DJI", model="XT2", focal_mm=13.0, gps=(47.0 + 1e-4 * k, 8.0, 620.0))
        xmp = dji_xmp_packet({"AbsoluteAltitude": 620.0, "RelativeAltitude": 60.0, "GimbalRollDegree": 0.0,
                              "GimbalPitchDegree": -90.0, "GimbalYawDegree": 0.0})
        (images / f"DJI_{k:04d}_R.jpg").write_bytes(
            jpeg_with_flir(jpeg_with_metadata(buf.getvalue(), exif, xmp), fff_file(raw, info)))
    return root


@pytest.fixture()
def store(tmp_path):
    """A database holding one certificate, and a function listing what the store holds."""
    db = tmp_path / "store.db"
    url = f"sqlite:///{db}"
    runner = CliRunner()
    assert runner.invoke(app, ["db", "upgrade", "--database-url", url]).exit_code == 0
    cams = tmp_path / "cameras.txt"
    cams.write_text("1 PINHOLE 640 512 764.7 764.7 320 256\n")
    res = runner.invoke(app, ["certificates", "import", str(cams), "--make", "NEC", "--model", "TS9260",
                              "--serial", "1", "--database-url", url])
    assert res.exit_code == 0, res.output

    def listing() -> tuple[str, bytes]:
        out = runner.invoke(app, ["certificates", "list", "--database-url", url]).output
        return out, db.read_bytes()

    return url, listing


def _process(flight: Path, url: str, tmp_path: Path):
    res = CliRunner().invoke(app, ["process", str(flight), "--database-url", url,
                                   "--artifacts", str(tmp_path / "art"), "--out", str(tmp_path / "run")])
    text = " ".join(res.output.split())
    assert res.exit_code == 2, f"seed {SEED}: {res.output}"
    assert "Traceback" not in res.output and "cannot be processed" in text, res.output
    assert not (tmp_path / "run").exists() and not (tmp_path / "art").exists()
    return text


def test_a_bad_altitude_cell_in_eo_csv_stops_process(tmp_path, store):
    url, listing = store
    before = listing()
    flight = _flight(tmp_path / "flight")
    (flight / "eo.csv").write_text(
        "image,lat,lon,alt\nDJI_0000_R.jpg,47.0,8.0,620\nDJI_0001_R.jpg,47.0001,8.0,abc\n"
        "DJI_0002_R.jpg,47.0002,8.0,620\n")
    text = _process(flight, url, tmp_path)
    assert "eo.csv:3: alt: alt 'abc' is not a number" in text and "could not be applied (line 3)" in text, text
    assert listing() == before


def test_an_image_without_an_eo_row_stops_process(tmp_path, store):
    url, listing = store
    before = listing()
    flight = _flight(tmp_path / "flight")
    (flight / "eo.csv").write_text("image,lat,lon,alt\nDJI_0000_R.jpg,47.0,8.0,620\nDJI_0001_R.jpg,47.0001,8.0,620\n")
    text = _process(flight, url, tmp_path)
    assert "1 ingested image(s) have no row: DJI_0002_R.jpg" in text and "vertical reference" in text, text
    assert listing() == before


def test_a_negative_focal_length_in_camera_json_is_named(tmp_path, store):
    url, listing = store
    before = listing()
    flight = _flight(tmp_path / "flight")
    (flight / "camera.json").write_text(json.dumps({
        "identity": {"make": "DJI", "model": "XT2", "serial": "42", "lens": "13mm"},
        "camera": {"width": 640, "height": 512, "f": -764.7, "cx": 320, "cy": 256}}))
    text = _process(flight, url, tmp_path)
    assert "camera.json: camera: 'camera' is not a valid Camera: focal length must be a positive number" in text
    assert listing() == before


def test_a_flight_folder_as_it_comes_off_the_drone_passes_the_checks(tmp_path):
    """The same three files without any fault: ingest finds nothing that stops processing (exit 0)."""
    flight = _flight(tmp_path / "flight")
    res = CliRunner().invoke(app, ["ingest", str(flight)])
    text = " ".join(res.output.split())
    assert res.exit_code == 0, res.output
    assert "0 error(s)" in text and "DJI | XT2 | no-serial 640x512 | 13.0 mm" in text, res.output
    assert "f 764.7 px" in text and "flying height" in text and "60.0 m" in text


def test_ground_control_from_files_outside_the_folder_is_read_as_process_reads_it(tmp_path):
    """`aerocal ingest FOLDER --gcp A --gcp B`: the control's coordinates in one file and its image measurements in
    another, neither in the folder, read by the reader `aerocal process` uses (both files are ingested: two GCPs,
    their three measurements); the folder alone has no control."""
    from aerocal.geometry import lonlat_to_projected

    flight = _flight(tmp_path / "flight")
    e, n = (float(v) for v in lonlat_to_projected(8.0, 47.0001, "EPSG:32632"))
    control = tmp_path / "control"
    control.mkdir()
    (control / "gcps.csv").write_text(
        f"# crs: EPSG:32632\nid,X,Y,Z,role\nG1,{e},{n},560.0,control\nG2,{e + 5},{n + 5},561.0,check\n")
    (control / "gcp_list.txt").write_text(
        f"EPSG:32632\n{e} {n} 560.0 320.5 256.5 DJI_0001_R.jpg G1\n{e} {n} 560.0 322.5 180.5 DJI_0002_R.jpg G1\n"
        f"{e + 5} {n + 5} 561.0 300.5 200.5 DJI_0001_R.jpg G2\n")
    alone = " ".join(CliRunner().invoke(app, ["ingest", str(flight)], env={"COLUMNS": "250"}).output.split())
    assert "GCPs" not in alone, alone
    res = CliRunner().invoke(app, ["ingest", str(flight), "--gcp", str(control / "gcps.csv"), "--gcp",
                                   str(control / "gcp_list.txt")], env={"COLUMNS": "250"})
    text = " ".join(res.output.split())
    assert res.exit_code == 0, res.output
    assert "2 GCPs (1 control, 1 check), 3 image measurements of 2" in text, res.output


def test_ground_control_1000_m_off_in_one_file_stops_process(tmp_path, store):
    """gcps.csv and gcp_list.txt disagree about G1 by 1000 m: one of them is wrong and only the user knows
    which, so the point is never used as control (it once put check points 87 m off, exit 0)."""
    from aerocal.geometry import lonlat_to_projected

    url, listing = store
    before = listing()
    flight = _flight(tmp_path / "flight")
    e, n = (float(v) for v in lonlat_to_projected(8.0, 47.0001, "EPSG:32632"))
    (flight / "gcps.csv").write_text(
        f"# crs: EPSG:32632\nid,X,Y,Z,role\nG1,{e + 1000.0},{n},560.0,control\nG2,{e + 5},{n + 5},561.0,control\n")
    (flight / "gcp_list.txt").write_text(
        f"EPSG:32632\n{e} {n} 560.0 320.5 256.5 DJI_0001_R.jpg G1\n{e + 5} {n + 5} 561.0 300.5 200.5 "
        "DJI_0001_R.jpg G2\n")
    text = _process(flight, url, tmp_path)
    assert "G1 lies 1000.000 m from its coordinates" in text and "one of the two is wrong" in text, text
    assert "G2 lies" not in text
    assert listing() == before


@pytest.mark.parametrize("name,text", [
    ("cameras.txt", "1 PINHOLE 640 1" + "0" * 400 + " 764.7 764.7 320 256\n"),
    ("cameras.txt", "1 PINHOLE 640 512 1e308 1e308 320 256\n"),
    ("cameras.json", '{"v2 x 640 512 brown 0.85": {"projection_type": "brown", "width": 640, "height": '
                     '-1' + "0" * 400 + ', "focal_x": 1.2, "focal_y": 1.2, "c_x": 0, "c_y": 0, "k1": 0, "k2": 0, '
                     '"p1": 0, "p2": 0, "k3": 0}}'),
    ("calibration.xml", '<?xml version="1.0" encoding="UTFabc"?><calibration><projection>frame</projection>'
                        "<width>640</width><height>512</height><f>764</f></calibration>"),
])
def test_a_hostile_certificate_file_is_refused_and_changes_nothing(name, text, tmp_path, store):
    url, listing = store
    before = listing()
    path = tmp_path / name
    path.write_text(text)
    res = CliRunner().invoke(app, ["certificates", "import", str(path), "--make", "NEC", "--model", "TS9260",
                                   "--serial", "1", "--database-url", url])
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and name in " ".join(res.output.split()), res.output
    assert listing() == before
