"""Ground truth from code that shares nothing with acm-rs's forward model (issue 25).

Synthetic data are only as honest as the code that makes their truth: when the truth and the
product share a forward model, a wrong rule in it (as in acm-rs before issue 25, where a
bone's rotation also turned its siblings) is invisible to every accuracy figure. This module
is plain NumPy written from the authors' code (bbo-lab/ACM ``model.py``:
``rodrigues2rotMat``, ``adjust_joint_marker_pos2``, ``map_m``), statement by statement, and
imports nothing from :mod:`acm_rs` (``tests/test_import_layers.py`` checks this). The
synthetic data of the tests, the demo and the benches (:mod:`acm_rs.datasets`) take their
markers, joints and pixels from here; only plain arrays (the tree, rest frames, lengths,
offsets, camera parameters) cross over from a :class:`acm_rs.Skeleton` or
:class:`acm_rs.CameraRig`.

The authors' forward model, for bones listed root first:

1. every bone's frame starts as the identity; for each bone ``i`` in order, the transposed
   rotation ``R(r_i)^T`` is multiplied from the left onto the frames of the bones that
   ``links[i]`` marks;
2. each frame is transposed and multiplied by the bone's rest frame ``coords0``, so bone
   ``b``'s orientation is ``R(r_a1) R(r_a2) ... R(r_ak) coords0[b]`` over the bones linked
   to it, in order;
3. joints: the root is ``t``; the end of bone ``b`` is its start plus ``l_b`` times the third
   column of its orientation;
4. markers: their joint plus the orientation of their bone times their offset.

The links default to those of the authors' files: the rotation of bone ``i`` moves bone ``i``
and its descendants.
"""

from __future__ import annotations

import numpy as np

_NUM_TOL = 2.0**-52  # the authors' num_tol: rotations this small are the identity


def rodrigues(r: np.ndarray) -> np.ndarray:
    """``rodrigues2rotMat``: ``(..., 3)`` rotation vectors (rad) -> ``(..., 3, 3)`` matrices.

    ``R = I + sin(theta) W + (1 - cos(theta)) W^2`` with ``W`` the cross-product matrix of the
    unit axis; vectors whose entries are all within ``2**-52`` of zero give the identity.
    """
    r = np.asarray(r, dtype=np.float64)
    theta = np.sqrt(np.sum(r**2, axis=-1))
    small = np.all(np.abs(r) <= _NUM_TOL, axis=-1)
    safe = np.where(small, 1.0, theta)
    w = r / safe[..., None]
    zero = np.zeros_like(theta)
    w_hat = np.stack(
        [
            np.stack([zero, -w[..., 2], w[..., 1]], axis=-1),
            np.stack([w[..., 2], zero, -w[..., 0]], axis=-1),
            np.stack([-w[..., 1], w[..., 0], zero], axis=-1),
        ],
        axis=-2,
    )
    eye = np.broadcast_to(np.eye(3), w_hat.shape)
    rot = (
        eye
        + np.sin(theta)[..., None, None] * w_hat
        + (1.0 - np.cos(theta))[..., None, None] * (w_hat @ w_hat)
    )
    return np.where(small[..., None, None], eye, rot)


def tree_links(edges: np.ndarray) -> np.ndarray:
    """``(B, B)`` bool: ``[i, j]`` when bone ``j`` is bone ``i`` or below it in the tree
    (the ``skeleton_vertices_links`` of the authors' files). ``edges``: ``(B, 2)``
    ``[start, end]`` joint indices."""
    edges = np.asarray(edges, dtype=np.int64)
    parent = {int(e): int(s) for s, e in edges}
    n = len(edges)
    out = np.zeros((n, n), dtype=bool)
    for i in range(n):
        top = int(edges[i, 1])
        for j in range(n):
            a = int(edges[j, 1])
            while a != top and a in parent:
                a = parent[a]
            out[i, j] = a == top
    return out


class BodyModel:
    """The authors' forward model over a tree of joints with markers.

    Parameters
    ----------
    edges : array_like of int, shape (B, 2)
        ``[start, end]`` joint indices of every bone; one root.
    coords0 : array_like, shape (B, 3, 3)
        Rest frame of every bone (columns = its axes in the world; the third along the bone).
    lengths : array_like, shape (B,)
        Bone lengths (world units).
    marker_joints, marker_bones : array_like of int, shape (M,)
        Joint each marker is attached to, and the bone whose frame holds its offset.
    offsets : array_like, shape (M, 3)
        Marker offsets in their bone's frame (world units).
    links : array_like of bool, shape (B, B), optional
        ``[i, j]``: the rotation of bone ``i`` moves bone ``j``. Default :func:`tree_links`.
    order : array_like of int, shape (B,), optional
        The order in which the rotations apply. Default: root first (by depth of the end
        joint, ties by index), the authors' file order.
    """

    def __init__(
        self,
        edges,
        coords0,
        lengths,
        marker_joints,
        marker_bones,
        offsets,
        links=None,
        order=None,
    ) -> None:
        self.edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        n = len(self.edges)
        self.coords0 = np.asarray(coords0, dtype=np.float64).reshape(n, 3, 3)
        self.lengths = np.asarray(lengths, dtype=np.float64).reshape(n)
        self.marker_joints = np.asarray(marker_joints, dtype=np.int64).ravel()
        self.marker_bones = np.asarray(marker_bones, dtype=np.int64).ravel()
        self.offsets = np.asarray(offsets, dtype=np.float64).reshape(-1, 3)
        self.links = tree_links(self.edges) if links is None else np.asarray(links, dtype=bool)
        parent = {int(e): int(s) for s, e in self.edges}
        starts = set(self.edges[:, 0].tolist()) - set(parent)
        if len(starts) != 1:
            raise ValueError(f"the bones must form one tree; roots {sorted(starts)}")
        self.root = starts.pop()
        self.n_joints = n + 1

        def depth(j: int) -> int:
            d = 0
            while j in parent:
                j, d = parent[j], d + 1
            return d

        # root first: every bone after the bone that ends at its start joint
        self.placement = sorted(range(n), key=lambda b: depth(int(self.edges[b, 1])))
        self.order = self.placement if order is None else [int(i) for i in order]

    @classmethod
    def from_skeleton(cls, skeleton) -> BodyModel:
        """The model of an :class:`acm_rs.Skeleton`'s plain arrays (tree, rest frames,
        lengths, marker attachments and offsets, and a link matrix set explicitly, e.g.
        from an ACM ``model.npy``); nothing of its forward kinematics is used."""
        custom = skeleton.custom_links
        links, order = (None, None) if custom is None else custom
        return cls(
            skeleton.bones,
            skeleton.rest_frames,
            skeleton.bone_lengths,
            skeleton.marker_joints,
            skeleton.marker_bones,
            skeleton.marker_offsets,
            links,
            order,
        )

    def forward(self, t: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Joints and markers of poses (``adjust_joint_marker_pos2``).

        Parameters
        ----------
        t : array_like, shape (T, 3)
            Root positions (world units).
        r : array_like, shape (T, B, 3)
            One rotation vector per bone (rad).

        Returns
        -------
        joints : numpy.ndarray, shape (T, J, 3)
        markers : numpy.ndarray, shape (T, M, 3)
        """
        t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(r, dtype=np.float64).reshape(len(t), len(self.edges), 3)
        n_t, n_b = len(t), len(self.edges)
        coords = np.tile(np.eye(3), (n_t, n_b, 1, 1))
        rot_t = np.swapaxes(rodrigues(r), -1, -2)  # R(r_i)^T
        for i in self.order:
            moved = self.links[i]
            coords[:, moved] = np.einsum("sij,sbjk->sbik", rot_t[:, i], coords[:, moved])
        coords = np.einsum("sbji,bjk->sbik", coords, self.coords0)  # transpose, then coords0
        joints = np.zeros((n_t, self.n_joints, 3))
        joints[:, self.root] = t
        for b in self.placement:
            s, e = self.edges[b]
            joints[:, e] = joints[:, s] + coords[:, b, :, 2] * self.lengths[b]
        markers = joints[:, self.marker_joints] + np.einsum(
            "skij,kj->ski", coords[:, self.marker_bones], self.offsets
        )
        return joints, markers


def project(params: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``map_m``: world points into every camera, OpenCV's pinhole and distortion model.

    Parameters
    ----------
    params : array_like, shape (C, 16) or (C, 15)
        Per camera ``[rvec (3), tvec (3), fx, fy, cx, cy, k1, k2, p1, p2, k3, skew]``, world to
        camera ``x_cam = R(rvec) x + tvec`` (a :class:`acm_rs.CameraRig`'s ``get_params()``);
        15 columns: no skew. The skew is MATLAB's, ``u = fx x'' + skew y'' + cx``.
    points : array_like, shape (..., 3)
        World points.

    Returns
    -------
    numpy.ndarray, shape (C, ..., 2)
        Pixels; NaN for points at or behind a camera's plane.
    """
    params = np.asarray(params, dtype=np.float64)
    params = params.reshape(-1, 16 if params.shape[-1] == 16 else 15)
    pts = np.asarray(points, dtype=np.float64)
    shape = pts.shape[:-1]
    pts = pts.reshape(-1, 3)
    out = []
    for p in params:
        rot = rodrigues(p[0:3])
        m_cam = pts @ rot.T + p[3:6]
        m = m_cam[:, :2] / m_cam[:, 2:3]
        k = p[10:15]
        r_2 = m[:, 0] ** 2 + m[:, 1] ** 2
        sum_term = 1.0 + k[0] * r_2 + k[1] * r_2**2 + k[4] * r_2**3
        xy2 = m[:, 0] * m[:, 1] * 2.0
        xd = m[:, 0] * sum_term + k[2] * xy2 + k[3] * (r_2 + 2.0 * m[:, 0] ** 2)
        yd = m[:, 1] * sum_term + k[2] * (r_2 + 2.0 * m[:, 1] ** 2) + k[3] * xy2
        skew = p[15] if p.size == 16 else 0.0
        u = p[8] + p[6] * xd + skew * yd
        v = p[9] + p[7] * yd
        uv = np.stack([u, v], axis=-1)
        uv[~(m_cam[:, 2] > 0)] = np.nan
        out.append(uv.reshape(*shape, 2))
    return np.array(out)
