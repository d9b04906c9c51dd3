"""Pure-NumPy reference of the ACM geometry: Rodrigues rotations, forward kinematics (Alg. 1)
and the OpenCV camera projection (ACM supplement sections 1, 2.1 and 3.1).

This module is the baseline of ``benches/bench_fk_projection.py`` and an independent check of
the Rust core in ``tests/test_numpy_reference.py``. It uses nothing from :mod:`acm_rs` except
the structure arrays of a :class:`acm_rs.Skeleton` (``parents``, ``bones``, ``rest_frames``,
``bone_lengths``, ``marker_offsets``, ``marker_joints``, ``marker_bones``).

Semantics (Alg. 1, eq. 8):

* Bone ``b`` runs from ``bones[b, 0]`` (start joint) to ``bones[b, 1]`` (end joint).
* The global orientation of bone ``j`` is ``R_j = Q_{a1} Q_{a2} ... Q_{ak} Rbar_j`` with
  ``Q_i = rodrigues(r_i)``; the product runs over the bones ``i`` with ``bone_links[i, j]``
  (by default bone ``j`` and its ancestors: a rotation moves its bone and the bone's
  descendants, never its siblings), in the order ``link_order`` (default: bone index).
* ``p_root = t`` and ``p_end(j) = p_start(j) + R_j[:, 2] * l_j``.
* Marker ``k`` is ``m_k = p_{joint(k)} + R_{b(k)} v_k`` with ``b(k) = marker_bones[k]``.


Implementation notes (speed, so that the benchmark compares against good NumPy):

* Everything is vectorised over frames; only the 28 bones (or joints) are looped over.
* Arrays are held "frames last" (e.g. ``(3, 3, T)`` for a stack of rotations) so that every
  3x3 product is a handful of long contiguous vector operations, which is several times faster
  than ``matmul`` on ``(T, 3, 3)`` stacks.
* ``R_j`` is never formed: the accumulated rotation ``A_j = Q_{a1} ... Q_{ak}`` of each bone
  is computed once (from the product of another bone whose acting bones are a prefix of its
  own, e.g. its parent bone's) and applied to the constant vectors ``Rbar_j e_z l_j`` and
  ``Rbar_{b(k)} v_k``.
* Joint positions are the root translation plus a sum of bone vectors along the path from the
  root, a single ``(J, B) @ (B, T)`` matrix product per coordinate.
* Frames (and projected points) are processed in blocks that fit in the CPU cache.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Points at or closer than this depth (camera z) are "behind" the camera and give NaN pixels.
MIN_DEPTH = 1e-9

_FRAMES_PER_BLOCK = 512
_POINTS_PER_BLOCK = 8192


# -- rotations ------------------------------------------------------------------------------
def _rodrigues_frames_last(r: np.ndarray) -> np.ndarray:
    """Rotation matrices of Rodrigues vectors held frames last: ``(3, ...)`` -> ``(3, 3, ...)``.

    Uses ``R = cos(theta) I + a [r]x + b r r^T`` with ``a = sin(theta) / theta`` and
    ``b = (1 - cos(theta)) / theta^2``, written with the half angle: ``h = sin(theta/2) / theta``
    (``h(0) = 1/2``), ``a = 2 h cos(theta/2)``, ``b = 2 h^2`` and ``cos(theta) = 1 - b theta^2``.
    This is exact at ``theta = 0``, free of the cancellation in ``1 - cos(theta)``, and needs
    only one ``sin`` and one ``cos`` per rotation (NumPy's float64 ``sin``/``cos`` cost far more
    than its arithmetic).
    """
    x, y, z = r[0], r[1], r[2]
    theta2 = x * x
    theta2 += y * y
    theta2 += z * z
    theta = np.sqrt(theta2)
    half = 0.5 * theta
    h = np.divide(np.sin(half), theta, out=np.full_like(theta, 0.5), where=theta > 0.0)
    a = np.cos(half, out=half)
    a *= h
    a *= 2.0
    b = np.multiply(h, h, out=h)
    b *= 2.0
    c = np.multiply(b, theta2, out=theta2)
    np.subtract(1.0, c, out=c)
    bx, by, bz = b * x, b * y, b * z
    ax, ay, az = a * x, a * y, a * z
    out = np.empty((3, 3) + x.shape)
    np.multiply(bx, x, out=out[0, 0])
    out[0, 0] += c
    np.multiply(by, y, out=out[1, 1])
    out[1, 1] += c
    np.multiply(bz, z, out=out[2, 2])
    out[2, 2] += c
    # Off-diagonal pairs (i, k) with [r]x[i, k] = -a r_l and [r]x[k, i] = +a r_l.
    for i, k, bik, arl in ((0, 1, bx * y, az), (1, 2, by * z, ax), (2, 0, bz * x, ay)):
        np.subtract(bik, arl, out=out[i, k])
        np.add(bik, arl, out=out[k, i])
    return out


def rodrigues_np(r: np.ndarray) -> np.ndarray:
    """Rotation matrices of Rodrigues vectors (ACM supp. eq. 2).

    Parameters
    ----------
    r : array_like, shape (..., 3)
        Rodrigues vectors ``theta * axis`` (rad).

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        ``R = I + sin(theta) K + (1 - cos(theta)) K^2`` with ``K`` the cross-product matrix of
        the unit axis; the identity for ``r = 0``.
    """
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-1:] != (3,):
        raise ValueError(f"r must have shape (..., 3), got {r.shape}")
    rot = _rodrigues_frames_last(np.moveaxis(r, -1, 0))
    return np.ascontiguousarray(np.moveaxis(rot, (0, 1), (-2, -1)))


def _matmul_fl(a: np.ndarray, b: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``a @ b`` for frames-last stacks of 3x3 matrices, shapes ``(3, 3, T)``."""
    return np.einsum("ijt,jkt->ikt", a, b, out=out)


# -- forward kinematics ---------------------------------------------------------------------
@dataclass(frozen=True)
class FKPlan:
    """Structure of a skeleton prepared for :func:`forward_np` (constant across poses).

    Attributes
    ----------
    n_joints, n_bones, n_markers : int
    root : int
        Root joint index.
    steps : tuple of (int, tuple of int)
        One entry (slot) per bone, in an order where every base comes first: the slot whose
        accumulated rotation is the left factor, or -1 for the identity, and the bones whose
        rotations are multiplied on the right, in application order.
    bone_slot : numpy.ndarray, shape (n_bones,)
        Slot of each bone.
    bone_vectors : numpy.ndarray, shape (n_bones, 3)
        ``Rbar_b e_z l_b``: the bone vector in the rest orientation.
    path : numpy.ndarray, shape (n_joints, n_bones)
        1 where bone ``b`` lies on the path from the root to joint ``j``.
    marker_joints : numpy.ndarray, shape (M,)
    marker_slot : numpy.ndarray, shape (M,)
        Slot of each marker's bone.
    marker_vectors : numpy.ndarray, shape (M, 3)
        ``Rbar_{b(k)} v_k``: marker offsets rotated into the rest orientation.
    """

    n_joints: int
    n_bones: int
    n_markers: int
    root: int
    steps: tuple[tuple[int, tuple[int, ...]], ...]
    bone_slot: np.ndarray
    bone_vectors: np.ndarray
    path: np.ndarray
    marker_joints: np.ndarray
    marker_slot: np.ndarray
    marker_vectors: np.ndarray


def _ancestors_or_self(parents: np.ndarray, j: int) -> list[int]:
    out = [j]
    while parents[out[-1]] >= 0:
        out.append(int(parents[out[-1]]))
        if len(out) > len(parents):
            raise ValueError("parents do not form a tree")
    return out


def fk_plan(skeleton) -> FKPlan:
    """Precompute the pose-independent structure of :func:`forward_np`.

    Parameters
    ----------
    skeleton : acm_rs.Skeleton
        Only its structure arrays are read.

    Returns
    -------
    FKPlan
    """
    parents = np.asarray(skeleton.parents, dtype=np.int64)
    bones = np.asarray(skeleton.bones, dtype=np.int64)
    rest = np.asarray(skeleton.rest_frames, dtype=np.float64)
    lengths = np.asarray(skeleton.bone_lengths, dtype=np.float64)
    offsets = np.asarray(skeleton.marker_offsets, dtype=np.float64)
    marker_joints = np.asarray(skeleton.marker_joints, dtype=np.int64)
    marker_bones = np.asarray(skeleton.marker_bones, dtype=np.int64)
    n_joints, n_bones = len(parents), len(bones)
    root = int(np.flatnonzero(parents < 0)[0])
    anc = [_ancestors_or_self(parents, j) for j in range(n_joints)]

    # Bones acting on each bone, in application order (the product of eq. 8).
    links = np.asarray(skeleton.bone_links, dtype=bool)
    order = [int(i) for i in getattr(skeleton, "link_order", range(n_bones))]
    acting = [[i for i in order if links[i, b]] for b in range(n_bones)]
    by_len = sorted(range(n_bones), key=lambda b: len(acting[b]))
    slot = {b: s for s, b in enumerate(by_len)}
    steps = []
    for k, b in enumerate(by_len):
        base = max(
            (c for c in by_len[:k] if acting[b][: len(acting[c])] == acting[c]),
            key=lambda c: len(acting[c]),
            default=None,
        )
        if base is None:
            steps.append((-1, tuple(acting[b])))  # the full product
        else:
            steps.append((slot[base], tuple(acting[b][len(acting[base]) :])))  # A_base Q...

    path = np.zeros((n_joints, n_bones))
    bone_of_end = {int(e): b for b, e in enumerate(bones[:, 1])}
    for j in range(n_joints):
        for a in anc[j]:
            if a in bone_of_end:
                path[j, bone_of_end[a]] = 1.0
    return FKPlan(
        n_joints=n_joints,
        n_bones=n_bones,
        n_markers=len(marker_joints),
        root=root,
        steps=tuple(steps),
        bone_slot=np.array([slot[b] for b in range(n_bones)], dtype=np.int64),
        bone_vectors=rest[:, :, 2] * lengths[:, None],
        path=path,
        marker_joints=marker_joints,
        marker_slot=np.array([slot[int(b)] for b in marker_bones], dtype=np.int64),
        marker_vectors=np.einsum("kij,kj->ki", rest[marker_bones], offsets),
    )


def _forward_block(plan: FKPlan, t: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames-last forward kinematics: ``t (3, T)``, ``r (3, B, T)`` -> ``(3, J, T), (3, M, T)``."""
    n_t = t.shape[1]
    q = _rodrigues_frames_last(r)  # (3, 3, B, T)
    acc = np.empty((len(plan.steps), 3, 3, n_t))  # A_j per bone, frames last
    for s, (base, own) in enumerate(plan.steps):
        factors = ([acc[base]] if base >= 0 else []) + [q[:, :, b] for b in own]
        if not factors:
            acc[s] = np.eye(3)[:, :, None]
        elif len(factors) == 1:
            acc[s] = factors[0]
        else:
            cur = factors[0]
            for f in factors[1:-1]:
                cur = _matmul_fl(cur, f)
            _matmul_fl(cur, factors[-1], out=acc[s])
    # Bone vectors R_j e_z l_j = A_start(j) (Rbar_j e_z l_j), then joints by path sums.
    dirs = np.einsum("bijt,bj->ibt", acc[plan.bone_slot], plan.bone_vectors)
    joints = np.matmul(plan.path, dirs)  # (3, J, T)
    joints += t[:, None, :]
    markers = np.einsum("kijt,kj->ikt", acc[plan.marker_slot], plan.marker_vectors)
    markers += joints[:, plan.marker_joints]
    return joints, markers


def forward_np(
    skeleton,
    t: np.ndarray,
    r: np.ndarray,
    *,
    plan: FKPlan | None = None,
    block: int = _FRAMES_PER_BLOCK,
) -> tuple[np.ndarray, np.ndarray]:
    """Forward kinematics (Alg. 1) of many poses, vectorised over frames.

    Parameters
    ----------
    skeleton : acm_rs.Skeleton
        Source of the structure arrays (ignored when ``plan`` is given).
    t : array_like, shape (T, 3)
        Root joint positions (world units).
    r : array_like, shape (T, n_bones, 3)
        Rodrigues vector per bone (rad).
    plan : FKPlan, optional
        Result of :func:`fk_plan` for ``skeleton``, to skip the structure set-up.
    block : int
        Frames processed at once (a cache-size trade-off; the result does not depend on it).

    Returns
    -------
    joints : numpy.ndarray, shape (T, J, 3)
    markers : numpy.ndarray, shape (T, M, 3)
    """
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    if plan is None:
        plan = fk_plan(skeleton)
    t = np.asarray(t, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 3 or r.shape != (t.shape[0], plan.n_bones, 3):
        raise ValueError(
            f"expected t (T, 3) and r (T, {plan.n_bones}, 3), got {t.shape} and {r.shape}"
        )
    n_t = t.shape[0]
    joints = np.empty((n_t, plan.n_joints, 3))
    markers = np.empty((n_t, plan.n_markers, 3))
    for f0 in range(0, n_t, block):
        f1 = min(f0 + block, n_t)
        tb = np.ascontiguousarray(t[f0:f1].T)
        rb = np.ascontiguousarray(r[f0:f1].transpose(2, 1, 0))
        jb, mb = _forward_block(plan, tb, rb)
        joints[f0:f1] = jb.transpose(2, 1, 0)
        markers[f0:f1] = mb.transpose(2, 1, 0)
    return joints, markers


# -- projection -----------------------------------------------------------------------------
def project_np(
    params: np.ndarray, points: np.ndarray, *, block: int = _POINTS_PER_BLOCK
) -> np.ndarray:
    """Project world points into cameras with the OpenCV model (ACM supp. eqs. 4-6).

    ``x_cam = R(rvec) x + tvec``; ``x' = X / Z``, ``y' = Y / Z``, ``r2 = x'^2 + y'^2``;
    ``x'' = x' (1 + k1 r2 + k2 r2^2 + k3 r2^3) + 2 p1 x' y' + p2 (r2 + 2 x'^2)``,
    ``y'' = y' (1 + k1 r2 + k2 r2^2 + k3 r2^3) + p1 (r2 + 2 y'^2) + 2 p2 x' y'``;
    ``u = fx x'' + s y'' + cx``, ``v = fy y'' + cy`` (skew ``s``, MATLAB's; 0 in OpenCV's).

    Parameters
    ----------
    params : array_like, shape (C, 16) or (C, 15)
        Per camera ``[rx, ry, rz, tx, ty, tz, fx, fy, cx, cy, k1, k2, p1, p2, k3, s]``;
        15 columns: no skew.
    points : array_like, shape (..., 3)
        World coordinates.
    block : int
        Points processed at once (the result does not depend on it).

    Returns
    -------
    numpy.ndarray, shape (C, ..., 2)
        Pixels ``(u, v)``; NaN for NaN points and for points with depth ``Z <= MIN_DEPTH``.
    """
    params = np.asarray(params, dtype=np.float64)
    if params.ndim != 2 or params.shape[1] not in (15, 16):
        raise ValueError(f"params must have shape (C, 16) or (C, 15), got {params.shape}")
    skew = params[:, 15, None] if params.shape[1] == 16 else np.zeros((params.shape[0], 1))
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3), got {points.shape}")
    lead = points.shape[:-1]
    flat = points.reshape(-1, 3)
    n_cam, n_pts = params.shape[0], flat.shape[0]
    rot = rodrigues_np(params[:, 0:3])  # (C, 3, 3)
    tvec = params[:, 3:6, None]  # (C, 3, 1)
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = (params[:, i, None] for i in range(6, 15))
    two_p1, two_p2 = 2.0 * p1, 2.0 * p2
    out = np.empty((n_cam, n_pts, 2))
    for n0 in range(0, n_pts, block):
        n1 = min(n0 + block, n_pts)
        cam = np.matmul(rot, np.ascontiguousarray(flat[n0:n1].T))  # (C, 3, n)
        cam += tvec
        z = cam[:, 2]
        inv_z = np.divide(1.0, z, out=np.full_like(z, np.nan), where=z > MIN_DEPTH)
        x = cam[:, 0]
        x *= inv_z  # x'
        y = cam[:, 1]
        y *= inv_z  # y'
        xy = x * y
        tx = x * x
        ty = y * y
        r2 = tx + ty
        radial = k3 * r2  # 1 + k1 r2 + k2 r2^2 + k3 r2^3 (Horner)
        radial += k2
        radial *= r2
        radial += k1
        radial *= r2
        radial += 1.0
        tx *= 2.0  # p2 (r2 + 2 x'^2)
        tx += r2
        tx *= p2
        ty *= 2.0  # p1 (r2 + 2 y'^2)
        ty += r2
        ty *= p1
        x *= radial  # x''
        x += tx
        x += np.multiply(two_p1, xy, out=tx)
        y *= radial  # y''
        y += ty
        y += np.multiply(two_p2, xy, out=ty)
        x *= fx
        x += skew * y
        x += cx
        y *= fy
        y += cy
        out[:, n0:n1, 0] = x
        out[:, n0:n1, 1] = y
    return out.reshape((n_cam,) + lead + (2,))


# -- the straightforward version --------------------------------------------------------------
def forward_np_simple(skeleton, t: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 1 as most NumPy code would write it: ``(T, 3, 3)`` stacks and ``np.matmul``.

    Same semantics and shapes as :func:`forward_np` (root-first bone order); kept as a second
    baseline to show what the tuned reference buys.
    """
    t = np.asarray(t, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    n_t = t.shape[0]
    bones = np.asarray(skeleton.bones)
    parents = np.asarray(skeleton.parents)
    frames = np.asarray(skeleton.rest_frames)
    lengths = np.asarray(skeleton.bone_lengths)
    q = rodrigues_np(r)  # (T, B, 3, 3)
    n_j = len(parents)
    acc = np.empty((n_t, n_j, 3, 3))
    pos = np.empty((n_t, n_j, 3))
    bone_rot = np.empty((n_t, len(bones), 3, 3))
    root = int(np.flatnonzero(parents < 0)[0])
    order = [root]
    for a in order:  # breadth-first; the list grows while iterating
        order.extend(int(j) for j in np.flatnonzero(parents == a))
    pos[:, root] = t
    for a in order:
        p = acc[:, parents[a]] if parents[a] >= 0 else np.broadcast_to(np.eye(3), (n_t, 3, 3))
        for b in np.flatnonzero(bones[:, 0] == a):
            p = p @ q[:, b]
        acc[:, a] = p
    for b, s in enumerate(bones[:, 0]):
        bone_rot[:, b] = acc[:, s] @ frames[b]
    for a in order[1:]:
        b = int(np.flatnonzero(bones[:, 1] == a)[0])
        pos[:, a] = pos[:, bones[b, 0]] + bone_rot[:, b, :, 2] * lengths[b]
    mj = np.asarray(skeleton.marker_joints)
    mb = np.asarray(skeleton.marker_bones)
    v = np.asarray(skeleton.marker_offsets)
    markers = pos[:, mj] + np.einsum("tmij,mj->tmi", bone_rot[:, mb], v)
    return pos, markers


def project_np_simple(params: np.ndarray, points: np.ndarray) -> np.ndarray:
    """OpenCV projection written directly on ``(..., 3)`` arrays, one camera at a time."""
    out = []
    for p in np.asarray(params, dtype=np.float64):
        rot = rodrigues_np(p[None, :3])[0]
        y = points @ rot.T + p[3:6]
        z = y[..., 2]
        xn, yn = y[..., 0] / z, y[..., 1] / z
        k1, k2, p1, p2, k3 = p[10:15]
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        uv = np.stack([p[6] * xd + p[8], p[7] * yd + p[9]], axis=-1)
        uv[z <= MIN_DEPTH] = np.nan
        out.append(uv)
    return np.stack(out)
