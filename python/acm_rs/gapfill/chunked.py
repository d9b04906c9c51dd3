"""Gap filling of long recordings in bounded memory (issue 16 item 4).

:func:`fill_chunked` cuts the recording into cores of ``chunk`` frames and fills each over a
window with ``margin`` frames of context on both sides, as an independent sequence, keeping
the core. Gaps are local, so every gap that touches a core lies inside its window when the
margin is longer than the longest gap; the model (subspace, ``Q``, ``R``) is learned per
window, as :func:`acm_rs.gapfill.fill` already learns it on at most 2,000 frames. Peak memory
is that of one window, whatever the recording's length. The input may be a ``numpy.memmap``
(read one window at a time) and so may ``out``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .filling import FillResult, fill

#: Frames per core and of context on each side (at least twice the longest gap).
DEFAULT_CHUNK = 20000
DEFAULT_MARGIN = 2000


def longest_gap(X: np.ndarray, block: int = 100_000) -> int:
    """Longest run of frames in which one marker is missing (NaN), read in blocks."""
    T = X.shape[0]
    run = np.zeros(X.shape[1], dtype=np.int64)
    best = 0
    for a in range(0, T, block):
        miss = np.isnan(np.asarray(X[a : a + block])).any(axis=-1)  # (B, M)
        for row in miss:
            run = np.where(row, run + 1, 0)
            best = max(best, int(run.max()))
    return best


def fill_chunked(
    X: np.ndarray,
    *,
    method: str = "lowdim",
    chunk: int = DEFAULT_CHUNK,
    margin: int | None = None,
    full_output: bool = False,
    out: np.ndarray | None = None,
    **options: Any,
) -> np.ndarray | FillResult:
    """Fill the gaps of a long recording window by window (module docstring).

    Parameters
    ----------
    X : array_like, shape (n_frames, n_markers, 3)
        Marker positions (e.g. mm), NaN missing; sliced ``X[a:b]`` per window.
    method, options
        As :func:`acm_rs.gapfill.fill`.
    chunk : int
        Frames per core.
    margin : int or None
        Frames of context on each side of a core; default ``max(2000, 2 × the longest gap)``.
    full_output : bool
        Return a :class:`FillResult` whose ``info`` lists the windows' diagnostics.
    out : ndarray, optional
        Where to write the filled values (e.g. an ``open_memmap``); default a new array.

    Returns
    -------
    ndarray or FillResult
        As :func:`acm_rs.gapfill.fill`.
    """
    shape = tuple(X.shape)
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"X must have shape (n_frames, n_markers, 3), got {shape}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    T = shape[0]
    gap = longest_gap(X)
    margin = max(DEFAULT_MARGIN, 2 * gap) if margin is None else int(margin)
    if margin < gap:
        raise ValueError(
            f"margin = {margin} frames is shorter than the longest gap ({gap} frames): a gap "
            "could be cut by a window's edge; use a larger margin"
        )
    if out is None:
        out = np.empty(shape, dtype=np.float64)
    elif tuple(out.shape) != shape:
        raise ValueError(f"out must have shape {shape}, got {tuple(out.shape)}")
    std = np.zeros(shape) if full_output else None
    imputed = np.zeros(shape, dtype=bool) if full_output else None
    infos = []
    for a in range(0, T, chunk):
        b = min(T, a + chunk)
        w0, w1 = max(0, a - margin), min(T, b + margin)
        win = np.asarray(X[w0:w1], dtype=np.float64)
        res = fill(win, method=method, full_output=True, **options)
        core = slice(a - w0, b - w0)
        out[a:b] = res.filled[core]
        if full_output:
            if res.std is not None:
                std[a:b] = res.std[core]
            imputed[a:b] = res.imputed[core]
            infos.append({"frames": (a, b), "window": (w0, w1)} | dict(res.info))
    if not full_output:
        return out
    info = {"chunk": chunk, "margin": margin, "longest_gap": gap, "windows": infos}
    has_std = method not in ("linear", "spline", "msvd")
    return FillResult(filled=out, std=std if has_std else None, imputed=imputed, info=info)
