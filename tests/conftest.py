"""Shared fixtures: seeded RNGs, a small branching skeleton and a 4-camera rig."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import acm_rs

SHARED = Path(__file__).resolve().parents[2] / "shared"


def look_at(
    center: np.ndarray, target: np.ndarray, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(rvec, tvec) of a camera at ``center`` looking at ``target`` (OpenCV axes: y down)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return acm_rs.rodrigues_inverse(rot), -rot @ center


def make_rig(distance: float = 40.0, n: int = 4) -> acm_rs.CameraRig:
    """Cameras on a ring above the origin, looking at it (world: z up)."""
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        center = np.array([distance * np.cos(a), distance * np.sin(a), 0.6 * distance])
        rvec, tvec = look_at(center, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        k = np.array([[1200.0 + 20 * i, 0, 640.0 + 5 * i], [0, 1190.0, 512.0 - 4 * i], [0, 0, 1]])
        dist = [-0.12 + 0.01 * i, 0.03, 0.0005 * i, -0.0003, 0.002]
        cams.append(acm_rs.Camera(k, dist, rvec, tvec, (1280, 1024), f"cam{i}"))
    return acm_rs.CameraRig(cams)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def rig() -> acm_rs.CameraRig:
    return make_rig()


@pytest.fixture(scope="session")
def rat() -> acm_rs.Skeleton:
    return acm_rs.models.rat()


@pytest.fixture
def small_skeleton() -> acm_rs.Skeleton:
    """root -> a -> {b_left -> c_left, b_right -> c_right}; markers on several joints."""
    joints = ["root", "a", "b_left", "c_left", "b_right", "c_right"]
    parents = [-1, 0, 1, 2, 1, 4]
    rest = np.array(
        [[0, 0, 0], [0, 0, 2.0], [-1, -0.5, 2], [-1, -0.5, 3], [1, -0.5, 2], [1, -0.5, 3]],
        dtype=float,
    )
    markers = ["m_root", "m_a", "m_left", "m_right"]
    mj = ["root", "a", "c_left", "c_right"]
    mrest = np.array([[0.1, 0.2, -0.1], [0, 0.4, 1.9], [-1.2, -0.4, 3.1], [1.2, -0.4, 3.1]])
    return acm_rs.Skeleton.from_rest_pose(
        joints,
        parents,
        rest,
        markers,
        mj,
        mrest,
        joint_limits={"c_left": np.radians([[-30, 60], [0, 0], [-10, 10]])},
        symmetry={
            "joints": [("b_left", "b_right"), ("c_left", "c_right")],
            "markers": [("m_left", "m_right")],
        },
        name="small",
        units="cm",
    )


def long_recording_case(n: int, seed: int, outage: tuple[int, int]) -> dict:
    """A synthetic rat recording for the long-recording smoothers (tests/test_long.py,
    tests/test_streaming.py): ``n`` frames, DeepLabCut-like detections, camera 2 out for the
    frames ``outage``, Θ learned by EM on two windows (random walk), and the smoother's
    model with the default gate."""
    from acm_rs import datasets, models
    from acm_rs.demo import demo_rig
    from acm_rs.tracking import long as L
    from acm_rs.tracking.track import DEFAULT_GATE, default_normalization, gate_threshold

    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, n, seed=seed)
    det, lik = datasets.dlc_like_detections(
        rig, sk, t, r, missing=0.15, outliers=0.01, seed=seed + 1
    )
    det[2, outage[0] : outage[1]] = np.nan
    norm = default_normalization(rig, sk)
    stub = L._Model(rig, sk, norm, True, 10, None, 1, {}, np.zeros((0, 0)), 0.9)
    wins = L.subset_windows(n, 300, 2)
    fit = L.learn_windows(
        rig, sk, [stub.detections(det[:, a:b], lik[:, a:b]) for a, b in wins], norm,
        motion="random_walk", windows=wins,
    )  # fmt: skip
    model = L._Model(
        rig, sk, norm, True, 10, gate_threshold(DEFAULT_GATE), 1, fit.params, fit.prior_cov, 0.9
    )
    return {"sk": sk, "rig": rig, "det": det, "lik": lik, "truth": sk.forward(t, r)[0],
            "model": model, "fit": fit}  # fmt: skip
