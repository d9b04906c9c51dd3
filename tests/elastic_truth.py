"""Independent truth for elastic segments (issue 28 item 2): a keypoint tree in plain NumPy,
projected by OpenCV's ``projectPoints``. Shares nothing with acm-rs's forward model, state or
noise model. Used by ``tests/test_elastic_tracking.py`` and ``benches/elastic_tracking.py``.

Bone directions wander smoothly around a rest direction; each segment's length is
``L exp(s_t)`` with a log-stretch ``s_t`` of known SD, smooth in time (AR(1) with coefficient
``ar``; the tracker assumes less, a memoryless stretch).
"""

from __future__ import annotations

import cv2
import numpy as np

NAMES = ["SpineM", "SpineF", "Head", "Snout", "Tail", "EarL", "EarR", "PawL", "PawR"]
EDGES = [
    ("SpineM", "SpineF"), ("SpineF", "Head"), ("Head", "Snout"), ("SpineM", "Tail"),
    ("Head", "EarL"), ("Head", "EarR"), ("SpineF", "PawL"), ("SpineF", "PawR"),
]  # fmt: skip
LENGTH = {"SpineF": 30.0, "Head": 18.0, "Snout": 15.0, "Tail": 25.0, "EarL": 10.0,
          "EarR": 10.0, "PawL": 20.0, "PawR": 20.0}  # fmt: skip
#: SD of each segment's log-length (0: rigid)
SD = {"SpineF": 0.12, "Head": 0.10, "Snout": 0.0, "Tail": 0.08, "EarL": 0.0, "EarR": 0.0,
      "PawL": 0.06, "PawR": 0.06}  # fmt: skip
REST = {"SpineF": (1, 0, 0), "Head": (1, 0, 0.3), "Snout": (1, 0, -0.4), "Tail": (-1, 0, 0),
        "EarL": (0, 1, 1), "EarR": (0, -1, 1), "PawL": (0.3, 0.6, -1),
        "PawR": (0.3, -0.6, -1)}  # fmt: skip


def _smooth(rng, n: int, dim: int, scale: float, width: int = 15) -> np.ndarray:
    x = rng.normal(0, 1, (n + 4 * width, dim))
    k = np.exp(-0.5 * (np.arange(-2 * width, 2 * width + 1) / width) ** 2)
    k /= np.sqrt((k**2).sum())
    return scale * np.stack([np.convolve(x[:, d], k, mode="valid")[:n] for d in range(dim)], 1)


def synthetic(n_frames: int, seed: int, ar: float = 0.9):
    """Keypoints (T, K, 3) in mm and the true log-stretch of each segment (by child)."""
    rng = np.random.default_rng(seed)
    pos = {"SpineM": np.cumsum(_smooth(rng, n_frames, 3, 1.0), 0)}
    stretch = {}
    for parent, child in EDGES:
        d = np.asarray(REST[child], float) / np.linalg.norm(REST[child])
        d = d + _smooth(rng, n_frames, 3, 0.35)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        s = rng.normal(0, SD[child], n_frames)
        for t in range(1, n_frames):  # smooth in time (the tracker assumes less: memoryless)
            s[t] = ar * s[t - 1] + np.sqrt(1 - ar**2) * s[t]
        stretch[child] = s
        pos[child] = pos[parent] + (LENGTH[child] * np.exp(s))[:, None] * d
    return np.stack([pos[n] for n in NAMES], 1), stretch


def cameras(n: int = 4, radius: float = 400.0):
    """``n`` pinhole cameras (f = 1000 px, 1280 x 1024, no distortion) on a circle around
    the origin, looking at it: ``(K, dist, rvec, tvec)`` in OpenCV's convention (mm)."""
    out = []
    for i in range(n):
        a = 2 * np.pi * i / n + 0.3
        c = np.array([radius * np.cos(a), radius * np.sin(a), 250.0 + 40 * i])
        z = -c / np.linalg.norm(c)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z])
        k = np.array([[1000.0, 0, 640], [0, 1000.0, 512], [0, 0, 1]])
        out.append((k, np.zeros(5), cv2.Rodrigues(rot)[0].ravel(), -rot @ c))
    return out


def project(cams, pts: np.ndarray) -> np.ndarray:
    """OpenCV projection of ``pts`` (T, K, 3) into every camera: ``(n_cams, T, K, 2)`` px."""
    n_frames = pts.shape[0]
    return np.stack(
        [
            cv2.projectPoints(pts.reshape(-1, 3), rv, tv, k, d)[0].reshape(n_frames, -1, 2)
            for k, d, rv, tv in cams
        ]
    )
