"""Learning the animal's skeleton and fitting poses (ACM supplement sections 3.2-3.4, 4.7).

:func:`learn_skeleton` minimises eq. 9 with the symmetric parameterisation of eq. 12 (reduced
bone lengths ``l*`` and marker offsets ``v*``, Alg. 2-3) jointly with every frame's pose, by
Levenberg-Marquardt in Rust on the exact Jacobian (the per-frame pose blocks eliminated by the
Schur complement, as in bundle adjustment; ``learning/lm.rs``). Poses are normalised as in
sec. 3.3 (``t / c_t``, ``r / c_r``); joint-angle limits (Supp. Table 1), marker box
constraints (sec. 6) and bone-length priors (Supp. Table 2) are box bounds. The authors'
optimiser, ``scipy.optimize.minimize(method="L-BFGS-B")`` on the value and exact gradient from
Rust, runs first when ``rounds > 0`` (it stalls in this problem's flat valleys,
``docs/models.md``).

Steps: (1) a robust initial pose per frame without user input: triangulate the labelled markers
(DLT on undistorted points), then align the generic model (rotations at the middle of their
limits) to them by iteratively reweighted Kabsch; (2) refine all poses with the generic skeleton
fixed; (3) estimate the animal's size from the labels; (4) learn lengths, offsets and poses
together, and multi-start the frames that stay off.

:func:`fit_pose` is the first-pose fit of sec. 4.7 (eq. 9 for one frame, ``l`` and ``v`` fixed)
that initialises the tracker's ``mu_0``.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import minimize

from . import _native
from ._arrays import as_float_array
from ._io import atomic_write
from .camera import CameraRig
from .labels import labels_in_skeleton_order as _labels_in_skeleton_order
from .labels import mask_by_likelihood, match_marker_names
from .rotation import rodrigues, rodrigues_inverse
from .skeleton import Skeleton
from .state import Normalization

__all__ = [
    "LBFGSB_DEFAULTS",
    "LearnedSkeleton",
    "fit_pose",
    "initial_poses",
    "learn_skeleton",
    "match_marker_names",
    "triangulate",
]

#: The authors' L-BFGS-B settings (overridable through ``options=``).
LBFGSB_DEFAULTS: dict[str, float | int] = {
    "maxcor": 100,
    "maxls": 200,
    "ftol": 2.0**-23,
    "gtol": 1e-10,
    "maxiter": 5000,
    "maxfun": 20000,
}


# -- initial guess --------------------------------------------------------------------------
def triangulate(rig: CameraRig, points_2d: np.ndarray, min_views: int = 2) -> np.ndarray:
    """Linear (DLT) triangulation of undistorted 2D points from every camera that sees them.

    Parameters
    ----------
    rig : CameraRig
    points_2d : array_like, shape (n_cams, ..., 2)
        Pixels, NaN where a point is not seen.
    min_views : int
        Points seen in fewer cameras stay NaN.

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        World coordinates (NaN where not triangulated).
    """
    pts = as_float_array(points_2d, "points_2d", (None, 2), finite=False)
    if pts.shape[0] != len(rig):
        raise ValueError(f"points_2d has {pts.shape[0]} cameras, the rig {len(rig)}")
    lead = pts.shape[1:-1]
    flat = pts.reshape(len(rig), -1, 2)
    n = flat.shape[1]
    a = np.zeros((n, 2 * len(rig), 4))
    for c, cam in enumerate(rig):
        ok = np.all(np.isfinite(flat[c]), axis=1)
        if not ok.any():
            continue
        # OpenCV ignores a skew: remove it from the pixels first (exact; no-op without skew)
        seen = cam.skew_free_pixels(flat[c, ok]).reshape(-1, 1, 2)
        und = cv2.undistortPoints(seen, cam.opencv_matrix, cam.dist).reshape(-1, 2)
        proj = np.hstack([cam.rotation_matrix, cam.tvec[:, None]])
        a[ok, 2 * c] = und[:, :1] * proj[2] - proj[0]
        a[ok, 2 * c + 1] = und[:, 1:] * proj[2] - proj[1]
    views = np.sum(np.all(np.isfinite(flat), axis=2), axis=0)
    out = np.full((n, 3), np.nan)
    good = views >= min_views
    if good.any():
        _, _, vt = np.linalg.svd(a[good])
        h = vt[:, -1]
        with np.errstate(divide="ignore", invalid="ignore"):
            out[good] = h[:, :3] / h[:, 3:]
    return out.reshape(lead + (3,))


def _kabsch(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation minimising sum w |R x + t - y|^2 (proper rotation)."""
    w = w / w.sum()
    mx, my = w @ x, w @ y
    h = (x - mx).T @ ((y - my) * w[:, None])
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rot, my - rot @ mx


def initial_poses(
    rig: CameraRig,
    skeleton: Skeleton,
    labels: np.ndarray,
    normalization: Normalization | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Rough per-frame poses from labels, without user input.

    Triangulates the labelled markers and aligns the generic model (every limited rotation at
    the middle of its range) to them with iteratively reweighted Kabsch (central markers
    weigh more than limb markers). Frames with fewer than 3 triangulated markers take the
    median rotation of the others and the centroid of what they have.

    Parameters
    ----------
    labels : array_like, shape (n_cams, n_frames, M, 2)

    Returns
    -------
    t : numpy.ndarray, shape (n_frames, 3)
    r : numpy.ndarray, shape (n_frames, n_bones, 3)
    """
    sm = skeleton.state_map(normalization, joint_limits=True)
    _, r_mid = sm.to_pose(np.zeros(sm.n_state))
    _, neutral = skeleton.forward(np.zeros(3), r_mid)  # root at the origin
    pts = triangulate(rig, labels)  # (F, M, 3)
    n_frames = pts.shape[0]
    paired = {m for pair in skeleton.symmetry.get("markers", []) for m in pair}
    base_w = np.array([0.3 if n in paired else 1.0 for n in skeleton.marker_names])
    rots = np.full((n_frames, 3, 3), np.nan)
    ts = np.full((n_frames, 3), np.nan)
    for f in range(n_frames):
        ok = np.all(np.isfinite(pts[f]), axis=1)
        if ok.sum() < 3:
            continue
        x, y, w = neutral[ok], pts[f, ok], base_w[ok]
        for _ in range(5):
            rot, t = _kabsch(x, y, w)
            res = np.linalg.norm(x @ rot.T + t - y, axis=1)
            s = max(np.median(res), 1e-9)
            w = base_w[ok] / np.maximum(1.0, res / (2.0 * s))  # Huber-like downweighting
        rots[f], ts[f] = rot, t
    aligned = np.isfinite(ts[:, 0])
    if not aligned.any():
        raise ValueError(
            "no frame has 3 markers labelled in at least 2 cameras; cannot place the model"
        )
    r0_med = rodrigues(np.median(rodrigues_inverse(rots[aligned]), axis=0))
    for f in np.flatnonzero(~aligned):
        ok = np.all(np.isfinite(pts[f]), axis=1)
        rots[f] = r0_med
        centre = pts[f, ok].mean(axis=0) if ok.any() else np.median(ts[aligned], axis=0)
        ts[f] = centre - r0_med @ (neutral[ok].mean(axis=0) if ok.any() else neutral.mean(0))
    # The whole body turned by the Kabsch rotation (every root bone's rotation composed with it).
    return ts, skeleton.turned(np.repeat(r_mid[None], n_frames, axis=0), rots)


# -- the optimisation -----------------------------------------------------------------------
def _reduced_indices(skeleton: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the central + left bones and markers in Alg. 2-3 order."""
    sym = skeleton.symmetry
    right_bones = {skeleton.bone_index(r) for _, r in sym.get("joints", [])}
    right_markers = {skeleton.marker_index(r) for _, r in sym.get("markers", [])}
    bones = np.array([b for b in range(skeleton.n_bones) if b not in right_bones], dtype=int)
    markers = np.array([k for k in range(skeleton.n_markers) if k not in right_markers], dtype=int)
    return bones, markers


def _pairs(skeleton: Skeleton, symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    if not symmetric:
        return np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64)
    sym = skeleton.symmetry
    bp = [(skeleton.bone_index(a), skeleton.bone_index(b)) for a, b in sym.get("joints", [])]
    mp = [(skeleton.marker_index(a), skeleton.marker_index(b)) for a, b in sym.get("markers", [])]
    return np.array(bp, np.int64).reshape(-1, 2), np.array(mp, np.int64).reshape(-1, 2)


def _pose_bounds(
    skeleton: Skeleton, norm: Normalization
) -> list[tuple[float | None, float | None]]:
    lim = skeleton.joint_limits.reshape(-1, 2)
    free = ~skeleton.fixed_pose_mask
    out: list[tuple[float | None, float | None]] = [(None, None)] * 3
    for lo, hi in lim[free[3:]]:
        out.append(
            (
                lo / norm.rotation if np.isfinite(lo) else None,
                hi / norm.rotation if np.isfinite(hi) else None,
            )
        )
    return out


def _to_state(t: np.ndarray, r: np.ndarray, skeleton: Skeleton, norm: Normalization) -> np.ndarray:
    pose = np.concatenate([t / norm.translation, r.reshape(len(t), -1) / norm.rotation], axis=1)
    return pose[:, ~skeleton.fixed_pose_mask]


def _clip_to_bounds(
    x: np.ndarray, bounds: Sequence[tuple[float | None, float | None]]
) -> np.ndarray:
    return np.clip(x, *_bound_arrays(bounds))


class _Progress:
    """Iteration counter for L-BFGS-B with an optional tqdm bar."""

    def __init__(self, enabled: bool | None, desc: str, total: int) -> None:
        self.values: list[float] = []
        self.bar = None
        if enabled is not False:
            try:
                from tqdm.auto import tqdm

                # disable=None: a bar only when stderr is a terminal
                self.bar = tqdm(
                    total=total, desc=desc, unit="it", leave=False,
                    disable=None if enabled is None else False,
                )  # fmt: skip
            except ImportError:  # pragma: no cover - tqdm is a dependency
                self.bar = None

    def __call__(self, intermediate_result) -> None:
        self.values.append(float(intermediate_result.fun))
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(rms_px=f"{np.sqrt(max(self.values[-1], 0.0)):.3f}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _minimize(
    problem: _native.NativeLearning,
    x0: np.ndarray,
    bounds: list,
    scale: float,
    options: dict,
    progress: bool | None,
    desc: str,
):
    """L-BFGS-B on ``scale * f`` with Jacobi preconditioning.

    The variables are rescaled, ``x = y / d`` with ``d_i`` the square root of the Gauss-Newton
    Hessian diagonal at ``x0`` (computed exactly in Rust), so that L-BFGS-B starts from a
    well-conditioned problem; bounds are rescaled with them. The minimiser is unchanged.
    """
    diag = problem.gauss_newton_diagonal(x0)
    d = np.sqrt(2.0 * scale / problem.n_labels * diag)
    positive = d[d > 0]
    fill = float(np.median(positive)) if positive.size else 1.0
    d = np.where(d > 1e-9 * fill, d, fill)

    def fun(y: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = problem.value_and_grad(y / d)
        return f * scale, g * (scale / d)

    y_bounds = [
        (None if lo is None else lo * di, None if hi is None else hi * di)
        for (lo, hi), di in zip(bounds, d, strict=True)
    ]
    prog = _Progress(progress, desc, int(options.get("maxiter", 5000)))
    try:
        res = minimize(
            fun, x0 * d, jac=True, method="L-BFGS-B", bounds=y_bounds, options=options,
            callback=prog,
        )  # fmt: skip
    finally:
        prog.close()
    res.x = np.clip(res.x / d, *_bound_arrays(bounds))
    return res, prog.values


def _bound_arrays(bounds: Sequence[tuple[float | None, float | None]]):
    lo = np.array([-np.inf if b[0] is None else b[0] for b in bounds])
    hi = np.array([np.inf if b[1] is None else b[1] for b in bounds])
    return lo, hi


@dataclass
class LearnedSkeleton:
    """Result of :func:`learn_skeleton`.

    Attributes
    ----------
    skeleton : Skeleton
        The generic model with the learned bone lengths and marker offsets.
    t : numpy.ndarray, shape (n_frames, 3)
        Per-frame translations (world units).
    r : numpy.ndarray, shape (n_frames, n_bones, 3)
        Per-frame bone rotations (rad).
    labels, projected : numpy.ndarray, shape (n_cams, n_frames, M, 2)
        The labels (skeleton marker order) and the learned model's reprojections (px).
    errors : numpy.ndarray, shape (n_cams, n_frames, M)
        Reprojection error per label (px), NaN where unlabelled.
    info : dict
        Optimiser outcome per stage (``success``, ``message``, ``nit``, ``fun``, ``seconds``)
        and the objective history.
    """

    skeleton: Skeleton
    t: np.ndarray
    r: np.ndarray
    labels: np.ndarray
    projected: np.ndarray
    errors: np.ndarray
    rig: CameraRig
    generic: Skeleton
    info: dict = field(default_factory=dict)

    @property
    def rms(self) -> float:
        """Root-mean-square reprojection error over all labels (px)."""
        e = self.errors[np.isfinite(self.errors)]
        return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")

    @property
    def per_marker_error(self) -> np.ndarray:
        """(M,) mean reprojection error per marker (px; NaN if never labelled)."""
        with np.errstate(invalid="ignore"):
            return np.nanmean(np.where(np.isfinite(self.errors), self.errors, np.nan), axis=(0, 1))

    @property
    def per_camera_error(self) -> np.ndarray:
        """(n_cams,) mean reprojection error per camera (px)."""
        return np.nanmean(self.errors.reshape(len(self.rig), -1), axis=1)

    def diagnostics(self, outlier_sigma: float = 5.0) -> dict:
        """What a user should look at before trusting the learned skeleton.

        Returns
        -------
        dict
            ``bones_on_bounds``: ``[(bone, length, bound)]`` bones that ended on a bound of
            their length (an anatomical prior, or the [0.2, 5] x generic box of free bones;
            right-side copies omitted); ``offsets_on_bounds``: ``[(marker, axis, value)]``
            offsets pushed against a box wall (sec. 6) that is not a fixed component;
            ``off_proportions``: ``[(bone, length, expected)]`` free bones more than 50 %
            away from the generic proportions at the fitted size (a joint that slid along a
            weakly determined chain); ``noise_px``: the label noise SD estimated from the
            median error (2D Gaussian); ``outliers``: ``[(camera, frame, marker, error_px)]``
            labels above ``outlier_sigma`` x that noise (and 0.5 px), worst first.
        """
        sk = self.skeleton
        out: dict = {"bones_on_bounds": [], "offsets_on_bounds": [], "off_proportions": []}
        right = {r for _, r in sk.symmetry.get("joints", [])}
        bounds = self.info.get("length_bounds")
        if bounds is not None:
            for b, (name, length) in enumerate(zip(sk.bone_names, sk.bone_lengths, strict=True)):
                lo, hi = bounds[b]
                if name in right or not lo < hi:
                    continue
                for bound in (lo, hi):
                    if abs(length - bound) <= 1e-6 * (1.0 + abs(bound)):
                        out["bones_on_bounds"].append((name, float(length), float(bound)))
        right_m = {r for _, r in sk.symmetry.get("markers", [])}
        mb, off = sk.marker_bounds, sk.marker_offsets
        for k, name in enumerate(sk.marker_names):
            if name in right_m:
                continue
            for a in range(3):
                lo, hi = mb[k, a]
                if not lo < hi:
                    continue
                for bound in (lo, hi):
                    if np.isfinite(bound) and abs(off[k, a] - bound) <= 1e-6:
                        out["offsets_on_bounds"].append((name, "xyz"[a], float(off[k, a])))
        for name, expected in self.info.get("length_prior", {}).items():
            length = float(sk.bone_lengths[sk.bone_index(name)])
            if abs(np.log(length / expected)) > np.log(1.5):
                out["off_proportions"].append((name, length, expected))
        err = self.errors
        ok = np.isfinite(err)
        sigma = float(np.median(err[ok]) / np.sqrt(2.0 * np.log(2.0))) if ok.any() else np.nan
        out["noise_px"] = sigma
        # (and above half a pixel: a model that fits exactly, e.g. elastic segments on labels
        # that are reprojections, has ~0 noise, and 1e-8 px is nothing to look at)
        idx = np.argwhere(ok & (err > outlier_sigma * sigma) & (err > 0.5))
        order = np.argsort(-err[tuple(idx.T)]) if idx.size else np.array([], int)
        names = self.rig.names
        out["outliers"] = [
            (names[c] or str(c), int(f), sk.marker_names[m], float(err[c, f, m]))
            for c, f, m in idx[order]
        ]
        return out

    def summary(self) -> str:
        """A short text report, with the :meth:`diagnostics` that need attention."""
        lines = [
            f"learned {self.skeleton.name}: {self.t.shape[0]} frames, "
            f"{int(np.isfinite(self.errors).sum())} labels, RMS reprojection error "
            f"{self.rms:.2f} px",
            "  per camera (px): "
            + ", ".join(
                f"{n or i}: {e:.2f}"
                for i, (n, e) in enumerate(zip(self.rig.names, self.per_camera_error, strict=True))
            ),
        ]
        worst = np.argsort(np.nan_to_num(self.per_marker_error, nan=-1))[::-1][:5]
        lines.append(
            "  worst markers (px): "
            + ", ".join(
                f"{self.skeleton.marker_names[k]} {self.per_marker_error[k]:.2f}" for k in worst
            )
        )
        for stage, st in self.info.get("stages", {}).items():
            lines.append(
                f"  {stage}: {st['nit']} iterations, {st['seconds']:.1f} s, {st['message']}"
            )
        for bone, length, lo, hi in self.info.get("prior_conflicts", []):
            lines.append(
                f"  note: the generic {bone} ({length:.3g} {self.skeleton.units}) lies outside "
                f"its prior [{lo:.3g}, {hi:.3g}] at this body weight; it started at the prior mean"
            )
        d = self.diagnostics()
        if d["bones_on_bounds"]:
            lines.append(
                "  WARNING bones on a bound of their length (check body_weight, or the labels "
                "of the markers around them): "
                + ", ".join(f"{b} {v:.3g}" for b, v, _ in d["bones_on_bounds"])
            )
        if d["offsets_on_bounds"]:
            lines.append(
                "  marker offsets against a wall of their box: "
                + ", ".join(f"{m}.{a} = {v:.3g}" for m, a, v in d["offsets_on_bounds"])
            )
        if d["off_proportions"]:
            lines.append(
                "  WARNING bones far from the generic proportions (a joint may have slid along "
                "a weakly determined chain; more labelled frames with that part bent help): "
                + ", ".join(f"{b} {v:.3g} (expected ~{e:.3g})" for b, v, e in d["off_proportions"])
            )
        if d["outliers"]:
            worst = ", ".join(
                f"{m} in {c} frame {f} ({e:.1f} px)" for c, f, m, e in d["outliers"][:5]
            )
            lines.append(
                f"  WARNING {len(d['outliers'])} labels above 5 x the label noise "
                f"(~{d['noise_px']:.2f} px): {worst}"
            )
        return "\n".join(lines)

    def pose_state(
        self, frame: int = 0, normalization: Normalization | None = None, joint_limits: bool = True
    ) -> np.ndarray:
        """The tracker state of one learned frame (e.g. ``mu_0``), shape (n_state,)."""
        sm = self.skeleton.state_map(normalization, joint_limits)
        return sm.from_pose(self.t[frame], self.r[frame])

    def plot_reprojection(self, frame: int | None = None):
        """Labelled (crosses) vs reprojected markers in every camera, like Supp. Fig. 2."""
        from .plotting import camera_views

        if frame is None:
            frame = int(np.argmax(np.isfinite(self.errors).sum(axis=(0, 2))))
        joints, markers = self.skeleton.forward(self.t[frame], self.r[frame])
        fig = camera_views(
            self.rig, self.skeleton, joints, markers, self.labels[:, frame], zoom=True
        )
        fig.suptitle(f"frame {frame}: labels (orange x) and learned model (green)")
        fig.tight_layout(rect=(0, 0, 1, 0.96))
        return fig

    def plot_skeleton(self):
        """Generic vs learned skeleton, top and side views, rotations mid-range (Supp. Fig. 1c)."""
        from .plotting import _pyplot, draw_skeleton_2d

        plt = _pyplot()
        fig, axes = plt.subplots(2, 2, figsize=(12, 5.5))
        for row, (sk, label) in enumerate(((self.generic, "generic"), (self.skeleton, "learned"))):
            sm = sk.state_map()
            t, r = sm.to_pose(np.zeros(sm.n_state))
            j, m = sk.forward(np.zeros(3), r)
            # body frame: x lateral, y dorsal, z caudal -> top view (z, x), side view (z, y)
            for ax, (a, b), view in zip(axes[row], [(2, 0), (2, 1)], ["top", "side"], strict=True):
                draw_skeleton_2d(ax, sk, j[:, [a, b]], m[:, [a, b]])
                ax.set_aspect("equal")
                ax.set_title(f"{label}: {view}")
                ax.set_xlabel(f"{'xyz'[a]} ({sk.units})")
                ax.set_ylabel(f"{'xyz'[b]} ({sk.units})")
                ax.grid(alpha=0.3)
        fig.tight_layout()
        return fig

    def save(self, prefix: str | Path) -> list[Path]:
        """Write ``<prefix>.toml`` (the learned skeleton) and ``<prefix>_fit.npz`` (poses,
        labels, reprojections, errors), atomically."""
        prefix = Path(prefix)
        skel_path = prefix.with_suffix(".toml")
        self.skeleton.save(skel_path)
        npz_path = prefix.with_name(prefix.name + "_fit.npz")
        with atomic_write(npz_path, "wb") as fh:
            np.savez_compressed(
                fh, t=self.t, r=self.r, labels=self.labels, projected=self.projected,
                errors=self.errors, bone_lengths=self.skeleton.bone_lengths,
                marker_offsets=self.skeleton.marker_offsets,
                marker_names=np.array(self.skeleton.marker_names),
            )  # fmt: skip
        return [skel_path, npz_path]


def learn_skeleton(
    rig: CameraRig,
    skeleton: Skeleton,
    labels: np.ndarray,
    *,
    body_weight: float | None = None,
    symmetric: bool = True,
    progress: bool | None = False,
    marker_names: Sequence[str] | None = None,
    likelihood: np.ndarray | None = None,
    pcutoff: float = 0.9,
    normalization: Normalization | None = None,
    sigma_factor: float = 10.0,
    options: dict | None = None,
    init: tuple[np.ndarray, np.ndarray] | None = None,
    rounds: int = 0,
    lm_iter: int = 100,
    scale_to_labels: bool = True,
    length_prior_sd: float | None = 0.15,
) -> LearnedSkeleton:
    """Learn bone lengths, marker offsets and per-frame poses from labelled frames (eq. 12).

    Parameters
    ----------
    rig : CameraRig
        Calibrated cameras (world units = the skeleton's units).
    skeleton : Skeleton
        The generic model (e.g. ``acm_rs.models.rat()``): starting lengths and offsets, joint
        limits, marker boxes, symmetry pairs and bone-length priors.
    labels : array_like, shape (n_cams, n_frames, n_markers, 2)
        Manual labels in pixels, NaN where a marker is not labelled. Columns are the
        skeleton's markers, or named by ``marker_names``.
    body_weight : float, optional
        Body weight (g) for weight-proportional bone-length priors (rat). Without it (and
        without absolute priors) lengths are bounded to [0.2, 5] x their generic value.
    symmetric : bool
        Enforce left/right symmetry (Alg. 2-3).
    progress : bool or None
        Show a progress bar (tqdm); None: only when stderr is a terminal; default quiet.
    marker_names : sequence of str, optional
        Names of the label columns (ACM ``spot_``/``marker_..._start`` spellings accepted).
    likelihood : array_like, shape (n_cams, n_frames, n_markers), optional
        Confidences of labels that come from predictions (DeepLabCut): labels below
        ``pcutoff`` are not used. None for manual labels.
    pcutoff : float
        Likelihood cutoff in [0, 1] (the authors' 0.9).
    normalization : Normalization, optional
        Sec. 3.3 constants (default: :meth:`Normalization.for_rig`, ``c_t`` from the rig's
        size, so results do not depend on the world unit; pixel scales from the image
        sizes). Lengths and offsets are scaled by ``normalization.translation / 50`` in the
        optimiser.
    sigma_factor : float
        Width of the bone-length priors in standard deviations (authors: 10).
    options : dict, optional
        L-BFGS-B options overriding :data:`LBFGSB_DEFAULTS`.
    init : (t, r), optional
        Initial poses ``(n_frames, 3)``, ``(n_frames, n_bones, 3)``; default
        :func:`initial_poses`.
    rounds : int
        Maximum number of L-BFGS-B runs of the joint problem (the authors' optimiser), each
        re-preconditioned at the previous result, before Levenberg-Marquardt. Default 0:
        L-BFGS-B stalls in this problem's flat valleys (``docs/models.md``).
    lm_iter : int
        Maximum number of Levenberg-Marquardt steps on the whole problem (exact Gauss-Newton
        steps, frames eliminated by the Schur complement, in Rust); 0 skips it.
    scale_to_labels : bool
        Scale the generic model to the size of the animal in the labels first (the scale
        with the smallest per-frame reprojection error, ``info["size_scale"]``).
    length_prior_sd : float or None
        Relative SD of a Gaussian prior on the lengths of the bones without an anatomical
        prior (spine, tail, girdles, digits), centred on the (scaled) generic model and
        weighted as if the labels had 1 px noise. Along a chain whose markers may slide
        along their bones, the data hardly tell where a joint sits; the prior decides there
        and nowhere else. None: no prior (the authors' tool has none).

    Returns
    -------
    LearnedSkeleton

    Raises
    ------
    ValueError
        Wrong shapes, labels for unknown markers, a frame with fewer than 3 labelled points,
        infinite labels, or labels for a different number of cameras.
    """
    norm = normalization or Normalization.for_rig(
        np.array([c.center for c in rig]), skeleton.units, [c.size for c in rig]
    )
    labels = mask_by_likelihood(labels, likelihood, pcutoff)
    lab = _labels_in_skeleton_order(labels, skeleton, rig, marker_names)
    n_frames = lab.shape[1]
    if n_frames == 0:
        raise ValueError("labels contain no frames")
    counts = np.isfinite(lab).all(axis=-1).sum(axis=(0, 2))
    if (counts < 3).any():
        f = int(np.flatnonzero(counts < 3)[0])
        raise ValueError(
            f"frame {f} has {counts[f]} labelled 2D points in total; at least 3 are needed"
        )
    opts = {**LBFGSB_DEFAULTS, **(options or {})}
    scale = norm.pixel[0] * norm.pixel[1]  # objective in ~px^2, as scipy's ftol expects O(1)
    length_scale = norm.translation / 50.0
    params = rig.get_params()
    lab_fcm = np.ascontiguousarray(lab.transpose(1, 0, 2, 3))
    lim = skeleton.joint_limits
    lower, upper = np.ascontiguousarray(lim[..., 0]), np.ascontiguousarray(lim[..., 1])
    bp, mp = _pairs(skeleton, symmetric)
    info: dict = {"stages": {}}

    check_units(rig, skeleton)
    info["scale_ratio"] = check_scale(rig, skeleton, lab)
    # (0) size: the generic model scaled to the animal in the labels (a 72 g and a 350 g rat
    # differ by ~1.7x in every length; starting from the wrong size ends in a wrong minimum)
    t0 = time.perf_counter()
    generic = skeleton
    size = 1.0
    # bones with an anatomical prior start at its mean (the authors' start), the rest of
    # the model is scaled to the labels
    info["prior_conflicts"] = check_body_weight(skeleton, body_weight, sigma_factor)
    prior_lo_hi = skeleton.bone_length_bounds(body_weight, sigma_factor)
    anatomical = np.isfinite(prior_lo_hi[:, 1])
    fixed_lengths = np.where(anatomical, prior_lo_hi.mean(axis=1), np.nan)
    if anatomical.any() and init is None:
        skeleton = skeleton.with_parameters(
            np.where(anatomical, fixed_lengths, skeleton.bone_lengths)
        )
    if scale_to_labels and init is None:
        size = _size_from_labels(
            rig, skeleton, lab_fcm, norm, length_scale, lower, upper, anatomical
        )
        if abs(np.log(size)) > 0.05:
            skeleton = skeleton.with_parameters(
                np.where(anatomical, skeleton.bone_lengths, skeleton.bone_lengths * size),
                skeleton.marker_offsets * size,
            )
    info["size_scale"] = size
    info["stages"]["size"] = {"nit": 0, "seconds": time.perf_counter() - t0,
                              "message": f"generic model scaled by {size:.3f}"}  # fmt: skip

    # (1) initial poses
    t0 = time.perf_counter()
    t_init, r_init = init if init is not None else initial_poses(rig, skeleton, lab, norm)
    pose_bounds = _pose_bounds(skeleton, norm)
    z0 = _to_state(np.asarray(t_init, float), np.asarray(r_init, float), skeleton, norm)
    z0 = np.stack([_clip_to_bounds(z, pose_bounds) for z in z0])
    info["stages"]["init"] = {"nit": 0, "seconds": time.perf_counter() - t0, "message": "ok"}

    # (2) poses with the generic skeleton fixed: box-constrained Levenberg-Marquardt per frame
    # in Rust (frames are independent here), then multi-start for frames left in a poor local
    # minimum (a limb folded the wrong way): a fast and robust start for the joint problem
    t0 = time.perf_counter()
    lo_z, hi_z = _bound_arrays(pose_bounds)
    z1, n_lm, n_retried = _fit_frames(
        skeleton, params, lab_fcm, lower, upper, norm, length_scale, z0, lo_z, hi_z,
        skeleton.bone_lengths, skeleton.marker_offsets, seed=0,
    )  # fmt: skip
    info["stages"]["poses"] = {
        "success": True, "nit": n_lm, "seconds": time.perf_counter() - t0,
        "message": f"per-frame Levenberg-Marquardt, {n_retried} frames multi-started",
    }  # fmt: skip
    hist1: list[float] = []

    # (3) everything together
    full = _native.NativeLearning(
        skeleton._native, params, lab_fcm, lower, upper, norm._tuple(), bp, mp, length_scale
    )
    if symmetric:
        rb, rm = _reduced_indices(skeleton)
    else:
        rb, rm = np.arange(skeleton.n_bones), np.arange(skeleton.n_markers)
    generic_l = skeleton.bone_lengths
    prior = skeleton.bone_length_bounds(body_weight, sigma_factor)
    l_lo = np.where(prior[:, 0] > 0, prior[:, 0], 0.2 * generic_l)
    l_hi = np.where(np.isfinite(prior[:, 1]), prior[:, 1], 5.0 * generic_l)
    if np.any(l_lo >= l_hi):
        b = int(np.flatnonzero(l_lo >= l_hi)[0])
        raise ValueError(f"bone-length bounds of {skeleton.bone_names[b]!r} are empty: "
                         f"[{l_lo[b]}, {l_hi[b]}]")  # fmt: skip
    mb = skeleton.marker_bounds
    x_bounds = [
        (lo / length_scale, hi / length_scale) for lo, hi in zip(l_lo[rb], l_hi[rb], strict=True)
    ]
    for k in rm:
        for ax in range(3):
            lo, hi = mb[k, ax]
            x_bounds.append((lo / length_scale if np.isfinite(lo) else None,
                             hi / length_scale if np.isfinite(hi) else None))  # fmt: skip
    x_skel = np.concatenate([generic_l[rb], skeleton.marker_offsets[rm].ravel()]) / length_scale
    x0 = np.concatenate([_clip_to_bounds(x_skel, x_bounds), z1.ravel()])
    bounds = x_bounds + pose_bounds * n_frames
    t0 = time.perf_counter()
    hist2: list[float] = []
    nit = 0
    x_fit = x0
    # L-BFGS-B stops at a relative reduction of ftol; restarting with the preconditioner
    # recomputed at the new point continues while a round still gains more than 1e-5.
    for _round in range(int(rounds)):
        res2, h = _minimize(full, x_fit, bounds, scale, opts, progress, "skeleton")
        hist2 += h
        nit += int(res2.nit)
        f_start = full.value_and_grad(x_fit)[0] * scale
        x_fit = res2.x
        info["stages"]["skeleton"] = _stage(res2, t0) | {"nit": nit, "rounds": _round + 1}
        if f_start - res2.fun <= 1e-5 * max(abs(res2.fun), 1e-12):
            break
    info["history"] = {"poses": hist1, "skeleton": hist2}
    info["length_bounds"] = np.stack([l_lo, l_hi], axis=1)
    if lm_iter > 0:
        # (4) Levenberg-Marquardt on everything (Schur complement in Rust): crosses the flat
        # valleys where L-BFGS-B stalls (a joint sliding along a chain with its markers)
        t0 = time.perf_counter()
        lo_x, hi_x = _bound_arrays(bounds)
        # the prior's centre: the generic proportions, then rescaled to the fitted size
        prior = _length_prior(
            skeleton, rb, skeleton.bone_lengths[rb], body_weight, sigma_factor,
            length_prior_sd, norm, length_scale, full.n_skeleton_params,
        )  # fmt: skip

        def lm(x):
            return full.fit_full_lm(x, lo_x, hi_x, int(lm_iter), 1e-10, *prior)

        x_fit, n_lm, f0, f1, msg = lm(x_fit)
        if prior:
            prior = _length_prior(
                skeleton, rb, x_fit[: rb.size] * length_scale, body_weight, sigma_factor,
                length_prior_sd, norm, length_scale, full.n_skeleton_params,
            )  # fmt: skip
            x_fit, n2, _, f1, msg = lm(x_fit)
            n_lm += n2
            centre, weight = prior
            # a free bone far from the proportions (a joint slid along a weakly determined
            # chain): restart those lengths at the prior's centre, keep it if that fits better
            nsk = centre.size
            ratio = x_fit[:nsk] / np.where(centre > 0, centre, 1.0)
            far = (weight > 0) & (np.abs(np.log(np.abs(ratio) + 1e-300)) > np.log(1.5))
            if far.any():
                for reset in (far, weight > 0):  # the far bones, or every free bone
                    x_try = x_fit.copy()
                    x_try[:nsk][reset] = centre[reset]
                    x_try, n2, _, f_try, msg_try = lm(np.clip(x_try, lo_x, hi_x))
                    n_lm += n2
                    if f_try < f1:
                        x_fit, f1, msg = x_try, f_try, msg_try
                info["chain_restarts"] = int(far.sum())
            info["length_prior"] = {
                skeleton.bone_names[b]: float(centre[i] * length_scale)
                for i, b in enumerate(rb)
                if weight[i] > 0
            }
        # frames left with a limb folded the wrong way: multi-start their poses with the
        # learned skeleton, then Levenberg-Marquardt again while that lowers the objective
        nsk = full.n_skeleton_params
        n_restarted = 0
        for attempt in range(3):
            _, lengths, offsets, _ = full.residuals(x_fit)
            z_fit = x_fit[nsk:].reshape(n_frames, -1)
            z_new, _, n_bad = _fit_frames(
                skeleton, params, lab_fcm, lower, upper, norm, length_scale, z_fit, lo_z, hi_z,
                lengths, offsets, seed=attempt + 1,
            )  # fmt: skip
            x_new = np.concatenate([x_fit[:nsk], z_new.ravel()])
            if n_bad == 0 or full.value_and_grad(x_new)[0] >= full.value_and_grad(x_fit)[0]:
                break
            n_restarted += n_bad
            x_fit, n2, _, f1, msg = lm(x_new)
            n_lm += n2
        info["stages"]["lm"] = {
            "success": True, "nit": n_lm, "seconds": time.perf_counter() - t0,
            "message": msg, "fun": f1 * scale, "fun_start": f0 * scale,
            "frames_restarted": n_restarted,
        }  # fmt: skip

    projected, lengths, offsets, poses = full.residuals(x_fit)
    learned = skeleton.with_parameters(lengths, offsets)
    projected = projected.transpose(1, 0, 2, 3)
    errors = np.linalg.norm(projected - lab, axis=-1)
    return LearnedSkeleton(
        skeleton=learned,
        t=poses[:, :3],
        r=poses[:, 3:].reshape(n_frames, skeleton.n_bones, 3),
        labels=lab,
        projected=projected,
        errors=errors,
        rig=rig,
        generic=generic,
        info=info,
    )


def _frame_rms(problem: _native.NativeLearning, x: np.ndarray, lab_fcm: np.ndarray) -> np.ndarray:
    projected = problem.residuals(x)[0]
    err = np.sum((projected - lab_fcm) ** 2, axis=-1)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.nanmean(np.where(np.isfinite(err), err, np.nan), axis=(1, 2)))


def check_units(rig: CameraRig, skeleton: Skeleton) -> None:
    """Refuse a rig and a skeleton that declare different length units, saying how to
    convert (undeclared units are checked from the data by :func:`check_scale`)."""
    from .state import UNIT_IN_CM

    a, b = rig.units, skeleton.units
    if not a or not b or a == b:
        return
    if a in UNIT_IN_CM and b in UNIT_IN_CM:
        f = UNIT_IN_CM[a] / UNIT_IN_CM[b]
        fix = f"rig.scaled({f:g}, units={b!r}) converts the calibration to {b}"
    else:
        fix = "convert one of them"
    raise ValueError(
        f"the calibration is in {a!r} but the skeleton {skeleton.name!r} in {b!r}: {fix}"
    )


def check_scale(
    rig: CameraRig, skeleton: Skeleton, labels: np.ndarray, limit: float = 4.0
) -> float:
    """Size of the animal in the labels relative to ``skeleton`` (1 = the model's size).

    Triangulates the labelled markers (frames with >= 4 markers seen by >= 2 cameras) and
    compares their spread about their centroid with the same markers' spread in the model's
    rest pose (median over frames). A calibration in other units than the model (mm vs cm:
    a ratio near 10 or 0.1) is refused.

    Parameters
    ----------
    labels : numpy.ndarray, shape (n_cams, F, M, 2)
        Pixels in the skeleton's marker order, NaN where missing.

    Raises
    ------
    ValueError
        When the ratio is above ``limit`` or below ``1 / limit``, saying how to fix it.
    """
    pts = triangulate(rig, labels)
    _, rest = skeleton.rest_pose()
    ratios = []
    for f in range(pts.shape[0]):
        ok = np.all(np.isfinite(pts[f]), axis=1)
        if ok.sum() < 4:
            continue
        a = pts[f, ok] - pts[f, ok].mean(axis=0)
        b = rest[ok] - rest[ok].mean(axis=0)
        sb = np.sqrt(np.mean(np.sum(b**2, axis=1)))
        if sb > 0:
            ratios.append(np.sqrt(np.mean(np.sum(a**2, axis=1))) / sb)
    if not ratios:
        return float("nan")
    ratio = float(np.median(ratios))
    if not 1.0 / limit <= ratio <= limit:
        units = skeleton.units or "the model's units"
        hint = ""
        for name, f in (("mm vs cm", 10.0), ("cm vs mm", 0.1), ("m vs cm", 0.01),
                        ("board squares of 6.5 cm", 1 / 6.5)):  # fmt: skip
            if abs(np.log(ratio / f)) < np.log(2.0):
                hint = f" A ratio near {f:g} suggests a calibration in {name.split(' vs ')[0]}"
                hint += " while the model is in " + (name.split(" vs ")[1] if " vs " in name
                                                     else units) + "."  # fmt: skip
        raise ValueError(
            f"the labelled markers triangulate to an animal {ratio:.3g} x the size of the "
            f"model {skeleton.name!r} ({units}): the calibration and the model are in "
            f"different length units, or the cameras are in the wrong order.{hint} Convert "
            "one of them (CameraRig.scaled(factor), or a model in the calibration's units)."
        )
    return ratio


def check_body_weight(
    skeleton: Skeleton, body_weight: float | None, sigma_factor: float = 10.0
) -> list[tuple[str, float, float, float]]:
    """Bones of ``skeleton`` whose length lies outside its anatomical prior at ``body_weight``.

    Returns ``[(bone, length, lower, upper)]`` (lengths in the skeleton's units), and warns
    when the list is not empty: learning then starts those bones at their prior means.

    Raises
    ------
    ValueError
        A body weight that is not a positive number of grams (e.g. 0.35: kilograms).
    """
    if body_weight is None:
        return []
    w = float(body_weight)
    if not np.isfinite(w) or w <= 0:
        raise ValueError(f"body_weight must be a positive number of grams, got {body_weight}")
    if w < 1.0 and any(c.slope is not None for c in skeleton.bone_length_constraints):
        raise ValueError(
            f"body_weight = {body_weight} g is not a rodent's weight: give grams "
            f"(e.g. {w * 1000:g} for {w:g} kg)"
        )
    bounds = skeleton.bone_length_bounds(w, sigma_factor)
    out = []
    for b, (name, length) in enumerate(
        zip(skeleton.bone_names, skeleton.bone_lengths, strict=True)
    ):
        lo, hi = bounds[b]
        tol = 1e-9 * max(hi, 1.0) if np.isfinite(hi) else 0.0
        if np.isfinite(hi) and not lo - tol <= length <= hi + tol:
            out.append((name, float(length), float(lo), float(hi)))
    if out:
        warnings.warn(
            f"body weight {w:g} g puts {len(out)} bones of the generic model {skeleton.name!r} "
            f"outside their priors (e.g. {out[0][0]} {out[0][1]:.3g} not in "
            f"[{out[0][2]:.3g}, {out[0][3]:.3g}] {skeleton.units}); learning starts them at "
            "their prior means. If the weight is right, the generic model is of another size.",
            stacklevel=3,
        )
    return out


def _length_prior(
    skeleton: Skeleton,
    rb: np.ndarray,
    fitted: np.ndarray,
    body_weight: float | None,
    sigma_factor: float,
    rel_sd: float | None,
    norm: Normalization,
    length_scale: float,
    n_skeleton_params: int,
) -> tuple[np.ndarray, np.ndarray] | tuple[()]:
    """``(centre, weight)`` of the reduced skeleton parameters for ``fit_full_lm``: lengths of
    bones without an anatomical prior ~ N(s g, (rel_sd s g)^2) with g the generic lengths and
    s the median ratio of the ``fitted`` lengths (reduced bones) to them, as residuals in
    normalised pixels for a label noise of 1 px; offsets free. ``()`` when disabled."""
    if rel_sd is None:
        return ()
    if not rel_sd > 0:
        raise ValueError(f"length_prior_sd must be > 0 or None, got {rel_sd}")
    centre = np.zeros(n_skeleton_params)
    weight = np.zeros(n_skeleton_params)
    anatomical = np.isfinite(skeleton.bone_length_bounds(body_weight, sigma_factor)[rb, 1])
    g = skeleton.bone_lengths[rb]
    if (~anatomical).any():
        g = g * float(np.exp(np.median(np.log(fitted[~anatomical] / g[~anatomical]))))
    generic = g / length_scale
    pixel = float(np.sqrt(norm.pixel[0] * norm.pixel[1]))
    centre[: rb.size] = generic
    weight[: rb.size] = np.where(anatomical, 0.0, 1.0 / (pixel * rel_sd * generic))
    return centre, weight


def _size_from_labels(
    rig: CameraRig,
    skeleton: Skeleton,
    lab_fcm: np.ndarray,
    norm: Normalization,
    length_scale: float,
    lower: np.ndarray,
    upper: np.ndarray,
    keep: np.ndarray,
    n_sub: int = 12,
) -> float:
    """Scale of the generic model that best explains the labels (lengths, except those where
    ``keep`` is true, and offsets times the scale): per-frame pose fits on up to ``n_sub``
    frames over a geometric grid from 0.4 to 3, refined around the best; returns the scale
    with the smallest median frame RMS."""
    counts = np.isfinite(lab_fcm).all(axis=-1).sum(axis=(1, 2))
    sub = np.sort(np.argsort(-counts)[: min(n_sub, counts.size)])
    lab_sub = np.ascontiguousarray(lab_fcm[sub])
    params = rig.get_params()
    pose_bounds = _pose_bounds(skeleton, norm)
    lo_z, hi_z = _bound_arrays(pose_bounds)
    empty = np.zeros((0, 2), np.int64)
    cache: dict[float, float] = {}

    def cost(log_s: float) -> float:
        key = round(log_s, 6)
        if key not in cache:
            s = float(np.exp(log_s))
            lengths = np.where(keep, skeleton.bone_lengths, skeleton.bone_lengths * s)
            sk = skeleton.with_parameters(lengths, skeleton.marker_offsets * s)
            t0, r0 = initial_poses(rig, sk, lab_sub.transpose(1, 0, 2, 3), norm)
            z0 = np.stack([_clip_to_bounds(z, pose_bounds) for z in _to_state(t0, r0, sk, norm)])
            prob = _native.NativeLearning(
                sk._native, params, lab_sub, lower, upper, norm._tuple(), empty, empty,
                length_scale, sk.bone_lengths, sk.marker_offsets,
            )  # fmt: skip
            x, _ = prob.fit_poses_lm(np.ascontiguousarray(z0.ravel()), lo_z, hi_z, 30)
            cache[key] = float(np.nanmedian(_frame_rms(prob, x, lab_sub)))
        return cache[key]

    grid = np.linspace(np.log(0.4), np.log(3.0), 9)
    best = min(grid, key=cost)
    step = grid[1] - grid[0]
    for _ in range(3):  # refine: halve the step around the best
        step /= 2
        best = min((best - step, best, best + step), key=cost)
    return float(np.exp(best))


def _fit_frames(
    skeleton: Skeleton,
    params: np.ndarray,
    lab_fcm: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    norm: Normalization,
    length_scale: float,
    z0: np.ndarray,
    lo_z: np.ndarray,
    hi_z: np.ndarray,
    lengths: np.ndarray,
    offsets: np.ndarray,
    seed: int,
    starts: int = 12,
) -> tuple[np.ndarray, int, int]:
    """Per-frame LM fits of the poses (lengths, offsets fixed); frames whose RMS error exceeds
    1.5x the median are retried from ``starts`` perturbed limb configurations (best kept)."""
    empty = np.zeros((0, 2), np.int64)

    def problem(labels: np.ndarray) -> _native.NativeLearning:
        return _native.NativeLearning(
            skeleton._native, params, np.ascontiguousarray(labels), lower, upper, norm._tuple(),
            empty, empty, length_scale, lengths, offsets,
        )  # fmt: skip

    whole = problem(lab_fcm)
    x, nits = whole.fit_poses_lm(np.ascontiguousarray(z0.ravel()), lo_z, hi_z, 50)
    z = x.reshape(z0.shape)
    rms = _frame_rms(whole, x, lab_fcm)
    bad = np.flatnonzero(rms > 1.5 * np.nanmedian(rms))
    n_it = int(np.sum(nits))
    if bad.size == 0:
        return z, n_it, 0
    rng = np.random.default_rng(seed)
    sub = problem(lab_fcm[bad])
    limited = np.isfinite(lo_z) & np.isfinite(hi_z)
    if not limited.any():
        # nothing to redraw: every start would be the same continuation of the fit, so one
        # gives the result of all (12 identical 50-iteration fits cost 0.25 s per track call
        # of a skeleton without joint limits)
        starts = min(starts, 1)
    lo_f, hi_f = np.where(limited, lo_z, 0.0), np.where(limited, hi_z, 0.0)
    mid, half = 0.5 * (lo_f + hi_f), 0.5 * (hi_f - lo_f)
    best, best_rms = z[bad].copy(), rms[bad].copy()
    for _ in range(starts):
        trial = z[bad].copy()
        # keep the translation and global rotation, redraw every limited rotation
        trial[:, limited] = (mid + half * rng.uniform(-0.9, 0.9, trial.shape))[:, limited]
        xt, it = sub.fit_poses_lm(np.ascontiguousarray(trial.ravel()), lo_z, hi_z, 50)
        n_it += int(np.sum(it))
        zt = xt.reshape(trial.shape)
        r = _frame_rms(sub, xt, lab_fcm[bad])
        better = r < best_rms
        best[better], best_rms[better] = zt[better], r[better]
    z[bad] = best
    return z, n_it, int(bad.size)


def _stage(res, t0: float) -> dict:
    return {
        "success": bool(res.success),
        "message": str(res.message),
        "nit": int(res.nit),
        "nfev": int(res.nfev),
        "fun": float(res.fun),
        "seconds": time.perf_counter() - t0,
    }


def fit_pose(
    rig: CameraRig,
    skeleton: Skeleton,
    labels: np.ndarray,
    *,
    normalization: Normalization | None = None,
    init: tuple[np.ndarray, np.ndarray] | None = None,
    options: dict | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """First-pose fit (sec. 4.7): eq. 9 for one frame with lengths and offsets fixed.

    Parameters
    ----------
    labels : array_like, shape (n_cams, M, 2)
        2D marker positions of one frame (px), NaN where missing.
    init : (t (3,), r (n_bones, 3)), optional
        Starting pose; default from :func:`initial_poses`.

    Returns
    -------
    t : numpy.ndarray, shape (3,)
    r : numpy.ndarray, shape (n_bones, 3)
    info : dict
        Optimiser outcome and the RMS reprojection error (px).
    """
    norm = normalization or Normalization()
    lab = as_float_array(labels, "labels", (None, None, 2), finite=False)
    if lab.ndim != 3:
        raise ValueError(f"labels must have shape (n_cams, n_markers, 2), got {lab.shape}")
    lab4 = _labels_in_skeleton_order(lab[:, None], skeleton, rig, None)
    if np.isfinite(lab4).all(axis=-1).sum() < 3:
        raise ValueError("the frame has fewer than 3 labelled 2D points")
    if init is None:
        t_i, r_i = initial_poses(rig, skeleton, lab4, norm)
    else:
        t_i, r_i = np.asarray(init[0], float)[None], np.asarray(init[1], float)[None]
    lim = skeleton.joint_limits
    bp, mp = _pairs(skeleton, False)
    problem = _native.NativeLearning(
        skeleton._native, rig.get_params(), np.ascontiguousarray(lab4.transpose(1, 0, 2, 3)),
        np.ascontiguousarray(lim[..., 0]), np.ascontiguousarray(lim[..., 1]), norm._tuple(),
        bp, mp, norm.translation / 50.0, skeleton.bone_lengths, skeleton.marker_offsets,
    )  # fmt: skip
    bounds = _pose_bounds(skeleton, norm)
    z0 = _clip_to_bounds(_to_state(t_i, r_i, skeleton, norm)[0], bounds)
    t0 = time.perf_counter()
    res, _ = _minimize(
        problem, z0, bounds, norm.pixel[0] * norm.pixel[1],
        {**LBFGSB_DEFAULTS, **(options or {})}, False, "pose",
    )  # fmt: skip
    projected, _, _, poses = problem.residuals(res.x)
    err = np.linalg.norm(projected[0] - lab4[:, 0], axis=-1)
    info = _stage(res, t0) | {"rms_px": float(np.sqrt(np.nanmean(err**2)))}
    return poses[0, :3], poses[0, 3:].reshape(skeleton.n_bones, 3), info
