"""2D label files of several cameras: DeepLabCut (manual ``CollectedData_*.csv/.h5`` and
predictions), Lightning Pose CSVs (DeepLabCut's CSV layout) and SLEAP (``.slp``, analysis
``.h5``; see :mod:`acm_rs.sleap`).

DeepLabCut stores a pandas DataFrame whose columns are a MultiIndex ``(scorer, bodyparts,
coords)`` or ``(scorer, individuals, bodyparts, coords)`` with ``coords`` in ``x, y`` (plus
``likelihood`` for predictions); rows are images (``labeled-data/<video>/img0123.png``, as one
index column or three) or frame numbers. CSV files carry the same header as 3 (4) rows. Reading
``.h5`` needs PyTables (``pip install tables``); CSV needs nothing extra.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .labels import default_pcutoff
from .sleap import is_sleap_analysis, read_sleap_analysis, read_slp

__all__ = ["LabelSet", "concat_labels", "read_dlc_table", "read_labels", "shift_labels"]

_COORDS = {"x", "y", "z", "likelihood"}


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
    sources : list of str or None
        Per camera, the tool that wrote its file ("deeplabcut", "sleap"; None: no file):
        its scores decide the default likelihood cutoff (:meth:`default_pcutoff`).
    """

    points: np.ndarray
    likelihood: np.ndarray | None
    frames: np.ndarray
    bodyparts: list[str]
    sources: list[str | None] = field(default_factory=list)

    def default_pcutoff(self) -> tuple[float, str]:
        """The likelihood cutoff for these files' scores and why
        (:func:`acm_rs.labels.default_pcutoff`: 0.9 for DeepLabCut, 0.2 for SLEAP)."""
        return default_pcutoff(self.sources)

    def resolve_pcutoff(self, pcutoff: float | str | None) -> tuple[float, str]:
        """``pcutoff`` as given (a number), or for None/"auto" the cutoff of the files'
        source, each with a phrase for the log."""
        if pcutoff is None or pcutoff == "auto":
            return self.default_pcutoff()
        return float(pcutoff), "given"


def load_dlc_config(path: str | Path, key: str) -> dict:
    """A DeepLabCut ``config.yaml`` as a dict; refused in one line when it is not YAML or has
    no ``key`` (e.g. ``"scorer"``, ``"bodyparts"``)."""
    import yaml

    p = Path(path)
    try:
        doc = yaml.safe_load(p.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise ValueError(f"{p}: invalid YAML: {exc}") from None
    if not isinstance(doc, dict) or key not in doc:
        raise ValueError(f"{p}: not a DeepLabCut config.yaml (no {key!r})")
    return doc


def label_source(path: str | Path) -> str:
    """The tool that wrote a 2D label file: "sleap" for ``.slp`` and SLEAP analysis
    ``.h5``, else "deeplabcut" (DeepLabCut's tables, also written by Lightning Pose)."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".slp" or (suffix in (".h5", ".hdf5") and p.exists() and is_sleap_analysis(p)):
        return "sleap"
    return "deeplabcut"


def _frame_number(label: object, fallback: int) -> int:
    if isinstance(label, tuple):
        label = label[-1]
    if isinstance(label, int | np.integer):
        return int(label)
    digits = re.findall(r"\d+", Path(str(label)).stem)
    return int(digits[-1]) if digits else fallback


def _read_csv(path: Path):
    """A DeepLabCut CSV as the DataFrame DeepLabCut wrote (MultiIndex columns, 1 or 3 index
    columns). The 3 (4) header rows are parsed here and the data rows by pandas without a
    header: pandas' multi-row-header parsing takes an entirely empty first data row (a frame
    without any detection) for a row of index names and drops it, shifting every frame."""
    import pandas as pd

    text, lines = _csv_lines(path)
    rows = _parse(path, lines[:6])  # the header rows and the first data rows
    if not rows:
        raise ValueError(f"{path}: empty file, not a DeepLabCut CSV")
    first = [r[0].strip() if r else "" for r in rows[:4]]
    n_header = 4 if len(first) > 1 and first[1] == "individuals" else 3
    if len(rows) < n_header or first[0] != "scorer":
        raise ValueError(f"{path}: not a DeepLabCut CSV (expected scorer/bodyparts/coords rows)")
    coords_row = [v.strip() for v in rows[n_header - 1]]
    n_index = next((i for i, v in enumerate(coords_row) if v in _COORDS), None)
    if n_index is None or n_index == 0:
        raise ValueError(f"{path}: not a DeepLabCut CSV (no x/y/likelihood header row)")
    _check_csv_rows(path, text, lines, len(coords_row))
    columns = pd.MultiIndex.from_arrays(
        [rows[h][n_index:] for h in range(n_header)], names=[rows[h][0] for h in range(n_header)]
    )
    skip = n_header
    if len(rows) > n_header and _is_index_names(rows[n_header], n_index):
        skip += 1  # pandas writes a row of index names when the index has names
    if not any(line.strip() for line in lines[skip:]):
        return pd.DataFrame(columns=columns)
    data = pd.read_csv(path, header=None, skiprows=skip)
    index = data.iloc[:, :n_index]
    df = data.iloc[:, n_index:]
    df.columns = columns
    df.index = pd.Index(index.iloc[:, 0]) if n_index == 1 else pd.MultiIndex.from_frame(index)
    return df


def _is_index_names(row: list[str], n_index: int) -> bool:
    """A row of index names (pandas ``to_csv`` of a named index) rather than a frame without
    detections: every data field empty and index fields without a digit (a frame number or
    image name always has one)."""
    return (
        not any(v.strip() for v in row[n_index:])
        and any(v.strip() for v in row[:n_index])
        and not any(c.isdigit() for v in row[:n_index] for c in v)
    )


def _csv_lines(path: Path) -> tuple[bytes, list[str]]:
    text = path.read_bytes()
    try:
        return text, text.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file (byte {exc.start} is not UTF-8)") from None


def _parse(path: Path, lines: list[str]) -> list[list[str]]:
    import csv

    try:
        return list(csv.reader(lines))
    except csv.Error as exc:
        raise ValueError(f"{path}: not a DeepLabCut CSV ({exc})") from None


def _check_csv_rows(path: Path, text: bytes, lines: list[str], width: int) -> None:
    """Refuse a DeepLabCut CSV with a row of another width than the header (pandas would pad
    it with NaN): a cut last row or a damaged line, named by its line number."""
    import csv

    for n, row in enumerate(csv.reader(lines), start=1):
        if row and len(row) != width:
            cut = n == len(lines) and not text.endswith((b"\n", b"\r"))
            raise ValueError(
                f"{path}: line {n} has {len(row)} fields, the header {width}"
                + ("; the last line is cut: the file is incomplete" if cut else "")
            )


def read_dlc_table(path: str | Path, individual: str | None = None):
    """Read one 2D label file: DeepLabCut or Lightning Pose ``.csv``, DeepLabCut ``.h5``
    (PyTables), SLEAP analysis ``.h5`` or SLEAP ``.slp`` (both read with h5py).

    Parameters
    ----------
    path : path
    individual : str, optional
        For multi-animal files, which individual (DeepLabCut) or track (SLEAP) to keep
        (required if there are several).

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
    if p.suffix.lower() == ".slp":
        return read_slp(p, individual)
    if p.suffix.lower() in (".h5", ".hdf5") and is_sleap_analysis(p):
        return read_sleap_analysis(p, individual)
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
        raise ValueError(f"{p}: expected a DeepLabCut/Lightning Pose .csv or .h5, or SLEAP .slp")
    cols = df.columns
    if cols.nlevels == 4:
        inds = list(dict.fromkeys(cols.get_level_values(1)))
        # DeepLabCut puts "unique body parts" (not part of any animal) under "single"
        animals = [i for i in inds if i != "single"] or inds
        if individual is None and len(animals) > 1:
            raise ValueError(
                f"{p}: several individuals {animals}; choose one with individual= "
                "(project.individual in config.toml, --individual on the command line)"
            )
        ind = individual if individual is not None else animals[0]
        if ind not in inds:
            raise ValueError(f"{p}: no individual {ind!r}; individuals: {inds}")
        df = df.xs(ind, axis=1, level=1)
        cols = df.columns
    if cols.nlevels != 3:
        raise ValueError(f"{p}: unexpected column levels {cols.nlevels} (expected 3 or 4)")
    if "z" in set(cols.get_level_values(-1)):
        # DeepLabCut 3D's triangulate writes <video>..._3D.h5/.csv with coords x, y, z
        raise ValueError(
            f"{p}: a 3D file (coords x, y, z, as DeepLabCut 3D's triangulate writes), not 2D "
            "labels; give each camera's 2D predictions (<video>DLC_<network>.h5 or .csv)"
        )
    # coordinate columns only: Lightning Pose adds a "set" column, EKS "x_ens_var" etc.
    xs = [c for c in cols if c[2] == "x"]
    if not xs:
        raise ValueError(f"{p}: no x/y columns")
    scorer = xs[0][0]
    bodyparts = list(dict.fromkeys(c[1] for c in xs if c[0] == scorer))
    n = len(df)
    points = np.full((n, len(bodyparts), 2), np.nan)
    has_lik = (scorer, bodyparts[0], "likelihood") in set(cols)
    lik = np.full((n, len(bodyparts)), np.nan) if has_lik else None
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


def read_labels(paths: Sequence[str | Path | None], individual: str | None = None) -> LabelSet:
    """Read the 2D label files of several cameras (one file per camera, rig order; None for
    a camera without labels, which is then NaN).

    Rows are matched across cameras by frame number (from the image names); a frame missing in
    one camera is NaN there. Body parts are matched by name (union, in first-seen order).

    Returns
    -------
    LabelSet
    """
    if not paths or all(p is None for p in paths):
        raise ValueError("no label files given")
    tables = [read_dlc_table(p, individual) if p is not None else None for p in paths]
    present = [t for t in tables if t is not None]
    bodyparts = list(dict.fromkeys(bp for t in present for bp in t[3]))
    frames = np.array(sorted({int(f) for t in present for f in t[2]}), dtype=np.int64)
    index = {f: i for i, f in enumerate(frames.tolist())}
    pts = np.full((len(tables), len(frames), len(bodyparts), 2), np.nan)
    any_lik = any(t[1] is not None for t in present)
    lik = np.full(pts.shape[:-1], np.nan) if any_lik else None
    for c, table in enumerate(tables):
        if table is None:
            continue
        p, lk, fr, bps = table
        rows = np.array([index[int(f)] for f in fr], dtype=int)
        cols = np.array([bodyparts.index(b) for b in bps], dtype=int)
        pts[c, rows[:, None], cols[None, :]] = p
        if lik is not None:
            # manual labels (no likelihood) mixed with predictions: a label counts as certain
            lk = lk if lk is not None else np.where(np.isfinite(p[..., 0]), 1.0, np.nan)
            lik[c, rows[:, None], cols[None, :]] = lk
    sources = [label_source(p) if p is not None else None for p in paths]
    return LabelSet(pts, lik, frames, bodyparts, sources)


def shift_labels(labels: LabelSet, offsets: np.ndarray | None) -> LabelSet:
    """Labels of cropped videos in the calibrated (full) image: ``points[c] + offsets[c]``.

    Anipose's convention (``[cameras.<name>] offset = [x, y, ...]``, triangulate.py): a
    video cropped at ``(x, y)`` has its 2D points shifted by ``(x, y)`` before
    triangulation; the calibration stays that of the full image.

    Parameters
    ----------
    labels : LabelSet
    offsets : array_like, shape (n_cams, 2), or None
        Pixels; None returns ``labels`` unchanged.
    """
    if offsets is None:
        return labels
    off = np.asarray(offsets, dtype=float)
    if off.shape != (labels.points.shape[0], 2) or not np.isfinite(off).all():
        raise ValueError(
            f"crop offsets must be finite, shape ({labels.points.shape[0]}, 2), got {off.shape}"
        )
    pts = labels.points + off[:, None, None, :]
    return LabelSet(pts, labels.likelihood, labels.frames, labels.bodyparts, labels.sources)


def concat_labels(sets: Sequence[LabelSet]) -> LabelSet:
    """Label sets of several recordings (same cameras) one after the other.

    Body parts are matched by name (union); ``frames`` keeps each recording's frame numbers,
    so it may repeat. A recording without likelihoods (manual labels) gets likelihood 1 where
    labelled when another has them.
    """
    if not sets:
        raise ValueError("no label sets")
    if len(sets) == 1:
        return sets[0]
    n_cams = {s.points.shape[0] for s in sets}
    if len(n_cams) != 1:
        raise ValueError(f"label sets of different camera counts {sorted(n_cams)}")
    bodyparts = list(dict.fromkeys(bp for s in sets for bp in s.bodyparts))
    any_lik = any(s.likelihood is not None for s in sets)
    pts, liks = [], []
    for s in sets:
        cols = [bodyparts.index(b) for b in s.bodyparts]
        p = np.full(s.points.shape[:2] + (len(bodyparts), 2), np.nan)
        p[:, :, cols] = s.points
        pts.append(p)
        if any_lik:
            lk = np.full(p.shape[:-1], np.nan)
            src = s.likelihood
            if src is None:
                src = np.where(np.isfinite(s.points[..., 0]), 1.0, np.nan)
            lk[:, :, cols] = src
            liks.append(lk)
    return LabelSet(
        np.concatenate(pts, axis=1),
        np.concatenate(liks, axis=1) if any_lik else None,
        np.concatenate([s.frames for s in sets]),
        bodyparts,
        # per camera, the sources of all recordings ("deeplabcut+sleap" if they differ)
        [
            "+".join(sorted({s.sources[c] for s in sets if c < len(s.sources) and s.sources[c]}))
            or None
            for c in range(pts[0].shape[0])
        ],
    )
