"""Simulated scenes: seeded, heights consistent with the grid, textures in physical ranges, targets."""

from __future__ import annotations

import numpy as np
import pytest

from aerocal.simulate.scene import (
    CLASS_GROUND,
    CLASS_ROOF,
    CLASS_VEGETATION,
    SceneConfig,
    make_scene,
)

SEED = 20240611
SMALL_CITY = SceneConfig(width_m=400.0, height_m=300.0, building_density=0.3, vegetation_density=0.1)


@pytest.fixture(scope="module")
def city():
    return make_scene(SMALL_CITY, seed=SEED)


def test_same_seed_same_scene_other_seed_differs(city):
    again = make_scene(SMALL_CITY, seed=SEED)
    other = make_scene(SMALL_CITY, seed=SEED + 1)
    assert np.array_equal(city.dsm, again.dsm), f"seed {SEED}: DSM not reproducible"
    assert np.array_equal(city.thermal_base, again.thermal_base), f"seed {SEED}: texture not reproducible"
    assert np.array_equal(city.classes, again.classes)
    assert not np.array_equal(city.dsm, other.dsm), f"seeds {SEED} and {SEED + 1} gave the same DSM"


def test_grid_layout_and_bounds(city):
    assert city.dsm.shape == (300, 400) and city.dsm.dtype == np.float32
    assert city.classes.dtype == np.uint8
    assert city.bounds() == (500000.0, 4_900_000.0, 500400.0, 4_900_300.0)


def test_height_at_matches_dsm_at_cell_centres(city):
    rng = np.random.default_rng(SEED)
    rows = rng.integers(0, city.shape[0], 500)
    cols = rng.integers(0, city.shape[1], 500)
    e, n = city.cell_centres(rows, cols)
    h = city.height_at(e, n)
    np.testing.assert_allclose(h, city.dsm[rows, cols], atol=1e-4, err_msg=f"seed {SEED}")
    # row 0 is the northern edge: the north-west cell centre is (origin_e + 0.5, origin_n + 299.5)
    assert city.height_at(np.array([500000.5]), np.array([4_900_299.5]))[0] == pytest.approx(city.dsm[0, 0])


def test_height_at_is_bilinear_between_centres(city):
    e0, n0 = city.cell_centres(np.array([100]), np.array([200]))
    e = e0 + 0.25
    n = n0 - 0.5  # a quarter cell east, half a cell south (towards row 101)
    d = city.dsm.astype(float)
    expected = (0.75 * 0.5 * d[100, 200] + 0.25 * 0.5 * d[100, 201]
                + 0.75 * 0.5 * d[101, 200] + 0.25 * 0.5 * d[101, 201])
    assert city.height_at(e, n)[0] == pytest.approx(expected, abs=1e-4)


def test_city_content(city):
    frac = np.bincount(city.classes.ravel(), minlength=4) / city.classes.size
    assert 0.2 < frac[CLASS_ROOF] < 0.4, f"seed {SEED}: roof fraction {frac[CLASS_ROOF]:.2f}"
    veg = frac[CLASS_VEGETATION]
    assert 0.03 < veg < 0.2, f"seed {SEED}: vegetation fraction {veg:.2f}"
    roof = city.classes == CLASS_ROOF
    above = (city.dsm - city.ground)[roof]
    assert np.median(above) > 6.0, f"seed {SEED}: roofs only {np.median(above):.1f} m above ground"
    ground = city.classes == CLASS_GROUND
    np.testing.assert_array_equal(city.dsm[ground], city.ground[ground])


def test_ground_height_ignores_buildings(city):
    rows, cols = np.nonzero(city.classes == CLASS_ROOF)
    e, n = city.cell_centres(rows[:200], cols[:200])
    assert np.all(city.height_at(e, n) > city.ground_height_at(e, n) + 3.0)


def test_thermal_texture_ranges_and_contrast(city):
    rng = np.random.default_rng(SEED)
    e0, n0, e1, n1 = city.bounds()
    e = rng.uniform(e0, e1, 20000)
    n = rng.uniform(n0, n1, 20000)
    t = city.thermal_at(e, n)
    assert 270.0 < t.min() and t.max() < 310.0, f"seed {SEED}: temperatures {t.min():.1f}-{t.max():.1f} K"
    cls = city.class_at(e, n)
    roofs = t[cls == CLASS_ROOF].mean()
    veg = t[cls == CLASS_VEGETATION].mean()
    assert roofs > veg + 2.0, f"seed {SEED}: roofs {roofs:.1f} K not warmer than vegetation {veg:.1f} K"
    # fine texture: neighbours 0.5 m apart differ (SIFT needs texture), but by a fraction of a kelvin
    d = city.thermal_at(e + 0.5, n) - t
    med = np.median(np.abs(d))
    assert 0.05 < med < 1.5, f"seed {SEED}: median 0.5 m gradient {med:.3f} K"
    rgb = city.rgb_at(e, n)
    assert rgb.shape == (20000, 3) and rgb.min() >= 0.0 and rgb.max() <= 255.0 and rgb.std() > 10.0


def test_flat_scene_is_flat():
    scene = make_scene(SceneConfig(width_m=200.0, height_m=150.0, flat=True, terrain_mean_m=42.0), seed=3)
    assert np.all(scene.dsm == 42.0)
    assert not np.any(scene.classes == CLASS_ROOF)
    assert scene.thermal_base.std() > 0.5  # still textured


def test_targets_are_painted(city):
    pos = city.open_ground_positions(3, np.random.default_rng(SEED), clearance_m=6.0)
    scene = city.place_targets(pos, radius_m=1.0)
    assert np.all(city.class_at(pos[:, 0], pos[:, 1]) == CLASS_GROUND)
    t_centre = scene.thermal_at(pos[:, 0], pos[:, 1])
    t_square = scene.thermal_at(pos[:, 0] + 1.5, pos[:, 1] - 1.5)
    t_out = scene.thermal_at(pos[:, 0] + 3.5, pos[:, 1])
    np.testing.assert_allclose(t_centre, SMALL_CITY.target_hot_k)
    np.testing.assert_allclose(t_square, SMALL_CITY.target_cold_k)
    np.testing.assert_allclose(t_out, city.thermal_at(pos[:, 0] + 3.5, pos[:, 1]))
    assert np.all(scene.rgb_at(pos[:, 0], pos[:, 1]) == SMALL_CITY.target_bright)
    # anti-aliased edge: on the disc's rim a sample with a footprint sees half disc, half square
    rim = scene.thermal_at(pos[:, 0] + 1.0, pos[:, 1], footprint_m=0.2)
    np.testing.assert_allclose(rim, 0.5 * (SMALL_CITY.target_hot_k + SMALL_CITY.target_cold_k))
    xyz = scene.target_points()
    np.testing.assert_allclose(xyz[:, 2], city.height_at(pos[:, 0], pos[:, 1]))
    with pytest.raises(ValueError, match="overlap"):
        scene.place_targets(pos[:1] + 1.0, radius_m=1.0)


def _hash_uniform_numpy(ix: np.ndarray, iy: np.ndarray, salt: int) -> np.ndarray:
    """The lattice hash as numpy wrote it before it was compiled: numpy's uint32 wraps."""
    with np.errstate(over="ignore"):
        h = (ix.astype(np.uint32) * np.uint32(0x8DA6B343)) ^ (iy.astype(np.uint32) * np.uint32(0xD8163841))
        h ^= np.uint32(salt & 0xFFFFFFFF) * np.uint32(0xCB1AB31F)
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x85EBCA6B)
        h ^= h >> np.uint32(13)
        h *= np.uint32(0xC2B2AE35)
        h ^= h >> np.uint32(16)
    return h.astype(np.float64) * (2.0 / 4294967295.0) - 1.0


def _value_noise_numpy(x: np.ndarray, y: np.ndarray, salt: int) -> np.ndarray:
    fx, fy = np.floor(x), np.floor(y)
    tx, ty = x - fx, y - fy
    tx, ty = tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty)
    ix, iy = fx.astype(np.int64), fy.astype(np.int64)
    v00, v10 = _hash_uniform_numpy(ix, iy, salt), _hash_uniform_numpy(ix + 1, iy, salt)
    v01, v11 = _hash_uniform_numpy(ix, iy + 1, salt), _hash_uniform_numpy(ix + 1, iy + 1, salt)
    a, b = v00 + tx * (v10 - v00), v01 + tx * (v11 - v01)
    return a + ty * (b - a)


def test_compiled_texture_detail_is_the_numpy_value_noise_to_the_bit():
    """The texture's compiled value noise: the same lattice hash (negative lattice coordinates and salts past 32
    bits included) and the same footprint weights as numpy arrays give it, every bit."""
    from aerocal.simulate.noise_kernels import detail

    rng = np.random.default_rng(SEED)
    e = rng.uniform(-3000.0, 3000.0, 20000)
    n = rng.uniform(-3000.0, 3000.0, 20000)
    fp = rng.uniform(0.0, 3.0, 20000)
    spacings = np.array([0.25, 0.5, 1.0, 2.0])
    salts = np.array([7919 * 2**33 + k for k in range(4)], dtype=np.int64)
    expected = np.zeros(len(e))
    for spacing, salt in zip(spacings, salts, strict=True):
        weight = np.clip(2.0 - 2.0 * fp / spacing, 0.0, 1.0)
        expected += weight * _value_noise_numpy(e / spacing, n / spacing, int(salt))
    got = detail(e, n, fp, spacings, salts)
    assert np.array_equal(got, expected), f"seed {SEED}: max difference {np.abs(got - expected).max():.3g}"
    assert np.abs(got).max() <= len(spacings) and got.std() > 0.3
