"""Windows of a long recording and the file they are written to (issue 16; shared by the
chunked smoother of :mod:`acm_rs.tracking.long` and the streaming smoother of
:mod:`acm_rs.tracking.streaming`).

- :class:`_Model`: everything needed to filter and smooth one window with fixed Θ
  (picklable, for Dask workers); :func:`smooth_window` does it for one window.
- :class:`_Source`: the raw inputs, read one window at a time (memmap / h5py / zarr).
- :class:`_H5Writer` / :func:`read_chunked`: the HDF5 poses file, written window by window
  into a temporary file renamed at the end.
- :func:`frame_px`: each frame's median reprojection error of given states.
"""

from __future__ import annotations

import json
import mmap
import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .. import _native
from .._io import new_file_mode
from ..camera import CameraRig
from ..skeleton import Skeleton
from ..state import Normalization, StateMap
from .track import _first_pose, _skeleton_order

#: Windows with this many consecutive frames without detections get the random walk's
#: linearisation hint under the velocity model.
HINT_GAP = 5


@dataclass
class _Model:
    """Everything a worker needs to smooth one window (picklable for Dask)."""

    rig: CameraRig
    skeleton: Skeleton
    norm: Normalization
    joint_limits: bool
    relinearize: int
    gate: float | None  # the chi-square threshold, not the probability
    order: int
    params: dict
    prior_cov: np.ndarray  # V0 of every window's start (order·n square)
    pcutoff: float
    marker_names: Sequence[str] | None = None
    #: Θ and window prior of the random walk, for the linearisation hint of the velocity
    #: model in windows with a stretch without detections (None for the random walk).
    rw_params: dict | None = None
    rw_prior_cov: np.ndarray | None = None

    #: Threads of each window's tracker (1: windows run in parallel instead).
    threads: int = 1
    #: A ``NativeBufferPool`` the trackers take their covariances from and give them back
    #: to (the streaming smoother's; None: allocated and freed, and the model picklable).
    buffers: object | None = field(default=None, repr=False, compare=False)

    def tracker(self, x: np.ndarray, order: int | None = None):
        lim = self.skeleton.joint_limits
        return _native.NativeTracker(
            self.skeleton._native, self.rig.get_params(), np.ascontiguousarray(lim[..., 0]),
            np.ascontiguousarray(lim[..., 1]), self.norm._tuple(), bool(self.joint_limits),
            np.ascontiguousarray(x), relinearize=int(self.relinearize), order=order or self.order,
            threads=int(self.threads), buffers=self.buffers,
        )  # fmt: skip

    def detections(self, det: np.ndarray, lik: np.ndarray | None) -> np.ndarray:
        """Raw window ``(C, W, K, 2)`` → skeleton order, below-cutoff and partial points NaN."""
        return _skeleton_order(self.rig, self.skeleton, det, lik, self.pcutoff,
                               self.marker_names, warn=False)  # fmt: skip


def _normalized(norm: Normalization, det: np.ndarray) -> np.ndarray:
    return norm.normalize_pixels(det).transpose(1, 0, 2, 3)  # (W, C, M, 2)


def _window_prior(model: _Model, det: np.ndarray) -> np.ndarray | None:
    """Prior mean of a window's start: the sec. 4.7 fit of its first frame with >= 3 points
    seen by >= 2 cameras (velocity 0); None if no frame qualifies."""
    try:
        _, t0, r0 = _first_pose(model.rig, model.skeleton, det, model.norm)
    except ValueError:
        return None
    sm = StateMap(model.skeleton, model.norm, model.joint_limits)
    mu = sm.start_state(t0, r0)
    return np.concatenate([mu, np.zeros(mu.size * (model.order - 1))])


def _has_empty_stretch(det: np.ndarray, min_len: int) -> bool:
    """Whether ``det (C, W, M, 2)`` has ``min_len`` consecutive frames without detections."""
    empty = ~np.isfinite(det[..., 0]).any(axis=(0, 2))
    run = 0
    for e in empty:
        run = run + 1 if e else 0
        if run >= min_len:
            return True
    return False


def set_hint(model: _Model, native, det: np.ndarray, x: np.ndarray, mu0: np.ndarray) -> bool:
    """Under the velocity model, a window with ``HINT_GAP`` frames without detections gets
    the random walk's posterior (smoothed over the window from ``mu0``) as linearisation
    hint: after such a stretch the velocity's prior is too broad (as in :func:`acm_rs.track`).
    Deterministic in its inputs. Whether a hint was set."""
    if model.order != 2 or model.rw_params is None or not _has_empty_stretch(det, HINT_GAP):
        return False
    rw, q = model.tracker(x, order=1), model.rw_params
    n = len(q["mu0"])
    rw.e_step(mu0[:n], model.rw_prior_cov, q["Vz"], q["Vx_diag"], model.gate,
              statistics=False)  # fmt: skip
    native.set_linearization_hint(rw.means(), rw.covs())
    return True


def smooth_window(
    model: _Model,
    det_raw: np.ndarray,
    lik_raw: np.ndarray | None,
    prior: tuple[np.ndarray, np.ndarray] | None = None,
) -> dict | None:
    """Filter and smooth one window with the fixed parameters (Alg. 7 + 9) from its own
    prior (the single-frame fit of its first frame with enough detections) or from
    ``prior = (mean (ns,), cov (ns, ns))`` of the state before its first frame, in the
    normalised state coordinates (e.g. a checkpoint of the filter); the posterior of every
    frame of the window (arrays with the window's frames on the first axis; ``status`` is
    ``(C, W, M)``), or None if no frame of the window has enough detections to start
    from."""
    det = model.detections(det_raw, lik_raw)
    if prior is None:
        mu0, cov0 = _window_prior(model, det), model.prior_cov
        if mu0 is None:
            return None
    else:
        mu0, cov0 = prior
    x = _normalized(model.norm, det)
    native = model.tracker(x)
    set_hint(model, native, det, x, mu0)
    p = model.params
    stats = native.e_step(mu0, cov0, p["Vz"], p["Vx_diag"], model.gate,
                          statistics=False)  # fmt: skip
    poses, joints, markers, joints_std, markers_std = native.posterior()
    status = native.mask()[..., 0].transpose(1, 0, 2)  # (C, W, M)
    return {
        "joints": joints, "joints_std": joints_std, "markers": markers,
        "markers_std": markers_std, "poses": poses, "status": status,
        "stats": {k: float(v) for k, v in stats.items()},
    }  # fmt: skip


#: Percentile of a frame's reprojection errors that :func:`frame_px` reports: high enough to
#: see a part of the body that is off (the rat's tail: 24 of 172 points), above the ~1 % of
#: confident outliers.
FRAME_PERCENTILE = 90.0


def frame_px(
    model: _Model, sm: StateMap, z: np.ndarray, det: np.ndarray, q: float = FRAME_PERCENTILE
) -> np.ndarray:
    """Per frame, the ``q``-th percentile of the distances (px) between the markers of the
    states ``z (W, n)`` projected and the detections ``det (C, W, M, 2)``; NaN with fewer
    than 3 detections."""
    t, r = sm.to_pose(z)
    err = np.linalg.norm(model.skeleton.project(model.rig, t, r) - det, axis=-1)  # (C, W, M)
    err = err.transpose(1, 0, 2).reshape(len(z), -1)
    ok = np.isfinite(err)
    out = np.full(len(z), np.nan)
    enough = ok.sum(axis=1) >= 3
    if enough.any():
        out[enough] = nanpercentile_rows(np.where(ok, err, np.nan)[enough], q)
    return out


def nanpercentile_rows(a: np.ndarray, q: float) -> np.ndarray:
    """``np.nanpercentile(a, q, axis=1)`` (its default linear method, the same numbers) of a
    2-D array whose rows each hold a finite value, without NumPy's loop over rows (which
    took 54 µs a frame in the streaming smoother's forward pass, 8 % of it)."""
    s = np.sort(a, axis=1)  # NaN last
    k = np.isfinite(a).sum(axis=1)
    virtual = (k - 1) * (q / 100.0)
    prev = np.floor(virtual)
    gamma = virtual - prev
    rows = np.arange(len(a))
    lo = np.clip(prev.astype(np.intp), 0, k - 1)
    x0, x1 = s[rows, lo], s[rows, np.minimum(lo + 1, k - 1)]
    d = x1 - x0
    # NumPy's _lerp: from the nearer end
    return np.where(gamma >= 0.5, x1 - d * (1 - gamma), x0 + d * gamma)


class _Source:
    """Windows of the raw inputs, read on demand (memmap / h5py / zarr friendly)."""

    def __init__(self, detections, likelihood) -> None:
        self.det, self.lik = detections, likelihood
        shape = tuple(detections.shape)
        if len(shape) != 4 or shape[-1] != 2:
            raise ValueError(f"detections must have shape (n_cams, T, n_markers, 2), got {shape}")
        if likelihood is not None and tuple(likelihood.shape) != shape[:3]:
            raise ValueError(
                f"likelihood must have shape {shape[:3]} (n_cams, T, n_markers), got "
                f"{tuple(likelihood.shape)}"
            )
        self.n_frames = shape[1]

    def window(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray | None]:
        det = np.asarray(self.det[:, a:b], dtype=np.float64)
        lik = None if self.lik is None else np.asarray(self.lik[:, a:b], dtype=np.float64)
        for arr in (self.det, self.lik):
            _release_pages(arr)
        return det, lik


def _release_pages(arr) -> None:
    """Drops the pages of a memory-mapped input from this process's resident memory once a
    window has been copied out (``madvise(MADV_DONTNEED)``; they stay in the page cache and
    are read back from there when needed): otherwise every page read so far counts towards
    the process's RSS, 1.5 GB for an hour's detections and likelihoods of the rat."""
    mm = getattr(arr, "_mmap", None)  # numpy.memmap, also np.load(..., mmap_mode="r")
    if mm is not None and hasattr(mm, "madvise") and hasattr(mmap, "MADV_DONTNEED"):
        try:
            mm.madvise(mmap.MADV_DONTNEED)
        except (OSError, ValueError):  # closed or not supported: only memory is at stake
            pass


def close_output(writer: _H5Writer, model: _Model, stored: dict) -> None:
    """Stores the run's info and Θ (with the window prior, and the random walk's Θ where the
    velocity model used it as linearisation hint) in the output and renames it into place."""
    params = model.params | {"window_prior_cov": model.prior_cov}
    if model.rw_params is not None:
        params |= {f"rw_{k}": v for k, v in model.rw_params.items()}
        params["rw_window_prior_cov"] = model.rw_prior_cov
    writer.close(stored, params)


class _H5Writer:
    """The output file, written core by core into a temporary file next to ``path`` and
    renamed onto it by :meth:`close` (never a partial file under ``path``)."""

    def __init__(self, path: Path, n_frames: int, skeleton: Skeleton, n_cams: int, chunk: int):
        import h5py

        self.path = path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        self.tmp = Path(tmp)
        self.f = h5py.File(self.tmp, "w")
        j, m, nb = skeleton.n_joints, skeleton.n_markers, skeleton.n_bones
        c = max(1, min(chunk, n_frames))
        shapes = {
            "joints": (n_frames, j, 3), "joints_std": (n_frames, j, 3),
            "markers": (n_frames, m, 3), "markers_std": (n_frames, m, 3),
            "t": (n_frames, 3), "r": (n_frames, nb, 3),
        }  # fmt: skip
        for name, shape in shapes.items():
            self.f.create_dataset(name, shape, dtype="f8", chunks=(c, *shape[1:]),
                                  fillvalue=np.nan)  # fmt: skip
        self.f.create_dataset("status", (n_cams, n_frames, m), dtype="u1",
                              chunks=(n_cams, c, m))  # fmt: skip
        self.f["joint_names"] = np.array(skeleton.joint_names, dtype="S")
        self.f["marker_names"] = np.array(skeleton.marker_names, dtype="S")
        self.nb = nb

    def write(self, a: int, b: int, res: dict | None, w0: int) -> None:
        if res is None:  # no detections to start from: NaN poses, status "missing"
            return
        s = slice(a - w0, b - w0)
        for name in ("joints", "joints_std", "markers", "markers_std"):
            self.f[name][a:b] = res[name][s]
        self.f["t"][a:b] = res["poses"][s, :3]
        self.f["r"][a:b] = res["poses"][s, 3:].reshape(b - a, self.nb, 3)
        self.f["status"][:, a:b] = res["status"][:, s]

    def close(self, info: dict, params: dict) -> Path:
        g = self.f.create_group("params")
        for k, v in params.items():
            g[k] = np.asarray(v)
        for k in ("seam_frames", "seam_difference", "burn_in"):
            self.f[k] = np.asarray(info.pop(k))
        self.f.attrs["info"] = json.dumps(info, default=_jsonable)
        self.f.attrs["format"] = "acm-rs chunked poses 1"
        self.f.close()
        os.chmod(self.tmp, new_file_mode())
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        try:
            self.f.close()
        finally:
            self.tmp.unlink(missing_ok=True)


def _jsonable(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def read_chunked(path: str | os.PathLike, frames: slice | None = None) -> dict:
    """Arrays of a :func:`track_long` file (``frames``: a slice of frames, default all) and
    its ``info`` dict."""
    import h5py

    s = frames if frames is not None else slice(None)
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != "acm-rs chunked poses 1":
            raise ValueError(f"{path} is not a chunked poses file of acm-rs")
        out = {k: f[k][s] for k in ("joints", "joints_std", "markers", "markers_std", "t", "r")}
        out["status"] = f["status"][:, s]
        out["params"] = {k: f["params"][k][()] for k in f["params"]}
        for k in ("seam_frames", "seam_difference", "burn_in"):
            out[k] = f[k][()]
        out["info"] = json.loads(f.attrs["info"])
        out["joint_names"] = [n.decode() for n in f["joint_names"][()]]
        out["marker_names"] = [n.decode() for n in f["marker_names"][()]]
    return out
