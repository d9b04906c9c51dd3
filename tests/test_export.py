"""Export round trips: each file is read back with the library the next tool uses."""

from __future__ import annotations

import os
import tomllib
import warnings

import numpy as np
import pytest
from acm_fixture import synthetic_result

import acm_rs
from acm_rs import export

pd = pytest.importorskip("pandas")


@pytest.fixture(scope="module")
def result():
    return synthetic_result(n_frames=10, seed=3)


@pytest.fixture(scope="module")
def det_result():
    return synthetic_result(n_frames=6, seed=4, cov=False)


# -- anipose CSV --------------------------------------------------------------------------------
def test_anipose_columns_exact():
    cols = export.anipose_columns(["nose", "tail"])
    assert cols[:6] == ["nose_x", "nose_y", "nose_z", "nose_error", "nose_ncams", "nose_score"]
    assert cols[6:12] == ["tail_x", "tail_y", "tail_z", "tail_error", "tail_ncams", "tail_score"]
    assert cols[12:21] == [f"M_{i}{j}" for i in range(3) for j in range(3)]
    assert cols[21:] == ["center_0", "center_1", "center_2", "fnum"]


@pytest.mark.parametrize("points", ["joints", "markers"])
def test_anipose_csv_round_trip(result, tmp_path, points):
    frames = np.arange(100, 100 + result.n_frames)
    files = export.to_anipose_csv(result, tmp_path / "pose.csv", points=points, frames=frames)
    assert files == [tmp_path / "pose.csv", tmp_path / "pose_variance.csv"]
    df = pd.read_csv(files[0])
    names = result.joint_names if points == "joints" else result.marker_names
    assert list(df.columns) == export.anipose_columns(names)
    pos = result.joints if points == "joints" else result.markers
    for k, n in enumerate(names):
        got = df[[f"{n}_x", f"{n}_y", f"{n}_z"]].to_numpy()
        np.testing.assert_allclose(got, pos[:, k], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(df["fnum"], frames)
    m = df[[f"M_{i}{j}" for i in range(3) for j in range(3)]].to_numpy().reshape(-1, 3, 3)
    np.testing.assert_array_equal(m, np.broadcast_to(np.eye(3), m.shape))
    assert np.all(df[["center_0", "center_1", "center_2"]].to_numpy() == 0)
    assert df[f"{names[0]}_ncams"].dtype.kind == "i"

    var = pd.read_csv(files[1])
    assert list(var.columns) == ["fnum"] + [f"{n}_{a}_var" for n in names for a in "xyz"]
    np.testing.assert_array_equal(var["fnum"], frames)
    assert np.all(var.drop(columns="fnum").to_numpy() >= 0)
    if points == "joints":
        got = var[[f"{names[2]}_{a}_var" for a in "xyz"]].to_numpy()
        np.testing.assert_allclose(got, result.joints_std[:, 2] ** 2, rtol=1e-12)


def test_anipose_quality_columns_match_detections(result, tmp_path):
    """error/ncams/score of a marker computed independently from detections and projection."""
    (path, _) = export.to_anipose_csv(result, tmp_path / "m.csv", points="markers")
    df = pd.read_csv(path)
    proj = result.projected()
    k = 5
    name = result.marker_names[k]
    d = result.detections[:, :, k]
    seen = np.isfinite(d[..., 0])
    ncams = seen.sum(axis=0)
    np.testing.assert_array_equal(df[f"{name}_ncams"], ncams)
    for t in range(result.n_frames):
        cams = np.flatnonzero(seen[:, t])
        if cams.size == 0:
            assert np.isnan(df[f"{name}_error"][t]) and df[f"{name}_score"][t] == 0
        else:
            e = np.mean([np.linalg.norm(d[c, t] - proj[c, t, k]) for c in cams])
            assert df[f"{name}_error"][t] == pytest.approx(e, rel=1e-9)
            assert df[f"{name}_score"][t] == 1.0
    # a camera that never sees the marker gives ncams 0 and score 0 (model-imputed position)
    res2 = synthetic_result(n_frames=4, seed=5, missing=0.0)
    res2.detections[:, 1, 0] = np.nan
    lik = np.full(res2.detections.shape[:-1], 0.95)
    lik[0, 2, 0] = 0.91
    [p2] = export.to_anipose_csv(
        res2, tmp_path / "m2.csv", points="markers", likelihood=lik, variance=False
    )
    df2 = pd.read_csv(p2)
    n0 = res2.marker_names[0]
    assert df2[f"{n0}_ncams"][1] == 0 and df2[f"{n0}_score"][1] == 0
    assert df2[f"{n0}_score"][2] == pytest.approx(np.mean([0.91, 0.95, 0.95, 0.95]))
    assert not (tmp_path / "m2_variance.csv").exists()


def test_joint_quality_aggregates_attached_markers(result, tmp_path):
    (path, _) = export.to_anipose_csv(result, tmp_path / "j.csv")
    df = pd.read_csv(path)
    sk = result.skeleton
    mj = np.asarray(sk.marker_joints)
    for j, name in enumerate(sk.joint_names):
        ks = np.flatnonzero(mj == j)
        if ks.size == 0:
            assert np.all(df[f"{name}_ncams"] == 0) and np.all(np.isnan(df[f"{name}_error"]))
            continue
        seen = np.isfinite(result.detections[:, :, ks, 0]).any(axis=2)
        np.testing.assert_array_equal(df[f"{name}_ncams"], seen.sum(axis=0))


def test_anipose_csv_deterministic_variance_is_nan(det_result, tmp_path):
    _, side = export.to_anipose_csv(det_result, tmp_path / "d.csv")
    var = pd.read_csv(side)
    assert var.drop(columns="fnum").isna().all().all()


def test_anipose_csv_errors(result, tmp_path):
    with pytest.raises(ValueError, match="points must be 'joints' or 'markers'"):
        export.to_anipose_csv(result, tmp_path / "x.csv", points="bones")
    with pytest.raises(ValueError, match="must end in .csv"):
        export.to_anipose_csv(result, tmp_path / "x.txt")
    with pytest.raises(ValueError, match=r"frames must have shape \(10,\)"):
        export.to_anipose_csv(result, tmp_path / "x.csv", frames=np.arange(3))
    with pytest.raises(ValueError, match="likelihood must have shape"):
        export.to_anipose_csv(result, tmp_path / "x.csv", likelihood=np.ones((2, 2)))
    assert not list(tmp_path.iterdir())


def test_marker_variance_matches_monte_carlo(result):
    """The unscented marker variance agrees with sampling the posterior (PoseResult.sample)."""
    from acm_rs.export._common import posterior_variance

    var = posterior_variance(result, "markers")
    _, mk = result.sample(3000, seed=1)
    mc = mk.var(axis=0)
    big = mc > 1e-4
    ratio = var[big] / mc[big]
    assert np.median(np.abs(ratio - 1)) < 0.1
    assert np.all((ratio > 0.5) & (ratio < 2.0))


# -- NWB ------------------------------------------------------------------------------------------
def test_nwb_round_trip(result, tmp_path):
    pytest.importorskip("ndx_pose")
    from pynwb import NWBHDF5IO, validate

    path = tmp_path / "session.nwb"
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        out = export.to_nwb(
            result, path, session_description="synthetic rat", rate=50.0, subject_id="rat7"
        )
    assert out == path and path.exists()
    assert not [p for p in tmp_path.iterdir() if p.name != "session.nwb"]  # no temp files left
    errors = validate(path=str(path))
    assert not errors, errors
    with NWBHDF5IO(str(path), "r") as io:
        f = io.read()
        assert f.session_description == "synthetic rat"
        assert f.subject.subject_id == "rat7"
        beh = f.processing["behavior"]
        skels = beh["Skeletons"].skeletons
        sj = skels["rat_joints"]
        assert list(sj.nodes[:]) == list(result.joint_names)
        np.testing.assert_array_equal(sj.edges[:], result.skeleton.bones)
        assert list(skels["rat_markers"].nodes[:]) == list(result.marker_names)

        pj = beh["PoseEstimationJoints"]
        assert pj.skeleton.name == "rat_joints"
        assert pj.source_software == "acm-rs"
        assert set(pj.pose_estimation_series) == set(result.joint_names)
        for k, n in enumerate(result.joint_names):
            s = pj.pose_estimation_series[n]
            np.testing.assert_allclose(s.data[:], result.joints[:, k], rtol=0, atol=1e-12)
            assert s.unit == "centimeters" and s.rate == 50.0
            assert np.all((s.confidence[:] >= 0) & (s.confidence[:] <= 1))
        pm = beh["PoseEstimationMarkers"]
        k = 7
        s = pm.pose_estimation_series[result.marker_names[k]]
        np.testing.assert_allclose(s.data[:], result.markers[:, k], rtol=0, atol=1e-12)
        std = beh["PosteriorStdJoints"]
        np.testing.assert_allclose(std.data[:], result.joints_std, rtol=1e-12)
        assert beh["PosteriorStdMarkers"].data.shape == result.markers.shape

        # calibration: CalibratedCamera devices, linked from the per-camera 2D detections
        for c, cam in enumerate(result.rig):
            dev = f.devices[cam.name]
            np.testing.assert_allclose(dev.intrinsic_matrix[:], cam.matrix, rtol=1e-6)
            np.testing.assert_allclose(dev.rotation_matrix[:], cam.rotation_matrix, atol=1e-6)
            np.testing.assert_allclose(dev.translation_vector[:], cam.tvec, rtol=1e-6, atol=1e-5)
            view = pm.pose_estimations[f"detections_{cam.name}"]
            assert view.device is dev
            d = view.pose_estimation_series[result.marker_names[3]].data[:]
            np.testing.assert_array_equal(d, result.detections[c, :, 3])


def test_nwb_timestamps_and_errors(det_result, tmp_path):
    pytest.importorskip("ndx_pose")
    from pynwb import NWBHDF5IO

    ts = np.linspace(1.0, 2.0, det_result.n_frames)
    path = export.to_nwb(
        det_result, tmp_path / "t.nwb", session_description="s", timestamps=ts, detections=False
    )
    with NWBHDF5IO(str(path), "r") as io:
        beh = io.read().processing["behavior"]
        s = beh["PoseEstimationJoints"].pose_estimation_series["head_001"]
        np.testing.assert_allclose(s.timestamps[:], ts)
        assert len(beh["PoseEstimationMarkers"].pose_estimations) == 0
        assert np.all(np.isnan(beh["PosteriorStdMarkers"].data[:]))
    with pytest.raises(ValueError, match="rate must be a positive frame rate"):
        export.to_nwb(det_result, tmp_path / "x.nwb", session_description="s")
    with pytest.raises(ValueError, match="session_description"):
        export.to_nwb(det_result, tmp_path / "x.nwb", session_description="", rate=10)
    with pytest.raises(ValueError, match=r"timestamps must have shape \(6,\)"):
        export.to_nwb(det_result, tmp_path / "x.nwb", session_description="s", timestamps=[0, 1])
    assert not (tmp_path / "x.nwb").exists()


# -- C3D ------------------------------------------------------------------------------------------
def test_c3d_round_trip(result, tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    res = synthetic_result(n_frames=5, seed=6)
    res.markers[2, 4] = np.nan
    res.detections[:, 0, 1] = np.nan  # marker 1 unseen in frame 0 -> imputed
    path = export.to_c3d(res, tmp_path / "trial.c3d", rate=120.0, joints=True)
    c = ezc3d.c3d(str(path))
    labels = c["parameters"]["POINT"]["LABELS"]["value"]
    assert labels == list(res.marker_names) + ["joint_" + n for n in res.joint_names]
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["mm"]
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == 120.0
    pts = c["data"]["points"]
    assert pts.shape == (4, res.skeleton.n_markers + res.skeleton.n_joints, 5)
    want = np.concatenate([res.markers, res.joints], axis=1).transpose(2, 1, 0) * 10.0  # cm->mm
    ok = np.isfinite(want)
    np.testing.assert_allclose(pts[:3][ok], want[ok], rtol=1e-6, atol=1e-3)  # float32 storage
    assert np.all(np.isnan(pts[:3, 4, 2]))
    resid = c["data"]["meta_points"]["residuals"]
    assert resid[0, 4, 2] == -1
    from acm_rs.gapfill.io import read

    m = read(path)
    # the convention of every acm-rs C3D: 1 detected, 0 placed by the model only, in the
    # fourth word's low byte as the C3D specification puts it (ezc3d 1.7.2 reads that byte as
    # camera mask: tests/test_real_c3d_encoding.py)
    assert m.source["residual"][0, 1] == 0 and m.source["residual"][0, 0] == 1
    assert os.stat(path).st_mode & 0o777 != 0o600
    assert m.filled is not None and m.filled[0, 1].all() and not m.filled[0, 0].any()


def test_long_c3d_export_writes_the_bytes_ezc3d_writes(tmp_path, monkeypatch):
    """Above the block threshold (long recordings) the frames are written in blocks after
    ezc3d's header and parameters: the same file as ezc3d writes."""
    pytest.importorskip("ezc3d")
    from acm_rs.gapfill import c3d_stream

    res = synthetic_result(n_frames=7, seed=8)
    res.markers[3, 2] = np.nan
    res.detections[:, 1, 0] = np.nan  # marker 0 unseen in frame 1 -> placed by the model
    a = export.to_c3d(res, tmp_path / "a.c3d", rate=100.0, joints=True)
    monkeypatch.setattr(c3d_stream, "STREAM_BYTES", 0)
    calls = []
    real = c3d_stream.write_streamed
    monkeypatch.setattr(c3d_stream, "write_streamed", lambda *a: calls.append(1) or real(*a))
    b = export.to_c3d(res, tmp_path / "b.c3d", rate=100.0, joints=True)
    assert calls and a.read_bytes() == b.read_bytes()


def test_c3d_units_and_errors(result, tmp_path):
    ezc3d = pytest.importorskip("ezc3d")
    path = export.to_c3d(result, tmp_path / "m.c3d", rate=30, units="m")
    c = ezc3d.c3d(str(path))
    assert c["parameters"]["POINT"]["UNITS"]["value"] == ["m"]
    np.testing.assert_allclose(c["data"]["points"][:3, 0].T, result.markers[:, 0] / 100, atol=1e-6)
    with pytest.raises(ValueError, match="units must be one of"):
        export.to_c3d(result, tmp_path / "x.c3d", rate=30, units="inch")
    with pytest.raises(ValueError, match="rate must be a positive"):
        export.to_c3d(result, tmp_path / "x.c3d", rate=0)
    with pytest.raises(ValueError, match="clash with marker names"):
        export.to_c3d(result, tmp_path / "x.c3d", rate=30, joints=True, joint_prefix="")


# -- NPZ ------------------------------------------------------------------------------------------
def test_npz_round_trip(result, tmp_path):
    path = export.to_npz(result, tmp_path / "pose.npz")
    with np.load(path) as z:  # no allow_pickle needed
        np.testing.assert_array_equal(z["joints"], result.joints)
        np.testing.assert_array_equal(z["state_cov"], result.state_cov)
        np.testing.assert_array_equal(z["detections"], result.detections)
    d = export.read_npz(path)
    assert d["units"] == "cm" and d["version"] == 1
    np.testing.assert_array_equal(d["markers"], result.markers)
    np.testing.assert_array_equal(d["r"], result.r)
    assert list(d["joint_names"]) == list(result.joint_names)
    assert list(d["camera_names"]) == result.rig.names
    np.testing.assert_array_equal(d["camera_params"], result.rig.get_params())
    assert d["info"]["method"] == "ukf"
    sk = acm_rs.Skeleton.from_dict(tomllib.loads(d["skeleton_toml"]))
    np.testing.assert_allclose(sk.bone_lengths, result.skeleton.bone_lengths, atol=1e-9)
    calib = tomllib.loads(d["calibration_toml"])
    assert calib["cam_0"]["name"] == result.rig.names[0]
    assert d["markers_var"].shape == result.markers.shape
    bad = tmp_path / "other.npz"
    np.savez(bad, a=np.zeros(2))
    with pytest.raises(ValueError, match="not an acm-rs pose file"):
        export.read_npz(bad)


def test_atomic_write_keeps_old_file_on_failure(result, tmp_path, monkeypatch):
    """A crash while writing leaves the previous file and no temporary file."""
    ezc3d = pytest.importorskip("ezc3d")
    path = export.to_c3d(result, tmp_path / "a.c3d", rate=30)
    before = path.read_bytes()

    def boom(self, name):
        with open(name, "wb") as fh:
            fh.write(b"partial")
        raise RuntimeError("killed")

    monkeypatch.setattr(ezc3d.c3d, "write", boom)
    with pytest.raises(RuntimeError, match="killed"):
        export.to_c3d(result, path, rate=30)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["a.c3d"]
