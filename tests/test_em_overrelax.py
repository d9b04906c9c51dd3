"""Over-relaxed EM in acm_rs.track (the Rust core's run_em; docs/tracking.md)."""

import numpy as np
import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig


@pytest.fixture(scope="module")
def session():
    rig, sk = demo_rig(), models.rat()
    t, r = datasets.smooth_motion(sk, 60, seed=3)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=4)
    return rig, sk, det, lik


def _track(session, **kw):
    rig, sk, det, lik = session
    return acm_rs.track(
        rig, sk, det, likelihood=lik, motion="random_walk", second_solutions=0, **kw
    )


def test_over_relaxed_steps_are_recorded_and_plain_em_has_none(session):
    plain = _track(session, overrelax=None, max_iter=8)
    assert all(h["step"] == 1.0 and not h["rejected"] for h in plain.em_history)
    over = _track(session, max_iter=8)
    steps = [h["step"] for h in over.em_history]
    assert steps[0] == 1.0 and max(steps) > 1.0
    # the same first E-step (the same start); from the second on the paths differ
    assert over.em_history[0]["log_likelihood"] == plain.em_history[0]["log_likelihood"]
    # an accepted over-relaxed E-step scores at least the one it was extrapolated from
    hist = over.em_history
    for prev, cur in zip(hist, hist[1:], strict=False):
        if cur["step"] > 1.0 and not cur["rejected"] and not prev["rejected"]:
            assert cur["log_likelihood"] >= prev["log_likelihood"]
    # after 8 E-steps over-relaxed EM is at least as far up as plain EM
    best = max(h["log_likelihood"] for h in hist)
    assert best >= max(h["log_likelihood"] for h in plain.em_history) - 1.0
    assert np.isfinite(over.joints).all()


@pytest.mark.parametrize("bad", [1.0, 0.5, float("nan")])
def test_bad_growth_factors_are_refused(session, bad):
    with pytest.raises(ValueError, match="overrelax"):
        _track(session, overrelax=bad, max_iter=2)


def test_the_bounded_memory_paths_windows_over_relax_too(session):
    rig, sk, det, lik = session
    kw = dict(likelihood=lik, motion="random_walk", memory_limit=1e5, second_solutions=0)
    with pytest.warns(UserWarning, match="bounded memory"):
        plain = acm_rs.track(rig, sk, det, overrelax=None, max_iter=8, **kw)
    assert all(h["step"] == 1.0 and not h["rejected"] for h in plain.em_history)
    with pytest.warns(UserWarning, match="bounded memory"):
        over = acm_rs.track(rig, sk, det, max_iter=8, **kw)
    assert over.info["bounded_memory"]
    steps = [h["step"] for h in over.em_history]
    assert steps[0] == 1.0 and max(steps) > 1.0
    best = max(h["log_likelihood"] for h in over.em_history)
    assert best >= max(h["log_likelihood"] for h in plain.em_history) - 1.0
    with pytest.raises(ValueError, match="overrelax"):
        acm_rs.track(rig, sk, det, overrelax=0.5, max_iter=2, **kw)


def test_the_native_extrapolation_checks_its_inputs():
    from acm_rs import _native

    a = (np.zeros(2), np.eye(2), 2 * np.eye(2), np.ones(3))
    b = (np.ones(2), 2 * np.eye(2), 4 * np.eye(2), 2 * np.ones(3))
    mu0, v0, vz, vx = _native.extrapolate_params(a, b, 2.0)
    # η = 2 in closed form: 2b − a, B A⁻¹ B, b² / a
    np.testing.assert_allclose(mu0, [2.0, 2.0])
    np.testing.assert_allclose(vz, 8 * np.eye(2), atol=1e-12)
    np.testing.assert_allclose(v0, 4 * np.eye(2), atol=1e-12)
    np.testing.assert_allclose(vx, 4 * np.ones(3))
    assert _native.extrapolate_params(a, (b[0], -np.eye(2), b[2], b[3]), 2.0) is None
    with pytest.raises(ValueError, match="mu0 must have shape"):
        _native.extrapolate_params(a, (np.ones(3), *b[1:]), 2.0)
    with pytest.raises(ValueError, match="eta must be finite"):
        _native.extrapolate_params(a, b, float("nan"))
