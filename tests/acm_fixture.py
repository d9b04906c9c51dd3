"""Test data builders: a synthetic :class:`PoseResult` and a small ACM dataset folder.

The ACM dataset is written from the format description in ``shared/docs/ACM_FORMATS.md`` with
plain numpy and dicts (not with :mod:`acm_rs.acm_formats`), so reader tests check the reader
against an independent writer. Everything is seeded and small (seconds).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

import acm_rs
from acm_rs.demo import demo_rig
from acm_rs.tracking.result import PoseResult


def synthetic_result(
    n_frames: int = 12,
    seed: int = 0,
    skeleton: acm_rs.Skeleton | None = None,
    rig: acm_rs.CameraRig | None = None,
    cov: bool = True,
    missing: float = 0.3,
) -> PoseResult:
    """A PoseResult from random states: FK poses near the arena centre, noisy detections.

    ``state_cov`` is a random SPD matrix per frame (std ~0.01 in the normalised state), and
    ``joints_std`` the Monte-Carlo std of the joints under it (or zeros without ``cov``).
    """
    rng = np.random.default_rng(seed)
    sk = skeleton or acm_rs.models.rat()
    rig = rig or demo_rig()
    sm = sk.state_map()
    n = sm.n_state
    z = rng.normal(scale=0.3, size=(n_frames, n))
    z[:, :3] = rng.normal(scale=0.05, size=(n_frames, 3))
    z[:, 2] = 6.0 / sm.normalization.translation
    t, r = sm.to_pose(z)
    joints, markers = sk.forward(t, r)
    state_cov = None
    joints_std = np.zeros_like(joints)
    if cov:
        a = rng.normal(scale=0.004, size=(n_frames, n, n))
        state_cov = a @ a.transpose(0, 2, 1) + 1e-4 * np.eye(n)
        chol = np.linalg.cholesky(state_cov)
        eps = rng.standard_normal((200, n_frames, n))
        zs = z[None] + np.einsum("tij,stj->sti", chol, eps)
        ts, rs = sm.to_pose(zs.reshape(-1, n))
        js, _ = sk.forward(ts, rs)
        joints_std = js.reshape(200, n_frames, sk.n_joints, 3).std(axis=0)
    det = sk.project(rig, t, r) + rng.normal(scale=1.0, size=(len(rig), n_frames, sk.n_markers, 2))
    det[rng.random(det.shape[:-1]) < missing] = np.nan
    return PoseResult(
        skeleton=sk,
        rig=rig,
        state_map=sm,
        joints=joints,
        joints_std=joints_std,
        markers=markers,
        t=t,
        r=r,
        state_mean=z,
        state_cov=state_cov,
        detections=det,
        em_history=[{"iteration": 1, "delta": 0.5, "seconds": 0.1, "gated": 0}],
        info={"method": "ukf", "converged": True, "iterations": 1},
    )


# -- a small ACM dataset folder -----------------------------------------------------------------
CONFIGURATION_PY = """\
import os
from datetime import datetime

# Frames present in the labels file, used to generate file name
dlc_index_frame_start = {dlc_start}
dlc_index_frame_end = {dlc_end}

# Frames to actually process
index_frame_start = {start}
index_frame_end = {end}

mode = 4 # should always be 4 for now
pcutoff = 0.9
slope = 1.0
noise = 1e-4
videos = [{videos}]
scale_factor = {scale_factor} # [cm]
use_rodrigues = True
num_tol = 2**-52

# NORMALIZATION
normalize_bone_lengths = 1.0
normalize_t0 = 50.0
normalize_r0 = 1.5707963267948966 # e.g. pi/2 [rad]
normalize_camera_sensor_x = 1280.0
normalize_camera_sensor_y = 1024.0

# CALIBRATION
sigma_factor = 10.0
body_weight = {body_weight} # [g]
dFrames_calib = {dframes_calib}
index_frames_calib = list([[{calib_start}, {calib_end}],])
opt_options_calib__maxiter = float('inf')

# INITIALIZATION
index_frame_ini = index_frame_start

# POSE RECONSTRUCTION
dt = {dt} # number of time points to skip between frames
nT = int((index_frame_end - index_frame_start) / dt)
tol = 5e-2
iter_max = 100

assert dlc_index_frame_start<=index_frame_start, "Requested frame range not in label range."

folder_project = os.path.dirname(os.path.realpath(__file__))
job_time = datetime.now()
folder_save = os.path.join(folder_project, 'results', f'{{job_time.strftime("%Y%m%d")}}')
file_labelsDLC = os.path.realpath(os.path.join(folder_project, \
    f'labels_dlc_{{dlc_index_frame_start:06}}_{{dlc_index_frame_end:06}}.npy'))
"""


@dataclass
class AcmDataset:
    """A written ACM dataset folder and the truth it was made from (arena frame, cm)."""

    folder: Path
    skeleton: acm_rs.Skeleton  # the individual's true skeleton (our order)
    rig: acm_rs.CameraRig  # world = arena frame, cm
    calib_rig: acm_rs.CameraRig  # world = calibration frame, calibration units
    origin: np.ndarray
    coord: np.ndarray
    scale_factor: float
    frames: np.ndarray  # every frame of labels_dlc
    t: np.ndarray  # (F, 3) true poses of those frames
    r: np.ndarray  # (F, n_bones, 3)
    manual_frames: np.ndarray
    acm_joint_names: list[str]
    acm_marker_names: list[str]
    config: dict


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    return acm_rs.rodrigues(np.asarray(axis, float) / np.linalg.norm(axis) * angle)


def write_acm_dataset(
    folder: str | Path,
    *,
    seed: int = 0,
    dlc_range: tuple[int, int] = (0, 120),
    frame_range: tuple[int, int] = (20, 100),
    dt: int = 4,
    manual_step: int = 10,
    scale_factor: float = 6.5,
    body_weight: float = 72.0,
    lowconf: float = 0.1,
) -> AcmDataset:
    """Write configuration.py, model.npy, multicalibration.npy, origin_coord.npy,
    labels_dlc_*.npy and labels_manual.npz of a synthetic rat in a 4-camera rig.

    The rat is an individual (perturbed bone lengths and marker offsets) moving smoothly
    (a random walk of its tracker state). ``model.npy`` is written from the bundled rat model
    in the authors' layout (alphabetical names, unit bone lengths); calibration is in units of
    ``scale_factor`` cm in a frame rotated and shifted from the arena by ``origin_coord``.
    DeepLabCut labels: projections + 1.5 px noise, likelihood in (0.9, 1] except a fraction
    ``lowconf`` in [0, 0.9] (with 40 px extra error, as outliers the cutoff removes).
    Manual labels: every ``manual_step``-th frame, 1 px noise, 20 % unlabelled (NaN).
    """
    from acm_rs.datasets import individual_skeleton, random_poses

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rat = acm_rs.models.rat()
    truth = individual_skeleton(rat, seed=seed + 1)
    rig = demo_rig()

    # --- smooth motion: random walk of the state around a random standing pose
    frames = np.arange(*dlc_range, dtype=np.int64)
    n_f = frames.size
    t0, r0 = random_poses(truth, 1, seed=seed + 2, arena=5.0)
    sm = truth.state_map()
    z0 = sm.from_pose(t0[0], r0[0])
    steps = rng.normal(scale=0.01, size=(n_f, sm.n_state))
    steps[:, :3] *= 0.2
    z = z0 + np.cumsum(steps, axis=0)
    t, r = sm.to_pose(z)
    # keep the global orientation of the standing pose, slowly turning about z (up)
    heading = np.cumsum(rng.normal(scale=0.02, size=n_f))
    from acm_rs.rotation import rodrigues_inverse

    glob = acm_rs.rodrigues(np.c_[np.zeros(n_f), np.zeros(n_f), heading]) @ acm_rs.rodrigues(
        r0[0, 0]
    )
    r[:, 0] = rodrigues_inverse(glob)

    # --- names in the authors' layout (alphabetical)
    acm_joints = sorted(rat.joint_names)
    acm_markers = sorted(rat.marker_names)
    jpos = {n: i for i, n in enumerate(acm_joints)}
    ours_j = [rat.joint_index(n) for n in acm_joints]  # our index of each ACM joint
    ours_m = [rat.marker_index(n) for n in acm_markers]

    # --- model.npy: topology + rest pose with unit bone lengths
    unit = rat.with_parameters(bone_lengths=np.ones(rat.n_bones))
    rest_j, _ = unit.rest_pose()
    edges = np.array([[jpos[rat.joint_names[s]], jpos[rat.joint_names[e]]] for s, e in rat.bones])
    model = {
        "joint_order": ["joint_" + n for n in acm_joints],
        "joint_marker_order": ["marker_" + n + "_start" for n in acm_markers],
        "joint_marker_index": np.array(
            [jpos[rat.joint_names[rat.marker_joints[k]]] for k in ours_m], dtype=np.int64
        ),
        "skeleton_edges": edges.astype(np.int64),
        "skeleton_vertices": rest_j[ours_j],
        "skeleton_coords": rat.rest_frames,
        "skeleton_vertices_links": rat.bone_links,
        "bone_lengths": np.zeros(rat.n_bones),
        "joint_marker_vectors": np.zeros((rat.n_markers, 3)),
        "skeleton_coords_index": np.arange(rat.n_bones, dtype=np.int64),
        "surface_triangles": np.zeros((0, 3), np.int32),
        "surface_vertices": np.zeros((0, 3)),
        "surface_vertices_weights": np.zeros((0, rat.n_joints)),
    }
    np.save(folder / "model.npy", model, allow_pickle=True)

    # --- arena frame inside the calibration frame, calibration in units of scale_factor cm
    coord = _rotation([0.3, -0.2, 1.0], 0.7) @ _rotation([1.0, 0.0, 0.0], 0.2)
    origin = np.array([3.0, -2.0, 10.0])
    np.save(folder / "origin_coord.npy", {"origin": origin, "coord": coord}, allow_pickle=True)
    cams = []
    for cam in rig:
        rot_c = cam.rotation_matrix @ coord.T
        t_c = cam.tvec / scale_factor - rot_c @ origin
        cams.append(
            acm_rs.Camera(cam.matrix, cam.dist, rodrigues_inverse(rot_c), t_c, cam.size, cam.name)
        )
    calib_rig = acm_rs.CameraRig(cams)
    n_c = len(rig)
    calib = {
        "nCameras": n_c,
        "A_fit": np.array(
            [[c.matrix[0, 0], c.matrix[0, 2], c.matrix[1, 1], c.matrix[1, 2]] for c in cams]
        ),
        "k_fit": np.array([c.dist for c in cams]),
        "rX1_fit": np.array([c.rvec for c in cams]),
        "RX1_fit": np.array([c.rotation_matrix for c in cams]),
        "tX1_fit": np.array([c.tvec for c in cams]),
        "recFileNames": [f"cam{i}.mp4" for i in range(n_c)],
    }
    np.save(folder / "multicalibration.npy", calib, allow_pickle=True)

    # --- DeepLabCut labels (F, n_cams, 43, 3) in ACM marker order
    px = truth.project(rig, t, r)  # (C, F, M, 2), arena rig
    px = px + rng.normal(scale=1.5, size=px.shape)
    lik = rng.uniform(0.9001, 1.0, size=px.shape[:-1])
    low = rng.random(px.shape[:-1]) < lowconf
    lik[low] = rng.uniform(0.0, 0.9, size=int(low.sum()))
    px[low] += rng.normal(scale=40.0, size=(int(low.sum()), 2))
    bad = ~np.all(np.isfinite(px), axis=-1)
    px[bad] = 0.0
    lik[bad] = 0.0
    labels_all = np.concatenate([px, lik[..., None]], axis=-1)[:, :, ours_m].transpose(1, 0, 2, 3)
    np.save(
        folder / f"labels_dlc_{dlc_range[0]:06d}_{dlc_range[1]:06d}.npy",
        {"file_save": "", "frame_list": frames, "labels_all": labels_all},
        allow_pickle=True,
    )

    # --- manual labels {frame: {"spot_<name>": (n_cams, 2)}}
    manual_frames = frames[::manual_step]
    clean = truth.project(rig, t, r)
    manual = {}
    for i in np.flatnonzero(np.isin(frames, manual_frames)):
        entry = {}
        for k, name in enumerate(rat.marker_names):
            xy = clean[:, i, k] + rng.normal(scale=1.0, size=(n_c, 2))
            xy[rng.random(n_c) < 0.2] = np.nan
            if np.all(np.isnan(xy)):
                continue
            entry["spot_" + name] = xy
        manual[int(frames[i])] = entry
    np.savez(folder / "labels_manual.npz", manual)

    cfg = {
        "dlc_start": dlc_range[0],
        "dlc_end": dlc_range[1],
        "start": frame_range[0],
        "end": frame_range[1],
        "videos": ", ".join(f"'cam{i}.mp4'" for i in range(n_c)),
        "scale_factor": scale_factor,
        "body_weight": body_weight,
        "dframes_calib": manual_step,
        "calib_start": int(manual_frames[0]),
        "calib_end": int(manual_frames[-1]) + 1,
        "dt": dt,
    }
    (folder / "configuration.py").write_text(CONFIGURATION_PY.format(**cfg), encoding="utf-8")
    return AcmDataset(
        folder=folder,
        skeleton=truth,
        rig=rig,
        calib_rig=calib_rig,
        origin=origin,
        coord=coord,
        scale_factor=scale_factor,
        frames=frames,
        t=t,
        r=r,
        manual_frames=manual_frames,
        acm_joint_names=acm_joints,
        acm_marker_names=acm_markers,
        config=cfg,
    )
