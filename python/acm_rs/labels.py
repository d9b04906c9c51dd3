"""Label columns -> skeleton markers: the name mapping shared by learning and tracking.

Readers (:mod:`acm_rs.dlc`, :mod:`acm_rs.acm_formats`) give 2D labels with their own column
names; :func:`match_marker_names` maps them to a skeleton's markers and
:func:`labels_in_skeleton_order` reorders a label array accordingly.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ._arrays import as_float_array

if TYPE_CHECKING:  # pragma: no cover
    from .camera import CameraRig
    from .skeleton import Skeleton

__all__ = ["labels_in_skeleton_order", "mask_by_likelihood", "match_marker_names"]


def match_marker_names(label_names: Sequence[str], skeleton: Skeleton) -> np.ndarray:
    """Map label column names to skeleton marker indices.

    Accepts the skeleton's names and the ACM/DeepLabCut spellings ``marker_<name>_start`` and
    ``spot_<name>``. Raises ``ValueError`` naming every unknown label.
    """
    known = {n: i for i, n in enumerate(skeleton.marker_names)}
    out, unknown = [], []
    for name in label_names:
        key = str(name)
        if key not in known:
            for prefix in ("marker_", "spot_"):
                key = key.removeprefix(prefix)
            key = key.removesuffix("_start")
        if key in known:
            out.append(known[key])
        else:
            unknown.append(str(name))
    if unknown:
        raise ValueError(
            f"labels for unknown markers {unknown}; the skeleton's markers are "
            f"{list(skeleton.marker_names)}"
        )
    if len(set(out)) != len(out):
        raise ValueError("two label columns map to the same skeleton marker")
    return np.asarray(out, dtype=np.int64)


def labels_in_skeleton_order(
    labels: np.ndarray, skeleton: Skeleton, rig: CameraRig, marker_names: Sequence[str] | None
) -> np.ndarray:
    """Labels ``(n_cams, n_frames, n_columns, 2)`` -> ``(n_cams, n_frames, M, 2)`` in the
    skeleton's marker order (NaN for markers without a column), checked against the rig.

    Without ``marker_names`` the columns must already be the skeleton's markers.
    """
    lab = as_float_array(labels, "labels", (None, None, None, 2), finite=False)
    if lab.ndim != 4:
        raise ValueError(
            f"labels must have shape (n_cams, n_frames, n_markers, 2), got {lab.shape}"
        )
    if np.isinf(lab).any():
        raise ValueError("labels contain infinity (use NaN for unlabelled points)")
    if lab.shape[0] != len(rig):
        raise ValueError(f"labels are for {lab.shape[0]} cameras but the rig has {len(rig)}")
    if marker_names is None:
        if lab.shape[2] != skeleton.n_markers:
            raise ValueError(
                f"labels have {lab.shape[2]} markers but the skeleton has {skeleton.n_markers}; "
                "pass marker_names to map label columns by name"
            )
        return lab
    if len(marker_names) != lab.shape[2]:
        raise ValueError(f"{len(marker_names)} marker_names for {lab.shape[2]} label columns")
    idx = match_marker_names(marker_names, skeleton)
    out = np.full(lab.shape[:2] + (skeleton.n_markers, 2), np.nan)
    out[:, :, idx] = lab
    return out


#: Fraction of a camera's points that a likelihood cutoff may drop before it is said.
DROPPED_WARNING = 0.5

#: Default likelihood cutoff per source of 2D points (``pcutoff="auto"``; issue 27 item 9).
#: DeepLabCut (and Lightning Pose, which writes its tables): 0.9, the ACM paper's value for
#: DeepLabCut likelihoods. SLEAP: 0.2, SLEAP's own ``peak_threshold`` (sleap.nn.inference),
#: below which SLEAP reports no point; sleap-anipose triangulates with no score cutoff. SLEAP's
#: scores are confidence-map peaks, not probabilities: on the predicted points of the real
#: SLEAP files in tests/data/real/sleap, 0.9 keeps 14-58 %, 0.2 keeps 80-100 %.
PCUTOFF_BY_SOURCE = {"deeplabcut": 0.9, "sleap": 0.2}


def default_pcutoff(sources: Sequence[str | None]) -> tuple[float, str]:
    """The cutoff for labels from ``sources`` (one per camera file: "deeplabcut", "sleap",
    None for a camera without a file) and a phrase saying why, e.g. ``(0.2, "SLEAP's
    peak threshold")``. Files from tools with different defaults are refused (their scores
    are not comparable: give ``pcutoff`` explicitly)."""
    known = sorted({part for s in sources if s for part in s.split("+")})
    if not known:
        return PCUTOFF_BY_SOURCE["deeplabcut"], "DeepLabCut's default in acm-rs"
    unknown = [s for s in known if s not in PCUTOFF_BY_SOURCE]
    if unknown:
        raise ValueError(f"unknown label source(s) {unknown}; known: {sorted(PCUTOFF_BY_SOURCE)}")
    values = {PCUTOFF_BY_SOURCE[s] for s in known}
    if len(values) > 1:
        raise ValueError(
            f"label files from {' and '.join(known)}, whose scores are on different scales: "
            "give the likelihood cutoff explicitly (pcutoff / --pcutoff)"
        )
    why = {"deeplabcut": "the ACM paper's cutoff for DeepLabCut likelihoods",
           "sleap": "SLEAP's own peak threshold"}  # fmt: skip
    return values.pop(), why[known[0]]


def mask_by_likelihood(
    points: np.ndarray, likelihood: np.ndarray | None, pcutoff: float, warn: bool = True
) -> np.ndarray:
    """Points with a likelihood below ``pcutoff`` (or NaN) set to NaN (a copy).

    Parameters
    ----------
    points : array_like, shape (n_cams, F, K, 2)
        Pixels, in the columns' own order.
    likelihood : array_like, shape (n_cams, F, K), or None
        Confidences in [0, 1] (DeepLabCut likelihoods; SLEAP scores as :mod:`acm_rs.sleap`
        reads them, clipped to 1); None returns ``points`` unchanged (manual labels).
    pcutoff : float
        In [0, 1].
    warn : bool
        Warn when the cutoff drops more than half of a camera's points (a cutoff made for
        another tool's scores, e.g. DeepLabCut's 0.9 on SLEAP scores).

    Raises
    ------
    ValueError
        Wrong shapes, a cutoff outside [0, 1], or likelihoods outside [0, 1] (e.g. a 0-100
        scale, or SLEAP scores not read by :mod:`acm_rs.sleap`), naming the largest value.
    """
    pts = np.array(points, dtype=np.float64)
    if likelihood is None:
        return pts
    if not 0.0 <= float(pcutoff) <= 1.0:
        raise ValueError(f"pcutoff must be in [0, 1], got {pcutoff}")
    lik = np.asarray(likelihood, dtype=np.float64)
    if lik.shape != pts.shape[:-1]:
        raise ValueError(
            f"likelihood must have shape {pts.shape[:-1]} (n_cams, frames, columns), "
            f"got {lik.shape}"
        )
    finite = lik[np.isfinite(lik)]
    if finite.size and (finite.min() < 0.0 or finite.max() > 1.0):
        hi = float(finite.max())
        if hi <= 2.0:
            # SLEAP's point scores are confidence-map peaks and reach ~1.35; dividing them by
            # 100 would drop every point
            hint = (" (SLEAP scores exceed 1: read SLEAP files with acm_rs.sleap, which clips "
                    "them to 1, or clip them with numpy.clip(scores, 0, 1))")  # fmt: skip
        elif hi <= 100.0:
            hint = " (a 0-100 scale? divide by 100)"
        else:
            hint = ""
        raise ValueError(
            f"likelihoods must lie in [0, 1] (DeepLabCut's scale); these range from "
            f"{finite.min():g} to {hi:g}{hint}"
        )
    with np.errstate(invalid="ignore"):
        drop = ~(lik >= pcutoff)
    present = np.isfinite(pts).all(axis=-1)
    if warn:
        _warn_dropped(present, drop, pcutoff)
    pts[drop] = np.nan
    return pts


def _warn_dropped(present: np.ndarray, drop: np.ndarray, pcutoff: float) -> None:
    """One warning naming the cameras whose points a cutoff mostly drops."""
    import warnings

    n = present.reshape(len(present), -1).sum(axis=1)
    lost = (present & drop).reshape(len(present), -1).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(n > 0, lost / np.maximum(n, 1), 0.0)
    bad = np.flatnonzero(frac > DROPPED_WARNING)
    if bad.size:
        which = ", ".join(f"camera {c}: {100 * frac[c]:.0f} %" for c in bad)
        warnings.warn(
            f"pcutoff {pcutoff:g} drops most of the detected points of {which} "
            f"(of {int(n.sum())} points in all, {int(lost.sum())} dropped): check that the "
            "cutoff suits the scores' source (DeepLabCut likelihoods; SLEAP scores are on "
            "another scale, and proofread SLEAP labels carry likelihood 1)",
            stacklevel=3,
        )
