"""Simulated flight folders (the simulator's contract), EO CSVs, ground control files and the strip rule."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from aerocal import tables
from aerocal.camera import Camera
from aerocal.geometry import projected_to_lonlat
from aerocal.ingest import IngestConfig, StripConfig, find_strips, ingest_folder, read_raw
from aerocal.ingest.metadata_writer import (
    dji_xmp_packet,
    exif_block,
    jpeg_with_metadata,
    write_tiff_with_metadata,
)

CRS = "EPSG:32632"
E0, N0 = 500_000.0, 5_200_000.0  # UTM 32N, 9 deg E, ~46.9 deg N
W, H = 64, 48
T0 = dt.datetime(2024, 5, 1, 10, 0, 0)
IDENTITY = {"make": "aerocal", "model": "SimTherm", "serial": "S123", "lens": "L13"}


def _plan() -> list[tuple[float, float, float]]:
    """Two opposite strips of 6 frames 50 m apart along north, two turn frames between: (E, N, yaw)."""
    out = [(E0, N0 + 50.0 * k, 0.0) for k in range(6)]
    out += [(E0 + 20.0, N0 + 300.0, 90.0), (E0 + 40.0, N0 + 300.0, 90.0)]
    out += [(E0 + 60.0, N0 + 250.0 - 50.0 * k, 180.0) for k in range(6)]
    return out


def make_flight(root: Path, fmt: str = "tiff", seed: int = 0, xmp_offset_m: float = 10.0) -> dict:
    """Write a flight folder as the simulator does; return what was written (truth for the test)."""
    rng = np.random.default_rng(seed)
    images = root / "images"
    images.mkdir(parents=True)
    plan = _plan()
    names, temps, lonlat = [], [], []
    for k, (e, n, yaw) in enumerate(plan):
        name = f"IMG_{k + 1:04d}.{'tif' if fmt == 'tiff' else 'jpg'}"
        lon, lat = projected_to_lonlat(e, n, CRS)
        xlon, xlat = projected_to_lonlat(e + xmp_offset_m, n, CRS)  # the metadata the EO CSV overrides
        xmp = dji_xmp_packet(
            {
                "GpsLatitude": float(xlat),
                "GpsLongitude": float(xlon),
                "AbsoluteAltitude": 900.0,
                "GimbalRollDegree": 0.0,
                "GimbalPitchDegree": -90.0,
                "GimbalYawDegree": yaw,
            }
        )
        when = T0 + dt.timedelta(seconds=2.5 * k)
        if fmt == "tiff":
            pixels = rng.integers(20000, 30000, size=(H, W), dtype=np.uint16)
            write_tiff_with_metadata(images / name, pixels, time=when, xmp=xmp, **IDENTITY)
        else:
            rgb = np.zeros((H, W, 3), np.uint8)
            rgb[..., 0], rgb[..., 1], rgb[..., 2] = 200, 120, 10
            ok, buf = cv2.imencode(".jpg", rgb[..., ::-1])  # OpenCV encodes BGR
            exif = exif_block(time=when, **IDENTITY)
            (images / name).write_bytes(jpeg_with_metadata(buf.tobytes(), exif=exif, xmp=xmp))
        names.append(name)
        temps.append(30.0 - 0.5 * k)
        lonlat.append((float(lon), float(lat)))
    rows = [
        f"{nm},{la:.9f},{lo:.9f},{850.0 + k},0.0,-90.0,{plan[k][2]},{temps[k]}"
        for k, (nm, (lo, la)) in enumerate(zip(names, lonlat, strict=True))
    ]
    (root / "eo.csv").write_text(
        "# crs: EPSG:4326\n# attitude: dji_gimbal\nimage,lat,lon,alt,roll,pitch,yaw,temperature\n"
        + "\n".join(rows)
    )
    gcps = {"G1": (E0 + 5.0, N0 + 20.0, 400.0, "control"), "G2": (E0 + 50.0, N0 + 200.0, 401.0, "check")}
    (root / "gcps.csv").write_text(
        "# crs: EPSG:32632\nid,X,Y,Z,sigma_xy,sigma_z,role\n"
        + "\n".join(f"{g},{x},{y},{z},0.01,0.02,{r}" for g, (x, y, z, r) in gcps.items())
    )
    (root / "gcp_list.txt").write_text(
        "EPSG:32632\n"
        f"{E0 + 5.0} {N0 + 20.0} 400.0 10.0 20.0 IMG_0001.{names[0][-3:]} G1\n"
        f"{E0 + 5.0} {N0 + 20.0} 400.0 30.0 12.0 IMG_0002.{names[0][-3:]} G1\n"
        f"{E0 + 50.0} {N0 + 200.0} 401.0 40.5 33.25 {names[12]} G2\n"
    )
    (root / "camera.json").write_text(
        json.dumps(
            {"identity": IDENTITY, "camera": {"width": W, "height": H, "f": 80.0, "cx": 32.0, "cy": 24.0}}
        )
    )
    (root / "truth.json").write_text("not json: ingest must never read this file")
    return {"names": names, "temps": temps, "lonlat": lonlat, "plan": plan}


# ---------------------------------------------------------------------------- simulated flights
def test_simulated_tiff_flight_folder(tmp_path):
    truth = make_flight(tmp_path / "flight", "tiff")
    r = ingest_folder(tmp_path / "flight")
    assert not r.errors, [str(p) for p in r.errors]
    assert not any("truth.json" in p.file or "truth.json" in p.message for p in r.problems)
    assert "truth" not in json.dumps(r.sources)
    img = tables.validate(r.images, "images")
    assert img.num_rows == 14 and r.crs == CRS
    assert set(img.column("bit_depth").to_pylist()) == {16}
    assert set(img.column("camera_id").to_pylist()) == {"aerocal|SimTherm|S123|L13"}
    # EO overrides the XMP position (which was shifted 10 m east)
    e = np.array(img.column("gnss_x").to_pylist())
    n = np.array(img.column("gnss_y").to_pylist())
    plan = np.array(truth["plan"])
    assert np.abs(e - plan[:, 0]).max() < 1e-3 and np.abs(n - plan[:, 1]).max() < 1e-3
    assert img.column("alt").to_pylist() == [850.0 + k for k in range(14)]
    assert img.column("temperature_c").to_pylist() == truth["temps"]
    assert set(img.column("attitude_convention").to_pylist()) == {"dji_gimbal"}
    assert img.column("time")[1].as_py() - img.column("time")[0].as_py() == dt.timedelta(seconds=2.5)
    strips = img.column("strip").to_pylist()
    assert strips == [0] * 6 + [-1, -1] + [1] * 6
    assert r.camera == Camera(width=W, height=H, f=80.0, cx=32.0, cy=24.0)
    assert r.camera_identity.camera_id == "aerocal|SimTherm|S123|L13"
    raw = read_raw(img.column("path")[0].as_py())
    assert raw.dtype == np.uint16 and raw.shape == (H, W) and raw.min() >= 20000
    # ground control: roles and sigmas from gcps.csv, measurements from gcp_list.txt (+0.5 px)
    g = {row["gcp_id"]: row for row in tables.validate(r.gcps, "gcps").to_pylist()}
    assert g["G1"]["role"] == "control" and g["G2"]["role"] == "check"
    assert g["G1"]["sigma_x"] == 0.01 and g["G2"]["sigma_z"] == 0.02 and g["G2"]["Z"] == 401.0
    obs = tables.validate(r.gcp_observations, "gcp_observations").to_pylist()
    assert [(o["gcp_id"], o["image_id"], o["x"], o["y"]) for o in obs] == [
        ("G1", 1, 10.5, 20.5),
        ("G1", 2, 30.5, 12.5),
        ("G2", 13, 41.0, 33.75),
    ]


def test_simulated_jpeg_flight_and_explicit_arguments(tmp_path):
    make_flight(tmp_path / "flight", "jpeg")
    eo = tmp_path / "other_eo.csv"
    eo.write_text("image,x,y,z,omega,phi,kappa\nIMG_0001.jpg,500001.0,5200002.0,777.0,1.0,2.0,3.0\n")
    r = ingest_folder(
        tmp_path / "flight", eo_file=eo, crs="EPSG:32632", gcp_file=tmp_path / "flight" / "gcps.csv"
    )
    img = r.images
    assert set(img.column("bit_depth").to_pylist()) == {8}
    first = img.slice(0, 1).to_pylist()[0]
    assert (first["gnss_x"], first["gnss_y"], first["alt"]) == (500001.0, 5200002.0, 777.0)
    assert first["attitude_convention"] == "opk" and (first["roll"], first["pitch"], first["yaw"]) == (
        1,
        2,
        3,
    )
    second = img.slice(1, 1).to_pylist()[0]
    assert abs(second["gnss_x"] - (E0 + 10.0)) < 0.02, "no EO row: the XMP position (1e-7 deg) is kept"
    assert second["attitude_convention"] == "dji_gimbal"
    missing = [p for p in r.problems if p.file == str(eo) and p.field == "image"]
    assert len(missing) == 1 and "13 ingested image(s) have no row" in missing[0].message
    # kept, and said: processing them would mix the file's positions with the XMP's (another vertical datum)
    assert missing[0].stops_processing and "another source and vertical reference" in missing[0].message
    assert r.gcp_observations.num_rows == 0 and r.gcps.num_rows == 2
    rgb = read_raw(first["path"])
    assert (
        rgb.shape == (H, W, 3)
        and abs(int(rgb[..., 0].mean()) - 200) < 4
        and abs(int(rgb[..., 2].mean()) - 10) < 4
    )


def test_list_of_images_and_missing_inputs(tmp_path):
    make_flight(tmp_path / "f", "tiff")
    files = sorted((tmp_path / "f" / "images").glob("*.tif"))[:3] + [tmp_path / "nope.tif"]
    r = ingest_folder(files)
    assert r.images.num_rows == 3
    assert any(p.file == str(tmp_path / "nope.tif") and p.severity == "error" for p in r.problems)
    empty = ingest_folder(tmp_path / "does_not_exist")
    assert empty.images.num_rows == 0 and empty.errors[0].file == str(tmp_path / "does_not_exist")
    bad_crs = ingest_folder(tmp_path / "f", crs="EPSG:4326")
    assert bad_crs.crs == CRS and any(
        p.field == "crs" and "not a projected" in p.message for p in bad_crs.errors
    )


# ---------------------------------------------------------------------------- EO CSV problems
def test_eo_csv_problems_are_reported_by_line(tmp_path):
    make_flight(tmp_path / "f", "tiff")
    eo = tmp_path / "eo.csv"
    eo.write_text(
        "# crs: EPSG:4326\n# attitude: dji_gimbal\n"
        "image,lat,lon,alt,roll,pitch,yaw,temperature\n"
        "IMG_0001.tif,400,9.0,100,0,-90,0,20\n"  # line 4: latitude 400
        "IMG_0002.tif,46.9,9.0,100,0,-90,0,nan\n"  # line 5: NaN temperature
        "IMG_0003.tif,46.9,abc,100,0,-90,0,20\n"  # line 6: non-numeric longitude
        "IMG_0004.tif,46.9,9.0,100,0,-90\n"  # line 7: wrong column count
        "IMG_9999.tif,46.9,9.0,100,0,-90,0,20\n"  # line 8: not in the folder
    )
    r = ingest_folder(tmp_path / "f", eo_file=eo)
    by_line = {p.line: p for p in r.problems if p.file == str(eo)}
    assert "outside the globe" in by_line[4].message
    assert by_line[5].field == "temperature" and "not a finite number" in by_line[5].message
    assert by_line[6].field == "lon" and "'abc' is not a number" in by_line[6].message
    assert "has 6 fields, the header has 8" in by_line[7].message
    assert "IMG_9999.tif is not among the ingested images" in by_line[8].message
    img = r.images.to_pylist()
    assert img[0]["lat"] is not None and abs(img[0]["lat"]) <= 90, "latitude 400 never reaches the table"
    assert img[1]["temperature_c"] is None, "NaN temperature never reaches the table"
    unknown = tmp_path / "eo2.csv"
    unknown.write_text("# attitude: ypr\nimage,x,y,z,roll,pitch,yaw\nIMG_0001.tif,1,2,3,0,0,0\n")
    r2 = ingest_folder(tmp_path / "f", eo_file=unknown)
    assert any(p.field == "crs" and "no '# crs: ...' line" in p.message for p in r2.errors)


# ---------------------------------------------------------------------------- ground control problems
def test_gcp_files_problems_by_file_and_line(tmp_path):
    make_flight(tmp_path / "f", "tiff")
    odm = tmp_path / "gcp_list.txt"
    odm.write_text(
        "EPSG:32632\n"
        f"{E0} {N0} 10.0 5.0 5.0 IMG_0001.tif A\n"  # 2 ok
        f"{E0} {N0} 10.0 5.0\n"  # 3 wrong column count
        f"{E0} abc 10.0 5.0 5.0 IMG_0001.tif A\n"  # 4 non-numeric
        f"{E0} {N0} 10.0 500.0 5.0 IMG_0002.tif A\n"  # 5 outside the image (64x48)
        f"{E0} {N0} 10.0 5.0 5.0 IMG_0404.tif A\n"  # 6 image not in the folder
        f"{E0 + 30} {N0} 10.0 5.5 5.2 IMG_0001.tif B\n"  # 7 two labels at one pixel (with line 2)
        f"{E0} {N0} 10.0 7.0 7.0 IMG_0001.tif A\n"  # 8 measured twice in one image
        f"{E0 + 1} {N0} 10.0 9.0 9.0 IMG_0003.tif A\n"  # 9 same label, other coordinates
        f"{E0 + 60} {N0} 11.0 20.0 20.0 IMG_0003.tif C\n"  # 10 label missing from the coordinate list
    )
    coords = tmp_path / "gcps.csv"
    coords.write_text(
        "# crs: EPSG:32632\nid,X,Y,Z,sigma_xy,sigma_z,role\n"
        f"A,{E0},{N0},10.0,0.01,0.02,control\n"  # 3
        f"B,{E0 + 30},{N0},10.0,0.01,0.02,chek\n"  # 4 bad role
        f"D,{E0},{N0},10.0,-1,0.02,check\n"  # 5 negative sigma
    )
    r = ingest_folder(tmp_path / "f", gcp_file=[coords, odm])
    odm_p = {p.line: p for p in r.problems if p.file == str(odm)}
    csv_p = {p.line: p for p in r.problems if p.file == str(coords)}
    assert "has 4 columns" in odm_p[3].message and odm_p[3].severity == "error"
    assert odm_p[4].field == "Y" and "'abc' is not a number" in odm_p[4].message
    assert "lies outside IMG_0002.tif (64x48)" in odm_p[5].message
    assert "IMG_0404.tif is not in the image folder" in odm_p[6].message
    assert "two labels" in odm_p[7].message and "A (line 2)" in odm_p[7].message
    assert "measured twice in IMG_0001.tif" in odm_p[8].message
    assert "has coordinates" in odm_p[9].message
    assert "label C is not in the coordinate list gcps.csv" in odm_p[10].message
    assert "role 'chek'" in csv_p[4].message and "sigma_xy -1.0 is not > 0" in csv_p[5].message
    assert sorted(r.gcps.column("gcp_id").to_pylist()) == ["A", "B", "C"]
    assert r.gcp_observations.num_rows == 1, "only IMG_0003/C survives (A and B conflict at one pixel)"
    keep = ingest_folder(
        tmp_path / "f", gcp_file=[coords, odm], config=IngestConfig(gcp_label_conflict="keep")
    )
    assert keep.gcp_observations.num_rows == 3
    assert [p.severity for p in keep.problems if "two labels" in p.message] == ["warning"]


def test_gcp_unknown_crs_zero_heights_and_planimetric_option(tmp_path):
    make_flight(tmp_path / "f", "tiff")
    bad = tmp_path / "bad.txt"
    bad.write_text("WGS84 UTM 99N\n1 2 3 4 5 IMG_0001.tif\n")
    r = ingest_folder(tmp_path / "f", gcp_file=bad)
    assert [(p.line, p.field) for p in r.errors if p.file == str(bad)] == [(1, "crs")]
    zero = tmp_path / "zero.txt"
    zero.write_text(f"WGS84 UTM 32N\n{E0} {N0} 0.0 4 5 IMG_0001.tif\n{E0} {N0} 0.0 6 7 IMG_0002.tif\n")
    r = ingest_folder(tmp_path / "f", gcp_file=zero, config=IngestConfig(unknown_height_sigma_z_m=1000.0))
    z = [p for p in r.problems if p.field == "Z"]
    assert len(z) == 1 and z[0].line == 2 and "planimetric" in z[0].message
    assert r.gcps.column("sigma_z").to_pylist() == [1000.0]
    assert r.gcps.column("gcp_id").to_pylist() == ["unlabelled-1"] and r.gcp_observations.num_rows == 2


# ---------------------------------------------------------------------------- strips
def _lawnmower(rng, n_strips, per_strip, spacing, heading, noise):
    """Strips ``spacing`` apart along, 1.5 ``spacing`` across, joined by U-turns with two frames on each
    arc (at 60 and 120 deg of the semicircle); returns x, y, heading (deg), true strip per frame."""
    gap, r = 1.5 * spacing, 0.75 * spacing
    pts, head, truth = [], [], []
    across = np.array([1.0, 0.0])
    for s in range(n_strips):
        d = np.array([0.0, 1.0]) if s % 2 == 0 else np.array([0.0, -1.0])
        start = np.array([s * gap, 0.0 if s % 2 == 0 else (per_strip - 1) * spacing])
        for k in range(per_strip):
            pts.append(start + k * spacing * d)
            head.append(d)
            truth.append(s)
        if s < n_strips - 1:
            centre = pts[-1] + 0.5 * spacing * d + r * across
            for theta in np.radians([60.0, 120.0]):
                pts.append(centre - r * across * np.cos(theta) + r * d * np.sin(theta))
                head.append(d * np.cos(theta) + across * np.sin(theta))
                truth.append(-1)
    rot = np.radians(heading)
    R = np.array([[np.cos(rot), np.sin(rot)], [-np.sin(rot), np.cos(rot)]])  # clockwise by ``heading``
    p = (np.array(pts) + rng.normal(0, noise, (len(pts), 2))) @ R.T
    h = np.array(head) @ R.T
    yaw = np.degrees(np.arctan2(h[:, 0], h[:, 1])) % 360 + rng.normal(0, 3.0, len(h))
    return p[:, 0], p[:, 1], yaw, np.array(truth)


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5, 6])
def test_strips_of_a_noisy_lawnmower(seed):
    rng = np.random.default_rng(seed)
    n_strips, per = int(rng.integers(2, 7)), int(rng.integers(5, 15))
    spacing = float(rng.uniform(20, 80))
    x, y, yaw, truth = _lawnmower(rng, n_strips, per, spacing, float(rng.uniform(0, 360)), 0.05 * spacing)
    got = find_strips(x, y, yaw)
    assert np.array_equal(got, truth), f"seed={seed}: got {got.tolist()} expected {truth.tolist()}"


def test_strips_without_headings_split_at_a_side_step():
    """A multirotor stops, side-steps 1.5 spacings in three short moves, and flies back: no heading needed."""
    along = np.arange(8) * 30.0
    x = np.r_[np.zeros(8), [15.0, 30.0], np.full(8, 45.0)]
    y = np.r_[along, [along[-1]] * 2, along[::-1]]
    got = find_strips(x, y)
    assert got.tolist() == [0] * 8 + [-1, -1] + [1] * 8 or got.tolist() == [0] * 8 + [-1, -1, -1] + [1] * 7


def test_strip_config_is_checked():
    with pytest.raises(ValueError, match="course_tolerance_deg"):
        StripConfig(course_tolerance_deg=0)
    with pytest.raises(ValueError, match="spacing_ratio"):
        StripConfig(spacing_ratio=1.0)
    with pytest.raises(ValueError, match="gcp_label_conflict"):
        IngestConfig(gcp_label_conflict="ignore")


def test_files_written_by_the_simulator_writers_read_back(tmp_path):
    """The simulator's own TIFF/JPEG writers and ingest agree on every field of the contract."""
    from aerocal.simulate.image_files import FrameMetadata, write_rgb_jpeg, write_thermal_tiff

    when = dt.datetime(2024, 5, 1, 10, 0, 0, 123000, tzinfo=dt.timezone(dt.timedelta(hours=2)))
    meta = FrameMetadata("aerocal", "SimTherm", "SN9", when, 46.9, 9.1, 900.0, 0.5, -89.5, 12.0)
    thermal = (np.arange(H * W).reshape(H, W) * 9).astype(np.uint16)
    rgb = np.dstack([np.full((H, W), v, np.uint8) for v in (200, 100, 10)])
    write_thermal_tiff(tmp_path / "IMG_0001.tif", thermal, meta)
    write_rgb_jpeg(tmp_path / "IMG_0002.jpg", rgb, meta)
    r = ingest_folder(tmp_path)
    # read back without a problem; only "no camera.json / flight.json" would stop processing
    assert not [p for p in r.errors if not p.stops_processing], [str(p) for p in r.errors]
    rows = r.images.to_pylist()
    assert [row["bit_depth"] for row in rows] == [16, 8]
    for row in rows:
        assert row["camera_id"] == "aerocal|SimTherm|SN9|"
        assert row["time"].isoformat() == "2024-05-01T08:00:00.123000+00:00"
        assert (row["lat"], row["lon"], row["alt"]) == (46.9, 9.1, 900.0)
        assert (row["roll"], row["pitch"], row["yaw"], row["attitude_convention"]) == (
            0.5,
            -89.5,
            12.0,
            "dji_gimbal",
        )
    assert np.array_equal(read_raw(rows[0]["path"]), thermal)
    assert np.abs(read_raw(rows[1]["path"]).astype(int) - rgb).max() <= 3


def test_gcp_coordinates_that_disagree_between_csv_and_odm_list(tmp_path):
    make_flight(tmp_path / "f", "tiff")
    odm = tmp_path / "gcp_list.txt"
    odm.write_text(f"EPSG:32632\n{E0} {N0} 10.0 5.0 5.0 IMG_0001.tif A\n")
    coords = tmp_path / "gcps.csv"
    coords.write_text(f"# crs: EPSG:32632\nid,X,Y,Z\nA,{E0 + 1.0},{N0},10.0\n")
    r = ingest_folder(tmp_path / "f", gcp_file=[odm, coords])
    moved = [p for p in r.problems if p.file == str(odm) and p.line == 2]
    assert len(moved) == 1 and "lies 1.000 m from its coordinates in gcps.csv line 3" in moved[0].message
    assert r.gcps.column("X").to_pylist() == [E0 + 1.0], "the coordinate list wins"
    assert r.gcps.column("sigma_x").to_pylist() == [IngestConfig().gcp_sigma_xy_m]


def test_strips_survive_consumer_gnss_on_short_steps():
    """Three 12-frame lines (8 m steps, 30 m apart) flown back and forth with 1.5 m GNSS noise per axis (a
    DJI without RTK at 60 m): single-step courses swing by 15-30 deg and step lengths by 25 %. The course
    and spacing tolerances widen to the flight's own noise, so lines stay (nearly) whole and turns still
    split them."""
    from aerocal.ingest.strips import find_strips

    seed = 17
    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for k in range(3):
        x = np.arange(12) * 8.0
        xs.append(x if k % 2 == 0 else x[::-1])
        ys.append(np.full(12, 30.0 * k))
    x, y = np.concatenate(xs), np.concatenate(ys)
    strip = find_strips(x + rng.normal(0, 1.5, x.size), y + rng.normal(0, 1.5, y.size))
    found = [set(strip[12 * k : 12 * (k + 1)].tolist()) - {-1} for k in range(3)]
    # no strip spans a turn, at most one line is cut in two (a 1.7 m step among 8 m ones is a jump as much as
    # noise), and at most 3 frames are left out (the fixed 25 deg, 2.5x rule left 4 out in 5 pieces)
    assert all(not (a & b) for i, a in enumerate(found) for b in found[i + 1:]), f"seed {seed}: {strip}"
    assert sum(len(f) for f in found) <= 4 and (strip == -1).sum() <= 3, f"seed {seed}: {strip}"
    clean = find_strips(x, y)
    assert sorted(set(clean.tolist())) == [0, 1, 2], clean
