"""Neurodata Without Borders (NWB) export with the ``ndx-pose`` extension (>= 0.4).

Layout of the file written by :func:`to_nwb` (``processing/behavior`` unless stated)::

    general/devices/<camera>          CalibratedCamera per camera (K, R, t, distortion)
    Skeletons/<model>_joints          Skeleton: nodes = joint names, edges = bones
    Skeletons/<model>_markers         Skeleton: nodes = marker names (no edges)
    PoseEstimationJoints              MultiCameraPoseEstimation: one 3D PoseEstimationSeries
                                      per joint (skeleton units, world frame)
    PoseEstimationMarkers             MultiCameraPoseEstimation: one 3D series per marker, and
                                      one PoseEstimation per camera with the 2D detections (px)
                                      linked to that camera's CalibratedCamera
    PosteriorStdJoints                TimeSeries (T, J, 3): posterior std of each coordinate
    PosteriorStdMarkers               TimeSeries (T, M, 3)
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._common import UNIT_NAMES, atomic_path, detection_stats, posterior_variance

if TYPE_CHECKING:  # pragma: no cover
    from ..tracking.result import PoseResult

__all__ = ["to_nwb"]

_CONFIDENCE_DEFINITION = (
    "Mean detector likelihood of the 2D detections used (1 when only detections above "
    "pcutoff are known); 0 where no camera detected the point and the position is the "
    "tracking model's posterior mean."
)


def _unit_name(units: str) -> str:
    return UNIT_NAMES.get(units, units or "unknown")


def _cameras(nwbfile, rig) -> list:
    from ndx_pose import CalibratedCamera

    devices = []
    for i, cam in enumerate(rig):
        name = cam.name or f"cam_{i}"
        meta = {
            "format": "acm-rs camera (anipose calibration.toml keys, float64)",
            "name": name,
            "size": list(cam.size) if cam.size is not None else None,
            "matrix": cam.matrix.tolist(),
            "distortions": cam.dist.tolist(),
            "rotation": cam.rvec.tolist(),
            "translation": cam.tvec.tolist(),
        }
        dev = CalibratedCamera(
            name=name,
            description=(
                "Camera of the rig; x_cam = R x_world + t; distortion (k1, k2, p1, p2, k3) in "
                "OpenCV order. Full-precision parameters as JSON: " + json.dumps(meta)
            ),
            intrinsic_matrix=cam.matrix,
            rotation_matrix=cam.rotation_matrix,
            translation_vector=cam.tvec,
            distortion_coefficients=cam.dist,
        )
        nwbfile.add_device(dev)
        devices.append(dev)
    return devices


def _timing(n_t: int, rate: float | None, timestamps: np.ndarray | None, start: float) -> dict:
    if timestamps is not None:
        ts = np.asarray(timestamps, float)
        if ts.shape != (n_t,):
            raise ValueError(f"timestamps must have shape ({n_t},) (one per frame), got {ts.shape}")
        if np.any(np.diff(ts) < 0) or not np.all(np.isfinite(ts)):
            raise ValueError("timestamps must be finite and non-decreasing (seconds)")
        return {"timestamps": ts}
    if rate is None or not np.isfinite(rate) or rate <= 0:
        raise ValueError(
            f"rate must be a positive frame rate in Hz (or give timestamps), got {rate}"
        )
    return {"rate": float(rate), "starting_time": float(start)}


def to_nwb(
    result: PoseResult,
    path: str | Path,
    *,
    session_description: str,
    rate: float | None = None,
    timestamps: np.ndarray | None = None,
    starting_time: float = 0.0,
    session_start_time: _dt.datetime | None = None,
    identifier: str | None = None,
    subject_id: str | None = None,
    likelihood: np.ndarray | None = None,
    detections: bool = True,
    reference_frame: str | None = None,
) -> Path:
    """Write poses, uncertainty and calibration to an NWB file (pynwb + ndx-pose >= 0.4).

    See the module docstring for the layout. Positions are stored in the skeleton's units
    (``unit`` = e.g. ``"centimeters"``, ``conversion`` = 1); the posterior standard deviation
    (ndx-pose has no covariance field) is stored as the extra TimeSeries
    ``PosteriorStdJoints`` (T, J, 3) and ``PosteriorStdMarkers`` (T, M, 3), whose
    ``description`` names the axis order; NaN for a result without posterior covariance.
    The series' ``confidence`` is the ``_score`` of the anipose CSV (see
    :func:`acm_rs.export.to_anipose_csv`).

    Parameters
    ----------
    result : PoseResult
        Tracked poses, T frames.
    path : path
        ``.nwb`` file to write (atomically: a temporary file in the same folder is renamed).
    session_description : str
        Required by NWB: what was recorded.
    rate : float, optional
        Frame rate in Hz (give ``rate`` or ``timestamps``).
    timestamps : array_like, shape (T,), optional
        Time of each frame in seconds.
    starting_time : float
        Time of the first frame in seconds (with ``rate``).
    session_start_time : datetime, optional
        Timezone-aware start of the session (default: now, UTC).
    identifier : str, optional
        Unique file identifier (default: a random UUID).
    subject_id : str, optional
        Adds an NWB Subject with this id (linked from the Skeletons).
    likelihood : array_like, shape (n_cams, T, M), optional
        Detector likelihoods of the detections, for the confidence and the 2D series.
    detections : bool
        Store the 2D detections per camera (pixels, NaN where missing).
    reference_frame : str, optional
        Description of the world frame (default: the calibration's world frame).

    Returns
    -------
    Path
    """
    import uuid

    from ndx_pose import (
        MultiCameraPoseEstimation,
        PoseEstimationSeries,
        Skeleton,
        Skeletons,
    )
    from pynwb import NWBHDF5IO, NWBFile, TimeSeries
    from pynwb.file import Subject

    from .._version import __version__

    path = Path(path)
    if path.suffix.lower() != ".nwb":
        raise ValueError(f"NWB path must end in .nwb, got {path.name!r}")
    if not session_description:
        raise ValueError("session_description must be a non-empty string (NWB requires it)")
    sk = result.skeleton
    n_t = result.n_frames
    timing = _timing(n_t, rate, timestamps, starting_time)
    if session_start_time is None:
        session_start_time = _dt.datetime.now(_dt.UTC)
    elif session_start_time.tzinfo is None:
        raise ValueError("session_start_time must be timezone-aware (e.g. tzinfo=datetime.UTC)")
    if max(sk.n_joints, sk.n_markers) > 256:
        raise ValueError("ndx-pose stores skeleton edges as uint8: at most 256 nodes")
    unit = _unit_name(sk.units)
    ref = reference_frame or (
        "world frame of the camera calibration (x_cam = R x_world + t); origin and axes as "
        "defined by the calibration"
    )

    nwbfile = NWBFile(
        session_description=session_description,
        identifier=identifier or str(uuid.uuid4()),
        session_start_time=session_start_time,
    )
    subject = None
    if subject_id is not None:
        subject = Subject(subject_id=subject_id)
        nwbfile.subject = subject
    cams = _cameras(nwbfile, result.rig)
    behavior = nwbfile.create_processing_module(
        name="behavior", description="3D pose tracked by acm-rs (ACM, Monsees et al. 2022)"
    )
    edges = np.asarray(sk.bones, dtype=np.uint8).reshape(-1, 2)
    sk_joints = Skeleton(
        name=f"{sk.name}_joints", nodes=list(sk.joint_names), edges=edges, subject=subject
    )
    sk_markers = Skeleton(
        name=f"{sk.name}_markers",
        nodes=list(sk.marker_names),
        edges=np.zeros((0, 2), np.uint8),
        subject=subject,
    )
    behavior.add(Skeletons(skeletons=[sk_joints, sk_markers]))

    software = {"source_software": "acm-rs", "source_software_version": __version__}
    method = result.info.get("method", "unknown")
    for points, names, data, skel in (
        ("joints", sk.joint_names, result.joints, sk_joints),
        ("markers", sk.marker_names, result.markers, sk_markers),
    ):
        _, _, score = detection_stats(result, points, likelihood)
        series = [
            PoseEstimationSeries(
                name=n,
                description=f"3D position of {points[:-1]} {n!r}",
                data=np.asarray(data[:, k], float),
                unit=unit,
                reference_frame=ref,
                confidence=np.asarray(score[:, k], float),
                confidence_definition=_CONFIDENCE_DEFINITION,
                **timing,
            )
            for k, n in enumerate(names)
        ]
        views = []
        if points == "markers" and detections:
            views = _views(result, cams, sk_markers, likelihood, timing, software)
        behavior.add(
            MultiCameraPoseEstimation(
                name=f"PoseEstimation{points.capitalize()}",
                pose_estimation_series=series,
                pose_estimations=views,
                description=(
                    f"3D {points} of the {sk.name} model from the ACM unscented Kalman smoother "
                    f"(method {method!r}) over {len(result.rig)} cameras"
                ),
                scorer=f"acm-rs {method}",
                skeleton=skel,
                **software,
            )
        )
        std = np.sqrt(posterior_variance(result, points))
        behavior.add(
            TimeSeries(
                name=f"PosteriorStd{points.capitalize()}",
                data=std,
                unit=unit,
                description=(
                    f"Posterior standard deviation of each {points[:-1]} coordinate, shape "
                    f"(time, {points}, xyz); axis 1 in the order of Skeleton "
                    f"{skel.name!r} nodes: {json.dumps(list(names))}"
                ),
                **timing,
            )
        )

    with atomic_path(path) as tmp:
        with NWBHDF5IO(str(tmp), "w") as io:
            io.write(nwbfile)
    return path


def _views(result, cams, skeleton, likelihood, timing, software) -> list:
    """One PoseEstimation (2D detections, px) per camera, linked to its CalibratedCamera."""
    from ndx_pose import PoseEstimation, PoseEstimationSeries

    det = np.asarray(result.detections, float)
    lik = None if likelihood is None else np.asarray(likelihood, float)
    views = []
    for c, dev in enumerate(cams):
        seen = np.all(np.isfinite(det[c]), axis=-1)
        conf = seen.astype(float) if lik is None else np.where(seen, lik[c], 0.0)
        series = [
            PoseEstimationSeries(
                name=n,
                description=f"2D detection of marker {n!r} in camera {dev.name!r}",
                data=det[c, :, k],
                unit="pixels",
                reference_frame="(0, 0) is the centre of the top-left pixel; y points down",
                confidence=conf[:, k],
                confidence_definition="detector likelihood; 0 where missing or below pcutoff",
                **timing,
            )
            for k, n in enumerate(result.marker_names)
        ]
        views.append(
            PoseEstimation(
                name=f"detections_{dev.name}",
                pose_estimation_series=series,
                description=f"2D detections used for tracking, camera {dev.name!r}",
                device=dev,
                skeleton=skeleton,
                **software,
            )
        )
    return views
