"""Multi-camera calibration (ACM supplement section 2.2, eq. 7).

Board detection with OpenCV (:mod:`.detection`, :class:`BoardSpec`), initialisation without
guesses (:mod:`.initialise`), refinement of eq. 7 with scipy's trust-region-reflective solver
on residuals and exact sparse Jacobians from Rust (:func:`calibrate`), a QC report
(:class:`CalibrationResult`), anipose ``calibration.toml`` output, ACM
``multicalibration.npy`` import (:mod:`.acm`) and Label3D / DANNCE ``.mat`` import
(:mod:`.label3d`), and refinement on an animal's labelled keypoints (:mod:`.keypoints`).
See ``docs/calibration.md``.
"""

from .acm import load_acm_calibration, save_acm_calibration
from .board import BoardSpec
from .detection import Detections, detect, detect_board
from .keypoints import KeypointRefinement, refine_on_keypoints
from .label3d import read_label3d_calibration
from .result import CalibrationResult
from .solve import CAMERA_PARAMS, calibrate
from .world import frame_from_points, transform_rig, triangulate

__all__ = [
    "BoardSpec",
    "CAMERA_PARAMS",
    "CalibrationResult",
    "Detections",
    "KeypointRefinement",
    "calibrate",
    "detect",
    "detect_board",
    "frame_from_points",
    "load_acm_calibration",
    "read_label3d_calibration",
    "refine_on_keypoints",
    "save_acm_calibration",
    "transform_rig",
    "triangulate",
]
