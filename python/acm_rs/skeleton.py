"""Skeleton model (ACM supplement section 3): tree, rest geometry, markers, constraints, and
forward kinematics (Alg. 1) computed in Rust.

Conventions (see ``docs/skeleton_format.md``):

* Bone ``b`` ends at the ``b``-th non-root joint (joint order) and starts at its parent, so a
  bone is named by its end joint. Each bone has a rest frame whose z-axis points along it, built
  from the rest pose and the ``up`` direction (y-axis as close to ``up`` as possible, x = y x z).
* ``r`` holds one Rodrigues vector per bone. The rotation of bone ``i`` moves bone ``i`` and its
  descendants, never its siblings (how the authors' published output moves; ``docs/models.md``,
  "Kinematics"); the bones that start at the root (:attr:`Skeleton.root_bones`, one for the rat)
  turn the whole body. An explicit link matrix (e.g. from an ACM ``model.npy``) replaces this
  rule (:meth:`Skeleton.with_links`). Joint-angle limits (Supp. Table 1) bound the components
  of ``r`` per bone; the paper's table names the start joint (the "left shoulder" limit is the
  humerus, the bone ``shoulder_left -> elbow_left``, named ``elbow_left`` here).
* A marker attached to joint ``j`` moves rigidly with the bone ending at ``j``; its offset is in
  that bone's frame. Markers attached to the root use the frame of the root's first bone.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from . import _native, _toml
from ._arrays import as_float_array, as_index_array
from ._io import atomic_write
from .rotation import rodrigues, rodrigues_inverse
from .state import Normalization, StateMap

if TYPE_CHECKING:  # pragma: no cover
    from .camera import CameraRig

FORMAT_NAME = "acm-rs-skeleton"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class BoneLengthConstraint:
    """Anatomical bone-length prior (Supp. Table 2).

    Either proportional to body weight (rat: ``length = slope * weight +- slope_sd * weight``,
    cm per g) or absolute (mouse: ``length = mean +- sd``).
    """

    bone: str
    slope: float | None = None
    slope_sd: float | None = None
    mean: float | None = None
    sd: float | None = None

    def __post_init__(self) -> None:
        by_weight = self.slope is not None and self.slope_sd is not None
        absolute = self.mean is not None and self.sd is not None
        if by_weight == absolute:
            raise ValueError(
                f"bone-length constraint of {self.bone!r} needs either slope and slope_sd "
                "or mean and sd"
            )

    def bounds(self, body_weight: float | None, sigma_factor: float = 10.0) -> tuple[float, float]:
        """``(lower, upper)`` length bound; ``(-inf, inf)`` if it needs an unknown body weight."""
        if self.mean is not None and self.sd is not None:
            mean, sd = self.mean, self.sd
        elif body_weight is None:
            return (-math.inf, math.inf)
        else:
            if not body_weight > 0:
                raise ValueError(f"body_weight must be > 0 g, got {body_weight}")
            mean, sd = self.slope * body_weight, self.slope_sd * body_weight  # type: ignore[operator]
        return (max(mean - sigma_factor * sd, 0.0), mean + sigma_factor * sd)


class FKJacobian(NamedTuple):
    """Forward kinematics of one pose with exact derivatives (all in world units / rad)."""

    joints: np.ndarray  #: (J, 3)
    markers: np.ndarray  #: (M, 3)
    d_joints_d_pose: np.ndarray  #: (J, 3, 3 + 3 n_bones), w.r.t. ``[t, r.ravel()]``
    d_markers_d_pose: np.ndarray  #: (M, 3, 3 + 3 n_bones)
    d_joints_d_lengths: np.ndarray  #: (J, 3, n_bones)
    d_markers_d_lengths: np.ndarray  #: (M, 3, n_bones)
    d_markers_d_offsets: np.ndarray  #: (M, 3, 3): ``d m_k / d v_k`` (zero across markers)


def _names(x: Sequence[str], what: str) -> tuple[str, ...]:
    names = tuple(str(n) for n in x)
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ValueError(f"{what} names must be unique; repeated: {dup}")
    return names


def _lookup(names: Sequence[str], name: str, what: str) -> int:
    try:
        return list(names).index(name)
    except ValueError:
        raise ValueError(f"unknown {what} {name!r}; known {what}s: {list(names)}") from None


class Skeleton:
    """A skeleton with markers, built with :meth:`from_rest_pose` or :meth:`load`.

    Attributes
    ----------
    name : str
        Model name.
    units : str
        Length unit of positions, lengths and offsets (e.g. ``"cm"``).
    """

    def __init__(
        self,
        *,
        joint_names: Sequence[str],
        parents: np.ndarray,
        marker_names: Sequence[str],
        marker_joints: np.ndarray,
        native: _native.NativeSkeleton,
        rest_root: np.ndarray,
        up: np.ndarray,
        joint_limits: np.ndarray,
        symmetry: Mapping[str, Sequence[tuple[str, str]]],
        marker_bounds: np.ndarray,
        bone_length_constraints: Sequence[BoneLengthConstraint] = (),
        name: str = "skeleton",
        units: str = "",
        explicit_frames: bool = False,
        stretch_sd: np.ndarray | None = None,
    ) -> None:
        self._joint_names = _names(joint_names, "joint")
        self._marker_names = _names(marker_names, "marker")
        self._parents = np.asarray(parents, dtype=np.int64)
        self._marker_joints = np.asarray(marker_joints, dtype=np.int64)
        self._native = native
        self._rest_root = np.asarray(rest_root, dtype=np.float64)
        self._up = np.asarray(up, dtype=np.float64)
        self._joint_limits = np.asarray(joint_limits, dtype=np.float64)
        self._marker_bounds = np.asarray(marker_bounds, dtype=np.float64)
        self._symmetry = {k: [tuple(p) for p in v] for k, v in symmetry.items()}
        self._constraints = tuple(bone_length_constraints)
        self.name = name
        self.units = units
        # rest frames given explicitly (not derivable from `up`): saved with the skeleton
        self._explicit_frames = bool(explicit_frames)
        n_bones = int(native.n_bones)
        sd = np.zeros(n_bones) if stretch_sd is None else np.asarray(stretch_sd, np.float64)
        if sd.shape != (n_bones,) or not np.all(np.isfinite(sd)) or np.any(sd < 0):
            raise ValueError(
                f"stretch_sd must be {n_bones} finite values >= 0 (one per bone), got {sd}"
            )
        self._stretch_sd = sd.copy()
        self._stretch_sd.setflags(write=False)
        for c in self._constraints:
            self.bone_index(c.bone)
        for arr in (self._parents, self._marker_joints, self._joint_limits, self._marker_bounds):
            arr.setflags(write=False)

    def __getstate__(self) -> dict:
        """Pickle support (e.g. to send a skeleton to Dask workers): the Python attributes
        and the native skeleton's arrays, bit for bit."""
        state = {k: v for k, v in self.__dict__.items() if k != "_native"}
        state["_native_args"] = (
            self._native.rest_frames, self._native.lengths, self._native.offsets,
            self.custom_links,
        )  # fmt: skip
        return state

    def __setstate__(self, state: dict) -> None:
        rest_frames, lengths, offsets, links = state.pop("_native_args")
        self.__dict__.update(state)
        self._native = _with_links(
            _native.NativeSkeleton(
                self._parents, np.ascontiguousarray(rest_frames), np.ascontiguousarray(lengths),
                self._marker_joints, np.ascontiguousarray(offsets),
            ),
            links,
        )  # fmt: skip

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def from_rest_pose(
        cls,
        joint_names: Sequence[str],
        parents: Sequence[int] | np.ndarray,
        rest_joints: np.ndarray,
        marker_names: Sequence[str],
        marker_joints: Sequence[int | str] | np.ndarray,
        marker_rest: np.ndarray,
        *,
        joint_limits: Mapping[str, np.ndarray] | np.ndarray | None = None,
        symmetry: Mapping[str, Sequence[tuple[str, str]]] | None = None,
        marker_bounds: Mapping[str, np.ndarray] | np.ndarray | None = None,
        bone_length_constraints: Sequence[BoneLengthConstraint] = (),
        up: Sequence[float] = (0.0, 1.0, 0.0),
        name: str = "skeleton",
        units: str = "",
        rest_frames: np.ndarray | None = None,
        bone_links: np.ndarray | None = None,
        link_order: Sequence[int] | np.ndarray | None = None,
        stretch_sd: Mapping[str, float] | np.ndarray | None = None,
    ) -> Skeleton:
        """Build a skeleton from joint and marker positions in a rest pose (all ``r = 0``).

        Parameters
        ----------
        joint_names : sequence of str, length J
        parents : array_like of int, shape (J,)
            Parent joint index, ``-1`` for the single root. Must form a tree.
        rest_joints : array_like, shape (J, 3)
            Joint positions of the rest pose (world units).
        marker_names : sequence of str, length M
        marker_joints : array_like, shape (M,)
            Joint (index or name) each marker is attached to; the marker moves rigidly with
            the bone that ends at that joint.
        marker_rest : array_like, shape (M, 3)
            Marker positions of the rest pose (world units).
        joint_limits : mapping or array, optional
            Rotation limits in radians: a mapping from a bone's end-joint name to a (3, 2)
            array of ``[lower, upper]`` per Rodrigues component, or an (n_bones, 3, 2) array.
            Unlisted bones are unbounded; ``lower == upper`` fixes the component.
        symmetry : mapping, optional
            ``{"joints": [(left, right), ...], "markers": [(left, right), ...]}`` by name.
        marker_bounds : mapping or array, optional
            Box constraints of the marker offsets in the bone frame (sec. 6): mapping from a
            marker name to a (3, 2) array, or an (M, 3, 2) array. Default unbounded.
        bone_length_constraints : sequence of BoneLengthConstraint
            Anatomical length priors (Supp. Table 2), by bone (end-joint) name.
        up : (3,) sequence
            Rest-pose direction used to orient bone frames (y-axis); ACM's body frame is
            x = the animal's right, y = dorsal, z = caudal, so the default is ``(0, 1, 0)``.
        name, units : str
            Model name and length unit.
        rest_frames : array_like, shape (n_bones, 3, 3), optional
            Rest orientation of every bone (columns = its x, y, z axes in the world; z along
            the bone) instead of the construction from ``up`` -- e.g. the authors' girdle
            frames read from an ACM ``model.npy``. Saved with the skeleton.
        bone_links : array_like of bool, shape (n_bones, n_bones), optional
            Which bones each rotation moves (``[i, j]``: bone i's rotation moves bone j), as
            an ACM ``model.npy``'s ``skeleton_vertices_links``. Default: the tree rule, a
            bone's rotation moves the bone and its descendants, never its siblings (how the
            animal moves; ``docs/models.md``). Saved with the skeleton.
        link_order : array_like of int, shape (n_bones,), optional
            With ``bone_links``: the order in which the rotations apply (default: bone index).

        Raises
        ------
        ValueError
            Wrong shapes, NaN, a parent list that is not a tree, zero-length bones, unknown
            names, limits with ``lower > upper``, or a link order that is not a permutation.
        """
        jn = _names(joint_names, "joint")
        mn = _names(marker_names, "marker")
        par = as_index_array(parents, "parents")
        if par.size != len(jn):
            raise ValueError(f"parents has {par.size} entries for {len(jn)} joint names")
        rj = as_float_array(rest_joints, "rest_joints", (len(jn), 3))
        if rj.ndim != 2:
            raise ValueError(f"rest_joints must have shape ({len(jn)}, 3), got {rj.shape}")
        mj_raw = list(marker_joints)
        mj = np.array(
            [_lookup(jn, j, "joint") if isinstance(j, str) else int(j) for j in mj_raw],
            dtype=np.int64,
        )
        if mj.size != len(mn):
            raise ValueError(f"marker_joints has {mj.size} entries for {len(mn)} marker names")
        mr = as_float_array(marker_rest, "marker_rest", (len(mn), 3)).reshape(len(mn), 3)
        upv = as_float_array(up, "up", (3,)).ravel()
        if np.linalg.norm(upv) == 0:
            raise ValueError("up must be a non-zero vector")
        frames = None
        if rest_frames is not None:
            nb = len(jn) - 1
            frames = as_float_array(rest_frames, "rest_frames", (nb, 3, 3)).reshape(nb, 3, 3)
        native = _native.NativeSkeleton.from_rest_pose(par, rj, mj, mr, upv, frames)
        if bone_links is not None:
            native = _with_links(native, (bone_links, link_order))
        elif link_order is not None:
            raise ValueError("link_order needs bone_links (the tree rule has its own order)")
        n_bones = int(native.n_bones)
        bones = native.bones
        bone_names = [jn[e] for e in bones[:, 1]]
        limits = _limits_array(joint_limits, bone_names, n_bones)
        bounds = _marker_bounds_array(marker_bounds, mn)
        sym = _check_symmetry(symmetry or {}, jn, mn)
        root = int(np.flatnonzero(par == -1)[0])
        return cls(
            joint_names=jn,
            parents=par,
            marker_names=mn,
            marker_joints=mj,
            native=native,
            rest_root=rj[root],
            up=upv,
            joint_limits=limits,
            symmetry=sym,
            marker_bounds=bounds,
            bone_length_constraints=bone_length_constraints,
            name=name,
            units=units,
            explicit_frames=frames is not None,
            stretch_sd=_stretch_array(stretch_sd, bone_names),
        )

    def with_parameters(
        self,
        bone_lengths: np.ndarray | None = None,
        marker_offsets: np.ndarray | None = None,
    ) -> Skeleton:
        """A copy with new bone lengths ``(n_bones,)`` and/or marker offsets ``(M, 3)``.

        Rest frames, limits and constraints are kept (e.g. to hold a learned skeleton).
        """
        lengths = self.bone_lengths if bone_lengths is None else bone_lengths
        offsets = self.marker_offsets if marker_offsets is None else marker_offsets
        lengths = as_float_array(lengths, "bone_lengths", (self.n_bones,))
        offsets = as_float_array(offsets, "marker_offsets", (self.n_markers, 3))
        native = _native.NativeSkeleton(
            self._parents,
            self._native.rest_frames,
            np.ascontiguousarray(lengths.reshape(self.n_bones)),
            self._marker_joints,
            np.ascontiguousarray(offsets.reshape(self.n_markers, 3)),
        )
        return self._copy_with(_with_links(native, self.custom_links))

    def scaled(self, factor: float, units: str = "") -> Skeleton:
        """The same animal in another length unit: bone lengths, marker offsets, their
        bounds, the rest root and the bone-length priors times ``factor`` (e.g. 10 from cm
        to mm), declared in ``units`` (the pair of :meth:`acm_rs.CameraRig.scaled`)."""
        f = float(factor)
        if not (math.isfinite(f) and f > 0):
            raise ValueError(f"scale factor must be finite and > 0, got {factor}")
        out = self.with_parameters(self.bone_lengths * f, self.marker_offsets * f)
        out._rest_root = self._rest_root * f
        out._marker_bounds = self._marker_bounds * f
        out._constraints = tuple(
            dataclasses.replace(
                c, **{k: getattr(c, k) * f for k in ("slope", "slope_sd", "mean", "sd")
                      if getattr(c, k) is not None}
            )
            for c in self._constraints
        )  # fmt: skip
        out.units = units
        return out

    def with_links(
        self, bone_links: np.ndarray | None, link_order: Sequence[int] | None = None
    ) -> Skeleton:
        """A copy whose rotations move the bones ``bone_links`` says (see
        :meth:`from_rest_pose`); ``bone_links=None`` goes back to the tree rule."""
        links = None if bone_links is None else (bone_links, link_order)
        return self._copy_with(_with_links(self._native, links))

    def _copy_with(self, native: _native.NativeSkeleton) -> Skeleton:
        return Skeleton(
            joint_names=self._joint_names,
            parents=self._parents,
            marker_names=self._marker_names,
            marker_joints=self._marker_joints,
            native=native,
            rest_root=self._rest_root,
            up=self._up,
            joint_limits=self._joint_limits,
            symmetry=self._symmetry,
            marker_bounds=self._marker_bounds,
            bone_length_constraints=self._constraints,
            name=self.name,
            units=self.units,
            explicit_frames=self._explicit_frames,
            stretch_sd=self._stretch_sd,
        )

    # -- structure --------------------------------------------------------------------------
    @property
    def joint_names(self) -> tuple[str, ...]:
        """Joint names, length J."""
        return self._joint_names

    @property
    def marker_names(self) -> tuple[str, ...]:
        """Marker names, length M."""
        return self._marker_names

    @property
    def parents(self) -> np.ndarray:
        """(J,) parent joint index, -1 for the root."""
        return self._parents

    @property
    def marker_joints(self) -> np.ndarray:
        """(M,) joint index each marker is attached to."""
        return self._marker_joints

    @property
    def bones(self) -> np.ndarray:
        """(n_bones, 2) ``[start, end]`` joint indices; bone ``b`` ends at a non-root joint."""
        return self._native.bones

    @property
    def bone_names(self) -> tuple[str, ...]:
        """Bone names = names of their end joints."""
        return tuple(self._joint_names[e] for e in self.bones[:, 1])

    @property
    def n_joints(self) -> int:
        """Number of joints J."""
        return len(self._joint_names)

    @property
    def n_bones(self) -> int:
        """Number of bones (J - 1)."""
        return int(self._native.n_bones)

    @property
    def n_markers(self) -> int:
        """Number of markers M."""
        return len(self._marker_names)

    @property
    def n_pose(self) -> int:
        """Length of the flat pose ``[t (3), r (n_bones * 3)]``."""
        return 3 + 3 * self.n_bones

    @property
    def bone_lengths(self) -> np.ndarray:
        """(n_bones,) bone lengths (world units)."""
        return self._native.lengths

    @property
    def marker_offsets(self) -> np.ndarray:
        """(M, 3) marker offsets ``v`` in the frame of the bone their joint ends."""
        return self._native.offsets

    @property
    def rest_frames(self) -> np.ndarray:
        """(n_bones, 3, 3) rest orientations; columns are the bone axes, z along the bone."""
        return self._native.rest_frames

    @property
    def marker_bones(self) -> np.ndarray:
        """(M,) bone whose frame each marker offset is expressed in."""
        return self._native.marker_bones

    @property
    def bone_links(self) -> np.ndarray:
        """(n_bones, n_bones) bool: ``[i, j]`` if the rotation of bone i moves bone j.

        By default (the tree rule) bone i's rotation moves bone i and its descendants."""
        return self._native.bone_links()

    @property
    def link_order(self) -> np.ndarray:
        """(n_bones,) the order in which the bone rotations apply (root first by default)."""
        return self._native.link_order

    @property
    def root_bones(self) -> np.ndarray:
        """Indices of the bones that turn the whole body together: under the tree rule the
        bones that start at the root (one for the rat), with an explicit link matrix the
        first bone in ``link_order`` if its rotation moves every bone (the authors' ``r0``)."""
        if self.custom_links is None:
            return np.flatnonzero(self.bones[:, 0] == self.parents.tolist().index(-1))
        first = int(self.link_order[0])
        if not self.bone_links[first].all():
            raise ValueError(
                "this skeleton's link matrix has no global rotation: the first rotation in "
                "link_order does not move every bone"
            )
        return np.array([first])

    def turned(self, r: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """The rotations of poses turned rigidly about the root.

        Parameters
        ----------
        r : array_like, shape (..., n_bones, 3)
            Rodrigues vectors (rad).
        rot : array_like, shape (..., 3, 3)
            Rotation applied to the whole body (world frame), one per pose.

        Returns
        -------
        numpy.ndarray, shape (..., n_bones, 3)
            ``r`` with the rotation of every root bone (:attr:`root_bones`) composed with
            ``rot`` from the left; all other rotations unchanged.
        """
        out = np.array(as_float_array(r, "r", (self.n_bones, 3)), dtype=np.float64)
        rot = np.asarray(rot, dtype=np.float64)
        for b in self.root_bones:
            out[..., b, :] = rodrigues_inverse(rot @ rodrigues(out[..., b, :]))
        return out

    @property
    def custom_links(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(bone_links, link_order)`` when set explicitly (e.g. from an ACM ``model.npy``),
        ``None`` for the tree rule."""
        if self._native.tree_links:
            return None
        return self.bone_links, self.link_order

    @property
    def up(self) -> np.ndarray:
        """(3,) rest-pose up direction used for the bone frames."""
        return self._up.copy()

    @property
    def joint_limits(self) -> np.ndarray:
        """(n_bones, 3, 2) ``[lower, upper]`` per Rodrigues component (rad); +-inf if unbounded."""
        return self._joint_limits

    @property
    def stretch_sd(self) -> np.ndarray:
        """``(n_bones,)`` SD of each bone's log-length over frames (elastic segments, issue 28;
        dimensionless: 0.1 is a bone whose length varies by ~10 % around its mean). 0: rigid,
        as in the ACM models. Learned by :func:`acm_rs.elastic.learn_stretch`."""
        return self._stretch_sd

    @property
    def elastic_bones(self) -> np.ndarray:
        """Indices of the bones with ``stretch_sd > 0``."""
        return np.flatnonzero(self._stretch_sd > 0)

    def with_stretch(self, stretch_sd: Mapping[str, float] | np.ndarray | None) -> Skeleton:
        """A copy with new stretch SDs: ``(n_bones,)`` or ``{bone name: SD}`` (others 0);
        ``None`` makes every bone rigid."""
        out = self._copy_with(self._native)
        out._stretch_sd = _stretch_array(stretch_sd, self.bone_names)
        out._stretch_sd.setflags(write=False)
        return out

    @property
    def fixed_pose_mask(self) -> np.ndarray:
        """(n_pose,) bool: pose entries fixed by ``[b, b]`` limits (not in the tracker state)."""
        lim = self._joint_limits.reshape(-1, 2)
        return np.concatenate([np.zeros(3, bool), lim[:, 0] == lim[:, 1]])

    @property
    def marker_bounds(self) -> np.ndarray:
        """(M, 3, 2) box constraints of the marker offsets in the bone frame (sec. 6)."""
        return self._marker_bounds

    @property
    def symmetry(self) -> dict[str, list[tuple[str, str]]]:
        """``{"joints": [(left, right)], "markers": [(left, right)]}``."""
        return {k: list(v) for k, v in self._symmetry.items()}

    @property
    def bone_length_constraints(self) -> tuple[BoneLengthConstraint, ...]:
        """Anatomical bone-length priors."""
        return self._constraints

    def joint_index(self, name: str) -> int:
        """Index of a joint by name (``ValueError`` listing the names if unknown)."""
        return _lookup(self._joint_names, name, "joint")

    def marker_index(self, name: str) -> int:
        """Index of a marker by name (``ValueError`` listing the names if unknown)."""
        return _lookup(self._marker_names, name, "marker")

    def bone_index(self, name: str) -> int:
        """Index of the bone ending at joint ``name``."""
        j = self.joint_index(name)
        hits = np.flatnonzero(self.bones[:, 1] == j)
        if hits.size == 0:
            raise ValueError(f"joint {name!r} is the root; no bone ends there")
        return int(hits[0])

    # -- kinematics -------------------------------------------------------------------------
    def forward(
        self,
        t: np.ndarray,
        r: np.ndarray,
        *,
        bone_lengths: np.ndarray | None = None,
        marker_offsets: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Forward kinematics (Alg. 1) of one or many poses, in parallel in Rust.

        Parameters
        ----------
        t : array_like, shape (T, 3) or (3,)
            Global translation = root joint position (world units).
        r : array_like, shape (T, n_bones, 3) or (n_bones, 3)
            Rodrigues vector per bone (rad).
        bone_lengths : array_like, shape (n_bones,), optional
            Override of the skeleton's bone lengths.
        marker_offsets : array_like, shape (M, 3), optional
            Override of the marker offsets.

        Returns
        -------
        joints : numpy.ndarray, shape (T, J, 3) or (J, 3)
        markers : numpy.ndarray, shape (T, M, 3) or (M, 3)
        """
        tt = as_float_array(t, "t", (3,))
        rr = as_float_array(r, "r", (self.n_bones, 3))
        single = tt.ndim == 1
        if single != (rr.ndim == 2) or tt.ndim > 2 or rr.ndim > 3:
            raise ValueError(
                f"t must be (T, 3) with r (T, {self.n_bones}, 3), or (3,) with "
                f"({self.n_bones}, 3); got t {tt.shape} and r {rr.shape}"
            )
        if not single and tt.shape[0] != rr.shape[0]:
            raise ValueError(f"t has {tt.shape[0]} frames but r has {rr.shape[0]}")
        lengths = None
        if bone_lengths is not None:
            lengths = as_float_array(bone_lengths, "bone_lengths", (self.n_bones,))
        offsets = None
        if marker_offsets is not None:
            offsets = as_float_array(marker_offsets, "marker_offsets", (self.n_markers, 3))
        joints, markers = self._native.forward(
            tt.reshape(-1, 3), rr.reshape(-1, self.n_bones, 3), lengths, offsets
        )
        if single:
            return joints[0], markers[0]
        return joints, markers

    def project(self, rig: CameraRig, t: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Fused forward kinematics and projection of the markers into every camera.

        Equals ``rig.project(self.forward(t, r)[1])`` without the intermediate 3D markers.

        Parameters
        ----------
        rig : CameraRig
        t : array_like, shape (T, 3) or (3,)
        r : array_like, shape (T, n_bones, 3) or (n_bones, 3)

        Returns
        -------
        numpy.ndarray, shape (n_cams, T, M, 2) or (n_cams, M, 2)
            Pixels; NaN where a marker is behind a camera.
        """
        tt = as_float_array(t, "t", (3,))
        rr = as_float_array(r, "r", (self.n_bones, 3))
        single = tt.ndim == 1
        if tt.shape[:-1] != rr.shape[:-2] or tt.ndim > 2:
            raise ValueError(
                f"t must be (T, 3) with r (T, {self.n_bones}, 3), or (3,) with "
                f"({self.n_bones}, 3); got t {tt.shape} and r {rr.shape}"
            )
        px = self._native.project_poses(
            rig.get_params(), tt.reshape(-1, 3), rr.reshape(-1, self.n_bones, 3)
        )
        return px[:, 0] if single else px

    def forward_jacobian(
        self,
        t: np.ndarray,
        r: np.ndarray,
        *,
        bone_lengths: np.ndarray | None = None,
        marker_offsets: np.ndarray | None = None,
    ) -> FKJacobian:
        """Forward kinematics of one pose with exact Jacobians w.r.t. t, r, lengths and offsets.

        Parameters
        ----------
        t : array_like, shape (3,)
        r : array_like, shape (n_bones, 3)
        bone_lengths, marker_offsets : optional overrides as in :meth:`forward`.

        Returns
        -------
        FKJacobian
        """
        tt = as_float_array(t, "t", (3,))
        rr = as_float_array(r, "r", (self.n_bones, 3))
        if tt.shape != (3,) or rr.shape != (self.n_bones, 3):
            raise ValueError(
                f"expected t (3,) and r ({self.n_bones}, 3), got {tt.shape}, {rr.shape}"
            )
        lengths = None
        if bone_lengths is not None:
            lengths = as_float_array(bone_lengths, "bone_lengths", (self.n_bones,))
        offsets = None
        if marker_offsets is not None:
            offsets = as_float_array(marker_offsets, "marker_offsets", (self.n_markers, 3))
        j, m, dp, dl, dv = self._native.forward_jacobian(tt, rr, lengths, offsets)
        nj = self.n_joints
        return FKJacobian(j, m, dp[:nj], dp[nj:], dl[:nj], dl[nj:], dv)

    def rest_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """``(joints (J, 3), markers (M, 3))`` with every rotation zero."""
        return self.forward(self._rest_root, np.zeros((self.n_bones, 3)))

    # -- derived maps -----------------------------------------------------------------------
    def symmetry_map(self) -> SymmetryMap:
        """Alg. 2-3 maps between reduced (central + left) and full lengths/offsets."""
        return SymmetryMap(self)

    def state_map(
        self, normalization: Normalization | None = None, joint_limits: bool = True
    ) -> StateMap:
        """Map between the tracker state (free entries) and ``(t, r)``; see :class:`StateMap`."""
        return StateMap(self, normalization, joint_limits)

    def bone_length_bounds(
        self, body_weight: float | None = None, sigma_factor: float = 10.0
    ) -> np.ndarray:
        """(n_bones, 2) length bounds from the anatomical priors (Supp. Table 2).

        Parameters
        ----------
        body_weight : float, optional
            Body weight in g, needed for weight-proportional (rat) priors.
        sigma_factor : float
            Half-width in standard deviations (the authors' tool uses 10).

        Returns
        -------
        numpy.ndarray
            ``[lower, upper]`` per bone; ``(0, inf)`` where no prior applies.
        """
        out = np.tile([0.0, np.inf], (self.n_bones, 1))
        for c in self._constraints:
            lo, hi = c.bounds(body_weight, sigma_factor)
            out[self.bone_index(c.bone)] = (max(lo, 0.0), hi)
        return out

    # -- files ------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The skeleton as the TOML document described in ``docs/skeleton_format.md``."""
        rest_j, rest_m = self.rest_pose()
        limits_deg = np.degrees(self._joint_limits)
        doc: dict = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "name": self.name,
            "units": self.units,
            "angle_units": "deg",
            "up": self._up.tolist(),
            "joints": [],
            "markers": [],
        }
        frames = self.rest_frames
        bone_of_end = {int(e): b for b, e in enumerate(self.bones[:, 1])}
        for j, n in enumerate(self._joint_names):
            parent = self._parents[j]
            entry = {
                "name": n,
                "parent": "" if parent < 0 else self._joint_names[parent],
                "position": [_clean(v) for v in rest_j[j]],
            }
            if self._explicit_frames and j in bone_of_end:
                entry["frame"] = [[_clean(v) for v in row] for row in frames[bone_of_end[j]]]
            doc["joints"].append(entry)
        for k, n in enumerate(self._marker_names):
            entry = {
                "name": n,
                "joint": self._joint_names[self._marker_joints[k]],
                "position": [_clean(v) for v in rest_m[k]],
            }
            b = self._marker_bounds[k]
            if np.any(np.isfinite(b)):
                entry["bounds"] = {
                    ax: [_clean(b[i, 0]), _clean(b[i, 1])] for i, ax in enumerate("xyz")
                }
            doc["markers"].append(entry)
        lim_entries = []
        for b, name in enumerate(self.bone_names):
            lim = limits_deg[b]
            if np.all(np.isinf(lim[:, 0])) and np.all(np.isinf(lim[:, 1])):
                continue
            lim_entries.append(
                {"bone": name}
                | {ax: [_clean(lim[i, 0]), _clean(lim[i, 1])] for i, ax in enumerate("xyz")}
            )
        doc["joint_limits"] = lim_entries
        doc["symmetry"] = {k: [list(p) for p in v] for k, v in self._symmetry.items()}
        if self._stretch_sd.any():
            doc["elastic"] = [
                {"bone": n, "sd": _clean(v)}
                for n, v in zip(self.bone_names, self._stretch_sd, strict=True)
                if v > 0
            ]
        doc["bone_length_constraints"] = [
            {k: v for k, v in vars(c).items() if v is not None} for c in self._constraints
        ]
        if self.custom_links is not None:
            links, order = self.custom_links
            names = self.bone_names
            doc["links"] = [
                {"bone": names[i], "moves": [names[j] for j in np.flatnonzero(links[i])]}
                for i in order
            ]
        return doc

    def save(self, path: str | Path) -> None:
        """Write the skeleton as TOML (atomically)."""
        with atomic_write(path, "w") as fh:
            fh.write(_toml.dumps(self.to_dict()))

    @classmethod
    def from_dict(cls, doc: Mapping, source: str = "<dict>") -> Skeleton:
        """Build a skeleton from a parsed skeleton document (see :meth:`to_dict`)."""
        if doc.get("format") != FORMAT_NAME:
            raise ValueError(
                f"{source}: not an acm-rs skeleton file (format = {doc.get('format')!r})"
            )
        if doc.get("version") != FORMAT_VERSION:
            raise ValueError(f"{source}: unsupported skeleton file version {doc.get('version')!r}")
        _check_keys(doc, _DOC_KEYS, source, "")
        for key, allowed in (("joints", _JOINT_KEYS), ("markers", _MARKER_KEYS)):
            for i, entry in enumerate(doc.get(key, [])):
                if isinstance(entry, Mapping):
                    _check_keys(entry, allowed, source, f"{key}[{i}] ({entry.get('name', '?')}): ")
        for key in ("joints", "markers"):
            seen: dict[str, int] = {}
            for i, entry in enumerate(doc.get(key, [])):
                name = entry.get("name") if isinstance(entry, Mapping) else None
                if name in seen:
                    raise ValueError(
                        f"{source}: {key}[{i}] repeats the name {name!r} of {key}[{seen[name]}]; "
                        f"{key[:-1]} names must be unique (rename one)"
                    )
                seen[name] = i
        try:
            joints = doc["joints"]
            markers = doc.get("markers", [])
            jn = [j["name"] for j in joints]
            parents = [
                -1 if j["parent"] in ("", None) else _lookup(jn, j["parent"], "joint")
                for j in joints
            ]
            rest_j = np.array([j["position"] for j in joints], dtype=np.float64)
            mn = [m["name"] for m in markers]
            mj = [m["joint"] for m in markers]
            rest_m = np.array([m["position"] for m in markers], dtype=np.float64).reshape(-1, 3)
        except KeyError as exc:
            raise ValueError(f"{source}: missing key {exc}") from None
        rest_frames = _frames_from_doc(joints, parents, source)
        deg = doc.get("angle_units", "deg")
        if deg not in ("deg", "rad"):
            raise ValueError(f"{source}: angle_units must be 'deg' or 'rad', got {deg!r}")
        scale = math.pi / 180.0 if deg == "deg" else 1.0
        limits = {}
        for entry in doc.get("joint_limits", []):
            lim = np.array([entry.get(ax, [-math.inf, math.inf]) for ax in "xyz"], dtype=float)
            limits[entry["bone"]] = lim * scale
        bounds = {
            m["name"]: np.array([m["bounds"].get(ax, [-math.inf, math.inf]) for ax in "xyz"])
            for m in markers
            if "bounds" in m
        }
        constraints = [BoneLengthConstraint(**c) for c in doc.get("bone_length_constraints", [])]
        links, link_order = _links_from_doc(doc.get("links"), jn, parents, source)
        stretch = {}
        for i, entry in enumerate(doc.get("elastic", [])):
            if not isinstance(entry, Mapping) or set(entry) != {"bone", "sd"}:
                raise ValueError(
                    f"{source}: elastic[{i}] must be a table with keys 'bone' and 'sd', "
                    f"got {entry!r}"
                )
            stretch[entry["bone"]] = entry["sd"]
        return cls.from_rest_pose(
            jn,
            parents,
            rest_j,
            mn,
            mj,
            rest_m,
            joint_limits=limits,
            symmetry=doc.get("symmetry", {}),
            marker_bounds=bounds,
            bone_length_constraints=constraints,
            up=doc.get("up", (0.0, 1.0, 0.0)),
            name=doc.get("name", "skeleton"),
            units=doc.get("units", ""),
            rest_frames=rest_frames,
            bone_links=links,
            link_order=link_order,
            stretch_sd=stretch or None,
        )

    @classmethod
    def load(cls, path: str | Path) -> Skeleton:
        """Read a skeleton TOML file (see ``docs/skeleton_format.md``)."""
        p = Path(path)
        with p.open("rb") as fh:
            try:
                doc = tomllib.load(fh)
            except tomllib.TOMLDecodeError as exc:
                raise ValueError(f"{p}: invalid TOML: {exc}") from None
        return cls.from_dict(doc, source=str(p))

    def __repr__(self) -> str:
        return (
            f"Skeleton({self.name!r}: {self.n_joints} joints, {self.n_bones} bones, "
            f"{self.n_markers} markers, {int((~self.fixed_pose_mask).sum())} free pose entries)"
        )


class SymmetryMap:
    """Alg. 2-3: reduced parameters (central and left-sided) <-> full lengths and offsets."""

    def __init__(self, skeleton: Skeleton) -> None:
        sym = skeleton.symmetry
        bone_pairs = [
            (skeleton.bone_index(left), skeleton.bone_index(right))
            for left, right in sym.get("joints", [])
        ]
        marker_pairs = [
            (skeleton.marker_index(left), skeleton.marker_index(right))
            for left, right in sym.get("markers", [])
        ]
        self._native = _native.NativeSymmetry(
            skeleton.n_bones,
            np.array(bone_pairs, dtype=np.int64).reshape(-1, 2),
            skeleton.n_markers,
            np.array(marker_pairs, dtype=np.int64).reshape(-1, 2),
        )

    @property
    def n_reduced_bones(self) -> int:
        """Number of free bone lengths ``n*_bone``."""
        return int(self._native.n_reduced_bones)

    @property
    def n_reduced_markers(self) -> int:
        """Number of free marker offsets ``n*_marker``."""
        return int(self._native.n_reduced_markers)

    def expand_lengths(self, reduced: np.ndarray) -> np.ndarray:
        """Alg. 2: ``(n*_bone,)`` -> ``(n_bones,)``."""
        return self._native.expand_lengths(as_float_array(reduced, "reduced lengths", (None,)))

    def expand_offsets(self, reduced: np.ndarray) -> np.ndarray:
        """Alg. 3: ``(n*_marker, 3)`` -> ``(M, 3)`` (right-side x mirrored)."""
        return self._native.expand_offsets(as_float_array(reduced, "reduced offsets", (None, 3)))

    def reduce_lengths(self, lengths: np.ndarray) -> np.ndarray:
        """Pair-averaged inverse of Alg. 2."""
        return self._native.reduce_lengths(as_float_array(lengths, "lengths", (None,)))

    def reduce_offsets(self, offsets: np.ndarray) -> np.ndarray:
        """Pair-averaged inverse of Alg. 3."""
        return self._native.reduce_offsets(as_float_array(offsets, "offsets", (None, 3)))

    def reduce_length_grad(self, grad: np.ndarray) -> np.ndarray:
        """Gradient pull-back through Alg. 2 (transpose of the map)."""
        return self._native.reduce_length_grad(as_float_array(grad, "gradient", (None,)))

    def reduce_offset_grad(self, grad: np.ndarray) -> np.ndarray:
        """Gradient pull-back through Alg. 3 (transpose of the map)."""
        return self._native.reduce_offset_grad(as_float_array(grad, "gradient", (None, 3)))


# -- helpers ---------------------------------------------------------------------------------
_DOC_KEYS = {
    "format", "version", "name", "units", "angle_units", "up", "symmetry", "joints", "markers",
    "joint_limits", "bone_length_constraints", "links", "elastic",
}  # fmt: skip
_JOINT_KEYS = {"name", "parent", "position", "frame"}
_MARKER_KEYS = {"name", "joint", "position", "bounds"}


def _stretch_array(
    stretch_sd: Mapping[str, float] | np.ndarray | None, bone_names: Sequence[str]
) -> np.ndarray:
    """Stretch SDs as ``(n_bones,)``, from an array or ``{bone name: SD}`` (others 0)."""
    n = len(bone_names)
    if stretch_sd is None:
        return np.zeros(n)
    if isinstance(stretch_sd, Mapping):
        out = np.zeros(n)
        for name, v in stretch_sd.items():
            out[_lookup(bone_names, name, "bone")] = float(v)
    else:
        out = np.array(stretch_sd, dtype=np.float64)
    if out.shape != (n,) or not np.all(np.isfinite(out)) or np.any(out < 0):
        raise ValueError(f"stretch SDs must be {n} finite values >= 0 (one per bone), got {out}")
    return out


def _check_keys(doc: Mapping, allowed: set[str], source: str, where: str) -> None:
    """Refuse unknown keys (a typo would otherwise be ignored), suggesting the closest."""
    import difflib

    unknown = sorted(set(doc) - allowed)
    if unknown:
        hints = []
        for k in unknown:
            close = difflib.get_close_matches(k, sorted(allowed), n=1)
            hints.append(f"{k!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        raise ValueError(
            f"{source}: {where}unknown key(s) {', '.join(hints)}; known: {sorted(allowed)}"
        )


def _frames_from_doc(
    joints: Sequence[Mapping], parents: Sequence[int], source: str
) -> np.ndarray | None:
    """Explicit rest frames (``frame`` of every non-root joint) in bone order, or None."""
    has = [("frame" in j) for j, p in zip(joints, parents, strict=True) if p >= 0]
    if not any(has):
        return None
    if not all(has):
        missing = [j["name"] for j, p in zip(joints, parents, strict=True) if p >= 0]
        missing = [n for n, h in zip(missing, has, strict=True) if not h]
        raise ValueError(
            f"{source}: some joints give a rest 'frame' and others do not (missing: "
            f"{', '.join(missing[:5])}); give one for every non-root joint or none"
        )
    # bone b ends at the b-th non-root joint in joint order
    out = np.array([j["frame"] for j, p in zip(joints, parents, strict=True) if p >= 0], float)
    if out.shape[1:] != (3, 3):
        raise ValueError(f"{source}: every joint 'frame' must be a 3 x 3 matrix (rows)")
    return out


def _clean(v: float) -> float:
    v = float(v)
    if math.isfinite(v):
        v = round(v, 12)
        return 0.0 if v == 0 else v
    return v


def _limits_array(
    limits: Mapping[str, np.ndarray] | np.ndarray | None, bone_names: list[str], n_bones: int
) -> np.ndarray:
    out = np.tile(np.array([-np.inf, np.inf]), (n_bones, 3, 1))
    if limits is None:
        return out
    if isinstance(limits, Mapping):
        for name, lim in limits.items():
            if name not in bone_names:
                raise ValueError(
                    f"joint limit for unknown bone {name!r} (bones are named by their end "
                    f"joint; known: {bone_names})"
                )
            arr = np.asarray(lim, dtype=np.float64)
            if arr.shape != (3, 2):
                raise ValueError(f"joint limit of {name!r} must have shape (3, 2), got {arr.shape}")
            out[bone_names.index(name)] = arr
    else:
        arr = np.asarray(limits, dtype=np.float64)
        if arr.shape != (n_bones, 3, 2):
            raise ValueError(f"joint_limits must have shape ({n_bones}, 3, 2), got {arr.shape}")
        out = arr.copy()
    if np.any(np.isnan(out)):
        raise ValueError("joint limits contain NaN")
    bad = np.argwhere(out[..., 0] > out[..., 1])
    if bad.size:
        b, ax = bad[0]
        raise ValueError(
            f"joint limit of bone {bone_names[b]!r} axis {'xyz'[ax]} has lower > upper: "
            f"{out[b, ax]}"
        )
    return out


def _marker_bounds_array(
    bounds: Mapping[str, np.ndarray] | np.ndarray | None, marker_names: Sequence[str]
) -> np.ndarray:
    m = len(marker_names)
    out = np.tile(np.array([-np.inf, np.inf]), (m, 3, 1))
    if bounds is None:
        return out
    if isinstance(bounds, Mapping):
        for name, b in bounds.items():
            k = _lookup(marker_names, name, "marker")
            arr = np.asarray(b, dtype=np.float64)
            if arr.shape != (3, 2):
                raise ValueError(
                    f"marker bounds of {name!r} must have shape (3, 2), got {arr.shape}"
                )
            out[k] = arr
    else:
        arr = np.asarray(bounds, dtype=np.float64)
        if arr.shape != (m, 3, 2):
            raise ValueError(f"marker_bounds must have shape ({m}, 3, 2), got {arr.shape}")
        out = arr.copy()
    if np.any(np.isnan(out)) or np.any(out[..., 0] > out[..., 1]):
        raise ValueError("marker bounds must be intervals [lower <= upper] without NaN")
    return out


def _check_symmetry(
    symmetry: Mapping[str, Sequence[tuple[str, str]]],
    joint_names: Sequence[str],
    marker_names: Sequence[str],
) -> dict[str, list[tuple[str, str]]]:
    unknown_keys = set(symmetry) - {"joints", "markers"}
    if unknown_keys:
        raise ValueError(
            f"symmetry keys must be 'joints' and/or 'markers', got {sorted(unknown_keys)}"
        )
    out: dict[str, list[tuple[str, str]]] = {"joints": [], "markers": []}
    for key, names, what in (("joints", joint_names, "joint"), ("markers", marker_names, "marker")):
        seen: set[str] = set()
        for pair in symmetry.get(key, []):
            if len(pair) != 2:
                raise ValueError(f"symmetry {key} entries must be (left, right) pairs, got {pair}")
            left, right = str(pair[0]), str(pair[1])
            _lookup(names, left, what)
            _lookup(names, right, what)
            if left == right or left in seen or right in seen:
                raise ValueError(f"{what} {left!r}/{right!r} repeated in symmetry pairs")
            seen.update((left, right))
            out[key].append((left, right))
    return out


def _with_links(native: _native.NativeSkeleton, links) -> _native.NativeSkeleton:
    """``native`` with ``links = (bone_links, link_order)`` set, or the tree rule for ``None``."""
    if links is None:
        return native if native.tree_links else native.with_links(None)
    bone_links, order = links
    lk = np.asarray(bone_links)
    if lk.dtype != bool:
        raise ValueError(f"bone_links must be a bool array, got dtype {lk.dtype}")
    order_arr = None if order is None else as_index_array(order, "link_order")
    return native.with_links(np.ascontiguousarray(lk), order_arr)


def _links_from_doc(entries, joint_names, parents, source):
    """``[[links]]`` of a skeleton file -> ``(bone_links, link_order)`` or ``(None, None)``."""
    if entries is None:
        return None, None
    bone_names = [n for n, p in zip(joint_names, parents, strict=True) if p != -1]
    n = len(bone_names)
    links = np.zeros((n, n), dtype=bool)
    order = []
    for k, entry in enumerate(entries):
        if not isinstance(entry, Mapping) or set(entry) != {"bone", "moves"}:
            raise ValueError(f"{source}: links[{k}] must have exactly the keys 'bone' and 'moves'")
        i = _lookup(bone_names, entry["bone"], "bone")
        if i in order:
            raise ValueError(f"{source}: links lists bone {entry['bone']!r} twice")
        order.append(i)
        for name in entry["moves"]:
            links[i, _lookup(bone_names, name, "bone")] = True
    if len(order) != n:
        missing = [bone_names[i] for i in range(n) if i not in order]
        raise ValueError(f"{source}: links must list every bone once; missing {missing}")
    return links, np.array(order, dtype=np.int64)
