"""Normalisation (ACM supp. section 3.3) and the map between tracker state and pose (Alg. 10).

The tracker's state holds only the *free* pose entries: the translation, and every rotation
entry whose joint-angle limits are not ``[b, b]``. Entries are normalised (``t = c_t z``,
``r = c_r z``) and, with ``joint_limits=True``, bounded entries go through the erf map of
Alg. 10: ``r = b0 + (b1 - b0) / 2 * (1 + erf(sqrt(pi) / 2 * z))``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from . import _native
from ._arrays import as_float_array
from .rotation import wrap_rotation_vectors

if TYPE_CHECKING:  # pragma: no cover
    from .camera import CameraRig
    from .skeleton import Skeleton


#: Length units the models and calibrations may declare, in centimetres.
UNIT_IN_CM = {"mm": 0.1, "cm": 1.0, "m": 100.0}

#: Largest ``|z|`` of a bounded (erf-mapped) state entry at the filter's start
#: (:meth:`StateMap.start_state`): the middle 47 % of the limits' range.
START_Z = 0.5


@dataclass(frozen=True)
class Normalization:
    """Normalisation constants of sec. 3.3 (defaults: the paper's values).

    Attributes
    ----------
    translation : float
        ``c_t`` in world units (50 for centimetres; use 500 for millimetres).
    rotation : float
        ``c_r`` in radians (pi / 2).
    pixel : (float, float)
        ``(c_1, c_2)`` in pixels, normally half the sensor size (640, 512).
    """

    translation: float = 50.0
    rotation: float = math.pi / 2
    pixel: tuple[float, float] = (640.0, 512.0)

    def __post_init__(self) -> None:
        for name, v in (
            ("translation", self.translation),
            ("rotation", self.rotation),
            ("pixel[0]", self.pixel[0]),
            ("pixel[1]", self.pixel[1]),
        ):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"normalisation constant {name} must be finite and > 0, got {v}")

    @classmethod
    def for_units(
        cls, units: str, image_sizes: Sequence[tuple[float, float]] = ()
    ) -> Normalization:
        """The paper's constants in a model's length unit: ``c_t`` = 50 cm in ``units``;
        ``c_1, c_2`` half the largest image size (640, 512 when none is given).

        Raises
        ------
        ValueError
            An unknown unit (known: mm, cm, m; "" is taken as cm).
        """
        if units not in UNIT_IN_CM and units != "":
            raise ValueError(
                f"unknown length unit {units!r}; use one of {sorted(UNIT_IN_CM)} (or convert "
                "the model and calibration to one of them)"
            )
        translation = 50.0 / UNIT_IN_CM.get(units, 1.0)
        sizes = [tuple(s) for s in image_sizes if s is not None]
        if sizes:
            w = max(s[0] for s in sizes)
            h = max(s[1] for s in sizes)
            return cls(translation=translation, pixel=(w / 2.0, h / 2.0))
        return cls(translation=translation)

    @classmethod
    def for_rig(
        cls,
        centres: np.ndarray,
        units: str = "",
        image_sizes: Sequence[tuple[float, float]] = (),
    ) -> Normalization:
        """Unit-free constants: ``c_t`` = 5/6 of the median distance of the camera centres
        from their centroid (50 for the demo rig in cm, whose cameras stand 60 cm from its
        centre: the paper's value for an arena of that size), so scaling the rig and the model
        by any factor scales ``c_t`` with them and leaves every result unchanged (in their
        units). With fewer than two distinct camera centres: :meth:`for_units`.

        Parameters
        ----------
        centres : array_like, shape (n_cams, 3)
            Camera centres in world units.
        units : str
            The model's length unit (only for the fallback).
        image_sizes : sequence of (width, height)
            Pixel scales ``c_1, c_2`` are half the largest.
        """
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        d = np.linalg.norm(c - c.mean(axis=0), axis=1) if len(c) else np.zeros(0)
        if len(c) < 2 or not np.all(np.isfinite(d)) or float(np.median(d)) <= 0:
            return cls.for_units(units, image_sizes)
        pixel = cls.for_units("", image_sizes).pixel  # any unit: c_t does not use it here
        return cls(translation=float(np.median(d)) * 5.0 / 6.0, pixel=pixel)

    @classmethod
    def from_image_size(
        cls, width: float, height: float, translation: float = 50.0
    ) -> Normalization:
        """Pixel scales from a sensor size ``(width, height)`` in px (``c = size / 2``)."""
        return cls(translation=translation, pixel=(width / 2.0, height / 2.0))

    def normalize_pixels(self, px: np.ndarray) -> np.ndarray:
        """Eq. 11: ``(..., 2)`` pixels -> ``(u / c_1 - 1, v / c_2 - 1)``."""
        return np.asarray(px, dtype=np.float64) / np.asarray(self.pixel) - 1.0

    def denormalize_pixels(self, pn: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`normalize_pixels`."""
        return (np.asarray(pn, dtype=np.float64) + 1.0) * np.asarray(self.pixel)

    def _tuple(self) -> tuple[float, float, float, float]:
        return (
            float(self.translation),
            float(self.rotation),
            float(self.pixel[0]),
            float(self.pixel[1]),
        )


class StateMap:
    """Map between the tracker state ``z`` and the full pose ``(t, r)`` of a skeleton.

    Parameters
    ----------
    skeleton : Skeleton
        The skeleton whose joint limits define free, fixed and bounded entries.
    normalization : Normalization, optional
        Scales of sec. 3.3 (default: the paper's).
    joint_limits : bool
        Enforce limits with the erf map of Alg. 10 (otherwise bounded entries are linear;
        fixed entries stay fixed either way).
    stretch : bool
        Append one entry per elastic bone of the skeleton (``skeleton.elastic_bones``): its
        log-stretch ``s``, the bone's length in that state being ``l_b exp(s)`` (elastic
        segments, :mod:`acm_rs.elastic`). Default: rigid bones, pose entries only.
    """

    def __init__(
        self,
        skeleton: Skeleton,
        normalization: Normalization | None = None,
        joint_limits: bool = True,
        stretch: bool = False,
    ) -> None:
        self.skeleton = skeleton
        self.joint_limits = bool(joint_limits)
        self.normalization = normalization or Normalization()
        lim = skeleton.joint_limits
        self.stretch_bones = (
            np.asarray(skeleton.elastic_bones, np.int64) if stretch else np.zeros(0, np.int64)
        )
        self._native = _native.NativeStateMap(
            np.ascontiguousarray(lim[..., 0]),
            np.ascontiguousarray(lim[..., 1]),
            self.normalization._tuple(),
            bool(joint_limits),
            self.stretch_bones if stretch else None,
        )

    @property
    def n_state(self) -> int:
        """Dimension of the state (50 for the authors' rat model)."""
        return int(self._native.n_state)

    @property
    def n_pose_state(self) -> int:
        """Number of pose entries (the first ones; the log-stretch entries follow)."""
        return self.n_state - len(self.stretch_bones)

    @property
    def free_indices(self) -> np.ndarray:
        """(n_pose_state,) indices of the free entries in the flat pose ``[t, r.ravel()]``."""
        return self._native.free_indices

    def lengths(self, z: np.ndarray) -> np.ndarray:
        """State ``(..., n_state)`` -> bone lengths ``(..., n_bones)`` (world units): the
        skeleton's, with each elastic bone times ``exp(s)`` of its entry."""
        zz = as_float_array(z, "z", (self.n_state,))
        out = np.broadcast_to(self.skeleton.bone_lengths, zz.shape[:-1] + (self.skeleton.n_bones,))
        out = np.array(out)
        if len(self.stretch_bones):
            out[..., self.stretch_bones] *= np.exp(zz[..., self.n_pose_state :])
        return out

    def forward(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics of states ``(..., n_state)`` with each state's bone lengths:
        ``(joints (..., J, 3), markers (..., M, 3))`` in world units (in parallel in Rust)."""
        zz = as_float_array(z, "z", (self.n_state,))
        lead = zz.shape[:-1]
        j, m = self._native.forward(
            self.skeleton._native, np.ascontiguousarray(zz.reshape(-1, self.n_state))
        )
        return j.reshape(lead + j.shape[1:]), m.reshape(lead + m.shape[1:])

    def to_pose(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """State ``(..., n_state)`` -> ``(t (..., 3), r (..., n_bones, 3))`` (Alg. 4 + Alg. 10)."""
        zz = as_float_array(z, "z", (self.n_state,))
        lead = zz.shape[:-1]
        pose, _ = self._native.to_pose(zz.reshape(-1, self.n_state))
        pose = pose.reshape(lead + (-1,))
        return pose[..., :3], pose[..., 3:].reshape(lead + (self.skeleton.n_bones, 3))

    def to_pose_derivative(self, z: np.ndarray) -> np.ndarray:
        """``(..., n_state)`` diagonal derivative ``d pose[free[i]] / d z[i]``."""
        zz = as_float_array(z, "z", (self.n_state,))
        _, d = self._native.to_pose(zz.reshape(-1, self.n_state))
        return d.reshape(zz.shape)

    def from_pose(self, t: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Inverse map: ``t (..., 3)``, ``r (..., n_bones, 3)`` -> ``z (..., n_state)``.

        Fixed entries are ignored; bounded entries at or beyond a limit are moved just inside;
        log-stretch entries are 0 (the mean lengths).
        """
        tt = as_float_array(t, "t", (3,))
        rr = as_float_array(r, "r", (self.skeleton.n_bones, 3))
        if tt.shape[:-1] != rr.shape[:-2]:
            raise ValueError(f"t {tt.shape} and r {rr.shape} have different leading shapes")
        lead = tt.shape[:-1]
        pose = np.concatenate([tt.reshape(-1, 3), rr.reshape(-1, 3 * self.skeleton.n_bones)], 1)
        return self._native.to_state(np.ascontiguousarray(pose)).reshape(lead + (self.n_state,))

    @property
    def bounded(self) -> np.ndarray:
        """(n_pose_state,) bool: entries mapped through the erf of Alg. 10 (joint limits)."""
        free = np.asarray(self.free_indices)
        if not self.joint_limits:
            return np.zeros(free.size, bool)
        lim = self.skeleton.joint_limits.reshape(-1, 2)  # (n_bones * 3, 2)
        rot = free - 3
        lo = np.where(rot >= 0, lim[np.maximum(rot, 0), 0], -np.inf)
        hi = np.where(rot >= 0, lim[np.maximum(rot, 0), 1], np.inf)
        return np.isfinite(lo) & np.isfinite(hi) & (lo < hi)

    def start_state(self, t: np.ndarray, r: np.ndarray) -> np.ndarray:
        """:meth:`from_pose` for the filter's starting point, with bounded entries moved to
        ``|z| <= START_Z`` (beyond the paper).

        A single-frame fit (sec. 4.7) can end at or near a joint limit (a local minimum of
        the box-constrained fit, typically along the tail chain). Out there the erf map of
        Alg. 10 is flat (slope ``exp(-π z²/4)``: 4 % of the slope at 0 for ``|z| = 2``, 1e-6
        at the limit), so the measurements cannot pull the filter back: on the synthetic rat
        with fixed Θ a tail bone stayed at its limit for 20,000 frames (tail tip 18 mm off,
        29 px), and a start clamped to ``|z| <= 2`` still took 500 frames to recover (4.7 mm
        in the first 250). Starting such entries in the middle of their range, where the map
        is steep, the filter (broad start prior) finds them within a few frames: 0.8 mm from
        the first frame on, with ``|z| <= 0.5`` and below (``benches/bench_long.py``). Entries
        already there, and unbounded ones (``t``, the global rotation), are unchanged.

        The rotation of a bone without limits (its components unbounded or fixed at 0) with
        ``|r| > 1.5 π`` starts at its shortest Rodrigues vector, ``|r| <= π``
        (:func:`acm_rs.rotation.wrap_rotation_vectors`): an unbounded fit can return the same
        rotation at ``|r|`` of many π, near whose multiples of 2π the map is singular and the
        filter cannot move the bone."""
        lim = self.skeleton.joint_limits  # (n_bones, 3, 2)
        free_or_zero = (np.isinf(lim[..., 0]) & np.isinf(lim[..., 1])) | (
            (lim[..., 0] == 0) & (lim[..., 1] == 0)
        )
        unlimited = free_or_zero.all(axis=-1)  # (n_bones,)
        r = np.array(r, dtype=np.float64)
        r[..., unlimited, :] = wrap_rotation_vectors(r[..., unlimited, :])
        z = self.from_pose(t, r)
        b = np.zeros(self.n_state, bool)
        b[: self.n_pose_state] = self.bounded
        z[..., b] = np.clip(z[..., b], -START_Z, START_Z)
        return z

    def emission(self, rig: CameraRig, z: np.ndarray) -> np.ndarray:
        """Alg. 4: states ``(n, n_state)`` -> normalised pixels ``(n, n_cams, M, 2)`` (eq. 11).

        NaN where a marker is behind a camera.
        """
        zz = as_float_array(z, "z", (self.n_state,))
        flat = zz.reshape(-1, self.n_state)
        g = self._native.emission(self.skeleton._native, rig.get_params(), flat)
        return g.reshape(zz.shape[:-1] + g.shape[1:])
