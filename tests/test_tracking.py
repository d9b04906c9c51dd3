"""acm_rs.track on synthetic rat data with known truth (seeded): smooth motion within the
joint limits, a 4-camera rig, 2 px noise, ~15 % missing in bursts and confident outliers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig
from acm_rs.tracking.track import _measurements

N_FRAMES = 150


@pytest.fixture(scope="module")
def session():
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, N_FRAMES, seed=2)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, missing=0.15, outliers=0.01, seed=3)
    truth_joints, _ = sk.forward(t, r)
    truth_px = sk.project(rig, t, r)
    return sk, rig, t, r, det, lik, truth_joints, truth_px


@pytest.fixture(scope="module")
def tracked(session):
    sk, rig, _, _, det, lik, _, _ = session
    return acm_rs.track(rig, sk, det, likelihood=lik, progress=False)


def joint_errors(result, truth):
    return np.linalg.norm(result.joints - truth, axis=-1)


def test_smoother_beats_the_per_frame_fit(session, tracked):
    sk, rig, _, _, det, lik, truth, _ = session
    det_result = acm_rs.track(rig, sk, det, likelihood=lik, method="deterministic", progress=False)
    e_ukf = joint_errors(tracked, truth)
    e_det = joint_errors(det_result, truth)
    assert np.mean(e_ukf) < 0.6 * np.mean(e_det), (np.mean(e_ukf), np.mean(e_det))
    assert np.percentile(e_ukf, 95) < 0.6 * np.percentile(e_det, 95)
    # Sub-millimetre on average (units: cm) with 2 px noise at ~60 cm.
    assert np.mean(e_ukf) < 0.1
    assert det_result.state_cov is None and np.all(det_result.joints_std == 0)


def test_em_converges_and_history_is_recorded(tracked):
    h = tracked.em_history
    assert tracked.info["converged"]
    assert all(x["seconds"] > 0 for x in h)
    assert tracked.info["iterations"] == len(h)
    p = tracked.info["params"]
    # default motion="auto": the position-velocity state (no stretch without detections)
    assert tracked.info["motion"] == "velocity", tracked.info["motion_note"]
    assert [x["motion"] for x in h][0] == "random_walk" and h[-1]["motion"] == "velocity"
    n = 2 * tracked.state_map.n_state
    assert p["Vz"].shape == (n, n) and p["Vx_diag"].shape == (4 * 43 * 2,)
    assert tracked.state_cov.shape[1:] == (n // 2, n // 2)
    # The learned measurement noise is close to the 2 px of the data (normalised units).
    px_sd = np.sqrt(np.median(p["Vx_diag"])) * 640
    assert 1.5 < px_sd < 3.5, px_sd


def test_posterior_intervals_cover_the_truth(tracked, session):
    truth = session[6]
    inside = np.abs(tracked.joints - truth) <= 1.96 * tracked.joints_std
    assert 0.85 < inside.mean() < 0.99, inside.mean()
    assert np.all(tracked.joints_std > 0)


def test_joint_limits_are_never_violated(tracked):
    lim = tracked.skeleton.joint_limits
    assert np.all(tracked.r >= lim[..., 0] - 1e-12)
    assert np.all(tracked.r <= lim[..., 1] + 1e-12)


def test_gate_rejects_the_confident_outliers(session, tracked):
    sk, rig, _, _, det, lik, truth, truth_px = session
    status = tracked.info["status"]  # (n_cams, T, M)
    off = np.linalg.norm(det - truth_px, axis=-1)
    usable = lik >= 0.9
    outlier = usable & (off > 25.0)
    inlier = usable & (off < 8.0)
    assert outlier.sum() > 50
    assert (status[outlier] == 2).mean() > 0.9
    assert (status[inlier] == 2).mean() < 0.005
    # ... and what it buys: the same data without the gate is clearly worse.
    ungated = acm_rs.track(rig, sk, det, likelihood=lik, gate=None, progress=False)
    assert np.mean(joint_errors(tracked, truth)) < 0.9 * np.mean(joint_errors(ungated, truth))


def test_samples_match_the_unscented_moments(tracked):
    joints, markers = tracked.sample(200, seed=0)
    assert joints.shape == (200,) + tracked.joints.shape
    assert markers.shape == (200,) + tracked.markers.shape
    sd = joints.std(axis=0)
    ratio = np.median(sd / tracked.joints_std)
    assert 0.85 < ratio < 1.15, ratio
    z = np.abs(joints.mean(axis=0) - tracked.joints) / tracked.joints_std
    assert np.median(z) < 0.5
    with pytest.raises(ValueError, match="n must be"):
        tracked.sample(0)


def test_reprojection_error_and_save_round_trip(tracked, tmp_path):
    err = tracked.reprojection_error()
    assert err.shape == tracked.detections.shape[:3]
    assert np.isnan(err[np.isnan(tracked.detections[..., 0])]).all()
    assert 1.0 < np.nanmedian(err) < 4.0
    npz, csv = tracked.save(tmp_path / "pose")
    back = np.load(npz)
    np.testing.assert_array_equal(back["joints"], tracked.joints)
    np.testing.assert_array_equal(back["state_cov"], tracked.state_cov)
    assert list(back["joint_names"]) == list(tracked.joint_names)
    df = pd.read_csv(csv)
    assert len(df) == tracked.n_frames
    j0 = tracked.joint_names[0]
    np.testing.assert_allclose(df[f"{j0}_x"], tracked.joints[:, 0, 0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(df[f"{j0}_z_std"], tracked.joints_std[:, 0, 2], rtol=1e-5)
    assert "converged" in tracked.summary()
    back = acm_rs.PoseResult.load(npz)
    np.testing.assert_array_equal(back.r, tracked.r)
    np.testing.assert_array_equal(back.info["status"], tracked.info["status"])
    np.testing.assert_array_equal(back.info["params"]["Vz"], tracked.info["params"]["Vz"])
    np.testing.assert_allclose(back.reprojection_error(), err, rtol=1e-9, atol=1e-9)  # px
    assert back.state_map.n_state == tracked.state_map.n_state


def test_missing_frames_are_predicted(session):
    sk, rig, _, _, det, lik, truth, _ = session
    d = det[:, :60].copy()
    d[:, 20:30] = np.nan  # ten frames without any detection
    res = acm_rs.track(rig, sk, d, likelihood=lik[:, :60], progress=False, max_iter=5)
    assert np.isfinite(res.joints).all()
    gap = joint_errors(res, truth[:60])[20:30]
    around = joint_errors(res, truth[:60])[:15]
    assert np.all(res.joints_std[20:30].mean(axis=(1, 2)) > res.joints_std[:15].mean())
    assert gap.mean() < 3.0 and around.mean() < 0.15  # interpolated in the gap (cm)


def test_marker_names_and_likelihood_cutoff(session):
    sk, rig, _, _, det, lik, _, _ = session
    order = np.random.default_rng(0).permutation(sk.n_markers)
    names = [f"marker_{sk.marker_names[k]}_start" for k in order]
    got = _measurements(rig, sk, det[:, :, order], lik[:, :, order], 0.9, names)
    ref = _measurements(rig, sk, det, lik, 0.9, None)
    np.testing.assert_array_equal(got, ref)
    assert np.isnan(ref[lik < 0.9]).all() and np.isfinite(ref[lik >= 0.9]).all()


def test_dlc_prediction_files_feed_the_tracker(session, tmp_path):
    sk, rig, _, _, det, lik, _, _ = session
    paths = []
    for c in range(len(rig)):
        cols = pd.MultiIndex.from_tuples(
            [("DLC_net", bp, co) for bp in sk.marker_names for co in ("x", "y", "likelihood")],
            names=["scorer", "bodyparts", "coords"],
        )
        data = np.concatenate([det[c, :20], lik[c, :20, :, None]], axis=-1).reshape(20, -1)
        p = tmp_path / f"cam{c}DLC_net.csv"
        pd.DataFrame(data, columns=cols).to_csv(p)
        paths.append(p)
    ls = acm_rs.dlc.read_labels(paths)
    got = _measurements(rig, sk, ls.points, ls.likelihood, 0.9, ls.bodyparts)
    np.testing.assert_allclose(got, _measurements(rig, sk, det[:, :20], lik[:, :20], 0.9, None))


@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda d, lk: (d[:3], lk[:3]), "cameras"),
        (lambda d, lk: (d[:, :, :10], lk[:, :, :10]), "markers"),
        (lambda d, lk: (d, lk[:, :5]), "likelihood must have shape"),
        (lambda d, lk: (np.full_like(d, np.nan), lk), "no detection is usable"),
        (lambda d, lk: (d, np.zeros_like(lk)), "pcutoff"),
        (lambda d, lk: (np.where(np.isnan(d), np.inf, d), lk), "infinity"),
    ],
)
def test_bad_input_is_a_clear_error(session, change, match):
    sk, rig, _, _, det, lik, _, _ = session
    d, lk = change(det[:, :10].copy(), lik[:, :10].copy())
    if match == "infinity":
        d[0, 0, 0, 0] = np.inf
    with pytest.raises(ValueError, match=match):
        acm_rs.track(rig, sk, d, likelihood=lk, progress=False)


def test_unknown_marker_names_and_options_are_errors(session):
    sk, rig, _, _, det, lik, _, _ = session
    names = list(sk.marker_names)
    names[3] = "marker_tail_tip_start_typo"
    with pytest.raises(ValueError, match="unknown markers"):
        acm_rs.track(rig, sk, det[:, :5], likelihood=lik[:, :5], marker_names=names)
    with pytest.raises(ValueError, match="method"):
        acm_rs.track(rig, sk, det[:, :5], method="kalman")
    with pytest.raises(ValueError, match="gate"):
        acm_rs.track(rig, sk, det[:, :5], gate=1.5, progress=False)
    with pytest.raises(ValueError, match="noise"):
        acm_rs.track(rig, sk, det[:, :5], noise=0.0)


def test_marker_std_from_rust_equals_the_python_unscented_transform(tracked):
    import dataclasses

    from acm_rs.export._common import posterior_variance

    # the forward kinematics' SDs (info["markers_std"] holds the model misfit too)
    rust = tracked.info["markers_std_fk"] ** 2
    np.testing.assert_array_equal(
        posterior_variance(tracked, "markers"), tracked.info["markers_std"] ** 2
    )
    info = {k: v for k, v in tracked.info.items() if k != "markers_std"}
    python = posterior_variance(dataclasses.replace(tracked, info=info), "markers")
    # (the Python path adds a 1e-12 jitter to the covariance: ~1e-9 cm² here)
    np.testing.assert_allclose(rust, python, rtol=1e-4, atol=1e-8)


def test_wrong_camera_order_and_units_are_refused(session):
    """DeepLabCut files in the wrong camera order, or a calibration in mm with a model in cm,
    are refused before EM with a message that says what to fix (issue 12 item 6)."""
    sk, rig, _, _, det, lik, _, _ = session
    short = det[:, :30]
    swapped = short[[1, 0, 2, 3]]
    with pytest.raises(ValueError, match=r"not in the calibration's camera order"):
        acm_rs.track(rig, sk, swapped, likelihood=lik[[1, 0, 2, 3], :30], progress=False)
    with (
        pytest.warns(UserWarning, match="implausible"),
        pytest.raises(ValueError, match=r"calibration in mm while the model is in cm"),
    ):
        acm_rs.track(rig.scaled(10.0), sk, short, likelihood=lik[:, :30], progress=False)


@pytest.mark.parametrize("motion", ["random_walk", "velocity"])
def test_results_do_not_depend_on_the_world_unit(session, motion):
    """Issue 26 item 2: the same detections with rig and skeleton in cm, in mm, or in 6.5 cm
    board squares (no unit declared) give the same joints in their units to 1 % of the
    median error, with EM run to its own stop (not a fixed iteration count), for the random
    walk and the velocity model."""
    sk, rig, _, _, det, lik, truth, _ = session
    det, lik, truth = det[:, :60], lik[:, :60], truth[:60]
    ref = acm_rs.track(rig, sk, det, likelihood=lik, progress=False, motion=motion)
    assert ref.info["converged"] and ref.info["motion"] == motion
    median_err = np.median(joint_errors(ref, truth))
    for factor, units in [(10.0, "mm"), (1 / 6.5, "")]:
        res = acm_rs.track(rig.scaled(factor, units=units or None), sk.scaled(factor, units),
                           det, likelihood=lik, progress=False, motion=motion)  # fmt: skip
        assert len(res.em_history) == len(ref.em_history)
        err = np.linalg.norm(res.joints / factor - ref.joints, axis=-1)
        assert err.max() < 0.01 * median_err, (err.max(), median_err)
        np.testing.assert_allclose(res.joints_std / factor, ref.joints_std, rtol=1e-6)
        assert res.info["log_likelihood"] == pytest.approx(ref.info["log_likelihood"], abs=1e-6)


def test_declared_units_are_recorded_and_checked(session, tmp_path):
    sk, rig, _, _, det, lik, _, _ = session
    assert rig.units == "cm"
    rig.scaled(10.0, units="mm").save(tmp_path / "calibration.toml")
    back = acm_rs.CameraRig.load(tmp_path / "calibration.toml")
    assert back.units == "mm"
    with pytest.raises(ValueError, match=r"rig.scaled\(0.1, units='cm'\)"):
        acm_rs.track(back, sk, det[:, :20], likelihood=lik[:, :20], progress=False)


def test_student_t_noise_model(session):
    """The Student-t measurement model (EM weights) tracks as well as the Gaussian with the
    gate, without any gate, and learns a measurement SD near the detections' 2 px."""
    sk, rig, _, _, det, lik, truth, _ = session
    res = acm_rs.track(rig, sk, det, likelihood=lik, progress=False, noise_model="student",
                       gate=None)  # fmt: skip
    ref = acm_rs.track(rig, sk, det, likelihood=lik, progress=False, gate=None)
    e, e_ref = joint_errors(res, truth), joint_errors(ref, truth)
    assert np.median(e) < 0.8 * np.median(e_ref)  # outliers no longer inflate V_x
    sd_px = np.sqrt(np.median(res.info["params"]["Vx_diag"])) * 640.0
    sd_ref = np.sqrt(np.median(ref.info["params"]["Vx_diag"])) * 640.0
    assert 1.5 < sd_px < 3.0 < sd_ref
    assert res.info["noise_model"] == "student"
    with pytest.raises(ValueError, match="noise_model"):
        acm_rs.track(rig, sk, det, likelihood=lik, progress=False, noise_model="cauchy")


def test_stretches_without_detections_are_reported(session):
    sk, rig, _, _, det, lik, _, _ = session
    d = det[:, :80].copy()
    d[:, 30:45] = np.nan
    with pytest.warns(UserWarning, match=r"frames 30-44\)"):
        res = acm_rs.track(rig, sk, d, likelihood=lik[:, :80], progress=False, max_iter=3)
    assert res.info["empty_stretches"] == [(30, 44)]


def test_velocity_model_beats_the_random_walk_also_across_a_gap(session, tracked):
    """Issue 12 item 4: the position-velocity state (default) against the paper's random
    walk on the same detections, and with 30 frames without any detection (the velocity's
    broad prior there is linearised about the random walk's posterior)."""
    sk, rig, _, _, det, lik, truth, _ = session
    rw = acm_rs.track(rig, sk, det, likelihood=lik, progress=False, motion="random_walk")
    assert rw.info["motion"] == "random_walk" and rw.info["params"]["Vz"].shape[0] == 50
    e_vel, e_rw = joint_errors(tracked, truth), joint_errors(rw, truth)
    assert np.mean(e_vel) < 0.9 * np.mean(e_rw), (np.mean(e_vel), np.mean(e_rw))
    gap = det.copy()
    gap[:, 40:70] = np.nan
    with pytest.warns(UserWarning, match="without any detection"):
        vel = acm_rs.track(rig, sk, gap, likelihood=lik, progress=False)
        rw = acm_rs.track(rig, sk, gap, likelihood=lik, progress=False, motion="random_walk")
    assert vel.info["motion"] == "velocity", vel.info["motion_note"]
    inside = slice(40, 70)
    e_vel, e_rw = joint_errors(vel, truth)[inside], joint_errors(rw, truth)[inside]
    assert np.median(e_vel) < 0.8 * np.median(e_rw), (np.median(e_vel), np.median(e_rw))
    # the frames after the gap are found again (no loss of lock)
    after = slice(70, 90)
    assert np.max(joint_errors(vel, truth)[after]) < 5 * np.max(joint_errors(tracked, truth))
    # the velocity's SDs grow inside the gap
    sd = np.linalg.norm(vel.joints_std, axis=-1).mean(axis=1)
    assert sd[55] > 5 * np.median(sd[:40])
    with pytest.raises(ValueError, match="motion must be one of"):
        acm_rs.track(rig, sk, det, likelihood=lik, progress=False, motion="spline")


def test_ctrl_c_in_the_random_walk_run_reports_the_random_walk(session, monkeypatch):
    """Interrupted before the velocity model's EM: the result says so and is the random
    walk's (not labelled velocity)."""
    import sys

    tr = sys.modules["acm_rs.tracking.track"]
    sk, rig, _, _, det, lik, _, _ = session

    def ctrl_c(self, iteration, delta, seconds, stats):
        if iteration == 2:
            raise KeyboardInterrupt
        return True

    monkeypatch.setattr(tr._Printer, "__call__", ctrl_c)
    res = acm_rs.track(rig, sk, det[:, :40], likelihood=lik[:, :40], max_iter=10)
    assert res.info["interrupted"] and res.info["motion"] == "random_walk"
    assert "interrupted" in res.info["motion_note"]
    assert [h["motion"] for h in res.em_history] == ["random_walk"] * 2


def test_em_says_when_max_iter_ended_it():
    """Issue 26 item 4 (in part): reaching max_iter without convergence is said, not only
    recorded in info["converged"]; a converged run says nothing of the kind."""
    import warnings

    rig = demo_rig()
    sk = models.rat()
    t, r = datasets.smooth_motion(sk, 12, seed=1)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=2)
    with pytest.warns(UserWarning, match="max_iter=2 without converging"):
        res = acm_rs.track(rig, sk, det, likelihood=lik, max_iter=2, motion="random_walk")
    assert not res.info["converged"] and 1 <= res.info["best_iteration"] <= 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = acm_rs.track(rig, sk, det, likelihood=lik, motion="random_walk")
    assert res.info["converged"]
    assert not [w for w in caught if "without converging" in str(w.message)]


def test_em_returns_the_parameters_of_its_best_log_likelihood(tracked):
    """Issue 26 item 4: the returned parameters score at least as high as every parameter
    set the E-steps of the model used evaluated (the log-likelihood is not monotone)."""
    info = tracked.info
    lls = [h["log_likelihood"] for h in tracked.em_history if h["motion"] == info["motion"]]
    used = tracked.em_history[-1]["used"]
    assert info["log_likelihood"] >= max(lls) - info["ll_tol"] * used
    k = info["returned_iteration"]
    assert k is None or 1 <= k <= len(lls)


def test_em_says_when_patience_ended_it():
    """Issue 26 item 4: a run that stopped because ``EM_PATIENCE`` E-steps stayed below the
    best says so (and not that ``max_iter`` ended it), naming the returned iteration."""
    from types import SimpleNamespace

    from acm_rs.tracking.track import EM_PATIENCE, _warn_em

    lls = [10.0, 20.0] + [19.0 - k for k in range(EM_PATIENCE)]
    hist = [{"log_likelihood": v, "used": 100, "motion": "velocity"} for v in lls]
    info = {"motion": "velocity", "interrupted": False, "converged": False, "stalled": True,
            "returned_iteration": 2}  # fmt: skip
    with pytest.warns(UserWarning) as rec:
        _warn_em(SimpleNamespace(info=info, em_history=hist), max_iter=100, ll_tol=1e-3)
    msgs = [str(w.message) for w in rec]
    assert len(msgs) == 1, msgs
    assert f"for {EM_PATIENCE} iterations" in msgs[0] and "iteration 2 are returned" in msgs[0]
    assert "max_iter" not in msgs[0]
    assert info["best_iteration"] == 2


@pytest.mark.parametrize("outliers", [0.0, 0.05])
def test_initial_vx_is_the_noise_of_the_detections(session, outliers):
    """V_x starts at the detections' noise (2 px), robust to confident outliers, and in
    normalised pixels per axis (640, 512)."""
    from acm_rs.tracking.track import default_normalization, initial_vx

    sk, rig, t, r, _, _, _, _ = session
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, noise_px=2.0, missing=0.1,
                                            outliers=outliers, seed=7)  # fmt: skip
    det = _measurements(rig, sk, det, lik, 0.9, None)
    norm = default_normalization(rig, sk)
    vx = initial_vx(rig, sk, det, norm)
    assert vx.shape == (4 * sk.n_markers * 2,)
    sd_px = np.sqrt(vx[:2]) * np.array(norm.pixel)
    assert np.all((sd_px > 1.6) & (sd_px < 2.6)), sd_px
    np.testing.assert_array_equal(vx[0::2], vx[0])


def test_scaled_skeleton_is_the_same_animal_in_another_unit(session):
    sk, _, t, r, _, _, _, _ = session
    mm = sk.scaled(10.0, "mm")
    assert mm.units == "mm" and sk.units != "mm"
    j, m = sk.forward(t[:5], r[:5])
    j10, m10 = mm.forward(10.0 * t[:5], r[:5])
    np.testing.assert_allclose(j10, 10.0 * j, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(m10, 10.0 * m, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(mm.rest_pose()[0], 10.0 * sk.rest_pose()[0], atol=1e-12)
    with pytest.raises(ValueError, match="scale factor"):
        sk.scaled(0.0)
