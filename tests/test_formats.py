"""Export/import of certificates: OpenCV YAML, COLMAP cameras.txt, OpenSfM cameras.json, Metashape XML.

Round trips are judged by where the imported camera puts image points (``Camera.project`` of the rays
through the original camera's corners), which checks the conventions (pixel centre, p1/p2 order,
normalisation), not only the numbers. Where the target tool is installed (OpenCV, COLMAP) the exported
file is also read back with the tool itself and projected with its own functions.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from aerocal.camera import Camera
from aerocal.certificates.document import CameraIdentity, CameraTerm, Certificate, Quality
from aerocal.formats import (
    FormatError,
    export_certificate,
    guess_format,
    import_certificate,
)
from aerocal.formats.opencv import to_opencv
from aerocal.formats.opensfm import to_opensfm

TOL_PX = 1e-6
SKEW_FREE = ("opencv", "colmap", "opensfm")
FILE_NAMES = {"certificate": "cert.json", "opencv": "camera.yaml", "colmap": "cameras.txt",
              "opensfm": "cameras.json", "metashape": "calibration.xml"}


def distorted_camera(b2: float = 0.0) -> Camera:
    """Strong distortion, off-centre principal point, affinity; skew only where the format holds it."""
    return Camera(width=640, height=512, f=1100.0, cx=327.35, cy=249.6, k1=-0.2, k2=0.05, k3=-0.01,
                  p1=1e-4, p2=-2e-4, b1=0.8, b2=b2)


def certificate_of(camera: Camera) -> Certificate:
    return Certificate(identity=CameraIdentity("Optris", "PI 640", "19071234", "O33"), camera=camera,
                       quality=Quality(reprojection_rms_px=0.31))


def corner_rays(camera: Camera) -> np.ndarray:
    """Camera-frame points (z = 1) that ``camera`` images exactly at its four corners."""
    xy = camera.unproject(camera.corners())
    rays = np.concatenate([xy, np.ones((4, 1))], axis=1)
    assert np.abs(camera.project(rays) - camera.corners()).max() < 1e-9
    return rays


def grid_rays(camera: Camera, n: int = 9) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(0, camera.width, n), np.linspace(0, camera.height, n))
    xy = camera.unproject(np.column_stack([u.ravel(), v.ravel()]))
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1)


def no_temporaries(folder: Path) -> bool:
    return not any(p.name.startswith(".tmp-") for p in folder.iterdir())


# ----------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("fmt", ["certificate", "opencv", "colmap", "opensfm", "metashape"])
def test_round_trip_reproduces_the_corners(fmt, tmp_path):
    camera = distorted_camera(b2=0.0 if fmt in SKEW_FREE else 0.3)
    cert = certificate_of(camera)
    path = export_certificate(cert, fmt, tmp_path / FILE_NAMES[fmt])
    assert path.exists() and no_temporaries(tmp_path)
    assert guess_format(path) == fmt
    back = import_certificate(path)
    got = back.camera
    assert (got.width, got.height) == (640, 512)
    err = np.abs(got.project(corner_rays(camera)) - camera.corners()).max()
    assert err < TOL_PX, f"{fmt}: corners moved by {err:.3g} px"
    np.testing.assert_allclose(got.params(), camera.params(), rtol=1e-12, atol=1e-10)


@pytest.mark.parametrize("fmt", ["opencv", "colmap", "opensfm", "metashape"])
def test_import_records_identity_and_file_hash(fmt, tmp_path):
    cert = certificate_of(distorted_camera())
    path = export_certificate(cert, fmt, tmp_path / FILE_NAMES[fmt])
    ident = CameraIdentity("Optris", "PI 640", "19071234", "O33")
    back = import_certificate(path, identity=ident)
    assert back.identity == ident
    assert import_certificate(path).identity.key == "unknown|unknown|unknown|unknown"
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert back.provenance.inputs == {f"{fmt}:{path.name}": digest}
    assert back.sigmas == {} and back.thermal is None  # the foreign format holds none of these
    assert Certificate.from_json(back.to_json()) == back  # a valid, complete certificate


def test_seeded_random_cameras_survive_every_format(tmp_path):
    seed = 20240517
    rng = np.random.default_rng(seed)
    for i in range(12):
        w, h = int(rng.integers(320, 6000)), int(rng.integers(240, 4000))
        f = float(rng.uniform(0.6, 3.0) * max(w, h))
        cx, cy = w / 2 + rng.normal(0, 0.02 * w), h / 2 + rng.normal(0, 0.02 * h)
        cam = Camera(width=w, height=h, f=f, cx=cx, cy=cy,
                     k1=rng.uniform(-0.3, 0.3), k2=rng.uniform(-0.1, 0.1), k3=rng.uniform(-0.02, 0.02),
                     p1=rng.normal(0, 5e-4), p2=rng.normal(0, 5e-4), b1=rng.normal(0, 2.0))
        rays = grid_rays(cam, 5)
        expected = cam.project(rays)
        for fmt in ("opencv", "colmap", "opensfm", "metashape"):
            path = export_certificate(certificate_of(cam), fmt, tmp_path / f"{i}-{FILE_NAMES[fmt]}")
            err = np.nanmax(np.abs(import_certificate(path).camera.project(rays) - expected))
            assert err < TOL_PX, f"seed {seed}, camera {i}, {fmt}: {err:.3g} px ({cam})"


def test_export_accepts_a_json_document(tmp_path):
    doc = certificate_of(distorted_camera(b2=0.3)).to_dict()
    path = export_certificate(doc, "metashape", tmp_path / "c.xml")
    assert import_certificate(path).camera.b2 == pytest.approx(0.3, abs=1e-15)
    doc["model"]["params"]["f"] = "abc"
    with pytest.raises(FormatError, match='model.params.f: expected a positive number, got "abc"'):
        export_certificate(doc, "opencv", tmp_path / "bad.yaml")
    assert not (tmp_path / "bad.yaml").exists()


# ----------------------------------------------------------------------------- conventions against the tools
def test_opencv_file_read_by_opencv_projects_like_aerocal(tmp_path):
    camera = distorted_camera()
    path = export_certificate(certificate_of(camera), "opencv", tmp_path / "camera.yaml")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat()
    assert int(fs.getNode("image_width").real()) == 640
    fs.release()
    rays = grid_rays(camera)
    uv_cv, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)
    # OpenCV puts the first pixel's centre at (0, 0), aerocal at (0.5, 0.5)
    err = np.abs(uv_cv.reshape(-1, 2) + 0.5 - camera.project(rays)).max()
    assert err < TOL_PX, f"OpenCV projects {err:.3g} px away from aerocal"


def test_colmap_file_read_by_colmap_projects_like_aerocal(tmp_path):
    camera = distorted_camera()
    export_certificate(certificate_of(camera), "colmap", tmp_path / "cameras.txt")
    (tmp_path / "images.txt").write_text("")
    (tmp_path / "points3D.txt").write_text("")
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path))
    cam = rec.cameras[1]
    assert cam.model.name == "FULL_OPENCV" and (cam.width, cam.height) == (640, 512)
    rays = grid_rays(camera)
    err = np.abs(np.asarray(cam.img_from_cam(rays)) - camera.project(rays)).max()
    assert err < TOL_PX, f"COLMAP projects {err:.3g} px away from aerocal"


def test_opensfm_parameters_follow_opensfm_projection(tmp_path):
    """OpenSfM's brown projection, transcribed from its sources (DistoBrown, Affine, denormalised
    image coordinates), applied to the exported parameters, must land on aerocal's pixels."""
    camera = distorted_camera()
    path = export_certificate(certificate_of(camera), "opensfm", tmp_path / "cameras.json")
    (key, o), = json.loads(path.read_text()).items()
    assert key.startswith("v2 optris pi 640 640 512 brown")
    rays = grid_rays(camera)
    x, y = rays[:, 0], rays[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (o["k1"] + r2 * (o["k2"] + r2 * o["k3"]))
    xd = x * radial + 2 * o["p1"] * x * y + o["p2"] * (r2 + 2 * x * x)
    yd = y * radial + 2 * o["p2"] * x * y + o["p1"] * (r2 + 2 * y * y)
    nx, ny = o["focal_x"] * xd + o["c_x"], o["focal_y"] * yd + o["c_y"]
    size = max(o["width"], o["height"])
    u_opencv = nx * size - 0.5 + o["width"] / 2.0  # features.denormalized_image_coordinates
    v_opencv = ny * size - 0.5 + o["height"] / 2.0
    err = np.abs(np.column_stack([u_opencv, v_opencv]) + 0.5 - camera.project(rays)).max()
    assert err < TOL_PX


def test_metashape_parameters_follow_metashape_projection(tmp_path):
    """Metashape's frame model (manual, appendix on camera models), applied to the exported values."""
    camera = distorted_camera(b2=0.3)
    path = export_certificate(certificate_of(camera), "metashape", tmp_path / "c.xml")
    import defusedxml.ElementTree as DET

    root = DET.parse(str(path), forbid_dtd=True).getroot()
    assert (root.tag, root.get("class"), root.get("type")) == ("calibration", "adjusted", "frame")
    v = {el.tag: el.text for el in root}
    p = {k: float(v[k]) for k in ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "p1", "p2")}
    w, h = int(v["width"]), int(v["height"])
    rays = grid_rays(camera)
    x, y = rays[:, 0], rays[:, 1]
    r2 = x * x + y * y
    radial = 1 + p["k1"] * r2 + p["k2"] * r2**2 + p["k3"] * r2**3
    xd = x * radial + p["p1"] * (r2 + 2 * x * x) + 2 * p["p2"] * x * y
    yd = y * radial + p["p2"] * (r2 + 2 * y * y) + 2 * p["p1"] * x * y
    u = w * 0.5 + p["cx"] + xd * (p["f"] + p["b1"]) + yd * p["b2"]
    vv = h * 0.5 + p["cy"] + yd * p["f"]
    assert np.abs(np.column_stack([u, vv]) - camera.project(rays)).max() < TOL_PX


def test_metashape_export_of_a_readout_sets_the_sensors_rolling_shutter_flag(tmp_path):
    """A certificate whose camera terms hold a readout goes to Metashape as a cameras XML sensor with its
    rolling-shutter flag on (the one Metashape field for it) and the readout in a comment; read back, it is the
    same camera. Without a readout the standalone calibration file is written, its flag absent."""
    camera = distorted_camera(b2=0.3).replace(pixel_size_mm=0.017)
    readout = CameraTerm((0.0301,), (0.0006,), "s", "measurements", ("flight 1", "flight 2"), "held-out +14 %")
    cert = dataclasses.replace(certificate_of(camera), terms={"rolling_shutter": readout})
    path = export_certificate(cert, "metashape", tmp_path / "cameras.xml")
    import defusedxml.ElementTree as DET

    root = DET.parse(str(path), forbid_dtd=True).getroot()
    sensor = root.find("chunk/sensors/sensor")
    props = {p.get("name"): p.get("value") for p in sensor.iter("property")}
    assert root.tag == "document" and props["rolling_shutter"] == "true" and float(props["pixel_width"]) == 0.017
    assert "rolling_shutter 0.0301 s" in path.read_text()
    back = import_certificate(path).camera
    assert np.abs(back.project(grid_rays(camera)) - camera.project(grid_rays(camera))).max() < TOL_PX
    assert back.pixel_size_mm == 0.017
    plain = export_certificate(certificate_of(camera), "metashape", tmp_path / "calibration.xml")
    assert DET.parse(str(plain), forbid_dtd=True).getroot().tag == "calibration"
    flag_off = export_certificate(certificate_of(camera), "metashape", tmp_path / "sensor.xml", form="sensor")
    assert 'name="rolling_shutter" value="false"' in flag_off.read_text()


# ----------------------------------------------------------------------------- files written by the tools
@pytest.mark.parametrize("dist_shape", [(1, 5), (5, 1), (5,)], ids=["row", "column", "nd"])
def test_yaml_written_by_cv2_filestorage_imports_to_the_same_camera(tmp_path, dist_shape):
    camera = distorted_camera()
    K, dist = to_opencv(camera)
    path = tmp_path / "calib.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Tue Mar 14 10:00:00 2017")
    fs.write("image_width", 640)
    fs.write("image_height", 512)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist.reshape(dist_shape))  # (5,): !!opencv-nd-matrix
    fs.write("avg_reprojection_error", 0.42)
    fs.release()
    assert path.read_text().startswith("%YAML")
    back = import_certificate(path)
    assert np.abs(back.camera.project(corner_rays(camera)) - camera.corners()).max() < TOL_PX
    assert back.quality.reprojection_rms_px == pytest.approx(0.42)


def test_opencv4_style_yaml_and_xml_storage_import(tmp_path):
    camera = distorted_camera()
    K, dist = to_opencv(camera)
    text = (
        "%YAML:1.0\n---\nimage_width: 640\nimage_height: 512\ncamera_matrix: !!opencv-matrix\n"
        f"   rows: 3\n   cols: 3\n   dt: d\n   data: [ {', '.join(repr(float(v)) for v in K.ravel())} ]\n"
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 8\n   dt: d\n"
        f"   data: [ {', '.join(repr(float(v)) for v in dist)}, 0., 0., 0. ]\n"
    )
    (tmp_path / "cv4.yaml").write_text(text)
    back = import_certificate(tmp_path / "cv4.yaml")
    assert np.abs(back.camera.project(corner_rays(camera)) - camera.corners()).max() < TOL_PX
    xml_path = tmp_path / "calib.xml"
    fs = cv2.FileStorage(str(xml_path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 512)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist)
    fs.release()
    assert guess_format(xml_path) == "opencv"
    back = import_certificate(xml_path)
    assert np.abs(back.camera.project(corner_rays(camera)) - camera.corners()).max() < TOL_PX


def test_cameras_txt_written_by_pycolmap_imports_correctly(tmp_path):
    params = [1100.8, 1100.0, 327.35, 249.6, -0.2, 0.05, -2e-4, 1e-4, -0.01, 0.0, 0.0, 0.0]
    cam = pycolmap.Camera(model="FULL_OPENCV", width=640, height=512, params=params, camera_id=1)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    rec.write_text(str(tmp_path))
    back = import_certificate(tmp_path / "cameras.txt")
    expected = distorted_camera()  # the same camera in aerocal's parameters
    rays = grid_rays(expected)
    assert np.abs(back.camera.project(rays) - np.asarray(cam.img_from_cam(rays))).max() < TOL_PX
    np.testing.assert_allclose(back.camera.params(), expected.params(), rtol=1e-12, atol=1e-12)


def test_metashape_cameras_xml_with_covariance_and_two_sensors(tmp_path):
    names = ["f", "cx", "cy", "b1", "k1", "k2", "p1", "p2"]
    sig = np.array([0.5, 0.4, 0.3, 0.05, 1e-3, 2e-3, 1e-5, 2e-5])
    corr = np.eye(8)
    corr[0, 4] = corr[4, 0] = 0.95
    cov = corr * np.outer(sig, sig)
    xml = f"""<?xml version="1.0" encoding="UTF-8"?>
<document version="1.5.0"><chunk label="Chunk 1"><sensors next_id="2">
  <sensor id="0" label="RGB (8mm)" type="frame"><resolution width="5472" height="3648"/>
    <calibration type="frame" class="adjusted"><resolution width="5472" height="3648"/>
      <f>3650.1</f><cx>12.5</cx><cy>-8.25</cy><k1>-0.01</k1></calibration></sensor>
  <sensor id="1" label="Optris PI 640 (O33)" type="frame"><resolution width="640" height="480"/>
    <property name="pixel_width" value="0.017"/><property name="pixel_height" value="0.017"/>
    <calibration type="frame" class="initial"><resolution width="640" height="480"/><f>1000</f></calibration>
    <calibration type="frame" class="adjusted"><resolution width="640" height="480"/>
      <f>1100.5</f><cx>3.5</cx><cy>-2.25</cy><b1>0.8</b1><k1>-0.2</k1><k2>0.05</k2>
      <p1>0.0001</p1><p2>-0.0002</p2></calibration>
    <covariance><params>{" ".join(names)}</params>
    <coeffs>{" ".join(repr(float(v)) for v in cov.ravel())}</coeffs>
    </covariance></sensor>
</sensors></chunk></document>"""
    path = tmp_path / "cameras.xml"
    path.write_text(xml)
    two_sensors = r"cameras.xml: <sensor>: 2 sensors: 0 \(RGB \(8mm\)\), 1 .*sensor="
    with pytest.raises(FormatError, match=two_sensors):
        import_certificate(path)
    back = import_certificate(path, sensor="Optris PI 640 (O33)")
    cam = back.camera
    assert (cam.width, cam.height, cam.f, cam.cx, cam.cy) == (640, 480, 1100.5, 323.5, 237.75)
    assert cam.pixel_size_mm == 0.017 and cam.b1 == 0.8 and cam.p2 == -0.0002
    assert back.estimated == tuple(names)
    np.testing.assert_allclose([back.sigmas[n] for n in names], sig, rtol=1e-12)
    assert back.correlation.value("f", "k1") == pytest.approx(0.95, abs=1e-12)
    assert import_certificate(path, sensor="0").camera.cx == 5472 / 2 + 12.5


# ----------------------------------------------------------------------------- safety
def test_billion_laughs_xml_is_refused(tmp_path):
    levels = "".join(f'<!ENTITY lol{i} "{f"&lol{i - 1};" * 10}">' for i in range(1, 10))
    path = tmp_path / "laughs.xml"
    path.write_text(f'<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol0 "lol">{levels}]>'
                    "<calibration><f>&lol9;</f></calibration>")
    with pytest.raises(FormatError) as info:
        import_certificate(path, "metashape")
    assert str(info.value).startswith(f"{path}: <!DOCTYPE>: XML document type declarations are refused")
    assert "remove the <!DOCTYPE" in str(info.value)


def test_external_entity_xml_is_refused(tmp_path):
    secret = tmp_path / "secret.txt"
    secret.write_text("TOP-SECRET-VALUE")
    path = tmp_path / "xxe.xml"
    path.write_text(f'<?xml version="1.0"?><!DOCTYPE c [<!ENTITY xxe SYSTEM "file://{secret}">]>'
                    "<calibration><width>&xxe;</width></calibration>")
    for fmt in ("metashape", "opencv", None):
        with pytest.raises(FormatError, match="XML document type declarations are refused") as info:
            import_certificate(path, fmt)
        assert "TOP-SECRET" not in str(info.value)


def test_yaml_with_python_object_tag_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.yaml"
    path.write_text("%YAML:1.0\n---\nimage_width: 640\nimage_height: 512\n"
                    f"camera_matrix: !!python/object/apply:os.system ['touch {marker}']\n")
    with pytest.raises(FormatError) as info:
        import_certificate(path)
    msg = str(info.value)
    expected = f"{path}: line 5, field camera_matrix: YAML tag tag:yaml.org,2002:python/object/apply"
    assert msg.startswith(expected), msg
    assert "remove the tag" in msg
    assert not marker.exists()


def test_yaml_aliases_are_refused(tmp_path):
    path = tmp_path / "alias.yaml"
    path.write_text("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a]\n"
                    "image_width: 640\n")
    with pytest.raises(FormatError, match=r"alias.yaml: line 2: invalid YAML \(YAML alias \*a refused"):
        import_certificate(path)


# ----------------------------------------------------------------------------- malformed files
def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


YAML_HEAD = "%YAML:1.0\n---\nimage_width: 640\nimage_height: 512\n"
K_OK = ("camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
        "   data: [1100., 0., 320., 0., 1100., 256., 0., 0., 1.]\n")

MALFORMED_FILES = [
    ("opencv", "a.yaml", YAML_HEAD, "a.yaml: field camera_matrix: missing; add the 3x3 camera_matrix"),
    ("opencv", "b.yaml", YAML_HEAD + "camera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n"
     "   data: [1., 2.]\n",
     "b.yaml: line 5, field camera_matrix: invalid YAML (!!opencv-matrix data must be 9"),
    ("opencv", "c.yaml", YAML_HEAD + K_OK + "distortion_coefficients: !!opencv-matrix\n"
     "   rows: 1\n   cols: 8\n   dt: d\n   data: [-0.2, 0.05, 0., 0., 0., 0.3, 0., 0.]\n",
     "c.yaml: line 10, field distortion_coefficients: coefficient k4 = 0.3 is not zero"),
    ("opencv", "d.yaml", "%YAML:1.0\n---\nimage_width: wide\nimage_height: 512\n" + K_OK,
     "d.yaml: line 3, field image_width: expected a positive integer, got 'wide'"),
    ("opencv", "e.yaml", YAML_HEAD + "camera_matrix: [1, 2\n", "e.yaml: line 6: invalid YAML"),
    ("colmap", "a.txt", "# c\n1 FULL_OPENCV 640 512 1100 1100 320 256\n",
     "a.txt: line 2, field PARAMS: FULL_OPENCV needs 12 parameters"),
    ("colmap", "b.txt", "1 OPENCV_FISHEYE 640 512 1100 1100 320 256 0 0 0 0\n",
     "b.txt: line 1, field MODEL: camera model OPENCV_FISHEYE cannot be held"),
    ("colmap", "c.txt", "1 PINHOLE 640 -512 1100 1100 320 256\n",
     "c.txt: line 1, field HEIGHT: expected a positive integer of at most 200000, got '-512'"),
    ("colmap", "d.txt", "1 PINHOLE 640 512 1100 1100 320 256\n2 PINHOLE 640 512 900 900 320 256\n",
     "d.txt: field CAMERA_ID: 2 cameras ([1, 2]); pass camera_id= to choose one"),
    ("colmap", "e.txt", "1 FULL_OPENCV 640 512 1100 1100 320 256 0 0 0 0 0 0.1 0 0\n",
     "e.txt: line 1, field PARAMS: FULL_OPENCV camera has rational terms"),
    ("opensfm", "a.json",
     '{"cam": {"projection_type": "brown", "width": 640, "height": 512, "focal_y": 1.7}}',
     "a.json: 'cam'.focal_x: missing"),
    ("opensfm", "b.json",
     '{"cam": {"projection_type": "fisheye", "width": 640, "height": 512, "focal": 1.7}}',
     "b.json: 'cam'.projection_type: 'fisheye' cannot be held by the Brown model"),
    ("opensfm", "c.json", '{"cam": {"projection_type": "brown", "width": 640, "height": 512,\n'
     '"focal_x": 1.7 "focal_y": 1.7}}', "c.json: line 2, column 16: invalid JSON"),
    ("opensfm", "d.json",
     '{"cam": {"projection_type": "brown", "width": 640, "height": 512, "focal_x": "1.7",'
     ' "focal_y": 1.7}}', "d.json: 'cam'.focal_x: expected a finite number, got '1.7'"),
    ("metashape", "a.xml", "<calibration><projection>frame</projection><width>640</width><height>512</height>"
     "<f>abc</f></calibration>", "a.xml: <f>: expected a number, got 'abc'; write a decimal number"),
    ("metashape", "b.xml", "<calibration><width>640</width><height>512</height><f>1100</f><k4>0.01</k4>"
     "</calibration>", "b.xml: <k4>: k4 = 0.01 cannot be held by the Brown model"),
    ("metashape", "c.xml", "<calibration><width>640</width><height>512</height></calibration>",
     "c.xml: <f>: missing; add <f>"),
    ("metashape", "d.xml", "<calibration><width>640<height>512</height></calibration>",
     "d.xml: line 1, column 46: malformed XML (mismatched tag)"),
    ("metashape", "e.xml",
     "<calibration><projection>fisheye</projection><width>640</width><height>512</height>"
     "<f>1</f></calibration>", "e.xml: <projection>: camera type 'fisheye' is not a frame camera"),
    ("certificate", "cert.json", None, "cert.json: model.params.f: expected a positive number, got \"abc\""),
]


@pytest.mark.parametrize(("fmt", "name", "text", "message"), MALFORMED_FILES,
                         ids=[f"{m[0]}-{m[1]}" for m in MALFORMED_FILES])
def test_malformed_file_error_names_file_field_and_fix(tmp_path, fmt, name, text, message):
    if text is None:  # a certificate document with a bad focal length
        doc = certificate_of(distorted_camera()).to_dict()
        doc["model"]["params"]["f"] = "abc"
        text = json.dumps(doc)
    path = _write(tmp_path, name, text)
    with pytest.raises(FormatError) as info:
        import_certificate(path, fmt)
    msg = str(info.value)
    assert msg.startswith(f"{tmp_path}{os.sep}{message}"), msg
    assert "\n" not in msg and "; " in msg


def test_missing_and_oversized_files_are_refused(tmp_path):
    with pytest.raises(FormatError, match="nothing.yaml: file not found; check the path"):
        import_certificate(tmp_path / "nothing.yaml")
    big = tmp_path / "big.txt"
    with open(big, "wb") as fh:
        fh.truncate(17 * 1024 * 1024)
    with pytest.raises(FormatError, match="big.txt: file is 17825792 bytes"):
        import_certificate(big)
    odd = _write(tmp_path, "calib.dat", "f = 1100\n")
    with pytest.raises(FormatError, match="calib.dat: cannot tell the format .*; pass fmt="):
        import_certificate(odd)


@pytest.mark.parametrize("fmt", SKEW_FREE)
def test_formats_without_skew_refuse_it_and_leave_the_old_file(fmt, tmp_path):
    path = tmp_path / FILE_NAMES[fmt]
    path.write_text("previous content\n")
    cert = certificate_of(distorted_camera(b2=0.3))
    with pytest.raises(FormatError, match=r"b2: camera has skew b2=0.3 px.*drop_skew=True.*Metashape"):
        export_certificate(cert, fmt, path)
    assert path.read_text() == "previous content\n" and no_temporaries(tmp_path)
    export_certificate(cert, fmt, path, drop_skew=True)
    assert import_certificate(path).camera.b2 == 0.0


def test_unknown_format_and_option_are_named():
    cert = certificate_of(distorted_camera())
    with pytest.raises(FormatError, match="format 'pix4d' unknown; use one of certificate, opencv"):
        export_certificate(cert, "pix4d", "x.cam")
    with pytest.raises(TypeError, match="option\\(s\\) sensor not accepted; valid: camera_id"):
        import_certificate("cameras.txt", "colmap", sensor="1")


def test_opensfm_import_of_perspective_and_reconstruction_json(tmp_path):
    camera = distorted_camera()
    brown = to_opensfm(camera)
    rec = [{"cameras": {"v2 a b 640 512 brown 1.7": brown}, "shots": {}, "points": {}}]
    path = _write(tmp_path, "reconstruction.json", json.dumps(rec))
    err = np.abs(import_certificate(path).camera.project(corner_rays(camera)) - camera.corners()).max()
    assert err < TOL_PX
    persp = _write(tmp_path, "persp.json", json.dumps(
        {"k": {"projection_type": "perspective", "width": 640, "height": 480, "focal": 0.9, "k1": -0.1}}))
    cam = import_certificate(persp).camera
    assert (cam.f, cam.cx, cam.cy, cam.k1, cam.b1) == (576.0, 320.0, 240.0, -0.1, 0.0)


#: what a hand edit, a script or an attacker puts where a number belongs
HOSTILE_NUMBERS = ["1" + "0" * 400, "-1" + "0" * 400, "1e400", "-1e400", "nan", "inf", "-5", "0", "1e-320", "abc",
                   "", "4294967297", "9" * 25]
FUZZ_SEED = 20261125


def test_hostile_numbers_in_every_format_are_format_errors(tmp_path):
    """750 seeded mutations (each number of an exported file replaced by a hostile token): every import either
    succeeds or raises FormatError naming the file; never OverflowError, TypeError or another crash."""
    import re

    rng = np.random.default_rng(FUZZ_SEED)
    for fmt, name in FILE_NAMES.items():
        path = tmp_path / name
        export_certificate(certificate_of(distorted_camera(0.3 if fmt in ("metashape", "certificate") else 0.0)),
                           fmt, path)
        text = path.read_text()
        numbers = list(re.finditer(r"-?\d+(\.\d+)?([eE][-+]?\d+)?", text))
        for k in range(150):
            m = numbers[int(rng.integers(len(numbers)))]
            token = HOSTILE_NUMBERS[int(rng.integers(len(HOSTILE_NUMBERS)))]
            bad = tmp_path / f"bad-{name}"
            bad.write_text(text[: m.start()] + token + text[m.end():])
            try:
                import_certificate(bad, fmt)
            except FormatError as exc:
                assert str(exc).startswith(str(bad)) and "\n" not in str(exc), f"seed {FUZZ_SEED} case {k}: {exc}"
            except Exception as exc:  # the assertion: nothing else is raised
                pytest.fail(f"seed {FUZZ_SEED}, {fmt} case {k}: {m.group(0)!r} -> {token[:20]!r}: "
                            f"{type(exc).__name__}: {exc}")
