"""A self-contained HTML viewer of a tracking result (plotly, JavaScript embedded, no network).

Left: the 3D skeleton of each frame (bones as lines, joints coloured by their posterior standard
deviation on a fixed scale), the cameras as small pyramids with their names, and the arena
floor; a time slider and play/pause buttons animate it. Right: the x, y, z traces of one joint
(mean ± 2 SD), chosen in a drop-down menu, with a line at the frame shown on the left.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._io import atomic_write

if TYPE_CHECKING:  # pragma: no cover
    from ..tracking.result import PoseResult

__all__ = ["BONE_COLOR", "view_figure", "view_html"]

#: Colour of the bones (an orange no other element uses, so tests can find the skeleton).
BONE_COLOR = "rgb(255,120,0)"
_SD_SCALE = "Viridis"
_AXIS_COLORS = ("rgb(31,119,180)", "rgb(44,160,44)", "rgb(214,39,40)")


def _bone_xyz(joints: np.ndarray, bones: np.ndarray, decimals: int) -> list[list[float | None]]:
    """Line coordinates of all bones of one frame, separated by None (one trace), rounded to
    ``decimals`` (the file holds one such list per animation frame)."""
    out: list[list[float | None]] = [[], [], []]
    for a, b in bones:
        for k in range(3):
            out[k] += [round(float(joints[a, k]), decimals), round(float(joints[b, k]), decimals),
                       None]  # fmt: skip
    return out


def _camera_lines(rig, size: float) -> tuple[list, list, list]:
    """Pyramids (apex at the camera centre, base = the image corners at depth ``size``)."""
    xs: list = []
    ys: list = []
    zs: list = []
    for cam in rig:
        w, h = cam.size if cam.size is not None else (2 * cam.matrix[0, 2], 2 * cam.matrix[1, 2])
        kinv = np.linalg.inv(cam.matrix)
        rays = np.array([kinv @ [u, v, 1.0] for u, v in ((0, 0), (w, 0), (w, h), (0, h))])
        rays *= size / np.linalg.norm(rays, axis=1, keepdims=True)
        corners = (cam.rotation_matrix.T @ rays.T).T + cam.center
        c = cam.center
        for p in corners:
            for k, arr in enumerate((xs, ys, zs)):
                arr += [c[k], p[k], None]
        ring = np.vstack([corners, corners[:1]])
        for k, arr in enumerate((xs, ys, zs)):
            arr += list(ring[:, k]) + [None]
    return xs, ys, zs


def _up(points: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """ "Up": the world axis closest (within 30°) to the direction from the animal to the
    cameras (calibrations with the floor as xy plane: +z); in other world frames (e.g. the
    first camera's) that direction itself."""
    up = centers.mean(axis=0) - points.mean(axis=0)
    up = up / (np.linalg.norm(up) or 1.0)
    for axis in np.vstack([np.eye(3), -np.eye(3)]):
        if up @ axis > np.cos(np.deg2rad(30)):
            return axis
    return up


def _plane_axes(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    u = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    return u, np.cross(up, u)


def _floor(points: np.ndarray, up: np.ndarray, pad: float) -> np.ndarray:
    """(4, 3) corners of the arena floor under the animal: the plane through its lowest point
    perpendicular to ``up``, ``pad`` beyond its path."""
    u, v = _plane_axes(up)
    a, b, h = points @ u, points @ v, float((points @ up).min())
    a0, a1, b0, b1 = a.min() - pad, a.max() + pad, b.min() - pad, b.max() + pad
    return np.array([h * up + x * u + y * v for x, y in ((a0, b0), (a1, b0), (a1, b1), (a0, b1))])


def _eye(centers: np.ndarray, animal: np.ndarray, up: np.ndarray, distance: float = 1.6) -> dict:
    """A plotly scene camera looking from between two cameras (not through one), from above."""
    u, v = _plane_axes(up)
    rel = centers - animal
    cam_az = np.arctan2(rel @ v, rel @ u)
    cands = np.deg2rad(np.arange(0, 360, 5))
    gap = np.abs((cands[:, None] - cam_az[None, :] + np.pi) % (2 * np.pi) - np.pi).min(axis=1)
    az = float(cands[int(np.argmax(gap))])
    eye = distance * (np.cos(az) * u + np.sin(az) * v + 0.6 * up)
    return {
        "eye": dict(zip("xyz", map(float, eye), strict=True)),
        "up": dict(zip("xyz", map(float, up), strict=True)),
    }


def view_html(
    result: PoseResult,
    path: str | Path,
    *,
    fps: float | None = None,
    max_frames: int = 1500,
    max_trace_points: int = 5000,
    title: str | None = None,
) -> Path:
    """Write one HTML file that shows the tracked skeleton in 3D in a browser.

    The figure of :func:`view_figure` with plotly.js embedded (no network needed); parameters
    as there.

    Returns
    -------
    Path
        ``path`` (written atomically; about 5 MB of plotly.js plus ~3 KB per animation frame).
    """
    fig = view_figure(
        result, fps=fps, max_frames=max_frames, max_trace_points=max_trace_points, title=title
    )
    html = fig.to_html(include_plotlyjs=True, full_html=True, auto_play=False)
    target = Path(path)
    with atomic_write(target, "w") as fh:
        fh.write(html)
    return target


def view_figure(
    result: PoseResult,
    *,
    fps: float | None = None,
    max_frames: int = 1500,
    max_trace_points: int = 5000,
    title: str | None = None,
):
    """The plotly figure of the viewer (layout in the module docs).

    Parameters
    ----------
    result : PoseResult
        Uses ``joints`` (T, J, 3) and ``joints_std`` (T, J, 3) in ``skeleton.units``, the bones
        and the rig (camera centres and orientations, same units).
    fps : float, optional
        Frame rate (Hz) for a time axis in seconds (frames otherwise).
    max_frames : int
        At most this many animation frames (every k-th frame of longer recordings).
    max_trace_points : int
        At most this many samples per line of the trace panel (every k-th frame of longer
        recordings), which bounds the file size of long recordings.
    title : str, optional

    Returns
    -------
    plotly.graph_objects.Figure
        Traces 0-2 floor and cameras, 3 bones, 4 joints (animated), then per joint 3 × (band,
        mean) of the trace panel, last the time cursor (animated); ``frames`` one per animated
        frame.
    """
    try:
        import plotly.graph_objects as go
        from plotly.subplots import make_subplots
    except ImportError as exc:
        raise ImportError("acm-rs view needs plotly (pip install 'acm-rs[view]')") from exc
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    sk = result.skeleton
    joints = np.asarray(result.joints, float)
    std = np.asarray(result.joints_std, float)
    n_t, n_j = joints.shape[:2]
    if n_t == 0:
        raise ValueError("the result has no frames")
    sd = np.sqrt(np.sum(std**2, axis=-1))  # (T, J) total SD of each joint
    units = sk.units or "units"
    finite_sd = sd[np.isfinite(sd)]
    sd_max = float(np.percentile(finite_sd, 99)) if finite_sd.size else 1.0
    sd_max = sd_max if sd_max > 0 else 1.0
    step = max(1, int(np.ceil(n_t / max_frames)))
    shown = np.arange(0, n_t, step)
    time = np.arange(n_t) / fps if fps else np.arange(n_t, dtype=float)
    tlabel = "time (s)" if fps else "frame"
    bones = np.asarray(sk.bones)

    fig = make_subplots(
        rows=1, cols=2, column_widths=[0.6, 0.4], horizontal_spacing=0.06,
        specs=[[{"type": "scene"}, {"type": "xy"}]],
        subplot_titles=("3D skeleton (joint colour: posterior SD)", "joint trace (mean ± 2 SD)"),
    )  # fmt: skip

    # -- static scene: floor and cameras
    finite = joints[np.isfinite(joints).all(axis=-1)]
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    span = float(np.max(hi - lo)) or 1.0
    centers = np.array([c.center for c in result.rig])
    up = _up(finite, centers)
    floor = _floor(finite, up, pad=0.25 * span)
    fig.add_trace(
        go.Mesh3d(
            x=floor[:, 0], y=floor[:, 1], z=floor[:, 2], i=[0, 0], j=[1, 2], k=[2, 3],
            color="rgb(200,200,200)", opacity=0.5, name="floor", hoverinfo="name",
            showscale=False,
        ),
        row=1, col=1,
    )  # fmt: skip
    cx, cy, cz = _camera_lines(result.rig, 0.08 * max(span, float(np.ptp(centers, axis=0).max())))
    fig.add_trace(
        go.Scatter3d(x=cx, y=cy, z=cz, mode="lines", line={"color": "rgb(90,90,90)", "width": 2},
                     name="cameras", hoverinfo="skip"),
        row=1, col=1,
    )  # fmt: skip
    fig.add_trace(
        go.Scatter3d(
            x=centers[:, 0], y=centers[:, 1], z=centers[:, 2], mode="markers+text",
            marker={"size": 3, "color": "rgb(90,90,90)"},
            text=[c.name or f"cam{i}" for i, c in enumerate(result.rig)], name="camera names",
            hoverinfo="text",
        ),
        row=1, col=1,
    )  # fmt: skip

    # -- animated traces: bones, joints (indices 3, 4) and the time cursor (last trace)
    # bone coordinates to 1e-4 of the animal's extent (0.1 mm for a rat in cm)
    decimals = max(0, 3 - int(np.floor(np.log10(span))))
    t0 = int(shown[0])
    bx, by, bz = _bone_xyz(joints[t0], bones, decimals)
    fig.add_trace(
        go.Scatter3d(x=bx, y=by, z=bz, mode="lines", line={"color": BONE_COLOR, "width": 10},
                     name="bones", hoverinfo="skip"),
        row=1, col=1,
    )  # fmt: skip
    fig.add_trace(
        go.Scatter3d(
            x=joints[t0, :, 0], y=joints[t0, :, 1], z=joints[t0, :, 2], mode="markers",
            marker={
                "size": 4, "color": sd[t0], "colorscale": _SD_SCALE, "cmin": 0.0,
                "cmax": sd_max,
                "colorbar": {"title": f"SD ({units})", "x": -0.01, "xanchor": "right", "len": 0.6},
            },
            text=list(sk.joint_names), name="joints",
            hovertemplate=f"%{{text}}: SD %{{marker.color:.3g}} {units}<extra></extra>",
        ),
        row=1, col=1,
    )  # fmt: skip

    # -- trace panel: per joint x, y, z mean and ±2 SD band; a drop-down picks the joint
    n_static = 5
    keep = slice(None, None, max(1, int(np.ceil(n_t / max(1, max_trace_points)))))
    tt = time[keep]
    for j in range(n_j):
        for a in range(3):
            m, s = joints[keep, j, a], std[keep, j, a]
            visible = j == 0
            fig.add_trace(
                go.Scatter(
                    x=np.concatenate([tt, tt[::-1]]),
                    y=np.concatenate([m + 2 * s, (m - 2 * s)[::-1]]),
                    fill="toself", fillcolor=_AXIS_COLORS[a].replace("rgb", "rgba")[:-1] + ",0.25)",
                    line={"width": 0}, hoverinfo="skip", showlegend=False, visible=visible,
                ),
                row=1, col=2,
            )  # fmt: skip
            fig.add_trace(
                go.Scatter(x=tt, y=m, mode="lines", line={"color": _AXIS_COLORS[a], "width": 1.5},
                           name=f"{'xyz'[a]}", visible=visible, legendgroup="xyz"[a],
                           showlegend=True),
                row=1, col=2,
            )  # fmt: skip
    lo_y, hi_y = float(np.nanmin(joints)), float(np.nanmax(joints))
    fig.add_trace(
        go.Scatter(x=[time[t0], time[t0]], y=[lo_y, hi_y], mode="lines",
                   line={"color": "black", "width": 1, "dash": "dot"}, name="frame shown",
                   showlegend=False, hoverinfo="skip"),
        row=1, col=2,
    )  # fmt: skip
    cursor = len(fig.data) - 1
    per_joint = 6
    buttons = []
    for j, name in enumerate(sk.joint_names):
        vis = [True] * n_static + [False] * (n_j * per_joint) + [True]
        vis[n_static + j * per_joint : n_static + (j + 1) * per_joint] = [True] * per_joint
        buttons.append(
            {"label": name, "method": "update",
             "args": [{"visible": vis}, {"yaxis.title.text": f"{name} ({units})"}]}
        )  # fmt: skip

    frames = []
    for t in shown:
        t = int(t)
        bx, by, bz = _bone_xyz(joints[t], bones, decimals)
        joints_t = go.Scatter3d(
            x=joints[t, :, 0], y=joints[t, :, 1], z=joints[t, :, 2],
            marker={"color": sd[t]},
        )  # fmt: skip
        cursor_t = go.Scatter(x=[time[t], time[t]], y=[lo_y, hi_y])
        bones_t = go.Scatter3d(x=bx, y=by, z=bz)
        frames.append(
            go.Frame(name=str(t), data=[bones_t, joints_t, cursor_t], traces=[3, 4, cursor])
        )
    fig.frames = frames
    label = (lambda t: f"{time[t]:.2f} s") if fps else (lambda t: str(t))
    slider = {
        "active": 0, "x": 0.14, "len": 0.84, "y": -0.02, "currentvalue": {"prefix": f"{tlabel}: "},
        "steps": [
            {"label": label(int(t)), "method": "animate",
             "args": [[str(int(t))], {"mode": "immediate", "frame": {"duration": 0, "redraw": True},
                                      "transition": {"duration": 0}}]}
            for t in shown
        ],
    }  # fmt: skip
    delay = max(10, int(1000 * step / fps)) if fps else 40
    play = {
        "type": "buttons", "direction": "left", "x": 0.0, "y": -0.02, "xanchor": "left",
        "yanchor": "top", "pad": {"t": 30},
        "buttons": [
            {"label": "▶ play", "method": "animate",
             "args": [None, {"frame": {"duration": delay, "redraw": True}, "fromcurrent": True,
                             "transition": {"duration": 0}}]},
            {"label": "❚❚ pause", "method": "animate",
             "args": [[None], {"mode": "immediate", "frame": {"duration": 0, "redraw": False}}]},
        ],
    }  # fmt: skip
    menu = {"buttons": buttons, "x": 0.62, "y": 1.08, "xanchor": "left", "active": 0}
    # the view holds the animal's whole path and the cameras
    everything = np.vstack([floor, centers, finite])
    box_lo, box_hi = everything.min(axis=0), everything.max(axis=0)
    margin = 0.05 * float(np.max(box_hi - box_lo))
    box_lo, box_hi = box_lo - margin, box_hi + margin
    fig.update_layout(
        title=title or f"acm-rs: {sk.name}, {n_t} frames ({result.info.get('method', '?')})",
        updatemenus=[play, menu], sliders=[slider], height=720, template="plotly_white",
        scene={
            "aspectmode": "data",
            "xaxis": {"title": f"x ({units})", "range": [box_lo[0], box_hi[0]]},
            "yaxis": {"title": f"y ({units})", "range": [box_lo[1], box_hi[1]]},
            "zaxis": {"title": f"z ({units})", "range": [box_lo[2], box_hi[2]]},
            "camera": _eye(centers, finite.mean(axis=0), up),
        },
        legend={"x": 1.0, "y": 1.0},
        margin={"l": 90, "r": 10, "t": 90, "b": 60},
    )  # fmt: skip
    fig.update_xaxes(title_text=tlabel, row=1, col=2)
    fig.update_yaxes(title_text=f"{sk.joint_names[0]} ({units})", row=1, col=2)
    return fig
