"""DSM from tie points: robust gridding, GeoTIFF output, agreement with the simulator's true surface."""

import numpy as np
import pytest
import rasterio

from aerocal.products.dsm import NODATA, Dsm, DsmConfig, dsm_from_points, read_dsm, write_dsm

CRS = "EPSG:32632"


def _plane(e, n):
    return 50.0 + 0.02 * (e - 686000.0) - 0.01 * (n - 4929000.0)


def test_plane_with_blunders_is_recovered_and_blunders_rejected():
    seed = 11
    rng = np.random.default_rng(seed)
    e = rng.uniform(686000, 686200, 4000)
    n = rng.uniform(4929000, 4929150, 4000)
    z = _plane(e, n) + rng.normal(0, 0.05, len(e))
    blunder = rng.choice(len(e), 25, replace=False)
    z[blunder] += rng.choice([-1, 1], 25) * rng.uniform(20, 60, 25)
    dsm = dsm_from_points(np.column_stack([e, n, z]), CRS, gsd_m=0.5)
    assert dsm.cell_m == pytest.approx(1.0), "default cell = 2 GSD"
    assert dsm.stats["rejected_outliers"] >= 25, f"seed {seed}: {dsm.stats}"
    E, N = dsm.cell_centres()
    inside = (E > 686005) & (E < 686195) & (N > 4929005) & (N < 4929145)
    err = dsm.heights[inside] - _plane(E[inside], N[inside])
    assert np.all(np.isfinite(err))
    assert np.max(np.abs(err)) < 0.3, f"seed {seed}: max error {np.max(np.abs(err)):.3f} m"
    assert abs(np.mean(err)) < 0.02, f"seed {seed}: mean error {np.mean(err):.4f} m"


def test_write_dsm_is_a_georeferenced_float32_cloud_optimized_geotiff(tmp_path):
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(0, 100, 500) + 686000, rng.uniform(0, 80, 500) + 4929000,
                           rng.uniform(40, 45, 500)])
    dsm = dsm_from_points(pts, CRS, config=DsmConfig(cell_m=2.0, max_fill_distance_m=3.0))
    assert np.isnan(dsm.heights).any(), "cells far from data stay empty with max_fill_distance_m"
    path = write_dsm(dsm, tmp_path / "dsm.tif")
    with rasterio.open(path) as src:
        assert src.crs.to_epsg() == 32632
        assert src.dtypes[0] == "float32" and src.nodata == NODATA
        assert src.transform.a == 2.0 and src.transform.e == -2.0
        assert (src.transform.c, src.transform.f) == (dsm.west, dsm.north)
        data = src.read(1, masked=True)
        assert data.mask.sum() == np.isnan(dsm.heights).sum()
        # a Cloud-Optimized GeoTIFF (what GDAL's COG driver writes and says of itself), tiled
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG", src.tags(ns="IMAGE_STRUCTURE")
        assert src.profile.get("tiled") and src.descriptions[0] == "height", src.profile
    back = read_dsm(path)
    np.testing.assert_array_equal(np.isnan(back.heights), np.isnan(dsm.heights))
    assert np.nanmax(np.abs(back.heights - dsm.heights)) == 0.0
    assert not list(tmp_path.glob(".tmp-*")), "no temporary file left behind"


def test_a_dsm_larger_than_a_block_has_gdals_average_overviews_down_to_one_block(tmp_path):
    """The overviews a GIS reads when zoomed out: GDAL's average of the heights, nodata left out, at the levels
    GDAL's COG driver makes (halving until one 256-cell block holds the level), each tiled."""
    from rasterio.enums import Resampling

    from aerocal.products.dsm import cog_overview_factors

    rng = np.random.default_rng(7)
    heights = (40.0 + np.cumsum(rng.normal(0, 0.2, (700, 1100)), axis=1)).astype(np.float32)
    heights[100:160, 300:420] = np.nan
    dsm = Dsm(heights=heights, west=686000.0, north=4929000.0, cell_m=0.5, crs=CRS)
    measured = np.isfinite(heights) & (rng.random(heights.shape) < 0.9)
    path = write_dsm(dsm, tmp_path / "dsm.tif", measured)
    assert cog_overview_factors(1100, 700) == [2, 4, 8]
    plain = tmp_path / "plain.tif"
    with rasterio.open(path) as src:
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert src.overviews(1) == src.overviews(2) == [2, 4, 8], src.overviews(1)
        with rasterio.open(plain, "w", **{**src.profile, "driver": "GTiff", "tiled": False, "compress": None}) as dst:
            dst.write(src.read())
            dst.build_overviews([2, 4, 8], Resampling.average)
    for level in range(3):
        with rasterio.open(path, overview_level=level) as a, rasterio.open(plain, overview_level=level) as b:
            assert a.block_shapes[0] == (256, 256) or max(a.shape) <= 256, (level, a.block_shapes)
            assert np.array_equal(a.read(), b.read()), f"overview 1/{2 ** (level + 1)}"
            h = a.read(1, masked=True)
            assert not h.mask.all() and h.min() >= np.nanmin(heights) - 1e-3, "nodata is left out of the averages"


def test_read_dsm_names_the_file_it_cannot_read(tmp_path):
    bad = tmp_path / "broken.tif"
    bad.write_text("not a tiff")
    with pytest.raises(ValueError, match="broken.tif"):
        read_dsm(bad)


def test_tie_point_dsm_matches_the_true_surface_where_it_has_data():
    from aerocal.simulate import simulate_flight

    seed = 3
    sim = simulate_flight("conte-calibration", seed=seed, max_images=14)
    gsd = sim.trajectory.gsd_m
    dsm = dsm_from_points(sim.tie.points, sim.crs, gsd_m=gsd)
    from aerocal.assess import compare_dems

    # cells within 2 m (2 cells) of a cell that holds a tie point: measured, not interpolated across
    near = compare_dems(dsm, sim.scene.height_at, mask=dsm.distance_m <= 2.0, selection="within 2 m of data")
    print(f"tie-point DSM - true DSM near data: mean {near.mean:.3f} m, NMAD {near.nmad:.3f} m, n {near.n}")
    assert near.n > 500  # cells no finer than a quarter of the tie-point spacing (DsmConfig.min_point_spacing)
    assert abs(near.mean) < gsd, f"seed {seed}: mean difference {near.mean:.3f} m above 1 GSD ({gsd:.2f} m)"
    assert abs(near.median) < 0.2 * gsd, f"seed {seed}: median {near.median:.3f} m"


@pytest.mark.parametrize("seed", [0, 1])
def test_sparse_points_far_below_the_ground_are_rejected_and_the_grid_keeps_its_height_range(seed):
    """Thermal tie points are sparse (tens of metres apart, no neighbour within the local radius); a weak
    intersection 7 km below the ground among them must not survive, a roof 12 m up 20 m away must."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 2000, (4000, 2))  # one point per ~1000 m2: ~30 m apart
    z = 50.0 + 0.01 * xy[:, 0] + rng.normal(0, 0.3, len(xy))
    pts = np.column_stack([xy, z])
    deep = np.array([[1000.0, 1000.0, -6941.0], [400.0, 1500.0, -800.0], [1600.0, 300.0, 900.0]])
    roof = np.array([[xy[0, 0] + 20.0, xy[0, 1], z[0] + 12.0]])
    d = dsm_from_points(np.vstack([pts, deep, roof]), "EPSG:32632", config=DsmConfig(cell_m=1.0))
    lo, hi = d.height_range()
    print(f"seed {seed}: rejected {d.stats['rejected_outliers']}, heights {lo:.1f}..{hi:.1f} m")
    assert 45.0 < lo and hi < 90.0, f"seed {seed}: the DSM spans {lo:.1f}..{hi:.1f} m"
    from aerocal.products.dsm import reject_outliers

    keep = reject_outliers(np.vstack([pts, deep, roof]), DsmConfig(cell_m=1.0), 1.0)
    assert not keep[len(pts):len(pts) + 3].any(), f"seed {seed}: a deep or high blunder kept"
    assert keep[-1], f"seed {seed}: the isolated roof point was rejected"
    assert keep[: len(pts)].mean() > 0.999, f"seed {seed}: ground points rejected"


def test_sparse_points_over_a_large_area_get_cells_sized_by_their_spacing():
    """1,782 tie points over 3.7 km x 3.7 km at a GSD of 0.15 m asked for 2 x 18146 x 18264 cells (over
    23 GB); the cell follows the points' spacing instead, and the surface is still recovered."""
    seed = 12
    rng = np.random.default_rng(seed)
    e = rng.uniform(686000, 689700, 1782)
    n = rng.uniform(4929000, 4932700, 1782)
    dsm = dsm_from_points(np.column_stack([e, n, _plane(e, n)]), CRS, gsd_m=0.15)
    spacing = np.sqrt(3700.0 * 3700.0 / 1782)
    assert dsm.cell_m == pytest.approx(0.25 * spacing, rel=0.01), dsm.cell_m
    assert dsm.heights.size < 60_000, dsm.heights.shape
    E, N = dsm.cell_centres()
    inside = (E > 686200) & (E < 689500) & (N > 4929200) & (N < 4932500)
    assert np.nanmax(np.abs(dsm.heights[inside] - _plane(E[inside], N[inside]))) < 0.5, f"seed {seed}"


@pytest.mark.parametrize("wild", [1, 20])
def test_a_few_points_intersected_far_off_the_block_do_not_coarsen_the_grid(wild):
    """One two-ray tie point 320 km from a 2 km block (measured on a rendered city flight) made the cells
    635 m; the cells follow the spacing of the block's own points whatever a few wild ones do."""
    seed = 7 + wild
    rng = np.random.default_rng(seed)
    e = rng.uniform(686000, 688000, 5000)
    n = rng.uniform(4929000, 4930700, 5000)
    pts = np.column_stack([e, n, _plane(e, n)])
    far = np.column_stack([rng.uniform(366000, 1e6, wild), rng.uniform(3.9e6, 6e6, wild),
                           rng.uniform(-1e7, 1e4, wild)])
    clean = dsm_from_points(pts, CRS, gsd_m=0.5)
    dsm = dsm_from_points(np.vstack([pts, far]), CRS, gsd_m=0.5)
    assert dsm.cell_m == pytest.approx(clean.cell_m, rel=0.02), f"seed {seed}: {dsm.cell_m} m, {clean.cell_m} m"
    w, s, e_, n_ = dsm.bounds()
    assert w > 685900 and s > 4928900 and e_ < 688100 and n_ < 4930800, f"seed {seed}: grid {dsm.bounds()}"
    E, N = dsm.cell_centres()
    inside = (E > 686200) & (E < 687800) & (N > 4929200) & (N < 4930500)
    assert np.nanmax(np.abs(dsm.heights[inside] - _plane(E[inside], N[inside]))) < 0.5, f"seed {seed}"


@pytest.mark.parametrize("seed", [0, 1])
def test_hole_filling_gives_scipy_griddata_values(seed):
    """Linear on the data cells' Delaunay triangles, nearest outside their hull: scipy's griddata values, but inside
    a circle through four or more data cells (where either diagonal is Delaunay, so either height is linear on a
    Delaunay triangulation) and where an equidistant tie outside the hull may take either cell."""
    from scipy.interpolate import griddata
    from scipy.spatial import cKDTree

    from aerocal.products.dsm import fill_holes, rim_triangles

    rng = np.random.default_rng(seed)
    heights = np.full((120, 90), np.nan)
    r, c = rng.integers(10, 110, 300), rng.integers(5, 80, 300)
    heights[r, c] = 100.0 + 0.3 * r - 0.2 * c + rng.normal(0.0, 2.0, 300)
    has = np.isfinite(heights)
    filled = fill_holes(heights, has)
    known, holes = np.argwhere(has), np.argwhere(~has)
    linear = griddata(known.astype(float), heights[has], holes.astype(float), method="linear")
    inside = np.isfinite(linear)
    got = filled[~has]
    assert np.isfinite(filled).all(), f"seed {seed}"
    # where the heights differ, the triangle over the cell has a fourth data cell on its circumcircle
    tri = known[rim_triangles(known[:, 0], known[:, 1])]  # every data cell borders a hole here
    differ = holes[inside][np.abs(got[inside] - linear[inside]) > 1e-9]
    for cell in differ:
        a, b, c_ = (tri[:, k].astype(np.int64) - cell for k in range(3))
        cross = lambda p, q: p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]  # noqa: E731
        over = tri[(np.sign(cross(b - a, -a)) * np.sign(cross(c_ - b, -b)) >= 0)
                   & (np.sign(cross(c_ - b, -b)) * np.sign(cross(a - c_, -c_)) >= 0)
                   & (np.sign(cross(b - a, -a)) * np.sign(cross(a - c_, -c_)) >= 0)][0].astype(np.int64)
        on_circle = [_in_circle_det(*over, p) for p in known.astype(np.int64)]
        assert sum(d == 0 for d in on_circle) >= 4, f"seed {seed}: cell {cell} differs from griddata in a " \
                                                    "triangle no fourth cell makes ambiguous"
        turn = int(np.sign(cross((over[1] - over[0])[None], (over[2] - over[0])[None])[0]))
        assert all(d * turn <= 0 for d in on_circle), f"seed {seed}: a data cell inside {over}'s circle"
    assert len(differ) < 0.02 * inside.sum(), f"seed {seed}: {len(differ)} cells"
    d, _ = cKDTree(known).query(holes[~inside], k=2)
    nearest = griddata(known.astype(float), heights[has], holes[~inside].astype(float), method="nearest")
    differ = got[~inside] != nearest
    assert np.allclose(d[differ, 0], d[differ, 1]), f"seed {seed}: a hole took a data cell that is not nearest"
    assert differ.mean() < 0.05, f"seed {seed}"


def _in_circle_det(a, b, c, p) -> int:
    """The in-circle determinant of p against the circle through a, b, c (integer cells; Python's exact ints):
    0 on the circle; inside it, the sign of the triangle's orientation."""
    rows = [(int(q[0]) - int(p[0]), int(q[1]) - int(p[1])) for q in (a, b, c)]
    (ax, ay), (bx, by), (cx, cy) = rows
    al, bl, cl = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    return ax * (by * cl - cy * bl) - ay * (bx * cl - cx * bl) + al * (bx * cy - cx * by)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_distance_to_data_is_the_exact_euclidean_transform(seed):
    """Every cell's distance to the nearest data cell: scipy's exact transform to float32 rounding, 0 on the data,
    inf where the grid holds no data at all (scipy would measure to a cell beyond the grid)."""
    from scipy import ndimage

    from aerocal.products.dsm import distance_to_data

    rng = np.random.default_rng(seed)
    has = ndimage.binary_opening(rng.random((310, 270)) < 0.4) | (rng.random((310, 270)) < 0.002)
    has[:, :60] = False  # a wide hole on the western edge
    got = distance_to_data(has)
    assert got.dtype == np.float32 and got.shape == has.shape
    np.testing.assert_allclose(got, ndimage.distance_transform_edt(~has), rtol=1e-6, atol=1e-5,
                               err_msg=f"seed {seed}")
    assert not got[has].any(), f"seed {seed}"
    assert np.isinf(distance_to_data(np.zeros((4, 5), dtype=bool))).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_pinholes_take_the_mean_of_their_neighbours(seed):
    """A hole cell whose 8 neighbours hold at least 4 heights takes their mean, pass after pass (zero beyond the
    grid): the neighbour sums of scipy's convolution to float32 rounding."""
    from scipy import ndimage

    from aerocal.products.dsm import PINHOLE_PASSES, _fill_pinholes

    rng = np.random.default_rng(seed)
    heights = (100.0 + rng.normal(0.0, 3.0, (140, 160))).astype(np.float32)
    has = rng.random(heights.shape) < 0.7
    heights[~has] = np.nan
    got, got_has = _fill_pinholes(heights, has)
    want, want_has = heights.copy(), has.copy()
    ring = np.ones((3, 3), dtype=np.float32)
    ring[1, 1] = 0.0
    for _ in range(PINHOLE_PASSES):
        count = ndimage.convolve(want_has.astype(np.float32), ring, mode="constant")
        pin = ~want_has & (count >= 4)
        total = ndimage.convolve(np.where(want_has, want, 0.0).astype(np.float32), ring, mode="constant")
        want[pin] = total[pin] / count[pin]
        want_has |= pin
    assert np.array_equal(got_has, want_has), f"seed {seed}"
    np.testing.assert_allclose(got[got_has], want[want_has], rtol=1e-6, err_msg=f"seed {seed}")
    assert got_has.mean() > has.mean() + 0.2, f"seed {seed}: the pinholes of a 70 % grid close"


def test_data_cells_on_one_line_fill_the_grid_with_the_nearest_height():
    """No triangle to interpolate on (one row of tie points, e.g. a single strip's centre line): the DSM is
    filled from the nearest cell instead of failing in qhull."""
    pts = np.column_stack([np.linspace(0.0, 100.0, 50), np.full(50, 10.0), np.linspace(20.0, 30.0, 50)])
    dsm = dsm_from_points(pts, "EPSG:32632", config=DsmConfig(cell_m=2.0))
    assert np.isfinite(dsm.heights).all()
    assert dsm.heights.min() >= 20.0 - 1e-6 and dsm.heights.max() <= 30.0 + 1e-6
    west_col = dsm.heights[:, :3]
    assert np.all(west_col < 21.0)


@pytest.mark.parametrize("seed", [5])
def test_cell_medians_are_the_median_of_the_points_in_each_cell(seed):
    """The gridding's per-cell median and count (bucketed in numba, the cell of each point computed where it is
    used) against their numpy definition, with points on cell edges, several per cell and outside the grid."""
    from aerocal.products.dsm import _cell_medians

    rng = np.random.default_rng(seed)
    west, north, cell, shape = 100.0, 500.0, 0.5, (40, 60)
    e = np.r_[rng.uniform(95.0, 135.0, 6000), west + cell * rng.integers(0, 60, 200)]  # some on cell edges
    n = np.r_[rng.uniform(475.0, 505.0, 6000), north - cell * rng.integers(0, 40, 200)]
    z = rng.normal(10.0, 3.0, len(e))
    heights, counts = _cell_medians(np.column_stack([e, n, z]), west, north, cell, shape)
    c, r = np.floor((e - west) / cell).astype(int), np.floor((north - n) / cell).astype(int)
    inside = (c >= 0) & (c < shape[1]) & (r >= 0) & (r < shape[0])
    assert (~inside).sum() > 500, f"seed {seed}: too few points outside the grid to test"
    want = np.full(shape, np.nan)
    want_counts = np.zeros(shape, dtype=int)
    keys = r[inside] * shape[1] + c[inside]
    for k in np.unique(keys):
        want.flat[k] = np.median(z[inside][keys == k])
        want_counts.flat[k] = np.count_nonzero(keys == k)
    assert np.array_equal(counts, want_counts), f"seed {seed}"
    assert np.array_equal(np.isnan(heights), np.isnan(want)), f"seed {seed}"
    assert np.allclose(heights[np.isfinite(want)], want[np.isfinite(want)], rtol=0, atol=1e-12), f"seed {seed}"


def test_a_grids_heights_in_one_pass_are_its_bilinear_heights_to_the_bit():
    """Dsm.heights_on (one compiled pass over a grid's rows and columns, what DSM comparisons use) gives the bits
    of Dsm.height_at, NaN cells and extended edges included; compare_dems gives the same figures with it as with
    the reference's height_at passed as a callable."""
    from aerocal.assess import compare_dems

    rng = np.random.default_rng(1)
    heights = rng.normal(100, 5, (130, 90)).astype(np.float32)
    heights[rng.random(heights.shape) < 0.05] = np.nan
    dem = Dsm(heights=heights, west=1000.0, north=5000.0, cell_m=0.5, crs="EPSG:32633")
    grid = rng.normal(100, 5, (30, 20)).astype(np.float32)
    grid[rng.random(grid.shape) < 0.05] = np.nan
    ref = Dsm(heights=grid, west=1010.0, north=4990.0, cell_m=2.0, crs="EPSG:32633")  # dem reaches beyond it
    E, N = dem.cell_centres()
    assert np.array_equal(ref.heights_on(E[0], N[:, 0]), ref.height_at(E, N), equal_nan=True)
    mask = rng.random(heights.shape) < 0.8
    a, b = compare_dems(dem, ref, mask=mask), compare_dems(dem, ref.height_at, mask=mask)
    assert (a.n, a.mean, a.median, a.nmad) == (b.n, b.mean, b.median, b.nmad) and a.n > 1000
    assert np.array_equal(a.difference, b.difference, equal_nan=True)


def test_the_bulk_extent_of_a_large_cloud_comes_from_a_sample_within_its_quantiles():
    """A cloud of millions of points: the extent from every k-th point is the whole cloud's to a fraction of a
    cell, and a few points far off do not stretch it."""
    from aerocal.products.dsm import bulk_extent

    seed = 29
    rng = np.random.default_rng(seed)
    xy = rng.uniform([1000.0, 2000.0], [3000.0, 3000.0], (3_000_000, 2))
    xy[:100] = 1e6  # a handful far off
    lo, hi = bulk_extent(xy)
    full_lo, full_hi = bulk_extent(xy, max_points=len(xy))
    assert np.abs(lo - full_lo).max() < 0.5 and np.abs(hi - full_hi).max() < 0.5, (seed, lo, hi, full_lo, full_hi)
    assert np.allclose(lo, [1000.0, 2000.0], atol=2.0) and np.allclose(hi, [3000.0, 3000.0], atol=2.0), (seed, lo, hi)


@pytest.mark.parametrize("seed", [0, 1])
def test_few_cells_outside_the_hull_take_the_same_nearest_height_from_the_rims_tree(seed, monkeypatch):
    """Where few cells lie outside the data's hull, the nearest data cell comes from a k-d tree of the holes' rims:
    the height the exact transform gives, but where two data cells are equally near."""
    from scipy.spatial import cKDTree

    import aerocal.products.dsm as dsm_module

    rng = np.random.default_rng(seed)
    heights = 100.0 + rng.normal(0.0, 2.0, (160, 140))
    has = rng.random(heights.shape) < 0.8
    for r, c in ((0, 0), (0, -4), (-4, 0), (-4, -4)):  # the corners cut off: cells outside the hull
        has[r:r + 4 if r >= 0 else None, c:c + 4 if c >= 0 else None] = False
    hull_outside = 4 * 6  # about: the triangles cut each 4 x 4 corner along its diagonal
    assert hull_outside * dsm_module.NEAREST_QUERY_CELLS < has.size, "the case is the k-d tree's"
    tree = dsm_module.fill_holes(heights.copy(), has)
    monkeypatch.setattr(dsm_module, "NEAREST_QUERY_CELLS", has.size)  # every query too dear: the transform
    exact = dsm_module.fill_holes(heights.copy(), has)
    assert np.isfinite(tree).all(), f"seed {seed}"
    differ = np.argwhere(tree != exact)
    known = np.argwhere(has)
    d, _ = cKDTree(known).query(differ, k=2)
    assert np.allclose(d[:, 0], d[:, 1]), f"seed {seed}: a cell took a data cell that is not nearest"
