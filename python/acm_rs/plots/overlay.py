"""Videos with the reprojected skeleton drawn over the recordings (OpenCV)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .tracking import STATUS_GATED, _status

if TYPE_CHECKING:  # pragma: no cover
    from ..tracking import PoseResult

# BGR colours
_LEFT, _RIGHT, _CENTRE = (60, 60, 230), (230, 120, 40), (200, 200, 200)
_MARKER, _DETECTION, _GATED = (80, 220, 80), (0, 200, 255), (0, 0, 255)


def _cv2():
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("overlay videos need OpenCV: pip install opencv-python-headless") from exc
    return cv2


def _bone_colors(result: PoseResult) -> list[tuple[int, int, int]]:
    out = []
    for name in result.skeleton.bone_names:
        out.append(_LEFT if "left" in name else _RIGHT if "right" in name else _CENTRE)
    return out


def _video_list(result: PoseResult, video_paths: Sequence | Mapping) -> list[Path]:
    names = [cam.name for cam in result.rig]
    if isinstance(video_paths, Mapping):
        missing = [n for n in names if n not in video_paths]
        if missing:
            raise ValueError(
                f"no video for camera(s) {missing}; video_paths has keys {list(video_paths)}"
            )
        paths = [Path(video_paths[n]) for n in names]
    else:
        paths = [Path(p) for p in video_paths]
        if len(paths) != len(names):
            raise ValueError(
                f"got {len(paths)} video(s) for {len(names)} cameras {names}; pass one per camera"
                " in rig order or a mapping camera name -> path"
            )
    for p in paths:
        if not p.is_file():
            raise ValueError(f"video not found: {p}")
    return paths


def _open(cv2, path: Path, n_frames: int):
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ValueError(f"cannot read video {path} (unsupported format or corrupt file)")
    count = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
    if count != n_frames:
        cap.release()
        raise ValueError(
            f"video {path} has {count} frames but the result has {n_frames}; "
            "overlay the video the detections came from (trim it to the tracked range)"
        )
    size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    return cap, size, float(cap.get(cv2.CAP_PROP_FPS))


def _scale(cam, size: tuple[int, int], path: Path) -> float:
    """Factor from calibrated pixels to video pixels (1 if the camera size is unknown)."""
    if cam.size is None:
        return 1.0
    sx, sy = size[0] / cam.size[0], size[1] / cam.size[1]
    if abs(sx - sy) > 0.01 * max(sx, sy):
        raise ValueError(
            f"video {path} is {size[0]}x{size[1]} px but camera {cam.name!r} was calibrated at "
            f"{cam.size[0]}x{cam.size[1]}; only uniformly scaled videos can be overlaid"
        )
    return float(sx)


def _draw(cv2, img, bones, colors, joints, markers, det, gated, scale):
    """Draw one camera's frame in place; all coordinates in calibrated pixels."""
    h, w = img.shape[:2]
    thick = max(1, round(2 * max(w, h) / 1280))
    radius = max(2, round(4 * max(w, h) / 1280))

    def pt(p):  # pixel centres at integers in both images
        return int(round((p[0] + 0.5) * scale - 0.5)), int(round((p[1] + 0.5) * scale - 0.5))

    def inside(p):
        return (
            np.all(np.isfinite(p)) and -w <= p[0] * scale <= 2 * w and -h <= p[1] * scale <= 2 * h
        )

    # detections first so the skeleton stays visible; gated outliers last, on top
    order = np.argsort(np.asarray(gated, dtype=bool), kind="stable")
    for k in order:
        if inside(det[k]):
            color = _GATED if gated[k] else _DETECTION
            cv2.drawMarker(img, pt(det[k]), color, cv2.MARKER_CROSS, 3 * radius, thick)
    for (s, e), c in zip(bones, colors, strict=True):
        if inside(joints[s]) and inside(joints[e]):
            cv2.line(img, pt(joints[s]), pt(joints[e]), c, thick, cv2.LINE_AA)
    for m in markers:
        if inside(m):
            cv2.circle(img, pt(m), radius, _MARKER, -1, cv2.LINE_AA)


def overlay_video(
    result: PoseResult,
    video_paths: Sequence[str | os.PathLike] | Mapping[str, str | os.PathLike],
    out_path: str | os.PathLike,
    *,
    frames: Sequence[int] | None = None,
    fps: float | None = None,
    tile: bool = True,
) -> list[Path]:
    """Draw the reprojected skeleton and the detections over each camera's video.

    On every frame: bones of the posterior mean pose projected into the camera as lines (left
    red, right blue, centre grey), its markers as green dots, the detections as crosses (orange
    when used, red when rejected by the innovation gate). Videos may be uniformly downscaled
    copies of the calibrated images (e.g. 320x256 for a 1280x1024 camera): the drawing is
    scaled to the video size. Output is MP4 (``mp4v``), written under a temporary name in the
    target folder and renamed when complete, so a crash never leaves a truncated file.

    Parameters
    ----------
    result : PoseResult
        Tracking result with T frames and ``n_cams`` cameras.
    video_paths : sequence of path, or mapping camera name -> path
        One video per camera (rig order for a sequence), each with exactly T frames.
    out_path : path
        ``tile=True``: the output file (``.mp4`` appended if it has another suffix).
        ``tile=False``: the base name; camera ``c`` goes to ``<stem>_<c>.mp4`` beside it.
    frames : sequence of int, optional
        Increasing frame indices to render (default: all T).
    fps : float, optional
        Frame rate of the output (default: that of the first video, 30 if unknown).
    tile : bool
        One video with the cameras in a grid of 2 columns (each tile the size of the first
        video) instead of one video per camera.

    Returns
    -------
    list of Path
        The videos written.

    Raises
    ------
    ValueError
        A missing or unreadable video (named), a wrong number of videos, a video whose frame
        count differs from T or whose size is not a scaled copy of the calibrated image size,
        bad frame indices.
    """
    cv2 = _cv2()
    n = result.n_frames
    paths = _video_list(result, video_paths)
    if frames is None:
        frames = range(n)
    sel = np.asarray(list(frames), dtype=np.int64)
    if sel.size == 0:
        raise ValueError("select at least one frame")
    if sel.min() < 0 or sel.max() >= n or np.any(np.diff(sel) <= 0):
        raise ValueError(f"frames must be increasing indices in [0, {n})")
    if fps is not None and not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")

    sk = result.skeleton
    rig = result.rig
    proj_markers = result.projected()  # (C, T, M, 2)
    proj_joints = rig.project(result.joints)  # (C, T, J, 2)
    gated = _status(result) == STATUS_GATED  # (C, T, M)
    bones = [tuple(int(i) for i in b) for b in sk.bones]
    colors = _bone_colors(result)

    caps, sizes, scales = [], [], []
    try:
        for cam, p in zip(rig, paths, strict=True):
            cap, size, video_fps = _open(cv2, p, n)
            caps.append(cap)
            sizes.append(size)
            scales.append(_scale(cam, size, p))
            if fps is None:
                fps = video_fps if video_fps > 0 else 30.0

        out = Path(out_path)
        names = [cam.name or f"camera{i}" for i, cam in enumerate(rig)]
        if tile:
            targets = [out if out.suffix.lower() == ".mp4" else out.with_name(out.name + ".mp4")]
            tw, th = sizes[0]
            cols = min(2, len(caps))
            rows = int(np.ceil(len(caps) / cols))
            out_sizes = [(tw * cols, th * rows)]
        else:
            stem = out.with_suffix("") if out.suffix.lower() == ".mp4" else out
            targets = [stem.with_name(f"{stem.name}_{c}.mp4") for c in names]
            out_sizes = list(sizes)
        for t in targets:
            t.parent.mkdir(parents=True, exist_ok=True)
        temps = [t.with_name(f".{t.stem}.{os.getpid()}.tmp.mp4") for t in targets]
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")
        writers = [
            cv2.VideoWriter(str(tmp), fourcc, float(fps), s)
            for tmp, s in zip(temps, out_sizes, strict=True)
        ]
        try:
            for w, t in zip(writers, targets, strict=True):
                if not w.isOpened():
                    raise ValueError(f"OpenCV cannot write MP4 (mp4v) video {t}")
            wanted = set(sel.tolist())
            for f in range(int(sel.max()) + 1):
                imgs = []
                for c, cap in enumerate(caps):
                    if f not in wanted:
                        if not cap.grab():
                            raise ValueError(f"video {paths[c]} ended early at frame {f}")
                        continue
                    ok, img = cap.read()
                    if not ok:
                        raise ValueError(f"video {paths[c]} ended early at frame {f}")
                    _draw(
                        cv2, img, bones, colors, proj_joints[c, f], proj_markers[c, f],
                        result.detections[c, f], gated[c, f], scales[c],
                    )  # fmt: skip
                    imgs.append(img)
                if f not in wanted:
                    continue
                if tile:
                    canvas = np.zeros((out_sizes[0][1], out_sizes[0][0], 3), np.uint8)
                    for c, img in enumerate(imgs):
                        if img.shape[:2] != (th, tw):
                            img = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
                        r0, c0 = (c // cols) * th, (c % cols) * tw
                        canvas[r0 : r0 + th, c0 : c0 + tw] = img
                        cv2.putText(
                            canvas, names[c], (c0 + 8, r0 + 20), cv2.FONT_HERSHEY_SIMPLEX,
                            0.5, (255, 255, 255), 1, cv2.LINE_AA,
                        )  # fmt: skip
                    writers[0].write(canvas)
                else:
                    for w, img in zip(writers, imgs, strict=True):
                        w.write(img)
        except BaseException:
            for w in writers:
                w.release()
            for tmp in temps:
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
            raise
        for w in writers:
            w.release()
        for tmp, t in zip(temps, targets, strict=True):
            os.replace(tmp, t)
        return targets
    finally:
        for cap in caps:
            cap.release()
