"""Accuracy assessment: residual statistics, achieved vs predicted accuracy, DEM differences, loop closure."""

import json

import numpy as np
import pytest

from aerocal import tables
from aerocal.assess import (
    VERDICT_OK,
    VERDICT_SYSTEMATIC,
    accuracy_ratio,
    compare_dems,
    loop_closure,
    point_residuals,
    reprojection_stats,
    triangulate_gcps,
)
from aerocal.camera import Camera
from aerocal.geometry import nadir_R_cw
from aerocal.products.dsm import Dsm
from aerocal.products.mosaic import FrameGeometry

SIGMA = np.array([0.05, 0.05, 0.12])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_rho_inside_the_band_for_gaussian_errors_with_known_sigmas(seed):
    rng = np.random.default_rng(seed)
    e = rng.normal(0.0, SIGMA, (500, 3))
    r = accuracy_ratio(e, SIGMA)
    lo, hi = r.band
    assert hi - 1 == pytest.approx(1.96 / np.sqrt(1000)), "band 1 +- 1.96/sqrt(2n)"
    assert np.all((r.rho > lo) & (r.rho < hi)), f"seed {seed}: rho {r.rho} outside {r.band}"
    assert r.verdict == VERDICT_OK, f"seed {seed}: {r.verdict}"
    json.dumps(r.to_dict())


@pytest.mark.parametrize("seed", [1, 2])
def test_rho_above_the_band_when_a_bias_is_added(seed):
    rng = np.random.default_rng(seed)
    e = rng.normal(0.0, SIGMA, (500, 3))
    e[:, 2] += 0.6 * SIGMA[2]  # a height bias of 0.6 sigma
    r = accuracy_ratio(e, np.tile(SIGMA, (500, 1)))
    assert r.rho[2] > r.band[1], f"seed {seed}: rho_U {r.rho[2]:.3f} not above {r.band[1]:.3f}"
    assert r.chi2_mean[2] > r.chi2_band[1]
    assert r.verdict == VERDICT_SYSTEMATIC and r.verdict_per_axis["U"] == VERDICT_SYSTEMATIC
    assert r.verdict_per_axis["E"] == VERDICT_OK, f"seed {seed}: {r.verdict_per_axis}"


def _dem(heights, west=1000.0, north=2000.0, cell=1.0):
    return Dsm(heights=np.asarray(heights, np.float32), west=west, north=north, cell_m=cell, crs="EPSG:32632")


def test_dem_difference_of_a_shifted_dem_gives_the_shift():
    rng = np.random.default_rng(5)
    ref = _dem(50 + np.cumsum(rng.normal(0, 0.2, (120, 150)), axis=1))
    shifted = _dem(ref.heights + 1.25 + rng.normal(0, 0.1, ref.shape))
    d = compare_dems(shifted, ref, transects=[((1010.0, 1950.0), (1100.0, 1950.0))])
    assert d.mean == pytest.approx(1.25, abs=0.01)
    assert d.median == pytest.approx(1.25, abs=0.01)
    assert d.nmad == pytest.approx(0.1, rel=0.05) and d.std == pytest.approx(0.1, rel=0.05)
    assert d.n == 120 * 150 and d.histogram_counts.sum() >= 0.999 * d.n, "histogram spans +-4 NMAD"
    centre = d.histogram_edges[np.argmax(d.histogram_counts)]
    assert abs(centre - 1.25) < 0.1, "the histogram peaks at the shift"
    t = d.transects[0]
    dz = np.array(t["height_m"]) - np.array(t["reference_m"])
    assert t["distance_m"][-1] == pytest.approx(90.0) and abs(np.mean(dz) - 1.25) < 0.05
    json.dumps(d.to_dict())


def test_dem_difference_respects_the_mask_and_holes():
    ref = _dem(np.full((20, 20), 10.0))
    test = ref.heights.copy()
    test[:10] += 2.0
    test[15:, :] = np.nan
    mask = np.zeros((20, 20), bool)
    mask[10:] = True
    d = compare_dems(_dem(test), ref, mask=mask, selection="southern half")
    assert d.n == 5 * 20 and d.mean == pytest.approx(0.0) and d.selection == "southern half"


def test_a_dem_difference_within_a_mask_gives_what_comparing_with_that_mask_gives():
    rng = np.random.default_rng(11)
    ref = _dem(50 + np.cumsum(rng.normal(0, 0.3, (90, 110)), axis=0))
    test = ref.heights + rng.normal(0.3, 0.2, ref.shape).astype(np.float32)
    test[40:50, 20:60] = np.nan
    inside = np.ones(ref.shape, bool)
    inside[:, 100:] = False
    near = rng.random(ref.shape) < 0.3
    whole = compare_dems(_dem(test), ref, mask=inside)
    direct = compare_dems(_dem(test), ref, mask=inside & near, selection="near")
    part = whole.within(near, "near")
    assert part.n == direct.n and part.selection == "near"
    for name in ("mean", "std", "median", "nmad", "rmse"):
        assert getattr(part, name) == pytest.approx(getattr(direct, name), rel=1e-6, abs=1e-6), name
    np.testing.assert_array_equal(part.histogram_counts, direct.histogram_counts)
    np.testing.assert_array_equal(np.isfinite(part.difference), np.isfinite(direct.difference))
    with pytest.raises(ValueError, match="shape"):
        whole.within(near[:10], "near")


def _gcps(xyz, roles):
    n = len(xyz)
    return tables.from_columns("gcps", {
        "gcp_id": [f"P{i}" for i in range(n)], "X": xyz[:, 0], "Y": xyz[:, 1], "Z": xyz[:, 2],
        "sigma_x": np.full(n, 0.02), "sigma_y": np.full(n, 0.02), "sigma_z": np.full(n, 0.03), "role": roles,
    })


def _block():
    cam = Camera.from_mm(640, 480, focal_mm=39.2, pixel_size_um=23.5).replace(k1=-0.08, k2=0.12, p1=2e-4)
    frames = []
    for i, (e, n) in enumerate([(0, 0), (100, 0), (200, 0), (200, 150), (100, 150), (0, 150), (0, 20), (100, 20)]):
        frames.append(FrameGeometry(image_id=i + 1, camera=cam, R_cw=nadir_R_cw(90.0), C=np.array([e, n, 900.0])))
    return cam, frames


def test_triangulated_check_points_and_their_residuals():
    seed = 8
    rng = np.random.default_rng(seed)
    cam, frames = _block()
    pts = np.column_stack([rng.uniform(20, 80, 6), rng.uniform(-30, 30, 6), rng.uniform(40, 60, 6)])
    shift = np.array([0.3, -0.2, 0.5])
    rows = {"gcp_id": [], "image_id": [], "x": [], "y": [], "sigma": []}
    for f in frames[:3]:
        uv = f.project(pts + shift)  # the block sees every point displaced by `shift`
        for k in range(len(pts)):
            if cam.in_image(uv[k]):
                rows["gcp_id"].append(f"P{k}")
                rows["image_id"].append(f.image_id)
                rows["x"].append(uv[k, 0])
                rows["y"].append(uv[k, 1])
                rows["sigma"].append(0.5)
    est = triangulate_gcps(frames, tables.from_columns("gcp_observations", rows))
    res = point_residuals(est, _gcps(pts, ["check"] * 3 + ["control"] * 3), role="check")
    assert res.n == 3 and res.ids == ["P0", "P1", "P2"]
    np.testing.assert_allclose(res.residuals, np.tile(shift, (3, 1)), atol=1e-6,
                               err_msg=f"seed {seed}")
    d = res.to_dict()
    assert d["rmse_m"]["U"] == pytest.approx(0.5, abs=1e-6)
    json.dumps(d)


def test_loop_closure_measures_the_drift_between_first_and_last_pair():
    seed = 4
    rng = np.random.default_rng(seed)
    cam, frames = _block()
    pts = np.column_stack([rng.uniform(0, 100, 300), rng.uniform(0, 150, 300), rng.uniform(45, 55, 300)])
    first, last = (1, 2), (7, 8)  # frames 7, 8 close the loop over frames 1, 2
    drift = np.array([0.4, 0.0, -0.3])
    drifted = [f if f.image_id not in last else FrameGeometry(f.image_id, f.camera, f.R_cw, f.C + drift)
               for f in frames]
    rows = {"image_id": [], "track_id": [], "x": [], "y": [], "sigma": []}
    for f in frames:
        uv = f.project(pts)
        ok = cam.in_image(uv)
        rows["image_id"] += [f.image_id] * int(ok.sum())
        rows["track_id"] += np.nonzero(ok)[0].tolist()
        rows["x"] += uv[ok, 0].tolist()
        rows["y"] += uv[ok, 1].tolist()
        rows["sigma"] += [0.5] * int(ok.sum())
    obs = tables.from_columns("observations", rows)
    closed = loop_closure(frames, obs, first, last)
    assert closed.n > 20 and closed.max_m < 1e-6, f"seed {seed}: a perfect block closes ({closed.max_m})"
    lc = loop_closure(drifted, obs, first, last)
    np.testing.assert_allclose(lc.mean_vector_m, drift, atol=1e-6, err_msg=f"seed {seed}")
    assert lc.mean_m == pytest.approx(0.5, abs=1e-6)
    json.dumps(lc.to_dict())


def test_reprojection_statistics_per_image_and_strip_and_over_the_image():
    seed = 6
    rng = np.random.default_rng(seed)
    n = 4000
    iid = rng.integers(1, 5, n)
    xy = rng.uniform([0, 0], [640, 480], (n, 2))
    res = rng.normal(0, 0.3, (n, 2))
    res[iid == 3] *= 3.0  # one bad image
    res[:, 0] += 0.5 * (xy[:, 0] - 320) / 320  # a radial-like pattern in x
    obs = tables.from_columns("observations", {"image_id": iid, "track_id": np.arange(n), "x": xy[:, 0],
                                               "y": xy[:, 1], "sigma": np.full(n, 0.3)})
    images = tables.from_columns("images", {
        "image_id": [1, 2, 3, 4], "name": ["a", "b", "c", "d"], "camera_id": ["c"] * 4, "width": [640] * 4,
        "height": [480] * 4, "strip": [1, 1, 2, 2]})
    st = reprojection_stats(obs, res, images)
    worst = max(st.per_image, key=lambda k: st.per_image[k]["rms_px"])
    assert worst == 3, f"seed {seed}: {st.per_image}"
    assert st.per_strip[2]["rms_px"] > 1.5 * st.per_strip[1]["rms_px"]
    b = st.binned
    assert b is not None and b.count.sum() == n
    assert b.mean[:, 0, 0].mean() < -0.3 and b.mean[:, -1, 0].mean() > 0.3, "left/right columns show the pattern"
    with pytest.raises(ValueError, match="expected"):
        reprojection_stats(obs, res[:10])
    json.dumps(st.to_dict())
