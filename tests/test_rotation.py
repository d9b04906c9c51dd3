"""Rodrigues rotations (eqs. 1-3) against OpenCV, round trips and exact derivatives."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import acm_rs

finite = st.floats(-7.0, 7.0, allow_nan=False)


def test_matches_cv2_rodrigues(rng):
    r = rng.normal(size=(200, 3)) * rng.uniform(0, 3, size=(200, 1))
    r[0] = 0.0
    r[1] = [np.pi, 0, 0]
    r[2] = [1e-9, -2e-9, 0]
    ours = acm_rs.rodrigues(r)
    for v, m in zip(r, ours, strict=True):
        ref, _ = cv2.Rodrigues(v.reshape(3, 1))
        np.testing.assert_allclose(m, ref, atol=1e-12)


def test_inverse_matches_cv2(rng):
    r = rng.normal(size=(100, 3))
    r *= rng.uniform(0, np.pi - 1e-3, size=(100, 1)) / np.linalg.norm(r, axis=1, keepdims=True)
    back = acm_rs.rodrigues_inverse(acm_rs.rodrigues(r))
    np.testing.assert_allclose(back, r, atol=1e-10)
    for v in r[:20]:
        ref, _ = cv2.Rodrigues(acm_rs.rodrigues(v))
        np.testing.assert_allclose(
            acm_rs.rodrigues_inverse(acm_rs.rodrigues(v)), ref.ravel(), atol=1e-9
        )


def test_leading_shapes_are_kept(rng):
    r = rng.normal(size=(4, 5, 3))
    m = acm_rs.rodrigues(r)
    assert m.shape == (4, 5, 3, 3)
    assert acm_rs.rodrigues_inverse(m).shape == (4, 5, 3)
    assert acm_rs.rodrigues(np.zeros(3)).shape == (3, 3)
    assert acm_rs.rodrigues_jacobian(r).shape == (4, 5, 3, 3, 3)


@pytest.mark.parametrize("theta", [0.0, 1e-10, 1e-5, 0.049, 0.051, 1.0, 3.0, np.pi - 1e-6])
def test_jacobian_vs_central_differences(theta):
    axis = np.array([0.48, -0.6, 0.64])
    r = axis * theta
    jac = acm_rs.rodrigues_jacobian(r)
    h = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (acm_rs.rodrigues(r + e) - acm_rs.rodrigues(r - e)) / (2 * h)
        np.testing.assert_allclose(jac[..., k], fd, atol=1e-8)


def test_near_pi_and_zero_round_trip():
    axis = np.array([0.0, 0.6, -0.8])
    for theta in [0.0, 1e-13, 1e-8, np.pi - 1e-9, np.pi]:
        m = acm_rs.rodrigues(axis * theta)
        np.testing.assert_allclose(acm_rs.rodrigues(acm_rs.rodrigues_inverse(m)), m, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(arrays(np.float64, (3,), elements=finite))
def test_properties(r):
    m = acm_rs.rodrigues(r)
    np.testing.assert_allclose(m.T @ m, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(m) - 1) < 1e-12
    back = acm_rs.rodrigues_inverse(m)
    assert np.linalg.norm(back) <= np.pi + 1e-9
    np.testing.assert_allclose(acm_rs.rodrigues(back), m, atol=1e-10)


def test_bad_input():
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        acm_rs.rodrigues(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="NaN"):
        acm_rs.rodrigues([np.nan, 0, 0])
    with pytest.raises(ValueError, match="not a rotation"):
        acm_rs.rodrigues_inverse(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="not a rotation"):
        acm_rs.rodrigues_inverse(2 * np.eye(3))
