"""Deterministic synthetic data: perturbed individual skeletons, random poses, noisy labels.

Used by the tests, the benchmarks and the demo; every function is seeded.
"""

from __future__ import annotations

import numpy as np

from .camera import CameraRig
from .rotation import rodrigues, rodrigues_inverse
from .skeleton import Skeleton

#: Rotation taking ACM's body frame (y dorsal, z caudal) to an arena frame with z up.
BODY_TO_ARENA = np.array([np.pi / 2, 0.0, 0.0])


def individual_skeleton(
    skeleton: Skeleton, length_sd: float = 0.08, offset_sd: float = 0.25, seed: int = 0
) -> Skeleton:
    """A mirror-symmetric individual: bone lengths scaled by ``1 + N(0, length_sd)`` and
    marker offsets moved by ``N(0, offset_sd)`` (skeleton units) within their boxes (sec. 6).

    Returns
    -------
    Skeleton
        Same structure, new lengths and offsets (left/right pairs stay mirror images).
    """
    rng = np.random.default_rng(seed)
    sym = skeleton.symmetry_map()
    l_red = sym.reduce_lengths(skeleton.bone_lengths)
    l_red = l_red * np.clip(1.0 + rng.normal(0.0, length_sd, l_red.shape), 0.7, 1.3)
    v_red = sym.reduce_offsets(skeleton.marker_offsets)
    right = {skeleton.marker_index(r) for _, r in skeleton.symmetry.get("markers", [])}
    reduced = [k for k in range(skeleton.n_markers) if k not in right]
    bounds = skeleton.marker_bounds[reduced]
    v_red = np.clip(v_red + rng.normal(0.0, offset_sd, v_red.shape), bounds[..., 0], bounds[..., 1])
    return skeleton.with_parameters(sym.expand_lengths(l_red), sym.expand_offsets(v_red))


def random_poses(
    skeleton: Skeleton,
    n: int,
    seed: int = 0,
    spread: float = 0.5,
    arena: float = 10.0,
    height: float = 6.0,
) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random poses within the joint limits in an arena frame with z up.

    Limited rotations are ``erf``-mapped normal states (Alg. 10, std ``spread``); the body is
    horizontal with a random heading and a small random tilt; the snout is within
    ``+-arena`` of the origin at ``height`` (skeleton units).

    Returns
    -------
    t : numpy.ndarray, shape (n, 3)
    r : numpy.ndarray, shape (n, n_bones, 3)
    """
    rng = np.random.default_rng(seed)
    sm = skeleton.state_map()
    z = rng.normal(scale=spread, size=(n, sm.n_state))
    _, r = sm.to_pose(z)
    heading = rng.uniform(-np.pi, np.pi, n)
    tilt = rng.normal(scale=0.15, size=(n, 3)) * [1.0, 1.0, 0.0]
    glob = (
        rodrigues(np.stack([np.zeros(n), np.zeros(n), heading], axis=1))
        @ rodrigues(tilt)
        @ rodrigues(BODY_TO_ARENA)
    )
    r[:, 0] = rodrigues_inverse(glob)
    t = np.column_stack([rng.uniform(-arena, arena, (n, 2)), np.full(n, height)])
    return t, r


def noisy_labels(
    rig: CameraRig,
    skeleton: Skeleton,
    t: np.ndarray,
    r: np.ndarray,
    noise_px: float = 2.0,
    missing: float = 0.3,
    seed: int = 0,
) -> np.ndarray:
    """Project the markers of poses into the rig, add Gaussian pixel noise and drop a fraction.

    Returns
    -------
    numpy.ndarray, shape (n_cams, n_frames, M, 2)
        Pixels; NaN for dropped labels and markers outside the image or behind a camera.
    """
    rng = np.random.default_rng(seed)
    px = skeleton.project(rig, t, r)
    px = px + rng.normal(scale=noise_px, size=px.shape)
    drop = rng.random(px.shape[:-1]) < missing
    for c, cam in enumerate(rig):
        if cam.size is not None:
            w, h = cam.size
            out = (px[c, ..., 0] < 0) | (px[c, ..., 0] >= w) | (px[c, ..., 1] < 0)
            drop[c] |= out | (px[c, ..., 1] >= h)
    px[drop] = np.nan
    return px
