"""Camera model: projection, un-projection, pycolmap conversion, thermal IO models."""

import cv2
import numpy as np
import pytest

from aerocal.camera import (
    Camera,
    LinearThermalModel,
    PolynomialThermalModel,
    SimilarityThermalModel,
    correct_measurements,
    from_pycolmap,
    thermal_model_from_dict,
    to_pycolmap,
)

STRONG = Camera(width=640, height=480, f=500.0, cx=322.3, cy=236.8, k1=-0.28, k2=0.09, k3=-0.012,
                p1=1.2e-3, p2=-8e-4, b1=0.7, b2=0.3)


def _border_and_corner_pixels(cam: Camera) -> np.ndarray:
    u = np.linspace(0, cam.width, 33)
    v = np.linspace(0, cam.height, 25)
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


def test_project_unproject_agree_at_corners_of_strongly_distorted_camera():
    uv = _border_and_corner_pixels(STRONG)
    xy = STRONG.unproject(uv)
    back = STRONG.project(np.column_stack([xy * 7.0, np.full(len(xy), 7.0)]))
    err = np.abs(back - uv).max()
    assert err < 1e-6, f"round trip error {err:.2e} px"
    corners = STRONG.corners()
    assert np.abs(STRONG.project(np.column_stack([STRONG.unproject(corners), np.ones(4)])) - corners).max() < 1e-6


def test_undistort_agrees_with_opencv():
    cam = STRONG.replace(b1=0.0, b2=0.0)
    uv = _border_and_corner_pixels(cam)
    K = np.array([[cam.f, 0, cam.cx - 0.5], [0, cam.f, cam.cy - 0.5], [0, 0, 1]])
    dist = np.array([cam.k1, cam.k2, cam.p2, cam.p1, cam.k3])  # OpenCV order, p1/p2 swapped
    ocv = cv2.undistortPoints((uv - 0.5).reshape(-1, 1, 2), K, dist,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14))
    ours = cam.unproject(uv)
    # OpenCV's fixed-point iteration stalls in the strongest corners; compare where it converged
    ocv_xy = ocv.reshape(-1, 2)
    ocv_back = cam.project(np.column_stack([ocv_xy, np.ones(len(ocv_xy))]))
    converged = np.abs(ocv_back - uv).max(axis=1) < 1e-6
    assert converged.mean() > 0.8
    assert np.abs(ours[converged] - ocv_xy[converged]).max() * cam.f < 1e-6


def test_param_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.5, 0.5, (20, 2))
    J = STRONG.param_jacobian(xy)
    p = STRONG.params()
    for i in range(len(p)):
        h = 1e-6 * max(1.0, abs(p[i]))
        up = STRONG.with_params(np.where(np.arange(len(p)) == i, p + h, p))
        dn = STRONG.with_params(np.where(np.arange(len(p)) == i, p - h, p))
        num = (up.normalised_to_pixels(up.distort(xy)) - dn.normalised_to_pixels(dn.distort(xy))) / (2 * h)
        assert np.allclose(J[:, :, i], num, rtol=1e-5, atol=1e-6), f"parameter {i}"


def test_pycolmap_round_trip_and_projection_agree():
    cam = STRONG.replace(b2=0.0)
    pc = to_pycolmap(cam)
    assert pc.model.name == "FULL_OPENCV"
    back = from_pycolmap(pc)
    assert np.allclose(back.params(), cam.params(), atol=1e-12)
    uv = _border_and_corner_pixels(cam)
    xy = cam.unproject(uv)
    colmap_uv = np.array(pc.img_from_cam(np.column_stack([xy, np.ones(len(xy))])))
    assert np.abs(colmap_uv[:, :2] - uv).max() < 1e-6, "conventions (p1/p2, pixel origin) must match COLMAP's"


def test_pycolmap_refuses_skew_unless_dropped():
    with pytest.raises(ValueError, match="skew"):
        to_pycolmap(STRONG)
    assert to_pycolmap(STRONG, drop_skew=True).params[0] == pytest.approx(STRONG.f + STRONG.b1)


def test_linear_thermal_model_correction_is_exact():
    base = STRONG
    model = LinearThermalModel(t0=20.0, df_dt=0.075, dcx_dt=0.02, dcy_dt=-0.01, valid_range=(15, 35))
    hot = model.camera_at(base, 32.0)
    assert hot.f == pytest.approx(base.f + 0.9)
    rays = base.unproject(_border_and_corner_pixels(base))
    pts = np.column_stack([rays, np.ones(len(rays))])
    seen_hot = hot.project(pts)
    corrected = correct_measurements(base, seen_hot, 32.0, model)
    assert np.abs(corrected - base.project(pts)).max() < 1e-9
    assert model.check_range([10.0, 30.0]) is not None and model.check_range([16, 30]) is None
    assert thermal_model_from_dict(model.to_dict()) == model


def test_similarity_thermal_model_recovers_a_known_similarity():
    rng = np.random.default_rng(5)
    centre = (320.0, 240.0)
    ref = rng.uniform(0, 640, (200, 2))
    # observed = reference scaled by 1+1e-4 and rotated 1e-4 rad about the centre, shifted by (0.2, -0.1)
    k, th = 1 + 1e-4, 1e-4
    c = np.asarray(centre)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    obs = c + np.array([0.2, -0.1]) + k * (ref - c) @ R.T
    tx, ty, s, a = SimilarityThermalModel.fit_one(obs, ref, centre)
    model = SimilarityThermalModel((20.0, 30.0), (0.0, tx), (0.0, ty), (1.0, s), (0.0, a), centre)
    assert np.abs(model.correct(obs, 30.0) - ref).max() < 1e-9
    assert np.abs(model.correct(ref, 20.0) - ref).max() < 1e-12


def test_polynomial_thermal_model_fits_focal_drift():
    rng = np.random.default_rng(9)
    cam = Camera.from_mm(640, 480, 39.2, 23.5)
    lin = LinearThermalModel(t0=20.0, df_dt=0.2)
    uv = rng.uniform(0, [640, 480], (500, 2))
    temps = rng.uniform(10, 40, 500)
    corrected = lin.correct(cam, uv, temps)
    disp = uv - corrected
    poly = PolynomialThermalModel.fit(uv, temps, disp, t0=20.0, centre=(cam.cx, cam.cy), norm=320.0, degree=2)
    assert np.abs(poly.correct(uv, temps) - corrected).max() < 1e-3
    assert thermal_model_from_dict(poly.to_dict()).coefficients == poly.coefficients
