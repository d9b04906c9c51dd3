"""acm_rs.track for a recording of any length (issue 29 item 1): above its memory budget it
takes the bounded-memory path (EM on windows, the exact streaming smoother), says so once, and
returns the same PoseResult, here from a memory-mapped input."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig
from acm_rs.tracking.track import MEMORY_LIMIT_CAP, default_memory_limit, in_memory_bytes


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, 400, seed=100)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, missing=0.15, outliers=0.01, seed=2)
    path = tmp_path_factory.mktemp("any_length") / "det.npy"
    np.save(path, det)
    truth = datasets.true_positions(sk, t, r)[0]
    return rig, sk, np.load(path, mmap_mode="r"), lik, truth


def test_memory_estimate_and_budget():
    # the velocity state doubles the state: four times the moments of the random walk
    assert in_memory_bytes(1000, 50, "velocity") == 4 * in_memory_bytes(1000, 50, "random_walk")
    assert in_memory_bytes(2000, 50, "auto") == 2 * in_memory_bytes(1000, 50, "velocity")
    assert 0 < default_memory_limit() <= MEMORY_LIMIT_CAP


def test_a_recording_over_the_budget_takes_the_bounded_path_with_the_same_result(case):
    rig, sk, det, lik, truth = case
    kw = dict(likelihood=lik, motion="random_walk")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        full = acm_rs.track(rig, sk, det, memory_limit=float("inf"), **kw)
        assert not [w for w in caught if "bounded memory" in str(w.message)]
        bounded = acm_rs.track(rig, sk, det, memory_limit=1e6, **kw)
    said = [w for w in caught if "bounded memory" in str(w.message)]
    assert len(said) == 1 and "400 frames" in str(said[0].message)
    assert bounded.info["bounded_memory"] and "bounded_memory" not in full.info
    assert bounded.state_cov is None and full.state_cov is not None
    # both searched one frame for second poses (the rat's joint limits leave none)
    for res in (bounded, full):
        assert res.info["second_solutions"]["joints"] == {}
    assert bounded.joints.shape == full.joints.shape == truth.shape
    assert bounded.info["status"].shape == det.shape[:3]
    # the same posterior away from the start (the streaming smoother starts from a single-frame
    # fit, the in-memory one from EM's mu0): within a small fraction of the posterior SD
    after = slice(50, None)
    diff = np.abs(bounded.joints - full.joints)[after] / full.joints_std[after]
    assert np.median(diff) < 0.1
    err_full = np.linalg.norm(full.joints - truth, axis=-1)[after]
    err_bounded = np.linalg.norm(bounded.joints - truth, axis=-1)[after]
    assert np.median(err_bounded) < 1.1 * np.median(err_full)
    assert np.percentile(err_bounded, 95) < 1.2 * np.percentile(err_full, 95)
    # PoseResult's methods work on it
    assert np.isfinite(bounded.reprojection_error()).any()
    assert "tracked 400 frames" in bounded.summary()


def test_options_the_bounded_path_cannot_take_are_refused(case):
    rig, sk, det, lik, _ = case
    with pytest.raises(ValueError, match="noise_model.*raise memory_limit"):
        acm_rs.track(rig, sk, det, likelihood=lik, memory_limit=1e6, noise_model="student")
    with pytest.raises(TypeError, match="unexpected keyword"):
        acm_rs.track(rig, sk, det, likelihood=lik, memory_limit=1e6, n_iterations=3)
    with pytest.raises(ValueError, match="memory_limit must be > 0"):
        acm_rs.track(rig, sk, det, likelihood=lik, memory_limit=0)
    # the per-frame method keeps no moments: never routed
    res = acm_rs.track(rig, sk, det[:, :20], method="deterministic", memory_limit=1.0)
    assert res.info["method"] == "deterministic"


def test_the_marker_misfit_is_not_estimated_on_the_bounded_path(case):
    rig, sk, det, lik, _ = case
    with pytest.raises(ValueError, match="misfit"):
        acm_rs.track(rig, sk, det, likelihood=lik, memory_limit=1e6, misfit="full")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = acm_rs.track(
            rig, sk, det[:, :120], likelihood=lik[:, :120], memory_limit=1e5, misfit="off",
            motion="random_walk", max_iter=3,
        )  # fmt: skip
    assert res.info["bounded_memory"] and res.info["misfit"] == "off"


def test_detections_converted_in_blocks_equal_the_whole(case):
    # the bounded path converts a memory-mapped recording a block at a time into its result
    from acm_rs.tracking.track import _measurements

    rig, sk, det, lik, _ = case
    lik = lik.copy()
    lik[0, 5:9] = 0.2  # below pcutoff
    whole = _measurements(rig, sk, det, lik, 0.9, None)
    blocks = _measurements(rig, sk, det, lik, 0.9, None, block=37)
    np.testing.assert_array_equal(blocks, whole)
    assert np.isnan(whole[0, 5:9]).all()
    # the warning about a cutoff that drops most of a camera's points judges the whole
    # recording, once, in both paths: camera 2 loses 60 % of its points here, in blocks of
    # 37 frames from all to none
    lik[2, :240] = 0.2
    said = []
    for block in (None, 37):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _measurements(rig, sk, det, lik, 0.9, None, block=block)
        said.append([str(w.message) for w in caught if "drops most" in str(w.message)])
    assert len(said[0]) == 1 and said[1] == said[0] and "camera 2" in said[0][0]


def test_em_windows_free_their_covariances_between_iterations(case):
    # the velocity EM of the windows frees each window's covariances after its M-step; the
    # next E-step gives them back (the same moments as a tracker that kept them), and what
    # needs them meanwhile says so
    from acm_rs.state import StateMap
    from acm_rs.tracking.long import _Model, _normalized
    from acm_rs.tracking.track import _first_pose, default_normalization

    rig, sk, det, lik, _ = case
    norm = default_normalization(rig, sk)
    model = _Model(rig, sk, norm, True, 10, None, 1, {}, np.zeros((0, 0)), 0.9)
    x = _normalized(norm, model.detections(np.asarray(det[:, :60]), lik[:, :60]))
    kept, freed = model.tracker(x, order=2), model.tracker(x, order=2)
    ns = kept.n_params_state
    mu0 = np.zeros(ns)
    _, t0, r0 = _first_pose(rig, sk, model.detections(det[:, :60], lik[:, :60]), norm)
    mu0[: kept.n_state] = StateMap(sk, norm, True).start_state(t0, r0)
    p = (mu0, np.eye(ns) * 2e-4, np.eye(ns) * 2e-4, np.full(x[0].size, 1e-4))
    for tr in (kept, freed):
        tr.e_step(*p)
    q = freed.m_step(*p)
    freed.release_covariances()
    for call in (freed.covs, freed.posterior, lambda: freed.m_step(*p)):
        with pytest.raises(ValueError, match="released"):
            call()
    q = (q["mu0"], q["V0"], q["Vz"], q["Vx_diag"])
    assert kept.e_step(*q) == freed.e_step(*q)
    np.testing.assert_array_equal(kept.covs(), freed.covs())
    np.testing.assert_array_equal(kept.means(), freed.means())
