"""The online tracker (issue 16 item 3): frame-by-frame filter, fixed-lag smoother and
prediction with parameters learned offline."""

from __future__ import annotations

import numpy as np
import pytest

import acm_rs
from acm_rs import _native, datasets, models
from acm_rs.demo import demo_rig
from acm_rs.state import StateMap
from acm_rs.tracking.track import DEFAULT_GATE, _first_pose, gate_threshold


@pytest.fixture(scope="module")
def data():
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, 80, seed=2)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, missing=0.15, outliers=0.01, seed=3)
    truth, _ = sk.forward(t, r)
    res = acm_rs.track(rig, sk, det, likelihood=lik, motion="random_walk", max_iter=15)
    return sk, rig, det, lik, truth, res


def _masked(det, lik, pcutoff=0.9):
    out = np.array(det, float)
    out[~(lik >= pcutoff)] = np.nan
    return out


def _offline(data, online, smooth: bool):
    """The native offline E-step (filter, or filter + smoother) with the learned parameters
    from the online tracker's start (sec. 4.7 fit of the first frame): joints and SDs."""
    sk, rig, det, lik, _, res = data
    norm = online.norm
    m = _masked(det, lik)
    _, t0, r0 = _first_pose(rig, sk, m, norm)
    mu0 = StateMap(sk, norm, True).start_state(t0, r0)
    lim = sk.joint_limits
    x = norm.normalize_pixels(m).transpose(1, 0, 2, 3)
    nt = _native.NativeTracker(
        sk._native, rig.get_params(), np.ascontiguousarray(lim[..., 0]),
        np.ascontiguousarray(lim[..., 1]), norm._tuple(), True, np.ascontiguousarray(x),
    )  # fmt: skip
    p = res.info["params"]
    nt.e_step(mu0, p["V0"], p["Vz"], p["Vx_diag"], gate_threshold(DEFAULT_GATE), smooth, False)
    _, joints, _, sd, _ = nt.posterior()
    return joints, sd


def test_online_filter_equals_the_offline_forward_pass(data):
    """Frame by frame through the Python wrapper and the binding = the offline filter with
    the same parameters and start (sec. 4.7 fit of the first frame), to rounding."""
    sk, rig, det, lik, _, res = data
    online = acm_rs.OnlineTracker.from_result(res, vz_shrinkage=0.0)
    joints = np.array([online.update(det[:, t], lik[:, t])[0] for t in range(det.shape[1])])
    assert online.frames == det.shape[1]
    off_joints, _ = _offline(data, online, smooth=False)  # the filter from the same start
    np.testing.assert_allclose(joints, off_joints, rtol=0, atol=1e-9)


def test_serial_steps_equal_the_parallel_ones(data):
    """serial=True runs each step on the calling thread alone: the same arithmetic, so the
    same poses and SDs bit for bit."""
    sk, rig, det, lik, _, res = data
    out = []
    for serial in (False, True):
        online = acm_rs.OnlineTracker.from_result(res, serial=serial)
        out.append([online.update(det[:, t], lik[:, t]) for t in range(det.shape[1])])
        assert online._native.serial is serial
    for (j0, s0), (j1, s1) in zip(*out, strict=True):
        np.testing.assert_array_equal(j0, j1)
        np.testing.assert_array_equal(s0, s1)
    assert np.isfinite(np.array([j for j, _ in out[1]])[5:]).all()


def test_full_lag_window_is_the_offline_smoother_with_fixed_parameters(data):
    """lag >= T - 1: after the last frame, lagged_window() is the RTS smoother (Alg. 8) of
    the recording with Θ fixed, from the same start; its first row is lagged()."""
    sk, rig, det, lik, _, res = data
    n_t = det.shape[1]
    online = acm_rs.OnlineTracker.from_result(res, vz_shrinkage=0.0, lag=n_t)
    for t in range(n_t):
        online.update(det[:, t], lik[:, t])
    joints, sd, k = online.lagged_window()
    assert k == n_t - 1 and joints.shape == (n_t, sk.n_joints, 3) == sd.shape
    j0, s0, _ = online.lagged()
    np.testing.assert_array_equal(joints[0], j0)
    np.testing.assert_array_equal(sd[0], s0)
    off_joints, off_sd = _offline(data, online, smooth=True)
    np.testing.assert_allclose(joints, off_joints, rtol=0, atol=1e-8)
    np.testing.assert_allclose(sd, off_sd, rtol=1e-6, atol=1e-10)


def test_fixed_lag_and_prediction(data):
    sk, rig, det, lik, truth, res = data
    n_t = det.shape[1]
    lag = 8
    online = acm_rs.OnlineTracker.from_result(res, lag=lag)
    filt = np.full_like(truth, np.nan)
    lagged = np.full_like(truth, np.nan)
    for t in range(n_t):
        filt[t], sd = online.update(det[:, t], lik[:, t])
        assert np.all(sd > 0)
        j, s, k = online.lagged()
        assert k == min(lag, t)
        lagged[t - k] = j
        if t == 30:
            p0, s0 = online.predict(0)
            np.testing.assert_allclose(p0, filt[t], atol=1e-12)
            p5, s5 = online.predict(5)
            assert np.all(s5 >= s0 - 1e-12)  # uncertainty grows ahead
    done = slice(0, n_t - lag)  # frames with a lagged estimate

    def err(a):
        return np.linalg.norm(a[done] - truth[done], axis=-1).mean()

    e_filt, e_lag, e_off = err(filt), err(lagged), err(res.joints)
    assert np.isfinite(lagged[done]).all() and np.isnan(lagged[n_t - lag :]).all()
    # the lag recovers much of what smoothing gains over filtering (the default shrinkage of
    # V_z costs some accuracy on the recording the parameters were learned on)
    assert e_lag < 0.95 * e_filt, (e_lag, e_filt)
    assert e_lag < 1.5 * e_off, (e_lag, e_off, e_filt)


def test_online_inputs_are_checked(data):
    sk, rig, det, lik, _, res = data
    online = acm_rs.OnlineTracker.from_result(res)
    with pytest.raises(ValueError, match="no frame processed"):
        online.lagged()
    # no detection at all: not started, NaN pose
    j, s = online.update(np.full(det[:, 0].shape, np.nan))
    assert np.isnan(j).all() and online.frames == 0
    with pytest.raises(ValueError, match="shape"):
        online.update(det[:, 0, :5])
    with pytest.raises(ValueError, match="inf"):
        bad = det[:, 0].copy()
        bad[0, 0, 0] = np.inf
        online.update(bad)
    with pytest.raises(ValueError, match="lag"):
        acm_rs.OnlineTracker.from_result(res, lag=-1)
    with pytest.raises(ValueError, match="vz_shrinkage"):
        acm_rs.OnlineTracker.from_result(res, vz_shrinkage=2.0)
    with pytest.raises(ValueError, match="velocity state"):
        acm_rs.OnlineTracker(
            rig, sk, res.info["params"], normalization=online.norm, motion="velocity"
        )
    det_res = acm_rs.track(rig, sk, det[:, :5], likelihood=lik[:, :5], method="deterministic")
    with pytest.raises(ValueError, match="no learned parameters"):
        acm_rs.OnlineTracker.from_result(det_res)
    online.update(det[:, 0], lik[:, 0])
    online.reset()
    assert online.frames == 0


def test_deeplabcut_live_adapter_pairs_cameras_and_maps_bodyparts(data):
    """Poses arrive per camera, out of step and in DeepLabCut's body-part order: the result
    equals feeding the tracker the frames directly."""
    from acm_rs.tracking.live import LiveRig

    sk, rig, det, lik, _, res = data
    n_t = 12
    direct = acm_rs.OnlineTracker.from_result(res)
    want = [direct.update(det[:, t], lik[:, t])[0] for t in range(n_t)]
    order = np.random.default_rng(0).permutation(sk.n_markers)
    names = [sk.marker_names[i] for i in order]
    seen = []
    live = LiveRig(
        acm_rs.OnlineTracker.from_result(res), bodyparts=names,
        on_pose=lambda f, j, s: seen.append((f, j)),
    )  # fmt: skip
    procs = [live.processor(c) for c in range(len(rig))]
    for c, proc in enumerate(procs):  # camera 0 delivers every frame first, then camera 1, ...
        for t in range(n_t):
            pose = np.column_stack([det[c, t, order], lik[c, t, order]])
            assert proc.process(pose) is pose
        assert len(seen) == (n_t if c == len(rig) - 1 else 0)
    assert [f for f, _ in seen] == list(range(n_t))
    for (_, j), w in zip(seen, want, strict=True):
        np.testing.assert_allclose(j, w, atol=1e-9, equal_nan=True)
    with pytest.raises(ValueError, match="shape"):
        procs[0].process(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="not in the rig"):
        live.processor(9)
