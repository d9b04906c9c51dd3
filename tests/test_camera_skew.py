"""Camera skew (MATLAB's model) and the Label3D / DANNCE calibration import (issue 28 item 3).

The real file is Label3D's ``label3d_voltest_dannce_m1.mat`` from spoonsso/dannce (six cameras
with skews of a few px, ``labelData`` holding Label3D's own 3D points and their 2D
reprojections); see ``tests/data/real/dannce/PROVENANCE.md``.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

import acm_rs
from acm_rs import _native
from acm_rs.calibration import calibrate, read_label3d_calibration

sys.path.insert(0, str(Path(__file__).parent))
from calib_synthetic import make_recording  # noqa: E402

sio = pytest.importorskip("scipy.io")

REAL = Path(__file__).parent / "data" / "real" / "dannce" / "label3d_voltest_dannce_m1.mat"


def matlab_project(k_matlab, r_row, t_row, rdist, tdist, pts):
    """MATLAB's documented model, written from its conventions (row vectors, K transposed):
    ``[x y z] = X r + t``, normalise, distort (radial k1 k2 k3, tangential p1 p2), then
    ``[u v 1] = [x'' y'' 1] K``."""
    cam = pts @ r_row + t_row
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    k = np.zeros(3)
    k[: len(rdist)] = rdist
    r2 = x * x + y * y
    radial = 1 + k[0] * r2 + k[1] * r2**2 + k[2] * r2**3
    xd = x * radial + 2 * tdist[0] * x * y + tdist[1] * (r2 + 2 * x * x)
    yd = y * radial + tdist[0] * (r2 + 2 * y * y) + 2 * tdist[1] * x * y
    uv1 = np.stack([xd, yd, np.ones_like(xd)], 1) @ k_matlab
    return uv1[:, :2]


def dannce_style_project(k_matlab, r_row, t_row, rdist, tdist, pts):
    """DANNCE's order of operations: undistorted pixels ``[X 1] [r; t] K`` (homogeneous),
    then back to normalised coordinates through K (skew included), distortion, and to pixels
    again with ``u = fx x'' + cx + s y''``."""
    proj = np.c_[pts, np.ones(len(pts))] @ np.vstack([r_row, t_row]) @ k_matlab
    px = proj[:, :2] / proj[:, 2:]
    fx, fy, s, cx, cy = k_matlab[0, 0], k_matlab[1, 1], k_matlab[1, 0], *k_matlab[2, :2]
    yn = (px[:, 1] - cy) / fy
    xn = (px[:, 0] - cx - s * yn) / fx
    r2 = xn**2 + yn**2
    k3 = rdist[2] if len(rdist) > 2 else 0.0
    a = rdist[0] * r2 + rdist[1] * r2**2 + k3 * r2**3
    xd = xn + xn * a + 2 * tdist[0] * xn * yn + tdist[1] * (r2 + 2 * xn**2)
    yd = yn + yn * a + tdist[0] * (r2 + 2 * yn**2) + 2 * tdist[1] * xn * yn
    return np.stack([xd * fx + cx + s * yd, yd * fy + cy], 1)


def real_params():
    """Per camera (name, K, r, t, RDistort, TDistort, data_3d (n, 3), data_2d (n, 2)) read with
    scipy.io.loadmat, independently of acm-rs."""
    m = sio.loadmat(str(REAL))
    out = []
    for i, cell in enumerate(m["params"].ravel()):
        lab = m["labelData"].ravel()[i]
        out.append(
            (
                str(m["camnames"].ravel()[i][0]),
                *(cell[k][0, 0].astype(float) for k in ("K", "r", "t")),
                cell["RDistort"][0, 0].ravel(),
                cell["TDistort"][0, 0].ravel(),
                lab["data_3d"][0, 0].reshape(-1, 3),
                lab["data_2d"][0, 0].reshape(-1, 2),
            )
        )
    return out


def skewed_camera(skew=-5.8):
    k = np.array([[1650.0, skew, 610.0], [0.0, 1660.0, 480.0], [0.0, 0.0, 1.0]])
    return acm_rs.Camera(
        k, [-0.15, 0.9, -0.002, 0.003, -2.7], [0.3, -0.2, 0.1], [10.0, 60.0, 300.0], (1220, 960)
    )


# -- the model ----------------------------------------------------------------------------------


def test_skew_matches_matlab_model():
    cam = skewed_camera()
    rng = np.random.default_rng(1)
    pts = rng.uniform(-40, 40, (400, 3))
    k_matlab = cam.matrix.T
    r_row = cam.rotation_matrix.T
    ref = matlab_project(k_matlab, r_row, cam.tvec, [-0.15, 0.9, -2.7], [-0.002, 0.003], pts)
    np.testing.assert_allclose(cam.project(pts), ref, rtol=0, atol=1e-9)
    ref_d = dannce_style_project(
        k_matlab, r_row, cam.tvec, [-0.15, 0.9, -2.7], [-0.002, 0.003], pts
    )
    np.testing.assert_allclose(cam.project(pts), ref_d, rtol=0, atol=1e-7)
    # the skew really moves u (by s y''), not v
    plain = acm_rs.Camera.from_params(np.r_[cam.params[:15], 0.0])
    dv = cam.project(pts) - plain.project(pts)
    assert np.all(dv[:, 1] == 0) and np.abs(dv[:, 0]).max() > 0.5
    assert cam.skew == -5.8 and cam.params[15] == -5.8 and cam.matrix[0, 1] == -5.8


def test_jacobians_match_finite_differences_with_skew():
    cam = skewed_camera()
    pts = np.random.default_rng(2).uniform(-40, 40, (20, 3))
    px, dp, dc = cam.project_jacobian(pts)
    assert dc.shape == (20, 2, 16)
    np.testing.assert_allclose(px, cam.project(pts), rtol=0, atol=1e-9)
    h = 1e-5
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        fd = (cam.project(pts + e) - cam.project(pts - e)) / (2 * h)
        np.testing.assert_allclose(dp[..., k], fd, rtol=1e-6, atol=1e-6)
    for k in range(16):
        step = 1e-6 * (1 + abs(cam.params[k]))
        pp, pm = cam.params.copy(), cam.params.copy()
        pp[k] += step
        pm[k] -= step
        fd = (
            acm_rs.Camera.from_params(pp).project(pts) - acm_rs.Camera.from_params(pm).project(pts)
        ) / (2 * step)
        np.testing.assert_allclose(dc[..., k], fd, rtol=1e-5, atol=1e-5, err_msg=str(k))
    # d u / d skew = y'' (nonzero), d v / d skew = 0
    assert np.all(dc[:, 1, 15] == 0) and np.abs(dc[:, 0, 15]).min() > 0


def test_zero_skew_is_the_skew_free_model_bit_for_bit(rig, rng):
    pts = rng.uniform(-8, 8, (500, 3))
    p16 = rig.get_params()
    assert p16.shape == (len(rig), 16) and np.all(p16[:, 15] == 0)
    # 15 columns (without skew) are accepted everywhere and mean skew 0
    px16, _ = _native.project(np.ascontiguousarray(p16), pts)
    px15, _ = _native.project(np.ascontiguousarray(p16[:, :15]), pts)
    np.testing.assert_array_equal(px16, px15)
    np.testing.assert_array_equal(rig.set_params(p16[:, :15]).get_params(), p16)
    np.testing.assert_array_equal(acm_rs.Camera.from_params(p16[0, :15]).params, p16[0])
    # the NumPy reference (acm_rs.truth) takes both layouts
    from acm_rs import truth

    np.testing.assert_allclose(truth.project(p16, pts), truth.project(p16[:, :15], pts), atol=0)
    np.testing.assert_allclose(truth.project(p16, pts), px16, atol=1e-9)


def test_fused_emission_applies_skew(rng):
    sk = acm_rs.models.rat()
    t = np.array([[0.0, 0.0, 5.0]])
    r = np.zeros((1, sk.n_bones, 3))
    cam = acm_rs.Camera(
        [[800.0, 7.0, 640.0], [0.0, 800.0, 512.0], [0.0, 0.0, 1.0]],
        [-0.1, 0.01],
        [np.pi / 2 + 0.3, 0.0, 0.0],
        [0.0, 0.0, 60.0],
    )
    rig = acm_rs.CameraRig([cam])
    _, markers = sk.forward(t[0], r[0])
    np.testing.assert_allclose(sk.project(rig, t, r)[0, 0], cam.project(markers), atol=1e-9)


def test_matrix_layout_errors_name_the_fix():
    k = np.array([[1000.0, 0, 0], [3.0, 1000.0, 0], [320.0, 240.0, 1.0]])  # MATLAB's K
    with pytest.raises(ValueError, match="transpose"):
        acm_rs.Camera(k, [0, 0], np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="16"):
        acm_rs.Camera.from_params(np.ones(14))


# -- calibration.toml ---------------------------------------------------------------------------


def test_toml_round_trip_writes_skew_only_when_nonzero(tmp_path, rig):
    cams = [skewed_camera(), acm_rs.Camera.from_params(rig[0].params, rig[0].size, "plain")]
    cams[0].name = "skewed"
    path = tmp_path / "calibration.toml"
    acm_rs.CameraRig(cams, units="mm").save(path)
    doc = tomllib.loads(path.read_text())
    assert doc["cam_0"]["skew"] == -5.8 and doc["cam_0"]["matrix"][0][1] == 0.0
    assert "skew" not in doc["cam_1"]
    back = acm_rs.CameraRig.load(path)
    np.testing.assert_array_equal(back.get_params(), acm_rs.CameraRig(cams).get_params())
    # aniposelib reads the file (it ignores the key) but projects without the skew
    aniposelib = pytest.importorskip("aniposelib")
    group = aniposelib.cameras.CameraGroup.load(str(path))
    pts = np.random.default_rng(3).uniform(-40, 40, (10, 3))
    theirs = group.cameras[0].project(pts).reshape(-1, 2)
    ours = back[0].project(pts)
    plain = acm_rs.Camera.from_params(np.r_[back[0].params[:15], 0.0])
    np.testing.assert_allclose(theirs, plain.project(pts), atol=1e-6)
    assert np.abs(ours - theirs)[:, 0].max() > 0.1


def test_toml_skewed_matrix_is_refused(tmp_path, rig):
    table = rig[0].to_dict() | {"name": "a"}
    table["matrix"][0][1] = 4.0
    from acm_rs import _toml

    path = tmp_path / "calibration.toml"
    path.write_text(_toml.dumps({"cam_0": table}))
    with pytest.raises(ValueError, match=r"skew = 4"):
        acm_rs.CameraRig.load(path)


# -- calibration --------------------------------------------------------------------------------


def skewed_recording(skews):
    syn = make_recording(n_cams=3, n_frames=60, noise=0.1, seed=4)
    p = syn.rig.get_params()
    p[:, 15] = skews
    rig = syn.rig.set_params(p)
    pts = syn.board_points @ acm_rs.rotation.rodrigues(syn.board_rvecs).transpose(0, 2, 1)
    pts = pts + syn.board_tvecs[:, None]
    clean = rig.project(pts)
    noise = np.random.default_rng(5).normal(0, 0.1, clean.shape)
    corners = np.where(np.isfinite(syn.corners), clean + noise, np.nan)
    return rig, syn.board_points, corners


def test_calibration_holds_skew_at_zero_by_default_and_can_estimate_it():
    rig, board, corners = skewed_recording([0.0, 6.0, -4.0])
    fixed = calibrate(corners, board, (1280, 1024))
    assert np.all(fixed.rig.get_params()[:, 15] == 0)
    assert fixed.info["fix_skew"] and "cam_0" not in fixed.info["fixed"]
    free = calibrate(corners, board, (1280, 1024), fix_skew=False)
    np.testing.assert_allclose(free.rig.get_params()[:, 15], [0.0, 6.0, -4.0], atol=0.6)
    assert free.rms < fixed.rms
    assert free.rms < 0.15


# -- the Label3D / DANNCE importer on the real file ---------------------------------------------


def test_label3d_import_values_match_scipy():
    ref = real_params()
    rig = read_label3d_calibration(REAL, pixel_origin=1)
    assert rig.units == "mm" and rig.names == [r[0] for r in ref]
    for cam, (_, k, r, t, rd, td, _, _) in zip(rig, ref, strict=True):
        np.testing.assert_allclose(cam.matrix, k.T, rtol=0, atol=1e-12)
        np.testing.assert_allclose(cam.rotation_matrix, r.T, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(cam.tvec, t.ravel())
        np.testing.assert_array_equal(cam.dist, [rd[0], rd[1], td[0], td[1], rd[2]])
        assert cam.skew == k[1, 0]
    skews = [c.skew for c in rig]
    assert min(skews) < -5.8 < max(skews)  # the rig of issue 28 ("about 5.8 px")
    zero = read_label3d_calibration(REAL)
    np.testing.assert_allclose(
        zero.get_params()[:, 8:10], rig.get_params()[:, 8:10] - 1.0, rtol=0, atol=1e-12
    )


def test_label3d_projection_reproduces_label3d_and_dannce():
    rig1 = read_label3d_calibration(REAL, pixel_origin=1)
    rig0 = read_label3d_calibration(REAL, pixel_origin=0)
    n_checked = 0
    for i, (_, k, r, t, rd, td, d3, d2) in enumerate(real_params()):
        ok = np.isfinite(d3).all(1) & np.isfinite(d2).all(1)
        ours = rig1[i].project(d3[ok])
        # Label3D's own reprojections of its 3D points (MATLAB's 1-based pixels)
        np.testing.assert_allclose(ours, d2[ok], rtol=0, atol=1e-9)
        # DANNCE's projection of the same points
        theirs = dannce_style_project(k, r, t.ravel(), rd, td, d3[ok])
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-7)
        np.testing.assert_allclose(ours, matlab_project(k, r, t, rd, td, d3[ok]), atol=1e-9)
        # 0-based pixels: one pixel less in both coordinates
        np.testing.assert_allclose(rig0[i].project(d3[ok]), d2[ok] - 1.0, rtol=0, atol=1e-9)
        n_checked += ok.sum()
    assert n_checked > 1000


def test_label3d_rig_round_trips_through_calibration_toml(tmp_path):
    rig = read_label3d_calibration(REAL)
    rig.save(tmp_path / "calibration.toml")
    back = acm_rs.CameraRig.load(tmp_path / "calibration.toml")
    np.testing.assert_array_equal(back.get_params(), rig.get_params())
    assert back.units == "mm" and back.names == rig.names


def test_dannce_per_camera_files(tmp_path):
    # DANNCE's convertCalibration.m writes hires_cam<i>_params.mat with K, r, t, RDistort,
    # TDistort; here written from the real file's values with scipy
    ref = real_params()[:2]
    paths = []
    for i, (_, k, r, t, rd, td, _, _) in enumerate(ref):
        paths.append(tmp_path / f"hires_cam{i + 1}_params.mat")
        sio.savemat(paths[-1], {"K": k, "r": r, "t": t, "RDistort": rd[None], "TDistort": td[None]})
    rig = read_label3d_calibration(paths, pixel_origin=1)
    assert rig.names == ["hires_cam1_params", "hires_cam2_params"]
    full = read_label3d_calibration(REAL, pixel_origin=1)
    np.testing.assert_array_equal(rig.get_params(), full.get_params()[:2])


def test_label3d_bad_files(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        read_label3d_calibration(tmp_path / "nope.mat")
    junk = tmp_path / "junk.mat"
    sio.savemat(junk, {"x": np.ones(3)})
    with pytest.raises(ValueError, match="lacks"):
        read_label3d_calibration(junk)
    k, r, t = real_params()[0][1:4]
    opencv_k = tmp_path / "k.mat"
    sio.savemat(opencv_k, {"K": k.T, "r": r, "t": t})
    with pytest.raises(ValueError, match="transpose it"):
        read_label3d_calibration(opencv_k)
    h5 = tmp_path / "v73.mat"
    h5.write_bytes(b"MATLAB 7.3 MAT-file, Platform: GLNXA64" + b"\0" * 200)
    with pytest.raises(ValueError, match="v7.3"):
        read_label3d_calibration(h5)
    with pytest.raises(ValueError, match="pixel_origin"):
        read_label3d_calibration(REAL, pixel_origin=2)


def test_triangulation_and_acm_export_handle_skew(tmp_path):
    rig = read_label3d_calibration(REAL)
    pts = real_params()[0][6]
    pts = pts[np.isfinite(pts).all(1)]
    # OpenCV's undistortPoints ignores a skew; the pixels are corrected first (exactly)
    cam = rig[0]
    np.testing.assert_allclose(
        acm_rs.Camera(cam.opencv_matrix, cam.dist, cam.rvec, cam.tvec).project(pts),
        cam.skew_free_pixels(cam.project(pts)),
        rtol=0,
        atol=1e-9,
    )
    back = acm_rs.learning.triangulate(rig, rig.project(pts))
    np.testing.assert_allclose(back, pts, atol=1e-6)
    from acm_rs.calibration import save_acm_calibration

    with pytest.raises(ValueError, match="skew"):
        save_acm_calibration(rig, tmp_path / "multicalibration.npy")
