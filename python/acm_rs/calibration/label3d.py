"""Import Label3D / DANNCE camera calibrations (MATLAB ``.mat``) as a :class:`CameraRig`.

Conventions (MATLAB's ``cameraParameters``, as Label3D and DANNCE store and use them):

- ``K`` is the *transpose* of the usual camera matrix, ``[[fx, 0, 0], [s, fy, 0], [cx, cy, 1]]``
  (MATLAB's ``IntrinsicMatrix``), with the skew ``s`` applied after distortion:
  ``u = fx x'' + s y'' + cx`` (DANNCE's ``ops.distortPoints`` reads ``K[1, 0]`` as the skew).
- ``r``, ``t`` use MATLAB's row vectors: ``x_cam = X_world r + t``, so the world-to-camera
  rotation of :class:`Camera` is ``r.T`` and the translation ``t``.
- ``RDistort`` is ``[k1 k2]`` or ``[k1 k2 k3]``, ``TDistort`` ``[p1 p2]``; the distortion model is
  OpenCV's (same formulas, same order of ``p1, p2``).
- Pixels are MATLAB's: the centre of the top-left pixel is ``(1, 1)``. Label3D's ``data_2d`` and
  DANNCE's own projection (``ops.project_to2d`` then ``ops.distortPoints``) use ``K`` as stored,
  i.e. 1-based pixels; DeepLabCut, SLEAP and OpenCV put that centre at ``(0, 0)``.
- Lengths are those of the calibration (DANNCE rigs: mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..camera import Camera, CameraRig
from ..rotation import rodrigues_inverse

_KEYS = ("K", "r", "t", "RDistort", "TDistort")


def read_label3d_calibration(
    path: str | Path | Sequence[str | Path],
    *,
    pixel_origin: int = 0,
    units: str = "mm",
    names: Sequence[str] | None = None,
) -> CameraRig:
    """Read a Label3D / DANNCE calibration.

    Parameters
    ----------
    path : path or sequence of paths
        A Label3D / DANNCE label file (``*_dannce.mat``, ``*_Label3D.mat``: variable
        ``params``, a cell of one struct per camera, and ``camnames``), or DANNCE per-camera
        files (``hires_cam1_params.mat``, ...: variables ``K, r, t, RDistort, TDistort``), one
        camera per file in the given order.
    pixel_origin : {0, 1}
        Pixel coordinates the cameras should produce. 0 (default): the centre of the top-left
        pixel is ``(0, 0)``, as in DeepLabCut, SLEAP, OpenCV and the rest of acm-rs; the
        principal point is MATLAB's minus 1. 1: MATLAB's pixels, ``K`` as stored, which is
        what Label3D's ``data_2d`` and DANNCE's own projection use.
    units : str
        Length unit of ``t`` (DANNCE calibrations are in mm).
    names : sequence of str, optional
        Camera names; default: the file's ``camnames``, else the file stems.

    Returns
    -------
    CameraRig
        One :class:`Camera` per camera, with the MATLAB skew; no image sizes (the files do not
        store them).

    Raises
    ------
    ValueError
        Not a MATLAB file of this kind (naming the variables found), a MATLAB v7.3 file, a ``K``
        that is not MATLAB's transposed matrix, an ``r`` that is not a rotation, or distortion
        arrays of the wrong length.
    """
    if pixel_origin not in (0, 1):
        raise ValueError(f"pixel_origin must be 0 or 1, got {pixel_origin!r}")
    paths = [Path(path)] if isinstance(path, (str, Path)) else [Path(p) for p in path]
    if not paths:
        raise ValueError("no calibration file given")
    tables: list[tuple[str, dict]] = []
    for p in paths:
        mat = _loadmat(p)
        if "params" in mat:
            if len(paths) > 1:
                raise ValueError(f"{p}: a Label3D file holds the whole rig; pass it alone")
            tables = _label3d_tables(p, mat)
        else:
            missing = [k for k in _KEYS[:3] if k not in mat]
            if missing:
                found = sorted(k for k in mat if not k.startswith("__"))
                raise ValueError(
                    f"{p}: neither a Label3D file (variable params) nor a DANNCE camera file "
                    f"(K, r, t, RDistort, TDistort); it lacks {missing} and has {found}"
                )
            tables.append((p.stem, {k: mat[k] for k in _KEYS if k in mat}))
    if names is not None:
        names = [str(n) for n in names]
        if len(names) != len(tables):
            raise ValueError(f"{len(names)} names given for {len(tables)} cameras")
    cams = [
        _camera(table, pixel_origin, names[i] if names is not None else name, paths[0])
        for i, (name, table) in enumerate(tables)
    ]
    return CameraRig(cams, units=units)


def _loadmat(path: Path) -> dict:
    from scipy.io import loadmat

    if not path.is_file():
        raise ValueError(f"calibration file not found: {path}")
    with open(path, "rb") as fh:
        head = fh.read(128)
    if head[:19] == b"MATLAB 7.3 MAT-file" or head[:8] == b"\x89HDF\r\n\x1a\n":
        raise ValueError(
            f"{path}: a MATLAB v7.3 (HDF5) file, which this reader does not take; in MATLAB, "
            "load it and save it again with save(..., '-v7')"
        )
    try:
        return loadmat(str(path))
    except Exception as exc:  # scipy raises several types for non-MATLAB files
        raise ValueError(f"{path}: not a MATLAB .mat file ({exc})") from None


def _label3d_tables(path: Path, mat: dict) -> list[tuple[str, dict]]:
    """``params`` (cell of structs) and ``camnames`` of a Label3D / DANNCE label file."""
    cells = np.asarray(mat["params"], dtype=object).ravel()
    names = []
    if "camnames" in mat:
        names = [str(np.asarray(n).ravel()[0]) for n in np.asarray(mat["camnames"]).ravel()]
    if names and len(names) != len(cells):
        raise ValueError(f"{path}: {len(names)} camnames for {len(cells)} cameras in params")
    out = []
    for i, cell in enumerate(cells):
        st = np.asarray(cell)
        fields = st.dtype.names or ()
        missing = [k for k in _KEYS[:3] if k not in fields]
        if missing:
            raise ValueError(f"{path}: params{{{i + 1}}} lacks {missing} (has {list(fields)})")
        table = {k: st[k].ravel()[0] for k in _KEYS if k in fields}
        out.append((names[i] if names else f"Camera{i + 1}", table))
    return out


def _camera(table: dict, origin: int, name: str, path: Path) -> Camera:
    where = f"{path}: camera {name!r}"
    k = np.asarray(table["K"], dtype=np.float64)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)):
        raise ValueError(f"{where}: K must be a finite 3 x 3 matrix, got shape {k.shape}")
    # MATLAB's IntrinsicMatrix: [fx 0 0; s fy 0; cx cy 1] (the transpose of OpenCV's)
    if np.any(np.abs(k[[0, 0, 1], [1, 2, 2]]) > 1e-9) or abs(k[2, 2] - 1.0) > 1e-9:
        raise ValueError(
            f"{where}: K = {k.tolist()} is not MATLAB's [fx 0 0; s fy 0; cx cy 1] (if it is "
            "already [fx s cx; 0 fy cy; 0 0 1], transpose it)"
        )
    r = np.asarray(table["r"], dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError(f"{where}: r is not a 3 x 3 rotation matrix: {r.tolist()}")
    t = np.asarray(table["t"], dtype=np.float64).ravel()
    if t.size != 3:
        raise ValueError(f"{where}: t must have 3 entries, got {t.size}")
    rd = np.asarray(table.get("RDistort", np.zeros(2)), dtype=np.float64).ravel()
    td = np.asarray(table.get("TDistort", np.zeros(2)), dtype=np.float64).ravel()
    if rd.size not in (2, 3) or td.size != 2:
        raise ValueError(
            f"{where}: RDistort must have 2 or 3 entries (k1 k2 [k3]) and TDistort 2 (p1 p2), "
            f"got {rd.size} and {td.size}"
        )
    k3 = rd[2] if rd.size == 3 else 0.0
    matrix = k.T.copy()  # [[fx, s, cx], [0, fy, cy], [0, 0, 1]]
    matrix[:2, 2] -= 1.0 - origin  # MATLAB's (1, 1) pixel centre -> (0, 0) for origin 0
    # x_cam = X r + t (row vectors) is x_cam = r^T X + t
    rvec = rodrigues_inverse(np.ascontiguousarray(r.T))
    return Camera(matrix, [rd[0], rd[1], td[0], td[1], k3], rvec, t, name=name)
