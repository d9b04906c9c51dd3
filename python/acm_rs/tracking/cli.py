"""``acm-rs track`` and ``acm-rs export`` subcommands."""

from __future__ import annotations

import argparse
from pathlib import Path

_CAM_REGEX_HELP = (
    "regex finding the camera name in the file names (first group, else the whole match; "
    r"default '(?i)cam(?:era)?[-_]?[a-z0-9]+'; anipose projects: their cam_regex)"
)


def _frame_slice(spec: str | None, n: int) -> slice:
    if not spec:
        return slice(0, n)
    try:
        a, b = (int(x) if x else None for x in spec.split(":"))
    except ValueError:
        raise ValueError(f"--frames must look like START:END, got {spec!r}") from None
    return slice(a, b)


def _track_outputs(args: argparse.Namespace, out: Path) -> list[Path]:
    """The files ``acm-rs track`` will write, checked before any work (overwrite policy,
    writable folder, --rate for C3D)."""
    from .._io import check_output_path

    if args.bundle:
        files = [out.with_suffix(".bundle.npz")]
    else:
        files = [out.with_suffix(".npz"), out.with_name(out.name + "_joints.csv")]
        for fmt in args.export or []:
            if fmt in ("c3d",) and not args.rate:
                raise ValueError("--export c3d needs the frame rate; pass --rate (Hz)")
            files.append(_export_path(fmt, out, "joints"))
    if args.rate is not None and not args.rate > 0:
        raise ValueError(f"--rate must be > 0 Hz, got {args.rate}")
    for f in files:
        check_output_path(f, args.overwrite)
    if args.plots and Path(args.plots).exists() and not args.overwrite:
        raise ValueError(f"{args.plots} exists; pass --overwrite to replace its figures")
    return files


def _cmd_track(args: argparse.Namespace) -> int:
    import sys

    from ..dlc import read_labels
    from ..models import load_name_or_file
    from ..project import rig_for_files
    from .any_length import track
    from .bundle import write_bundle

    _track_outputs(args, Path(args.output))
    rig, table = rig_for_files(args.calibration, args.dlc, args.camera_names, args.cam_regex)
    if table:
        print("acm-rs track: cameras matched by the names in the files:\n  "
              + table.replace("\n", "\n  "))  # fmt: skip
    if len(args.dlc) != len(rig):
        raise ValueError(
            f"{len(args.dlc)} DeepLabCut files for {len(rig)} cameras (give one per camera in "
            f"rig order{'' if args.camera_names else '; --camera-names sets the order'})"
        )
    skeleton = load_name_or_file(args.skeleton)
    ls = read_labels(args.dlc, individual=args.individual)
    pcutoff, why = ls.resolve_pcutoff(args.pcutoff)
    if ls.likelihood is not None:
        print(f"acm-rs track: likelihood cutoff {pcutoff:g} ({why})")
    sel = _frame_slice(args.frame_range, ls.points.shape[1])
    points = ls.points[:, sel]
    lik = ls.likelihood[:, sel] if ls.likelihood is not None else None
    if lik is None:
        print("acm-rs track: the files have no likelihood column; using every detection")
    out = Path(args.output)
    opts = {
        "likelihood": lik, "pcutoff": pcutoff, "joint_limits": not args.no_limits,
        "max_iter": args.max_iter, "tol": args.tol, "gate": None if args.no_gate else args.gate,
        "marker_names": ls.bodyparts, "stop": args.stop, "ll_tol": args.ll_tol,
    }  # fmt: skip
    print(
        f"acm-rs track: {skeleton.name} ({skeleton.n_markers} markers), {len(rig)} cameras, "
        f"{points.shape[1]} frames from {', '.join(str(p) for p in args.dlc)}"
    )
    if args.bundle and args.motion == "velocity":
        raise ValueError(
            "--bundle: acm-smooth runs the paper's random walk only; drop --motion velocity "
            "or track in Python (without --bundle)"
        )
    if args.bundle:
        path = write_bundle(out.with_suffix(".bundle.npz"), rig, skeleton, points, **opts)
        print(f"  wrote {path}; smooth it with: acm-smooth {path}")
        return 0
    res = track(
        rig, skeleton, points, method=args.method, progress=None, motion=args.motion,
        noise_model=args.noise_model, second_solutions=args.second_solutions, **opts,
        **({} if args.overrelax is None else {"overrelax": args.overrelax or None}),
    )  # fmt: skip
    res.info["frames"] = ls.frames[sel]
    if res.info.get("interrupted"):
        # marked in the file (info["interrupted"]); no exports or plots of a partial result
        path = res.save(out.with_name(out.name + "_interrupted"))[0]
        print(
            f"acm-rs track: interrupted (Ctrl-C); the unfinished result is in {path} "
            "(marked interrupted); nothing else written",
            file=sys.stderr,
        )
        return 130
    second = res.info.get("second_solutions")
    if second and not second["joints"]:
        print(f"  no second pose fits the markers in the {len(second['frames'])} searched frames")
    files = res.save(out)
    for fmt in args.export or []:
        files += _export(res, fmt, out, args.rate, "joints")
    if args.plots:
        from ..plots import plot_all

        files += plot_all(res, Path(args.plots))
    for f in files:
        print(f"  wrote {f}")
    return 0


def _cmd_track_long(args: argparse.Namespace) -> int:
    import numpy as np

    from .._io import check_output_path
    from ..camera import CameraRig
    from ..dlc import read_labels
    from ..models import load_name_or_file
    from ..project import rig_for_files
    from .long import track_long

    out = check_output_path(args.output, args.overwrite, "poses file")
    if bool(args.dlc) == bool(args.npy):
        raise ValueError("give either --dlc files (one per camera) or --npy DETECTIONS.npy")
    skeleton = load_name_or_file(args.skeleton)
    names = None
    if args.npy:
        # memory-mapped: read one window at a time (bounded memory)
        points = np.load(args.npy, mmap_mode="r")
        lik = np.load(args.likelihood, mmap_mode="r") if args.likelihood else None
        rig = CameraRig.load(args.calibration, names=args.camera_names)
        pcutoff = args.pcutoff if args.pcutoff is not None else 0.9
    else:
        rig, table = rig_for_files(args.calibration, args.dlc, args.camera_names, args.cam_regex)
        if table:
            print("acm-rs track-long: cameras matched by the names in the files:\n  "
                  + table.replace("\n", "\n  "))  # fmt: skip
        ls = read_labels(args.dlc, individual=args.individual)
        points, lik, names = ls.points, ls.likelihood, ls.bodyparts
        pcutoff, why = ls.resolve_pcutoff(args.pcutoff)
        if lik is not None:
            print(f"acm-rs track-long: likelihood cutoff {pcutoff:g} ({why})")
    method = args.method or ("chunked" if args.scheduler else "streaming")
    how = (
        f"the streaming smoother in segments of {args.chunk}" if method == "streaming"
        else f"chunks of {args.chunk} (+{args.burn_in} burn-in)"
    )  # fmt: skip
    print(
        f"acm-rs track-long: {skeleton.name}, {len(rig)} cameras, {points.shape[1]} frames; "
        f"EM on {args.windows} windows of {args.subset // args.windows} frames, then {how} on "
        f"{args.scheduler or f'{args.workers} threads'}"
    )
    info = track_long(
        rig, skeleton, points, out, likelihood=lik, pcutoff=pcutoff, marker_names=names,
        joint_limits=not args.no_limits, motion=args.motion, subset=args.subset,
        n_windows=args.windows, chunk=args.chunk, burn_in=args.burn_in, tol=args.seam_tol,
        gate=None if args.no_gate else args.gate, client=args.scheduler, workers=args.workers,
        overwrite=args.overwrite, progress=None, method=method, poor_fit=args.poor_fit,
    )  # fmt: skip
    detail = (
        f"{info['poor_fit_frames']} poorly fit frames" if method == "streaming"
        else f"largest seam difference {info['seam_difference_max']:.3g} SD"
    )  # fmt: skip
    print(
        f"  {info['motion']}, {len(info['em_history'])} EM iterations ({info['seconds_em']:.0f} s);"
        f" smoothing {info['seconds_smoothing']:.0f} s; {detail}\n  wrote {info['path']}"
    )
    return 0


FORMATS = ("anipose", "nwb", "c3d", "npz", "movement")


def _export_path(fmt: str, out: Path, points: str) -> Path:
    """The file ``_export`` writes for ``fmt`` (anipose: the CSV; its sidecar is beside it)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; choose from {', '.join(FORMATS)}")
    if fmt == "anipose":
        return out.with_name(out.stem + "_3d.csv")
    if fmt == "movement":
        return out.with_name(out.stem + "_movement.nc")
    return out.with_suffix({"nwb": ".nwb", "c3d": ".c3d", "npz": ".npz"}[fmt])


def _export(res, fmt: str, out: Path, rate: float | None, points: str) -> list[Path]:
    from .. import export

    if fmt == "anipose":
        return export.to_anipose_csv(res, out.with_name(out.stem + "_3d.csv"), points=points)
    if fmt == "nwb":
        return [
            export.to_nwb(
                res,
                out.with_suffix(".nwb"),
                session_description=f"acm-rs poses of {out.stem}",
                rate=rate,
            )  # fmt: skip
        ]
    if fmt == "c3d":
        if not rate:
            raise ValueError("C3D needs the frame rate; pass --rate")
        return [export.to_c3d(res, out.with_suffix(".c3d"), rate, joints=True)]
    if fmt == "npz":
        return [export.to_npz(res, out.with_suffix(".npz"))]
    if fmt == "movement":
        path = out.with_name(out.stem + "_movement.nc")
        return [export.to_movement_file(res, path, fps=rate, points=points)]
    raise ValueError(f"unknown export format {fmt!r}; choose from {', '.join(FORMATS)}")


def _cmd_export(args: argparse.Namespace) -> int:
    from .._io import check_output_path
    from .result import PoseResult

    out = Path(args.output) if args.output else Path(args.input).with_suffix("")
    for fmt in args.format:
        if fmt == "c3d" and not args.rate:
            raise ValueError("--format c3d needs the frame rate; pass --rate (Hz)")
        target = _export_path(fmt, out, args.points)
        if target.resolve() == Path(args.input).resolve():
            raise ValueError(f"{target} is the input; give another --output")
        check_output_path(target, args.overwrite)
    res = PoseResult.load(args.input)
    if res.info.get("interrupted"):
        print(f"acm-rs export: WARNING: {args.input} is the result of an interrupted run")
    files: list[Path] = []
    for fmt in args.format:
        files += _export(res, fmt, out, args.rate, args.points)
    for f in files:
        print(f"  wrote {f}")
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from ..plots.viewer import view_html
    from .result import PoseResult

    res = PoseResult.load(args.input)
    out = Path(args.output) if args.output else Path(args.input).with_suffix(".html")
    view_html(res, out, fps=args.fps, max_frames=args.max_frames)
    print(f"acm-rs view: wrote {out} ({out.stat().st_size / 1e6:.1f} MB, opens offline)")
    return 0


def add_subcommands(sub) -> None:
    """Add ``acm-rs track``, ``acm-rs export`` and ``acm-rs view`` to an argparse subparsers
    object."""
    from ..pipeline import add_project_option, project_step_or

    p = sub.add_parser(
        "track",
        help="reconstruct 3D poses from DeepLabCut detections (EM + unscented RTS smoother)",
        description="ACM supplement sec. 4: learns the noise model by EM and writes the "
        "smoothed posterior (OUT.npz, OUT_joints.csv; exports on request).",
    )
    p.add_argument("--calibration", help="anipose calibration.toml")
    p.add_argument(
        "--camera-names", nargs="+",
        help="calibrated camera names in the order of --dlc (default: from the file names "
        "when each names one camera, e.g. rat-cam0DLC_...h5; else the calibration's order)",
    )  # fmt: skip
    p.add_argument("--cam-regex", help=_CAM_REGEX_HELP)
    p.add_argument(
        "--skeleton", default="rat", help="learned skeleton TOML (acm-rs learn) or a model name"
    )
    p.add_argument(
        "--dlc", nargs="+",
        help="2D poses, one file per camera: DeepLabCut or Lightning Pose .h5/.csv, SLEAP "
        ".slp/.analysis.h5",
    )  # fmt: skip
    p.add_argument(
        "--individual", help="individual (DeepLabCut) or track (SLEAP) in multi-animal files"
    )
    p.add_argument("--frames", dest="frame_range", help="frame range START:END (row indices)")
    p.add_argument(
        "--pcutoff", type=float, default=None,
        help="likelihood cutoff in [0, 1] (default by the files' tool: 0.9 DeepLabCut, 0.2 SLEAP; "
        "0.9 for --npy)",
    )  # fmt: skip
    p.add_argument("--max-iter", type=int, default=100, help="EM iterations at most (100)")
    p.add_argument(
        "--stop", choices=["loglik", "alg13"], default="loglik",
        help="EM convergence rule: the marginal log-likelihood's gain per measurement "
        "(--ll-tol, default) or Alg. 13's relative parameter change (--tol)",
    )  # fmt: skip
    p.add_argument("--ll-tol", type=float, default=1e-3,
                   help="nats per measurement entry for --stop loglik (1e-3)")  # fmt: skip
    p.add_argument("--tol", type=float, default=0.05, help="EM tolerance of Alg. 13 (0.05)")
    p.add_argument(
        "--overrelax", type=float, default=None, metavar="A",
        help="growth factor > 1 of over-relaxed EM (default: acm_rs.track's); 0: plain EM "
        "(Alg. 11)",
    )  # fmt: skip
    p.add_argument("--gate", type=float, default=0.999, help="outlier gate probability (0.999)")
    p.add_argument("--no-gate", action="store_true", help="use every confident detection")
    p.add_argument("--no-limits", action="store_true", help="do not enforce joint-angle limits")
    p.add_argument(
        "--method", choices=["ukf", "deterministic"], default="ukf",
        help="ukf (default): EM with the unscented Kalman filter and RTS smoother; "
        "deterministic: independent per-frame fits, for comparison",
    )  # fmt: skip
    p.add_argument(
        "--motion", choices=["auto", "velocity", "random_walk"], default="auto",
        help="motion model: position and velocity (auto, default: unless it fits worse than "
        "the random walk) or the paper's random walk (docs/tracking.md)",
    )  # fmt: skip
    p.add_argument(
        "--noise-model", choices=["gauss", "student"], default="gauss",
        help="measurement noise: Gaussian (the paper's, with the outlier gate) or Student-t",
    )  # fmt: skip
    p.add_argument(
        "--export", nargs="+", choices=[f for f in FORMATS if f != "npz"],
        help="also write these formats (movement: netCDF for the movement toolbox)",
    )  # fmt: skip
    p.add_argument("--rate", type=float, help="frame rate (Hz) for NWB/C3D/movement exports")
    p.add_argument("--plots", help="folder for the tracking figures")
    p.add_argument("--bundle", action="store_true", help="only write OUT.bundle.npz for acm-smooth")
    p.add_argument("--second-solutions", type=int, default=3, metavar="N",
                   help="search N frames for second poses that fit the markers as well, name "
                   "the joints the markers leave ambiguous and widen their SDs to reach the "
                   "second poses (3; 0: skip)")  # fmt: skip
    p.add_argument("-o", "--output", help="output prefix, e.g. out/session1")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_project_option(p, "track")
    p.set_defaults(
        func=lambda a: project_step_or(
            a, "track", _cmd_track, ("--calibration", "--dlc", "--output")
        )
    )

    t = sub.add_parser(
        "track-long",
        help="track a recording of any length in bounded memory (EM on a subset, chunked "
        "smoother, HDF5 output; threads or a Dask cluster)",
        description="Issue 16: learns the model by EM on evenly spread windows, then smooths "
        "the whole recording in chunks with overlapping burn-in whose seams are checked, "
        "writing OUT.h5 chunk by chunk (docs/tracking.md, 'Long recordings').",
    )
    t.add_argument("--calibration", required=True, help="anipose calibration.toml")
    t.add_argument("--camera-names", nargs="+", help="calibrated camera names in input order")
    t.add_argument("--cam-regex", help=_CAM_REGEX_HELP)
    t.add_argument(
        "--skeleton", default="rat", help="learned skeleton TOML (acm-rs learn) or a model name"
    )
    t.add_argument(
        "--dlc", nargs="+",
        help="2D poses, one file per camera (read whole: for bounded memory use --npy)",
    )  # fmt: skip
    t.add_argument(
        "--npy",
        help="detections (n_cams, T, n_markers, 2) in pixels, skeleton marker order, NaN "
        "missing; memory-mapped",
    )  # fmt: skip
    t.add_argument("--likelihood", help="likelihoods (n_cams, T, n_markers) .npy for --npy")
    t.add_argument("--individual", help="individual in multi-animal files")
    t.add_argument(
        "--pcutoff", type=float, default=None,
        help="likelihood cutoff in [0, 1] (default by the files' tool: 0.9 DeepLabCut, 0.2 SLEAP; "
        "0.9 for --npy)",
    )  # fmt: skip
    t.add_argument("--gate", type=float, default=0.999, help="outlier gate probability (0.999)")
    t.add_argument("--no-gate", action="store_true", help="use every confident detection")
    t.add_argument("--no-limits", action="store_true", help="do not enforce joint-angle limits")
    t.add_argument(
        "--motion", choices=["auto", "velocity", "random_walk"], default="auto",
        help="motion model (as acm-rs track)",
    )  # fmt: skip
    t.add_argument("--subset", type=int, default=10000, help="frames for EM (10000)")
    t.add_argument("--windows", type=int, default=10, help="EM windows, evenly spread (10)")
    t.add_argument(
        "--method", choices=["streaming", "chunked"],
        help="streaming (default without --scheduler): the exact smoother from checkpointed "
        "filter states (sequential forward pass, restarts where the animal was lost); "
        "chunked (default with --scheduler): overlapping windows, parallel in time",
    )  # fmt: skip
    t.add_argument("--chunk", type=int, default=2000,
                   help="frames per segment or chunk (2000)")  # fmt: skip
    t.add_argument("--poor-fit", type=float, default=4.0,
                   help="streaming: report stretches reprojecting worse than this multiple of "
                   "a typical frame (4)")  # fmt: skip
    t.add_argument("--burn-in", type=int, default=100,
                   help="chunked: extra frames on each side of a chunk (100)")  # fmt: skip
    t.add_argument(
        "--seam-tol", type=float, default=None,
        help="chunked: largest seam difference between chunks in posterior SDs before the burn-in "
        "is doubled (0.005)",
    )  # fmt: skip
    t.add_argument("--workers", type=int, default=2, help="threads without --scheduler (2)")
    t.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://host:8786)")
    t.add_argument("-o", "--output", required=True, help="output HDF5 file, e.g. poses.h5")
    t.add_argument("--overwrite", action="store_true", help="replace an existing output")
    t.set_defaults(func=_cmd_track_long)

    e = sub.add_parser("export", help="convert a tracking result (.npz) to other formats")
    e.add_argument("input", nargs="?", help="result written by acm-rs track (OUT.npz)")
    e.add_argument(
        "--format", nargs="+", choices=FORMATS,
        help="output formats (anipose CSV, NWB/ndx-pose, C3D, NPZ, movement netCDF)",
    )  # fmt: skip
    e.add_argument(
        "--points", choices=["joints", "markers"], default="joints",
        help="export the joints (default) or the surface markers",
    )  # fmt: skip
    e.add_argument(
        "--rate", type=float,
        help="video frame rate (Hz): needed for C3D; time in seconds for NWB and movement",
    )  # fmt: skip
    e.add_argument("-o", "--output", help="output prefix (default: next to the input)")
    e.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_project_option(e, "export")
    e.set_defaults(func=lambda a: project_step_or(a, "export", _cmd_export, ("input", "--format")))

    v = sub.add_parser(
        "view",
        help="write one self-contained HTML file showing a result in 3D (animated, offline)",
        description="3D skeleton with a time slider and play button, joints coloured by their "
        "posterior SD, cameras and floor, and a per-joint trace panel. Needs plotly.",
    )
    v.add_argument("input", help="result written by acm-rs track (OUT.npz)")
    v.add_argument("-o", "--output", help="HTML file to write (default: INPUT with .html)")
    v.add_argument("--fps", type=float, help="video frame rate (Hz) for a time axis in seconds")
    v.add_argument(
        "--max-frames", type=int, default=1500,
        help="animate at most this many frames (every k-th of longer results; default 1500)",
    )  # fmt: skip
    v.set_defaults(func=_cmd_view)


__all__ = ["add_subcommands"]
