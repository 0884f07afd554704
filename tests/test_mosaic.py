"""Orthomosaic of a rendered simulated flight: a GeoTIFF a GIS opens, targets where they were surveyed."""

import cv2
import numpy as np
import pytest
import rasterio
from rasterio.enums import Resampling

from aerocal.assess import mosaic_target_residuals
from aerocal.camera import Camera, LinearThermalModel
from aerocal.ingest.pixels import read_raw
from aerocal.products.dsm import Dsm, dsm_from_points
from aerocal.products.mosaic import TILES_PER_TASK, MosaicConfig, build_mosaic, frames_from_poses

SEED = 3


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """An effect-free conte-calibration sub-block of 12 frames, rendered once; the true poses and camera
    stand for the adjusted block, the DSM is gridded from the true tie points."""
    from aerocal.simulate import simulate_flight
    from aerocal.simulate.raycast import RenderConfig
    from aerocal.simulate.rendered_frames import render_flight_images
    from aerocal.simulate.simulator import true_poses

    sim = simulate_flight("conte-calibration", seed=SEED, max_images=12)
    out = tmp_path_factory.mktemp("frames")
    render_flight_images(sim, out, config=RenderConfig(modality="thermal", supersample=2))
    names = dict(zip(sim.images.column("image_id").to_pylist(), sim.images.column("name").to_pylist(),
                     strict=True))
    images = {i: out / n for i, n in names.items()}
    frames = frames_from_poses(true_poses(sim), {e.image_id: e.camera for e in sim.exposures})
    gsd = sim.trajectory.gsd_m
    dsm = dsm_from_points(sim.tie.points, sim.crs, gsd_m=gsd)
    work = tmp_path_factory.mktemp("mosaic")
    calls = []
    result = build_mosaic(frames, images, dsm, work / "ortho.tif", MosaicConfig(gsd_m=gsd),
                          progress=lambda done, total: calls.append((done, total)))
    return {"sim": sim, "images": images, "frames": frames, "dsm": dsm, "gsd": gsd, "work": work,
            "serial": result, "calls": calls}


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def test_mosaic_opens_with_the_flight_crs_grid_and_radiometry(flight):
    res, sim, gsd = flight["serial"], flight["sim"], flight["gsd"]
    with rasterio.open(res.path) as src:
        assert src.crs.to_string() == sim.crs
        assert src.transform.a == pytest.approx(gsd) and src.transform.e == pytest.approx(-gsd)
        assert src.transform.b == 0 and src.transform.d == 0
        assert src.dtypes == ("uint16",) and src.nodata == 65535
        assert src.profile["compress"] == "deflate" and src.profile["tiled"]
        assert src.overviews(1), "overviews for a GIS"
        data = src.read(1, masked=True)
        mask = src.read_masks(1)
    valid = data.compressed()
    assert 0.9 < valid.size / data.size, f"coverage {valid.size / data.size:.3f}"
    kelvin = valid / 100.0
    assert 270 < np.median(kelvin) < 305 and kelvin.min() > 220, "kelvin * 100, original radiometry"
    assert np.array_equal(mask == 0, np.ma.getmaskarray(data))
    assert flight["calls"][-1] == (res.tiles, res.tiles) and len(flight["calls"]) == res.tiles
    assert not list(res.path.parent.glob(".tmp-*")), "written atomically, nothing left behind"


def test_overviews_are_gdals_average_of_the_mosaic_to_the_bit(flight, tmp_path):
    """The tiles make the overview levels (GDAL made them after the last tile, on one core): as a COG and as a
    tiled GeoTIFF, each level is what GDAL's own average overviews make of the mosaic's pixels, to the bit, and
    the grid is a whole number of the coarsest level's pixels (each level halves the one before exactly)."""
    res = flight["serial"]
    plain = build_mosaic(flight["frames"], flight["images"], flight["dsm"], tmp_path / "ortho_gtiff.tif",
                         MosaicConfig(gsd_m=flight["gsd"], cog=False))
    for made, cog in ((res, True), (plain, False)):
        with rasterio.open(made.path) as src:
            full, profile, factors = src.read(), src.profile, src.overviews(1)
            assert not cog or src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert factors and made.width % factors[-1] == 0 and made.height % factors[-1] == 0, (factors, made)
        gdal = tmp_path / f"gdal_{cog}.tif"
        with rasterio.open(gdal, "w", **(profile | {"driver": "GTiff", "compress": "none"})) as dst:
            dst.write(full)
        with rasterio.open(gdal, "r+") as dst:
            dst.build_overviews(factors, Resampling.average)
        for level, f in enumerate(factors):
            with rasterio.open(made.path, overview_level=level) as a, rasterio.open(gdal, overview_level=level) as b:
                assert a.shape == (made.height // f, made.width // f)
                assert np.array_equal(a.read(), b.read()), f"COG {cog}: overview 1/{f}"


def test_overviews_the_tiles_cannot_make_are_gdals_and_the_grid_keeps_its_size(flight, tmp_path):
    """Where a level's factor does not divide the tile (48-pixel tiles: 32 does not), GDAL makes the overviews from
    the finished mosaic, and the grid is not grown: it ends within a pixel of the bounds."""
    from aerocal.products.mosaic import overview_factors

    res = flight["serial"]
    bounds = _bounds(res)
    config = MosaicConfig(gsd_m=flight["gsd"], tile_px=48, bounds=bounds)
    assert overview_factors(res.width, res.height, config) == []
    made = build_mosaic(flight["frames"], flight["images"], flight["dsm"], tmp_path / "ortho_48.tif", config)
    assert (made.width, made.height) == (res.width, res.height)  # the bounds of a grid already whole
    odd = MosaicConfig(gsd_m=flight["gsd"], tile_px=48, bounds=(bounds[0], bounds[1] + 0.5 * flight["gsd"],
                                                                 bounds[2] - 7.5 * flight["gsd"], bounds[3]))
    made = build_mosaic(flight["frames"], flight["images"], flight["dsm"], tmp_path / "ortho_odd.tif", odd)
    assert (made.width, made.height) == (res.width - 7, res.height), "not grown beyond the bounds' last pixel"
    with rasterio.open(made.path) as src:
        assert src.overviews(1) and src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"


def test_mosaic_value_is_the_original_pixel_value(flight):
    """At the nadir of a frame the mosaic samples that frame alone: its DN, bilinearly resampled."""
    from aerocal.products.mosaic import read_frame

    res, fr = flight["serial"], flight["frames"][4]
    img = read_frame(flight["images"][fr.image_id]).astype(float)
    uv = np.array([[300.5, 240.5], [330.5, 220.5], [310.5, 260.5]])
    rays = np.column_stack([fr.camera.unproject(uv), np.ones(3)]) @ fr.R_cw
    dsm = flight["dsm"]
    X = []
    for d in rays:  # intersect with the DSM by fixed point on the height
        z = float(np.nanmedian(dsm.heights))
        for _ in range(20):
            p = fr.C + (z - fr.C[2]) / d[2] * d
            z = float(dsm.height_at(p[0], p[1]))
        X.append(p)
    X = np.array(X)
    with rasterio.open(res.path) as src:
        vals = np.array([v[0] for v in src.sample(X[:, :2])], float)
    expect = img[(uv[:, 1] - 0.5).astype(int), (uv[:, 0] - 0.5).astype(int)]
    assert np.all(np.abs(vals - expect) < 60), f"mosaic {vals} vs frame {expect} (DN, 0.01 K)"


def test_check_targets_in_the_mosaic_within_one_gsd(flight, client):
    sim, gsd = flight["sim"], flight["gsd"]
    res = mosaic_target_residuals(flight["serial"].path, sim.gcps, role="check", window_px=11)
    rmse = float(np.sqrt(np.mean(np.sum(res.residuals**2, axis=1))))
    print(f"check targets on the tie-point DSM mosaic: n {res.n}, RMSE {rmse:.3f} m = {rmse / gsd:.2f} GSD")
    assert res.n >= 8, f"seed {SEED}: only {res.n} of 12 check targets located"
    assert rmse < gsd, f"seed {SEED}: planimetric RMSE {rmse:.3f} m above 1 GSD {gsd:.3f} m"
    # on the true surface the geometry alone is tested: targets land to a small fraction of a pixel
    scene = sim.scene
    rows = scene.shape[0]
    true_dsm = Dsm(heights=scene.dsm, west=scene.config.origin_e,
                   north=scene.config.origin_n + rows * scene.config.cell_m, cell_m=scene.config.cell_m,
                   crs=sim.crs)
    exact = build_mosaic(flight["frames"], flight["images"], true_dsm, flight["work"] / "ortho_true.tif",
                         MosaicConfig(gsd_m=gsd, bounds=_bounds(flight["serial"])), client=client)
    res_true = mosaic_target_residuals(exact.path, sim.gcps, role="check", window_px=11)
    rmse_true = float(np.sqrt(np.mean(np.sum(res_true.residuals**2, axis=1))))
    print(f"check targets on the true DSM mosaic: n {res_true.n}, RMSE {rmse_true:.3f} m")
    assert res_true.n >= res.n and rmse_true < 0.2 * gsd, f"seed {SEED}: RMSE {rmse_true:.3f} m on the true DSM"


def _bounds(res):
    a, _, c, _, e, f = res.transform
    return (c, f + res.height * e, c + res.width * a, f)


def test_dask_and_serial_mosaics_are_identical(flight, client):
    calls = []
    res = build_mosaic(flight["frames"], flight["images"], flight["dsm"], flight["work"] / "ortho_dask.tif",
                       MosaicConfig(gsd_m=flight["gsd"]), client=client,
                       progress=lambda done, total: calls.append(done))
    with rasterio.open(res.path) as a, rasterio.open(flight["serial"].path) as b:
        assert a.transform == b.transform and a.shape == b.shape
        assert np.array_equal(a.read(), b.read())
        factors = a.overviews(1)
        assert factors == b.overviews(1)
    for level in range(len(factors)):  # the levels the tiles made on the workers
        with rasterio.open(res.path, overview_level=level) as a, \
                rasterio.open(flight["serial"].path, overview_level=level) as b:
            assert np.array_equal(a.read(), b.read()), f"overview {level}"
    assert sorted(calls) == list(range(1, res.tiles + 1))
    assert res.tiles > 2 * TILES_PER_TASK  # several tasks of several tiles each


def test_a_mosaic_on_threads_is_the_serial_one_and_leaves_the_process_its_opencv_threads(flight, monkeypatch):
    """The tiles on three threads of this process (the product's path without a Dask scheduler): the same file
    values as on one, every tile reported once, each frame decoded once (threads that need a frame another is
    decoding wait for it), and OpenCV's thread count afterwards what it was before (each tile runs OpenCV on one
    thread; a later step's semi-global matching must keep every core)."""
    import cv2

    import aerocal.products.mosaic as mosaic

    reads = []
    monkeypatch.setattr(mosaic, "read_frame", lambda p: reads.append(p) or read_raw(p))
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        calls = []
        res = build_mosaic(flight["frames"], flight["images"], flight["dsm"], flight["work"] / "ortho_threads.tif",
                           MosaicConfig(gsd_m=flight["gsd"]), progress=lambda done, total: calls.append(done),
                           threads=3)
        assert cv2.getNumThreads() == 2
    finally:
        cv2.setNumThreads(before)
    with rasterio.open(res.path) as a, rasterio.open(flight["serial"].path) as b:
        assert a.transform == b.transform and a.shape == b.shape
        assert np.array_equal(a.read(), b.read())
    assert calls == list(range(1, res.tiles + 1))
    assert len(reads) == len(set(reads)) == len(flight["frames"]), sorted(reads)


def test_a_frame_is_decoded_once_and_the_crop_it_is_resampled_from_changes_no_value(flight, monkeypatch):
    """Tiles touching a frame read it from the process's cache (a visible block's mosaic was decode-bound), and
    each tile converts only the part of the frame it reads: the same bytes as resampling whole frames held in
    memory."""
    import aerocal.products.mosaic as mosaic

    reads = []
    monkeypatch.setattr(mosaic, "_decoded", mosaic.FrameCache(mosaic._decoded.max_bytes))
    monkeypatch.setattr(mosaic, "read_frame", lambda p: reads.append(p) or read_raw(p))
    res = build_mosaic(flight["frames"], flight["images"], flight["dsm"], flight["work"] / "ortho_once.tif",
                       MosaicConfig(gsd_m=flight["gsd"], tile_px=64))
    assert res.tiles > 4 * len(flight["frames"]), res.tiles  # many tiles per frame
    assert len(reads) == len(set(reads)) <= len(flight["frames"]), sorted(reads)
    whole = {f.image_id: read_raw(flight["images"][f.image_id]) for f in flight["frames"]}
    held = build_mosaic(flight["frames"], whole, flight["dsm"], flight["work"] / "ortho_held.tif",
                        MosaicConfig(gsd_m=flight["gsd"], tile_px=64))
    with rasterio.open(res.path) as a, rasterio.open(held.path) as b:
        assert np.array_equal(a.read(), b.read())
    # the crop: where a tile reads, the values of resampling the whole frame, to the bit
    rng = np.random.default_rng(SEED)
    img = whole[flight["frames"][0].image_id]
    h, w = img.shape[:2]
    for u0, v0 in [(0.0, 0.0), (w - 40.0, h - 40.0), (300.0, 200.0)]:
        map_u = (u0 + 40 * rng.random((32, 32)) - 0.5).astype(np.float32)
        map_v = (v0 + 40 * rng.random((32, 32)) - 0.5).astype(np.float32)
        used = rng.random((32, 32)) < 0.7
        map_u[~used] = -10.0  # a pixel the frame does not see
        full = cv2.remap(img.astype(np.float32), map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        box = (map_u[used].min(), map_u[used].max(), map_v[used].min(), map_v[used].max())
        assert np.array_equal(mosaic._resampled(img, map_u, map_v, *box)[used], full[used]), (u0, v0)


def test_hilbert_order_visits_every_tile_once_each_next_to_the_last():
    from aerocal.products.mosaic import _hilbert_order

    for rows, cols in [(16, 16), (5, 13), (1, 7), (1, 1)]:
        order = _hilbert_order(rows, cols)
        assert sorted(order.tolist()) == list(range(rows * cols))
        r, c = np.divmod(order, cols)
        steps = np.abs(np.diff(r)) + np.abs(np.diff(c))
        if rows == cols == 16:
            assert np.all(steps == 1)
        else:  # the curve leaves the grid and comes back: most steps are still to a neighbour
            assert np.mean(steps == 1) > 0.8 if len(steps) else True


def test_tiles_whose_frames_are_missing_are_nodata_not_zeros(flight, client):
    frames = flight["frames"][:2]
    images = {f.image_id: flight["images"][f.image_id] for f in frames}
    res = build_mosaic(frames, images, flight["dsm"], flight["work"] / "ortho_part.tif",
                       MosaicConfig(gsd_m=flight["gsd"], bounds=_bounds(flight["serial"])), client=client)
    assert res.tiles_with_data < res.tiles
    with rasterio.open(res.path) as src:
        data = src.read(1)
        mask = src.read_masks(1)
    assert not np.any(data == 0), "no zeros: pixels no frame sees are nodata"
    empty = data == 65535
    assert 0.3 < empty.mean() < 0.95 and np.array_equal(empty, mask == 0)
    tiles = [data[r:r + 256, c:c + 256] for r in range(0, data.shape[0], 256) for c in range(0, data.shape[1], 256)]
    blank = sum(bool(np.all(t == 65535)) for t in tiles)
    assert blank == res.tiles - res.tiles_with_data >= 1, "tiles outside both footprints are wholly nodata"


def test_thermal_model_gives_each_frame_its_io_and_a_missing_temperature_is_named(flight):
    from aerocal.simulate.simulator import true_poses

    cam = Camera.from_mm(640, 480, focal_mm=39.2, pixel_size_um=23.5)
    model = LinearThermalModel(t0=20.0, df_dt=0.2, dcx_dt=0.05, dcy_dt=-0.03)
    poses = true_poses(flight["sim"])
    temps = {i: 15.0 + i for i in poses.column("image_id").to_pylist()}
    frames = frames_from_poses(poses, cam, temps, model)
    for f in frames:
        dt = temps[f.image_id] - 20.0
        assert f.camera.f == pytest.approx(cam.f + 0.2 * dt) and f.camera.cy == pytest.approx(cam.cy - 0.03 * dt)
    temps.pop(3)
    with pytest.raises(ValueError, match="image 3 has no sensor temperature"):
        frames_from_poses(poses, cam, temps, model)


def test_compiled_frame_view_is_the_camera_model(flight):
    """The compiled per-frame loop of the tiles gives the recorded pixels, nadir scores and tapers of the
    camera model (numpy, :meth:`FrameGeometry.project`) on a strongly distorted, affine camera, including
    ground points behind the camera, outside the frame and without a height."""
    import dataclasses

    from aerocal.products.kernels import frame_view
    from aerocal.products.mosaic import _frame_view_numpy

    rng = np.random.default_rng(SEED)
    fr = flight["frames"][4]
    cam = fr.camera.replace(k1=-0.3, k2=0.2, k3=-0.05, p1=1e-3, p2=-2e-3, b1=3.0, b2=-1.5)
    fr = dataclasses.replace(fr, camera=cam)
    e = fr.C[0] + np.linspace(-250.0, 250.0, 96)
    n = fr.C[1] + np.linspace(200.0, -200.0, 80)
    H = rng.uniform(-50.0, 80.0, (80, 96))
    H[rng.random(H.shape) < 0.05] = np.nan
    H[:3, :3] = fr.C[2] + 100.0  # above the camera: behind it
    E, N = np.meshgrid(e, n)
    got = [np.empty(H.shape, np.float32), np.empty(H.shape, np.float32), np.empty(H.shape), np.empty(H.shape)]
    want = [np.empty_like(a) for a in got]
    frame_view(e, n, H, fr.R_cw, fr.C, cam.params(), float(cam.width), float(cam.height), 8.0, *got, np.zeros(3))
    _frame_view_numpy(fr, np.stack([E, N, H], axis=-1), 8.0, *want)
    inside = np.isfinite(want[2])
    assert 0.2 < inside.mean() < 0.9, "the test grid must reach beyond the frame"
    np.testing.assert_allclose(got[0], want[0], atol=1e-3)
    np.testing.assert_allclose(got[1], want[1], atol=1e-3)
    np.testing.assert_array_equal(np.isfinite(got[2]), inside)
    np.testing.assert_allclose(got[2][inside], want[2][inside], rtol=1e-9)
    np.testing.assert_allclose(got[3], want[3], rtol=1e-9, atol=1e-12)


def test_a_global_shutters_vector_loop_gives_the_bits_of_the_pixel_by_pixel_loop():
    """:func:`frame_view`'s loop without branches (a global shutter) computes every pixel and chooses by selects:
    the same bits as the pixel-by-pixel loop the readout needs, given no motion, for random poses and distorted
    cameras, with ground points behind the camera, above it, without a height and at infinite heights."""
    from aerocal.geometry import matrix_from_quat_wxyz
    from aerocal.products.kernels import _frame_view_moving, frame_view

    rng = np.random.default_rng(SEED)
    seen = 0
    for trial in range(60):
        q = rng.normal(size=4) if trial % 2 else np.array([0.0, 1.0, 0.0, 0.0]) + rng.normal(0.0, 0.3, 4)
        R = matrix_from_quat_wxyz(q / np.linalg.norm(q))
        C = rng.normal(0.0, 50.0, 3) + [0.0, 0.0, 300.0]
        io = np.array([800.0, 320.0 + rng.normal(0, 5), 256.0 + rng.normal(0, 5), rng.normal(0, 0.2),
                       rng.normal(0, 0.1), rng.normal(0, 0.05), rng.normal(0, 1e-3), rng.normal(0, 1e-3),
                       rng.normal(0, 2.0), rng.normal(0, 1.0)])
        e = C[0] + rng.normal(0.0, 100.0) + 2.0 * np.arange(53)
        n = C[1] + rng.normal(0.0, 100.0) - 2.0 * np.arange(37)
        H = rng.normal(0.0, 30.0, (37, 53))
        for value, share in [(np.nan, 0.05), (np.inf, 0.01), (-np.inf, 0.01), (400.0, 0.02)]:
            H[rng.random(H.shape) < share] = value
        got = [np.empty(H.shape, np.float32), np.empty(H.shape, np.float32), np.empty(H.shape), np.empty(H.shape)]
        want = [np.empty_like(a) for a in got]
        args = (e, n, H, R, C, io, 640.0, 512.0, 8.0)
        assert frame_view(*args, *got, np.zeros(3)) == _frame_view_moving(*args, *want, np.zeros(3)), trial
        for a, b in zip(got, want, strict=True):
            assert np.array_equal(a, b, equal_nan=True), trial
        seen += int(np.isfinite(got[2]).sum())
    assert seen > 5000  # the poses see the ground often enough for the comparison to mean something


def test_a_frame_read_out_row_by_row_is_projected_as_the_simulator_exposed_it(flight):
    """A rolling readout in the products: a frame's ground points land on the rows the simulator's true sensor
    model put them on (:class:`aerocal.simulate.exposure.Exposure`, 30 ms at 60 m/s, 1.8 m of motion over the
    frame), in the numpy path and in the compiled tiles' loop alike."""
    import dataclasses

    from aerocal.products.kernels import frame_view
    from aerocal.products.mosaic import _frame_view_numpy
    from aerocal.simulate.exposure import Exposure

    fr = flight["frames"][4]
    velocity, readout = np.array([60.0, 8.0, 0.0]), 0.03
    true = Exposure(image_id=fr.image_id, camera=fr.camera, R_cw=fr.R_cw, C=fr.C, velocity=velocity,
                    readout_s=readout)
    moving = dataclasses.replace(fr, motion=velocity * readout)
    e = fr.C[0] + np.linspace(-200.0, 200.0, 64)
    n = fr.C[1] + np.linspace(150.0, -150.0, 48)
    E, N = np.meshgrid(e, n)
    H = np.full(E.shape, 40.0)
    X = np.stack([E, N, H], axis=-1).reshape(-1, 3)
    want = true.project(X)
    inside = fr.camera.in_image(want)
    assert inside.mean() > 0.3, "the grid must cover the frame"
    np.testing.assert_allclose(moving.project(X)[inside], want[inside], atol=1e-6)
    assert np.max(np.abs(fr.project(X)[inside] - want[inside])) > 1.0, "the readout moves the rows by pixels"
    got = [np.empty(H.shape, np.float32), np.empty(H.shape, np.float32), np.empty(H.shape), np.empty(H.shape)]
    ref = [np.empty_like(a) for a in got]
    frame_view(e, n, H, fr.R_cw, fr.C, fr.camera.params(), float(fr.camera.width), float(fr.camera.height), 8.0,
               *got, velocity * readout)
    _frame_view_numpy(moving, np.stack([E, N, H], axis=-1), 8.0, *ref)
    np.testing.assert_allclose(got[0], ref[0], atol=1e-3)
    np.testing.assert_allclose(got[1], ref[1], atol=1e-3)


def test_score_bounds_hold_every_score_of_a_distorted_tilted_frame(flight):
    """The bounds that let a tile skip a frame hold every score the frame gives a point of the tile's volume, on
    a strongly distorted, affine camera turned 30 degrees about its axis, over relief."""
    import dataclasses

    from aerocal.geometry import rot_z
    from aerocal.products.kernels import frame_view, score_bounds

    rng = np.random.default_rng(SEED)
    fr = flight["frames"][4]
    cam = fr.camera.replace(k1=-0.3, k2=0.2, k3=-0.05, p1=1e-3, p2=-2e-3, b1=3.0, b2=-1.5)
    fr = dataclasses.replace(fr, camera=cam, R_cw=rot_z(np.radians(30.0)) @ fr.R_cw)
    checked = 0
    for _ in range(40):
        w, s = fr.C[0] + rng.uniform(-300, 250), fr.C[1] + rng.uniform(-300, 250)
        e, n = w + (np.arange(64) + 0.5) * 0.8, s + 51.2 - (np.arange(64) + 0.5) * 0.8
        H = rng.uniform(-20.0, 40.0, (64, 64))
        box = np.array([[w, s, H.min()], [w + 51.2, s + 51.2, H.max()]])
        low, high, whole = score_bounds(box, fr.R_cw, fr.C, cam.params(), float(cam.width), float(cam.height))
        out = [np.empty(H.shape, np.float32), np.empty(H.shape, np.float32), np.empty(H.shape), np.empty(H.shape)]
        frame_view(e, n, H, fr.R_cw, fr.C, cam.params(), float(cam.width), float(cam.height), 8.0, *out,
                   np.zeros(3))
        score = out[2][np.isfinite(out[2])]
        if score.size:
            checked += 1
            assert low <= score.min() and score.max() <= high, (low, score.min(), score.max(), high)
        assert not whole or score.size == H.size, "a frame said to see the whole tile sees every pixel"
    assert checked >= 10


def test_frames_a_tile_skips_would_have_carried_no_weight(flight, monkeypatch):
    """Skipping the frames the score bounds rule out changes no byte of the mosaic, and skips a fifth of them or
    more."""
    import aerocal.products.mosaic as mosaic

    kept, every = [], []
    skip = mosaic._may_be_seen

    def counted(frames, *args):
        out = skip(frames, *args)
        kept.append(len(out))
        every.append(len(frames))
        return out

    monkeypatch.setattr(mosaic, "_may_be_seen", counted)
    config = MosaicConfig(gsd_m=flight["gsd"], tile_px=64)
    pruned = build_mosaic(flight["frames"], flight["images"], flight["dsm"], flight["work"] / "o_pruned.tif", config)
    monkeypatch.setattr(mosaic, "_may_be_seen", lambda frames, *a: list(enumerate(frames)))
    full = build_mosaic(flight["frames"], flight["images"], flight["dsm"], flight["work"] / "o_full.tif", config)
    with rasterio.open(pruned.path) as a, rasterio.open(full.path) as b:
        assert np.array_equal(a.read(), b.read())
    print(f"frames projected: {sum(kept)} of {sum(every)}")
    assert sum(kept) < 0.8 * sum(every)  # 718 of 1,109 when written


def test_a_mosaic_keeps_no_frame_after_it_and_reads_a_rewritten_frame_again(flight, tmp_path, client):
    """The frames a mosaic decoded are released when it ends, here and on the workers: a long-lived process holds
    none, and a frame written again at the same path is read as it is now."""
    import shutil

    import tifffile

    import aerocal.products.mosaic as mosaic

    def held() -> int:
        return len(mosaic._decoded)

    images = {}
    for k, path in flight["images"].items():
        images[k] = tmp_path / path.name
        shutil.copy(path, images[k])
    config = MosaicConfig(gsd_m=flight["gsd"], tile_px=128)
    build_mosaic(flight["frames"], images, flight["dsm"], tmp_path / "a.tif", config)
    assert held() == 0
    build_mosaic(flight["frames"], images, flight["dsm"], tmp_path / "b.tif", config, client=client)
    assert held() == 0 and set(client.run(held).values()) == {0}
    first = flight["frames"][0].image_id
    raw = read_raw(images[first])
    tifffile.imwrite(images[first], np.full_like(raw, 30000))  # the first frame rewritten, uniform
    again = build_mosaic(flight["frames"], images, flight["dsm"], tmp_path / "c.tif", config)
    with rasterio.open(tmp_path / "a.tif") as a, rasterio.open(again.path) as c:
        assert not np.array_equal(a.read(), c.read())


def test_frame_cache_reads_a_key_once_for_threads_that_miss_it_at_once():
    """Threads that miss the same key while it is being read wait for that read; where it fails, each reads
    again itself and meets the error."""
    import threading

    from aerocal.products.mosaic import FrameCache

    cache = FrameCache(1 << 20)
    started, release = threading.Event(), threading.Event()
    reads = []

    def slow():
        reads.append(1)
        started.set()
        release.wait(5)
        return (np.arange(4),)

    got = []
    first = threading.Thread(target=lambda: got.append(cache.get("a", slow)))
    first.start()
    started.wait(5)
    second = threading.Thread(target=lambda: got.append(cache.get("a", slow)))
    second.start()
    release.set()
    first.join(5)
    second.join(5)
    assert len(reads) == 1 and len(got) == 2 and got[0][0] is got[1][0]

    def broken():
        reads.append(2)
        raise ValueError("unreadable")

    with pytest.raises(ValueError, match="unreadable"):
        cache.get("b", broken)
    with pytest.raises(ValueError, match="unreadable"):  # nothing kept, nothing pending: read again
        cache.get("b", broken)
    assert reads.count(2) == 2 and len(cache) == 1


@pytest.mark.parametrize("shape, dtype, nodata", [((3, 9, 7), np.uint8, 0), ((1, 8, 5), np.uint16, 65535),
                                                   ((1, 6, 6), np.uint8, 100)])
def test_halve_is_the_rounded_mean_of_each_blocks_valid_pixels(shape, dtype, nodata):
    """An overview level's pixel: the mean of the valid pixels of its 2 x 2 block (an odd last row or column a
    block of its own pixels), rounded half up; nodata where none is valid, and a mean equal to nodata moved one
    count inward."""
    from aerocal.products.kernels import halve

    rng = np.random.default_rng(SEED)
    src = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    src[:, rng.random(shape[1:]) < 0.3] = nodata
    src[:, src[0] == nodata] = nodata  # a mosaic's pixel is nodata in every band or in none
    hi = np.iinfo(dtype).max
    # the first block: two valid pixels either side of nodata where it lies between (their mean is nodata: moved)
    src[:, 0, 0] = nodata - 1 if nodata > 0 else 1
    src[:, 1, 1] = nodata + 1 if 0 < nodata < hi else src[0, 0, 0]
    src[:, 0, 1] = src[:, 1, 0] = nodata
    out = np.empty((shape[0], -(-shape[1] // 2), -(-shape[2] // 2)), dtype=dtype)
    halve(src, nodata, hi, out)
    for r in range(out.shape[1]):
        for c in range(out.shape[2]):
            block = src[:, 2 * r:2 * r + 2, 2 * c:2 * c + 2].reshape(shape[0], -1).astype(float)
            valid = block[0] != nodata
            if not valid.any():
                assert np.all(out[:, r, c] == nodata), (r, c)
                continue
            mean = np.floor(block[:, valid].mean(axis=1) + 0.5)
            expect = np.where(mean == nodata, nodata - 1 if nodata == hi else nodata + 1, mean)
            assert np.array_equal(out[:, r, c], expect), (r, c, out[:, r, c], expect)
