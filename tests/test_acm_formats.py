"""Readers and writers of the authors' ACM dataset files, against an independent fixture."""

from __future__ import annotations

import math

import numpy as np
import pytest
from acm_fixture import synthetic_result, write_acm_dataset

import acm_rs
from acm_rs import acm_formats as af


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_acm_dataset(tmp_path_factory.mktemp("acm") / "rat_session", seed=0)


# -- configuration.py -----------------------------------------------------------------------------
def test_configuration_values(dataset):
    cfg = af.read_configuration(dataset.folder)
    assert (cfg.index_frame_start, cfg.index_frame_end) == (20, 100)
    assert (cfg.dlc_index_frame_start, cfg.dlc_index_frame_end) == (0, 120)
    assert cfg.dt == 4 and cfg.pcutoff == 0.9 and cfg.scale_factor == 6.5
    assert cfg.body_weight == 72.0 and cfg.species == "rat" and cfg.mode == 4
    assert cfg.tol == 0.05 and cfg.iter_max == 100 and cfg.noise == 1e-4
    assert cfg.normalize_r0 == pytest.approx(math.pi / 2)
    assert cfg.sensor_size == (1280.0, 1024.0)
    assert cfg.index_frames_calib == [[0, 111]]
    np.testing.assert_array_equal(cfg.frames, np.arange(20, 100, 4))
    # derived literals are evaluated, code is skipped with a reason
    assert cfg.values["nT"] == 20 and cfg.values["index_frame_ini"] == 20
    assert cfg.values["num_tol"] == 2**-52
    assert math.isinf(cfg.values["opt_options_calib__maxiter"])
    assert "folder_project" in cfg.skipped and "os.path" in cfg.skipped["folder_project"]
    assert "job_time" in cfg.skipped


def _config(tmp_path, body: str):
    base = "index_frame_start = 0\nindex_frame_end = 50\n"
    (tmp_path / "configuration.py").write_text(base + body, encoding="utf-8")
    return tmp_path


def test_configuration_never_executes(tmp_path):
    marker = tmp_path / "executed"
    _config(
        tmp_path,
        f"import os\nopen({str(marker)!r}, 'w').write('x')\n"
        f"__import__('os').system('touch {marker}')\nfoo = open({str(marker)!r}, 'w')\n"
        "big = 10 ** 10 ** 10\nrep = 'a' * 10**9\n",
    )
    cfg = af.read_configuration(tmp_path)
    assert not marker.exists()
    assert "foo" in cfg.skipped and "big" in cfg.skipped and "rep" in cfg.skipped
    assert cfg.dt == 5 and cfg.pcutoff == 0.9  # documented defaults


@pytest.mark.parametrize(
    "body, match",
    [
        ("import os\ndt = int(os.environ['DT'])\n", r"configuration.py:4: dt must be a literal"),
        ("pcutoff = 'high'\n", r"pcutoff must be int or float .*got str 'high'"),
        ("pcutoff = 1.5\n", r"pcutoff = 1.5 is invalid: expected a likelihood in \[0, 1\]"),
        ("dt = 2.5\n", r"dt must be an integer"),
        ("species = 'cat'\n", r"species = 'cat' is invalid: expected 'rat' or 'mouse'"),
        ("index_frame_end = 0\n", r"index_frame_end \(0\) must be > index_frame_start"),
        (
            "dlc_index_frame_start = 10\ndlc_index_frame_end = 40\n",
            r"outside the DeepLabCut label range 10-40",
        ),
        ("dt = (\n", r"invalid Python syntax"),
    ],
)
def test_configuration_errors(tmp_path, body, match):
    _config(tmp_path, body)
    with pytest.raises(ValueError, match=match):
        af.read_configuration(tmp_path / "configuration.py")


def test_configuration_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="no configuration.py"):
        af.read_configuration(tmp_path)
    (tmp_path / "configuration.py").write_text("index_frame_end = 5\n")
    with pytest.raises(ValueError, match="missing index_frame_start"):
        af.read_configuration(tmp_path)


# -- model.npy ------------------------------------------------------------------------------------
def test_model_names_and_order(dataset):
    m = af.read_model(dataset.folder)
    assert m.source == "model.npy"
    assert m.acm_joint_names == dataset.acm_joint_names
    assert m.acm_marker_names == dataset.acm_marker_names
    sk = m.skeleton
    assert [sk.joint_names[i] for i in m.joint_index] == dataset.acm_joint_names
    assert [sk.marker_names[i] for i in m.marker_index] == dataset.acm_marker_names
    x = np.arange(sk.n_joints * 3, dtype=float).reshape(1, sk.n_joints, 3)
    assert m.to_acm_joints(x)[0, 0, 0] == x[0, sk.joint_index(dataset.acm_joint_names[0]), 0]
    # limits, marker boxes, priors and pairs come from the bundled model by name
    rat = acm_rs.models.rat()
    for name in ("knee_left", "knee_right", "spine_003", "toe_left_002"):
        np.testing.assert_array_equal(
            sk.joint_limits[sk.bone_index(name)], rat.joint_limits[rat.bone_index(name)]
        )
    assert sk.state_map().n_state == 50
    assert {c.bone for c in sk.bone_length_constraints} == {
        c.bone for c in rat.bone_length_constraints
    }


def test_model_rest_pose_is_the_authors(dataset, tmp_path):
    """As the authors' forward model: every bone along +z at rest with the identity frame,
    except the girdles, whose frames come from skeleton_coords (anatomy.get_skeleton_coords0);
    root markers get no offset."""
    d = np.load(dataset.folder / "model.npy", allow_pickle=True).item()
    jn = [n[len("joint_") :] for n in d["joint_order"]]
    # a girdle frame that is not the bundled model's: a turn about the bone's own axis
    edges = d["skeleton_edges"]
    hip = int(np.flatnonzero(edges[:, 1] == jn.index("hip_left"))[0])
    c = d["skeleton_coords"][hip].copy()
    d["skeleton_coords"][hip] = c @ acm_rs.rodrigues(np.array([0.0, 0.0, 0.3]))
    np.save(tmp_path / "model.npy", d, allow_pickle=True)
    m = af.read_model(tmp_path)
    sk = m.skeleton
    frames = sk.rest_frames
    girdles = {"hip_left", "hip_right", "shoulder_left", "shoulder_right"}
    for b, name in enumerate(sk.bone_names):
        if name not in girdles:
            np.testing.assert_allclose(frames[b], np.eye(3), atol=1e-12)
    # hips: the file's frame through float16 Euler angles (within float16 rounding)
    np.testing.assert_allclose(
        frames[sk.bone_index("hip_left")], d["skeleton_coords"][hip], atol=2e-3
    )
    assert not np.allclose(frames[sk.bone_index("hip_left")], c, atol=1e-2)
    # root markers: fixed at the root
    root_markers = [k for k, j in enumerate(sk.marker_joints) if sk.parents[j] < 0]
    assert root_markers and np.all(sk.marker_bounds[root_markers] == 0.0)
    # the explicit frames survive a save/load round trip
    sk.save(tmp_path / "sk.toml")
    back = acm_rs.Skeleton.load(tmp_path / "sk.toml")
    np.testing.assert_allclose(back.rest_frames, frames, atol=1e-12)
    t, r = np.array([1.0, 2.0, 3.0]), np.random.default_rng(0).normal(size=(sk.n_bones, 3))
    np.testing.assert_allclose(back.forward(t, r)[1], sk.forward(t, r)[1], atol=1e-9)


def test_model_other_topology_builds_skeleton(dataset, tmp_path):
    """A model without one marker is still read (names, pairs and limits by name)."""
    d = np.load(dataset.folder / "model.npy", allow_pickle=True).item()
    drop = d["joint_marker_order"].index("marker_side_left_start")
    d["joint_marker_order"] = [n for i, n in enumerate(d["joint_marker_order"]) if i != drop]
    d["joint_marker_index"] = np.delete(d["joint_marker_index"], drop)
    np.save(tmp_path / "model.npy", d, allow_pickle=True)
    m = af.read_model(tmp_path)
    sk = m.skeleton
    assert sk.n_joints == 29 and sk.n_markers == 42 and sk.units == "cm"
    rat = acm_rs.models.rat()
    b = sk.bone_index("knee_left")
    np.testing.assert_array_equal(sk.joint_limits[b], rat.joint_limits[rat.bone_index("knee_left")])
    assert "side_right" not in dict(sk.symmetry["markers"]).values()
    assert sk.state_map().n_state == 50


def test_model_links_are_applied_as_the_file_holds_them(dataset, tmp_path):
    """Any skeleton_vertices_links: the skeleton applies exactly those (in our bone order),
    with the global rotation (file bone 0) moving every bone, and says which rule it is."""
    d = np.load(dataset.folder / "model.npy", allow_pickle=True).item()
    links = np.array(d["skeleton_vertices_links"], bool)
    links[3:] = np.eye(len(links), dtype=bool)[3:]  # each rotation moves only its own bone
    d["skeleton_vertices_links"] = links
    np.save(tmp_path / "model.npy", d, allow_pickle=True)
    m = af.read_model(tmp_path)
    assert m.links_rule == "other"
    edges = d["skeleton_edges"]
    jn = [n.removeprefix("joint_") for n in d["joint_order"]]
    file_bone = [int(np.flatnonzero(edges[:, 1] == jn.index(n))[0]) for n in m.skeleton.bone_names]
    expect = links.copy()
    expect[0] = True
    np.testing.assert_array_equal(m.skeleton.bone_links, expect[np.ix_(file_bone, file_bone)])
    np.testing.assert_array_equal(np.array(file_bone)[m.skeleton.link_order], np.arange(len(edges)))
    tree = af.read_model(dataset.folder)
    assert tree.links_rule == "tree" and tree.skeleton.custom_links is not None
    r = np.random.default_rng(0).normal(scale=0.3, size=(m.skeleton.n_bones, 3))
    assert (
        np.abs(
            m.skeleton.forward(np.zeros(3), r)[0] - tree.skeleton.forward(np.zeros(3), r)[0]
        ).max()
        > 0.1
    )


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda d: ["not", "a", "dict"], "expected a pickled dict"),
        (lambda d: {k: v for k, v in d.items() if k != "skeleton_edges"}, r"lacks keys \['skel"),
        (lambda d: d | {"joint_order": ["head"] + d["joint_order"][1:]}, "not of the form joint_"),
        (lambda d: d | {"skeleton_edges": d["skeleton_edges"][:-1]}, "skeleton_edges must have"),
        (lambda d: d | {"joint_marker_index": d["joint_marker_index"] + 100}, "missing joints"),
        (lambda d: d | {"skeleton_vertices_links": np.eye(3, dtype=bool)}, "links has shape"),
    ],
)
def test_model_refuses_unexpected(dataset, tmp_path, mutate, match):
    d = np.load(dataset.folder / "model.npy", allow_pickle=True).item()
    np.save(tmp_path / "model.npy", np.array(mutate(d), dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match=match):
        af.read_model(tmp_path / "model.npy")


# -- labels ---------------------------------------------------------------------------------------
def test_labels_dlc(dataset):
    cfg = af.read_configuration(dataset.folder)
    path = af.labels_dlc_path(dataset.folder, cfg)
    assert path.name == "labels_dlc_000000_000120.npy"
    m = af.read_model(dataset.folder)
    raw = af.read_labels_dlc(path, m.acm_marker_names)
    assert raw.points.shape == (4, 120, 43, 2) and raw.likelihood.shape == (4, 120, 43)
    np.testing.assert_array_equal(raw.frames, dataset.frames)
    lab = af.read_labels_dlc(path, m.acm_marker_names, pcutoff=cfg.pcutoff)
    assert np.all(np.isnan(lab.points[raw.likelihood <= 0.9]))
    assert np.all(np.isfinite(lab.points[raw.likelihood > 0.9]))
    ours = lab.reorder(dataset.skeleton.marker_names)
    truth = dataset.skeleton.project(dataset.rig, dataset.t, dataset.r)
    err = np.linalg.norm(ours.points - truth, axis=-1)
    ok = np.isfinite(err)
    assert ok.mean() > 0.8 and np.median(err[ok]) < 3.0  # 1.5 px noise
    sel = ours.select(cfg.frames)
    np.testing.assert_array_equal(sel.frames, cfg.frames)
    np.testing.assert_array_equal(sel.points, ours.points[:, 20:100:4])
    with pytest.raises(ValueError, match=r"frames \[500\] are not in the labels"):
        ours.select([500])


def test_labels_dlc_path_errors(dataset, tmp_path):
    with pytest.raises(FileNotFoundError, match="expected one labels_dlc"):
        af.labels_dlc_path(tmp_path)
    assert af.labels_dlc_path(dataset.folder).name == "labels_dlc_000000_000120.npy"


def test_labels_manual(dataset):
    lab = af.read_labels_manual(
        dataset.folder / "labels_manual.npz", dataset.skeleton.marker_names, n_cams=4
    )
    np.testing.assert_array_equal(lab.frames, dataset.manual_frames)
    assert lab.points.shape == (4, len(dataset.manual_frames), 43, 2) and lab.likelihood is None
    idx = np.searchsorted(dataset.frames, dataset.manual_frames)
    truth = dataset.skeleton.project(dataset.rig, dataset.t[idx], dataset.r[idx])
    err = np.linalg.norm(lab.points - truth, axis=-1)
    ok = np.isfinite(err)
    assert 0.6 < ok.mean() < 0.95 and np.max(err[ok]) < 6.0


def test_labels_manual_unknown_marker(dataset, tmp_path):
    raw = np.load(dataset.folder / "labels_manual.npz", allow_pickle=True)["arr_0"].item()
    first = next(iter(raw))
    raw[first]["spot_knee_lefft"] = np.zeros((4, 2))
    np.savez(tmp_path / "labels_manual.npz", raw)
    m = af.read_model(dataset.folder)
    with pytest.raises(ValueError, match=r"'knee_lefft' \(did you mean 'knee_left'\?\)"):
        af.read_labels_manual(tmp_path / "labels_manual.npz", m.skeleton.marker_names)
    raw[first]["spot_knee_lefft"] = np.zeros((3, 2))
    raw[first]["spot_knee_left"] = np.zeros((3, 2))
    del raw[first]["spot_knee_lefft"]
    np.savez(tmp_path / "labels_manual.npz", raw)
    with pytest.raises(ValueError, match=r"has shape \(3, 2\), expected \(4, 2\)"):
        af.read_labels_manual(tmp_path / "labels_manual.npz", n_cams=4)


# -- origin_coord.npy -----------------------------------------------------------------------------
def test_origin_coord_and_arena_rig(dataset, rng):
    origin, coord = af.read_origin_coord(dataset.folder)
    np.testing.assert_allclose(origin, dataset.origin)
    rig = af.arena_rig(dataset.calib_rig, origin, coord, dataset.scale_factor)
    x_arena = rng.normal(scale=10.0, size=(50, 3)) + [0, 0, 5]
    np.testing.assert_allclose(rig.project(x_arena), dataset.rig.project(x_arena), atol=1e-6)
    x_calib = (coord @ (x_arena / dataset.scale_factor).T).T + origin
    back = af.calibration_to_arena(x_calib, origin, coord, dataset.scale_factor)
    np.testing.assert_allclose(back, x_arena, atol=1e-9)


def test_origin_coord_refuses_non_rotation(tmp_path):
    np.save(tmp_path / "origin_coord.npy", {"origin": np.zeros(3), "coord": 2 * np.eye(3)})
    with pytest.raises(ValueError, match="coord must be a rotation"):
        af.read_origin_coord(tmp_path)
    np.save(tmp_path / "origin_coord.npy", np.zeros(3))
    with pytest.raises(ValueError, match="expected a pickled dict"):
        af.read_origin_coord(tmp_path)


# -- outputs --------------------------------------------------------------------------------------
def test_write_pose_layout(dataset, tmp_path):
    m = af.read_model(dataset.folder)
    res = synthetic_result(n_frames=5, seed=2, skeleton=m.skeleton, rig=dataset.rig)
    path = af.write_pose(tmp_path / "pose.npy", res, m)
    d = np.load(path, allow_pickle=True).item()
    assert set(d) == {"joint_positions_3d", "marker_positions_3d", "marker_positions_2d"}
    assert d["joint_positions_3d"].shape == (5, 29, 3)
    assert d["marker_positions_3d"].shape == (5, 43, 3)
    assert d["marker_positions_2d"].shape == (5, 4, 43, 2)
    k = dataset.acm_joint_names.index("knee_left")
    np.testing.assert_array_equal(
        d["joint_positions_3d"][:, k], res.joints[:, m.skeleton.joint_index("knee_left")]
    )
    q = dataset.acm_marker_names.index("toe_right_002")
    px = (d["marker_positions_2d"][:, 2, q] + 1) * np.array([1280, 1024]) / 2
    np.testing.assert_allclose(
        px, res.projected()[2, :, m.skeleton.marker_index("toe_right_002")], atol=1e-9
    )


def test_write_save_dict(tmp_path):
    res = synthetic_result(n_frames=4, seed=1)
    n = res.state_mean.shape[1]
    with pytest.raises(ValueError, match=r"lacks \['mu0', 'V0', 'Vz', 'Vx_diag'\]"):
        af.write_save_dict(tmp_path / "save_dict.npy", res)
    res.info["params"] = {
        "mu0": np.zeros(n),
        "V0": np.eye(n),
        "Vz": 2 * np.eye(n),
        "Vx_diag": np.full(8, 3.0),
    }
    d = np.load(af.write_save_dict(tmp_path / "save_dict.npy", res), allow_pickle=True).item()
    assert d["mu_uks"].shape == (5, n) and d["var_uks"].shape == (5, n, n)
    np.testing.assert_array_equal(d["mu_uks"][1:], res.state_mean)
    np.testing.assert_array_equal(d["var_uks"][0], np.eye(n))
    np.testing.assert_array_equal(d["var_g"], 3 * np.eye(8))
    res.state_cov = None
    d = np.load(af.write_save_dict(tmp_path / "s2.npy", res), allow_pickle=True).item()
    assert set(d) == {"mu_fit"} and np.all(np.isnan(d["mu_fit"][0]))
