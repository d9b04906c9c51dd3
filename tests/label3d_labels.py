"""Label3D's own labels read independently of acm-rs (``scipy.io.loadmat``): the truth of the
tests and benchmarks on the real Label3D / DANNCE file (``tests/data/real/dannce``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.io


def read_labels(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """2D labels ``(n_cams, n_frames, n_points, 2)`` in 0-based pixels and 3D labels
    ``(n_frames, n_points, 3)`` (the file's units, mm) of a Label3D ``labelData`` file."""
    m = scipy.io.loadmat(str(path))
    lab2, lab3 = [], None
    for cell in m["labelData"].ravel():
        d2 = cell["data_2d"][0, 0].astype(float)
        lab2.append(d2.reshape(len(d2), -1, 2) - 1.0)  # MATLAB's 1-based pixels
        d3 = cell["data_3d"][0, 0].astype(float)
        lab3 = d3.reshape(len(d3), -1, 3)
    return np.stack(lab2), lab3
