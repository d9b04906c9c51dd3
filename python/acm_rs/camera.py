"""Pinhole cameras with OpenCV distortion (ACM supplement section 2.1, eqs. 4-6).

``x_cam = R(rvec) x_world + tvec`` (eq. 4); distortion ``(k1, k2, p1, p2, k3)`` in OpenCV order
(the paper's eq. 5 is the case ``p1 = p2 = k3 = 0``); pixels ``u = fx x'' + s y'' + cx``,
``v = fy y'' + cy`` (eq. 6). The skew ``s`` is MATLAB's (``cameraParameters``, Bouguet's
``alpha_c fx``), applied after distortion; OpenCV has none (``s = 0``, which gives OpenCV's
projection bit for bit). Projection runs in Rust; points behind a camera give NaN pixels
(and ``False`` in :meth:`Camera.in_front`), never a silently mirrored projection.
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from . import _native, _toml
from ._arrays import as_float_array
from ._io import atomic_write
from .rotation import rodrigues

#: Order of the 16 camera parameters used by :attr:`Camera.params` and the Jacobians; the
#: first 15 are OpenCV's model (arrays of 15 columns are accepted as cameras without skew).
PARAM_NAMES: tuple[str, ...] = (
    "rx", "ry", "rz", "tx", "ty", "tz", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3",
    "skew",
)  # fmt: skip
N_PARAMS = len(PARAM_NAMES)


class Camera:
    """One calibrated camera.

    Parameters
    ----------
    matrix : array_like, shape (3, 3)
        Camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels; ``s`` is the skew
        (MATLAB's ``K(2, 1)``, applied after distortion), 0 in OpenCV's model.
    dist : array_like, shape (2,) or (5,)
        Distortion: the paper's ``(k1, k2)`` or OpenCV's ``(k1, k2, p1, p2, k3)``.
    rvec : array_like, shape (3,)
        Rodrigues vector of the world-to-camera rotation (radians).
    tvec : array_like, shape (3,)
        World-to-camera translation (world units).
    size : (int, int), optional
        Image ``(width, height)`` in pixels.
    name : str, optional
        Camera name (as in anipose ``calibration.toml``).
    """

    __slots__ = ("_params", "size", "name")

    def __init__(
        self,
        matrix: np.ndarray,
        dist: Sequence[float] | np.ndarray,
        rvec: Sequence[float] | np.ndarray,
        tvec: Sequence[float] | np.ndarray,
        size: tuple[int, int] | None = None,
        name: str | None = None,
    ) -> None:
        m = as_float_array(matrix, "matrix", (3, 3))
        if m.ndim != 2:
            raise ValueError(f"matrix must have shape (3, 3), got {m.shape}")
        if np.any(np.abs(m[1:, 0]) > 1e-9) or abs(m[2, 1]) > 1e-9:
            raise ValueError(
                f"matrix must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {m.tolist()} (a "
                "MATLAB/DANNCE K is the transpose: pass K.T)"
            )
        if abs(m[2, 2] - 1.0) > 1e-9:
            raise ValueError(f"matrix[2, 2] must be 1, got {m[2, 2]}")
        d = as_float_array(dist, "dist", (None,)).ravel()
        if d.size == 2:
            d = np.concatenate([d, np.zeros(3)])
        elif d.size == 4:
            d = np.concatenate([d, np.zeros(1)])
        elif d.size != 5:
            raise ValueError(
                f"dist must have 2 (k1, k2) or 5 (k1, k2, p1, p2, k3) entries, got {d.size}"
            )
        r = as_float_array(rvec, "rvec", (3,)).ravel()
        t = as_float_array(tvec, "tvec", (3,)).ravel()
        if r.size != 3 or t.size != 3:
            raise ValueError("rvec and tvec must have 3 entries each")
        params = np.concatenate([r, t, [m[0, 0], m[1, 1], m[0, 2], m[1, 2]], d, [m[0, 1]]])
        self._params = _checked_params(params[None, :])[0]
        self._params.setflags(write=False)
        if size is not None:
            if len(size) != 2 or min(int(size[0]), int(size[1])) <= 0:
                raise ValueError(f"size must be (width, height) > 0, got {size}")
            size = (int(size[0]), int(size[1]))
        self.size = size
        self.name = name

    @classmethod
    def from_params(
        cls,
        params: np.ndarray,
        size: tuple[int, int] | None = None,
        name: str | None = None,
    ) -> Camera:
        """Build a camera from its 16 parameters (order :data:`PARAM_NAMES`), or the first 15
        (skew 0)."""
        p = as_float_array(params, "params", (None,)).ravel()
        if p.size not in (15, N_PARAMS):
            raise ValueError(f"params must have 16 (or 15, without skew) entries, got {p.size}")
        s = p[15] if p.size == N_PARAMS else 0.0
        matrix = np.array([[p[6], s, p[8]], [0.0, p[7], p[9]], [0.0, 0.0, 1.0]])
        return cls(matrix, p[10:15], p[0:3], p[3:6], size=size, name=name)

    # -- parameters -------------------------------------------------------------------------
    @property
    def params(self) -> np.ndarray:
        """(16,) parameters ``[rvec, tvec, fx, fy, cx, cy, k1, k2, p1, p2, k3, skew]``
        (read-only)."""
        return self._params

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels."""
        p = self._params
        return np.array([[p[6], p[15], p[8]], [0.0, p[7], p[9]], [0.0, 0.0, 1.0]])

    @property
    def skew(self) -> float:
        """Skew ``s`` in pixels (``u = fx x'' + s y'' + cx``); 0 in OpenCV's model."""
        return float(self._params[15])

    @property
    def opencv_matrix(self) -> np.ndarray:
        """(3, 3) camera matrix without the skew, for OpenCV functions (which ignore
        ``matrix[0, 1]``); use it with :meth:`skew_free_pixels`."""
        m = self.matrix
        m[0, 1] = 0.0
        return m

    def skew_free_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels ``(..., 2)`` of this camera as the same camera without skew would see them,
        ``u - s (v - cy) / fy`` (exact: ``v`` has no skew term), so that OpenCV functions
        (``cv2.undistortPoints``, which ignore the skew) get them right with
        :attr:`opencv_matrix`. Unchanged (bit for bit) when the skew is 0."""
        px = np.array(pixels, dtype=np.float64)
        p = self._params
        px[..., 0] -= p[15] * ((px[..., 1] - p[9]) / p[7])
        return px

    @property
    def dist(self) -> np.ndarray:
        """(5,) OpenCV distortion ``(k1, k2, p1, p2, k3)``."""
        return self._params[10:15].copy()

    @property
    def rvec(self) -> np.ndarray:
        """(3,) Rodrigues vector of the world-to-camera rotation (radians)."""
        return self._params[0:3].copy()

    @property
    def tvec(self) -> np.ndarray:
        """(3,) world-to-camera translation (world units)."""
        return self._params[3:6].copy()

    @property
    def rotation_matrix(self) -> np.ndarray:
        """(3, 3) world-to-camera rotation."""
        return rodrigues(self._params[0:3])

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, ``-R^T t``."""
        return -self.rotation_matrix.T @ self._params[3:6]

    # -- projection -------------------------------------------------------------------------
    def project(self, points: np.ndarray) -> np.ndarray:
        """Project world points to pixels (eq. 4).

        Parameters
        ----------
        points : array_like, shape (..., 3)
            World coordinates (world units). NaN rows (missing points) stay NaN.

        Returns
        -------
        numpy.ndarray, shape (..., 2)
            Pixel coordinates ``(u, v)``; NaN for points at or behind the camera plane.
        """
        return _project(self._params[None, :], points)[0]

    def in_front(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask ``(...)``: whether each point lies in front of the camera."""
        pts = as_float_array(points, "points", (3,), finite=False)
        depth = (pts @ self.rotation_matrix.T + self._params[3:6])[..., 2]
        return depth > 1e-9

    def project_jacobian(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project points and return exact derivatives.

        Parameters
        ----------
        points : array_like, shape (..., 3)
            World coordinates; NaN rows are missing points.

        Returns
        -------
        pixels : numpy.ndarray, shape (..., 2)
        d_point : numpy.ndarray, shape (..., 2, 3)
            ``d(u, v) / d(x, y, z)``.
        d_params : numpy.ndarray, shape (..., 2, 16)
            ``d(u, v) / d params`` in the order of :data:`PARAM_NAMES`.
            All three are NaN for missing points and points behind the camera.
        """
        pts = as_float_array(points, "points", (3,), finite=False)
        lead = pts.shape[:-1]
        px, dp, dc = _native.project_jacobian(self._params[None, :], pts.reshape(-1, 3))
        return (
            px[0].reshape(lead + (2,)),
            dp[0].reshape(lead + (2, 3)),
            dc[0].reshape(lead + (2, N_PARAMS)),
        )

    def to_dict(self) -> dict:
        """Anipose ``calibration.toml`` table of this camera.

        A nonzero skew is written as the key ``skew`` (px), an acm-rs extension that aniposelib
        ignores (it reads the keys it knows; OpenCV's projection has no skew), with the
        ``matrix`` skew-free; there is no ``skew`` key when the skew is 0.
        """
        matrix = self.matrix
        matrix[0, 1] = 0.0
        out: dict = {
            "name": self.name if self.name is not None else "",
            "matrix": matrix.tolist(),
            "distortions": self.dist.tolist(),
            "rotation": self.rvec.tolist(),
            "translation": self.tvec.tolist(),
        }
        if self.size is not None:
            out["size"] = list(self.size)
        if self.skew != 0.0:
            out["skew"] = self.skew
        return out

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        """Inverse of :meth:`to_dict` (anipose keys)."""
        missing = {"matrix", "distortions", "rotation", "translation"} - set(d)
        if missing:
            raise ValueError(f"camera table lacks keys {sorted(missing)}")
        if d.get("fisheye"):
            # aniposelib's FisheyeCamera: 4 coefficients of OpenCV's fisheye model, not the
            # pinhole k1, k2, p1, p2 this reader would take them for
            raise ValueError(
                "fisheye = true: an anipose fisheye camera (cv2.fisheye model), which acm-rs "
                "does not support; calibrate without fisheye = true"
            )
        size = tuple(d["size"]) if "size" in d else None
        if size is not None:
            _check_size(size, d["matrix"])
        return cls(
            _matrix_with_skew(d), d["distortions"], d["rotation"], d["translation"], size,
            d.get("name"),
        )  # fmt: skip

    def __repr__(self) -> str:
        p = self._params
        return (
            f"Camera(name={self.name!r}, f=({p[6]:.1f}, {p[7]:.1f}), "
            f"c=({p[8]:.1f}, {p[9]:.1f}), center={np.round(self.center, 3).tolist()})"
        )


class CameraRig:
    """An ordered set of cameras sharing one world frame.

    Parameters
    ----------
    cameras : iterable of Camera
        At least one camera; names (when given) must be unique.
    units : str
        Length unit of the world frame and translations ("mm", "cm", "m"; "" = not
        declared). Recorded in ``calibration.toml`` (``[metadata] units``) and checked
        against the skeleton's units by learning and tracking.
    metadata : dict, optional
        The other keys of the file's ``[metadata]`` table (anipose writes ``adjusted`` and
        ``error``), kept so that :meth:`save` writes them back; None: the file had no table.
    """

    def __init__(
        self, cameras: Iterable[Camera], units: str = "", metadata: dict | None = None
    ) -> None:
        cams = list(cameras)
        if not cams:
            raise ValueError("a camera rig needs at least one camera")
        for c in cams:
            if not isinstance(c, Camera):
                raise ValueError(f"CameraRig takes Camera objects, got {type(c).__name__}")
        names = [c.name for c in cams if c.name is not None]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        self.cameras: list[Camera] = cams
        self.units = str(units or "")
        self.metadata: dict | None = None if metadata is None else dict(metadata)

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, key: int | str) -> Camera:
        if isinstance(key, str):
            for c in self.cameras:
                if c.name == key:
                    return c
            raise KeyError(f"no camera named {key!r}; cameras: {self.names}")
        return self.cameras[key]

    @property
    def names(self) -> list[str | None]:
        """Camera names in rig order."""
        return [c.name for c in self.cameras]

    def get_params(self) -> np.ndarray:
        """(n_cams, 16) parameters, rows in rig order (see :data:`PARAM_NAMES`)."""
        return np.stack([c.params for c in self.cameras])

    def set_params(self, params: np.ndarray) -> CameraRig:
        """Return a new rig with the given (n_cams, 16) parameters, or (n_cams, 15) without
        skew (sizes and names kept)."""
        p = as_float_array(params, "params", (len(self), None))
        return CameraRig(
            (
                Camera.from_params(row, c.size, c.name)
                for row, c in zip(p, self.cameras, strict=True)
            ),
            self.units,
        )

    def scaled(self, factor: float, units: str | None = None) -> CameraRig:
        """The same rig in another length unit: translations times ``factor`` (e.g. 0.1 for
        a calibration in mm used with a model in cm, 6.5 for board squares of 6.5 cm), with
        ``units`` the new unit (default: undeclared unless ``factor`` is 1)."""
        f = float(factor)
        if not (np.isfinite(f) and f > 0):
            raise ValueError(f"scale factor must be finite and > 0, got {factor}")
        p = self.get_params().copy()
        p[:, 3:6] *= f  # [r (3), t (3), fx, fy, cx, cy, k1, k2, p1, p2, k3, skew]
        out = self.set_params(p)
        out.units = units if units is not None else (self.units if f == 1.0 else "")
        out.metadata = None if self.metadata is None else dict(self.metadata)  # same calibration
        return out

    def project(self, points: np.ndarray) -> np.ndarray:
        """Project world points into every camera.

        Parameters
        ----------
        points : array_like, shape (..., 3)
            World coordinates; NaN rows stay NaN.

        Returns
        -------
        numpy.ndarray, shape (n_cams, ..., 2)
            Pixels; NaN where a point is missing or behind a camera.
        """
        return _project(self.get_params(), points)

    def save(self, path: str | Path, metadata: dict | None = None) -> None:
        """Write an anipose-compatible ``calibration.toml`` (atomically).

        Tables ``[cam_0]``, ``[cam_1]``, ... in rig order with ``name``, ``size``, ``matrix``,
        ``distortions`` (OpenCV order), ``rotation`` (Rodrigues, world to camera) and
        ``translation``, plus ``skew`` (px) for a camera with nonzero skew (an acm-rs extension
        that aniposelib ignores, see :meth:`Camera.to_dict`); ``[metadata]``: the rig's
        :attr:`metadata` (as read), ``units``, then ``metadata`` (which wins on shared keys).
        An empty ``[metadata]`` table read is written back empty.
        """
        doc: dict = {}
        for i, cam in enumerate(self.cameras):
            table = cam.to_dict()
            if not table["name"]:
                table["name"] = f"cam_{i}"
            doc[f"cam_{i}"] = table
        meta = dict(self.metadata or {})
        if self.units:
            meta["units"] = self.units
        meta.update(metadata or {})
        if meta or self.metadata is not None:
            doc["metadata"] = meta
        with atomic_write(path) as fh:
            fh.write(_toml.dumps(doc))

    @classmethod
    def load(cls, path: str | Path, names: Sequence[str] | None = None) -> CameraRig:
        """Read an anipose ``calibration.toml``.

        Parameters
        ----------
        path : path
        names : sequence of str, optional
            Camera names in the wanted order (cameras are matched by name, not table order);
            default: the ``cam_<i>`` tables in numeric order.

        Raises
        ------
        ValueError
            Invalid TOML, no camera tables, a missing key, or a requested name that is absent.
        """
        p = Path(path)
        if not p.is_file():
            raise ValueError(f"calibration file not found: {p}")
        try:
            doc = tomllib.loads(p.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{p}: invalid TOML: {exc}") from None
        except UnicodeDecodeError as exc:
            raise ValueError(
                f"{p}: not a text file (byte {exc.start} is not UTF-8); expected an anipose "
                "calibration.toml"
            ) from None
        tables = {
            k: v for k, v in doc.items() if isinstance(v, dict) and re.fullmatch(r"cam_\d+", k)
        }
        if not tables:
            raise ValueError(f"{p}: no [cam_<i>] tables (not an anipose calibration file)")
        cams = []
        for k in sorted(tables, key=lambda k: int(k[4:])):
            try:
                cams.append(Camera.from_dict(tables[k]))
            except (ValueError, TypeError) as exc:
                raise ValueError(f"{p}: [{k}]: {exc}") from None
        if names is not None:
            by_name = {c.name: c for c in cams}
            missing = [n for n in names if n not in by_name]
            if missing:
                raise ValueError(f"{p}: no camera named {missing}; cameras: {list(by_name)}")
            cams = [by_name[n] for n in names]
        meta = doc.get("metadata")
        if meta is not None and not isinstance(meta, dict):
            raise ValueError(f"{p}: metadata must be a table [metadata]")
        units = (meta or {}).get("units", "")
        kept = None if meta is None else {k: v for k, v in meta.items() if k != "units"}
        return cls(cams, units=str(units), metadata=kept)

    def __repr__(self) -> str:
        return f"CameraRig({len(self)} cameras: {self.names})"


def _check_size(size: tuple, matrix) -> None:
    """Refuse an image ``size`` (width, height) px that does not hold the principal point,
    naming a swapped (height, width) pair."""
    try:
        w, h = (float(v) for v in size)
        cx, cy = float(np.asarray(matrix, float)[0, 2]), float(np.asarray(matrix, float)[1, 2])
    except (TypeError, ValueError, IndexError):
        raise ValueError(f"size must be [width, height] in pixels, got {list(size)}") from None
    if not (w > 0 and h > 0):
        raise ValueError(f"size must be [width, height] > 0 px, got {list(size)}")
    if 0 <= cx <= w and 0 <= cy <= h:
        # inside, but far off-centre where the swapped size would centre it: swapped
        off = max(abs(cx - w / 2) / w, abs(cy - h / 2) / h)
        off_swapped = max(abs(cx - h / 2) / h, abs(cy - w / 2) / w)
        if off > 0.08 and off_swapped < off / 3:
            raise ValueError(
                f"size {list(size)} looks swapped: the principal point ({cx:g}, {cy:g}) is the "
                f"centre of a {h:g} x {w:g} image; anipose stores size = [width, height]"
            )
        return
    if 0 <= cx <= h and 0 <= cy <= w:
        raise ValueError(
            f"size {list(size)} looks swapped: the principal point ({cx:g}, {cy:g}) lies in a "
            f"{h:g} x {w:g} image; anipose stores size = [width, height]"
        )
    raise ValueError(
        f"the principal point ({cx:g}, {cy:g}) lies outside the {w:g} x {h:g} image (size = "
        "[width, height]); the matrix or the size is wrong"
    )


def _matrix_with_skew(d: dict) -> np.ndarray:
    """The camera matrix of an anipose table with the acm-rs ``skew`` key applied.

    A nonzero ``matrix[0][1]`` is refused: aniposelib projects with OpenCV, which ignores it,
    so the file would mean one camera to aniposelib and another to acm-rs.
    """
    m = np.array(d["matrix"], dtype=np.float64)
    if m.shape != (3, 3):
        raise ValueError(f"matrix must have shape (3, 3), got {m.shape}")
    if abs(m[0, 1]) > 1e-9:
        raise ValueError(
            f"matrix[0][1] = {m[0, 1]:g}: a skewed camera matrix, whose skew aniposelib "
            "(OpenCV) ignores; write matrix[0][1] = 0 and the skew as the key skew = "
            f"{m[0, 1]:g} (px), which acm-rs applies"
        )
    skew = d.get("skew", 0.0)
    if isinstance(skew, bool) or not isinstance(skew, (int, float)):
        raise ValueError(f"skew must be a number (px), got {skew!r}")
    m[0, 1] = float(skew)
    return m


def _checked_params(params: np.ndarray) -> np.ndarray:
    """Validate ``(n, 16)`` camera parameters in Rust (finite, focal lengths > 0); a copy.
    ``(n, 15)`` (without skew) gets a zero skew column."""
    params = np.array(params, dtype=np.float64, order="C")
    if params.ndim == 2 and params.shape[1] == 15:
        params = np.ascontiguousarray(np.pad(params, ((0, 0), (0, 1))))
    _native.project(params, np.zeros((0, 3)))
    return params


def _project(params: np.ndarray, points: np.ndarray) -> np.ndarray:
    pts = as_float_array(points, "points", (3,), finite=False)
    if np.isinf(pts).any():
        raise ValueError("points contain infinity (use NaN for missing points)")
    lead = pts.shape[:-1]
    px, _ = _native.project(params, pts.reshape(-1, 3))
    return px.reshape((params.shape[0],) + lead + (2,))
