"""Diagnostic figures of a tracking result (:class:`acm_rs.tracking.PoseResult`).

Every function returns a :class:`matplotlib.figure.Figure` (headless Agg backend); write it with
:func:`save_figure` (PNG, optional PDF, atomically) or all of them at once with :func:`plot_all`.
Lengths are in ``result.skeleton.units``, image coordinates in pixels, angles in degrees.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._io import atomic_write
from ..plotting import _pyplot, draw_skeleton_2d

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure

    from ..skeleton import Skeleton
    from ..tracking import PoseResult

#: Values of ``result.info["status"]`` (n_cams, T, M) written by :func:`acm_rs.track`.
STATUS_MISSING, STATUS_USED, STATUS_GATED, STATUS_UNPREDICTABLE = 0, 1, 2, 3

#: Default number of joints in :func:`joint_traces` when ``joints`` is None.
MAX_DEFAULT_JOINTS = 6

_FIGURES = (
    "reprojection_histograms",
    "joint_traces",
    "joint_angle_traces",
    "skeleton_snapshots",
    "em_convergence",
)


# -- helpers -----------------------------------------------------------------------------------
def save_figure(
    fig: Figure, path: str | Path, pdf: bool = False, *, dpi: int = 120, close: bool = True
) -> list[Path]:
    """Write ``<path>.png`` (and ``<path>.pdf``) atomically.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
    path : str or Path
        Output path without suffix; a ``.png`` or ``.pdf`` suffix is stripped, any other
        suffix is kept as part of the name (``run.v2`` -> ``run.v2.png``).
    pdf : bool
        Also write a vector PDF.
    dpi : int
        Resolution of the PNG (dots per inch).
    close : bool
        Close the figure afterwards (frees its memory in long batch runs).

    Returns
    -------
    list of Path
        The files written, PNG first.
    """
    p = Path(path)
    if p.suffix.lower() in (".png", ".pdf"):
        p = p.with_suffix("")
    written = []
    for fmt in ("png", "pdf") if pdf else ("png",):
        target = p.with_name(f"{p.name}.{fmt}")
        with atomic_write(target, "wb") as fh:
            fig.savefig(fh, format=fmt, dpi=dpi)
        written.append(target)
    if close:
        _pyplot().close(fig)
    return written


def _status(result: PoseResult) -> np.ndarray:
    """(n_cams, T, M) status; without ``info["status"]`` every finite detection counts as used."""
    status = result.info.get("status")
    if status is not None:
        return np.asarray(status)
    finite = np.isfinite(result.detections).all(axis=-1)
    return np.where(finite, STATUS_USED, STATUS_MISSING).astype(np.uint8)


def _time_axis(n_frames: int, frame_rate: float | None) -> tuple[np.ndarray, str]:
    if frame_rate is None:
        return np.arange(n_frames, dtype=float), "frame"
    if not frame_rate > 0:
        raise ValueError(f"frame_rate must be > 0 (frames per second), got {frame_rate}")
    return np.arange(n_frames) / float(frame_rate), "time (s)"


def _indices(names: Sequence[str], wanted: Sequence[str | int], what: str) -> list[int]:
    out = []
    for w in wanted:
        if isinstance(w, (int, np.integer)):
            if not 0 <= int(w) < len(names):
                raise ValueError(f"{what} index {w} out of range [0, {len(names)})")
            out.append(int(w))
        elif w in names:
            out.append(list(names).index(w))
        else:
            raise ValueError(f"unknown {what} {w!r}; known {what}s: {list(names)}")
    if not out:
        raise ValueError(f"select at least one {what}")
    return out


def _grid(n: int, ncols: int) -> tuple[int, int]:
    cols = max(1, min(n, ncols))
    return int(np.ceil(n / cols)), cols


# -- 1. reprojection error ---------------------------------------------------------------------
def reprojection_histograms(result: PoseResult, bins: int = 40) -> Figure:
    """Histogram of the reprojection error per camera (one panel per camera).

    Errors (px) are distances between detections and the markers of the posterior mean pose
    projected into the camera (:meth:`PoseResult.reprojection_error`). Detections the tracker
    used (``info["status"] == 1``) are drawn in blue with their median and 95th percentile as
    vertical lines; outliers rejected by the innovation gate (status 2) in red. The x axis is
    logarithmic with ``bins`` bins shared by all panels; errors outside its range are counted in
    the first or last bin, so each histogram's counts sum to its number of detections.

    Parameters
    ----------
    result : PoseResult
        Tracking result; without ``info["status"]`` (``method="deterministic"``) every finite
        detection counts as used.
    bins : int
        Number of logarithmic bins.

    Returns
    -------
    matplotlib.figure.Figure
        ``n_cams`` axes; on each, ``ax.containers[0]`` holds the used and ``ax.containers[1]``
        (if any) the gated detections' bars.
    """
    plt = _pyplot()
    err = result.reprojection_error()  # (C, T, M)
    status = _status(result)
    ok = np.isfinite(err)
    used_all = ok & (status == STATUS_USED)
    gated_all = ok & (status == STATUS_GATED)
    shown = err[used_all | gated_all]
    if shown.size:
        lo = max(float(np.min(shown)), 1e-2)
        hi = max(float(np.max(shown)), lo * 10)
    else:
        lo, hi = 1e-2, 1e2
    edges = np.geomspace(lo, hi, bins + 1)
    n = len(result.rig)
    rows, cols = _grid(n, 2)
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 3.6 * rows), squeeze=False)
    for i, cam in enumerate(result.rig):
        ax = axes.flat[i]
        used = np.clip(err[i][used_all[i]], lo, hi)
        gated = np.clip(err[i][gated_all[i]], lo, hi)
        ax.hist(used, bins=edges, color="tab:blue", alpha=0.8, label=f"used (n={used.size})")
        if gated.size:
            ax.hist(gated, bins=edges, color="tab:red", alpha=0.7, label=f"gated (n={gated.size})")
        if used.size:
            med, p95 = np.percentile(err[i][used_all[i]], [50, 95])
            ax.axvline(med, color="k", lw=1.2, label=f"median {med:.2f} px")
            ax.axvline(p95, color="k", lw=1.2, ls="--", label=f"95th pct {p95:.2f} px")
        ax.set_xscale("log")
        ax.set_xlabel("reprojection error (px)")
        ax.set_ylabel("detections")
        ax.set_title(cam.name or f"camera {i}")
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    for j in range(n, rows * cols):
        axes.flat[j].remove()
    fig.tight_layout()
    return fig


# -- 2. joint traces ---------------------------------------------------------------------------
def _default_joints(skeleton: Skeleton) -> list[int]:
    """The root and the leaf joints (paws, tail tip, ...), at most MAX_DEFAULT_JOINTS."""
    parents = skeleton.parents
    leaves = [j for j in range(skeleton.n_joints) if j not in set(parents.tolist())]
    roots = [int(j) for j in np.flatnonzero(parents < 0)]
    return (roots + leaves)[:MAX_DEFAULT_JOINTS]


def joint_traces(
    result: PoseResult,
    joints: Sequence[str | int] | None = None,
    frame_rate: float | None = None,
) -> Figure:
    """x, y, z of selected joints over time with posterior mean ± 2 std bands.

    Parameters
    ----------
    result : PoseResult
        Uses ``joints`` (T, J, 3) and ``joints_std`` (T, J, 3), in ``skeleton.units``.
    joints : sequence of str or int, optional
        Joint names or indices (default: the root and the leaf joints, at most
        :data:`MAX_DEFAULT_JOINTS`).
    frame_rate : float, optional
        Frames per second; the time axis is in seconds if given, in frames otherwise.

    Returns
    -------
    matplotlib.figure.Figure
        ``len(joints)`` rows by 3 columns (x, y, z); on each axis ``lines[0]`` is the mean and
        ``collections[0]`` the band from mean - 2 std to mean + 2 std.
    """
    plt = _pyplot()
    sk = result.skeleton
    idx = _default_joints(sk) if joints is None else _indices(sk.joint_names, joints, "joint")
    time, xlabel = _time_axis(result.n_frames, frame_rate)
    fig, axes = plt.subplots(
        len(idx), 3, figsize=(12, 1.9 * len(idx) + 0.8), sharex=True, squeeze=False
    )
    for row, j in enumerate(idx):
        for a in range(3):
            ax = axes[row, a]
            mean = result.joints[:, j, a]
            std = result.joints_std[:, j, a]
            ax.plot(time, mean, color=f"C{a}", lw=1.2)
            ax.fill_between(time, mean - 2 * std, mean + 2 * std, color=f"C{a}", alpha=0.3, lw=0)
            ax.set_ylabel(f"{sk.joint_names[j]}\n{'xyz'[a]} ({sk.units})", fontsize=8)
            ax.grid(alpha=0.3)
            if row == 0:
                ax.set_title(f"{'xyz'[a]} (mean ± 2 std)")
    for ax in axes[-1]:
        ax.set_xlabel(xlabel)
    fig.tight_layout()
    return fig


# -- 3. joint angles ---------------------------------------------------------------------------
def bone_angles(
    joints: np.ndarray, parents: Sequence[int] | np.ndarray, ends: Sequence[int] | None = None
) -> tuple[np.ndarray, list[int]]:
    """Flexion angle of bones relative to their parent bone, in degrees.

    A bone is identified by its end joint ``e``; it runs from ``s = parents[e]`` to ``e``. Its
    parent bone runs from ``g = parents[s]`` to ``s``. The angle is the one between the two bone
    directions, ``arccos(<s - g, e - s> / (|s - g| |e - s|))``: 0° when the bone continues its
    parent in a straight line, 90° at a right angle, 180° when folded back. It is independent of
    the bone's twist and of the skeleton's rest pose. Bones starting at the root have no parent
    bone and have no angle.

    Parameters
    ----------
    joints : array_like, shape (T, J, 3) or (J, 3)
        Joint positions.
    parents : array_like of int, shape (J,)
        Parent joint per joint, -1 for the root (``Skeleton.parents``).
    ends : sequence of int, optional
        End joints of the bones to measure (default: every joint whose parent is not a root).

    Returns
    -------
    angles : numpy.ndarray, shape (T, len(ends)) or (len(ends),)
        Degrees in [0, 180]; NaN where a bone has zero length or a position is not finite.
    ends : list of int
        The end joints, in the order of the columns.

    Raises
    ------
    ValueError
        A requested bone starts at the root (it has no parent bone) or an index is invalid.
    """
    pts = np.asarray(joints, dtype=np.float64)
    par = np.asarray(parents, dtype=np.int64)
    single = pts.ndim == 2
    if single:
        pts = pts[None]
    if pts.ndim != 3 or pts.shape[1:] != (len(par), 3):
        raise ValueError(f"joints must have shape (T, {len(par)}, 3), got {np.shape(joints)}")
    if ends is None:
        ends = [e for e in range(len(par)) if par[e] >= 0 and par[par[e]] >= 0]
    ends = [int(e) for e in ends]
    for e in ends:
        if not 0 <= e < len(par):
            raise ValueError(f"joint index {e} out of range [0, {len(par)})")
        if par[e] < 0 or par[par[e]] < 0:
            raise ValueError(f"joint {e} ends a bone without a parent bone (no angle defined)")
    e = np.array(ends, dtype=np.int64)
    s = par[e]
    g = par[s]
    child = pts[:, e] - pts[:, s]
    parent = pts[:, s] - pts[:, g]
    norms = np.linalg.norm(child, axis=-1) * np.linalg.norm(parent, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = np.einsum("tbi,tbi->tb", child, parent) / norms
    cos[~(norms > 0)] = np.nan
    angles = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return (angles[0] if single else angles), ends


def joint_angle_traces(
    result: PoseResult,
    bones: Sequence[str | int] | None = None,
    frame_rate: float | None = None,
) -> Figure:
    """Flexion angle of each selected bone relative to its parent bone over time.

    The angle is defined in :func:`bone_angles` (0° = straight continuation of the parent
    bone, 90° = right angle), computed from the posterior mean joints ``result.joints``.

    Parameters
    ----------
    result : PoseResult
    bones : sequence of str or int, optional
        Bones by name (= the name of their end joint, ``Skeleton.bone_names``) or bone index
        (row of ``Skeleton.bones``). Default: every bone that has a parent bone and a
        rotation not fixed by its joint limits.
    frame_rate : float, optional
        Frames per second; the time axis is in seconds if given, in frames otherwise.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per bone (4 columns); ``ax.lines[0]`` holds the angles (degrees).
    """
    plt = _pyplot()
    sk = result.skeleton
    if bones is None:
        # every bone with a parent bone whose rotation is free (fixed bones give constants)
        lim = sk.joint_limits
        fixed = np.all(lim[..., 0] == lim[..., 1], axis=1)  # (n_bones,)
        ends = [
            int(e)
            for b, e in enumerate(sk.bones[:, 1])
            if not fixed[b] and sk.parents[sk.parents[e]] >= 0
        ]
    else:
        ends = [int(sk.bones[b, 1]) for b in _indices(sk.bone_names, bones, "bone")]
    angles, ends = bone_angles(result.joints, sk.parents, ends)
    time, xlabel = _time_axis(result.n_frames, frame_rate)
    rows, cols = _grid(len(ends), 4)
    fig, axes = plt.subplots(
        rows, cols, figsize=(3.4 * cols, 2.1 * rows + 0.6), sharex=True, squeeze=False
    )
    for k, e in enumerate(ends):
        ax = axes.flat[k]
        ax.plot(time, angles[:, k], color="tab:purple", lw=1.2)
        finite = angles[:, k][np.isfinite(angles[:, k])]
        if finite.size and np.ptp(finite) < 5.0:  # no rounding noise blown up to full height
            mid = 0.5 * (finite.min() + finite.max())
            ax.set_ylim(mid - 2.5, mid + 2.5)
        ax.set_title(f"{sk.joint_names[e]} vs {sk.joint_names[sk.parents[e]]}", fontsize=8)
        ax.grid(alpha=0.3)
        if k % cols == 0:
            ax.set_ylabel("angle (deg)")
        if k >= len(ends) - cols:
            ax.set_xlabel(xlabel)
    for j in range(len(ends), rows * cols):
        axes.flat[j].remove()
    fig.tight_layout()
    return fig


# -- 4. skeleton snapshots ---------------------------------------------------------------------
def skeleton_snapshots(result: PoseResult, frames: Sequence[int] | None = None) -> Figure:
    """The 3D skeleton at a few frames seen from the top (x-y) and the side (x-z).

    Bones are coloured by side (left red, right blue, centre grey, as
    :func:`acm_rs.plotting.draw_skeleton_2d`), joints black, markers green. All panels share
    their limits and have an equal aspect, so sizes and positions are comparable.

    Parameters
    ----------
    result : PoseResult
        Uses ``joints`` (T, J, 3) and ``markers`` (T, M, 3), in ``skeleton.units``.
    frames : sequence of int, optional
        Frame indices (default: 4 evenly spaced frames including the first and the last).

    Returns
    -------
    matplotlib.figure.Figure
        2 rows (top, side) by ``len(frames)`` columns.
    """
    plt = _pyplot()
    sk = result.skeleton
    n = result.n_frames
    if frames is None:
        frames = np.unique(np.linspace(0, n - 1, min(4, n)).round().astype(int)).tolist()
    frames = [int(f) for f in frames]
    if not frames:
        raise ValueError("select at least one frame")
    for f in frames:
        if not -n <= f < n:
            raise ValueError(f"frame {f} out of range for {n} frames")
    pts = np.concatenate([result.joints[frames], result.markers[frames]], axis=1).reshape(-1, 3)
    pts = pts[np.isfinite(pts).all(axis=1)]
    lo, hi = (pts.min(axis=0), pts.max(axis=0)) if len(pts) else (np.zeros(3), np.ones(3))
    pad = 0.05 * max(float(np.max(hi - lo)), 1e-9)
    fig, axes = plt.subplots(2, len(frames), figsize=(3.6 * len(frames) + 0.5, 6.8), squeeze=False)
    views = [((0, 1), "top (x-y)"), ((0, 2), "side (x-z)")]
    for row, ((a, b), label) in enumerate(views):
        for col, f in enumerate(frames):
            ax = axes[row, col]
            draw_skeleton_2d(ax, sk, result.joints[f][:, [a, b]], result.markers[f][:, [a, b]])
            ax.set_xlim(lo[a] - pad, hi[a] + pad)
            ax.set_ylim(lo[b] - pad, hi[b] + pad)
            ax.set_aspect("equal")
            ax.set_title(f"frame {f % n}, {label}", fontsize=9)
            ax.set_xlabel(f"{'xyz'[a]} ({sk.units})")
            ax.set_ylabel(f"{'xyz'[b]} ({sk.units})")
            ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


# -- 5. EM convergence -------------------------------------------------------------------------
def em_convergence(result: PoseResult) -> Figure:
    """EM progress: what the stop rule watched per iteration, and wall time per iteration.

    Parameters
    ----------
    result : PoseResult
        Uses ``em_history`` (``iteration``, ``seconds``; ``log_likelihood`` and ``rejected``
        under the default ``stop="loglik"``, else ``delta``) and ``info["stop"]``,
        ``info["tol"]``.

    Returns
    -------
    matplotlib.figure.Figure
        Two axes. Under ``stop="loglik"`` (with the log-likelihoods in the history): the
        marginal log-likelihood (nats) of each iteration kept (``lines[0]``) and, as red
        crosses, the over-relaxed steps replaced by the plain one (``lines[1]``, if any).
        Otherwise Alg. 13's Δ (log axis, ``lines[0]``, one point per iteration) with the
        tolerance as a dashed line. Then seconds per iteration as bars.

    Raises
    ------
    ValueError
        The result has no EM history (``method="deterministic"``).
    """
    if not result.em_history:
        raise ValueError("this result has no EM history (method='deterministic'); nothing to plot")
    plt = _pyplot()
    it = np.array([h["iteration"] for h in result.em_history], dtype=float)
    delta = np.array([h["delta"] for h in result.em_history], dtype=float)
    secs = np.array([h["seconds"] for h in result.em_history], dtype=float)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    hist = result.em_history
    if result.info.get("stop", "loglik") == "loglik" and all("log_likelihood" in h for h in hist):
        ll = np.array([h["log_likelihood"] for h in hist], dtype=float)
        rej = np.array([bool(h.get("rejected")) for h in hist])
        ax1.plot(it[~rej], ll[~rej], "o-", color="tab:blue", label="marginal log-likelihood")
        if rej.any():
            ax1.plot(it[rej], ll[rej], "x", color="tab:red", label="over-relaxed step, replaced")
        ax1.set_ylabel("log-likelihood (nats)")
    else:
        ax1.plot(it, delta, "o-", color="tab:blue", label="Δ (mean relative change)")
        tol = result.info.get("tol")
        if tol is not None:
            ax1.axhline(tol, color="tab:red", ls="--", label=f"tolerance {tol:g}")
        ax1.set_yscale("log")
        ax1.set_ylabel("Δ")
    ax1.set_xlabel("EM iteration")
    state = "converged" if result.info.get("converged") else "not converged"
    ax1.set_title(f"convergence ({state})")
    ax1.legend(fontsize=8)
    ax1.grid(alpha=0.3, which="both")
    ax2.bar(it, secs, color="tab:gray")
    ax2.set_xlabel("EM iteration")
    ax2.set_ylabel("seconds")
    ax2.set_title(f"time per iteration (total {secs.sum():.2f} s)")
    ax2.grid(alpha=0.3, axis="y")
    for ax in (ax1, ax2):
        ax.xaxis.get_major_locator().set_params(integer=True)
    fig.tight_layout()
    return fig


# -- 7. everything -----------------------------------------------------------------------------
def plot_all(
    result: PoseResult,
    out_dir: str | Path,
    pdf: bool = False,
    *,
    frame_rate: float | None = None,
) -> list[Path]:
    """Write every figure of this module into ``out_dir`` (not the overlay video).

    File names are stable: ``reprojection_histograms``, ``joint_traces``,
    ``joint_angle_traces``, ``skeleton_snapshots`` and ``em_convergence`` (the last only when
    the result has an EM history), each ``.png`` and, with ``pdf``, ``.pdf``.

    Parameters
    ----------
    result : PoseResult
    out_dir : str or Path
        Folder, created if needed.
    pdf : bool
        Also write PDFs.
    frame_rate : float, optional
        Frames per second for the time axes (frames if None).

    Returns
    -------
    list of Path
        The files written.
    """
    out = Path(out_dir)
    makers = {
        "reprojection_histograms": lambda: reprojection_histograms(result),
        "joint_traces": lambda: joint_traces(result, frame_rate=frame_rate),
        "joint_angle_traces": lambda: joint_angle_traces(result, frame_rate=frame_rate),
        "skeleton_snapshots": lambda: skeleton_snapshots(result),
        "em_convergence": lambda: em_convergence(result),
    }
    written: list[Path] = []
    for name in _FIGURES:
        if name == "em_convergence" and not result.em_history:
            continue
        written += save_figure(makers[name](), out / name, pdf=pdf)
    return written
