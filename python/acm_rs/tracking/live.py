"""DeepLabCut-Live adapter for :class:`acm_rs.OnlineTracker` (issue 16 item 3).

DeepLabCut-Live runs one network per camera and hands each frame's pose to a ``Processor``
(``process(pose, **kwargs) -> pose``, ``pose`` of shape ``(n_bodyparts, 3)``: x, y,
likelihood). :class:`LiveRig` gives every camera its processor
(``DLCLive(model, processor=live.processor(i))``), pairs the cameras' poses frame by frame
(the ``k``-th pose of every camera is frame ``k``) and runs the online tracker once all
cameras delivered. ``dlclive`` itself is optional: when it is installed the processors
subclass ``dlclive.Processor``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from ..labels import labels_in_skeleton_order
from .online import OnlineTracker

try:  # pragma: no cover - optional dependency
    from dlclive import Processor as _ProcessorBase
except ImportError:  # pragma: no cover

    class _ProcessorBase:  # type: ignore[no-redef]
        """Stand-in for ``dlclive.Processor`` when DeepLabCut-Live is not installed."""

        def __init__(self, **kwargs) -> None:
            pass

        def save(self, file: str = "") -> int:
            return 0


class LiveRig:
    """Pairs the per-camera poses of DeepLabCut-Live and tracks them in 3D.

    Parameters
    ----------
    online : OnlineTracker
        The tracker (parameters learned offline).
    bodyparts : sequence of str, optional
        DeepLabCut's body-part names in the order of its pose rows (mapped to the skeleton's
        markers by name); default: the rows are the skeleton's markers.
    on_pose : callable, optional
        ``on_pose(frame, joints, sd)`` after every tracked frame (joints, sd: ``(J, 3)``).
    latency_frames : int
        Report the pose predicted this many frames ahead (the closed loop's latency).

    Attributes
    ----------
    latest : tuple or None
        ``(frame, joints, sd)`` of the last tracked frame.
    """

    def __init__(
        self,
        online: OnlineTracker,
        bodyparts: Sequence[str] | None = None,
        on_pose: Callable[[int, np.ndarray, np.ndarray], None] | None = None,
        latency_frames: int = 0,
    ) -> None:
        if int(latency_frames) != latency_frames or latency_frames < 0:
            raise ValueError(f"latency_frames must be an integer >= 0, got {latency_frames}")
        self.online = online
        self.bodyparts = list(bodyparts) if bodyparts is not None else None
        self.on_pose = on_pose
        self.latency = int(latency_frames)
        self._queues: list[deque] = [deque() for _ in range(len(online.rig))]
        self.frame = 0
        self.latest: tuple[int, np.ndarray, np.ndarray] | None = None

    def processor(self, camera: int) -> CameraProcessor:
        """The DeepLabCut-Live ``Processor`` of camera ``camera`` (rig order)."""
        if not 0 <= camera < len(self._queues):
            raise ValueError(f"camera {camera} is not in the rig (0..{len(self._queues) - 1})")
        return CameraProcessor(self, camera)

    def submit(self, camera: int, pose: np.ndarray) -> None:
        """One pose ``(n_bodyparts, 3)`` (x, y in px, likelihood) of camera ``camera``; tracks
        the frame once every camera has delivered its pose of it."""
        p = np.asarray(pose, dtype=float)
        rows = len(self.bodyparts) if self.bodyparts is not None else self.online.skeleton.n_markers
        if p.shape != (rows, 3):
            raise ValueError(f"camera {camera}: pose must have shape ({rows}, 3), got {p.shape}")
        self._queues[camera].append(p)
        if all(self._queues):
            poses = np.stack([q.popleft() for q in self._queues])  # (C, K, 3)
            self._track(poses)

    def _track(self, poses: np.ndarray) -> None:
        rig, sk = self.online.rig, self.online.skeleton
        xy = labels_in_skeleton_order(poses[:, None, :, :2], sk, rig, self.bodyparts)[:, 0]
        lik2 = np.repeat(poses[:, None, :, 2:3], 2, axis=-1)
        lik = labels_in_skeleton_order(lik2, sk, rig, self.bodyparts)[:, 0, :, 0]
        lik = np.where(np.isnan(lik), 0.0, lik)  # markers DeepLabCut does not track
        joints, sd = self.online.update(xy, lik)
        if self.latency and self.online.frames:
            joints, sd = self.online.predict(self.latency)
        self.latest = (self.frame, joints, sd)
        if self.on_pose is not None:
            self.on_pose(self.frame, joints, sd)
        self.frame += 1


class CameraProcessor(_ProcessorBase):
    """The ``Processor`` of one camera: passes the pose on to its :class:`LiveRig` and returns
    it unchanged (what DeepLabCut-Live expects)."""

    def __init__(self, rig: LiveRig, camera: int) -> None:
        super().__init__()
        self.rig, self.camera = rig, camera

    def process(self, pose, **kwargs):
        self.rig.submit(self.camera, pose)
        return pose


__all__ = ["CameraProcessor", "LiveRig"]
