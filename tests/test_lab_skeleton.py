"""Skeletons from a lab's own keypoint definitions (acm_rs.lab_skeleton, issue 28 item 1).

Every reader is compared with an independent reader of the same real file (PyYAML, sleap-io,
tomllib, scipy/h5py round trips); the skeleton is built from the real SLEAP multi-camera
session of tests/data/real/sleap and checked against the triangulated labels."""

from __future__ import annotations

import time
import tomllib
import warnings

import numpy as np
import pytest

from acm_rs import Skeleton
from acm_rs import lab_skeleton as ls
from acm_rs.learning import learn_skeleton, triangulate

REAL = __import__("pathlib").Path(__file__).parent / "data" / "real"
SESSION = REAL / "sleap" / "min_session_user_labeled.slp"


# -- readers against independent readers ---------------------------------------------------------
def test_dlc_config_matches_yaml():
    import yaml

    path = REAL / "dlc" / "config_multi_mouse.yaml"
    doc = yaml.safe_load(path.read_text())
    g = ls.read_keypoint_graph(path)
    assert g.tool == "deeplabcut"
    assert g.keypoints == doc["multianimalbodyparts"]
    assert g.edges == [tuple(e) for e in doc["skeleton"]]
    assert any("uniquebodyparts" in n for n in g.notes)  # corners are not the animal's
    tree = ls.spanning_tree(g.keypoints, g.edges)  # a triangle: one edge must go
    assert len(tree.dropped) == 1 and tree.rule == "bfs"


@pytest.mark.parametrize(
    "name", ["min_session.slp", "min_session_user_labeled.slp", "flies13.json"]
)
def test_sleap_skeleton_matches_sleap_io(name):
    sio = pytest.importorskip("sleap_io")
    path = REAL / "sleap" / name
    ref = sio.load_skeleton(path) if name.endswith(".json") else sio.load_slp(path).skeletons[0]
    ref = ref[0] if isinstance(ref, list) else ref
    g = ls.read_keypoint_graph(path)
    assert g.tool == "sleap"
    assert g.keypoints == ref.node_names
    assert sorted(map(sorted, g.edges)) == sorted(map(sorted, ref.edge_names))
    assert sorted(map(sorted, g.symmetry)) == sorted(map(sorted, ref.symmetry_names))
    if name == "flies13.json":
        assert len(g.symmetry) == 5  # stored both ways in the file, kept once


def test_dannce_skeleton_and_its_round_trips(tmp_path):
    import h5py
    import scipy.io

    path = REAL / "dannce" / "mouse22_skeleton.mat"
    g = ls.read_keypoint_graph(path)
    assert g.tool == "dannce" and len(g.keypoints) == 22 and len(g.edges) == 24
    # 1-based MATLAB indices: the first rows of joints_idx are (1, 2), (2, 3), (1, 3)
    assert g.keypoints[:3] == ["EarL", "EarR", "Snout"]
    assert g.edges[:3] == [("EarL", "EarR"), ("EarR", "Snout"), ("EarL", "Snout")]
    # written again by scipy (MATLAB 5) and as MATLAB 7.3 HDF5 (h5py): the same graph
    idx = np.array([[g.keypoints.index(a) + 1, g.keypoints.index(b) + 1] for a, b in g.edges])
    v5 = tmp_path / "v5.mat"
    cell = np.empty((1, len(g.keypoints)), dtype=object)
    cell[0, :] = g.keypoints
    scipy.io.savemat(v5, {"joint_names": cell, "joints_idx": idx.astype(np.uint8)})
    v73 = tmp_path / "v73.mat"
    with h5py.File(v73, "w") as f:
        refs = []
        for k, n in enumerate(g.keypoints):
            d = f.create_dataset(f"#refs#/{k}", data=np.array([[ord(c)] for c in n], np.uint16))
            refs.append(d.ref)
        f.create_dataset("joint_names", data=np.array(refs, dtype=h5py.ref_dtype)[None, :])
        f.create_dataset("joints_idx", data=idx.T.astype(np.float64))  # column-major
    names73, idx73 = ls._read_mat73(v73)
    assert names73 == g.keypoints and np.array_equal(idx73, idx)
    for p in (v5,):
        h = ls.read_keypoint_graph(p)
        assert (h.keypoints, h.edges) == (g.keypoints, g.edges)
    tree = ls.spanning_tree(g.keypoints, g.edges)
    assert len(tree.names) == 22 and len(tree.dropped) == 24 - 21


def test_anipose_constraints_match_tomllib():
    path = REAL / "anipose" / "allen7_config.toml"
    doc = tomllib.loads(path.read_text())
    g = ls.read_keypoint_graph(path)
    assert g.tool == "anipose"
    assert g.edges == [tuple(p) for p in doc["triangulation"]["constraints"]]
    assert set(g.keypoints) == {n for p in doc["triangulation"]["constraints"] for n in p}
    assert any("constraints_weak" in n for n in g.notes)
    # the head and the tail tip are pieces of their own in this config: no tree without data
    with pytest.raises(ValueError, match="3 pieces"):
        ls.spanning_tree(g.keypoints, g.edges)


def test_unknown_definitions_are_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown keypoint definition"):
        ls.read_keypoint_graph(REAL / "dlc" / "CollectedData_Mackenzie.csv")
    with pytest.raises(ValueError, match="no \\[triangulation\\] constraints"):
        ls.read_keypoint_graph(REAL / "anipose" / "allen7_calibration.toml")
    bad = tmp_path / "s.mat"
    __import__("scipy.io").io.savemat(bad, {"joint_names": np.array(["a", "b"], dtype=object),
                                            "joints_idx": np.array([[0, 1]])})  # fmt: skip
    with pytest.raises(ValueError, match="1-based"):
        ls.read_keypoint_graph(bad)


# -- names, trees ------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "names, pairs",
    [
        (["Ear_L", "Ear_R", "Nose"], [("Ear_L", "Ear_R")]),
        (["Shoulder_left", "Shoulder_right", "Trunk"], [("Shoulder_left", "Shoulder_right")]),
        (["right_eye", "left_eye"], [("left_eye", "right_eye")]),
        (["EarL", "EarR", "TailL"], [("EarL", "EarR")]),  # TailL has no partner
        (["wingL1", "wingR1", "L-ear", "R-ear"], [("wingL1", "wingR1"), ("L-ear", "R-ear")]),
        (["LF-paw", "RF-paw", "LeftHip", "RightHip"], [("LF-paw", "RF-paw"),
                                                       ("LeftHip", "RightHip")]),
        (["ear_l", "ear_r"], [("ear_l", "ear_r")]),
        (["Tail(base)", "SpineL", "SpineM", "Trunk", "TTI"], []),
    ],
)  # fmt: skip
def test_symmetry_from_names(names, pairs):
    assert ls.symmetry_from_names(names) == pairs


def _chain_points(n_frames=40, seed=0):
    """Keypoints a-b-c-d on a rigid chain plus a loose pair: b-d varies, a-c is rigid."""
    rng = np.random.default_rng(seed)
    base = np.array([[0, 0, 0], [1, 0, 0], [2, 0.1, 0], [3, 0, 0.2]], float)
    pts = []
    for _ in range(n_frames):
        p = base.copy()
        p[3] = p[2] + rng.uniform(0.5, 1.5) * np.array([1.0, 0, 0])  # c-d stretches
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        pts.append(p @ q.T * np.sign(np.linalg.det(q)) + rng.normal(size=3))
    return np.array(pts)


def test_spanning_tree_keeps_rigid_edges_and_joins_pieces():
    names = ["a", "b", "c", "d"]
    pts = _chain_points()
    # cycle a-b-c-d-a: c-d and d-a both vary; the tree keeps a-b, b-c and the more rigid
    # of the two edges to d, and drops the other
    cv_cd = ls._edge_cv(pts, 2, 3)
    cv_da = ls._edge_cv(pts, 3, 0)
    tree = ls.spanning_tree(names, [("a", "b"), ("b", "c"), ("c", "d"), ("d", "a")], pts)
    assert tree.rule == "rigidity"
    assert tree.dropped == ([("c", "d")] if cv_cd > cv_da else [("d", "a")])
    # pieces {a, b} and {c, d}: joined by the most rigid pair between them
    tree = ls.spanning_tree(names, [("a", "b"), ("c", "d")], pts)
    cross = {(x, y): ls._edge_cv(pts, names.index(x), names.index(y))
             for x in "ab" for y in "cd"}  # fmt: skip
    assert tree.added == [min(cross, key=cross.get)]
    assert sorted(tree.names) == names and tree.parents.count(-1) == 1
    # the root is the centre (least eccentricity) unless named
    star = ls.spanning_tree(["x", "hub", "y", "z"], [("x", "hub"), ("hub", "y"), ("y", "z")])
    assert star.root in ("hub", "y") and star.root == "hub"  # tie broken by name order
    assert ls.spanning_tree(names, [("a", "b"), ("b", "c"), ("c", "d")], root="d").root == "d"
    with pytest.raises(ValueError, match="not a keypoint"):
        ls.spanning_tree(names, [("a", "b")], pts, root="q")


# -- the skeleton from the real session --------------------------------------------------------
@pytest.fixture(scope="module")
def session():
    from acm_rs.sleap_session import read_sleap_session

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_sleap_session(SESSION, individual="track_0")


def test_skeleton_from_the_real_session(session, tmp_path):
    rig, labels = session.rig, session.labels
    res = ls.skeleton_from_labels(SESSION, rig, labels)
    sk = res.skeleton
    g = ls.read_keypoint_graph(SESSION)
    assert sorted(sk.joint_names) == sorted(g.keypoints) and sk.marker_names == sk.joint_names
    assert res.tree.root == "Head"  # Head and TTI are the centres of this star; name order
    assert np.all(sk.marker_offsets == 0) and np.all(sk.marker_bounds == 0)
    assert sk.symmetry["joints"] == [("Ear_L", "Ear_R"), ("Shoulder_left", "Shoulder_right"),
                                     ("Haunch_left", "Haunch_right")]  # fmt: skip
    # bone lengths = median triangulated distances (computed here from the labels)
    pts = triangulate(rig, labels.points)
    col = {n: labels.bodyparts.index(n) for n in sk.joint_names}
    for b, (s, e) in enumerate(sk.bones):
        d = np.linalg.norm(pts[:, col[sk.joint_names[e]]] - pts[:, col[sk.joint_names[s]]], axis=1)
        assert sk.bone_lengths[b] == pytest.approx(np.nanmedian(d), rel=1e-9)
    # one fixed component per bone; 2 free per bone + translation
    assert int((~sk.fixed_pose_mask).sum()) == 3 + 2 * sk.n_bones
    # the labelled poses: exact bone directions, inside the limits, fixed components 0
    order = [col[n] for n in sk.joint_names]
    fixed = np.argmax(sk.joint_limits[..., 0] == sk.joint_limits[..., 1], axis=1)
    t, r = ls.poses_from_points(sk, pts[:, order], fixed)
    joints, _ = sk.forward(t, np.nan_to_num(r))
    for f in range(len(t)):
        for s, e in sk.bones:
            want = pts[f, order[e]] - pts[f, order[s]]
            if np.isfinite(want).all() and np.isfinite(r[f]).all():
                got = joints[f, e] - joints[f, s]
                np.testing.assert_allclose(got / np.linalg.norm(got),
                                           want / np.linalg.norm(want), atol=1e-9)  # fmt: skip
    fin = np.isfinite(r)
    assert np.all(r[fin.all(-1)][:, :][np.broadcast_to(np.eye(3, dtype=bool)[fixed],
                                                        r.shape)[fin.all(-1)]] == 0)  # fmt: skip
    lim = sk.joint_limits
    inside = (r >= lim[None, ..., 0] - 1e-12) & (r <= lim[None, ..., 1] + 1e-12)
    assert inside[fin].all()
    # saved and read back as any skeleton file
    sk.save(tmp_path / "lab.toml")
    back = Skeleton.load(tmp_path / "lab.toml")
    np.testing.assert_allclose(back.bone_lengths, sk.bone_lengths, rtol=1e-9)
    np.testing.assert_allclose(back.joint_limits, sk.joint_limits, atol=1e-9)
    assert back.symmetry == sk.symmetry


def test_learning_with_the_lab_skeleton(session):
    rig, labels = session.rig, session.labels
    t0 = time.perf_counter()
    res = ls.skeleton_from_labels(SESSION, rig, labels)
    learned = learn_skeleton(rig, res.skeleton, labels.points, marker_names=labels.bodyparts)
    seconds = time.perf_counter() - t0
    dlt = triangulate(rig, labels.points)
    e = np.linalg.norm(rig.project(dlt) - labels.points, axis=-1)
    dlt_rms = float(np.sqrt(np.nanmean(e**2)))
    # 14 bone lengths with symmetry against a free 3D point per keypoint: close to it
    assert learned.rms < 1.25 * dlt_rms, (learned.rms, dlt_rms)
    assert seconds < 10


def test_no_joint_limits_and_missing_keypoints(session):
    rig, labels = session.rig, session.labels
    res = ls.skeleton_from_labels(SESSION, rig, labels, joint_limits=False, root="TTI")
    lim = res.skeleton.joint_limits
    assert res.tree.root == "TTI"
    assert np.all((lim[..., 0] == 0) & (lim[..., 1] == 0) | np.isinf(lim).all(axis=-1))
    pts = labels.points.copy()
    pts[:, :, labels.bodyparts.index("Nose")] = np.nan
    with pytest.raises(ValueError, match="Nose"):
        ls.skeleton_from_labels(SESSION, rig, pts, bodyparts=labels.bodyparts)
    with pytest.raises(ValueError, match="no labels"):
        ls.skeleton_from_labels(SESSION, rig, pts[:, :, 1:], bodyparts=labels.bodyparts[1:])


def test_pieces_are_joined_with_a_warning(rig):
    """anipose's allen7 constraints leave the head and the tail tip apart: labelled frames of
    an animal with those keypoints join them by the most rigid pairs, and it is said."""
    g = ls.read_keypoint_graph(REAL / "anipose" / "allen7_config.toml")
    rng = np.random.default_rng(1)
    base = rng.normal(scale=3.0, size=(len(g.keypoints), 3))
    frames = []
    for _ in range(12):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        q *= np.sign(np.linalg.det(q))
        frames.append(base @ (np.eye(3) + 0.05 * (q - np.eye(3))).T + rng.normal(scale=0.5, size=3))
    px = rig.project(np.array(frames))
    with pytest.warns(UserWarning, match="in pieces; joined"):
        res = ls.skeleton_from_labels(g, rig, px, bodyparts=g.keypoints)
    assert len(res.tree.added) == 2
    assert res.skeleton.n_joints == len(g.keypoints)
