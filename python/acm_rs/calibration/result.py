"""``CalibrationResult``: the calibrated rig, board poses, residuals and the QC report."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._io import atomic_write
from ..camera import CameraRig
from ..rotation import rodrigues, rodrigues_inverse
from . import world

#: Relative tolerance of the scale check (triangulated square size vs the board's).
SCALE_TOLERANCE = 0.01
#: Grid used for the image coverage figure (cells per side).
COVERAGE_GRID = 10


@dataclass
class CalibrationResult:
    """Result of :func:`acm_rs.calibrate`.

    Attributes
    ----------
    rig : CameraRig
        Calibrated cameras (world frame = reference camera unless changed with
        :meth:`with_world_frame`), translations in board units.
    board_rvecs, board_tvecs : numpy.ndarray, shape (n_frames, 3)
        Board → world pose of every view; NaN for views not used.
    residuals : numpy.ndarray, shape (n_cams, n_frames, n_points, 2)
        Projection minus detection (px); NaN where no detection was used.
    corners : numpy.ndarray, shape (n_cams, n_frames, n_points, 2)
        The detections (px, NaN = not detected).
    board_points : numpy.ndarray, shape (n_points, 3)
    used_frames : numpy.ndarray, shape (n_frames,), bool
    reference_camera : int
    initial_rms : float
        RMS reprojection error (px) of the initialisation.
    info : dict
        Optimiser details and timings (JSON-able).
    """

    rig: CameraRig
    board_rvecs: np.ndarray
    board_tvecs: np.ndarray
    residuals: np.ndarray
    corners: np.ndarray
    board_points: np.ndarray
    used_frames: np.ndarray
    reference_camera: int
    initial_rms: float
    info: dict = field(default_factory=dict)

    # -- errors ---------------------------------------------------------------------------
    @property
    def errors(self) -> np.ndarray:
        """(n_cams, n_frames, n_points) reprojection distance (px); NaN where unused."""
        return np.linalg.norm(self.residuals, axis=-1)

    @property
    def rms(self) -> float:
        """RMS reprojection distance (px) over all used detections, ``sqrt(mean |e|^2)``
        (OpenCV's convention; with isotropic noise of ``sigma`` px per coordinate it is about
        ``sqrt(2) sigma``)."""
        e = self.errors
        return float(np.sqrt(np.nanmean(e**2)))

    @property
    def per_camera_rms(self) -> np.ndarray:
        """(n_cams,) RMS reprojection distance (px) per camera."""
        e = self.errors.reshape(self.errors.shape[0], -1)
        return np.sqrt(np.nanmean(e**2, axis=1))

    def view_rms(self) -> np.ndarray:
        """(n_cams, n_frames) RMS reprojection distance (px) per camera and view; NaN where
        the camera has no used detection in the view."""
        e = self.errors
        ok = np.isfinite(e)
        n = ok.sum(axis=2)
        ssq = np.where(ok, e, 0.0) ** 2
        return np.where(n > 0, np.sqrt(ssq.sum(axis=2) / np.maximum(n, 1)), np.nan)

    @property
    def camera_names(self) -> list[str]:
        """Camera names in rig order."""
        return [str(n) for n in self.rig.names]

    def board_world_points(self) -> np.ndarray:
        """(n_frames, n_points, 3) board corners in world coordinates; NaN for unused views."""
        out = np.full((len(self.board_rvecs),) + self.board_points.shape, np.nan)
        used = self.used_frames
        rots = rodrigues(self.board_rvecs[used])
        out[used] = self.board_points @ rots.transpose(0, 2, 1) + self.board_tvecs[used, None]
        return out

    # -- world frame ----------------------------------------------------------------------
    def with_world_frame(
        self,
        *,
        board_view: int | None = None,
        points: np.ndarray | None = None,
    ) -> CalibrationResult:
        """A copy in a new world frame.

        Parameters
        ----------
        board_view : int, optional
            Use the board of this view as the world frame (origin at board point
            ``(0, 0, 0)``, axes of the board).
        points : array_like, shape (3, 3), optional
            Three world points (rows, current world units): the origin, a point on the new
            +x axis, and a point in the new xy plane with positive y (see
            :func:`acm_rs.calibration.frame_from_points`).
        """
        if (board_view is None) == (points is None):
            raise ValueError("give exactly one of board_view and points")
        if board_view is not None:
            f = int(board_view)
            if not 0 <= f < len(self.used_frames) or not self.used_frames[f]:
                raise ValueError(f"board view {board_view} is not a used view")
            rot, origin = rodrigues(self.board_rvecs[f]), self.board_tvecs[f]
        else:
            rot, origin = world.frame_from_points(points)
        rig = world.transform_rig(self.rig, rot, origin)
        used = self.used_frames
        rv = np.full_like(self.board_rvecs, np.nan)
        tv = np.full_like(self.board_tvecs, np.nan)
        rv[used] = rodrigues_inverse(rot.T @ rodrigues(self.board_rvecs[used]))
        tv[used] = (self.board_tvecs[used] - origin) @ rot
        return CalibrationResult(
            rig, rv, tv, self.residuals, self.corners, self.board_points, self.used_frames,
            self.reference_camera, self.initial_rms, dict(self.info),
        )  # fmt: skip

    # -- files ----------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the rig as an anipose ``calibration.toml`` (atomically), with ``[metadata]``
        ``error`` (RMS px), per-camera RMS, the reference camera and the loss."""
        meta = {
            "error": round(self.rms, 6),
            "per_camera_rms": [round(float(v), 6) for v in self.per_camera_rms],
            "reference_camera": self.camera_names[self.reference_camera],
            "n_views": int(self.used_frames.sum()),
            "loss": str(self.info.get("loss", "linear")),
            "software": "acm-rs",
        }
        self.rig.save(path, metadata=meta)
        return Path(path)

    # -- report ---------------------------------------------------------------------------
    def report(
        self, outlier_px: float | None = None, worst: int = 10, max_outliers: int = 200
    ) -> dict:
        """Quality-control report (JSON-able dict).

        Parameters
        ----------
        outlier_px : float, optional
            Detections with a reprojection distance above this (px) are outliers; default
            ``max(1, 5 sigma)`` with ``sigma = median distance / 1.1774`` (Rayleigh).
        worst : int
            Number of worst (camera, view) pairs listed.
        max_outliers : int
            Longest outlier list (the count is always complete).

        Returns
        -------
        dict
            ``summary`` (rms, initial_rms, counts, timings), ``cameras`` (per camera: views,
            detections, rms/median/max px, intrinsics, centre, image coverage), ``views``
            (per used view: cameras, rms/median/max), ``worst_views``, ``outliers``
            (threshold, count, list of camera/view/point/error), ``plausibility`` (scale from
            the square size, board in front of cameras, cameras on the board's front side,
            mirrored) and ``optimizer``. ``text`` holds :meth:`summary`.
        """
        e = self.errors
        names = self.camera_names
        finite = np.isfinite(e)
        all_e = e[finite]
        sigma = float(np.median(all_e) / 1.1774) if all_e.size else 0.0
        thr = float(outlier_px) if outlier_px is not None else max(1.0, 5.0 * sigma)
        cams = []
        for i, cam in enumerate(self.rig):
            ei = e[i][finite[i]]
            p = cam.params
            cams.append(
                {
                    "name": names[i],
                    "n_views": int(np.any(finite[i], axis=1).sum()),
                    "n_detections": int(ei.size),
                    "rms_px": _f(np.sqrt(np.mean(ei**2))) if ei.size else None,
                    "median_px": _f(np.median(ei)) if ei.size else None,
                    "max_px": _f(np.max(ei)) if ei.size else None,
                    "fx": _f(p[6]),
                    "fy": _f(p[7]),
                    "cx": _f(p[8]),
                    "cy": _f(p[9]),
                    "k1": _f(p[10]),
                    "k2": _f(p[11]),
                    "center": [_f(v) for v in cam.center],
                    "coverage": _f(self._coverage(i)),
                }
            )
        views = []
        for f in np.flatnonzero(self.used_frames):
            ef = e[:, f][finite[:, f]]
            if ef.size == 0:
                continue
            views.append(
                {
                    "view": int(f),
                    "n_cams": int(np.any(finite[:, f], axis=1).sum()),
                    "rms_px": _f(np.sqrt(np.mean(ef**2))),
                    "median_px": _f(np.median(ef)),
                    "max_px": _f(np.max(ef)),
                }
            )
        pair_rms = self.view_rms()
        order = np.argsort(np.where(np.isfinite(pair_rms), -pair_rms, np.inf), axis=None)
        worst_list = []
        for k in order[:worst]:
            c, f = np.unravel_index(k, pair_rms.shape)
            if np.isfinite(pair_rms[c, f]):
                worst_list.append(
                    {"camera": names[c], "view": int(f), "rms_px": _f(pair_rms[c, f])}
                )
        out_idx = np.argwhere(finite & (np.where(finite, e, 0) > thr))
        out_err = e[tuple(out_idx.T)]
        out_idx = out_idx[np.argsort(-out_err)]
        outliers = {
            "threshold_px": _f(thr),
            "count": int(len(out_idx)),
            "list": [
                {"camera": names[c], "view": int(f), "point": int(j), "error_px": _f(e[c, f, j])}
                for c, f, j in out_idx[:max_outliers]
            ],
        }
        rep = {
            "summary": {
                "n_cameras": len(self.rig),
                "reference_camera": names[self.reference_camera],
                "n_views": int(self.corners.shape[1]),
                "n_views_used": int(self.used_frames.sum()),
                "n_detections": int(all_e.size),
                "rms_px": _f(self.rms),
                "initial_rms_px": _f(self.initial_rms),
                "median_px": _f(np.median(all_e)) if all_e.size else None,
                "max_px": _f(np.max(all_e)) if all_e.size else None,
            },
            "cameras": cams,
            "views": views,
            "worst_views": worst_list,
            "outliers": outliers,
            "plausibility": self.plausibility(),
            "optimizer": self.info,
        }
        rep["text"] = self.summary(rep)
        return rep

    def plausibility(self) -> dict:
        """Physical checks of the rig (JSON-able dict).

        * ``scale_ratio``: median distance between neighbouring board corners triangulated
          from the detections with the calibrated cameras (not the board poses) over their
          distance on the board; ``scale_ok`` when within ``SCALE_TOLERANCE``.
        * ``corners_behind_camera``: used detections whose board corner lies behind its camera.
        * ``views_from_board_back``: (camera, view) pairs whose camera lies on the back side
          (``z > 0`` in board coordinates) of the board it detected.
        * ``mirrored``: a negative focal length, an improper rotation, or either count above
          non-zero.
        """
        names = self.camera_names
        pts = self.board_world_points()
        behind = 0
        back = []
        for i, cam in enumerate(self.rig):
            seen = np.isfinite(self.errors[i])
            if not seen.any():
                continue
            depth = (pts @ cam.rotation_matrix.T + cam.tvec)[..., 2]
            behind += int(np.sum(seen & ~(depth > 0)))
            for f in np.flatnonzero(seen.any(axis=1)):
                rb = rodrigues(self.board_rvecs[f])
                z = (rb.T @ (cam.center - self.board_tvecs[f]))[2]
                if z > 0:
                    back.append({"camera": names[i], "view": int(f)})
        ratio = self._scale_ratio()
        improper = any(
            np.linalg.det(c.rotation_matrix) < 0 or c.params[6] <= 0 or c.params[7] <= 0
            for c in self.rig
        )
        mirrored = bool(improper or behind > 0 or len(back) > 0)
        scale_ok = ratio is not None and abs(ratio - 1.0) <= SCALE_TOLERANCE
        return {
            "scale_ratio": _f(ratio) if ratio is not None else None,
            "scale_ok": bool(scale_ok),
            "corners_behind_camera": int(behind),
            "views_from_board_back": back[:50],
            "n_views_from_board_back": len(back),
            "mirrored": mirrored,
            "ok": bool(scale_ok and not mirrored),
        }

    def summary(self, rep: dict | None = None) -> str:
        """Text table: per-camera views, detections, RMS/median/max (px), focal lengths,
        coverage; totals and the plausibility checks."""
        rep = rep if rep is not None else {k: v for k, v in self.report().items() if k != "text"}
        s = rep["summary"]
        w = max(6, *(len(c["name"]) for c in rep["cameras"]))
        head = (
            f"{'camera':<{w}} {'views':>5} {'corners':>7} {'rms px':>7} {'med px':>7} "
            f"{'max px':>7} {'fx px':>8} {'fy px':>8} {'k1':>7} {'cover':>5}"
        )
        lines = [head, "-" * len(head)]
        for c in rep["cameras"]:
            lines.append(
                f"{c['name']:<{w}} {c['n_views']:>5} {c['n_detections']:>7} "
                f"{_fmt(c['rms_px'])} {_fmt(c['median_px'])} {_fmt(c['max_px'])} "
                f"{c['fx']:>8.1f} {c['fy']:>8.1f} {c['k1']:>7.3f} {c['coverage']:>5.0%}"
            )
        lines.append("-" * len(head))
        lines.append(
            f"{'all':<{w}} {s['n_views_used']:>5} {s['n_detections']:>7} {_fmt(s['rms_px'])} "
            f"{_fmt(s['median_px'])} {_fmt(s['max_px'])}   (initial rms {s['initial_rms_px']:.3f})"
        )
        p = rep["plausibility"]
        o = rep["outliers"]
        ratio = "n/a" if p["scale_ratio"] is None else f"{p['scale_ratio']:.4f}"
        lines.append(
            f"scale from square size: {ratio} ({'ok' if p['scale_ok'] else 'CHECK'}); "
            f"corners behind cameras: {p['corners_behind_camera']}; views from the board's "
            f"back: {p['n_views_from_board_back']}; mirrored: {'yes' if p['mirrored'] else 'no'}"
        )
        lines.append(f"outliers > {o['threshold_px']:.2f} px: {o['count']}")
        if rep["worst_views"]:
            wv = ", ".join(
                f"{v['camera']}@{v['view']} ({v['rms_px']:.2f})" for v in rep["worst_views"][:5]
            )
            lines.append(f"worst views: {wv}")
        return "\n".join(lines)

    def save_report(self, path: str | Path, png: str | Path | None = None) -> dict:
        """Write :meth:`report` as JSON (atomically) and optionally the QC figure as PNG."""
        rep = self.report()
        with atomic_write(path) as fh:
            json.dump(rep, fh, indent=1)
        if png is not None:
            from ..plotting import save_figure

            save_figure(self.plot(), png)
        return rep

    def plot(self):
        """QC figure: per-camera board coverage (detected corners over the image, coloured
        by error), error histograms, per-view RMS and camera positions with the board
        corners (3D)."""
        from ..plotting import _pyplot

        plt = _pyplot()
        n = len(self.rig)
        e = self.errors
        fig = plt.figure(figsize=(max(12, 3.2 * n), 8.5), constrained_layout=True)
        gs = fig.add_gridspec(2, max(n, 3))
        vmax = float(np.nanpercentile(e, 99)) if np.isfinite(e).any() else 1.0
        sc = None
        for i, cam in enumerate(self.rig):
            ax = fig.add_subplot(gs[0, i])
            ok = np.isfinite(e[i])
            xy = self.corners[i][ok]
            sc = ax.scatter(xy[:, 0], xy[:, 1], c=e[i][ok], s=2, cmap="viridis", vmin=0, vmax=vmax)
            w, h = cam.size if cam.size is not None else (np.nanmax(xy[:, 0]), np.nanmax(xy[:, 1]))
            ax.set_xlim(0, w)
            ax.set_ylim(h, 0)
            ax.set_aspect("equal")
            ax.set_title(f"{self.camera_names[i]}: {self.per_camera_rms[i]:.2f} px", fontsize=9)
            ax.tick_params(labelsize=7)
        if sc is not None:
            fig.colorbar(sc, ax=fig.axes[:n], shrink=0.6, label="reprojection error (px)")
        ax = fig.add_subplot(gs[1, 0])
        for i in range(n):
            ei = e[i][np.isfinite(e[i])]
            ax.hist(ei, bins=50, histtype="step", label=self.camera_names[i])
        ax.set_xlabel("reprojection error (px)")
        ax.set_ylabel("detections")
        ax.legend(fontsize=7)
        ax = fig.add_subplot(gs[1, 1])
        pair = self.view_rms()
        for i in range(n):
            ax.plot(pair[i], ".", ms=3, label=self.camera_names[i])
        ax.set_xlabel("view")
        ax.set_ylabel("view RMS (px)")
        ax3 = fig.add_subplot(gs[1, 2:], projection="3d")
        pts = self.board_world_points().reshape(-1, 3)
        ax3.scatter(*pts[np.isfinite(pts[:, 0])].T, s=0.3, c="0.6")
        span = float(np.nanmax(np.ptp(pts[np.isfinite(pts[:, 0])], axis=0))) if len(pts) else 1.0
        for cam, name in zip(self.rig, self.camera_names, strict=True):
            c = cam.center
            z = cam.rotation_matrix[2] * 0.3 * span
            ax3.scatter(*c, s=30)
            ax3.plot(*np.stack([c, c + z]).T, "k-", lw=1)
            ax3.text(*c, name, fontsize=8)
        every = np.vstack([pts[np.isfinite(pts[:, 0])], [c.center for c in self.rig]])
        mid, half = every.mean(0), np.ptp(every, axis=0).max() / 2
        ax3.set_xlim(mid[0] - half, mid[0] + half)
        ax3.set_ylim(mid[1] - half, mid[1] + half)
        ax3.set_zlim(mid[2] - half, mid[2] + half)
        ax3.set_box_aspect((1, 1, 1))
        ax3.set_title("cameras (optical axes) and board corners, world frame", fontsize=9)
        fig.suptitle(f"calibration QC: rms {self.rms:.3f} px over {np.isfinite(e).sum()} corners")
        return fig

    # -- helpers --------------------------------------------------------------------------
    def _coverage(self, i: int) -> float:
        """Fraction of a COVERAGE_GRID² grid over camera i's image holding a used corner."""
        cam = self.rig[i]
        ok = np.isfinite(self.errors[i])
        if cam.size is None or not ok.any():
            return 0.0
        xy = self.corners[i][ok]
        w, h = cam.size
        gx = np.clip((xy[:, 0] / w * COVERAGE_GRID).astype(int), 0, COVERAGE_GRID - 1)
        gy = np.clip((xy[:, 1] / h * COVERAGE_GRID).astype(int), 0, COVERAGE_GRID - 1)
        return len(set(zip(gx.tolist(), gy.tolist(), strict=True))) / COVERAGE_GRID**2

    def _scale_ratio(self) -> float | None:
        pts = world.triangulate(
            self.rig, np.where(np.isfinite(self.errors)[..., None], self.corners, np.nan)
        )
        pairs, dist = _neighbour_pairs(self.board_points)
        if len(pairs) == 0:
            return None
        d = np.linalg.norm(pts[:, pairs[:, 0]] - pts[:, pairs[:, 1]], axis=-1) / dist
        d = d[np.isfinite(d)]
        return float(np.median(d)) if d.size else None


def _neighbour_pairs(board: np.ndarray) -> tuple[np.ndarray, float]:
    """Index pairs of board points at the smallest non-zero distance (one square apart)."""
    d = np.linalg.norm(board[:, None] - board[None], axis=-1)
    nz = d[d > 0]
    if nz.size == 0:
        return np.zeros((0, 2), int), 1.0
    m = nz.min()
    i, j = np.nonzero(np.triu(np.abs(d - m) <= 1e-6 * m, 1))
    return np.stack([i, j], 1), float(m)


def _f(v) -> float:
    return float(v)


def _fmt(v) -> str:
    return f"{'n/a':>7}" if v is None else f"{v:>7.3f}"
