"""Rotation conventions, CRS helpers and similarity transforms."""

import numpy as np
import pytest

from aerocal import geometry as g


def test_zero_angles_are_a_nadir_camera_with_north_up_in_every_convention():
    nadir = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # x east, y south (image down), z down
    assert np.allclose(g.opk_to_R_cw(0, 0, 0), nadir)
    assert np.allclose(g.dji_gimbal_to_R_cw(0, -90, 0), nadir)
    assert np.allclose(g.body_rpy_to_R_cw(0, 0, 0), nadir)


def test_heading_east_turns_the_image_top_to_the_east():
    R = g.nadir_R_cw(90.0)
    up_in_image = -R[1]  # world direction of the image's -y axis
    assert np.allclose(up_in_image, [1, 0, 0], atol=1e-12)


@pytest.mark.parametrize("angles", [(2.0, -3.0, 40.0), (-10.0, 5.0, -170.0), (0.3, 0.1, 90.0)])
def test_conventions_round_trip(angles):
    R = g.opk_to_R_cw(*angles)
    assert np.allclose(g.R_cw_to_opk(R), angles)
    R = g.body_rpy_to_R_cw(*angles)
    assert np.allclose(g.R_cw_to_body_rpy(R), angles)
    gimbal = (angles[0], -90 + angles[1], angles[2])
    R = g.dji_gimbal_to_R_cw(*gimbal)
    assert np.allclose(g.dji_gimbal_to_R_cw(*g.R_cw_to_dji_gimbal(R)), R, atol=1e-12)


def test_positive_roll_swings_a_belly_camera_to_the_left():
    # banking right (right wing down, heading north) turns the belly, and a nadir camera, to the west
    R = g.body_rpy_to_R_cw(5.0, 0.0, 0.0)
    view = R[2]  # camera z in the world
    assert view[0] == pytest.approx(-np.sin(np.radians(5.0))) and view[2] < 0


def test_utm_zone_and_projection():
    assert g.utm_crs_for(11.34, 44.49) == "EPSG:32632"
    assert g.utm_crs_for(-83.0, 40.0) == "EPSG:32617"
    assert g.utm_crs_for(-47.9, -15.8) == "EPSG:32723"
    x, y = g.lonlat_to_projected(9.0, 0.0, "EPSG:32632")
    assert x == pytest.approx(500000.0, abs=1e-6) and y == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError, match="outside"):
        g.utm_crs_for(0.0, 400.0)
    with pytest.raises(ValueError, match="not projected"):
        g.validate_crs("EPSG:4326")
    with pytest.raises(ValueError, match="unknown CRS"):
        g.validate_crs("EPSG:999999")


def test_similarity_recovers_seven_parameters():
    rng = np.random.default_rng(11)
    src = rng.normal(0, 100, (30, 3))
    R = g.small_rotation(np.array([0.1, -0.2, 0.3]))
    dst = 1.0003 * src @ R.T + np.array([10.0, -5.0, 2.0])
    sim = g.estimate_similarity(src, dst)
    assert sim.scale == pytest.approx(1.0003, rel=1e-12)
    assert np.allclose(sim.R, R) and np.allclose(sim.apply(src), dst)
    assert np.allclose(sim.inverse().apply(dst), src)
    with pytest.raises(ValueError, match="collinear"):
        g.estimate_similarity(np.outer(np.arange(5.0), [1, 1, 1]), np.outer(np.arange(5.0), [1, 2, 3]))


def test_quaternions_scalar_first():
    R = g.opk_to_R_cw(3, 4, 5)
    q = g.quat_wxyz_from_matrix(R)
    assert q[0] > 0 and np.isclose(np.linalg.norm(q), 1)
    assert np.allclose(g.matrix_from_quat_wxyz(q), R)
