"""``calibrate``: initialisation + refinement of eq. 7 (ACM supp. sec. 2.2).

The refinement minimises eq. 7 with ``scipy.optimize.least_squares(method="trf",
x_scale="jac")``; residuals and the exact sparse Jacobian (CSR, fixed pattern) come from Rust
(``NativeCalibration``, ``src/calibration.rs``). For conditioning (the role of supp. sec. 3.3's
normalisation) board poses are refined about the board's centroid and the solver works in
variables ``z`` with ``x = M z`` (:func:`schur_preconditioner`); residuals stay in pixels so
that costs and tolerances are readable.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Mapping, Sequence

import numpy as np

from .. import _native
from ..camera import Camera, CameraRig
from ..rotation import rodrigues
from .initialise import initialise
from .result import CalibrationResult

#: Order of the 13 per-camera parameters of the refinement (``skew``: MATLAB's skew in px,
#: held at its initial value unless ``calibrate(fix_skew=False)``).
CAMERA_PARAMS: tuple[str, ...] = (
    "fx", "fy", "cx", "cy", "k1", "k2", "rx", "ry", "rz", "tx", "ty", "tz", "skew",
)  # fmt: skip
_N_CAM = len(CAMERA_PARAMS)
_SKEW = CAMERA_PARAMS.index("skew")
PARAM_GROUPS: dict[str, tuple[str, ...]] = {
    "intrinsics": CAMERA_PARAMS[:6] + ("skew",),
    "focal": ("fx", "fy"),
    "principal_point": ("cx", "cy"),
    "distortion": ("k1", "k2"),
    "r": ("rx", "ry", "rz"),
    "t": ("tx", "ty", "tz"),
    "pose": CAMERA_PARAMS[6:12],
}
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


def _names_mask(names: str | Sequence[str]) -> np.ndarray:
    if isinstance(names, str):
        names = [names]
    mask = np.zeros(_N_CAM, bool)
    for n in names:
        group = PARAM_GROUPS.get(n, (n,))
        for g in group:
            if g not in CAMERA_PARAMS:
                raise ValueError(
                    f"unknown parameter {n!r} in fix; use {list(CAMERA_PARAMS)} or groups "
                    f"{list(PARAM_GROUPS)}"
                )
            mask[CAMERA_PARAMS.index(g)] = True
    return mask


def fixed_mask(fix, n_cams: int, names: list[str]) -> np.ndarray:
    """Parse ``fix`` into an ``(n_cams, 13)`` boolean mask (see :func:`calibrate`); a boolean
    ``(n_cams, 12)`` mask (without the skew column) leaves the skew to ``fix_skew``."""
    if fix is None:
        return np.zeros((n_cams, _N_CAM), bool)
    if isinstance(fix, np.ndarray) and fix.dtype == bool:
        if fix.shape == (n_cams, _N_CAM - 1):
            return np.pad(fix, ((0, 0), (0, 1)))
        if fix.shape != (n_cams, _N_CAM):
            raise ValueError(
                f"a boolean fix mask must have shape ({n_cams}, {_N_CAM}), got {fix.shape}"
            )
        return fix.copy()
    if isinstance(fix, Mapping):
        out = np.zeros((n_cams, _N_CAM), bool)
        for key, val in fix.items():
            if isinstance(key, str):
                if key not in names:
                    raise ValueError(f"fix names camera {key!r}, cameras are {names}")
                c = names.index(key)
            else:
                c = int(key)
                if not 0 <= c < n_cams:
                    raise ValueError(f"fix names camera {c}, have {n_cams} cameras")
            out[c] |= _names_mask(val)
        return out
    return np.tile(_names_mask(fix), (n_cams, 1))


def _check_inputs(corners, board_points, image_size):
    c = np.asarray(corners, dtype=np.float64)
    if c.ndim != 4 or c.shape[-1] != 2:
        raise ValueError(f"corners must have shape (n_cams, n_frames, n_points, 2), got {c.shape}")
    if np.isinf(c).any():
        idx = np.argwhere(np.isinf(c))[0]
        raise ValueError(
            f"corners contain infinity (camera {idx[0]}, frame {idx[1]}, point {idx[2]}); "
            "use NaN for undetected corners"
        )
    half = np.isnan(c[..., 0]) != np.isnan(c[..., 1])
    if half.any():
        idx = np.argwhere(half)[0]
        raise ValueError(
            f"corners: camera {idx[0]}, frame {idx[1]}, point {idx[2]} has one NaN coordinate "
            "(an undetected corner must be NaN in both)"
        )
    b = np.asarray(board_points, dtype=np.float64)
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"board_points must have shape (n_points, 3), got {b.shape}")
    if b.shape[0] != c.shape[2]:
        raise ValueError(
            f"board_points has {b.shape[0]} points but corners has {c.shape[2]} per view"
        )
    if not np.all(np.isfinite(b)):
        raise ValueError("board_points must be finite")
    if b.shape[0] < 4:
        raise ValueError(f"a board needs at least 4 points, got {b.shape[0]}")
    if np.ptp(b[:, 2]) > 1e-9 * max(np.ptp(b[:, :2]), 1e-300):
        raise ValueError("board_points must lie in the plane z = const (a planar board)")
    s = np.asarray(image_size, dtype=np.float64)
    n_cams = c.shape[0]
    if s.shape == (2,):
        s = np.tile(s, (n_cams, 1))
    if s.shape != (n_cams, 2):
        raise ValueError(f"image_size must be (w, h) or have shape ({n_cams}, 2), got {s.shape}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise ValueError(f"image sizes must be positive, got {s.tolist()}")
    neg = c < -0.5
    if neg.any():
        idx = np.argwhere(neg)[0]
        raise ValueError(
            f"corners: camera {idx[0]}, frame {idx[1]}, point {idx[2]} is at "
            f"{c[tuple(idx[:3])].tolist()} px, outside the image; undetected corners must be "
            "NaN (not -1): corners = np.where(corners < 0, np.nan, corners)"
        )
    for cam in range(n_cams):
        w, h = s[cam]
        with np.errstate(invalid="ignore"):
            out = (c[cam, ..., 0] > w + 0.5) | (c[cam, ..., 1] > h + 0.5)
        if out.any():
            f, q = np.argwhere(out)[0]
            swapped = bool(np.nanmax(c[cam, ..., 0]) <= h and np.nanmax(c[cam, ..., 1]) <= w)
            raise ValueError(
                f"corners: camera {cam}, frame {f}, point {q} at {c[cam, f, q].tolist()} px lies "
                f"outside its image_size {s[cam].tolist()} (width, height)"
                + ("; the size looks swapped: give (width, height)" if swapped else "")
            )
    return np.ascontiguousarray(c), np.ascontiguousarray(b), s.round().astype(np.int64)


def calibrate(
    corners: np.ndarray,
    board_points: np.ndarray,
    image_size,
    reference_camera: int = 0,
    *,
    loss: str = "linear",
    fix=None,
    camera_names: Sequence[str] | None = None,
    f_scale: float = 1.0,
    intrinsics: CameraRig | Sequence[Camera | None] | None = None,
    max_nfev: int | None = None,
    fix_skew: bool = True,
) -> CalibrationResult:
    """Calibrate a multi-camera rig from board detections (ACM supp. eq. 7).

    Parameters
    ----------
    corners : array_like, shape (n_cams, n_frames, n_points, 2)
        Detected board corners in pixels; NaN where a corner was not detected. Frames are
        synchronous board views shared by all cameras.
    board_points : array_like, shape (n_points, 3)
        Board corners in board units (e.g. mm), planar with ``z = 0``. The calibrated
        translations come out in these units.
    image_size : (int, int) or array_like, shape (n_cams, 2)
        Image ``(width, height)`` in px, for all cameras or per camera.
    reference_camera : int
        Camera defining the world frame (its ``r, t`` are zero and fixed).
    loss : {"linear", "soft_l1", "huber", "cauchy", "arctan"}
        Robust loss of ``least_squares``; ``f_scale`` (px) is the inlier scale.
    fix : None, sequence of str, dict or bool array (n_cams, 13), optional
        Parameters held at their initial values: names from ``fx, fy, cx, cy, k1, k2, rx, ry,
        rz, tx, ty, tz, skew`` or groups ``intrinsics`` (with ``skew``), ``focal``,
        ``principal_point``, ``distortion``, ``r``, ``t``, ``pose``; a sequence applies to
        every camera, a dict maps camera index or name to names.
    camera_names : sequence of str, optional
        Default ``cam_0, cam_1, ...``.
    f_scale : float
        Soft margin (px) of the robust loss.
    intrinsics : CameraRig or sequence of (Camera or None), optional
        Known intrinsics per camera (matrix with its skew, and ``k1, k2``; ``p1 = p2 = k3 = 0``
        required), used instead of OpenCV's estimate; combine with ``fix="intrinsics"`` to
        keep them.
    max_nfev : int, optional
        Most function evaluations of the refinement (default: scipy's).
    fix_skew : bool
        Hold every camera's skew at its initial value (0, or the known intrinsics' skew), as
        OpenCV's calibration does (default). ``False`` estimates it (MATLAB's
        ``EstimateSkew``) unless ``fix`` names it; a skew is rarely identifiable from board
        views, so estimate it only with many views tilted in every direction.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    ValueError
        Mismatched shapes, infinite corners, a camera that never sees the board, fewer than 3
        usable views, a disconnected camera graph, an unknown loss or fix name, or a refinement
        that ends with board corners behind a camera.
    """
    from scipy.optimize import least_squares
    from scipy.sparse import csr_matrix
    from scipy.sparse.linalg import spsolve
    from threadpoolctl import threadpool_limits

    c, b, sizes = _check_inputs(corners, board_points, image_size)
    n_cams, n_frames, n_points = c.shape[:3]
    names = [f"cam_{i}" for i in range(n_cams)] if camera_names is None else list(camera_names)
    if len(names) != n_cams or len(set(names)) != n_cams:
        raise ValueError(f"camera_names must be {n_cams} unique names, got {names}")
    if not 0 <= int(reference_camera) < n_cams:
        raise ValueError(f"reference_camera {reference_camera} out of range for {n_cams} cameras")
    ref = int(reference_camera)
    if loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
    if not f_scale > 0:
        raise ValueError(f"f_scale must be > 0, got {f_scale}")
    asked = fixed_mask(fix, n_cams, names)  # what the caller fixed (reported in info["fixed"])
    fixed = asked.copy()
    if fix_skew:
        fixed[:, _SKEW] = True
    known = _known_intrinsics(intrinsics, n_cams)
    skew0 = np.zeros(n_cams)
    for i, k in enumerate(known or []):
        if k is not None:  # the skew starts the refinement; OpenCV's initialisation has none
            skew0[i], k[0][0, 1] = k[0][0, 1], 0.0

    t0 = time.perf_counter()
    init = initialise(c, b, sizes, ref, names, known)
    t1 = time.perf_counter()

    used = init.used_frames
    if init.n_reversed:
        warnings.warn(
            f"{init.n_reversed} checkerboard detections were in reversed corner order "
            "(a half-turn-symmetric board) and were reordered",
            stacklevel=2,
        )
    c = init.corners
    c_used = c.copy()
    c_used[:, ~used] = np.nan
    # Board poses are refined about the board's centroid (not its first corner): same
    # residuals, but rotation and translation of a view decouple, which cuts the LSMR
    # iterations of the trust-region steps several-fold.
    centroid = b.mean(axis=0)
    poses0 = np.where(used[:, None], init.poses, 0.0)
    poses0[:, 3:] += np.einsum("fij,j->fi", rodrigues(poses0[:, :3]), centroid)
    # initialise gives (n_cams, 12) cameras; the refinement adds the skew (src/calibration.rs)
    cams0 = np.concatenate([init.cameras, skew0[:, None]], axis=1)
    params0 = np.concatenate([cams0.ravel(), poses0.ravel()])
    mask = np.concatenate([fixed.ravel(), np.zeros(6 * n_frames, bool)])
    prob = _native.NativeCalibration(b - centroid, c_used, ref, params0, mask)
    shape = (2 * prob.n_observations, prob.n_free)
    indptr, indices = prob.indptr, prob.indices
    free = prob.free_indices
    x0 = params0[free]

    def jac_x(x: np.ndarray) -> csr_matrix:
        return csr_matrix((prob.jacobian_data(x), indices, indptr), shape=shape)

    r0 = prob.residuals(x0)[0]
    # Solve in z with x = M z (a fixed invertible linear change of variables, see
    # schur_preconditioner): the exact Jacobian in z is J(x) M.
    m = schur_preconditioner(jac_x(x0), int(np.sum(free < _N_CAM * n_cams)), free, n_cams)
    z0 = spsolve(m.tocsc(), x0)

    def fun(z: np.ndarray) -> np.ndarray:
        return prob.residuals(m @ z)[0]

    def jac(z: np.ndarray) -> csr_matrix:
        return (jac_x(m @ z) @ m).tocsr()

    # One BLAS thread: LSMR's vector operations are far too small to gain from threads, and
    # spinning BLAS threads next to rayon's slow the solve down several-fold on small machines.
    with threadpool_limits(limits=1, user_api="blas"):
        sol = least_squares(
            fun, z0, jac=jac, method="trf", x_scale="jac", loss=loss, f_scale=f_scale,
            tr_solver="lsmr", tr_options={"atol": 1e-10, "btol": 1e-10},
            ftol=1e-10, xtol=1e-10, gtol=1e-10, max_nfev=max_nfev,
        )  # fmt: skip
    t2 = time.perf_counter()
    if sol.status == 0:
        warnings.warn(
            f"calibration refinement stopped after {sol.nfev} evaluations without converging",
            stacklevel=2,
        )
    x_opt = m @ sol.x
    full = prob.full_params(x_opt)
    res_flat, behind = prob.residuals(x_opt)
    if behind:
        raise ValueError(
            f"refinement ended with {behind} board corners behind their camera: the "
            "initialisation was wrong (check the board spec and for mirrored detections)"
        )
    residuals = np.full((n_cams * n_frames * n_points, 2), np.nan)
    residuals[prob.observation_index] = res_flat.reshape(-1, 2)
    residuals = residuals.reshape(n_cams, n_frames, n_points, 2)
    cams13 = full[: _N_CAM * n_cams].reshape(n_cams, _N_CAM)
    poses = full[_N_CAM * n_cams :].reshape(n_frames, 6).copy()
    poses[:, 3:] -= np.einsum("fij,j->fi", rodrigues(poses[:, :3]), centroid)
    poses[~used] = np.nan
    rig = CameraRig(
        Camera(
            [[p[0], p[_SKEW], p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]],
            [p[4], p[5]],
            p[6:9],
            p[9:12],
            size=(int(sizes[i, 0]), int(sizes[i, 1])),
            name=names[i],
        )
        for i, p in enumerate(cams13)
    )
    return CalibrationResult(
        rig=rig,
        board_rvecs=poses[:, :3],
        board_tvecs=poses[:, 3:],
        residuals=residuals,
        corners=c,
        board_points=b,
        used_frames=used,
        reference_camera=ref,
        initial_rms=float(np.sqrt(np.mean(r0.reshape(-1, 2) ** 2) * 2)),
        info={
            "loss": loss,
            "f_scale": float(f_scale),
            "n_free_parameters": int(prob.n_free),
            "n_reversed_detections": int(init.n_reversed),
            "jacobian_nnz": int(prob.nnz),
            "nfev": int(sol.nfev),
            "njev": int(sol.njev or 0),
            "status": int(sol.status),
            "message": str(sol.message),
            "seconds_init": t1 - t0,
            "seconds_refine": t2 - t1,
            "spanning_tree": [
                {"parent": names[a], "child": names[c_], "shared_views": int(n)}
                for a, c_, n in init.tree
            ],
            "fixed": {
                names[i]: [CAMERA_PARAMS[k] for k in np.flatnonzero(asked[i])]
                for i in range(n_cams)
                if asked[i].any()
            },
            "fix_skew": bool(fix_skew),
        },
    )


def _sym_inverse_sqrt_factor(g: np.ndarray) -> np.ndarray:
    """``L^{-T}`` of the Cholesky factor of a small SPD matrix (so that ``P^T g P = I``),
    regularised by ``1e-12 trace`` (an eigen-decomposition fallback for a singular block)."""
    g = g + 1e-12 * np.trace(g) * np.eye(len(g))
    try:
        return np.linalg.inv(np.linalg.cholesky(g)).T
    except np.linalg.LinAlgError:
        w, v = np.linalg.eigh(g)
        return v / np.sqrt(np.maximum(w, 1e-12 * max(w.max(), 1e-300)))


def schur_preconditioner(jac0, n_cam_cols: int, free: np.ndarray, n_cams: int):
    """Linear change of variables ``x = M z`` that whitens the Gauss-Newton matrix at x0.

    The columns are the camera parameters (first ``n_cam_cols``) and the board-view poses
    (groups of up to 6, one per view). With ``G = J0^T J0``, each view's pose is shifted by
    ``K_f = -G_ff^{-1} G_fc`` times the camera change (so camera columns of ``J0 M`` are
    orthogonal to every pose column: the Schur complement ``S`` of the pose blocks), and each
    camera's block of ``S`` and each pose block are whitened by their Cholesky factors. Then
    ``(J0 M)^T (J0 M)`` is the identity up to the camera-camera coupling, and LSMR inside the
    trust-region solver needs a few iterations per step instead of hundreds. The problem is
    unchanged (an invertible linear map); this is the role of the normalisation of supp.
    sec. 3.3 here.

    Parameters
    ----------
    jac0 : scipy.sparse.csr_matrix, shape (n_res, n_free)
        Exact Jacobian at the initial values.
    n_cam_cols : int
    free : numpy.ndarray, shape (n_free,)
        Full-layout indices of the free parameters (ascending).
    n_cams : int
        Number of cameras (the board views' block starts at ``13 n_cams``).

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n_free, n_free)
    """
    from scipy.sparse import coo_matrix

    n = jac0.shape[1]
    nc = n_cam_cols
    g = (jac0.T @ jac0).tocsr()
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []

    def add_block(r0: int, c0: int, block: np.ndarray) -> None:
        r, c = np.meshgrid(np.arange(block.shape[0]) + r0, np.arange(block.shape[1]) + c0)
        rows.append(r.T.ravel())
        cols.append(c.T.ravel())
        vals.append(block.ravel())

    s = g[:nc, :nc].toarray()
    g_pc = g[nc:, :nc].toarray()
    view = (free[nc:] - _N_CAM * n_cams) // 6  # the pose block of each column
    starts = np.flatnonzero(np.r_[True, view[1:] != view[:-1]])
    ends = np.r_[starts[1:], len(view)]
    k_rows = []
    for a, b in zip(starts, ends, strict=True):
        gff = g[nc + a : nc + b, nc + a : nc + b].toarray()
        gff = gff + 1e-12 * np.trace(gff) * np.eye(b - a)
        k_f = -np.linalg.lstsq(gff, g_pc[a:b], rcond=None)[0] if nc else None
        if nc:
            s += g_pc[a:b].T @ k_f
            k_rows.append(k_f)
        add_block(nc + a, nc + a, _sym_inverse_sqrt_factor(gff))
    if nc:
        # Whiten each camera's diagonal block of S (not all of S: a dense factor would mix
        # cameras and make every Jacobian row dense); pose rows of M's camera columns: K B_c.
        b_c = np.zeros((nc, nc))
        cam = free[:nc] // _N_CAM
        for c in np.unique(cam):
            idx = np.flatnonzero(cam == c)
            b_c[np.ix_(idx, idx)] = _sym_inverse_sqrt_factor(s[np.ix_(idx, idx)])
        add_block(0, 0, b_c)
        add_block(nc, 0, np.vstack(k_rows) @ b_c)
    m = coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    ).tocsr()
    m.eliminate_zeros()
    return m


def _known_intrinsics(intrinsics, n_cams: int):
    if intrinsics is None:
        return None
    cams = list(intrinsics)
    if len(cams) != n_cams:
        raise ValueError(f"intrinsics: {len(cams)} cameras given for {n_cams}")
    out = []
    for i, cam in enumerate(cams):
        if cam is None:
            out.append(None)
            continue
        if not isinstance(cam, Camera):
            raise ValueError(f"intrinsics[{i}] must be a Camera or None")
        d = cam.dist
        if np.any(np.abs(d[2:]) > 1e-12):
            raise ValueError(
                f"intrinsics[{i}] has p1, p2, k3 = {d[2:].tolist()}; the calibration model has "
                "k1, k2 only (ACM supp. eq. 5)"
            )
        out.append((cam.matrix, d[:2]))
    return out
