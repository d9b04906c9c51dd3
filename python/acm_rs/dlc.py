"""DeepLabCut files: manual labels (``CollectedData_*.csv/.h5``) of several cameras.

DeepLabCut stores a pandas DataFrame whose columns are a MultiIndex ``(scorer, bodyparts,
coords)`` or ``(scorer, individuals, bodyparts, coords)`` with ``coords`` in ``x, y`` (plus
``likelihood`` for predictions); rows are images (``labeled-data/<video>/img0123.png``, as one
index column or three) or frame numbers. CSV files carry the same header as 3 (4) rows. Reading
``.h5`` needs PyTables (``pip install tables``); CSV needs nothing extra.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["LabelSet", "read_dlc_table", "read_labels"]

_COORDS = {"x", "y", "likelihood"}


@dataclass
class LabelSet:
    """Labels of several cameras on a common frame axis.

    Attributes
    ----------
    points : numpy.ndarray, shape (n_cams, n_frames, n_bodyparts, 2)
        Pixels, NaN where a body part is not labelled.
    likelihood : numpy.ndarray or None, shape (n_cams, n_frames, n_bodyparts)
        Present for DeepLabCut predictions.
    frames : numpy.ndarray, shape (n_frames,)
        Frame number of each row (parsed from image names, else the row number).
    bodyparts : list of str
    """

    points: np.ndarray
    likelihood: np.ndarray | None
    frames: np.ndarray
    bodyparts: list[str]


def _frame_number(label: object, fallback: int) -> int:
    if isinstance(label, tuple):
        label = label[-1]
    if isinstance(label, int | np.integer):
        return int(label)
    digits = re.findall(r"\d+", Path(str(label)).stem)
    return int(digits[-1]) if digits else fallback


def _read_csv(path: Path):
    import pandas as pd

    try:
        raw = pd.read_csv(path, header=None, nrows=5, dtype=str, keep_default_na=False)
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    except pd.errors.ParserError as exc:
        raise ValueError(f"{path}: not a DeepLabCut CSV ({exc})") from None
    except pd.errors.EmptyDataError:
        raise ValueError(f"{path}: empty file, not a DeepLabCut CSV") from None
    first = [str(v).strip() for v in raw.iloc[:, 0]]
    n_header = 4 if len(first) > 1 and first[1] == "individuals" else 3
    if len(raw) < n_header or first[0] != "scorer":
        raise ValueError(f"{path}: not a DeepLabCut CSV (expected scorer/bodyparts/coords rows)")
    coords_row = [str(v).strip() for v in raw.iloc[n_header - 1]]
    n_index = next((i for i, v in enumerate(coords_row) if v in _COORDS), None)
    if n_index is None or n_index == 0:
        raise ValueError(f"{path}: not a DeepLabCut CSV (no x/y/likelihood header row)")
    _check_csv_rows(path, len(coords_row))
    return pd.read_csv(path, header=list(range(n_header)), index_col=list(range(n_index)))


def _check_csv_rows(path: Path, width: int) -> None:
    """Refuse a DeepLabCut CSV with a row of another width than the header (pandas would pad
    it with NaN): a cut last row or a damaged line, named by its line number."""
    import csv

    text = path.read_bytes()
    try:
        lines = text.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None
    for n, row in enumerate(csv.reader(lines), start=1):
        if row and len(row) != width:
            cut = n == len(lines) and not text.endswith((b"\n", b"\r"))
            raise ValueError(
                f"{path}: line {n} has {len(row)} fields, the header {width}"
                + ("; the last line is cut: the file is incomplete" if cut else "")
            )


def read_dlc_table(path: str | Path, individual: str | None = None):
    """Read one DeepLabCut ``.csv``/``.h5`` file.

    Parameters
    ----------
    path : path
    individual : str, optional
        For multi-animal files, which individual to keep (required if there are several).

    Returns
    -------
    points : numpy.ndarray, shape (n_rows, n_bodyparts, 2)
    likelihood : numpy.ndarray or None, shape (n_rows, n_bodyparts)
    frames : numpy.ndarray of int, shape (n_rows,)
    bodyparts : list of str
    """
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: no such file")
    if p.suffix.lower() in (".h5", ".hdf5"):
        import pandas as pd

        try:
            with pd.HDFStore(p, mode="r") as store:
                keys = store.keys()
                if not keys:
                    raise ValueError(f"{p}: an HDF5 file without a DeepLabCut table")
                key = "/df_with_missing" if "/df_with_missing" in keys else keys[0]
                df = store[key]
        except ImportError as exc:
            raise ValueError(
                f"{p}: reading DeepLabCut .h5 files needs PyTables (pip install tables), "
                "or read the .csv file DeepLabCut writes beside it"
            ) from exc
        except ValueError:
            raise
        except Exception as exc:  # PyTables/HDF5 errors on damaged or truncated files
            raise ValueError(
                f"{p}: damaged or incomplete HDF5 file ({type(exc).__name__}); use the .csv "
                "DeepLabCut writes beside it, or export the predictions again"
            ) from None
        if not hasattr(df, "columns") or not hasattr(df.columns, "nlevels"):
            raise ValueError(f"{p}: the HDF5 table is not a DeepLabCut DataFrame")
    elif p.suffix.lower() == ".csv":
        df = _read_csv(p)
    else:
        raise ValueError(f"{p}: expected a DeepLabCut .csv or .h5 file")
    cols = df.columns
    if cols.nlevels == 4:
        inds = list(dict.fromkeys(cols.get_level_values(1)))
        if individual is None and len(inds) > 1:
            raise ValueError(f"{p}: several individuals {inds}; choose one with individual=")
        ind = individual if individual is not None else inds[0]
        if ind not in inds:
            raise ValueError(f"{p}: no individual {ind!r}; individuals: {inds}")
        df = df.xs(ind, axis=1, level=1)
        cols = df.columns
    if cols.nlevels != 3:
        raise ValueError(f"{p}: unexpected column levels {cols.nlevels} (expected 3 or 4)")
    bodyparts = list(dict.fromkeys(cols.get_level_values(1)))
    n = len(df)
    points = np.full((n, len(bodyparts), 2), np.nan)
    has_lik = "likelihood" in set(cols.get_level_values(2))
    lik = np.full((n, len(bodyparts)), np.nan) if has_lik else None
    scorer = cols.get_level_values(0)[0]
    for j, bp in enumerate(bodyparts):
        name = "x"
        try:
            for c, name in enumerate(("x", "y")):
                points[:, j, c] = df[(scorer, bp, name)].to_numpy(dtype=float)
            if lik is not None:
                name = "likelihood"
                lik[:, j] = df[(scorer, bp, "likelihood")].to_numpy(dtype=float)
        except KeyError:
            raise ValueError(f"{p}: body part {bp!r} has no {name!r} column") from None
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{p}: body part {bp!r}, {name}: not numbers ({exc})") from None
    frames = np.array([_frame_number(lab, i) for i, lab in enumerate(df.index)], dtype=np.int64)
    if len(set(frames.tolist())) != len(frames):
        raise ValueError(f"{p}: two rows have the same frame number")
    return points, lik, frames, bodyparts


def read_labels(paths: Sequence[str | Path], individual: str | None = None) -> LabelSet:
    """Read the DeepLabCut label files of several cameras (one file per camera, rig order).

    Rows are matched across cameras by frame number (from the image names); a frame missing in
    one camera is NaN there. Body parts are matched by name (union, in first-seen order).

    Returns
    -------
    LabelSet
    """
    if not paths:
        raise ValueError("no label files given")
    tables = [read_dlc_table(p, individual) for p in paths]
    bodyparts = list(dict.fromkeys(bp for t in tables for bp in t[3]))
    frames = np.array(sorted({int(f) for t in tables for f in t[2]}), dtype=np.int64)
    index = {f: i for i, f in enumerate(frames.tolist())}
    pts = np.full((len(tables), len(frames), len(bodyparts), 2), np.nan)
    any_lik = any(t[1] is not None for t in tables)
    lik = np.full(pts.shape[:-1], np.nan) if any_lik else None
    for c, (p, lk, fr, bps) in enumerate(tables):
        rows = np.array([index[int(f)] for f in fr], dtype=int)
        cols = np.array([bodyparts.index(b) for b in bps], dtype=int)
        pts[c, rows[:, None], cols[None, :]] = p
        if lik is not None and lk is not None:
            lik[c, rows[:, None], cols[None, :]] = lk
    return LabelSet(pts, lik, frames, bodyparts)
