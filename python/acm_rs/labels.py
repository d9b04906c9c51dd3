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


def mask_by_likelihood(
    points: np.ndarray, likelihood: np.ndarray | None, pcutoff: float
) -> np.ndarray:
    """Points with a likelihood below ``pcutoff`` (or NaN) set to NaN (a copy).

    Parameters
    ----------
    points : array_like, shape (n_cams, F, K, 2)
        Pixels, in the columns' own order.
    likelihood : array_like, shape (n_cams, F, K), or None
        DeepLabCut confidences in [0, 1]; None returns ``points`` unchanged (manual labels).
    pcutoff : float
        In [0, 1].

    Raises
    ------
    ValueError
        Wrong shapes, a cutoff outside [0, 1], or likelihoods outside [0, 1] (e.g. a 0-100
        scale), naming the largest value.
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
        raise ValueError(
            f"likelihoods must lie in [0, 1] (DeepLabCut's scale); these range from "
            f"{finite.min():g} to {finite.max():g}" + (" (a 0-100 scale? divide by 100)"
                                                       if finite.max() <= 100 else "")
        )  # fmt: skip
    with np.errstate(invalid="ignore"):
        pts[~(lik >= pcutoff)] = np.nan
    return pts
