"""Ingest of the measured data sets (seneca, h20t_forest, copr): what a user checks after ingesting them."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from aerocal import tables
from aerocal.geometry import lonlat_to_projected
from aerocal.ingest import IngestConfig, ingest_folder, read_raw, summary_rows

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

SHARED_MISSING = f"measured data not found at {DATA} (a clone without ../shared/data)"
pytestmark = pytest.mark.skipif(not DATA.is_dir(), reason=SHARED_MISSING)  # only without ../shared/data


@pytest.fixture(scope="module")
def seneca():
    t0 = time.perf_counter()
    result = ingest_folder(DATA / "seneca")
    print(f"\nseneca: ingested {result.images.num_rows} images in {time.perf_counter() - t0:.2f} s")
    return result


@pytest.fixture(scope="module")
def h20t():
    return ingest_folder(DATA / "h20t_forest")


@pytest.fixture(scope="module")
def copr():
    return ingest_folder(DATA / "copr")


def _by_time(result):
    return result.images.sort_by("time")


def _strip_courses(images) -> dict[int, float]:
    x = np.array(images.column("gnss_x").to_pylist(), dtype=float)
    y = np.array(images.column("gnss_y").to_pylist(), dtype=float)
    s = np.array(images.column("strip").to_pylist())
    out = {}
    for k in sorted(set(s[s >= 0])):
        i = np.flatnonzero(s == k)
        out[int(k)] = float(np.degrees(np.arctan2(x[i[-1]] - x[i[0]], y[i[-1]] - y[i[0]])) % 360)
    return out


# ---------------------------------------------------------------------------- seneca
def test_seneca_every_image_has_position_attitude_and_temperature(seneca):
    img = tables.validate(seneca.images, "images")
    # the first frame is stored at 1620x1215, the others at 1800x1350: left out, with the reason
    assert img.num_rows == 166 and seneca.skipped_images == ["IMG_0446.jpg"]
    cols = ("lat", "lon", "alt", "gnss_x", "gnss_y", "gnss_z", "roll", "pitch", "yaw", "temperature_c")
    for col in (*cols, "time"):
        assert img.column(col).null_count == 0, f"{col} has nulls"
    assert set(img.column("attitude_convention").to_pylist()) == {"body_rpy"}
    assert set(img.column("camera_id").to_pylist()) == {"Canon|Canon PowerShot ELPH 300 HS||"}
    assert seneca.crs == "EPSG:32617" and tables.crs_of(img) == "EPSG:32617"
    # the folder as published has no camera.json and no flight.json, and the camera is not in the catalogue:
    # the nominal camera comes from EXIF FocalLength and FocalPlaneXResolution, the flying height from the
    # senseFly XMP Height; nothing stops processing
    assert not seneca.errors, [str(p) for p in seneca.errors]
    left_out = [p for p in seneca.problems if p.file.endswith("IMG_0446.jpg")]
    assert len(left_out) == 1 and "left out: its frame is 1620x1215" in left_out[0].message, left_out
    assert "FocalPlaneXResolution" in seneca.camera_source and seneca.camera.width == 1800
    assert 60 < seneca.height_agl_m < 80 and "senseFly XMP Height" in seneca.flight_facts["height_agl_m"]
    # projected positions are the WGS84 positions in UTM 17N
    lat, lon = img.column("lat").to_pylist()[0], img.column("lon").to_pylist()[0]
    x, y = lonlat_to_projected(lon, lat, "EPSG:32617")
    assert abs(img.column("gnss_x")[0].as_py() - x) < 1e-6
    assert abs(img.column("gnss_y")[0].as_py() - y) < 1e-6
    # alt is the ellipsoidal AltitudeWGS84; the geoid lies ~33 m below the ellipsoid in Ohio, AMSL is higher
    alt = np.array(img.column("alt").to_pylist())
    amsl = np.array(seneca.extra.column("sensefly_altitude_amsl_m").to_pylist())
    assert set(seneca.extra.column("alt_reference").to_pylist()) == {"ellipsoidal (AltitudeWGS84)"}
    assert np.all((alt > 265) & (alt < 305)) and 30 < np.median(amsl - alt) < 40


def test_seneca_camera_temperature_falls_from_37_to_23(seneca):
    temps = np.array(_by_time(seneca).column("temperature_c").to_pylist())
    assert temps[0] == 37.0 and temps[-1] == 23.0
    assert np.all(np.diff(temps) <= 0.0), "the camera cools monotonically in this flight"
    t = [v.timestamp() for v in _by_time(seneca).column("time").to_pylist()]
    first = int(np.argmax(temps == 23.0))
    reached = (t[first] - t[0]) / 60
    # the data set's description says "over the first ~7 minutes"; the first frame at 23 degC is at 9.3 min
    assert 6 < reached < 10, f"23 degC first reached after {reached:.1f} min"
    assert np.all(temps[first:] == 23.0) and (t[-1] - t[first]) / 60 > 8, "then it stays at 23 degC"


def test_seneca_times_are_utc_from_the_gnss_zone(seneca):
    times = _by_time(seneca).column("time").to_pylist()
    # camera clock 13:37:29 local, GNSS UTC 17:38:03: zone UTC-4 (EDT), clock 34 s behind; the first frame
    # (13:37:29) is left out for its size, the second is 6 s later
    assert times[0].isoformat() == "2013-06-04T17:37:35+00:00"
    assert 18.5 < (times[-1] - times[0]).total_seconds() / 60 < 20
    zone = [p for p in seneca.problems if p.field == "time"]
    assert len(zone) == 1 and "UTC-04:00" in zone[0].message and "-34 s" in zone[0].message


def test_seneca_strips_follow_the_lawnmower_pattern(seneca):
    """Read from the positions: 12 lines flown north-east (course ~57 deg, ~30 m spacing, into wind),
    8 return lines flown south-west (course ~236 deg, fast, 3-7 frames) and 3 cross strips."""
    img = _by_time(seneca)
    courses = _strip_courses(img)
    ne = [c for c in courses.values() if abs(c - 57) < 20]
    sw = [c for c in courses.values() if abs(c - 236) < 20]
    assert len(courses) == 23, courses
    assert (len(ne), len(sw), len(courses) - len(ne) - len(sw)) == (12, 8, 3)
    strips = np.array(img.column("strip").to_pylist())
    assert (strips == -1).sum() <= 5
    x = np.array(img.column("gnss_x").to_pylist())
    y = np.array(img.column("gnss_y").to_pylist())
    for k in courses:
        p = np.c_[x[strips == k], y[strips == k]]
        c = p - p.mean(axis=0)
        across = np.linalg.svd(c, full_matrices=False)[2][1]
        assert np.abs(c @ across).max() < 10.0, f"strip {k} is not straight"
        assert np.all(np.diff(np.flatnonzero(strips == k)) == 1), f"strip {k} is not consecutive in time"


def test_seneca_summary_rows(seneca):
    rows = dict(summary_rows(seneca))
    assert rows["images"] == "166 ingested, 1 skipped"
    assert rows["strips"].startswith("23 ")
    assert "23.0 .. 37.0 degC" in rows["camera temperature"]
    assert rows["problems"] == "0 error(s), 2 warning(s)"


def test_metadata_parser_agrees_with_pillow():
    """Ingest's reading of the EXIF values (text clean-up, degrees from DMS, hemispheres, altitude reference)
    gives what Pillow's own ``Image.open(...).getexif()`` gives, on all three cameras."""
    from PIL import Image

    from aerocal.ingest.metadata import read_image_metadata

    files = [
        DATA / "seneca" / "images" / "IMG_0446.jpg",
        DATA / "seneca" / "images" / "IMG_0612.jpg",
        DATA / "copr" / "images" / "IMG_0031.jpg",
        DATA / "h20t_forest" / "images" / "DJI_20220602143649_0240_T.JPG",
        DATA / "flir_samples" / "fff_dji_xtr.jpg",  # southern and western hemispheres
        DATA / "flir_samples" / "fff_dji_xt2.jpg",
    ]
    for path in files:
        meta, problems = read_image_metadata(path)
        assert meta is not None and not problems, problems
        with Image.open(path) as im:
            ex = im.getexif()
            exif, gps = ex.get_ifd(0x8769), ex.get_ifd(0x8825)
        assert (meta.make, meta.model) == (ex[271].strip(), ex[272].strip())
        assert meta.local_time.strftime("%Y:%m:%d %H:%M:%S") == exif[0x9003]
        if exif.get(0xA431):
            assert meta.serial == exif[0xA431]
        if gps.get(2):
            lat = sum(float(v) / 60**i for i, v in enumerate(gps[2]))
            lon = sum(float(v) / 60**i for i, v in enumerate(gps[4]))
            lat, lon = (-lat if gps[1] == "S" else lat), (-lon if gps[3] == "W" else lon)
            assert abs(meta.pose.lat - lat) < 1e-6 and abs(meta.pose.lon - lon) < 1e-6
            if meta.pose.alt_reference == "sea level (EXIF GPSAltitude)":  # DJI XMP AbsoluteAltitude wins
                assert abs(meta.pose.alt - float(gps[6])) < 1e-3


# ---------------------------------------------------------------------------- h20t_forest
def test_h20t_raw_thermal_frames(h20t):
    img = tables.validate(h20t.images, "images")
    assert img.num_rows == 42
    assert set(img.column("bit_depth").to_pylist()) == {16}
    sizes = zip(img.column("width").to_pylist(), img.column("height").to_pylist(), strict=True)
    assert set(sizes) == {(640, 512)}
    for k in (0, 20, 41):
        raw = read_raw(img.column("path")[k].as_py())
        assert raw.dtype == np.uint16 and raw.shape == (512, 640)
        assert raw.max() > 255 and raw.std() > 100, f"looks like an 8-bit preview: std {raw.std():.1f}"
        assert len(np.unique(raw)) > 1000
    # the visible JPEG is a false-colour preview of the same size: raw values are not its bytes
    assert read_raw(img.column("path")[0].as_py()).mean() > 5000


def test_h20t_dji_xmp_fields(h20t):
    img = h20t.images
    pitch = np.array(img.column("pitch").to_pylist())
    assert np.all(np.abs(pitch + 90.0) < 0.5), "gimbal pitch must be nadir (-90)"
    assert set(img.column("attitude_convention").to_pylist()) == {"dji_gimbal"}
    rel = np.array(h20t.extra.column("dji_relative_altitude_m").to_pylist())
    assert np.all(np.abs(rel - 95.0) < 1.0)
    lrf = np.array(h20t.extra.column("dji_lrf_target_distance_m").to_pylist(), dtype=float)
    assert np.nanmin(lrf) > 10 and np.nanmax(lrf) < 150
    assert "dji_flight_x_speed_mps" in h20t.extra.column_names
    # local 14:35:46 with +02:00 in XMP CreateDate
    assert h20t.images.column("time")[0].as_py().isoformat() == "2022-06-02T12:35:46+00:00"


def test_h20t_app4_floats_reported_as_undocumented(h20t):
    extra = h20t.extra
    for off in (132, 136, 156):
        values = np.array(extra.column(f"dji_app4_f{off}_undocumented").to_pylist())
        assert np.all((values > 20) & (values < 35)), (off, values.min(), values.max())
        assert values[0] > values[-1], "they drift down over the flight"
    assert h20t.images.column("temperature_c").null_count == 42, "not the sensor temperature by default"
    notes = [p for p in h20t.problems if p.field == "APP4"]
    assert len(notes) == 1 and "UNDOCUMENTED" in notes[0].message
    opted = ingest_folder(DATA / "h20t_forest", config=IngestConfig(dji_app4_temperature=132))
    used = opted.images.column("temperature_c").to_pylist()
    assert np.allclose(used, extra.column("dji_app4_f132_undocumented").to_pylist())


def test_h20t_two_opposite_strips(h20t):
    courses = _strip_courses(_by_time(h20t))
    assert len(courses) == 2
    a, b = courses.values()
    assert abs(((a - b) % 360) - 180) < 15, courses
    strips = np.array(_by_time(h20t).column("strip").to_pylist())
    assert (strips == 0).sum() >= 15 and (strips == 1).sum() >= 15 and 3 <= (strips == -1).sum() <= 8


# ---------------------------------------------------------------------------- copr
def test_copr_ground_control_defects_are_reported(copr):
    gcp_list = str(DATA / "copr" / "gcp_list.txt")
    conflict = [p for p in copr.problems if p.field == "label" and "two labels" in p.message]
    assert len(conflict) == 1
    p = conflict[0]
    assert p.file == gcp_list and p.line == 25 and p.severity == "error"
    for word in ("IMG_0031.jpg", "gcp00", "gcp04", "line 6"):
        assert word in p.message
    zero = [p for p in copr.problems if p.field == "Z"]
    assert len(zero) == 1 and zero[0].file == gcp_list and zero[0].line == 2
    assert "unknown, not sea level" in zero[0].message
    gcps = tables.validate(copr.gcps, "gcps")
    assert gcps.num_rows == 10 and set(gcps.column("role").to_pylist()) == {"control"}
    obs = tables.validate(copr.gcp_observations, "gcp_observations")
    assert obs.num_rows == 27 - 2, "both conflicting measurements dropped"
    # ODM pixel (1804.686, 1146.898) of gcp02 in IMG_0037 -> aerocal corner convention (+0.5)
    names = dict(
        zip(copr.images.column("image_id").to_pylist(), copr.images.column("name").to_pylist(), strict=True)
    )
    rows = [r for r in obs.to_pylist() if r["gcp_id"] == "gcp02" and names[r["image_id"]] == "IMG_0037.jpg"]
    assert len(rows) == 1 and abs(rows[0]["x"] - 1805.1864) < 1e-3 and abs(rows[0]["y"] - 1147.3976) < 1e-3
    g02 = [r for r in gcps.to_pylist() if r["gcp_id"] == "gcp02"][0]
    assert (g02["X"], g02["Y"], g02["Z"]) == (235269.88, 3811198.11, 0.0)
    assert copr.crs == "EPSG:32611"


def test_copr_images_ingest_without_gnss_reported_once(copr):
    img = copr.images
    assert img.num_rows == 22 and not copr.skipped_images
    assert img.column("lat").null_count == 22 and img.column("gnss_x").null_count == 22
    assert img.column("strip").null_count == 22
    gnss = [p for p in copr.problems if p.field == "gnss"]
    assert len(gnss) == 1 and gnss[0].severity == "warning" and "22 images" in gnss[0].message
    assert not [p for p in copr.errors if p.file.endswith(".jpg")]
    temps = np.array(img.column("temperature_c").to_pylist())
    assert np.all((temps >= 20) & (temps <= 30)), "EOS ShotInfo temperature (value - 128)"
    assert set(img.column("camera_id").to_pylist()) == {
        "Canon|Canon EOS DIGITAL REBEL XSi|1670520998|EF28-80mm f/3.5-5.6 USM"
    }
    # as shared (images and gcp_list.txt, nothing hand-written), nothing stops `aerocal process`: the nominal camera
    # from EXIF FocalLength over FocalPlaneXResolution's pitch, within 1 % of 30 mm on a 22.2 mm wide APS-C sensor
    assert not copr.blocking, [str(p) for p in copr.blocking]
    assert copr.camera.f == pytest.approx(30.0 / (22.2 / 2136), rel=0.01), copr.camera_source


def test_copr_other_ground_control_files(copr):
    d = DATA / "copr"
    noimg = ingest_folder(d, gcp_file=d / "gcp_list_noimg.txt")
    lines = sorted(p.line for p in noimg.errors if p.field == "columns")
    assert lines == list(range(2, 12)) and noimg.gcps.num_rows == 0
    nocoord = ingest_folder(d, gcp_file=d / "gcp_list_nocoord.txt")
    first = [p for p in nocoord.errors if p.field == "crs"]
    assert len(first) == 1 and first[0].line == 1 and "found a data line" in first[0].message
    avg = ingest_folder(d, gcp_file=d / "GPS_average.txt")
    assert avg.gcps.num_rows == 10 and avg.crs == "EPSG:32611"
    # cop-target1 of GPS_average.txt is gcp00 of gcp_list.txt (the files number the targets differently)
    t1 = [r for r in avg.gcps.to_pylist() if r["gcp_id"] == "cop-target1"][0]
    assert abs(t1["X"] - 235277.61) < 0.01 and abs(t1["Y"] - 3811190.36) < 0.01
    fullres = ingest_folder(d, gcp_file=d / "gcp_list_fullres_original.txt")
    outside = [p for p in fullres.errors if p.field == "px/py"]
    assert len(outside) >= 10 and all("lies outside" in p.message for p in outside)


def test_read_raw_jpeg_is_rgb_of_the_stored_grid(seneca, copr):
    from PIL import Image

    for result in (seneca, copr):
        row = result.images.slice(1, 1).to_pylist()[0]
        rgb = read_raw(row["path"])
        assert rgb.dtype == np.uint8 and rgb.shape == (row["height"], row["width"], 3)
        with Image.open(row["path"]) as im:
            ref = np.asarray(im.convert("RGB"), dtype=float)
        assert np.abs(rgb - ref).mean() < 2.0, "channels in RGB order, no EXIF rotation"
