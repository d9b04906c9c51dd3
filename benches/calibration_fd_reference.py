"""Pure NumPy/SciPy reference of the calibration refinement (ACM supp. eq. 7) for benchmarks.

Same parameter layout and residuals as ``src/calibration.rs`` (per camera ``[fx, fy, cx, cy,
k1, k2, r, t]``, per board view ``[r, t]``), written with NumPy; the Jacobian is left to
``least_squares``' finite differences with the known sparsity pattern (``jac_sparsity``), the
way aniposelib does it.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix


def rodrigues(r: np.ndarray) -> np.ndarray:
    """(n, 3) Rodrigues vectors → (n, 3, 3) rotation matrices."""
    theta = np.linalg.norm(r, axis=1)
    safe = np.where(theta > 1e-12, theta, 1.0)
    k = r / safe[:, None]
    kx = np.zeros((len(r), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    out = np.eye(3) + s * kx + (1 - c) * kx @ kx
    out[theta <= 1e-12] = np.eye(3)
    return out


class Problem:
    """Residuals of eq. 7 over the free parameters (reference camera's r, t fixed)."""

    def __init__(self, board, corners, reference, params0):
        n_cams, n_frames, _, _ = corners.shape
        self.n_cams, self.n_frames = n_cams, n_frames
        ok = np.isfinite(corners[..., 0])
        self.cam, self.frame, self.point = np.nonzero(ok)
        self.obs = corners[ok]
        self.board = board
        n_full = 12 * n_cams + 6 * n_frames
        fixed = np.zeros(n_full, bool)
        fixed[12 * reference + 6 : 12 * reference + 12] = True
        seen = np.zeros(n_frames, bool)
        seen[self.frame] = True
        for f in np.flatnonzero(~seen):
            fixed[12 * n_cams + 6 * f : 12 * n_cams + 6 * f + 6] = True
        self.free = np.flatnonzero(~fixed)
        self.base = params0.copy()

    def full(self, x):
        p = self.base.copy()
        p[self.free] = x
        return p

    def residuals(self, x):
        p = self.full(x)
        cams = p[: 12 * self.n_cams].reshape(-1, 12)
        poses = p[12 * self.n_cams :].reshape(-1, 6)
        rb = rodrigues(poses[:, :3])
        xw = np.einsum("nij,nj->ni", rb[self.frame], self.board[self.point]) + poses[self.frame, 3:]
        rc = rodrigues(cams[:, 6:9])
        c = cams[self.cam]
        xc = np.einsum("nij,nj->ni", rc[self.cam], xw) + c[:, 9:12]
        xn, yn = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (c[:, 4] + r2 * c[:, 5])
        u = c[:, 0] * xn * radial + c[:, 2]
        v = c[:, 1] * yn * radial + c[:, 3]
        return (np.stack([u, v], 1) - self.obs).ravel()

    def sparsity(self):
        col = -np.ones(len(self.base), int)
        col[self.free] = np.arange(len(self.free))
        s = lil_matrix((2 * len(self.obs), len(self.free)), dtype=int)
        for k, (c, f) in enumerate(zip(self.cam, self.frame, strict=True)):
            cols = np.concatenate([col[12 * c : 12 * c + 12], col[12 * self.n_cams + 6 * f :][:6]])
            cols = cols[cols >= 0]
            s[2 * k, cols] = 1
            s[2 * k + 1, cols] = 1
        return s.tocsr()


def refine(board, corners, reference, params0, **kw):
    """``least_squares`` with finite differences → (full parameters, OptimizeResult)."""
    prob = Problem(board, corners, reference, params0)
    sol = least_squares(
        prob.residuals, params0[prob.free], jac="2-point", jac_sparsity=prob.sparsity(),
        method="trf", x_scale="jac", **kw,
    )  # fmt: skip
    return prob.full(sol.x), sol
