"""``acm-rs run-acm DATASET -o OUT``: run an ACM dataset folder end to end.

Reads the authors' files (formats in ``docs/exports.md`` / :mod:`acm_rs.acm_formats`):
``configuration.py`` (parsed, never executed), ``model.npy``, ``multicalibration.npy`` +
``origin_coord.npy`` (the rig in the arena frame in cm), ``labels_manual.npz`` (skeleton
learning) and ``labels_dlc_*.npy`` (tracking over ``index_frame_start:index_frame_end:dt``
with ``pcutoff``, ``tol``, ``iter_max``, the normalisation constants and ``noise``), then
writes ``OUT/pose.npy`` and ``OUT/save_dict.npy`` in the authors' layout next to our own
``OUT/acm-rs/`` outputs (pose NPZ + CSV, learned skeleton, calibration.toml).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import acm_formats
from .state import Normalization

__all__ = ["AcmRun", "run_acm"]


@dataclass
class AcmRun:
    """Outcome of :func:`run_acm`: files written, timings (s), the results."""

    files: list[Path]
    seconds: dict[str, float] = field(default_factory=dict)
    learned: object = None
    result: object = None


def _calibration_frames(cfg: acm_formats.AcmConfig, frames: np.ndarray) -> np.ndarray:
    """Manual-label frames used for learning (``index_frames_calib``, ``dFrames_calib``)."""
    spec = cfg.index_frames_calib
    if spec is None or spec == "all":
        return frames
    keep = np.zeros(frames.size, bool)
    for start, end in spec:
        step = max(int(cfg.dFrames_calib or 1), 1)
        keep |= (frames >= start) & (frames < end) & ((frames - start) % step == 0)
    if not keep.any():
        raise ValueError(
            f"no manual label lies in index_frames_calib {spec} (labelled frames: "
            f"{frames.min()}-{frames.max()})"
        )
    return frames[keep]


def run_acm(
    dataset: str | Path,
    out: str | Path,
    *,
    progress: bool | None = False,
    max_frames: int | None = None,
) -> AcmRun:
    """Learn the skeleton from the manual labels and track the configured frame range.

    Parameters
    ----------
    dataset : path
        ACM dataset folder (``configuration.py``, ``model.npy``, ``multicalibration.npy``,
        ``origin_coord.npy``, ``labels_dlc_*.npy``, ``labels_manual.npz``).
    out : path
        Output folder (created).
    max_frames : int, optional
        Track only the first ``max_frames`` time points (quick looks).

    Returns
    -------
    AcmRun
    """
    from .calibration import load_acm_calibration
    from .learning import learn_skeleton
    from .tracking import track

    d = Path(dataset)
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: not an ACM dataset folder")
    for name in ("configuration.py", "model.npy", "multicalibration.npy", "labels_manual.npz"):
        if not (d / name).is_file():
            raise FileNotFoundError(f"{d / name}: missing (an ACM dataset folder needs it)")
    out = Path(out)
    ours = out / "acm-rs"
    ours.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    cfg = acm_formats.read_configuration(d / "configuration.py")
    model = acm_formats.read_model(d / "model.npy", species=cfg.species)
    origin = d / "origin_coord.npy"
    rig = load_acm_calibration(
        d / "multicalibration.npy", origin if origin.is_file() else None,
        scale_factor=cfg.scale_factor,
        image_size=tuple(int(v) for v in cfg.sensor_size),
    )  # fmt: skip
    manual = acm_formats.read_labels_manual(
        d / "labels_manual.npz", model.acm_marker_names, n_cams=len(rig)
    )
    manual = manual.select(_calibration_frames(cfg, manual.frames))
    norm = Normalization(
        translation=cfg.normalize_t0,
        rotation=cfg.normalize_r0,
        pixel=(cfg.normalize_camera_sensor_x / 2.0, cfg.normalize_camera_sensor_y / 2.0),
    )
    seconds["read"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    learned = learn_skeleton(
        rig, model.skeleton, manual.points, body_weight=cfg.body_weight,
        marker_names=manual.marker_names, normalization=norm, progress=progress,
    )  # fmt: skip
    seconds["learn"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    dlc = acm_formats.read_labels_dlc(acm_formats.labels_dlc_path(d, cfg), model.acm_marker_names)
    frames = cfg.frames if max_frames is None else cfg.frames[:max_frames]
    dlc = dlc.select(frames)
    # ACM treats likelihood <= pcutoff as missing; track drops likelihood < pcutoff.
    lik = np.where(dlc.likelihood > cfg.pcutoff, dlc.likelihood, 0.0)
    result = track(
        rig, learned.skeleton, dlc.points, likelihood=lik, pcutoff=cfg.pcutoff,
        max_iter=cfg.iter_max, tol=cfg.tol, normalization=norm, noise=cfg.noise,
        marker_names=dlc.marker_names, progress=progress,
    )  # fmt: skip
    result.info["frames"] = frames
    seconds["track"] = time.perf_counter() - t0

    files = [
        acm_formats.write_pose(out / "pose.npy", result, model, sensor_size=cfg.sensor_size),
        acm_formats.write_save_dict(out / "save_dict.npy", result),
    ]
    files += result.save(ours / "pose")
    learned.skeleton.save(ours / "skeleton.toml")
    rig.save(ours / "calibration.toml")
    files += [ours / "skeleton.toml", ours / "calibration.toml"]
    return AcmRun(files, seconds, learned, result)


def _cmd_run_acm(args) -> int:
    res = run_acm(args.dataset, args.output, max_frames=args.max_frames, progress=None)
    s = res.seconds
    print(
        f"acm-rs run-acm: learned the skeleton in {s['learn']:.1f} s (RMS "
        f"{res.learned.rms:.2f} px); tracked {res.result.n_frames} time points in "
        f"{s['track']:.1f} s ({len(res.result.em_history)} EM iterations)"
    )
    for line in res.learned.summary().splitlines():
        if "WARNING" in line or "note:" in line:
            print(line)
    for f in res.files:
        print(f"  wrote {f}")
    return 0


def add_subcommands(sub) -> None:
    """Add ``acm-rs run-acm`` to an argparse subparsers object."""
    p = sub.add_parser(
        "run-acm",
        help="run an ACM dataset folder (configuration.py, model.npy, ...) end to end",
        description=(
            "Run a dataset folder of the authors' ACM tool end to end: read configuration.py "
            "(parsed, never executed), model.npy, multicalibration.npy and origin_coord.npy "
            "(the rig in the arena frame, cm), learn the skeleton from labels_manual.npz, track "
            "labels_dlc_*.npy over index_frame_start:index_frame_end:dt with pcutoff, iter_max "
            "and the normalisation constants, and write OUT/pose.npy and OUT/save_dict.npy in "
            "the authors' layout next to acm-rs's own files in OUT/acm-rs/."
        ),
    )
    p.add_argument("dataset", help="ACM dataset folder")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--max-frames", type=int, help="track only the first N time points")
    p.set_defaults(func=_cmd_run_acm)
