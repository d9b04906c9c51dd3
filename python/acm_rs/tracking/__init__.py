"""Probabilistic pose estimation (ACM supp. sec. 4): :func:`track` and :class:`PoseResult`."""

from .bundle import read_smoothed, smooth_bundle, write_bundle
from .online import OnlineTracker
from .result import PoseResult
from .track import DEFAULT_GATE, default_normalization, gate_threshold, track

__all__ = [
    "DEFAULT_GATE",
    "OnlineTracker",
    "PoseResult",
    "default_normalization",
    "gate_threshold",
    "read_smoothed",
    "smooth_bundle",
    "track",
    "write_bundle",
]
