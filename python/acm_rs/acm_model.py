"""The authors' skeleton from an ACM ``model.npy``: rest frames, rotation links, marker rules.

The authors' tool (bbo-lab/ACM, ``helper.get_model3d`` + ``anatomy.py`` + ``model.py``) does
not pose the skeleton as ``model.npy`` draws it. Its forward model (``adjust_joint_marker_pos2``)
starts every bone from the identity frame, so with every rotation zero the skeleton is a
straight line along +z, except the four girdle bones (``spine_004 -> shoulder_*``,
``spine_002 -> hip_*``), whose rest frames ``coords0`` come from the file's ``skeleton_coords``
(``anatomy.get_skeleton_coords0``):

* hips: the file's frame, written as x-y-z Euler angles (``R = Rx Ry Rz``, the solution with
  the smaller squared norm) rounded to float16 and rebuilt;
* shoulders: the same after a turn about +z by the angle between the shoulder and the hip
  axes in the xy-plane of the file (``arccos`` of their dot product: always a positive turn).

Bones grow along the z-axis of their frame; a marker moves with the bone that ends at its
joint, its offset in that bone's frame; a marker on the root gets no offset. Which bones a
rotation moves is the file's ``skeleton_vertices_links``; Alg. 1 (and our forward kinematics)
moves every bone whose end joint descends from the rotated bone's start joint, and a file
with another rule is reported. ``docs/models.md`` lists every fact with its source.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence

import numpy as np

GIRDLE_JOINTS = ("hip_left", "hip_right", "shoulder_left", "shoulder_right")


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_xyz(angles: Sequence[float]) -> np.ndarray:
    """``Rx(a) @ Ry(b) @ Rz(c)`` for angles ``(a, b, c)`` in rad (``anatomy.r2R_xyz``)."""
    a, b, c = (float(v) for v in angles)
    return _rx(a) @ _ry(b) @ _rz(c)


def euler_xyz_angles(rot: np.ndarray) -> np.ndarray:
    """The x-y-z Euler angles of ``rot`` with the smaller squared norm, rounded to float16.

    Both solutions of ``rot = Rx Ry Rz`` (``b`` and ``pi - b``) are formed and rounded to
    float16 as the authors' ``recover_coord_xyz`` does (with zero bounds, where both count
    as valid); the one with the smaller sum of squares is returned (float64 values).
    """
    r = np.asarray(rot, dtype=np.float64)
    sy = float(np.clip(r[0, 2], -1.0, 1.0))
    out = []
    for b in (np.arcsin(sy), np.pi - np.arcsin(sy)):
        cb = np.cos(b)
        a = np.arctan2(-r[1, 2] / cb, r[2, 2] / cb)
        c = np.arctan2(-r[0, 1] / cb, r[0, 0] / cb)
        out.append(np.array([a, b, c], dtype=np.float16).astype(np.float64))
    return out[0] if np.sum(out[0] ** 2) < np.sum(out[1] ** 2) else out[1]


def girdle_frames(
    joint_names: Sequence[str],
    edges: np.ndarray,
    vertices: np.ndarray,
    coords: np.ndarray,
) -> dict[int, np.ndarray]:
    """Rest frames of the girdle bones (``anatomy.get_skeleton_coords0``), by file bone index.

    Parameters
    ----------
    joint_names : sequence of str
        The file's joint names without the ``joint_`` prefix.
    edges : numpy.ndarray, shape (n_bones, 2)
        ``skeleton_edges`` (start, end) joint indices.
    vertices : numpy.ndarray, shape (n_joints, 3)
        ``skeleton_vertices``.
    coords : numpy.ndarray, shape (n_bones, 3, 3)
        ``skeleton_coords`` (columns = bone axes).

    Returns
    -------
    dict
        ``{bone index: (3, 3) rotation}`` for the bones ending at ``hip_left``, ``hip_right``,
        ``shoulder_left`` and ``shoulder_right`` (empty when the model lacks one of them).
    """
    names = list(joint_names)
    if not all(n in names for n in GIRDLE_JOINTS):
        return {}
    end_bone = {int(e): b for b, (_, e) in enumerate(np.asarray(edges))}
    bone = {n: end_bone[names.index(n)] for n in GIRDLE_JOINTS}
    v = np.asarray(vertices, dtype=np.float64)

    def axis_xy(left: str, right: str) -> np.ndarray:
        d = v[names.index(right)] - v[names.index(left)]
        d = d[:2]
        norm = np.linalg.norm(d)
        if norm == 0:
            raise ValueError(f"model.npy: {left} and {right} coincide in the xy-plane")
        return d / norm

    pelvis = axis_xy("hip_left", "hip_right")
    collar = axis_xy("shoulder_left", "shoulder_right")
    turn = _rz(float(np.arccos(np.clip(collar @ pelvis, -1.0, 1.0))))
    out = {}
    for n in GIRDLE_JOINTS:
        c = np.asarray(coords[bone[n]], dtype=np.float64)
        if n.startswith("shoulder"):
            c = turn @ c
        out[bone[n]] = euler_xyz(euler_xyz_angles(c))
    return out


def alg1_links(parents: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``[i, j]``: Alg. 1 lets the rotation of bone ``i`` move bone ``j`` (the end joint of
    ``j`` is a child, at any depth, of the start joint of ``i``). Bones as in ``edges``."""
    par = np.asarray(parents)
    n = len(edges)
    out = np.zeros((n, n), dtype=bool)
    for i, (si, _) in enumerate(edges):
        for j, (_, ej) in enumerate(edges):
            a = int(par[int(ej)])
            while a >= 0 and a != si:
                a = int(par[a])
            out[i, j] = a == si
    return out


def check_links(
    links: np.ndarray | None, parents: np.ndarray, edges: np.ndarray, bone_names: Sequence[str]
) -> list[str]:
    """Compare the file's ``skeleton_vertices_links`` with Alg. 1; warn and return the
    differences (``"rotation of A moves B"`` lines) when the file uses another rule."""
    if links is None:
        return []
    lk = np.asarray(links, dtype=bool)
    ref = alg1_links(parents, edges)
    if lk.shape != ref.shape:
        raise ValueError(
            f"model.npy: skeleton_vertices_links has shape {lk.shape}, expected {ref.shape}"
        )
    diff = []
    # row 0 is unused: the first bone's rotation is the global one (moves everything)
    for i0, j in zip(*np.nonzero(lk[1:] != ref[1:]), strict=True):
        i = i0 + 1
        verb = "moves" if lk[i, j] else "does not move"
        diff.append(f"rotation of bone {bone_names[i]} {verb} bone {bone_names[j]}")
    if diff:
        warnings.warn(
            "model.npy: skeleton_vertices_links differs from Alg. 1 (which acm-rs implements) "
            f"in {len(diff)} entries, e.g. {'; '.join(diff[:3])}. Poses are computed with "
            "Alg. 1's rule; results can differ from the authors' tool for this model.",
            stacklevel=3,
        )
    return diff
