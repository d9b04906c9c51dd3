"""Marker files: C3D (ezc3d), TRC and CSV, read into ``(n_frames, n_markers, 3)`` arrays.

Every writer goes through :func:`acm_rs._io.atomic_write` (C3D: a temporary file renamed over the
target), so a failed write never leaves a partial file. Every reader checks that the file is
complete (declared vs present frames, a cut last record) and refuses with the file name and
what is wrong.

Metadata travel with the data: labels, rate and units of a C3D or TRC survive a CSV copy (the
CSV header names the markers, a sidecar ``<file>.acm.json`` keeps rate, units and labels), and a
file written without a frame rate is refused for C3D/TRC, whose headers need one. Filled values
are marked: in C3D by the residual (see :data:`C3D_RESIDUALS`), in TRC and CSV by the sidecar.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._io import atomic_write, new_file_mode
from . import c3d_stream
from .c3d_stream import set_c3d_frame_count, set_param

__all__ = [
    "C3D_NON_MARKER_GROUPS",
    "C3D_RESIDUALS",
    "MISSING_NAN",
    "MISSING_NEGATIVE",
    "MISSING_ZERO",
    "Markers",
    "check_output",
    "read",
    "read_c3d",
    "read_csv",
    "read_trc",
    "set_c3d_frame_count",
    "sidecar_path",
    "write",
    "write_like",
]

C3D_RESIDUALS = {"missing": -1.0, "filled": 0.0, "measured_unknown": 1.0}
"""The residuals acm-rs writes in C3D files: ``-1`` a missing point (the C3D rule for an invalid
point), ``0`` a point filled by acm-rs (C3D's value for a computed, not measured, point), and a
measured point keeps the residual of its source, or ``1`` (the smallest stored residual, in
POINT:UNITS) when the source had none or 0. :func:`read_c3d` reads residual 0 back as
``Markers.filled`` only in files carrying the ``ACM_RS:FILLED_RESIDUAL`` parameter."""

C3D_NON_MARKER_GROUPS = {
    "ANGLES": "angle",
    "FORCES": "force",
    "MOMENTS": "moment",
    "POWERS": "power",
    "SCALARS": "scalar",
    "REACTIONS": "reaction",
}
"""The POINT parameters that list the points of a C3D that are not markers (model outputs such
as Plug-in Gait's joint angles, forces, moments and powers), with the kind each gives. These are
the point types of the C3D convention as BTK/Mokka read them (btkC3DFileIO.cpp: ANGLE, FORCE,
MOMENT, POWER, SCALAR, REACTION, with ``<TYPE>_UNITS``); continuation parameters (``ANGLES2``,
...) are read too."""

MISSING_NEGATIVE = "negative residual"
"""Reason a C3D point is missing: its fourth word (residual) is negative, the C3D rule for an
invalid point (c3d.org, "3D data" and "Notes for programmers"; ezc3d, BTK and py-c3d alike)."""
MISSING_NAN = "NaN coordinates"
"""Reason a C3D point is missing: a coordinate is NaN (written by tools that store gaps as NaN)
while its residual does not say invalid."""
MISSING_ZERO = "zero-coded (0, 0, 0)"
"""Reason a C3D marker is missing: all three coordinates are exactly 0, how some systems code a
gap (e.g. Qualisys Track Manager 2004-2005: (0, 0, 0) with a fourth word 65535.0, which ezc3d
and py-c3d decode as a positive residual). Only markers: a model output (a power, a force
without contact) is legitimately 0."""

C3D_WORD4 = 2
"""Value of the parameter ``ACM_RS:WORD4`` in the C3D files acm-rs writes: their fourth point
words follow the C3D specification (camera mask in the high byte, residual in the low byte).
acm-rs files without it (older versions) hold the residual in the high byte and are read so."""

_SIDECAR_FORMAT = "acm-rs-markers"


@dataclass
class Markers:
    """Marker trajectories with their metadata.

    Attributes
    ----------
    xyz : ndarray, shape (n_frames, n_markers, 3)
        Positions in ``units``; NaN where a marker is missing.
    labels : list of str
        Marker names (``n_markers``).
    rate : float or None
        Frame rate in Hz; None when the file does not say (CSV without a sidecar).
    units : str
        Length unit (``"mm"`` for C3D and most TRC files).
    source : dict
        Format-specific data needed to write a faithful copy (the ezc3d object, TRC header).
    filled : ndarray of bool, shape (n_frames, n_markers), or None
        True where a value was filled by acm-rs (from the C3D residuals or the sidecar).
    kinds : list of str or None
        What each point is (``n_markers`` entries): ``"marker"``, or for the model outputs a
        C3D lists in POINT:ANGLES, FORCES, MOMENTS, POWERS, SCALARS or REACTIONS ``"angle"``,
        ``"force"``, ``"moment"``, ``"power"``, ``"scalar"``, ``"reaction"`` (see
        :data:`C3D_NON_MARKER_GROUPS`). None: every point is a marker (TRC, CSV).
    missing_reasons : dict of str to ndarray of bool, shape (n_frames, n_markers)
        Why points were read as missing (NaN in ``xyz``), one mask per reason: for C3D
        :data:`MISSING_NEGATIVE` (the C3D rule) and :data:`MISSING_ZERO` (markers coded as
        exactly (0, 0, 0)); empty when the format has no such codes.
    """

    xyz: np.ndarray
    labels: list[str]
    rate: float | None = None
    units: str = "mm"
    source: dict[str, Any] = field(default_factory=dict)
    filled: np.ndarray | None = None
    kinds: list[str] | None = None
    missing_reasons: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def is_marker(self) -> np.ndarray:
        """Bool (n_markers,): True for the points that are markers (all of them when
        ``kinds`` is None)."""
        if self.kinds is None:
            return np.ones(self.xyz.shape[1], dtype=bool)
        return np.array([k == "marker" for k in self.kinds], dtype=bool)


def sidecar_path(path: str | os.PathLike[str]) -> Path:
    """The metadata sidecar of a TRC/CSV file: ``<file>.acm.json`` next to it."""
    p = Path(path)
    return p.with_name(p.name + ".acm.json")


def _runs(mask: np.ndarray) -> list[list[int]]:
    """``[start, stop)`` frame intervals where a 1-D bool mask is True."""
    m = np.concatenate([[False], np.asarray(mask, bool), [False]])
    edges = np.flatnonzero(m[1:] != m[:-1])
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _write_sidecar(path: Path, m: Markers, n_frames: int, filled: np.ndarray | None) -> None:
    meta: dict[str, Any] = {
        "format": _SIDECAR_FORMAT,
        "version": 1,
        "file": path.name,
        "n_frames": int(n_frames),
        "labels": list(m.labels),
        "rate": m.rate,
        "units": m.units,
        "filled": {},
    }
    if filled is not None:
        meta["filled"] = {
            m.labels[j]: _runs(filled[:, j]) for j in range(filled.shape[1]) if filled[:, j].any()
        }
    with atomic_write(sidecar_path(path)) as fh:
        json.dump(meta, fh, indent=1)
        fh.write("\n")


def _read_sidecar(path: Path, n_frames: int, labels: list[str] | None) -> dict | None:
    """The sidecar of ``path`` checked against the data (None if there is none)."""
    sc = sidecar_path(path)
    if not sc.is_file():
        return None
    try:
        meta = json.loads(sc.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{sc}: not a readable acm-rs sidecar ({exc}); delete it") from None
    if not isinstance(meta, dict) or meta.get("format") != _SIDECAR_FORMAT:
        raise ValueError(f"{sc}: not an acm-rs marker sidecar (no format {_SIDECAR_FORMAT!r})")
    if meta.get("n_frames") != n_frames or (labels is not None and meta.get("labels") != labels):
        raise ValueError(
            f"{sc} describes {meta.get('n_frames')} frames of {meta.get('labels')}, but {path} "
            f"holds {n_frames} frames of {labels}: the data changed after the sidecar was "
            "written; delete the sidecar or restore the file"
        )
    return meta


def _sidecar_filled(meta: dict | None, labels: list[str], n_frames: int) -> np.ndarray | None:
    if meta is None:
        return None
    filled = np.zeros((n_frames, len(labels)), dtype=bool)
    for name, runs in (meta.get("filled") or {}).items():
        j = labels.index(name)
        for a, b in runs:
            filled[a:b, j] = True
    return filled


def _read_text(p: Path, kind: str) -> str:
    if not p.is_file():
        raise ValueError(f"{kind} file not found: {p}")
    try:
        return p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(
            f"{p}: not a text {kind} file (byte {exc.start} is not UTF-8); is it a binary file "
            "or a different format?"
        ) from None


def _param(c, group: str, name: str):
    try:
        return np.asarray(c["parameters"][group][name]["value"]).ravel()
    except KeyError:
        return None


def _c3d_check_sections(p: Path) -> None:
    """Refuse a file too short for the header, parameter section and data start it declares,
    before ezc3d reads it (ezc3d crashes the process on some such files)."""
    size = p.stat().st_size
    with open(p, "rb") as fh:
        head = fh.read(512)
        if len(head) < 512 or head[1] != 0x50 or head[0] < 2:
            raise ValueError(
                f"{p}: not a C3D file, or cut inside its 512-byte header ({size} bytes; a C3D "
                "starts with the parameter block number and 0x50)"
            )
        fh.seek((head[0] - 1) * 512)
        params = fh.read(4)
    if len(params) < 4:
        raise ValueError(f"{p}: incomplete C3D file: cut before its parameter section")
    end = (head[0] - 1 + params[2]) * 512
    order = ">u2" if params[3] == 86 else "<u2"
    data_start = int(np.frombuffer(head[16:18], dtype=order)[0])
    need = max(end, (data_start - 1) * 512)
    if size < need:
        raise ValueError(
            f"{p}: incomplete C3D file: its header and parameters need {need} bytes before the "
            f"data, the file has {size}; the file was cut (copy or download it again)"
        )
    with open(p, "rb") as fh:
        fh.seek((head[0] - 1) * 512)
        section = fh.read(params[2] * 512)
    _c3d_check_parameters(p, section, "big" if params[3] == 86 else "little")


def _c3d_check_parameters(p: Path, sec: bytes, order: str) -> None:
    """Walk the parameter records of a C3D (name, id, offset to the next record, type, dims,
    data, description) and refuse one that points or reaches past its section."""

    def bad(at: int, what: str) -> ValueError:
        return ValueError(
            f"{p}: damaged C3D parameter section ({what} at byte {at} of the section); the "
            "file is corrupt"
        )

    pos, n = 4, len(sec)
    groups: dict[int, str] = {}
    used: dict[int, int] = {}
    while pos + 2 <= n:
        n_chars = abs(int.from_bytes(sec[pos : pos + 1], "little", signed=True))
        if n_chars == 0:
            break
        ident = int.from_bytes(sec[pos + 1 : pos + 2], "little", signed=True)
        body = pos + 2 + n_chars
        if ident == 0 or body + 2 > n:
            raise bad(pos, "a record without a valid id or name")
        step = int.from_bytes(sec[body : body + 2], order, signed=True)
        q = body + 2
        name = bytes(sec[pos + 2 : body]).upper()
        if ident < 0:
            if -ident in groups or name in groups.values():
                raise bad(pos, f"a second group {-ident} {name!r}")
            groups[-ident] = name
        else:
            used.setdefault(ident, pos)
        if ident > 0:  # a parameter: type, dimensions, data
            if q + 2 > n:
                raise bad(q, "a parameter cut short")
            kind = int.from_bytes(sec[q : q + 1], "little", signed=True)
            n_dims = sec[q + 1]
            if kind not in (-1, 1, 2, 4) or n_dims > 7 or q + 2 + n_dims > n:
                raise bad(q, f"a parameter of type {kind} with {n_dims} dimensions")
            count = int(np.prod(list(sec[q + 2 : q + 2 + n_dims]), dtype=np.int64))
            q += 2 + n_dims + count * abs(kind)
        if q + 1 > n or q + 1 + sec[q] > n:
            raise bad(pos, "a record reaching past the section")
        if step == 0:
            break
        nxt = body + step
        if q + 1 + sec[q] > nxt:
            raise bad(pos, "a record longer than its link to the next one")
        if step < 0 or nxt <= pos or nxt > n:
            raise bad(pos, f"a link to byte {nxt}")
        pos = nxt
    orphans = sorted(set(used) - set(groups))
    if orphans:
        raise bad(used[orphans[0]], f"a parameter of group {orphans[0]}, which does not exist")


def _c3d_header_frames(p: Path) -> int | None:
    """Frames in the raw C3D header (words 4 and 5: first and last frame), None if saturated
    (65535) or unreadable. ezc3d shortens its copy of the header to the data it found, so a
    truncated file is recognised from the bytes."""
    h = c3d_stream.header_layout(p)
    if h is None:
        return None
    first, last = h["first"], h["last"]
    if last >= 65535 or last < first:
        return None
    return int(last - first + 1)


def _c3d_declared_frames(c, p: Path | None = None) -> int:
    """Frames a C3D declares: POINT:LONG_FRAMES, else TRIAL:ACTUAL_END/START_FIELD (two 16-bit
    words each), else the raw header or POINT:FRAMES (the conventions for recordings over
    65535 frames)."""
    long = _param(c, "POINT", "LONG_FRAMES")
    if long is not None and long.size:
        return int(round(float(long[0])))
    start, end = _param(c, "TRIAL", "ACTUAL_START_FIELD"), _param(c, "TRIAL", "ACTUAL_END_FIELD")
    if start is not None and end is not None and start.size >= 2 and end.size >= 2:

        def word(v: np.ndarray) -> int:
            return (int(v[1]) & 0xFFFF) << 16 | (int(v[0]) & 0xFFFF)

        n = word(end) - word(start) + 1
        if n > 0:
            return n
    frames = _param(c, "POINT", "FRAMES")
    n = int(round(float(frames[0]))) if frames is not None and frames.size else 0
    n = n + 65536 if n < 0 else n  # a signed 16-bit count above 32767
    header = _c3d_header_frames(p) if p is not None else None
    return max(n, header or 0)


def _c3d_layout(c, p: Path) -> tuple[int, int, int, float]:
    """(data offset in bytes, words per frame, bytes per word, scale) of a C3D's data block."""
    start = _param(c, "POINT", "DATA_START")
    n_points = int(_param(c, "POINT", "USED")[0])
    scale_v = _param(c, "POINT", "SCALE")
    scale = float(scale_v[0]) if scale_v is not None and scale_v.size else -1.0
    used = _param(c, "ANALOG", "USED")
    n_analog = int(used[0]) if used is not None and used.size else 0
    if n_analog:
        arate = float(_param(c, "ANALOG", "RATE")[0])
        prate = float(_param(c, "POINT", "RATE")[0])
        n_analog *= int(round(arate / prate)) if prate > 0 else 0
    if start is None or not start.size or int(start[0]) < 2 or n_points < 0 or n_analog < 0:
        raise ValueError(f"{p}: damaged C3D file: POINT:DATA_START, POINT:USED or ANALOG:USED")
    return (int(start[0]) - 1) * 512, 4 * n_points + n_analog, 4 if scale < 0 else 2, scale


def _c3d_legacy_words(c) -> bool:
    """True for a file written by acm-rs before the ``ACM_RS:WORD4`` marker (it has
    ``ACM_RS:FILLED_RESIDUAL`` only): its fourth words hold the residual in the high byte."""
    acm_rs = _param(c, "ACM_RS", "FILLED_RESIDUAL") is not None
    return acm_rs and _param(c, "ACM_RS", "WORD4") is None


def _c3d_points_raw(p: Path, c, n_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Point data of a C3D read in blocks from the file (long or large files, see
    :mod:`acm_rs.gapfill.c3d_stream`): ``(xyz (n_frames, n_points, 3), residual (n_frames,
    n_points), camera mask (n_frames, n_points), where the frames are)``; Intel float format
    only. Fourth words decoded by the C3D specification (old acm-rs files: their layout)."""
    from .c3d_stream import header_layout, read_points

    offset, words, size, scale = _c3d_layout(c, p)
    h = header_layout(p)
    if size != 4 or h is None or h["processor"] != 84:
        raise ValueError(
            f"{p}: C3D with more than 65535 frames in integer or non-Intel format is not "
            "supported; convert it to the Intel floating-point format"
        )
    n_points = int(_param(c, "POINT", "USED")[0])
    xyz, residual, mask = read_points(
        p, offset, words, n_points, n_frames, scale, _c3d_legacy_words(c)
    )
    where = {"path": str(p), "offset": offset, "words": words, "n_points": n_points,
             "n_frames": n_frames}  # fmt: skip
    return xyz, residual, mask, where


def _c3d_point_words(p: Path, c, n_frames: int, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and camera masks of a C3D that ezc3d read whole, decoded from the file's
    fourth words by the C3D specification (ezc3d 1.7.2 swaps the two bytes; see
    :mod:`acm_rs.gapfill.c3d_stream`): ``(residual, mask)``, each (n_frames, n_points)."""
    offset, words, size, scale = _c3d_layout(c, p)
    h = c3d_stream.header_layout(p)
    word = c3d_stream.read_fourth_words(
        p, offset, words, n_points, n_frames, h["processor"], size == 4
    )
    return c3d_stream.decode_point_words(word, scale, _c3d_legacy_words(c))


def _c3d_check_layout(p: Path, c, declared: int, offset: int, words: int, size: int) -> None:
    """Refuse a C3D whose header and parameters give different frame sizes when its data fit
    the header's: ezc3d follows the parameters (POINT:USED, ANALOG:USED x ANALOG:RATE /
    POINT:RATE) and would read every frame shifted (c3d.org sample28, BTS files with
    ANALOG:USED 0 but analog words in the frames); BTK follows the header."""
    h = c3d_stream.header_layout(p)
    if h is None or h["words"] == words or h["words"] <= 0 or words <= 0:
        return
    data = p.stat().st_size - offset
    by_header, by_params = data // (h["words"] * size), data // (words * size)
    spare = 512 // (words * size) + 1  # frames the padding of the last block can hold
    if by_header == declared and by_params > declared + spare:
        raise ValueError(
            f"{p}: the C3D header says {h['words']} words per frame and the parameters "
            f"{words} (POINT:USED, ANALOG:USED, ANALOG:RATE); the data fit the header, so the "
            "parameters are wrong and readers that follow them read shifted frames; fix "
            "ANALOG:USED/ANALOG:RATE or export the file again"
        )


def _c3d_values(group: dict, name: str) -> list:
    """A parameter's values with its continuations (``LABELS``, ``LABELS2``, ...: the C3D
    convention for lists over 255 entries)."""
    out: list = []
    for key in [name] + [f"{name}{i}" for i in range(2, 100)]:
        if key not in group:
            break
        out += list(np.asarray(group[key]["value"]).ravel())
    return out


def _c3d_check_labels(p: Path, c, group: str, used: int) -> list[str]:
    """The labels of the ``used`` (``<group>:USED``) points or analog channels: the first
    ``used`` entries of ``<group>:LABELS`` (+ LABELS2, ...), the C3D meaning of USED. Surplus
    labels name no stored data (c3d.org sample01/02, Vicon 370: 48 or 75 point labels for 26 or
    36 points; ezc3d reads them all, BTK only USED) and are dropped from the parameters (said in
    a warning), so a copy has as many labels as data (ezc3d refuses to write it otherwise). Too
    few labels: refused before any work."""
    par = c["parameters"].get(group, {})
    labels = [str(s) for s in _c3d_values(par, "LABELS")]
    if len(labels) < used:
        raise ValueError(
            f"{p}: {group}:LABELS has {len(labels)} labels for {used} {group}:USED entries; "
            "the file is damaged (add the missing labels)"
        )
    if len(labels) > used:
        import warnings

        warnings.warn(
            f"{p}: {group}:LABELS has {len(labels)} entries for {used} {group}:USED; the "
            f"first {used} name the data, the other {len(labels) - used} name nothing and are "
            "left out of a written copy",
            stacklevel=3,
        )
        keep = used
        for key in ["LABELS"] + [f"LABELS{i}" for i in range(2, 100)]:
            if key not in par:
                break
            vals = list(par[key]["value"])
            par[key]["value"] = vals[:keep]
            keep = max(keep - len(vals), 0)
        for key in [f"LABELS{i}" for i in range(2, 100)]:
            if key in par and not len(par[key]["value"]):
                del par[key]
    return labels[:used]


def _c3d_point_labels(p: Path, c, n_points: int) -> list[str]:
    """The labels of the ``n_points`` points (POINT:LABELS cut to POINT:USED), after the same
    check of the analog labels (see :func:`_c3d_check_labels`)."""
    used = _param(c, "ANALOG", "USED")
    if used is not None and used.size and "LABELS" in c["parameters"].get("ANALOG", {}):
        _c3d_check_labels(p, c, "ANALOG", int(used[0]))
    return _c3d_check_labels(p, c, "POINT", n_points)


def _c3d_point_kinds(c, labels: list[str]) -> list[str]:
    """The kind of each point: ``"marker"``, or the kind of the POINT group that lists it
    (:data:`C3D_NON_MARKER_GROUPS`); labels are compared without surrounding blanks."""
    point = c["parameters"]["POINT"]
    kind_of: dict[str, str] = {}
    for group, kind in C3D_NON_MARKER_GROUPS.items():
        for name in _c3d_values(point, group):
            kind_of.setdefault(str(name).strip(), kind)
    return [kind_of.get(lab.strip(), "marker") for lab in labels]


def _c3d_missing(
    xyz: np.ndarray, residual: np.ndarray | None, is_marker: np.ndarray
) -> dict[str, np.ndarray]:
    """Set to NaN (in place) the points a C3D codes as missing and say why, per reason:
    :data:`MISSING_NEGATIVE` (a negative residual) and :data:`MISSING_NAN` (a NaN coordinate
    with a valid residual) for every point, :data:`MISSING_ZERO` (x = y = z = 0 exactly) for
    the points where ``is_marker`` (markers of files not written by acm-rs). One coordinate
    at 0 is a valid value (2-D data, a marker on a lab axis).
    Returns one mask (n_frames, n_points) per reason, each point under its first reason."""
    nan = np.isnan(xyz).any(axis=2)
    negative = np.zeros_like(nan) if residual is None else residual < 0
    nan &= ~negative
    zero = (xyz == 0).all(axis=2) & is_marker[None, :] & ~negative
    xyz[negative | nan | zero] = np.nan
    return {MISSING_NEGATIVE: negative, MISSING_NAN: nan, MISSING_ZERO: zero}


def read_c3d(path: str | os.PathLike[str]) -> Markers:
    """Read a C3D file with ezc3d (large files: parameters with ezc3d, frames in blocks).

    Missing points become NaN, each counted under its reason in ``missing_reasons``: a negative
    residual (the C3D rule), NaN coordinates, and for markers exactly (0, 0, 0) (how Qualisys
    and other systems code gaps). Points listed in POINT:ANGLES, FORCES, MOMENTS, POWERS,
    SCALARS or REACTIONS are model outputs, not markers (``kinds``). Only the first POINT:USED
    labels name points. The number of frames is the declared one (POINT:LONG_FRAMES,
    TRIAL:ACTUAL_END_FIELD or POINT:FRAMES, so files over 65535 frames read whole), and a file
    holding fewer frames than it declares is refused.

    Parameters
    ----------
    path : path-like
        The ``.c3d`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_markers, 3) in the file's POINT:UNITS; ``filled`` from
        the residuals of a file acm-rs wrote (see :data:`C3D_RESIDUALS`).

    Raises
    ------
    ValueError
        If the file cannot be parsed as C3D or is incomplete (truncated).
    """
    import ezc3d

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"C3D file not found: {p}")
    _c3d_check_sections(p)
    c3d_stream.check_processor(p)  # big-endian (SGI/MIPS): refused in one line
    stream = c3d_stream.wants_streaming(p)
    try:
        c = c3d_stream.read_parameters(p) if stream else ezc3d.c3d(str(p))
        pts = np.asarray(c["data"]["points"], dtype=np.float64)
        declared = _c3d_declared_frames(c, p)
        offset, words, size, _ = _c3d_layout(c, p)
    except ValueError:
        raise
    except Exception as exc:  # ezc3d raises RuntimeError/IndexError on corrupt files
        raise ValueError(f"cannot read C3D file {p}: {exc}") from None
    have = (p.stat().st_size - offset) // (words * size) if words else declared
    if words and have < declared:
        raise ValueError(
            f"{p}: incomplete C3D file: it declares {declared} frames but holds only {have} "
            f"({p.stat().st_size} bytes); the file was cut (copy or download it again)"
        )
    _c3d_check_layout(p, c, declared, offset, words, size)
    labels = _c3d_point_labels(p, c, int(_param(c, "POINT", "USED")[0]))
    kinds = _c3d_point_kinds(c, labels)
    where = None
    if stream or declared > pts.shape[2]:
        try:
            xyz, residual, mask, where = _c3d_points_raw(p, c, declared)
        except ValueError:
            raise
        except Exception as exc:  # a damaged layout (negative offset, odd sizes)
            raise ValueError(f"{p}: damaged C3D file: {type(exc).__name__}: {exc}") from None
    else:
        if pts.shape[2] != declared:
            raise ValueError(
                f"{p}: C3D declares {declared} frames but ezc3d read {pts.shape[2]}; the file "
                "is damaged"
            )
        xyz = pts[:3].transpose(2, 1, 0).copy()
        # the fourth words from the file, by the C3D specification (not ezc3d's residuals)
        residual, mask = _c3d_point_words(p, c, declared, xyz.shape[1])
    # (0, 0, 0) as a gap is a convention of other writers (old Qualisys); acm-rs codes its gaps
    # by a negative word, so in its own files a marker at the origin is a measurement
    zero_coded = np.array([k == "marker" for k in kinds], dtype=bool)
    if _param(c, "ACM_RS", "WORD4") is not None:
        zero_coded[:] = False
    reasons = _c3d_missing(xyz, residual, zero_coded)
    point = c["parameters"]["POINT"]
    rate = float(np.asarray(point["RATE"]["value"]).ravel()[0])
    units = point.get("UNITS", {}).get("value", ["mm"])
    filled = None
    if _param(c, "ACM_RS", "FILLED_RESIDUAL") is not None and residual is not None:
        filled = (residual == 0) & ~np.isnan(xyz[:, :, 0])
    src = {"c3d": c, "residual": residual, "camera_mask": mask, "frames_at": where}
    unit = str(units[0]) if len(units) else "mm"
    return Markers(xyz, labels, rate, unit, src, filled, kinds, reasons)


def _c3d_float_scale(c) -> float:
    """POINT:SCALE of a float-format output, set in ``c``: negative (the float-format flag; an
    integer source's positive scale is negated, ezc3d writes floats), -1 when absent or 0."""
    v = _param(c, "POINT", "SCALE")
    scale = -abs(float(v[0])) if v is not None and v.size and float(v[0]) != 0 else -1.0
    set_param(c, "POINT", "SCALE", [scale])
    return scale


def _c3d_output_words(
    m: Markers, xyz: np.ndarray, filled: np.ndarray | None, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and camera masks of a C3D output (:data:`C3D_RESIDUALS`): -1 missing, 0 and no
    camera where filled, the source's residual and camera mask where measured (or the unknown
    residual, 1 in POINT:UNITS, when the source has none or 0)."""
    n_frames, n_markers, _ = xyz.shape
    # "measured, residual unknown": 1 unit, or the largest residual the file can store
    unknown = min(C3D_RESIDUALS["measured_unknown"], 255 * abs(scale))
    residual = np.full((n_frames, n_markers), unknown)
    mask = np.zeros((n_frames, n_markers), np.uint8)
    src_res, src_mask = m.source.get("residual"), m.source.get("camera_mask")
    if src_res is not None and src_res.shape == residual.shape:
        np.copyto(residual, src_res, where=src_res > 0)
        if src_mask is not None and src_mask.shape == mask.shape:
            np.copyto(mask, src_mask, where=src_res >= 0)
    if filled is not None:
        residual[filled] = C3D_RESIDUALS["filled"]
        mask[filled] = 0  # C3D: all camera bits 0 for a computed point
    gone = np.isnan(xyz).any(axis=2)
    residual[gone] = C3D_RESIDUALS["missing"]
    mask[gone] = 0
    return residual, mask


def _write_c3d(path: Path, m: Markers, xyz: np.ndarray, filled: np.ndarray | None) -> None:
    import ezc3d

    n_frames, n_markers, _ = xyz.shape
    c = m.source.get("c3d")
    if c is None:
        c = ezc3d.c3d()
        c["parameters"]["POINT"]["RATE"]["value"] = [float(m.rate)]
        c["parameters"]["POINT"]["LABELS"]["value"] = list(m.labels)
        c["parameters"]["POINT"]["UNITS"]["value"] = [m.units]
    scale = _c3d_float_scale(c)
    residual, mask = _c3d_output_words(m, xyz, filled, scale)
    set_param(c, "ACM_RS", "FILLED_RESIDUAL", [float(C3D_RESIDUALS["filled"])])
    set_param(c, "ACM_RS", "WORD4", [C3D_WORD4])
    big = n_frames > 65535 or 16 * n_frames * n_markers > c3d_stream.STREAM_BYTES
    if big or m.source.get("frames_at") is not None:
        # frames in blocks after ezc3d's header and parameters (bounded memory); always for a
        # source read in blocks, whose ezc3d object holds one frame (of analogs too)
        c3d_stream.write_streamed(path, c, xyz, residual, m.source.get("frames_at"), mask)
        return
    pts = np.ones((4, n_markers, n_frames))
    pts[:3] = xyz.transpose(2, 1, 0)
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {
        "residuals": residual.T[None].copy(),
        "camera_masks": np.zeros((7, n_markers, n_frames), dtype=bool),
    }
    set_c3d_frame_count(c, n_frames)
    # ezc3d writes by path and needs a .c3d suffix: write a temporary .c3d next to the target,
    # then rename it over the target (the same guarantee as atomic_write).
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".c3d", dir=path.parent)
    os.close(fd)
    try:
        c.write(tmp)
        # ezc3d writes the fourth words with the bytes swapped and the header's scale as -1:
        # both are rewritten by the C3D specification
        c3d_stream.patch_point_words(Path(tmp), residual, scale, mask)
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def read_trc(path: str | os.PathLike[str]) -> Markers:
    """Read a TRC file (5 header lines, ``Frame#``, ``Time``, x y z per marker).

    Empty fields are missing values (NaN). A file with fewer (or more) data rows than its
    NumFrames, or whose last line has no line end (a cut file), is refused. The file is read
    in blocks (:mod:`acm_rs.gapfill.text_stream`): memory is the array and one block, and each
    value is the one ``float()`` gives for its field.

    Parameters
    ----------
    path : path-like
        The ``.trc`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_markers, 3); ``rate`` from DataRate, ``units`` from Units,
        ``filled`` from the sidecar if there is one; ``source["trc"]`` keeps the Frame# and Time
        fields as written.
    """
    from .text_stream import read_trc_text

    p = Path(path)

    def header_dict(lines: list[str]) -> dict[str, str]:
        keys = [k.strip() for k in lines[1].split("\t")]
        vals = lines[2].split("\t")
        named, given = [k for k in keys if k], [v for v in vals if v.strip()]
        if any(v.strip() for v in vals[len(keys) :]) and len(named) == len(given):
            # values past the last name: separated by double tabs (some exporters, e.g.
            # OpenSim's Rajagopal example data); pair the names with the non-empty values
            return dict(zip(named, given, strict=True))
        return dict(zip(keys, vals, strict=False))

    def expected(lines: list[str]) -> int:  # NumFrames, to size the array
        try:
            return int(float(header_dict(lines).get("NumFrames", "")))
        except (ValueError, OverflowError):
            return 0

    t = read_trc_text(p, expected)
    hdr = header_dict(t.header)
    labels = [s.strip() for s in t.header[3].split("\t")[2:] if s.strip()]
    n_rows = len(t.values)
    if not n_rows:
        raise ValueError(f"{p}: no data rows")
    declared = hdr.get("NumFrames", "").strip()
    if declared:
        try:
            n_declared = int(float(declared))
        except (ValueError, OverflowError):  # OverflowError: "inf", "1e999"
            raise ValueError(f"{p}: NumFrames {declared!r} is not a number") from None
        if n_declared != n_rows:
            raise ValueError(
                f"{p}: NumFrames says {n_declared} frames but the file holds {n_rows} data "
                "rows; the file is incomplete or was edited (fix NumFrames or restore the file)"
            )
    declared_m = hdr.get("NumMarkers", "").strip()
    if declared_m and declared_m.isdigit() and int(declared_m) != len(labels):
        raise ValueError(f"{p}: NumMarkers says {declared_m} but line 4 names {len(labels)}")
    xyz = t.values.reshape(n_rows, len(labels), 3)
    try:
        rate = float(hdr["DataRate"]) if hdr.get("DataRate", "").strip() else None
    except ValueError:
        raise ValueError(f"{p}: DataRate {hdr['DataRate']!r} is not a number") from None
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"{p}: DataRate {rate} is not a positive frame rate")
    units = hdr.get("Units", "mm").strip() or "mm"
    meta = _read_sidecar(p, n_rows, labels)
    filled = _sidecar_filled(meta, labels, n_rows)
    src = {"trc": {"frames": t.frames, "times": t.times}}
    return Markers(xyz, labels, rate, units, src, filled)


def _write_trc(path: Path, m: Markers, xyz: np.ndarray) -> None:
    from .text_stream import trc_rows

    n_frames, n_markers, _ = xyz.shape
    rate = float(m.rate)
    src = m.source.get("trc", {})
    frames, times = src.get("frames"), src.get("times")
    if frames is None or times is None or len(frames) != n_frames or len(times) != n_frames:
        # new frame numbers and times (1-based frames, times from 0 at the rate)
        frames, times = (lambda i: str(i + 1)), (lambda i: f"{i / rate:.6f}")
    else:  # the source's fields, kept as written
        frames, times = frames.__getitem__, times.__getitem__
    with atomic_write(path) as fh:
        fh.write(f"PathFileType\t4\t(X/Y/Z)\t{path.name}\n")
        fh.write(
            "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
            "OrigDataStartFrame\tOrigNumFrames\n"
        )
        r = f"{rate:.15g}"  # all the digits of the rate (``:g`` keeps only 6)
        fh.write(f"{r}\t{r}\t{n_frames}\t{n_markers}\t{m.units}\t{r}\t1\t{n_frames}\n")
        fh.write("Frame#\tTime\t" + "\t\t\t".join(m.labels) + "\t\t\n")
        fh.write(
            "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(n_markers)) + "\n"
        )
        for text in trc_rows(xyz, frames, times):  # blocks of rows
            fh.write(text)


def read_csv(path: str | os.PathLike[str]) -> Markers:
    """Read a CSV of marker positions: one row per frame, x, y, z per marker.

    A first line with non-numeric fields is a header (labels taken from ``<name>_x`` columns or
    the fields themselves); empty fields and ``NaN`` are missing. Rate and units come from the
    sidecar ``<file>.acm.json`` when there is one (``rate`` is None otherwise). Rows of
    different widths and a last line without a line end (a cut file) are refused. The file is
    read in blocks (:mod:`acm_rs.gapfill.text_stream`): memory is the array and one block, and
    each value is the one ``float()`` gives for its field.

    Parameters
    ----------
    path : path-like
        The ``.csv`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_columns / 3, 3).
    """
    from .text_stream import read_csv_text

    p = Path(path)
    t = read_csv_text(p)
    header = t.header
    n_rows, d = t.values.shape
    if d % 3:
        raise ValueError(f"{p}: {d} columns is not a multiple of 3 (x, y, z per marker)")
    xyz = t.values.reshape(n_rows, d // 3, 3)
    if header:
        labels = [h[:-2] if h.lower().endswith(("_x", ".x")) else h for h in header[::3]]
    else:
        labels = [f"M{i:02d}" for i in range(d // 3)]
    meta = _read_sidecar(p, n_rows, None)
    rate, units = None, "mm"
    if meta is not None:
        if header is None or meta.get("labels") == labels:
            labels = list(meta["labels"])
        else:
            raise ValueError(f"{sidecar_path(p)} names {meta.get('labels')}, {p} {labels}")
        rate = None if meta.get("rate") is None else float(meta["rate"])
        units = meta.get("units") or "mm"
    filled = _sidecar_filled(meta, labels, n_rows)
    return Markers(xyz, labels, rate, units, {"csv": {"header": header}}, filled)


def _write_csv(path: Path, m: Markers, xyz: np.ndarray) -> None:
    from .text_stream import csv_rows

    header = m.source.get("csv", {}).get("header")
    if not header:
        header = [f"{lab}_{a}" for lab in m.labels for a in "xyz"]
    with atomic_write(path) as fh:
        fh.write(",".join(header) + "\n")
        for text in csv_rows(xyz):  # blocks of rows, values as repr, NaN missing
            fh.write(text)


_READERS = {".c3d": read_c3d, ".trc": read_trc, ".csv": read_csv}


def read(path: str | os.PathLike[str]) -> Markers:
    """Read a C3D, TRC or CSV marker file, chosen by extension.

    Parameters
    ----------
    path : path-like
        ``.c3d``, ``.trc`` or ``.csv``.

    Returns
    -------
    Markers
    """
    ext = Path(path).suffix.lower()
    if ext not in _READERS:
        raise ValueError(f"unsupported marker file {path!s}; expected .c3d, .trc or .csv")
    return _READERS[ext](path)


def check_output(path: str | os.PathLike[str], rate: float | None) -> Path:
    """Check an output marker file before any work: known format, a rate where needed.

    Parameters
    ----------
    path : path-like
        ``.c3d``, ``.trc`` or ``.csv``.
    rate : float or None
        The frame rate (Hz) the file will get.

    Returns
    -------
    Path
    """
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in _READERS:
        raise ValueError(f"unsupported output {p}; expected .c3d, .trc or .csv")
    if ext in (".c3d", ".trc") and rate is None:
        raise ValueError(
            f"{p}: a {ext[1:].upper()} file needs the frame rate and the input does not give "
            "one; pass --rate (Hz)"
        )
    if rate is not None and not (math.isfinite(float(rate)) and float(rate) > 0):
        raise ValueError(f"the frame rate must be a positive number of Hz, got {rate}")
    return p


def write_like(
    path: str | os.PathLike[str],
    m: Markers,
    xyz: np.ndarray,
    filled: np.ndarray | None = None,
) -> None:
    """Write ``xyz`` with the labels, rate and metadata of ``m`` (format from the extension).

    A C3D read with :func:`read_c3d` keeps all its parameters (labels, rate, units, analogs);
    only the point data change. TRC and CSV outputs get a sidecar ``<file>.acm.json`` (labels,
    rate, units, filled frames). C3D and TRC need ``m.rate``; it is never made up.

    Parameters
    ----------
    path : path-like
        Output ``.c3d``, ``.trc`` or ``.csv`` (written atomically).
    m : Markers
        The source of labels and metadata.
    xyz : ndarray, shape (n_frames, n_markers, 3)
        The values to write (NaN = missing).
    filled : ndarray of bool, shape (n_frames, n_markers) or (n_frames, n_markers, 3), optional
        True where a value was filled (C3D residual 0, listed in the sidecar).
    """
    p = check_output(path, m.rate)
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 3 or xyz.shape[1:] != m.xyz.shape[1:]:
        raise ValueError(f"xyz must have shape (n, {m.xyz.shape[1]}, 3), got {xyz.shape}")
    if filled is not None:
        filled = np.asarray(filled, dtype=bool)
        if filled.ndim == 3:
            filled = filled.any(axis=2)
        if filled.shape != xyz.shape[:2]:
            raise ValueError(f"filled must have shape {xyz.shape[:2]}, got {filled.shape}")
    ext = p.suffix.lower()
    if ext == ".c3d":
        if xyz.shape[0] != m.xyz.shape[0] and "c3d" in m.source:
            raise ValueError("a C3D copy must keep the number of frames")
        _write_c3d(p, m, xyz, filled)
        return
    if ext == ".trc":
        _write_trc(p, m, xyz)
    else:
        _write_csv(p, m, xyz)
    _write_sidecar(p, m, xyz.shape[0], filled)


def write(
    path: str | os.PathLike[str],
    xyz: np.ndarray,
    labels: list[str],
    rate: float,
    units: str = "mm",
) -> None:
    """Write new marker data (no source file) as C3D, TRC or CSV.

    Parameters
    ----------
    path : path-like
        Output file; the extension selects the format.
    xyz : ndarray, shape (n_frames, n_markers, 3)
        Positions in ``units`` (NaN = missing).
    labels : list of str
        Marker names.
    rate : float
        Frame rate in Hz (required: never made up).
    units : str
        Length unit (default mm).
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 3 or xyz.shape[2] != 3 or len(labels) != xyz.shape[1]:
        raise ValueError("xyz must have shape (n_frames, len(labels), 3)")
    if rate is None:
        raise ValueError("write needs the frame rate (Hz)")
    write_like(path, Markers(xyz, list(labels), float(rate), units, {}), xyz)
