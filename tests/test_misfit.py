"""The markers' model misfit (issue 26 item 3, :mod:`acm_rs.tracking.misfit`).

The data are made without acm-rs's forward model or projection where it matters: true markers
from :mod:`acm_rs.truth` (through ``datasets.true_positions``) or plain NumPy, moved off the
model by known per-marker offsets, projected by plain NumPy (pinhole) or OpenCV's
``projectPoints`` (the demo rig's distortion).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig
from acm_rs.tracking import misfit as mf

# -- the estimator and the posterior alone (no tracker) ---------------------------------------


def _pinhole_rig(n_cams: int = 4, focal: float = 2000.0, distance: float = 100.0):
    """(K, R, t) per camera on a circle of ``distance`` cm around the origin, looking at it,
    as plain arrays, and the same cameras as an acm-rs rig (no distortion)."""
    cv2 = pytest.importorskip("cv2")
    cams, plain = [], []
    for c in range(n_cams):
        a = 2 * np.pi * c / n_cams
        centre = distance * np.array([np.cos(a), np.sin(a), 0.4])
        z = -centre / np.linalg.norm(centre)  # optical axis towards the origin
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        rot = np.stack([x, y, z])  # world -> camera
        t = -rot @ centre
        k = np.array([[focal, 0, 640.0], [0, focal, 512.0], [0, 0, 1]])
        plain.append((k, rot, t))
        rvec = cv2.Rodrigues(rot)[0].ravel()  # OpenCV's, not acm-rs's
        cams.append(acm_rs.Camera(k, np.zeros(5), rvec, t, size=(1280, 1024)))
    return plain, acm_rs.CameraRig(cams)


def _project_plain(plain, points):
    """(C, ..., 2) pinhole projection in plain NumPy."""
    out = []
    for k, rot, t in plain:
        cam = points @ rot.T + t
        uv = cam @ k.T
        out.append(uv[..., :2] / uv[..., 2:])
    return np.stack(out)


def _synthetic(sd_mm, n_frames=600, n_markers=6, noise_px=1.0, missing=0.1, seed=0):
    """FK markers (exact poses), true markers = FK + N(0, sd_k² I) (cm), detections."""
    rng = np.random.default_rng(seed)
    plain, rig = _pinhole_rig()
    fk = rng.uniform(-15, 15, (n_frames, n_markers, 3))
    sd = np.asarray(sd_mm, float) / 10.0
    truth = fk + rng.normal(size=fk.shape) * sd[None, :, None]
    det = _project_plain(plain, truth) + rng.normal(scale=noise_px, size=(4,) + fk.shape[:2] + (2,))
    used = rng.random(det.shape[:3]) > missing
    det[~used] = np.nan
    noise = np.full((4, n_markers, 2), noise_px**2)
    return rig, fk, truth, det, used, noise


@pytest.mark.parametrize("shape", ["isotropic", "full"])
def test_estimated_misfit_recovers_the_known_one(shape):
    sd_mm = np.array([1.0, 1.5, 2.0, 1.0, 3.0, 2.5])
    rig, fk, truth, det, used, noise = _synthetic(sd_mm)
    r, jac, used = mf.camera_residuals(rig, fk, det, used)
    sigma, pairs = mf.estimate_misfit(r, jac, used, noise, shape)
    est_mm = np.sqrt(np.trace(sigma, axis1=1, axis2=2) / 3) * 10
    assert (pairs > 1000).all()
    np.testing.assert_allclose(est_mm, sd_mm, rtol=0.2)
    # the posterior of the true markers covers them (the FK markers alone do not)
    fk_cov = np.zeros(fk.shape + (3,))
    markers, cov = mf.marker_posterior(fk, fk_cov, r, jac, used, noise, sigma)
    std = np.sqrt(np.diagonal(cov, axis1=2, axis2=3))
    coverage = np.mean(np.abs(markers - truth) <= 1.96 * std)
    assert 0.93 <= coverage <= 0.97, coverage
    assert (
        np.linalg.norm(markers - truth, axis=-1).mean() < np.linalg.norm(fk - truth, axis=-1).mean()
    )


def test_no_misfit_estimates_about_zero_and_changes_nothing():
    rig, fk, truth, det, used, noise = _synthetic(np.zeros(6))
    r, jac, used = mf.camera_residuals(rig, fk, det, used)
    sigma, _ = mf.estimate_misfit(r, jac, used, noise, "isotropic")
    est_mm = np.sqrt(np.trace(sigma, axis1=1, axis2=2) / 3) * 10
    assert est_mm.max() < 0.15  # against 1-3 mm above; noise 1 px ~ 0.5 mm
    fk_cov = np.broadcast_to(np.eye(3) * 1e-4, fk.shape + (3,))
    markers, cov = mf.marker_posterior(fk, fk_cov, r, jac, used, noise, sigma)
    shift = np.linalg.norm(markers - fk, axis=-1)  # cm; 1 px is ~0.5 mm here
    assert np.percentile(shift, 95) < 0.01 and shift.max() < 0.02
    # Σ = 0 exactly: the FK markers and their covariance come back unchanged
    markers, cov = mf.marker_posterior(fk, fk_cov, r, jac, used, noise, np.zeros((6, 3, 3)))
    np.testing.assert_array_equal(markers, fk)
    np.testing.assert_allclose(cov, fk_cov, rtol=0, atol=1e-18)


def test_unseen_markers_get_the_misfit_and_fk_covariance():
    rig, fk, _, det, used, noise = _synthetic(np.full(6, 1.0), n_frames=50)
    used[:, 10] = False  # nobody sees frame 10
    r, jac, used = mf.camera_residuals(rig, fk, det, used)
    sigma = np.broadcast_to(np.diag([0.01, 0.02, 0.03]), (6, 3, 3)).copy()
    fk_cov = np.broadcast_to(np.eye(3) * 1e-3, fk.shape + (3,))
    markers, cov = mf.marker_posterior(fk, fk_cov, r, jac, used, noise, sigma)
    np.testing.assert_array_equal(markers[10], fk[10])
    np.testing.assert_allclose(cov[10], sigma + 1e-3 * np.eye(3), rtol=1e-12)
    # seen frames: narrower than Σ + P, and equal to the information form
    t, k = 3, 2
    j = np.concatenate([jac[c, t, k] for c in range(4) if used[c, t, k]])
    w = np.concatenate([1 / noise[c, k] for c in range(4) if used[c, t, k]])
    info_form = np.linalg.inv(np.linalg.inv(sigma[k]) + j.T @ (w[:, None] * j))
    kj = info_form @ j.T @ (w[:, None] * j)  # K J
    want = info_form + (np.eye(3) - kj) @ fk_cov[t, k] @ (np.eye(3) - kj).T
    np.testing.assert_allclose(cov[t, k], want, rtol=1e-9)


# -- through acm_rs.track ------------------------------------------------------------------


def _project_opencv(rig, points):
    cv2 = pytest.importorskip("cv2")
    out = []
    for cam in rig:
        px, _ = cv2.projectPoints(
            points.reshape(-1, 1, 3), cam.rvec, cam.tvec, cam.matrix, cam.dist
        )
        out.append(px.reshape(points.shape[:-1] + (2,)))
    return np.stack(out)


@pytest.fixture(scope="module")
def tracked():
    """The synthetic rat (60 frames) with and without a known misfit (1-2 mm per marker),
    tracked once each with the default ``misfit="auto"``."""
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, 60, seed=2)
    _, markers = datasets.true_positions(sk, t, r)  # acm_rs.truth, not acm-rs's FK
    rng = np.random.default_rng(3)
    sd = rng.uniform(0.1, 0.2, sk.n_markers)  # cm
    out = {}
    for name, s in (("exact", 0 * sd), ("misfit", sd)):
        true = markers + rng.normal(size=markers.shape) * s[None, :, None]
        det = _project_opencv(rig, true) + rng.normal(
            scale=1.0, size=(len(rig),) + true.shape[:2] + (2,)
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = acm_rs.track(rig, sk, det, progress=False)
        out[name] = (res, true, s)
    return out


def _coverage(est, std, truth):
    return float(np.mean(np.abs(est - truth) <= 1.96 * std))


def test_track_recovers_a_known_misfit(tracked):
    res, true, sd = tracked["misfit"]
    info = res.info
    assert info["misfit"] == "auto" and info["misfit_shape"] == "isotropic"
    ratio = info["misfit_sd"] / sd
    assert 0.75 <= np.median(ratio) <= 1.2, np.median(ratio)
    fk_cov = _coverage(info["markers_fk"], info["markers_std_fk"], true)
    cov = _coverage(res.markers, info["markers_std"], true)
    assert fk_cov < 0.8  # the FK-only intervals are far too narrow
    assert 0.9 <= cov <= 0.99, cov
    err = np.linalg.norm(res.markers - true, axis=-1).mean()
    assert err < np.linalg.norm(info["markers_fk"] - true, axis=-1).mean()
    # joints and poses untouched; FK markers are the forward kinematics of the poses
    _, fk = res.skeleton.forward(res.t, res.r)
    np.testing.assert_allclose(info["markers_fk"], fk, atol=1e-9)


def test_track_without_misfit_changes_little(tracked):
    res, true, _ = tracked["exact"]
    info = res.info
    assert np.median(info["misfit_sd"]) < 0.01  # cm: 0.1 mm (against 1-2 mm above)
    shift = np.linalg.norm(res.markers - info["markers_fk"], axis=-1)
    assert np.percentile(shift, 95) < 0.01
    a = _coverage(info["markers_fk"], info["markers_std_fk"], true)
    b = _coverage(res.markers, info["markers_std"], true)
    assert a - 0.005 <= b <= a + 0.02  # (the short EM's own coverage is ~0.89 here)


def test_misfit_off_is_the_forward_kinematics(tracked):
    res, _, _ = tracked["misfit"]
    # apply_misfit on a copy of the FK-only result with "off" changes nothing
    import copy

    off = copy.copy(res)
    off.info = dict(res.info, markers_std=res.info["markers_std_fk"])
    off.markers = res.info["markers_fk"]
    mf.apply_misfit(off, "off")
    assert off.info["misfit"] == "off"
    np.testing.assert_array_equal(off.markers, res.info["markers_fk"])
    with pytest.raises(ValueError, match="misfit must be one of"):
        mf.apply_misfit(off, "sometimes")


def test_track_refuses_an_unknown_misfit_option():
    rig = demo_rig()
    sk = models.rat()
    det = np.full((len(rig), 3, sk.n_markers, 2), 1.0)
    with pytest.raises(ValueError, match="misfit must be one of"):
        acm_rs.track(rig, sk, det, misfit="yes")


def test_saved_result_keeps_the_misfit(tracked, tmp_path):
    res, _, _ = tracked["misfit"]
    res.save(tmp_path / "pose")
    back = acm_rs.PoseResult.load(tmp_path / "pose.npz")
    np.testing.assert_array_equal(back.markers, res.markers)
    np.testing.assert_array_equal(back.info["misfit_sd"], res.info["misfit_sd"])
    np.testing.assert_array_equal(back.info["markers_fk"], res.info["markers_fk"])
