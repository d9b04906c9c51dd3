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
rotation moves is the file's ``skeleton_vertices_links``, used as the authors' tool uses it
(:func:`file_links`): in the authors' own files a rotation moves its bone and the bone's
descendants (the tree rule, acm-rs's default); any other matrix is applied as it stands.
``docs/models.md`` lists every fact with its source.
"""

from __future__ import annotations

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


def tree_links(parents: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``[i, j]``: the rotation of bone ``i`` moves bone ``j`` when ``j`` is ``i`` or one of
    its descendants (the tree rule; the authors' documentation of
    ``skeleton_vertices_links``). Bones as in ``edges``."""
    par = np.asarray(parents)
    n = len(edges)
    out = np.zeros((n, n), dtype=bool)
    for i, (_, ei) in enumerate(edges):
        for j, (_, ej) in enumerate(edges):
            a = int(ej)
            while a >= 0 and a != ei:
                a = int(par[a])
            out[i, j] = a == ei
    return out


def literal_alg1_links(parents: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """``[i, j]``: the literal reading of Alg. 1 line 5, "if j₁ is child of i₀": bone ``i``
    moves bone ``j`` when ``j``'s end joint descends from ``i``'s start joint (so also the
    siblings that share ``i``'s start joint). Bones as in ``edges``."""
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


def file_links(
    links: np.ndarray | None, parents: np.ndarray, edges: np.ndarray
) -> tuple[np.ndarray, str]:
    """The link matrix the authors' forward model applies for a ``model.npy`` (bones as in
    ``edges``) and the name of its rule (``"tree"``, ``"literal Alg. 1"`` or ``"other"``).

    ``adjust_joint_marker_pos2`` applies the global rotation ``r0`` (the first bone's) to
    every bone whatever row 0 says, and then, in file order, the rotation of bone ``i`` to
    the bones ``links[i]`` marks; a file without links gets the tree rule.
    """
    n = len(edges)
    if links is None:
        lk = tree_links(parents, edges)
    else:
        lk = np.array(links, dtype=bool)
        if lk.shape != (n, n):
            raise ValueError(
                f"model.npy: skeleton_vertices_links has shape {lk.shape}, expected ({n}, {n})"
            )
    lk[0] = True  # r0, the global rotation, moves every bone
    rule = "other"
    for name, ref in (
        ("tree", tree_links(parents, edges)),
        ("literal Alg. 1", literal_alg1_links(parents, edges)),
    ):
        ref[0] = True
        if np.array_equal(lk, ref):
            rule = name
            break
    return lk, rule
