"""Straightforward NumPy implementation of Burke & Lasenby (2016), Algorithm 1.

Covariance form with a per-frame inverse of the (n_present x n_present) innovation covariance,
as the authors' code does; the published settings (gamma = 0.9975 on singular values,
R = 1e-3 I, Q = V^T diag(std(diff X)) V, P0 = 1e12 I, m0 = 0). ``printed_gain=True`` uses the
backward gain as printed in Algorithm 1 (P_t Phat_t^-1) instead of the RTS gain
P_t Phat_{t+1}^-1. Written from the paper for benchmarks and tests; not part of the package.
"""

from __future__ import annotations

import numpy as np


def lowdim_paper(
    Y: np.ndarray, *, gamma=0.9975, r=1e-3, printed_gain=False, p0_scale=1e12
) -> np.ndarray:
    """Fill a (T, D) array with NaN gaps; returns the filled copy (observed values kept).

    ``p0_scale``: P0 = p0_scale * I (the authors' 1e12). In this covariance form S = H P H^T + r I
    has a condition number of ~1e15 in the first frames with 1e12, which costs the first few
    filled values up to ~1 mm of rounding; a smaller scale (1e6) gives the same limit well
    conditioned."""
    complete = ~np.isnan(Y).any(axis=1)
    X = Y[complete]
    mean = X.mean(axis=0)
    _, s, vt = np.linalg.svd(X - mean, full_matrices=False)
    k = int(np.searchsorted(np.cumsum(s) / s.sum(), gamma * (1 - 1e-12)) + 1)
    V = vt[:k].T
    Q = V.T @ np.diag(np.std(np.diff(X, axis=0), axis=0)) @ V
    T = Y.shape[0]
    m, P = np.zeros(k), p0_scale * np.eye(k)
    ms, Ps, mp, Pp = [], [], [], []
    for t in range(T):
        m_hat, P_hat = (m, P) if t == 0 else (m, P + Q)
        pres = ~np.isnan(Y[t])
        if pres.any():
            H = V[pres]
            S = H @ P_hat @ H.T + r * np.eye(int(pres.sum()))
            K = P_hat @ H.T @ np.linalg.inv(S)
            m = m_hat + K @ (Y[t, pres] - H @ m_hat - mean[pres])
            P = (np.eye(k) - K @ H) @ P_hat
        else:
            m, P = m_hat, P_hat
        ms.append(m)
        Ps.append(P)
        mp.append(m_hat)
        Pp.append(P_hat)
    sm = ms[-1]
    out = np.empty_like(Y)
    out[-1] = V @ sm + mean
    for t in range(T - 2, -1, -1):
        C = Ps[t] @ np.linalg.inv(Pp[t] if printed_gain else Pp[t + 1])
        sm = ms[t] + C @ (sm - mp[t + 1])
        out[t] = V @ sm + mean
    keep = ~np.isnan(Y)
    out[keep] = Y[keep]
    return out
