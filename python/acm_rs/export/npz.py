"""NumPy ``.npz`` export: every array of a result plus the model and calibration as text."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .. import _toml
from .._io import atomic_write
from ._common import frame_numbers, posterior_variance

if TYPE_CHECKING:  # pragma: no cover
    from ..tracking.result import PoseResult

__all__ = ["read_npz", "to_npz"]

NPZ_FORMAT = "acm-rs-pose"
NPZ_VERSION = 1


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
    ``joint_names``, ``marker_names``, ``camera_names``, ``camera_params`` (n_cams, 15,
    :data:`acm_rs.PARAM_NAMES` order), ``em_delta``, ``em_seconds``; text: ``units``,
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
    ``str``; ``info_json`` is also parsed into ``info``.
    """
    with np.load(path, allow_pickle=False) as z:
        if "format" not in z.files or str(z["format"]) != NPZ_FORMAT:
            raise ValueError(f"{path}: not an acm-rs pose file (written by acm_rs.export.to_npz)")
        out = {k: z[k] for k in z.files}
    for k in ("format", "units", "skeleton_toml", "calibration_toml", "info_json"):
        out[k] = str(out[k])
    out["version"] = int(out["version"])
    out["info"] = json.loads(out["info_json"])
    params = {k[7:]: out[k] for k in out if k.startswith("param__")}
    if params:
        out["info"]["params"] = params
    for k in [k for k in out if k.startswith("info__")]:
        out["info"][k[6:]] = out[k]
    return out
