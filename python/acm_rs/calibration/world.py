"""World frames for calibrated rigs (and :func:`triangulate`, re-exported from learning)."""

from __future__ import annotations

import numpy as np

from .._arrays import as_float_array
from ..camera import Camera, CameraRig
from ..learning import triangulate  # DLT on undistorted rays, shared with learning
from ..rotation import rodrigues_inverse

__all__ = ["frame_from_points", "transform_rig", "triangulate"]


def frame_from_points(points) -> tuple[np.ndarray, np.ndarray]:
    """A right-handed frame from three points.

    Parameters
    ----------
    points : array_like, shape (3, 3)
        Rows: the new origin, a point on the new +x axis, a point in the new xy plane on the
        +y side (world units).

    Returns
    -------
    rot : numpy.ndarray, shape (3, 3)
        Columns: the new x, y, z axes in current world coordinates.
    origin : numpy.ndarray, shape (3,)
        So that ``x_current = rot @ x_new + origin``.

    Raises
    ------
    ValueError
        Non-finite or (nearly) collinear points.
    """
    p = as_float_array(points, "points", (3, 3))
    if p.shape != (3, 3):
        raise ValueError(f"points must have shape (3, 3), got {p.shape}")
    o = p[0]
    x = p[1] - o
    y = p[2] - o
    nx = np.linalg.norm(x)
    if nx == 0:
        raise ValueError("the x-axis point coincides with the origin")
    x = x / nx
    y = y - (y @ x) * x
    ny = np.linalg.norm(y)
    if ny <= 1e-9 * max(nx, np.linalg.norm(p[2] - o)):
        raise ValueError("the three points are collinear: they do not define a plane")
    y = y / ny
    return np.stack([x, y, np.cross(x, y)], axis=1), o.copy()


def transform_rig(rig: CameraRig, rot: np.ndarray, origin: np.ndarray) -> CameraRig:
    """The rig expressed in a new world frame with ``x_current = rot @ x_new + origin``.

    Parameters
    ----------
    rig : CameraRig
    rot : numpy.ndarray, shape (3, 3)
        Proper rotation (columns: new axes in current coordinates).
    origin : numpy.ndarray, shape (3,)
        New origin in current world units.
    """
    rot = np.asarray(rot, float)
    origin = np.asarray(origin, float)
    if abs(np.linalg.det(rot) - 1.0) > 1e-6 or np.abs(rot.T @ rot - np.eye(3)).max() > 1e-6:
        raise ValueError("rot must be a proper rotation matrix")
    cams = []
    for cam in rig:
        r = cam.rotation_matrix
        cams.append(
            Camera(
                cam.matrix,
                cam.dist,
                rodrigues_inverse(r @ rot),
                r @ origin + cam.tvec,
                cam.size,
                cam.name,
            )  # fmt: skip
        )
    return CameraRig(cams, rig.units)
