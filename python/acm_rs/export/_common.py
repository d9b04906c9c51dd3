"""Quantities shared by the exporters: per-point detection statistics and posterior variances.

Frame numbers and posterior variances are also stored in a result's NPZ file, so they live in
:mod:`acm_rs.tracking.result_npz` (the exporters import the result, never the reverse) and are
re-exported here.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..tracking.result_npz import POINTS, check_points, frame_numbers, posterior_variance

if TYPE_CHECKING:  # pragma: no cover
    from ..tracking.result import PoseResult

__all__ = [
    "POINTS",
    "UNIT_MM",
    "UNIT_NAMES",
    "atomic_path",
    "check_points",
    "detection_stats",
    "frame_numbers",
    "point_names",
    "positions",
    "posterior_variance",
]

#: Length units the exporters can convert between, in millimetres.
UNIT_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}

#: NWB-style spelled-out names of the length units.
UNIT_NAMES = {"mm": "millimeters", "cm": "centimeters", "m": "meters"}


def point_names(result: PoseResult, points: str) -> tuple[str, ...]:
    """Names of the exported points."""
    return result.joint_names if check_points(points) == "joints" else result.marker_names


def positions(result: PoseResult, points: str) -> np.ndarray:
    """(T, P, 3) positions of the exported points (skeleton units)."""
    return np.asarray(result.joints if check_points(points) == "joints" else result.markers, float)


def detection_stats(
    result: PoseResult, points: str, likelihood: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Anipose-style per-point quality columns.

    Parameters
    ----------
    result : PoseResult
    points : {"joints", "markers"}
    likelihood : array_like, shape (n_cams, T, M), optional
        Detector confidences (e.g. DeepLabCut likelihood) of ``result.detections``.

    Returns
    -------
    error : numpy.ndarray, shape (T, P)
        Mean reprojection error (px) over the cameras that detected the marker (for a joint:
        over the detections of the markers attached to it); NaN without detections.
    ncams : numpy.ndarray of int, shape (T, P)
        Cameras with a detection (for a joint: with a detection of any attached marker).
    score : numpy.ndarray, shape (T, P)
        Mean ``likelihood`` of the used detections; without ``likelihood`` 1 for a detected
        point (detections passed ``pcutoff``); 0 without detections (model-imputed position).
    """
    det = np.asarray(result.detections, float)
    n_cams, n_t, n_m = det.shape[:3]
    seen = np.all(np.isfinite(det), axis=-1)  # (C, T, M)
    err = result.reprojection_error()
    err = np.where(seen, err, np.nan)
    if likelihood is None:
        lik = np.where(seen, 1.0, np.nan)
    else:
        lik = np.asarray(likelihood, float)
        if lik.shape != (n_cams, n_t, n_m):
            raise ValueError(
                f"likelihood must have shape {(n_cams, n_t, n_m)} like result.detections "
                f"without the last axis, got {lik.shape}"
            )
        lik = np.where(seen, lik, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        if check_points(points) == "markers":
            error = np.nanmean(err, axis=0)
            ncams = seen.sum(axis=0)
            score = np.nanmean(lik, axis=0)
        else:
            n_j = result.skeleton.n_joints
            mj = np.asarray(result.skeleton.marker_joints)
            error = np.full((n_t, n_j), np.nan)
            ncams = np.zeros((n_t, n_j), np.int64)
            score = np.full((n_t, n_j), np.nan)
            for j in range(n_j):
                ks = np.flatnonzero(mj == j)
                if ks.size == 0:
                    continue
                e = err[:, :, ks].transpose(1, 0, 2).reshape(n_t, -1)
                s = lik[:, :, ks].transpose(1, 0, 2).reshape(n_t, -1)
                error[:, j] = np.nanmean(e, axis=1)
                score[:, j] = np.nanmean(s, axis=1)
                ncams[:, j] = seen[:, :, ks].any(axis=2).sum(axis=0)
    score = np.where(ncams > 0, score, 0.0)
    return error, ncams.astype(np.int64), score


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary file name next to ``path`` (same suffix); rename it over ``path`` on
    success, remove it on failure. For libraries that only write to a file name."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=target.suffix, dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
