"""acm-rs: fast 3D skeletal kinematics from multi-camera video (ACM) with a Rust core.

The geometry of the Anatomically Constrained Model (Monsees et al. 2022, supplementary text):
Rodrigues rotations (sec. 1), pinhole cameras with distortion (sec. 2.1), skeleton forward
kinematics (sec. 3.1, Alg. 1), symmetry maps (Alg. 2-3), normalisation (sec. 3.3) and the
joint-limit state map (Alg. 10), all with exact derivatives computed in Rust.
"""

from . import (
    acm_formats,
    batch,
    calibration,
    datasets,
    dlc,
    export,
    gapfill,
    models,
    pipeline,
    plots,
    project,
)
from ._native import AcmNumericalError
from ._version import __version__
from .calibration import CalibrationResult, calibrate
from .camera import PARAM_NAMES, Camera, CameraRig
from .learning import LearnedSkeleton, fit_pose, learn_skeleton
from .rotation import rodrigues, rodrigues_inverse, rodrigues_jacobian
from .skeleton import BoneLengthConstraint, FKJacobian, Skeleton, SymmetryMap
from .state import Normalization, StateMap
from .tracking import (
    OnlineTracker,
    PoseResult,
    SecondSolutions,
    read_chunked,
    second_solutions,
    track,
    track_long,
)

__all__ = [
    "AcmNumericalError",
    "BoneLengthConstraint",
    "CalibrationResult",
    "Camera",
    "CameraRig",
    "FKJacobian",
    "LearnedSkeleton",
    "Normalization",
    "PARAM_NAMES",
    "OnlineTracker",
    "PoseResult",
    "SecondSolutions",
    "Skeleton",
    "StateMap",
    "SymmetryMap",
    "__version__",
    "acm_formats",
    "batch",
    "calibrate",
    "calibration",
    "datasets",
    "dlc",
    "export",
    "gapfill",
    "fit_pose",
    "learn_skeleton",
    "models",
    "pipeline",
    "plots",
    "project",
    "read_chunked",
    "rodrigues",
    "rodrigues_inverse",
    "rodrigues_jacobian",
    "second_solutions",
    "track",
    "track_long",
]
