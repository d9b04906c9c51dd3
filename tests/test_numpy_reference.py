"""acm_rs forward kinematics (Alg. 1) and projection against the pure-NumPy reference.

The reference (``benches/numpy_reference.py``) is written independently of the Rust core; this
file adds a second, literal per-frame transcription of Alg. 1 (the double loop over bone pairs
``(i, j)``, with the tree rule of ``docs/models.md``: bone ``i``'s rotation moves bone ``j``
when ``j``'s end joint is ``i``'s end joint or below it) and checks the reference's
projection against OpenCV.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import acm_rs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benches"))
from bench_fk_projection import make_rig, random_poses  # noqa: E402
from numpy_reference import fk_plan, forward_np, project_np, rodrigues_np  # noqa: E402

N_POSES = 50
TOL_WORLD = 1e-9  # world units (cm)
TOL_PX = 1e-6  # pixels

MODELS = {"rat": acm_rs.models.rat, "mouse": acm_rs.models.mouse}


# -- a literal, slow transcription of Alg. 1 -----------------------------------------------
def _rodrigues_textbook(r: np.ndarray) -> np.ndarray:
    """``I + sin(theta) K + (1 - cos(theta)) K^2`` with ``K`` the unit-axis cross matrix."""
    theta = float(np.linalg.norm(r))
    if theta == 0.0:
        return np.eye(3)
    x, y, z = r / theta
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)


def _is_descendant(parents: np.ndarray, joint: int, ancestor: int) -> bool:
    """Whether ``joint`` is a (strict) descendant of ``ancestor``."""
    j = int(parents[joint])
    while j >= 0:
        if j == ancestor:
            return True
        j = int(parents[j])
    return False


def forward_literal(skeleton: acm_rs.Skeleton, t: np.ndarray, r: np.ndarray):
    """Alg. 1 for one pose, line by line: ``t (3,)``, ``r (n_bones, 3)`` -> joints, markers."""
    parents, bones = skeleton.parents, skeleton.bones
    rest, lengths = skeleton.rest_frames, skeleton.bone_lengths
    n_bones = len(bones)
    rot = [np.eye(3) for _ in range(n_bones)]  # line 2
    # lines 3-6, root first: does the rotation of bone i move end joint j_1?
    depth = [sum(1 for a in range(skeleton.n_joints) if _is_descendant(parents, e, a))
             for e in bones[:, 1]]  # fmt: skip
    for i in sorted(range(n_bones), key=lambda b: depth[b]):
        q_i = _rodrigues_textbook(r[i])
        for j in range(n_bones):
            if bones[j, 1] == bones[i, 1] or _is_descendant(parents, bones[j, 1], bones[i, 1]):
                rot[j] = q_i.T @ rot[j]
    rot = [rot[j].T @ rest[j] for j in range(n_bones)]  # lines 7-8
    joints = np.full((skeleton.n_joints, 3), np.nan)
    joints[np.flatnonzero(parents < 0)[0]] = t  # line 9
    pending = list(range(n_bones))
    while pending:  # lines 10-11, each bone once its start joint is known (any bone order)
        j = next(j for j in pending if np.all(np.isfinite(joints[bones[j, 0]])))
        pending.remove(j)
        joints[bones[j, 1]] = joints[bones[j, 0]] + rot[j][:, 2] * lengths[j]
    markers = np.array(  # lines 12-15
        [
            joints[j] + rot[b] @ v
            for j, b, v in zip(
                skeleton.marker_joints, skeleton.marker_bones, skeleton.marker_offsets, strict=True
            )
        ]
    )
    return joints, markers


# -- helpers --------------------------------------------------------------------------------
def large_poses(skeleton: acm_rs.Skeleton, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``t (n, 3)`` and ``r (n, n_bones, 3)`` with random axes and ``|r|`` up to 3 rad.

    The first pose is the rest pose; some bones get exactly zero or tiny rotations, and the
    last pose has every ``|r|`` equal to 3.
    """
    rng = np.random.default_rng(seed)
    t = rng.uniform(-20.0, 20.0, size=(n, 3))
    axes = rng.normal(size=(n, skeleton.n_bones, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    angle = rng.uniform(0.0, 3.0, size=(n, skeleton.n_bones, 1))
    angle[rng.uniform(size=angle.shape) < 0.1] = 0.0
    angle[rng.uniform(size=angle.shape) < 0.05] = 1e-7
    angle[0] = 0.0
    angle[-1] = 3.0
    return t, axes * angle


def assert_same_pixels(a: np.ndarray, b: np.ndarray, tol: float = TOL_PX) -> None:
    assert a.shape == b.shape
    np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
    ok = ~np.isnan(a)
    assert np.max(np.abs(a[ok] - b[ok]), initial=0.0) < tol


@pytest.fixture(scope="module", params=sorted(MODELS))
def model(request) -> acm_rs.Skeleton:
    return MODELS[request.param]()


# -- tests ----------------------------------------------------------------------------------
def test_models_are_root_first(model):
    """Bone index order is root-to-leaf, so "increasing index" is the Alg. 1 product order."""
    bones = model.bones
    end_index = {int(e): b for b, e in enumerate(bones[:, 1])}
    for b, (start, _) in enumerate(bones):
        assert start not in end_index or end_index[int(start)] < b


def test_rodrigues_matches_acm_rs():
    rng = np.random.default_rng(1)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate([[0.0, 1e-12, 1e-8, 1e-4, np.pi - 1e-9, np.pi], rng.uniform(0, 6, 194)])
    r = axes * angles[:, None]
    got = rodrigues_np(r)
    np.testing.assert_allclose(got, acm_rs.rodrigues(r), rtol=0, atol=1e-14)
    np.testing.assert_allclose(got @ got.transpose(0, 2, 1), np.broadcast_to(np.eye(3), got.shape),
                               rtol=0, atol=1e-14)  # fmt: skip
    for k in range(0, 200, 17):
        np.testing.assert_allclose(got[k], _rodrigues_textbook(r[k]), rtol=0, atol=1e-14)


def test_forward_matches_acm_rs(model):
    t, r = large_poses(model, N_POSES, seed=2)
    joints, markers = model.forward(t, r)
    ref_joints, ref_markers = forward_np(model, t, r)
    assert joints.shape == ref_joints.shape == (N_POSES, model.n_joints, 3)
    assert markers.shape == ref_markers.shape == (N_POSES, model.n_markers, 3)
    np.testing.assert_allclose(joints, ref_joints, rtol=0, atol=TOL_WORLD)
    np.testing.assert_allclose(markers, ref_markers, rtol=0, atol=TOL_WORLD)
    # The rest pose puts every joint at its rest position.
    rest_joints, rest_markers = model.rest_pose()
    j0, m0 = forward_np(model, t[:1], np.zeros((1, model.n_bones, 3)))
    np.testing.assert_allclose(j0[0] - t[0], rest_joints - rest_joints[0], rtol=0, atol=TOL_WORLD)
    np.testing.assert_allclose(m0[0] - t[0], rest_markers - rest_joints[0], rtol=0, atol=TOL_WORLD)


def test_literal_alg1_matches_reference_and_acm_rs(model):
    t, r = large_poses(model, N_POSES, seed=3)
    ref_joints, ref_markers = forward_np(model, t, r)
    acm_joints, acm_markers = model.forward(t, r)
    for f in range(N_POSES):
        joints, markers = forward_literal(model, t[f], r[f])
        np.testing.assert_allclose(ref_joints[f], joints, rtol=0, atol=TOL_WORLD)
        np.testing.assert_allclose(ref_markers[f], markers, rtol=0, atol=TOL_WORLD)
        np.testing.assert_allclose(acm_joints[f], joints, rtol=0, atol=TOL_WORLD)
        np.testing.assert_allclose(acm_markers[f], markers, rtol=0, atol=TOL_WORLD)


def test_literal_alg1_for_a_bone_order_that_is_not_root_first():
    """Joints listed leaf-first: bone 0 (a -> b) precedes its parent bone 1 (root -> a).

    The rotations still compose root to leaf (the skeleton's ``link_order``), in the
    reference, the literal transcription and acm_rs alike.
    """
    skeleton = acm_rs.Skeleton.from_rest_pose(
        ["b", "a", "c", "root"],
        [1, 3, 1, -1],
        np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 1.5], [0.5, 0.0, 2.5], [0.0, 0.0, 0.0]]),
        ["mb", "ma", "mc", "mroot"],
        ["b", "a", "c", "root"],
        np.array([[0.3, 0.0, 3.0], [0.0, 0.2, 1.5], [0.6, 0.1, 2.4], [0.1, 0.1, -0.2]]),
    )
    plan = fk_plan(skeleton)
    assert list(skeleton.link_order) != sorted(skeleton.link_order)
    t, r = large_poses(skeleton, 20, seed=10)
    ref_joints, ref_markers = forward_np(skeleton, t, r, plan=plan)
    acm_joints, acm_markers = skeleton.forward(t, r)
    for f in range(len(t)):
        joints, markers = forward_literal(skeleton, t[f], r[f])
        np.testing.assert_allclose(ref_joints[f], joints, rtol=0, atol=TOL_WORLD)
        np.testing.assert_allclose(ref_markers[f], markers, rtol=0, atol=TOL_WORLD)
        np.testing.assert_allclose(acm_joints[f], joints, rtol=0, atol=TOL_WORLD)
        np.testing.assert_allclose(acm_markers[f], markers, rtol=0, atol=TOL_WORLD)


def test_forward_with_other_lengths_and_offsets(model):
    """The reference reads lengths and offsets from the skeleton (``with_parameters``)."""
    rng = np.random.default_rng(4)
    other = model.with_parameters(
        bone_lengths=model.bone_lengths * rng.uniform(0.5, 1.5, model.n_bones),
        marker_offsets=model.marker_offsets + rng.normal(scale=0.5, size=(model.n_markers, 3)),
    )
    t, r = large_poses(other, N_POSES, seed=5)
    for got, ref in zip(other.forward(t, r), forward_np(other, t, r), strict=True):
        np.testing.assert_allclose(got, ref, rtol=0, atol=TOL_WORLD)


@pytest.mark.parametrize("block", [1, 7, 64, 10_000])
def test_forward_block_size_does_not_matter(block):
    skeleton = acm_rs.models.rat()
    t, r = large_poses(skeleton, N_POSES, seed=6)
    plan = fk_plan(skeleton)
    ref = forward_np(skeleton, t, r, plan=plan)
    got = forward_np(skeleton, t, r, plan=plan, block=block)
    for a, b in zip(ref, got, strict=True):  # equal up to the summation order of BLAS
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_projection_matches_acm_rs(model, rig):
    """Bench rig (k1, k2 only) and the conftest rig (full OpenCV distortion, z-up world)."""
    t, r = large_poses(model, N_POSES, seed=7)
    t *= 0.25  # keep the animal well inside both rigs (cameras 40-100 cm away)
    _, markers = model.forward(t, r)
    for cams in (make_rig(), rig):
        params = cams.get_params()
        got = cams.project(markers)
        assert got.shape == (len(cams), N_POSES, model.n_markers, 2)
        assert np.isfinite(got).all()
        assert_same_pixels(got, project_np(params, markers))
        # Fused native path (FK + projection in one call): (C, N, M, 2).
        assert_same_pixels(model.project(cams, t, r), project_np(params, markers))


def test_end_to_end_bench_poses(model):
    """The benchmark's poses (middle of the joint limits) through FK and projection."""
    rig = make_rig()
    t, r = random_poses(model, N_POSES, np.random.default_rng(8))
    _, markers = model.forward(t, r)
    _, ref_markers = forward_np(model, t, r)
    np.testing.assert_allclose(markers, ref_markers, rtol=0, atol=TOL_WORLD)
    assert_same_pixels(rig.project(markers), project_np(rig.get_params(), ref_markers))


def test_projection_matches_opencv(rig):
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(9)
    pts = rng.uniform(-15.0, 15.0, size=(500, 3))
    for cam in list(make_rig()) + list(rig):
        ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), cam.rvec, cam.tvec, cam.matrix, cam.dist)
        got = project_np(cam.params[None, :], pts)[0]
        np.testing.assert_allclose(got, ref.reshape(-1, 2), rtol=0, atol=1e-7)


def test_projection_behind_camera_and_nan_points():
    rig = make_rig()
    cam = rig[0]
    params = rig.get_params()
    ahead = 0.5 * cam.center  # between the camera and the origin it looks at
    behind = 1.5 * cam.center
    pts = np.array([ahead, behind, cam.center])
    got = project_np(params, pts)
    assert_same_pixels(got, rig.project(pts))
    assert np.isfinite(got[0, 0]).all()
    assert np.isnan(got[0, 1:]).all()
    # Missing (NaN) points give NaN pixels in every camera.
    assert np.isnan(project_np(params, np.array([[np.nan, 0.0, 0.0]]))).all()


def test_projection_shapes():
    params = make_rig().get_params()
    pts = np.zeros((2, 5, 7, 3))
    assert project_np(params, pts).shape == (4, 2, 5, 7, 2)
    assert project_np(params, np.zeros(3)).shape == (4, 2)
    assert project_np(params, np.zeros((0, 3))).shape == (4, 0, 2)
    with pytest.raises(ValueError):
        project_np(params[:, :14], pts)
    with pytest.raises(ValueError):
        forward_np(acm_rs.models.rat(), np.zeros((3, 3)), np.zeros((3, 27, 3)))
