"""Cross-validated accuracy on a lab's own labelled frames (issue 28 item 4).

Leave one camera out: fit every labelled frame with the other cameras, project into the
held-out camera and compare with the human labels there. Two predictions side by side, from
the same cameras and the same labels:

* ``model``: the skeleton fitted per frame (eq. 9, lengths and offsets fixed; the per-frame
  Levenberg-Marquardt of :func:`acm_rs.learning.learn_skeleton` with ``lm_iter=0``), or with
  ``relearn=True`` the skeleton learned again without the held-out camera first (nothing of
  that camera enters the prediction). A skeleton with elastic segments (``stretch_sd``,
  :mod:`acm_rs.elastic`) is fitted with per-frame bone lengths around its means, from the rigid
  fit's poses;
* ``triangulation``: plain linear (DLT) triangulation of each keypoint from the other cameras
  (:func:`acm_rs.learning.triangulate`), as a tool without a body model would.

Errors are pixel distances in the held-out camera. A keypoint that the other cameras see in
fewer than 2 views cannot be triangulated, while the model still places it: the tables give
the errors on the labels both predict (the fair comparison) and the model's error and count on
the labels only it predicts. A frame is fitted when the other cameras hold >= 3 labelled
points in >= 2 cameras. It is the accuracy measure a lab can compute without ground truth;
it includes the labelling noise of the held-out camera.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import CameraRig
from .elastic import learn_stretch, project_stretched
from .learning import learn_skeleton, triangulate
from .skeleton import Skeleton

__all__ = ["Evaluation", "RefinedEvaluation", "evaluate", "evaluate_refined"]


@dataclass
class Evaluation:
    """Result of :func:`evaluate`.

    Attributes
    ----------
    keypoints, cameras : list of str
    model_error, triangulation_error : numpy.ndarray, shape (n_cams, F, K)
        Pixel error of each held-out label; NaN where unlabelled or not predicted.
    per_keypoint, per_camera : pandas.DataFrame
        One row per keypoint / camera and a last row ``"all"``: ``n`` labels both predict,
        ``model_px`` and ``triangulation_px`` their mean errors, ``model_median_px``,
        ``triangulation_median_px``, ``n_model_only`` labels only the model predicts and
        ``model_only_px`` its mean error there.
    info : dict
        Frames fitted per fold, seconds, settings.
    """

    keypoints: list[str]
    cameras: list[str]
    model_error: np.ndarray
    triangulation_error: np.ndarray
    per_keypoint: object
    per_camera: object
    info: dict = field(default_factory=dict)

    def table(self) -> str:
        """Both tables as text."""
        import pandas as pd

        with pd.option_context("display.width", 120, "display.max_rows", 500):
            return (
                "leave-one-camera-out reprojection error (px) per keypoint:\n"
                + self.per_keypoint.round(2).to_string()
                + "\n\nper held-out camera:\n"
                + self.per_camera.round(2).to_string()
            )

    def summary(self) -> str:
        """One line: the overall errors."""
        a = self.per_camera.loc["all"]
        line = (
            f"leave-one-camera-out on {self.info.get('frames', '?')} frames, "
            f"{len(self.cameras)} cameras: model {a['model_px']:.2f} px, triangulation "
            f"{a['triangulation_px']:.2f} px (mean over {int(a['n'])} held-out labels both "
            f"predict)"
        )
        if a["n_model_only"]:
            line += (
                f"; {int(a['n_model_only'])} more labels only the model predicts "
                f"({a['model_only_px']:.2f} px)"
            )
        return line

    def plot(self):
        """A figure: mean error per keypoint and per held-out camera, both methods."""
        from .plotting import _pyplot

        plt = _pyplot()
        fig, axes = plt.subplots(
            1, 2, figsize=(12, 4.5), gridspec_kw={"width_ratios": [max(len(self.keypoints), 1),
                                                                    max(len(self.cameras), 1)]}
        )  # fmt: skip
        for ax, df, what in ((axes[0], self.per_keypoint, "keypoint"),
                             (axes[1], self.per_camera, "held-out camera")):  # fmt: skip
            d = df.drop(index="all")
            x = np.arange(len(d))
            ax.bar(x - 0.2, d["model_px"], 0.4, label="skeleton model fit")
            ax.bar(x + 0.2, d["triangulation_px"], 0.4, label="DLT triangulation")
            ax.set_xticks(x, list(d.index), rotation=60, ha="right", fontsize=8)
            ax.set_ylabel("mean error in the held-out camera (px)")
            ax.set_title(f"per {what}")
        axes[0].legend(fontsize=8)
        fig.suptitle(self.summary(), fontsize=9)
        fig.tight_layout()
        return fig

    def save(self, prefix: str | Path) -> list[Path]:
        """``<prefix>_keypoints.csv``, ``<prefix>_cameras.csv`` and ``<prefix>.png``."""
        from ._io import atomic_write
        from .plotting import save_figure

        p = Path(prefix)
        out = []
        for name, df in (("keypoints", self.per_keypoint), ("cameras", self.per_camera)):
            f = p.with_name(f"{p.name}_{name}.csv")
            with atomic_write(f, "w") as fh:
                df.to_csv(fh, index_label=name[:-1])
            out.append(f)
        out.append(save_figure(self.plot(), p.with_name(p.name + ".png")))
        return out


def _table(model: np.ndarray, tri: np.ndarray, index: list[str], axis: tuple[int, ...]):
    """Rows along the axis not in ``axis`` (errors (C, F, K)) plus an ``"all"`` row."""
    import pandas as pd

    both = np.isfinite(model) & np.isfinite(tri)
    only = np.isfinite(model) & ~np.isfinite(tri)

    def stats(sel: tuple) -> dict:
        m, t, b, o = model[sel], tri[sel], both[sel], only[sel]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return {
                "n": int(b.sum()),
                "model_px": float(np.mean(m[b])) if b.any() else np.nan,
                "triangulation_px": float(np.mean(t[b])) if b.any() else np.nan,
                "model_median_px": float(np.median(m[b])) if b.any() else np.nan,
                "triangulation_median_px": float(np.median(t[b])) if b.any() else np.nan,
                "n_model_only": int(o.sum()),
                "model_only_px": float(np.mean(m[o])) if o.any() else np.nan,
            }

    rows = {}
    keep = [a for a in range(3) if a not in axis][0]
    for i, name in enumerate(index):
        sel = [slice(None)] * 3
        sel[keep] = i
        rows[name] = stats(tuple(sel))
    rows["all"] = stats((slice(None),) * 3)
    return pd.DataFrame.from_dict(rows, orient="index")


def _elastic_fold(rig, skeleton, sub, t, r, learn_sd: bool) -> np.ndarray:
    """The fold's frames fitted with elastic segments, from the rigid fit's poses, projected
    into every camera ``(n_cams, F, K, 2)``. The label noise is learned from the fold's
    cameras; the stretch SDs too with ``learn_sd`` (else the skeleton's)."""
    bones = skeleton.elastic_bones if skeleton.stretch_sd.any() else "all"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = learn_stretch(
            rig, skeleton, sub, bones=bones, init=(t, r), learn_sd=learn_sd,
            learn_lengths=learn_sd,
        )  # fmt: skip
    return project_stretched(rig, fit.skeleton, fit.t, fit.r, fit.lengths)


def _masked_labels(labels, bodyparts, likelihood, pcutoff: float):
    """``(points (C, F, K, 2) with scores below pcutoff set to NaN, column names)``."""
    lab, cols, lik = _labels_array(labels, bodyparts)
    if likelihood is None:
        likelihood = lik
    if likelihood is not None and pcutoff > 0:
        lab = np.where((np.asarray(likelihood) >= pcutoff)[..., None], lab, np.nan)
    return lab, cols


def _labels_array(labels, bodyparts):
    if hasattr(labels, "points") and hasattr(labels, "bodyparts"):
        return (np.asarray(labels.points, dtype=np.float64), list(labels.bodyparts),
                getattr(labels, "likelihood", None))  # fmt: skip
    if bodyparts is None:
        raise ValueError("labels given as an array need bodyparts= (the column names)")
    return np.asarray(labels, dtype=np.float64), list(bodyparts), None


def evaluate(
    rig: CameraRig,
    skeleton: Skeleton,
    labels,
    *,
    bodyparts: Sequence[str] | None = None,
    likelihood: np.ndarray | None = None,
    pcutoff: float = 0.0,
    relearn: bool = False,
    body_weight: float | None = None,
    elastic: bool | None = None,
) -> Evaluation:
    """Leave-one-camera-out reprojection error of the skeleton model and of triangulation.

    Parameters
    ----------
    rig : CameraRig
        Calibration of the labelled cameras (at least 3: two to predict, one held out).
    skeleton : Skeleton
        The (learned) skeleton; its markers must be among the label columns.
    labels : LabelSet or array_like, shape (n_cams, F, n_columns, 2)
        Human labels in pixels, NaN where not labelled.
    bodyparts : sequence of str, optional
        Column names of an array ``labels``.
    likelihood : array_like, shape (n_cams, F, n_columns), optional
        Scores of predicted labels (default ``labels.likelihood``); below ``pcutoff`` unused.
    relearn : bool
        Learn the skeleton again without the held-out camera in each fold (slower; the
        strict cross-validation of the whole method). Default: the given skeleton's lengths.
    body_weight : float, optional
        For ``relearn`` with weight-proportional bone-length priors.
    elastic : bool, optional
        Fit each frame with elastic segments (:mod:`acm_rs.elastic`: per-frame bone lengths
        around the means, with the skeleton's ``stretch_sd``; with ``relearn`` the SDs are
        learned again without the held-out camera). Default: when the skeleton has elastic
        bones. ``True`` with a rigid skeleton learns SDs for every bone in each fold.

    Returns
    -------
    Evaluation
    """
    import time

    start = time.perf_counter()
    lab, cols = _masked_labels(labels, bodyparts, likelihood, pcutoff)
    if lab.ndim != 4 or lab.shape[0] != len(rig) or lab.shape[2] != len(cols):
        raise ValueError(
            f"labels must have shape ({len(rig)} cameras, frames, {len(cols)} columns, 2), "
            f"got {lab.shape}"
        )
    if len(rig) < 3:
        raise ValueError(
            f"leave-one-camera-out needs >= 3 cameras (2 to predict from, 1 held out); "
            f"the rig has {len(rig)}"
        )
    unknown = [m for m in skeleton.marker_names if m not in cols]
    if unknown:
        raise ValueError(
            f"the skeleton's markers {unknown} have no label column (columns: {cols}); "
            "evaluate needs the labels the skeleton was made for"
        )
    names = list(skeleton.marker_names)
    lab = lab[:, :, [cols.index(m) for m in names]]
    n_cams, n_frames, k = lab.shape[:3]
    seen = np.isfinite(lab).all(axis=-1)
    model_err = np.full((n_cams, n_frames, k), np.nan)
    tri_err = np.full((n_cams, n_frames, k), np.nan)
    fitted = {}
    if elastic is None:
        elastic = bool(skeleton.stretch_sd.any())
    for c in range(n_cams):
        others = lab.copy()
        others[c] = np.nan
        target = seen[c]
        # triangulation from the other cameras (>= 2 views)
        x_tri = triangulate(rig, others)
        p_tri = rig.project(x_tri)[c]
        tri_err[c] = np.where(target, np.linalg.norm(p_tri - lab[c], axis=-1), np.nan)
        # the model: frames with a held-out label and >= 3 points in >= 2 other cameras
        o_seen = np.isfinite(others).all(axis=-1)
        cams_per_frame = (o_seen.any(axis=2)).sum(axis=0)
        ok = target.any(axis=1) & (o_seen.sum(axis=(0, 2)) >= 3) & (cams_per_frame >= 2)
        fitted[rig[c].name or str(c)] = int(ok.sum())
        if not ok.any():
            continue
        sub = others[:, ok]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # per-fold learning chatter; the tables say it
            if relearn:
                res = learn_skeleton(rig, skeleton, sub, progress=False, body_weight=body_weight)
                sk = res.skeleton
            else:
                res = learn_skeleton(
                    rig, skeleton, sub, progress=False, lm_iter=0, rounds=0, symmetric=False,
                    scale_to_labels=False, length_prior_sd=None,
                )  # fmt: skip
                sk = skeleton
        if elastic:
            px = _elastic_fold(rig, sk, sub, res.t, res.r, relearn or not sk.stretch_sd.any())[c]
        else:
            px = sk.project(rig, res.t, res.r)[c]  # (F_ok, K, 2)
        err = np.linalg.norm(px - lab[c, ok], axis=-1)
        model_err[c, ok] = np.where(target[ok], err, np.nan)
    cams = [cam.name or str(i) for i, cam in enumerate(rig)]
    per_kp = _table(model_err, tri_err, names, (0, 1))
    per_cam = _table(model_err, tri_err, cams, (1, 2))
    info = {
        "frames": n_frames, "fitted_frames": fitted, "relearn": relearn, "elastic": elastic,
        "seconds": time.perf_counter() - start,
    }  # fmt: skip
    return Evaluation(names, cams, model_err, tri_err, per_kp, per_cam, info)


@dataclass
class RefinedEvaluation:
    """Result of :func:`evaluate_refined`: held-out frames evaluated with the starting
    calibration (``before``) and with the one refined on the training frames' keypoints
    (``after``, :func:`acm_rs.calibration.refine_on_keypoints`)."""

    before: Evaluation
    after: Evaluation
    refinement: object  # KeypointRefinement
    train_frames: np.ndarray
    test_frames: np.ndarray

    def summary(self) -> str:
        b, a = self.before.per_camera.loc["all"], self.after.per_camera.loc["all"]
        return (
            f"{self.refinement.summary()}\n"
            f"held-out frames ({len(self.test_frames)}; trained on {len(self.train_frames)}): "
            f"model {b['model_px']:.2f} -> {a['model_px']:.2f} px, triangulation "
            f"{b['triangulation_px']:.2f} -> {a['triangulation_px']:.2f} px"
        )


def evaluate_refined(
    rig: CameraRig,
    skeleton: Skeleton,
    labels,
    *,
    bodyparts: Sequence[str] | None = None,
    likelihood: np.ndarray | None = None,
    pcutoff: float = 0.0,
    train_frames: Sequence[int] | None = None,
    intrinsics: bool = False,
    **options,
) -> RefinedEvaluation:
    """Refine the calibration on the keypoints of training frames and evaluate held-out
    frames before and after (issue 28: where the cameras disagree more than a body model can
    fix).

    Parameters
    ----------
    rig, skeleton, labels, bodyparts, likelihood, pcutoff
        As :func:`evaluate`.
    train_frames : sequence of int, optional
        Frames the calibration is refined on (default every other labelled frame, the
        others are held out).
    intrinsics : bool
        Refine focal lengths and principal points too.
    **options
        Passed to :func:`evaluate` (``relearn``, ``elastic``, ...).

    Returns
    -------
    RefinedEvaluation
    """
    from .calibration.keypoints import refine_on_keypoints

    lab, cols = _masked_labels(labels, bodyparts, likelihood, pcutoff)
    n_frames = lab.shape[1]
    labelled = np.flatnonzero(np.isfinite(lab).all(axis=-1).any(axis=(0, 2)))
    train = labelled[::2] if train_frames is None else np.asarray(train_frames, int)
    test = np.setdiff1d(labelled, train)
    if not (train.size and test.size) or train.min() < 0 or train.max() >= n_frames:
        raise ValueError(
            f"need training and held-out frames among the {labelled.size} labelled frames "
            f"(train_frames within 0..{n_frames - 1})"
        )
    # every labelled column is a calibration target, in the skeleton or not
    ref = refine_on_keypoints(rig, lab[:, train], intrinsics=intrinsics)
    held = lab[:, test]
    before = evaluate(rig, skeleton, held, bodyparts=cols, **options)
    after = evaluate(ref.rig, skeleton, held, bodyparts=cols, **options)
    return RefinedEvaluation(before, after, ref, train, test)
