"""Model misfit of the markers: honest marker uncertainty on real motion (issue 26 item 3).

The tracker's emission (ACM supp. eq. 3-4) puts marker ``k`` of frame ``t`` exactly at the
forward kinematics ``FK_k(z_t)`` of the pose. A real animal is not a rigid skeleton with
markers glued to its bones (skin slides, the spine bends between joints, a keypoint detector's
"marker" is not a fixed point of a bone), so the true marker deviates from ``FK_k(z_t)`` by a
per-marker misfit the posterior does not contain, and its 95 % intervals are too narrow. This
module estimates that misfit from the tracked result and the detections (never from a truth)
and folds it into the marker posterior.

Model (``u = m_{k,t} - FK_k(ẑ_t)``: the FK marker's error)::

    m_{k,t}   = FK_k(z_t) + δ_{k,t},          δ_{k,t} ~ N(0, Σ_k), independent over frames
    x_{c,k,t} = π_c(m_{k,t}) + ε_{c,k,t},     ε ~ N(0, R_{c,k})  (px², per image axis)
    r_c       = x_c - π_c(FK_k(ẑ_t)) ≈ J_c u + ε_c,   J_c = ∂π_c/∂m at FK_k(ẑ_t)  (2 × 3)

Estimate of ``Σ_k`` (method of moments). Detection noise is independent per camera, the
marker's error ``u`` is common to all cameras, so for two cameras ``c ≠ c'`` that both used
the marker's detection in frame ``t``::

    E[r_c r_c'ᵀ] = J_c U_k J_c'ᵀ,        U_k = E[u uᵀ]

whatever ``V_x`` EM learned (EM's ``V_x`` absorbs part of the misfit, so subtracting it
would subtract misfit too). ``U_k`` (``σ_k² I₃``, or 3 × 3 symmetric) is the least-squares
solution of these equations over every pair and frame, each whitened by ``V_x^{-1/2}``, and
``Σ_k = psd(U_k)`` (negative eigenvalues set to 0). The posterior covariance ``P_{k,t}`` of
the FK marker is not subtracted: the pose was fitted to these same detections, so its error
is anti-correlated with their noise (for an exact linear-Gaussian model the residuals have
covariance ``R - J P Jᵀ``, common part ``-J_c P J_c'ᵀ``); where the model is exact ``U_k``
is ``≤ 0`` and ``Σ_k ≈ 0``. Measured through the tracker on motion with a known misfit,
``psd(U_k)`` recovers 0.91-0.95 of the true SD, ``psd(U_k - P̄_k)`` 0.76-0.87 and
``psd(U_k + P̄_k)`` 0.96-1.12 (docs/tracking.md).

Detection noise net of the misfit: EM's ``V_x`` is the mean squared residual about the model
and holds both, so ``R_{c,k} = max(V_x - mean_t diag(J_c Σ_k J_cᵀ), 0.1 V_x)``
(:func:`detection_noise`; with ``V_x`` itself the intervals cover 99.5 % where the noise is
small against the misfit).

Posterior of the true marker given the smoothed pose and the frame's detections (the
Kalman form of ``(Σ_k⁻¹ + Jᵀ R⁻¹ J)⁻¹``, which needs no ``Σ_k⁻¹``; ``J, R, r`` stacked over
the cameras that used the detection; ``P_{k,t}`` the FK marker's posterior covariance, the
unscented transform of the state posterior as for the tracker's ``markers_std``)::

    S = J Σ_k Jᵀ + R,   K = Σ_k Jᵀ S⁻¹
    δ̂ = K r                                     (= (Σ⁻¹ + JᵀR⁻¹J)⁻¹ JᵀR⁻¹ r)
    m̂ = FK_k(ẑ_t) + δ̂
    cov(m) = (Σ_k - K J Σ_k) + (I - K J) P_{k,t} (I - K J)ᵀ

(the error of ``m̂`` is ``(I - K J) u - K ε`` with ``u = δ + e_FK``: the first term is
``(Σ_k⁻¹ + JᵀR⁻¹J)⁻¹``, the second the FK marker's error seen through the correction).
Where no camera used the detection ``δ̂ = 0`` and ``cov(m) = Σ_k + P_{k,t}``; where
``Σ_k = 0`` nothing changes. Joints are not changed (the misfit concerns the markers).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from .result import PoseResult

#: measurement status of the tracker (``filter.rs`` ``status::USED``)
USED = 1
#: shape of ``Σ_k`` that ``misfit="auto"`` uses (measured: docs/tracking.md)
AUTO_SHAPE = "isotropic"
#: options of :func:`acm_rs.track`'s ``misfit``
MODES = ("auto", "full", "isotropic", "off")

__all__ = [
    "MODES",
    "apply_misfit",
    "camera_residuals",
    "detection_noise",
    "estimate_misfit",
    "marker_covariances",
    "marker_posterior",
    "moment_equations",
    "projected_misfit",
    "solve_misfit",
]


def marker_covariances(result: PoseResult, chunk: int = 64) -> np.ndarray:
    """(T, M, 3, 3) posterior covariance of the FK markers (skeleton units²).

    The unscented transform of the state posterior ``N(μ̂_t, V̂_t)`` (position block)
    through forward kinematics with the ``2 n`` sigma points ``μ̂ ± √n L e_i`` and equal
    weights: the full 3 × 3 version of the tracker's ``markers_std`` (whose squares are its
    diagonal).
    """
    if result.state_cov is None:
        raise ValueError("this result has no posterior covariance (method='deterministic')")
    sm, sk = result.state_map, result.skeleton
    n = sm.n_state
    mean = np.asarray(result.state_mean, float)[:, :n]
    cov = np.asarray(result.state_cov, float)[:, :n, :n]
    n_t, n_m = mean.shape[0], sk.n_markers
    out = np.empty((n_t, n_m, 3, 3))
    eye = 1e-14 * np.eye(n)
    for s in range(0, n_t, chunk):
        e = min(s + chunk, n_t)
        c = 0.5 * (cov[s:e] + cov[s:e].transpose(0, 2, 1)) + eye
        dirs = (np.linalg.cholesky(c) * np.sqrt(n)).transpose(0, 2, 1)  # row i: √n L e_i
        sig = np.concatenate([mean[s:e, None] + dirs, mean[s:e, None] - dirs], axis=1)
        _, mk = sm.forward(sig.reshape(-1, n))  # (each sigma point's bone lengths)
        mk = mk.reshape(e - s, 2 * n, n_m, 3)
        d = mk - mk.mean(axis=1, keepdims=True)
        out[s:e] = np.einsum("tsmi,tsmj->tmij", d, d) / (2 * n)
    return out


def camera_residuals(
    rig, markers: np.ndarray, detections: np.ndarray, used: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Residuals of the used detections about the FK markers and the projection Jacobians.

    Parameters
    ----------
    rig : CameraRig
        The cameras (world units = the markers' units).
    markers : (T, M, 3)
        FK markers of the mean poses.
    detections : (C, T, M, 2)
        Detections (px).
    used : (C, T, M) bool
        Entries the tracker used (status 1: not missing, not gated).

    Returns
    -------
    r : (C, T, M, 2)
        ``x - π_c(FK)`` (px), 0 where not used.
    jac : (C, T, M, 2, 3)
        ``∂π_c/∂m`` at the FK markers (px per unit), 0 where not used.
    used : (C, T, M) bool
        ``used`` and finite.
    """
    n_c = detections.shape[0]
    r = np.zeros(detections.shape)
    jac = np.zeros(detections.shape + (3,))
    ok = np.asarray(used, bool).copy()
    for c in range(n_c):
        px, dp, _ = rig[c].project_jacobian(markers)
        good = ok[c] & np.isfinite(px).all(-1) & np.isfinite(detections[c]).all(-1)
        good &= np.isfinite(dp).all(axis=(-2, -1))
        ok[c] = good
        r[c][good] = detections[c][good] - px[good]
        jac[c][good] = dp[good]
    return r, jac, ok


def _sym_basis() -> np.ndarray:
    """(6, 3, 3) basis of symmetric 3 × 3 matrices (xx, yy, zz, xy, xz, yz)."""
    b = np.zeros((6, 3, 3))
    for k, (i, j) in enumerate([(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]):
        b[k, i, j] = b[k, j, i] = 1.0
    return b


def moment_equations(
    r: np.ndarray, jac: np.ndarray, used: np.ndarray, noise_px2: np.ndarray, shape: str = "full"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal equations of ``E[r_c r_c'ᵀ] = J_c U_k J_c'ᵀ`` (every pair of cameras ``c < c'``
    that used marker ``k`` in a frame), whitened by ``R^{-1/2}``; frames can be summed in
    chunks. Returns ``ata (M, nb, nb)``, ``atb (M, nb)`` and ``pairs (M,)`` with ``nb`` 6
    (``shape="full"``) or 1 (``"isotropic"``)."""
    n_c, _, n_m = used.shape
    w = 1.0 / np.sqrt(noise_px2)  # (C, M, 2)
    rw = r * w[:, None]  # whitened residuals (C, T, M, 2)
    jw = jac * w[:, None, :, :, None]
    basis = _basis(shape)
    nb = len(basis)
    ata = np.zeros((n_m, nb, nb))
    atb = np.zeros((n_m, nb))
    pairs = np.zeros(n_m, np.int64)
    for a in range(n_c):
        for b in range(a + 1, n_c):
            both = used[a] & used[b]  # (T, M)
            if not both.any():
                continue
            # J_a E J_bᵀ for every basis matrix E (T, M, nb, 2, 2), and r_a r_bᵀ
            des = np.einsum("tmij,njk,tmlk->tmnil", jw[a], basis, jw[b])
            obs = np.einsum("tmi,tml->tmil", rw[a], rw[b])
            des = des.reshape(des.shape[:3] + (4,)) * both[..., None, None]
            obs = obs.reshape(obs.shape[:2] + (4,)) * both[..., None]
            ata += np.einsum("tmne,tmoe->mno", des, des)
            atb += np.einsum("tmne,tme->mn", des, obs)
            pairs += both.sum(axis=0)
    return ata, atb, pairs


def _basis(shape: str) -> np.ndarray:
    if shape not in ("full", "isotropic"):
        raise ValueError(f"shape must be 'full' or 'isotropic', got {shape!r}")
    return _sym_basis() if shape == "full" else np.eye(3)[None]


def solve_misfit(
    ata: np.ndarray,
    atb: np.ndarray,
    pairs: np.ndarray,
    shape: str = "full",
) -> tuple[np.ndarray, np.ndarray]:
    """``Σ_k = psd(U_k)`` from the normal equations of :func:`moment_equations`; returns
    ``(Σ (M, 3, 3), U (M, 3, 3))``."""
    basis = _basis(shape)
    n_m, nb = atb.shape
    theta = np.zeros((n_m, nb))
    for m in np.flatnonzero(pairs > 0):
        theta[m] = np.linalg.lstsq(ata[m], atb[m], rcond=None)[0]
    common = np.einsum("mn,nij->mij", theta, basis)
    vals, vecs = np.linalg.eigh(common)
    sigma = np.einsum("mij,mj,mkj->mik", vecs, np.clip(vals, 0.0, None), vecs)
    sigma[pairs == 0] = 0.0
    return sigma, common


def estimate_misfit(
    r: np.ndarray,
    jac: np.ndarray,
    used: np.ndarray,
    noise_px2: np.ndarray,
    shape: str = "isotropic",
) -> tuple[np.ndarray, np.ndarray]:
    """Per-marker misfit covariance ``Σ_k`` by the method of moments (module docstring).

    Parameters
    ----------
    r, jac, used
        As returned by :func:`camera_residuals`.
    noise_px2 : (C, M, 2)
        Detection noise variance per camera, marker and image axis (px²), used only to
        whiten the equations.
    shape : {"full", "isotropic"}
        ``Σ_k`` a full 3 × 3 matrix or ``σ_k² I₃``.

    Returns
    -------
    sigma : (M, 3, 3)
        ``Σ_k`` (units²), positive semi-definite; 0 for markers with no frame seen by two
        cameras.
    pairs : (M,)
        Number of (camera pair, frame) equations per marker.
    """
    ata, atb, pairs = moment_equations(r, jac, used, noise_px2, shape)
    return solve_misfit(ata, atb, pairs, shape)[0], pairs


def projected_misfit(
    jac: np.ndarray, used: np.ndarray, sigma: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Sum over the used frames of ``diag(J_c Σ_k J_cᵀ)`` (C, M, 2) px² and their count
    (C, M): the misfit's share of each detection's residual variance."""
    proj = np.einsum("ctmai,mij,ctmaj->ctma", jac, sigma, jac) * used[..., None]
    return proj.sum(axis=1), used.sum(axis=1)


def detection_noise(
    noise_px2: np.ndarray, proj_sum: np.ndarray, count: np.ndarray, floor: float = 0.1
) -> np.ndarray:
    """(C, M, 2) detection noise net of the misfit: ``V_x - mean_t diag(J_c Σ_k J_cᵀ)``
    (EM's ``V_x``, the mean squared residual about the model, holds both), at least
    ``floor · V_x``."""
    mean = proj_sum / np.maximum(count, 1)[..., None]
    return np.maximum(noise_px2 - mean, floor * noise_px2)


def marker_posterior(
    markers: np.ndarray,
    fk_cov: np.ndarray,
    r: np.ndarray,
    jac: np.ndarray,
    used: np.ndarray,
    noise_px2: np.ndarray,
    sigma: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean and covariance of the true markers (module docstring).

    Parameters
    ----------
    markers : (T, M, 3)
        FK markers of the mean poses.
    fk_cov : (T, M, 3, 3)
        Their posterior covariance.
    r, jac, used
        As returned by :func:`camera_residuals` (px, px per unit).
    noise_px2 : (C, M, 2)
        Detection noise variance (px²).
    sigma : (M, 3, 3)
        Misfit covariance ``Σ_k``.

    Returns
    -------
    markers : (T, M, 3)
        ``FK_k(ẑ_t) + δ̂``.
    cov : (T, M, 3, 3)
        ``(Σ_k - K J Σ_k) + (I - K J) P_{k,t} (I - K J)ᵀ``.
    """
    n_c, n_t, n_m = used.shape
    # stack the cameras: J (T, M, 2C, 3), r (T, M, 2C), R (M, 2C); unused rows get J = 0,
    # r = 0 and a unit variance, which makes them carry no information
    jj = (jac * used[..., None, None]).transpose(1, 2, 0, 3, 4).reshape(n_t, n_m, 2 * n_c, 3)
    rr = (r * used[..., None]).transpose(1, 2, 0, 3).reshape(n_t, n_m, 2 * n_c)
    var = np.where(used[..., None], noise_px2[:, None], 1.0)  # (C, T, M, 2)
    var = var.transpose(1, 2, 0, 3).reshape(n_t, n_m, 2 * n_c)
    sj = np.einsum("mij,tmkj->tmik", sigma, jj)  # Σ Jᵀ (T, M, 3, 2C)
    s = np.einsum("tmki,tmil->tmkl", jj, sj)  # J Σ Jᵀ
    s += var[..., None] * np.eye(2 * n_c)
    gain = np.linalg.solve(s, sj.transpose(0, 1, 3, 2)).transpose(0, 1, 3, 2)  # K = Σ Jᵀ S⁻¹
    delta = np.einsum("tmik,tmk->tmi", gain, rr)
    post = sigma[None] - np.einsum("tmik,tmkj->tmij", gain, sj.transpose(0, 1, 3, 2))
    post = 0.5 * (post + post.transpose(0, 1, 3, 2))
    a = np.eye(3) - np.einsum("tmik,tmkj->tmij", gain, jj)  # I - K J
    fk_cov = np.einsum("tmij,tmjk,tmlk->tmil", a, fk_cov, a)
    return markers + delta, post + fk_cov


def apply_misfit(result: PoseResult, mode: str = "auto", chunk: int = 1024) -> PoseResult:
    """Fold the markers' model misfit into ``result`` (in place; returns it).

    ``result.markers`` becomes ``FK(ẑ) + δ̂`` and ``info["markers_std"]`` the SDs of
    ``cov(m)`` (module docstring); the FK-only ones stay in
    ``info["markers_fk"]`` and ``info["markers_std_fk"]``, and ``info["misfit"]`` records
    the mode, ``info["misfit_cov"]`` (M, 3, 3) ``Σ_k`` and ``info["misfit_sd"]`` (M,) the
    RMS SD ``√(tr Σ_k / 3)`` per marker (skeleton units). ``mode``: ``"full"`` (3 × 3
    ``Σ_k``), ``"isotropic"`` (``σ_k² I₃``), ``"auto"`` (the default choice, measured in
    ``docs/tracking.md``) or ``"off"`` (nothing changes). Frames are processed ``chunk`` at
    a time (memory).
    """
    if mode not in MODES:
        raise ValueError(f"misfit must be one of {MODES}, got {mode!r}")
    result.info["misfit"] = mode
    if mode == "off" or result.state_cov is None:
        return result
    shape = AUTO_SHAPE if mode == "auto" else mode
    info = result.info
    info["misfit_shape"] = shape
    n_c, n_t, n_m = result.detections.shape[:3]
    pixel = np.asarray(info["normalization"]["pixel"], float)
    noise = np.asarray(info["params"]["Vx_diag"], float).reshape(n_c, n_m, 2) * pixel**2
    status = np.asarray(info["status"]) == USED
    fk = np.asarray(result.markers, float)
    fk_cov = marker_covariances(result)
    nb = len(_basis(shape))
    ata, atb = np.zeros((n_m, nb, nb)), np.zeros((n_m, nb))
    pairs = np.zeros(n_m, np.int64)
    blocks = [slice(s, min(s + chunk, n_t)) for s in range(0, n_t, chunk)]
    for b in blocks:
        r, jac, used = camera_residuals(result.rig, fk[b], result.detections[:, b], status[:, b])
        a1, a2, a3 = moment_equations(r, jac, used, noise, shape)
        ata, atb, pairs = ata + a1, atb + a2, pairs + a3
    sigma, _ = solve_misfit(ata, atb, pairs, shape)
    proj, count = np.zeros((n_c, n_m, 2)), np.zeros((n_c, n_m), np.int64)
    for b in blocks:
        r, jac, used = camera_residuals(result.rig, fk[b], result.detections[:, b], status[:, b])
        p1, c1 = projected_misfit(jac, used, sigma)
        proj, count = proj + p1, count + c1
    net = detection_noise(noise, proj, count)
    markers, std = np.empty_like(fk), np.empty_like(fk)
    for b in blocks:
        r, jac, used = camera_residuals(result.rig, fk[b], result.detections[:, b], status[:, b])
        markers[b], cov = marker_posterior(fk[b], fk_cov[b], r, jac, used, net, sigma)
        std[b] = np.sqrt(np.clip(np.diagonal(cov, axis1=2, axis2=3), 0.0, None))
    info["markers_fk"] = fk
    info["markers_std_fk"] = info.get("markers_std")
    info["misfit_cov"] = sigma
    info["misfit_sd"] = np.sqrt(np.trace(sigma, axis1=1, axis2=2) / 3.0)
    info["misfit_pairs"] = pairs
    info["misfit_noise_px"] = np.sqrt(net)
    result.markers = markers
    info["markers_std"] = std
    return result
