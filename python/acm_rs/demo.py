"""The demo job: pose the ACM rat model, project it into a 4-camera rig, save pictures.

This is what exists so far (geometry and kinematics); calibration, skeleton learning and
tracking will join the demo as they land.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import models
from ._io import atomic_write
from .camera import Camera, CameraRig
from .datasets import BODY_TO_ARENA, individual_skeleton, noisy_labels, random_poses
from .learning import LearnedSkeleton, learn_skeleton
from .rotation import rodrigues, rodrigues_inverse
from .skeleton import Skeleton


def look_at(
    center: np.ndarray, target: np.ndarray, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(rvec, tvec)`` of a camera at ``center`` (world) looking at ``target``.

    OpenCV camera axes: z forward, x right, y down in the image; ``up`` is the world's up.
    """
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("viewing direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])
    return rodrigues_inverse(rot), -rot @ np.asarray(center, float)


def demo_rig(distance: float = 60.0, height: float = 45.0) -> CameraRig:
    """Four 1280x1024 cameras on a ring around an arena centred at the origin (cm, z up)."""
    cams = []
    for i in range(4):
        a = np.pi / 4 + i * np.pi / 2
        center = np.array([distance * np.cos(a), distance * np.sin(a), height])
        rvec, tvec = look_at(center, np.array([0.0, 0.0, 3.0]), np.array([0.0, 0.0, 1.0]))
        matrix = np.array([[1400.0, 0.0, 640.0], [0.0, 1400.0, 512.0], [0.0, 0.0, 1.0]])
        cams.append(Camera(matrix, [-0.15, 0.08], rvec, tvec, (1280, 1024), f"cam{i}"))
    return CameraRig(cams)


def demo_pose(skeleton: Skeleton, heading: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """A standing pose: every limited rotation at the middle of its bounds (as Supp. Fig. 1a),
    spine and tail straight, the body turned to ``heading`` (rad) about the arena's z (up) axis
    and centred on the origin, snout 6 cm above the floor."""
    sm = skeleton.state_map()
    _, r = sm.to_pose(np.zeros(sm.n_state))
    glob = rodrigues(np.array([0.0, 0.0, heading])) @ rodrigues(BODY_TO_ARENA)
    r = r.copy()
    r[0] = rodrigues_inverse(glob)
    joints, _ = skeleton.forward(np.zeros(3), r)
    centre = 0.5 * (joints.min(axis=0) + joints.max(axis=0))
    t = np.array([-centre[0], -centre[1], 6.0])
    return t, r


@dataclass
class DemoResult:
    """Files written by :func:`run_demo`, the measured throughput and the learning outcome."""

    out: Path
    files: list[Path]
    n_frames: int
    seconds: float
    learned: LearnedSkeleton | None = None
    truth: Skeleton | None = None

    def learning_report(self) -> str:
        """Learned vs true bone lengths and marker offsets (empty without learning)."""
        if self.learned is None or self.truth is None:
            return ""
        generic, learned, truth = self.learned.generic, self.learned.skeleton, self.truth
        before = np.abs(generic.bone_lengths / truth.bone_lengths - 1)
        after = np.abs(learned.bone_lengths / truth.bone_lengths - 1)
        off = np.linalg.norm(learned.marker_offsets - truth.marker_offsets, axis=1)
        unit = learned.units
        return (
            f"  skeleton learning from {self.learned.t.shape[0]} labelled frames (2 px noise, "
            f"30 % unlabelled) in {self.learned.info['seconds']:.1f} s: RMS reprojection "
            f"{self.learned.rms:.2f} px\n"
            f"    bone lengths vs truth: median error {100 * np.median(after):.2f} % "
            f"(generic model: {100 * np.median(before):.1f} %), max {100 * after.max():.1f} %\n"
            f"    marker offsets vs truth: median error {np.median(off):.3f} {unit}"
        )


def run_demo(
    out: str | Path = "demo_out", frames: int = 100_000, seed: int = 0, learn_frames: int = 100
) -> DemoResult:
    """Run the demo: a posed rat in 4 cameras, batch throughput, and skeleton learning.

    Parameters
    ----------
    out : path
        Output folder (created).
    frames : int
        Number of random poses to push through batch FK + projection (for the timing).
    seed : int
        Seed of the random poses and of the synthetic animal.
    learn_frames : int
        Labelled frames of a synthetic individual to learn its skeleton from (0: skip).

    Returns
    -------
    DemoResult
    """
    from .plotting import camera_views, save_figure, skeleton_views

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rat = models.rat()
    rig = demo_rig()
    files: list[Path] = []

    t, r = demo_pose(rat, heading=0.0)
    joints, markers = rat.forward(t, r)
    title = "ACM rat model, rotations at the middle of their bounds (arena frame, z up)"
    files.append(save_figure(skeleton_views(rat, joints, markers, title), out / "rat_model.png"))
    t, r = demo_pose(rat)
    joints, markers = rat.forward(t, r)
    files.append(save_figure(camera_views(rig, rat, joints, markers), out / "camera_views.png"))

    rig.save(out / "calibration.toml")
    files.append(out / "calibration.toml")
    tb, rb = random_poses(rat, frames, seed)
    start = time.perf_counter()
    _, mk = rat.forward(tb, rb)
    px = rig.project(mk)
    seconds = time.perf_counter() - start
    path = out / "projections.npz"
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(
            fh,
            t=tb[:1000],
            r=rb[:1000],
            pixels=px[:, :1000],
            camera_params=rig.get_params(),
            marker_names=np.array(rat.marker_names),
        )
    files.append(path)
    result = DemoResult(out, files, frames, seconds)
    if learn_frames > 0:
        # Sec. 3.2: learn an individual's bone lengths and marker offsets from noisy labels.
        truth = individual_skeleton(rat, seed=seed + 1)
        tl, rl = random_poses(truth, learn_frames, seed=seed + 2)
        labels = noisy_labels(rig, truth, tl, rl, 2.0, missing=0.3, seed=seed + 3)
        start = time.perf_counter()
        learned = learn_skeleton(rig, rat, labels, progress=False)
        learned.info["seconds"] = time.perf_counter() - start
        files += learned.save(out / "learned_rat")
        files.append(save_figure(learned.plot_reprojection(), out / "learn_reprojection.png"))
        files.append(save_figure(learned.plot_skeleton(), out / "learn_skeleton.png"))
        result.learned, result.truth = learned, truth
    return result
