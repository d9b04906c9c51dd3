"""Symmetry maps (Alg. 2-3), joint-limit map (Alg. 10), normalisation and emission (Alg. 4)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

import acm_rs


def test_rat_has_the_papers_50_free_entries(rat):
    sm = rat.state_map()
    assert sm.n_state == 50
    assert sm.free_indices.size == (~rat.fixed_pose_mask).sum()
    fixed = rat.fixed_pose_mask[3:].reshape(-1, 3)
    for name in ("shoulder_left", "hip_right"):  # clavicle, pelvis half
        assert fixed[rat.bone_index(name)].all()
    assert fixed[rat.bone_index("ankle_left")].tolist() == [False, True, True]  # knee: x only
    assert not fixed[rat.bone_index("spine_005")].any()  # global rotation


def test_symmetry_maps_mirror_x(rat):
    sym = rat.symmetry_map()
    assert sym.n_reduced_bones == rat.n_bones - 9
    assert sym.n_reduced_markers == rat.n_markers - 14
    rng = np.random.default_rng(3)
    v_red = rng.normal(size=(sym.n_reduced_markers, 3))
    v = sym.expand_offsets(v_red)
    for left, right in rat.symmetry["markers"]:
        a, b = rat.marker_index(left), rat.marker_index(right)
        np.testing.assert_array_equal(v[b], v[a] * [-1, 1, 1])
    l_red = rng.uniform(1, 2, sym.n_reduced_bones)
    lengths = sym.expand_lengths(l_red)
    for left, right in rat.symmetry["joints"]:
        assert lengths[rat.bone_index(left)] == lengths[rat.bone_index(right)]
    np.testing.assert_allclose(sym.reduce_lengths(lengths), l_red)
    np.testing.assert_allclose(sym.reduce_offsets(v), v_red)
    # The gradient maps are the transposes of the expansions.
    g = rng.normal(size=(rat.n_markers, 3))
    assert np.isclose(np.sum(v * g), np.sum(v_red * sym.reduce_offset_grad(g)))
    gl = rng.normal(size=rat.n_bones)
    assert np.isclose(np.sum(lengths * gl), np.sum(l_red * sym.reduce_length_grad(gl)))


def test_rat_rest_pose_and_model_are_mirror_symmetric(rat):
    joints, markers = rat.rest_pose()
    for left, right in rat.symmetry["joints"]:
        np.testing.assert_allclose(
            joints[rat.joint_index(right)], joints[rat.joint_index(left)] * [-1, 1, 1], atol=1e-9
        )
    for left, right in rat.symmetry["markers"]:
        a, b = rat.marker_index(left), rat.marker_index(right)
        np.testing.assert_allclose(markers[b], markers[a] * [-1, 1, 1], atol=1e-9)
        np.testing.assert_allclose(
            rat.marker_offsets[b], rat.marker_offsets[a] * [-1, 1, 1], atol=1e-9
        )
        np.testing.assert_array_equal(rat.marker_bounds[b, 0], -rat.marker_bounds[a, 0, ::-1])
    # The offsets of the model respect their own box constraints (sec. 6).
    lo, hi = rat.marker_bounds[..., 0], rat.marker_bounds[..., 1]
    assert np.all(rat.marker_offsets >= lo - 1e-9) and np.all(rat.marker_offsets <= hi + 1e-9)


def test_erf_map_inside_bounds_monotone_and_inverse(rat):
    sm = rat.state_map()
    z = np.linspace(-6, 6, 241)[:, None] * np.ones((1, sm.n_state))
    t, r = sm.to_pose(z)
    lim = rat.joint_limits
    assert np.all(r >= lim[..., 0] - 1e-12) and np.all(r <= lim[..., 1] + 1e-12)
    pose = np.concatenate([t, r.reshape(len(z), -1)], axis=1)[:, sm.free_indices]
    assert np.all(np.diff(pose, axis=0) >= 0)
    # Alg. 10 formula, checked with scipy's erf on a bounded entry (left humerus x).
    b = rat.bone_index("elbow_left")
    i = list(sm.free_indices).index(3 + 3 * b)
    b0, b1 = lim[b, 0]
    np.testing.assert_allclose(
        r[:, b, 0], b0 + 0.5 * (b1 - b0) * (1 + erf(np.sqrt(np.pi) / 2 * z[:, i]))
    )
    # The centre of the state is the middle of every bounded range.
    _, r0 = sm.to_pose(np.zeros(sm.n_state))
    assert np.isclose(r0[b, 0], 0.5 * (b0 + b1))
    zz = np.random.default_rng(0).normal(size=(10, sm.n_state))
    np.testing.assert_allclose(sm.from_pose(*sm.to_pose(zz)), zz, atol=1e-8)


def test_state_map_derivative_and_normalisation(rat):
    norm = acm_rs.Normalization(translation=500.0)
    sm = rat.state_map(norm)
    z = np.random.default_rng(1).normal(size=sm.n_state)
    t, _ = sm.to_pose(z)
    np.testing.assert_allclose(t, 500.0 * z[:3])
    d = sm.to_pose_derivative(z)
    h = 1e-6
    for i in range(sm.n_state):
        e = np.zeros(sm.n_state)
        e[i] = h
        tp, rp = sm.to_pose(z + e)
        tm, rm = sm.to_pose(z - e)
        fd = (np.concatenate([tp, rp.ravel()]) - np.concatenate([tm, rm.ravel()])) / (2 * h)
        assert np.isclose(fd[sm.free_indices[i]], d[i], rtol=1e-6, atol=1e-9)
    free = rat.state_map(joint_limits=False)
    t, r = free.to_pose(np.ones(free.n_state))
    b = rat.bone_index("elbow_left")
    assert np.isclose(r[b, 0], np.pi / 2)  # linear: r = c_r z


def test_emission_is_fk_then_normalised_projection(rat, rig):
    sm = rat.state_map()
    rng = np.random.default_rng(2)
    z = rng.normal(size=(7, sm.n_state)) * 0.3
    g = sm.emission(rig, z)
    assert g.shape == (7, len(rig), rat.n_markers, 2)
    t, r = sm.to_pose(z)
    _, markers = rat.forward(t, r)
    px = rig.project(markers)  # (C, 7, M, 2)
    np.testing.assert_allclose(
        g, sm.normalization.normalize_pixels(px.transpose(1, 0, 2, 3)), atol=1e-9
    )


def test_normalization_validation():
    n = acm_rs.Normalization.from_image_size(1280, 1024)
    assert n.pixel == (640.0, 512.0)
    np.testing.assert_allclose(n.denormalize_pixels(n.normalize_pixels([[3.0, 4.0]])), [[3.0, 4.0]])
    with pytest.raises(ValueError, match="finite and > 0"):
        acm_rs.Normalization(rotation=0.0)


def test_bone_length_bounds(rat):
    free = rat.bone_length_bounds()
    assert np.all(free[:, 0] == 0) and np.all(np.isinf(free[:, 1]))
    b = rat.bone_length_bounds(body_weight=400.0)
    hum = b[rat.bone_index("elbow_left")]
    np.testing.assert_allclose(
        hum, [0.0075 * 400 - 10 * 0.0005 * 400, 0.0075 * 400 + 10 * 0.0005 * 400]
    )
    assert np.isinf(b[rat.bone_index("spine_003"), 1])
    mouse = acm_rs.models.mouse().bone_length_bounds(sigma_factor=1.0)
    np.testing.assert_allclose(
        mouse[acm_rs.models.mouse().bone_index("knee_left")], [1.668 - 0.029, 1.668 + 0.029]
    )
    with pytest.raises(ValueError, match="body_weight"):
        rat.bone_length_bounds(body_weight=-1)


def test_joint_limit_table_is_the_papers(rat):
    deg = np.degrees(rat.joint_limits)
    np.testing.assert_allclose(deg[rat.bone_index("elbow_left")], [[25, 205], [-85, 25], [-35, 35]])
    # right hip y: the authors' code has [-25, 65] (the mirror of the left hip's [-65, 25]);
    # Supp. Table 1 prints [25, 65] (docs/models.md)
    np.testing.assert_allclose(deg[rat.bone_index("knee_right")], [[35, 195], [-25, 65], [-40, 85]])
    np.testing.assert_allclose(deg[rat.bone_index("toe_right_002")], [[0, 0], [0, 0], [-35, 15]])
    np.testing.assert_allclose(deg[rat.bone_index("tail_003")], [[-90, 90], [-90, 90], [0, 0]])
    assert np.all(np.isinf(deg[rat.bone_index("spine_005")]))


def test_start_state_moves_bounded_entries_off_the_flat_ends_of_the_limit_map():
    # a single-frame fit that ended at a joint limit maps to |z| ~ 4 (from_pose moves it
    # just inside), where the pose no longer depends on z and a filter started there stays
    # stuck; the start moves bounded entries to |z| <= START_Z, nothing else
    from acm_rs import datasets, models
    from acm_rs.state import START_Z, StateMap

    sk = datasets.individual_skeleton(models.rat(), seed=1)
    sm = StateMap(sk)
    t, r = datasets.smooth_motion(sk, 3, seed=2)
    lim = sk.joint_limits
    b = sk.joint_names.index("tail_002")
    r[:, b, 0] = lim[b, 0, 0]  # at the lower limit
    z, zs = sm.from_pose(t, r), sm.start_state(t, r)
    bounded = sm.bounded
    assert bounded.sum() == 44 and not bounded[:6].any()  # t and the global rotation are free
    assert np.abs(z[:, bounded]).max() > 4 and np.abs(zs[:, bounded]).max() == START_Z
    moved = z != zs
    assert moved.any() and not moved[:, ~bounded].any()
    assert np.all(np.abs(z[moved]) > START_Z) and np.all(np.abs(zs[moved]) == START_Z)
    # the moved tail bone is now where the pose depends on it again
    _, r2 = sm.to_pose(zs)
    assert lim[b, 0, 0] + 0.2 * np.ptp(lim[b, 0]) < r2[0, b, 0] < np.mean(lim[b, 0])
    # without limits nothing is bounded
    assert not StateMap(sk, joint_limits=False).bounded.any()
