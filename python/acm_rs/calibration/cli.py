"""The ``acm-rs calibrate`` subcommand."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_subcommand(sub) -> None:
    """Register ``calibrate`` on the ``acm-rs`` subparsers."""
    from ..pipeline import add_project_option

    p = sub.add_parser(
        "calibrate",
        help="calibrate cameras from checkerboard/ChArUco videos or image folders (sec. 2.2)",
        description=(
            "Detect the board in every camera (frames matched by index), calibrate the rig "
            "(ACM supp. eq. 7) and write an anipose calibration.toml, a JSON QC report and a "
            "QC figure. Camera names default to the video stems / folder names."
        ),
    )
    src = p.add_mutually_exclusive_group()
    src.add_argument("--videos", nargs="+", help="one video per camera")
    src.add_argument("--images", nargs="+", help="one image folder per camera")
    p.add_argument("--board", help="board spec TOML (anipose keys)")
    p.add_argument("-o", "--output", help="calibration.toml to write")
    p.add_argument("--stride", type=int, default=1, help="use every n-th frame (default 1)")
    p.add_argument("--camera-names", nargs="+", help="camera names, in source order")
    p.add_argument("--reference", default="0", help="reference camera (index or name)")
    p.add_argument(
        "--loss", default="linear", choices=["linear", "soft_l1", "huber", "cauchy", "arctan"],
        help="robust loss of the bundle adjustment (scipy least_squares; default linear)",
    )  # fmt: skip
    p.add_argument("--cache", help="detection cache (default: <output>.detections.npz)")
    p.add_argument("--no-cache", action="store_true", help="neither read nor write a cache")
    p.add_argument("--report", help="JSON QC report (default: <output>.report.json)")
    p.add_argument("--qc-png", help="QC figure (default: <output>.qc.png)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument(
        "--no-progress", action="store_true", help="no progress bars (shown only on a terminal)"
    )
    add_project_option(p, "calibrate")
    p.set_defaults(func=_dispatch)


def _dispatch(args: argparse.Namespace) -> int:
    from ..pipeline import project_step_or

    if not args.project and not (args.videos or args.images):
        raise ValueError("acm-rs calibrate needs --videos or --images (or --project DIR)")
    return project_step_or(args, "calibrate", run, ("--board", "--output"))


def run(args: argparse.Namespace) -> int:
    """Run ``acm-rs calibrate``; returns the exit code."""
    from .board import BoardSpec
    from .detection import detect
    from .solve import calibrate

    out = Path(args.output)
    if out.exists() and not args.overwrite:
        raise ValueError(f"{out} exists (pass --overwrite to replace it)")
    stem = out.with_suffix("")
    spec = BoardSpec.load(args.board)
    sources = args.videos if args.videos else args.images
    cache = None if args.no_cache else (args.cache or f"{stem}.detections.npz")
    det = detect(
        sources,
        spec,
        kind="videos" if args.videos else "images",
        stride=args.stride,
        camera_names=args.camera_names,
        cache=cache,
        progress=False if args.no_progress else None,
    )
    names = det.camera_names
    boards = ", ".join(f"{n}: {int(k)}" for n, k in zip(names, det.n_boards, strict=True))
    print(f"acm-rs calibrate: {det.corners.shape[1]} frames, boards detected per camera: {boards}")
    ref = int(args.reference) if args.reference.isdigit() else None
    if ref is None:
        if args.reference not in names:
            raise ValueError(f"--reference {args.reference!r} is not a camera; cameras: {names}")
        ref = names.index(args.reference)
    res = calibrate(
        det.corners,
        spec.board_points,
        det.image_sizes,
        ref,
        loss=args.loss,
        camera_names=names,
    )
    res.save(out)
    report = Path(args.report or f"{stem}.report.json")
    png = Path(args.qc_png or f"{stem}.qc.png")
    rep = res.save_report(report, png=png)
    print(rep["text"])
    info = res.info
    print(
        f"initialisation {info['seconds_init']:.2f} s, refinement {info['seconds_refine']:.2f} s "
        f"({info['nfev']} evaluations)"
    )
    if not rep["plausibility"]["ok"]:
        print("WARNING: plausibility checks failed; see the report")
    for f in (out, report, png) + ((Path(cache),) if cache else ()):
        print(f"  wrote {f}")
    return 0
