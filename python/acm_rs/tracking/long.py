"""Hour-long recordings in bounded memory (issue 16 items 1-2; beyond the paper).

Two steps, each with memory that does not grow with the recording's length ``T``:

1. **Θ by EM on a subset** (:func:`learn_windows`): ``n_windows`` evenly spread windows of
   the recording (default 10 × 1,000 frames), treated as independent sequences of one model:
   each window has its own ``μ0, V0`` (eqs. 77-78 per window), ``V_z`` and ``V_x`` are
   shared (eq. 79 summed over the windows' transitions, eq. 81 over their measurements).
   Windows that the tracker fits implausibly (90th percentile reprojection error above 1.5 ×
   the windows' median) are left out, with a warning, and EM continues on the rest.
   Evenly spread windows see the animal's whole range of behaviour (one contiguous block
   would see one bout); joining them into one sequence would make every join a jump that
   inflates ``V_z``. The motion model is chosen as in :func:`acm_rs.track`.

2. **Smoothing with Θ fixed**: by default the exact smoother of the whole recording from
   checkpointed filter states (:mod:`acm_rs.tracking.streaming`); with a Dask client, or
   ``method="chunked"``, in chunks (below). **The chunked smoother** (:func:`smooth_chunked`): the
   recording is cut into cores of ``chunk`` frames; each core is filtered and smoothed (Alg. 7 +
   9) over a window extended by ``burn_in`` frames on both sides, starting from the single-frame
   fit (sec. 4.7) of the window's first frame with a broad prior. The filter forgets that start
   and the smoother the window's end within a few frames of detections, so the cores equal the
   smoother of the whole recording up to a small difference — which is **checked**, not assumed:
   neighbouring windows overlap, and at each seam their estimates of the two frames either side
   must agree within ``tol`` of the posterior SD (default 5 %; 0.5 % for the chunks started
   from checkpoints, :func:`smooth_checkpointed`); where they do not (a stretch without
   detections across the seam), both windows are recomputed with twice the burn-in, up
   to ``max_burn_in`` and while each doubling at least halves the difference, and a seam that
   still disagrees is reported (``info["seams_disagreeing"]``, a warning). Cores are
   independent: they run in parallel on a thread pool or on a Dask cluster (``client``) with
   identical results, and are written to an HDF5 file in order as they are done (atomically: a
   temporary file renamed at the end).

Memory: the inputs are read one window at a time, so ``detections`` may be a
``numpy.memmap``, an ``h5py`` or ``zarr`` array (anything sliced as ``a[:, t0:t1]``); each
window in flight holds ``(chunk + 2 burn_in) · (order · n)² · 8`` bytes of moments (176 MB for
the rat's velocity state and the defaults).
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .. import _native
from .._io import check_output_path
from .._version import __version__
from ..camera import CameraRig
from ..learning import check_scale, check_units
from ..skeleton import Skeleton
from ..state import Normalization, StateMap
from .result import PoseResult
from .streaming import forward_pass, report_poor_fit, smooth_streaming
from .track import (
    DEFAULT_GATE,
    DEFAULT_LL_TOL,
    DEFAULT_MOTION,
    DEFAULT_NOISE,
    DEFAULT_OVERRELAX,
    EM_PATIENCE,
    MAX_OVERRELAX,
    MOTION_ORDER,
    _first_pose,
    _measurements,
    _norm_dict,
    _on_terminal,
    _Printer,
    _velocity_init,
    _velocity_worse,
    check_camera_order,
    check_overrelax,
    default_normalization,
    gate_threshold,
    initial_vx,
)
from .windows import (
    _H5Writer,
    _Model,
    _normalized,
    _Source,
    close_output,
    frame_px,
    read_chunked,
    smooth_window,
)

#: Frames per core of :func:`smooth_chunked`.
DEFAULT_CHUNK = 2000
#: Frames of burn-in on each side of a core (measured: docs/tracking.md, "Long recordings").
DEFAULT_BURN_IN = 100
#: Frames of the EM subset and number of windows it is spread over. 10,000 rather than 20,000
#: since session 17: on the 100,000-frame bench the joints were the same (velocity 0.463 /
#: 0.330 mm against 0.463 / 0.331; random walk 0.672 / 0.503 against 0.676 / 0.504 mm) for
#: EM in 0.5-0.65 × the time and 0.6 × the memory (benches/README.md, "track() on 100,000
#: frames").
DEFAULT_SUBSET = 10000
DEFAULT_WINDOWS = 10
#: Largest seam difference between neighbouring windows, in posterior SDs.
DEFAULT_TOL = 0.05
#: ... and for chunks started from the exact filter's checkpoints: issue 16's "within 1 % of
#: the posterior SD" with a margin (20,000 frames: 0.44 % at most; 0.01 gave 1.01 %).
CHECKPOINT_TOL = 0.005

_USED = 1  # filter.rs status::USED


def subset_windows(
    n_frames: int, subset: int = DEFAULT_SUBSET, n_windows: int = DEFAULT_WINDOWS
) -> list[tuple[int, int]]:
    """``n_windows`` evenly spread frame ranges ``[(start, stop)]`` of ``subset // n_windows``
    frames each, the first starting at frame 0 and the last ending at ``n_frames``; the whole
    recording as one window if it has at most ``subset`` frames."""
    if n_frames < 1:
        raise ValueError(f"the recording has no frames (n_frames = {n_frames})")
    if subset < 2 or n_windows < 1:
        raise ValueError(f"subset must be >= 2 and n_windows >= 1, got {subset}, {n_windows}")
    if n_frames <= subset:
        return [(0, n_frames)]
    length = max(2, subset // n_windows)
    starts = np.linspace(0, n_frames - length, n_windows).round().astype(int)
    return [(int(s), int(s) + length) for s in np.unique(starts)]


# -- EM on a subset of windows ----------------------------------------------------------------


def _combine(new: list[dict], frames: list[int], counts: list[np.ndarray], prev_vx) -> tuple:
    """Shared ``V_z`` (eq. 79 over all windows' transitions) and ``V_x`` (eq. 81 over all
    windows' used entries) from the per-window M-steps."""
    w = np.asarray(frames, dtype=float)
    vz = sum(wk * p["Vz"] for wk, p in zip(w, new, strict=True)) / w.sum()
    c = np.sum(counts, axis=0)
    s = sum(ck * p["Vx_diag"] for ck, p in zip(counts, new, strict=True))
    vx = np.where(c > 0, s / np.maximum(c, 1), prev_vx)
    return 0.5 * (vz + vz.T), vx


def _extrapolate(p: tuple, q: tuple, eta: float) -> tuple | None:
    """Parameters ``eta`` times as far from ``p`` as the M-step's ``q`` (Rust
    ``tracking::extrapolate``); None where a covariance is not positive definite."""
    c = [tuple(np.ascontiguousarray(a, dtype=np.float64) for a in x) for x in (p, q)]
    return _native.extrapolate_params(c[0], c[1], float(eta))


def _em_windows(
    trackers: list, inits: list[tuple], max_iter: int, ll_tol: float, gate: float | None,
    pool: ThreadPoolExecutor, printer: Callable, release: bool = False,
    overrelax: float | None = None,
) -> tuple[list[tuple], list[dict], bool]:  # fmt: skip
    """Alg. 11 over independent windows (one ``NativeTracker`` each; each window's E- and
    M-step in parallel with the others'); stops when the summed marginal log-likelihood gains
    less than ``ll_tol`` nats per used entry. The trackers then hold the moments of the last
    iteration's E-step, under the parameters before its M-step (when EM converged, their
    log-likelihoods differ by less than the stop's tolerance; a final E-step under the
    returned parameters cost 3-5 % of EM's time and is not run). As ``Tracker::run_em``, it
    keeps the parameters of the highest summed log-likelihood: when the last iteration scored
    lower than an earlier one by more than the tolerance, or ``EM_PATIENCE`` iterations in a
    row stayed below the best (then it stops), the best parameters are returned, after one
    E-step under them so that the trackers hold their moments. ``release``: each window's
    covariances are freed after its M-step (only its means are kept), so that EM holds the
    covariances of only the windows being worked on: EM's peak RSS 1.76 → 1.15 GB at the
    default 10 × 1,000 frames of the velocity state. ``overrelax``: over-relaxed EM as
    ``Tracker::run_em`` (``EmOptions::overrelax``): each window's parameters are moved ``η``
    times the M-step's change (``_native.extrapolate_params``; the shared ``V_z``, ``V_x``
    alike in every window), ``η`` growing by this factor while the summed log-likelihood
    does not fall below the point the step came from; a step that falls is replaced by the
    plain M-step. Only plain steps' changes decide the stop; an over-relaxed step of factor
    ``η`` that changed the log-likelihood by less than ``η · ll_tol`` per entry makes the next
    step plain."""
    params = list(inits)
    history: list[dict] = []
    converged = False
    frames = [tr.n_frames for tr in trackers]

    def em_step(tr, p: tuple) -> tuple[dict, dict, np.ndarray]:
        stats = tr.e_step(*p, gate)
        new = tr.m_step(*p)
        if release:
            tr.release_covariances()
        return stats, new, (tr.mask() == _USED).sum(axis=0).ravel()

    best: tuple[float, int, list[tuple]] | None = None  # (log-likelihood, iteration, params)
    # over-relaxation: the factor of the evaluated step, the next step's, and (for an
    # over-relaxed step) the plain M-step's parameters and the log-likelihood to beat
    step, eta = 1.0, 1.0
    fallback: tuple[list[tuple], float] | None = None
    for it in range(1, max_iter + 1):
        t0 = time.perf_counter()
        evaluated = params
        done = list(pool.map(em_step, trackers, params))
        stats, new, counts = ([d[k] for d in done] for k in range(3))
        tot = {k: sum(s[k] for s in stats) for k in stats[0]}
        ll = float(tot["log_likelihood"])
        if np.isfinite(ll) and (best is None or ll > best[0]):
            best = (ll, it, evaluated)
        if fallback is not None:
            plain, ll_from = fallback
            fallback = None
            if not ll >= ll_from:
                # the over-relaxed step scored lower: evaluate the plain one next
                seconds = time.perf_counter() - t0
                history.append({
                    "iteration": it, "delta": float("nan"), "seconds": seconds, **tot,
                    "step": step, "rejected": True,
                })  # fmt: skip
                printer(it, float("nan"), seconds, tot)
                params, step, eta = plain, 1.0, 1.0
                continue
        vz, vx = _combine(new, frames, counts, params[0][3])
        nxt = [(p["mu0"], p["V0"], vz, vx) for p in new]
        # Alg. 13's measure over the shared parameters (diag V_z, V_x)
        prev = np.concatenate([params[0][2].diagonal(), params[0][3]])
        delta = float(np.mean(np.abs(np.concatenate([vz.diagonal(), vx]) / prev - 1)))
        seconds = time.perf_counter() - t0
        history.append({
            "iteration": it, "delta": delta, "seconds": seconds, **tot,
            "step": step, "rejected": False,
        })  # fmt: skip
        printer(it, delta, seconds, tot)
        held = [h for h in history if not h["rejected"]]
        # a plain step's change decides the stop; a small one after an over-relaxed step of
        # factor η (below η · ll_tol: it may have passed the maximum along its direction)
        # makes the next step plain (as Tracker::run_em, ll_settled / overrelaxed_settled)
        small_far = False
        if len(held) > 1:
            gain = abs(held[-1]["log_likelihood"] - held[-2]["log_likelihood"])
            if step <= 1.0 and gain < ll_tol * max(tot["used"], 1):
                params = nxt
                converged = True
                break
            small_far = step > 1.0 and gain < step * ll_tol * max(tot["used"], 1)
        if best is not None and it >= best[1] + EM_PATIENCE:
            params = nxt
            break
        params, step = nxt, 1.0
        if overrelax is not None and np.isfinite(ll) and not small_far:
            grown = min(eta * overrelax, MAX_OVERRELAX) if history[-1]["step"] > 1.0 else overrelax
            far = [_extrapolate(p, q, grown) for p, q in zip(evaluated, nxt, strict=True)]
            if all(f is not None for f in far):
                fallback = (nxt, ll)
                params, step, eta = far, grown, grown
    if fallback is not None:
        # max_iter ended on an over-relaxed step that was never evaluated
        params = fallback[0]
    if best is not None and history:
        last = history[-1]
        stalled = best[1] + EM_PATIENCE <= last["iteration"] and not converged
        if stalled or last["log_likelihood"] < best[0] - ll_tol * max(last["used"], 1):
            params = best[2]

            def redo(tr, p: tuple) -> None:
                tr.e_step(*p, gate, smooth=True, statistics=False)
                if release:
                    tr.release_covariances()

            list(pool.map(redo, trackers, params))
            history[-1] = history[-1] | {"returned_iteration": best[1], "stalled": stalled}
    return params, history, converged


def _warn_windows_em(history: list[dict], motion: str, converged: bool, max_iter: int) -> None:
    """Say how the windows' EM of the model used ended when it did not converge (as
    ``track``'s ``_warn_em``): after ``EM_PATIENCE`` iterations below its best, or at
    ``max_iter``, and which iteration's parameters were returned."""
    hist = [h for h in history if h.get("motion", motion) == motion]
    if converged or not hist:
        return
    name = motion.replace("_", " ")
    last = hist[-1]
    kept = last.get("returned_iteration")
    which = (
        f"the parameters of iteration {kept} (its best summed log-likelihood) are returned"
        if kept is not None
        else "the last parameters are returned"
    )
    if last.get("stalled"):
        why = f"its summed log-likelihood stayed below its best for {EM_PATIENCE} iterations"
    else:
        why = f"it reached max_iter={max_iter} without converging"
    warnings.warn(
        f"EM over the windows stopped after {len(hist)} iterations of the {name} "
        f"model: {why}; {which}; check the fit's history",
        stacklevel=3,
    )


@dataclass
class SubsetFit:
    """Θ learned by :func:`learn_windows`."""

    params: dict  # shared V_z, V_x; mu0, V0 of the first window
    motion: str
    motion_note: str
    history: list[dict]
    converged: bool
    windows: list[tuple[int, int]]
    prior_cov: np.ndarray
    seconds: float
    extra: dict = field(default_factory=dict)


def learn_windows(
    rig: CameraRig,
    skeleton: Skeleton,
    windows_det: Sequence[np.ndarray],
    norm: Normalization,
    *,
    motion: str = DEFAULT_MOTION,
    joint_limits: bool = True,
    max_iter: int = 100,
    ll_tol: float = DEFAULT_LL_TOL,
    gate: float | None = DEFAULT_GATE,
    noise: float = DEFAULT_NOISE,
    relinearize: int = 10,
    progress: bool | None = False,
    windows: Sequence[tuple[int, int]] = (),
    workers: int = 2,
    overrelax: float | None = DEFAULT_OVERRELAX,
) -> SubsetFit:
    """Learn Θ by EM (Alg. 11) on independent windows of one recording.

    Parameters
    ----------
    windows_det : sequence of arrays, shape (n_cams, W_k, M, 2)
        Detections of each window in pixels, skeleton marker order, NaN where missing.
    norm : Normalization
        Sec. 3.3 constants.
    motion, joint_limits, max_iter, ll_tol, gate, noise, relinearize, progress, overrelax
        As :func:`acm_rs.track` (the Gaussian noise model).
    windows : sequence of (start, stop)
        The windows' frame ranges, recorded in the result.

    Returns
    -------
    SubsetFit
        Shared parameters, the motion model used, the EM history and the prior covariance
        of a window start for :func:`smooth_chunked`: the position block is 4 × the mean
        smoothed ``V0`` of the windows (a single-frame fit's uncertainty, generously), the
        velocity block the covariance of the smoothed velocities.
    """
    if motion not in MOTION_ORDER:
        raise ValueError(f"motion must be one of {sorted(MOTION_ORDER)}, got {motion!r}")
    check_overrelax(overrelax)
    t_start = time.perf_counter()
    sm = StateMap(skeleton, norm, joint_limits)
    n = sm.n_state
    xs, mus = [], []
    for k, det in enumerate(windows_det):
        try:
            _, t0, r0 = _first_pose(rig, skeleton, det, norm)
        except ValueError:
            raise ValueError(
                f"EM window {k} {tuple(windows[k]) if windows else ''} has no frame with 3 "
                "markers seen by 2 cameras; choose other windows (subset, n_windows)"
            ) from None
        mus.append(sm.start_state(t0, r0))
        xs.append(_normalized(norm, det))
    gate_thr = gate_threshold(gate)
    printer = _Printer(progress)
    # one tracker constructor for the windows and the chunks (_Model.tracker)
    maker = _Model(
        rig, skeleton, norm, joint_limits, relinearize, gate_thr, 1, {}, np.zeros((0, 0)), 0.9,
        threads=1 if workers > 1 and len(xs) > 1 else 0,
    )  # fmt: skip

    def trackers(order: int, which: Sequence[int], buffers=None) -> list:
        m = maker if buffers is None else replace(maker, buffers=buffers)
        return [m.tracker(xs[k], order=order) for k in which]

    eye = np.eye(n) * noise
    # V_x starts at the detections' noise, as in track (docs/tracking.md, "The start")
    vx0 = initial_vx(rig, skeleton, np.concatenate(list(windows_det), axis=1), norm)
    inits = [(mu, eye, eye.copy(), vx0) for mu in mus]
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        rw = trackers(1, range(len(xs)))
        # (the last iteration's posterior serves the fits, hints and the velocity start below)
        params, history, converged = _em_windows(rw, inits, max_iter, ll_tol, gate_thr, pool,
                                                 printer, overrelax=overrelax)  # fmt: skip
        for h in history:
            h["motion"] = "random_walk"
        # windows where the tracker does badly (e.g. a hard stretch) would inflate the shared
        # noise for every other frame: leave them out and continue EM on the rest
        fit_px = [_fit_px(rig, skeleton, tr, d) for tr, d in zip(rw, windows_det, strict=True)]
        keep = _plausible(fit_px)
        dropped = [
            (tuple(windows[k]) if windows else k, fit_px[k])
            for k in range(len(rw)) if k not in keep
        ]  # fmt: skip
        if dropped:
            warnings.warn(
                f"EM window(s) {[d[0] for d in dropped]} fit implausibly (90th percentile "
                f"reprojection error {[round(d[1], 1) for d in dropped]} px against a median "
                f"of {np.median(fit_px):.1f} px): left out of the shared parameters",
                stacklevel=2,
            )
            rw = [rw[k] for k in keep]
            left = max(1, max_iter - len(history))
            params, more, converged = _em_windows(
                rw, [params[k] for k in keep], left, ll_tol, gate_thr, pool, printer,
                overrelax=overrelax,
            )  # fmt: skip
            history = history + [h | {"motion": "random_walk", "windows": len(rw)} for h in more]
        used, note, final = "random_walk", "", rw
        rw_params = params
        # what is needed of the random walk's trackers later: their smoothed means
        rw_means = [tr.means() for tr in rw]
        if MOTION_ORDER[motion] == 2:
            vinit, d2s = [], []
            for tr, p in zip(rw, params, strict=True):
                d = {"mu0": p[0], "V0": p[1], "Vz": p[2], "Vx_diag": p[3]}
                vinit.append(_velocity_init(d, tr.means()))
                d2s.append(max(1, tr.n_frames - 1))
            # one Q_v pooled over the windows' second differences
            w = np.asarray(d2s, float)
            vz = sum(wk * v[2] for wk, v in zip(w, vinit, strict=True)) / w.sum()
            vinit = [(v[0], v[1], vz, v[3]) for v in vinit]
            # each window's covariances, released after its M-step, go to a pool from which
            # the next window's E-step takes them (fresh pages: ~3 % of EM in page faults)
            vel = trackers(2, keep, buffers=_native.NativeBufferPool(2 * max(1, workers)))
            for tv, tr in zip(vel, rw, strict=True):
                tv.set_linearization_hint(tr.means(), tr.covs())
            # the hints hold the random walk's moments now: its trackers' memory (~46 MB per
            # 2,000-frame window) is released before the velocity EM
            del tr
            rw = final = []
            left = max(1, max_iter - len(history))
            # (the velocity trackers' moments serve only the spread of the smoothed velocities
            # in the window prior: the means of EM's last E-step do, without a final one and
            # without the covariances)
            vparams, more, vconv = _em_windows(vel, vinit, left, ll_tol, gate_thr, pool, printer,
                                               release=True, overrelax=overrelax)  # fmt: skip
            for h in more:
                h["motion"] = "velocity"
            worse = _velocity_worse(history[-1], more[-1]) if history and more else ""
            if worse and motion == "auto":
                note = worse
            else:
                if worse:
                    warnings.warn(
                        f"motion='velocity' fits these windows worse than the random walk "
                        f"({worse}); consider motion='random_walk'",
                        stacklevel=2,
                    )
                used, params, converged, final = "velocity", vparams, vconv, vel
            history = history + more
    prior = _window_prior_cov(params, final, n, MOTION_ORDER[used])
    # a typical frame's reprojection error (frame_px: 90th percentile) over the kept windows
    probe = _Model(rig, skeleton, norm, joint_limits, relinearize, None, 1, {}, np.zeros((0, 0)),
                   0.9)  # fmt: skip
    per_frame = np.concatenate([
        frame_px(probe, sm, m[1:], windows_det[k]) for k, m in zip(keep, rw_means, strict=True)
    ])  # fmt: skip
    typical_px = float(np.nanmedian(per_frame)) if np.isfinite(per_frame).any() else math.nan
    first, rw_first = params[0], rw_params[0]
    out = {"mu0": first[0], "V0": first[1], "Vz": first[2], "Vx_diag": first[3]}
    extra = {}
    if used == "velocity":
        # the random walk's Θ: its smoother gives the linearisation hint of windows with a
        # stretch without detections (as in acm_rs.track)
        extra = {
            "rw_params": {"mu0": rw_first[0], "V0": rw_first[1], "Vz": rw_first[2],
                          "Vx_diag": rw_first[3]},
            "rw_prior_cov": _window_prior_cov(rw_params, [], n, 1),
        }  # fmt: skip
    extra |= {"window_fit_px": fit_px, "dropped_windows": dropped, "typical_px": typical_px}
    _warn_windows_em(history, used, converged, max_iter)
    return SubsetFit(
        params=out, motion=used, motion_note=note, history=history, converged=converged,
        windows=list(windows), prior_cov=prior, seconds=time.perf_counter() - t_start,
        extra=extra,
    )  # fmt: skip


#: An EM window whose 90th percentile reprojection error exceeds this multiple of the
#: windows' median is left out of Θ (on the 20,000-frame bench: 10.5 px against 4.7 px for a
#: hard stretch; leaving it out took the error elsewhere from 0.93 to 0.69 mm).
DROP_FACTOR = 1.5


def _fit_px(rig: CameraRig, skeleton: Skeleton, tracker, det: np.ndarray) -> float:
    """90th percentile (px) of the distances between a window's smoothed posterior markers,
    projected, and its detections ``(C, W, M, 2)``."""
    poses = tracker.posterior()[0]
    t, r = poses[:, :3], poses[:, 3:].reshape(len(poses), skeleton.n_bones, 3)
    err = np.linalg.norm(skeleton.project(rig, t, r) - det, axis=-1)
    err = err[np.isfinite(err)]
    return float(np.percentile(err, 90)) if err.size else math.inf


def _plausible(fit_px: list[float]) -> list[int]:
    """Indices of the windows to keep: all but those above ``DROP_FACTOR`` × the median
    (only with >= 3 windows, and never more than half of them)."""
    if len(fit_px) < 3:
        return list(range(len(fit_px)))
    limit = DROP_FACTOR * float(np.median(fit_px))
    keep = [k for k, v in enumerate(fit_px) if v <= limit]
    return keep if 2 * len(keep) >= len(fit_px) else list(range(len(fit_px)))


def _window_prior_cov(params: list[tuple], trackers: list, n: int, order: int) -> np.ndarray:
    """Prior covariance of a window's start: 4 × the windows' mean smoothed ``V0`` for the
    position (a single-frame fit's uncertainty, generously) and, for the velocity, the spread
    of the smoothed velocities (the position means' differences) plus their mean ``V0``."""
    ns = order * n
    prior = np.zeros((ns, ns))
    prior[:n, :n] = 4.0 * np.mean([p[1][:n, :n] for p in params], axis=0)
    if order == 2:
        vel = np.concatenate([np.diff(tr.means()[1:], axis=0) for tr in trackers])
        prior[n:, n:] = np.cov(vel.T) + np.mean([p[1][n:, n:] for p in params], axis=0)
    return 0.5 * (prior + prior.T)


# -- chunked smoothing ------------------------------------------------------------------------


def _seam_difference(left: dict, l0: int, right: dict, r0: int, frames: Sequence[int]) -> float:
    """Largest joint difference between two windows' estimates (window starts ``l0``,
    ``r0``) of ``frames``, in units of the smaller of their posterior SDs."""
    worst = 0.0
    for f in frames:
        a, b = left["joints"][f - l0], right["joints"][f - r0]
        sd = np.minimum(left["joints_std"][f - l0], right["joints_std"][f - r0])
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.abs(a - b) / sd
        rel = rel[np.isfinite(rel)]
        if rel.size:
            worst = max(worst, float(rel.max()))
    return worst


class _LocalMap:
    """Runs windows on a thread pool (the native work releases the GIL)."""

    def __init__(self, model: _Model, workers: int) -> None:
        self.model, self.pool = model, ThreadPoolExecutor(max_workers=max(1, workers))
        self.workers = max(1, workers)

    def submit(self, det, lik, prior=None):
        return self.pool.submit(smooth_window, self.model, det, lik, prior)

    def close(self) -> None:
        self.pool.shutdown()


class _DaskMap:
    """Runs windows on a Dask cluster: the model is sent to every worker once."""

    def __init__(self, model: _Model, client) -> None:
        from distributed import Client

        self.own = isinstance(client, str)
        self.client = Client(client) if self.own else client
        self.model = self.client.scatter(model, broadcast=True)
        self.workers = max(1, len(self.client.scheduler_info()["workers"]))

    def submit(self, det, lik, prior=None):
        return self.client.submit(smooth_window, self.model, det, lik, prior, pure=False)

    def close(self) -> None:
        if self.own:
            self.client.close()


def _close_chunked(writer, model: _Model, info, run: dict, frames, diffs, burn) -> dict:
    """Stores a chunked run (info, seams, burn-ins, Θ) and returns its info."""
    stored = dict(info or {}) | run
    stored |= {"seam_frames": frames, "seam_difference": diffs, "burn_in": burn}
    close_output(writer, model, stored)
    return dict(info or {}) | run | {"seam_difference_max": float(max(diffs)) if diffs else 0.0}


def smooth_chunked(
    model: _Model,
    source: _Source,
    out: Path,
    *,
    chunk: int = DEFAULT_CHUNK,
    burn_in: int = DEFAULT_BURN_IN,
    tol: float | None = None,
    max_burn_in: int | None = None,
    client=None,
    workers: int = 2,
    starts: str = "checkpoints",
    info: dict | None = None,
    progress: bool | None = False,
    **checkpoint_options,
) -> dict:
    """Smooth a whole recording with fixed parameters, core by core (see the module
    docstring), writing the HDF5 file ``out``; returns the run's info (also stored in the
    file's ``info`` attribute). ``starts``: ``"checkpoints"`` (default; see
    :func:`smooth_checkpointed`, which takes ``checkpoint_options``: the exact filter's
    checkpoints from a sequential forward pass, then the chunks in parallel: within ``tol``
    SDs of the exact smoother) or ``"fresh"`` (every window from its own single-frame fit
    with ``burn_in`` frames on both sides: no sequential pass, but windows reach different
    poses)."""
    if starts == "checkpoints":
        tol = CHECKPOINT_TOL if tol is None else tol
        return smooth_checkpointed(
            model, source, out, chunk=chunk, burn_in=burn_in, tol=tol, max_burn_in=max_burn_in,
            client=client, workers=workers, info=info, progress=progress, **checkpoint_options,
        )  # fmt: skip
    if starts != "fresh":
        raise ValueError(f"starts must be 'checkpoints' or 'fresh', got {starts!r}")
    if checkpoint_options:
        raise TypeError(f"{sorted(checkpoint_options)} apply to starts='checkpoints' only")
    tol = DEFAULT_TOL if tol is None else tol
    t_start = time.perf_counter()
    T = source.n_frames
    if chunk < 1 or burn_in < 1:
        raise ValueError(f"chunk and burn_in must be >= 1, got {chunk}, {burn_in}")
    max_burn_in = max(burn_in, max_burn_in if max_burn_in is not None else 8 * burn_in)
    cores = [(a, min(a + chunk, T)) for a in range(0, T, chunk)]
    n_chunks = len(cores)
    burn = [burn_in] * n_chunks
    runner = _DaskMap(model, client) if client is not None else _LocalMap(model, workers)
    try:
        writer = _H5Writer(out, T, model.skeleton, len(model.rig), chunk)
    except BaseException:
        runner.close()
        raise
    show = _on_terminal(progress)
    recomputed, disagree, seam_frames, seam_diff = 0, [], [], []
    totals: dict[str, float] = {}

    def window(k: int) -> tuple[int, int]:
        a, b = cores[k]
        return max(0, a - burn[k]), min(T, b + burn[k])

    def submit(k: int):
        w0, w1 = window(k)
        return (w0, runner.submit(*source.window(w0, w1)))

    def result(job) -> tuple[int, dict | None]:
        return job[0], job[1].result()

    try:
        depth = runner.workers + 1
        pending = {k: submit(k) for k in range(min(depth, n_chunks))}
        prev = result(pending.pop(0))
        for k in range(1, n_chunks + 1):
            if k + depth - 1 < n_chunks:
                pending[k + depth - 1] = submit(k + depth - 1)
            if k == n_chunks:
                cur = None
            else:
                cur = result(pending.pop(k))
                e = cores[k][0]
                frames = (e - 1, e)
                last = math.inf
                while True:
                    (l0, lres), (r0, rres) = prev, cur
                    diff = (
                        math.inf if lres is None or rres is None
                        else _seam_difference(lres, l0, rres, r0, frames)
                    )  # fmt: skip
                    if diff <= tol or (burn[k - 1] >= max_burn_in and burn[k] >= max_burn_in):
                        break
                    if math.isfinite(last) and diff > 0.5 * last:
                        # doubling the burn-in did not halve the difference: the windows
                        # disagree for another reason (below), not for a short burn-in
                        break
                    last = diff
                    burn[k - 1] = min(2 * burn[k - 1], max_burn_in)
                    burn[k] = min(2 * burn[k], max_burn_in)
                    recomputed += 2
                    prev, cur = result(submit(k - 1)), result(submit(k))
                seam_frames.append(e)
                seam_diff.append(diff)
                if diff > tol:
                    disagree.append(e)
            w0, lres = prev
            writer.write(*cores[k - 1], lres, w0)
            if lres is not None:
                for key, v in lres["stats"].items():
                    totals[key] = totals.get(key, 0.0) + v
            if show:
                done = cores[k - 1][1]
                print(f"\rsmoothed {done}/{T} frames", end="", file=sys.stderr, flush=True)
            prev = cur
        if show:
            print(file=sys.stderr)
        if disagree:
            warnings.warn(
                f"{len(disagree)} seam(s) between chunks disagree by more than {tol} posterior "
                f"SD (up to {max(seam_diff):.3g} SD, burn-in up to {max(burn)} frames; frames "
                f"{disagree[:5]}): windows that start elsewhere reach different poses there "
                "(a camera out, no detections, an overconfident posterior); the result near "
                "these seams depends on the chunking (docs/tracking.md, 'Long recordings')",
                stacklevel=2,
            )
        run = {
            "chunk": int(chunk), "burn_in_default": int(burn_in), "tol": float(tol),
            "max_burn_in": int(max_burn_in), "windows_recomputed": recomputed,
            "seams_disagreeing": disagree, "n_frames": T, "n_chunks": n_chunks,
            "seconds_smoothing": time.perf_counter() - t_start,
            "scheduler": "dask" if client is not None else f"threads({workers})",
            "stats": totals, "acm_rs_version": __version__,
        }  # fmt: skip
        return _close_chunked(writer, model, info, run, seam_frames, seam_diff, burn)
    except BaseException:
        writer.abort()
        raise
    finally:
        runner.close()


def smooth_checkpointed(
    model: _Model,
    source: _Source,
    out: Path,
    *,
    chunk: int = DEFAULT_CHUNK,
    burn_in: int = DEFAULT_BURN_IN,
    tol: float = CHECKPOINT_TOL,
    max_burn_in: int | None = None,
    poor_fit: float | None = 4.0,
    typical_px: float | None = None,
    restart: bool = True,
    client=None,
    workers: int = 2,
    info: dict | None = None,
    progress: bool | None = False,
) -> dict:
    """The chunked smoother started from the exact filter's checkpoints (``starts=
    "checkpoints"`` of :func:`smooth_chunked`): the forward pass of the streaming smoother
    (:func:`~acm_rs.tracking.streaming.forward_pass`, sequential, with its restarts) keeps
    the filtered moments at every chunk's start; then every chunk is filtered again from
    its checkpoint — the exact filter — over its frames and ``burn_in`` frames after them,
    and smoothed backwards from the filtered end there (in parallel: threads or Dask). Only
    that end differs from the exact smoother, whose backward pass forgets it
    geometrically: at each seam the chunk's last frames are compared with the next chunk's
    estimate (exact there up to its own far end), and the burn-in is doubled while they
    differ by more than ``tol`` posterior SDs. A chunk reaching the end of its sequence is
    the exact smoother. The next chunk's estimate stands for the exact one when it reaches
    much further than the burn-in (the default chunks of 2,000 frames do: the difference
    fell from 0.7 to 0.0007 SD between 150 and 300 frames of burn-in on the test rat).

    ``chunk``, ``burn_in``, ``max_burn_in``: frames; ``tol``: posterior SDs; ``poor_fit``,
    ``typical_px``, ``restart``: the forward pass's restarts and report, as
    :func:`~acm_rs.tracking.streaming.smooth_streaming` (``info["poor_fit"]``, a warning).
    Caveat (velocity model): a chunk with ``HINT_GAP`` frames without detections linearises
    about the random walk's posterior of its window including the burn-in, the forward pass
    about that of its segment alone; the filtered moments can then differ there, which the
    seam test measures like any other difference."""
    t_start = time.perf_counter()
    T = source.n_frames
    if chunk < 2 or burn_in < 2:
        raise ValueError(f"chunk and burn_in must be >= 2, got {chunk}, {burn_in}")
    max_burn_in = max(burn_in, max_burn_in if max_burn_in is not None else 8 * burn_in)
    show = _on_terminal(progress)
    filtered_px = np.full(T, np.nan)
    fwd = forward_pass(
        model, source, chunk, poor_fit=poor_fit, typical_px=typical_px, restart=restart,
        folder=None, filtered_px=filtered_px, show=show,
    )  # fmt: skip
    poor, limit = report_poor_fit(filtered_px, poor_fit, fwd.typical)
    segs = fwd.segments
    t_forward = time.perf_counter() - t_start
    ends, end = [0] * len(segs), T
    for k in range(len(segs) - 1, -1, -1):  # the end of each chunk's sequence
        end = segs[k].b if segs[k].last else end
        ends[k] = end
    burn = [burn_in] * len(segs)
    runner = _DaskMap(model, client) if client is not None else _LocalMap(model, workers)
    try:
        writer = _H5Writer(out, T, model.skeleton, len(model.rig), chunk)
    except BaseException:
        runner.close()
        raise
    recomputed, disagree, seam_frames, seam_diff = 0, [], [], []

    def submit(k: int):
        seg = segs[k]
        w1 = min(seg.b + burn[k], ends[k])
        return runner.submit(*source.window(seg.a, w1), prior=(seg.mu, seg.cov))

    try:
        depth = runner.workers + 1
        pending = {k: submit(k) for k in range(min(depth, len(segs)))}
        for k, seg in enumerate(segs):
            if k + depth < len(segs):
                pending[k + depth] = submit(k + depth)
            res = pending.pop(k).result()
            if not seg.last:
                # the next chunk starts at this one's end with the exact filter
                nxt = pending[k + 1].result()
                e = seg.b
                frames = [f for f in (e, e + 1) if f < segs[k + 1].b]
                while True:
                    # (no "must halve" rule here: the difference does shrink towards the
                    # sequence's end, but slowly where the posterior SD is small)
                    diff = _seam_difference(res, seg.a, nxt, e, frames)
                    reached = seg.b + burn[k] >= ends[k]
                    if diff <= tol or reached or burn[k] >= max_burn_in:
                        break
                    burn[k] = min(2 * burn[k], max_burn_in)
                    recomputed += 1
                    res = submit(k).result()
                seam_frames.append(e)
                seam_diff.append(diff)
                if diff > tol and not reached:  # (reached: this chunk is the exact smoother)
                    disagree.append(e)
            writer.write(seg.a, seg.b, res, seg.a)
            if show:
                print(f"\rsmoothed {seg.b}/{T} frames", end="", file=sys.stderr, flush=True)
        if show:
            print(file=sys.stderr)
        if disagree:
            warnings.warn(
                f"{len(disagree)} seam(s) between checkpointed chunks differ by more than {tol} "
                f"posterior SD (up to {max(seam_diff):.3g} SD, burn-in up to {max(burn)} "
                f"frames; frames {disagree[:5]})",
                stacklevel=2,
            )
        run = {
            "chunk": int(chunk), "burn_in_default": int(burn_in), "tol": float(tol),
            "max_burn_in": int(max_burn_in), "windows_recomputed": recomputed,
            "seams_disagreeing": disagree, "n_frames": T, "n_chunks": len(segs),
            "starts": "checkpoints", "restarts": fwd.restarts[:100],
            "poor_fit": poor[:100], "poor_fit_frames": sum(b - a for a, b in poor),
            "poor_fit_factor": poor_fit, "poor_fit_px": None if limit is None else float(limit),
            "typical_px": fwd.typical,
            "n_restarts": len(fwd.restarts), "seconds_forward": t_forward,
            "seconds_smoothing": time.perf_counter() - t_start,
            "scheduler": "dask" if client is not None else f"threads({workers})",
            "stats": fwd.totals, "acm_rs_version": __version__,
        }  # fmt: skip
        return _close_chunked(writer, model, info, run, seam_frames, seam_diff, burn)
    except BaseException:
        writer.abort()
        raise
    finally:
        runner.close()


# -- the whole job ----------------------------------------------------------------------------


def track_long(
    rig: CameraRig,
    skeleton: Skeleton,
    detections,
    out: str | os.PathLike,
    *,
    likelihood=None,
    pcutoff: float = 0.9,
    marker_names: Sequence[str] | None = None,
    joint_limits: bool = True,
    motion: str = DEFAULT_MOTION,
    subset: int = DEFAULT_SUBSET,
    n_windows: int = DEFAULT_WINDOWS,
    chunk: int = DEFAULT_CHUNK,
    burn_in: int = DEFAULT_BURN_IN,
    tol: float | None = None,
    max_iter: int = 100,
    ll_tol: float = DEFAULT_LL_TOL,
    gate: float | None = DEFAULT_GATE,
    relinearize: int = 10,
    normalization: Normalization | None = None,
    noise: float = DEFAULT_NOISE,
    vz_shrinkage: float = 0.8,
    method: str = "auto",
    poor_fit: float | None = 4.0,
    client=None,
    workers: int = 2,
    overwrite: bool = False,
    progress: bool | None = False,
    overrelax: float | None = DEFAULT_OVERRELAX,
) -> dict:
    """Track a recording of any length in bounded memory: Θ by EM on a subset of windows,
    then the chunked (or the exact streaming) smoother with Θ fixed, streamed to an HDF5
    file (module docstring).

    Parameters
    ----------
    detections : array_like, shape (n_cams, T, n_markers, 2)
        Pixels, NaN where missing; read one window at a time, so a ``numpy.memmap`` or an
        ``h5py``/``zarr`` dataset keeps memory bounded.
    out : path
        The HDF5 file: datasets ``joints``, ``joints_std``, ``markers``, ``markers_std``
        ``(T, ·, 3)`` in the skeleton's units, ``t (T, 3)``, ``r (T, n_bones, 3)``,
        ``status (C, T, M)`` (1 used, 2 gated, 3 invisible, 0 missing), ``params/*``,
        ``seam_frames``, ``seam_difference`` (SDs), ``burn_in`` per chunk, and the JSON
        ``info`` attribute. Written atomically.
    likelihood : array_like, shape (n_cams, T, n_markers), optional
        DeepLabCut confidences; below ``pcutoff`` is missing.
    subset, n_windows : int
        EM runs on ``n_windows`` evenly spread windows of ``subset // n_windows`` frames.
    method : {"auto", "streaming", "chunked"}
        ``"streaming"``: the exact smoother of the whole recording, from checkpointed (and,
        where the disk has room, spilled) filtered states, with restarts where the filter
        lost the animal (:mod:`acm_rs.tracking.streaming`; forward pass sequential). On the
        benches it is the more accurate and the faster one (100,000 frames, velocity:
        0.49 mm at 1,035 frames/s; 720,000 frames, random walk: 1,745 frames/s).
        ``"chunked"``: independent overlapping windows, parallel in time and on a Dask
        cluster; they differ from the exact smoother near seams (module docstring).
        ``"auto"`` (default): ``"chunked"`` with a Dask ``client``, else ``"streaming"``.
    chunk : int
        Frames per segment (streaming) or per core (chunked).
    poor_fit : float or None
        The forward pass of both methods (``"chunked"`` starts from its checkpoints):
        stretches of 10+ frames (``POOR_FRAMES``) whose filtered poses reproject further
        than this multiple of a typical frame's error (the EM windows') start a new sequence
        from a fresh single-frame fit (so do 50+ frames with > 5 % of the entries gated);
        both report them (``info["poor_fit"]``, a warning). None: neither.
    burn_in, tol : int, float or None
        Chunked only: burn-in (after each chunk; with ``starts="fresh"`` on each side), and
        the largest seam difference in posterior SDs before the burn-in is doubled (None:
        ``CHECKPOINT_TOL`` = 0.005, or ``DEFAULT_TOL`` = 0.05 for fresh starts).
    vz_shrinkage : float in [0, 1]
        Shrink the learned ``V_z`` towards its diagonal (:func:`shrink_vz`).
    client : None, str or distributed.Client
        Run the chunks on a Dask cluster (a scheduler address or a Client); the result is
        identical to the local run's. None: a local thread pool of ``workers`` threads.
    Others : as :func:`acm_rs.track` (Gaussian noise model).

    Returns
    -------
    dict
        ``path``, the motion model, the EM history and timings, seam statistics.
    """
    t_start = time.perf_counter()
    if method not in ("auto", "streaming", "chunked"):
        raise ValueError(f"method must be 'auto', 'streaming' or 'chunked', got {method!r}")
    if method == "auto":
        method = "chunked" if client is not None else "streaming"
    if method == "streaming" and client is not None:
        raise ValueError("a Dask client runs method='chunked' (the streaming smoother's "
                         "forward pass is sequential)")  # fmt: skip
    path = check_output_path(out, overwrite, "poses file")
    source = _Source(detections, likelihood)
    T = source.n_frames
    norm = normalization or default_normalization(rig, skeleton)
    check_units(rig, skeleton)
    stub = _Model(rig, skeleton, norm, joint_limits, relinearize, None, 1, {}, np.zeros((0, 0)),
                  pcutoff, marker_names)  # fmt: skip
    wins = subset_windows(T, subset, n_windows)
    windows_det = [stub.detections(*source.window(a, b)) for a, b in wins]
    first = windows_det[0]
    fit_px = check_camera_order(rig, skeleton, first, norm)
    check_scale(rig, skeleton, first)
    fit = learn_windows(
        rig, skeleton, windows_det, norm, motion=motion, joint_limits=joint_limits,
        max_iter=max_iter, ll_tol=ll_tol, gate=gate, noise=noise, relinearize=relinearize,
        progress=progress, windows=wins, workers=workers, overrelax=overrelax,
    )  # fmt: skip
    del windows_det
    rw_params = fit.extra.get("rw_params")
    model = _Model(
        rig, skeleton, norm, joint_limits, relinearize, gate_threshold(gate),
        MOTION_ORDER[fit.motion], shrink_vz(fit.params, vz_shrinkage), fit.prior_cov, pcutoff,
        marker_names, rw_params and shrink_vz(rw_params, vz_shrinkage),
        fit.extra.get("rw_prior_cov"),
    )  # fmt: skip
    info = {
        "method": "ukf-chunked", "motion": fit.motion, "motion_requested": motion,
        "motion_note": fit.motion_note, "em_windows": wins, "em_history": fit.history,
        "em_converged": fit.converged, "seconds_em": fit.seconds, "gate": gate,
        "pcutoff": pcutoff, "joint_limits": joint_limits, "relinearize": relinearize,
        "normalization": _norm_dict(norm), "check_fit_px": fit_px,
        "units": skeleton.units, "vz_shrinkage": vz_shrinkage,
        "em_window_fit_px": fit.extra["window_fit_px"],
        "em_windows_dropped": fit.extra["dropped_windows"],
        "em_typical_px": fit.extra["typical_px"],
    }  # fmt: skip
    if method == "streaming":
        info["method"] = "ukf-streaming"
        run = smooth_streaming(
            model, source, path, segment=chunk, poor_fit=poor_fit,
            typical_px=fit.extra["typical_px"], workers=workers, info=info, progress=progress,
        )  # fmt: skip
    else:
        run = smooth_chunked(
            model, source, path, chunk=chunk, burn_in=burn_in, tol=tol, client=client,
            workers=workers, info=info, progress=progress, poor_fit=poor_fit,
            typical_px=fit.extra["typical_px"],
        )  # fmt: skip
    run["path"] = str(path)
    run["seconds"] = time.perf_counter() - t_start
    return run


def track_bounded(
    rig: CameraRig,
    skeleton: Skeleton,
    detections,
    *,
    need: int,
    limit: float,
    likelihood=None,
    pcutoff: float = 0.9,
    marker_names: Sequence[str] | None = None,
    normalization: Normalization | None = None,
    progress: bool | None = False,
    **options,
) -> PoseResult:
    """:func:`acm_rs.track` of a recording too long for its in-memory EM: :func:`track_long`
    into a temporary HDF5 file, read back as a :class:`PoseResult` (no ``state_cov``; the
    state means from the poses). ``need``/``limit``: the bytes that made the choice, said in
    one warning. ``options``: :func:`track_long`'s."""
    import tempfile

    T = np.shape(detections)[1]
    warnings.warn(
        f"{T} frames would need ~{need / 2**30:.1f} GiB in memory (limit "
        f"{limit / 2**30:.1f} GiB): tracking them in bounded memory (acm_rs.track_long: EM "
        "on windows, the exact streaming smoother); memory_limit=float('inf') forces the "
        "in-memory EM",
        stacklevel=3,
    )
    norm = normalization or default_normalization(rig, skeleton)
    # EM's windows within the budget (each frame of them costs need / T), at least 1,000
    # frames each; a recording that fits whole is learned whole, and its V_z is then not
    # shrunk (shrinkage guards the transfer of Θ from windows to other frames)
    subset = int(min(DEFAULT_SUBSET, max(1000, limit * T / need)))
    options.setdefault("subset", subset)
    options.setdefault("n_windows", max(1, min(DEFAULT_WINDOWS, subset // 1000)))
    if T <= options["subset"]:
        options.setdefault("vz_shrinkage", 0.0)
    with tempfile.TemporaryDirectory(prefix="acm-rs-track-") as tmp:
        path = Path(tmp) / "poses.h5"
        run = track_long(
            rig, skeleton, detections, path, likelihood=likelihood, pcutoff=pcutoff,
            marker_names=marker_names, normalization=norm, progress=progress, **options,
        )  # fmt: skip
        arrays = read_chunked(path)
    det = _measurements(rig, skeleton, detections, likelihood, pcutoff, marker_names,
                        block=10_000)  # fmt: skip
    sm = StateMap(skeleton, norm, options.get("joint_limits", True))
    info = dict(arrays["info"]) | {
        "bounded_memory": True, "memory_needed": need, "memory_limit": limit,
        "status": arrays["status"], "markers_std": arrays["markers_std"],
        "params": arrays["params"], "converged": bool(run.get("em_converged", True)),
        "interrupted": False, "seconds": run["seconds"],
        "misfit": "off", "misfit_note": "not estimated: the bounded-memory path keeps no state "
        "covariances (markers are the skeleton's, markers_std without model misfit)",
    }  # fmt: skip
    info.setdefault("em_converged", info["converged"])
    history = list(info.get("em_history", []))
    return PoseResult(
        skeleton=skeleton, rig=rig, state_map=sm, joints=arrays["joints"],
        joints_std=arrays["joints_std"], markers=arrays["markers"], t=arrays["t"],
        r=arrays["r"], state_mean=sm.from_pose(arrays["t"], arrays["r"]), state_cov=None,
        detections=det, em_history=history, info=info,
    )  # fmt: skip


def shrink_vz(params: dict, s: float) -> dict:
    """``V_z ← (1 − s) V_z + s diag(V_z)`` (as :class:`acm_rs.OnlineTracker`): the full
    ``V_z`` learned on some frames carries their movements' correlations to the others. On
    8,000 frames smoothed with Θ from 4 × 1,000 other frames, ``s = 0.5 / 0.8 / 1`` kept the
    error at 2.2-2.9 mm where ``s = 0`` drifted from 3 to 5.5 mm (gated detections piling
    up; docs/tracking.md)."""
    if not 0.0 <= s <= 1.0:
        raise ValueError(f"vz_shrinkage must be in [0, 1], got {s}")
    vz = np.asarray(params["Vz"])
    return dict(params) | {"Vz": (1.0 - s) * vz + s * np.diag(np.diag(vz))}
