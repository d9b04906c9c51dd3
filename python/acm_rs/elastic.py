"""Elastic segments learned by EM (issue 28 item 2; beyond the paper).

A lab's keypoints (10-30 landmarks on fur over joints, a spine, ears) are not fixed points
of rigid bones: in real 3D labels a mouse's SpineM-SpineF varies by ~15 % and even limb
segments by 1-2 mm. Each elastic bone's length in frame ``tau`` is

    l_{b,tau} = l_b exp(s_{b,tau}),    s_{b,tau} ~ N(0, sigma_b^2)  (independent over frames),

the labels are ``x = pi(FK(z_tau, l_tau)) + N(0, sigma_x^2 I)`` (px), and EM learns the mean
lengths ``l_b``, the stretch SDs ``sigma_b`` (dimensionless, so unit-free) and the label
noise ``sigma_x``:

* E-step (Rust, ``crate::learning::elastic``; Laplace approximation): each frame's MAP pose and
  log-stretch of ``sum |pi - x|^2 / sigma_x^2 + sum_b s_b^2 / sigma_b^2`` and the Gauss-Newton
  posterior covariance ``H^-1`` there;
* M-step (here): ``mu_b = mean s_b`` (moved into ``l_b``), ``sigma_b^2 = mean((s_b - mu_b)^2 +
  H^-1_bb)``, ``sigma_x^2 = (sum |pi - x|^2 + sigma_x^2 sum d_tau) / N`` with ``d_tau`` the
  frame's effective number of parameters.

Rigid bones come out with ``sigma_b -> 0`` (floored at ``sd_floor``); a spine or ear segment
stretches as much as the data say. The ACM's rat and mouse models keep rigid bones (their
``stretch_sd`` is 0). The stop rule is unit-free: the largest change of ``sigma_b`` (relative,
or in units of 1 % stretch below 1 %), ``log sigma_x`` and ``mu_b`` below ``tol``.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from . import _native
from .camera import CameraRig
from .labels import labels_in_skeleton_order
from .learning import _bound_arrays, _clip_to_bounds, _pose_bounds, _to_state, learn_skeleton
from .skeleton import Skeleton
from .state import Normalization

__all__ = ["StretchFit", "add_stretch", "learn_stretch", "project_stretched"]


@dataclass
class StretchFit:
    """Result of :func:`learn_stretch`.

    Attributes
    ----------
    skeleton : Skeleton
        With the learned mean lengths and ``stretch_sd`` (0 for bones kept rigid).
    t : numpy.ndarray, shape (F, 3)
        Root translation per frame (world units).
    r : numpy.ndarray, shape (F, n_bones, 3)
        Rodrigues vectors per frame (rad).
    lengths : numpy.ndarray, shape (F, n_bones)
        Each frame's bone lengths ``l_b exp(s_b)`` (world units).
    stretch, stretch_var : numpy.ndarray, shape (F, n_bones)
        MAP log-stretch and its posterior variance (0 for rigid bones).
    noise_px : float
        Learned label noise ``sigma_x`` (px per coordinate).
    iterations : int
    converged : bool
    history : list of dict
        Per EM iteration: ``noise_px``, ``stretch_sd`` (elastic bones), ``change``.
    """

    skeleton: Skeleton
    t: np.ndarray
    r: np.ndarray
    lengths: np.ndarray
    stretch: np.ndarray
    stretch_var: np.ndarray
    noise_px: float
    iterations: int
    converged: bool
    history: list = field(default_factory=list)

    def length_sd(self) -> np.ndarray:
        """``(n_bones,)`` the learned SD of each bone's length in world units
        (``l_b sqrt(exp(sigma_b^2) - 1) exp(sigma_b^2 / 2)``, the log-normal SD)."""
        s2 = self.skeleton.stretch_sd**2
        return self.skeleton.bone_lengths * np.sqrt(np.expm1(s2)) * np.exp(0.5 * s2)

    def summary(self) -> str:
        sk = self.skeleton
        lines = [
            f"elastic segments: {len(sk.elastic_bones)} of {sk.n_bones} bones, EM "
            f"{self.iterations} iterations ({'converged' if self.converged else 'NOT converged'}), "
            f"label noise {self.noise_px:.3g} px",
            f"{'bone':<24} {'length':>9} {'SD':>9} {'SD %':>6}",
        ]
        sd = self.length_sd()
        for b in range(sk.n_bones):
            lines.append(
                f"{sk.bone_names[b]:<24} {sk.bone_lengths[b]:9.4g} {sd[b]:9.3g} "
                f"{100 * sk.stretch_sd[b]:6.1f}"
            )
        return "\n".join(lines)


def _bone_indices(skeleton: Skeleton, bones) -> np.ndarray:
    if bones is None or (isinstance(bones, str) and bones == "all"):
        return np.arange(skeleton.n_bones)
    if isinstance(bones, str):
        bones = [bones]
    idx = [b if isinstance(b, int | np.integer) else skeleton.bone_index(b) for b in bones]
    out = np.array(sorted(set(int(i) for i in idx)), np.int64)
    if out.size and (out.min() < 0 or out.max() >= skeleton.n_bones):
        raise ValueError(f"bone indices must be in 0..{skeleton.n_bones - 1}, got {list(bones)}")
    return out


def project_stretched(
    rig: CameraRig, skeleton: Skeleton, t: np.ndarray, r: np.ndarray, lengths: np.ndarray
) -> np.ndarray:
    """Markers of poses with per-frame bone lengths, projected: ``(n_cams, F, M, 2)`` px.

    ``t`` (F, 3), ``r`` (F, n_bones, 3), ``lengths`` (F, n_bones) in world units.
    """
    markers = np.stack(
        [skeleton.forward(t[f], r[f], bone_lengths=lengths[f])[1] for f in range(len(t))]
    )
    return rig.project(markers)


def learn_stretch(
    rig: CameraRig,
    skeleton: Skeleton,
    labels: np.ndarray,
    *,
    bones: str | Sequence[str | int] | None = "all",
    init: tuple[np.ndarray, np.ndarray] | None = None,
    initial_sd: float = 0.05,
    learn_sd: bool = True,
    learn_lengths: bool = True,
    max_iter: int = 500,
    tol: float = 1e-3,
    sd_floor: float = 1e-4,
    noise_floor_px: float = 1e-3,
    normalization: Normalization | None = None,
) -> StretchFit:
    """Learn elastic segments by EM from labelled frames (module docs for the model).

    Parameters
    ----------
    rig : CameraRig
    skeleton : Skeleton
        The (rigidly learned) skeleton; its lengths are the starting means.
    labels : array_like, shape (n_cams, F, M, 2)
        Labels in pixels, in the skeleton's marker order, NaN where unlabelled.
    bones : "all", sequence of bone names / indices, or None
        The elastic bones (default every bone; ``None`` = "all").
    init : (t (F, 3), r (F, n_bones, 3)), optional
        Starting poses; default the rigid per-frame fit (:func:`acm_rs.learning.learn_skeleton`
        with lengths and offsets fixed).
    initial_sd : float
        Starting ``sigma_b`` where the skeleton has none (log-stretch SD).
    learn_sd, learn_lengths : bool
        Update ``sigma_b`` / the mean lengths in the M-step (False: keep the skeleton's; e.g.
        to fit held-out data with a learned model).
    max_iter, tol : int, float
        EM stops when every change is below ``tol`` (module docs) or after ``max_iter``
        iterations (then a warning says so).
    sd_floor, noise_floor_px : float
        Lower bounds of ``sigma_b`` and ``sigma_x`` (px): data that fit exactly (e.g. 2D labels
        that are reprojections of 3D labels) would otherwise drive them to 0.

    Returns
    -------
    StretchFit
    """
    lab = labels_in_skeleton_order(labels, skeleton, rig, None)
    n_cams, n_frames = lab.shape[:2]
    if n_frames == 0:
        raise ValueError("labels contain no frames")
    elastic = _bone_indices(skeleton, bones)
    if elastic.size == 0:
        raise ValueError("no elastic bones: give at least one bone, or use learn_skeleton")
    if not (initial_sd > 0 and sd_floor > 0 and noise_floor_px > 0 and tol > 0):
        raise ValueError("initial_sd, sd_floor, noise_floor_px and tol must be > 0")
    norm = normalization or Normalization.for_rig(
        np.array([c.center for c in rig]), skeleton.units, [c.size for c in rig]
    )
    if init is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the rigid fit's chatter; the result says enough
            rigid = learn_skeleton(
                rig, skeleton, lab, progress=False, lm_iter=0, rounds=0, symmetric=False,
                scale_to_labels=False, length_prior_sd=None, normalization=norm,
            )  # fmt: skip
        t0, r0 = rigid.t, rigid.r
    else:
        t0, r0 = np.asarray(init[0], float), np.asarray(init[1], float)
        if t0.shape != (n_frames, 3) or r0.shape != (n_frames, skeleton.n_bones, 3):
            raise ValueError(
                f"init must be t ({n_frames}, 3) and r ({n_frames}, {skeleton.n_bones}, 3), "
                f"got {t0.shape} and {r0.shape}"
            )
    bounds = _pose_bounds(skeleton, norm)
    lo_z, hi_z = _bound_arrays(bounds)
    z = np.stack([_clip_to_bounds(v, bounds) for v in _to_state(t0, r0, skeleton, norm)])
    lab_fcm = np.ascontiguousarray(lab.transpose(1, 0, 2, 3))
    lim = skeleton.joint_limits
    lower, upper = np.ascontiguousarray(lim[..., 0]), np.ascontiguousarray(lim[..., 1])
    empty = np.zeros((0, 2), np.int64)
    params = rig.get_params()
    lengths = skeleton.bone_lengths.copy()
    offsets = np.ascontiguousarray(skeleton.marker_offsets)

    def problem(lengths: np.ndarray) -> _native.NativeLearning:
        return _native.NativeLearning(
            skeleton._native, params, lab_fcm, lower, upper, norm._tuple(), empty, empty,
            norm.translation / 50.0, np.ascontiguousarray(lengths), offsets,
        )  # fmt: skip

    stored = skeleton.stretch_sd[elastic]
    sd = np.where(stored > 0, stored, initial_sd).astype(float)
    sd = np.maximum(sd, sd_floor)
    # starting noise: the rigid fit's residual, per coordinate
    px0 = skeleton.project(rig, t0, r0)
    res0 = (px0 - lab)[np.isfinite(lab).all(-1)]
    noise = max(float(np.sqrt(np.mean(res0**2))) if res0.size else 1.0, noise_floor_px)
    s = np.zeros((n_frames, len(elastic)))
    x = np.ascontiguousarray(z.ravel())
    prob = problem(lengths)
    history: list[dict] = []
    converged = False
    iterations = 0
    var = np.zeros_like(s)
    for it in range(1, int(max_iter) + 1):
        iterations = it
        x, s, var, sq, dof, n_px, _ = prob.fit_poses_elastic(
            x, lo_z, hi_z, elastic, sd, np.ascontiguousarray(s), noise, 50
        )
        n_res = float(np.sum(n_px))
        noise_new = max(float(np.sqrt((sq.sum() + noise**2 * dof.sum()) / max(n_res, 1.0))),
                        noise_floor_px)  # fmt: skip
        mu = s.mean(axis=0) if learn_lengths else np.zeros(len(elastic))
        sd_new = sd
        if learn_sd:
            sd_new = np.maximum(np.sqrt(np.mean((s - mu) ** 2 + var, axis=0)), sd_floor)
        # relative change of a real stretch, absolute (in 1 % stretch) near rigid: EM creeps
        # towards 0 for rigid bones, and those last 1e-5 do not matter
        change = max(
            float(np.max(np.abs(sd_new - sd) / np.maximum(sd, 0.01), initial=0.0)),
            abs(np.log(noise_new / noise)),
            float(np.max(np.abs(mu), initial=0.0)),
        )
        history.append({"noise_px": noise_new, "stretch_sd": sd_new.copy(), "change": change})
        sd, noise = sd_new, noise_new
        if learn_lengths and np.any(mu != 0):
            lengths[elastic] *= np.exp(mu)
            s = s - mu
            prob = problem(lengths)
        if change < tol:
            converged = True
            break
    if not converged:
        warnings.warn(
            f"elastic-segment EM stopped at max_iter={max_iter} without converging (last "
            f"change {history[-1]['change']:.3g} > tol {tol}); raise max_iter",
            RuntimeWarning,
            stacklevel=2,
        )
    full_sd = np.zeros(skeleton.n_bones)
    full_sd[elastic] = sd
    learned = skeleton.with_parameters(lengths).with_stretch(full_sd)
    pose = prob.residuals(x)[3]  # (F, n_pose): the state map's decoding
    stretch = np.zeros((n_frames, skeleton.n_bones))
    stretch_var = np.zeros((n_frames, skeleton.n_bones))
    stretch[:, elastic], stretch_var[:, elastic] = s, var
    return StretchFit(
        skeleton=learned,
        t=pose[:, :3],
        r=pose[:, 3:].reshape(n_frames, skeleton.n_bones, 3),
        lengths=lengths[None] * np.exp(stretch),
        stretch=stretch,
        stretch_var=stretch_var,
        noise_px=noise,
        iterations=iterations,
        converged=converged,
        history=history,
    )


def add_stretch(
    learned, bones: str | Sequence[str | int] | None = None, **kwargs
) -> tuple[object, StretchFit]:
    """Elastic segments on top of a rigid :func:`acm_rs.learning.learn_skeleton` result.

    Parameters
    ----------
    learned : acm_rs.learning.LearnedSkeleton
        The rigid result (its labels, poses and skeleton are the start).
    bones : "all", sequence of names / indices, or None
        Elastic bones; ``None``: the skeleton's own elastic bones, or every bone if it has none.
    **kwargs
        Passed to :func:`learn_stretch`.

    Returns
    -------
    (LearnedSkeleton, StretchFit)
        A copy of ``learned`` whose skeleton carries the learned means and ``stretch_sd``
        (bones whose SD stayed within 10x the floor are made rigid, SD 0), whose projections
        and errors use each frame's lengths, and whose ``info["elastic"]`` has the EM outcome.
    """
    import dataclasses

    sk = learned.skeleton
    if bones is None:
        bones = sk.elastic_bones if sk.stretch_sd.any() else "all"
    fit = learn_stretch(
        learned.rig, sk, learned.labels, bones=bones, init=(learned.t, learned.r), **kwargs
    )
    floor = kwargs.get("sd_floor", 1e-4)
    sd = np.where(fit.skeleton.stretch_sd > 10 * floor, fit.skeleton.stretch_sd, 0.0)
    fit.skeleton = fit.skeleton.with_stretch(sd)
    projected = project_stretched(learned.rig, fit.skeleton, fit.t, fit.r, fit.lengths)
    info = dict(learned.info)
    info["elastic"] = {
        "iterations": fit.iterations, "converged": fit.converged, "noise_px": fit.noise_px,
        "stretch_sd": {sk.bone_names[b]: float(sd[b]) for b in range(sk.n_bones)},
        "rigid": [sk.bone_names[b] for b in _bone_indices(sk, bones) if sd[b] == 0],
    }  # fmt: skip
    out = dataclasses.replace(
        learned, skeleton=fit.skeleton, t=fit.t, r=fit.r, projected=projected,
        errors=np.linalg.norm(projected - learned.labels, axis=-1), info=info,
    )  # fmt: skip
    return out, fit
