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
    "C3D_RESIDUALS",
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
    """

    xyz: np.ndarray
    labels: list[str]
    rate: float | None = None
    units: str = "mm"
    source: dict[str, Any] = field(default_factory=dict)
    filled: np.ndarray | None = None


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


def _c3d_points_raw(p: Path, c, n_frames: int) -> tuple[np.ndarray, np.ndarray, dict]:
    """Point data of a C3D read in blocks from the file (long or large files, see
    :mod:`acm_rs.gapfill.c3d_stream`): ``(xyz (n_frames, n_points, 3), residual (n_frames,
    n_points), where the frames are)``; Intel float format only."""
    from .c3d_stream import header_layout, read_points

    offset, words, size, scale = _c3d_layout(c, p)
    h = header_layout(p)
    if size != 4 or h is None or h["processor"] != 84:
        raise ValueError(
            f"{p}: C3D with more than 65535 frames in integer or non-Intel format is not "
            "supported; convert it to the Intel floating-point format"
        )
    n_points = int(_param(c, "POINT", "USED")[0])
    xyz, residual = read_points(p, offset, words, n_points, n_frames, scale)
    where = {"path": str(p), "offset": offset, "words": words, "n_points": n_points,
             "n_frames": n_frames}  # fmt: skip
    return xyz, residual, where


def read_c3d(path: str | os.PathLike[str]) -> Markers:
    """Read a C3D file with ezc3d (large files: parameters with ezc3d, frames in blocks).

    Missing markers (NaN, or a negative residual) become NaN. The number of frames is the
    declared one (POINT:LONG_FRAMES, TRIAL:ACTUAL_END_FIELD or POINT:FRAMES, so files over
    65535 frames read whole), and a file holding fewer frames than it declares is refused.

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
    meta = c["data"].get("meta_points", {})
    res = meta.get("residuals") if isinstance(meta, dict) else None
    where = None
    if stream or declared > pts.shape[2]:
        try:
            xyz, residual, where = _c3d_points_raw(p, c, declared)
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
        residual = None
        if res is not None:
            res = np.asarray(res)
            if res.shape == (1, xyz.shape[1], xyz.shape[0]):
                residual = res[0].T
    if residual is not None:
        xyz[residual < 0] = np.nan
    point = c["parameters"]["POINT"]
    labels = [str(s) for s in point["LABELS"]["value"]][: xyz.shape[1]]
    rate = float(np.asarray(point["RATE"]["value"]).ravel()[0])
    units = point.get("UNITS", {}).get("value", ["mm"])
    filled = None
    if _param(c, "ACM_RS", "FILLED_RESIDUAL") is not None and residual is not None:
        filled = (residual == 0) & ~np.isnan(xyz[:, :, 0])
    src = {"c3d": c, "residual": residual, "frames_at": where}
    return Markers(xyz, labels, rate, str(units[0]) if len(units) else "mm", src, filled)


def _write_c3d(path: Path, m: Markers, xyz: np.ndarray, filled: np.ndarray | None) -> None:
    import ezc3d

    n_frames, n_markers, _ = xyz.shape
    c = m.source.get("c3d")
    if c is None:
        c = ezc3d.c3d()
        c["parameters"]["POINT"]["RATE"]["value"] = [float(m.rate)]
        c["parameters"]["POINT"]["LABELS"]["value"] = list(m.labels)
        c["parameters"]["POINT"]["UNITS"]["value"] = [m.units]
    # Residuals (C3D_RESIDUALS): -1 missing, 0 filled, the source's (or 1) where measured.
    residual = np.full((n_frames, n_markers), C3D_RESIDUALS["measured_unknown"])
    src_res = m.source.get("residual")
    if src_res is not None and src_res.shape == residual.shape:
        np.copyto(residual, src_res, where=src_res > 0)
    if filled is not None:
        residual[filled] = C3D_RESIDUALS["filled"]
    residual[np.isnan(xyz).any(axis=2)] = C3D_RESIDUALS["missing"]
    set_param(c, "ACM_RS", "FILLED_RESIDUAL", [float(C3D_RESIDUALS["filled"])])
    big = n_frames > 65535 or 16 * n_frames * n_markers > c3d_stream.STREAM_BYTES
    if big or m.source.get("frames_at") is not None:
        # frames in blocks after ezc3d's header and parameters (bounded memory); always for a
        # source read in blocks, whose ezc3d object holds one frame (of analogs too)
        c3d_stream.write_streamed(path, c, xyz, residual, m.source.get("frames_at"))
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
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def read_trc(path: str | os.PathLike[str]) -> Markers:
    """Read a TRC file (5 header lines, ``Frame#``, ``Time``, x y z per marker).

    Empty fields are missing values (NaN). A file with fewer (or more) data rows than its
    NumFrames, or whose last line has no line end (a cut file), is refused.

    Parameters
    ----------
    path : path-like
        The ``.trc`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_markers, 3); ``rate`` from DataRate, ``units`` from Units,
        ``filled`` from the sidecar if there is one.
    """
    p = Path(path)
    text = _read_text(p, "TRC")
    lines = text.splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise ValueError(f"{p}: not a TRC file (no PathFileType header)")
    keys = [k.strip() for k in lines[1].split("\t")]
    vals = lines[2].split("\t")
    hdr = dict(zip(keys, vals, strict=False))
    labels = [s.strip() for s in lines[3].split("\t")[2:] if s.strip()]
    if not labels:
        raise ValueError(f"{p}: line 4 names no markers")
    d = 3 * len(labels)
    rows, frames, times = [], [], []
    last = len(lines)
    for n, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        f = line.split("\t")
        if len(f) > d + 2:
            raise ValueError(f"{p}: line {n} has {len(f)} fields, expected <= {d + 2}")
        if n == last and not text.endswith(("\n", "\r")):
            raise ValueError(
                f"{p}: the last line ({n}) has no line end ({len(f)} of {d + 2} fields): the "
                "file may be cut; if it is complete, end it with a line break"
            )
        f += [""] * (d + 2 - len(f))
        try:
            rows.append([float(v) if v.strip() else np.nan for v in f[2:]])
        except ValueError as exc:
            raise ValueError(f"{p}: line {n}: {exc}") from None
        frames.append(f[0])
        times.append(f[1])
    if not rows:
        raise ValueError(f"{p}: no data rows")
    declared = hdr.get("NumFrames", "").strip()
    if declared:
        try:
            n_declared = int(float(declared))
        except ValueError:
            raise ValueError(f"{p}: NumFrames {declared!r} is not a number") from None
        if n_declared != len(rows):
            raise ValueError(
                f"{p}: NumFrames says {n_declared} frames but the file holds {len(rows)} data "
                "rows; the file is incomplete or was edited (fix NumFrames or restore the file)"
            )
    declared_m = hdr.get("NumMarkers", "").strip()
    if declared_m and declared_m.isdigit() and int(declared_m) != len(labels):
        raise ValueError(f"{p}: NumMarkers says {declared_m} but line 4 names {len(labels)}")
    xyz = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(labels), 3)
    try:
        rate = float(hdr["DataRate"]) if hdr.get("DataRate", "").strip() else None
    except ValueError:
        raise ValueError(f"{p}: DataRate {hdr['DataRate']!r} is not a number") from None
    if rate is not None and not (math.isfinite(rate) and rate > 0):
        raise ValueError(f"{p}: DataRate {rate} is not a positive frame rate")
    units = hdr.get("Units", "mm").strip() or "mm"
    meta = _read_sidecar(p, len(rows), labels)
    filled = _sidecar_filled(meta, labels, len(rows))
    return Markers(xyz, labels, rate, units, {"trc": {"frames": frames, "times": times}}, filled)


def _write_trc(path: Path, m: Markers, xyz: np.ndarray) -> None:
    n_frames, n_markers, _ = xyz.shape
    rate = float(m.rate)
    src = m.source.get("trc", {})
    frames = src.get("frames") or [str(i + 1) for i in range(n_frames)]
    times = src.get("times") or [f"{i / rate:.6f}" for i in range(n_frames)]
    if len(frames) != n_frames:
        frames = [str(i + 1) for i in range(n_frames)]
        times = [f"{i / rate:.6f}" for i in range(n_frames)]
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
        for i in range(n_frames):
            vals = ["" if np.isnan(v) else repr(float(v)) for v in xyz[i].ravel()]
            fh.write(f"{frames[i]}\t{times[i]}\t" + "\t".join(vals) + "\n")


def read_csv(path: str | os.PathLike[str]) -> Markers:
    """Read a CSV of marker positions: one row per frame, x, y, z per marker.

    A first line with non-numeric fields is a header (labels taken from ``<name>_x`` columns or
    the fields themselves); empty fields and ``NaN`` are missing. Rate and units come from the
    sidecar ``<file>.acm.json`` when there is one (``rate`` is None otherwise). Rows of
    different widths and a last line without a line end (a cut file) are refused.

    Parameters
    ----------
    path : path-like
        The ``.csv`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_columns / 3, 3).
    """
    p = Path(path)
    raw = _read_text(p, "CSV")
    numbered = [(n, ln) for n, ln in enumerate(raw.splitlines(), start=1) if ln.strip()]
    if not numbered:
        raise ValueError(f"{p}: empty CSV file")
    header = None
    first = numbered[0][1].split(",")

    def _num(s: str) -> bool:
        try:
            float(s) if s.strip() else None
            return True
        except ValueError:
            return False

    if not all(_num(f) for f in first):
        header = [f.strip() for f in first]
        numbered = numbered[1:]
    if not numbered:
        raise ValueError(f"{p}: no data rows after the header")
    width = len(header) if header else len(numbered[0][1].split(","))
    rows = []
    ends = raw.endswith(("\n", "\r"))
    for n, line in numbered:
        f = line.split(",")
        if n == numbered[-1][0] and not ends and len(f) == width:
            raise ValueError(
                f"{p}: the last line ({n}) has no line end: the file may be cut; if it is "
                "complete, end it with a line break"
            )
        if len(f) != width:
            cut = n == numbered[-1][0] and not raw.endswith(("\n", "\r"))
            raise ValueError(
                f"{p}: line {n} has {len(f)} fields, expected {width}"
                + ("; the last line is cut: the file is incomplete" if cut else "")
            )
        try:
            rows.append([float(v) if v.strip() else np.nan for v in f])
        except ValueError as exc:
            raise ValueError(f"{p}: line {n}: {exc}") from None
    d = width
    if d % 3:
        raise ValueError(f"{p}: {d} columns is not a multiple of 3 (x, y, z per marker)")
    xyz = np.asarray(rows, dtype=np.float64).reshape(len(rows), d // 3, 3)
    if header:
        labels = [h[:-2] if h.lower().endswith(("_x", ".x")) else h for h in header[::3]]
    else:
        labels = [f"M{i:02d}" for i in range(d // 3)]
    meta = _read_sidecar(p, len(rows), None)
    rate, units = None, "mm"
    if meta is not None:
        if header is None or meta.get("labels") == labels:
            labels = list(meta["labels"])
        else:
            raise ValueError(f"{sidecar_path(p)} names {meta.get('labels')}, {p} {labels}")
        rate = None if meta.get("rate") is None else float(meta["rate"])
        units = meta.get("units") or "mm"
    filled = _sidecar_filled(meta, labels, len(rows))
    return Markers(xyz, labels, rate, units, {"csv": {"header": header}}, filled)


def _write_csv(path: Path, m: Markers, xyz: np.ndarray) -> None:
    header = m.source.get("csv", {}).get("header")
    if not header:
        header = [f"{lab}_{a}" for lab in m.labels for a in "xyz"]
    with atomic_write(path) as fh:
        fh.write(",".join(header) + "\n")
        for row in xyz.reshape(xyz.shape[0], -1):
            fh.write(",".join("NaN" if np.isnan(v) else repr(float(v)) for v in row) + "\n")


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
