"""Gap filling: ``fill`` (Burke & Lasenby 2016 and baselines), its options and results.

``fill(X)`` takes an ``(n_frames, n_markers, 3)`` array with NaN for missing values and returns a
filled copy. The default method, ``"lowdim"``, is the low-dimensional Kalman smoother of Burke &
Lasenby (2016) with the fixes and extensions described in ``docs/gapfill.md``; ``"lowdim-paper"``
keeps the published settings; ``"linear"``, ``"spline"``, ``"rw"``, ``"cv"`` and ``"msvd"`` are the
baselines of the paper's Table 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import _native

if TYPE_CHECKING:
    from .io import Markers

__all__ = ["METHODS", "FillResult", "MarkerFill", "fill", "fill_markers"]

METHODS: tuple[str, ...] = ("lowdim", "lowdim-paper", "linear", "spline", "rw", "cv", "msvd")
"""Method names accepted by :func:`fill`, in the order of the evaluation tables."""

_DEFAULTS: dict[str, Any] = {
    "gamma": 0.9999,
    "criterion": "energy",
    "dim": None,
    "r": None,
    "em_iters": 3,
    "paper_q": False,
    "subspace_iters": 2,
    "min_complete": 0,
    "combine": "auto",
    "short_gap": None,
    "keep_original": True,
    "memo_tol": 1e-6,
    "seed": 0,
    "window": "auto",
}

#: ``window="auto"``: sequences longer than twice this are smoothed in windows of this many
#: frames (the same fill as one pass, in bounded memory; ``acm_rs::gapfill::AUTO_WINDOW``).
AUTO_WINDOW: int = _native.GAPFILL_AUTO_WINDOW
_PAPER: dict[str, Any] = {
    **_DEFAULTS,
    "gamma": 0.9975,
    "criterion": "singular-values",
    "r": 1e-3,
    "em_iters": 0,
    "paper_q": True,
    "subspace_iters": 0,
    "combine": "none",
}


@dataclass(frozen=True)
class FillResult:
    """Output of :func:`fill` with ``full_output=True``.

    Attributes
    ----------
    filled : ndarray, shape (n_frames, n_markers, 3)
        The filled sequence (same units as the input, e.g. mm).
    std : ndarray or None, shape (n_frames, n_markers, 3)
        Posterior (predictive) standard deviation of every imputed value, 0 at observed
        values; ``None`` for methods without an uncertainty (linear, spline, msvd).
    imputed : ndarray of bool, shape (n_frames, n_markers, 3)
        True where a value was missing and has been filled.
    info : dict
        Diagnostics: subspace dimension ``dim``, learned noise ``r`` (units²) and ``q_trace``,
        ``complete_frames``, ``iterated_subspace``, ``short_gap``, ``em_iters``,
        ``distinct_covariances`` and the options used.
    """

    filled: np.ndarray
    std: np.ndarray | None
    imputed: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


def _as_sequence(X: object) -> np.ndarray:
    """``X`` as a float64 array of shape (n_frames, n_markers, 3), checked; not copied when it
    already is one."""
    try:
        arr = np.asarray(X, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"X must be a numeric array: {exc}") from None
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"X must have shape (n_frames, n_markers, 3), got {arr.shape}")
    if arr.shape[0] < 2:
        raise ValueError(f"X needs at least 2 frames, got {arr.shape[0]}")
    if arr.shape[1] < 1:
        raise ValueError("X has no markers")
    if np.isinf(arr).any():
        bad = tuple(int(i) for i in np.argwhere(np.isinf(arr))[0])
        raise ValueError(f"X contains infinity at index {bad}; use NaN for missing values")
    return arr


def fill(
    X: object,
    *,
    method: str = "lowdim",
    full_output: bool = False,
    empty: str = "error",
    **options: Any,
) -> np.ndarray | FillResult:
    """Fill the gaps (NaN) of marker trajectories.

    Parameters
    ----------
    X : array_like, shape (n_frames, n_markers, 3)
        Marker positions (any length unit, typically mm); NaN marks a missing value. A marker
        with some coordinates NaN is estimated as missing (the model needs whole points), but
        its observed coordinates are returned unchanged: only the NaN coordinates are filled
        (with ``keep_original=True``, the default).
    method : {"lowdim", "lowdim-paper", "linear", "spline", "rw", "cv", "msvd"}
        ``"lowdim"`` (default): low-dimensional Kalman smoothing (Burke & Lasenby 2016,
        Algorithm 1) with the RTS gain fixed, Q and R learned by EM, a subspace that also works
        without complete frames, border-residual correction and the cubic spline on short gaps
        (length threshold calibrated on the data). ``"lowdim-paper"``: the
        published settings. Baselines: linear and natural cubic spline interpolation per
        coordinate, random-walk (``"rw"``) and constant-velocity (``"cv"``) RTS smoothing per
        coordinate, iterative low-rank imputation (``"msvd"``).
    full_output : bool
        If True return a :class:`FillResult` (filled values, posterior standard deviation,
        imputed mask, diagnostics) instead of the filled array.
    empty : {"error", "skip"}
        Markers missing in every frame cannot be estimated from data: ``"error"`` raises
        ``ValueError``; ``"skip"`` leaves them NaN in the output (and ``False`` in ``imputed``).
    **options
        ``gamma`` (energy kept by the subspace, default 0.9999; paper 0.9975),
        ``criterion`` (``"energy"`` on squared singular values, default, or
        ``"singular-values"`` as published), ``dim`` (fixed subspace dimension), ``r``
        (measurement noise variance in units², R = r·I; default learned by EM, paper 1e-3),
        ``em_iters`` (default 3, on at most 2000 frames), ``paper_q`` (published Q),
        ``subspace_iters`` (impute → SVD →
        smooth rounds when complete frames are scarce, default 2), ``min_complete`` (complete
        frames needed to skip those rounds; 0 = max(n_markers, 10)), ``combine``
        (``"none"``; ``"residual"``: the observed-minus-smoothed residual at both borders
        carried into each gap; ``"auto"`` (default): residual, plus the cubic spline for gaps
        up to ``short_gap`` frames), ``short_gap`` (frames; ``None`` = calibrated on the data
        by hiding probe gaps of 1-270 frames; the posterior ``std`` stays the smoother's
        also where the spline fills), ``keep_original``
        (default True), ``memo_tol`` (1e-6), ``seed`` (calibration seed), ``window``
        (frames, ``None`` or ``"auto"``: the smoothing pass of ``lowdim``/``lowdim-paper`` runs
        window by window, each with the longest gap plus a burn-in of context on both sides,
        while the model is still learned from the whole sequence, so the fill equals one pass
        to ~1e-9 of the data's scale in memory of one window; ``None``: one pass; default
        ``"auto"``: windows of :data:`AUTO_WINDOW` frames above twice that length).

    Returns
    -------
    ndarray, shape (n_frames, n_markers, 3), or FillResult
        A filled copy of ``X`` (observed values unchanged unless ``keep_original=False``).

    Raises
    ------
    ValueError
        Wrong shape, fewer than 2 frames, infinite values, unknown method or option, a marker
        missing in every frame (with ``empty="error"``), or ``"lowdim-paper"`` without complete
        frames.

    Examples
    --------
    >>> import numpy as np
    >>> from acm_rs.gapfill import fill
    >>> t = np.linspace(0, 1, 50)[:, None]
    >>> X = np.stack([np.hstack([t, 2 * t, 0 * t]), np.hstack([t, 2 * t, 1 + 0 * t])], axis=1)
    >>> X[10:15, 1] = np.nan
    >>> bool(np.isfinite(fill(X, method="spline")).all())
    True
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    if empty not in ("error", "skip"):
        raise ValueError(f"empty must be 'error' or 'skip', got {empty!r}")
    base = _PAPER if method == "lowdim-paper" else _DEFAULTS
    unknown = set(options) - set(base)
    if unknown:
        raise ValueError(f"unknown option(s) {sorted(unknown)}; known: {sorted(base)}")
    opts = {**base, **options}
    arr = _as_sequence(X)
    n_frames, n_markers, _ = arr.shape
    # A marker is present only with all three coordinates (elementwise ors: 10x faster than
    # ``any(axis=2)`` on a length-3 axis). The input is copied only if some marker is missing
    # in part (then all its coordinates become NaN) or it is not C-contiguous.
    nan = np.isnan(arr)
    missing = nan[..., 0] | nan[..., 1] | nan[..., 2]
    partial = np.count_nonzero(nan) != 3 * np.count_nonzero(missing)
    observed = arr
    if partial:
        arr = arr.copy()
        np.copyto(arr, np.nan, where=missing[..., None])
    dead = missing.all(axis=0)
    if dead.all():
        raise ValueError("every marker is missing in every frame; nothing to fill from")
    if dead.any() and empty == "error":
        raise ValueError(
            f"marker(s) {np.flatnonzero(dead).tolist()} are missing in every frame and cannot be "
            "estimated; remove them or pass empty='skip'"
        )
    keep = ~dead
    everything = bool(keep.all())
    # Boolean indexing copies (and costs more than the fill of a short recording): avoid it
    # when every marker is kept.
    sub = arr if everything else arr[:, keep]
    sub = np.ascontiguousarray(sub.reshape(n_frames, -1))
    window = opts["window"]
    if isinstance(window, str):
        if window != "auto":
            raise ValueError(f"window must be a number of frames, None or 'auto', got {window!r}")
        window = AUTO_WINDOW if n_frames > 2 * AUTO_WINDOW else None
    elif window is not None:
        if isinstance(window, bool) or int(window) != window or window < 1:
            raise ValueError(f"window must be a positive number of frames, got {window!r}")
        window = int(window)
    if opts["min_complete"] == 0:
        opts["min_complete"] = max(int(keep.sum()), 10)
    filled_sub, std_sub, info = _native.gapfill_fill(
        sub,
        method,
        float(opts["gamma"]),
        str(opts["criterion"]),
        None if opts["dim"] is None else int(opts["dim"]),
        None if opts["r"] is None else float(opts["r"]),
        int(opts["em_iters"]),
        bool(opts["paper_q"]),
        int(opts["subspace_iters"]),
        int(opts["min_complete"]),
        str(opts["combine"]),
        None if opts["short_gap"] is None else int(opts["short_gap"]),
        bool(opts["keep_original"]),
        bool(full_output),
        float(opts["memo_tol"]),
        int(opts["seed"]),
        window,
    )
    if everything:
        out = filled_sub.reshape(arr.shape)
    else:
        out = arr.copy()
        out[:, keep] = filled_sub.reshape(n_frames, -1, 3)
    if partial and opts["keep_original"]:
        # a fill never changes an observed coordinate, also of a partly observed point
        np.copyto(out, observed, where=~nan)
    if not full_output:
        return out
    imputed = np.zeros(arr.shape, dtype=bool)
    imputed[:, keep] = np.repeat(missing[:, keep, None], 3, axis=2)
    if partial and opts["keep_original"]:
        imputed &= nan
    std = None
    if std_sub is not None and method not in ("linear", "spline", "msvd"):
        std = np.zeros(arr.shape)
        std[:, keep] = std_sub.reshape(n_frames, -1, 3)
        std[:, dead] = np.nan
        if partial and opts["keep_original"]:
            std[~nan] = 0.0
    info = {**info, "method": method, "options": opts, "skipped_markers": np.flatnonzero(dead)}
    return FillResult(filled=out, std=std, imputed=imputed, info=info)


@dataclass(frozen=True)
class MarkerFill:
    """Output of :func:`fill_markers`: every point of a marker file, the filled ones and the
    ones left as read.

    Attributes
    ----------
    filled : ndarray, shape (n_frames, n_points, 3)
        The points of the file: the selected ones filled, the others exactly as read (NaN
        where missing).
    imputed : ndarray of bool, shape (n_frames, n_points, 3)
        True where a missing coordinate was filled.
    std : ndarray or None, shape (n_frames, n_points, 3)
        Posterior standard deviations (when asked for and the method has them): 0 at observed
        values and at the points left as read, NaN where a value is still missing.
    selected : ndarray of bool, shape (n_points,)
        The points given to the filler (the markers, or every point).
    skipped : dict of str to list of str
        Labels of the points left as read, by kind (``"angle"``, ``"force"``, ...).
    result : FillResult or None
        The filler's own output on the selected points (``full_output``).
    """

    filled: np.ndarray
    imputed: np.ndarray
    std: np.ndarray | None
    selected: np.ndarray
    skipped: dict[str, list[str]]
    result: FillResult | None = None


def fill_markers(
    m: Markers,
    *,
    include_non_markers: bool = False,
    method: str = "lowdim",
    std: bool = False,
    empty: str = "skip",
    **options: Any,
) -> MarkerFill:
    """Fill the gaps of the markers of a file read with :func:`acm_rs.gapfill.io.read`.

    Points that are not markers (model outputs a C3D lists in POINT:ANGLES, FORCES, MOMENTS,
    POWERS, SCALARS, REACTIONS: ``m.kinds``) are left exactly as read and kept out of the
    model (their units and motion are not a marker's); ``include_non_markers=True`` fills
    them too, in the same model.

    Parameters
    ----------
    m : Markers
        ``m.xyz`` (n_frames, n_points, 3), NaN where missing; ``m.kinds`` says which points
        are markers (None: all).
    include_non_markers : bool
        Also fill the points that are not markers (default False).
    method, empty, **options
        As for :func:`fill` (``empty="skip"`` by default: a point never observed stays NaN).
    std : bool
        Also compute posterior standard deviations (``full_output`` of :func:`fill`).

    Returns
    -------
    MarkerFill

    Raises
    ------
    ValueError
        When no point is selected (a file of model outputs only, without
        ``include_non_markers``), or as :func:`fill`.
    """
    xyz = np.asarray(m.xyz, dtype=np.float64)
    is_marker = np.asarray(m.is_marker, dtype=bool)
    selected = np.ones_like(is_marker) if include_non_markers else is_marker
    kinds = m.kinds or ["marker"] * xyz.shape[1]
    skipped: dict[str, list[str]] = {}
    for j in np.flatnonzero(~selected):
        skipped.setdefault(kinds[j], []).append(m.labels[j])
    if not selected.any():
        raise ValueError(
            "the file holds no markers, only model outputs ("
            + ", ".join(f"{k}s: {len(v)}" for k, v in skipped.items())
            + "); pass include_non_markers=True (--include-non-markers) to fill them"
        )
    everything = bool(selected.all())
    sub = xyz if everything else xyz[:, selected]
    res = fill(sub, method=method, full_output=std, empty=empty, **options)
    out_sub = res.filled if std else res
    filled = out_sub if everything else xyz.copy()
    if not everything:
        filled[:, selected] = out_sub
    imputed = np.isnan(xyz) & np.isfinite(filled)
    sd = None
    if std and res.std is not None:
        sd = np.zeros_like(xyz)
        sd[:, selected] = res.std
        sd[np.isnan(filled)] = np.nan
    return MarkerFill(filled, imputed, sd, selected, skipped, res if std else None)
