"""NPZ bundles for the standalone ``acm-smooth`` binary (batch smoothing without Python).

:func:`write_bundle` stores everything the Rust tracker needs (skeleton, cameras, detections,
``mu0`` from the single-frame fit of sec. 4.7, options); ``acm-smooth BUNDLE.npz`` (or
:func:`smooth_bundle` in-process) writes ``BUNDLE.smoothed.npz``; :func:`read_smoothed` turns
that back into a :class:`PoseResult`. Layout: ``docs/tracking.md``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import _native
from .._io import atomic_write
from ..camera import CameraRig
from ..skeleton import Skeleton
from ..state import Normalization, StateMap
from .result import PoseResult, em_history
from .track import (
    DEFAULT_GATE,
    DEFAULT_LL_TOL,
    DEFAULT_NOISE,
    _em_start,
    _in_rig_units,
    _measurements,
    default_normalization,
    gate_threshold,
    warn_rigid_lengths,
)


def write_bundle(
    path: str | Path,
    rig: CameraRig,
    skeleton: Skeleton,
    detections: np.ndarray,
    *,
    likelihood: np.ndarray | None = None,
    pcutoff: float = 0.9,
    joint_limits: bool = True,
    max_iter: int = 100,
    tol: float = 0.05,
    gate: float | None = DEFAULT_GATE,
    normalization: Normalization | None = None,
    noise: float = DEFAULT_NOISE,
    marker_names=None,
    stop: str = "loglik",
    ll_tol: float = DEFAULT_LL_TOL,
) -> Path:
    """Write an ``acm-smooth`` input bundle (NPZ, atomically).

    Parameters are those of :func:`acm_rs.track`; ``detections`` ``(n_cams, T, M, 2)`` px
    and ``likelihood`` ``(n_cams, T, M)``. The single-frame fit for ``mu0`` and the start of
    ``V_x`` (:func:`~acm_rs.tracking.track.initial_vx`, key ``vx_init``) run here.

    Returns
    -------
    pathlib.Path
        The bundle's path.
    """
    warn_rigid_lengths(skeleton, "acm-smooth")
    if stop not in ("loglik", "alg13"):
        raise ValueError(f"stop must be 'loglik' or 'alg13', got {stop!r}")
    det = _measurements(rig, skeleton, detections, likelihood, pcutoff, marker_names)
    norm = normalization or default_normalization(rig, skeleton)
    # the start as track computes it (in units of c_t, so the same in any length unit)
    rig_u, sk_u, norm_u, _ = _in_rig_units(rig, skeleton, norm)
    _, mu0, vx_init = _em_start(rig_u, sk_u, det, norm_u, joint_limits)
    g = gate_threshold(gate)
    arrays = {
        "parents": skeleton.parents.astype(np.int64),
        "rest_frames": skeleton.rest_frames,
        "bone_lengths": skeleton.bone_lengths,
        "marker_joints": skeleton.marker_joints.astype(np.int64),
        "marker_offsets": skeleton.marker_offsets,
        "joint_limits": skeleton.joint_limits,
        "cameras": rig.get_params(),
        "normalization": np.array(norm._tuple()),
        "detections": det,
        "mu0": mu0,
        "max_iter": np.float64(max_iter),
        "tol": np.float64(tol),
        "ll_tol": np.float64(ll_tol if stop == "loglik" else np.nan),
        "gate": np.float64(np.nan if g is None else g),
        "noise": np.float64(noise),
        "vx_init": vx_init,
        "joint_limits_on": np.float64(joint_limits),
    }
    if skeleton.custom_links is not None:  # an explicit link matrix (e.g. an ACM model.npy)
        links, order = skeleton.custom_links
        arrays["bone_links"] = links.astype(np.float64)
        arrays["link_order"] = order.astype(np.int64)
    path = Path(path)
    with atomic_write(path, "wb") as fh:
        np.savez(fh, **{k: np.ascontiguousarray(v) for k, v in arrays.items()})
    return path


def smooth_bundle(path: str | Path, output: str | Path | None = None, keep_cov: bool = True):
    """Run the ``acm-smooth`` work on one bundle in this process (GIL released).

    Returns
    -------
    output : pathlib.Path
        ``<stem>.smoothed.npz`` next to the bundle unless ``output`` is given.
    summary : dict
        ``n_frames``, ``iterations``, ``converged``, ``mean_reprojection_px``.
    """
    path = Path(path)
    out = Path(output) if output is not None else path.with_name(path.stem + ".smoothed.npz")
    n, it, conv, err = _native.smooth_bundle(str(path), str(out), keep_cov)
    return out, {"n_frames": n, "iterations": it, "converged": conv, "mean_reprojection_px": err}


def read_smoothed(
    path: str | Path, rig: CameraRig, skeleton: Skeleton, bundle: str | Path
) -> PoseResult:
    """Read an ``acm-smooth`` result as a :class:`PoseResult` (with its input ``bundle``)."""
    res = np.load(path)
    inp = np.load(bundle)
    norm = Normalization(*inp["normalization"][:2], pixel=tuple(inp["normalization"][2:]))
    sm = StateMap(skeleton, norm, bool(inp["joint_limits_on"]))
    history = em_history(res["em_delta"], res["em_seconds"])
    return PoseResult(
        skeleton=skeleton, rig=rig, state_map=sm, joints=res["joints"],
        joints_std=res["joints_std"], markers=res["markers"], t=res["t"], r=res["r"],
        state_mean=res["state_mean"],
        state_cov=res["state_cov"] if "state_cov" in res else None,
        detections=inp["detections"], em_history=history,
        info={
            "method": "ukf", "converged": bool(res["converged"]), "iterations": len(history),
            "status": res["status"], "markers_std": res["markers_std"],
            "params": {k: res[k] for k in ("mu0", "V0", "Vz", "Vx_diag")},
        },
    )  # fmt: skip
