"""The project workflow: calibrate -> learn -> track -> export -> plot, step by step.

Each step reads what the previous one wrote in the project folder (layout in
``docs/project.md``), writes atomically and logs to ``<project>/logs/acm-rs-<time>.log``. A
finished step leaves a record of what it was made from (:mod:`acm_rs._provenance`: digests of
its inputs, its settings, the package version); the next run skips it only while that record
still matches and says why it skips or redoes it. A re-made output changes the record of the
steps after it, so they are redone too; an interrupted step is never taken as done:

=============  ==================================================  ===========================
step           input                                               output
=============  ==================================================  ===========================
calibrate      ``calibration/`` videos or image folders of a board  ``paths.calibration``
learn          ``paths.manual_labels`` (DeepLabCut CollectedData)   ``skeleton.toml``
track          session ``paths.labels`` (DeepLabCut predictions)    ``<output>/pose.npz``
export         ``pose.npz``                                         ``pose_3d.csv``, ``.nwb``,
                                                                    ``.c3d`` (with ``fps``)
plot           ``pose.npz``                                         ``<output>/plots/*.png``,
                                                                    ``view.html``
=============  ==================================================  ===========================

:func:`run_session` is the per-session function of :mod:`acm_rs.batch` (Dask).
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import time
from collections.abc import Iterator
from pathlib import Path

from . import _provenance as prov
from .project import ProjectConfig, Session, find_sessions, load_config

__all__ = [
    "STEPS",
    "project_log",
    "run_all",
    "run_session",
    "step_calibrate",
    "step_export",
    "step_learn",
    "step_plot",
    "step_track",
]

STEPS = ("calibrate", "learn", "track", "export", "plot")
SKELETON_NAME = "skeleton.toml"
POSE_NAME = "pose.npz"
log = logging.getLogger("acm_rs.pipeline")


@contextlib.contextmanager
def project_log(config: ProjectConfig) -> Iterator[Path]:
    """Log this run (INFO and above) to ``<project>/logs/acm-rs-<YYYYmmdd-HHMMSS>.log``."""
    folder = config.root / "logs"
    folder.mkdir(exist_ok=True)
    path = folder / f"acm-rs-{time.strftime('%Y%m%d-%H%M%S')}.log"
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    root = logging.getLogger("acm_rs")
    root.addHandler(handler)
    old = root.level
    root.setLevel(logging.INFO)
    try:
        yield path
    finally:
        root.removeHandler(handler)
        root.setLevel(old)
        handler.close()


#: Whether stage lines also go to stdout (the command line); the log file always gets them.
_ECHO: contextvars.ContextVar[bool] = contextvars.ContextVar("acm_rs_pipeline_echo", default=False)


def _say(msg: str) -> None:
    if _ECHO.get():
        print(msg, flush=True)
    log.info(msg)


def _skip(path: Path, overwrite: bool, what: str, fresh: dict) -> bool:
    """Whether the step that makes ``path`` can be skipped; says why it skips or redoes."""
    if overwrite:
        if path.exists():
            _say(f"{what}: --overwrite: redoing {path}")
        return False
    why = prov.stale(path, fresh)
    if why is None:
        if prov.read_record(path) is None:
            _say(
                f"{what}: {path} exists and was not made by this workflow (no record), kept "
                "(--overwrite to redo)"
            )
        else:
            _say(f"{what}: {path} is up to date (same inputs, settings, version), skipped")
        return True
    if path.exists():
        _say(f"{what}: redoing {path}: {why}")
    return False


def _calibration_path(config: ProjectConfig) -> Path:
    return config.root / config.paths["calibration"]


def step_calibrate(config: ProjectConfig, overwrite: bool = False) -> Path:
    """Calibrate from ``<project>/calibration/`` (one video, or one image folder, per camera;
    camera names from ``cameras.regex``) with the board of ``config.toml``.

    Returns
    -------
    Path
        The ``calibration.toml`` written (or found).
    """
    from .calibration import BoardSpec, calibrate, detect
    from .project import VIDEO_SUFFIXES, _camera_of

    out = _calibration_path(config)
    folder = config.root / "calibration"
    if out.exists() and not folder.is_dir() and not overwrite:
        _say(f"calibrate: {out} exists and there is no calibration/ folder, kept")
        return out
    if not folder.is_dir():
        raise FileNotFoundError(
            f"{folder}: no calibration folder; put one board video (or image folder) per camera "
            f"there, or an anipose calibration file at {out}"
        )
    regex = config.camera_regex
    sources = {}
    for p in sorted(folder.iterdir()):
        if p.is_dir() or p.suffix.lower() in VIDEO_SUFFIXES:
            cam = _camera_of(p, regex)
            if cam is not None:
                sources[cam] = p
    names = list(config.cameras["names"]) or sorted(sources)
    fresh = prov.fresh_record(
        "calibrate",
        {f"board:{n}": sources.get(n) for n in names},
        {"board": config.board(), "cameras": names},
    )
    if _skip(out, overwrite, "calibrate", fresh):
        return out
    missing = [n for n in names if n not in sources]
    if missing or not names:
        raise ValueError(
            f"{folder}: no calibration video or image folder for camera(s) {missing or names}; "
            f"found {sorted(sources)} with cameras.regex {regex.pattern!r}"
        )
    spec = BoardSpec.from_dict(config.board())
    det = detect(
        [sources[n] for n in names], spec, camera_names=names,
        cache=out.with_suffix(".detections.npz"), progress=None,
    )  # fmt: skip
    res = calibrate(det.corners, spec.board_points, det.image_sizes, camera_names=names)
    res.save(out)
    res.save_report(out.with_suffix(".report.json"), png=out.with_suffix(".qc.png"))
    prov.write_record(out, fresh)
    _say(f"calibrate: {len(names)} cameras, RMS {res.rms:.3f} px -> {out}")
    return out


def _load_rig(config: ProjectConfig, session: Session | None = None, cameras=None):
    """The calibrated rig in the order of ``cameras`` (default: the session's cameras, else
    ``cameras.names``, else the calibration's), cameras matched by name
    (:func:`acm_rs.project.match_cameras`). Returns ``(rig, {camera: (calibration name,
    how)})``."""
    from .camera import CameraRig
    from .project import match_cameras

    path = session.calibration if session is not None else _calibration_path(config)
    if path is None or not Path(path).is_file():
        raise FileNotFoundError(
            f"no calibration file {config.paths['calibration']} in the session or project; "
            "run `acm-rs run-all` (calibrate step) or copy an anipose calibration.toml there"
        )
    if cameras is None:
        cameras = session.cameras if session is not None else (config.cameras["names"] or None)
    calib_names = [c.name for c in CameraRig.load(path)]
    if cameras is None:
        cameras = calib_names
    mapping = match_cameras(list(cameras), calib_names, config.cameras["regex"])
    rig = CameraRig.load(path, names=[mapping[c][0] for c in cameras])
    return rig, mapping


def _model_file(config: ProjectConfig) -> Path | None:
    """The project's model file when ``project.model`` is a path (None for a bundled name)."""
    local = config.root / config.project["model"]
    return local if local.is_file() else None


def _generic_model(config: ProjectConfig):
    from .models import load_name_or_file

    spec = config.project["model"]
    local = config.root / spec
    return load_name_or_file(str(local) if local.is_file() else spec)


def step_learn(config: ProjectConfig, overwrite: bool = False) -> Path:
    """Learn bone lengths and marker offsets from ``paths.manual_labels`` (one DeepLabCut
    ``CollectedData`` file per camera, camera names from ``cameras.regex``).

    Without manual labels nothing is saved (and the log says so: tracking then uses the
    generic model). Skipped while its record (:mod:`acm_rs._provenance`) matches.
    """
    from .dlc import concat_labels, read_labels, shift_labels
    from .learning import learn_skeleton
    from .project import camera_table, find_manual_labels, read_dlc_config

    out = config.root / SKELETON_NAME
    folder = config.root / config.paths["manual_labels"]
    dlc = read_dlc_config(config.root)
    groups = find_manual_labels(folder, config.camera_regex, dlc.get("scorer") if dlc else None)
    if not groups:
        # nothing is learned, so nothing is saved as skeleton.toml: track says it uses the
        # generic model, and a later run with labels learns.
        _say(
            f"learn: WARNING: no manual labels in {folder} (files or "
            "<video>/CollectedData_*.h5|.csv); nothing learned, tracking will use the generic "
            f"{config.project['model']} model (bones off by the animal's size)"
        )
        return out
    label_files = {
        f"labels:{name or '.'}:{c}": f for name, g in sorted(groups.items()) for c, f in g.items()
    }
    fresh = prov.fresh_record(
        "learn",
        {**label_files, "calibration": _calibration_path(config), "model": _model_file(config)},
        {"model": config.project["model"], "body_weight": config.project.get("body_weight"),
         "pcutoff": config.tracking["pcutoff"], "individual": config.project.get("individual"),
         "cameras": list(config.cameras["names"]),
         **({"crop_offsets": config.crop_offsets} if config.crop_offsets else {})},
    )  # fmt: skip
    if _skip(out, overwrite, "learn", fresh):
        return out
    generic = _generic_model(config)
    cams = sorted({c for g in groups.values() for c in g})
    names = list(config.cameras["names"]) or cams
    unknown = sorted(set(cams) - set(names))
    if unknown:
        raise ValueError(f"{folder}: labels of camera(s) {unknown}, not in cameras.names {names}")
    rig, mapping = _load_rig(config, cameras=names)
    for name, files in sorted(groups.items()):
        table = camera_table(mapping, {f"labels {name or folder.name}": files})
        for line in table.splitlines():
            _say("learn: " + line)
    sets = [
        read_labels([g.get(c) for c in names], individual=config.project.get("individual"))
        for g in groups.values()
    ]
    # labelled frames come from the (cropped) videos: anipose crop offsets apply too
    labels = shift_labels(concat_labels(sets), config.offsets_for(names))
    pcutoff, why = labels.resolve_pcutoff(config.tracking["pcutoff"])
    if labels.likelihood is not None:
        _say(f"learn: likelihood cutoff {pcutoff:g} ({why})")
    res = learn_skeleton(
        rig, generic, labels.points, body_weight=config.project.get("body_weight"),
        marker_names=labels.bodyparts, progress=None, likelihood=labels.likelihood,
        pcutoff=pcutoff,
    )  # fmt: skip
    if generic.stretch_sd.any():  # a model with elastic segments: learn their SDs again
        from .elastic import add_stretch

        res, fit = add_stretch(res)
        _say(
            f"learn: elastic segments, EM {fit.iterations} iterations, label noise "
            f"{fit.noise_px:.2f} px, {len(res.skeleton.elastic_bones)} elastic bones"
        )
    res.skeleton.save(out)
    prov.write_record(out, fresh)
    _say(
        f"learn: {labels.points.shape[1]} labelled frames of {len(groups)} recording(s), "
        f"RMS {res.rms:.2f} px -> {out}"
    )
    for line in res.summary().splitlines():
        if "WARNING" in line or "note:" in line:
            _say("learn: " + line.strip())
    if len(rig) >= 3:  # leave-one-camera-out accuracy on the labels (docs/lab_keypoints.md)
        from .evaluate import evaluate

        try:
            ev = evaluate(rig, res.skeleton, labels, pcutoff=pcutoff)
        except ValueError as exc:
            _say(f"learn: no leave-one-camera-out evaluation: {exc}")
        else:
            files = ev.save(out.with_name("evaluation"))
            _say(f"learn: {ev.summary()} -> {files[0].name}, {files[-1].name}")
    return out


def _session_output(session: Session, out: Path | None) -> Path:
    return Path(out) if out is not None else session.output


def step_track(
    config: ProjectConfig, session: Session, overwrite: bool = False, out: Path | None = None
) -> Path:
    """Track one session's DeepLabCut predictions with the learned skeleton."""
    from .dlc import read_labels, shift_labels
    from .skeleton import Skeleton
    from .tracking import track

    folder = _session_output(session, out)
    path = folder / POSE_NAME
    if not session.labels:
        raise FileNotFoundError(
            f"{session.path / config.paths['labels']}: no DeepLabCut predictions for this session"
        )
    from .project import camera_table

    skel_path = config.root / SKELETON_NAME
    learned = skel_path.is_file()
    fresh = prov.fresh_record(
        f"track {session.name}",
        {**{f"labels:{c}": session.labels.get(c) for c in session.cameras},
         "calibration": session.calibration, "skeleton": skel_path if learned else None,
         "model": None if learned else _model_file(config)},
        {"tracking": {k: v for k, v in config.tracking.items() if k != "fps"},  # fps: export
         "em": config.em, "cameras": list(session.cameras),
         "individual": config.project.get("individual"),
         "model": None if learned else config.project["model"],
         **({"crop_offsets": config.crop_offsets} if config.crop_offsets else {})},
    )  # fmt: skip
    if _skip(path, overwrite, f"track {session.name}", fresh):
        return path
    rig, mapping = _load_rig(config, session)
    table = camera_table(mapping, {"video": session.videos, "2D poses": session.labels})
    for line in table.splitlines():
        _say(f"track {session.name}: " + line)
    if learned:
        skeleton = Skeleton.load(skel_path)
    else:
        skeleton = _generic_model(config)
        _say(
            f"track {session.name}: WARNING: no learned {skel_path}; tracking with the generic "
            f"{skeleton.name} model (run the learn step with manual labels for accurate bones)"
        )
    ls = read_labels(
        [session.labels[c] for c in session.cameras], individual=config.project.get("individual")
    )
    ls = shift_labels(ls, config.offsets_for(session.cameras))  # anipose crop offsets
    dt = int(config.tracking["dt"])
    lik = ls.likelihood[:, ::dt] if ls.likelihood is not None else None
    pcutoff, why = ls.resolve_pcutoff(config.tracking["pcutoff"])
    if lik is not None:
        _say(f"track {session.name}: likelihood cutoff {pcutoff:g} ({why})")
    res = track(
        rig, skeleton, ls.points[:, ::dt], likelihood=lik, pcutoff=pcutoff,
        max_iter=config.em["max_iter"], tol=config.em["tol"], marker_names=ls.bodyparts,
        progress=None,
    )  # fmt: skip
    res.info["frames"] = ls.frames[::dt]
    res.info["skeleton"] = "learned" if learned else f"generic {skeleton.name}"
    folder.mkdir(parents=True, exist_ok=True)
    res.save(path)
    interrupted = bool(res.info.get("interrupted"))
    prov.write_record(path, fresh, interrupted=interrupted)
    if interrupted:
        _say(f"track {session.name}: interrupted (Ctrl-C); {path} is marked unfinished")
        raise KeyboardInterrupt
    _say(f"track {session.name}: {res.summary().splitlines()[0]} -> {path}")
    return path


def _check_finished(pose: Path, what: str) -> None:
    """Refuse to work from a pose file of an interrupted (or missing) track step."""
    if not pose.is_file():
        raise FileNotFoundError(f"{what}: no {pose}; run the track step first")
    rec = prov.read_record(pose)
    if rec is not None and rec.get("interrupted"):
        raise ValueError(f"{what}: {pose} is from an interrupted track step; run track again")


def step_export(
    config: ProjectConfig, session: Session, overwrite: bool = False, out: Path | None = None
) -> list[Path]:
    """anipose CSV (+ variance sidecar) always; NWB, C3D and movement netCDF when the frame
    rate is known (``tracking.fps`` or the videos' metadata)."""
    from . import export
    from .tracking import PoseResult

    folder = _session_output(session, out)
    csv = folder / "pose_3d.csv"
    video_fps = session_fps(config, session)
    fps = video_fps / int(config.tracking["dt"]) if video_fps else None  # the tracked frames
    fresh = prov.fresh_record(f"export {session.name}", {"pose": folder / POSE_NAME}, {"fps": fps})
    _check_finished(folder / POSE_NAME, f"export {session.name}")
    if _skip(csv, overwrite, f"export {session.name}", fresh):
        return [csv]
    res = PoseResult.load(folder / POSE_NAME)
    files = export.to_anipose_csv(res, csv)
    if fps:
        try:
            files.append(export.to_movement_file(res, folder / "pose_movement.nc", fps=video_fps))
        except ImportError as exc:  # xarray/netCDF are the optional extra [movement]
            _say(f"export {session.name}: no movement file ({exc})")
        files.append(
            export.to_nwb(
                res,
                folder / "pose.nwb",
                rate=fps,
                session_description=f"acm-rs poses of session {session.name}",
            )  # fmt: skip
        )
        files.append(export.to_c3d(res, folder / "pose.c3d", fps, joints=True))
    else:
        _say(
            f"export {session.name}: no frame rate (tracking.fps unset, no video metadata); "
            "NWB, C3D and movement files skipped"
        )
    prov.write_record(csv, fresh)
    _say(f"export {session.name}: {', '.join(f.name for f in files)}")
    return files


def session_fps(config: ProjectConfig, session: Session) -> float | None:
    """Frame rate (Hz) of a session's videos: ``tracking.fps``, else the videos' metadata."""
    from .project import videos_fps

    fps = config.tracking.get("fps")
    if fps:
        return float(fps)
    return videos_fps([session.videos[c] for c in session.cameras if c in session.videos])


def step_plot(
    config: ProjectConfig, session: Session, overwrite: bool = False, out: Path | None = None
) -> list[Path]:
    """The tracking figures of :func:`acm_rs.plots.plot_all` in ``<output>/plots``."""
    from .plots import plot_all
    from .tracking import PoseResult

    folder = _session_output(session, out) / "plots"
    pose = _session_output(session, out) / POSE_NAME
    fps = session_fps(config, session)
    rate = fps / int(config.tracking["dt"]) if fps else None  # of the tracked frames
    fresh = prov.fresh_record(
        f"plot {session.name}",
        {"pose": pose, **{f"video:{c}": v for c, v in session.videos.items()}},
        {"fps": rate, "dt": config.tracking["dt"]},
    )
    _check_finished(pose, f"plot {session.name}")
    if _skip(folder, overwrite, f"plot {session.name}", fresh):
        return []
    res = PoseResult.load(pose)
    files = plot_all(res, folder, frame_rate=rate)
    try:
        from .plots.viewer import view_html

        files.append(view_html(res, folder / "view.html", fps=rate))
    except ImportError as exc:  # plotly is the optional extra [view]
        _say(f"plot {session.name}: no 3D viewer ({exc})")
    _say(f"plot {session.name}: {len(files)} figures in {folder}")
    if session.videos and all(c in session.videos for c in session.cameras):
        from .plots import overlay_video

        dt = int(config.tracking["dt"])
        try:
            if dt != 1:
                raise ValueError(f"tracking.dt = {dt}: the overlay needs every frame tracked")
            files += overlay_video(
                res, [session.videos[c] for c in session.cameras], folder / "overlay.mp4"
            )
            _say(f"plot {session.name}: overlay video {folder / 'overlay.mp4'}")
        except ValueError as exc:  # e.g. videos longer than the tracked range
            _say(f"plot {session.name}: no overlay video ({exc})")
    prov.write_record(folder, fresh)
    return files


def run_all(
    project: str | Path,
    overwrite: bool = False,
    steps: tuple[str, ...] = STEPS,
    verbose: bool = False,
) -> dict[str, str]:
    """Run ``steps`` on every session of a project; a failing session does not stop the
    others. Returns ``{session name: "ok" | error message}``.

    One line per stage goes to the project's log file; with ``verbose`` (the command line)
    also to stdout. Progress bars appear only on a terminal.
    """
    token = _ECHO.set(bool(verbose))
    try:
        return _run_all(project, overwrite, steps)
    finally:
        _ECHO.reset(token)


def _run_all(project: str | Path, overwrite: bool, steps: tuple[str, ...]) -> dict[str, str]:
    bad = [s for s in steps if s not in STEPS]
    if bad:
        raise ValueError(f"unknown step(s) {bad}; steps are {list(STEPS)}")
    config = load_config(Path(project) / "config.toml")
    status: dict[str, str] = {}
    with project_log(config) as log_path:
        _say(f"acm-rs: project {config.root}, steps {', '.join(steps)}; log {log_path}")
        has_board_media = (config.root / "calibration").is_dir() and any(
            p.suffix.lower() != ".toml" and not p.name.startswith(".")
            for p in (config.root / "calibration").iterdir()
        )
        if "calibrate" in steps and (has_board_media or not _calibration_path(config).exists()):
            step_calibrate(config, overwrite)
        if "learn" in steps:
            step_learn(config, overwrite)
        for session in find_sessions(config):
            try:
                if "track" in steps:
                    step_track(config, session, overwrite)
                if "export" in steps:
                    step_export(config, session, overwrite)
                if "plot" in steps:
                    step_plot(config, session, overwrite)
                status[session.name] = "ok"
            except KeyboardInterrupt:
                status[session.name] = "interrupted"
                _say(f"acm-rs: session {session.name} interrupted; it is not done")
                raise
            except (ValueError, OSError, ArithmeticError) as exc:
                status[session.name] = f"{type(exc).__name__}: {exc}"
                log.exception("session %s failed", session.name)
                if _ECHO.get():
                    print(f"session {session.name} FAILED: {exc}", flush=True)
        _say(f"acm-rs: {sum(v == 'ok' for v in status.values())}/{len(status)} sessions ok")
    return status


def run_session(session_dir: str | Path, out_dir: str | Path) -> dict:
    """Track, export and plot one session (the default per-session function of
    :func:`acm_rs.batch.run`); the project's ``config.toml`` is in the session's parent (or in
    the session folder itself: a DeepLabCut project)."""
    session_dir = Path(session_dir)
    own = session_dir / "config.toml"
    config = load_config(own if own.is_file() else session_dir.parent / "config.toml")
    matches = [s for s in find_sessions(config) if s.path.resolve() == session_dir.resolve()]
    if not matches:
        raise ValueError(f"{session_dir} is not a session of the project {config.root}")
    s = matches[0]
    out = Path(out_dir)
    pose = step_track(config, s, True, out)
    files = step_export(config, s, True, out)
    plots = step_plot(config, s, True, out)
    return {"pose": str(pose), "exports": [str(f) for f in files], "plots": len(plots)}


def run_step(
    project: str | Path, step: str, overwrite: bool = False, verbose: bool = False
) -> dict[str, str]:
    """One step of the workflow on a project (``acm-rs <step> --project DIR``)."""
    return run_all(project, overwrite=overwrite, steps=(step,), verbose=verbose)


def add_project_option(parser, step: str) -> None:
    """``--project DIR``: run this command as a step of the project workflow instead."""
    parser.add_argument(
        "--project",
        help=f"run the {step} step on a project folder (config.toml; see docs/project.md) "
        "instead of on the files given; other options are then ignored",
    )
    parser.add_argument(
        "--overwrite-step", action="store_true", help="with --project: redo finished work"
    )


def project_step_or(args, step: str, func, required: tuple[str, ...]) -> int:
    """Dispatch for commands that also work on a project folder: with ``--project`` run the
    step there, else check the command's own required options and run ``func(args)``."""
    if getattr(args, "project", None):
        status = run_step(args.project, step, overwrite=args.overwrite_step, verbose=True)
        return 0 if all(v == "ok" for v in status.values()) else 1
    missing = [r for r in required if not getattr(args, r.lstrip("-").replace("-", "_"), None)]
    if missing:
        raise ValueError(
            f"acm-rs {step} needs {', '.join(missing)} (or --project DIR for a project folder)"
        )
    return int(func(args))


def _cmd_run_all(args) -> int:
    steps = tuple(args.steps.split(",")) if args.steps else STEPS
    status = run_all(args.project, overwrite=args.overwrite, steps=steps, verbose=True)
    return 0 if all(v == "ok" for v in status.values()) else 1


def _cmd_plot(args) -> int:
    from .plots import plot_all
    from .tracking import PoseResult

    src = Path(args.input)
    if src.is_dir():
        config = load_config(src / "config.toml")
        token = _ECHO.set(True)
        try:
            with project_log(config):
                for session in find_sessions(config):
                    step_plot(config, session, overwrite=args.overwrite)
        finally:
            _ECHO.reset(token)
        return 0
    out = Path(args.output) if args.output else src.with_name(src.stem + "_plots")
    if out.is_dir() and any(out.iterdir()) and not args.overwrite:
        raise ValueError(f"{out} holds files already; pass --overwrite to replace its figures")
    res = PoseResult.load(src)
    files = plot_all(res, out, pdf=args.pdf, frame_rate=args.rate)
    for f in files:
        print(f"  wrote {f}")
    return 0


def add_subcommands(sub) -> None:
    """Add ``acm-rs run-all`` and ``acm-rs plot`` to an argparse subparsers object."""
    p = sub.add_parser(
        "run-all",
        help="run calibrate, learn, track, export and plot on a project folder",
        description="Runs the project workflow (docs/project.md); finished steps are skipped "
        "unless --overwrite; one log per run in <project>/logs/.",
    )
    p.add_argument("project", nargs="?", default=".", help="project folder (config.toml)")
    p.add_argument("--steps", help=f"comma-separated subset of {','.join(STEPS)}")
    p.add_argument("--overwrite", action="store_true", help="redo finished steps")
    p.set_defaults(func=_cmd_run_all)
    q = sub.add_parser("plot", help="tracking figures of a result (.npz) or of a whole project")
    q.add_argument("input", help="pose .npz (acm-rs track) or a project folder")
    q.add_argument("-o", "--output", help="folder for the figures (default: <input>_plots)")
    q.add_argument("--pdf", action="store_true", help="also write PDF")
    q.add_argument("--rate", type=float, help="frame rate (Hz) for time axes in seconds")
    q.add_argument("--overwrite", action="store_true", help="replace existing figures")
    q.set_defaults(func=_cmd_plot)
