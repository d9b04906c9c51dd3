"""Probabilistic pose estimation (ACM supp. sec. 4): EM with the unscented RTS smoother.

The numerical work (Alg. 5-13) runs in Rust (``acm_rs._native.NativeTracker``) with the GIL
released; this module prepares the measurements, initialises ``mu_0`` by the single-frame fit
of sec. 4.7 and packages the posterior as a :class:`PoseResult`.
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from collections.abc import Sequence

import numpy as np

from .. import _native
from ..camera import CameraRig
from ..labels import _warn_dropped, labels_in_skeleton_order, mask_by_likelihood
from ..learning import _pose_bounds, _to_state, check_scale, check_units, initial_poses
from ..skeleton import Skeleton
from ..state import Normalization, StateMap
from .ambiguity import second_solutions as search_second_solutions
from .ambiguity import widen
from .misfit import MODES as MISFIT_MODES
from .misfit import apply_misfit
from .result import PoseResult

#: Default innovation gate: probability mass of the chi-square distribution with 2 degrees of
#: freedom inside the gate (an image point is rejected for the frame when its squared
#: Mahalanobis innovation exceeds ``-2 ln(1 - p)``; 0.999 -> 13.8).
DEFAULT_GATE = 0.999

#: Default EM stop: the marginal log-likelihood gains less than this many nats per used
#: measurement entry (on the synthetic rat: ~17 iterations, joints 0.49 mm vs 0.67 mm after
#: the 6 that Alg. 13's tol = 0.05 allows; docs/tracking.md).
DEFAULT_LL_TOL = 1e-3

#: Default start of ``V0`` and ``V_z`` (diagonal, normalised state units): measured on real
#: and synthetic rat motion (docs/tracking.md, "The start"; the paper's 0.001 settles at worse
#: optima on real motion, 1e-4 costs the synthetic rat's tail and coverage).
DEFAULT_NOISE = 2e-4

#: EM stops when this many E-steps in a row stay below its best marginal log-likelihood and
#: returns the best parameters (``info["stalled"]``; the Rust core's ``DEFAULT_PATIENCE``,
#: passed explicitly; docs/tracking.md, "What is guaranteed").
EM_PATIENCE = 10

#: Growth factor of over-relaxed EM (Salakhutdinov & Roweis 2003; the Rust core's
#: ``DEFAULT_OVERRELAX``): on real rat motion it reaches plain EM's log-likelihood in
#: 13-17 E-steps instead of 20-25 (docs/tracking.md, "Over-relaxed EM").
DEFAULT_OVERRELAX = _native.DEFAULT_OVERRELAX
#: Largest step factor of over-relaxed EM (the Rust core's ``MAX_OVERRELAX``).
MAX_OVERRELAX = _native.MAX_OVERRELAX

#: Motion models and the order of their state (1: position, the paper's random walk;
#: 2: position and velocity).
MOTION_ORDER = {"random_walk": 1, "velocity": 2, "auto": 2}
#: Default motion model (chosen by measurement, docs/tracking.md).
DEFAULT_MOTION = "auto"

#: Rounds of the elastic segments' mean lengths between EM runs (see track_in_memory).
MAX_LENGTH_ROUNDS = 5

#: Bytes per frame the in-memory EM keeps, in units of ``(order · n_state)²`` doubles
#: (filtered, predicted and smoothed moments and the cross-covariances of Alg. 9; measured
#: peak RSS of the rat, 50 entries: 70 KB/frame for the random walk, 206 KB/frame for the
#: velocity state).
MOMENT_COPIES = 3.5
#: Upper bound of the default memory budget of the in-memory EM (:func:`acm_rs.track`).
MEMORY_LIMIT_CAP = 4 * 2**30


def in_memory_bytes(n_frames: int, n_state: int, motion: str) -> int:
    """Bytes :func:`track_in_memory`'s EM needs for ``n_frames`` frames of a state of
    ``n_state`` entries (``motion`` "auto" and "velocity" double the state)."""
    k = MOTION_ORDER[motion] * n_state
    return int(n_frames * MOMENT_COPIES * k * k * 8)


def default_memory_limit() -> int:
    """:func:`acm_rs.track`'s budget for the in-memory EM: half of the memory available now, at most
    ``MEMORY_LIMIT_CAP`` (4 GiB; where the system does not say, the cap)."""
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return MEMORY_LIMIT_CAP
    return int(min(MEMORY_LIMIT_CAP, avail // 2))


def default_normalization(rig: CameraRig, skeleton: Skeleton) -> Normalization:
    """Sec. 3.3 constants for a rig and skeleton (:meth:`Normalization.for_rig`).

    ``c_1, c_2`` are half the largest image size in the rig (640, 512 for 1280x1024 sensors,
    the paper's value when sizes are unknown); ``c_t`` follows the rig's size (5/6 of the
    median camera distance from the rig's centre: 50 cm for a rig whose cameras stand 60 cm
    from it), so results do not depend on the world unit.
    """
    centres = np.array([cam.center for cam in rig])
    return Normalization.for_rig(centres, skeleton.units, [cam.size for cam in rig])


def _norm_dict(norm: Normalization) -> dict:
    return {
        "translation": norm.translation,
        "rotation": norm.rotation,
        "pixel": [float(norm.pixel[0]), float(norm.pixel[1])],
    }


def gate_threshold(p: float | None) -> float | None:
    """Chi-square (2 dof) quantile ``-2 ln(1 - p)`` for a gate probability ``p`` (None: off)."""
    if p is None:
        return None
    if not 0.0 < p < 1.0:
        raise ValueError(f"gate must be a probability in (0, 1) or None, got {p}")
    return -2.0 * math.log1p(-p)


def _skeleton_order(
    rig: CameraRig,
    skeleton: Skeleton,
    detections: np.ndarray,
    likelihood: np.ndarray | None,
    pcutoff: float,
    marker_names: Sequence[str] | None,
    warn: bool = True,
) -> np.ndarray:
    """Detections ``(C, F, M, 2)`` in pixels as a new float64 array in skeleton marker order,
    NaN where missing, partial or below ``pcutoff``."""
    # (mask_by_likelihood returns a copy: the reordering may then work in place)
    masked = mask_by_likelihood(detections, likelihood, pcutoff, warn=warn)
    det = labels_in_skeleton_order(masked, skeleton, rig, marker_names)
    det[~np.isfinite(det).all(axis=-1)] = np.nan
    return det


def _measurements(
    rig: CameraRig,
    skeleton: Skeleton,
    detections: np.ndarray,
    likelihood: np.ndarray | None,
    pcutoff: float,
    marker_names: Sequence[str] | None,
    block: int | None = None,
) -> np.ndarray:
    """:func:`_skeleton_order` of a whole recording, with an error if nothing is usable;
    ``block``: converted that many frames at a time into the result (a long memory-mapped
    recording then needs no whole-recording float64 temporaries; the warning about points a
    cutoff drops still judges the whole recording)."""
    T = np.shape(detections)[1]
    if block is None or T <= block:
        det = _skeleton_order(rig, skeleton, detections, likelihood, pcutoff, marker_names)
    else:
        det = np.empty((len(rig), T, skeleton.n_markers, 2))
        present, drop = [], []
        for a in range(0, T, block):
            b = min(T, a + block)
            raw = detections[:, a:b]
            lik = None if likelihood is None else likelihood[:, a:b]
            det[:, a:b] = _skeleton_order(rig, skeleton, raw, lik, pcutoff, marker_names, False)
            if lik is not None:
                present.append(np.isfinite(np.asarray(raw)).all(axis=-1))
                drop.append(~(np.asarray(lik) >= pcutoff))
        if present:
            _warn_dropped(np.concatenate(present, axis=1), np.concatenate(drop, axis=1), pcutoff)
    if not np.isfinite(det).any():
        raise ValueError(
            "no detection is usable: every entry is NaN"
            + (f" or has likelihood < pcutoff = {pcutoff}" if likelihood is not None else "")
        )
    return det


def _first_pose(
    rig: CameraRig, skeleton: Skeleton, det: np.ndarray, norm: Normalization
) -> tuple[int, np.ndarray, np.ndarray]:
    """Sec. 4.7: fit the first frame (the first with >= 3 points seen by >= 2 cameras).

    Eq. 9 for that frame with lengths and offsets fixed, minimised by the box-constrained
    Levenberg-Marquardt of the Rust core from a triangulation + Kabsch start (the same
    minimiser as the paper's L-BFGS-B, ~100x faster for one frame).
    """
    seen = (np.isfinite(det[..., 0]).sum(axis=0) >= 2).sum(axis=1)  # (T,)
    ok = np.flatnonzero(seen >= 3)
    if ok.size == 0:
        raise ValueError("no frame has 3 markers detected in at least 2 cameras")
    f0 = int(ok[0])
    t0, r0 = _deterministic(rig, skeleton, det[:, f0 : f0 + 1], norm)
    return f0, t0[0], r0[0]


def _frames_rms(rig: CameraRig, skeleton: Skeleton, det: np.ndarray, norm: Normalization) -> float:
    """Median over frames of the median reprojection error (px) of per-frame fits (medians:
    a few confident outliers must not make a correct rig look wrong)."""
    t, r = _deterministic(rig, skeleton, det, norm)
    err = np.linalg.norm(skeleton.project(rig, t, r) - det, axis=-1)
    with np.errstate(invalid="ignore"):
        per_frame = np.nanmedian(np.where(np.isfinite(err), err, np.nan), axis=(0, 2))
    return float(np.nanmedian(per_frame))


def check_camera_order(
    rig: CameraRig,
    skeleton: Skeleton,
    det: np.ndarray,
    norm: Normalization,
    n_frames: int = 5,
    plausible_px: float = 10.0,
) -> float:
    """Fit the ``n_frames`` best-detected frames; if their median reprojection error is
    implausible for detections (> ``plausible_px``), try every other assignment of the
    detection files to the cameras (up to 5 cameras) and refuse when one fits far better.

    Returns the median per-frame median error (px) in the given order.

    Raises
    ------
    ValueError
        When another camera order fits at least 3x better: the files are in the wrong order.

    Warns
    -----
    UserWarning
        When no order fits plausibly (wrong calibration, model or units).
    """
    import itertools
    import warnings

    seen = (np.isfinite(det[..., 0]).sum(axis=0) >= 2).sum(axis=1)
    frames = np.argsort(-seen, kind="stable")[:n_frames]
    frames = np.sort(frames[seen[frames] >= 3])
    if frames.size == 0:
        return float("nan")
    sub = det[:, frames]
    rms = _frames_rms(rig, skeleton, sub, norm)
    if not rms > plausible_px:
        return rms
    n_cams = len(rig)
    best, best_perm = rms, None
    if n_cams <= 5:
        for perm in itertools.permutations(range(n_cams)):
            if perm == tuple(range(n_cams)):
                continue
            e = _frames_rms(rig, skeleton, sub[list(perm)], norm)
            if e < best:
                best, best_perm = e, perm
    names = [c.name or str(i) for i, c in enumerate(rig)]
    if best_perm is not None and best < rms / 3.0:
        order = ", ".join(f"{names[i]} <- file {k + 1}" for i, k in enumerate(best_perm))
        raise ValueError(
            f"the detections fit the calibration with {rms:.1f} px median reprojection error in "
            f"the given camera order, but with {best:.1f} px when assigned as {order}: the "
            "detection files are not in the calibration's camera order. Give one file per "
            f"camera in the order {names} (or name the cameras so they can be matched)."
        )
    warnings.warn(
        f"the best-detected frames fit with {rms:.1f} px median reprojection error, implausible "
        "for DeepLabCut detections (typically 2-5 px), and no other camera order fits better: "
        "check the calibration (units, frame), the skeleton (another animal or model) and "
        "the detection files",
        stacklevel=3,
    )
    return rms


def _deterministic(
    rig: CameraRig, skeleton: Skeleton, det: np.ndarray, norm: Normalization, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame fits of eq. 9 (lengths and offsets fixed), each frame independently."""
    from ..learning import _fit_frames

    lab_fcm = np.ascontiguousarray(det.transpose(1, 0, 2, 3))
    t_i, r_i = initial_poses(rig, skeleton, det, norm)
    bounds = _pose_bounds(skeleton, norm)
    lo_z = np.array([-np.inf if b[0] is None else b[0] for b in bounds])
    hi_z = np.array([np.inf if b[1] is None else b[1] for b in bounds])
    z0 = np.clip(_to_state(t_i, r_i, skeleton, norm), lo_z, hi_z)
    lim = skeleton.joint_limits
    lower, upper = np.ascontiguousarray(lim[..., 0]), np.ascontiguousarray(lim[..., 1])
    params = rig.get_params()
    length_scale = norm.translation / 50.0
    z, _, _ = _fit_frames(
        skeleton, params, lab_fcm, lower, upper, norm, length_scale, z0, lo_z, hi_z,
        skeleton.bone_lengths, skeleton.marker_offsets, seed,
    )  # fmt: skip
    empty = np.zeros((0, 2), np.int64)
    problem = _native.NativeLearning(
        skeleton._native, params, lab_fcm, lower, upper, norm._tuple(), empty, empty,
        length_scale, skeleton.bone_lengths, skeleton.marker_offsets,
    )  # fmt: skip
    _, _, _, poses = problem.residuals(np.ascontiguousarray(z.ravel()))
    return poses[:, :3], poses[:, 3:].reshape(len(poses), skeleton.n_bones, 3)


def warn_rigid_lengths(skeleton: Skeleton, where: str) -> None:
    """One warning when ``where`` keeps the skeleton's elastic segments at their mean
    lengths (only the in-memory :func:`track_in_memory` tracks their stretch)."""
    n = int(np.count_nonzero(skeleton.stretch_sd))
    if n:
        warnings.warn(
            f"{where} keeps every bone at its mean length: the skeleton's {n} elastic "
            "segments are tracked by acm_rs.track in memory only",
            UserWarning,
            stacklevel=3,
        )


def _in_rig_units(
    rig: CameraRig, skeleton: Skeleton, norm: Normalization
) -> tuple[CameraRig, Skeleton, Normalization, float]:
    """The rig and skeleton with lengths in units of ``c_t`` (``norm.translation``), the
    normalisation that goes with them (``c_t = 1``) and ``c_t``.

    Every fit and filter of :func:`track` runs on these copies, so the same detections with a
    rig and skeleton in cm, mm or board squares give the same numbers to rounding (1e-10 of
    the median error on real rat motion, ``benches/README.md``): the iterative steps (the
    first pose's fit, EM's stops, the gate) see identical inputs instead of inputs that
    differ in their last bits and paths that drift apart."""
    import dataclasses

    c_t = float(norm.translation)
    f = 1.0 / c_t
    rig_u = rig.scaled(f, units="")
    sk_u = skeleton.scaled(f)
    return rig_u, sk_u, dataclasses.replace(norm, translation=1.0), c_t


def initial_vx(
    rig: CameraRig, skeleton: Skeleton, det: np.ndarray, norm: Normalization, n_frames: int = 10
) -> np.ndarray:
    """Start of ``diag(V_x)`` from the data: the squared robust scale of the reprojection
    residuals of per-frame fits (eq. 9, lengths and offsets fixed) of the ``n_frames``
    best-detected frames, per image axis, in normalised pixels (eq. 11), corrected for the
    degrees of freedom the fits used. Returns ``(n_cams * M * 2,)`` in the layout of one
    frame's measurements (camera, marker, axis).

    The paper starts ``V_x`` at 0.001 (sec. 4.7): 20 px SD for 1280x1024 images, ~10x the
    noise of DeepLabCut detections. From such a start the innovation gate admits the
    confident outliers, they inflate ``V_x`` and ``V_z``, and EM settles at a worse optimum
    (real rat motion: log-likelihood 270,000 vs 277,000-279,000 from starts near the data's
    noise; docs/tracking.md)."""
    n_cams, _, n_markers, _ = det.shape
    seen = (np.isfinite(det[..., 0]).sum(axis=0) >= 2).sum(axis=1)
    frames = np.argsort(-seen, kind="stable")[:n_frames]
    frames = np.sort(frames[seen[frames] >= 3])
    if frames.size == 0:
        raise ValueError("no frame has 3 markers detected in at least 2 cameras")
    sub = det[:, frames].copy()
    pixel = np.asarray(norm.pixel, dtype=float)
    n_par = frames.size * (3 + 3 * skeleton.n_bones)
    out = np.full(2, np.nan)
    for _ in range(2):
        # least-squares fits, then again without the points they leave > 5 SD off
        # (confident outliers pull a least-squares fit and with it the inliers' residuals)
        t, r = _deterministic(rig, skeleton, sub, norm)
        res = (skeleton.project(rig, t, r) - sub) / pixel
        ok = np.isfinite(res).all(axis=-1)
        n_obs = 2 * int(ok.sum())
        dof = n_obs / max(n_obs - n_par, 0.25 * n_obs)
        for a in range(2):
            e = np.abs(res[..., a][ok])
            # 1.4826 x the median absolute residual: the SD of Gaussian noise
            out[a] = (1.4826 * float(np.median(e))) ** 2 * dof if e.size else np.nan
        if not np.isfinite(out).all():
            break
        far = ok & (np.abs(res) > 5.0 * np.sqrt(out)).any(axis=-1)
        if not far.any():
            break
        sub[far] = np.nan
    if not np.isfinite(out).all() or not (out > 0).all():
        raise ValueError("the reprojection residuals of the best-detected frames are not usable")
    return np.tile(out, n_cams * n_markers)


def _em_start(
    rig_u: CameraRig, sk_u: Skeleton, det: np.ndarray, norm_u: Normalization, joint_limits: bool
) -> tuple[int, np.ndarray, np.ndarray]:
    """EM's start for the rig and skeleton of :func:`_in_rig_units`: ``(first frame, mu0,
    diag V_x)``, ``mu0`` from the first well-detected frame's fit (sec. 4.7), ``V_x`` from
    the detections' noise (:func:`initial_vx`). Shared by :func:`track` and the bundles of
    ``acm-smooth``, which must start alike."""
    f0, t0, r0 = _first_pose(rig_u, sk_u, det, norm_u)
    mu0 = StateMap(sk_u, norm_u, joint_limits).start_state(t0, r0)
    return f0, mu0, initial_vx(rig_u, sk_u, det, norm_u)


def _velocity_init(params: dict, means: np.ndarray, memoryless=()) -> tuple:
    """Start of EM for the position-velocity state from the random walk's EM result:
    ``μ0 = (μ̂_0, μ̂_1 − μ̂_0)``, ``V0 = diag(V0, 2 V0 + Q_v)``, ``V_z = diag(V_z / 10, Q_v)``
    with ``Q_v`` the covariance of the second differences of the smoothed means ``(T+1, n)``,
    and the learned ``V_x``. Memoryless entries (elastic segments' log-stretch) keep their
    learned variance in ``V_z`` (it is their variance, not a step's)."""
    m = np.asarray(means)
    n = m.shape[1]
    d2 = np.diff(m, 2, axis=0) if len(m) > 2 else np.zeros((1, n))
    qv = d2.T @ d2 / len(d2) + 1e-12 * np.eye(n)
    z = np.zeros((n, n))
    v0, vz = params["V0"], params["Vz"]
    mu0 = np.concatenate([params["mu0"], m[1] - m[0] if len(m) > 1 else np.zeros(n)])
    v0 = np.block([[v0, z], [z, 2 * v0 + qv]])
    keep = np.asarray(memoryless, np.int64)
    vz_pos = 0.1 * vz
    vz_pos[np.ix_(keep, keep)] = vz[np.ix_(keep, keep)]
    vz = np.block([[vz_pos, z], [z, qv]])
    return mu0, v0, vz, params["Vx_diag"]


def _velocity_worse(a: dict, b: dict) -> str:
    """Why the position-velocity fit ``b`` is worse than the random walk's ``a`` ('' if it is
    not): fewer detections used (the filter lost the animal) or a lower marginal
    log-likelihood of the detections; ``a`` and ``b`` are E-step statistics."""
    if b["used"] < 0.98 * a["used"]:
        return f"it used {b['used']} detection entries against {a['used']}"
    if b["log_likelihood"] < a["log_likelihood"]:
        return f"log-likelihood {b['log_likelihood']:.6g} against {a['log_likelihood']:.6g}"
    return ""


def _on_terminal(progress: bool | None) -> bool:
    """``progress`` with None meaning "when stderr is a terminal"."""
    if progress is None:
        return bool(getattr(sys.stderr, "isatty", lambda: False)())
    return bool(progress)


class _Printer:
    """One line per EM iteration on stderr (or nothing)."""

    def __init__(self, enabled: bool | None) -> None:
        self.enabled = _on_terminal(enabled)

    def __call__(self, iteration: int, delta: float, seconds: float, stats: dict) -> bool:
        if self.enabled:
            gated = f", {stats['gated'] // 2} points gated" if stats.get("gated") else ""
            ll = stats.get("log_likelihood", float("nan"))
            print(
                f"EM iteration {iteration:3d}: log-likelihood {ll:.6g}, delta {delta:.4g} "
                f"({seconds:.2f} s{gated})",
                file=sys.stderr,
                flush=True,
            )
        return True


def _empty_stretches(det: np.ndarray, min_len: int = 10) -> list[tuple[int, int]]:
    """``[(first, last)]`` frame ranges of at least ``min_len`` frames without any detection,
    with a warning: their poses are the motion model's bridge between the frames around them,
    and its intervals may be too narrow there (issue 12: 79 % coverage in a 40-frame gap
    with the velocity model, 59 % with the random walk)."""
    import warnings

    empty = ~np.isfinite(det[..., 0]).any(axis=(0, 2))
    out, start = [], None
    for t, e in enumerate(np.append(empty, False)):
        if e and start is None:
            start = t
        elif not e and start is not None:
            if t - start >= min_len:
                out.append((start, t - 1))
            start = None
    if out:
        where = ", ".join(f"{a}-{b}" for a, b in out[:5])
        warnings.warn(
            f"{len(out)} stretch(es) of >= {min_len} frames without any detection (frames "
            f"{where}): their poses are bridged by the motion model, not measured, and their "
            "95 % intervals may be too narrow (79 % coverage inside a synthetic 40-frame gap, "
            "docs/tracking.md); result.info['empty_stretches'] lists them",
            stacklevel=4,
        )
    return out


def _warn_implausible_fit(result: PoseResult, fit_px: float, factor: float = 3.0) -> None:
    """Warn when the tracked poses reproject far worse than per-frame fits of the same
    detections did (median error > ``factor`` x theirs and > 5 px): the temporal model
    over-smooths or diverged (e.g. EM fed on a long stretch without detections)."""
    import warnings

    err = result.reprojection_error()
    ok = np.isfinite(err)
    if not ok.any() or not np.isfinite(fit_px):
        return
    med = float(np.median(err[ok]))
    result.info["median_reprojection_px"] = med
    if med > max(5.0, factor * fit_px):
        warnings.warn(
            f"the tracked poses reproject with a median error of {med:.1f} px, {med / fit_px:.1f}"
            f" x that of per-frame fits of the same detections ({fit_px:.1f} px): the "
            "temporal model does not fit these data (check result.em_history and the frames "
            "without detections; method='deterministic' gives the per-frame fits)",
            stacklevel=4,
        )


def warn_second_solutions(result: PoseResult, frames: int) -> None:
    """Search ``frames`` frames for second poses; record and name the ambiguous joints, and
    widen their SDs to reach the second poses (:func:`~acm_rs.tracking.ambiguity.widen`)."""
    t0 = time.perf_counter()
    found = search_second_solutions(result, frames=frames)
    rows = found.ambiguous()
    added = widen(result, found)
    result.info["second_solutions"] = {
        "frames": found.frames.tolist(),
        "chi2": found.chi2,
        "joints": {
            name: {"fraction": frac, "distance": dist, "widened_sd": float(added[j])}
            for name, frac, dist in rows
            for j in [result.joint_names.index(name)]
        },
        "seconds": time.perf_counter() - t0,
    }
    if rows:
        warnings.warn(
            f"{found.summary()}; their SDs (result.joints_std) are widened to reach the "
            f"second poses; searched frames {found.frames.tolist()} (info['second_solutions']; "
            "acm_rs.second_solutions(result, frames=N) searches N, "
            "acm_rs.tracking.ambiguity.widen(result, found) applies it)",
            stacklevel=3,
        )


def check_overrelax(overrelax: float | None) -> None:
    """Refuse an over-relaxation growth factor that is not a finite number > 1 (or None)."""
    if overrelax is not None and not (math.isfinite(overrelax) and overrelax > 1):
        raise ValueError(f"overrelax must be a growth factor > 1 or None, got {overrelax}")


def _warn_em(result: PoseResult, max_iter: int, ll_tol: float) -> None:
    """Say when EM ended at ``max_iter`` without converging, when ``EM_PATIENCE`` iterations
    in a row stayed below its best log-likelihood, and when its marginal
    log-likelihood fell well below its best iteration (the unscented E-step and the outlier
    gate do not guarantee a monotone rise; ``docs/tracking.md``). The parameters returned are
    those of the highest log-likelihood evaluated (``info["returned_iteration"]``)."""
    import warnings

    info = result.info
    # (over-relaxed steps that scored lower and were replaced are not EM's path)
    hist = [
        h
        for h in result.em_history
        if h.get("motion", info["motion"]) == info["motion"] and not h.get("rejected")
    ]
    if not hist or info["interrupted"]:
        return
    name = info["motion"].replace("_", " ")
    ll = np.array([h["log_likelihood"] for h in hist], dtype=float)
    best = int(np.nanargmax(ll)) if np.isfinite(ll).any() else len(ll) - 1
    info["best_iteration"] = best + 1
    if info.get("stalled"):
        warnings.warn(
            f"EM stopped after {len(hist)} iterations of the {name} model: its marginal "
            f"log-likelihood stayed below its best ({ll[best]:.6g}, iteration {best + 1}) for "
            f"{EM_PATIENCE} iterations (last {ll[-1]:.6g}); the parameters of iteration "
            f"{info.get('returned_iteration')} are returned; check result.em_history",
            stacklevel=4,
        )
        return
    if not info["converged"]:
        warnings.warn(
            f"EM stopped at max_iter={max_iter} without converging ({len(hist)} iterations of "
            f"the {name} model; log-likelihood {ll[-1]:.6g}, best {ll[best]:.6g} at iteration "
            f"{best + 1}): the poses are those of its best parameters, not of a converged fit; "
            "check result.em_history or raise max_iter",
            stacklevel=4,
        )
    drop = ll[best] - ll[-1]
    if np.isfinite(drop) and drop > 10.0 * ll_tol * max(hist[-1]["used"], 1):
        kept = info.get("returned_iteration")
        which = (
            f"the parameters returned are those of iteration {kept}"
            if kept is not None
            else "the last parameters scored as high again and are returned"
        )
        warnings.warn(
            f"EM's marginal log-likelihood peaked at iteration {best + 1} ({ll[best]:.6g}) "
            f"and fell to {ll[-1]:.6g} ({name} model): {which}; check result.em_history",
            stacklevel=4,
        )


def track_in_memory(
    rig: CameraRig,
    skeleton: Skeleton,
    detections: np.ndarray,
    *,
    likelihood: np.ndarray | None = None,
    pcutoff: float = 0.9,
    joint_limits: bool = True,
    max_iter: int = 100,
    tol: float = 0.05,
    progress: bool | None = False,
    method: str = "ukf",
    gate: float | None = DEFAULT_GATE,
    normalization: Normalization | None = None,
    noise: float = DEFAULT_NOISE,
    marker_names: Sequence[str] | None = None,
    stop: str = "loglik",
    ll_tol: float = DEFAULT_LL_TOL,
    noise_model: str = "gauss",
    dof: float = 4.0,
    motion: str = DEFAULT_MOTION,
    relinearize: int = 10,
    misfit: str = "auto",
    elastic: bool | None = None,
    second_solutions: int = 3,
    overrelax: float | None = DEFAULT_OVERRELAX,
) -> PoseResult:
    """Reconstruct the poses of a recording in memory (ACM supp. sec. 4); what
    :func:`acm_rs.track` runs when the recording's moments fit its memory budget.

    ``method="ukf"`` (default) learns the model parameters by EM (Alg. 11: unscented RTS
    smoother as E-step, Alg. 12 as M-step, Alg. 13 convergence) and returns the smoothed
    posterior under the learned parameters. ``method="deterministic"`` fits every frame
    independently (eq. 9 with bone lengths and marker offsets fixed), for comparison.

    Parameters
    ----------
    rig : CameraRig
        Calibrated cameras (world units = the skeleton's units).
    skeleton : Skeleton
        The learned skeleton (:func:`acm_rs.learn_skeleton`).
    detections : array_like, shape (n_cams, T, n_markers, 2)
        2D marker detections in pixels, NaN where missing; markers in skeleton order unless
        ``marker_names`` maps the columns by name.
    likelihood : array_like, shape (n_cams, T, n_markers), optional
        Detection confidence (DeepLabCut likelihood); entries below ``pcutoff`` are missing.
    pcutoff : float
        Confidence threshold (0.9 as in the paper).
    joint_limits : bool
        Enforce joint-angle limits through the erf map of Alg. 10.
    max_iter, tol : int, float
        EM stops after ``max_iter`` iterations, or (``stop="alg13"``) when the mean relative
        parameter change of Alg. 13 falls below ``tol`` (the paper's 100 and 0.05).
    stop : {"loglik", "alg13"}
        Convergence rule. ``"loglik"`` (default): the marginal log-likelihood of the
        detections (from the filter's innovations, ``em_history[i]["log_likelihood"]``) gains
        less than ``ll_tol`` nats per used measurement between iterations. Alg. 13's relative
        change stops early on smooth data and never on real data, where it oscillates.
    ll_tol : float
        Threshold of ``stop="loglik"`` (1e-3 nats per measurement entry).
    overrelax : float or None
        Over-relaxed EM (beyond the paper): each M-step's change of the parameters is
        taken ``η`` times (``μ0`` on the line, ``V0``, ``V_z`` on the geodesic of positive
        definite matrices, ``V_x`` geometrically); ``η`` grows by this factor while the
        log-likelihood does not fall below the point the step came from, and a step that
        falls is replaced by the plain M-step (``em_history[i]["step"]``, ``["rejected"]``).
        None: plain EM (Alg. 11). The Gaussian model only (the Student-t model runs
        plain EM); the bounded-memory path's windows EM takes it too.
    noise_model : {"gauss", "student"}
        Measurement noise per image point: the paper's Gaussian, or a Student-t with ``dof``
        degrees of freedom learned by EM weights (``docs/tracking.md``): confident
        DeepLabCut mistakes get small weights and do not inflate ``V_x``.
    dof : float
        Degrees of freedom of the Student-t model.
    motion : {"auto", "velocity", "random_walk"}
        Motion model of the state. ``"random_walk"``: the paper's ``z_t = z_{t-1} + ε``
        (eq. 49). ``"velocity"``: position and velocity, ``z_t = z_{t-1} + ż_{t-1} + ε``,
        ``ż_t = ż_{t-1} + ε'`` with the whole ``2n × 2n`` transition covariance learned by EM
        (beyond the paper), started from the random walk's EM result: fast movements do not
        lag, and stretches without detections are bridged by smooth curves whose SD grows
        with the gap; where the prior is too broad (after such a stretch) the update is
        linearised about the random walk's posterior. ``"auto"`` (default): after the random
        walk's EM, one filter pass scores the velocity model at its start against it; the
        velocity EM runs only if that start scores higher, and is kept only if its fit does not use
        fewer detections or reach a lower marginal log-likelihood than the random walk's;
        ``info["motion"]`` says which was used and ``info["motion_note"]`` why
        (``docs/tracking.md``).
    relinearize : int
        At most this many iterated posterior linearisations of a frame's update where the
        single unscented update of Alg. 6 does not hold (the first frame with detections
        after a stretch without any); 0 gives the paper's filter.
    elastic : bool or None
        Track the skeleton's elastic segments (``skeleton.stretch_sd``, issue 28; beyond the
        paper): each elastic bone's log-stretch is a state entry with a memoryless
        transition, ``s_t ~ N(0, σ_b²)``, ``σ_b²`` starting at the skeleton's and learned by
        the M-step (its block of ``V_z``). Results: ``info["bone_lengths"]`` (T, n_bones)
        and ``info["bone_lengths_std"]``, ``info["stretch_sd"]`` (n_bones,) learned. Default:
        when the skeleton has elastic bones; False keeps every bone at its mean length.
    misfit : {"auto", "isotropic", "full", "off"}
        Model misfit of the markers (issue 26 item 3, beyond the paper): the true marker is
        ``FK(z) + δ`` with ``δ ~ N(0, Σ_k)`` per marker, ``Σ_k`` estimated from the
        detections' cross-camera residuals (:mod:`acm_rs.tracking.misfit`), and
        ``markers`` / ``info["markers_std"]`` are the posterior of the true markers
        (``info["markers_fk"]``, ``info["markers_std_fk"]``: forward kinematics only;
        ``info["misfit_sd"]``: per marker). ``"auto"`` (default): ``σ_k² I₃``, measured in
        ``docs/tracking.md``; ``"off"``: FK markers only. Joints are not changed.
    second_solutions : int
        Frames (evenly spread over those with the most detections) searched for a second pose
        that fits the markers as well with
        a joint beyond its 95 % interval (:func:`acm_rs.second_solutions`; beyond the paper).
        Joints found are named in a warning and in ``info["second_solutions"]``: the marker
        layout does not decide them. Their ``joints_std`` are widened so that the 95 %
        interval reaches the second pose (:func:`acm_rs.tracking.ambiguity.widen`:
        ``sqrt(f) D / 1.96`` added per coordinate, ``D`` the median distance to the second
        pose, ``f`` the fraction of searched frames with one; ``info["joints_std_widening"]``).
        Default 3 frames (1 frame left the real-motion cases at 81-86 % joint coverage, 3
        at 91-93 %, ``docs/tracking.md``). 0: no search, the Gaussian posterior's SDs.
        :func:`acm_rs.track` runs it on the bounded-memory path too.
        Cost per frame: ~0.07 s for the bundled rat, ~0.2 s for a 29-joint skeleton without
        joint limits.
    progress : bool or None
        Print one line per EM iteration and a summary to stderr; None: only when stderr is
        a terminal (what the command line passes); default False (quiet).
    gate : float or None
        Innovation gate against confident outliers: an image point whose innovation lies
        outside this probability mass of its predicted distribution is ignored in that frame
        (unless more than half of the frame's points would be; see ``docs/tracking.md``).
        None disables it.
    normalization : Normalization, optional
        Sec. 3.3 constants (default: :func:`default_normalization`).
    noise : float
        Initial diagonal of ``V0`` and ``V_z`` in normalised state units (2e-4; sec. 4.7
        has 0.001, which lets EM settle at worse optima on real motion,
        ``docs/tracking.md``). ``V_x`` starts at the detections' own noise
        (:func:`initial_vx`); ``info["vx_init_px"]`` records it (px, per image axis).
    marker_names : sequence of str, optional
        Names of the detection columns, mapped to skeleton markers (DeepLabCut body parts,
        ``marker_<name>_start`` and ``spot_<name>`` spellings accepted).
    Returns
    -------
    PoseResult
        Joints ``(T, J, 3)`` with posterior std, markers, poses, state moments, EM history.
        EM returns the parameters of the highest marginal log-likelihood it evaluated
        (``info["returned_iteration"]``, ``info["log_likelihood"]``). The fits run with the
        rig and skeleton in units of ``c_t``, so the same detections give the same result
        in any length unit.

    Raises
    ------
    ValueError
        Shape mismatches, unknown marker names, no usable detection, bad options.
    acm_rs.AcmNumericalError
        A covariance that is not positive definite (e.g. a user-supplied ``noise`` <= 0).
    """
    t_start = time.perf_counter()
    if method not in ("ukf", "deterministic"):
        raise ValueError(f"method must be 'ukf' or 'deterministic', got {method!r}")
    if max_iter < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if not (math.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be > 0, got {tol}")
    if stop not in ("loglik", "alg13"):
        raise ValueError(f"stop must be 'loglik' or 'alg13', got {stop!r}")
    if noise_model not in ("gauss", "student"):
        raise ValueError(f"noise_model must be 'gauss' or 'student', got {noise_model!r}")
    if not (math.isfinite(dof) and dof > 0):
        raise ValueError(f"dof must be > 0, got {dof}")
    if not (math.isfinite(ll_tol) and ll_tol > 0):
        raise ValueError(f"ll_tol must be > 0, got {ll_tol}")
    if int(second_solutions) != second_solutions or second_solutions < 0:
        raise ValueError(f"second_solutions must be a whole number >= 0, got {second_solutions}")
    if not (math.isfinite(noise) and noise > 0):
        raise ValueError(f"noise must be > 0, got {noise}")
    if motion not in MOTION_ORDER:
        raise ValueError(f"motion must be one of {sorted(MOTION_ORDER)}, got {motion!r}")
    if misfit not in MISFIT_MODES:
        raise ValueError(f"misfit must be one of {MISFIT_MODES}, got {misfit!r}")
    if int(relinearize) != relinearize or relinearize < 0:
        raise ValueError(f"relinearize must be an integer >= 0, got {relinearize}")
    check_overrelax(overrelax)
    det = _measurements(rig, skeleton, detections, likelihood, pcutoff, marker_names)
    n_frames = det.shape[1]
    norm = normalization or default_normalization(rig, skeleton)
    # sanity checks that speak: declared units, camera order, then units from the data
    # (each refuses with the fix)
    check_units(rig, skeleton)
    # from here on the world is in units of c_t (unit-free to rounding)
    rig_u, sk_u, norm_u, c_t = _in_rig_units(rig, skeleton, norm)
    fit_px = check_camera_order(rig_u, sk_u, det, norm_u)
    check_scale(rig, skeleton, det)
    empty = _empty_stretches(det)
    has_stretch = bool(skeleton.stretch_sd.any())
    elastic = has_stretch if elastic is None else bool(elastic)
    if elastic and not has_stretch:
        raise ValueError(
            "elastic=True needs a skeleton with elastic bones (stretch_sd > 0): learn them with "
            "acm_rs.elastic.add_stretch or `acm-rs learn --elastic`"
        )
    elastic = elastic and method == "ukf"
    sm = StateMap(skeleton, norm, joint_limits, stretch=elastic)
    bones = sm.stretch_bones
    if method == "deterministic":
        t, r = _deterministic(rig_u, sk_u, det, norm_u)
        t = t * c_t
        joints, markers = skeleton.forward(t, r)
        result = PoseResult(
            skeleton=skeleton, rig=rig, state_map=sm, joints=joints,
            joints_std=np.zeros_like(joints), markers=markers, t=t, r=r,
            state_mean=sm.from_pose(t, r), state_cov=None, detections=det,
            info={
                "method": "deterministic", "joint_limits": bool(joint_limits),
                "check_fit_px": fit_px,
                "normalization": _norm_dict(norm), "seconds": time.perf_counter() - t_start,
            },
        )  # fmt: skip
        if _on_terminal(progress):
            print(result.summary(), file=sys.stderr)
        return result

    f0, mu0, vx0 = _em_start(rig_u, sk_u, det, norm_u, joint_limits)
    mu0 = np.concatenate([mu0, np.zeros(len(bones))])  # log-stretch 0: the mean lengths
    x = norm.normalize_pixels(det).transpose(1, 0, 2, 3)  # (T, C, M, 2)
    lim = skeleton.joint_limits

    def make_tracker(order: int):
        return _native.NativeTracker(
            sk_u._native, rig_u.get_params(), np.ascontiguousarray(lim[..., 0]),
            np.ascontiguousarray(lim[..., 1]), norm_u._tuple(), bool(joint_limits),
            np.ascontiguousarray(x), relinearize=int(relinearize), order=order,
            stretch=bones if elastic else None,
        )  # fmt: skip

    def run(native, init: tuple, max_iter: int):
        return native.run_em(
            *init, int(max_iter), float(tol), gate_threshold(gate), _Printer(progress),
            float(ll_tol) if stop == "loglik" else None,
            float(dof) if noise_model == "student" else None, EM_PATIENCE,
            None if overrelax is None else float(overrelax),
        )  # fmt: skip

    native = make_tracker(1)
    # V0 = V_z = noise I on the pose entries; the skeleton's stretch variances on the rest
    eye = np.diag(
        np.concatenate([np.full(sm.n_pose_state, noise), skeleton.stretch_sd[bones] ** 2])
    )
    t_init = time.perf_counter() - t_start
    # Alg. 11 with the random walk: mu0 of sec. 4.7, V0 = V_z = noise I, V_x from the data
    params, history, converged, interrupted = run(native, (mu0, eye, eye.copy(), vx0), max_iter)
    length_rounds = 0
    if elastic:
        # the mean lengths too (a conditional M-step): the stretch model is s ~ N(b, σ²);
        # b = mean_t E[s_t] moves into l_b (l_b exp(s) = l_b e^b exp(s − b)), and EM goes on
        # from there. Lengths from a few labelled frames are biased by their stretch (a 13 %
        # paw on 40 frames took a 2x stretch SD to explain).
        idx = np.arange(sm.n_pose_state, sm.n_state)
        for _ in range(MAX_LENGTH_ROUNDS):
            if interrupted or len(history) >= max_iter:
                break
            b = native.means()[1:, idx].mean(axis=0)
            sd = np.sqrt(np.diag(params["Vz"])[idx])
            if np.all(np.abs(b) <= 0.1 * np.maximum(sd, 0.01)):
                break
            length_rounds += 1
            new = sk_u.bone_lengths.copy()
            new[bones] *= np.exp(b)
            sk_u = sk_u.with_parameters(new)
            skeleton = skeleton.with_parameters(new * c_t)
            mu0_b = params["mu0"].copy()
            mu0_b[idx] -= b
            native = make_tracker(1)
            # (V_z keeps its E[s²]: the next M-step takes b² out of it)
            params, more, converged, interrupted = run(
                native, (mu0_b, params["V0"], params["Vz"], params["Vx_diag"]),
                max_iter - len(history),
            )  # fmt: skip
            history = history + more
        sm = StateMap(skeleton, norm, joint_limits, stretch=True)
    for h in history:
        h["motion"] = "random_walk"
    outcome = native.em_outcome()
    used = "velocity" if motion == "auto" else motion
    motion_note = ""
    if used == "velocity" and interrupted:
        used, motion_note = "random_walk", "interrupted before the velocity model's EM"
    if used == "velocity" and not interrupted:
        # EM of the position-velocity model started from the random walk's answer (from
        # the sec. 4.7 start it wanders: docs/tracking.md)
        rw = (native, params, history, converged, outcome)
        init = _velocity_init(params, native.means(), np.arange(sm.n_pose_state, sm.n_state))
        hint = (native.means(), native.covs())
        native = make_tracker(2)
        # where the velocity's prior is too broad (after stretches without detections), the
        # update is linearised about the random walk's posterior (the model is unchanged)
        native.set_linearization_hint(*hint)
        worse = ""
        if motion == "auto" and noise_model == "gauss":
            # the choice: one filter pass of the velocity model at its start against the random
            # walk's optimum (log-likelihoods of the same detections, unit-free); EM of the
            # velocity model only raises its score, so a start that already scores higher
            # decides for it, and one that scores lower is not pursued. (The Student-t
            # model's first pass has no outlier weights yet: there the two EMs' ends are
            # compared.) The marginal log-likelihood is the filter's: no smoother needed.
            first = native.e_step(*init, gate=gate_threshold(gate), smooth=False)
            worse = _velocity_worse(outcome["final"], first)
            if worse:
                worse = f"at its start {worse}"
        if not worse:
            params, more, converged, interrupted = run(
                native, init, max(1, max_iter - len(history))
            )
            for h in more:
                h["motion"] = "velocity"
            history = history + more
            worse = _velocity_worse(outcome["final"], native.em_outcome()["final"])
            outcome = native.em_outcome()
        if worse:
            if motion == "auto":
                native, params, _, converged, outcome = rw
                used, motion_note = "random_walk", f"the velocity model fits worse: {worse}"
            else:
                import warnings

                warnings.warn(
                    f"motion='velocity' fits these detections worse than the random walk "
                    f"({worse}); consider motion='random_walk'",
                    stacklevel=3,
                )
    poses, joints, markers, joints_std, markers_std = native.posterior()
    # back to the caller's length unit
    poses[:, :3] *= c_t
    joints, markers, joints_std, markers_std = (
        a * c_t for a in (joints, markers, joints_std, markers_std)
    )
    means, covs = native.means(), native.covs()
    mask = native.mask().transpose(1, 0, 2, 3)[..., 0]  # (C, T, M)
    t = poses[:, :3]
    r = poses[:, 3:].reshape(n_frames, skeleton.n_bones, 3)
    stretch_info = {"elastic": elastic}
    if elastic:
        idx = np.arange(sm.n_pose_state, sm.n_state)
        s_mean = means[1:, idx]
        s_sd = np.sqrt(np.maximum(covs[1:, idx, idx], 0.0))
        lengths = np.broadcast_to(skeleton.bone_lengths, (n_frames, skeleton.n_bones)).copy()
        lengths[:, bones] *= np.exp(s_mean)
        lengths_sd = np.zeros_like(lengths)
        lengths_sd[:, bones] = lengths[:, bones] * s_sd  # first order in s
        learned = np.zeros(skeleton.n_bones)
        learned[bones] = np.sqrt(np.diag(params["Vz"])[idx])
        stretch_info |= {
            "bone_lengths": lengths, "bone_lengths_std": lengths_sd, "stretch_sd": learned,
            "mean_lengths": skeleton.bone_lengths, "length_rounds": length_rounds,
        }  # fmt: skip
    result = PoseResult(
        skeleton=skeleton, rig=rig, state_map=sm, joints=joints, joints_std=joints_std,
        markers=markers, t=t, r=r, state_mean=means[1:], state_cov=covs[1:], detections=det,
        em_history=history,
        info={
            "method": "ukf", "converged": bool(converged), "interrupted": bool(interrupted),
            "iterations": len(history), "tol": float(tol), "gate": gate,
            "stop": stop, "ll_tol": float(ll_tol), "noise_model": noise_model, "dof": float(dof),
            "motion": used, "motion_requested": motion, "motion_note": motion_note,
            "relinearize": int(relinearize),
            "empty_stretches": empty,
            "params": params, "status": mask, "markers_std": markers_std,
            "first_frame": f0, "mu0_init": mu0, "joint_limits": bool(joint_limits),
            "vx_init_px": np.sqrt(vx0[:2]) * np.asarray(norm.pixel, dtype=float),
            "returned_iteration": outcome["returned_iteration"],
            "stalled": bool(outcome.get("stalled", False)),
            "log_likelihood": float(outcome["final"]["log_likelihood"]),
            "check_fit_px": fit_px,
            "normalization": _norm_dict(norm),
            "seconds_init": t_init, "seconds": time.perf_counter() - t_start,
        } | stretch_info,
    )  # fmt: skip
    if interrupted:
        print(
            "EM interrupted (Ctrl-C); returning the posterior under the last parameters",
            file=sys.stderr,
        )
    t_misfit = time.perf_counter()
    apply_misfit(result, misfit)
    result.info["seconds_misfit"] = time.perf_counter() - t_misfit
    if second_solutions > 0 and result.state_cov is not None and not interrupted:
        warn_second_solutions(result, second_solutions)
    result.info["seconds"] = time.perf_counter() - t_start
    _warn_implausible_fit(result, fit_px)
    _warn_em(result, max_iter, ll_tol)
    if _on_terminal(progress):
        print(result.summary(), file=sys.stderr)
    return result
