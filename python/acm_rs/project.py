"""Project folders like anipose's: a commented ``config.toml`` and one subfolder per session.

::

    my_project/
      config.toml                    # acm-rs init writes it; load_config validates it
      calibration/calibration.toml   # shared calibration (or one per session)
      session_01/
        videos/  rat-camA.mp4 rat-camB.mp4 ...
        pose-2d/ rat-camADLC_resnet50_...h5 ...
        acm-rs/                      # outputs of this session (paths.output)

Camera names are parsed from file names with ``cameras.regex``; see ``docs/project.md``.
"""

from __future__ import annotations

import difflib
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ._io import atomic_write

__all__ = [
    "CONFIG_NAME",
    "ProjectConfig",
    "Session",
    "find_sessions",
    "init_project",
    "load_config",
]

CONFIG_NAME = "config.toml"
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".ccv")
LABEL_SUFFIXES = (".h5", ".csv")


@dataclass(frozen=True)
class _Opt:
    """One config key: default, accepted types, check, hint for errors, comment for init."""

    default: Any
    types: tuple[type, ...]
    comment: str
    check: Callable[[Any], bool] | None = None
    hint: str = ""
    optional: bool = False  # may be absent (no default written)


_NUM = (int, float)
_LIST = (list,)


def _pair_of_ints(v: Any) -> bool:
    return len(v) == 2 and all(isinstance(x, int) and not isinstance(x, bool) and x > 1 for x in v)


def _regex_ok(v: str) -> bool:
    try:
        re.compile(v)
    except re.error:
        return False
    return True


#: The schema of config.toml: section -> key -> option (order = order in the written file).
SCHEMA: dict[str, dict[str, _Opt]] = {
    "project": {
        "model": _Opt(
            "rat",
            (str,),
            "skeleton model: 'rat', 'mouse' or the path of a skeleton TOML file",
            lambda v: bool(v),
            "a model name or path",
        ),
        "body_weight": _Opt(
            None,
            _NUM,
            "body weight in g, for the bone-length priors of the rat model",
            lambda v: v > 0,
            "> 0 g",
            optional=True,
        ),
    },
    "paths": {
        "videos": _Opt("videos", (str,), "per session: folder of the videos"),
        "labels": _Opt("pose-2d", (str,), "per session: folder of the DeepLabCut 2D predictions"),
        "calibration": _Opt(
            "calibration/calibration.toml",
            (str,),
            "anipose calibration.toml, looked up in the session, then in the project folder",
        ),
        "manual_labels": _Opt(
            "labeled-data",
            (str,),
            "folder of DeepLabCut CollectedData_*.csv/.h5 used for skeleton learning",
        ),
        "output": _Opt("acm-rs", (str,), "per session: folder acm-rs writes its results to"),
    },
    "cameras": {
        "regex": _Opt(
            r"cam([A-Za-z0-9]+)",
            (str,),
            "regex finding the camera name in file names (first group, else the whole match)",
            _regex_ok,
            "a valid regular expression",
        ),
        "names": _Opt(
            [],
            _LIST,
            "camera names in rig order; empty: every camera found, sorted",
            lambda v: all(isinstance(x, str) and x for x in v) and len(set(v)) == len(v),
            "a list of distinct names",
        ),
    },
    "calibration": {
        "board_type": _Opt(
            "charuco",
            (str,),
            "'charuco' or 'checkerboard' (anipose keys)",
            lambda v: v in ("charuco", "checkerboard"),
            "'charuco' or 'checkerboard'",
        ),
        "board_size": _Opt(
            [10, 7], _LIST, "[squares x, squares y]", _pair_of_ints, "two integers > 1"
        ),
        "board_square_side_length": _Opt(
            2.5, _NUM, "square side, in the length unit of the results (e.g. cm)", lambda v: v > 0
        ),
        "board_marker_length": _Opt(
            1.875, _NUM, "ArUco marker side (same unit; ChArUco only)", lambda v: v > 0
        ),
        "board_marker_bits": _Opt(4, (int,), "bits per marker side (4, 5, 6 or 7)", None),
        "board_marker_dict_number": _Opt(
            50, (int,), "markers in the ArUco dictionary (50, 100, 250 or 1000)", None
        ),
        "legacy_pattern": _Opt(
            False,
            (bool,),
            "true for boards printed for OpenCV < 4.6 (the #1 cause of '0 boards detected')",
        ),
    },
    "tracking": {
        "pcutoff": _Opt(
            0.9,
            _NUM,
            "detections with a lower likelihood are treated as missing",
            lambda v: 0 <= v <= 1,
            "a likelihood in [0, 1]",
        ),
        "dt": _Opt(1, (int,), "track every dt-th frame", lambda v: v >= 1, "an integer >= 1"),
        "fps": _Opt(
            None, _NUM, "video frame rate in Hz (exports)", lambda v: v > 0, "> 0", optional=True
        ),
    },
    "em": {
        "max_iter": _Opt(100, (int,), "maximum EM iterations", lambda v: v >= 1, ">= 1"),
        "tol": _Opt(0.05, _NUM, "stop when the relative change is below tol", lambda v: v > 0),
    },
}

_HEADER = """\
# acm-rs project configuration. Written by `acm-rs init`; edit freely.
# Paths are relative to the session folder (or this folder). Sessions are the subfolders
# of this folder that contain the videos or labels folder named below.
# Docs: docs/project.md. Unknown keys are errors (typos are caught).
"""


def _toml_value(v: Any) -> str:
    from ._toml import _value

    return _value(v)


def _config_text(overrides: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    lines = [_HEADER.rstrip("\n")]
    for section, opts in SCHEMA.items():
        lines += ["", f"[{section}]"]
        for key, opt in opts.items():
            value = (overrides or {}).get(section, {}).get(key, opt.default)
            lines.append(f"# {opt.comment}")
            if value is None:
                lines.append(f"# {key} = ...")
            else:
                lines.append(f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def init_project(
    path: str | Path,
    *,
    overwrite: bool = False,
    **sections: Mapping[str, Any],
) -> Path:
    """Create a project folder with a commented ``config.toml`` (anipose-like).

    Parameters
    ----------
    path : path
        Project folder (created).
    overwrite : bool
        Replace an existing ``config.toml`` (default: refuse).
    **sections : mapping
        Values to write instead of the defaults, by section, e.g.
        ``init_project(p, project={"model": "mouse"}, tracking={"pcutoff": 0.8})``;
        validated like :func:`load_config`.

    Returns
    -------
    Path
        The ``config.toml`` written (atomically).
    """
    root = Path(path)
    target = root / CONFIG_NAME
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} exists; pass overwrite=True (--overwrite) to replace it")
    text = _config_text(sections)
    _validate(tomllib.loads(text), str(target))  # overrides are checked before writing
    root.mkdir(parents=True, exist_ok=True)
    with atomic_write(target, "w") as fh:
        fh.write(text)
    return target


@dataclass
class ProjectConfig:
    """A validated ``config.toml``: ``config.tracking["pcutoff"]``, ``config.em["tol"]``, ...

    Attributes
    ----------
    root : Path
        Project folder (the folder of config.toml).
    project, paths, cameras, calibration, tracking, em : dict
        Every key of the section with defaults filled in (None for absent optional keys).
    path : Path
        The config file.
    """

    root: Path
    project: dict
    paths: dict
    cameras: dict
    calibration: dict
    tracking: dict
    em: dict
    path: Path

    @property
    def camera_regex(self) -> re.Pattern:
        """Compiled ``cameras.regex``."""
        return re.compile(self.cameras["regex"])

    def board(self) -> dict:
        """The board spec with anipose's keys (``board_type``, ``board_size``, ...)."""
        return dict(self.calibration)


def _closest(name: str, options: list[str]) -> str:
    close = difflib.get_close_matches(name, options, n=1, cutoff=0.5)
    return f"; did you mean {close[0]!r}?" if close else f"; valid: {options}"


def _type_name(types: tuple[type, ...]) -> str:
    names = {int: "an integer", float: "a number", str: "a string", bool: "true/false"}
    names[list] = "a list"
    if types == _NUM:
        return "a number"
    return " or ".join(names.get(t, t.__name__) for t in types)


def _validate(doc: Mapping[str, Any], source: str) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for section in doc:
        if section not in SCHEMA:
            raise ValueError(
                f"{source}: unknown section [{section}]" + _closest(section, list(SCHEMA))
            )
        if not isinstance(doc[section], dict):
            raise ValueError(f"{source}: {section} must be a table [{section}]")
    for section, opts in SCHEMA.items():
        table = doc.get(section, {})
        for key in table:
            if key not in opts:
                raise ValueError(
                    f"{source}: unknown key {section}.{key}" + _closest(key, list(opts))
                )
        values = {}
        for key, opt in opts.items():
            if key not in table:
                values[key] = opt.default
                continue
            v = table[key]
            ok_type = isinstance(v, opt.types) and not (
                isinstance(v, bool) and bool not in opt.types
            )
            if not ok_type:
                raise ValueError(
                    f"{source}: {section}.{key} must be {_type_name(opt.types)}, got "
                    f"{type(v).__name__} {v!r}"
                )
            if opt.check is not None and not opt.check(v):
                raise ValueError(
                    f"{source}: {section}.{key} = {v!r} is invalid"
                    + (f": expected {opt.hint}" if opt.hint else "")
                )
            values[key] = float(v) if opt.types == _NUM else v
        out[section] = values
    return out


def load_config(path: str | Path) -> ProjectConfig:
    """Read and validate a project's ``config.toml`` (the file or its folder).

    Raises
    ------
    FileNotFoundError
        No config file (the message says to run ``acm-rs init``).
    ValueError
        Invalid TOML; an unknown section or key (naming the closest valid one, for typos);
        a value of the wrong type (naming the key and the expected type) or out of range.
    """
    p = Path(path)
    if p.is_dir():
        p = p / CONFIG_NAME
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no project config; create one with `acm-rs init {p.parent}`")
    try:
        doc = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{p}: invalid TOML: {exc}") from None
    sections = _validate(doc, str(p))
    return ProjectConfig(root=p.parent.resolve(), path=p, **sections)


# -- sessions -------------------------------------------------------------------------------------
@dataclass
class Session:
    """One recording session of a project.

    Attributes
    ----------
    name : str
        Folder name.
    path : Path
    cameras : list of str
        Camera names in rig order.
    videos, labels : dict
        Camera name -> file (empty if the session has no such folder).
    calibration : Path or None
        The calibration file found (session first, then project).
    output : Path
        Folder for this session's results.
    """

    name: str
    path: Path
    cameras: list[str]
    videos: dict[str, Path] = field(default_factory=dict)
    labels: dict[str, Path] = field(default_factory=dict)
    calibration: Path | None = None
    output: Path = Path()


def _camera_of(file: Path, regex: re.Pattern) -> str | None:
    """Camera name in a file name; DeepLabCut outputs ``<video stem>DLC_<network>...`` are
    matched on the video stem only."""
    stem = file.stem.split("DLC_", 1)[0] if "DLC_" in file.stem else file.stem
    m = regex.search(stem)
    if m is None:
        return None
    return m.group(1) if m.groups() and m.group(1) is not None else m.group(0)


def _files_by_camera(folder: Path, suffixes: tuple[str, ...], regex: re.Pattern) -> dict:
    out: dict[str, Path] = {}
    if not folder.is_dir():
        return out
    for f in sorted(folder.iterdir()):
        if not f.is_file() or f.name.startswith(".") or f.suffix.lower() not in suffixes:
            continue
        cam = _camera_of(f, regex)
        if cam is None:
            raise ValueError(
                f"{f}: no camera name matches cameras.regex {regex.pattern!r}; rename the file "
                "or change the regex in config.toml"
            )
        if cam in out:
            if out[cam].suffix.lower() == ".csv" and f.suffix.lower() == ".h5":
                out[cam] = f  # DeepLabCut writes both; prefer the .h5
                continue
            if out[cam].suffix.lower() == ".h5" and f.suffix.lower() == ".csv":
                continue
            raise ValueError(
                f"{folder}: two files for camera {cam!r}: {out[cam].name} and {f.name}; keep one"
            )
        out[cam] = f
    return out


def find_sessions(config: ProjectConfig) -> list[Session]:
    """The sessions of a project: subfolders holding ``paths.videos`` or ``paths.labels``.

    Camera names come from the file names via ``cameras.regex``. With ``cameras.names`` set,
    each named camera must have a file in each present folder, and every file must belong to
    a named camera.

    Raises
    ------
    FileNotFoundError
        No session folder at all (the message says what a session needs).
    ValueError
        A file without a camera name, a configured camera that matches no file (naming the
        camera, the folder and the cameras found), two files for one camera, or sessions
        whose video and label folders name different cameras.
    """
    regex = config.camera_regex
    root = config.root
    names = list(config.cameras["names"])
    sessions = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        if folder.name.startswith((".", "_")):
            continue
        vdir, ldir = folder / config.paths["videos"], folder / config.paths["labels"]
        if not (vdir.is_dir() or ldir.is_dir()):
            continue
        videos = _files_by_camera(vdir, VIDEO_SUFFIXES, regex)
        labels = _files_by_camera(ldir, LABEL_SUFFIXES, regex)
        found = {"videos": videos, "labels": labels}
        for kind, files in found.items():
            d = vdir if kind == "videos" else ldir
            if not d.is_dir():
                continue
            if names:
                missing = [c for c in names if c not in files]
                if missing:
                    raise ValueError(
                        f"{d}: camera {missing[0]!r} (cameras.names) matches no file; cameras "
                        f"found with regex {regex.pattern!r}: {sorted(files) or 'none'}. "
                        "Fix the file names, cameras.names or cameras.regex"
                    )
                extra = sorted(set(files) - set(names))
                if extra:
                    raise ValueError(
                        f"{d}: file {files[extra[0]].name} is camera {extra[0]!r}, which is not "
                        f"in cameras.names {names}; add it or move the file"
                    )
        cams = names or sorted(set(videos) | set(labels))
        if not names and videos and labels and set(videos) != set(labels):
            raise ValueError(
                f"{folder}: videos name cameras {sorted(videos)} but labels name "
                f"{sorted(labels)}; every camera needs both (or set cameras.names)"
            )
        calib = None
        for base in (folder, root):
            cand = base / config.paths["calibration"]
            if cand.is_file():
                calib = cand
                break
        sessions.append(
            Session(
                name=folder.name,
                path=folder,
                cameras=cams,
                videos=videos,
                labels=labels,
                calibration=calib,
                output=folder / config.paths["output"],
            )
        )
    if not sessions:
        raise FileNotFoundError(
            f"{root}: no sessions: a session is a subfolder with a {config.paths['videos']}/ or "
            f"{config.paths['labels']}/ folder (paths.videos / paths.labels in config.toml)"
        )
    return sessions


# -- command line ---------------------------------------------------------------------------------
def _cmd_init(args) -> int:
    overrides: dict[str, dict] = {}
    if args.model:
        overrides["project"] = {"model": args.model}
    path = init_project(args.path, overwrite=args.overwrite, **overrides)
    print(f"acm-rs init: wrote {path}")
    print("  edit it (board, camera regex, pcutoff), then put one folder per session beside it")
    return 0


def add_subcommands(sub) -> None:
    """Add ``acm-rs init`` to an argparse subparsers object."""
    p = sub.add_parser("init", help="create a project folder with a commented config.toml")
    p.add_argument("path", nargs="?", default=".", help="project folder (default: here)")
    p.add_argument("--model", help="'rat', 'mouse' or a skeleton TOML path (default rat)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing config.toml")
    p.set_defaults(func=_cmd_init)
