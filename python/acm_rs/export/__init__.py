"""Export tracked poses (:class:`acm_rs.tracking.result.PoseResult`) to the files the rest of
a lab's stack reads: anipose 3D CSV (+ variance sidecar), NWB (ndx-pose), C3D, NPZ and
movement's xarray layout (netCDF).

Every writer is atomic (a temporary file in the target folder is renamed over the target), so a
killed job never leaves a half-written file. See ``docs/exports.md``.
"""

from __future__ import annotations

from .anipose_csv import anipose_columns, to_anipose_csv, variance_path
from .c3d import to_c3d
from .movement import to_movement, to_movement_file
from .npz import read_npz, to_npz
from .nwb import to_nwb

__all__ = [
    "anipose_columns",
    "read_npz",
    "to_anipose_csv",
    "to_c3d",
    "to_movement",
    "to_movement_file",
    "to_npz",
    "to_nwb",
    "variance_path",
]
