"""Calibration refined on the animal's own labelled keypoints (issue 28; beyond the paper).

Where the cameras of a rig disagree about the animal more than a body model can absorb (a
board calibration a little off, a camera bumped after calibrating), the labelled keypoints
themselves are a calibration target, as in anipose's bundle adjustment on keypoints: the
cameras' extrinsics (optionally focal lengths and principal points) and one 3D point per
labelled (frame, keypoint) seen in >= 2 cameras minimise

    sum rho(|pi_c(X_fk) - x_cfk|^2 / s^2)  +  sum |(theta_c - theta_c0) / sigma_theta|^2

with a robust ``rho`` (scipy's ``soft_l1``, scale ``s`` px) against mislabels, and a weak prior
that holds the cameras near the board calibration (it fixes the gauge: a rigid motion and a
scale of the whole rig leave the reprojections unchanged). Solved by
``scipy.optimize.least_squares(method="trf")`` with the exact sparse Jacobian from Rust
(``_native.project_jacobian``). Use training frames only; :func:`acm_rs.evaluate.evaluate`
with ``refine_calibration=True`` reports held-out frames before and after.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from .. import _native
from ..camera import CameraRig
from ..learning import triangulate
from ..rotation import rodrigues, rodrigues_jacobian

__all__ = ["KeypointRefinement", "refine_on_keypoints"]

#: Camera parameters refined: extrinsics, and with ``intrinsics=True`` fx, fy, cx, cy.
EXTRINSICS = np.arange(6)
INTRINSICS = np.arange(6, 10)


@dataclass
class KeypointRefinement:
    """Result of :func:`refine_on_keypoints`.

    Attributes
    ----------
    rig : CameraRig
        The refined calibration.
    rms_before, rms_after : float
        RMS reprojection error (px) of the used labels about their best 3D points with the
        starting rig (only the points fitted, same robust loss), and with the refined rig.
    per_camera_before, per_camera_after : numpy.ndarray, shape (n_cams,)
        The same per camera.
    change : dict
        Per camera: rotation change (deg), camera-centre shift (world units) and, with
        intrinsics, focal-length change (%).
    info : dict
        Labels and points used, optimiser outcome.
    """

    rig: CameraRig
    rms_before: float
    rms_after: float
    per_camera_before: np.ndarray
    per_camera_after: np.ndarray
    change: dict
    info: dict = field(default_factory=dict)

    def summary(self) -> str:
        names = [c.name or str(i) for i, c in enumerate(self.rig)]
        lines = [
            f"calibration refined on {self.info['labels']} keypoint labels "
            f"({self.info['points']} 3D points, {self.info['frames']} frames): RMS "
            f"{self.rms_before:.2f} -> {self.rms_after:.2f} px",
        ]
        for i, n in enumerate(names):
            ch = self.change[n]
            lines.append(
                f"  {n}: {self.per_camera_before[i]:.2f} -> {self.per_camera_after[i]:.2f} px, "
                f"rotated {ch['rotation_deg']:.2f} deg, moved {ch['shift']:.3g}"
                + (f", focal {ch['focal_pct']:+.2f} %" if "focal_pct" in ch else "")
            )
        return "\n".join(lines)


def _centres(params: np.ndarray) -> np.ndarray:
    """Camera centres ``-R(r)^T t`` of parameter rows ``(C, 16)`` -> ``(C, 3)``."""
    rot = rodrigues(params[:, :3])
    return -np.einsum("cba,cb->ca", rot, params[:, 3:6])


def _rms(residual_px: np.ndarray, cams: np.ndarray, n_cams: int) -> tuple[float, np.ndarray]:
    sq = np.sum(residual_px.reshape(-1, 2) ** 2, axis=1)
    per = np.array(
        [np.sqrt(np.mean(sq[cams == c])) if np.any(cams == c) else np.nan for c in range(n_cams)]
    )
    return float(np.sqrt(np.mean(sq))), per


def _problem(
    rig: CameraRig,
    labels: np.ndarray,
    intrinsics: bool,
    scale_px: float,
    rotation_sd_deg: float,
    shift_sd: float | None,
    min_views: int,
) -> SimpleNamespace:
    """The least-squares problem of :func:`refine_on_keypoints`: residuals ``fun(x)``, their
    exact sparse Jacobian ``jac(x)``, the start ``x0`` (cameras' free parameters, then the
    points), and what the solver and the report need."""
    from scipy.sparse import csr_matrix

    lab = np.asarray(labels, dtype=np.float64)
    n_cams = len(rig)
    if lab.ndim != 4 or lab.shape[0] != n_cams or lab.shape[-1] != 2:
        raise ValueError(f"labels must have shape ({n_cams} cameras, F, K, 2), got {lab.shape}")
    if not (scale_px > 0 and rotation_sd_deg > 0):
        raise ValueError("scale_px and rotation_sd_deg must be > 0")
    seen = np.isfinite(lab).all(axis=-1)  # (C, F, K)
    use = seen.sum(axis=0) >= max(min_views, 2)  # (F, K)
    if use.sum() < 6:
        raise ValueError(
            f"only {int(use.sum())} keypoints are labelled in >= {max(min_views, 2)} cameras; "
            "refining a calibration needs more (label more frames in more cameras)"
        )
    lonely = [c for c in range(n_cams) if not (seen[c] & use).any()]
    if lonely:
        names = [rig[c].name or str(c) for c in lonely]
        raise ValueError(f"cameras {names} share no labelled keypoint with another camera")
    x0_pts = triangulate(rig, np.where(use[None, ..., None], lab, np.nan))[use]  # (P, 3)
    ok = np.isfinite(x0_pts).all(axis=1)
    fk = np.argwhere(use)[ok]  # (P, 2) frame, keypoint
    x0_pts = x0_pts[ok]
    n_pts = len(fk)
    point_of = np.full(use.shape, -1)
    point_of[fk[:, 0], fk[:, 1]] = np.arange(n_pts)
    obs_c, obs_f, obs_k = np.nonzero(seen & (point_of >= 0)[None])
    obs_p = point_of[obs_f, obs_k]
    obs_px = lab[obs_c, obs_f, obs_k]  # (N, 2)
    n_obs = len(obs_c)
    free = np.concatenate([EXTRINSICS, INTRINSICS]) if intrinsics else EXTRINSICS
    n_free = len(free)
    p0 = rig.get_params()  # (C, 16)
    centres0 = _centres(p0)
    if shift_sd is None:
        dist = np.linalg.norm(centres0[:, None] - x0_pts[None].mean(axis=1, keepdims=True), axis=-1)
        shift_sd = 0.02 * float(np.mean(dist))
    if not shift_sd > 0:
        raise ValueError(f"shift_sd must be > 0, got {shift_sd}")
    rot_sd = np.radians(rotation_sd_deg)

    def unpack(x):
        params = p0.copy()
        params[:, free] = x[: n_cams * n_free].reshape(n_cams, n_free)
        return params, x[n_cams * n_free :].reshape(n_pts, 3)

    x0 = np.concatenate([p0[:, free].ravel(), x0_pts.ravel()])
    n_cam_cols = n_cams * n_free
    intr_sd = np.repeat(0.05 * p0[:, 6:7], 4, axis=1)  # (C, 4): fx, fy, cx, cy within ~5 %

    def project(x):
        params, pts = unpack(x)
        # every point in every camera with exact derivatives, then the labelled pairs
        px, d_pt, d_par = _native.project_jacobian(np.ascontiguousarray(params), pts)
        return px[obs_c, obs_p], d_pt[obs_c, obs_p], d_par[obs_c, obs_p][..., free]

    def fun(x):
        params, _ = unpack(x)
        px, _, _ = project(x)
        parts = [
            ((px - obs_px) / scale_px).ravel(),
            (params[:, :3] - p0[:, :3]).ravel() / rot_sd,
            (_centres(params) - centres0).ravel() / shift_sd,
        ]
        if intrinsics:
            parts.append(((params[:, 6:10] - p0[:, 6:10]) / intr_sd).ravel())
        out = np.concatenate(parts)
        return np.where(np.isfinite(out), out, 1e6)  # (a point behind a camera)

    def jac(x):
        params, _ = unpack(x)
        _, d_pt, d_par = project(x)
        # labels: camera columns and point columns, exact (Rust)
        cols_par = np.repeat(obs_c[:, None] * n_free + np.arange(n_free)[None], 2, axis=0)
        cols_pt = np.repeat(n_cam_cols + obs_p[:, None] * 3 + np.arange(3)[None], 2, axis=0)
        rows = [np.repeat(np.arange(2 * n_obs), n_free + 3)]
        cols = [np.concatenate([cols_par, cols_pt], axis=1).ravel()]
        data = [np.concatenate([d_par.reshape(-1, n_free), d_pt.reshape(-1, 3)], 1).ravel()]
        data[0] = data[0] / scale_px
        r0 = 2 * n_obs
        cam = np.arange(n_cams)
        # rotation prior: identity / rot_sd on each camera's r
        rows.append(r0 + np.arange(3 * n_cams))
        cols.append((cam[:, None] * n_free + np.arange(3)[None]).ravel())
        data.append(np.full(3 * n_cams, 1.0 / rot_sd))
        r0 += 3 * n_cams
        # centre prior, C = -R(r)^T t: dC/dt = -R^T, dC_i/dr_a = -(dR/dr_a)^T_i. t (exact)
        rot = rodrigues(params[:, :3])  # (C, 3, 3)
        d_rot = rodrigues_jacobian(params[:, :3])  # (C, 3, 3, 3): dR_ab / dr_k
        d_c_dr = -np.einsum("cbik,cb->cik", d_rot, params[:, 3:6])  # (C, 3 [i], 3 [k])
        d_c_dt = -rot.transpose(0, 2, 1)  # (C, 3 [i], 3 [a])
        ii, aa = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
        for block, off in ((d_c_dr, 0), (d_c_dt, 3)):
            rows.append((r0 + 3 * cam[:, None, None] + ii[None]).ravel())
            cols.append((cam[:, None, None] * n_free + off + aa[None]).ravel())
            data.append(block.ravel() / shift_sd)
        r0 += 3 * n_cams
        if intrinsics:
            rows.append(r0 + np.arange(4 * n_cams))
            cols.append((cam[:, None] * n_free + 6 + np.arange(4)[None]).ravel())
            data.append((1.0 / intr_sd).ravel())
            r0 += 4 * n_cams
        return csr_matrix(
            (np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))),
            shape=(r0, len(x)),
        )

    return SimpleNamespace(
        fun=fun, jac=jac, x0=x0, n_cam_cols=n_cam_cols, n_px=2 * n_obs, project=project,
        unpack=unpack, obs_px=obs_px, obs_c=obs_c, n_cams=n_cams, fk=fk, p0=p0,
        centres0=centres0, shift_sd=shift_sd, n_obs=n_obs, n_pts=n_pts,
    )  # fmt: skip


def refine_on_keypoints(
    rig: CameraRig,
    labels: np.ndarray,
    *,
    intrinsics: bool = False,
    scale_px: float = 2.0,
    rotation_sd_deg: float = 2.0,
    shift_sd: float | None = None,
    min_views: int = 2,
    max_nfev: int = 200,
) -> KeypointRefinement:
    """Refine a rig on labelled keypoints (module docs).

    Parameters
    ----------
    rig : CameraRig
        The starting (board) calibration.
    labels : array_like, shape (n_cams, F, K, 2)
        Labelled keypoints in pixels, NaN where not labelled (training frames only).
    intrinsics : bool
        Also refine fx, fy, cx, cy (distortion and skew stay).
    scale_px : float
        Scale of the robust loss (px): residuals well above it count linearly.
    rotation_sd_deg, shift_sd : float
        SDs of the prior on each camera's rotation (deg) and centre (world units; default
        2 % of the mean camera distance from the triangulated points).
    min_views : int
        A keypoint is used where at least this many cameras labelled it.

    Returns
    -------
    KeypointRefinement
    """
    from scipy.optimize import least_squares

    pr = _problem(rig, labels, intrinsics, scale_px, rotation_sd_deg, shift_sd, min_views)
    fun, jac, x0, n_cam_cols, n_px = pr.fun, pr.jac, pr.x0, pr.n_cam_cols, pr.n_px
    project, unpack, obs_px, obs_c, n_cams = pr.project, pr.unpack, pr.obs_px, pr.obs_c, pr.n_cams
    # before: the starting rig with its best points (only the points move)
    cams_fixed = x0[:n_cam_cols]
    pts_only = least_squares(
        lambda xp: fun(np.concatenate([cams_fixed, xp]))[:n_px],
        x0[n_cam_cols:],
        jac=lambda xp: jac(np.concatenate([cams_fixed, xp]))[:n_px, n_cam_cols:],
        method="trf", loss="soft_l1", f_scale=1.0, x_scale="jac", tr_solver="lsmr",
        max_nfev=max_nfev,
    )  # fmt: skip
    x1 = np.concatenate([cams_fixed, pts_only.x])
    px_b, _, _ = project(x1)
    before = _rms(px_b - obs_px, obs_c, n_cams)
    res = least_squares(
        fun, x1, jac=jac, method="trf", loss="soft_l1", f_scale=1.0, x_scale="jac",
        tr_solver="lsmr", max_nfev=max_nfev,
    )  # fmt: skip
    params, _ = unpack(res.x)
    refined = rig.set_params(params)
    px1, _, _ = project(res.x)
    after = _rms(px1 - obs_px, obs_c, n_cams)
    change = {}
    c1 = _centres(params)
    for c, cam in enumerate(rig):
        r_rel = rodrigues(params[c, :3]) @ cam.rotation_matrix.T
        angle = np.degrees(np.arccos(np.clip((np.trace(r_rel) - 1) / 2, -1, 1)))
        ch = {"rotation_deg": float(angle), "shift": float(np.linalg.norm(c1[c] - pr.centres0[c]))}
        if intrinsics:
            ch["focal_pct"] = float(100 * (params[c, 6] / pr.p0[c, 6] - 1))
        change[cam.name or str(c)] = ch
    return KeypointRefinement(
        rig=refined, rms_before=before[0], rms_after=after[0], per_camera_before=before[1],
        per_camera_after=after[1], change=change,
        info={
            "labels": int(pr.n_obs), "points": int(pr.n_pts),
            "frames": int(np.unique(pr.fk[:, 0]).size),
            "nfev": int(res.nfev), "status": int(res.status), "message": str(res.message),
            "intrinsics": bool(intrinsics), "scale_px": scale_px,
            "rotation_sd_deg": rotation_sd_deg, "shift_sd": pr.shift_sd,
        },
    )  # fmt: skip
