"""The ``acm-rs`` command line."""

from __future__ import annotations

import argparse
import sys
import time
import traceback
from collections.abc import Sequence

from ._version import __version__


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    start = time.perf_counter()
    res = run_demo(
        args.out, frames=args.frames, seed=args.seed, learn_frames=args.learn_frames,
        track_frames=args.track_frames,
    )  # fmt: skip
    rate = res.n_frames / res.seconds if res.seconds > 0 else float("inf")
    print(f"acm-rs demo: rat model (29 joints, 43 markers) in a 4-camera rig -> {res.out}/")
    print(
        f"  forward kinematics + projection of {res.n_frames:,} poses into 4 cameras: "
        f"{res.seconds:.3f} s ({rate:,.0f} poses/s)"
    )
    for report in (res.calibration_report(), res.learning_report(), res.tracking_report()):
        if report:
            print(report)
    print(f"  {len(res.files)} files written; whole demo {time.perf_counter() - start:.1f} s")
    look = ["camera_views.png", "calibration_qc.png", "learn_reprojection.png"]
    if res.tracked is not None:
        look += ["plots/joint_traces.png", "plots/skeleton_snapshots.png"]
    print("look at: " + ", ".join(str(res.out / f) for f in look if (res.out / f).exists()))
    return 0


def _cmd_model(args: argparse.Namespace) -> int:
    from . import models

    if args.name is None:
        print("bundled models:", ", ".join(models.available()))
        return 0
    sk = models.load(args.name)
    print(sk)
    print(f"  units: {sk.units}; state dimension: {sk.state_map().n_state}")
    print(f"  bones: {', '.join(sk.bone_names)}")
    if args.save:
        from ._io import check_output_path

        check_output_path(args.save, args.overwrite)
        sk.save(args.save)
        print(f"  wrote {args.save}")
    if args.plot:
        from .plotting import save_figure, skeleton_views

        j, m = sk.rest_pose()
        save_figure(skeleton_views(sk, j, m, f"{sk.name}: rest pose"), args.plot)
        print(f"  wrote {args.plot}")
    return 0


def _cmd_learn(args: argparse.Namespace) -> int:
    from pathlib import Path

    import numpy as np

    from ._io import check_output_path
    from .dlc import read_labels
    from .learning import learn_skeleton
    from .models import load_name_or_file
    from .plotting import save_figure
    from .project import rig_for_files

    prefix = Path(args.output).with_suffix("")
    for f in (prefix.with_suffix(".toml"), prefix.with_name(prefix.name + "_fit.npz")):
        check_output_path(f, args.overwrite)  # before the work (error and overwrite policy)
    rig, table = rig_for_files(args.calibration, args.labels, args.camera_names, args.cam_regex)
    if table:
        print("acm-rs learn: cameras matched by the names in the files:\n  "
              + table.replace("\n", "\n  "))  # fmt: skip
    if len(args.labels) != len(rig):
        raise ValueError(
            f"{len(args.labels)} label files for {len(rig)} cameras (give one per camera, in "
            f"rig order{'' if args.camera_names else '; --camera-names sets the order'})"
        )
    skeleton = load_name_or_file(args.model)
    labels = read_labels(args.labels, individual=args.individual)
    print(
        f"acm-rs learn: {skeleton.name} ({skeleton.n_markers} markers), {len(rig)} cameras, "
        f"{labels.points.shape[1]} labelled frames, {len(labels.bodyparts)} body parts"
    )
    pcutoff, why = labels.resolve_pcutoff(args.pcutoff)
    if labels.likelihood is not None:
        low = int(np.sum(labels.likelihood < pcutoff))
        print(f"  predictions: {low} labels below pcutoff {pcutoff:g} ({why}) are not used")
    res = learn_skeleton(
        rig, skeleton, labels.points, body_weight=args.body_weight,
        symmetric=not args.no_symmetry, marker_names=labels.bodyparts, progress=None,
        likelihood=labels.likelihood, pcutoff=pcutoff,
    )  # fmt: skip
    if args.elastic or skeleton.stretch_sd.any():
        from .elastic import add_stretch

        res, fit = add_stretch(res, "all" if args.elastic else None)
        print(fit.summary())
    out = Path(args.output)
    files = res.save(out.with_suffix(""))
    print(res.summary())
    if args.plots:
        plots = Path(args.plots)
        files.append(save_figure(res.plot_reprojection(), plots / "learn_reprojection.png"))
        files.append(save_figure(res.plot_skeleton(), plots / "learn_skeleton.png"))
    for f in files:
        print(f"  wrote {f}")
    return 0


def _rig_and_labels(args: argparse.Namespace):
    """``(rig, LabelSet, what)`` from ``--session`` (a SLEAP multi-camera .slp) or from
    ``--calibration`` with one ``--labels`` file per camera (as ``learn``)."""
    if args.session:
        from .sleap_session import read_sleap_session

        ses = read_sleap_session(args.session, individual=args.individual)
        return ses.rig, ses.labels, ses.summary()
    if not (args.calibration and args.labels):
        raise ValueError("give --session FILE.slp, or --calibration with --labels (one per camera)")
    from .dlc import read_labels
    from .project import rig_for_files

    rig, table = rig_for_files(args.calibration, args.labels, args.camera_names, args.cam_regex)
    if len(args.labels) != len(rig):
        raise ValueError(f"{len(args.labels)} label files for {len(rig)} cameras (one per camera)")
    labels = read_labels(args.labels, individual=args.individual)
    return rig, labels, table or f"{len(rig)} cameras from {args.calibration}"


def _cmd_from_labels(args: argparse.Namespace) -> int:
    from ._io import check_output_path
    from .lab_skeleton import skeleton_from_labels

    check_output_path(args.output, args.overwrite)
    rig, labels, what = _rig_and_labels(args)
    print(f"acm-rs model from-labels: {what}")
    pcutoff, why = labels.resolve_pcutoff(args.pcutoff)
    res = skeleton_from_labels(
        args.definition, rig, labels, pcutoff=pcutoff if labels.likelihood is not None else 0.0,
        root=args.root, joint_limits=not args.no_joint_limits,
        limit_margin_deg=args.limit_margin, name=args.name,
    )  # fmt: skip
    if labels.likelihood is not None:
        print(f"  likelihood cutoff {pcutoff:g} ({why})")
    print(res.summary())
    res.skeleton.save(args.output)
    print(f"  wrote {args.output} (use it as --model / project.model for learn, track, run-all)")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from .evaluate import evaluate, evaluate_refined
    from .models import load_name_or_file

    if args.refine_calibration:
        from ._io import check_output_path

        check_output_path(args.refine_calibration, args.overwrite)
    rig, labels, what = _rig_and_labels(args)
    print(f"acm-rs evaluate: {what}")
    pcutoff, why = labels.resolve_pcutoff(args.pcutoff)
    cutoff = pcutoff if labels.likelihood is not None else 0.0
    skeleton = load_name_or_file(args.model)
    ev = evaluate(rig, skeleton, labels, relearn=args.relearn, pcutoff=cutoff)
    print(ev.table())
    print(ev.summary())
    if args.output:
        for f in ev.save(args.output):
            print(f"  wrote {f}")
    if args.refine_calibration:
        ref = evaluate_refined(
            rig, skeleton, labels, relearn=args.relearn, pcutoff=cutoff,
            intrinsics=args.refine_intrinsics,
        )  # fmt: skip
        print(ref.summary())
        ref.refinement.rig.save(args.refine_calibration)
        print(f"  wrote {args.refine_calibration} (refined on frames {ref.train_frames.tolist()})")
    return 0


def _add_label_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--session", help="SLEAP .slp with a multi-camera session (calibration+labels)")
    p.add_argument("--calibration", help="anipose calibration.toml (with --labels)")
    p.add_argument("--labels", nargs="+", help="labelled frames, one file per camera (as learn)")
    p.add_argument("--camera-names", nargs="+", help="cameras in label-file order (as learn)")
    p.add_argument("--cam-regex", help="regex of the camera name in the file names (as learn)")
    p.add_argument("--individual", help="individual (track) in multi-animal label files")
    p.add_argument(
        "--pcutoff", type=float, default=None,
        help="likelihood cutoff of predicted labels (default by the files' tool)",
    )  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``acm-rs``."""
    from .pipeline import add_project_option, project_step_or

    p = argparse.ArgumentParser(prog="acm-rs", description=__doc__)
    p.add_argument("--version", action="version", version=f"acm-rs {__version__}")
    p.add_argument("--debug", action="store_true", help="show the traceback of an error")
    sub = p.add_subparsers(dest="command", required=True)
    d = sub.add_parser(
        "demo", help="the whole pipeline on a synthetic rat: calibrate, learn, track, export, plots"
    )
    d.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    d.add_argument("--frames", type=int, default=100_000, help="poses for the timing")
    d.add_argument("--seed", type=int, default=0, help="seed of the synthetic session (0)")
    d.add_argument(
        "--learn-frames", type=int, default=100, help="labelled frames for skeleton learning"
    )
    d.add_argument(
        "--track-frames", type=int, default=400, help="frames of the behaviour sequence to track"
    )
    d.set_defaults(func=_cmd_demo)
    m = sub.add_parser("model", help="list the bundled models or describe one")
    m.add_argument("name", nargs="?", help="model name (rat, mouse)")
    m.add_argument("--save", help="write the model as a skeleton TOML file")
    m.add_argument("--plot", help="write a PNG of the rest pose")
    m.add_argument("--overwrite", action="store_true", help="replace an existing --save file")
    m.set_defaults(func=_cmd_model)
    fl = sub.add_parser(
        "model-from-labels",
        help="a skeleton from a lab's keypoints (DeepLabCut config.yaml, SLEAP .slp/.json, "
        "DANNCE .mat, anipose config.toml) and its labelled frames; also 'model from-labels'",
    )
    fl.add_argument("definition", help="the lab's keypoint definition file (or DLC project)")
    _add_label_options(fl)
    fl.add_argument("--root", help="root keypoint (default: the centre of the tree)")
    fl.add_argument("--no-joint-limits", action="store_true", help="no joint-angle limits")
    fl.add_argument(
        "--limit-margin", type=float, default=30.0,
        help="degrees added on each side of the labelled angle ranges (default 30)",
    )  # fmt: skip
    fl.add_argument("--name", help="model name (default: the definition file's name)")
    fl.add_argument("-o", "--output", required=True, help="skeleton TOML to write")
    fl.add_argument("--overwrite", action="store_true", help="replace an existing output")
    fl.set_defaults(func=_cmd_from_labels)
    ev = sub.add_parser(
        "evaluate",
        help="leave-one-camera-out accuracy on labelled frames: skeleton fit vs triangulation",
    )
    ev.add_argument("--model", required=True, help="(learned) skeleton TOML or bundled model")
    _add_label_options(ev)
    ev.add_argument(
        "--relearn", action="store_true",
        help="learn the skeleton again without the held-out camera in each fold",
    )  # fmt: skip
    ev.add_argument(
        "--refine-calibration", metavar="TOML",
        help="also refine the calibration on the keypoints of every other labelled frame, "
        "write it here, and report the held-out frames before and after",
    )  # fmt: skip
    ev.add_argument(
        "--refine-intrinsics", action="store_true",
        help="with --refine-calibration: refine focal lengths and principal points too",
    )  # fmt: skip
    ev.add_argument("--overwrite", action="store_true", help="replace an existing calibration")
    ev.add_argument("-o", "--output", help="prefix of the CSV tables and the PNG figure")
    ev.set_defaults(func=_cmd_evaluate)
    lp = sub.add_parser(
        "learn", help="learn bone lengths and marker offsets from labelled frames (sec. 3.2)"
    )
    lp.add_argument("--calibration", help="anipose calibration.toml")
    lp.add_argument(
        "--camera-names", nargs="+",
        help="cameras to use, in label-file order (default: from the file names when each "
        "names one camera; else the calibration's order)",
    )  # fmt: skip
    lp.add_argument(
        "--cam-regex",
        help="regex finding the camera name in the file names (first group, else the whole "
        r"match; default '(?i)cam(?:era)?[-_]?[a-z0-9]+')",
    )
    lp.add_argument("--model", default="rat", help="bundled model name or skeleton TOML")
    lp.add_argument(
        "--labels", nargs="+",
        help="manual labels, one file per camera: DeepLabCut CollectedData .csv/.h5 (or SLEAP "
        ".slp)",
    )  # fmt: skip
    lp.add_argument("--individual", help="individual to use in multi-animal label files")
    lp.add_argument("--body-weight", type=float, help="body weight (g) for bone-length priors")
    lp.add_argument(
        "--pcutoff", type=float, default=None,
        help="labels from predictions: likelihood cutoff in [0, 1] (default by the files' tool: "
        "0.9 DeepLabCut, 0.2 SLEAP); manual CollectedData files have no likelihood and are "
        "used whole",
    )  # fmt: skip
    lp.add_argument("--no-symmetry", action="store_true", help="do not enforce left/right symmetry")
    lp.add_argument(
        "--elastic", action="store_true",
        help="learn elastic segments for every bone (per-frame lengths around learned means, "
        "SDs by EM; for a lab's sparse keypoints). A model with elastic bones relearns them "
        "without this flag",
    )  # fmt: skip
    lp.add_argument("-o", "--output", help="learned skeleton TOML to write")
    lp.add_argument("--plots", help="folder for the reprojection and skeleton figures")
    lp.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_project_option(lp, "learn")
    lp.set_defaults(
        func=lambda a: project_step_or(
            a, "learn", _cmd_learn, ("--calibration", "--labels", "--output")
        )
    )
    from .batch import add_subcommands as add_batch
    from .pipeline import add_subcommands as add_pipeline
    from .project import add_subcommands as add_init
    from .run_acm import add_subcommands as add_run_acm
    from .tracking.cli import add_subcommands as add_track

    add_init(sub)
    add_track(sub)
    add_pipeline(sub)
    add_run_acm(sub)
    add_batch(sub)
    from .gapfill.cli import add_subcommands as add_gapfill

    add_gapfill(sub)
    from .calibration.cli import add_subcommand as add_calibrate

    add_calibrate(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``acm-rs`` command."""
    argv = list(sys.argv[1:] if argv is None else argv)
    i = next((k for k, a in enumerate(argv) if not a.startswith("-")), len(argv))
    if argv[i : i + 2] == ["model", "from-labels"]:  # the two-word spelling
        argv[i : i + 2] = ["model-from-labels"]
    args = build_parser().parse_args(argv)
    if getattr(args, "frames", 1) < 1:
        print("acm-rs: --frames must be >= 1", file=sys.stderr)
        return 2
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        # docs/architecture.md, error and overwrite policy: Ctrl-C exits 130
        print("acm-rs: interrupted (Ctrl-C); unfinished outputs were not written", file=sys.stderr)
        return 130
    except (ValueError, OSError, ArithmeticError) as exc:
        # input and numerical problems: one line naming the file and the fix; --debug for more
        if args.debug:
            traceback.print_exc()
        kind = "numerical error" if isinstance(exc, ArithmeticError) else "error"
        print(f"acm-rs: {kind}: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # a bug, not an input problem: say so, traceback on --debug
        if args.debug:
            traceback.print_exc()
        print(
            f"acm-rs: internal error: {type(exc).__name__}: {exc} (please report it with the "
            "output of the same command with --debug)",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
