"""NumPy ``.npz`` export: every array of a result plus the model and calibration as text.

The format belongs to :class:`~acm_rs.tracking.result.PoseResult` (``PoseResult.save`` and
``PoseResult.load`` use it); it is implemented in :mod:`acm_rs.tracking.result_npz`.
"""

from __future__ import annotations

from ..tracking.result_npz import NPZ_FORMAT, NPZ_VERSION, read_npz, to_npz

__all__ = ["NPZ_FORMAT", "NPZ_VERSION", "read_npz", "to_npz"]
