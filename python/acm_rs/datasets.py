"""Deterministic synthetic data: perturbed individual skeletons, random poses, noisy labels.

Used by the tests, the benchmarks and the demo; every function is seeded. The true markers,
joints and pixels come from :mod:`acm_rs.truth` (the authors' forward model and projection in
plain NumPy), never from acm-rs's own forward kinematics or cameras, so that a defect there
shows up against the truth.
"""

from __future__ import annotations

import numpy as np

from . import truth
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


def _place_body(
    skeleton: Skeleton, r: np.ndarray, heading: np.ndarray, tilt: np.ndarray
) -> np.ndarray:
    """``r (n, n_bones, 3)`` with the body turned by ``heading`` about the arena's z (up) axis
    and tilted by ``tilt`` (n, 3), from ACM's body frame (``BODY_TO_ARENA``): the first root
    bone's own rotation is replaced, the other root bones' are turned with it."""
    n = len(heading)
    glob = (
        rodrigues(np.stack([np.zeros(n), np.zeros(n), heading], axis=1))
        @ rodrigues(tilt)
        @ rodrigues(BODY_TO_ARENA)
    )
    r = np.array(r, dtype=np.float64)
    r[:, skeleton.root_bones[0]] = 0.0
    return skeleton.turned(r, glob)


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
    r = _place_body(skeleton, r, heading, tilt)
    t = np.column_stack([rng.uniform(-arena, arena, (n, 2)), np.full(n, height)])
    return t, r


def true_positions(
    skeleton: Skeleton, t: np.ndarray, r: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """True joints ``(T, J, 3)`` and markers ``(T, M, 3)`` of poses ``t (T, 3)``,
    ``r (T, n_bones, 3)``, by the independent forward model of :mod:`acm_rs.truth`."""
    t = np.asarray(t, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    return truth.BodyModel.from_skeleton(skeleton).forward(
        t.reshape(-1, 3), r.reshape(-1, skeleton.n_bones, 3)
    )


def true_pixels(rig: CameraRig, skeleton: Skeleton, t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """True pixels ``(n_cams, T, M, 2)`` of the markers of poses ``t (T, 3)``,
    ``r (T, n_bones, 3)`` (:mod:`acm_rs.truth`; NaN behind a camera)."""
    _, markers = true_positions(skeleton, t, r)
    px = truth.project(rig.get_params(), markers)
    return px[:, 0] if np.ndim(t) == 1 else px


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
    px = true_pixels(rig, skeleton, t, r)
    px = px + rng.normal(scale=noise_px, size=px.shape)
    drop = rng.random(px.shape[:-1]) < missing
    for c, cam in enumerate(rig):
        if cam.size is not None:
            w, h = cam.size
            out = (px[c, ..., 0] < 0) | (px[c, ..., 0] >= w) | (px[c, ..., 1] < 0)
            drop[c] |= out | (px[c, ..., 1] >= h)
    px[drop] = np.nan
    return px


def smooth_motion(
    skeleton: Skeleton,
    n_frames: int,
    seed: int = 0,
    spread: float = 0.5,
    speed: float = 1.0,
    arena: float = 8.0,
    height: float = 6.0,
    start: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """A smooth behaviour sequence within the joint limits (arena frame, z up).

    Every free rotation entry follows a sum of three sinusoids in the erf state space of
    Alg. 10 (so limits always hold), the heading turns slowly and the body wanders on a
    smooth path within ``+-arena``. ``speed`` scales all frequencies (1.0: periods of
    roughly 40-200 frames, i.e. natural movement at 100 Hz when ``dt = 1``). ``start``: the
    first frame's index, so that blocks ``[a, b)`` of one long sequence (same seed) can be
    generated one at a time and join without a jump.

    Returns
    -------
    t : numpy.ndarray, shape (n_frames, 3)
    r : numpy.ndarray, shape (n_frames, n_bones, 3)
    """
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    rng = np.random.default_rng(seed)
    sm = skeleton.state_map()
    k = np.arange(start, start + n_frames, dtype=float)[:, None]

    def wave(n_series: int) -> np.ndarray:
        out = np.zeros((n_frames, n_series))
        for _ in range(3):
            period = rng.uniform(40.0, 200.0, n_series) / speed
            phase = rng.uniform(0.0, 2 * np.pi, n_series)
            out += np.sin(2 * np.pi * k / period + phase) / np.sqrt(3.0)
        return out

    z = spread * wave(sm.n_state)
    _, r = sm.to_pose(z)
    heading = rng.uniform(-np.pi, np.pi) + 0.8 * wave(1)[:, 0]
    tilt = 0.1 * wave(3) * [1.0, 1.0, 0.0]
    r = _place_body(skeleton, r, heading, tilt)
    t = np.column_stack([arena * 0.8 * wave(2), height + 0.5 * wave(1)])
    return t, r


def dlc_like_detections(
    rig: CameraRig,
    skeleton: Skeleton,
    t: np.ndarray,
    r: np.ndarray,
    noise_px: float = 2.0,
    missing: float = 0.15,
    burst: float = 8.0,
    outliers: float = 0.01,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """2D detections like a DeepLabCut network's: noise, occlusion bursts, confident outliers.

    Parameters
    ----------
    noise_px : float
        Standard deviation of the Gaussian pixel noise.
    missing : float
        Fraction of entries missing, in bursts (per camera and marker) of mean length
        ``burst`` frames; their likelihood is low (< 0.5).
    outliers : float
        Fraction of entries replaced by a wrong location 30-150 px away with a *high*
        likelihood (0.95-1.0), the failure mode that a likelihood cutoff cannot catch.

    Returns
    -------
    detections : numpy.ndarray, shape (n_cams, T, M, 2)
        Pixels; NaN only where a marker is behind a camera or outside the image.
    likelihood : numpy.ndarray, shape (n_cams, T, M)
    """
    rng = np.random.default_rng(seed)
    px = true_pixels(rig, skeleton, t, r)
    px = px + rng.normal(scale=noise_px, size=px.shape)
    n_cams, n_frames, n_markers = px.shape[:3]
    lik = rng.uniform(0.95, 1.0, px.shape[:3])
    # Occlusion bursts: a two-state Markov chain per (camera, marker) with the requested
    # stationary fraction and mean burst length.
    p_end = 1.0 / max(burst, 1.0)
    p_start = p_end * missing / max(1.0 - missing, 1e-9)
    state = rng.random((n_cams, n_markers)) < missing
    for f in range(n_frames):
        u = rng.random((n_cams, n_markers))
        state = np.where(state, u >= p_end, u < p_start)
        lik[:, f][state] = rng.uniform(0.0, 0.5, int(state.sum()))
    wrong = (rng.random(px.shape[:3]) < outliers) & (lik >= 0.95)
    angle = rng.uniform(0, 2 * np.pi, int(wrong.sum()))
    dist = rng.uniform(30.0, 150.0, int(wrong.sum()))
    px[wrong] += np.column_stack([np.cos(angle), np.sin(angle)]) * dist[:, None]
    for c, cam in enumerate(rig):
        if cam.size is not None:
            w, h = cam.size
            out = (px[c, ..., 0] < 0) | (px[c, ..., 0] >= w) | (px[c, ..., 1] < 0)
            px[c][out | (px[c, ..., 1] >= h)] = np.nan
    return px, lik


def checkerboard_points(squares: tuple[int, int] = (10, 7), square: float = 2.0) -> np.ndarray:
    """Inner corners of a checkerboard with ``squares`` (x, y) squares of side ``square``.

    Returns
    -------
    numpy.ndarray, shape ((sx - 1) * (sy - 1), 3)
        Row-major grid in the board plane (z = 0), first corner at the origin.
    """
    sx, sy = squares
    gx, gy = np.meshgrid(np.arange(sx - 1), np.arange(sy - 1))
    return np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]) * float(square)


def board_views(
    rig: CameraRig,
    board_points: np.ndarray,
    n_views: int = 40,
    noise_px: float = 0.3,
    dropout: float = 0.1,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Synchronous detections of a board moved through the arena (for calibration demos).

    View 0 lies flat on the floor with its first corner at the world origin and its axes along
    world x and y (so it defines the world frame); the others are at random places, heights
    and tilts (up to 50 degrees). A camera sees a view when the board faces it and every corner
    is inside its image; a fraction ``dropout`` of those detections fails at random.

    Returns
    -------
    corners : numpy.ndarray, shape (n_cams, n_views, P, 2)
        Pixels with Gaussian noise ``noise_px``; NaN where the camera did not detect the board.
    rvecs, tvecs : numpy.ndarray, shape (n_views, 3)
        Board-to-world poses (``x_world = R(rvec) x_board + tvec``).
    """
    rng = np.random.default_rng(seed)
    pts = np.asarray(board_points, float)
    centre = pts.mean(axis=0)
    rvecs = np.zeros((n_views, 3))
    tvecs = np.zeros((n_views, 3))
    for v in range(1, n_views):
        axis = np.array([*rng.normal(size=2), 0.0])
        tilt = rodrigues(axis / np.linalg.norm(axis) * np.radians(rng.uniform(0, 50)))
        rot = tilt @ rodrigues(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)]))
        place = np.array([*rng.uniform(-12, 12, 2), rng.uniform(2, 20)])
        rvecs[v] = rodrigues_inverse(rot)
        tvecs[v] = place - rot @ centre
    world = np.einsum("vij,pj->vpi", rodrigues(rvecs), pts) + tvecs[:, None]
    corners = np.full((len(rig), n_views, len(pts), 2), np.nan)
    normals = rodrigues(rvecs)[:, :, 2]
    for c, cam in enumerate(rig):
        px = truth.project(cam.params, world.reshape(-1, 3))[0].reshape(n_views, len(pts), 2)
        facing = np.einsum("vi,vi->v", normals, cam.center - world.mean(axis=1)) > 0
        w, h = cam.size if cam.size is not None else (np.inf, np.inf)
        inside = ((px >= 5) & (px <= np.array([w, h]) - 5)).all(axis=(1, 2))
        seen = facing & inside & (rng.random(n_views) >= dropout)
        seen[0] = facing[0] and inside[0]
        noisy = px + rng.normal(scale=noise_px, size=px.shape)
        corners[c, seen] = noisy[seen]
    return corners, rvecs, tvecs
