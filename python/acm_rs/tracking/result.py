"""The result of :func:`acm_rs.track`: smoothed poses, their uncertainty and diagnostics."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._io import atomic_write
from .result_npz import read_npz, to_npz

if TYPE_CHECKING:  # pragma: no cover
    from ..camera import CameraRig
    from ..skeleton import Skeleton
    from ..state import StateMap


def em_history(delta: np.ndarray, seconds: np.ndarray, stored=None) -> list[dict]:
    """``em_history`` records from stored per-iteration Δ and wall times, and from
    ``stored`` (a mapping such as the loaded NPZ) the log-likelihood, the over-relaxed step
    factor and whether the step was rejected where the file has them (``em_log_likelihood``,
    ``em_step``, ``em_rejected``; files before them have Δ and times only)."""
    out = [
        {"iteration": i + 1, "delta": float(a), "seconds": float(b)}
        for i, (a, b) in enumerate(zip(delta, seconds, strict=True))
    ]
    stored = {} if stored is None else stored
    for key, name, kind in (
        ("em_log_likelihood", "log_likelihood", float),
        ("em_step", "step", float),
        ("em_rejected", "rejected", bool),
    ):
        if key in stored and len(stored[key]) == len(out):
            for h, v in zip(out, stored[key], strict=True):
                h[name] = kind(v)
    return out


@dataclass
class PoseResult:
    """Poses of one recording reconstructed by :func:`acm_rs.track`.

    Lengths are in the units of the skeleton and the rig (``skeleton.units``, e.g. mm).

    Attributes
    ----------
    joints : numpy.ndarray, shape (T, J, 3)
        Joint positions (forward kinematics of the posterior mean pose).
    joints_std : numpy.ndarray, shape (T, J, 3)
        Posterior standard deviation of each joint coordinate (unscented transform of the
        state posterior through forward kinematics); zeros for ``method="deterministic"``.
        For joints whose markers leave a second pose open (``track(second_solutions=)``),
        widened to reach it: ``info["joints_std_widening"]`` (J,) is the SD added
        (:func:`acm_rs.tracking.ambiguity.widen`).
    markers : numpy.ndarray, shape (T, M, 3)
        Marker positions: the posterior mean of the true markers, forward kinematics of the
        mean pose plus the estimated model misfit ``δ̂`` (``track(misfit=...)``,
        :mod:`acm_rs.tracking.misfit`); with ``misfit="off"`` or ``Σ_k = 0`` the forward
        kinematics alone, which ``info["markers_fk"]`` keeps. Their posterior SDs are
        ``info["markers_std"]`` (FK only: ``info["markers_std_fk"]``).
    t : numpy.ndarray, shape (T, 3)
        Global translation per frame.
    r : numpy.ndarray, shape (T, n_bones, 3)
        Bone rotations (Rodrigues vectors, rad), within the joint limits.
    state_mean : numpy.ndarray, shape (T, n_state)
        Smoothed state means (normalised, erf-constrained state of Alg. 10).
    state_cov : numpy.ndarray, shape (T, n_state, n_state) or None
        Smoothed state covariances (None for the deterministic method).
    detections : numpy.ndarray, shape (n_cams, T, M, 2)
        The measurements used (px, skeleton marker order), NaN where missing or below pcutoff.
    em_history : list of dict
        Per EM iteration: ``iteration``, ``delta`` (mean relative change of Alg. 13),
        ``seconds`` (wall time of the iteration), ``gated`` (measurements rejected by the
        innovation gate).
    info : dict
        ``method``, ``converged``, ``iterations``, ``tol``, ``params`` (learned ``mu0``,
        ``V0``, ``Vz``, ``Vx_diag``), ``gated`` (mask of gated measurements), timings;
        ``misfit``, ``misfit_shape``, ``misfit_cov`` (M, 3, 3), ``misfit_sd`` (M,),
        ``markers_fk``, ``markers_std_fk`` (the markers' model misfit).
    """

    skeleton: Skeleton
    rig: CameraRig
    state_map: StateMap
    joints: np.ndarray
    joints_std: np.ndarray
    markers: np.ndarray
    t: np.ndarray
    r: np.ndarray
    state_mean: np.ndarray
    state_cov: np.ndarray | None
    detections: np.ndarray
    em_history: list[dict] = field(default_factory=list)
    info: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        """Number of frames T."""
        return int(self.joints.shape[0])

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the J joints."""
        return self.skeleton.joint_names

    @property
    def marker_names(self) -> tuple[str, ...]:
        """Names of the M markers."""
        return self.skeleton.marker_names

    def projected(self) -> np.ndarray:
        """Markers of the mean poses projected into every camera, shape (n_cams, T, M, 2) px."""
        return self.skeleton.project(self.rig, self.t, self.r)

    def reprojection_error(self) -> np.ndarray:
        """Distance between detections and reprojected markers, shape (n_cams, T, M) px.

        NaN where there was no detection (missing or below ``pcutoff``).
        """
        return np.linalg.norm(self.projected() - self.detections, axis=-1)

    def sample(self, n: int, seed: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Draw poses from the posterior and propagate them through forward kinematics.

        The paper reports mean ± std of 1000 such propagations.

        Parameters
        ----------
        n : int
            Number of samples per frame.
        seed : int, optional
            Seed of the random generator.

        Returns
        -------
        joints : numpy.ndarray, shape (n, T, J, 3)
        markers : numpy.ndarray, shape (n, T, M, 3)
            Forward kinematics of the sampled poses (without the markers' model misfit).
        """
        if self.state_cov is None:
            raise ValueError("this result has no posterior covariance (method='deterministic')")
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        rng = np.random.default_rng(seed)
        chol = np.linalg.cholesky(
            0.5 * (self.state_cov + self.state_cov.transpose(0, 2, 1))
            + 1e-12 * np.eye(self.state_cov.shape[-1])
        )
        eps = rng.standard_normal((n,) + self.state_mean.shape)
        z = self.state_mean[None] + np.einsum("tij,ntj->nti", chol, eps)
        joints, markers = self.state_map.forward(z.reshape(-1, z.shape[-1]))
        shape = (n, self.n_frames)
        return joints.reshape(shape + joints.shape[1:]), markers.reshape(shape + markers.shape[1:])

    def summary(self) -> str:
        """A short text report: method, EM iterations, convergence, reprojection error."""
        err = self.reprojection_error()
        ok = np.isfinite(err)
        lines = [
            f"tracked {self.n_frames} frames ({self.info.get('method', '?')}): "
            + (
                f"{len(self.em_history)} EM iterations, "
                + ("converged" if self.info.get("converged") else "NOT converged")
                + f" (last delta {self.em_history[-1]['delta']:.3g}), "
                if self.em_history
                else ""
            )
            + f"mean reprojection error {np.mean(err[ok]):.2f} px over {int(ok.sum())} "
            f"detections (median {np.median(err[ok]):.2f} px)"
            if ok.any()
            else "no detections"
        ]
        if self.info.get("elastic"):
            sd = np.asarray(self.info["stretch_sd"])
            e = self.skeleton.elastic_bones
            lines.append(
                f"  elastic segments: {len(e)} bones, learned stretch SD "
                f"{100 * sd[e].min():.1f}-{100 * sd[e].max():.1f} % of their lengths"
            )
        second = self.info.get("second_solutions")
        if second and second.get("joints"):
            names = ", ".join(second["joints"])
            lines.append(
                f"  joints the markers do not decide (a second pose fits them as well at frame(s) "
                f"{second['frames']}): {names}"
            )
        if "seconds" in self.info:
            lines.append(f"  wall time {self.info['seconds']:.2f} s")
        return "\n".join(lines)

    def save(self, path: str | Path) -> list[Path]:
        """Write ``<path>.npz`` (:func:`acm_rs.export.to_npz`: every array, the skeleton and
        the calibration; :meth:`load` reads it back) and ``<path>_joints.csv``, atomically.

        The CSV has one row per frame and columns ``<joint>_x, <joint>_y, <joint>_z`` followed
        by ``<joint>_x_std, ...``; lengths in ``skeleton.units``.
        """
        path = Path(path)
        base = path.with_suffix("") if path.suffix in (".npz", ".csv") else path
        npz = to_npz(self, base.with_suffix(".npz"))
        csv = base.with_name(base.name + "_joints.csv")
        cols = [f"{j}_{a}" for j in self.joint_names for a in "xyz"]
        header = ",".join(["frame"] + cols + [c + "_std" for c in cols])
        table = np.concatenate(
            [
                np.arange(self.n_frames)[:, None],
                self.joints.reshape(self.n_frames, -1),
                self.joints_std.reshape(self.n_frames, -1),
            ],
            axis=1,
        )
        with atomic_write(csv, "w") as fh:
            np.savetxt(fh, table, delimiter=",", header=header, comments="", fmt="%.6g")
        return [npz, csv]

    @classmethod
    def load(cls, path: str | Path) -> PoseResult:
        """Read a result written by :meth:`save` / :func:`acm_rs.export.to_npz`."""
        import tomllib

        from ..camera import Camera, CameraRig
        from ..skeleton import Skeleton
        from ..state import Normalization, StateMap

        d = read_npz(path)
        skeleton = Skeleton.from_dict(tomllib.loads(d["skeleton_toml"]), source=str(path))
        cal = tomllib.loads(d["calibration_toml"])
        cams = [
            cal[k]
            for k in sorted((k for k in cal if k.startswith("cam_")), key=lambda k: int(k[4:]))
        ]
        rig = CameraRig([Camera.from_dict(c) for c in cams])
        info = d["info"]
        nd = info.get("normalization") or {}
        norm = Normalization(
            translation=nd.get("translation", 50.0),
            rotation=nd.get("rotation", np.pi / 2),
            pixel=tuple(nd.get("pixel", (640.0, 512.0))),
        )
        sm = StateMap(
            skeleton, norm, bool(info.get("joint_limits", True)), stretch=bool(info.get("elastic"))
        )
        history = em_history(d["em_delta"], d["em_seconds"], d)
        return cls(
            skeleton=skeleton, rig=rig, state_map=sm, joints=d["joints"],
            joints_std=d["joints_std"], markers=d["markers"], t=d["t"], r=d["r"],
            state_mean=d["state_mean"], state_cov=d.get("state_cov"),
            detections=d["detections"], em_history=history, info=info,
        )  # fmt: skip
