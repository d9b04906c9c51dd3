"""Marker files: C3D (ezc3d), TRC and CSV, read into ``(n_frames, n_markers, 3)`` arrays.

Every writer goes through :func:`acm_rs._io.atomic_write`, so a failed write never leaves a
partial file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .._io import atomic_write

__all__ = ["Markers", "read", "read_c3d", "read_csv", "read_trc", "write", "write_like"]


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
        Frame rate in Hz.
    units : str
        Length unit (``"mm"`` for C3D and most TRC files).
    source : dict
        Format-specific data needed to write a faithful copy (the ezc3d object, TRC header).
    """

    xyz: np.ndarray
    labels: list[str]
    rate: float | None = None
    units: str = "mm"
    source: dict[str, Any] = field(default_factory=dict)


def read_c3d(path: str | os.PathLike[str]) -> Markers:
    """Read a C3D file with ezc3d.

    Missing markers (NaN, or a negative residual) become NaN.

    Parameters
    ----------
    path : path-like
        The ``.c3d`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_markers, 3) in the file's POINT:UNITS.

    Raises
    ------
    ValueError
        If the file cannot be parsed as C3D.
    """
    import ezc3d

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"C3D file not found: {p}")
    try:
        c = ezc3d.c3d(str(p))
        pts = np.asarray(c["data"]["points"], dtype=np.float64)
    except Exception as exc:  # ezc3d raises RuntimeError/IndexError on corrupt files
        raise ValueError(f"cannot read C3D file {p}: {exc}") from None
    xyz = pts[:3].transpose(2, 1, 0).copy()
    meta = c["data"].get("meta_points", {})
    res = meta.get("residuals") if isinstance(meta, dict) else None
    if res is not None:
        res = np.asarray(res)
        if res.shape == (1, xyz.shape[1], xyz.shape[0]):
            xyz[res[0].T < 0] = np.nan
    point = c["parameters"]["POINT"]
    labels = [str(s) for s in point["LABELS"]["value"]][: xyz.shape[1]]
    rate = float(np.asarray(point["RATE"]["value"]).ravel()[0])
    units = point.get("UNITS", {}).get("value", ["mm"])
    return Markers(xyz, labels, rate, str(units[0]) if len(units) else "mm", {"c3d": c})


def _write_c3d(path: Path, m: Markers, xyz: np.ndarray) -> None:
    import ezc3d

    c = m.source.get("c3d")
    if c is None:
        c = ezc3d.c3d()
        c["parameters"]["POINT"]["RATE"]["value"] = [float(m.rate or 100.0)]
        c["parameters"]["POINT"]["LABELS"]["value"] = list(m.labels)
        c["parameters"]["POINT"]["UNITS"]["value"] = [m.units]
    pts = np.ones((4, xyz.shape[1], xyz.shape[0]))
    pts[:3] = xyz.transpose(2, 1, 0)
    c["data"]["points"] = pts
    # Residual 0 = valid (filled); -1 where still missing. Drop stale meta arrays.
    if "meta_points" in c["data"]:
        del c["data"]["meta_points"]
    # ezc3d writes by path and needs a .c3d suffix: write a temporary .c3d next to the target,
    # then rename it over the target (the same guarantee as atomic_write).
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".c3d", dir=path.parent)
    os.close(fd)
    try:
        c.write(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def read_trc(path: str | os.PathLike[str]) -> Markers:
    """Read a TRC file (5 header lines, ``Frame#``, ``Time``, x y z per marker).

    Empty fields are missing values (NaN).

    Parameters
    ----------
    path : path-like
        The ``.trc`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_markers, 3); ``rate`` from DataRate, ``units`` from Units.
    """
    lines = Path(path).read_text().splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise ValueError(f"{path}: not a TRC file (no PathFileType header)")
    keys = lines[1].split("\t")
    vals = lines[2].split("\t")
    hdr = dict(zip(keys, vals, strict=False))
    labels = [s.strip() for s in lines[3].split("\t")[2:] if s.strip()]
    d = 3 * len(labels)
    rows, frames, times = [], [], []
    for n, line in enumerate(lines[5:], start=6):
        if not line.strip():
            continue
        f = line.split("\t")
        if len(f) > d + 2:
            raise ValueError(f"{path}: line {n} has {len(f)} fields, expected <= {d + 2}")
        f += [""] * (d + 2 - len(f))
        try:
            rows.append([float(v) if v.strip() else np.nan for v in f[2:]])
        except ValueError as exc:
            raise ValueError(f"{path}: line {n}: {exc}") from None
        frames.append(f[0])
        times.append(f[1])
    if not rows:
        raise ValueError(f"{path}: no data rows")
    xyz = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(labels), 3)
    rate = float(hdr["DataRate"]) if hdr.get("DataRate", "").strip() else None
    units = hdr.get("Units", "mm").strip() or "mm"
    return Markers(xyz, labels, rate, units, {"trc": {"frames": frames, "times": times}})


def _write_trc(path: Path, m: Markers, xyz: np.ndarray) -> None:
    n_frames, n_markers, _ = xyz.shape
    rate = m.rate or 100.0
    src = m.source.get("trc", {})
    frames = src.get("frames") or [str(i + 1) for i in range(n_frames)]
    times = src.get("times") or [f"{i / rate:.6f}" for i in range(n_frames)]
    with atomic_write(path) as fh:
        fh.write(f"PathFileType\t4\t(X/Y/Z)\t{path.name}\n")
        fh.write(
            "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
            "OrigDataStartFrame\tOrigNumFrames\n"
        )
        fh.write(
            f"{rate:g}\t{rate:g}\t{n_frames}\t{n_markers}\t{m.units}\t{rate:g}\t1\t{n_frames}\n"
        )
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
    the fields themselves); empty fields and ``NaN`` are missing.

    Parameters
    ----------
    path : path-like
        The ``.csv`` file.

    Returns
    -------
    Markers
        ``xyz`` of shape (n_frames, n_columns / 3, 3).
    """
    text = Path(path).read_text().splitlines()
    text = [ln for ln in text if ln.strip()]
    if not text:
        raise ValueError(f"{path}: empty CSV file")
    header = None
    first = text[0].split(",")

    def _num(s: str) -> bool:
        try:
            float(s) if s.strip() else None
            return True
        except ValueError:
            return False

    if not all(_num(f) for f in first):
        header = [f.strip() for f in first]
        text = text[1:]
    rows = []
    for n, line in enumerate(text, start=2 if header else 1):
        f = line.split(",")
        try:
            rows.append([float(v) if v.strip() else np.nan for v in f])
        except ValueError as exc:
            raise ValueError(f"{path}: line {n}: {exc}") from None
    widths = {len(r) for r in rows}
    if len(widths) != 1:
        raise ValueError(f"{path}: rows have different numbers of fields {sorted(widths)}")
    d = widths.pop()
    if d % 3:
        raise ValueError(f"{path}: {d} columns is not a multiple of 3 (x, y, z per marker)")
    xyz = np.asarray(rows, dtype=np.float64).reshape(len(rows), d // 3, 3)
    if header and len(header) == d:
        labels = [h[:-2] if h.lower().endswith(("_x", ".x")) else h for h in header[::3]]
    else:
        labels = [f"M{i:02d}" for i in range(d // 3)]
    return Markers(xyz, labels, None, "mm", {"csv": {"header": header}})


def _write_csv(path: Path, m: Markers, xyz: np.ndarray) -> None:
    header = m.source.get("csv", {}).get("header")
    with atomic_write(path) as fh:
        if header:
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


def write_like(path: str | os.PathLike[str], m: Markers, xyz: np.ndarray) -> None:
    """Write ``xyz`` with the labels, rate and metadata of ``m`` (format from the extension).

    A C3D read with :func:`read_c3d` keeps all its parameters (labels, rate, units, analogs);
    only the point data change.

    Parameters
    ----------
    path : path-like
        Output ``.c3d``, ``.trc`` or ``.csv`` (written atomically).
    m : Markers
        The source of labels and metadata.
    xyz : ndarray, shape (n_frames, n_markers, 3)
        The values to write (NaN = missing).
    """
    p = Path(path)
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.shape[1:] != m.xyz.shape[1:] or xyz.ndim != 3:
        raise ValueError(f"xyz must have shape (n, {m.xyz.shape[1]}, 3), got {xyz.shape}")
    ext = p.suffix.lower()
    if ext == ".c3d":
        if xyz.shape[0] != m.xyz.shape[0] and "c3d" in m.source:
            raise ValueError("a C3D copy must keep the number of frames")
        _write_c3d(p, m, xyz)
    elif ext == ".trc":
        _write_trc(p, m, xyz)
    elif ext == ".csv":
        _write_csv(p, m, xyz)
    else:
        raise ValueError(f"unsupported output {p}; expected .c3d, .trc or .csv")


def write(path: str | os.PathLike[str], xyz: np.ndarray, labels: list[str], rate: float) -> None:
    """Write new marker data (no source file) as C3D, TRC or CSV.

    Parameters
    ----------
    path : path-like
        Output file; the extension selects the format.
    xyz : ndarray, shape (n_frames, n_markers, 3)
        Positions in mm (NaN = missing).
    labels : list of str
        Marker names.
    rate : float
        Frame rate in Hz.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 3 or xyz.shape[2] != 3 or len(labels) != xyz.shape[1]:
        raise ValueError("xyz must have shape (n_frames, len(labels), 3)")
    write_like(path, Markers(xyz, list(labels), rate, "mm", {}), xyz)
