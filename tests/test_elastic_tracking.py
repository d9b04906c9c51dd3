"""Elastic segments in the tracker (issue 28 item 2): the log-stretch of each elastic bone is
a memoryless state entry whose variance EM learns.

Truth from independent code (``tests/elastic_truth.py``): a keypoint tree in plain NumPy (bone
directions that wander smoothly, lengths ``L exp(s_t)`` with a smooth log-stretch of known
SD), projected by OpenCV's ``projectPoints``. Nothing of acm-rs's forward model, state or
noise model makes it.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import acm_rs
from acm_rs.elastic import add_stretch
from acm_rs.lab_skeleton import KeypointGraph, skeleton_from_labels
from acm_rs.learning import learn_skeleton
from acm_rs.rotation import rodrigues, wrap_rotation_vectors
from acm_rs.tracking.result import PoseResult

sys.path.insert(0, str(Path(__file__).parent))
from elastic_truth import EDGES, LENGTH, NAMES, SD, cameras, project, synthetic  # noqa: E402

cv2 = pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def case():
    n_frames = 240
    pts, stretch = synthetic(n_frames, seed=1)
    cams = cameras()
    px = project(cams, pts)
    det = px + np.random.default_rng(5).normal(0, 1.0, px.shape)
    rig = acm_rs.CameraRig(
        [acm_rs.Camera(k, d, rv, tv, (1280, 1024), name=f"c{i}") for i, (k, d, rv, tv) in
         enumerate(cams)], units="mm",
    )  # fmt: skip
    # the user's path: a skeleton from the lab's graph, learned on 40 labelled frames
    lab = det[:, :40]
    sk0 = skeleton_from_labels(
        KeypointGraph(NAMES, EDGES), rig, lab, bodyparts=NAMES, joint_limits=False
    ).skeleton
    order = [NAMES.index(m) for m in sk0.marker_names]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rigid = learn_skeleton(rig, sk0, lab[:, :, order], progress=False)
    elastic, _ = add_stretch(rigid)
    det_k = det[:, :, order]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res_rigid = acm_rs.track(rig, rigid.skeleton, det_k)
        res = acm_rs.track(rig, elastic.skeleton, det_k)
    return {
        "rig": rig, "truth": pts[:, order], "stretch": stretch, "rigid": res_rigid,
        "elastic": res, "skeleton": elastic.skeleton, "rigid_skeleton": rigid.skeleton,
        "det": det_k,
    }  # fmt: skip


def keypoints(res):
    names = list(res.skeleton.joint_names)
    idx = [names.index(m) for m in res.skeleton.marker_names]
    return res.joints[:, idx], res.joints_std[:, idx]


def test_elastic_tracking_follows_stretching_segments(case):
    truth = case["truth"]
    j_r, _ = keypoints(case["rigid"])
    j_e, sd_e = keypoints(case["elastic"])
    e_r = np.linalg.norm(j_r - truth, axis=-1)
    e_e = np.linalg.norm(j_e - truth, axis=-1)
    # a rigid tree cannot follow 6-12 % stretch: its tail errors are several mm
    assert np.percentile(e_r, 95) > 3.0
    assert np.median(e_e) < 0.6 and np.percentile(e_e, 95) < 1.5 and e_e.max() < 3.0
    assert np.percentile(e_e, 95) < 0.4 * np.percentile(e_r, 95)
    # honest intervals (the rigid model's are not)
    cover = np.mean(np.abs(j_e - truth) <= 1.96 * sd_e)
    assert 0.90 <= cover <= 0.99, cover
    assert case["elastic"].info["elastic"] and not case["rigid"].info["elastic"]


def test_em_learns_each_segments_stretch(case):
    res, sk = case["elastic"], case["skeleton"]
    learned = res.info["stretch_sd"]
    lengths = res.info["bone_lengths"]
    joints = sk.joint_names
    for b, (a, c) in enumerate(sk.bones):
        pair = {joints[a], joints[c]}
        child = next(ch for p, ch in EDGES if {p, ch} == pair)
        s = case["stretch"][child]
        if SD[child] > 0:
            # the SD over the recording (sample of a smooth process), within 25 %
            assert abs(learned[b] / np.std(s) - 1) < 0.25, (child, learned[b], np.std(s))
            true_len = LENGTH[child] * np.exp(s)
            # each frame's length is estimated, not the mean: half the spread or better
            assert np.median(np.abs(lengths[:, b] - true_len)) < 0.5 * np.std(true_len)
        else:
            assert learned[b] < 0.03, (child, learned[b])  # rigid segments stay (nearly) rigid


def test_elastic_option_and_results_round_trip(case, tmp_path):
    rig, det = case["rig"], case["det"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = acm_rs.track(rig, case["skeleton"], det[:, :60], elastic=False, max_iter=3)
    assert "bone_lengths" not in res.info and res.state_map.n_state == res.state_map.n_pose_state
    with pytest.raises(ValueError, match="elastic bones"):
        acm_rs.track(rig, case["rigid_skeleton"], det[:, :60], elastic=True)
    full = case["elastic"]
    n_e = len(case["skeleton"].elastic_bones)
    assert f"elastic segments: {n_e} bones" in full.summary()
    assert full.state_map.n_state == full.state_map.n_pose_state + n_e
    path = tmp_path / "elastic.npz"
    full.save(path)
    back = PoseResult.load(path)
    assert back.state_map.n_state == full.state_map.n_state
    np.testing.assert_allclose(back.info["bone_lengths"], full.info["bone_lengths"])
    # samples: forward kinematics of sampled states with each one's lengths
    joints, _ = back.sample(200, seed=0)
    j_e, sd_e = keypoints(full)
    names = list(back.skeleton.joint_names)
    idx = [names.index(m) for m in back.skeleton.marker_names]
    np.testing.assert_allclose(joints[:, :, idx].std(axis=0), sd_e, rtol=0.25, atol=0.02)


def test_state_forward_uses_each_states_lengths(case):
    res = case["elastic"]
    sm, sk = res.state_map, res.skeleton
    z = np.array(res.state_mean[:5, : sm.n_state])
    z[:, sm.n_pose_state :] += 0.1
    joints, markers = sm.forward(z)
    t, r = sm.to_pose(z)
    lengths = sm.lengths(z)
    for f in range(5):
        j, m = sk.forward(t[f], r[f], bone_lengths=lengths[f])
        np.testing.assert_allclose(joints[f], j, atol=1e-10)
        np.testing.assert_allclose(markers[f], m, atol=1e-10)
    np.testing.assert_allclose(
        lengths[:, sk.elastic_bones] / sk.bone_lengths[sk.elastic_bones],
        np.exp(z[:, sm.n_pose_state :]),
    )
    # the tracker's emission (Rust, per state) = those markers projected (OpenCV), normalised
    rig = case["rig"]
    g = sm.emission(rig, z)  # (5, C, M, 2) normalised pixels
    for c, cam in enumerate(rig):
        px = cv2.projectPoints(markers.reshape(-1, 3), cam.rvec, cam.tvec, cam.matrix, cam.dist)[
            0
        ].reshape(5, -1, 2)
        np.testing.assert_allclose(g[:, c], sm.normalization.normalize_pixels(px), atol=1e-9)


def test_wrapped_rotation_vectors_are_the_same_rotations():
    rng = np.random.default_rng(0)
    r = rng.normal(0, 20.0, (50, 3))
    r[:10, 2] = 0.0  # a fixed component stays 0
    w = wrap_rotation_vectors(r, beyond=np.pi)
    assert np.all(np.linalg.norm(w, axis=-1) <= np.pi + 1e-12)
    np.testing.assert_allclose(rodrigues(w), rodrigues(r), atol=1e-9)
    np.testing.assert_array_equal(w[:10, 2], 0.0)
    small = rng.normal(0, 0.5, (5, 3))
    np.testing.assert_array_equal(wrap_rotation_vectors(small), small)
    # by default only vectors beyond 1.5 pi change (those near the singularity at 2 pi)
    mid = np.array([[0.0, 0.0, 1.2 * np.pi], [0.0, 1.7 * np.pi, 0.0]])
    out = wrap_rotation_vectors(mid)
    np.testing.assert_array_equal(out[0], mid[0])
    np.testing.assert_allclose(out[1], [0.0, -0.3 * np.pi, 0.0])


def test_paths_without_elastic_segments_say_so(case, tmp_path):
    """The online tracker, acm-smooth bundles and the bounded-memory path keep the mean
    lengths: each says so, and parameters of an elastic track are refused by the online one."""
    from acm_rs import OnlineTracker
    from acm_rs.tracking.bundle import write_bundle

    rig, det, sk = case["rig"], case["det"], case["skeleton"]
    with pytest.raises(ValueError, match="elastic=False"):
        OnlineTracker.from_result(case["elastic"])
    with pytest.warns(UserWarning, match="online tracker keeps every bone at its mean length"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rigid = acm_rs.track(rig, sk, det[:, :60], elastic=False, max_iter=3)
        OnlineTracker.from_result(rigid)
    with pytest.warns(UserWarning, match="acm-smooth keeps every bone at its mean length"):
        write_bundle(tmp_path / "b.npz", rig, sk, det[:, :30], max_iter=2)
    with pytest.warns(UserWarning, match="bounded-memory path"):
        acm_rs.track(rig, sk, det[:, :120], memory_limit=1e5, max_iter=2)
