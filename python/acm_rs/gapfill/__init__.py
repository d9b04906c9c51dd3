"""Gap filling of motion-capture marker trajectories (Burke & Lasenby 2016 and baselines).

``fill(X)`` takes an ``(n_frames, n_markers, 3)`` array with NaN for missing values and returns a
filled copy. The default method, ``"lowdim"``, is the low-dimensional Kalman smoother of Burke &
Lasenby (2016) with the fixes and extensions described in ``docs/gapfill.md``; ``"lowdim-paper"``
keeps the published settings; ``"linear"``, ``"spline"``, ``"rw"``, ``"cv"`` and ``"msvd"`` are the
baselines of the paper's Table 1.
"""

from .chunked import fill_chunked
from .filling import METHODS, FillResult, MarkerFill, fill, fill_markers

__all__ = ["METHODS", "FillResult", "MarkerFill", "fill", "fill_chunked", "fill_markers"]
