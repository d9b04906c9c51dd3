"""The exact smoother of a whole recording in bounded memory (issue 16 item 1; beyond the
paper): checkpointed filtered states with recomputation.

With Θ fixed, the smoother of a recording (Alg. 7 + 9) needs every frame's filtered moments
in the backward pass: ``(T+1) (order · n)² · 8`` bytes, 58 GB for an hour of the rat at 200
fps under the velocity model. Instead:

1. **Forward** (sequential): the recording is filtered segment by segment (``segment``
   frames each); only the filtered moments at each segment's end are kept (the checkpoints,
   ``(order · n)² · 8`` bytes each).
2. **Backward** (segments in reverse): each segment is filtered again from its checkpoint —
   the same numbers as in step 1 — and smoothed backwards (Alg. 8) starting from the
   smoothed moments at the start of the next segment (``NativeTracker.smooth_filtered``).

The result equals the smoother of the whole recording to rounding (tested).

**The spill** (default where the disk has room): the forward pass also writes each
segment's filtered moments to a scratch directory beside the output — means and the lower
triangles of the covariances in float64 (``(order · n) (order · n + 1) / 2 + order · n``
values per frame: 10.6 kB for the rat's random walk, 41 kB with velocity; 7.6 / 30 GB for
an hour at 200 fps) and the entry statuses — and the backward pass reads them back instead
of filtering again: the same numbers bit for bit (tested), at the cost of disk, not memory.
The backward pass is pipelined: while one segment is smoothed, the posterior of the
previous one (joints, markers and their SDs) is computed and written by a second thread.
Without a spill (``spill=False``, or too little free disk) each segment is filtered again
from its checkpoint (a second forward pass), ``workers`` segments ahead in parallel with
the backward pass of the current one.

Memory: a few segments' moments (``segment · (order · n)² · 8`` bytes each, 160 MB for the
rat's velocity state and the defaults) plus the checkpoints (T / segment of them).

**Sequences.** The filter starts at the first frame with enough detections (the sec. 4.7
fit, broad prior); segments before it without any such frame are written as NaN.

**Restarts where the filter lost the animal** (``restart=True``, the default). With Θ
fixed a filter can lose a body part for good: under the velocity model the rat's tail went
off in the first 1,200 frames of the 100,000-frame bench and stayed 5-6 mm off to the end
(its image points beyond the innovation gate, too few for the "more than half" rule). When
a segment's filtered poses fit poorly (the ``poor_fit`` test below), or the gate rejects
more than ``RESTART_GATED`` (5 %) of the measured entries in each of ``RESTART_GATED_FRAMES``
(50) frames, from frame ``s`` on, the segment is cut at ``s`` and a new sequence starts
there with a fresh single-frame fit and the broad prior — not where one has just started
(then the detections, not the filter, are off). Each sequence is smoothed on its own (the
backward pass does not cross a restart); restarts are listed in ``info["restarts"]``. On
that bench, the first 6,000 frames: 4.1-7.0 mm per 500 frames without restarts (8-10 % of
the entries gated, the 90th-percentile reprojection only ~2 × a typical frame's: the
``poor_fit`` test alone restarted at frame 1,194), one restart at frame 136 with the gate
test, then 0.46-0.52 mm (0.7 % of the entries gated, as where the animal is tracked).

**Poorly fit stretches are reported, not hidden.** Every frame's 90th percentile
reprojection error of the filtered pose is stored (``filtered_px``; a percentile that sees a
tail that is off, which the median does not); stretches of ``POOR_FRAMES`` or more frames
above ``poor_fit`` × the typical error (the EM windows') are listed in
``info["poor_fit"]`` with a warning (a camera moved, another animal, a movement the fixed
Θ cannot follow).

Under the velocity model, segments with ``HINT_GAP`` frames without detections linearise
about the random walk's posterior of that segment (as the chunked smoother's windows do).
"""

from __future__ import annotations

import math
import shutil
import sys
import tempfile
import time
import warnings
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .. import _native
from .._version import __version__
from ..state import StateMap
from .track import _on_terminal
from .windows import (
    _H5Writer,
    _Model,
    _normalized,
    _Source,
    _window_prior,
    close_output,
    frame_px,
    set_hint,
)

#: Frames per segment of the streaming smoother.
DEFAULT_SEGMENT = 2000
#: Covariance buffers a run keeps for its next trackers (a segment's whole-state and position
#: covariances, for the one being filtered and the one being checked or written).
BUFFERS = 4
#: A poorly fit stretch has at least this many consecutive frames ...
POOR_FRAMES = 10
#: ... whose reprojection error (px, :func:`frame_px`) is this multiple of a typical frame's.
DEFAULT_POOR_FIT = 4.0


@dataclass
class _Segment:
    a: int
    b: int
    mu: np.ndarray  # checkpoint: filtered moments before frame a (or a sequence's prior)
    cov: np.ndarray
    last: bool = False  # its backward pass starts from its own filtered end


def _filtered(model: _Model, source: _Source, seg: _Segment):
    """Filter one segment from its checkpoint → (tracker, detections in skeleton order,
    the filter's counts)."""
    det = model.detections(*source.window(seg.a, seg.b))
    x = _normalized(model.norm, det)
    native = model.tracker(x)
    set_hint(model, native, det, x, seg.mu)
    p = model.params
    stats = native.e_step(seg.mu, seg.cov, p["Vz"], p["Vx_diag"], model.gate, smooth=False)
    return native, det, stats


def report_poor_fit(
    px: np.ndarray, poor_fit: float | None, typical: float | None
) -> tuple[list[tuple[int, int]], float | None]:
    """The stretches of :func:`poor_stretches` of the frames' reprojection errors ``px``
    (``(T,)``, px) above ``poor_fit × typical`` (px), with a warning if there are any, and
    that limit (None: ``poor_fit`` or ``typical`` is None, nothing reported)."""
    limit = None if poor_fit is None or typical is None else poor_fit * typical
    poor = [] if limit is None else poor_stretches(px, limit)
    if poor:
        frames = sum(b - a for a, b in poor)
        warnings.warn(
            f"{len(poor)} stretch(es) ({frames} frames, first {poor[:3]}) where the "
            f"filtered poses reproject > {limit:.3g} px ({poor_fit} x a typical frame's "
            f"{typical:.3g} px) for {POOR_FRAMES}+ frames: a moved camera, another animal, "
            "or movement the fixed parameters cannot follow (dataset filtered_px)",
            stacklevel=3,
        )
    return poor, limit


def poor_stretches(px: np.ndarray, limit: float, run: int = POOR_FRAMES) -> list[tuple[int, int]]:
    """Frame ranges ``[(start, stop)]`` of at least ``run`` consecutive frames with
    ``px > limit`` (NaN counts as fine: no detections to judge by)."""
    bad = np.concatenate([[False], np.nan_to_num(px, nan=0.0) > limit, [False]])
    edges = np.flatnonzero(np.diff(bad.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a >= run]


#: Free disk space left over beyond the spill's size before ``spill="auto"`` spills (bytes).
SPILL_RESERVE = 2 * 2**30


def spill_bytes(n_frames: int, n_state: int, n_meas: int, n_segments: int = 1) -> int:
    """Disk space of the spill of ``n_frames`` frames (bytes): per frame the filtered mean
    and the lower triangle of the covariance of the ``n_state``-dimensional state (float64)
    and ``n_meas`` entry statuses (uint8); one more row per segment (its checkpoint)."""
    rows = n_frames + n_segments
    return rows * (n_state + n_state * (n_state + 1) // 2) * 8 + n_frames * n_meas


def _spill_dir(spill, out: Path, need: int) -> tuple[Path | None, str]:
    """The spill's scratch directory (created; None: filter again) and, if none, why."""
    if spill is None or spill is False:
        return None, "spill=False"
    if isinstance(spill, str) and spill == "auto":
        base = out.parent
        free = shutil.disk_usage(base).free
        if free < need + SPILL_RESERVE:
            return None, (f"{need / 1e9:.1f} GB needed, {free / 1e9:.1f} GB free in {base} "
                          f"(keeping {SPILL_RESERVE / 2**30:.0f} GiB)")  # fmt: skip
    elif spill is True:
        base = out.parent
    elif isinstance(spill, (str, Path)):
        base = Path(spill)
        if not base.is_dir():
            raise ValueError(f"spill directory {base} does not exist")
    else:
        raise ValueError(f"spill must be 'auto', True, False or a directory, got {spill!r}")
    return Path(tempfile.mkdtemp(prefix=f".{out.name}.spill.", dir=base)), ""


def _save_segment(folder: Path, k: int, means, packed, mask) -> None:
    for name, arr in (("means", means), ("packed", packed), ("mask", mask)):
        np.save(folder / f"{k}.{name}.npy", arr, allow_pickle=False)


def _load_segment(model: _Model, source: _Source, seg: _Segment, folder: Path, k: int):
    """A tracker of the segment holding its filtered moments read back from the spill (the
    files are removed once read)."""
    det = model.detections(*source.window(seg.a, seg.b))
    native = model.tracker(_normalized(model.norm, det))
    arrays = []
    for name in ("means", "packed", "mask"):
        f = folder / f"{k}.{name}.npy"
        arrays.append(np.load(f, allow_pickle=False))
        f.unlink()
    native.load_filtered(*arrays)
    return native


def _finish(model: _Model, writer: _H5Writer, seg: _Segment, native) -> None:
    """Posterior of a smoothed segment (poses, joints, markers and their SDs) → the file."""
    poses, joints, markers, joints_std, markers_std = native.posterior()
    status = native.mask()[..., 0].transpose(1, 0, 2)
    res = {
        "joints": joints, "joints_std": joints_std, "markers": markers,
        "markers_std": markers_std, "poses": poses, "status": status,
    }  # fmt: skip
    writer.write(seg.a, seg.b, res, seg.a)


#: A restart also where at least this share of a frame's measured entries is gated ...
RESTART_GATED = 0.05
#: ... in this many consecutive frames (the rat's lost tail: 8-10 % of the entries gated
#: frame after frame, against ~1 % confident outliers when it is tracked).
RESTART_GATED_FRAMES = 50


def gated_fraction(mask: np.ndarray) -> np.ndarray:
    """Per frame, the share of the measured entries that the innovation gate rejected
    (``mask``: the filter's statuses, frames first)."""
    m = mask.reshape(len(mask), -1)
    measured = (m != 0).sum(axis=1)
    return np.where(measured > 0, (m == 2).sum(axis=1) / np.maximum(measured, 1), 0.0)


@dataclass
class ForwardPass:
    """What the forward pass of :func:`forward_pass` leaves: the segments (with their
    checkpoints and sequence ends), the filter's counts, a typical frame's reprojection
    error (px) and the frames where new sequences started."""

    segments: list[_Segment]
    totals: dict[str, float]
    typical: float | None
    restarts: list[int]


def forward_pass(
    model: _Model,
    source: _Source,
    segment: int,
    *,
    poor_fit: float | None,
    typical_px: float | None,
    restart: bool,
    folder: Path | None,
    filtered_px,
    show: bool = False,
) -> ForwardPass:
    """The forward pass of the streaming smoother (module docstring): the recording filtered
    segment after segment (``segment`` frames each), each segment's checkpoint kept, a new
    sequence started where the filter lost the animal (``restart``; ``poor_fit`` a multiple
    of ``typical_px``, a typical frame's 90th percentile reprojection error in px, None: the
    median over the first segment), each frame's reprojection error (px) written into
    ``filtered_px`` (length ``T``: an array or an HDF5 dataset), and the filtered moments
    spilled to ``folder`` if given."""
    T = source.n_frames
    sm = StateMap(model.skeleton, model.norm, model.joint_limits)
    n = sm.n_state
    totals: dict[str, float] = {}
    segs: list[_Segment] = []
    a, prior = 0, None
    # one segment at a time: its tracker uses all cores (the sigma points and the Gram
    # products of each frame split between them; 2 vCPU: 2,250 vs 2,000 frames/s)
    sequential = replace(model, threads=0)
    typical = typical_px if typical_px is not None and math.isfinite(typical_px) else None
    restarts: list[int] = []
    last_restart = -1
    # the next segment is filtered from this one's end while this one is checked, spilled and
    # scored (the second core's work; discarded if this one is cut by a restart)
    pending: tuple[_Segment, Future] | None = None
    with ThreadPoolExecutor(max_workers=1) as saver, \
            ThreadPoolExecutor(max_workers=1) as filterer:  # fmt: skip
        saved: Future | None = None

        def keep(seg: _Segment, native, det, stats, px=None) -> None:
            """Accept a filtered segment: counts, spill, reprojection errors."""
            nonlocal saved, typical
            for key, v in stats.items():
                totals[key] = totals.get(key, 0.0) + float(v)
            if folder is not None:
                means, packed = native.filtered_packed()
                if saved is not None:
                    saved.result()  # one segment in flight: memory stays bounded
                saved = saver.submit(_save_segment, folder, len(segs), means, packed,
                                     native.mask())  # fmt: skip
            if px is None:
                px = frame_px(model, sm, native.means()[1:, :n], det)
            if typical is None and np.isfinite(px).any():
                typical = float(np.nanmedian(px))
            filtered_px[seg.a : seg.b] = px
            segs.append(seg)

        while a < T:
            b = min(a + segment, T)
            fresh = prior is None
            if fresh:
                det = model.detections(*source.window(a, b))
                mu = _window_prior(sequential, det)
                if mu is None:  # nothing to start from in these frames
                    a = b
                    continue
                prior = (mu, model.prior_cov)
            if pending is not None and pending[0].a == a and not fresh:
                seg = pending[0]
                native, det, stats = pending[1].result()
            else:
                seg = _Segment(a, b, prior[0], prior[1])
                native, det, stats = _filtered(sequential, source, seg)
            pending = None
            if b < T:
                nxt = _Segment(b, min(b + segment, T), *native.state_row(-1))
                pending = (nxt, filterer.submit(_filtered, sequential, source, nxt))
            cut, px = None, None
            if fresh:
                tail_px, tail_g = np.zeros(0), np.zeros(0)
            if restart and poor_fit is not None:
                px = frame_px(model, sm, native.means()[1:, :n], det)
                gated = gated_fraction(native.mask())
                ref = typical
                if ref is None and np.isfinite(px).any():
                    ref = float(np.nanmedian(px))
                # the previous segment's last frames of this sequence go in front: a stretch
                # across the boundary counts whole (and starts here at the earliest)
                pre_px, pre_g = len(tail_px), len(tail_g)
                lost = [] if ref is None else [
                    (max(0, s0 - pre_px), e - pre_px)
                    for s0, e in poor_stretches(np.concatenate([tail_px, px]), poor_fit * ref)
                    if e > pre_px
                ]  # fmt: skip
                lost += [
                    (max(0, s0 - pre_g), e - pre_g)
                    for s0, e in poor_stretches(np.concatenate([tail_g, gated]), RESTART_GATED,
                                                run=RESTART_GATED_FRAMES)
                    if e > pre_g
                ]  # fmt: skip
                tail_px = px[-(POOR_FRAMES - 1) :] if POOR_FRAMES > 1 else px[:0]
                tail_g = gated[-(RESTART_GATED_FRAMES - 1) :]
                for s0, _ in sorted(lost):
                    # the filter lost the animal at a + s0: start afresh there (not where it
                    # has just started afresh: then the detections are off)
                    if a + s0 > last_restart and (s0 > 0 or not fresh):
                        cut = a + s0
                        break
            if cut is None:
                keep(seg, native, det, stats, px)
                prior = native.state_row(-1)
                a = b
            else:
                del native
                if pending is not None:  # filtered from a state that is not kept: its
                    pending[1].exception()  # result, or error, is dropped once it is done
                    pending = None
                if cut > a:  # the frames before the loss end this sequence
                    part = _Segment(a, cut, seg.mu, seg.cov)
                    keep(part, *_filtered(sequential, source, part))
                if segs:
                    segs[-1].last = True
                restarts.append(cut)
                last_restart, prior, a = cut, None, cut
            if show:
                print(f"\rfiltered {a}/{T} frames", end="", file=sys.stderr, flush=True)
        if saved is not None:
            saved.result()
    if segs:
        segs[-1].last = True
    return ForwardPass(segs, totals, typical, restarts)


def smooth_streaming(
    model: _Model,
    source: _Source,
    out: Path,
    *,
    segment: int = DEFAULT_SEGMENT,
    poor_fit: float | None = DEFAULT_POOR_FIT,
    typical_px: float | None = None,
    workers: int = 2,
    spill: str | Path | bool | None = "auto",
    restart: bool = True,
    info: dict | None = None,
    progress: bool | None = False,
) -> dict:
    """Smooth a whole recording with fixed parameters exactly, in bounded memory (module
    docstring), writing the HDF5 file ``out`` (the layout of :func:`acm_rs.track_long`, plus
    ``filtered_px (T,)``, each frame's 90th percentile reprojection error of the filtered
    pose); returns the run's info.

    ``poor_fit``: report stretches of ``POOR_FRAMES`` frames that reproject further than
    ``poor_fit × typical_px`` (None: do not). ``typical_px``: a typical frame's 90th
    percentile reprojection error (default: the median over the first segment's frames).
    ``spill``: where the forward pass keeps the filtered moments for the backward pass
    (:func:`spill_bytes` of disk; removed at the end): ``"auto"`` (default) a scratch
    directory beside ``out`` if that disk has room for it plus ``SPILL_RESERVE``, else none;
    ``True`` beside ``out`` regardless; a directory; ``False``: none (each segment is
    filtered again, ``workers`` segments in parallel). The result is the same.
    ``restart``: where the filtered poses fit poorly (as ``poor_fit``), start a new sequence
    with a fresh single-frame fit (module docstring); needs ``poor_fit``."""
    t_start = time.perf_counter()
    T = source.n_frames
    if segment < 2:
        raise ValueError(f"segment must be >= 2 frames, got {segment}")
    if poor_fit is not None and not poor_fit > 1.0:
        raise ValueError(f"poor_fit must be > 1 (a multiple of the typical error), got {poor_fit}")
    sm = StateMap(model.skeleton, model.norm, model.joint_limits)
    n = sm.n_state
    ns = n * model.order
    n_meas = 2 * len(model.rig) * model.skeleton.n_markers
    # the trackers of this run hand their covariances on instead of each taking fresh pages
    # from the kernel (1.5 million page faults per 20,000 velocity frames, on the filter's
    # critical path; src/tracking/buffers.rs)
    model = replace(model, buffers=_native.NativeBufferPool(BUFFERS))
    need = spill_bytes(T, ns, n_meas, -(-T // segment))
    show = _on_terminal(progress)
    out = Path(out)
    # the writer first: it creates the output's folder, where the spill goes by default
    writer = _H5Writer(out, T, model.skeleton, len(model.rig), segment)
    folder = None
    try:
        folder, no_spill = _spill_dir(spill, out, need)
        filtered_px = writer.f.create_dataset(
            "filtered_px", (T,), dtype="f8", chunks=(max(1, min(segment, T)),), fillvalue=np.nan
        )
        fwd = forward_pass(
            model, source, segment, poor_fit=poor_fit, typical_px=typical_px, restart=restart,
            folder=folder, filtered_px=filtered_px, show=show,
        )  # fmt: skip
        segs, totals, typical, restarts = fwd.segments, fwd.totals, fwd.typical, fwd.restarts
        poor, limit = report_poor_fit(filtered_px[:], poor_fit, typical)
        t_forward = time.perf_counter() - t_start
        # -- backward: the filtered moments (read back or filtered again, ahead), smoothed;
        # the posterior and the writing of each segment overlap the next one's smoothing --
        ahead_n = 1 if folder is not None else max(1, workers)
        with ThreadPoolExecutor(max_workers=ahead_n) as pool, \
                ThreadPoolExecutor(max_workers=1) as finisher:  # fmt: skip
            jobs: dict[int, Future] = {}
            order = list(range(len(segs) - 1, -1, -1))

            def ahead(i: int) -> None:
                if i < len(order) and order[i] not in jobs:
                    k = order[i]
                    if folder is not None:  # (one segment at a time: all cores for it)
                        jobs[k] = pool.submit(_load_segment, replace(model, threads=0), source,
                                              segs[k], folder, k)  # fmt: skip
                    else:
                        jobs[k] = pool.submit(lambda k=k: _filtered(model, source, segs[k])[0])

            for i in range(ahead_n):
                ahead(i)
            end = None
            written: Future | None = None
            for i, k in enumerate(order):
                native = jobs.pop(k).result()
                ahead(i + ahead_n)
                seg, p = segs[k], model.params
                native.smooth_filtered(seg.mu, seg.cov, p["Vz"], p["Vx_diag"],
                                       end=None if seg.last else end)  # fmt: skip
                end = native.state_row(0)
                if written is not None:
                    written.result()
                written = finisher.submit(_finish, model, writer, seg, native)
                del native
                if show:
                    print(f"\rsmoothed {len(order) - i - 1} segments left  ", end="",
                          file=sys.stderr, flush=True)  # fmt: skip
            if written is not None:
                written.result()
        if show:
            print(file=sys.stderr)
        run = {
            "segment": int(segment), "n_frames": T, "n_segments": len(segs),
            "poor_fit": poor[:100], "poor_fit_frames": sum(b - a for a, b in poor),
            "poor_fit_factor": poor_fit, "poor_fit_px": None if limit is None else float(limit),
            "typical_px": typical,
            "seconds_forward": t_forward, "seconds_smoothing": time.perf_counter() - t_start,
            "scheduler": f"threads({workers})", "stats": totals,
            "restarts": restarts[:100], "n_restarts": len(restarts),
            "spill": folder is not None, "spill_bytes": need if folder is not None else 0,
            "no_spill_reason": no_spill,
            "acm_rs_version": __version__,
        }  # fmt: skip
        stored = dict(info or {}) | run
        stored |= {"seam_frames": [], "seam_difference": [], "burn_in": []}
        close_output(writer, model, stored)
        return dict(info or {}) | run
    except BaseException:
        writer.abort()
        raise
    finally:
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)
