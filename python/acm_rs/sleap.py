"""SLEAP files: predictions or labels as ``.slp`` and analysis ``.h5``, both read with h5py.

A SLEAP analysis file (``sleap-convert --format analysis``, ``sio.save_analysis_h5``) holds
``tracks`` stored as (n_tracks, 2, n_nodes, n_frames) px, ``point_scores``
(n_tracks, n_nodes, n_frames), ``node_names`` and ``track_names`` as byte strings.

A ``.slp`` file (SLEAP's labels format, read here without sleap-io) holds flat tables:
``frames`` (one row per labelled frame: video, frame_idx, a range of ``instances``),
``instances`` (type 0 = user, 1 = predicted; skeleton, track (-1 = none), from_predicted,
a range of ``points`` or ``pred_points``), ``points``/``pred_points`` (x, y, visible, complete
[, score]), ``tracks_json``, ``videos_json`` and the JSON attribute of ``metadata``
(``nodes``; each skeleton lists its nodes as indices into them, in the order its points are
stored). Each instance is looked up by its own track, so a track is never given another
track's points (issue 27 item 3).

Both readers return what :func:`acm_rs.dlc.read_dlc_table` returns, so label files of SLEAP,
DeepLabCut and Lightning Pose can be mixed per camera.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["SlpFile", "is_sleap_analysis", "read_sleap_analysis", "read_slp", "read_slp_file"]


def _names(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).ravel()]


def _pick_track(p: Path, tracks: list[str], individual: str | None) -> int:
    if individual is not None:
        if individual not in tracks:
            raise ValueError(f"{p}: no track {individual!r}; tracks: {tracks}")
        return tracks.index(individual)
    if len(tracks) > 1:
        raise ValueError(
            f"{p}: several tracks {tracks}; choose one with individual= (project.individual "
            "in config.toml, --individual on the command line)"
        )
    return 0


def is_sleap_analysis(path: str | Path) -> bool:
    """True if ``path`` is an HDF5 file with SLEAP's analysis datasets (``tracks``,
    ``node_names``); False for other files (e.g. DeepLabCut's PyTables ``.h5``)."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "tracks" in f and "node_names" in f
    except OSError:
        return False


def read_sleap_analysis(path: str | Path, individual: str | None = None):
    """Read a SLEAP analysis ``.h5`` file.

    Parameters
    ----------
    path : path
    individual : str, optional
        Track name; required when the file has several tracks.

    Returns
    -------
    points : numpy.ndarray, shape (n_frames, n_nodes, 2)
        Pixels, NaN where the node was not predicted.
    likelihood : numpy.ndarray, shape (n_frames, n_nodes)
        SLEAP's point scores clipped to [0, 1] (they are confidence-map peaks and exceed 1
        for many good points: up to ~1.35); 1 for points of user (proofread) instances,
        which SLEAP stores without a score (NaN); NaN where not predicted.
    frames : numpy.ndarray of int, shape (n_frames,)
        0, 1, ... (analysis files hold every frame of the video from 0).
    bodyparts : list of str
        Node names.
    """
    import h5py

    p = Path(path)
    with h5py.File(p, "r") as f:
        if "tracks" not in f or "node_names" not in f:
            raise ValueError(f"{p}: not a SLEAP analysis file (no 'tracks'/'node_names')")
        tracks = np.asarray(f["tracks"], dtype=float)  # (n_tracks, 2, n_nodes, n_frames)
        nodes = _names(f["node_names"][()])
        track_names = _names(f["track_names"][()]) if "track_names" in f else []
        scores = np.asarray(f["point_scores"], dtype=float) if "point_scores" in f else None
    if tracks.ndim != 4 or tracks.shape[1] != 2 or tracks.shape[2] != len(nodes):
        raise ValueError(
            f"{p}: 'tracks' has shape {tracks.shape}; expected (n_tracks, 2, {len(nodes)} nodes, "
            "n_frames) as SLEAP writes it"
        )
    names = track_names or [f"track_{i}" for i in range(tracks.shape[0])]
    k = _pick_track(p, names, individual) if tracks.shape[0] else None
    if k is None:
        raise ValueError(f"{p}: no tracks")
    points = tracks[k].transpose(2, 1, 0)  # (n_frames, n_nodes, 2)
    seen = np.isfinite(points[..., 0])
    if scores is not None:
        lik = _scores_as_likelihood(scores[k].T.copy(), seen)
    else:
        lik = np.where(seen, 1.0, np.nan)
    frames = np.arange(points.shape[0], dtype=np.int64)
    return np.ascontiguousarray(points), lik, frames, nodes


def _scores_as_likelihood(scores: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """SLEAP point scores as likelihoods in [0, 1]: clipped (confidence-map peaks exceed 1),
    1 where a point exists without a score (user-labelled, proofread), NaN where none."""
    with np.errstate(invalid="ignore"):
        lik = np.clip(scores, 0.0, 1.0)
    lik[seen & ~np.isfinite(lik)] = 1.0
    lik[~seen] = np.nan
    return lik


#: SLEAP's instance types (``instances/instance_type``): a user (proofread) instance and a
#: predicted one (sleap-io ``InstanceType``).
USER, PREDICTED = 0, 1
#: First ``format_id`` whose layout this reader does not know (sleap-io refuses it too).
SLP_FORMAT_LIMIT = 3.0


@dataclass(frozen=True)
class SlpFile:
    """The tables of a SLEAP ``.slp`` file that 2D tracking needs (see the module docs).

    Attributes
    ----------
    path : Path
    format_id : float
        ``metadata`` attribute ``format_id``; below 1.1 coordinates were stored with the
        pixel's corner at 0 and are shifted by -0.5 here, as SLEAP and sleap-io do.
    nodes : list of str
        Node names of the skeleton, in the order its points are stored.
    tracks : list of str
        Track names (``tracks_json``), index = ``instances/track``.
    videos : list of str
        Video file names (``videos_json``), index = ``frames/video``.
    frames, instances : numpy structured arrays
        The ``frames`` and ``instances`` tables as stored.
    points, pred_points : numpy.ndarray, shape (n, 2)
        Pixels of user and predicted points; NaN where not visible.
    pred_scores : numpy.ndarray, shape (n,)
        Scores of predicted points (confidence-map peaks, may exceed 1).
    sessions : list of dict
        ``sessions_json`` decoded (SLEAP multi-camera sessions), empty without.
    session_data : dict of numpy arrays
        The ``session_data`` group of sleap-io's format 2.8+ (instance groups), else empty.
    """

    path: Path
    format_id: float
    nodes: list[str]
    tracks: list[str]
    videos: list[str]
    frames: np.ndarray
    instances: np.ndarray
    points: np.ndarray
    pred_points: np.ndarray
    pred_scores: np.ndarray
    sessions: list[dict]
    session_data: dict


def _json_rows(f, name: str) -> list:
    if name not in f:
        return []
    return [json.loads(r.decode() if isinstance(r, bytes) else r) for r in f[name][()]]


def _video_name(d: dict) -> str:
    backend = d.get("backend") or {}
    name = d.get("filename") or backend.get("filename") or ""
    if isinstance(name, list):  # image sequences: a list of files
        name = name[0] if name else ""
    return Path(str(name).replace("\\", "/")).name


def _skeleton_nodes(p: Path, meta: dict) -> list[str]:
    """Node names of the file's one skeleton in point order: each skeleton lists its nodes as
    indices into ``metadata.nodes`` (SLEAP >= 1.3.2 nests the graph under ``nx_graph``)."""
    skeletons = meta.get("skeletons") or []
    if len(skeletons) != 1:
        raise ValueError(f"{p}: {len(skeletons)} skeletons; acm-rs reads SLEAP files with one")
    names = [n["name"] for n in meta.get("nodes", [])]
    graph = skeletons[0].get("nx_graph", skeletons[0])
    ids = [n["id"] for n in graph.get("nodes", [])]
    if not ids or any(not isinstance(i, int) or not 0 <= i < len(names) for i in ids):
        raise ValueError(f"{p}: the skeleton's nodes do not index metadata 'nodes'")
    return [names[i] for i in ids]


def _xy(table: np.ndarray, shift: float) -> np.ndarray:
    """(n, 2) pixels of a ``points``/``pred_points`` table, NaN where not visible."""
    xy = np.stack([table["x"], table["y"]], axis=1).astype(np.float64) - shift
    xy[~table["visible"].astype(bool)] = np.nan
    return xy


def read_slp_file(path: str | Path) -> SlpFile:
    """Read the tables of a SLEAP ``.slp`` file with h5py (no sleap-io needed).

    Raises
    ------
    ValueError
        Not an HDF5 file, not a SLEAP labels file, a format newer than this reader knows,
        several skeletons, or instances whose point count differs from the skeleton's.
    """
    import h5py

    p = Path(path)
    try:
        f = h5py.File(p, "r")
    except OSError:
        raise ValueError(f"{p}: not an HDF5 file (damaged or not a SLEAP .slp)") from None
    with f:
        need = [k for k in ("metadata", "frames", "instances", "videos_json") if k not in f]
        if need:
            raise ValueError(f"{p}: not a SLEAP labels file (no {need})")
        attrs = f["metadata"].attrs
        fmt = float(attrs.get("format_id", 1.0))
        if fmt >= SLP_FORMAT_LIMIT:
            raise ValueError(
                f"{p}: SLP format {fmt:g} is newer than acm-rs reads (< {SLP_FORMAT_LIMIT:g}); "
                "export an analysis .h5 from SLEAP (File > Export Analysis HDF5)"
            )
        raw = attrs.get("json")
        meta = json.loads(raw.decode() if isinstance(raw, bytes) else str(raw)) if raw else {}
        nodes = _skeleton_nodes(p, meta)
        frames, instances = f["frames"][()], f["instances"][()]
        empty = np.zeros(0, dtype=[("x", "f8"), ("y", "f8"), ("visible", "?"), ("score", "f8")])
        pts = f["points"][()] if "points" in f else empty
        pred = f["pred_points"][()] if "pred_points" in f else empty
        tracks = [
            str(t[1]) if isinstance(t, list) else str(t) for t in _json_rows(f, "tracks_json")
        ]
        videos = [_video_name(v) for v in _json_rows(f, "videos_json")]
        sessions = _json_rows(f, "sessions_json")
        session_data = (
            {k: f["session_data"][k][()] for k in f["session_data"]} if "session_data" in f
            else {}
        )  # fmt: skip
    # SLEAP < 1.1 (format_id < 1.1) put the pixel's top-left corner at 0 (sleap-io shifts too)
    shift = 0.5 if fmt < 1.1 else 0.0
    n = instances["point_id_end"].astype(np.int64) - instances["point_id_start"]
    if n.size and (n != len(nodes)).any():
        raise ValueError(f"{p}: instances with {sorted(set(n.tolist()))} points for a "
                         f"skeleton of {len(nodes)} nodes")  # fmt: skip
    return SlpFile(
        path=p, format_id=fmt, nodes=nodes, tracks=tracks, videos=videos, frames=frames,
        instances=instances, points=_xy(pts, shift), pred_points=_xy(pred, shift),
        pred_scores=np.asarray(pred["score"], dtype=np.float64) if len(pred) else np.zeros(0),
        sessions=sessions, session_data=session_data,
    )  # fmt: skip


def _video_index(slp: SlpFile, video: int | str | None) -> int:
    n = len(slp.videos)
    if n == 0:
        raise ValueError(f"{slp.path}: no videos in this SLEAP file")
    if video is None:
        if n > 1:
            hint = (" (a multi-camera session: acm-rs init DIR --from-sleap-session FILE.slp "
                    "imports all its views)" if slp.sessions else "")  # fmt: skip
            raise ValueError(f"{slp.path}: {n} videos {slp.videos}; choose one with video={hint}")
        return 0
    if isinstance(video, str):
        names = [v for v in slp.videos if v == Path(video).name]
        if len(names) != 1:
            raise ValueError(f"{slp.path}: no single video named {video!r}; videos: {slp.videos}")
        return slp.videos.index(names[0])
    if not 0 <= int(video) < n:
        raise ValueError(f"{slp.path}: video {video} out of range; the file has {n} videos")
    return int(video)


def instance_table(slp: SlpFile) -> dict[str, np.ndarray]:
    """Per instance: ``video``, ``frame`` (frame index in its video), ``row`` (row of its
    labelled frame in ``frames``), ``track`` (-1 = none), ``user``, ``used``.

    A user instance without a track takes the track of the prediction it was made from
    (``from_predicted``). A predicted instance is not ``used`` when a user instance of its
    frame replaces it (made from it, or of the same track): SLEAP's rule (and sleap-io's
    ``Labels.numpy``) that proofread instances are preferred over predictions.
    """
    ins, fr = slp.instances, slp.frames
    row_of = {int(fid): r for r, fid in enumerate(fr["frame_id"])}
    row = np.array([row_of[int(i)] for i in ins["frame_id"]], dtype=np.int64)
    user = ins["instance_type"] == USER
    track = ins["track"].astype(np.int64)
    idx_of = {int(i): k for k, i in enumerate(ins["instance_id"])}
    src = np.array([idx_of.get(int(i), -1) for i in ins["from_predicted"]], dtype=np.int64)
    inherit = user & (track < 0) & (src >= 0)
    track[inherit] = track[src[inherit]]
    used = np.ones(len(ins), dtype=bool)
    replaced = src[user & (src >= 0)]
    used[replaced[row[replaced] == row[np.flatnonzero(user & (src >= 0))]]] = False
    width = len(slp.tracks) + 2
    user_keys = (row * width + track + 1)[user & (track >= 0)]
    used[~user & (track >= 0) & np.isin(row * width + track + 1, user_keys)] = False
    return {
        "video": fr["video"][row].astype(np.int64), "frame": fr["frame_idx"][row].astype(np.int64),
        "row": row, "track": track, "user": user, "used": used,
    }  # fmt: skip


def _frame_range(slp: SlpFile, v: int) -> int:
    sel = slp.frames["frame_idx"][slp.frames["video"] == v]
    if sel.size == 0:
        raise ValueError(f"{slp.path}: video {v} ({slp.videos[v]}) has no labelled frames")
    return int(sel.max()) + 1


def track_points(
    slp: SlpFile,
    video: int,
    track: int | None,
    n_frames: int | None = None,
    table: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points and scores of one track (or, ``track=None``, of the only instance per frame)
    in one video.

    Returns
    -------
    points : numpy.ndarray, shape (n_frames, n_nodes, 2)
        Pixels; NaN where the track has no instance or a node is not visible.
    scores : numpy.ndarray, shape (n_frames, n_nodes)
        SLEAP's point scores as stored (NaN for user points and where there is no point).

    Raises
    ------
    ValueError
        Two instances of the track (or, untracked, two instances) in one frame.
    """
    t = instance_table(slp) if table is None else table
    n_frames = _frame_range(slp, video) if n_frames is None else n_frames
    sel = (t["video"] == video) & t["used"]
    if track is not None:
        sel &= t["track"] == track
    k = np.flatnonzero(sel)
    frames = t["frame"][k]
    uniq, counts = np.unique(frames, return_counts=True)
    if (counts > 1).any():
        f0 = int(uniq[counts > 1][0])
        what = (f"{int(counts.max())} instances of track {slp.tracks[track]!r}" if track is not None
                else f"{int(counts.max())} untracked instances")  # fmt: skip
        fix = ("fix the tracks in SLEAP" if track is not None else
               "track them in SLEAP (or keep one instance per frame)")  # fmt: skip
        raise ValueError(f"{slp.path}: {what} in frame {f0} of video {video} "
                         f"({slp.videos[video]}); {fix}")  # fmt: skip
    K = len(slp.nodes)
    pts = np.full((n_frames, K, 2), np.nan)
    scores = np.full((n_frames, K), np.nan)
    start = slp.instances["point_id_start"][k].astype(np.int64)
    idx = start[:, None] + np.arange(K)
    user = t["user"][k]
    if user.any():
        pts[frames[user]] = slp.points[idx[user]]
    if (~user).any():
        pts[frames[~user]] = slp.pred_points[idx[~user]]
        scores[frames[~user]] = slp.pred_scores[idx[~user]]
    scores[~np.isfinite(pts[..., 0])] = np.nan
    return pts, scores


def pick_slp_track(slp: SlpFile, individual: str | None, table: dict) -> int | None:
    """Track index for ``individual`` (None: the file is untracked, or has one track).

    Raises ``ValueError`` for an unknown track, a track without any instance, an individual
    asked of an untracked file, or several tracks without ``individual``.
    """
    p, tracks = slp.path, slp.tracks
    if not tracks:
        if individual is not None:
            raise ValueError(
                f"{p}: no tracks (untracked instances), so individual {individual!r} cannot be "
                "chosen; track the file in SLEAP or remove individual / --individual"
            )
        return None
    k = _pick_track(p, tracks, individual)
    present = sorted({tracks[i] for i in np.unique(table["track"][table["used"]]) if i >= 0})
    if k not in set(np.unique(table["track"][table["used"]]).tolist()):
        raise ValueError(
            f"{p}: track {tracks[k]!r} has no instance in this file; tracks with instances: "
            f"{present}"
        )
    return k


def read_slp(path: str | Path, individual: str | None = None, video: int | str | None = None):
    """Read a SLEAP ``.slp`` file (predictions or user labels) with h5py.

    Parameters
    ----------
    path : path
    individual : str, optional
        Track name; required when the file has several tracks. Each frame gives the points
        of the instance with that track (a user instance before the prediction it replaces),
        NaN where the track has none.
    video : int or str, optional
        Which video of a multi-video file (index or file name); required if there are several.

    Returns
    -------
    points, likelihood, frames, bodyparts
        As :func:`read_sleap_analysis` (scores clipped to [0, 1]); user-labelled points have
        likelihood 1. Rows are the frames 0 .. last labelled frame of the video.

    Raises
    ------
    ValueError
        Several tracks without ``individual``; a track absent from the file (naming the
        tracks present); several untracked instances in one frame. A track absent only from
        the chosen video gives NaN with a warning.
    """
    slp = read_slp_file(path)
    v = _video_index(slp, video)
    table = instance_table(slp)
    k = pick_slp_track(slp, individual, table)
    if k is not None:
        here = (table["video"] == v) & table["used"]
        extra = int((here & (table["track"] < 0)).sum())
        if extra:
            warnings.warn(
                f"{slp.path}: {extra} untracked instances of video {v} are not used (only "
                f"track {slp.tracks[k]!r})",
                stacklevel=2,
            )
        if not (here & (table["track"] == k)).any():
            warnings.warn(
                f"{slp.path}: track {slp.tracks[k]!r} has no instance in video {v} "
                f"({slp.videos[v]}); its points there are NaN",
                stacklevel=2,
            )
    points, scores = track_points(slp, v, k, table=table)
    seen = np.isfinite(points[..., 0])
    lik = _scores_as_likelihood(scores, seen)
    frames = np.arange(points.shape[0], dtype=np.int64)
    return points, lik, frames, list(slp.nodes)
