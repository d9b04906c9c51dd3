"""Figures and overlay videos of a tracking result (:class:`acm_rs.tracking.PoseResult`).

>>> from acm_rs import plots
>>> plots.plot_all(result, "session/plots", pdf=True)  # doctest: +SKIP
>>> plots.overlay_video(result, ["cam0.mp4", "cam1.mp4"], "session/overlay.mp4")  # doctest: +SKIP
>>> from acm_rs.plots.viewer import view_html  # needs plotly
>>> view_html(result, "session/view.html", fps=100)  # doctest: +SKIP
"""

from .overlay import overlay_video
from .tracking import (
    bone_angles,
    em_convergence,
    joint_angle_traces,
    joint_traces,
    plot_all,
    reprojection_histograms,
    save_figure,
    skeleton_snapshots,
)

__all__ = [
    "bone_angles",
    "em_convergence",
    "joint_angle_traces",
    "joint_traces",
    "overlay_video",
    "plot_all",
    "reprojection_histograms",
    "save_figure",
    "skeleton_snapshots",
]
