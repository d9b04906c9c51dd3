"""NPZ files of a :class:`~acm_rs.tracking.result.PoseResult`, owned by the result.

:meth:`PoseResult.save` / :meth:`PoseResult.load` and :func:`acm_rs.export.to_npz` /
:func:`acm_rs.export.read_npz` all use this module, so the result never imports the exporters
(they import the result). Also here: the quantities the file stores that other exporters
share, :func:`frame_numbers` and :func:`posterior_variance` (re-exported by
``acm_rs.export._common``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import _toml
from .._io import atomic_write

if TYPE_CHECKING:  # pragma: no cover
    from .result import PoseResult

__all__ = ["POINTS", "check_points", "frame_numbers", "posterior_variance", "read_npz", "to_npz"]

NPZ_FORMAT = "acm-rs-pose"
NPZ_VERSION = 1

POINTS = ("joints", "markers")


def check_points(points: str) -> str:
    """Validate the ``points`` argument of the exporters (``"joints"`` or ``"markers"``)."""
    if points not in POINTS:
        raise ValueError(f"points must be 'joints' or 'markers', got {points!r}")
    return points


def frame_numbers(result: PoseResult, frames: np.ndarray | None) -> np.ndarray:
    """(T,) frame numbers: ``frames`` if given, else ``result.info["frames"]``, else 0..T-1."""
    if frames is None:
        frames = result.info.get("frames")
    if frames is None:
        return np.arange(result.n_frames, dtype=np.int64)
    out = np.asarray(frames)
    if out.shape != (result.n_frames,):
        raise ValueError(
            f"frames must have shape ({result.n_frames},) (one number per tracked frame), "
            f"got {out.shape}"
        )
    if not np.issubdtype(out.dtype, np.integer):
        if not np.all(np.isfinite(out)) or np.any(out != np.round(out)):
            raise ValueError("frames must be whole frame numbers")
        out = out.astype(np.int64)
    return out


def posterior_variance(result: PoseResult, points: str, chunk: int = 256) -> np.ndarray:
    """(T, P, 3) posterior variance of each coordinate (skeleton units squared).

    Joints: ``result.joints_std ** 2``. Markers: ``result.info["markers_std"] ** 2`` when the
    tracker stored it, otherwise the unscented transform of the state posterior
    through forward kinematics (the ``2 n`` symmetric sigma points ``mean +- sqrt(n) L e_i``,
    equal weights), as the tracker does for the joints. NaN everywhere when the result has no
    posterior covariance (``method="deterministic"``).
    """
    check_points(points)
    n_t = result.n_frames
    n_p = result.skeleton.n_joints if points == "joints" else result.skeleton.n_markers
    if result.state_cov is None:
        return np.full((n_t, n_p, 3), np.nan)
    if points == "joints":
        return np.asarray(result.joints_std, float) ** 2
    stored = result.info.get("markers_std")  # computed in Rust by the tracker
    if isinstance(stored, np.ndarray) and stored.shape == (n_t, n_p, 3):
        return stored**2
    mean = np.asarray(result.state_mean, float)
    cov = np.asarray(result.state_cov, float)
    n = mean.shape[1]
    out = np.empty((n_t, n_p, 3))
    eye = 1e-12 * np.eye(n)
    for s in range(0, n_t, chunk):
        e = min(s + chunk, n_t)
        c = 0.5 * (cov[s:e] + cov[s:e].transpose(0, 2, 1)) + eye
        chol = np.linalg.cholesky(c) * np.sqrt(n)  # (t, n, n), columns = sigma directions
        dirs = chol.transpose(0, 2, 1)  # (t, n, n): row i = sqrt(n) L e_i
        sig = np.concatenate([mean[s:e, None] + dirs, mean[s:e, None] - dirs], axis=1)
        _, mk = result.state_map.forward(sig.reshape(-1, n))
        mk = mk.reshape(e - s, 2 * n, n_p, 3)
        out[s:e] = mk.var(axis=1)
    return out


def _calibration_toml(rig) -> str:
    doc = {}
    for i, cam in enumerate(rig):
        table = cam.to_dict()
        table["name"] = table["name"] or f"cam_{i}"
        doc[f"cam_{i}"] = table
    return _toml.dumps(doc)


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist() if obj.size <= 64 else f"<array {obj.shape}>"
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, str | int | float | bool) or obj is None:
        return obj
    return repr(obj)


def to_npz(
    result: PoseResult,
    path: str | Path,
    *,
    frames: np.ndarray | None = None,
    compressed: bool = True,
    marker_variance: bool = True,
) -> Path:
    """Write a result as one ``.npz`` (atomically); read it with :func:`read_npz` or np.load.

    Arrays (lengths in ``units``): ``joints`` (T, J, 3), ``joints_std`` (T, J, 3),
    ``markers`` (T, M, 3), ``markers_var`` (T, M, 3) (posterior variance, if
    ``marker_variance``), ``t`` (T, 3), ``r`` (T, n_bones, 3) rad, ``state_mean`` (T, n),
    ``state_cov`` (T, n, n) if present, ``detections`` (n_cams, T, M, 2) px, ``frames`` (T,),
    ``joint_names``, ``marker_names``, ``camera_names``, ``camera_params`` (n_cams, 16,
    :data:`acm_rs.PARAM_NAMES` order), ``em_delta``, ``em_seconds``, ``em_log_likelihood``,
    ``em_step`` (over-relaxation factor, 1: plain EM), ``em_rejected``; text: ``units``,
    ``skeleton_toml`` (load with ``Skeleton.from_dict(tomllib.loads(...))``),
    ``calibration_toml`` (anipose), ``info_json``; ``format`` and ``version``; the arrays of
    ``info`` as ``param__<name>`` (learned ``mu0``, ``V0``, ``Vz``, ``Vx_diag``) and
    ``info__<key>`` (e.g. ``info__status`` (n_cams, T, M) measurement status).
    No pickles: ``np.load(path)`` works without ``allow_pickle``.

    Returns
    -------
    Path
    """
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise ValueError(f"NPZ path must end in .npz, got {path.name!r}")
    sk = result.skeleton
    # Arrays of ``info`` (learned parameters, measurement status) are stored as arrays:
    # ``param__<name>`` and ``info__<key>``; read_npz puts them back into ``info``.
    info = dict(result.info)
    info_arrays = {
        f"param__{k}": np.asarray(v) for k, v in (info.pop("params", None) or {}).items()
    }
    for k, v in list(info.items()):
        if isinstance(v, np.ndarray):
            info_arrays[f"info__{k}"] = info.pop(k)
    arrays = {
        "format": np.array(NPZ_FORMAT),
        "version": np.array(NPZ_VERSION),
        "units": np.array(sk.units),
        "joints": np.asarray(result.joints, float),
        "joints_std": np.asarray(result.joints_std, float),
        "markers": np.asarray(result.markers, float),
        "t": np.asarray(result.t, float),
        "r": np.asarray(result.r, float),
        "state_mean": np.asarray(result.state_mean, float),
        "detections": np.asarray(result.detections, float),
        "frames": frame_numbers(result, frames),
        "joint_names": np.array(sk.joint_names, dtype=str),
        "marker_names": np.array(sk.marker_names, dtype=str),
        "camera_names": np.array(
            [n or f"cam_{i}" for i, n in enumerate(result.rig.names)], dtype=str
        ),
        "camera_params": result.rig.get_params(),
        "em_delta": np.array([h.get("delta", np.nan) for h in result.em_history], float),
        "em_seconds": np.array([h.get("seconds", np.nan) for h in result.em_history], float),
        "em_log_likelihood": np.array(
            [h.get("log_likelihood", np.nan) for h in result.em_history], float
        ),
        "em_step": np.array([h.get("step", 1.0) for h in result.em_history], float),
        "em_rejected": np.array([bool(h.get("rejected")) for h in result.em_history], bool),
        "skeleton_toml": np.array(_toml.dumps(sk.to_dict())),
        "calibration_toml": np.array(_calibration_toml(result.rig)),
        "info_json": np.array(json.dumps(_jsonable(info))),
        **info_arrays,
    }
    if result.state_cov is not None:
        arrays["state_cov"] = np.asarray(result.state_cov, float)
    if marker_variance:
        arrays["markers_var"] = posterior_variance(result, "markers")
    with atomic_write(path, "wb") as fh:
        (np.savez_compressed if compressed else np.savez)(fh, **arrays)
    return path


def read_npz(path: str | Path) -> dict:
    """Read a file written by :func:`to_npz` into a dict of arrays and strings.

    Text entries (``units``, ``skeleton_toml``, ``calibration_toml``, ``info_json``) become
    ``str``; ``info_json`` is also parsed into ``info``. A damaged or truncated file (zip
    directory, CRC, compressed data) or another kind of NPZ is refused with ``ValueError``
    naming the file.
    """
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"pose file not found: {p}")
    with open(p, "rb") as fh:
        magic = fh.read(4)
    if magic != b"PK\x03\x04":
        raise ValueError(
            f"{p}: not a pose file: expected the .npz that acm-rs track writes (a zip archive)"
            + (f", got a {p.suffix} file" if p.suffix and p.suffix != ".npz" else "")
        )
    try:
        with np.load(p, allow_pickle=False) as z:
            if "format" not in z.files or str(z["format"]) != NPZ_FORMAT:
                raise ValueError(
                    f"{p}: not an acm-rs pose file (written by acm-rs track or "
                    "acm_rs.export.to_npz)"
                )
            out = {k: z[k] for k in z.files}
    except ValueError as exc:
        if str(p) in str(exc):
            raise
        raise ValueError(
            f"{p}: not a readable pose file ({exc}); an object array or another format? "
            "Re-run acm-rs track to make it again"
        ) from None
    except Exception as exc:  # zip, CRC, zlib, a damaged .npy header (SyntaxError), ...
        raise ValueError(
            f"{p}: damaged or incomplete pose file ({type(exc).__name__}: {exc}); it was "
            "probably cut while copying or writing; re-run acm-rs track to make it again"
        ) from None
    required = ("format", "units", "skeleton_toml", "calibration_toml", "info_json", "version")
    lost = [k for k in required + ("joints",) if k not in out]
    if lost:
        raise ValueError(
            f"{p}: damaged pose file: entries {lost} are missing (a damaged zip directory?); "
            "re-run acm-rs track to make it again"
        )
    for k in required[:-1]:
        out[k] = str(out[k])
    try:
        out["version"] = int(out["version"])
        out["info"] = json.loads(out["info_json"])
    except (ValueError, TypeError) as exc:
        raise ValueError(f"{p}: damaged pose file ({exc}); re-run acm-rs track") from None
    params = {k[7:]: out[k] for k in out if k.startswith("param__")}
    if params:
        out["info"]["params"] = params
    for k in [k for k in out if k.startswith("info__")]:
        out["info"][k[6:]] = out[k]
    return out
