"""Second poses that fit the markers as well as the tracked one (joint ambiguity).

A marker layout can leave a joint's position ambiguous: with the rat model's 3 mm marker
offsets at shoulder, elbow, hip, knee and ankle, a limb's middle joint can swing about the
axis from its parent to its child to a second position where every marker lands where it
was (the two roots of a two-link chain's swivel). The markers then cannot tell the two
poses apart, and a Gaussian posterior around one of them (UKF/RTS, ACM supp. Alg. 7-9)
states a joint SD that does not cover the other. :func:`second_solutions` searches for such
poses at a sample of frames so that a user learns which joints the markers do not decide.

The search, per frame and per joint ``b`` with parent ``a`` and one child ``c``: rotate
``b`` by pi about the axis ``a -> c``; fit the rotations of the bones from ``a -> b`` down
(those of the free entries of the result's state map) to the frame's forward-kinematics
markers plus the swung joint (Levenberg-Marquardt
with the exact Jacobians of Alg. 1); then fit the markers alone from there, each marker
coordinate weighted by its posterior SD. A pose whose markers differ from the tracked pose's
by ``Δχ² = Σ (Δm / σ_m)² ≤ chi2`` (default 4: a likelihood ratio of at least e⁻² in the
markers' own uncertainty), inside the joint limits when the result enforced them, and that
moves some joint beyond its own 95 % interval is a second solution.

:func:`widen` then makes the joints' SDs honest about what the search found. A joint with a
second pose at distance ``D`` in a fraction ``f`` of the searched frames gets the variance
``f (D / 1.96)²`` added to each coordinate in every frame: where the search found a second
pose (``f = 1``), the 95 % interval about the tracked joint reaches it, as a 95 % region of a
posterior with two poses of comparable likelihood must (``Δχ² ≤ 4`` is a likelihood ratio of
at least e⁻²). ``D`` is the median over the frames where one was found; frames between the
searched ones get the same widening, an approximation that the search's frame count sets.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..rotation import rodrigues
from ..skeleton import Skeleton
from .result import PoseResult

#: Default bound on ``Δχ²`` of a second pose's markers in the metric of their posterior SDs.
CHI2 = 4.0


@dataclass(frozen=True)
class SecondSolutions:
    """Result of :func:`second_solutions`.

    Attributes
    ----------
    frames : numpy.ndarray, shape (K,)
        The frames searched.
    distance : numpy.ndarray, shape (K, J)
        Largest distance (world units) between a joint in the tracked pose and in a second
        pose whose markers are within ``Δχ² ≤ chi2``; NaN where none moved the joint beyond
        1.96 times the norm of its posterior SD.
    displacement : numpy.ndarray, shape (K, J, 3)
        The joint's move to that second pose (world units); NaN where ``distance`` is.
    joint_names : tuple of str
    units : str
        The skeleton's length unit.
    chi2 : float
        Bound on the markers' ``Δχ²`` within which a second pose counts as fitting as well.
    """

    frames: np.ndarray
    distance: np.ndarray
    displacement: np.ndarray
    joint_names: tuple[str, ...]
    units: str
    chi2: float

    def ambiguous(self) -> list[tuple[str, float, float]]:
        """``(joint, fraction of the searched frames, median distance)`` of every joint with
        a second solution in at least one frame, most frequent first."""
        found = np.isfinite(self.distance)
        rows = [
            (name, float(found[:, j].mean()), float(np.nanmedian(self.distance[found[:, j], j])))
            for j, name in enumerate(self.joint_names)
            if found[:, j].any()
        ]
        return sorted(rows, key=lambda row: (-row[1], -row[2]))

    def widening(self) -> np.ndarray:
        """SD to add to each coordinate of each joint, shape (J,) (world units; 0 for the
        joints without a second pose): ``sqrt(f) D / 1.96`` with ``f`` the fraction of the
        searched frames with a second pose and ``D`` its median distance there."""
        found = np.isfinite(self.distance)
        out = np.zeros(len(self.joint_names))
        for j in np.flatnonzero(found.any(axis=0)):
            frac = found[:, j].mean()
            out[j] = np.sqrt(frac) * np.median(self.distance[found[:, j], j]) / 1.96
        return out

    def summary(self) -> str:
        """One line naming the ambiguous joints (or saying there are none)."""
        rows = self.ambiguous()
        if not rows:
            return (
                f"no second pose fits the markers within Δχ² {self.chi2:g} in "
                f"{len(self.frames)} searched frames"
            )
        unit = self.units or "world units"
        parts = ", ".join(
            f"{name} ({100 * frac:.0f} % of frames, {dist:.3g} {unit})" for name, frac, dist in rows
        )
        return (
            f"the markers do not decide these joints: a second pose fits them within Δχ² "
            f"{self.chi2:g} (their posterior SDs) with the joint elsewhere: {parts} (joint "
            "limits or more markers away from the joints' axes decide them)"
        )


def widen(result: PoseResult, found: SecondSolutions) -> np.ndarray:
    """Widen ``result.joints_std`` by what ``found`` says the markers leave open (see the
    module docstring), in place of an earlier widening of the same result.

    Parameters
    ----------
    result : PoseResult
        Its ``joints_std`` (T, J, 3) is replaced; ``info["joints_std_widening"]`` (J,) records
        the SD added (world units), so that ``sqrt(joints_std² − widening²)`` is the Gaussian
        posterior's SD.
    found : SecondSolutions
        A search of this result (:func:`second_solutions`).

    Returns
    -------
    numpy.ndarray, shape (J,)
        The SD added to each joint's coordinates (world units).
    """
    if tuple(found.joint_names) != tuple(result.joint_names):
        raise ValueError("the search is of another skeleton than the result's")
    added = found.widening()
    before = np.asarray(result.info.get("joints_std_widening", np.zeros_like(added)))
    var = result.joints_std**2 + (added**2 - before**2)[None, :, None]
    result.joints_std = np.sqrt(np.maximum(var, 0.0))
    result.info["joints_std_widening"] = added
    return added


def gaussian_joints_std(result: PoseResult) -> np.ndarray:
    """The joints' SDs of the Gaussian posterior, shape (T, J, 3) (world units):
    ``result.joints_std`` without a :func:`widen` widening. The search measures "beyond the
    95 % interval" against these, so that a second search of a widened result finds what the
    first one found."""
    added = result.info.get("joints_std_widening")
    if added is None:
        return result.joints_std
    var = result.joints_std**2 - np.asarray(added)[None, :, None] ** 2
    return np.sqrt(np.maximum(var, 0.0))


def _swivel(points: np.ndarray, a: int, b: int, c: int, angle: float) -> np.ndarray:
    """``points`` with point ``b`` rotated by ``angle`` about the axis through ``a`` and ``c``."""
    axis = points[c] - points[a]
    norm = np.linalg.norm(axis)
    out = points.copy()
    if norm > 0:
        out[b] = points[a] + rodrigues(axis * (angle / norm)) @ (points[b] - points[a])
    return out


def _subtree(children: list[np.ndarray], root: int) -> set[int]:
    """The joint ``root`` and all its descendants."""
    out, todo = set(), [root]
    while todo:
        j = todo.pop()
        out.add(j)
        todo.extend(int(c) for c in children[j])
    return out


def _fit(skeleton, x_full, free, lengths, marker_target, weight, joint_target):
    """Levenberg-Marquardt on the free pose entries (marker residuals times ``weight``,
    (M, 3); joint residuals times its median); returns the full pose vector."""
    w_markers = weight.ravel()[:, None]
    w_joints = float(np.median(weight))

    def unpack(z):
        x = x_full.copy()
        x[free] = z
        return x[:3], x[3:].reshape(-1, 3)

    def residual(z):
        joints, markers = skeleton.forward(*unpack(z), bone_lengths=lengths)
        res = [(markers - marker_target).ravel() * w_markers[:, 0]]
        if joint_target is not None:
            res.append((joints - joint_target).ravel() * w_joints)
        return np.concatenate(res)

    def jacobian(z):
        d = skeleton.forward_jacobian(*unpack(z), bone_lengths=lengths)
        rows = [d.d_markers_d_pose.reshape(-1, skeleton.n_pose)[:, free] * w_markers]
        if joint_target is not None:
            rows.append(d.d_joints_d_pose.reshape(-1, skeleton.n_pose)[:, free] * w_joints)
        return np.vstack(rows)

    sol = least_squares(
        residual, x_full[free], jac=jacobian, method="lm", xtol=1e-6, ftol=1e-6, max_nfev=50
    )
    x = x_full.copy()
    x[free] = sol.x
    return x


def second_solutions(
    result: PoseResult,
    *,
    frames: int | np.ndarray = 10,
    chi2: float = CHI2,
    angles: tuple[float, ...] = (np.pi,),
) -> SecondSolutions:
    """Search a sample of frames of a tracking result for second poses that fit the markers
    as well.

    Parameters
    ----------
    result : PoseResult
        A result of :func:`acm_rs.track` (its skeleton, state map, poses, joint SDs and
        ``info["markers_std_fk"]``, else ``info["markers_std"]``, are used).
    frames : int or array_like of int
        The number of frames to search, evenly spread over the frames with at least the
        median number of detections, or the frames themselves. Each frame costs two small
        least-squares fits per joint with one child (~0.07 s for the bundled rat, ~0.2 s for
        a 29-joint skeleton without joint limits).
    chi2 : float
        Bound on ``Σ (Δm / σ_m)²`` over the marker coordinates (σ: the posterior SDs of the
        result's forward-kinematics markers) within which a second pose fits as well.
    angles : tuple of float
        Swing angles (rad) to start each joint's search from (default pi; each costs as
        much).

    Returns
    -------
    SecondSolutions
    """
    n_frames = result.n_frames
    if np.ndim(frames) == 0:
        count = int(frames)
        if count < 1:
            raise ValueError(f"frames must be at least 1, got {count}")
        # evenly spread over the frames with at least the median number of detections
        seen = np.isfinite(result.detections[..., 0]).sum(axis=(0, 2))
        candidates = np.flatnonzero((seen >= np.median(seen)) & (seen > 0))
        if candidates.size == 0:
            raise ValueError("no frame has a detection: nothing to search")
        count = min(count, candidates.size)
        picked = candidates[((np.arange(count) + 0.5) * candidates.size / count).astype(int)]
    else:
        picked = np.asarray(frames, dtype=np.int64).ravel()
        if picked.size == 0 or picked.min() < 0 or picked.max() >= n_frames:
            raise ValueError(f"frames must lie in [0, {n_frames}), got {picked.tolist()}")
    msd = result.info.get("markers_std_fk", result.info.get("markers_std"))
    if msd is None or not np.any(result.joints_std):
        raise ValueError("the result has no posterior (method='deterministic'?): nothing to test")
    state_map = result.state_map
    lengths = None
    if state_map.stretch_bones.size:
        lengths = np.array([state_map.lengths(result.state_mean[f]) for f in picked])
    return search(
        result.skeleton,
        result.t[picked],
        result.r[picked],
        marker_std=np.asarray(msd)[picked],
        chi2=chi2,
        joints_std=gaussian_joints_std(result)[picked],
        free=np.asarray(state_map.free_indices, dtype=np.int64)[: state_map.n_pose_state],
        within_limits=state_map.joint_limits,
        bone_lengths=lengths,
        frames=picked,
        angles=angles,
    )


def search(
    skeleton: Skeleton,
    t: np.ndarray,
    r: np.ndarray,
    *,
    marker_std: float | np.ndarray,
    chi2: float = CHI2,
    joints_std: np.ndarray | None = None,
    free: np.ndarray | None = None,
    within_limits: bool = False,
    bone_lengths: np.ndarray | None = None,
    frames: np.ndarray | None = None,
    angles: tuple[float, ...] = (np.pi,),
) -> SecondSolutions:
    """Search given poses for second poses with the same markers (see the module docstring).

    Parameters
    ----------
    skeleton : Skeleton
    t : numpy.ndarray, shape (K, 3)
        Translations (world units).
    r : numpy.ndarray, shape (K, n_bones, 3)
        Bone rotations (Rodrigues vectors, rad).
    marker_std : float or numpy.ndarray, shape (K, M, 3)
        SD of each marker coordinate (world units): the metric of ``Δχ²``. Values below
        1e-6 of their median are raised to it.
    chi2 : float
        Bound on ``Σ (Δm / σ_m)²`` within which a second pose fits as well.
    joints_std : numpy.ndarray, shape (K, J, 3), optional
        Posterior SDs: a joint counts as moved beyond ``1.96 |SD|``, and always beyond
        ``2 sqrt(chi2 / 3)`` marker SDs (their median).
    free : numpy.ndarray of int, optional
        Indices of the pose entries ``[t, r.ravel()]`` the search may change (default all
        rotation entries).
    within_limits : bool
        Count only second poses inside ``skeleton.joint_limits``.
    bone_lengths : numpy.ndarray, shape (K, n_bones), optional
        Per-pose bone lengths (elastic bones); default the skeleton's.
    frames : numpy.ndarray of int, shape (K,), optional
        Frame numbers to report (default ``0..K-1``).
    angles : tuple of float
        Swing angles (rad) to start from (default pi).

    Returns
    -------
    SecondSolutions
    """
    sk = skeleton
    t = np.asarray(t, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(r, dtype=np.float64).reshape(len(t), sk.n_bones, 3)
    if not (np.isfinite(chi2) and chi2 > 0):
        raise ValueError(f"chi2 must be positive, got {chi2}")
    sd = np.broadcast_to(np.asarray(marker_std, dtype=np.float64), (len(t), sk.n_markers, 3))
    if not np.isfinite(sd).all() or not (sd > 0).any():
        raise ValueError("marker_std must be finite and positive")
    floor = 1e-6 * float(np.median(sd[sd > 0]))
    weight = 1.0 / np.maximum(sd, floor)
    if free is None:
        free = np.arange(3, sk.n_pose)
    free = np.asarray(free, dtype=np.int64)
    limits = sk.joint_limits.reshape(-1, 2)  # (3 n_bones, 2), rad
    parents = np.asarray(sk.parents)
    children = [np.flatnonzero(parents == j) for j in range(len(parents))]
    bones = np.asarray(sk.bones)
    chains = []
    for b in range(len(parents)):
        if parents[b] < 0 or len(children[b]) != 1:
            continue
        a = int(parents[b])
        # The swing moves ``b`` and its subtree: refit the rotations of the bones ending in it
        # (``a -> b`` and below). Each rotation is relative to its parent's frame (Alg. 1), so
        # the rest of the pose, ``b``'s siblings included, stays. (Session 22 refit ``a``'s
        # whole subtree: 81-84 entries for a shoulder or the spine, 2.4 x the search's time
        # for the same coverage, docs/tracking.md.)
        inside = _subtree(children, b)
        entries = np.array([3 + 3 * k + i for k in range(len(bones)) if bones[k, 1] in inside
                            for i in range(3)], dtype=np.int64)  # fmt: skip
        local = np.intersect1d(free, entries)
        if local.size:
            chains.append((a, b, int(children[b][0]), local))
    distance = np.full((len(t), len(parents)), np.nan)
    displacement = np.full((len(t), len(parents), 3), np.nan)
    for row in range(len(t)):
        x0 = np.concatenate([t[row], r[row].ravel()])
        if not np.isfinite(x0).all():
            continue
        lengths = None if bone_lengths is None else bone_lengths[row]
        joints, markers = sk.forward(t[row], r[row], bone_lengths=lengths)
        beyond = np.full(len(parents), 2.0 * np.sqrt(chi2 / 3.0) / np.median(weight[row]))
        if joints_std is not None:
            beyond = np.maximum(beyond, 1.96 * np.linalg.norm(joints_std[row], axis=-1))
        for (a, b, c, local), angle in itertools.product(chains, angles):
            swung = _swivel(joints, a, b, c, angle)
            start = _fit(sk, x0, local, lengths, markers, weight[row], swung)
            x = _fit(sk, start, local, lengths, markers, weight[row], None)
            new_joints, new_markers = sk.forward(x[:3], x[3:].reshape(-1, 3), bone_lengths=lengths)
            if float((((new_markers - markers) * weight[row]) ** 2).sum()) > chi2:
                continue
            if within_limits:
                rot = x[3:]
                if ((rot < limits[:, 0] - 1e-9) | (rot > limits[:, 1] + 1e-9)).any():
                    continue
            moved = np.linalg.norm(new_joints - joints, axis=-1)
            hit = (moved > beyond) & ~(moved <= distance[row])  # beyond, and the largest
            distance[row, hit] = moved[hit]
            displacement[row, hit] = (new_joints - joints)[hit]
    picked = np.arange(len(t)) if frames is None else np.asarray(frames, dtype=np.int64)
    return SecondSolutions(
        picked, distance, displacement, tuple(sk.joint_names), sk.units, float(chi2)
    )
