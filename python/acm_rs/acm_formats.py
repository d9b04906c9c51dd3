"""Files of the authors' ACM tool (bbo-lab/ACM), so ACM users can switch with their data.

Readers: ``configuration.py`` (parsed with :mod:`ast`, never imported or executed),
``model.npy`` (-> :class:`acm_rs.Skeleton` plus the name/order maps), ``labels_dlc_*.npy``,
``labels_manual.npz`` and ``origin_coord.npy``. Writers: ``pose.npy`` and ``save_dict.npy`` in
the authors' layout. ``multicalibration.npy`` is read by :mod:`acm_rs.calibration`.

**Trust.** The authors' ``.npy``/``.npz`` files are pickled Python dicts; unpickling can run
arbitrary code, so load them only from sources you trust (as you would run their
``configuration.py``). The readers unpickle only those files, then refuse anything that is not
the documented dict (keys, types and shapes are checked).

Names: ACM's ``joint_<name>``, ``marker_<name>_start`` and ``spot_<name>`` all map to our
``<name>`` (the bundled rat model uses the authors' names without prefixes).
"""

from __future__ import annotations

import ast
import difflib
import math
import operator
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from . import acm_model
from ._io import atomic_write

if TYPE_CHECKING:  # pragma: no cover
    from .camera import CameraRig
    from .skeleton import Skeleton
    from .tracking.result import PoseResult

__all__ = [
    "AcmConfig",
    "AcmLabels",
    "AcmModel",
    "arena_rig",
    "calibration_to_arena",
    "labels_dlc_path",
    "read_configuration",
    "read_labels_dlc",
    "read_labels_manual",
    "read_model",
    "read_origin_coord",
    "write_pose",
    "write_save_dict",
]


# -- configuration.py -----------------------------------------------------------------------------
_BINOPS: dict[type, Callable[[Any, Any], Any]] = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: operator.truediv,
    ast.FloorDiv: operator.floordiv,
    ast.Mod: operator.mod,
    ast.Pow: operator.pow,
}
_UNOPS: dict[type, Callable[[Any], Any]] = {
    ast.UAdd: operator.pos,
    ast.USub: operator.neg,
    ast.Not: operator.not_,
}
_CALLS: dict[str, Callable[..., Any]] = {
    "int": int,
    "float": float,
    "str": str,
    "bool": bool,
    "list": list,
    "tuple": tuple,
    "abs": abs,
    "min": min,
    "max": max,
    "round": round,
}
_CONSTANTS = {"np.pi": math.pi, "numpy.pi": math.pi, "math.pi": math.pi, "np.inf": math.inf}


class _NotLiteral(Exception):
    """An expression outside the safe subset (the message says what was found)."""


def _safe_eval(node: ast.AST, names: Mapping[str, Any]) -> Any:
    """Evaluate literals, arithmetic, names assigned earlier, ``np.pi`` and pure builtins."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.List | ast.Tuple | ast.Set):
        items = [_safe_eval(e, names) for e in node.elts]
        return {ast.List: list, ast.Tuple: tuple, ast.Set: set}[type(node)](items)
    if isinstance(node, ast.Dict):
        if any(k is None for k in node.keys):
            raise _NotLiteral("a dict unpacking (**)")
        return {
            _safe_eval(k, names): _safe_eval(v, names)
            for k, v in zip(node.keys, node.values, strict=True)
        }
    if isinstance(node, ast.UnaryOp) and type(node.op) in _UNOPS:
        return _UNOPS[type(node.op)](_safe_eval(node.operand, names))
    if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
        left, right = _safe_eval(node.left, names), _safe_eval(node.right, names)
        if isinstance(node.op, ast.Pow) and (
            not isinstance(right, int | float) or abs(right) > 1024 or abs(left) > 1e6
        ):
            raise _NotLiteral("a power with a huge operand")
        if isinstance(node.op, ast.Mult) and any(
            isinstance(v, str | list | tuple) for v in (left, right)
        ):
            raise _NotLiteral("a repeated sequence (sequence * n)")
        try:
            return _BINOPS[type(node.op)](left, right)
        except (TypeError, ZeroDivisionError, OverflowError) as exc:
            raise _NotLiteral(f"an expression that fails ({exc})") from None
    if isinstance(node, ast.Name):
        if node.id in names:
            return names[node.id]
        if node.id in ("True", "False", "None"):  # pragma: no cover - Constant in py3.8+
            return {"True": True, "False": False, "None": None}[node.id]
        raise _NotLiteral(f"the name {node.id!r}, which is not assigned a literal before")
    if isinstance(node, ast.Attribute):
        dotted = ast.unparse(node)
        if dotted in _CONSTANTS:
            return _CONSTANTS[dotted]
        raise _NotLiteral(f"the attribute {dotted!r}")
    if isinstance(node, ast.Call):
        fname = node.func.id if isinstance(node.func, ast.Name) else None
        if fname in _CALLS and not node.keywords:
            args = [_safe_eval(a, names) for a in node.args]
            try:
                return _CALLS[fname](*args)
            except (TypeError, ValueError) as exc:
                raise _NotLiteral(f"a call of {fname}() that fails ({exc})") from None
        raise _NotLiteral(f"a call of {ast.unparse(node.func)}()")
    raise _NotLiteral(f"the expression {ast.unparse(node)!r}")


@dataclass(frozen=True)
class _Key:
    default: Any
    types: tuple[type, ...]
    check: Callable[[Any], bool] | None = None
    hint: str = ""


_NUM = (int, float)
#: Keys of configuration.py that acm-rs uses, with the authors' defaults (None = required).
CONFIG_KEYS: dict[str, _Key] = {
    "index_frame_start": _Key(None, (int,), lambda v: v >= 0, "a frame number >= 0"),
    "index_frame_end": _Key(None, (int,), lambda v: v >= 0, "a frame number >= 0"),
    "dlc_index_frame_start": _Key(None, (int,), lambda v: v >= 0, "a frame number >= 0"),
    "dlc_index_frame_end": _Key(None, (int,), lambda v: v >= 0, "a frame number >= 0"),
    "dt": _Key(5, (int,), lambda v: v >= 1, "frames skipped, an integer >= 1"),
    "pcutoff": _Key(0.9, _NUM, lambda v: 0 <= v <= 1, "a likelihood in [0, 1]"),
    "scale_factor": _Key(1.0, _NUM, lambda v: v > 0, "calibration unit -> cm, > 0"),
    "body_weight": _Key(None, _NUM, lambda v: v > 0, "grams, > 0"),
    "species": _Key("rat", (str,), lambda v: v in ("rat", "mouse"), "'rat' or 'mouse'"),
    "mode": _Key(4, (int,), lambda v: v in (1, 2, 3, 4), "1, 2, 3 or 4"),
    "tol": _Key(0.05, _NUM, lambda v: v > 0, "> 0"),
    "iter_max": _Key(100, (int, float), lambda v: v >= 1, ">= 1"),
    "noise": _Key(1e-4, _NUM, lambda v: v > 0, "> 0"),
    "sigma_factor": _Key(10.0, _NUM, lambda v: v > 0, "> 0"),
    "normalize_t0": _Key(50.0, _NUM, lambda v: v > 0, "> 0"),
    "normalize_r0": _Key(math.pi / 2, _NUM, lambda v: v > 0, "> 0 rad"),
    "normalize_camera_sensor_x": _Key(1280.0, _NUM, lambda v: v > 0, "px, > 0"),
    "normalize_camera_sensor_y": _Key(1024.0, _NUM, lambda v: v > 0, "px, > 0"),
    "dFrames_calib": _Key(200, (int,), lambda v: v >= 1, "an integer >= 1"),
    "index_frames_calib": _Key("all", (str, list, tuple), None, "'all' or [[start, end], ...]"),
}


@dataclass
class AcmConfig:
    """Settings of an ACM dataset's ``configuration.py`` (see :func:`read_configuration`).

    Attributes
    ----------
    index_frame_start, index_frame_end : int
        Frames to reconstruct (end exclusive, as in ACM).
    dlc_index_frame_start, dlc_index_frame_end : int or None
        Frame range in the name of the ``labels_dlc_*.npy`` file.
    dt : int
        Frames skipped between time points (``nT = (end - start) // dt``).
    pcutoff : float
        Detections with likelihood <= pcutoff are missing.
    scale_factor : float
        Calibration unit -> cm.
    body_weight : float or None
        Grams, for the bone-length priors.
    species : str
        ``'rat'`` or ``'mouse'``.
    mode, tol, iter_max, noise, sigma_factor :
        Model mode (1-4), EM tolerance and maximum iterations, initial covariance diagonal,
        bone-length prior width (SD).
    normalize_t0, normalize_r0, normalize_camera_sensor_x, normalize_camera_sensor_y : float
        Normalisation constants (cm, rad, px).
    dFrames_calib, index_frames_calib :
        Frames used for skeleton learning (step and ``'all'`` or ``[[start, end], ...]``).
    values : dict
        Every top-level assignment that could be evaluated safely.
    skipped : dict
        Assignments that were not evaluated (name -> reason), e.g. paths built with ``os``.
    path : Path
    """

    index_frame_start: int
    index_frame_end: int
    dlc_index_frame_start: int | None
    dlc_index_frame_end: int | None
    dt: int
    pcutoff: float
    scale_factor: float
    body_weight: float | None
    species: str
    mode: int
    tol: float
    iter_max: int
    noise: float
    sigma_factor: float
    normalize_t0: float
    normalize_r0: float
    normalize_camera_sensor_x: float
    normalize_camera_sensor_y: float
    dFrames_calib: int  # noqa: N815 - the authors' key
    index_frames_calib: Any
    values: dict = field(default_factory=dict, repr=False)
    skipped: dict = field(default_factory=dict, repr=False)
    path: Path | None = None

    @property
    def frames(self) -> np.ndarray:
        """Frame numbers of the reconstructed time points: ``range(start, end, dt)``
        truncated to ``nT = (end - start) // dt`` entries (the authors' count)."""
        n_t = (self.index_frame_end - self.index_frame_start) // self.dt
        return self.index_frame_start + self.dt * np.arange(n_t, dtype=np.int64)

    @property
    def sensor_size(self) -> tuple[float, float]:
        """(width, height) in px used to normalise 2D positions."""
        return (self.normalize_camera_sensor_x, self.normalize_camera_sensor_y)


def read_configuration(path: str | Path) -> AcmConfig:
    """Parse an ACM ``configuration.py`` safely (its folder or the file itself).

    The file is parsed with :mod:`ast` and never imported or executed. Top-level assignments
    are evaluated when they are literals, arithmetic on literals, names assigned before,
    ``np.pi`` or calls of ``int``/``float``/``list``/... on those; everything else (``import``,
    ``os.path`` calls, ``datetime.now()``, ``assert``) is skipped. A key that acm-rs uses
    (:data:`CONFIG_KEYS`) must evaluate, else ``ValueError`` names the key, the line and what
    was found.

    Returns
    -------
    AcmConfig

    Raises
    ------
    FileNotFoundError
        No ``configuration.py``.
    ValueError
        Syntax error; a used key that is not a literal, has the wrong type or value, or is
        missing (``index_frame_start``, ``index_frame_end``); ``index_frame_end <=
        index_frame_start``.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "configuration.py"
    if not p.is_file():
        raise FileNotFoundError(
            f"{p}: no configuration.py (an ACM dataset folder needs one; see "
            "docs/project.md 'ACM datasets')"
        )
    text = p.read_text(encoding="utf-8")
    try:
        tree = ast.parse(text, filename=str(p))
    except SyntaxError as exc:
        raise ValueError(f"{p}:{exc.lineno}: invalid Python syntax: {exc.msg}") from None
    values: dict[str, Any] = {}
    skipped: dict[str, str] = {}
    lines: dict[str, int] = {}
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign):
            targets, value = stmt.targets, stmt.value
        elif isinstance(stmt, ast.AnnAssign) and stmt.value is not None:
            targets, value = [stmt.target], stmt.value
        else:
            continue
        simple = [t.id for t in targets if isinstance(t, ast.Name)]
        if len(simple) != len(targets):
            continue
        for name in simple:
            lines[name] = stmt.lineno
        try:
            v = _safe_eval(value, values)
        except _NotLiteral as exc:
            for name in simple:
                values.pop(name, None)
                skipped[name] = str(exc)
            continue
        for name in simple:
            values[name] = v
            skipped.pop(name, None)

    kwargs: dict[str, Any] = {}
    for key, spec in CONFIG_KEYS.items():
        where = f"{p}:{lines[key]}" if key in lines else str(p)
        if key in skipped:
            raise ValueError(
                f"{where}: {key} must be a literal value (e.g. {key} = "
                f"{spec.default if spec.default is not None else 100!r}); found {skipped[key]}. "
                "acm-rs parses configuration.py without running it"
            )
        if key not in values:
            if spec.default is None and key in ("index_frame_start", "index_frame_end"):
                raise ValueError(f"{p}: missing {key} (the frames to reconstruct)")
            kwargs[key] = spec.default
            continue
        v = values[key]
        if isinstance(v, float) and int in spec.types and float not in spec.types:
            if v.is_integer():
                v = int(v)
            elif not math.isinf(v):
                raise ValueError(f"{where}: {key} must be an integer ({spec.hint}), got {v!r}")
        if key == "iter_max" and isinstance(v, float) and math.isinf(v):
            v = 10**9
        if isinstance(v, bool) or not isinstance(v, spec.types):
            want = " or ".join(t.__name__ for t in spec.types)
            raise ValueError(
                f"{where}: {key} must be {want} ({spec.hint}), got {type(v).__name__} {v!r}"
            )
        if spec.check is not None and not spec.check(v):
            raise ValueError(f"{where}: {key} = {v!r} is invalid: expected {spec.hint}")
        kwargs[key] = v
    if kwargs["index_frame_end"] <= kwargs["index_frame_start"]:
        raise ValueError(
            f"{p}: index_frame_end ({kwargs['index_frame_end']}) must be > index_frame_start "
            f"({kwargs['index_frame_start']})"
        )
    if (kwargs["index_frame_end"] - kwargs["index_frame_start"]) // kwargs["dt"] < 1:
        raise ValueError(f"{p}: the frame range holds no time point with dt = {kwargs['dt']}")
    lo, hi = kwargs["dlc_index_frame_start"], kwargs["dlc_index_frame_end"]
    if (
        lo is not None
        and hi is not None
        and not (lo <= kwargs["index_frame_start"] and kwargs["index_frame_end"] <= hi)
    ):
        raise ValueError(
            f"{p}: frames {kwargs['index_frame_start']}-{kwargs['index_frame_end']} are outside "
            f"the DeepLabCut label range {lo}-{hi} (dlc_index_frame_start/end)"
        )
    for key in ("pcutoff", "scale_factor", "tol", "noise", "sigma_factor"):
        kwargs[key] = float(kwargs[key])
    if kwargs["body_weight"] is not None:
        kwargs["body_weight"] = float(kwargs["body_weight"])
    kwargs["iter_max"] = int(kwargs["iter_max"])
    return AcmConfig(**kwargs, values=values, skipped=skipped, path=p)


# -- pickled dicts --------------------------------------------------------------------------------
def _load_dict(path: Path, what: str, required: Mapping[str, str]) -> dict:
    """Unpickle a ``.npy`` holding one dict and check its required keys (name -> hint)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing {what} file")
    try:
        raw = np.load(path, allow_pickle=True)
    except (ValueError, OSError, EOFError) as exc:
        raise ValueError(f"{path}: not a NumPy file ({exc})") from None
    if isinstance(raw, np.ndarray) and raw.dtype == object and raw.shape == ():
        raw = raw.item()
    if not isinstance(raw, dict):
        raise ValueError(
            f"{path}: expected a pickled dict ({what}), got {type(raw).__name__}; refusing it"
        )
    missing = [k for k in required if k not in raw]
    if missing:
        raise ValueError(
            f"{path}: {what} lacks keys {missing} ("
            + "; ".join(f"{k}: {required[k]}" for k in missing)
            + ")"
        )
    return raw


def _array(d: dict, key: str, path: Path, shape: tuple, dtype: str = "float") -> np.ndarray:
    """``d[key]`` as a numeric array of ``shape`` (None = any); ValueError naming the key."""
    v = d[key]
    arr = None
    if isinstance(v, list | tuple | np.ndarray):
        try:
            arr = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            arr = None
    if arr is None or arr.ndim != len(shape):
        raise ValueError(
            f"{path}: {key} must be a numeric array of shape {shape}, got "
            f"{type(v).__name__} {np.shape(v) if arr is not None else ''}"
        )
    for got, want in zip(arr.shape, shape, strict=True):
        if want is not None and got != want:
            raise ValueError(f"{path}: {key} must have shape {shape}, got {arr.shape}")
    if dtype == "int":
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise ValueError(f"{path}: {key} must hold integers")
        return arr.astype(np.int64)
    return arr


def _names(d: dict, key: str, path: Path, prefix: str, suffix: str = "") -> list[str]:
    v = d[key]
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if not isinstance(v, list | tuple) or not all(isinstance(s, str) for s in v):
        raise ValueError(f"{path}: {key} must be a list of names, got {type(v).__name__}")
    out = []
    for s in v:
        if not (s.startswith(prefix) and s.endswith(suffix)) or len(s) <= len(prefix + suffix):
            raise ValueError(f"{path}: {key} entry {s!r} is not of the form {prefix}<name>{suffix}")
        out.append(s[len(prefix) : len(s) - len(suffix)] if suffix else s[len(prefix) :])
    if len(set(out)) != len(out):
        raise ValueError(f"{path}: {key} repeats names")
    return out


# -- model.npy ------------------------------------------------------------------------------------
@dataclass
class AcmModel:
    """An ACM ``model.npy`` as an acm-rs skeleton plus the maps between the two orders.

    Attributes
    ----------
    skeleton : Skeleton
        Joints in root-first order (our FK order), cm.
    acm_joint_names : list of str, length J
        ``joint_order`` without the ``joint_`` prefix (ACM order).
    acm_marker_names : list of str, length M
        ``joint_marker_order`` without ``marker_`` and ``_start`` (ACM order).
    joint_index : numpy.ndarray, shape (J,)
        ``skeleton`` joint index of each ACM joint: ``ours[:, joint_index]`` is in ACM order.
    marker_index : numpy.ndarray, shape (M,)
        ``skeleton`` marker index of each ACM marker.
    source : str
        ``"template"`` if the model equals the bundled model of that name (its lengths,
        markers, limits are used), else ``"model.npy"``.
    links_rule : str
        Which rotation links the file holds: ``"tree"`` (a rotation moves its bone and the
        bone's descendants, as in the authors' files), ``"literal Alg. 1"`` (siblings
        coupled) or ``"other"``; the skeleton applies them exactly as the authors' tool does.
    """

    skeleton: Skeleton
    acm_joint_names: list[str]
    acm_marker_names: list[str]
    joint_index: np.ndarray
    marker_index: np.ndarray
    source: str
    links_rule: str = "tree"

    def to_acm_joints(self, x: np.ndarray) -> np.ndarray:
        """``(..., J, k)`` in skeleton order -> ACM ``joint_order``."""
        return np.asarray(x)[..., self.joint_index, :]

    def to_acm_markers(self, x: np.ndarray) -> np.ndarray:
        """``(..., M, k)`` in skeleton order -> ACM ``joint_marker_order``."""
        return np.asarray(x)[..., self.marker_index, :]


_MODEL_KEYS = {
    "joint_order": "list of 29 'joint_<name>'",
    "joint_marker_order": "list of 'marker_<name>_start'",
    "joint_marker_index": "(n_markers,) joint index of each marker",
    "skeleton_edges": "(n_bones, 2) [start, end] joint indices",
    "skeleton_vertices": "(n_joints, 3) rest positions",
}


def read_model(
    path: str | Path, species: str = "rat", template: Skeleton | None = None
) -> AcmModel:
    """Read an ACM ``model.npy`` (a trusted pickle) into an :class:`AcmModel`.

    The skeleton is built as the authors' tool builds it (:mod:`acm_rs.acm_model`): tree,
    names and marker attachments from the file; every bone straight along +z at rest except
    the girdle bones, whose rest frames come from the file's ``skeleton_coords``; no offset
    for markers on the root. The file carries no lengths or offsets (they are learned), so
    the starting lengths and offsets, joint limits (Supp. Table 1), marker boxes (sec. 6),
    bone-length priors (Supp. Table 2) and left/right pairs are taken by name from
    ``template`` (default: the bundled model ``species``), offsets clipped to their boxes.

    Parameters
    ----------
    path : path
        ``model.npy`` or its folder.
    species : {"rat", "mouse"}
        Bundled model used as the template.
    template : Skeleton, optional
        Template instead of the bundled model.

    Raises
    ------
    ValueError
        Not the expected dict, bad shapes, names without the ``joint_``/``marker_`` prefixes,
        edges that do not form a tree, marker indices out of range.

    The file's ``skeleton_vertices_links`` are applied as the authors' forward model applies
    them (the global rotation moves every bone; then each bone's rotation, in file order, the
    bones its row marks), whatever rule they follow (:func:`acm_model.file_links`).
    """
    from . import models
    from .skeleton import Skeleton

    p = Path(path)
    if p.is_dir():
        p = p / "model.npy"
    d = _load_dict(p, "ACM model", _MODEL_KEYS)
    jn = _names(d, "joint_order", p, "joint_")
    mn = _names(d, "joint_marker_order", p, "marker_", "_start")
    n_j, n_m = len(jn), len(mn)
    edges = _array(d, "skeleton_edges", p, (n_j - 1, 2), "int")
    verts = _array(d, "skeleton_vertices", p, (n_j, 3))
    mji = _array(d, "joint_marker_index", p, (n_m,), "int")
    if np.any((edges < 0) | (edges >= n_j)) or np.any((mji < 0) | (mji >= n_j)):
        raise ValueError(f"{p}: skeleton_edges / joint_marker_index refer to missing joints")
    parent = np.full(n_j, -1)
    for s, e in edges:
        if parent[e] != -1:
            raise ValueError(f"{p}: joint {jn[e]!r} has two parents in skeleton_edges")
        parent[e] = s
    roots = np.flatnonzero(parent == -1)
    if roots.size != 1:
        raise ValueError(f"{p}: skeleton_edges must form one tree; roots: {[jn[r] for r in roots]}")
    if template is None:
        if species not in models.available():
            raise ValueError(f"species must be one of {models.available()}, got {species!r}")
        template = models.load(species)
    coords = None
    if "skeleton_coords" in d:
        coords = _array(d, "skeleton_coords", p, (n_j - 1, 3, 3))
    links, rule = acm_model.file_links(d.get("skeleton_vertices_links"), parent, edges)
    sk = _skeleton_from_model(p, jn, mn, parent, edges, verts, coords, mji, template, Skeleton)
    # the file's links in our bone order (our bone b ends at joint sk.bones[b, 1])
    ours = {sk.joint_index(jn[int(e)]): b for b, (_, e) in enumerate(edges)}
    file_bone = np.array([ours[int(e)] for e in sk.bones[:, 1]], dtype=np.int64)
    sk = sk.with_links(links[np.ix_(file_bone, file_bone)], np.argsort(file_bone))
    joint_index = np.array([sk.joint_index(n) for n in jn], dtype=np.int64)
    marker_index = np.array([sk.marker_index(n) for n in mn], dtype=np.int64)
    return AcmModel(sk, jn, mn, joint_index, marker_index, "model.npy", rule)


def _skeleton_from_model(p, jn, mn, parent, edges, verts, coords, mji, template, skeleton_cls):
    n_j = len(jn)
    # root-first (breadth-first) order, children in file order
    order = [int(np.flatnonzero(parent == -1)[0])]
    for j in order:
        order += [int(c) for c in np.flatnonzero(parent == j)]
    if len(order) != n_j:
        raise ValueError(f"{p}: skeleton_edges contain a cycle")
    pos = {j: i for i, j in enumerate(order)}
    names = [jn[j] for j in order]
    parents = [pos[parent[j]] if parent[j] >= 0 else -1 for j in order]
    # rest frames: identity, girdles from skeleton_coords (anatomy.get_skeleton_coords0)
    file_bone_of_end = {int(e): b for b, (_, e) in enumerate(edges)}
    girdles = {}
    if coords is None:
        warnings.warn(
            f"{p}: no skeleton_coords; the girdle bones get the template's rest directions",
            stacklevel=3,
        )
    else:
        girdles = acm_model.girdle_frames(jn, edges, verts, coords)
    t_len = dict(zip(template.bone_names, template.bone_lengths, strict=True))
    t_frames = dict(zip(template.bone_names, template.rest_frames, strict=True))
    frames = np.tile(np.eye(3), (n_j - 1, 1, 1))
    lengths = np.ones(n_j - 1)
    for b, j in enumerate(order[1:]):  # bone b of ours ends at joint order[b + 1]
        fb = file_bone_of_end[j]
        if fb in girdles:
            frames[b] = girdles[fb]
        elif coords is None and jn[j] in t_frames and jn[j] in acm_model.GIRDLE_JOINTS:
            frames[b] = t_frames[jn[j]]
        lengths[b] = t_len.get(jn[j], 1.0)
    rest = np.zeros((n_j, 3))
    for b in range(n_j - 1):
        rest[b + 1] = rest[parents[b + 1]] + frames[b][:, 2] * lengths[b]
    # marker offsets: the template's (by name) clipped to the boxes; none on the root
    t_off = dict(zip(template.marker_names, template.marker_offsets, strict=True))
    t_box = dict(zip(template.marker_names, template.marker_bounds, strict=True))
    root = order[0]
    boxes = {}
    marker_rest = np.zeros((len(mn), 3))
    for k, name in enumerate(mn):
        box = np.array(t_box.get(name, np.tile([-np.inf, np.inf], (3, 1))), dtype=float)
        if mji[k] == root:
            box = np.zeros((3, 2))  # the authors' forward model gives root markers no offset
        boxes[name] = box
        v = np.clip(t_off.get(name, np.zeros(3)), box[:, 0], box[:, 1])
        j = mji[k]
        frame = np.eye(3) if j == root else frames[pos[j] - 1]
        marker_rest[k] = rest[pos[j]] + frame @ v
    bone_names = set(names[1:])
    limits = {}
    for b, name in enumerate(template.bone_names):
        if name in bone_names:
            limits[name] = template.joint_limits[b]
    constraints = [c for c in template.bone_length_constraints if c.bone in bone_names]
    sym: dict[str, list[tuple[str, str]]] = {"joints": [], "markers": []}
    for key, pool in (("joints", names[1:]), ("markers", mn)):
        for n in pool:
            if "left" in n and n.replace("left", "right") in pool:
                sym[key].append((n, n.replace("left", "right")))
    return skeleton_cls.from_rest_pose(
        names,
        parents,
        rest,
        mn,
        [jn[j] for j in mji],
        marker_rest,
        joint_limits=limits,
        symmetry=sym,
        marker_bounds=boxes,
        bone_length_constraints=constraints,
        name=p.parent.name or "acm_model",
        units="cm",
        rest_frames=frames,
    )


# -- labels ---------------------------------------------------------------------------------------
@dataclass
class AcmLabels:
    """2D labels of several cameras (from ``labels_dlc_*.npy`` or ``labels_manual.npz``).

    Attributes
    ----------
    points : numpy.ndarray, shape (n_cams, F, M, 2)
        Pixels, NaN where missing (or likelihood <= pcutoff when a cutoff was applied).
    likelihood : numpy.ndarray or None, shape (n_cams, F, M)
        DeepLabCut confidence (None for manual labels).
    frames : numpy.ndarray, shape (F,)
        Frame numbers.
    marker_names : list of str, length M
        Marker names without ACM's prefixes, in the order of ``points``.
    """

    points: np.ndarray
    likelihood: np.ndarray | None
    frames: np.ndarray
    marker_names: list[str]

    def select(self, frames: Sequence[int] | np.ndarray) -> AcmLabels:
        """The labels of the given frame numbers (ValueError naming frames that are absent)."""
        want = np.asarray(frames, dtype=np.int64)
        pos = {int(f): i for i, f in enumerate(self.frames)}
        missing = [int(f) for f in want if int(f) not in pos]
        if missing:
            raise ValueError(
                f"frames {missing[:5]}{' ...' if len(missing) > 5 else ''} are not in the labels "
                f"(they hold frames {int(self.frames.min())}-{int(self.frames.max())})"
            )
        idx = np.array([pos[int(f)] for f in want], dtype=np.int64)
        lik = None if self.likelihood is None else self.likelihood[:, idx]
        return AcmLabels(self.points[:, idx], lik, want, list(self.marker_names))

    def reorder(self, marker_names: Sequence[str]) -> AcmLabels:
        """Labels in another marker order (e.g. ``skeleton.marker_names``); markers absent
        from the labels become NaN; a labelled marker absent from ``marker_names`` is an
        error naming it."""
        extra = [n for n in self.marker_names if n not in marker_names]
        if extra:
            raise ValueError(_unknown_markers_message(extra, marker_names))
        n_c, n_f = self.points.shape[:2]
        pts = np.full((n_c, n_f, len(marker_names), 2), np.nan)
        lik = None if self.likelihood is None else np.zeros((n_c, n_f, len(marker_names)))
        for k, n in enumerate(self.marker_names):
            j = list(marker_names).index(n)
            pts[:, :, j] = self.points[:, :, k]
            if lik is not None:
                lik[:, :, j] = self.likelihood[:, :, k]  # type: ignore[index]
        return AcmLabels(pts, lik, self.frames.copy(), list(marker_names))


def _unknown_markers_message(extra: Sequence[str], known: Sequence[str]) -> str:
    hints = []
    for n in extra[:5]:
        close = difflib.get_close_matches(n, list(known), n=1)
        hints.append(f"{n!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    return (
        f"the labels contain markers the model lacks: {', '.join(hints)}"
        f"{' ...' if len(extra) > 5 else ''}; add them to the model or drop them from the labels"
    )


def labels_dlc_path(folder: str | Path, config: AcmConfig | None = None) -> Path:
    """The ``labels_dlc_{start:06d}_{end:06d}.npy`` of a dataset folder.

    Uses the configured ``dlc_index_frame_start/end`` if given, else the only
    ``labels_dlc_*.npy`` in the folder (FileNotFoundError listing what is there otherwise).
    """
    folder = Path(folder)
    if config is not None and config.dlc_index_frame_start is not None:
        name = f"labels_dlc_{config.dlc_index_frame_start:06d}_{config.dlc_index_frame_end:06d}.npy"
        p = folder / name
        if not p.is_file():
            found = sorted(x.name for x in folder.glob("labels_dlc_*.npy"))
            raise FileNotFoundError(
                f"{p}: missing (from dlc_index_frame_start/end in configuration.py); "
                f"labels_dlc files present: {found or 'none'}"
            )
        return p
    found = sorted(folder.glob("labels_dlc_*.npy"))
    if len(found) != 1:
        raise FileNotFoundError(
            f"{folder}: expected one labels_dlc_<start>_<end>.npy, found "
            f"{[x.name for x in found] or 'none'}; set dlc_index_frame_start/end in "
            "configuration.py to choose"
        )
    return found[0]


def read_labels_dlc(
    path: str | Path, marker_names: Sequence[str], pcutoff: float | None = None
) -> AcmLabels:
    """Read ``labels_dlc_*.npy``: ``labels_all`` (F, n_cams, M, 3) -> (n_cams, F, M, 2).

    Parameters
    ----------
    path : path
    marker_names : sequence of str, length M
        Names of the label columns (the model's ``joint_marker_order``, e.g.
        ``AcmModel.acm_marker_names``).
    pcutoff : float, optional
        Set points with likelihood <= pcutoff to NaN (as ACM does); default: keep all.

    Returns
    -------
    AcmLabels
        Points in px, likelihood, ``frame_list`` as frames; markers in file order.
    """
    p = Path(path)
    d = _load_dict(
        p, "DeepLabCut labels", {"frame_list": "(F,) frames", "labels_all": "(F, C, M, 3)"}
    )
    frames = _array(d, "frame_list", p, (None,), "int")
    lab = _array(d, "labels_all", p, (frames.size, None, len(marker_names), 3))
    pts = lab[..., :2].transpose(1, 0, 2, 3).copy()
    lik = lab[..., 2].transpose(1, 0, 2).copy()
    if pcutoff is not None:
        pts[lik <= pcutoff] = np.nan
    return AcmLabels(pts, lik, frames, list(marker_names))


def read_labels_manual(
    path: str | Path, marker_names: Sequence[str] | None = None, n_cams: int | None = None
) -> AcmLabels:
    """Read ``labels_manual.npz``: ``{frame: {"spot_<name>": (n_cams, 2)}}`` (a trusted pickle).

    Parameters
    ----------
    path : path
    marker_names : sequence of str, optional
        Marker order of the output (e.g. ``skeleton.marker_names``); a labelled marker not in
        it is an error naming it. Default: the labelled names, sorted.
    n_cams : int, optional
        Expected number of cameras (checked).

    Returns
    -------
    AcmLabels
        Points (n_cams, F, M, 2) px, NaN where unlabelled; frames sorted; likelihood None.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: missing manual labels file")
    try:
        with np.load(p, allow_pickle=True) as z:
            if "arr_0" not in z.files:
                raise ValueError(f"{p}: expected one dict under key 'arr_0', found {z.files}")
            raw = z["arr_0"]
    except (OSError, EOFError) as exc:
        raise ValueError(f"{p}: not a NumPy .npz file ({exc})") from None
    if isinstance(raw, np.ndarray) and raw.dtype == object and raw.shape == ():
        raw = raw.item()
    if not isinstance(raw, dict):
        raise ValueError(f"{p}: arr_0 must be a dict {{frame: {{'spot_<name>': (n_cams, 2)}}}}")
    frames = []
    names: set[str] = set()
    for f, entry in raw.items():
        if not isinstance(f, int | np.integer) or isinstance(f, bool):
            raise ValueError(f"{p}: frame keys must be integers, got {f!r}")
        if not isinstance(entry, dict):
            raise ValueError(f"{p}: labels of frame {f} must be a dict, got {type(entry).__name__}")
        for k in entry:
            if not isinstance(k, str) or not k.startswith("spot_"):
                raise ValueError(f"{p}: frame {f}: label {k!r} is not of the form spot_<name>")
            names.add(k[5:])
        frames.append(int(f))
    frames.sort()
    order = sorted(names) if marker_names is None else list(marker_names)
    extra = sorted(names - set(order))
    if extra:
        raise ValueError(f"{p}: " + _unknown_markers_message(extra, order))
    if n_cams is None:
        shapes = {np.shape(v) for e in raw.values() for v in e.values()}
        n_cams = next(iter(shapes))[0] if shapes else 0
    pts = np.full((n_cams, len(frames), len(order), 2), np.nan)
    col = {n: i for i, n in enumerate(order)}
    for i, f in enumerate(frames):
        for k, v in raw[f].items():
            try:
                arr = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"{p}: frame {f} label {k!r} is not numeric") from None
            if arr.shape != (n_cams, 2):
                raise ValueError(
                    f"{p}: frame {f} label {k!r} has shape {arr.shape}, expected ({n_cams}, 2) "
                    "(one row per camera)"
                )
            pts[:, i, col[k[5:]]] = arr
    return AcmLabels(pts, None, np.array(frames, dtype=np.int64), order)


# -- origin_coord.npy -----------------------------------------------------------------------------
def read_origin_coord(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``origin_coord.npy`` (a trusted pickle) -> ``(origin (3,), coord (3, 3))``.

    Calibration coordinates = ``coord @ x_arena + origin`` (columns of ``coord`` are the arena
    axes in calibration coordinates, the third one up). ``coord`` must be a rotation.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "origin_coord.npy"
    d = _load_dict(p, "arena frame", {"origin": "(3,) arena origin", "coord": "(3, 3) axes"})
    origin = _array(d, "origin", p, (3,))
    coord = _array(d, "coord", p, (3, 3))
    if not (np.all(np.isfinite(origin)) and np.all(np.isfinite(coord))):
        raise ValueError(f"{p}: origin and coord must be finite")
    if not np.allclose(coord.T @ coord, np.eye(3), atol=1e-4) or np.linalg.det(coord) < 0:
        raise ValueError(
            f"{p}: coord must be a rotation (orthonormal columns, det +1); got det "
            f"{np.linalg.det(coord):.4f}"
        )
    return origin, coord


def calibration_to_arena(
    x: np.ndarray, origin: np.ndarray, coord: np.ndarray, scale_factor: float = 1.0
) -> np.ndarray:
    """Calibration coordinates ``(..., 3)`` -> arena coordinates in cm:
    ``scale_factor * coord^T (x - origin)``."""
    x = np.asarray(x, float)
    return scale_factor * (x - origin) @ np.asarray(coord, float)


def arena_rig(
    rig: CameraRig, origin: np.ndarray, coord: np.ndarray, scale_factor: float
) -> CameraRig:
    """The rig with the arena frame in cm as its world frame.

    With ``x_calib = coord @ x_arena / s + origin`` and ``x_cam = R x_calib + t`` (calibration
    units), scaling camera coordinates by ``s`` (projection is scale-invariant) gives
    ``R' = R coord`` and ``t' = s (R origin + t)``, in cm.
    """
    from .camera import Camera, CameraRig
    from .rotation import rodrigues_inverse

    if not scale_factor > 0:
        raise ValueError(f"scale_factor must be > 0, got {scale_factor}")
    cams = []
    for cam in rig:
        rot = cam.rotation_matrix
        r2 = rot @ coord
        t2 = scale_factor * (rot @ origin + cam.tvec)
        cams.append(Camera(cam.matrix, cam.dist, rodrigues_inverse(r2), t2, cam.size, cam.name))
    return CameraRig(cams, units="cm")  # the authors' arena frame in cm


# -- outputs --------------------------------------------------------------------------------------
def write_pose(
    path: str | Path,
    result: PoseResult,
    model: AcmModel,
    *,
    sensor_size: tuple[float, float] = (1280.0, 1024.0),
) -> Path:
    """Write ``pose.npy`` in the authors' layout (a pickled dict, atomically).

    ``joint_positions_3d`` (nT, J, 3) and ``marker_positions_3d`` (nT, M, 3) in the ACM orders of
    ``model``, ``marker_positions_2d`` (nT, n_cams, M, 2) projections normalised to [-1, 1]
    (``v = 2 px / sensor - 1``, so ``px = (v + 1) sensor / 2``). ``result`` must be in the
    arena frame in cm (track with :func:`arena_rig`), as ACM's output is.
    """
    if result.skeleton.units not in ("cm", ""):
        raise ValueError(
            f"pose.npy holds cm; the result is in {result.skeleton.units!r} (track in cm)"
        )
    j = model.to_acm_joints(result.joints)
    m = model.to_acm_markers(result.markers)
    px = model.to_acm_markers(result.projected()).transpose(1, 0, 2, 3)
    half = np.asarray(sensor_size, float) / 2.0
    doc = {
        "joint_positions_3d": np.ascontiguousarray(j, dtype=np.float64),
        "marker_positions_3d": np.ascontiguousarray(m, dtype=np.float64),
        "marker_positions_2d": np.ascontiguousarray(px / half - 1.0, dtype=np.float64),
    }
    return _save_dict(path, doc)


def write_save_dict(path: str | Path, result: PoseResult) -> Path:
    """Write ``save_dict.npy`` in the authors' layout (normalised state space, atomically).

    Probabilistic results: ``A`` (identity), ``mu0``, ``var0``, ``var_f`` (V_z), ``var_g``
    (diagonal V_x), ``mu_uks`` (nT+1, n) and ``var_uks`` (nT+1, n, n) with the initial state
    (``mu0``, ``var0``) as row 0, like ACM. The EM parameters come from
    ``result.info["params"]`` (``mu0``, ``V0``, ``Vz``, ``Vx_diag``). Deterministic results
    (no covariance): ``{"mu_fit": (nT+1, n)}`` with a NaN row 0. For the position-velocity
    model (``info["motion"] == "velocity"``) the position blocks of ``mu0``, ``V0`` and
    ``V_z`` are written (ACM's random-walk layout, ``A`` the identity) and the whole
    ``2n``-state parameters under the extra key ``velocity_params``.
    """
    mean = np.asarray(result.state_mean, float)
    n = mean.shape[1]
    if result.state_cov is None:
        mu_fit = np.vstack([np.full((1, n), np.nan), mean])
        return _save_dict(path, {"mu_fit": mu_fit})
    params = result.info.get("params", {})
    missing = [k for k in ("mu0", "V0", "Vz", "Vx_diag") if k not in params]
    if missing:
        raise ValueError(f"result.info['params'] lacks {missing} (needed for save_dict.npy)")
    ns = np.asarray(params["mu0"]).size
    if ns not in (n, 2 * n):
        raise ValueError(f"result.info['params']['mu0'] has {ns} entries, the state {n}")
    mu0 = np.asarray(params["mu0"], float).reshape(ns)[:n]
    var0 = np.asarray(params["V0"], float).reshape(ns, ns)[:n, :n]
    doc = {
        "A": np.eye(n),
        "mu0": mu0,
        "var0": var0,
        "var_f": np.asarray(params["Vz"], float).reshape(ns, ns)[:n, :n],
        "var_g": np.diag(np.asarray(params["Vx_diag"], float).ravel()),
        "mu_uks": np.vstack([mu0[None], mean]),
        "var_uks": np.concatenate([var0[None], np.asarray(result.state_cov, float)]),
    }
    if ns == 2 * n:
        doc["velocity_params"] = {k: np.asarray(params[k], float) for k in ("mu0", "V0", "Vz")}
    return _save_dict(path, doc)


def _save_dict(path: str | Path, doc: dict) -> Path:
    p = Path(path)
    if p.suffix != ".npy":
        raise ValueError(f"ACM output files end in .npy, got {p.name!r}")
    with atomic_write(p, "wb") as fh:
        np.save(fh, np.array(doc, dtype=object), allow_pickle=True)
    return p
