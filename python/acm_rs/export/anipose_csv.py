"""Anipose-compatible 3D CSV (``pose-3d/*.csv``) with a posterior-variance sidecar."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._io import atomic_write
from ._common import (
    check_points,
    detection_stats,
    frame_numbers,
    point_names,
    positions,
    posterior_variance,
)

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

    from ..tracking.result import PoseResult

__all__ = ["anipose_columns", "to_anipose_csv", "variance_path"]

#: Per-point column suffixes, in anipose's order.
SUFFIXES = ("x", "y", "z", "error", "ncams", "score")


def anipose_columns(names: tuple[str, ...] | list[str]) -> list[str]:
    """The column names anipose writes for these body parts (in its order).

    ``<bp>_x, <bp>_y, <bp>_z, <bp>_error, <bp>_ncams, <bp>_score`` per body part, then the
    alignment rotation ``M_00 .. M_22`` (row-major), ``center_0 .. center_2`` and ``fnum``.
    """
    cols = [f"{n}_{s}" for n in names for s in SUFFIXES]
    cols += [f"M_{i}{j}" for i in range(3) for j in range(3)]
    cols += [f"center_{i}" for i in range(3)]
    return cols + ["fnum"]


def variance_path(path: str | Path) -> Path:
    """The variance sidecar of an anipose CSV: ``<stem>_variance.csv`` beside it."""
    p = Path(path)
    return p.with_name(f"{p.stem}_variance.csv")


def _table(
    result: PoseResult,
    points: str,
    frames: np.ndarray | None,
    likelihood: np.ndarray | None,
) -> pd.DataFrame:
    import pandas as pd

    names = point_names(result, points)
    pos = positions(result, points)
    error, ncams, score = detection_stats(result, points, likelihood)
    fnum = frame_numbers(result, frames)
    data: dict[str, np.ndarray] = {}
    for k, n in enumerate(names):
        data[f"{n}_x"] = pos[:, k, 0]
        data[f"{n}_y"] = pos[:, k, 1]
        data[f"{n}_z"] = pos[:, k, 2]
        data[f"{n}_error"] = error[:, k]
        data[f"{n}_ncams"] = ncams[:, k]
        data[f"{n}_score"] = score[:, k]
    eye = np.eye(3)
    for i in range(3):
        for j in range(3):
            data[f"M_{i}{j}"] = np.full(result.n_frames, eye[i, j])
    for i in range(3):
        data[f"center_{i}"] = np.zeros(result.n_frames)
    data["fnum"] = fnum
    return pd.DataFrame(data, columns=anipose_columns(names))


def to_anipose_csv(
    result: PoseResult,
    path: str | Path,
    *,
    points: str = "joints",
    frames: np.ndarray | None = None,
    likelihood: np.ndarray | None = None,
    variance: bool = True,
) -> list[Path]:
    """Write poses as an anipose 3D CSV (what ``anipose triangulate`` writes) plus a sidecar.

    The main file has exactly anipose's columns (see :func:`anipose_columns`), so anipose's
    tools and ``movement.io.load_poses.from_anipose_file`` read it:

    * ``<name>_x, _y, _z``: positions in ``result.skeleton.units`` in the rig's world frame
      (always filled: frames without detections hold the model's posterior mean);
    * ``<name>_error``: mean reprojection error (px) of the detections used, NaN without any;
    * ``<name>_ncams``: cameras that detected the point;
    * ``<name>_score``: mean detector likelihood of those detections (``likelihood``), or 1
      when only thresholded detections are known, 0 for a model-imputed point;
    * ``M_00..M_22`` = identity and ``center_0..2`` = 0 (positions are already in the world
      frame; anipose stores its axis alignment here); ``fnum`` frame number.

    For ``points="joints"`` the quality columns aggregate the markers attached to each joint
    (a joint without markers gets error NaN, ncams 0, score 0).

    The sidecar ``<stem>_variance.csv`` (see :func:`variance_path`) holds ``fnum`` and
    ``<name>_x_var, _y_var, _z_var``: the posterior variance of each coordinate
    (units squared; NaN for a result without posterior covariance). It is separate because
    anipose readers reject other column suffixes.

    Parameters
    ----------
    result : PoseResult
        Tracked poses, T frames.
    path : path
        CSV file to write (parent folders are created).
    points : {"joints", "markers"}
        Export the J joints or the M markers.
    frames : array_like of int, shape (T,), optional
        Frame numbers for ``fnum`` (default ``result.info["frames"]`` or ``0..T-1``).
    likelihood : array_like, shape (n_cams, T, M), optional
        Detector confidences of ``result.detections`` for the ``_score`` columns.
    variance : bool
        Also write the variance sidecar.

    Returns
    -------
    list of Path
        The files written (CSV, then the sidecar). Both are written atomically.
    """
    import pandas as pd

    check_points(points)
    path = Path(path)
    if path.suffix.lower() != ".csv":
        raise ValueError(f"anipose CSV path must end in .csv, got {path.name!r}")
    table = _table(result, points, frames, likelihood)
    with atomic_write(path, "w") as fh:
        table.to_csv(fh, index=False, lineterminator="\n")
    written = [path]
    if variance:
        var = posterior_variance(result, points)
        names = point_names(result, points)
        cols: dict[str, np.ndarray] = {"fnum": table["fnum"].to_numpy()}
        for k, n in enumerate(names):
            for a, ax in enumerate("xyz"):
                cols[f"{n}_{ax}_var"] = var[:, k, a]
        side = variance_path(path)
        with atomic_write(side, "w") as fh:
            pd.DataFrame(cols).to_csv(fh, index=False, lineterminator="\n")
        written.append(side)
    return written
