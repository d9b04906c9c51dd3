"""Seeded synthetic multi-camera board recordings with known parameters (test helper)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import acm_rs
from acm_rs.rotation import rodrigues, rodrigues_inverse

SIZE = (1280, 1024)


@dataclass
class Synthetic:
    rig: acm_rs.CameraRig  # world = camera 0
    board_points: np.ndarray  # (P, 3)
    board_rvecs: np.ndarray  # (F, 3) board -> world
    board_tvecs: np.ndarray  # (F, 3)
    corners: np.ndarray  # (C, F, P, 2) noisy, NaN = dropped
    clean: np.ndarray  # (C, F, P, 2) noise-free projections (NaN where dropped)


def board_grid(nx: int = 7, ny: int = 5, square: float = 25.0) -> np.ndarray:
    c, r = np.meshgrid(np.arange(nx), np.arange(ny))
    return np.stack([c.ravel(), r.ravel(), np.zeros(nx * ny)], 1) * square


def _look_at(center: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(z, x), z])
    return rot, -rot @ center


def make_recording(
    n_cams: int = 4,
    n_frames: int = 60,
    noise: float = 0.3,
    dropout: float = 0.1,
    view_dropout: float = 0.25,
    seed: int = 0,
    nx: int = 9,
    ny: int = 6,
    square: float = 40.0,
) -> Synthetic:
    """Cameras on a ring ~1 m from the arena centre (z up), a board moving and tilting in
    the middle. ``noise`` is the per-coordinate Gaussian sigma (px); ``dropout`` drops single
    corners, ``view_dropout`` whole (camera, view) detections."""
    rng = np.random.default_rng(seed)
    world_cams = []
    for i in range(n_cams):
        a = 2 * np.pi * i / n_cams + rng.uniform(-0.2, 0.2)
        center = np.array([900 * np.cos(a), 900 * np.sin(a), 700 + rng.uniform(-80, 80)])
        rot, t = _look_at(center, rng.uniform(-40, 40, 3))
        k = np.array(
            [
                [rng.uniform(1100, 1300), 0, 640 + rng.uniform(-20, 20)],
                [0, 0, 512 + rng.uniform(-20, 20)],
                [0, 0, 1],
            ]
        )
        k[1, 1] = k[0, 0] * rng.uniform(0.99, 1.01)
        dist = [rng.uniform(-0.25, 0.05), rng.uniform(-0.05, 0.1)]
        world_cams.append((k, dist, rot, t))
    # Re-express in camera 0's frame: x_c0 = R0 x_w + t0.
    r0, t0 = world_cams[0][2], world_cams[0][3]
    cams = []
    for i, (k, dist, rot, t) in enumerate(world_cams):
        rr = rot @ r0.T
        cams.append(acm_rs.Camera(k, dist, rodrigues_inverse(rr), t - rr @ t0, SIZE, f"cam{i}"))
    rig = acm_rs.CameraRig(cams)
    board = board_grid(nx, ny, square)
    centre = board.mean(0)
    flip = np.diag([1.0, -1.0, -1.0])  # board z down: its front faces the cameras above
    rv, tv = [], []
    for _ in range(n_frames):
        tilt = rodrigues(rng.normal(0, 0.35, 3) * np.array([1, 1, 2]))
        rb_w = tilt @ flip
        pos = rng.uniform([-350, -350, -50], [350, 350, 250])
        tb_w = pos - rb_w @ centre
        # world -> camera-0 frame
        rv.append(rodrigues_inverse(r0 @ rb_w))
        tv.append(r0 @ tb_w + t0)
    rv, tv = np.array(rv), np.array(tv)
    pts = board @ rodrigues(rv).transpose(0, 2, 1) + tv[:, None]
    clean = rig.project(pts)
    inside = (
        (clean[..., 0] >= 0) & (clean[..., 0] < SIZE[0]) & (clean[..., 1] >= 0)
        & (clean[..., 1] < SIZE[1])
    )  # fmt: skip
    # A camera behind the board's plane (board z > 0 side) cannot see its printed face.
    centers = np.stack([c.center for c in rig])
    local_z = np.einsum("fji,cfj->cfi", rodrigues(rv), centers[:, None] - tv[None])[..., 2]
    inside &= (local_z < 0)[..., None]
    keep = inside & (rng.random(inside.shape) > dropout)
    keep &= (rng.random(inside.shape[:2]) > view_dropout)[..., None]
    clean = np.where(keep[..., None], clean, np.nan)
    noisy = clean + rng.normal(0, noise, clean.shape)
    return Synthetic(rig, board, rv, tv, noisy, clean)


@dataclass
class Rendered:
    rig: acm_rs.CameraRig  # truth, world = camera 0, no distortion
    images: list[list[np.ndarray]]  # [camera][frame] uint8 grey
    pixels: np.ndarray  # (C, F, P, 2) true corner pixels (NaN if the board is off-image)


def render_views(spec, n_cams: int = 3, n_frames: int = 10, seed: int = 0, size=(640, 480)):
    """Synthetic camera images of a board (OpenCV-rendered, warped by the exact homography
    ``K [r1 r2 t]`` of each camera and board pose, plus grey noise)."""
    import cv2

    rng = np.random.default_rng(seed)
    img, to_px = spec.render(60, 40)
    w, h = size
    k = np.array([[520.0, 0, w / 2 + 3], [0, 518.0, h / 2 - 4], [0, 0, 1]])
    world = []
    for i in range(n_cams):
        a = 2 * np.pi * i / n_cams + 0.3
        world.append(_look_at(np.array([330 * np.cos(a), 330 * np.sin(a), 330.0]), np.zeros(3)))
    r0, t0 = world[0]
    cams = []
    for i, (rot, t) in enumerate(world):
        rr = rot @ r0.T
        cams.append(acm_rs.Camera(k, [0, 0], rodrigues_inverse(rr), t - rr @ t0, size, f"cam{i}"))
    rig = acm_rs.CameraRig(cams)
    centre = spec.board_points.mean(0)
    images: list[list[np.ndarray]] = [[] for _ in range(n_cams)]
    pixels = np.full((n_cams, n_frames, spec.n_points, 2), np.nan)
    for f in range(n_frames):
        rb = rodrigues(rng.normal(0, 0.25, 3) * [1, 1, 3]) @ np.diag([1.0, -1, -1])
        tb = rng.uniform([-50, -50, -20], [50, 50, 50]) - rb @ centre
        for i, (rot, t) in enumerate(world):
            rc, tc = rot @ rb, rot @ tb + t
            hom = k @ np.column_stack([rc[:, 0], rc[:, 1], tc])
            out = cv2.warpPerspective(img, hom @ np.linalg.inv(to_px), size, borderValue=150)
            noisy = np.clip(out + rng.normal(0, 2.0, out.shape), 0, 255).astype(np.uint8)
            images[i].append(noisy)
            p = (spec.board_points @ rc.T + tc) @ k.T
            pixels[i, f] = p[:, :2] / p[:, 2:]
    return Rendered(rig, images, pixels)
