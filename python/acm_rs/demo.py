"""The demo job: the whole pipeline on a deterministic synthetic session.

A synthetic individual rat (perturbed bone lengths and marker offsets) is filmed by a 4-camera
rig: checkerboard views calibrate the rig (sec. 2), labelled frames teach the skeleton
(sec. 3), and a behaviour sequence of DeepLabCut-like detections (noise, occlusion bursts,
confident outliers) is tracked (sec. 4), exported and plotted; every stage is compared with
the known truth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
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
    return CameraRig(cams, units="cm")


def demo_pose(skeleton: Skeleton, heading: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
    """A standing pose: every limited rotation at the middle of its bounds (as Supp. Fig. 1a),
    spine and tail straight, the body turned to ``heading`` (rad) about the arena's z (up) axis
    and centred on the origin, snout 6 cm above the floor."""
    sm = skeleton.state_map()
    _, r = sm.to_pose(np.zeros(sm.n_state))
    glob = rodrigues(np.array([0.0, 0.0, heading])) @ rodrigues(BODY_TO_ARENA)
    r = r.copy()
    r[skeleton.root_bones[0]] = 0.0
    r = skeleton.turned(r, glob)
    joints, _ = skeleton.forward(np.zeros(3), r)
    centre = 0.5 * (joints.min(axis=0) + joints.max(axis=0))
    t = np.array([-centre[0], -centre[1], 6.0])
    return t, r


@dataclass
class DemoResult:
    """Files written by :func:`run_demo`, timings and the outcome of each stage."""

    out: Path
    files: list[Path]
    n_frames: int
    seconds: float
    learned: LearnedSkeleton | None = None
    truth: Skeleton | None = None
    calibration: object = None
    true_rig: CameraRig | None = None
    tracked: object = None
    true_joints: np.ndarray | None = None
    stage_seconds: dict = field(default_factory=dict)

    def calibration_report(self) -> str:
        """Calibrated vs true cameras (empty without calibration)."""
        if self.calibration is None or self.true_rig is None:
            return ""
        cal = self.calibration
        centre = [
            np.linalg.norm(a.center - b.center) for a, b in zip(cal.rig, self.true_rig, strict=True)
        ]
        f_err = [
            abs(a.matrix[0, 0] / b.matrix[0, 0] - 1)
            for a, b in zip(cal.rig, self.true_rig, strict=True)
        ]
        n_views = int(np.asarray(cal.used_frames).sum())
        unit = self.truth.units if self.truth is not None else ""
        return (
            f"  calibration from {n_views} checkerboard views (0.3 px noise) in "
            f"{self.stage_seconds.get('calibrate', 0):.1f} s: RMS {cal.rms:.3f} px; camera "
            f"centres within {max(centre):.3f} {unit} of the truth, focal lengths within "
            f"{100 * max(f_err):.2f} %"
        )

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

    def tracking_report(self) -> str:
        """Tracked vs true joints (empty without tracking)."""
        res = self.tracked
        if res is None or self.true_joints is None:
            return ""
        err = np.linalg.norm(res.joints - self.true_joints, axis=-1)
        inside = np.abs(res.joints - self.true_joints) <= 1.96 * res.joints_std
        unit = res.skeleton.units
        gated = int((res.info["status"] == 2).sum())
        return (
            f"  tracking {res.n_frames} frames (2 px noise, ~15 % missing in bursts, 1 % "
            f"confident outliers) in {self.stage_seconds.get('track', 0):.1f} s: "
            f"{len(res.em_history)} EM iterations, "
            f"{'converged' if res.info.get('converged') else 'not converged'}, "
            f"{gated} outlier detections gated\n"
            f"    joints vs truth: mean {err.mean():.3f} {unit}, median {np.median(err):.3f} "
            f"{unit}, 95th percentile {np.percentile(err, 95):.3f} {unit}; "
            f"{100 * inside.mean():.1f} % of true coordinates inside the 95 % intervals"
        )


def run_demo(
    out: str | Path = "demo_out",
    frames: int = 100_000,
    seed: int = 0,
    learn_frames: int = 100,
    track_frames: int = 400,
    calibration_views: int = 40,
) -> DemoResult:
    """Run the demo: calibrate -> learn skeleton -> track -> export -> plots, against truth.

    Parameters
    ----------
    out : path
        Output folder (created).
    frames : int
        Number of random poses to push through batch FK + projection (for the timing).
    seed : int
        Seed of every random choice (the demo is deterministic for a seed).
    learn_frames : int
        Labelled frames of the synthetic individual for skeleton learning (0: skip learning
        and tracking).
    track_frames : int
        Frames of the behaviour sequence to track (0: skip tracking).
    calibration_views : int
        Checkerboard views for the calibration (0: use the true rig).

    Returns
    -------
    DemoResult
    """
    from . import export
    from .calibration import calibrate
    from .datasets import (
        board_views,
        checkerboard_points,
        dlc_like_detections,
        smooth_motion,
        true_positions,
    )
    from .plots import plot_all
    from .plotting import camera_views, save_figure, skeleton_views
    from .tracking import track

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rat = models.rat()
    true_rig = demo_rig()
    files: list[Path] = []
    stage: dict[str, float] = {}

    t, r = demo_pose(rat, heading=0.0)
    joints, markers = rat.forward(t, r)
    title = "ACM rat model, rotations at the middle of their bounds (arena frame, z up)"
    files.append(save_figure(skeleton_views(rat, joints, markers, title), out / "rat_model.png"))
    t, r = demo_pose(rat)
    joints, markers = rat.forward(t, r)
    files.append(
        save_figure(camera_views(true_rig, rat, joints, markers), out / "camera_views.png")
    )

    tb, rb = random_poses(rat, frames, seed)
    start = time.perf_counter()
    px = rat.project(true_rig, tb, rb)  # fused FK + projection (Rust, all cores)
    seconds = time.perf_counter() - start
    path = out / "projections.npz"
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(
            fh,
            t=tb[:1000],
            r=rb[:1000],
            pixels=px[:, :1000],
            camera_params=true_rig.get_params(),
            marker_names=np.array(rat.marker_names),
        )
    files.append(path)
    result = DemoResult(out, files, frames, seconds, true_rig=true_rig, stage_seconds=stage)

    # Sec. 2: calibrate the rig from checkerboard views; view 0 lies on the floor at the
    # arena origin and defines the world frame.
    rig = true_rig
    if calibration_views > 0:
        board = checkerboard_points((10, 7), 2.0)
        corners, _, _ = board_views(true_rig, board, calibration_views, seed=seed + 5)
        start = time.perf_counter()
        cal = calibrate(corners, board, (1280, 1024), camera_names=true_rig.names).with_world_frame(
            board_view=0
        )
        stage["calibrate"] = time.perf_counter() - start
        rig = cal.rig
        result.calibration = cal
        cal.save_report(out / "calibration_report.json", png=out / "calibration_qc.png")
        files += [out / "calibration_report.json", out / "calibration_qc.png"]
    rig.save(out / "calibration.toml")
    files.append(out / "calibration.toml")

    if learn_frames > 0:
        # Sec. 3.2: learn an individual's bone lengths and marker offsets from noisy labels.
        truth = individual_skeleton(rat, seed=seed + 1)
        tl, rl = random_poses(truth, learn_frames, seed=seed + 2)
        labels = noisy_labels(true_rig, truth, tl, rl, 2.0, missing=0.3, seed=seed + 3)
        start = time.perf_counter()
        learned = learn_skeleton(rig, rat, labels, progress=False)
        learned.info["seconds"] = stage["learn"] = time.perf_counter() - start
        files += learned.save(out / "learned_rat")
        files.append(save_figure(learned.plot_reprojection(), out / "learn_reprojection.png"))
        files.append(save_figure(learned.plot_skeleton(), out / "learn_skeleton.png"))
        result.learned, result.truth = learned, truth

        if track_frames > 0:
            # Sec. 4: a behaviour sequence with DeepLabCut-like detections.
            tt, rt = smooth_motion(truth, track_frames, seed=seed + 6)
            det, lik = dlc_like_detections(true_rig, truth, tt, rt, seed=seed + 7)
            start = time.perf_counter()
            res = track(rig, learned.skeleton, det, likelihood=lik, progress=False)
            stage["track"] = time.perf_counter() - start
            result.tracked = res
            result.true_joints = true_positions(truth, tt, rt)[0]
            start = time.perf_counter()
            files += res.save(out / "pose")
            files += export.to_anipose_csv(res, out / "pose_3d.csv")
            files.append(
                export.to_nwb(
                    res,
                    out / "pose.nwb",
                    rate=100.0,
                    session_description="acm-rs demo: synthetic rat, 4 cameras",
                )  # fmt: skip
            )
            files.append(export.to_c3d(res, out / "pose.c3d", 100.0, joints=True))
            stage["export"] = time.perf_counter() - start
            start = time.perf_counter()
            files += plot_all(res, out / "plots", frame_rate=100.0)
            stage["plots"] = time.perf_counter() - start
    return result
