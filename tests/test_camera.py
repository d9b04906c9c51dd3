"""Camera model (eqs. 4-6) against cv2.projectPoints, exact Jacobians, bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import acm_rs


def cv2_project(cam: acm_rs.Camera, pts: np.ndarray) -> np.ndarray:
    px, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), cam.rvec, cam.tvec, cam.matrix, cam.dist)
    return px.reshape(-1, 2)


def points_in_view(rng, n=300):
    return rng.uniform(-8, 8, size=(n, 3))


def test_paper_model_matches_opencv(rng, rig):
    # dist = [k1, k2, 0, 0, 0]: the paper's eq. 5.
    cam = acm_rs.Camera(rig[0].matrix, [-0.2, 0.05], rig[0].rvec, rig[0].tvec)
    np.testing.assert_allclose(cam.dist, [-0.2, 0.05, 0, 0, 0])
    pts = points_in_view(rng)
    np.testing.assert_allclose(cam.project(pts), cv2_project(cam, pts), atol=1e-7)


def test_full_opencv_model_matches(rng, rig):
    pts = points_in_view(rng)
    for cam in rig:
        np.testing.assert_allclose(cam.project(pts), cv2_project(cam, pts), atol=1e-7)


def test_rig_projection_shape_and_nan_passthrough(rng, rig):
    pts = rng.uniform(-5, 5, size=(7, 5, 3))
    pts[2, 3] = np.nan
    px = rig.project(pts)
    assert px.shape == (4, 7, 5, 2)
    assert np.all(np.isnan(px[:, 2, 3]))
    np.testing.assert_allclose(px[1, 0], rig[1].project(pts[0]))


def test_points_behind_camera_are_reported(rig):
    cam = rig[0]
    behind = cam.center - 10 * (np.zeros(3) - cam.center) / np.linalg.norm(cam.center)
    front = np.zeros(3)
    px = cam.project(np.stack([behind, front]))
    assert np.all(np.isnan(px[0])) and np.all(np.isfinite(px[1]))
    np.testing.assert_array_equal(cam.in_front(np.stack([behind, front])), [False, True])
    pix, dp, dc = cam.project_jacobian(behind)
    assert np.isnan(pix).all() and np.isnan(dp).all() and np.isnan(dc).all()


def test_jacobians_vs_central_differences(rng, rig):
    pts = rng.uniform(-5, 5, size=(6, 3))
    h = 1e-6
    for cam in rig:
        _, dp, dc = cam.project_jacobian(pts)
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            fd = (cam.project(pts + e) - cam.project(pts - e)) / (2 * h)
            np.testing.assert_allclose(dp[..., k], fd, rtol=1e-6, atol=1e-5)
        for k in range(15):
            step = h * max(1.0, abs(cam.params[k]))
            pp, pm = cam.params.copy(), cam.params.copy()
            pp[k] += step
            pm[k] -= step
            fd = (
                acm_rs.Camera.from_params(pp).project(pts)
                - acm_rs.Camera.from_params(pm).project(pts)
            ) / (2 * step)
            np.testing.assert_allclose(
                dc[..., k], fd, rtol=1e-5, atol=1e-4, err_msg=acm_rs.PARAM_NAMES[k]
            )


def test_params_round_trip_and_dict(rig):
    cam = rig[2]
    again = acm_rs.Camera.from_params(cam.params, cam.size, cam.name)
    np.testing.assert_array_equal(again.params, cam.params)
    d = cam.to_dict()
    assert set(d) >= {"name", "matrix", "distortions", "rotation", "translation", "size"}
    np.testing.assert_array_equal(acm_rs.Camera.from_dict(d).params, cam.params)
    moved = rig.set_params(rig.get_params() + 0.01)
    assert moved.names == rig.names and moved is not rig
    np.testing.assert_allclose(moved.get_params(), rig.get_params() + 0.01)
    np.testing.assert_allclose(cam.rotation_matrix @ cam.center + cam.tvec, 0, atol=1e-12)


def test_bad_input(rig):
    k = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
    with pytest.raises(ValueError, match="2 .* or 5"):
        acm_rs.Camera(k, [0.1, 0.2, 0.3], np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="focal lengths must be positive"):
        acm_rs.Camera(np.diag([-1.0, 1.0, 1.0]), [0, 0], np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        acm_rs.Camera(k, [0, 0], [np.nan, 0, 0], np.zeros(3))
    skewed = k.copy()
    skewed[0, 1] = 3.0  # a skew is part of the model (tests/test_camera_skew.py) ...
    assert acm_rs.Camera(skewed, [0, 0], np.zeros(3), np.zeros(3)).skew == 3.0
    lower = k.copy()
    lower[1, 0] = 3.0  # ... a lower-triangle entry is not (a MATLAB K, transposed)
    with pytest.raises(ValueError, match="matrix must be"):
        acm_rs.Camera(lower, [0, 0], np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        rig.project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="unique"):
        acm_rs.CameraRig([rig[0], rig[0]])
    with pytest.raises(ValueError, match="at least one camera"):
        acm_rs.CameraRig([])
    with pytest.raises(KeyError, match="no camera named"):
        rig["nope"]
