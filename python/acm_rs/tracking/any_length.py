""":func:`track` for a recording of any length (issue 29): the in-memory EM
(:func:`~acm_rs.tracking.track.track_in_memory`) while the recording's moments fit a memory
budget, else the bounded-memory path (:func:`~acm_rs.tracking.long.track_bounded`: EM on
windows, the exact streaming smoother), with the same :class:`PoseResult` back.
"""

from __future__ import annotations

import inspect

import numpy as np

from ..camera import CameraRig
from ..skeleton import Skeleton
from ..state import StateMap
from .long import track_bounded
from .result import PoseResult
from .track import (
    DEFAULT_MOTION,
    MOTION_ORDER,
    default_memory_limit,
    in_memory_bytes,
    track_in_memory,
    warn_rigid_lengths,
    warn_second_solutions,
)

#: Options of :func:`track_in_memory` that the bounded-memory path passes on.
_BOUNDED_OPTIONS = (
    "likelihood", "pcutoff", "joint_limits", "max_iter", "progress", "gate", "normalization",
    "noise", "marker_names", "ll_tol", "motion", "relinearize", "overrelax",
)  # fmt: skip


def track(
    rig: CameraRig,
    skeleton: Skeleton,
    detections,
    *,
    memory_limit: float | None = None,
    **options,
) -> PoseResult:
    """Reconstruct the poses of a recording of any length (ACM supp. sec. 4).

    Parameters other than ``memory_limit``, the result and the errors: as
    :func:`acm_rs.tracking.track.track_in_memory` (its docstring follows).

    memory_limit : float, optional
        Bytes the in-memory EM may use (default
        :func:`~acm_rs.tracking.track.default_memory_limit`: half of the available memory, at
        most 4 GiB). A recording whose moments need more
        (:func:`~acm_rs.tracking.track.in_memory_bytes`: ``T · 3.5 · (order · n_state)²``
        doubles; the rat's velocity state: 206 KB a frame, so ~20,000 frames in 4 GiB) goes the
        bounded-memory path of :func:`acm_rs.track_long` (EM on windows that fit the budget,
        then the exact streaming smoother), says so in one warning, and comes back as the same
        :class:`PoseResult` without ``state_cov`` (``info["bounded_memory"]``). It supports the
        Gaussian noise model with the log-likelihood stop (other options are refused with the
        fix). ``detections`` may be a ``numpy.memmap``: that path reads it a window at a time.
        ``float("inf")`` forces the in-memory EM.
    """
    if memory_limit is not None and not memory_limit > 0:
        raise ValueError(f"memory_limit must be > 0 bytes, got {memory_limit}")
    method = options.get("method", "ukf")
    if method == "ukf" and np.ndim(detections) == 4:
        motion = options.get("motion", DEFAULT_MOTION)
        limit = default_memory_limit() if memory_limit is None else memory_limit
        n_frames = np.shape(detections)[1]
        elastic = bool(skeleton.stretch_sd.any()) and options.get("elastic", None) is not False
        n_state = StateMap(
            skeleton, None, options.get("joint_limits", True), stretch=elastic
        ).n_state
        # an unknown motion is refused by track_in_memory
        need = in_memory_bytes(n_frames, n_state, motion) if motion in MOTION_ORDER else 0
        if need > limit:
            # (the marker misfit needs the state covariances, which that path does not keep:
            # its default is not applied there, "off" is accepted)
            allowed = {k: (v, "off") if k == "misfit" else (v,) for k, v in _DEFAULTS.items()}
            unsupported = {
                k: options[k] for k in _DEFAULTS if k in options and options[k] not in allowed[k]
            }
            if unsupported:
                raise ValueError(
                    f"{n_frames} frames need ~{need / 2**30:.1f} GiB in memory (limit "
                    f"{limit / 2**30:.1f} GiB), and the bounded-memory path does not take "
                    f"{unsupported}: leave them at their defaults, or raise memory_limit"
                )
            unknown = (
                set(options) - set(_BOUNDED_OPTIONS) - set(_DEFAULTS)
                - {"method", "elastic", "second_solutions"}
            )  # fmt: skip
            if unknown:
                raise TypeError(f"track() got unexpected keyword argument(s) {sorted(unknown)}")
            if options.get("elastic", True) is not False:
                warn_rigid_lengths(skeleton, "the bounded-memory path (raise memory_limit)")
            result = track_bounded(
                rig, skeleton, detections, need=need, limit=limit,
                **{k: v for k, v in options.items() if k in _BOUNDED_OPTIONS},
            )  # fmt: skip
            second = options.get("second_solutions", _SECOND_DEFAULT)
            if second > 0 and not result.info.get("interrupted"):
                warn_second_solutions(result, second)
            return result
    return track_in_memory(rig, skeleton, detections, **options)


_SIGNATURE = inspect.signature(track_in_memory)
#: Frames the second-pose search takes by default (both paths run it).
_SECOND_DEFAULT = _SIGNATURE.parameters["second_solutions"].default
#: Defaults of the options the bounded-memory path cannot change.
_DEFAULTS = {
    k: _SIGNATURE.parameters[k].default for k in ("noise_model", "stop", "tol", "dof", "misfit")
}
track.__doc__ = (track.__doc__ or "") + "\n" + (track_in_memory.__doc__ or "")
track.__signature__ = _SIGNATURE.replace(  # type: ignore[attr-defined]
    parameters=[
        *_SIGNATURE.parameters.values(),
        inspect.Parameter("memory_limit", inspect.Parameter.KEYWORD_ONLY, default=None),
    ]
)
