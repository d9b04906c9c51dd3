"""TRC and marker CSV read and written in blocks (issue 27 item 14).

Every value must be the one ``float()`` gives for its field, bit for bit, whichever way a block
is parsed (pandas or the per-line reader) and wherever the blocks are cut; errors still name
the right line; real OpenSim TRC files read as an independent parse (the csv module) reads
them and survive a round trip.
"""

from __future__ import annotations

import csv
import math
import random
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from acm_rs.gapfill import text_stream as ts
from acm_rs.gapfill.io import read, read_csv, read_trc, sidecar_path, write, write_like

REAL = Path(__file__).parent / "data" / "real" / "trc"
BLOCKS = [7, 300, 4096, ts.BLOCK_BYTES]  # 7: blocks shorter than a line


@pytest.fixture(params=BLOCKS, ids=lambda b: f"block{b}")
def block(request, monkeypatch):
    monkeypatch.setattr(ts, "BLOCK_BYTES", request.param)
    return request.param


# ----------------------------------------------------------------------- independent readers


def ref_trc(path: Path):
    """The TRC data as the csv module and ``float()`` read them: blank lines skipped, an empty
    field missing, empty fields after the last Z ignored (values, frames, times)."""
    with open(path, encoding="utf-8", newline="") as fh:
        text = fh.read()
    lines = text.splitlines()
    labels = [s.strip() for s in lines[3].split("\t")[2:] if s.strip()]
    d = 3 * len(labels)
    rows, frames, times = [], [], []
    for f in csv.reader(lines[5:], delimiter="\t", quoting=csv.QUOTE_NONE):
        if not "".join(f).strip():
            continue
        assert not any(x.strip() for x in f[d + 2 :])
        f = f[: d + 2] + [""] * (d + 2 - len(f))
        rows.append([float(v) if v.strip() else math.nan for v in f[2:]])
        frames.append(f[0])
        times.append(f[1])
    return np.array(rows, dtype=np.float64).reshape(len(rows), d), frames, times


def ref_csv(path: Path):
    """A marker CSV as ``float()`` reads it (header skipped, blank lines skipped)."""
    with open(path, encoding="utf-8", newline="") as fh:
        lines = [ln for ln in fh.read().splitlines() if ln.strip()]
    rows = list(csv.reader(lines, quoting=csv.QUOTE_NONE))
    try:
        [float(v) if v.strip() else 0.0 for v in rows[0]]
    except ValueError:
        rows = rows[1:]
    return np.array([[float(v) if v.strip() else math.nan for v in r] for r in rows])


def same_bits(a, b) -> None:
    """Equal bit for bit (NaN payloads and the sign of zero included)."""
    a, b = np.ascontiguousarray(a, np.float64), np.ascontiguousarray(b, np.float64)
    assert a.shape == b.shape
    a, b = a.ravel(), b.ravel()
    bad = np.flatnonzero(a.view(np.int64) != b.view(np.int64))
    assert bad.size == 0, f"{bad.size} differ, first {a[bad[0]]!r} vs {b[bad[0]]!r} at {bad[0]}"


# ------------------------------------------------------------------------------ quirky files

# fields float() reads, in the spellings files use (and some they should not)
ODD_VALUES = ["", " ", "NaN", "nan", "NAN", "-nan", "+nan", "nAn", "       NaN", "inf", "-inf",
              "+Infinity", "-0", "-0.0", "0", "12", "1e5", "-2.73E-01", "1.5e-300", "4.9e-324",
              "1e400", " 3.25 ", "1_000", "\u0661\u0662", "9007199254740993",
              "1.00000000000000011102230246251565404236316680908203125", ".5", "5."]  # fmt: skip


# fields float() refuses (pandas reads some: True as 1.0)
REFUSED = ["1e", "e5", "+-1", "True", "FALSE", "0x10", "1d3", "1.2.3", "--1", "nan(1)", "infinit"]


def _value(rng: random.Random) -> str:
    r = rng.random()
    x = rng.uniform(-2000, 2000)
    if r < 0.6:
        return repr(x)
    if r < 0.75:
        return f"{x:.6f}"
    if r < 0.8:
        return f"{x:.3E}"
    if r < 0.85:
        return ""
    return rng.choice(ODD_VALUES)


def quirky_trc(path: Path, n_frames: int, n_markers: int, eol: str = "\n", seed: int = 0,
               odd: bool = True) -> None:  # fmt: skip
    """A TRC whose rows are mostly plain and sometimes odd: short rows, trailing tabs, blank
    and whitespace lines, odd spellings, a non-ASCII frame label."""
    rng = random.Random(seed)
    d = 3 * n_markers
    rows = []
    for i in range(n_frames):
        vals = [(_value(rng) if odd else repr(rng.uniform(-2000, 2000))) for _ in range(d)]
        frame, time = str(i + 1), f"{i / 120:.6f}"
        if odd and rng.random() < 0.02:
            frame = "\u0661" + frame  # a non-ASCII frame label, kept as written
        line = f"{frame}\t{time}\t" + "\t".join(vals)
        if odd and rng.random() < 0.05:
            line = line.rstrip("\t") + "\t"  # OpenSim's trailing tab
        if odd and rng.random() < 0.03:
            line = "\t".join(line.split("\t")[: d - 1])  # missing last markers
        rows.append(line)
        if odd and rng.random() < 0.01:
            rows.append(rng.choice(["", "   ", "\t\t\t", " \t "]))
    header = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame"
        "\tOrigNumFrames",
        f"120\t120\t{n_frames}\t{n_markers}\tmm\t120\t1\t{n_frames}",
        "Frame#\tTime\t" + "\t\t\t".join(f"M{j}" for j in range(n_markers)) + "\t\t",
        "\t\t" + "\t".join(f"X{j + 1}\tY{j + 1}\tZ{j + 1}" for j in range(n_markers)),
        "",
    ]
    path.write_bytes((eol.join(header + rows) + eol).encode("utf-8"))


def quirky_csv(path: Path, n_frames: int, n_markers: int, eol: str = "\n", seed: int = 0) -> None:
    rng = random.Random(seed)
    lines = [",".join(f"m{j}_{a}" for j in range(n_markers) for a in "xyz")]
    for _ in range(n_frames):
        lines.append(",".join(_value(rng).replace(",", "") for _ in range(3 * n_markers)))
        if rng.random() < 0.01:
            lines.append(rng.choice(["", "   "]))
    path.write_bytes((eol.join(lines) + eol).encode("utf-8"))


@pytest.mark.parametrize("eol", ["\n", "\r\n", "\r"], ids=["lf", "crlf", "cr"])
def test_trc_values_are_float_of_each_field(tmp_path, block, eol):
    p = tmp_path / "q.trc"
    quirky_trc(p, 1500 if block > 100 else 300, 4, eol)
    m = read_trc(p)
    values, frames, times = ref_trc(p)
    same_bits(m.xyz.reshape(len(values), -1), values)
    assert m.source["trc"]["frames"] == frames and m.source["trc"]["times"] == times


@pytest.mark.parametrize("eol", ["\n", "\r\n"], ids=["lf", "crlf"])
def test_csv_values_are_float_of_each_field(tmp_path, block, eol):
    p = tmp_path / "q.csv"
    quirky_csv(p, 1500 if block > 100 else 300, 4, eol)
    m = read_csv(p)
    same_bits(m.xyz.reshape(len(m.xyz), -1), ref_csv(p))
    assert m.labels == [f"m{j}" for j in range(4)]


def test_unusual_line_separators_split_as_before(tmp_path, monkeypatch):
    """A form feed or U+2028 ends a line for str.splitlines (the old reader): still so."""
    monkeypatch.setattr(ts, "BLOCK_BYTES", 64)
    p = tmp_path / "ff.csv"
    p.write_text("1,2,3\n4,5,6\x0c7,8,9\n10,11,12\u202813,14,15\n", encoding="utf-8")
    same_bits(read_csv(p).xyz.reshape(-1, 3), np.arange(1.0, 16.0).reshape(5, 3))


def test_fast_path_never_reads_other_than_float():
    """Blocks of random tokens over the characters the fast path accepts: pandas' result, when
    it gives one, is float() of every field, and a field float() refuses sends the block to
    the exact reader."""
    rng = random.Random(1)
    alphabet = ts._NUMBER.decode()
    fast = 0
    for trial in range(400):
        toks = []
        odd = 0.5 if trial % 4 == 2 else 0.03  # most blocks mostly plain (fast path)
        for _ in range(20 * 3):
            if rng.random() > odd:
                toks.append(rng.choice([repr(rng.uniform(-1e3, 1e3)), f"{rng.random():.3E}", ""]))
            elif rng.random() < 0.5:
                toks.append(rng.choice(ODD_VALUES + REFUSED))
            else:
                toks.append("".join(rng.choice(alphabet) for _ in range(rng.randint(1, 6))))
        if trial % 4 in (0, 1):  # blocks of valid fields only
            toks = [t if _float_ok(t) else "1.5" for t in toks]
        if trial % 4 == 1:  # but one that float() refuses
            toks[rng.randrange(len(toks))] = rng.choice(REFUSED)
        lines = ["\t".join([str(i), "0"] + toks[3 * i : 3 * i + 3]) for i in range(20)]
        got = ts._trc_fast(("\n".join(lines) + "\n").encode("utf-8"), 3)
        if got is None:
            continue
        fast += 1
        assert all(_float_ok(t) for t in toks)
        want = np.array([float(t) if t.strip() else math.nan for t in toks]).reshape(20, 3)
        same_bits(got[0], want)
        csv_got = ts._csv_fast(("\n".join(",".join(toks[3 * i : 3 * i + 3]) for i in range(20))
                                + "\n").encode(), 3)  # fmt: skip
        if csv_got is not None:
            same_bits(csv_got, want)
    assert fast > 50  # the fast path was exercised


def _float_ok(t: str) -> bool:
    try:
        float(t) if t.strip() else None
        return True
    except ValueError:
        return False


# ------------------------------------------------------------------------------------ errors


def test_trc_errors_name_the_line_across_blocks(tmp_path, block):
    p = tmp_path / "e.trc"
    quirky_trc(p, 150, 3, odd=False)
    lines = p.read_text().split("\n")
    bad = list(lines)
    bad[100] = "\t".join(bad[100].split("\t")[:4] + ["12x"] + bad[100].split("\t")[5:])
    p.write_text("\n".join(bad))
    with pytest.raises(
        ValueError, match=r"e\.trc: line 101: could not convert string to float: '12x'"
    ):
        read_trc(p)
    bad = list(lines)
    bad[80] += "\t\t5"
    p.write_text("\n".join(bad))
    with pytest.raises(ValueError, match=r"line 81 has 13 fields, expected <= 11"):
        read_trc(p)
    p.write_text("\n".join(lines).rstrip("\n")[:-3])  # cut inside the last number
    with pytest.raises(ValueError, match=r"the last line \(156\) has no line end"):
        read_trc(p)
    p.write_text("\n".join(lines[:100]) + "\n")
    with pytest.raises(ValueError, match="NumFrames says 150 frames but the file holds 94"):
        read_trc(p)
    p.write_bytes(("\n".join(lines[:100]) + "\n").encode() + b"\xff\n")
    with pytest.raises(ValueError, match=r"not a text TRC file \(byte \d+ is not UTF-8\)"):
        read_trc(p)


def test_booleans_are_not_numbers(tmp_path, block):
    """pandas reads a column of True/False as 1.0/0.0 even as float64; float() refuses them."""
    p = tmp_path / "b.trc"
    quirky_trc(p, 40, 2, odd=False)
    lines = p.read_text().split("\n")
    for i in range(6, 46):
        f = lines[i].split("\t")
        f[4] = "True" if i % 2 else "FALSE"
        lines[i] = "\t".join(f)
    p.write_text("\n".join(lines))
    with pytest.raises(ValueError, match="line 7: could not convert string to float: 'FALSE'"):
        read_trc(p)
    q = tmp_path / "b.csv"
    q.write_text("a_x,a_y,a_z\n" + "".join(f"{i},True,2\n" for i in range(40)))
    with pytest.raises(ValueError, match="line 2: could not convert string to float: 'True'"):
        read_csv(q)


def test_csv_errors_name_the_line_across_blocks(tmp_path, block):
    p = tmp_path / "e.csv"
    rows = ["a_x,a_y,a_z"] + [f"{i}.5,{i},-{i}e-3" for i in range(150)]
    p.write_text("\n".join(rows[:100] + ["1,2"] + rows[100:]) + "\n")
    with pytest.raises(ValueError, match=r"e\.csv: line 101 has 2 fields, expected 3$"):
        read_csv(p)
    p.write_text("\n".join(rows[:120] + ["1,two,3"] + rows[120:]) + "\n")
    with pytest.raises(ValueError, match=r"line 121: could not convert string to float: 'two'"):
        read_csv(p)
    p.write_text("\n".join(rows))
    with pytest.raises(ValueError, match=r"the last line \(151\) has no line end"):
        read_csv(p)
    p.write_text("\n".join(rows)[:-10])  # "149.5,1"
    with pytest.raises(
        ValueError, match=r"line 151 has 2 fields, expected 3; the last line is cut"
    ):
        read_csv(p)
    p.write_text("\n".join(rows) + "\n\n   ")  # the cut line is blank: the one before counts
    with pytest.raises(ValueError, match=r"the last line \(151\) has no line end"):
        read_csv(p)
    p.write_text("\n".join(rows) + "\n\n")
    assert read_csv(p).xyz.shape == (150, 1, 3)


# ------------------------------------------------------------------------------------ writing


def test_written_text_is_the_old_writers(tmp_path, monkeypatch):
    monkeypatch.setattr(ts, "WRITE_ROWS", 7)
    rng = np.random.default_rng(0)
    X = rng.normal(0, 500, (50, 4, 3))
    X[rng.random(X.shape) < 0.1] = np.nan
    X[0, 0] = [-0.0, np.inf, 1e-300]
    X[1, 0] = [1e22, 1e16, 0.1]
    labels = ["a", "b", "c", "d"]
    write(tmp_path / "o.trc", X, labels, 100.0)
    write(tmp_path / "o.csv", X, labels, 100.0)
    flat = X.reshape(50, -1)
    trc = (tmp_path / "o.trc").read_text().split("\n")[5:-1]
    assert trc == [
        f"{i + 1}\t{i / 100:.6f}\t" + "\t".join("" if np.isnan(v) else repr(float(v)) for v in r)
        for i, r in enumerate(flat)
    ]
    csv_lines = (tmp_path / "o.csv").read_text().split("\n")[1:-1]
    assert csv_lines == [",".join("NaN" if np.isnan(v) else repr(float(v)) for v in r)
                         for r in flat]  # fmt: skip
    same_bits(read(tmp_path / "o.trc").xyz, X)
    same_bits(read(tmp_path / "o.csv").xyz, X)


def test_native_repr_is_pythons():
    """The Rust formatter of the writers gives ``repr`` for every kind of double: random bit
    patterns, decimals, powers of 2 and 10 and their neighbours, and exact halfway cases
    (``1140579860715907.25``: dtoa's even digit ``.2``, where Rust's own digits end in 3)."""
    from acm_rs._native import gapfill_format_rows

    rng = np.random.default_rng(0)
    halves = rng.integers(2**50, 2**53, 5000) + rng.choice([0.25, 0.5, 0.75], 5000)
    special = [2.0**k for k in range(-1074, 1024)] + [10.0**k for k in range(-323, 309)]
    special += [np.nextafter(v, d) for v in special[-60:] for d in (-np.inf, np.inf)]
    x = np.concatenate([
        rng.integers(0, 2**64, 100_000, dtype=np.uint64).view(np.float64),
        rng.normal(0, 1, 50_000) * 10.0 ** rng.integers(-30, 30, 50_000),
        np.round(rng.uniform(-2000, 2000, 50_000), 6), halves, special,
        [0.0, -0.0, np.inf, -np.inf, 5e-324, 0.1 + 0.2, 9007199254740993.0],
    ])  # fmt: skip
    x = x[~np.isnan(x)]
    got = gapfill_format_rows(x.reshape(-1, 1), "\t", "")
    want = [repr(v) for v in x.tolist()]
    bad = [(w, g) for w, g in zip(want, got, strict=True) if w != g]
    assert not bad, f"{len(bad)} differ, e.g. {bad[:3]}"
    assert gapfill_format_rows(np.array([[1.0, np.nan, 2.5]]), ",", "NaN") == ["1.0,NaN,2.5"]


def test_read_memory_is_the_array_and_a_block(tmp_path, monkeypatch):
    """Python-side peak while reading 2,000 frames x 41 markers in 64 KiB blocks: the array
    (2 MB), frame and time labels, one block; the whole-file reader took ~7x the array."""
    p = tmp_path / "m.trc"
    quirky_trc(p, 2000, 41, odd=False)
    monkeypatch.setattr(ts, "BLOCK_BYTES", 64 * 1024)
    read_trc(p)  # imports
    tracemalloc.start()
    m = read_trc(p)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 2 * m.xyz.nbytes + 1.5e6, (
        f"peak {peak / 1e6:.1f} MB for {m.xyz.nbytes / 1e6:.1f} MB"
    )


def test_gapfill_cli_keeps_text_files(tmp_path, monkeypatch):
    """``acm-rs gapfill`` on a TRC and a CSV (small blocks): observed values bit for bit,
    frames and times as written, filled values listed in the sidecar."""
    from acm_rs.cli import main

    monkeypatch.setattr(ts, "BLOCK_BYTES", 2048)
    monkeypatch.setattr(ts, "WRITE_ROWS", 100)
    t = np.arange(1200) / 120
    X = np.stack([np.stack([np.sin(t + j), np.cos(t + j), t * j], -1) * 100 for j in range(5)], 1)
    G = X.copy()
    G[300:340, 1] = np.nan
    src = tmp_path / "g.trc"
    write(src, G, [f"m{j}" for j in range(5)], 120.0)
    text = src.read_text().replace("\t0.000000\t", "\t0\t", 1)  # a time kept as written
    src.write_text(text)
    for ext in ("trc", "csv"):
        out = tmp_path / f"o.{ext}"
        assert main(["gapfill", str(src), "-o", str(out), "--method", "spline"]) == 0
        back = read(out)
        seen = ~np.isnan(G)
        same_bits(back.xyz[seen], G[seen])
        assert np.isfinite(back.xyz).all()
        assert back.filled[300:340, 1].all() and back.filled.sum() == 40
        if ext == "trc":
            assert back.source["trc"]["times"][:2] == ["0", "0.008333"]
        assert sidecar_path(out).is_file()


# -------------------------------------------------------------------------------- real files


def real(name: str) -> Path:
    return REAL / name


REAL_READABLE = ["dataWithEformat.trc", "dataWithNaNsOfDifferentCases.trc",
                 "gait10dof18musc_walk_CRLF_line_ending.trc", "std_walking5_markers.trc",
                 "markers_walk.trc"]  # fmt: skip


@pytest.mark.parametrize("name", REAL_READABLE)
@pytest.mark.parametrize("crlf", [False, True], ids=["lf", "crlf"])
def test_real_trc_reads_as_an_independent_parse(tmp_path, name, crlf, monkeypatch):
    p = real(name)
    if crlf:  # the repository keeps \n; a Windows checkout has \r\n
        p = tmp_path / name
        p.write_bytes(real(name).read_bytes().replace(b"\n", b"\r\n"))
    monkeypatch.setattr(ts, "BLOCK_BYTES", 4096)
    m = read_trc(p)
    values, frames, times = ref_trc(p)
    same_bits(m.xyz.reshape(len(values), -1), values)
    assert m.source["trc"]["frames"] == frames and m.source["trc"]["times"] == times
    header = real(name).read_text().splitlines()
    assert len(m.labels) == int(header[2].split()[3])  # NumMarkers
    assert len(values) == int(header[2].split()[2])  # NumFrames


@pytest.mark.parametrize("name", REAL_READABLE)
def test_real_trc_round_trip(tmp_path, name):
    m = read_trc(real(name))
    for ext in ("trc", "csv"):
        out = tmp_path / f"copy.{ext}"
        write_like(out, m, m.xyz)
        back = read(out)
        same_bits(back.xyz, m.xyz)
        assert back.labels == m.labels and back.rate == m.rate and back.units == m.units
    copy = (tmp_path / "copy.trc").read_text().splitlines()[5:]
    assert [ln.split("\t")[0] for ln in copy] == m.source["trc"]["frames"]
    assert [ln.split("\t")[1] for ln in copy] == m.source["trc"]["times"]


def test_real_trc_conventions(tmp_path):
    e = read_trc(real("dataWithEformat.trc"))  # scientific notation, metres
    assert e.units == "m" and e.rate == 119.88012 and e.xyz.shape == (5, 14, 3)
    same_bits(e.xyz[0, 0], [float("-2.73E-01"), float("7.46E-02"), float("-1.57E+00")])
    n = read_trc(real("dataWithNaNsOfDifferentCases.trc"))  # NaN, nan, NAN, Nan, naN
    raw = real("dataWithNaNsOfDifferentCases.trc").read_text().split("\t")
    assert np.isnan(n.xyz).sum() == sum(f.strip().lower() == "nan" for f in raw) == 15
    s = read_trc(real("std_walking5_markers.trc"))  # empty fields for missing markers
    assert np.isnan(s.xyz).sum() == 6231 and s.rate == 250.0
    w = read_trc(real("markers_walk.trc"))  # header values after double tabs
    assert (w.rate, w.units, w.xyz.shape) == (100.0, "mm", (238, 41, 3))
    with pytest.raises(
        ValueError, match=r"exampleFormat\.trc: the last line \(10\) has no line end"
    ):
        read_trc(real("exampleFormat.trc"))
    ended = tmp_path / "exampleFormat.trc"
    ended.write_bytes(real("exampleFormat.trc").read_bytes() + b"\n")
    x = read_trc(ended)
    assert x.units == "m" and np.isnan(x.xyz[0, 0]).all() and np.isnan(x.xyz[2, 1]).all()
    assert np.isfinite(x.xyz).sum() == 5 * 9 - 6


def test_header_with_an_empty_value_stays_positional(tmp_path):
    """An empty CameraRate is not a double tab: values pair with names by position."""
    p = tmp_path / "h.trc"
    quirky_trc(p, 10, 2, odd=False)
    lines = p.read_text().split("\n")
    lines[2] = "100\t\t10\t2\tmm\t100\t1\t10"
    p.write_text("\n".join(lines))
    m = read_trc(p)
    assert m.rate == 100.0 and m.xyz.shape == (10, 2, 3)
