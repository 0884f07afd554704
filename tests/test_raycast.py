"""The renderer: ray-DSM hits on the surface, target geometry to a tenth of a pixel, radiometry, files."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import cv2
import defusedxml.ElementTree as ET
import numpy as np
import pytest
import tifffile
from PIL import Image

from aerocal.camera import Camera
from aerocal.geometry import dji_gimbal_to_R_cw, nadir_R_cw, small_rotation, world_to_camera
from aerocal.ingest.metadata_writer import DJI_NAMESPACE
from aerocal.simulate.image_files import FrameMetadata, write_rgb_jpeg, write_thermal_tiff
from aerocal.simulate.raycast import (
    RenderConfig,
    intersect_dsm,
    render_frame,
    render_radiance,
    vignetting_factor,
)
from aerocal.simulate.scene import SKY_KELVIN, SceneConfig, make_scene
from aerocal.targets import locate_targets

SEED = 7301
ALTITUDE = 600.0  # metres above the mean terrain
TARGET_RADIUS_PX = 2.5


@dataclass(frozen=True)
class PinholeExposure:
    """Stand-in for the simulator's exposure: a global-shutter frame camera with Brown distortion."""

    camera: Camera
    R_cw: np.ndarray
    C: np.ndarray

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.concatenate([self.camera.unproject(np.asarray(uv, float)), np.ones((len(uv), 1))], axis=1)
        d = d @ self.R_cw
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.broadcast_to(self.C, d.shape).copy(), d

    def project(self, X: np.ndarray) -> np.ndarray:
        return self.camera.project(world_to_camera(self.R_cw, self.C, X))


CAMERA = Camera(width=480, height=360, f=1200.0, cx=243.0, cy=177.0, k1=-0.1, p1=1e-3)
POSE = small_rotation(np.radians([4.0, -3.0, 0.0])) @ nadir_R_cw(30.0)  # 30 deg heading, ~5 deg tilt


def exposure_over(scene, R_cw=POSE, camera=CAMERA, height=ALTITUDE):
    e0, n0, e1, n1 = scene.bounds()
    return PinholeExposure(camera, R_cw, np.array([(e0 + e1) / 2, (n0 + n1) / 2, 50.0 + height]))


@pytest.fixture(scope="module")
def city():
    cfg = SceneConfig(width_m=420.0, height_m=360.0, building_density=0.3, vegetation_density=0.1)
    return make_scene(cfg, seed=SEED)


@pytest.fixture(scope="module")
def flat():
    return make_scene(SceneConfig(width_m=420.0, height_m=360.0, flat=True), seed=SEED)


# ------------------------------------------------------------------------------------------ intersection
def _ray_samples(scene, rng, n):
    """Rays of the camera at random pixels (the central 80 %) plus oblique rays (20-50 deg off nadir) from random places
    10 m above the highest roof (all of them reach the ground inside the scene)."""
    exp = exposure_over(scene)
    uv = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (n, 2)) * 0.8 + 0.1 * np.array([480, 360])
    o1, d1 = exp.rays(uv)
    e0, n0, e1, n1 = scene.bounds()
    z = scene.height_range[1] + 10.0
    o2 = np.column_stack([rng.uniform(e0 + 120, e1 - 120, n), rng.uniform(n0 + 120, n1 - 120, n), np.full(n, z)])
    off, az = np.radians(rng.uniform(20, 50, n)), rng.uniform(0, 2 * np.pi, n)
    d2 = np.column_stack([np.sin(off) * np.sin(az), np.sin(off) * np.cos(az), -np.cos(off)])
    return np.vstack([o1, o2]), np.vstack([d1, d2])


def test_hits_lie_on_the_surface_and_on_the_rays(city):
    rng = np.random.default_rng(SEED)
    o, d = _ray_samples(city, rng, 20000)
    hits = intersect_dsm(city, o, d)
    assert hits.hit.all(), f"seed {SEED}: {np.count_nonzero(~hits.hit)} downward rays found no surface"
    p = hits.points
    dz = np.abs(p[:, 2] - city.height_at(p[:, 0], p[:, 1]))
    print(f"hit height error: max {dz.max():.2e} m, median {np.median(dz):.2e} m")
    assert dz.max() < 0.01, f"seed {SEED}: hit height error {dz.max() * 100:.2f} cm (tolerance 1 cm)"
    off_ray = np.linalg.norm(np.cross(p - o, d), axis=1)
    assert off_ray.max() < 1e-6, f"seed {SEED}: hit {off_ray.max():.2e} m off its ray"
    # first crossing: points before the hit (every 10 cm) are above the surface
    s = np.arange(1, 200) * 0.1
    t_before = hits.t[:, None] - s[None, :]
    q = o[:, None, :] + t_before[..., None] * d[:, None, :]
    clear = q[..., 2] - city.height_at(q[..., 0], q[..., 1])
    bad = np.any((clear < -0.01) & (t_before > 0), axis=1)
    assert bad.mean() < 1e-3, f"seed {SEED}: {bad.mean():.2%} of rays passed through the surface earlier"


def test_hit_on_flat_ground_is_exact(flat):
    o = np.array([[500200.0, 4_900_180.0, 150.0]] * 3)
    d = np.array([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8], [0.0, -0.28, -0.96]])
    hits = intersect_dsm(flat, o, d)
    np.testing.assert_allclose(hits.t, 100.0 / -d[:, 2], atol=1e-6)
    np.testing.assert_allclose(hits.points[:, 2], 50.0, atol=1e-3)


def test_rays_from_below_the_surface_and_upwards(city):
    e0, n0, e1, n1 = city.bounds()
    zmax = city.height_range[1]
    o = np.array([[e0 + 100, n0 + 100, 0.0], [e0 + 100, n0 + 100, zmax + 50.0]])
    d = np.array([[0.0, 0.0, -1.0], [0.0, 0.6, 0.8]])
    hits = intersect_dsm(city, o, d)
    assert hits.hit.tolist() == [True, False]
    assert hits.t[0] == 0.0 and np.isinf(hits.t[1])


# ------------------------------------------------------------------------------------------ target geometry
def _targets_in_view(scene, exp, positions):
    X = np.column_stack([positions, scene.height_at(positions[:, 0], positions[:, 1])])
    uv = exp.project(X)
    keep = np.isfinite(uv).all(axis=1) & CAMERA.in_image(uv, margin=15)
    return positions[keep]


def _located_errors(scene, exp, config, rng, window_px=11):
    img = render_frame(scene, exp, config, rng)
    truth = exp.project(scene.target_points())
    start = truth + rng.uniform(-1.0, 1.0, truth.shape)  # a user's click, about a pixel off
    found = locate_targets(img, start, window_px=window_px)
    return img, found - truth


def test_targets_on_flat_ground_sit_on_their_projection(flat):
    exp = exposure_over(flat)
    grid = np.stack(np.meshgrid(np.linspace(30, 450, 7), np.linspace(30, 330, 5)), -1).reshape(-1, 2)
    grid = grid + np.random.default_rng(SEED).uniform(-0.5, 0.5, grid.shape)  # arbitrary sub-pixel phases
    o, d = exp.rays(grid)
    pos = intersect_dsm(flat, o, d).points[:, :2]
    r_m = TARGET_RADIUS_PX * ALTITUDE / CAMERA.f
    scene = flat.place_targets(pos, r_m)
    img, err = _located_errors(scene, exp, RenderConfig(supersample=3), np.random.default_rng(SEED))
    assert img.dtype == np.uint16 and img.shape == (360, 480)
    assert np.isfinite(err).all(), f"seed {SEED}: targets not found: {np.nonzero(~np.isfinite(err))[0]}"
    worst = np.abs(err).max()
    print(f"flat: {len(err)} targets, max error {worst:.4f} px, rms {np.sqrt((err**2).mean()):.4f} px")
    assert worst < 0.1, f"seed {SEED}: target centroid {worst:.3f} px from its projection"


def test_targets_between_buildings_sit_on_their_projection(city):
    exp = exposure_over(city)
    rng = np.random.default_rng(SEED)
    pos = _targets_in_view(city, exp, city.open_ground_positions(25, rng, clearance_m=10.0, min_spacing_m=15.0))
    assert len(pos) >= 8, f"seed {SEED}: only {len(pos)} open-ground targets in view"
    r_m = TARGET_RADIUS_PX * ALTITUDE / CAMERA.f
    scene = city.place_targets(pos, r_m)
    img, err = _located_errors(scene, exp, RenderConfig(supersample=3), rng)
    assert np.isfinite(err).all(), f"seed {SEED}: targets not found: {np.nonzero(~np.isfinite(err))[0]}"
    worst = np.abs(err).max()
    print(f"city: {len(err)} targets, max error {worst:.4f} px, rms {np.sqrt((err**2).mean()):.4f} px")
    assert worst < 0.1, f"seed {SEED}: target centroid {worst:.3f} px from its projection"
    # thermal radiometry of a city: uint16 DN = 100 T, a realistic spread of temperatures
    t = img.astype(float) / 100.0
    lo, hi = np.percentile(t, [1, 99])
    assert 270.0 < lo and hi < 320.0, f"seed {SEED}: temperatures {lo:.1f}-{hi:.1f} K"
    assert t.std() > 1.5, f"seed {SEED}: temperature spread only {t.std():.2f} K"


def test_rgb_frame_and_target(flat):
    exp = exposure_over(flat)
    o, d = exp.rays(np.array([[200.3, 150.6], [330.8, 90.1]]))
    scene = flat.place_targets(intersect_dsm(flat, o, d).points[:, :2], TARGET_RADIUS_PX * ALTITUDE / CAMERA.f)
    img, err = _located_errors(scene, exp, RenderConfig(modality="rgb"), np.random.default_rng(SEED))
    assert img.dtype == np.uint8 and img.shape == (360, 480, 3)
    assert np.abs(err).max() < 0.1, f"seed {SEED}: RGB target error {np.abs(err).max():.3f} px"


def test_accelerated_rendering_matches_ray_per_sample(city):
    """Sub-pixel rays and hits derived from pixel-centre rays give the image of tracing every ray."""
    cam = Camera(width=160, height=120, f=400.0, cx=81.0, cy=59.0, k1=-0.1, p1=1e-3)
    exp = exposure_over(city, camera=cam, height=200.0)  # GSD 0.5 m over roofs, streets and trees
    fast = render_radiance(city, exp, RenderConfig(accelerate=True))
    exact = render_radiance(city, exp, RenderConfig(accelerate=False))
    diff = np.abs(fast - exact)
    print(f"accelerated vs exact: max {diff.max():.2e} K, 99.9 % within {np.percentile(diff, 99.9):.2e} K")
    assert np.percentile(diff, 99.9) < 1e-3, f"seed {SEED}: accelerated image differs by {diff.max():.3f} K"
    assert diff.max() < 0.1, f"seed {SEED}: accelerated image differs by {diff.max():.3f} K"


def test_locate_targets_near_the_border_gives_nan():
    img = np.zeros((50, 60), np.uint16)
    img[20:23, 30:33] = 1000
    found = locate_targets(img, np.array([[31.5, 21.5], [2.0, 2.0], [np.nan, 5.0]]), window_px=9)
    np.testing.assert_allclose(found[0], [31.5, 21.5])
    assert np.isnan(found[1:]).all()


def test_vignetting_falls_off_to_the_corner():
    v = vignetting_factor(Camera(width=100, height=80, f=100.0, cx=50.0, cy=40.0), 0.2)
    assert v[40, 50] == pytest.approx(1.0, abs=1e-3) and v[0, 0] == pytest.approx(0.8, abs=0.01)


# ------------------------------------------------------------------------------------------ radiometry
def test_netd_noise_level(flat):
    exp = exposure_over(flat)
    scene = flat.place_targets(intersect_dsm(flat, *exp.rays(np.array([[240.0, 180.0]]))).points[:, :2], 8.0)
    quiet = render_frame(scene, exp, RenderConfig(netd_k=0.0), np.random.default_rng(SEED))
    noisy = render_frame(scene, exp, RenderConfig(netd_k=0.06), np.random.default_rng(SEED))
    diff = noisy.astype(float) - quiet.astype(float)
    assert diff.std() == pytest.approx(6.0, rel=0.05), f"seed {SEED}: noise {diff.std():.2f} DN, expected 6"
    # inside the uniform cold square of the big target (16 m disc, square half-side 24 m at 0.5 m GSD)
    uv = exp.project(scene.target_points())[0]
    r0, c0 = int(uv[1]), int(uv[0])
    ring = noisy[r0 - 30:r0 + 30, c0 - 30:c0 + 30].astype(float)
    yy, xx = np.mgrid[-30:30, -30:30]
    rho = np.hypot(yy, xx)
    band = ring[(rho > 20) & (rho < 28)]
    assert band.mean() == pytest.approx(100 * 275.0, abs=3.0)
    assert band.std() == pytest.approx(6.0, rel=0.15), f"seed {SEED}: flat-region std {band.std():.2f} DN"
    assert quiet[(r0 - 30):(r0 + 30), (c0 - 30):(c0 + 30)][(rho > 20) & (rho < 28)].std() < 0.6


def test_sky_above_the_horizon_and_beyond_the_scene(city):
    """A camera 60 m up at the southern edge looking north, 8 deg below the horizon: the upper rows look
    past the scene (sky), the lower rows see the ground."""
    e0, n0, e1, _ = city.bounds()
    exp = PinholeExposure(CAMERA, dji_gimbal_to_R_cw(0.0, -8.0, 0.0), np.array([(e0 + e1) / 2, n0 + 20, 110.0]))
    img = render_frame(city, exp, RenderConfig(supersample=1, netd_k=0.0, blur_sigma_px=0.0),
                       np.random.default_rng(SEED))
    assert np.all(img[:50] == round(100 * SKY_KELVIN))
    assert np.all(img[-50:] > 27000)


# ------------------------------------------------------------------------------------------ files
META = FrameMetadata(
    make="DJI", model="ZH20T", serial="1ZNBJ7R00C00TT", time=dt.datetime(2024, 6, 11, 10, 20, 30, 456000),
    gps_latitude=44.123456789, gps_longitude=-7.987654321, absolute_altitude=712.345,
    gimbal_roll_deg=0.1, gimbal_pitch_deg=-89.9, gimbal_yaw_deg=123.4,
)


def _parse_xmp(packet: bytes) -> dict[str, str]:
    root = ET.fromstring(packet)
    desc = root.find(".//{http://www.w3.org/1999/02/22-rdf-syntax-ns#}Description")
    ns = "{" + DJI_NAMESPACE + "}"
    return {k[len(ns):]: v for k, v in desc.attrib.items() if k.startswith(ns)}


def _check_xmp(fields: dict[str, str]) -> None:
    assert float(fields["GpsLatitude"]) == pytest.approx(META.gps_latitude, abs=1e-9)
    assert float(fields["GpsLongitude"]) == pytest.approx(META.gps_longitude, abs=1e-9)
    assert float(fields["AbsoluteAltitude"]) == pytest.approx(META.absolute_altitude, abs=1e-3)
    assert float(fields["GimbalRollDegree"]) == pytest.approx(0.1)
    assert float(fields["GimbalPitchDegree"]) == pytest.approx(-89.9)
    assert float(fields["GimbalYawDegree"]) == pytest.approx(123.4)


def test_thermal_tiff_reads_back_with_metadata(tmp_path):
    img = np.random.default_rng(SEED).integers(27000, 31000, (120, 160)).astype(np.uint16)
    path = write_thermal_tiff(tmp_path / "frame_0001.tif", img, META)
    assert [p.name for p in tmp_path.iterdir()] == ["frame_0001.tif"]  # no temporary file left
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16 and np.array_equal(back, img)
    with tifffile.TiffFile(path) as tif:
        tags = tif.pages[0].tags
        assert tags[271].value == "DJI" and tags[272].value == "ZH20T"
        assert tags[306].value == "2024:06:11 10:20:30"
        exif = tags[34665].value
        assert exif["DateTimeOriginal"] == "2024:06:11 10:20:30"
        assert exif["BodySerialNumber"] == "1ZNBJ7R00C00TT"
        _check_xmp(_parse_xmp(tags[700].value))


def test_rgb_jpeg_reads_back_with_metadata(tmp_path):
    img = np.random.default_rng(SEED).integers(0, 255, (120, 160, 3)).astype(np.uint8)
    path = write_rgb_jpeg(tmp_path / "frame_0001.jpg", img, META)
    back = cv2.imread(str(path))
    assert back.dtype == np.uint8 and back.shape == (120, 160, 3)
    with Image.open(path) as im:
        exif = im.getexif()
        assert exif[271] == "DJI" and exif[272] == "ZH20T"
        sub = exif.get_ifd(0x8769)
        assert sub[0x9003] == "2024:06:11 10:20:30" and sub[0xA431] == "1ZNBJ7R00C00TT"
    # the XMP packet as an APP1 segment, found by walking the JPEG markers
    data = path.read_bytes()
    pos, xmp = 2, None
    while pos < len(data) and data[pos] == 0xFF and data[pos + 1] not in (0xDA, 0xD9):
        size = int.from_bytes(data[pos + 2:pos + 4], "big")
        body = data[pos + 4:pos + 2 + size]
        if data[pos + 1] == 0xE1 and body.startswith(b"http://ns.adobe.com/xap/1.0/\x00"):
            xmp = body[29:]
        pos += 2 + size
    assert xmp is not None, f"{path}: no XMP APP1 segment"
    _check_xmp(_parse_xmp(xmp))


def test_bad_frame_names_the_file(tmp_path):
    with pytest.raises(ValueError, match="frame_0002.tif"):
        write_thermal_tiff(tmp_path / "frame_0002.tif", np.zeros((4, 4), np.float32), META)
    assert not any(tmp_path.iterdir())


def _upsample_numpy(grid: np.ndarray, ss: int) -> np.ndarray:
    """Bilinear interpolation of pixel-centre values with a one-pixel border at the ``ss x ss`` sub-pixel
    centres, as numpy did it before it was compiled: along the columns, then along the rows."""
    h, w = grid.shape[0] - 2, grid.shape[1] - 2
    cols = np.empty((grid.shape[0], w * ss) + grid.shape[2:], dtype=grid.dtype)
    for k in range(ss):
        x = (k + 0.5) / ss + 0.5
        x0 = int(np.floor(x))
        cols[:, k::ss] = grid[:, x0:x0 + w] * (1.0 - (x - x0)) + grid[:, x0 + 1:x0 + 1 + w] * (x - x0)
    out = np.empty((h * ss,) + cols.shape[1:], dtype=grid.dtype)
    for k in range(ss):
        y = (k + 0.5) / ss + 0.5
        y0 = int(np.floor(y))
        out[k::ss] = cols[y0:y0 + h] * (1.0 - (y - y0)) + cols[y0 + 1:y0 + 1 + h] * (y - y0)
    return out


@pytest.mark.parametrize("ss", [1, 2, 3, 4])
def test_compiled_sub_pixel_rays_are_the_bilinear_interpolation_to_the_bit(ss):
    from aerocal.simulate.raycast_kernels import subpixel_rays

    rng = np.random.default_rng(SEED + ss)
    oa = rng.normal(0.0, 100.0, (7, 9, 3))
    da = rng.normal(0.0, 1.0, (7, 9, 3))
    da /= np.linalg.norm(da, axis=2, keepdims=True)
    o, d = subpixel_rays(oa, da, ss)
    expected_o = _upsample_numpy(oa, ss).reshape(-1, 3)
    expected_d = _upsample_numpy(da, ss).reshape(-1, 3)
    expected_d /= np.linalg.norm(expected_d, axis=1, keepdims=True)
    assert o.shape == (5 * ss * 7 * ss, 3)
    assert np.array_equal(o, expected_o) and np.array_equal(d, expected_d), f"seed {SEED + ss}"
