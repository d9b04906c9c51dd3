"""TRC and marker CSV files read and written in blocks (issue 27 item 14).

The readers used to decode a whole file, split it into lines and parse every field with
``float()`` into Python lists: 200,000 frames x 41 markers took 2.1 GB and 10-33 s to read.
Here a file is read in blocks of whole lines (:data:`BLOCK_BYTES`) and the values of a block go
into one preallocated array, so memory is that array plus one block.

Each block is parsed in one of two ways, with the same result:

* **Fast**: pandas' C parser (``sep`` tab or comma, every value column ``float64``). It is used
  only for a block it is known to read exactly as ``float()``: ASCII of the characters numbers
  are written with (:data:`_TRC_CHARS`, :data:`_CSV_CHARS`; no ``True``/``False``, which pandas
  would turn into 1 and 0), ``\\n`` or ``\\r\\n`` line ends, every line's field count right
  (counted here with NumPy: pandas silently drops extra fields) and no blank line. pandas >= 3.1
  converts with fast_float, older versions with ``float_precision="round_trip"`` (CPython's own
  ``PyOS_string_to_double``): both round correctly, as ``float()`` does.
* **Exact**: the old per-line reader (``str.splitlines``, ``float()`` per field) for any other
  block: non-ASCII text, unusual spellings (``-nan``, ``1_000``, Unicode digits), blank or
  whitespace lines, lone ``\\r`` line ends, bad numbers, wrong field counts and the file's last
  line. Its errors name the line, as before.

The writers write :data:`WRITE_ROWS` rows at a time, each value as Python's ``repr`` (the
shortest text that reads back to the same float) formatted in Rust (``gapfill_format_rows``:
Rust's shortest digits, with exact halfway cases rounded to the even digit as CPython's dtoa
does; ``repr`` itself took half the time of gap filling a long TRC).
"""

from __future__ import annotations

import csv
import functools
import io
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Bytes of whole lines per block (a line longer than this makes a longer block).
BLOCK_BYTES = 8 * 2**20
#: Rows formatted per write.
WRITE_ROWS = 4096

_NUMBER = b"0123456789.+-eE naNiIfFtTyY"  # digits, signs, exponents, nan, inf, infinity
_TRC_CHARS = _NUMBER + b"\t\r\n"
_CSV_CHARS = _NUMBER + b",\r\n"
_NA = ["", "NaN", "nan", "NAN"]  # read as float("nan") by both parsers


@functools.cache
def _pandas_exact() -> dict:
    """The read_csv option that makes pandas round as float() does (see module docstring)."""
    import pandas as pd

    major, minor = (int(x) for x in pd.__version__.split(".")[:2])
    return {} if (major, minor) >= (3, 1) else {"float_precision": "round_trip"}


@dataclass
class _Block:
    data: bytes
    offset: int  # of its first byte in the file
    line: int  # number (1-based) of its first line
    last: bool  # the file's last block (which may end without a line end)


def _raw_blocks(fh, offset: int) -> Iterator[tuple[bytes, int, bool]]:
    """(bytes, offset, last) blocks of whole lines: each ends with ``\\n`` or ``\\r`` (never
    between the two of a ``\\r\\n``) except the last, which holds the rest of the file."""
    buf, nxt = b"", fh.read(BLOCK_BYTES)
    while True:
        buf, nxt = buf + nxt, fh.read(BLOCK_BYTES)
        if not nxt:
            yield buf, offset, True
            return
        if buf.endswith(b"\r") and nxt.startswith(b"\n"):
            buf, nxt = buf + b"\n", nxt[1:]
        cut = max(buf.rfind(b"\n"), buf.rfind(b"\r")) + 1
        if cut:  # else a line longer than the block: read on
            yield buf[:cut], offset, False
            offset += cut
            buf = buf[cut:]


class _Reader:
    """Blocks of a text file, with the decoding checks of the old whole-file reader."""

    def __init__(self, p: Path, kind: str):
        if not p.is_file():
            raise ValueError(f"{kind} file not found: {p}")
        self.p, self.kind = p, kind
        self._fh = open(p, "rb")  # noqa: SIM115 (closed by close())
        self._it = _raw_blocks(self._fh, 0)
        self._back: _Block | None = None
        self.line = 1

    def close(self) -> None:
        self._fh.close()

    def decode(self, b: _Block) -> str:
        try:
            return b.data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ValueError(
                f"{self.p}: not a text {self.kind} file (byte {b.offset + exc.start} is not "
                "UTF-8); is it a binary file or a different format?"
            ) from None

    def next(self) -> _Block | None:
        """The next block (numbered from the lines before it), None after the last."""
        if self._back is not None:
            b, self._back = self._back, None
            return b
        try:
            data, offset, last = next(self._it)
        except StopIteration:
            return None
        return _Block(data, offset, 0, last)

    def head(self, enough) -> tuple[list[str], _Block]:
        """The first lines (with their ends) of the blocks to come, merged until
        ``enough(lines)`` or the end of the file; returns them and the merged block."""
        b = self.next()
        while True:
            lines = self.decode(b).splitlines(keepends=True)
            if b.last or enough(lines):
                return lines, b
            c = self.next()
            b = _Block(b.data + c.data, b.offset, 0, c.last)

    def consume(self, b: _Block, lines: list[str], k: int) -> None:
        """Take the first ``k`` of ``lines`` (the start of ``b``); the rest of ``b`` comes
        next."""
        used = len("".join(lines[:k]).encode("utf-8"))
        self.line += k
        self._back = _Block(b.data[used:], b.offset + used, 0, b.last)

    def blocks(self) -> Iterator[_Block]:
        """The remaining blocks, each with the number of its first line."""
        while (b := self.next()) is not None:
            b.line = self.line
            yield b
            if b.last:
                return


class _Rows:
    """A growing ``(n, width)`` float64 array, filled block by block; sized at the first
    block for ``expected`` rows (if given and plausible) or as many as the file's size and
    the first block's line length suggest."""

    def __init__(self, p: Path, width: int, expected: int = 0):
        self.size, self.width, self.expected = p.stat().st_size, width, expected
        self.a: np.ndarray | None = None
        self.n = 0

    def _allocate(self, first: bytes) -> None:
        per_byte = (first.count(b"\n") + first.count(b"\r") + 1) / max(len(first), 1)
        guess = int(self.size * per_byte * 1.05) + 16
        n = self.expected if 0 < self.expected <= 2 * guess else guess
        self.a = np.empty((n, self.width))

    def add(self, v: np.ndarray, data: bytes) -> None:
        if self.a is None:
            self._allocate(data)
        need = self.n + len(v)
        if need > len(self.a):
            grown = np.empty((max(need, len(self.a) * 5 // 4), self.a.shape[1]))
            grown[: self.n] = self.a[: self.n]
            self.a = grown
        self.a[self.n : need] = v
        self.n = need

    def values(self) -> np.ndarray:
        return np.empty((0, self.width)) if self.a is None else self.a[: self.n]


def _line_ends(data: bytes) -> np.ndarray | None:
    """Positions of the line ends of a block of ``\\n`` or ``\\r\\n`` lines ending with one;
    None for any other block."""
    if not data.endswith(b"\n") or (b"\r" in data and data.count(b"\r") != data.count(b"\r\n")):
        return None
    return np.flatnonzero(np.frombuffer(data, np.uint8) == 10)


def _fields(data: bytes, ends: np.ndarray, sep: int) -> np.ndarray:
    """Fields per line (separators + 1)."""
    is_sep = (np.frombuffer(data, np.uint8) == sep).view(np.uint8)
    starts = np.concatenate([[0], ends[:-1] + 1])
    return np.add.reduceat(is_sep, starts, dtype=np.int64) + 1


def _pandas(data: bytes, sep: str, width: int, numbers: range):
    """The block parsed by pandas (columns in ``numbers`` as float64, the others as text), or
    None if pandas raised or warned."""
    import pandas as pd

    names = list(range(width))
    dtype = {c: (np.float64 if c in numbers else str) for c in names}
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            df = pd.read_csv(
                io.BytesIO(data), sep=sep, header=None, names=names, index_col=False,
                dtype=dtype, keep_default_na=False,
                na_values={c: _NA for c in numbers}, skip_blank_lines=False,
                quoting=csv.QUOTE_NONE, engine="c", **_pandas_exact(),
            )  # fmt: skip
    except Exception:  # any doubt: the exact reader decides (and names the line)
        return None
    return None if caught else df


def _float(v: str) -> float:
    return float(v) if v.strip() else np.nan  # an empty or blank field is missing


# ---------------------------------------------------------------------------------------- TRC


@dataclass
class TrcText:
    """What a TRC file holds: header lines 1-5, values ``(n_frames, 3 x n_markers)`` and the
    Frame# and Time fields as written."""

    header: list[str]
    values: np.ndarray
    frames: list[str]
    times: list[str]


def _trc_fast(data: bytes, d: int):
    if data.translate(None, _TRC_CHARS) or (ends := _line_ends(data)) is None:
        return None
    width = max(int(_fields(data, ends, 9).max()), d + 2)
    df = _pandas(data, "\t", width, range(2, d + 2))
    if df is None or len(df) != len(ends):
        return None
    for c in range(d + 2, width):  # fields after the last Z: empty (a trailing tab) or refused
        if not (df[c].fillna("").str.strip() == "").all():
            return None  # the exact reader refuses the line
    frames, times = df[0].fillna(""), df[1].fillna("")
    if ((frames.str.strip() == "") & (times.str.strip() == "")).any():
        return None  # maybe a blank line, which is skipped
    return df.iloc[:, 2 : d + 2].to_numpy(np.float64), frames.tolist(), times.tolist()


def _trc_exact(p: Path, text: str, first: int, d: int, last: bool):
    """The old per-line reader on one block (``last``: the file's last block)."""
    lines = text.splitlines()
    cut = last and bool(text) and not text.endswith(("\n", "\r"))
    rows, frames, times = [], [], []
    for i, line in enumerate(lines):
        n = first + i
        if not line.strip():
            continue
        f = line.split("\t")
        if len(f) > d + 2:
            # OpenSim and Motion Analysis end lines with a tab: empty fields after the last Z
            if any(x.strip() for x in f[d + 2 :]):
                raise ValueError(
                    f"{p}: line {n} has {len(f)} fields, expected <= {d + 2} (2 + 3 per marker "
                    "named on line 4; only empty fields may follow)"
                )
            f = f[: d + 2]
        if cut and i == len(lines) - 1:
            raise ValueError(
                f"{p}: the last line ({n}) has no line end ({len(f)} of {d + 2} fields): the "
                "file may be cut; if it is complete, end it with a line break"
            )
        f += [""] * (d + 2 - len(f))
        try:
            rows.append([_float(v) for v in f[2:]])
        except ValueError as exc:
            raise ValueError(f"{p}: line {n}: {exc}") from None
        frames.append(f[0])
        times.append(f[1])
    return np.array(rows, dtype=np.float64).reshape(len(rows), d), frames, times, len(lines)


def read_trc_text(p: Path, expected=None) -> TrcText:
    """Read a TRC file's header and data in blocks (module docstring).

    Parameters
    ----------
    p : Path
        The ``.trc`` file.
    expected : callable, optional
        ``expected(header_lines) -> int``: the number of frames the header declares (to size
        the array; any number of rows is still read).

    Returns
    -------
    TrcText
        ``values`` of shape (n_frames, 3 x n_markers), n_markers from header line 4.
    """
    rd = _Reader(p, "TRC")
    try:
        lines, b = rd.head(lambda ls: len(ls) > 5)
        header = "".join(lines[:5]).splitlines()
        if len(header) < 5 or not header[0].startswith("PathFileType"):
            raise ValueError(f"{p}: not a TRC file (no PathFileType header)")
        labels = [s.strip() for s in header[3].split("\t")[2:] if s.strip()]
        if not labels:
            raise ValueError(f"{p}: line 4 names no markers")
        d = 3 * len(labels)
        rd.consume(b, lines, 5)
        rows = _Rows(p, d, expected(header) if expected else 0)
        frames: list[str] = []
        times: list[str] = []
        for blk in rd.blocks():
            got = None if blk.last else _trc_fast(blk.data, d)
            if got is None:
                *got, n_lines = _trc_exact(p, rd.decode(blk), blk.line, d, blk.last)
            else:
                n_lines = len(got[1])
            rows.add(got[0], blk.data)
            frames += got[1]
            times += got[2]
            rd.line += n_lines
    finally:
        rd.close()
    return TrcText(header, rows.values(), frames, times)


# ---------------------------------------------------------------------------------------- CSV


@dataclass
class CsvText:
    """What a marker CSV holds: its header fields (None without a header) and values
    ``(n_frames, n_columns)``."""

    header: list[str] | None
    values: np.ndarray


def _is_number(s: str) -> bool:
    try:
        _float(s)
        return True
    except ValueError:
        return False


def _csv_fast(data: bytes, width: int):
    if width < 2 or data.translate(None, _CSV_CHARS) or (ends := _line_ends(data)) is None:
        return None
    if (_fields(data, ends, 44) != width).any():
        return None  # a blank line (skipped) or a row of another width (refused)
    df = _pandas(data, ",", width, range(width))
    if df is None or len(df) != len(ends):
        return None
    return df.to_numpy(np.float64)


def _csv_exact(p: Path, text: str, first: int, width: int, last: bool):
    """The old per-line reader on one block; also returns the number and field count of its
    last non-blank line (None if none) and its number of lines."""
    lines = text.splitlines()
    cut = last and bool(text) and not text.endswith(("\n", "\r"))
    final = max((i for i, ln in enumerate(lines) if ln.strip()), default=None) if cut else None
    rows, seen = [], None
    for i, line in enumerate(lines):
        n = first + i
        if not line.strip():
            continue
        f = line.split(",")
        seen = (n, len(f))
        if i == final and len(f) == width:
            raise ValueError(
                f"{p}: the last line ({n}) has no line end: the file may be cut; if it is "
                "complete, end it with a line break"
            )
        if len(f) != width:
            raise ValueError(
                f"{p}: line {n} has {len(f)} fields, expected {width}"
                + ("; the last line is cut: the file is incomplete" if i == final else "")
            )
        try:
            rows.append([_float(v) for v in f])
        except ValueError as exc:
            raise ValueError(f"{p}: line {n}: {exc}") from None
    values = np.array(rows, dtype=np.float64).reshape(len(rows), width)
    return values, seen, len(lines)


def read_csv_text(p: Path) -> CsvText:
    """Read a marker CSV in blocks (module docstring): a first non-blank line with a
    non-numeric field is the header; every row must have the width of the header (or of the
    first row).

    Returns
    -------
    CsvText
        ``values`` of shape (n_frames, n_columns).
    """
    rd = _Reader(p, "CSV")
    try:

        def two(ls: list[str]) -> bool:
            return sum(1 for ln in ls if ln.strip()) >= 2

        lines, b = rd.head(two)
        filled = [i for i, ln in enumerate(lines) if ln.strip()]
        if not filled:
            raise ValueError(f"{p}: empty CSV file")
        first = lines[filled[0]].splitlines()[0].split(",")
        header = None
        if not all(_is_number(f) for f in first):
            header = [f.strip() for f in first]
            if len(filled) < 2:
                raise ValueError(f"{p}: no data rows after the header")
            rd.consume(b, lines, filled[0] + 1)
        else:
            rd.consume(b, lines, 0)
        width = len(header) if header else len(first)
        rows = _Rows(p, width)
        seen = None  # (line, fields) of the last non-blank line read
        for blk in rd.blocks():
            got = None if blk.last else _csv_fast(blk.data, width)
            if got is None:
                got, seen_here, n_lines = _csv_exact(p, rd.decode(blk), blk.line, width, blk.last)
                seen = seen_here or seen
                if blk.last and blk.data and not blk.data.endswith((b"\n", b"\r")):
                    if seen_here is None and seen is not None:
                        _refuse_cut(p, seen, width)  # the cut line was blank: the one before
            else:
                n_lines = len(got)
                seen = (blk.line + n_lines - 1, width)
            rows.add(got, blk.data)
            rd.line += n_lines
    finally:
        rd.close()
    if rows.n == 0:
        raise ValueError(f"{p}: no data rows after the header")
    return CsvText(header, rows.values())


def _refuse_cut(p: Path, seen: tuple[int, int], width: int) -> None:
    n, k = seen
    if k == width:
        raise ValueError(
            f"{p}: the last line ({n}) has no line end: the file may be cut; if it is "
            "complete, end it with a line break"
        )
    raise ValueError(
        f"{p}: line {n} has {k} fields, expected {width}; the last line is cut: the file is "
        "incomplete"
    )


# ------------------------------------------------------------------------------------ writing


def _rows_text(xyz: np.ndarray, a: int, sep: str, nan_text: str) -> list[str]:
    """Rows ``a .. a + WRITE_ROWS`` of ``xyz`` (n_frames, n_markers, 3) as text: each value as
    Python's ``repr`` (the shortest text that reads back to the same float; formatted in Rust,
    ``gapfill_format_rows``, ~5x faster than ``repr``), NaN as ``nan_text``."""
    from .._native import gapfill_format_rows

    block = np.ascontiguousarray(xyz[a : a + WRITE_ROWS], dtype=np.float64)
    return gapfill_format_rows(block.reshape(len(block), -1), sep, nan_text)


def trc_rows(xyz: np.ndarray, frames, times) -> Iterator[str]:
    """The data lines of a TRC, :data:`WRITE_ROWS` at a time: ``frame, time, x, y, z ...``
    tab-separated, values as ``repr``, missing values empty; ``frames(i)`` and ``times(i)``
    give the first two fields of row ``i``."""
    for a in range(0, len(xyz), WRITE_ROWS):
        rows = _rows_text(xyz, a, "\t", "")
        yield "".join(f"{frames(a + i)}\t{times(a + i)}\t{r}\n" for i, r in enumerate(rows))


def csv_rows(xyz: np.ndarray) -> Iterator[str]:
    """The data lines of a marker CSV, :data:`WRITE_ROWS` at a time: values as ``repr``,
    missing values ``NaN``."""
    for a in range(0, len(xyz), WRITE_ROWS):
        yield "".join(r + "\n" for r in _rows_text(xyz, a, ",", "NaN"))
