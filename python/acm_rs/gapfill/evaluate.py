"""Evaluation protocol of Burke & Lasenby (2016, sec. 4): insert gaps into a complete sequence,
fill them, and score the removed values only.

Gap model (documented in ``docs/gapfill.md``): gaps start at uniformly random frames in
uniformly random markers; their durations are log-normal with a median of ``median_s`` seconds
(default 0.05 s) and a log-standard deviation of ``sigma`` (default 1.2), truncated to
``[1 frame, max_s]`` (default 5 s). Most gaps are a few frames long, about 1 in 30 is longer
than half a second and a few last several seconds, the shape of the real gap histogram in the
paper's Fig. 1. The number of gaps is ``rate_per_marker_s`` (default 0.5) × markers × duration.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._io import atomic_write
from .filling import METHODS, fill

__all__ = ["EvalResult", "evaluate", "insert_gaps", "run_lengths"]


def insert_gaps(
    X: np.ndarray,
    rate: float,
    rng: np.random.Generator,
    *,
    rate_per_marker_s: float = 0.5,
    median_s: float = 0.05,
    sigma: float = 1.2,
    max_s: float = 5.0,
) -> np.ndarray:
    """Return a copy of ``X`` with random marker gaps (NaN).

    Parameters
    ----------
    X : ndarray, shape (n_frames, n_markers, 3)
        A complete sequence (mm).
    rate : float
        Frame rate in Hz (converts durations to frames).
    rng : numpy.random.Generator
        Seeded generator.
    rate_per_marker_s, median_s, sigma, max_s : float
        Gap model (see the module docstring).

    Returns
    -------
    ndarray, shape (n_frames, n_markers, 3)
        The gapped copy; every marker keeps at least 2 observed frames.
    """
    X = np.asarray(X, dtype=np.float64)
    n_frames, n_markers, _ = X.shape
    n_gaps = max(1, round(rate_per_marker_s * n_markers * n_frames / rate))
    lengths = np.exp(rng.normal(np.log(median_s * rate), sigma, n_gaps))
    lengths = np.clip(np.round(lengths), 1, max(1, min(max_s * rate, n_frames // 3))).astype(int)
    G = X.copy()
    for length in lengths:
        m = int(rng.integers(n_markers))
        s = int(rng.integers(0, n_frames - length + 1))
        G[s : s + length, m] = np.nan
    # Never remove a marker entirely: restore its first and last frame if needed.
    for m in np.flatnonzero(np.isnan(G[:, :, 0]).sum(axis=0) > n_frames - 2):
        G[[0, -1], m] = X[[0, -1], m]
    return G


def run_lengths(mask: np.ndarray) -> np.ndarray:
    """Length of the run of True containing each True entry, per column.

    Parameters
    ----------
    mask : ndarray of bool, shape (n_frames, n_markers)

    Returns
    -------
    ndarray of int, shape (n_frames, n_markers)
        0 where ``mask`` is False.
    """
    out = np.zeros(mask.shape, dtype=np.int64)
    for j in range(mask.shape[1]):
        col = mask[:, j].astype(np.int8)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], col, [0]])))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            out[a:b, j] = b - a
    return out


@dataclass
class EvalResult:
    """Errors of every method on the removed values of every repetition.

    Attributes
    ----------
    errors : dict of str to ndarray
        Euclidean marker error (mm) of each removed marker-frame, all repetitions concatenated.
    gap_frames : ndarray of int
        Length (frames) of the gap containing each removed marker-frame (same order).
    seconds : dict of str to list of float
        Wall time of each fill.
    rate : float
        Frame rate (Hz).
    failures : dict of str to str
        Methods that raised, with the message.
    """

    errors: dict[str, np.ndarray]
    gap_frames: np.ndarray
    seconds: dict[str, list[float]]
    rate: float
    failures: dict[str, str] = field(default_factory=dict)

    def summary(self) -> dict[str, dict[str, float]]:
        """Median, mean, SD, Q3 and max error (mm) and mean time (s) per method (Table 1/2)."""
        out = {}
        for m, e in self.errors.items():
            out[m] = {
                "median": float(np.median(e)),
                "mean": float(np.mean(e)),
                "sd": float(np.std(e)),
                "q3": float(np.percentile(e, 75)),
                "max": float(np.max(e)),
                "seconds": float(np.mean(self.seconds[m])),
            }
        return out

    def by_length(self, edges_s: tuple[float, ...] = (0, 0.05, 0.1, 0.25, 0.5, 1, 2, 5, 1e9)):
        """Mean error (mm) per gap-length bin (seconds), as in Fig. 3."""
        sec = self.gap_frames / self.rate
        rows = {}
        for m, e in self.errors.items():
            rows[m] = [
                float(e[(sec > a) & (sec <= b)].mean()) if np.any((sec > a) & (sec <= b)) else None
                for a, b in zip(edges_s[:-1], edges_s[1:], strict=True)
            ]
        return list(edges_s), rows

    def table(self, units: str = "mm") -> str:
        """The summary as a Markdown table: reconstruction errors of the removed marker-frames
        in ``units`` (those of the positions evaluated), fill time in s."""
        s = self.summary()
        u = f" ({units})"
        lines = [
            f"| method | median{u} | mean{u} | SD{u} | Q3{u} | max{u} | time (s) |",
            "|---|---|---|---|---|---|---|",
        ]
        for m, v in s.items():
            lines.append(
                f"| {m} | {v['median']:.2f} | {v['mean']:.2f} | {v['sd']:.2f} | {v['q3']:.2f} "
                f"| {v['max']:.1f} | {v['seconds']:.3f} |"
            )
        return "\n".join(lines)

    def save_json(self, path: str | Path) -> None:
        """Write the summary and the error-vs-length table as JSON (atomically)."""
        edges, rows = self.by_length()
        doc = {
            "summary_mm": self.summary(),
            "by_gap_length": {"edges_s": edges, "mean_mm": rows},
            "failures": self.failures,
            "n_values": int(self.gap_frames.size),
        }
        with atomic_write(path) as fh:
            json.dump(doc, fh, indent=2)

    def plot(self, path: str | Path) -> Path:
        """Error vs gap length (Fig. 3 of the paper) as a PNG: median and IQR per length bin."""
        from ..plotting import _pyplot, save_figure

        plt = _pyplot()
        fig, ax = plt.subplots(figsize=(7, 4.5))
        sec = self.gap_frames / self.rate
        edges = np.unique(np.geomspace(1, max(2, self.gap_frames.max() + 1), 14).astype(int))
        centres = np.sqrt(edges[:-1] * edges[1:]) / self.rate
        for m, e in self.errors.items():
            med, lo, hi = [], [], []
            for a, b in zip(edges[:-1], edges[1:], strict=True):
                sel = (self.gap_frames >= a) & (self.gap_frames < b)
                if sel.any():
                    q = np.percentile(e[sel], [25, 50, 75])
                    lo.append(q[0])
                    med.append(q[1])
                    hi.append(q[2])
                else:
                    lo.append(np.nan)
                    med.append(np.nan)
                    hi.append(np.nan)
            (line,) = ax.plot(centres, med, marker="o", ms=3, label=m)
            ax.fill_between(centres, lo, hi, color=line.get_color(), alpha=0.12)
        del sec
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("gap length (s)")
        ax.set_ylabel("marker error (mm), median and IQR")
        ax.legend(fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        return save_figure(fig, path)


def evaluate(
    X: np.ndarray,
    rate: float,
    *,
    methods: tuple[str, ...] | list[str] = METHODS,
    repeats: int = 3,
    seed: int = 0,
    gap_options: dict[str, float] | None = None,
    method_options: dict[str, dict[str, Any]] | None = None,
) -> EvalResult:
    """Run the protocol: ``repeats`` gapped copies of ``X``, filled by every method.

    Parameters
    ----------
    X : ndarray, shape (n_frames, n_markers, 3)
        A complete sequence (mm); NaN-free.
    rate : float
        Frame rate (Hz).
    methods : sequence of str
        Names accepted by :func:`acm_rs.gapfill.fill`; ``"name:label"`` is not supported, use
        ``method_options`` keyed by the method name.
    repeats : int
        Number of gapped copies (seeds ``seed, seed + 1, ...``).
    seed : int
        First seed.
    gap_options : dict, optional
        Keyword arguments of :func:`insert_gaps`.
    method_options : dict, optional
        Extra ``fill`` options per method name.

    Returns
    -------
    EvalResult
    """
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 3 or X.shape[2] != 3:
        raise ValueError(f"X must have shape (n_frames, n_markers, 3), got {X.shape}")
    if not np.isfinite(X).all():
        raise ValueError("the evaluation needs a complete (NaN-free) ground-truth sequence")
    if repeats < 1:
        raise ValueError("repeats must be >= 1")
    method_options = method_options or {}
    errors: dict[str, list[np.ndarray]] = {m: [] for m in methods}
    seconds: dict[str, list[float]] = {m: [] for m in methods}
    failures: dict[str, str] = {}
    lengths = []
    for rep in range(repeats):
        rng = np.random.default_rng(seed + rep)
        G = insert_gaps(X, rate, rng, **(gap_options or {}))
        removed = np.isnan(G[:, :, 0])
        lengths.append(run_lengths(removed)[removed])
        for m in methods:
            t0 = time.perf_counter()
            try:
                F = fill(G, method=m, **method_options.get(m, {}))
            except ValueError as exc:
                failures[m] = str(exc)
                F = np.full_like(G, np.nan)
            seconds[m].append(time.perf_counter() - t0)
            errors[m].append(np.linalg.norm(F - X, axis=2)[removed])
    ok = [m for m in methods if m not in failures]
    return EvalResult(
        {m: np.concatenate(errors[m]) for m in ok},
        np.concatenate(lengths),
        {m: seconds[m] for m in ok},
        float(rate),
        failures,
    )
