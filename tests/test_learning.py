"""Skeleton learning (eq. 9/12): ground-truth recovery, exact gradient, first-pose fit,
DeepLabCut labels, CLI, bad input."""

from __future__ import annotations

import numpy as np
import pytest

import acm_rs
from acm_rs import _native, datasets
from acm_rs.cli import main as cli_main
from acm_rs.demo import demo_rig
from acm_rs.dlc import read_labels
from acm_rs.learning import initial_poses, match_marker_names, triangulate

NOISE_PX = 2.0


@pytest.fixture(scope="module")
def synthetic():
    rat = acm_rs.models.rat()
    true = datasets.individual_skeleton(rat, seed=1)
    rig = demo_rig()
    t, r = datasets.random_poses(true, 150, seed=2)
    labels = datasets.noisy_labels(rig, true, t, r, NOISE_PX, missing=0.3, seed=3)
    return rat, true, rig, t, r, labels


@pytest.fixture(scope="module")
def learned(synthetic):
    rat, _, rig, _, _, labels = synthetic
    return acm_rs.learn_skeleton(rig, rat, labels, progress=False)


def test_recovers_bone_lengths_and_offsets(synthetic, learned):
    rat, true, *_ = synthetic
    rel = np.abs(learned.skeleton.bone_lengths / true.bone_lengths - 1.0)
    tail = np.array([name.startswith("tail") for name in rat.bone_names])
    # Most bones are within 2 %; the worst are at the noise floor in absolute terms (2 px at
    # ~60 cm is ~0.8 mm), which for sub-centimetre bones is a few per cent.
    assert np.median(rel[~tail]) < 0.01
    absolute = np.abs(learned.skeleton.bone_lengths - true.bone_lengths)
    assert absolute[~tail].max() < 0.1, dict(zip(rat.bone_names, absolute.round(3), strict=True))
    assert np.mean(rel[~tail] < 0.02) > 0.85
    # Single tail bones are weakly determined (their markers may slide along the bones, and
    # consecutive tail bones trade length), so only the whole tail is held to a tight bound.
    total = learned.skeleton.bone_lengths[tail].sum() / true.bone_lengths[tail].sum()
    assert abs(total - 1.0) < 0.05, total
    err = np.linalg.norm(learned.skeleton.marker_offsets - true.marker_offsets, axis=1)
    assert np.median(err) < 0.05  # cm
    assert err.max() < 0.3  # a few mm
    # The generic model started far away (lengths perturbed by ~8 %).
    assert np.abs(rat.bone_lengths / true.bone_lengths - 1.0)[~tail].max() > 0.05


def test_symmetry_and_bounds_hold(learned):
    sk = learned.skeleton
    for left, right in sk.symmetry["joints"]:
        assert sk.bone_lengths[sk.bone_index(left)] == sk.bone_lengths[sk.bone_index(right)]
    for left, right in sk.symmetry["markers"]:
        a, b = sk.marker_offsets[sk.marker_index(left)], sk.marker_offsets[sk.marker_index(right)]
        np.testing.assert_allclose(b, a * [-1, 1, 1], atol=1e-12)
    lo, hi = sk.marker_bounds[..., 0], sk.marker_bounds[..., 1]
    assert np.all(sk.marker_offsets >= lo - 1e-9) and np.all(sk.marker_offsets <= hi + 1e-9)
    lim = sk.joint_limits
    assert np.all(learned.r >= lim[..., 0] - 1e-9) and np.all(learned.r <= lim[..., 1] + 1e-9)


def test_reprojects_to_the_noise_level(learned):
    # 2D error of isotropic noise with sigma 2 px has RMS 2.83 px; the fit absorbs a little.
    assert 0.8 * NOISE_PX * np.sqrt(2) < learned.rms < 1.05 * NOISE_PX * np.sqrt(2)
    assert learned.per_camera_error.shape == (4,)
    assert np.all(np.isfinite(learned.per_marker_error))
    assert "RMS reprojection error" in learned.summary()


def test_gradient_matches_finite_differences(synthetic):
    rat, _, rig, _, _, labels = synthetic
    lab = np.ascontiguousarray(labels[:, :3].transpose(1, 0, 2, 3))
    lim = rat.joint_limits
    sym = rat.symmetry_map()
    pairs_b = np.array([(rat.bone_index(a), rat.bone_index(b)) for a, b in rat.symmetry["joints"]])
    pairs_m = np.array(
        [(rat.marker_index(a), rat.marker_index(b)) for a, b in rat.symmetry["markers"]]
    )
    p = _native.NativeLearning(
        rat._native, rig.get_params(), lab, np.ascontiguousarray(lim[..., 0]),
        np.ascontiguousarray(lim[..., 1]), acm_rs.Normalization()._tuple(), pairs_b, pairs_m, 1.0,
    )  # fmt: skip
    assert p.n_skeleton_params == sym.n_reduced_bones + 3 * sym.n_reduced_markers
    rng = np.random.default_rng(0)
    x = rng.normal(scale=0.2, size=p.n_params)
    x[: sym.n_reduced_bones] = sym.reduce_lengths(rat.bone_lengths)
    x[p.n_skeleton_params :: 50] += 0.1  # translations (normalised by c_t)
    f, g = p.value_and_grad(x)
    h = 1e-6
    for i in rng.choice(p.n_params, 40, replace=False):
        e = np.zeros_like(x)
        e[i] = h
        fd = (p.value_and_grad(x + e)[0] - p.value_and_grad(x - e)[0]) / (2 * h)
        assert abs(fd - g[i]) < 1e-6 * (1 + abs(fd)), (i, fd, g[i])
    assert f > 0


def test_first_pose_fit_recovers_a_noise_free_frame(synthetic):
    _, true, rig, t, r, _ = synthetic
    px = true.project(rig, t[5], r[5])
    t_fit, r_fit, info = acm_rs.fit_pose(rig, true, px)
    assert info["rms_px"] < 0.01
    j_fit, _ = true.forward(t_fit, r_fit)
    j_true, _ = true.forward(t[5], r[5])
    assert np.abs(j_fit - j_true).max() < 0.05  # cm; joints of the fitted pose


def test_triangulation_and_initial_poses(synthetic):
    _, true, rig, t, r, _ = synthetic
    _, markers = true.forward(t[:4], r[:4])
    px = rig.project(markers)
    np.testing.assert_allclose(triangulate(rig, px), markers, atol=1e-6)
    t0, r0 = initial_poses(rig, true, px)
    # A rough alignment (limbs, neck and tail at mid-range): the snout lands within a few cm
    # of the truth on a 25 cm animal, and the body axis points the right way.
    assert np.linalg.norm(t0 - t[:4], axis=1).max() < 6.0
    j0, _ = true.forward(t0, r0)
    j, _ = true.forward(t[:4], r[:4])
    tail_base = true.joint_index("spine_001")
    axis0, axis = j0[:, tail_base] - j0[:, 0], j[:, tail_base] - j[:, 0]
    cos = np.einsum("fi,fi->f", axis0, axis) / np.linalg.norm(axis0, axis=1)
    assert (cos / np.linalg.norm(axis, axis=1)).min() > 0.9


def test_marker_name_mapping(synthetic):
    rat = synthetic[0]
    idx = match_marker_names(["spot_head_001", "marker_spine_002_start", "knee_left"], rat)
    assert [rat.marker_names[i] for i in idx] == ["head_001", "spine_002", "knee_left"]
    with pytest.raises(ValueError, match="unknown markers \\['nose'\\]"):
        match_marker_names(["nose", "head_001"], rat)


def test_bad_input(synthetic):
    rat, _, rig, _, _, labels = synthetic
    few = labels[:, :4].copy()
    few[:, 2] = np.nan
    few[0, 2, :2] = 100.0
    with pytest.raises(ValueError, match="frame 2 has 2 labelled 2D points"):
        acm_rs.learn_skeleton(rig, rat, few, progress=False)
    with pytest.raises(ValueError, match="3 cameras but the rig has 4"):
        acm_rs.learn_skeleton(rig, rat, labels[:3, :4], progress=False)
    with pytest.raises(ValueError, match="unknown markers"):
        acm_rs.learn_skeleton(
            rig, rat, labels[:, :4, :2], marker_names=["head_001", "nose"], progress=False
        )
    bad = labels[:, :4].copy()
    bad[1, 1, 1, 0] = np.inf
    with pytest.raises(ValueError, match="infinity"):
        acm_rs.learn_skeleton(rig, rat, bad, progress=False)
    with pytest.raises(ValueError, match="NaN"):  # a NaN calibration cannot even be built
        rig.set_params(np.where(np.arange(16) == 3, np.nan, rig.get_params()))


def write_dlc_csv(path, frames, bodyparts, xy):
    """A CollectedData CSV as DeepLabCut writes it (3 index columns, 3 header rows)."""
    head = [
        ["scorer", "", ""] + ["me"] * (2 * len(bodyparts)),
        ["bodyparts", "", ""] + [b for b in bodyparts for _ in (0, 1)],
        ["coords", "", ""] + ["x", "y"] * len(bodyparts),
    ]
    rows = []
    for f, row in zip(frames, xy, strict=True):
        vals = ["" if np.isnan(v) else f"{v:.6f}" for v in row.ravel()]
        rows.append(["labeled-data", "cam", f"img{f:04d}.png"] + vals)
    path.write_text("\n".join(",".join(r) for r in head + rows) + "\n")


def test_read_dlc_labels_of_several_cameras(tmp_path, synthetic):
    rat, _, rig, _, _, labels = synthetic
    names = list(rat.marker_names[:10])
    paths = []
    for c in range(len(rig)):
        frames = [0, 1, 2, 3] if c != 2 else [1, 3]  # camera 2 has fewer labelled images
        xy = labels[c, frames][:, :10]
        paths.append(tmp_path / f"CollectedData_cam{c}.csv")
        write_dlc_csv(paths[-1], frames, names, xy)
    ls = read_labels(paths)
    assert ls.bodyparts == names and ls.frames.tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(ls.points[0, :, :10], labels[0, :4, :10], atol=1e-5)
    assert np.isnan(ls.points[2, 0]).all() and np.isnan(ls.points[2, 2]).all()
    np.testing.assert_allclose(ls.points[2, 1], labels[2, 1, :10], atol=1e-5)
    with pytest.raises(ValueError, match="not a DeepLabCut CSV"):
        bad = tmp_path / "bad.csv"
        bad.write_text("a,b\n1,2\n")
        read_labels([bad])


def test_cli_learn(tmp_path, synthetic, capsys):
    rat, true, rig, t, r, _ = synthetic
    rig.save(tmp_path / "calibration.toml")
    labels = datasets.noisy_labels(rig, true, t[:25], r[:25], 1.0, missing=0.2, seed=9)
    paths = []
    for c in range(len(rig)):
        paths.append(tmp_path / f"CollectedData_{c}.csv")
        write_dlc_csv(paths[-1], range(25), list(rat.marker_names), labels[c])
    out = tmp_path / "learned.toml"
    argv = ["learn", "--calibration", str(tmp_path / "calibration.toml"), "--model", "rat",
            "--labels", *map(str, paths), "-o", str(out), "--plots", str(tmp_path)]  # fmt: skip
    assert cli_main(argv) == 0
    text = capsys.readouterr().out
    assert "RMS reprojection error" in text
    learned = acm_rs.Skeleton.load(out)
    assert learned.n_markers == rat.n_markers
    assert (tmp_path / "learned_fit.npz").exists()
    assert (tmp_path / "learn_reprojection.png").read_bytes()[:4] == b"\x89PNG"


def test_calibration_toml_round_trip(tmp_path, rig):
    rig.save(tmp_path / "c.toml", metadata={"error": 0.5})
    again = acm_rs.CameraRig.load(tmp_path / "c.toml")
    np.testing.assert_allclose(again.get_params(), rig.get_params())
    assert again.names == rig.names
    reordered = acm_rs.CameraRig.load(tmp_path / "c.toml", names=["cam2", "cam0"])
    np.testing.assert_allclose(reordered.get_params(), rig.get_params()[[2, 0]])
    with pytest.raises(ValueError, match="no camera named"):
        acm_rs.CameraRig.load(tmp_path / "c.toml", names=["zz"])


def test_read_dlc_h5_multi_animal(tmp_path):
    pd = pytest.importorskip("pandas")
    pytest.importorskip("tables")
    cols = pd.MultiIndex.from_product(
        [["me"], ["rat1", "rat2"], ["head_001", "spine_001"], ["x", "y"]],
        names=["scorer", "individuals", "bodyparts", "coords"],
    )
    index = pd.MultiIndex.from_tuples([("labeled-data", "cam", f"img{f:03d}.png") for f in (7, 9)])
    values = np.arange(2 * 8, dtype=float).reshape(2, 8)
    values[1, 4] = np.nan
    pd.DataFrame(values, index=index, columns=cols).to_hdf(
        tmp_path / "CollectedData_me.h5", key="df_with_missing", mode="w"
    )
    with pytest.raises(ValueError, match="several individuals"):
        read_labels([tmp_path / "CollectedData_me.h5"])
    ls = read_labels([tmp_path / "CollectedData_me.h5"], individual="rat2")
    assert ls.frames.tolist() == [7, 9] and ls.bodyparts == ["head_001", "spine_001"]
    np.testing.assert_array_equal(ls.points[0, 0], [[4.0, 5.0], [6.0, 7.0]])
    assert np.isnan(ls.points[0, 1, 0, 0])


def test_pose_state_initialises_the_tracker(learned):
    # mu_0 of the tracker: the learned pose in the erf-constrained state space (Alg. 10).
    z = learned.pose_state(3)
    sm = learned.skeleton.state_map()
    assert z.shape == (sm.n_state,) == (50,)
    t, r = sm.to_pose(z)
    np.testing.assert_allclose(t, learned.t[3], atol=1e-9)
    np.testing.assert_allclose(r, learned.r[3], atol=1e-6)
