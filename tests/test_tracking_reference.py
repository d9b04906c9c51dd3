"""The Rust UKF / RTS smoother / M-step against a literal NumPy transcription of the
supplement's Alg. 5-9 and 12 (sigma points everywhere, S with identity rows for missing
measurements, D from sigma points, pairwise sigma points for V_z), on a small skeleton."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_rig

import acm_rs
from acm_rs import _native


def f_ut(m: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 5 with alpha = 1, kappa = 0 (eqs. 42, 46-47)."""
    d = m.size
    chol = np.linalg.cholesky(cov)
    pts = np.empty((2 * d + 1, d))
    pts[0] = m
    pts[1 : d + 1] = m + np.sqrt(d) * chol.T
    pts[d + 1 :] = m - np.sqrt(d) * chol.T
    w = np.full(2 * d + 1, 1.0 / (2 * d))
    w[0] = 0.0
    return pts, w


def wcov(w, a, b):
    return (w[:, None] * a).T @ b


def ukf_step(mu, v, vz, vx, x_t, g):
    """Alg. 6, line by line."""
    z, w = f_ut(mu, v)
    zbar = w @ z
    p = vz + wcov(w, z - zbar, z - zbar)
    z, w = f_ut(zbar, p)
    xs = g(z)
    xbar = w @ xs
    s = np.diag(vx) + wcov(w, xs - xbar, xs - xbar)
    miss = np.isnan(x_t)
    s[miss, :] = 0.0
    s[:, miss] = 0.0
    s[miss, miss] = 1.0
    c = wcov(w, z - zbar, xs - xbar)
    c[:, miss] = 0.0
    k = c @ np.linalg.inv(s)
    nu = x_t - xbar
    nu[miss] = 0.0
    return zbar + k @ nu, p - k @ c.T


def uks_step(mu_f, v_f, mu_next, v_next, vz):
    """Alg. 8, line by line."""
    z, w = f_ut(mu_f, v_f)
    zbar = w @ z
    p = vz + wcov(w, z - zbar, z - zbar)
    d = wcov(w, z - mu_f, z - zbar)
    g = d @ np.linalg.inv(p)
    return mu_f + g @ (mu_next - zbar), v_f + (g @ v_next - d) @ g.T, g


def uks(mu0, v0, vz, vx, x, g):
    """Alg. 7 + 9."""
    t_len = x.shape[0]
    mf, vf = [mu0], [v0]
    for t in range(t_len):
        m, v = ukf_step(mf[-1], vf[-1], vz, vx, x[t], g)
        mf.append(m)
        vf.append(v)
    ms, vs, gs = list(mf), list(vf), [None] * t_len
    for t in range(t_len - 1, -1, -1):
        ms[t], vs[t], gs[t] = uks_step(mf[t], vf[t], ms[t + 1], vs[t + 1], vz)
    return np.array(mf), np.array(vf), np.array(ms), np.array(vs), gs


def m_step(ms, vs, gs, x, g):
    """Alg. 12 with eq. 81 for V_x."""
    t_len, n = x.shape[0], ms.shape[1]
    vz = np.zeros((n, n))
    sums = np.zeros(x.shape[1])
    counts = np.zeros(x.shape[1])
    for t in range(1, t_len + 1):
        pm = np.concatenate([ms[t], ms[t - 1]])
        cross = vs[t] @ gs[t - 1].T
        pv = np.block([[vs[t], cross], [cross.T, vs[t - 1]]])
        pts, w = f_ut(pm, pv)
        diff = pts[:, :n] - pts[:, n:]
        vz += wcov(w, diff, diff) / t_len
        z, w = f_ut(ms[t], vs[t])
        xs = g(z)
        ok = ~np.isnan(x[t - 1])
        sums[ok] += w @ (x[t - 1, ok] - xs[:, ok]) ** 2
        counts[ok] += 1
    return ms[0], vs[0], vz, sums / counts


@pytest.fixture
def problem(small_skeleton):
    sk = small_skeleton
    rig = make_rig(distance=15.0, n=2)
    norm = acm_rs.Normalization(translation=5.0)
    sm = acm_rs.StateMap(sk, norm, joint_limits=True)
    rng = np.random.default_rng(4)
    t_len = 9
    z_true = np.cumsum(rng.normal(scale=0.05, size=(t_len, sm.n_state)), axis=0)
    z_true[:, :3] += [0.0, 0.0, 0.1]

    def g(z):
        return sm.emission(rig, z).reshape(len(z), -1)

    x = g(z_true) + rng.normal(scale=0.002, size=(t_len, 2 * len(rig) * sk.n_markers))
    x[rng.random(x.shape) < 0.2] = np.nan
    x[3] = np.nan  # a frame without any measurement
    x[5, 2:] = np.nan
    n = sm.n_state
    mu0 = z_true[0] + 0.01
    v0 = np.eye(n) * 2e-3 + 1e-4
    vz = np.eye(n) * 1e-3 + 2e-4 * np.ones((n, n))
    vx = np.linspace(1e-4, 3e-4, x.shape[1])
    lim = sk.joint_limits
    native = _native.NativeTracker(
        sk._native, rig.get_params(), np.ascontiguousarray(lim[..., 0]),
        np.ascontiguousarray(lim[..., 1]), norm._tuple(), True,
        np.ascontiguousarray(x.reshape(t_len, len(rig), sk.n_markers, 2)),
        relinearize=0,  # the paper's single unscented update, as the reference
    )  # fmt: skip
    return native, (mu0, v0, vz, vx), x, g


def test_filter_smoother_and_m_step_match_the_literal_algorithms(problem):
    native, (mu0, v0, vz, vx), x, g = problem
    mf, vf, ms, vs, gs = uks(mu0, v0, vz, vx, x, g)
    native.e_step(mu0, v0, vz, vx, None, False)
    np.testing.assert_allclose(native.means(), mf, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(native.covs(), vf, rtol=1e-6, atol=1e-10)
    stats = native.e_step(mu0, v0, vz, vx)
    assert stats["used"] == int(np.isfinite(x).sum())
    np.testing.assert_allclose(native.means(), ms, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(native.covs(), vs, rtol=1e-6, atol=1e-10)
    p = native.m_step(mu0, v0, vz, vx)
    mu0_r, v0_r, vz_r, vx_r = m_step(ms, vs, gs, x, g)
    np.testing.assert_allclose(p["mu0"], mu0_r, rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(p["V0"], v0_r, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(p["Vz"], vz_r, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(p["Vx_diag"], vx_r, rtol=1e-6, atol=1e-12)
    assert (native.mask()[3] == 0).all()


def test_em_iterations_match_the_reference(problem):
    native, (mu0, v0, vz, vx), x, g = problem
    params = (mu0, v0, vz, vx)
    deltas = []
    for _ in range(3):
        _, _, ms, vs, gs = uks(*params, x, g)
        new = m_step(ms, vs, gs, x, g)
        rel = [np.abs((b - a) / a) for a, b in zip(
            (params[0], np.diag(params[1]), np.diag(params[2]), params[3]),
            (new[0], np.diag(new[1]), np.diag(new[2]), new[3]), strict=True)]  # fmt: skip
        deltas.append(np.concatenate(rel).mean())  # Alg. 13
        params = new
    got, history, converged, interrupted = native.run_em(mu0, v0, vz, vx, 3, 1e-12)
    assert not converged and not interrupted and len(history) == 3
    np.testing.assert_allclose([h["delta"] for h in history], deltas, rtol=1e-6)
    np.testing.assert_allclose(got["Vz"], params[2], rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(got["Vx_diag"], params[3], rtol=1e-5, atol=1e-14)
    # After run_em the moments are the smoother's under the returned parameters.
    _, _, ms, _, _ = uks(*params, x, g)
    np.testing.assert_allclose(native.means(), ms, rtol=1e-6, atol=1e-9)


def test_callback_can_stop_em(problem):
    native, (mu0, v0, vz, vx), _, _ = problem
    calls = []

    def cb(it, delta, seconds, stats):
        calls.append((it, delta))
        return it < 2

    _, history, converged, interrupted = native.run_em(mu0, v0, vz, vx, 50, 1e-12, None, cb)
    assert interrupted and not converged
    assert [c[0] for c in calls] == [1, 2] and len(history) == 2


def test_non_positive_definite_covariance_raises(problem):
    native, (mu0, v0, vz, vx), _, _ = problem
    bad = vz.copy()
    bad[0, 0] = -1.0
    with pytest.raises(acm_rs.AcmNumericalError, match="not positive definite"):
        native.e_step(mu0, v0, bad, vx)
    with pytest.raises(ValueError, match="V_x must be positive"):
        native.e_step(mu0, v0, vz, np.zeros_like(vx))
    with pytest.raises(ValueError, match="shape"):
        native.e_step(mu0[:-1], v0, vz, vx)
