"""SLEAP multi-camera sessions: the calibration and per-view tracks of a ``.slp`` file.

SLEAP (>= 1.4 multi-view) and sleap-io (>= 0.2) store a ``RecordingSession`` in the ``.slp``
dataset ``sessions_json``, one JSON document per session:

* ``calibration``: one table per camera with anipose's keys (``name``, ``size`` = (width,
  height), ``matrix``, ``distortions`` = OpenCV's (k1, k2, p1, p2, k3), ``rotation`` =
  Rodrigues vector and ``translation`` of world -> camera) plus ``metadata``; camera ``i`` is
  the ``i``-th table (the order of the JSON object, as sleap-io's ``make_camera_group``);
* ``camcorder_to_video_idx_map``: camera index -> video index of the file;
* instance groups, the instances of one animal in the views of one frame: inline under
  ``frame_group_dicts`` (``camcorder_to_lf_and_inst_idx_map``: camera -> (labelled frame row,
  instance position in that frame); SLEAP and sleap-io < 2.8 format), or the columnar group
  ``session_data`` of sleap-io's format 2.8 (``frame_groups`` -> ``instance_groups`` ->
  ``instance_group_members`` (camera, lf, inst)).

:func:`read_sleap_session` turns the calibration into a :class:`~acm_rs.camera.CameraRig`
(the same conventions as acm-rs's, no conversion) and the per-view tracks into a
:class:`~acm_rs.dlc.LabelSet`; :func:`write_session_views` writes one SLEAP analysis file per
camera for a project.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera, CameraRig
from .dlc import LabelSet
from .sleap import (
    SlpFile,
    _scores_as_likelihood,
    instance_table,
    pick_slp_track,
    read_slp_file,
    track_points,
)

__all__ = ["SleapSession", "has_sleap_session", "read_sleap_session", "write_session_views"]


@dataclass
class SleapSession:
    """A SLEAP recording session read from a ``.slp`` file.

    Attributes
    ----------
    path : Path
    rig : CameraRig
        The cameras that have a video, in the session's camera order (units not declared:
        SLEAP does not record them; they are the calibration board's).
    videos : list of int
        Video index (in the file) of each camera.
    tracks : list of str
        Track names of the file.
    individual : str or None
        The track read into ``labels`` (None: untracked, one instance per frame).
    labels : LabelSet
        ``points`` (n_cams, n_frames, n_nodes, 2) px, ``likelihood`` (scores clipped to
        [0, 1], 1 for user points), ``frames`` 0 .. last labelled frame, ``bodyparts``.
    n_groups : int
        Instance groups (cross-view links) checked against the tracks.
    notes : list of str
        What was left out (cameras without a video, views without the track).
    """

    path: Path
    rig: CameraRig
    videos: list[int]
    tracks: list[str]
    individual: str | None
    labels: LabelSet
    n_groups: int = 0
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """One line: what was imported."""
        lab = self.labels
        n_pts = int(np.isfinite(lab.points[..., 0]).sum())
        who = f"track {self.individual!r}" if self.individual else "untracked instances"
        groups = f", {self.n_groups} cross-view instance groups agree" if self.n_groups else ""
        return (
            f"{self.path.name}: {len(self.rig)} cameras {self.rig.names} with calibration, "
            f"{who} of {len(self.tracks) or 1}: {lab.points.shape[1]} frames, "
            f"{len(lab.bodyparts)} nodes, {n_pts} 2D points{groups}"
        )


def has_sleap_session(path: str | Path) -> bool:
    """True if ``path`` is a ``.slp`` file holding a recording session."""
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return "sessions_json" in f and len(f["sessions_json"]) > 0
    except OSError:
        return False


def _session_rig(slp: SlpFile, doc: dict) -> tuple[list[Camera], list[int], list[str]]:
    """Cameras of a session with their video indices; notes on cameras left out."""
    calib = doc.get("calibration")
    if not isinstance(calib, dict):
        raise ValueError(f"{slp.path}: the session has no calibration")
    tables = [(k, v) for k, v in calib.items() if k != "metadata" and isinstance(v, dict)]
    if not tables:
        raise ValueError(f"{slp.path}: the session's calibration has no cameras")
    video_of = {int(c): int(v) for c, v in (doc.get("camcorder_to_video_idx_map") or {}).items()}
    cams, vids, notes = [], [], []
    for i, (key, table) in enumerate(tables):
        try:
            cam = Camera.from_dict(table)
        except (ValueError, TypeError, KeyError) as exc:
            raise ValueError(f"{slp.path}: session camera {key!r}: {exc}") from None
        cam.name = cam.name or key
        if i not in video_of:
            notes.append(f"camera {cam.name!r} has no video in the file: left out")
            continue
        if not 0 <= video_of[i] < len(slp.videos):
            raise ValueError(f"{slp.path}: camera {cam.name!r} maps to video {video_of[i]}, "
                             f"but the file has {len(slp.videos)}")  # fmt: skip
        cams.append(cam)
        vids.append(video_of[i])
    if not cams:
        raise ValueError(f"{slp.path}: no camera of the session has a video")
    return cams, vids, notes


def _instance_groups(slp: SlpFile, doc: dict) -> list[list[tuple[int, int, int]]]:
    """Each instance group as [(camera, labelled-frame row, instance position), ...]."""
    groups = []
    for fg in doc.get("frame_group_dicts") or []:
        for ig in fg.get("instance_groups") or []:
            members = ig.get("camcorder_to_lf_and_inst_idx_map") or {}
            groups.append([(int(c), int(lf), int(k)) for c, (lf, k) in members.items()])
    sd = slp.session_data
    if "fg_start" in doc and sd:
        fgs, igs, mem = sd["frame_groups"], sd["instance_groups"], sd["instance_group_members"]
        for fg in fgs[int(doc["fg_start"]) : int(doc["fg_end"])]:
            for ig in igs[int(fg["ig_start"]) : int(fg["ig_end"])]:
                rows = mem[int(ig["member_start"]) : int(ig["member_end"])]
                groups.append([(int(r["camera"]), int(r["lf"]), int(r["inst"])) for r in rows])
    return groups


def _check_groups(slp: SlpFile, groups, names: list[str], table: dict) -> None:
    """Instance groups link one animal across views: all their instances must carry one
    track, else the track names are not the same animal in every view."""
    start = slp.frames["instance_id_start"]
    for g in groups:
        tracks = {}
        for cam, lf, k in g:
            if not 0 <= lf < len(slp.frames):
                raise ValueError(f"{slp.path}: an instance group names labelled frame {lf}, "
                                 f"but the file has {len(slp.frames)}")  # fmt: skip
            t = int(table["track"][int(start[lf]) + k])
            tracks[names[cam] if cam < len(names) else str(cam)] = t
        if len(set(tracks.values())) > 1:
            frame = int(slp.frames["frame_idx"][g[0][1]])
            shown = ", ".join(
                f"{c}: {slp.tracks[t] if t >= 0 else 'untracked'}" for c, t in tracks.items()
            )
            raise ValueError(
                f"{slp.path}: an instance group of frame {frame} links instances of different "
                f"tracks ({shown}); the track names are not one animal in every view: make the "
                "tracks agree across views in SLEAP"
            )


def read_sleap_session(
    path: str | Path, individual: str | None = None, session: int = 0
) -> SleapSession:
    """Read a SLEAP multi-camera session: calibration and the per-view 2D tracks.

    Parameters
    ----------
    path : path
        ``.slp`` file with a recording session (``sessions_json``).
    individual : str, optional
        Track to read; required when the file has several tracks. A view without that
        track is NaN (with a warning); a track absent from every view is an error.
    session : int
        Which session of the file (default the first).

    Returns
    -------
    SleapSession

    Raises
    ------
    ValueError
        No session, a camera table that is not a pinhole camera with OpenCV distortion,
        several tracks without ``individual``, an unknown track, several untracked instances
        in one frame, or an instance group that links different tracks.
    """
    slp = read_slp_file(path)
    if not slp.sessions:
        raise ValueError(
            f"{slp.path}: no recording session (sessions_json) in this file; read single views "
            "with acm_rs.sleap.read_slp and give the calibration separately"
        )
    if not 0 <= session < len(slp.sessions):
        raise ValueError(f"{slp.path}: session {session} out of range ({len(slp.sessions)})")
    doc = slp.sessions[session]
    cams, vids, notes = _session_rig(slp, doc)
    table = instance_table(slp)
    k = pick_slp_track(slp, individual, table)
    names = [
        Camera.from_dict(v).name or key
        for key, v in doc["calibration"].items()
        if key != "metadata" and isinstance(v, dict)
    ]
    groups = _instance_groups(slp, doc)
    if k is not None:
        _check_groups(slp, groups, names, table)
    n_frames = max(_last_frame(slp, v) for v in vids) + 1
    pts = np.full((len(cams), n_frames, len(slp.nodes), 2), np.nan)
    lik = np.full(pts.shape[:-1], np.nan)
    for c, v in enumerate(vids):
        p, s = track_points(slp, v, k, n_frames=n_frames, table=table)
        pts[c], lik[c] = p, _scores_as_likelihood(s, np.isfinite(p[..., 0]))
        if k is not None and not np.isfinite(p).any():
            notes.append(f"camera {cams[c].name!r} has no instance of track {slp.tracks[k]!r}")
    for note in notes:
        warnings.warn(f"{slp.path}: {note}", stacklevel=2)
    labels = LabelSet(
        pts, lik, np.arange(n_frames, dtype=np.int64), list(slp.nodes), ["sleap"] * len(cams)
    )
    return SleapSession(
        path=slp.path, rig=CameraRig(cams), videos=vids, tracks=list(slp.tracks),
        individual=slp.tracks[k] if k is not None else None, labels=labels,
        n_groups=len(groups) if k is not None else 0, notes=notes,
    )  # fmt: skip


def _last_frame(slp: SlpFile, video: int) -> int:
    sel = slp.frames["frame_idx"][slp.frames["video"] == video]
    return int(sel.max()) if sel.size else -1


def write_session_views(path: str | Path, folder: str | Path, session: int = 0) -> list[Path]:
    """Write one SLEAP analysis file per camera of a session, holding every track.

    The files use SLEAP's analysis layout (``tracks`` (n_tracks, 2, n_nodes, n_frames) px,
    ``point_scores`` (n_tracks, n_nodes, n_frames) as SLEAP stores them (NaN for user points),
    ``node_names``, ``track_names``), so :func:`acm_rs.sleap.read_sleap_analysis` and SLEAP's
    own tools read them; the file of camera ``name`` is ``<folder>/<name>.analysis.h5``.

    Returns
    -------
    list of Path
        The files written, in the session's camera order.
    """
    import h5py

    from ._io import atomic_write

    slp = read_slp_file(path)
    if not slp.sessions:
        raise ValueError(f"{slp.path}: no recording session (sessions_json) in this file")
    cams, vids, _ = _session_rig(slp, slp.sessions[session])
    table = instance_table(slp)
    tracks: list[int | None] = list(range(len(slp.tracks))) or [None]
    n_frames = max(_last_frame(slp, v) for v in vids) + 1
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for cam, v in zip(cams, vids, strict=True):
        xy = np.full((len(tracks), 2, len(slp.nodes), n_frames), np.nan)
        sc = np.full((len(tracks), len(slp.nodes), n_frames), np.nan)
        for i, t in enumerate(tracks):
            p, s = track_points(slp, v, t, n_frames=n_frames, table=table)
            xy[i], sc[i] = p.transpose(2, 1, 0), s.T
        target = out / f"{cam.name}.analysis.h5"
        with atomic_write(target, "w+b") as fh, h5py.File(fh, "w") as f:
            f["tracks"] = xy
            f["point_scores"] = sc
            f["node_names"] = np.array([n.encode() for n in slp.nodes])
            f["track_names"] = np.array([t.encode() for t in slp.tracks], dtype="S")
            f["video_path"] = slp.videos[v]
            f["labels_path"] = str(slp.path)
        files.append(target)
    return files
