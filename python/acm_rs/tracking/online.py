"""Frame-by-frame tracking for closed-loop experiments (issue 16, beyond the paper).

:class:`OnlineTracker` runs one step of the unscented Kalman filter (Alg. 6) per incoming
frame with the parameters that :func:`acm_rs.track` learned offline on an earlier recording of
the same rig and animal, and returns the pose of the current frame with its posterior SD.
Optional: a fixed-lag smoother over the last ``lag`` frames (more accurate, ``lag`` frames
late) and a prediction ahead by a given latency. The step runs in Rust with the GIL released.
"""

from __future__ import annotations

import numpy as np

from .._native import NativeOnlineTracker
from ..camera import CameraRig
from ..skeleton import Skeleton
from ..state import Normalization, StateMap
from .result import PoseResult
from .track import DEFAULT_GATE, MOTION_ORDER, _first_pose, gate_threshold, warn_rigid_lengths


class OnlineTracker:
    """Track one live recording frame by frame with fixed parameters.

    Parameters
    ----------
    rig : CameraRig
        The calibrated cameras (world units = the skeleton's).
    skeleton : Skeleton
        The learned skeleton.
    params : dict
        Learned parameters ``mu0, V0, Vz, Vx_diag`` (``PoseResult.info["params"]``) of a state
        of size ``order × n_state``.
    normalization : Normalization
        The sec. 3.3 constants the parameters were learned with.
    motion : {"random_walk", "velocity"}
        The motion model of the parameters.
    lag : int
        Fixed-lag window of :meth:`lagged` (0: filter only).
    gate : float or None
        Innovation gate probability (as in :func:`acm_rs.track`).
    pcutoff : float
        Detections with a likelihood below this are missing.
    joint_limits : bool
        Enforce joint-angle limits (Alg. 10), as when the parameters were learned.
    vz_shrinkage : float in [0, 1]
        ``V_z ← (1 − s) V_z + s diag(V_z)``. The full ``V_z`` learned on one recording
        encodes that recording's movements and does not carry over to the next: on a second
        synthetic recording of the same rat the offline filter with the learned full ``V_z``
        erred 3.5 mm (mean joint error; 0.57 mm on the recording it was learned on), with
        ``s = 0.8`` 0.95 mm (0.73 mm in-sample), with the diagonal 0.94 mm (0.82 mm)
        (``docs/tracking.md``). 0 uses the learned ``V_z`` as it is.
    serial : bool
        True (default): each step runs on the calling thread alone: no allocation at all
        per frame, no other thread woken, the other cores free for the 2D network. False:
        the sigma points and Gram products are shared with the thread pool (which
        allocates a small block of its job queue every ~60 frames). On the rat with 4
        cameras both took the same time (p99 0.69-1.02 ms serial, 0.74-1.07 ms parallel;
        ``benches/README.md``, online tracker).

    The prior of the first frame is the single-frame fit of the first frame with enough
    detections (sec. 4.7) with the learned ``V0``; frames before it return NaN.
    """

    def __init__(
        self,
        rig: CameraRig,
        skeleton: Skeleton,
        params: dict,
        *,
        normalization: Normalization,
        motion: str = "random_walk",
        lag: int = 0,
        gate: float | None = DEFAULT_GATE,
        pcutoff: float = 0.9,
        joint_limits: bool = True,
        relinearize: int = 10,
        vz_shrinkage: float = 0.8,
        serial: bool = True,
    ) -> None:
        if motion not in ("random_walk", "velocity"):
            raise ValueError(f"motion must be 'random_walk' or 'velocity', got {motion!r}")
        if int(lag) != lag or lag < 0:
            raise ValueError(f"lag must be an integer >= 0, got {lag}")
        missing = [k for k in ("mu0", "V0", "Vz", "Vx_diag") if k not in params]
        if missing:
            raise ValueError(f"params lacks {missing} (PoseResult.info['params'] has them)")
        self.rig, self.skeleton, self.norm = rig, skeleton, normalization
        if not 0.0 <= vz_shrinkage <= 1.0:
            raise ValueError(f"vz_shrinkage must be in [0, 1], got {vz_shrinkage}")
        self.params = {k: np.ascontiguousarray(params[k], dtype=float) for k in params}
        vz = self.params["Vz"]
        if vz.ndim == 2:
            self.params["Vz"] = np.ascontiguousarray(
                (1.0 - vz_shrinkage) * vz + vz_shrinkage * np.diag(np.diag(vz))
            )
        self.order = MOTION_ORDER[motion]
        self.lag, self.pcutoff, self.gate = int(lag), float(pcutoff), gate
        self.joint_limits, self.relinearize = bool(joint_limits), int(relinearize)
        self.serial = bool(serial)
        self._sm = StateMap(skeleton, normalization, joint_limits)
        ns = self.order * self._sm.n_state
        stretched = self.order * StateMap(skeleton, normalization, joint_limits, True).n_state
        if skeleton.stretch_sd.any() and self.params["mu0"].shape == (stretched,):
            raise ValueError(
                "these parameters come from a track with elastic segments, which the online "
                "tracker does not follow yet: learn them with acm_rs.track(..., elastic=False)"
            )
        warn_rigid_lengths(skeleton, "the online tracker")
        if self.params["mu0"].shape != (ns,):
            raise ValueError(
                f"params['mu0'] has shape {self.params['mu0'].shape}, the {motion} state of "
                f"this skeleton needs ({ns},)"
            )
        self._native: NativeOnlineTracker | None = None
        self._empty = np.full((skeleton.n_joints, 3), np.nan)

    @classmethod
    def from_result(cls, result: PoseResult, **kwargs) -> OnlineTracker:
        """An online tracker with the rig, skeleton, parameters, normalisation and motion
        model of an offline :func:`acm_rs.track` result (keyword arguments as the class)."""
        info = result.info
        if "params" not in info:
            raise ValueError("the result has no learned parameters (method='deterministic'?)")
        nd = info["normalization"]
        norm = Normalization(
            translation=float(nd["translation"]), rotation=float(nd["rotation"]),
            pixel=(float(nd["pixel"][0]), float(nd["pixel"][1])),
        )  # fmt: skip
        kwargs.setdefault("motion", info.get("motion", "random_walk"))
        kwargs.setdefault("joint_limits", bool(info.get("joint_limits", True)))
        return cls(result.rig, result.skeleton, info["params"], normalization=norm, **kwargs)

    @property
    def frames(self) -> int:
        """Frames processed since the first pose fit (0 before)."""
        return 0 if self._native is None else self._native.frames

    def _start(self, det: np.ndarray) -> bool:
        """Sec. 4.7 on this frame: the prior mean from its single-frame fit."""
        try:
            _, t0, r0 = _first_pose(self.rig, self.skeleton, det[:, None], self.norm)
        except ValueError:
            return False  # not enough detections yet
        mu0 = np.zeros(self.order * self._sm.n_state)
        mu0[: self._sm.n_state] = self._sm.start_state(t0, r0)
        lim = self.skeleton.joint_limits
        p = self.params
        self._native = NativeOnlineTracker(
            self.skeleton._native, self.rig.get_params(), np.ascontiguousarray(lim[..., 0]),
            np.ascontiguousarray(lim[..., 1]), self.norm._tuple(), self.joint_limits,
            mu0, p["V0"], p["Vz"], p["Vx_diag"], order=self.order,
            gate=gate_threshold(self.gate), relinearize=self.relinearize, lag=self.lag,
            serial=self.serial,
        )  # fmt: skip
        return True

    def update(
        self, detections: np.ndarray, likelihood: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Process one frame.

        Parameters
        ----------
        detections : array_like, shape (n_cams, n_markers, 2)
            2D detections of this frame in pixels (NaN = missing), markers in skeleton order.
        likelihood : array_like, shape (n_cams, n_markers), optional
            Detection confidence; below ``pcutoff`` is missing.

        Returns
        -------
        joints, sd : ndarray, shape (n_joints, 3)
            Filtered joint positions and posterior SD (skeleton units) of this frame; NaN
            until the first frame with enough detections for the initial fit.
        """
        det = np.array(detections, dtype=float)
        want = (len(self.rig), self.skeleton.n_markers, 2)
        if det.shape != want:
            raise ValueError(f"detections must have shape {want}, got {det.shape}")
        if np.isinf(det).any():
            raise ValueError("detections contain ±inf (use NaN for missing)")
        if likelihood is not None:
            lik = np.asarray(likelihood, dtype=float)
            if lik.shape != want[:2]:
                raise ValueError(f"likelihood must have shape {want[:2]}, got {lik.shape}")
            det[~(lik >= self.pcutoff)] = np.nan
        if self._native is None and not self._start(det):
            return self._empty.copy(), self._empty.copy()
        assert self._native is not None
        self._native.update(np.ascontiguousarray(self.norm.normalize_pixels(det)))
        return self._native.filtered_pose()

    def lagged(self) -> tuple[np.ndarray, np.ndarray, int]:
        """``(joints, sd, k)``: the pose of the frame ``k = min(lag, frames - 1)`` frames
        before the last one, smoothed with every frame up to the last (fixed-lag RTS)."""
        if self._native is None:
            raise ValueError("no frame processed yet")
        return self._native.lagged_pose()

    def lagged_window(self) -> tuple[np.ndarray, np.ndarray, int]:
        """``(joints, sd, k)``: the poses of the last ``k + 1`` frames (``k`` as in
        :meth:`lagged`), each smoothed with every frame up to the last; ``joints`` and ``sd``
        of shape (k + 1, n_joints, 3) in time order. With ``lag >= n_frames - 1``, after the
        last frame, this is the offline smoother (Alg. 8) of the recording with Θ fixed."""
        if self._native is None:
            raise ValueError("no frame processed yet")
        js, ss, k = self._native.lagged_window_poses()
        return np.stack(js), np.stack(ss), k

    def predict(self, frames_ahead: int) -> tuple[np.ndarray, np.ndarray]:
        """``(joints, sd)`` predicted ``frames_ahead`` frames after the last processed frame
        (e.g. the loop's latency in frames)."""
        if self._native is None:
            raise ValueError("no frame processed yet")
        if int(frames_ahead) != frames_ahead or frames_ahead < 0:
            raise ValueError(f"frames_ahead must be an integer >= 0, got {frames_ahead}")
        return self._native.predicted_pose(int(frames_ahead))

    def reset(self) -> None:
        """Forget the recording: the next frame starts from a new single-frame fit."""
        self._native = None


__all__ = ["OnlineTracker"]
