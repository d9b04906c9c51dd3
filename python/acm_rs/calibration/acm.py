"""Import (and export) of the ACM / calibcam ``multicalibration.npy`` and ``origin_coord.npy``.

Both files are pickled Python dicts: loading them runs the pickle machinery, so only load
files you trust. Anything that is not a dict with the expected keys is refused.

* ``multicalibration.npy``: ``A_fit`` ((n, 4) as ``[fx, cx, fy, cy]`` or (n, 3, 3)),
  ``k_fit`` (n, 5) OpenCV ``(k1, k2, p1, p2, k3)``, ``rX1_fit`` (n, 3) Rodrigues, ``tX1_fit``
  (n, 3) in calibration units; ``x_cam = R x_world + t``.
* ``origin_coord.npy``: ``origin`` (3,), ``coord`` (3, 3) with
  ``x_calibration = coord @ x_arena + origin``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._io import atomic_write
from ..camera import Camera, CameraRig
from .world import transform_rig


def _load_dict(path: str | Path, keys: tuple[str, ...]) -> dict:
    """A trusted ACM pickle holding one dict with ``keys`` (see :mod:`acm_rs.acm_formats`)."""
    from ..acm_formats import _load_dict as load

    return load(Path(path), "ACM calibration", {k: "required" for k in keys})


def load_acm_calibration(
    path: str | Path,
    origin_coord: str | Path | None = None,
    *,
    names: list[str] | None = None,
    image_size: tuple[int, int] | None = (1280, 1024),
    scale_factor: float = 1.0,
) -> CameraRig:
    """Read an ACM ``multicalibration.npy`` as a :class:`~acm_rs.CameraRig`.

    Parameters
    ----------
    path : path
        ``multicalibration.npy``.
    origin_coord : path, optional
        ``origin_coord.npy``: the rig is returned in the arena frame it defines.
    names : list of str, optional
        Camera names (default ``cam_0 ...``).
    image_size : (int, int) or None
        Image ``(width, height)`` (ACM's files do not store it; default 1280×1024).
    scale_factor : float
        Arena length unit per calibration unit (ACM ``configuration.py``'s
        ``scale_factor``, e.g. 6.5 cm per board square); translations are multiplied by it.

    Raises
    ------
    ValueError
        Not a dict with ``A_fit``, ``k_fit``, ``rX1_fit``, ``tX1_fit``; inconsistent sizes;
        non-finite values.
    """
    d = _load_dict(path, ("A_fit", "k_fit", "rX1_fit", "tX1_fit"))
    a = np.asarray(d["A_fit"], float)
    k = np.asarray(d["k_fit"], float)
    r = np.asarray(d["rX1_fit"], float)
    t = np.asarray(d["tX1_fit"], float)
    n = r.shape[0] if r.ndim == 2 else -1
    if a.shape == (n, 4):
        mats = np.zeros((n, 3, 3))
        mats[:, 0, 0], mats[:, 0, 2], mats[:, 1, 1], mats[:, 1, 2] = a.T
        mats[:, 2, 2] = 1.0
    elif a.shape == (n, 3, 3):
        mats = a
    else:
        raise ValueError(f"{path}: A_fit has shape {a.shape}, expected ({n}, 4) or ({n}, 3, 3)")
    if r.shape != (n, 3) or t.shape != (n, 3) or k.ndim != 2 or k.shape[0] != n:
        raise ValueError(
            f"{path}: inconsistent shapes rX1_fit {r.shape}, tX1_fit {t.shape}, k_fit {k.shape}"
        )
    if not scale_factor > 0:
        raise ValueError(f"scale_factor must be > 0, got {scale_factor}")
    names = names or [f"cam_{i}" for i in range(n)]
    if len(names) != n:
        raise ValueError(f"{len(names)} names for {n} cameras")
    dist = np.zeros((n, 5))
    dist[:, : min(5, k.shape[1])] = k[:, :5]
    rig = CameraRig(Camera(mats[i], dist[i], r[i], t[i], image_size, names[i]) for i in range(n))
    if origin_coord is not None:
        oc = _load_dict(origin_coord, ("origin", "coord"))
        origin = np.asarray(oc["origin"], float).reshape(3)
        coord = np.asarray(oc["coord"], float).reshape(3, 3)
        rig = transform_rig(rig, coord, origin)
    if scale_factor != 1.0:
        rig = CameraRig(
            Camera(c.matrix, c.dist, c.rvec, c.tvec * scale_factor, c.size, c.name) for c in rig
        )
    rig.units = "cm"  # the authors' arena frame: calibration units x scale_factor = cm
    return rig


def save_acm_calibration(rig: CameraRig, path: str | Path) -> Path:
    """Write a rig as an ACM ``multicalibration.npy`` (pickled dict, atomically)."""
    p = rig.get_params()
    if np.any(p[:, 15] != 0):
        skewed = [c.name for c in rig if c.skew != 0]
        raise ValueError(
            f"cameras {skewed} have a skew, which ACM's multicalibration.npy (A_fit = fx, cx, "
            "fy, cy) cannot hold; save the rig as calibration.toml instead (CameraRig.save)"
        )
    d = {
        "nCameras": len(rig),
        "A_fit": np.stack([p[:, 6], p[:, 8], p[:, 7], p[:, 9]], axis=1),
        "k_fit": p[:, 10:15].copy(),
        "rX1_fit": p[:, 0:3].copy(),
        "RX1_fit": np.stack([c.rotation_matrix for c in rig]),
        "tX1_fit": p[:, 3:6].copy(),
    }
    with atomic_write(path, "wb") as fh:
        np.save(fh, np.array(d, dtype=object), allow_pickle=True)
    return Path(path)
