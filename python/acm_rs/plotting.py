"""Figures with matplotlib (Agg backend; PNG/PDF written atomically)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._io import atomic_write

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from .camera import CameraRig
    from .skeleton import Skeleton


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _side_colors(skeleton: Skeleton) -> list[str]:
    colors = []
    for name in skeleton.bone_names:
        colors.append("tab:red" if "left" in name else "tab:blue" if "right" in name else "0.25")
    return colors


def draw_skeleton_2d(
    ax: Axes, skeleton: Skeleton, joints_2d: np.ndarray, markers_2d: np.ndarray | None = None
) -> None:
    """Draw bones (left red, right blue, centre grey) and markers (green) on 2D axes.

    Parameters
    ----------
    joints_2d : array_like, shape (J, 2)
    markers_2d : array_like, shape (M, 2), optional
    """
    for (s, e), c in zip(skeleton.bones, _side_colors(skeleton), strict=True):
        ax.plot(joints_2d[[s, e], 0], joints_2d[[s, e], 1], "-", color=c, lw=1.8)
    ax.plot(joints_2d[:, 0], joints_2d[:, 1], "o", color="k", ms=2.5)
    if markers_2d is not None:
        ax.plot(markers_2d[:, 0], markers_2d[:, 1], ".", color="tab:green", ms=4)


def skeleton_views(
    skeleton: Skeleton, joints: np.ndarray, markers: np.ndarray | None = None, title: str = ""
) -> Figure:
    """Top (xy) and side (xz) views of one pose, like Supp. Fig. 1a/c.

    Parameters
    ----------
    joints : array_like, shape (J, 3)
        World coordinates (skeleton units).
    markers : array_like, shape (M, 3), optional
    """
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, (a, b), label in zip(axes, [(0, 1), (0, 2)], ["top (x-y)", "side (x-z)"], strict=True):
        m2 = None if markers is None else markers[:, [a, b]]
        draw_skeleton_2d(ax, skeleton, joints[:, [a, b]], m2)
        ax.set_aspect("equal")
        ax.set_title(label)
        ax.set_xlabel(f"{'xyz'[a]} ({skeleton.units})")
        ax.set_ylabel(f"{'xyz'[b]} ({skeleton.units})")
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def camera_views(
    rig: CameraRig,
    skeleton: Skeleton,
    joints: np.ndarray,
    markers: np.ndarray,
    detections: np.ndarray | None = None,
    zoom: bool = False,
) -> Figure:
    """One panel per camera with the projected skeleton (image coordinates, y down).

    Parameters
    ----------
    joints : array_like, shape (J, 3)
    markers : array_like, shape (M, 3)
    detections : array_like, shape (n_cams, M, 2), optional
        2D observations drawn as crosses with lines to the projected markers.
    zoom : bool
        Show only the region around the animal (40 px margin) instead of the whole image.
    """
    plt = _pyplot()
    n = len(rig)
    cols = min(n, 2)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 4.8 * rows), squeeze=False)
    pj = rig.project(joints)
    pm = rig.project(markers)
    for i, cam in enumerate(rig):
        ax = axes.flat[i]
        draw_skeleton_2d(ax, skeleton, pj[i], pm[i])
        if detections is not None:
            d = detections[i]
            ax.plot(d[:, 0], d[:, 1], "x", color="tab:orange", ms=4)
            for a, b in zip(d, pm[i], strict=True):
                ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="tab:orange", lw=0.6)
        w, h = cam.size if cam.size is not None else (2 * cam.params[8], 2 * cam.params[9])
        pts = [pj[i], pm[i]] + ([detections[i]] if detections is not None else [])
        pts = np.concatenate(pts)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if zoom and len(pts):
            lo, hi = pts.min(axis=0) - 40, pts.max(axis=0) + 40
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(hi[1], lo[1])
        else:
            ax.set_xlim(0, w)
            ax.set_ylim(h, 0)
        ax.set_aspect("equal")
        ax.set_title(cam.name or f"camera {i}")
        ax.set_facecolor("0.97")
    for j in range(n, rows * cols):
        axes.flat[j].axis("off")
    fig.tight_layout()
    return fig


def save_figure(fig: Figure, path: str | Path, dpi: int = 120) -> Path:
    """Save a figure atomically (format from the suffix) and close it."""
    plt = _pyplot()
    p = Path(path)
    with atomic_write(p, "wb") as fh:
        fig.savefig(fh, dpi=dpi, format=p.suffix.lstrip(".") or "png")
    plt.close(fig)
    return p
