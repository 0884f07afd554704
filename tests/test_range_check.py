"""The surface against a laser range finder on the camera's axis: the range through the principal point to a known
surface, a wrong surface seen as a wrong range, and axes off the measured cells left out."""

import numpy as np
import pytest

from aerocal.camera import Camera
from aerocal.geometry import opk_to_R_cw
from aerocal.products.dsm import Dsm
from aerocal.products.mosaic import FrameGeometry
from aerocal.products.range_check import axis_range, laser_range_check

CAMERA = Camera(width=640, height=512, f=1125.0, cx=330.0, cy=250.0)


def _slope_dsm(offset_m: float = 0.0) -> Dsm:
    """A 400 m square of 0.5 m cells, the plane h = 20 + 0.1 E + offset (a 5.7-degree slope up to the east)."""
    cell = 0.5
    e = -200 + (np.arange(800) + 0.5) * cell
    heights = np.broadcast_to(20.0 + 0.1 * e + offset_m, (800, 800)).astype(np.float32)
    return Dsm(heights=heights.copy(), west=-200.0, north=200.0, cell_m=cell, crs="EPSG:32633",
               distance_m=np.zeros((800, 800), np.float32))


def _frame(image_id: int, omega_deg: float, phi_deg: float, C=(10.0, -5.0, 120.0)) -> FrameGeometry:
    R = opk_to_R_cw(omega_deg, phi_deg, 0.0)
    return FrameGeometry(image_id, CAMERA, R, np.asarray(C, dtype=float))


def _true_range(frame: FrameGeometry) -> float:
    """The axis's range to the plane in closed form: C + t d on h = 20 + 0.1 E."""
    xy = CAMERA.unproject(np.array([[CAMERA.cx, CAMERA.cy]]))[0]
    d = np.array([xy[0], xy[1], 1.0]) @ frame.R_cw
    d /= np.linalg.norm(d)
    C = frame.C
    return float((20.0 + 0.1 * C[0] - C[2]) / (d[2] - 0.1 * d[0]))


@pytest.mark.parametrize("omega, phi", [(0.0, 0.0), (-4.0, 3.0), (3.0, -5.0)])
def test_the_axis_range_is_the_distance_to_the_surface_through_the_principal_point(omega, phi):
    frame = _frame(1, omega, phi)
    truth = _true_range(frame)
    assert 90 < truth < 110, truth  # the axis points down
    assert axis_range(frame, _slope_dsm(), None) == pytest.approx(truth, abs=0.02)


def test_a_surface_one_metre_high_reads_one_metre_short_and_axes_off_the_measured_cells_are_left_out():
    frames = [_frame(i, 2 * np.sin(i), 2 * np.cos(i), C=(10.0 * i - 50, 4.0 * i, 120.0)) for i in range(12)]
    laser = {f.image_id: _true_range(f) + 0.05 * ((-1) ** f.image_id) for f in frames}
    high = _slope_dsm(offset_m=1.0)
    measured = np.ones(high.shape, bool)
    E, _ = high.cell_centres()
    measured[:, E[0] > 45.0] = False  # where the last frames look: a filled area
    check = laser_range_check(frames, laser, high, measured)
    assert check is not None and check.unmatched == 2 and len(check.image_ids) == 10, check
    # the surface is 1 m higher: the camera sees it 1 m sooner along a near-vertical axis
    assert check.median_m == pytest.approx(-1.0, abs=0.07), check.difference_m
    assert 0.0 < check.nmad_m < 0.15 and check.median_error_m < 0.1, (check.nmad_m, check.median_error_m)
    assert laser_range_check(frames, {}, high, measured) is None
    doc = check.to_json(gsd_m=0.1)
    assert doc["n"] == 10 and doc["unmatched"] == 2 and len(doc["images"]) == 10, doc
    # 1 m at a 0.1 m ground sample: beyond 2 GSD and twice the median's error; within 2 GSD at 1 m samples
    assert not doc["agrees"] and doc["verdict"].startswith("DISAGREES") and "1.0 m (1 % of the range) closer to" \
        in doc["verdict"], doc
    assert doc["median_relative"] == pytest.approx(-1.0 / np.median(check.laser_m), rel=0.1), doc
    assert check.agrees(gsd_m=1.0) and check.verdict(1.0).startswith("agrees"), check.verdict(1.0)


def test_the_flying_height_over_the_ground_is_the_cameras_height_above_it_under_them():
    from aerocal.products.range_check import flying_height_check

    frames = [_frame(i, 0.0, 0.0, C=(10.0 * i - 50, 4.0 * i, 120.0 + 0.2 * i)) for i in range(11)]
    ground = _slope_dsm()  # h = 20 + 0.1 E
    check = flying_height_check(frames, ground, recorded_m=98.0)
    # the middle frame: E 0, Z 121 -> 101 m above the ground
    assert check["frames"] == 11 and check["from_surface_m"] == pytest.approx(101.0, abs=0.01), check
    assert check["difference_m"] == pytest.approx(3.0, abs=0.01) and check["relative"] == pytest.approx(3 / 98)
    far = [_frame(0, 0.0, 0.0, C=(5000.0, 0.0, 120.0))]
    assert flying_height_check(far, ground, recorded_m=98.0) is None
