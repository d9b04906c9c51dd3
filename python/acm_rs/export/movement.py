"""Export to ``movement`` (neuroinformatics-unit/movement): an xarray Dataset in its poses layout.

Layout of :func:`to_movement` (the variables and attributes ``movement.io.load_poses.from_numpy``
creates, plus acm-rs extras that movement ignores)::

    position        (time, space, keypoints, individuals)  skeleton units (e.g. mm)
    confidence      (time, keypoints, individuals)         mean detector likelihood, 0 = imputed
    position_std    (time, space, keypoints, individuals)  posterior SD, skeleton units
    frame           (time)                                 video frame number
    attrs: source_software "acm-rs", ds_type "poses", fps (Hz of the tracked frames, when
           known), time_unit "seconds" | "frames", units (length), points "joints"|"markers"

:func:`to_movement_file` writes it as netCDF (``xarray.open_dataset`` reads it back, movement's
documented way to save and load datasets). Needs ``xarray`` and a netCDF backend
(``pip install 'acm-rs[movement]'``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._common import (
    atomic_path,
    check_points,
    detection_stats,
    frame_numbers,
    point_names,
    positions,
    posterior_variance,
)

if TYPE_CHECKING:  # pragma: no cover
    import xarray as xr

    from ..tracking.result import PoseResult

__all__ = ["to_movement", "to_movement_file"]


def to_movement(
    result: PoseResult,
    *,
    fps: float | None = None,
    points: str = "joints",
    individual: str = "individual_0",
    likelihood: np.ndarray | None = None,
) -> xr.Dataset:
    """The tracked poses as a ``movement`` poses dataset.

    Parameters
    ----------
    result : PoseResult
        T tracked frames.
    fps : float, optional
        Frame rate (Hz) of the video the frame numbers count (``result.info["frames"]``,
        default 0..T-1). With it, ``time`` is in seconds (frame number / fps) and the ``fps``
        attribute is the rate of the tracked frames (fps / step when every step-th frame was
        tracked); without it, ``time`` is the frame number.
    points : {"joints", "markers"}
        Which 3D points are the keypoints.
    individual : str
        Name of the (one) individual.
    likelihood : array_like, shape (n_cams, T, M), optional
        Detector confidences of ``result.detections`` for the ``confidence`` variable
        (default: 1 where a camera detected the point, 0 where the position is imputed).

    Returns
    -------
    xarray.Dataset
        ``position`` (T, 3, P, 1), ``confidence`` (T, P, 1), ``position_std`` (T, 3, P, 1),
        coordinates ``time``, ``space`` = x, y, z, ``keypoints``, ``individuals``.
    """
    try:
        import xarray as xr
    except ImportError as exc:
        raise ImportError(
            "the movement export needs xarray (pip install 'acm-rs[movement]')"
        ) from exc
    check_points(points)
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive frame rate in Hz, got {fps}")
    pos = positions(result, points)  # (T, P, 3)
    std = np.sqrt(posterior_variance(result, points))
    _, _, score = detection_stats(result, points, likelihood)
    frames = frame_numbers(result, None)
    if fps is not None:
        time = frames / float(fps)
        step = float(np.median(np.diff(frames))) if len(frames) > 1 else 1.0
        rate = float(fps) / step if step > 0 else float(fps)
        attrs = {"fps": rate, "time_unit": "seconds"}
    else:
        time = frames.astype(float)
        attrs = {"time_unit": "frames"}
    names = list(point_names(result, points))
    dims4 = ("time", "space", "keypoints", "individuals")
    ds = xr.Dataset(
        {
            "position": (dims4, pos.transpose(0, 2, 1)[..., None]),
            "confidence": (("time", "keypoints", "individuals"), score[..., None]),
            "position_std": (dims4, std.transpose(0, 2, 1)[..., None]),
            "frame": (("time",), frames.astype(np.int64)),
        },
        coords={
            "time": time,
            "space": ["x", "y", "z"],
            "keypoints": names,
            "individuals": [individual],
        },
        attrs={
            "source_software": "acm-rs",
            "ds_type": "poses",
            **attrs,
            "units": result.skeleton.units or "unknown",
            "points": points,
            "method": str(result.info.get("method", "")),
        },
    )
    unit = result.skeleton.units or "unknown"
    ds["position"].attrs = {"units": unit, "long_name": f"3D {points} position (world frame)"}
    ds["position_std"].attrs = {"units": unit, "long_name": "posterior standard deviation"}
    ds["confidence"].attrs = {
        "long_name": "mean detector likelihood of the 2D detections used; 0 = imputed"
    }
    return ds


def to_movement_file(
    result: PoseResult,
    path: str | Path,
    *,
    fps: float | None = None,
    points: str = "joints",
    individual: str = "individual_0",
    likelihood: np.ndarray | None = None,
) -> Path:
    """Write :func:`to_movement` as a netCDF file (atomically); returns the path.

    Read it with ``xarray.open_dataset(path)``; the result passes movement's dataset validator.
    """
    ds = to_movement(result, fps=fps, points=points, individual=individual, likelihood=likelihood)
    target = Path(path)
    with atomic_path(target) as tmp:
        ds.to_netcdf(tmp)
    return target
