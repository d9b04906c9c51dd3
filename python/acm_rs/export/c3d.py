"""C3D motion-capture export (ezc3d): 3D markers, optionally joints as virtual markers."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._common import UNIT_MM, atomic_path, detection_stats

if TYPE_CHECKING:  # pragma: no cover
    from ..tracking.result import PoseResult

__all__ = ["to_c3d"]


def to_c3d(
    result: PoseResult,
    path: str | Path,
    rate: float,
    *,
    joints: bool = False,
    joint_prefix: str = "joint_",
    units: str = "mm",
) -> Path:
    """Write the 3D markers (and optionally the joints) as a C3D file with ezc3d.

    ``POINT:LABELS`` are the marker names (joints follow as virtual markers named
    ``joint_prefix + name``), ``POINT:UNITS`` is ``units``, ``POINT:RATE`` is ``rate``.
    Positions are converted from ``result.skeleton.units`` to ``units`` (mm by default, what
    most C3D readers expect); ``POINT:DESCRIPTIONS`` say which points are markers and which
    joints. Frames where a point is not finite are written as NaN with residual -1 (the C3D
    "invalid" flag); a valid point has residual 1 if some camera detected it and 0 if only the
    tracking model placed it (C3D's value for a computed point; camera mask 0), written by the
    C3D specification (residual in the low byte of the fourth word), the convention of every C3D
    file acm-rs writes (:data:`acm_rs.gapfill.io.C3D_RESIDUALS`; the file carries the
    ``ACM_RS:FILLED_RESIDUAL`` parameter, so :func:`acm_rs.gapfill.io.read` reads such
    points back as filled).

    Parameters
    ----------
    result : PoseResult
        Tracked poses, T frames.
    path : path
        ``.c3d`` file (written to a temporary file in the same folder, then renamed).
    rate : float
        Frame rate in Hz.
    joints : bool
        Append the J joints as virtual markers.
    joint_prefix : str
        Label prefix of the joints (marker and joint names overlap in the ACM models).
    units : {"mm", "cm", "m"}
        Length unit of the file.

    Returns
    -------
    Path
    """
    import ezc3d

    from ..gapfill import c3d_stream
    from ..gapfill.io import C3D_RESIDUALS, C3D_WORD4, set_c3d_frame_count

    path = Path(path)
    if path.suffix.lower() != ".c3d":
        raise ValueError(f"C3D path must end in .c3d, got {path.name!r}")
    if not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"rate must be a positive frame rate in Hz, got {rate}")
    src = result.skeleton.units
    if units not in UNIT_MM:
        raise ValueError(f"units must be one of {sorted(UNIT_MM)}, got {units!r}")
    if src not in UNIT_MM:
        raise ValueError(
            f"cannot convert skeleton units {src!r} to {units!r}: the skeleton's units must be "
            f"one of {sorted(UNIT_MM)} (set skeleton.units)"
        )
    scale = UNIT_MM[src] / UNIT_MM[units]
    labels = list(result.marker_names)
    descriptions = [f"marker {n} ({result.skeleton.name} model)" for n in labels]
    pts = [np.asarray(result.markers, float)]
    _, ncams, _ = detection_stats(result, "markers")
    seen = [ncams > 0]
    if joints:
        jl = [joint_prefix + n for n in result.joint_names]
        clash = sorted(set(jl) & set(labels))
        if clash:
            raise ValueError(f"joint labels {clash} clash with marker names; change joint_prefix")
        labels += jl
        descriptions += [f"joint {n} (virtual marker)" for n in result.joint_names]
        pts.append(np.asarray(result.joints, float))
        _, jcams, _ = detection_stats(result, "joints")
        seen.append(jcams > 0)
    xyz = np.concatenate(pts, axis=1) * scale  # (T, P, 3)
    measured = np.concatenate(seen, axis=1)  # (T, P)
    n_t, n_p = xyz.shape[:2]
    valid = np.all(np.isfinite(xyz), axis=2)  # (T, P)
    measured_r, filled_r = C3D_RESIDUALS["measured_unknown"], C3D_RESIDUALS["filled"]
    residuals = np.where(valid, np.where(measured, measured_r, filled_r), C3D_RESIDUALS["missing"])

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(rate)]
    c["parameters"]["POINT"]["LABELS"]["value"] = labels
    c["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = descriptions
    c["parameters"]["POINT"]["UNITS"]["value"] = [units]
    c.add_parameter("PROCESSING", "SOFTWARE", "acm-rs")
    c.add_parameter("ACM_RS", "FILLED_RESIDUAL", [float(filled_r)])
    c.add_parameter("ACM_RS", "WORD4", [C3D_WORD4])
    scale = float(np.asarray(c["parameters"]["POINT"]["SCALE"]["value"]).ravel()[0])
    if n_t > 65535 or 16 * n_t * n_p > c3d_stream.STREAM_BYTES:
        # long recordings: ezc3d's header and parameters, the frames in blocks (bounded
        # memory; over 65,535 frames in the layout ezc3d reads whole; gapfill/c3d_stream.py)
        xyz[~valid] = np.nan
        c3d_stream.write_streamed(path, c, xyz, residuals, None)
        return path
    data = np.ones((4, n_p, n_t))
    data[:3] = xyz.transpose(2, 1, 0)
    data[:3, ~valid.T] = np.nan
    c["data"]["points"] = data
    c["data"]["meta_points"]["residuals"] = residuals.T[None]
    set_c3d_frame_count(c, n_t)  # recordings over 65535 frames
    with atomic_path(path) as tmp:
        c.write(str(tmp))
        # the fourth words by the C3D specification (ezc3d swaps their two bytes)
        c3d_stream.patch_point_words(Path(tmp), residuals, scale)
    return path
