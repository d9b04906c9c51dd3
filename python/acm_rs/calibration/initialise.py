"""Initial values for the calibration, without user guesses (ACM supp. sec. 2.2).

1. Intrinsics per camera with ``cv2.calibrateCamera`` (the paper's model: radial ``k1, k2``,
   no tangential terms, ``k3 = 0``).
2. Board pose per (camera, view) with ``cv2.solvePnP`` (IPPE, planar board).
3. Camera-to-camera poses from every view two cameras share, averaged robustly (medoid
   rotation, inliers within a few median deviations, chordal mean; median translation), chained
   from the reference camera over a maximum spanning tree of the shared-view graph.
4. For boards symmetric under a half turn (checkerboards), complete detections reported in
   reversed corner order by one camera are reversed to agree with the other cameras.
5. Board → world pose of each view from the camera that saw most of its corners.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

#: Fewest corners of a view used for intrinsics / board poses.
MIN_VIEW_CORNERS = 6
#: Most views given to ``cv2.calibrateCamera`` per camera (evenly spread; it is the slow part).
MAX_INTRINSIC_VIEWS = 40
#: Fewest usable views per camera and overall.
MIN_VIEWS = 3


@dataclass
class Initialisation:
    """Initial calibration values.

    Attributes
    ----------
    cameras : numpy.ndarray, shape (n_cams, 12)
        ``[fx, fy, cx, cy, k1, k2, rx, ry, rz, tx, ty, tz]`` (world = reference camera).
    poses : numpy.ndarray, shape (n_frames, 6)
        Board → world ``[rx, ry, rz, tx, ty, tz]``; NaN for views without a usable detection.
    view_poses : numpy.ndarray, shape (n_cams, n_frames, 6)
        Board → camera pose of every usable (camera, view) detection; NaN elsewhere.
    tree : list of (int, int, int)
        Spanning-tree edges ``(parent, child, n_shared_views)`` used for chaining.
    corners : numpy.ndarray, shape (n_cams, n_frames, n_points, 2)
        The detections with a consistent corner order (see ``_unify_corner_order``).
    n_reversed : int
        Complete detections whose corner order was reversed.
    """

    cameras: np.ndarray
    poses: np.ndarray
    view_poses: np.ndarray
    tree: list[tuple[int, int, int]]
    corners: np.ndarray
    n_reversed: int = 0

    @property
    def used_frames(self) -> np.ndarray:
        """(n_frames,) bool: views with an initial board pose."""
        return np.isfinite(self.poses[:, 0])


def _rt(rvec: np.ndarray, tvec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    return cv2.Rodrigues(np.asarray(rvec, np.float64))[0], np.asarray(tvec, np.float64)


def _rvec(rot: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(rot)[0].ravel()


def usable_views(corners: np.ndarray, board_points: np.ndarray) -> np.ndarray:
    """(n_cams, n_frames) bool: views with at least ``MIN_VIEW_CORNERS`` corners that do not
    all lie on one line of the board."""
    ok = np.isfinite(corners[..., 0]) & np.isfinite(corners[..., 1])
    out = ok.sum(-1) >= MIN_VIEW_CORNERS
    xy = board_points[:, :2]
    for c, f in zip(*np.nonzero(out), strict=True):
        pts = xy[ok[c, f]]
        s = np.linalg.svd(pts - pts.mean(0), compute_uv=False)
        out[c, f] = s[-1] > 1e-6 * max(s[0], 1e-12)
    return out


def intrinsics(
    corners: np.ndarray, board_points: np.ndarray, image_size: tuple[int, int], views: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """One camera's intrinsics with OpenCV.

    Parameters
    ----------
    corners : numpy.ndarray, shape (n_frames, n_points, 2)
    board_points : numpy.ndarray, shape (n_points, 3)
    image_size : (int, int)
        ``(width, height)`` in px.
    views : numpy.ndarray, shape (n_frames,), bool
        Usable views (see :func:`usable_views`).

    Returns
    -------
    matrix : numpy.ndarray, shape (3, 3)
    dist : numpy.ndarray, shape (2,)
        ``(k1, k2)``.
    """
    import cv2

    idx = np.flatnonzero(views)
    if idx.size > MAX_INTRINSIC_VIEWS:
        idx = idx[np.linspace(0, idx.size - 1, MAX_INTRINSIC_VIEWS).round().astype(int)]
    obj, img = [], []
    for f in idx:
        ok = np.isfinite(corners[f, :, 0])
        obj.append(board_points[ok].astype(np.float32))
        img.append(corners[f, ok].astype(np.float32).reshape(-1, 1, 2))
    flags = cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K3
    _, k, dist, _, _ = cv2.calibrateCamera(
        obj, img, (int(image_size[0]), int(image_size[1])), None, None, flags=flags
    )
    return np.asarray(k, np.float64), np.asarray(dist, np.float64).ravel()[:2]


def view_poses(
    corners: np.ndarray,
    board_points: np.ndarray,
    matrix: np.ndarray,
    dist: np.ndarray,
    views: np.ndarray,
) -> np.ndarray:
    """Board → camera pose of each usable view → (n_frames, 6) ``[rvec, tvec]``, NaN elsewhere."""
    import cv2

    out = np.full((corners.shape[0], 6), np.nan)
    d5 = np.array([dist[0], dist[1], 0.0, 0.0, 0.0])
    for f in np.flatnonzero(views):
        ok = np.isfinite(corners[f, :, 0])
        obj = board_points[ok].astype(np.float64)
        img = corners[f, ok].astype(np.float64).reshape(-1, 1, 2)
        good, r, t = cv2.solvePnP(obj, img, matrix, d5, flags=cv2.SOLVEPNP_IPPE)
        if not good:
            continue
        r, t = cv2.solvePnP(obj, img, matrix, d5, r, t, True, cv2.SOLVEPNP_ITERATIVE)[1:]
        if np.all(np.isfinite(r)) and np.all(np.isfinite(t)) and t.ravel()[2] > 0:
            out[f] = np.concatenate([r.ravel(), t.ravel()])
    return out


def _rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (rad) between rotations ``a (..., 3, 3)`` and ``b (3, 3)``."""
    c = (np.einsum("...ij,ij->...", a, b) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def robust_mean_pose(rots: np.ndarray, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Robust average of rigid transforms ``(k, 3, 3)``, ``(k, 3)`` → ``(R, t, n_inliers)``.

    The medoid rotation (least summed chordal distance) seeds the inlier set: rotations within
    ``max(3 median angle, 1°)`` and translations within ``max(3 median distance, 1% of the
    median translation)`` of the medoid / median. The rotation is the chordal L2 mean of the
    inliers (SVD projection), the translation their median.
    """
    k = len(rots)
    flat = rots.reshape(k, 9)
    dist = np.linalg.norm(flat[:, None] - flat[None], axis=2).sum(1)
    med_r = rots[np.argmin(dist)]
    ang = _rotation_angle(rots, med_r)
    med_t = np.median(ts, axis=0)
    dt = np.linalg.norm(ts - med_t, axis=1)
    inl = (ang <= max(3 * np.median(ang), np.radians(1.0))) & (
        dt <= max(3 * np.median(dt), 0.01 * np.linalg.norm(med_t))
    )
    if not inl.any():
        inl = ang <= np.median(ang)
    u, _, vt = np.linalg.svd(rots[inl].mean(0))
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return rot, np.median(ts[inl], axis=0), int(inl.sum())


def chain_cameras(
    poses: np.ndarray, reference: int, names: list[str]
) -> tuple[np.ndarray, list[tuple[int, int, int]]]:
    """Camera poses relative to the reference from per-view board poses.

    Parameters
    ----------
    poses : numpy.ndarray, shape (n_cams, n_frames, 6)
        Board → camera ``[rvec, tvec]``, NaN where unknown.
    reference : int
    names : list of str
        Camera names (for error messages).

    Returns
    -------
    extrinsics : numpy.ndarray, shape (n_cams, 6)
        World (= reference camera) → camera ``[rvec, tvec]``.
    tree : list of (parent, child, n_shared)

    Raises
    ------
    ValueError
        Naming the cameras not connected to the reference by shared views.
    """
    n_cams = poses.shape[0]
    have = np.isfinite(poses[..., 0])
    shared = (have[:, None, :] & have[None, :, :]).sum(-1)
    # Prim's maximum spanning tree from the reference.
    done = np.zeros(n_cams, bool)
    done[reference] = True
    heap = [(-int(shared[reference, j]), reference, j) for j in range(n_cams) if j != reference]
    heapq.heapify(heap)
    ext = np.full((n_cams, 6), np.nan)
    ext[reference] = 0.0
    tree = []
    rot_cache = {}

    def rt(c: int, f: int) -> tuple[np.ndarray, np.ndarray]:
        if (c, f) not in rot_cache:
            rot_cache[c, f] = _rt(poses[c, f, :3], poses[c, f, 3:])
        return rot_cache[c, f]

    while heap:
        neg, a, b = heapq.heappop(heap)
        if done[b] or neg == 0:
            continue
        frames = np.flatnonzero(have[a] & have[b])
        rots, ts = [], []
        for f in frames:
            ra, ta = rt(a, f)
            rb, tb = rt(b, f)
            r = rb @ ra.T
            rots.append(r)
            ts.append(tb - r @ ta)
        r_ba, t_ba, _ = robust_mean_pose(np.array(rots), np.array(ts))
        r_a, t_a = _rt(ext[a, :3], ext[a, 3:])
        ext[b] = np.concatenate([_rvec(r_ba @ r_a), r_ba @ t_a + t_ba])
        done[b] = True
        tree.append((a, b, -neg))
        for j in range(n_cams):
            if not done[j] and shared[b, j] > 0:
                heapq.heappush(heap, (-int(shared[b, j]), b, j))
    if not done.all():
        lost = [names[i] for i in np.flatnonzero(~done)]
        raise ValueError(
            f"camera(s) {lost} share no board view (directly or through other cameras) with "
            f"the reference camera {names[reference]!r}: the camera graph is disconnected; "
            "record views where the board is seen by these and at least one connected camera"
        )
    return ext, tree


def initialise(
    corners: np.ndarray,
    board_points: np.ndarray,
    image_sizes: np.ndarray,
    reference: int,
    names: list[str],
    known_intrinsics: list[tuple[np.ndarray, np.ndarray] | None] | None = None,
) -> Initialisation:
    """Initial cameras and board poses (module docs).

    Parameters
    ----------
    corners : numpy.ndarray, shape (n_cams, n_frames, n_points, 2)
        Pixels, NaN = not detected.
    board_points : numpy.ndarray, shape (n_points, 3)
    image_sizes : numpy.ndarray, shape (n_cams, 2)
        ``(width, height)`` px.
    reference : int
    names : list of str
    known_intrinsics : list of (matrix (3, 3), (k1, k2)) or None, optional
        Per camera: use these intrinsics instead of estimating them.

    Raises
    ------
    ValueError
        A camera with fewer than ``MIN_VIEWS`` usable views (naming it), fewer than
        ``MIN_VIEWS`` usable views overall, or a disconnected camera graph.
    """
    n_cams, n_frames = corners.shape[:2]
    usable = usable_views(corners, board_points)
    counts = usable.sum(1)
    for c in range(n_cams):
        if counts[c] == 0:
            seen = int(np.any(np.isfinite(corners[c, ..., 0]), axis=1).sum())
            raise ValueError(
                f"camera {names[c]!r} never sees the board"
                + (
                    f" (corners in {seen} views, but none with >= {MIN_VIEW_CORNERS} corners "
                    "off a single line)"
                    if seen
                    else ""
                )
            )
    if usable.any(0).sum() < MIN_VIEWS:
        raise ValueError(
            f"only {int(usable.any(0).sum())} usable board views (need >= {MIN_VIEWS} views "
            f"with >= {MIN_VIEW_CORNERS} corners)"
        )
    cams = np.zeros((n_cams, 12))
    vp = np.full((n_cams, n_frames, 6), np.nan)
    for c in range(n_cams):
        known = known_intrinsics[c] if known_intrinsics is not None else None
        if known is None:
            if counts[c] < MIN_VIEWS:
                raise ValueError(
                    f"camera {names[c]!r} sees the board in only {counts[c]} usable views "
                    f"(need >= {MIN_VIEWS} to estimate its intrinsics)"
                )
            k, d = intrinsics(corners[c], board_points, tuple(image_sizes[c]), usable[c])
        else:
            k, d = np.asarray(known[0], float), np.asarray(known[1], float)[:2]
        if not (k[0, 0] > 0 and k[1, 1] > 0 and np.all(np.isfinite(k)) and np.all(np.isfinite(d))):
            raise ValueError(f"camera {names[c]!r}: intrinsic estimation failed (K = {k})")
        cams[c, :6] = [k[0, 0], k[1, 1], k[0, 2], k[1, 2], d[0], d[1]]
        vp[c] = view_poses(corners[c], board_points, k, d, usable[c])
    ext, tree = chain_cameras(vp, reference, names)
    corners, n_reversed = _unify_corner_order(corners, board_points, cams, ext, vp, usable)
    if n_reversed:
        for c in range(n_cams):
            k, d = _matrix(cams[c]), cams[c, 4:6]
            vp[c] = view_poses(corners[c], board_points, k, d, usable[c])
        ext, tree = chain_cameras(vp, reference, names)
    cams[:, 6:] = ext
    # Board → world from the camera with most corners in each view.
    n_corners = np.where(np.isfinite(vp[..., 0]), np.isfinite(corners[..., 0]).sum(-1), -1)
    poses = np.full((n_frames, 6), np.nan)
    for f in range(n_frames):
        c = int(np.argmax(n_corners[:, f]))
        if n_corners[c, f] < 0:
            continue
        rc, tc = _rt(ext[c, :3], ext[c, 3:])
        rb, tb = _rt(vp[c, f, :3], vp[c, f, 3:])
        poses[f] = np.concatenate([_rvec(rc.T @ rb), rc.T @ (tb - tc)])
    if np.isfinite(poses[:, 0]).sum() < MIN_VIEWS:
        raise ValueError(
            f"only {int(np.isfinite(poses[:, 0]).sum())} board views have a pose (need >= "
            f"{MIN_VIEWS})"
        )
    return Initialisation(cams, poses, vp, tree, corners, n_reversed)


def _matrix(cam12: np.ndarray) -> np.ndarray:
    return np.array([[cam12[0], 0.0, cam12[2]], [0.0, cam12[1], cam12[3]], [0.0, 0.0, 1.0]])


def _reversed(corners, board_points, cams, ext, vp, ref: int, c: int, f: int) -> bool:
    """Whether camera c's detection of view f matches the pose seen by camera ref much better
    in reversed corner order."""
    import cv2

    r_ref, t_ref = _rt(ext[ref, :3], ext[ref, 3:])
    r_b, t_b = _rt(vp[ref, f, :3], vp[ref, f, 3:])
    r_w, t_w = r_ref.T @ r_b, r_ref.T @ (t_b - t_ref)  # board -> world
    r_c, t_c = _rt(ext[c, :3], ext[c, 3:])
    d5 = np.array([cams[c, 4], cams[c, 5], 0.0, 0.0, 0.0])
    pred = cv2.projectPoints(board_points, _rvec(r_c @ r_w), r_c @ t_w + t_c, _matrix(cams[c]), d5)[
        0
    ].reshape(-1, 2)
    fwd = np.median(np.linalg.norm(corners[c, f] - pred, axis=1))
    rev = np.median(np.linalg.norm(corners[c, f, ::-1] - pred, axis=1))
    return bool(fwd > 5.0 and rev * 3 < fwd)


def _unify_corner_order(corners, board_points, cams, ext, vp, usable):
    """Make the corner order of complete detections of a 180°-symmetric board consistent
    across the cameras of each view.

    OpenCV may report a checkerboard whose pattern is symmetric under a half turn in either
    order. For each view, the board pose seen by one camera is projected into the others
    (with the chained extrinsics); a complete detection that matches that projection much
    better in reversed order (median error at least 3× smaller and the forward error above
    5 px) is reversed. The reference camera of the view is the one needing fewest reversals.
    Returns ``(corners, n_reversed)``.
    """
    b2 = board_points[:, :2]
    centre = b2.mean(0)
    scale = max(np.ptp(b2), 1e-300)
    if np.abs(b2[::-1] - (2 * centre - b2)).max() > 1e-9 * scale:
        return corners, 0
    complete = np.isfinite(corners[..., 0]).all(-1)
    have = np.isfinite(vp[..., 0])
    out = corners
    n = 0
    for f in np.flatnonzero((have & complete).sum(0) >= 2):
        cands = np.flatnonzero(have[:, f] & complete[:, f])
        # Try every camera's order as the reference; keep the one needing fewest reversals.
        best: list[int] | None = None
        for ref in cands:
            flips = [
                c
                for c in cands
                if c != ref and _reversed(corners, board_points, cams, ext, vp, ref, c, f)
            ]
            if best is None or len(flips) < len(best):
                best = flips
        for c in best or []:
            if out is corners:
                out = corners.copy()
            out[c, f] = corners[c, f, ::-1]
            n += 1
    return out, n
