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
A DeepLabCut project folder (``config.yaml``, ``videos/``, ``labeled-data/``) is itself a
session when ``paths.videos`` names its ``videos/`` folder (``acm-rs init`` on a DeepLabCut
project writes such a config).
"""

from __future__ import annotations

import difflib
import re
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._io import atomic_write

__all__ = [
    "CONFIG_NAME",
    "ProjectConfig",
    "Session",
    "camera_table",
    "dlc_bodyparts",
    "find_manual_labels",
    "find_sessions",
    "init_project",
    "load_config",
    "match_cameras",
    "pick_label_file",
    "read_dlc_config",
    "rig_for_files",
    "video_fps",
    "videos_fps",
]

CONFIG_NAME = "config.toml"
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".ccv")
LABEL_SUFFIXES = (".h5", ".csv", ".slp")
DLC_CONFIG = "config.yaml"


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
        "individual": _Opt(
            None,
            (str,),
            "multi-animal DeepLabCut/SLEAP files: the individual (track) to reconstruct",
            lambda v: bool(v),
            "an individual's name",
            optional=True,
        ),
    },
    "paths": {
        "videos": _Opt("videos", (str,), "per session: folder of the videos"),
        "labels": _Opt(
            "pose-2d",
            (str,),
            "per session: folder of the 2D predictions (DeepLabCut/Lightning Pose .h5/.csv, "
            "SLEAP .slp/.analysis.h5)",
        ),
        "labels_filter": _Opt(
            "",
            (str,),
            "use only prediction files whose name contains this text (e.g. a DeepLabCut scorer "
            "'DLC_resnet50_ratJan1shuffle1_100000'); empty: all",
        ),
        "prefer_filtered": _Opt(
            False,
            (bool,),
            "use DeepLabCut's *_filtered predictions when present (default: the raw ones; the "
            "tracking model smooths in time itself)",
        ),
        "calibration": _Opt(
            "calibration/calibration.toml",
            (str,),
            "anipose calibration.toml, looked up in the session, then in the project folder",
        ),
        "manual_labels": _Opt(
            "labeled-data",
            (str,),
            "folder of DeepLabCut manual labels for skeleton learning: <video>/CollectedData_"
            "<scorer>.h5|.csv (DeepLabCut's labeled-data layout) or CollectedData files",
        ),
        "output": _Opt("acm-rs", (str,), "per session: folder acm-rs writes its results to"),
    },
    "cameras": {
        "regex": _Opt(
            # "camera" is taken whole: DeepLabCut 3D names cameras camera-1, camera-2, and a
            # match of "camera" alone would give both files the same name
            r"(?i)cam(?:era)?[-_]?[a-z0-9]+",
            (str,),
            "regex finding the camera name in file names (first group, else the whole match); "
            "names are matched to the calibration's exactly, else ignoring case, separators "
            "and a 'cam'/'camera' prefix (cam0 = Cam_0 = 0, camera-1 = 1)",
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
            "auto",
            (*_NUM, str),
            'detections with a lower likelihood are treated as missing; "auto": by the label '
            "files' tool (0.9 DeepLabCut, 0.2 SLEAP)",
            lambda v: v == "auto" if isinstance(v, str) else 0 <= v <= 1,
            'a likelihood in [0, 1] or "auto"',
        ),
        "dt": _Opt(1, (int,), "track every dt-th frame", lambda v: v >= 1, "an integer >= 1"),
        "fps": _Opt(
            None,
            _NUM,
            "video frame rate in Hz (time axes, exports); absent: read from the session's videos",
            lambda v: v > 0,
            "> 0",
            optional=True,
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
    if target.is_file() and _is_anipose_file(target):
        # --overwrite would destroy the anipose project's config, which acm-rs reads as is
        raise FileExistsError(
            f"{target} is an anipose project's config, which acm-rs reads as it is (no init "
            f"needed); put acm-rs settings in its [{ANIPOSE_TABLE}.<section>] tables, e.g. "
            f"[{ANIPOSE_TABLE}.project] model = 'mouse'"
        )
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
    #: Anipose crop offsets: camera name -> (x, y) px of the cropped video's top-left corner
    #: in the calibrated (full) image, from ``[cameras.<name>] offset``.
    crop_offsets: dict = field(default_factory=dict)
    #: For an anipose project's config: what else was read from it (``constraints``,
    #: ``constraints_weak``, ``nesting``); None for an acm-rs config.
    anipose: dict | None = None

    @property
    def camera_regex(self) -> re.Pattern:
        """Compiled ``cameras.regex``."""
        return re.compile(self.cameras["regex"])

    def offsets_for(self, cameras: list[str]) -> np.ndarray | None:
        """``(n_cams, 2)`` crop offsets (x, y) px of ``cameras`` (0 for a camera without one,
        as anipose does); None when the project has none. Warns about offsets of cameras not
        in ``cameras`` (a camera-name mismatch would otherwise leave points unshifted)."""
        if not self.crop_offsets:
            return None
        unused = sorted(set(self.crop_offsets) - set(cameras))
        if unused:
            import warnings

            warnings.warn(
                f"{self.path}: crop offsets for camera(s) {unused}, which no file of the "
                f"session names (cameras: {cameras}); check cameras.regex / cam_regex",
                stacklevel=2,
            )
        return np.array([self.crop_offsets.get(c, (0.0, 0.0)) for c in cameras], dtype=float)

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
    if is_anipose_config(doc):
        return _anipose_config(doc, p)
    sections = _validate(doc, str(p))
    return ProjectConfig(root=p.parent.resolve(), path=p, **sections)


# -- anipose projects -----------------------------------------------------------------------------
#: Keys only an anipose ``config.toml`` has (anipose.py's DEFAULT_CONFIG and its docs).
_ANIPOSE_KEYS = {
    "model_folder", "nesting", "video_extension", "model_type", "converted_video_speed",
    "triangulation", "pipeline", "filter", "filter3d", "labeling", "angles",
    "manual_verification",
}  # fmt: skip
_ANIPOSE_BOARD_KEYS = (
    "board_type", "board_size", "board_marker_bits", "board_marker_dict_number",
    "board_marker_length", "board_square_side_length",
)  # fmt: skip
#: acm-rs's settings inside an anipose config (anipose ignores tables it does not know).
ANIPOSE_TABLE = "acm_rs"


def is_anipose_config(doc: Mapping[str, Any]) -> bool:
    """Whether a parsed ``config.toml`` is an anipose project's (``project = "name"`` is a
    string there, or a key only anipose has)."""
    return isinstance(doc.get("project"), str) or bool(_ANIPOSE_KEYS & set(doc))


def _anipose_config(doc: Mapping[str, Any], p: Path) -> ProjectConfig:
    """An anipose project's ``config.toml`` as a :class:`ProjectConfig`.

    Read (anipose's keys and defaults): ``[pipeline] videos_raw`` (``videos-raw``), ``pose_2d``
    (``pose-2d``) and ``calibration_results`` (``calibration``) as the paths;
    ``[triangulation] cam_regex`` as ``cameras.regex``; the board of ``[calibration]``;
    ``[cameras.<name>] offset = [x, y]`` or ``[x, y, w, h]`` as crop offsets; ``constraints``
    and ``constraints_weak`` kept in ``config.anipose``. acm-rs's own settings (model,
    pcutoff, ...) go in an ``[acm_rs.<section>]`` table of the same file.
    """
    src = str(p)
    nesting = doc.get("nesting", 1)
    if nesting not in (0, 1):
        raise ValueError(
            f"{src}: anipose nesting = {nesting!r}: acm-rs finds sessions in the project folder "
            "and its subfolders (nesting 0 or 1); move the session folders up to one level"
        )
    pipe = _table(doc, "pipeline", src)
    tri = _table(doc, "triangulation", src)
    cal = _table(doc, "calibration", src)
    if cal.get("board_type") == "aruco":
        raise ValueError(
            f"{src}: anipose board_type 'aruco': acm-rs calibrates with charuco or checkerboard "
            "boards only; calibrate with `anipose calibrate` (acm-rs reads its calibration.toml)"
            " and set board_type under [acm_rs.calibration]"
        )
    if cal.get("fisheye"):
        raise ValueError(
            f"{src}: anipose calibration.fisheye = true: acm-rs supports pinhole cameras with "
            "OpenCV's k1, k2, p1, p2, k3 distortion only"
        )
    calib_dir = pipe.get("calibration_results", "calibration")
    sections: dict[str, dict] = {
        "paths": {
            "videos": pipe.get("videos_raw", "videos-raw"),
            "labels": pipe.get("pose_2d", "pose-2d"),
            "calibration": f"{calib_dir}/calibration.toml",
        },
        "cameras": {"regex": tri["cam_regex"]} if "cam_regex" in tri else {},
        "calibration": {k: cal[k] for k in _ANIPOSE_BOARD_KEYS if k in cal},
    }
    own = _table(doc, ANIPOSE_TABLE, src)
    for section, table in own.items():
        if not isinstance(table, dict):
            raise ValueError(f"{src}: {ANIPOSE_TABLE}.{section} must be a table")
        sections.setdefault(section, {}).update(table)
    values = _validate(sections, f"{src} (anipose config)")
    offsets = _anipose_offsets(_table(doc, "cameras", src), src)
    extra = {
        "constraints": _pairs(tri.get("constraints", []), "constraints", src),
        "constraints_weak": _pairs(tri.get("constraints_weak", []), "constraints_weak", src),
        "nesting": nesting,
        "project": doc.get("project"),
    }
    return ProjectConfig(
        root=p.parent.resolve(), path=p, crop_offsets=offsets, anipose=extra, **values
    )


def _is_anipose_file(path: Path) -> bool:
    try:
        return is_anipose_config(tomllib.loads(path.read_text(encoding="utf-8")))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError):
        return False


def _table(doc: Mapping[str, Any], key: str, src: str) -> dict:
    t = doc.get(key, {})
    if not isinstance(t, dict):
        raise ValueError(f"{src}: {key} must be a table [{key}]")
    return t


def _anipose_offsets(cameras: Mapping[str, Any], src: str) -> dict[str, tuple[float, float]]:
    """``[cameras.<name>] offset``: anipose adds ``offset[0], offset[1]`` to the x, y of every
    2D point of that camera (triangulate.py, load_pose2d_fnames); width and height (entries
    2, 3, when given) describe the crop and are not used."""
    out = {}
    for name, t in cameras.items():
        if not isinstance(t, dict) or "offset" not in t:
            continue
        off = t["offset"]
        ok = isinstance(off, list) and len(off) in (2, 4)
        ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in off)
        if not ok or not all(np.isfinite(off)):
            raise ValueError(
                f"{src}: cameras.{name}.offset must be [x, y] or [x, y, width, height] in "
                f"pixels, got {off!r}"
            )
        out[str(name)] = (float(off[0]), float(off[1]))
    return out


def _pairs(v: Any, key: str, src: str) -> list[tuple[str, str]]:
    if not isinstance(v, list) or not all(
        isinstance(x, list) and len(x) == 2 and all(isinstance(s, str) for s in x) for x in v
    ):
        raise ValueError(f"{src}: triangulation.{key} must be a list of [bodypart, bodypart]")
    return [(a, b) for a, b in v]


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
    """Camera name in a file (or folder) name; DeepLabCut outputs ``<video stem>DLC_<network>...``
    are matched on the video stem only."""
    stem = file.name if file.is_dir() else file.stem
    stem = stem.split("DLC_", 1)[0] if "DLC_" in stem else stem
    m = regex.search(stem)
    if m is None:
        return None
    return m.group(1) if m.groups() and m.group(1) is not None else m.group(0)


def _video_stem(file: Path) -> str:
    """The video a file belongs to: the stem without DeepLabCut's ``DLC_<network>...`` tail and
    SLEAP's ``.analysis``/``.predictions`` tags."""
    stem = file.stem.split("DLC_", 1)[0]
    for tag in (".analysis", ".predictions"):
        stem = stem.removesuffix(tag)
    return stem


def _no_camera(f: Path, regex: re.Pattern) -> ValueError:
    return ValueError(
        f"{f}: no camera name matches cameras.regex {regex.pattern!r}; rename the file "
        "or change the regex in config.toml"
    )


_SLEAP_TAGS = (".analysis", ".predictions")


def _label_variant(f: Path) -> tuple[str, bool, int]:
    """(identity, filtered, format rank) of a 2D label file: the DeepLabCut ``.h5`` and ``.csv``
    of one analysis, and its ``_filtered`` versions, share the identity; so do a SLEAP ``.slp``
    and its analysis ``.h5``. Lower rank = preferred format (``.h5`` needs no CSV parsing, an
    analysis ``.h5`` no instance tables)."""
    stem = f.stem
    for tag in _SLEAP_TAGS:
        stem = stem.removesuffix(tag)
    filtered = stem.endswith("_filtered")
    stem = stem.removesuffix("_filtered")
    rank = {".h5": 0, ".csv": 1, ".slp": 2}.get(f.suffix.lower(), 3)
    return stem, filtered, rank


def pick_label_file(
    files: list[Path], *, prefer_filtered: bool = False, camera: str = "", folder: Path = Path()
) -> tuple[Path, list[Path]]:
    """Choose the label file of one camera among the files its name matched.

    DeepLabCut writes ``.h5`` and ``.csv`` of the same predictions, and ``filterpredictions``
    adds ``*_filtered`` versions; SLEAP users often keep the ``.slp`` and its analysis ``.h5``.
    These are one analysis: the raw (or, with ``prefer_filtered``, the filtered) ``.h5`` is
    used. Files of different analyses (two networks, two recordings) are an error.

    Returns
    -------
    chosen : Path
    skipped : list of Path
        The other files of the same analysis.
    """
    groups: dict[str, list[Path]] = {}
    for f in files:
        groups.setdefault(_label_variant(f)[0], []).append(f)
    if len(groups) > 1:
        names = ", ".join(sorted(f.name for f in files))
        raise ValueError(
            f"{folder}: two files for camera {camera!r} from different analyses: {names}; keep "
            "one, or set paths.labels_filter in config.toml to text only the wanted files contain"
        )

    def order(f: Path) -> tuple[bool, int, str]:
        _, filtered, rank = _label_variant(f)
        return (filtered != prefer_filtered, rank, f.name)

    ranked = sorted(files, key=order)
    return ranked[0], ranked[1:]


def _files_by_camera(
    folder: Path,
    suffixes: tuple[str, ...],
    regex: re.Pattern,
    *,
    prefer_filtered: bool = False,
    contains: str = "",
    skipped: list[Path] | None = None,
) -> dict:
    """``{camera: file}`` in ``folder``. For videos, DeepLabCut's labelled videos
    (``<video>DLC_<network>..._labeled.mp4``) are not recordings and are left out; for labels
    (``LABEL_SUFFIXES``) one file per camera is chosen with :func:`pick_label_file`."""
    out: dict[str, list[Path]] = {}
    if not folder.is_dir():
        return {}
    labels = suffixes == LABEL_SUFFIXES
    for f in sorted(folder.iterdir()):
        if not f.is_file() or f.name.startswith(".") or f.suffix.lower() not in suffixes:
            continue
        if not labels and "DLC_" in f.stem:
            continue  # a video DeepLabCut drew its predictions on
        if labels and contains and contains not in f.name:
            continue
        cam = _camera_of(f, regex)
        if cam is None:
            raise _no_camera(f, regex)
        out.setdefault(cam, []).append(f)
    chosen = {}
    for cam, files in out.items():
        stems = {_video_stem(f) for f in files}
        if len(stems) > 1:
            # different recordings or different cameras that the regex names alike (e.g.
            # camera-1, camera-2 under a regex taking "camera"): never "different analyses"
            count = "two" if len(files) == 2 else str(len(files))
            raise ValueError(
                f"{folder}: {count} files for camera {cam!r} by cameras.regex "
                f"{regex.pattern!r} ({', '.join(f.name for f in files)}); if they are different "
                "cameras, change cameras.regex (a group around the distinguishing part), else "
                "keep one"
            )
        if not labels:
            chosen[cam] = files[0]
            continue
        chosen[cam], rest = pick_label_file(
            files, prefer_filtered=prefer_filtered, camera=cam, folder=folder
        )
        if skipped is not None:
            skipped += rest
    return chosen


def read_dlc_config(folder: str | Path) -> dict | None:
    """A DeepLabCut project's ``config.yaml`` (``Task``, ``scorer``, ``bodyparts`` or
    ``multianimalbodyparts`` + ``individuals``, ``video_sets``), or None without one."""
    from .dlc import load_dlc_config

    p = Path(folder) / DLC_CONFIG
    if not p.is_file():
        return None
    return load_dlc_config(p, "scorer")


def dlc_bodyparts(doc: Mapping[str, Any]) -> list[str]:
    """Body parts of a DeepLabCut config: ``bodyparts``, or for multi-animal projects
    ``multianimalbodyparts`` (+ ``uniquebodyparts``)."""
    if doc.get("multianimalproject"):
        return list(doc.get("multianimalbodyparts") or []) + list(doc.get("uniquebodyparts") or [])
    bps = doc.get("bodyparts") or []
    return [] if bps == "MULTI!" else list(bps)


def find_manual_labels(
    folder: str | Path, regex: re.Pattern, scorer: str | None = None
) -> dict[str, dict[str, Path]]:
    """Manual labels for skeleton learning, grouped by recording and camera.

    DeepLabCut's layout ``labeled-data/<video stem>/CollectedData_<scorer>.h5|.csv`` (camera
    from the video stem, recording = the stem without the camera name, so ``s1-cam0`` and
    ``s1-cam1`` label the same frames) and files directly in ``folder`` (one recording).
    ``<video>_labeled`` folders (``check_labels``) and machine labels are ignored.

    Parameters
    ----------
    folder : path
    regex : compiled cameras.regex
    scorer : str, optional
        The DeepLabCut scorer (``config.yaml``): its ``CollectedData_<scorer>`` file is used
        when a folder holds several.

    Returns
    -------
    dict
        ``{recording: {camera: file}}``; empty if there are no labels.
    """
    root = Path(folder)
    out: dict[str, dict[str, Path]] = {}
    if not root.is_dir():
        return out
    direct = _files_by_camera(root, LABEL_SUFFIXES, regex)
    if direct:
        out[""] = direct
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        if sub.name.startswith(".") or sub.name.endswith("_labeled"):
            continue
        files = [
            f
            for f in sorted(sub.iterdir())
            if f.is_file()
            and f.name.startswith("CollectedData_")
            and f.suffix.lower() in (".h5", ".csv")
        ]
        if not files:
            continue
        if scorer is not None and any(f.stem == f"CollectedData_{scorer}" for f in files):
            files = [f for f in files if f.stem == f"CollectedData_{scorer}"]
        if len({f.stem for f in files}) > 1:
            raise ValueError(
                f"{sub}: labels of several scorers {sorted({f.stem for f in files})}; keep one "
                "(or put the DeepLabCut config.yaml with its scorer in the project folder)"
            )
        m = regex.search(sub.name)
        if m is None:
            raise ValueError(
                f"{sub}: no camera name in this labeled-data folder matches cameras.regex "
                f"{regex.pattern!r}; rename the video (and folder) or change the regex"
            )
        cam = m.group(1) if m.groups() and m.group(1) is not None else m.group(0)
        recording = (sub.name[: m.start()] + "*" + sub.name[m.end() :]).strip("-_ ")
        group = out.setdefault(recording, {})
        if cam in group:
            raise ValueError(f"{root}: two labeled-data folders for {recording!r} camera {cam!r}")
        group[cam] = min(files, key=lambda f: (f.suffix.lower() != ".h5", f.name))
    return out


def _norm_camera(name: str) -> str:
    s = re.sub(r"[^a-z0-9]", "", name.lower())
    s = re.sub(r"^cam(era)?", "", s)
    return s or name.lower()


def match_cameras(
    cameras: list[str], calibration: list[str], regex: str | None = None
) -> dict[str, tuple[str, str]]:
    """Match camera names from file names to a calibration's camera names.

    A name matches exactly, else ignoring case, separators and a leading ``cam``/``camera``
    (``cam0`` = ``Cam_0`` = ``0``) when that is unambiguous.

    Returns
    -------
    dict
        ``{camera: (calibration name, how)}``, how in ``"exact"``, ``"normalised"``.

    Raises
    ------
    ValueError
        A camera without a match (or with several), naming both lists and the regex.
    """
    out: dict[str, tuple[str, str]] = {}
    calib = list(calibration)
    norm = {}
    for c in calib:
        norm.setdefault(_norm_camera(c), []).append(c)
    bad = []
    for cam in cameras:
        if cam in calib:
            out[cam] = (cam, "exact")
            continue
        cands = norm.get(_norm_camera(cam), [])
        if len(cands) == 1:
            out[cam] = (cands[0], "normalised")
        else:
            bad.append(cam)
    used = [v[0] for v in out.values()]
    if bad or len(set(used)) != len(used):
        hint = f" (camera names come from file names with cameras.regex {regex!r})" if regex else ""
        raise ValueError(
            f"cameras {bad or cameras} match no single camera of the calibration{hint}; "
            f"file cameras: {list(cameras)}, calibration cameras: {calib}. Rename the files, "
            "change cameras.regex, or rename the cameras in the calibration file"
        )
    return out


def camera_table(
    mapping: Mapping[str, tuple[str, str]], files: Mapping[str, Mapping[str, Path]]
) -> str:
    """A text table of which file belongs to which calibrated camera.

    Parameters
    ----------
    mapping : dict
        From :func:`match_cameras`.
    files : dict
        ``{column title: {camera: file}}``, e.g. ``{"video": session.videos, ...}``.
    """
    head = ["camera", "calibration", "match"] + list(files)
    rows = [
        [cam, calib, how] + [files[k][cam].name if cam in files[k] else "-" for k in files]
        for cam, (calib, how) in mapping.items()
    ]
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
                     for r in [head] + rows)  # fmt: skip


def rig_for_files(
    calibration: str | Path,
    files: list[str | Path],
    names: list[str] | None = None,
    regex: str | None = None,
):
    """The calibrated rig in the order of per-camera files given on the command line.

    With ``names`` (``--camera-names``) those cameras in that order. Otherwise, when every
    file name holds a camera name (``regex``, ``--cam-regex``; default ``cameras.regex``)
    matching one calibrated camera (:func:`match_cameras`), the rig is put in the files' order,
    whatever order they are given in. When no file name holds a camera name, the files are
    taken in the calibration's order, with a warning that says so.

    Returns
    -------
    rig : CameraRig
    table : str or None
        :func:`camera_table` of the match made from the file names (None if not).

    Raises
    ------
    ValueError
        Two files whose names give the same camera (listing the files and the names), or
        file names that name cameras the calibration does not match (never a silent fall
        back to the calibration's order).
    """
    import warnings

    from .camera import CameraRig

    if names:
        return CameraRig.load(calibration, names=names), None
    rig = CameraRig.load(calibration)
    pattern = regex or SCHEMA["cameras"]["regex"].default
    try:
        compiled = re.compile(pattern)
    except re.error as exc:
        raise ValueError(
            f"--cam-regex {pattern!r} is not a valid regular expression: {exc}"
        ) from None
    paths = [Path(f) for f in files]
    found = [_camera_of(p, compiled) for p in paths]
    given = [(p.name, c) for p, c in zip(paths, found, strict=True) if c is not None]
    if len(paths) != len(rig) or not given:
        if len(paths) == len(rig):
            warnings.warn(
                f"no camera name in the file names (regex {pattern!r}): the files are taken "
                f"in the calibration's order {rig.names}; give --camera-names to be sure",
                stacklevel=2,
            )
        return rig, None
    if None in found or len(set(found)) != len(found):
        listing = ", ".join(f"{n} -> {c!r}" for n, c in zip(
            [p.name for p in paths], found, strict=True))  # fmt: skip
        raise ValueError(
            f"the file names do not give one camera each with regex {pattern!r} ({listing}); "
            "give --cam-regex with a group for the distinguishing part, or --camera-names"
        )
    mapping = match_cameras(found, [c.name for c in rig], regex=pattern)
    ordered = CameraRig.load(calibration, names=[mapping[c][0] for c in found])
    table = camera_table(mapping, {"file": dict(zip(found, paths, strict=True))})
    return ordered, table


def video_fps(path: str | Path) -> float | None:
    """Frame rate (Hz) in a video's metadata (OpenCV), or None if it has none."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS)) if cap.isOpened() else 0.0
    finally:
        cap.release()
    return fps if np.isfinite(fps) and 0 < fps < 10_000 else None


def videos_fps(files: list[Path]) -> float | None:
    """The common frame rate (Hz) of videos; None if none has one; error if they disagree."""
    rates = {f: video_fps(f) for f in files}
    known = {f: r for f, r in rates.items() if r is not None}
    if not known:
        return None
    values = sorted(set(round(r, 3) for r in known.values()))
    if values[-1] - values[0] > 1e-3 * values[-1]:
        listing = ", ".join(f"{f.name} {r:g}" for f, r in known.items())
        raise ValueError(f"the videos have different frame rates ({listing} Hz); set tracking.fps")
    return float(np.median(list(known.values())))


def find_sessions(config: ProjectConfig) -> list[Session]:
    """The sessions of a project: the project folder itself (a DeepLabCut project) and the
    subfolders holding ``paths.videos`` or ``paths.labels``.

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
    folders = [root] + sorted(p for p in root.iterdir() if p.is_dir())
    for folder in folders:
        if folder.name.startswith((".", "_")) and folder != root:
            continue
        vdir, ldir = folder / config.paths["videos"], folder / config.paths["labels"]
        if not (vdir.is_dir() or ldir.is_dir()):
            continue
        videos = _files_by_camera(vdir, VIDEO_SUFFIXES, regex)
        labels = _files_by_camera(
            ldir, LABEL_SUFFIXES, regex, prefer_filtered=config.paths["prefer_filtered"],
            contains=config.paths["labels_filter"],
        )  # fmt: skip
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
                f"{sorted(labels)} (cameras.regex {regex.pattern!r}); every camera needs both "
                "(or set cameras.names)"
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
def _project_videos(root: Path, videos: str) -> list[Path]:
    out = []
    for folder in [root / videos] + sorted(p / videos for p in root.iterdir() if p.is_dir()):
        if folder.is_dir():
            out += [
                f
                for f in sorted(folder.iterdir())
                if f.suffix.lower() in VIDEO_SUFFIXES and "DLC_" not in f.stem
            ]
    return out


def _dlc_summary(doc: Mapping[str, Any], model: str) -> list[str]:
    from .labels import match_marker_names
    from .models import load_name_or_file

    bps = dlc_bodyparts(doc)
    lines = [
        f"  DeepLabCut project {doc.get('Task', '?')!r} (scorer {doc.get('scorer')!r}): "
        f"{len(bps)} body parts"
        + (f", individuals {list(doc.get('individuals') or [])}" if doc.get("multianimalproject")
           else "")
    ]  # fmt: skip
    try:
        sk = load_name_or_file(model)
    except ValueError:
        return lines
    unknown = []
    for bp in bps:
        try:
            match_marker_names([bp], sk)
        except ValueError:
            unknown.append(bp)
    lines.append(
        f"  {len(bps) - len(unknown)} of them are markers of the model {sk.name!r}"
        + (f"; not in the model (ignored by tracking): {unknown}" if unknown else "")
    )
    return lines


def _cmd_init(args) -> int:
    root = Path(args.path)
    if (root / CONFIG_NAME).is_file() and _is_anipose_file(root / CONFIG_NAME):
        init_project(root)  # raises: the anipose config is read as it is
    overrides: dict[str, dict] = {"project": {}, "paths": {}, "tracking": {}}
    if args.model:
        overrides["project"]["model"] = args.model
    notes = []
    dlc = read_dlc_config(root) if root.is_dir() else None
    if dlc is not None:
        # DeepLabCut keeps videos and their predictions in videos/, manual labels in
        # labeled-data/<video>/: the project folder is the (one) session
        overrides["paths"].update(videos="videos", labels="videos", manual_labels="labeled-data")
        notes += _dlc_summary(dlc, args.model or SCHEMA["project"]["model"].default)
        inds = [i for i in (dlc.get("individuals") or []) if i != "single"]
        if dlc.get("multianimalproject") and len(inds) == 1:
            overrides["project"]["individual"] = inds[0]
    fps = args.fps
    if fps is None and root.is_dir():
        vids = _project_videos(root, overrides["paths"].get("videos", "videos"))
        fps = videos_fps(vids)
        if fps is not None:
            notes.append(f"  frame rate {fps:g} Hz from the metadata of {len(vids)} video(s)")
    if fps is None:
        raise ValueError(
            f"{root}: no video with a frame rate in its metadata; give it with --fps HZ "
            "(needed for time axes and the NWB/C3D/movement exports)"
        )
    overrides["tracking"]["fps"] = float(fps)
    sleap = None
    if getattr(args, "from_sleap_session", None):
        sleap = _sleap_session_overrides(args, overrides)
    path = init_project(root, overwrite=args.overwrite, **{k: v for k, v in overrides.items() if v})
    if sleap is not None:
        notes += _write_sleap_session(root, args.from_sleap_session, sleap, args.overwrite)
    print(f"acm-rs init: wrote {path}" + (" for a DeepLabCut project" if dlc is not None else ""))
    for line in notes:
        print(line)
    if sleap is not None:
        print("  calibration and 2D tracks are in place: set project.model to a skeleton whose "
              "markers are the SLEAP nodes")  # fmt: skip
    elif dlc is None:
        print("  edit it (board, camera regex, pcutoff), then put one folder per session beside it")
    else:
        print("  put one board video per camera in calibration/, then run `acm-rs run-all`")
    return 0


def _sleap_session_overrides(args, overrides: dict):
    """Read a SLEAP session for ``init --from-sleap-session`` (nothing written yet) and set
    the config: its cameras in session order, found by the file names this route writes."""
    from .sleap_session import read_sleap_session

    sess = read_sleap_session(args.from_sleap_session, individual=args.individual)
    overrides.setdefault("cameras", {}).update(regex=r"^[^.]+", names=list(sess.rig.names))
    if sess.individual is not None:
        overrides["project"]["individual"] = sess.individual
    return sess


def _write_sleap_session(root: Path, file: str, sess, overwrite: bool) -> list[str]:
    """Write the session's calibration and one analysis file per camera into the project."""
    from .sleap_session import write_session_views

    calib = root / SCHEMA["paths"]["calibration"].default
    if calib.exists() and not overwrite:
        raise FileExistsError(f"{calib} exists; pass --overwrite to replace it")
    sess.rig.save(calib, metadata={"source": f"SLEAP session {Path(file).name}"})
    views = root / Path(file).stem.removesuffix(".pkg") / SCHEMA["paths"]["labels"].default
    files = write_session_views(file, views)
    return [
        f"  SLEAP session {sess.summary()}",
        f"  wrote {calib} and {len(files)} per-camera files in {views}",
    ]


def add_subcommands(sub) -> None:
    """Add ``acm-rs init`` to an argparse subparsers object."""
    p = sub.add_parser(
        "init",
        help="create a project folder with a commented config.toml (also inside a DeepLabCut "
        "project)",
        description="Writes config.toml. In a DeepLabCut project folder (config.yaml) the "
        "paths point to its videos/ and labeled-data/. The frame rate comes from the videos' "
        "metadata, else --fps is required.",
    )
    p.add_argument("path", nargs="?", default=".", help="project folder (default: here)")
    p.add_argument("--model", help="'rat', 'mouse' or a skeleton TOML path (default rat)")
    p.add_argument(
        "--fps", type=float, help="video frame rate in Hz (default: from the videos' metadata)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing config.toml")
    p.add_argument(
        "--from-sleap-session", metavar="FILE.slp",
        help="import a SLEAP multi-camera session: its calibration (calibration/calibration."
        "toml) and per-camera 2D tracks (<file stem>/pose-2d/<camera>.analysis.h5)",
    )  # fmt: skip
    p.add_argument("--individual", help="with --from-sleap-session: the track to reconstruct")
    p.set_defaults(func=_cmd_init)
