"""Tile-parallel SIFT, footprint pairs, verified matches and tracks, on real frames and synthetic grids."""

from __future__ import annotations

import dataclasses
import functools
import re
import time
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pytest
from scipy.spatial import ConvexHull, cKDTree

from aerocal import enhance as E
from aerocal import geometry, tables
from aerocal.camera import Camera
from aerocal.matching import (
    FeatureConfig,
    MatchConfig,
    build_tracks,
    candidate_pairs_from_footprints,
    convex_overlap_area,
    detect,
    exhaustive_pairs,
    extract_features,
    footprints,
    match_pairs,
    match_pairs_detailed,
    sequential_pairs,
)
from aerocal.matching.pairs import prior_poses

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
H20T = DATA / "h20t_forest" / "images"
SENECA = DATA / "seneca" / "images"
#: Ten consecutive frames of one strip of the Seneca flight (heading ~50 deg).
SENECA_STRIP = [f"IMG_{k:04d}.jpg" for k in range(473, 483)]


def _need(folder: Path) -> None:
    if not folder.is_dir():
        pytest.skip(f"measured data not found at {folder} (a clone without ../shared/data)")


def read_h20t_raw(path: Path) -> np.ndarray:
    """The raw 640x512 uint16 frame of a DJI H20T R-JPEG: the APP3 payloads, concatenated in order."""
    data = Path(path).read_bytes()
    pos, chunks = 2, []
    while pos + 4 <= len(data) and data[pos] == 0xFF and data[pos + 1] != 0xDA:
        length = int.from_bytes(data[pos + 2 : pos + 4], "big")
        if data[pos + 1] == 0xE3:
            chunks.append(data[pos + 4 : pos + 2 + length])
        pos += 2 + length
    return np.frombuffer(b"".join(chunks), dtype="<u2").reshape(512, 640)


def load_h20t_enhanced(path: str, lo: float, hi: float) -> np.ndarray:
    """Loader for the workers: raw frame -> dataset-wide 2 % stretch -> Wallis -> uint8."""
    sp = E.StretchParams(lo=lo, hi=hi, percent=2.0, n_frames=0, n_pixels=0)
    return E.enhance(read_h20t_raw(Path(path)), sp, E.EnhanceConfig())


def load_grey(path: str) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise OSError(f"{path}: not a readable image")
    return img


@pytest.fixture(scope="module")
def client():
    """One real two-process LocalCluster for the module (starts in about a second)."""
    from aerocal.matching import local_client

    with local_client(n_workers=2) as c:
        yield c


def test_local_cluster_workers_keep_one_blas_thread_and_glibc_malloc_defaults(client):
    import os

    env = client.run(lambda: {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "OPENBLAS_NUM_THREADS")})
    assert len(env) == 2
    for worker, values in env.items():
        assert values == {"MALLOC_TRIM_THRESHOLD_": None, "OPENBLAS_NUM_THREADS": "1"}, (worker, values)


def test_local_cluster_teardown_stops_the_worker_heartbeats_before_the_scheduler_goes():
    """A heartbeat that finds the scheduler's stream closed logs a traceback on the user's terminal."""
    from aerocal.matching import local_client
    from aerocal.matching.cluster import _quiet_teardown

    with local_client(n_workers=2) as c:
        assert all(c.run(lambda dask_worker: dask_worker.periodic_callbacks["heartbeat"].is_running()).values())
        _quiet_teardown(c)
        running = c.run(lambda dask_worker: dask_worker.periodic_callbacks["heartbeat"].is_running())
        assert len(running) == 2 and not any(running.values()), running


@pytest.fixture(scope="module")
def h20t_paths() -> list[Path]:
    _need(H20T)
    return sorted(H20T.glob("*_T.JPG"))


@pytest.fixture(scope="module")
def h20t_loader(h20t_paths):
    sp = E.stretch_params([read_h20t_raw(p) for p in h20t_paths], sample_frames=16)
    return functools.partial(load_h20t_enhanced, lo=sp.lo, hi=sp.hi)


# ----------------------------------------------------------------------------- (b) tiles vs whole image
def test_tiled_detection_agrees_with_untiled_detection_on_a_real_h20t_frame(h20t_paths, h20t_loader):
    img = h20t_loader(str(h20t_paths[5]))
    whole, _ = detect(img, FeatureConfig(max_features=0, tile_size=0))
    tiled, desc = detect(img, FeatureConfig(max_features=0, tile_size=256, tile_overlap=64))  # 3 x 3 tiles
    assert len(whole) > 2000 and desc.shape == (len(tiled), 128) and desc.dtype == np.uint8
    d, _ = cKDTree(whole[:, :2]).query(tiled[:, :2])
    agree = float(np.mean(d < 0.01))
    assert agree > 0.98, f"only {agree:.3f} of tiled keypoints within 0.01 px of an untiled one"
    # and nothing is lost or duplicated in the overlaps
    assert abs(len(tiled) - len(whole)) < 0.01 * len(whole), (len(tiled), len(whole))
    assert len(np.unique(tiled, axis=0)) == len(tiled)


def test_keypoints_are_in_the_aerocal_pixel_convention(h20t_paths, h20t_loader):
    """Mirror the image: with the origin at the pixel corner, x and the mirrored x' sum to the width."""
    img = h20t_loader(str(h20t_paths[5]))
    cfg = FeatureConfig(max_features=0, tile_size=256, tile_overlap=64)
    kp, _ = detect(img, cfg)
    kpm, _ = detect(np.ascontiguousarray(img[:, ::-1]), cfg)
    w = img.shape[1]
    d, j = cKDTree(np.column_stack([w - kpm[:, 0], kpm[:, 1]])).query(kp[:, :2])
    ok = d < 0.3
    assert ok.mean() > 0.9
    offset = float(np.median(kp[ok, 0] + kpm[j[ok], 0] - w))
    assert abs(offset) < 0.01, f"x + x' - W = {offset:.3f} px (0 expected; -1 would be OpenCV's convention)"


def test_a_frame_detected_from_octave_0_keeps_the_pixel_convention_and_its_tiles_agree(h20t_paths, h20t_loader):
    """A frame above ``fine_octave_max_pixels`` is reduced twice before OpenCV sees it: its keypoints are in the
    frame's pixels (a mirrored frame gives x + x' = W), and tiles of the frame give the whole frame's keypoints."""
    img = cv2.resize(h20t_loader(str(h20t_paths[5])), (1280, 1024), interpolation=cv2.INTER_CUBIC)
    octave0 = {"fine_octave_max_pixels": 1_000_000}  # the 1.3 MP frame detected from octave 0
    whole, _ = detect(img, FeatureConfig(max_features=0, tile_size=0, **octave0))
    upsampled, _ = detect(img, FeatureConfig(max_features=0, tile_size=0))
    assert 500 < len(whole) < 0.8 * len(upsampled), (len(whole), len(upsampled))
    tiled, _ = detect(img, FeatureConfig(max_features=0, tile_size=576, tile_overlap=64, **octave0))  # 3 x 2 tiles
    d, _ = cKDTree(whole[:, :2]).query(tiled[:, :2])
    assert np.mean(d < 0.02) > 0.97 and abs(len(tiled) - len(whole)) < 0.02 * len(whole), (len(tiled), len(whole))
    mirrored, _ = detect(np.ascontiguousarray(img[:, ::-1]), FeatureConfig(max_features=0, tile_size=0, **octave0))
    d, j = cKDTree(np.column_stack([1280 - mirrored[:, 0], mirrored[:, 1]])).query(whole[:, :2])
    ok = d < 0.5
    assert ok.mean() > 0.9
    offset = float(np.median(whole[ok, 0] + mirrored[j[ok], 0] - 1280))
    assert abs(offset) < 0.02, f"x + x' - W = {offset:.3f} px from octave 0 (0 expected)"
    # octave -1 holds the scales below SIFT's base sigma (1.6 px of the frame); octave 0 none of them
    assert np.quantile(upsampled[:, 2], 0.05) < 1.4 and np.quantile(whole[:, 2], 0.01) > 1.5, \
        (np.quantile(upsampled[:, 2], 0.05), np.quantile(whole[:, 2], 0.01))


def test_cap_keeps_the_strongest_features(h20t_paths, h20t_loader):
    img = h20t_loader(str(h20t_paths[8]))
    full, dfull = detect(img, FeatureConfig(max_features=0))
    capped, dcap = detect(img, FeatureConfig(max_features=500))
    assert len(capped) == 500 < len(full)
    assert np.array_equal(capped, full[:500]) and np.array_equal(dcap, dfull[:500])


# ----------------------------------------------------------------------------- (c) Dask vs serial
DASK_CASE = FeatureConfig(max_features=1500, tile_size=256, tile_overlap=64)  # 3 x 3 tiles per frame


@pytest.fixture(scope="module")
def dask_case_items(h20t_paths):
    return [(int(k), str(p)) for k, p in zip((3, 7, 11), h20t_paths[10:13], strict=True)]


@pytest.fixture(scope="module")
def serial_keypoints(dask_case_items, h20t_loader):
    return extract_features(dask_case_items, h20t_loader, DASK_CASE, client=None)


@pytest.mark.parametrize("granularity", ["image", "tile"])
def test_dask_and_serial_extraction_give_identical_keypoints(
    client, dask_case_items, h20t_loader, serial_keypoints, granularity
):
    cfg = dataclasses.replace(DASK_CASE, granularity=granularity)
    calls: list[tuple[int, int]] = []
    on_cluster = extract_features(
        dask_case_items, h20t_loader, cfg, client=client, progress=lambda d, t: calls.append((d, t))
    )
    tables.validate(on_cluster, "keypoints")
    assert on_cluster.num_rows == 3 * 1500
    assert on_cluster.equals(serial_keypoints)  # every column, descriptors included
    assert sorted(set(on_cluster.column("image_id").to_pylist())) == [3, 7, 11]
    assert calls[-1][0] == calls[-1][1] and len(calls) == calls[-1][1]
    assert calls[-1][1] == (3 if granularity == "image" else 3 * 9)


def test_dask_and_serial_matching_give_identical_matches(client, dask_case_items, serial_keypoints, h20t_paths):
    pairs = exhaustive_pairs([3, 7, 11])
    cfg = MatchConfig(pairs_per_task=2)
    on_cluster = match_pairs_detailed(pairs, serial_keypoints, cfg, client=client)
    here = match_pairs_detailed(pairs, serial_keypoints, cfg)
    assert on_cluster.matches.num_rows > 200
    assert on_cluster.matches.equals(here.matches)
    assert on_cluster.pair_stats.equals(here.pair_stats)


@pytest.mark.parametrize("granularity", ["image", "tile"])
def test_streamed_detection_and_matching_give_the_two_phase_tables(
    client, dask_case_items, h20t_loader, serial_keypoints, granularity
):
    """Pairs matched as soon as their images are detected: the serial keypoints and matches, every column; an
    image in a pair but not in the images has no features, as in the two-phase path."""
    from aerocal.matching import detect_and_match

    pairs = np.vstack([exhaustive_pairs([3, 7, 11]), [[3, 99]]])
    cfg, fcfg = MatchConfig(pairs_per_task=2), dataclasses.replace(DASK_CASE, granularity=granularity)
    calls: list[tuple[int, int]] = []
    kp, streamed = detect_and_match(dask_case_items, h20t_loader, pairs, fcfg, cfg, client,
                                    progress=lambda d, t: calls.append((d, t)))
    here = match_pairs_detailed(pairs, serial_keypoints, cfg)
    assert kp.equals(serial_keypoints)
    assert streamed.matches.num_rows > 200
    assert streamed.matches.equals(here.matches)
    assert streamed.pair_stats.equals(here.pair_stats)
    assert streamed.pair_stats.num_rows == 4  # (3, 99) tried, not verified
    assert calls[-1] == (3 + 4, 3 + 4) and all(a[0] <= b[0] for a, b in zip(calls, calls[1:], strict=False))
    deadline = time.monotonic() + 10.0  # releases reach the scheduler asynchronously
    while client.who_has() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not client.who_has(), "the cluster still holds features or matches after the call"


# ----------------------------------------------------------------------------- (d) footprint pairs
def _grid_block(seed: int, strips: int = 6, per_strip: int = 12):
    """Nadir serpentine block: 640x512 thermal camera, 100 m above ground, 60 % / 30 % overlap."""
    rng = np.random.default_rng(seed)
    cam = Camera.from_mm(640, 512, 13.5, 12.0)
    height = 100.0
    gx = 640 * 0.012 * height / 13.5  # across-track footprint, m (image x across track)
    gy = 512 * 0.012 * height / 13.5  # along-track footprint, m
    R, C = [], []
    for s in range(strips):
        heading = 0.0 if s % 2 == 0 else 180.0
        for k in range(per_strip):
            north = k * 0.4 * gy
            roll, pitch, dyaw = rng.normal(0, 2.0, 3)
            R.append(geometry.body_rpy_to_R_cw(roll, pitch, heading + dyaw))
            C.append([s * 0.7 * gx, north, 250.0 + rng.normal(0, 1.0)])
    return cam, np.array(R), np.array(C), 150.0, (gx, gy)


def test_footprint_of_a_nadir_camera_has_the_expected_size():
    cam = Camera.from_mm(640, 512, 13.5, 12.0)
    fp = footprints(geometry.nadir_R_cw(0.0)[None], np.array([[100.0, 200.0, 95.0]]), cam, 0.0)[0]
    gx, gy = 640 * 0.012 * 95 / 13.5, 512 * 0.012 * 95 / 13.5
    assert np.ptp(fp[:, 0]) == pytest.approx(gx, rel=1e-9) and np.ptp(fp[:, 1]) == pytest.approx(gy, rel=1e-9)
    assert fp.mean(axis=0) == pytest.approx([100.0, 200.0], abs=1e-9)
    # heading 90 deg (image top to the east): the footprint turns, its long side now runs north-south
    fp90 = footprints(geometry.nadir_R_cw(90.0)[None], np.array([[100.0, 200.0, 95.0]]), cam, 0.0)[0]
    assert np.ptp(fp90[:, 0]) == pytest.approx(gy, rel=1e-9) and np.ptp(fp90[:, 1]) == pytest.approx(gx, rel=1e-9)


@pytest.mark.parametrize("seed", [1, 2])
def test_footprint_candidates_include_every_overlapping_pair_and_no_far_pair(seed):
    cam, R, C, terrain, (gx, gy) = _grid_block(seed)
    n = len(C)
    cols = {"R_cw": R, "C": C, "image_id": np.arange(100, 100 + n)}
    pairs, frac = candidate_pairs_from_footprints(cols, cam, terrain, min_overlap=0.05, return_overlap=True)
    found = {tuple(p) for p in pairs.tolist()}
    # brute force: every one of the n (n - 1) / 2 pairs
    fp = footprints(R, C, cam, terrain)
    i, j = np.triu_indices(n, k=1)
    area = convex_overlap_area(fp, fp)  # a footprint's overlap with itself is its area
    inter = convex_overlap_area(fp[i], fp[j])
    true_frac = inter / np.minimum(area[i], area[j])
    truth = {(100 + a, 100 + b) for a, b, f in zip(i, j, true_frac, strict=True) if f >= 0.05}
    assert truth - found == set(), f"seed={seed}: missed overlapping pairs {sorted(truth - found)[:5]}"
    assert found - truth == set(), f"seed={seed}: pairs below the overlap threshold {sorted(found - truth)[:5]}"
    # pairs in the same strip two frames apart overlap by ~20 %; far pairs are excluded
    centre = C[:, :2]
    far = np.linalg.norm(centre[i] - centre[j], axis=1) > 1.5 * np.hypot(gx, gy)
    assert not any((100 + a, 100 + b) in found for a, b in zip(i[far], j[far], strict=True)), f"seed={seed}"
    assert len(found) < 0.2 * len(i), f"seed={seed}: {len(found)} of {len(i)} pairs is not selective"
    assert np.all(frac >= 0.05) and np.all(frac <= 1.0)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_cap_on_pairs_keeps_each_images_most_overlapping_ones(seed):
    """A pair stays where it is among the k largest overlaps of either of its images, and only then."""
    cam, R, C, terrain, _ = _grid_block(seed)
    cols = {"R_cw": R, "C": C, "image_id": np.arange(100, 100 + len(C))}
    every, frac = candidate_pairs_from_footprints(cols, cam, terrain, min_overlap=0.05, return_overlap=True)
    k = 3
    kept = {tuple(p) for p in candidate_pairs_from_footprints(cols, cam, terrain, min_overlap=0.05,
                                                              max_pairs_per_image=k).tolist()}
    top = set()
    for image in np.unique(every):
        mine = np.nonzero((every == image).any(axis=1))[0]
        top |= {tuple(every[m]) for m in mine[np.argsort(-frac[mine], kind="stable")[:k]]}
    # ties in overlap would let either of two equal pairs be the k-th: the grid's overlaps are distinct
    assert len(np.unique(np.round(frac, 12))) == len(frac), f"seed={seed}"
    assert kept == top, f"seed={seed}: kept {sorted(kept - top)[:3]} beyond, left out {sorted(top - kept)[:3]}"
    assert len(kept) < len(every), f"seed={seed}: the cap of {k} kept every one of {len(every)} pairs"


def test_overlap_area_agrees_with_convex_hull_of_the_intersection():
    """Independent check of the vectorised clipping: hull of (vertices inside the other + edge crossings)."""
    seed = 4
    rng = np.random.default_rng(seed)
    P = 300
    ang = np.sort(rng.uniform(0, 2 * np.pi, (P, 2, 4)), axis=-1)
    rad = rng.uniform(5, 10, (P, 2, 4))
    ctr = rng.uniform(-6, 6, (P, 2, 1, 2))
    quads = ctr + np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=-1)  # (P, 2, 4, 2), CCW
    # keep convex quads only (angle-sorted points on varying radii can be concave)
    def convex(q):
        e = np.roll(q, -1, axis=1) - q
        cross = e[:, :, 0] * np.roll(e, -1, axis=1)[:, :, 1] - e[:, :, 1] * np.roll(e, -1, axis=1)[:, :, 0]
        return (cross > 0).all(axis=1)

    ok = convex(quads[:, 0]) & convex(quads[:, 1])
    a, b = quads[ok, 0], quads[ok, 1]
    got = convex_overlap_area(a, b)

    def inside(pts, poly):
        e = np.roll(poly, -1, axis=0) - poly
        rel = pts[:, None, :] - poly[None]
        return ((e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]) >= -1e-12).all(axis=1)

    for k in range(len(a)):
        pts = [a[k][inside(a[k], b[k])], b[k][inside(b[k], a[k])]]
        for s in range(4):
            p, r = a[k][s], a[k][(s + 1) % 4] - a[k][s]
            for t in range(4):
                q, u = b[k][t], b[k][(t + 1) % 4] - b[k][t]
                den = r[0] * u[1] - r[1] * u[0]
                if abs(den) < 1e-12:
                    continue
                tt = ((q - p)[0] * u[1] - (q - p)[1] * u[0]) / den
                uu = ((q - p)[0] * r[1] - (q - p)[1] * r[0]) / den
                if 0 <= tt <= 1 and 0 <= uu <= 1:
                    pts.append((p + tt * r)[None])
        allp = np.concatenate(pts)
        expected = ConvexHull(allp).volume if len(allp) >= 3 else 0.0
        assert got[k] == pytest.approx(expected, rel=1e-9, abs=1e-9), f"seed={seed} pair {k}"
    assert ok.sum() > 50 and (got > 0).sum() > 20 and (got == 0).sum() > 5


def test_pairs_helpers_and_errors():
    assert exhaustive_pairs(4).tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    assert exhaustive_pairs([7, 3]).tolist() == [[3, 7]]
    assert sequential_pairs(5, window=2).tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3], [2, 4], [3, 4]]
    cam = Camera.from_mm(640, 512, 13.5, 12.0)
    with pytest.raises(ValueError, match="height reference"):
        footprints(geometry.nadir_R_cw(0.0)[None], np.array([[0.0, 0.0, 50.0]]), cam, 80.0)
    images = {"image_id": [1, 2], "name": ["a.jpg", "b.jpg"], "gnss_x": [0.0, None], "gnss_y": [0.0, 1.0],
              "gnss_z": [100.0, 100.0], "roll": [0.0, 0.0], "pitch": [0.0, 0.0], "yaw": [0.0, 0.0],
              "attitude_convention": ["body_rpy", "body_rpy"]}
    with pytest.raises(ValueError, match=r"b\.jpg"):
        prior_poses({k: np.array(v, dtype=object) for k, v in images.items()})


# ----------------------------------------------------------------------------- (e) real Seneca strip
def _sensefly_xmp(path: Path) -> dict[str, float]:
    text = path.read_bytes()[:400_000].decode("latin-1")
    keys = ("Latitude", "Longitude", "Height", "RollAngle", "PitchAngle", "Heading")
    return {k: float(re.search(rf"<sensefly:{k}>([^<]+)<", text).group(1)) for k in keys}


@pytest.fixture(scope="module")
def seneca_strip(client):
    _need(SENECA)
    paths = [SENECA / n for n in SENECA_STRIP]
    meta = [_sensefly_xmp(p) for p in paths]
    lon = np.array([m["Longitude"] for m in meta])
    lat = np.array([m["Latitude"] for m in meta])
    crs = geometry.utm_crs_for(lon[0], lat[0])
    x, y = geometry.lonlat_to_projected(lon, lat, crs)
    images = tables.from_columns("images", {
        "image_id": np.arange(len(paths)), "name": SENECA_STRIP, "path": [str(p) for p in paths],
        "camera_id": ["Canon|PowerShot ELPH 300 HS||"] * len(paths),
        "width": [1800] * len(paths), "height": [1350] * len(paths),
        "gnss_x": x, "gnss_y": y, "gnss_z": [m["Height"] for m in meta],  # height above take-off, m
        "roll": [m["RollAngle"] for m in meta], "pitch": [m["PitchAngle"] for m in meta],
        "yaw": [m["Heading"] for m in meta], "attitude_convention": ["body_rpy"] * len(paths),
    }, crs=crs)
    cam = Camera.from_mm(1800, 1350, 4.3, 3.08)  # 1/2.3" sensor, 6.16 mm over 2000 (halved) pixels
    pairs = candidate_pairs_from_footprints(images, cam, terrain_height=0.0, min_overlap=0.2)
    kp = extract_features(images, load_grey, FeatureConfig(max_features=4000), client=client)
    result = match_pairs_detailed(pairs, kp, MatchConfig(), client=client)
    return images, pairs, kp, result


def test_seneca_neighbours_are_matched_with_a_reasonable_inlier_ratio(seneca_strip):
    images, pairs, kp, result = seneca_strip
    n = images.num_rows
    consecutive = {(k, k + 1) for k in range(n - 1)}
    assert consecutive <= {tuple(p) for p in pairs.tolist()}, "footprints missed consecutive frames"
    stats = result.pair_stats.to_pylist()
    by_pair = {(r["image_id1"], r["image_id2"]): r for r in stats}
    verified = [by_pair[p] for p in sorted(consecutive) if by_pair[p]["verified"]]
    assert len(verified) >= 7, f"only {len(verified)} of {n - 1} consecutive pairs verified"
    ratios = [r["n_inliers"] / r["n_putative"] for r in verified]
    assert np.median(ratios) > 0.8, f"median RANSAC inlier ratio {np.median(ratios):.2f}"
    assert np.median([r["n_inliers"] for r in verified]) > 100
    rms = [r["rms_px"] for r in verified]
    assert max(rms) < 1.0, f"inlier Sampson RMS up to {max(rms):.2f} px with a 1 px threshold"
    m = result.matches
    assert m.num_rows == sum(r["n_inliers"] for r in stats if r["verified"])
    assert (m.column("image_id1").to_numpy() < m.column("image_id2").to_numpy()).all()


# ----------------------------------------------------------------------------- (f) tracks
def test_tracks_from_real_matches_contain_no_image_twice(seneca_strip):
    _, _, kp, result = seneca_strip
    obs = build_tracks(result.matches, kp)
    tables.validate(obs, "observations")
    track = obs.column("track_id").to_numpy()
    image = obs.column("image_id").to_numpy()
    pairs = np.column_stack([track, image])
    assert len(np.unique(pairs, axis=0)) == len(pairs), "a track holds two keypoints of one image"
    length = np.bincount(track)
    assert length.min() >= 2 and (length >= 3).sum() > 50, "expected multi-image tracks along the strip"
    assert np.array_equal(np.unique(track), np.arange(track.max() + 1))
    assert np.all(obs.column("sigma").to_numpy() == np.float32(0.5))
    # observations are the keypoints' own positions
    key = {(int(i), round(float(x), 3), round(float(y), 3)) for i, x, y in zip(
        kp.column("image_id").to_numpy(), kp.column("x").to_numpy(), kp.column("y").to_numpy(), strict=True)}
    sample = zip(image[:200], obs.column("x").to_numpy()[:200], obs.column("y").to_numpy()[:200], strict=True)
    assert all((int(i), round(float(np.float32(x)), 3), round(float(np.float32(y)), 3)) in key for i, x, y in sample)


def test_inconsistent_tracks_are_dropped_and_consistent_ones_kept():
    # image 0 keypoints 0 and 1 both end up in one component through images 1 and 2: drop it
    kp = tables.from_columns("keypoints", {
        "image_id": [0, 0, 1, 2, 0, 1, 2, 3], "keypoint_id": [0, 1, 0, 0, 2, 1, 1, 0],
        "x": [1.0, 2.0, 3.0, 4.0, 10.0, 11.0, 12.0, 13.0], "y": [0.5] * 8,
    })
    matches = tables.from_columns("matches", {
        "image_id1": [0, 1, 0, 0, 1, 2], "image_id2": [1, 2, 2, 1, 2, 3],
        "keypoint_id1": [0, 0, 1, 2, 1, 1], "keypoint_id2": [0, 0, 0, 1, 1, 0],
    })
    obs = build_tracks(matches, kp, MatchConfig(sigma_px=0.7))
    assert obs.column("track_id").to_pylist() == [0, 0, 0, 0]
    assert obs.column("image_id").to_pylist() == [0, 1, 2, 3]
    assert obs.column("x").to_pylist() == [10.0, 11.0, 12.0, 13.0]
    assert obs.column("sigma").to_numpy() == pytest.approx(0.7)
    bad = tables.from_columns("matches", {"image_id1": [0], "image_id2": [5], "keypoint_id1": [0],
                                          "keypoint_id2": [9]})
    with pytest.raises(ValueError, match=r"\(5, 9\)"):
        build_tracks(bad, kp)


def test_detect_refuses_16_bit_input_with_the_fix():
    with pytest.raises(ValueError, match="aerocal.enhance"):
        detect(np.zeros((64, 64), np.uint16))
    with pytest.raises(ValueError, match="multiple of 32"):
        FeatureConfig(tile_size=500, tile_overlap=64)


def test_match_pairs_returns_an_empty_valid_table_for_featureless_images():
    kp = tables.empty("keypoints")
    m = match_pairs([[0, 1]], kp)
    assert isinstance(m, pa.Table) and m.num_rows == 0
    tables.validate(m, "matches")



def _reference_matches(d1: np.ndarray, d2: np.ndarray, ratio: float) -> set[tuple[int, int]]:
    """Mutual nearest neighbours passing the ratio test both ways, from float64 distances, by definition."""
    a, b = d1.astype(np.float64), d2.astype(np.float64)
    dist = np.sqrt(np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2 * a @ b.T, 0))
    out = set()
    for i in range(len(a)):
        j = int(np.argmin(dist[i]))
        row, col = np.sort(dist[i]), np.sort(dist[:, j])
        if int(np.argmin(dist[:, j])) == i and row[0] < ratio * row[1] and col[0] < ratio * col[1]:
            out.add((i, j))
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_exact_matcher_finds_the_true_mutual_neighbours_in_one_piece_and_in_blocks(seed, monkeypatch):
    import importlib

    verify_module = importlib.import_module("aerocal.matching.verify")  # the package exports a function too
    rng = np.random.default_rng(seed)
    n1, n2, shared = 700, 600, 400
    base = rng.integers(0, 120, (shared, 128))
    d1 = np.vstack([base, rng.integers(0, 120, (n1 - shared, 128))])
    d2 = np.vstack([base + rng.integers(-6, 7, base.shape), rng.integers(0, 120, (n2 - shared, 128))])
    d1, d2 = np.clip(d1, 0, 255).astype(np.uint8), np.clip(d2, 0, 255).astype(np.uint8)
    p1, p2 = rng.permutation(n1), rng.permutation(n2)  # row r of d1 holds generated descriptor p1[r]
    d1, d2 = d1[p1], d2[p2]
    dup = int(np.nonzero(p2 == 0)[0][0])
    d2 = np.vstack([d2, d2[dup]])  # a duplicated descriptor: generated descriptor 0 has no unique neighbour
    dup1 = int(np.nonzero(p1 == 1)[0][0])
    d1 = np.vstack([d1, d1[dup1]])  # and a duplicated row, in another row block than its twin: a column's tie

    truth = _reference_matches(d1, d2, 0.8)
    found = set(map(tuple, verify_module.match_descriptors(d1, d2, MatchConfig()).tolist()))
    monkeypatch.setattr(verify_module, "EXACT_MAX_CELLS", 97 * len(d2))  # 97-row blocks, both directions from them
    blocks = set(map(tuple, verify_module.match_descriptors(d1, d2, MatchConfig()).tolist()))
    print(f"seed {seed}: {len(found)} matches, {len(truth)} by definition")
    assert found == truth, f"seed {seed}: {len(found ^ truth)} matches differ from the definition"
    assert blocks == truth, f"seed {seed}: the block-wise matcher differs from the definition"
    planted = {(int(np.nonzero(p1 == k)[0][0]), int(np.nonzero(p2 == k)[0][0])) for k in range(1, shared)}
    assert len(found & planted) > 0.95 * len(planted) and not found - planted, f"seed {seed}"
    assert not any(j in (dup, len(d2) - 1) for _, j in found), f"seed {seed}: a tie was matched"
    assert not any(i in (dup1, len(d1) - 1) for i, _ in found), f"seed {seed}: a column's tie was matched"


def test_exact_and_flann_matchers_agree_on_real_frames(seneca_strip):
    from aerocal.matching.features import image_features
    from aerocal.matching.verify import match_descriptors

    feats = image_features(seneca_strip[2])
    d1, d2 = feats[0][2], feats[1][2]
    exact = set(map(tuple, match_descriptors(d1, d2, MatchConfig()).tolist()))
    flann = set(map(tuple, match_descriptors(d1, d2, MatchConfig(matcher="flann")).tolist()))
    print(f"exact {len(exact)}, FLANN {len(flann)}, both {len(exact & flann)}")
    assert len(exact & flann) > 0.95 * len(flann) and len(exact) >= 0.99 * len(flann)
