"""Multi-camera calibration (ACM supp. sec. 2.2, eq. 7) on synthetic rigs with known truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from calib_synthetic import make_recording
from scipy.sparse import csr_matrix

import acm_rs
from acm_rs import _native
from acm_rs.calibration import (
    CalibrationResult,
    calibrate,
    frame_from_points,
    load_acm_calibration,
    save_acm_calibration,
)
from acm_rs.rotation import rodrigues

SIZE = (1280, 1024)


def _angle_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    c = (np.trace(r_a.T @ r_b) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


@pytest.fixture(scope="module")
def four_cam():
    rec = make_recording(n_cams=4, n_frames=60, noise=0.3, seed=11)
    return rec, calibrate(rec.corners, rec.board_points, SIZE)


@pytest.mark.parametrize("n_cams,seed", [(3, 1), (4, 2), (6, 3)])
def test_recovers_synthetic_rig(n_cams, seed):
    noise = 0.3
    rec = make_recording(n_cams=n_cams, n_frames=60, noise=noise, seed=seed)
    res = calibrate(rec.corners, rec.board_points, SIZE)
    truth, est = rec.rig.get_params(), res.rig.get_params()
    # Intrinsics: focal lengths to 0.1 %, principal point to 2 px, k1 to 0.01.
    np.testing.assert_allclose(est[:, 6:8], truth[:, 6:8], rtol=1e-3)
    np.testing.assert_allclose(est[:, 8:10], truth[:, 8:10], atol=2.0)
    np.testing.assert_allclose(est[:, 10], truth[:, 10], atol=0.01)
    np.testing.assert_allclose(est[:, 11], truth[:, 11], atol=0.05)
    assert np.all(est[:, 12:] == 0)  # p1, p2, k3 are not part of the model
    # Extrinsics: camera centres to 2 mm (cameras ~1.3 m apart), rotations to 0.1 degree.
    for ct, ce in zip(rec.rig, res.rig, strict=True):
        assert np.linalg.norm(ct.center - ce.center) < 2.0
        assert _angle_deg(ct.rotation_matrix, ce.rotation_matrix) < 0.1
    # Board poses: corners in world (1-1.5 m from the reference camera) to 3 mm.
    used = res.used_frames
    pts_t = rec.board_points @ rodrigues(rec.board_rvecs[used]).transpose(0, 2, 1)
    pts_t += rec.board_tvecs[used, None]
    assert np.nanmax(np.abs(res.board_world_points()[used] - pts_t)) < 3.0
    # RMS distance ~ sqrt(2) sigma, less the fitted degrees of freedom.
    n_res = 2 * np.isfinite(res.errors).sum()
    expected = noise * np.sqrt(2 * (1 - res.info["n_free_parameters"] / n_res))
    assert abs(res.rms - expected) < 0.05 * expected
    assert res.per_camera_rms.shape == (n_cams,)
    assert np.all(np.abs(res.per_camera_rms - expected) < 0.1 * expected)
    assert res.residuals.shape == rec.corners.shape
    # Residuals exist exactly where a used detection exists.
    det = np.isfinite(rec.corners[..., 0]) & used[None, :, None]
    assert np.array_equal(np.isfinite(res.residuals[..., 0]), det)
    assert res.plausibility()["ok"]


def test_result_attributes_and_unused_views(four_cam):
    rec, res = four_cam
    assert isinstance(res, CalibrationResult)
    assert res.board_rvecs.shape == res.board_tvecs.shape == (60, 3)
    rec2 = make_recording(n_cams=3, n_frames=20, seed=5)
    corners = rec2.corners.copy()
    corners[:, 7] = np.nan  # a view nobody saw
    res2 = calibrate(corners, rec2.board_points, SIZE, camera_names=["a", "b", "c"])
    assert not res2.used_frames[7]
    assert np.all(np.isnan(res2.board_rvecs[7])) and np.all(np.isnan(res2.board_tvecs[7]))
    assert res2.rig.names == ["a", "b", "c"]
    # World frame = reference camera.
    np.testing.assert_allclose(res2.rig[0].params[:6], 0.0, atol=0)


def test_reference_camera_defines_world(four_cam):
    rec, _ = four_cam
    res = calibrate(rec.corners, rec.board_points, SIZE, reference_camera=2)
    np.testing.assert_array_equal(res.rig[2].params[:6], 0.0)
    # Same relative geometry as the truth: camera 0 seen from camera 2.
    rel_t = rec.rig[2].rotation_matrix @ rec.rig[0].rotation_matrix.T
    rel_e = res.rig[0].rotation_matrix.T  # camera 2 is the world
    assert _angle_deg(rel_t, rel_e) < 0.1


def test_jacobian_matches_finite_differences():
    rec = make_recording(n_cams=3, n_frames=6, seed=7, view_dropout=0.0)
    rng = np.random.default_rng(0)
    n_cams, n_frames = 3, 6
    cams = []
    for c in rec.rig:
        p = c.params
        # [fx, fy, cx, cy, k1, k2, r, t, skew]; a nonzero skew, free, for its column's check
        cams.append([p[6], p[7], p[8], p[9], p[10], p[11], *p[0:3], *p[3:6], 2.0])
    poses = np.concatenate([rec.board_rvecs, rec.board_tvecs], axis=1)
    params = np.concatenate([np.ravel(cams), poses.ravel()])
    params += rng.normal(0, 1e-3, params.size) * np.maximum(np.abs(params), 1)
    fixed = np.zeros(params.size, bool)
    fixed[13 + 4] = True  # camera 1's k1
    prob = _native.NativeCalibration(rec.board_points, rec.corners, 0, params, fixed)
    free = prob.free_indices
    assert 13 + 4 not in free and not np.isin(np.arange(6, 12), free).any()
    assert {12, 25, 38} <= set(free)  # every skew is free here (the reference camera's too)
    x = params[free]
    jac = csr_matrix(
        (prob.jacobian_data(x), prob.indices, prob.indptr),
        shape=(2 * prob.n_observations, prob.n_free),
    ).toarray()
    fd = np.empty_like(jac)
    for k in range(x.size):
        h = 1e-6 * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        fd[:, k] = (prob.residuals(xp)[0] - prob.residuals(xm)[0]) / (2 * h)
    scale = np.abs(jac).max(axis=0) + 1e-12
    assert np.max(np.abs(fd - jac) / scale) < 1e-6
    assert prob.residuals(x)[1] == 0
    assert n_cams * 13 + n_frames * 6 == prob.n_full


def test_fixed_known_intrinsics_stay_fixed(four_cam):
    rec, _ = four_cam
    res = calibrate(rec.corners, rec.board_points, SIZE, fix="intrinsics", intrinsics=rec.rig)
    np.testing.assert_array_equal(res.rig.get_params()[:, 6:12], rec.rig.get_params()[:, 6:12])
    for ct, ce in zip(rec.rig, res.rig, strict=True):
        assert np.linalg.norm(ct.center - ce.center) < 2.0
    assert res.info["fixed"]["cam_0"] == ["fx", "fy", "cx", "cy", "k1", "k2", "skew"]
    # Per-camera fixing by name.
    res2 = calibrate(
        rec.corners, rec.board_points, SIZE, fix={"cam1": ["k2"]}, camera_names=rec.rig.names
    )
    assert res2.info["fixed"] == {"cam1": ["k2"]}


def test_robust_loss_resists_outliers():
    rec = make_recording(n_cams=4, n_frames=40, seed=4)
    corners = rec.corners.copy()
    rng = np.random.default_rng(1)
    ok = np.argwhere(np.isfinite(corners[..., 0]))
    bad = ok[rng.choice(len(ok), size=len(ok) // 50, replace=False)]
    corners[tuple(bad.T)] += rng.normal(0, 15, (len(bad), 2))
    plain = calibrate(corners, rec.board_points, SIZE)
    robust = calibrate(corners, rec.board_points, SIZE, loss="soft_l1", f_scale=1.0)
    err = lambda r: np.abs(r.rig.get_params()[:, 6] - rec.rig.get_params()[:, 6]).max()  # noqa: E731
    assert err(robust) < err(plain)
    assert err(robust) < 3.0
    rep = robust.report()
    assert rep["outliers"]["count"] >= 0.8 * len(bad)


def test_report_json_png_and_toml_round_trip(four_cam, tmp_path):
    rec, res = four_cam
    rep = res.report()
    json.dumps(rep)  # JSON-able
    assert set(rep) >= {
        "summary", "cameras", "views", "worst_views", "outliers", "plausibility", "text",
    }  # fmt: skip
    cam = rep["cameras"][0]
    assert {"rms_px", "median_px", "max_px", "coverage", "center", "n_views"} <= set(cam)
    assert 0 < cam["coverage"] <= 1
    assert rep["plausibility"]["scale_ok"] and not rep["plausibility"]["mirrored"]
    assert abs(rep["plausibility"]["scale_ratio"] - 1) < 2e-3
    assert "rms px" in rep["text"] and "cam_3" in rep["text"]
    assert len(rep["views"]) == int(res.used_frames.sum())
    out = res.save_report(tmp_path / "qc.json", png=tmp_path / "qc.png")
    assert json.loads((tmp_path / "qc.json").read_text())["summary"] == out["summary"]
    assert (tmp_path / "qc.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    path = res.save(tmp_path / "calibration.toml")
    back = acm_rs.CameraRig.load(path, names=["cam_2", "cam_0", "cam_1", "cam_3"])
    np.testing.assert_array_equal(back["cam_0"].params, res.rig["cam_0"].params)
    np.testing.assert_array_equal(back.get_params()[1], res.rig.get_params()[0])
    assert back[0].size == SIZE
    assert "error" in (tmp_path / "calibration.toml").read_text()


def test_world_frame_from_board_and_points(four_cam):
    rec, res = four_cam
    f = int(np.flatnonzero(res.used_frames)[3])
    w = res.with_world_frame(board_view=f)
    np.testing.assert_allclose(w.board_rvecs[f], 0, atol=1e-9)
    np.testing.assert_allclose(w.board_tvecs[f], 0, atol=1e-7)
    # Projections are unchanged by a change of world frame.
    pts = res.board_world_points()[f]
    np.testing.assert_allclose(
        w.rig.project(w.board_world_points()[f]), res.rig.project(pts), atol=1e-6
    )
    # Three points: the board's origin, a point along its x axis and one along y.
    three = np.stack([pts[0], pts[1], pts[9]])
    wp = res.with_world_frame(points=three)
    np.testing.assert_allclose(wp.rig.get_params(), w.rig.get_params(), atol=1e-6)
    with pytest.raises(ValueError, match="collinear"):
        frame_from_points(np.stack([pts[0], pts[1], pts[2]]))
    with pytest.raises(ValueError, match="exactly one"):
        res.with_world_frame()


def test_acm_multicalibration_round_trip(four_cam, tmp_path):
    _, res = four_cam
    path = save_acm_calibration(res.rig, tmp_path / "multicalibration.npy")
    back = load_acm_calibration(path, image_size=SIZE, names=res.rig.names)
    np.testing.assert_allclose(back.get_params(), res.rig.get_params(), rtol=0, atol=1e-12)
    # (n, 3, 3) camera matrices are accepted too.
    d = np.load(path, allow_pickle=True).item()
    d["A_fit"] = np.stack([c.matrix for c in res.rig])
    np.save(tmp_path / "m33.npy", np.array(d, dtype=object), allow_pickle=True)
    np.testing.assert_allclose(
        load_acm_calibration(tmp_path / "m33.npy").get_params(), res.rig.get_params(), atol=1e-12
    )
    # origin_coord: calibration coords = coord @ arena + origin.
    coord = rodrigues(np.array([0.1, -0.2, 0.3]))
    origin = np.array([10.0, -20.0, 300.0])
    np.save(tmp_path / "oc.npy", np.array({"origin": origin, "coord": coord}, dtype=object))
    arena = load_acm_calibration(path, tmp_path / "oc.npy")
    x_arena = np.array([[5.0, 7.0, -3.0], [50.0, 0.0, 10.0]])
    np.testing.assert_allclose(
        arena.project(x_arena), res.rig.project(x_arena @ coord.T + origin), atol=1e-8
    )
    # Not the expected dict -> ValueError.
    np.save(tmp_path / "bad.npy", np.array({"A_fit": 1}, dtype=object), allow_pickle=True)
    with pytest.raises(ValueError, match="lacks keys"):
        load_acm_calibration(tmp_path / "bad.npy")
    np.save(tmp_path / "arr.npy", np.zeros(3))
    with pytest.raises(ValueError, match="pickled dict"):
        load_acm_calibration(tmp_path / "arr.npy")


# -- bad input ----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small():
    return make_recording(n_cams=3, n_frames=15, seed=9)


def test_camera_never_seeing_the_board(small):
    corners = small.corners.copy()
    corners[1] = np.nan
    with pytest.raises(ValueError, match="'cam_1' never sees the board"):
        calibrate(corners, small.board_points, SIZE)


def test_disconnected_camera_graph(small):
    corners = small.corners.copy()
    # Camera 2 only sees views that no other camera sees.
    corners[2, :8] = np.nan
    corners[:2, 8:] = np.nan
    with pytest.raises(ValueError, match=r"\['cam_2'\].*disconnected"):
        calibrate(corners, small.board_points, SIZE)


def test_too_few_views(small):
    corners = small.corners.copy()
    corners[:, 2:] = np.nan
    with pytest.raises(ValueError, match="usable"):
        calibrate(corners, small.board_points, SIZE)


def test_infinite_corners_and_shapes(small):
    corners = small.corners.copy()
    corners[0, 3, 4, 1] = np.inf
    with pytest.raises(ValueError, match="infinity.*camera 0, frame 3, point 4"):
        calibrate(corners, small.board_points, SIZE)
    half = small.corners.copy()
    half[1, 2, 3, 0] = np.nan
    half[1, 2, 3, 1] = 100.0
    with pytest.raises(ValueError, match="one NaN coordinate"):
        calibrate(half, small.board_points, SIZE)
    with pytest.raises(ValueError, match="n_cams, n_frames, n_points, 2"):
        calibrate(small.corners[0], small.board_points, SIZE)
    with pytest.raises(ValueError, match="board_points has"):
        calibrate(small.corners, small.board_points[:-1], SIZE)
    with pytest.raises(ValueError, match="image_size"):
        calibrate(small.corners, small.board_points, [(1280, 1024)] * 2)
    with pytest.raises(ValueError, match="planar"):
        b = small.board_points.copy()
        b[0, 2] = 5.0
        calibrate(small.corners, b, SIZE)
    with pytest.raises(ValueError, match="reference_camera"):
        calibrate(small.corners, small.board_points, SIZE, reference_camera=3)
    with pytest.raises(ValueError, match="loss"):
        calibrate(small.corners, small.board_points, SIZE, loss="l2")
    with pytest.raises(ValueError, match="unknown parameter"):
        calibrate(small.corners, small.board_points, SIZE, fix=["focal_length"])
    with pytest.raises(ValueError, match="camera_names"):
        calibrate(small.corners, small.board_points, SIZE, camera_names=["a", "a", "b"])


def test_native_errors_are_value_errors(small):
    n_full = 13 * 3 + 6 * 15
    with pytest.raises(ValueError, match="fixed"):
        _native.NativeCalibration(
            small.board_points, small.corners, 0, np.ones(n_full), np.zeros(n_full - 1, bool)
        )
    with pytest.raises(ValueError, match="focal"):
        _native.NativeCalibration(
            small.board_points, small.corners, 0, np.zeros(n_full), np.zeros(n_full, bool)
        )


def test_reversed_checkerboard_order_is_unified():
    rec = make_recording(n_cams=4, n_frames=40, seed=6, dropout=0.0)
    corners = rec.corners.copy()
    complete = np.isfinite(corners[..., 0]).all(-1)
    pairs = np.argwhere(complete)
    # Reverse the corner order of a few complete detections (not the whole view).
    multi = [(c, f) for c, f in pairs if complete[:, f].sum() >= 3][::7][:6]
    for c, f in multi:
        corners[c, f] = corners[c, f, ::-1]
    with pytest.warns(UserWarning, match="reversed corner order"):
        res = calibrate(corners, rec.board_points, SIZE)
    assert res.info["n_reversed_detections"] == len(multi)
    assert res.rms < 0.5
    for ct, ce in zip(rec.rig, res.rig, strict=True):
        assert np.linalg.norm(ct.center - ce.center) < 3.0


def test_single_camera():
    rec = make_recording(n_cams=3, n_frames=30, seed=8)
    res = calibrate(rec.corners[1:2], rec.board_points, SIZE)
    np.testing.assert_allclose(res.rig[0].params[6:8], rec.rig[1].params[6:8], rtol=5e-3)
    assert res.rms < 0.5
