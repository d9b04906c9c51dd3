"""SLEAP files: predictions or labels as ``.slp`` (through sleap-io) and analysis ``.h5``.

A SLEAP analysis file (``sleap-convert --format analysis``, ``sio.save_analysis_h5``) is plain
HDF5 read with h5py: ``tracks`` stored as (n_tracks, 2, n_nodes, n_frames) px, ``point_scores``
(n_tracks, n_nodes, n_frames), ``node_names`` and ``track_names`` as byte strings. ``.slp``
files need the optional package ``sleap-io`` (``pip install acm-rs[sleap]``).

Both readers return what :func:`acm_rs.dlc.read_dlc_table` returns, so label files of SLEAP,
DeepLabCut and Lightning Pose can be mixed per camera.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["is_sleap_analysis", "read_sleap_analysis", "read_slp"]


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


def read_slp(path: str | Path, individual: str | None = None, video: int | str | None = None):
    """Read a SLEAP ``.slp`` file (predictions or user labels) with sleap-io.

    Parameters
    ----------
    path : path
    individual : str, optional
        Track name; required when the file has several tracks.
    video : int or str, optional
        Which video of a multi-video file (index or file name); required if there are several.

    Returns
    -------
    points, likelihood, frames, bodyparts
        As :func:`read_sleap_analysis` (scores clipped to [0, 1]); user-labelled points have
        likelihood 1. Rows are the
        frames 0 .. last labelled frame; frames without an instance are NaN.
    """
    p = Path(path)
    try:
        import sleap_io as sio
    except ImportError as exc:
        raise ValueError(
            f"{p}: reading SLEAP .slp files needs sleap-io (pip install 'acm-rs[sleap]' or "
            "pip install sleap-io), or export an analysis .h5 from SLEAP"
        ) from exc
    labels = sio.load_slp(str(p))
    if not labels.videos:
        raise ValueError(f"{p}: no videos in this SLEAP file")
    if video is None and len(labels.videos) > 1:
        raise ValueError(
            f"{p}: {len(labels.videos)} videos "
            f"{[Path(str(v.filename)).name for v in labels.videos]}; choose one with video="
        )
    if len(labels.skeletons) != 1:
        raise ValueError(f"{p}: {len(labels.skeletons)} skeletons; expected one")
    nodes = list(labels.skeletons[0].node_names)
    tracks = [t.name for t in labels.tracks]
    arr = labels.numpy(video=video, untracked=not tracks, return_confidence=True)
    # (n_frames, n_tracks, n_nodes, 3)
    if arr.ndim != 4 or arr.shape[1] == 0:
        raise ValueError(f"{p}: no instances")
    k = _pick_track(p, tracks, individual) if tracks else 0
    if not tracks and arr.shape[1] > 1 and individual is None:
        # untracked files with several instances per frame: the order is arbitrary
        if np.isfinite(arr[:, 1:, :, 0]).any():
            raise ValueError(f"{p}: several untracked instances per frame; track them in SLEAP")
    points = np.ascontiguousarray(arr[:, k, :, :2], dtype=float)
    seen = np.isfinite(points[..., 0])
    lik = _scores_as_likelihood(np.array(arr[:, k, :, 2], dtype=float), seen)
    frames = np.arange(points.shape[0], dtype=np.int64)
    return points, lik, frames, nodes
