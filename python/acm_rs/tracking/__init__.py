"""Probabilistic pose estimation (ACM supp. sec. 4): :func:`track` and :class:`PoseResult`."""

from .ambiguity import SecondSolutions, second_solutions
from .any_length import track
from .bundle import read_smoothed, smooth_bundle, write_bundle
from .long import track_long
from .online import OnlineTracker
from .result import PoseResult
from .track import DEFAULT_GATE, default_normalization, gate_threshold
from .windows import read_chunked

__all__ = [
    "DEFAULT_GATE",
    "OnlineTracker",
    "PoseResult",
    "SecondSolutions",
    "default_normalization",
    "gate_threshold",
    "read_chunked",
    "read_smoothed",
    "second_solutions",
    "smooth_bundle",
    "track",
    "track_long",
    "write_bundle",
]
