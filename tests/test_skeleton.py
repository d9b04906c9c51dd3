"""Skeleton construction, forward kinematics (Alg. 1) invariants, exact Jacobians, files."""

from __future__ import annotations

import numpy as np
import pytest

import acm_rs


def random_pose(rng, sk, n=None, scale=1.0):
    shape = () if n is None else (n,)
    t = rng.normal(size=shape + (3,))
    r = rng.normal(size=shape + (sk.n_bones, 3)) * scale
    return t, r


def test_zero_rotation_reproduces_rest_pose(small_skeleton):
    sk = small_skeleton
    joints, markers = sk.forward(np.zeros(3), np.zeros((sk.n_bones, 3)))
    np.testing.assert_allclose(joints[3], [-1, -0.5, 3], atol=1e-12)
    np.testing.assert_allclose(markers[2], [-1.2, -0.4, 3.1], atol=1e-12)
    np.testing.assert_allclose(markers[0], [0.1, 0.2, -0.1], atol=1e-12)


def test_bone_lengths_and_marker_distances_preserved(rng, rat):
    t, r = random_pose(rng, rat, 64, 1.5)
    joints, markers = rat.forward(t, r)
    bones = rat.bones
    lengths = np.linalg.norm(joints[:, bones[:, 1]] - joints[:, bones[:, 0]], axis=-1)
    np.testing.assert_allclose(
        lengths, np.broadcast_to(rat.bone_lengths, lengths.shape), atol=1e-12
    )
    d = np.linalg.norm(markers - joints[:, rat.marker_joints], axis=-1)
    np.testing.assert_allclose(
        d, np.broadcast_to(np.linalg.norm(rat.marker_offsets, axis=1), d.shape), atol=1e-12
    )
    np.testing.assert_allclose(joints[:, 0], t, atol=1e-15)


def test_root_rotation_rotates_rigidly(rng, rat):
    rest_j, rest_m = rat.forward(np.zeros(3), np.zeros((rat.n_bones, 3)))
    r = np.zeros((rat.n_bones, 3))
    r[0] = [0.4, -1.0, 0.3]
    t = np.array([3.0, -2.0, 1.0])
    joints, markers = rat.forward(t, r)
    rot = acm_rs.rodrigues(r[0])
    np.testing.assert_allclose(joints, t + rest_j @ rot.T, atol=1e-12)
    np.testing.assert_allclose(markers, t + rest_m @ rot.T, atol=1e-12)


def test_tree_rule_order_eq8(rat):
    # Humerus orientation: the rotations of the bones from the root down to the humerus,
    # applied root-first (eq. 8); not the sibling clavicle nor spine_003, which share a
    # start joint with a bone on the path.
    rng = np.random.default_rng(1)
    r = rng.normal(size=(rat.n_bones, 3)) * 0.5
    joints, _ = rat.forward(np.zeros(3), r)
    b = rat.bone_index("elbow_left")
    acting = [i for i in range(rat.n_bones) if rat.bone_links[i, b]]
    names = [rat.bone_names[i] for i in acting]
    assert names == [
        "spine_005",
        "spine_004",
        "shoulder_left",
        "elbow_left",
    ]
    rot = np.eye(3)
    for i in acting:
        rot = rot @ acm_rs.rodrigues(r[i])
    rot = rot @ rat.rest_frames[b]
    start, end = rat.bones[b]
    np.testing.assert_allclose(
        joints[end] - joints[start], rot[:, 2] * rat.bone_lengths[b], atol=1e-12
    )


def test_marker_on_root_moves_with_first_rotation(rng, small_skeleton):
    sk = small_skeleton
    r = np.zeros((sk.n_bones, 3))
    r[1:] = rng.normal(size=(sk.n_bones - 1, 3))  # every bone but the first
    _, markers = sk.forward(np.zeros(3), r)
    np.testing.assert_allclose(markers[0], [0.1, 0.2, -0.1], atol=1e-12)


def test_batch_equals_single(rng, rat):
    t, r = random_pose(rng, rat, 5)
    joints, markers = rat.forward(t, r)
    j2, m2 = rat.forward(t[3], r[3])
    np.testing.assert_array_equal(joints[3], j2)
    np.testing.assert_array_equal(markers[3], m2)


def test_overrides(rng, rat):
    t, r = random_pose(rng, rat)
    lengths = rat.bone_lengths * 1.2
    offsets = rat.marker_offsets + 0.1
    j1, m1 = rat.forward(t, r, bone_lengths=lengths, marker_offsets=offsets)
    j2, m2 = rat.with_parameters(lengths, offsets).forward(t, r)
    np.testing.assert_allclose(j1, j2, atol=1e-12)
    np.testing.assert_allclose(m1, m2, atol=1e-12)


def test_jacobians_vs_central_differences(rng, rat):
    t, r = random_pose(rng, rat, scale=0.8)
    lengths = rat.bone_lengths * rng.uniform(0.9, 1.1, rat.n_bones)
    offsets = rat.marker_offsets + rng.normal(scale=0.1, size=(rat.n_markers, 3))
    jac = rat.forward_jacobian(t, r, bone_lengths=lengths, marker_offsets=offsets)

    def flat(t_, r_, l_=lengths, v_=offsets):
        j, m = rat.forward(t_, r_, bone_lengths=l_, marker_offsets=v_)
        return np.concatenate([j, m])

    h = 1e-6
    pose = np.concatenate([t, r.ravel()])
    d_pose = np.concatenate([jac.d_joints_d_pose, jac.d_markers_d_pose])
    for c in range(pose.size):
        e = np.zeros(pose.size)
        e[c] = h
        p, m = pose + e, pose - e
        fd = (flat(p[:3], p[3:].reshape(-1, 3)) - flat(m[:3], m[3:].reshape(-1, 3))) / (2 * h)
        np.testing.assert_allclose(d_pose[..., c], fd, atol=2e-7)
    d_len = np.concatenate([jac.d_joints_d_lengths, jac.d_markers_d_lengths])
    for b in range(rat.n_bones):
        e = np.zeros(rat.n_bones)
        e[b] = h
        fd = (flat(t, r, lengths + e) - flat(t, r, lengths - e)) / (2 * h)
        np.testing.assert_allclose(d_len[..., b], fd, atol=2e-7)
    for k in [0, 2, 17, 42]:
        for c in range(3):
            e = np.zeros_like(offsets)
            e[k, c] = h
            fd = (flat(t, r, v_=offsets + e) - flat(t, r, v_=offsets - e)) / (2 * h)
            np.testing.assert_allclose(
                jac.d_markers_d_offsets[k, :, c], fd[rat.n_joints + k], atol=2e-7
            )
            others = np.delete(fd[rat.n_joints :], k, axis=0)
            assert np.abs(others).max() < 1e-9


def test_bone_links_match_authors_definition(rat):
    """``skeleton_vertices_links`` as the authors document it: a bone is affected by the
    rotation of a preceding bone in the skeleton graph (and by its own)."""
    links = rat.bone_links
    bones = rat.bones
    parents = rat.parents

    def ancestors_or_self(j):
        out = {j}
        while parents[j] >= 0:
            j = parents[j]
            out.add(j)
        return out

    for i in range(rat.n_bones):
        for j in range(rat.n_bones):
            expect = bones[i, 1] in ancestors_or_self(bones[j, 1])
            assert links[i, j] == expect


def test_toml_round_trip(tmp_path, small_skeleton):
    path = tmp_path / "sk.toml"
    small_skeleton.save(path)
    again = acm_rs.Skeleton.load(path)
    assert again.joint_names == small_skeleton.joint_names
    assert again.marker_names == small_skeleton.marker_names
    np.testing.assert_allclose(again.bone_lengths, small_skeleton.bone_lengths, atol=1e-12)
    np.testing.assert_allclose(again.marker_offsets, small_skeleton.marker_offsets, atol=1e-12)
    np.testing.assert_allclose(again.rest_frames, small_skeleton.rest_frames, atol=1e-12)
    np.testing.assert_allclose(again.joint_limits, small_skeleton.joint_limits, atol=1e-12)
    assert again.symmetry == small_skeleton.symmetry


def test_learned_parameters_survive_a_file(tmp_path, rat):
    learned = rat.with_parameters(rat.bone_lengths * 1.07, rat.marker_offsets * 0.9)
    learned.save(tmp_path / "learned.toml")
    again = acm_rs.Skeleton.load(tmp_path / "learned.toml")
    np.testing.assert_allclose(again.bone_lengths, learned.bone_lengths, atol=1e-9)
    np.testing.assert_allclose(again.marker_offsets, learned.marker_offsets, atol=1e-9)
    assert again.bone_length_constraints == rat.bone_length_constraints
    np.testing.assert_array_equal(again.marker_bounds, rat.marker_bounds)


def test_bad_input(small_skeleton):
    sk = small_skeleton
    names = list(sk.joint_names)
    rest, mrest = sk.rest_pose()
    args = (names, sk.parents, rest, list(sk.marker_names), sk.marker_joints, mrest)
    with pytest.raises(ValueError, match="exactly one root"):
        acm_rs.Skeleton.from_rest_pose(names, [-1, -1, 1, 2, 1, 4], *args[2:])
    with pytest.raises(ValueError, match="not connected to the root"):
        acm_rs.Skeleton.from_rest_pose(names, [-1, 2, 1, 2, 1, 4], *args[2:])
    with pytest.raises(ValueError, match="not a joint index"):
        acm_rs.Skeleton.from_rest_pose(names, [-1, 0, 9, 2, 1, 4], *args[2:])
    with pytest.raises(ValueError, match="unknown joint 'nope'"):
        acm_rs.Skeleton.from_rest_pose(*args[:4], ["root", "a", "nope", "c_right"], mrest)
    with pytest.raises(ValueError, match="unknown bone 'root'"):
        acm_rs.Skeleton.from_rest_pose(*args, joint_limits={"root": np.zeros((3, 2))})
    with pytest.raises(ValueError, match="lower > upper"):
        acm_rs.Skeleton.from_rest_pose(*args, joint_limits={"a": [[1, 0], [0, 0], [0, 0]]})
    with pytest.raises(ValueError, match="unknown marker"):
        acm_rs.Skeleton.from_rest_pose(*args, symmetry={"markers": [("m_left", "zz")]})
    bad_rest = rest.copy()
    bad_rest[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        acm_rs.Skeleton.from_rest_pose(names, sk.parents, bad_rest, *args[3:])
    dup = rest.copy()
    dup[3] = dup[2]
    with pytest.raises(ValueError, match="zero length"):
        acm_rs.Skeleton.from_rest_pose(names, sk.parents, dup, *args[3:])
    with pytest.raises(ValueError, match="shape"):
        sk.forward(np.zeros((2, 3)), np.zeros((2, sk.n_bones + 1, 3)))
    with pytest.raises(ValueError, match="frames"):
        sk.forward(np.zeros((2, 3)), np.zeros((3, sk.n_bones, 3)))
    with pytest.raises(ValueError, match="NaN"):
        sk.forward(np.zeros(3), np.full((sk.n_bones, 3), np.nan))
    with pytest.raises(ValueError, match="positive"):
        sk.forward(np.zeros(3), np.zeros((sk.n_bones, 3)), bone_lengths=-np.ones(sk.n_bones))
    with pytest.raises(ValueError, match="unknown joint"):
        sk.joint_index("elbow")


def test_load_rejects_foreign_files(tmp_path):
    p = tmp_path / "x.toml"
    p.write_text('format = "something-else"\n')
    with pytest.raises(ValueError, match="not an acm-rs skeleton"):
        acm_rs.Skeleton.load(p)
    p.write_text("this is = = not toml")
    with pytest.raises(ValueError, match="invalid TOML"):
        acm_rs.Skeleton.load(p)


def test_unknown_keys_in_skeleton_files_are_refused():
    """A typo in a skeleton file is an error naming the key and the closest known one."""
    doc = acm_rs.models.rat().to_dict()
    with pytest.raises(ValueError, match=r"'joint_limit' \(did you mean 'joint_limits'\?\)"):
        acm_rs.Skeleton.from_dict(doc | {"joint_limit": []})
    doc["markers"][0] = dict(doc["markers"][0]) | {"positon": [0.0, 0.0, 0.0]}
    with pytest.raises(ValueError, match=r"markers\[0\] \(head_001\): unknown key\(s\) 'positon'"):
        acm_rs.Skeleton.from_dict(doc)
