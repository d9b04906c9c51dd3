"""Board detection with OpenCV, from image folders or videos, with a detection cache.

Frames are matched across cameras by index (the i-th image / the i-th sampled video frame of
every camera is one board view). Detections are stored in an NPZ cache (format in
``docs/calibration.md``); a re-run with the same sources, board and stride loads it instead of
detecting again.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._io import atomic_write
from .board import BoardSpec

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
CACHE_VERSION = 1
#: Fewest corners of one board detection that are kept (a homography needs 4).
MIN_CORNERS = 4


def detect_board(image: np.ndarray, spec: BoardSpec) -> np.ndarray:
    """Detect the board's corners in one image.

    Parameters
    ----------
    image : numpy.ndarray, shape (h, w) or (h, w, 3)
        8-bit grey or BGR image.
    spec : BoardSpec

    Returns
    -------
    numpy.ndarray, shape (n_points, 2)
        Sub-pixel corner positions (px, OpenCV convention: pixel centres at integers) in the
        order of ``spec.board_points``; NaN rows for corners not found (all NaN when the board
        was not found or fewer than ``MIN_CORNERS`` corners were).
    """
    import cv2

    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if gray.dtype != np.uint8:
        raise ValueError(f"images must be 8-bit, got {gray.dtype}")
    out = np.full((spec.n_points, 2), np.nan)
    if spec.board_type == "checkerboard":
        flags = (
            cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
        )
        found, corners = cv2.findChessboardCorners(gray, spec.inner_corners, flags=flags)
        if not found or corners is None:
            return out
        corners = corners.reshape(-1, 2).astype(np.float32)
        # Sub-pixel half-window: well inside one (foreshortened) square, so that it never
        # reaches a neighbouring corner.
        nx, ny = spec.inner_corners
        grid = corners.reshape(ny, nx, 2)
        spacing = min(
            np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
            np.linalg.norm(np.diff(grid, axis=0), axis=2).min(),
        )
        win = int(np.clip(spacing * 0.3, 2, 11))
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        corners = cv2.cornerSubPix(gray, corners.reshape(-1, 1, 2), (win, win), (-1, -1), criteria)
        out[:] = corners.reshape(-1, 2)
        return out
    detector = _charuco_detector(spec)
    ch_corners, ch_ids, _, _ = detector.detectBoard(gray)
    if ch_ids is None or len(ch_ids) < MIN_CORNERS:
        return out
    out[np.asarray(ch_ids).ravel()] = np.asarray(ch_corners, dtype=np.float64).reshape(-1, 2)
    return out


_DETECTORS: dict[str, object] = {}


def _charuco_detector(spec: BoardSpec):
    import cv2

    key = spec.key()
    if key not in _DETECTORS:
        _DETECTORS[key] = cv2.aruco.CharucoDetector(spec.cv_board())
    return _DETECTORS[key]


# -- frame sources --------------------------------------------------------------------------
def _natural_key(p: Path) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def list_images(folder: str | Path) -> list[Path]:
    """Image files of a folder in natural order (``img2`` before ``img10``)."""
    d = Path(folder)
    if not d.is_dir():
        raise ValueError(f"{d} is not a folder")
    files = sorted((p for p in d.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
    if not files:
        raise ValueError(f"{d} contains no images ({', '.join(IMAGE_SUFFIXES)})")
    return files


def _video_frames(path: Path, stride: int) -> Iterator[np.ndarray]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ValueError(f"cannot open video {path}")
    try:
        i = 0
        while True:
            if i % stride == 0:
                ok, frame = cap.read()
                if not ok:
                    return
                yield frame
            elif not cap.grab():
                return
            i += 1
    finally:
        cap.release()


def _video_length(path: Path) -> int:
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        return int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        cap.release()


@dataclass
class Detections:
    """Board detections of several cameras on one frame axis.

    Attributes
    ----------
    corners : numpy.ndarray, shape (n_cams, n_frames, n_points, 2)
        Pixels; NaN where a corner was not detected.
    image_sizes : numpy.ndarray, shape (n_cams, 2), int
        ``(width, height)`` of each camera's images.
    camera_names : list of str
    sources : list of str
        The image folder or video of each camera.
    """

    corners: np.ndarray
    image_sizes: np.ndarray
    camera_names: list[str]
    sources: list[str]

    @property
    def n_boards(self) -> np.ndarray:
        """(n_cams,) number of frames in which each camera detected the board."""
        return np.sum(np.any(np.isfinite(self.corners[..., 0]), axis=2), axis=1)


def detect(
    sources: Sequence[str | Path],
    spec: BoardSpec,
    *,
    kind: str = "auto",
    stride: int = 1,
    camera_names: Sequence[str] | None = None,
    cache: str | Path | None = None,
    progress: bool | None = False,
) -> Detections:
    """Detect the board in every camera's images or video.

    Parameters
    ----------
    sources : sequence of path
        One image folder or video file per camera.
    spec : BoardSpec
    kind : {"auto", "images", "videos"}
        Source type; ``auto`` takes folders as image folders and files as videos.
    stride : int
        Use every ``stride``-th image / video frame (>= 1).
    camera_names : sequence of str, optional
        Default: the folder names / video file stems.
    cache : path, optional
        NPZ detection cache: loaded when it matches ``sources``, ``spec`` and ``stride``,
        written (atomically) otherwise.
    progress : bool or None
        Show a tqdm progress bar per camera; None: only when stderr is a terminal.

    Returns
    -------
    Detections

    Raises
    ------
    ValueError
        Missing sources, unreadable videos, no images, or a board detected in no frame at all
        (the message lists what to check).
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    paths = [Path(s) for s in sources]
    if not paths:
        raise ValueError("give at least one image folder or video")
    for p in paths:
        if not p.exists():
            raise ValueError(f"{p} does not exist")
    names = (
        list(camera_names)
        if camera_names is not None
        else [p.name if p.is_dir() else p.stem for p in paths]
    )
    if len(names) != len(paths):
        raise ValueError(f"{len(names)} camera names for {len(paths)} sources")
    if len(set(names)) != len(names):
        raise ValueError(f"camera names must be unique, got {names} (pass camera_names)")
    srcs = [str(p.resolve()) for p in paths]
    if cache is not None and Path(cache).exists():
        cached = load_cache(cache)
        if (
            cached is not None
            and cached[1] == spec.key()
            and cached[2] == stride
            and cached[0].sources == srcs
        ):
            det = cached[0]
            det.camera_names = names
            return det
    per_cam, sizes = [], []
    for name, p in zip(names, paths, strict=True):
        is_images = p.is_dir() if kind == "auto" else kind == "images"
        if is_images:
            files = list_images(p)[::stride]
            frames: Iterator[np.ndarray] = (_read_image(f) for f in files)
            total = len(files)
        else:
            frames = _video_frames(p, stride)
            n = _video_length(p)
            total = -(-n // stride) if n > 0 else None
        rows, size = [], None
        for img in _progress(frames, total, f"detect {name}", progress):
            if size is None:
                size = (img.shape[1], img.shape[0])
            elif size != (img.shape[1], img.shape[0]):
                raise ValueError(f"{p}: image size changes from {size} to {img.shape[1::-1]}")
            rows.append(detect_board(img, spec))
        if size is None:
            raise ValueError(f"{p}: no frames could be read")
        per_cam.append(np.stack(rows))
        sizes.append(size)
    n_frames = min(len(c) for c in per_cam)
    if any(len(c) != n_frames for c in per_cam):
        counts = {n: len(c) for n, c in zip(names, per_cam, strict=True)}
        warnings.warn(
            f"cameras have different numbers of frames {counts}; using the first {n_frames}",
            stacklevel=2,
        )
    corners = np.stack([c[:n_frames] for c in per_cam])
    det = Detections(corners, np.asarray(sizes, dtype=np.int64), names, srcs)
    if not det.n_boards.any():
        raise ValueError(no_boards_message(spec))
    if cache is not None:
        save_cache(cache, det, spec, stride)
    return det


def no_boards_message(spec: BoardSpec) -> str:
    """The '0 boards detected' error text, with what to check."""
    hints = [f"board_size = {list(spec.squares)} counts squares, not inner corners"]
    if spec.board_type == "charuco":
        hints.append(
            f"the dictionary (DICT_{spec.marker_bits}X{spec.marker_bits}_{spec.dict_number}: "
            "board_marker_bits, board_marker_dict_number)"
        )
        hints.append(
            f"legacy_pattern (now {str(spec.legacy_pattern).lower()}; boards made with OpenCV "
            "< 4.6 need true)"
        )
    else:
        hints.append("board_type (a ChArUco board is not found as a checkerboard)")
    return "0 boards detected in any camera; check " + "; ".join(hints)


def _read_image(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ValueError(f"cannot read image {path}")
    return img


def _progress(it, total, desc: str, enabled: bool | None):
    if enabled is False:
        return it
    from tqdm.auto import tqdm

    disable = None if enabled is None else False  # None: a bar only on a terminal
    return tqdm(it, total=total, desc=desc, unit="frame", disable=disable)


# -- cache ----------------------------------------------------------------------------------
def save_cache(path: str | Path, det: Detections, spec: BoardSpec, stride: int) -> None:
    """Write detections to an NPZ cache (atomically; format in ``docs/calibration.md``)."""
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(
            fh,
            format_version=np.int64(CACHE_VERSION),
            corners=det.corners,
            image_sizes=det.image_sizes,
            camera_names=np.array(det.camera_names, dtype=str),
            sources=np.array(det.sources, dtype=str),
            board=np.array(spec.key()),
            stride=np.int64(stride),
        )


def load_cache(path: str | Path) -> tuple[Detections, str, int] | None:
    """Read a detection cache → ``(detections, board key, stride)``; None if unreadable or of
    another format version (it is then rebuilt)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["format_version"]) != CACHE_VERSION:
                return None
            det = Detections(
                np.asarray(z["corners"], dtype=np.float64),
                np.asarray(z["image_sizes"], dtype=np.int64),
                [str(s) for s in z["camera_names"]],
                [str(s) for s in z["sources"]],
            )
            return det, str(z["board"]), int(z["stride"])
    except (OSError, KeyError, ValueError):
        return None
