# Type stubs of the private native module built from src/python/ (pyo3).
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

N_CAMERA_PARAMS: int
DEFAULT_OVERRELAX: float
MAX_OVERRELAX: float

class AcmNumericalError(ArithmeticError): ...

def rodrigues(r: F64) -> F64: ...
def rodrigues_log(mats: F64) -> F64: ...
def rodrigues_jacobian(r: F64) -> F64: ...
def project(params: F64, points: F64) -> tuple[F64, NDArray[np.bool_]]: ...
def project_jacobian(params: F64, points: F64) -> tuple[F64, F64, F64]: ...

class NativeSkeleton:
    def __init__(
        self, parents: I64, rest_frames: F64, lengths: F64, marker_joints: I64, offsets: F64
    ) -> None: ...
    @staticmethod
    def from_rest_pose(
        parents: I64,
        rest_joints: F64,
        marker_joints: I64,
        marker_rest: F64,
        up: F64,
        rest_frames: F64 | None = None,
    ) -> NativeSkeleton: ...
    @property
    def n_bones(self) -> int: ...
    @property
    def rest_frames(self) -> F64: ...
    @property
    def lengths(self) -> F64: ...
    @property
    def offsets(self) -> F64: ...
    @property
    def bones(self) -> I64: ...
    @property
    def marker_bones(self) -> I64: ...
    def bone_links(self) -> NDArray[np.bool_]: ...
    @property
    def link_order(self) -> I64: ...
    @property
    def tree_links(self) -> bool: ...
    def with_links(
        self, links: NDArray[np.bool_] | None, order: I64 | None = None
    ) -> NativeSkeleton: ...
    def forward(
        self, t: F64, r: F64, lengths: F64 | None = None, offsets: F64 | None = None
    ) -> tuple[F64, F64]: ...
    def forward_jacobian(
        self, t: F64, r: F64, lengths: F64 | None = None, offsets: F64 | None = None
    ) -> tuple[F64, F64, F64, F64, F64]: ...
    def project_poses(self, params: F64, t: F64, r: F64) -> F64: ...

class NativeSymmetry:
    def __init__(
        self, n_bones: int, bone_pairs: I64, n_markers: int, marker_pairs: I64
    ) -> None: ...
    @property
    def n_reduced_bones(self) -> int: ...
    @property
    def n_reduced_markers(self) -> int: ...
    def expand_lengths(self, l: F64) -> F64: ...
    def expand_offsets(self, v: F64) -> F64: ...
    def reduce_lengths(self, l: F64) -> F64: ...
    def reduce_offsets(self, v: F64) -> F64: ...
    def reduce_length_grad(self, g: F64) -> F64: ...
    def reduce_offset_grad(self, g: F64) -> F64: ...

class NativeStateMap:
    def __init__(
        self,
        lower: F64,
        upper: F64,
        norm: tuple[float, float, float, float],
        enforce: bool,
        stretch: I64 | None = None,
    ) -> None: ...
    @property
    def free_indices(self) -> I64: ...
    @property
    def n_state(self) -> int: ...
    def to_pose(self, z: F64) -> tuple[F64, F64]: ...
    def to_state(self, pose: F64) -> F64: ...
    def emission(self, skeleton: NativeSkeleton, params: F64, states: F64) -> F64: ...

class NativeLearning:
    def __init__(
        self,
        skeleton: NativeSkeleton,
        params: F64,
        labels: F64,
        lower: F64,
        upper: F64,
        norm: tuple[float, float, float, float],
        bone_pairs: I64,
        marker_pairs: I64,
        length_scale: float,
        lengths: F64 | None = None,
        offsets: F64 | None = None,
    ) -> None: ...
    @property
    def n_params(self) -> int: ...
    @property
    def n_skeleton_params(self) -> int: ...
    @property
    def n_labels(self) -> int: ...
    @property
    def n_frames(self) -> int: ...
    def value_and_grad(self, x: F64) -> tuple[float, F64]: ...
    def gauss_newton_diagonal(self, x: F64) -> F64: ...
    def fit_poses_lm(
        self, x: F64, lower: F64, upper: F64, max_iter: int
    ) -> tuple[F64, list[int]]: ...
    def fit_poses_elastic(
        self,
        x: F64,
        lower: F64,
        upper: F64,
        stretch_bones: I64,
        stretch_sd: F64,
        stretch0: F64,
        noise_px: float,
        max_iter: int,
    ) -> tuple[F64, F64, F64, F64, F64, list[int], list[int]]: ...
    def fit_full_lm(
        self,
        x: F64,
        lower: F64,
        upper: F64,
        max_iter: int,
        tol: float,
        prior_centre: F64 | None = None,
        prior_weight: F64 | None = None,
    ) -> tuple[F64, int, float, float, str]: ...
    def residuals(self, x: F64) -> tuple[F64, F64, F64, F64]: ...

def gapfill_fill(
    x: F64,
    method: str,
    gamma: float,
    criterion: str,
    dim: int | None,
    r: float | None,
    em_iters: int,
    paper_q: bool,
    subspace_iters: int,
    min_complete: int,
    combine: str,
    short_gap: int | None,
    keep_original: bool,
    want_std: bool,
    memo_tol: float,
    seed: int,
    window: int | None = None,
) -> tuple[F64, F64 | None, dict[str, object]]: ...
def gapfill_format_rows(x: F64, sep: str, nan_text: str) -> list[str]: ...

GAPFILL_AUTO_WINDOW: int

class NativeCalibration:
    """Eq. 7 residuals and exact CSR Jacobian (layout in src/calibration.rs)."""

    def __init__(
        self,
        board: F64,
        corners: F64,
        reference: int,
        params0: F64,
        fixed: NDArray[np.bool_],
    ) -> None: ...
    @property
    def n_free(self) -> int: ...
    @property
    def n_full(self) -> int: ...
    @property
    def n_observations(self) -> int: ...
    @property
    def nnz(self) -> int: ...
    @property
    def free_indices(self) -> I64: ...
    @property
    def observation_index(self) -> I64: ...
    @property
    def indptr(self) -> NDArray[np.int32]: ...
    @property
    def indices(self) -> NDArray[np.int32]: ...
    def full_params(self, x: F64) -> F64: ...
    def residuals(self, x: F64) -> tuple[F64, int]: ...
    def jacobian_data(self, x: F64) -> F64: ...

class NativeBufferPool:
    """Covariance buffers handed from dropped trackers to new ones (src/tracking/buffers.rs)."""

    def __init__(self, max_buffers: int = 4) -> None: ...
    def __len__(self) -> int: ...

class NativeTracker:
    """UKF / unscented RTS smoother / EM of ACM supp. sec. 4 (see src/tracking/)."""

    def __init__(
        self,
        skeleton: NativeSkeleton,
        params: F64,
        lower: F64,
        upper: F64,
        norm: tuple[float, float, float, float],
        joint_limits: bool,
        x: F64,
        relinearize: int = 10,
        order: int = 1,
        threads: int = 0,
        stretch: I64 | None = None,
        buffers: NativeBufferPool | None = None,
    ) -> None: ...
    @property
    def n_state(self) -> int: ...
    @property
    def n_frames(self) -> int: ...
    def run_em(
        self,
        mu0: F64,
        v0: F64,
        vz: F64,
        vx: F64,
        max_iter: int,
        tol: float,
        gate: float | None = None,
        callback: Callable[[int, float, float, dict[str, int]], bool | None] | None = None,
        ll_tol: float | None = None,
        dof: float | None = None,
        patience: int | None = 10,
        overrelax: float | None = None,
    ) -> tuple[dict[str, F64], list[dict[str, float]], bool, bool]: ...
    def em_outcome(self) -> dict[str, Any] | None: ...
    def e_step(
        self,
        mu0: F64,
        v0: F64,
        vz: F64,
        vx: F64,
        gate: float | None = None,
        smooth: bool = True,
        statistics: bool = True,
    ) -> dict[str, int]: ...
    def m_step(self, mu0: F64, v0: F64, vz: F64, vx: F64) -> dict[str, F64]: ...
    def smooth_filtered(
        self,
        mu0: F64,
        v0: F64,
        vz: F64,
        vx: F64,
        end: tuple[F64, F64] | None = None,
    ) -> None: ...
    def state_row(self, k: int) -> tuple[F64, F64]: ...
    def filtered_packed(self) -> tuple[F64, F64]: ...
    def load_filtered(self, means: F64, packed: F64, mask: NDArray[np.uint8]) -> None: ...
    def set_linearization_hint(self, means: F64 | None = None, covs: F64 | None = None) -> None: ...
    def means(self) -> F64: ...
    def covs(self) -> F64: ...
    def mask(self) -> NDArray[np.uint8]: ...
    def posterior(self) -> tuple[F64, F64, F64, F64, F64]: ...

def smooth_bundle(
    input: str, output: str, keep_cov: bool = True
) -> tuple[int, int, bool, float]: ...
def extrapolate_params(
    a: tuple[F64, F64, F64, F64], b: tuple[F64, F64, F64, F64], eta: float
) -> tuple[F64, F64, F64, F64] | None: ...
