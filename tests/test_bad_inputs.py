# ruff: noqa: E501 - the tables of cases read best one case per line
"""A catalogue of bad inputs (issue 14): each must give the right kind of error, naming the file
and what is wrong, or the correct masked result; never a silent partial or made-up answer.

``CASES`` are API calls that must raise (type + key words of the message); ``CLI_CASES`` are
command lines that must exit with the given code, print the key words on stderr and no
traceback; the remaining tests check results (masks, metadata, permissions, interruption,
workflow records) and, with hypothesis, the readers and writers on random data and on every
truncation.
"""

from __future__ import annotations

import json
import os
import re
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import acm_rs
from acm_rs import _provenance as prov
from acm_rs import _toml, models
from acm_rs.calibration import calibrate
from acm_rs.camera import CameraRig
from acm_rs.cli import main
from acm_rs.demo import demo_rig
from acm_rs.dlc import read_dlc_table, read_labels
from acm_rs.gapfill import fill
from acm_rs.gapfill.io import read, read_c3d, read_csv, read_trc, write, write_like
from acm_rs.labels import mask_by_likelihood
from acm_rs.skeleton import Skeleton
from acm_rs.state import Normalization
from acm_rs.tracking.result_npz import NPZ_FORMAT, read_npz

ezc3d = pytest.importorskip("ezc3d")

N_FRAMES, N_MARKERS = 40, 4


def _seq(n: int = N_FRAMES, m: int = N_MARKERS) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n)[:, None]
    return np.stack(
        [
            np.hstack([100 * np.sin(t + k), 80 * np.cos(1.3 * t + k), 10.0 * k + 5 * t])
            for k in range(m)
        ],
        axis=1,
    )


def _dlc_csv(path: Path, bodyparts: list[str], n: int, lik: float = 0.95) -> Path:
    cols = pd.MultiIndex.from_tuples(
        [("DLC_net", bp, co) for bp in bodyparts for co in ("x", "y", "likelihood")],
        names=["scorer", "bodyparts", "coords"],
    )
    rng = np.random.default_rng(0)
    data = np.column_stack(
        [rng.uniform(100, 500, n) if co != "likelihood" else np.full(n, lik)
         for _ in bodyparts for co in ("x", "y", "likelihood")]
    )  # fmt: skip
    pd.DataFrame(data, columns=cols).to_csv(path)
    return path


def _pose_npz(path: Path, **extra) -> Path:
    arrays = {
        "format": np.array(NPZ_FORMAT), "version": np.array(1), "units": np.array("cm"),
        "skeleton_toml": np.array(""), "calibration_toml": np.array(""),
        "info_json": np.array("{}"), "joints": np.arange(600.0).reshape(50, 4, 3), **extra,
    }  # fmt: skip
    np.savez_compressed(path, **arrays)
    return path


@pytest.fixture(scope="module")
def w(tmp_path_factory):
    """A folder of good files that the cases damage copies of."""
    d = tmp_path_factory.mktemp("bad_inputs")
    X = _seq()
    X[10:14, 1] = np.nan
    labels = [f"m{i}" for i in range(N_MARKERS)]
    write(d / "good.trc", X, labels, 100.0)
    write(d / "good.csv", X, labels, 100.0)
    write(d / "good.c3d", X, labels, 100.0)
    (d / "plain.csv").write_text(
        "\n".join(",".join(repr(float(v)) for v in r) for r in _seq(6, 1).reshape(6, 3)) + "\n"
    )
    rig = demo_rig()
    rig.save(d / "calibration.toml")
    sk = models.rat()
    sk.save(d / "skeleton.toml")
    dlc = [_dlc_csv(d / f"{c.name}DLC_net.csv", list(sk.marker_names), 8) for c in rig]
    _pose_npz(d / "pose.npz")
    return {"d": d, "X": X, "labels": labels, "rig": rig, "sk": sk, "dlc": dlc}


def cut(src: Path, dst: Path, keep: float | int) -> Path:
    """A copy of ``src`` with only its first ``keep`` bytes (a fraction or a count)."""
    b = src.read_bytes()
    n = int(len(b) * keep) if isinstance(keep, float) else keep
    dst.write_bytes(b[:n])
    return dst


def text(d: Path, name: str, content: str | bytes) -> Path:
    p = d / name
    (p.write_bytes if isinstance(content, bytes) else p.write_text)(content)
    return p


def edit(src: Path, dst: Path, old: str, new: str, count: int = 1) -> Path:
    s = src.read_text()
    assert old in s, old
    dst.write_text(s.replace(old, new, count))
    return dst


def _cal_with(w, d: Path, name: str, **cam0) -> Path:
    import tomllib

    from acm_rs import _toml

    doc = tomllib.loads((w["d"] / "calibration.toml").read_text())
    doc["cam_0"].update(cam0)
    for k in [k for k, v in cam0.items() if v is None]:
        del doc["cam_0"][k]
    p = d / name
    p.write_text(_toml.dumps(doc))
    return p


def _corners(value):
    board = np.c_[np.mgrid[0:3, 0:3].reshape(2, -1).T.astype(float), np.zeros(9)]
    c = np.full((2, 4, 9, 2), 300.0) + np.arange(9)[None, None, :, None]
    c[0, 1, 3] = value
    return c, board


# (id, call(w, tmp) -> None, exception, key words of the message (regex, all must match))
CASES = [
    # ---- C3D
    ("c3d-cut-in-half", lambda w, t: read_c3d(cut(w["d"] / "good.c3d", t / "h.c3d", 0.5)),
     ValueError, [r"h\.c3d", "incomplete C3D", f"declares {N_FRAMES} frames"]),
    ("c3d-cut-in-header", lambda w, t: read_c3d(cut(w["d"] / "good.c3d", t / "h.c3d", 700)),
     ValueError, [r"h\.c3d"]),
    ("c3d-garbage", lambda w, t: read_c3d(text(t, "g.c3d", b"not a c3d" * 100)),
     ValueError, [r"g\.c3d", "C3D"]),
    ("c3d-empty", lambda w, t: read_c3d(text(t, "e.c3d", b"")), ValueError, [r"e\.c3d"]),
    ("c3d-parameter-link-past-section", lambda w, t: read_c3d(_patch(w["d"] / "good.c3d", t / "l.c3d", 523, b"\xff\x7f")),
     ValueError, [r"l\.c3d", "damaged C3D parameter section", "link"]),
    ("c3d-parameter-of-no-group", lambda w, t: read_c3d(_patch(w["d"] / "good.c3d", t / "o.c3d", 527, b"\x78")),
     ValueError, ["damaged C3D parameter section", "group 120, which does not exist"]),
    ("c3d-parameter-type", lambda w, t: read_c3d(_patch(w["d"] / "good.c3d", t / "y.c3d", 534, b"\x03")),
     ValueError, ["damaged C3D parameter section", "type 3"]),
    ("c3d-missing", lambda w, t: read_c3d(t / "none.c3d"), ValueError, ["not found", "none.c3d"]),
    # ---- TRC
    ("trc-cut-mid-line", lambda w, t: read_trc(cut(w["d"] / "good.trc", t / "a.trc", 0.5)),
     ValueError, [r"a\.trc", "no line end", "cut"]),
    ("trc-cut-at-line", lambda w, t: read_trc(text(t, "b.trc", "\n".join(
        (w["d"] / "good.trc").read_text().splitlines()[:20]) + "\n")),
     ValueError, [r"b\.trc", f"NumFrames says {N_FRAMES}", "holds 15"]),
    ("trc-numframes-too-small", lambda w, t: read_trc(edit(
        w["d"] / "good.trc", t / "c.trc", f"\t{N_FRAMES}\t{N_MARKERS}\t", f"\t3\t{N_MARKERS}\t")),
     ValueError, ["NumFrames says 3"]),
    ("trc-numframes-text", lambda w, t: read_trc(edit(
        w["d"] / "good.trc", t / "c.trc", f"\t{N_FRAMES}\t{N_MARKERS}\t", f"\tmany\t{N_MARKERS}\t")),
     ValueError, ["NumFrames 'many' is not a number"]),
    ("trc-nummarkers-wrong", lambda w, t: read_trc(edit(
        w["d"] / "good.trc", t / "c.trc", f"\t{N_FRAMES}\t{N_MARKERS}\t", f"\t{N_FRAMES}\t9\t")),
     ValueError, ["NumMarkers says 9"]),
    ("trc-bad-number", lambda w, t: read_trc(edit(w["d"] / "good.trc", t / "d.trc", "\n1\t0.000000\t", "\n1\t0.000000\tabc")),
     ValueError, [r"d\.trc", "line 6"]),
    ("trc-too-many-fields", lambda w, t: read_trc(edit(w["d"] / "good.trc", t / "e.trc", "\n2\t", "\n2\t1\t2\t3\t4\t")),
     ValueError, ["line 7 has", "fields"]),
    ("trc-no-header", lambda w, t: read_trc(text(t, "f.trc", "1\t2\t3\n")),
     ValueError, ["not a TRC file", "PathFileType"]),
    ("trc-binary", lambda w, t: read_trc(text(t, "g.trc", b"\x89PNG\r\n\x1a\n\xff\xfe" * 50)),
     ValueError, [r"g\.trc", "not a text TRC file", "UTF-8"]),
    ("trc-rate-text", lambda w, t: read_trc(edit(w["d"] / "good.trc", t / "h.trc", "\n100\t100\t", "\nfast\t100\t")),
     ValueError, ["DataRate 'fast'"]),
    ("trc-rate-zero", lambda w, t: read_trc(edit(w["d"] / "good.trc", t / "h.trc", "\n100\t100\t", "\n0\t100\t")),
     ValueError, ["DataRate 0.0 is not a positive frame rate"]),
    ("trc-no-markers", lambda w, t: read_trc(text(t, "i.trc", "PathFileType\t4\na\nb\nFrame#\tTime\n\n1\t0\n")),
     ValueError, ["names no markers"]),
    ("trc-no-rows", lambda w, t: read_trc(text(t, "j.trc", "\n".join(
        (w["d"] / "good.trc").read_text().splitlines()[:5]) + "\n")),
     ValueError, ["no data rows"]),
    ("trc-missing", lambda w, t: read_trc(t / "none.trc"), ValueError, ["not found"]),
    # ---- marker CSV
    ("csv-cut-mid-row", lambda w, t: read_csv(cut(w["d"] / "good.csv", t / "a.csv", 0.5)),
     ValueError, [r"a\.csv", "line", "cut|no line end"]),
    ("csv-no-final-newline", lambda w, t: read_csv(text(t, "b.csv", "1,2,3\n4,5,6")),
     ValueError, [r"last line \(2\)", "no line end"]),
    ("csv-cut-at-row-with-sidecar", lambda w, t: (
        text(t, "c.csv", "\n".join((w["d"] / "good.csv").read_text().splitlines()[:9]) + "\n"),
        (t / "c.csv.acm.json").write_text((w["d"] / "good.csv.acm.json").read_text()),
        read_csv(t / "c.csv"))[-1],
     ValueError, ["acm.json", f"{N_FRAMES} frames", "holds 8 frames"]),
    ("csv-width-not-3", lambda w, t: read_csv(text(t, "d.csv", "1,2\n3,4\n")),
     ValueError, ["multiple of 3"]),
    ("csv-ragged", lambda w, t: read_csv(text(t, "e.csv", "1,2,3\n4,5,6,7,8,9\n")),
     ValueError, ["line 2 has 6 fields, expected 3"]),
    ("csv-bad-number", lambda w, t: read_csv(text(t, "f.csv", "1,2,3\n4,five,6\n")),
     ValueError, [r"f\.csv", "line 2"]),
    ("csv-empty", lambda w, t: read_csv(text(t, "g.csv", "\n\n")), ValueError, ["empty CSV"]),
    ("csv-header-only", lambda w, t: read_csv(text(t, "h.csv", "a_x,a_y,a_z\n")),
     ValueError, ["no data rows"]),
    ("csv-binary", lambda w, t: read_csv(text(t, "i.csv", b"\xff\xd8\xff\xe0" * 64)),
     ValueError, ["not a text CSV file"]),
    ("csv-sidecar-garbage", lambda w, t: (
        text(t, "j.csv", "1,2,3\n4,5,6\n"), text(t, "j.csv.acm.json", "{oops"),
        read_csv(t / "j.csv"))[-1],
     ValueError, ["j.csv.acm.json", "not a readable acm-rs sidecar"]),
    ("csv-sidecar-other-labels", lambda w, t: (
        text(t, "k.csv", "a_x,a_y,a_z\n1,2,3\n4,5,6\n"),
        text(t, "k.csv.acm.json", json.dumps({"format": "acm-rs-markers", "n_frames": 2, "labels": ["b"]})),
        read_csv(t / "k.csv"))[-1],
     ValueError, ["names", r"\['b'\]", r"\['a'\]"]),
    ("marker-file-unknown-type", lambda w, t: read(text(t, "x.xyz", "1")),
     ValueError, ["unsupported marker file", ".c3d, .trc or .csv"]),
    # ---- marker writers
    ("csv-to-trc-no-rate", lambda w, t: write_like(t / "o.trc", read_csv(w["d"] / "plain.csv"), _seq(6, 1)),
     ValueError, ["TRC file needs the frame rate", "--rate"]),
    ("csv-to-c3d-no-rate", lambda w, t: write_like(t / "o.c3d", read_csv(w["d"] / "plain.csv"), _seq(6, 1)),
     ValueError, ["C3D file needs the frame rate"]),
    ("write-unknown-type", lambda w, t: write(t / "o.txt", _seq(3, 1), ["a"], 100.0),
     ValueError, ["unsupported output", "o.txt"]),
    ("write-negative-rate", lambda w, t: write(t / "o.trc", _seq(3, 1), ["a"], -5.0),
     ValueError, ["positive number of Hz"]),
    ("write-no-rate", lambda w, t: write(t / "o.trc", _seq(3, 1), ["a"], None),
     ValueError, ["frame rate"]),
    ("write-labels-mismatch", lambda w, t: write(t / "o.trc", _seq(3, 2), ["a"], 100.0),
     ValueError, ["len\\(labels\\)"]),
    ("write-like-wrong-shape", lambda w, t: write_like(t / "o.trc", read(w["d"] / "good.trc"), np.zeros((3, 2, 3))),
     ValueError, ["shape"]),
    ("write-like-wrong-mask", lambda w, t: write_like(
        t / "o.trc", read(w["d"] / "good.trc"), w["X"], filled=np.zeros((3, 3), bool)),
     ValueError, ["filled must have shape"]),
    # ---- gap filling
    ("fill-infinity", lambda w, t: fill(np.where(np.arange(3)[None, None] == 0, np.inf, _seq(5, 2))),
     ValueError, ["infinity", "NaN for missing"]),
    ("fill-2d", lambda w, t: fill(np.zeros((10, 3))), ValueError, [r"shape \(n_frames, n_markers, 3\)"]),
    ("fill-one-frame", lambda w, t: fill(np.zeros((1, 2, 3))), ValueError, ["at least 2 frames"]),
    ("fill-text", lambda w, t: fill([["a"]]), ValueError, ["numeric"]),
    ("fill-unknown-method", lambda w, t: fill(_seq(), method="magic"), ValueError, ["unknown method"]),
    ("fill-unknown-option", lambda w, t: fill(_seq(), gamm=0.9), ValueError, [r"unknown option.*gamm"]),
    ("fill-all-missing", lambda w, t: fill(np.full((5, 2, 3), np.nan)), ValueError, ["every marker is missing"]),
    ("fill-dead-marker", lambda w, t: fill(np.where(np.arange(2)[None, :, None] == 1, np.nan, _seq(20, 2))),
     ValueError, [r"marker\(s\) \[1\]", "empty='skip'"]),
    ("fill-empty-option", lambda w, t: fill(_seq(), empty="ignore"), ValueError, ["empty must be"]),
    # ---- pose.npz
    ("pose-npz-cut", lambda w, t: read_npz(cut(w["d"] / "pose.npz", t / "p.npz", 0.6)),
     ValueError, [r"p\.npz", "damaged or incomplete", "re-run acm-rs track"]),
    ("pose-npz-crc", lambda w, t: read_npz(_flip(w["d"] / "pose.npz", t / "q.npz")),
     ValueError, [r"q\.npz", "damaged or incomplete"]),
    ("pose-is-toml", lambda w, t: read_npz(w["d"] / "calibration.toml"),
     ValueError, ["not a pose file", "got a .toml file"]),
    ("pose-other-npz", lambda w, t: (np.savez(t / "o.npz", a=np.arange(3)), read_npz(t / "o.npz"))[-1],
     ValueError, ["not an acm-rs pose file"]),
    ("pose-missing", lambda w, t: read_npz(t / "none.npz"), ValueError, ["not found"]),
    # ---- calibration.toml
    ("calibration-binary", lambda w, t: CameraRig.load(text(t, "c.toml", os.urandom(64) + b"\xff")),
     ValueError, [r"c\.toml", "not a text file", "anipose"]),
    ("calibration-bad-toml", lambda w, t: CameraRig.load(text(t, "c.toml", "[cam_0\nname=")),
     ValueError, [r"c\.toml", "invalid TOML"]),
    ("calibration-no-cameras", lambda w, t: CameraRig.load(text(t, "c.toml", "a = 1\n")),
     ValueError, [r"no \[cam_<i>\] tables"]),
    ("calibration-size-swapped", lambda w, t: CameraRig.load(_cal_with(w, t, "s.toml", size=[1024, 1280])),
     ValueError, [r"s\.toml", r"\[cam_0\]", "looks swapped", r"\[width, height\]"]),
    ("calibration-centre-outside", lambda w, t: CameraRig.load(_cal_with(w, t, "o.toml", size=[100, 80])),
     ValueError, [r"\[cam_0\]", "outside the 100 x 80 image"]),
    ("calibration-missing-key", lambda w, t: CameraRig.load(_cal_with(w, t, "k.toml", rotation=None)),
     ValueError, [r"\[cam_0\]", "lacks keys", "rotation"]),
    ("calibration-unknown-camera", lambda w, t: CameraRig.load(w["d"] / "calibration.toml", names=["camZ"]),
     ValueError, ["no camera named", "camZ"]),
    ("calibration-missing", lambda w, t: CameraRig.load(t / "none.toml"), ValueError, ["not found"]),
    # ---- board corners (calibrate)
    ("corners-minus-one", lambda w, t: calibrate(*_corners(-1.0), (1280, 1024)),
     ValueError, ["camera 0, frame 1, point 3", r"NaN \(not -1\)"]),
    ("corners-integer-minus-one", lambda w, t: calibrate(_corners(-1)[0].astype(np.int64), _corners(-1)[1], (1280, 1024)),
     ValueError, [r"NaN \(not -1\)"]),
    ("corners-size-swapped", lambda w, t: calibrate(*_corners([1100.0, 900.0]), (1024, 1280)),
     ValueError, ["outside its image_size", "looks swapped"]),
    ("corners-infinity", lambda w, t: calibrate(*_corners(np.inf), (1280, 1024)), ValueError, ["infinity"]),
    ("corners-half-nan", lambda w, t: calibrate(*_corners([np.nan, 5.0]), (1280, 1024)),
     ValueError, ["one NaN coordinate"]),
    # ---- DeepLabCut files
    ("dlc-cut-mid-row", lambda w, t: read_dlc_table(cut(w["dlc"][0], t / "c.csv", 0.6)),
     ValueError, [r"c\.csv", "line", "fields", "cut"]),
    ("dlc-short-row", lambda w, t: read_dlc_table(_short_row(w["dlc"][0], t / "s.csv")),
     ValueError, [r"s\.csv", "line 6 has"]),
    ("dlc-not-dlc", lambda w, t: read_dlc_table(text(t, "n.csv", "a,b\n1,2\n")),
     ValueError, ["not a DeepLabCut CSV"]),
    ("dlc-binary", lambda w, t: read_dlc_table(text(t, "b.csv", b"\xff\xfe\x00\x01" * 40)),
     ValueError, ["not a text file|not a DeepLabCut"]),
    ("dlc-empty", lambda w, t: read_dlc_table(text(t, "e.csv", "")), ValueError, ["empty file|not a DeepLabCut"]),
    ("dlc-missing", lambda w, t: read_dlc_table(t / "none.csv"), ValueError, ["no such file"]),
    ("dlc-wrong-suffix", lambda w, t: read_dlc_table(text(t, "x.json", "{}")), ValueError, [".csv or .h5"]),
    ("dlc-h5-cut", lambda w, t: read_dlc_table(_h5(w, t, cut_to=0.5)),
     ValueError, [r"c\.h5", "damaged or incomplete HDF5"]),
    ("dlc-likelihood-0-100", lambda w, t: mask_by_likelihood(np.zeros((1, 2, 3, 2)), np.full((1, 2, 3), 95.0), 0.9),
     ValueError, ["0-100 scale", "divide by 100"]),
    ("dlc-pcutoff-percent", lambda w, t: mask_by_likelihood(np.zeros((1, 2, 3, 2)), np.full((1, 2, 3), 0.95), 90),
     ValueError, [r"pcutoff must be in \[0, 1\]"]),
    # ---- skeletons and units
    ("skeleton-duplicate-joint", lambda w, t: Skeleton.from_dict(_dup(w["sk"], "joints"), "d.toml"),
     ValueError, [r"d\.toml", "repeats the name", "joint names must be unique"]),
    ("skeleton-duplicate-marker", lambda w, t: Skeleton.from_dict(_dup(w["sk"], "markers"), "d.toml"),
     ValueError, ["markers\\[1\\] repeats", "marker names must be unique"]),
    ("skeleton-unknown-key", lambda w, t: Skeleton.from_dict({**w["sk"].to_dict(), "nmae": "x"}, "u.toml"),
     ValueError, ["unknown key", "nmae"]),
    ("skeleton-not-skeleton", lambda w, t: Skeleton.load(w["d"] / "calibration.toml"),
     ValueError, ["not an acm-rs skeleton file"]),
    ("units-inches", lambda w, t: Normalization.for_units("inches"), ValueError, ["unknown length unit 'inches'"]),
    ("body-weight-kg", lambda w, t: acm_rs.learning.check_body_weight(w["sk"], 0.35),
     ValueError, ["not a rodent's weight", "350 for 0.35 kg"]),
]  # fmt: skip


def _folder_with_file(folder: Path, name: str = "old.png") -> Path:
    folder.mkdir()
    (folder / name).write_text("x")
    return folder


def _patch(src: Path, dst: Path, at: int, new: bytes) -> Path:
    """A copy of ``src`` with the bytes at ``at`` replaced by ``new``."""
    b = bytearray(src.read_bytes())
    b[at : at + len(new)] = new
    dst.write_bytes(bytes(b))
    return dst


def _flip(src: Path, dst: Path) -> Path:
    """A copy with one byte of the first member's compressed data changed (CRC mismatch)."""
    b = bytearray(src.read_bytes())
    with zipfile.ZipFile(src) as z:
        info = z.infolist()[-1]
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    b[start + info.compress_size // 2] ^= 0x55
    dst.write_bytes(bytes(b))
    return dst


def _short_row(src: Path, dst: Path) -> Path:
    lines = src.read_text().splitlines()
    lines[5] = ",".join(lines[5].split(",")[:-4])
    dst.write_text("\n".join(lines) + "\n")
    return dst


def _h5(w, t: Path, cut_to: float) -> Path:
    pytest.importorskip("tables")
    df = pd.read_csv(w["dlc"][0], header=[0, 1, 2], index_col=0)
    full = t / "full.h5"
    df.to_hdf(full, key="df_with_missing")
    return cut(full, t / "c.h5", cut_to)


def _dup(sk, key: str) -> dict:
    d = sk.to_dict()
    d[key][1] = {**d[key][1], "name": d[key][0]["name"]}
    return d


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_refused(case, w, tmp_path):
    _, call, exc, words = case
    with pytest.raises(exc) as info:
        call(w, tmp_path)
    msg = str(info.value)
    for word in words:
        assert re.search(word, msg), f"{word!r} not in: {msg}"
    assert "Traceback" not in msg and "allow_pickle" not in msg and "Some(" not in msg


def test_the_catalogue_is_large_enough():
    assert len(CASES) + len(CLI_CASES) >= 60


# ---- command lines: (id, argv builder, exit code, stderr key words)
def _g(w, t, *extra):
    return ["gapfill", str(w["d"] / "good.trc"), *extra]


def _track(w, t, *extra):
    return [
        "track", "--calibration", str(w["d"] / "calibration.toml"), "--skeleton",
        str(w["d"] / "skeleton.toml"), "--dlc", *map(str, w["dlc"]), "--max-iter", "1", *extra,
    ]  # fmt: skip


CLI_CASES = [
    ("gapfill-output-exists", lambda w, t: _g(w, t, "-o", str(text(t, "o.trc", "x"))), 1,
     ["o.trc exists", "--overwrite"]),
    ("gapfill-std-exists", lambda w, t: _g(w, t, "-o", str(t / "o.trc"), "--std", str(text(t, "s.trc", "x"))), 1,
     ["s.trc exists", "--overwrite"]),
    ("gapfill-csv-to-trc-no-rate", lambda w, t: ["gapfill", str(w["d"] / "plain.csv"), "-o", str(t / "o.trc")], 1,
     ["needs the frame rate", "--rate"]),
    ("gapfill-rate-disagrees", lambda w, t: _g(w, t, "-o", str(t / "o.trc"), "--rate", "60"), 1,
     ["says 100 Hz", "--rate 60 disagrees"]),
    ("gapfill-output-folder-is-file", lambda w, t: _g(w, t, "-o", str(text(t, "f", "x") / "o.trc")), 1,
     ["is not a folder"]),
    ("gapfill-output-is-folder", lambda w, t: _g(w, t, "-o", str(t)), 1, ["is a folder"]),
    ("gapfill-truncated-input", lambda w, t: ["gapfill", str(cut(w["d"] / "good.trc", t / "c.trc", 0.5)),
                                              "-o", str(t / "o.trc")], 1, ["c.trc", "no line end"]),
    ("gapfill-unknown-output-type", lambda w, t: _g(w, t, "-o", str(t / "o.xlsx")), 1, ["unsupported output"]),
    ("track-c3d-export-without-rate", lambda w, t: _track(w, t, "-o", str(t / "s"), "--export", "c3d"), 1,
     ["--export c3d needs the frame rate", "--rate"]),
    ("track-output-exists", lambda w, t: _track(w, t, "-o", str(t / "s"))
     if (t / "s.npz").write_text("x") else None, 1, ["s.npz exists", "--overwrite"]),
    ("track-output-folder-is-file", lambda w, t: _track(w, t, "-o", str(text(t, "f", "x") / "s")), 1,
     ["is not a folder"]),
    ("export-c3d-without-rate", lambda w, t: ["export", str(w["d"] / "pose.npz"), "--format", "c3d",
                                              "-o", str(t / "e")], 1, ["needs the frame rate"]),
    ("plot-calibration-toml", lambda w, t: ["plot", str(w["d"] / "calibration.toml"), "-o", str(t / "p")], 1,
     ["calibration.toml", "not a pose file"]),
    ("export-truncated-pose", lambda w, t: ["export", str(cut(w["d"] / "pose.npz", t / "p.npz", 0.5)),
                                            "--format", "npz", "-o", str(t / "e")], 1,
     ["p.npz", "damaged or incomplete"]),
    ("learn-duplicate-joint", lambda w, t: [
        "learn", "--calibration", str(w["d"] / "calibration.toml"), "--labels", *map(str, w["dlc"]),
        "--model", str(text(t, "d.toml", _toml.dumps(_dup(w["sk"], "joints")))),
        "-o", str(t / "l.toml")], 1, ["repeats the name"]),
    ("model-save-exists", lambda w, t: ["model", "rat", "--save", str(text(t, "m.toml", "x"))], 1,
     ["m.toml exists", "--overwrite"]),
    ("plot-output-has-files", lambda w, t: [
        "plot", str(w["d"] / "pose.npz"), "-o", str(_folder_with_file(t / "figs2"))], 1,
     ["holds files already", "--overwrite"]),
    ("gapfill-eval-results-exist", lambda w, t: [
        "gapfill-eval", str(w["d"] / "good.trc"), "--out", str(_folder_with_file(t / "ev", "gapfill_eval.json"))], 1,
     ["gapfill_eval.json exists", "--overwrite"]),
    ("learn-output-exists", lambda w, t: [
        "learn", "--calibration", str(w["d"] / "calibration.toml"), "--labels", *map(str, w["dlc"]),
        "-o", str(text(t, "l.toml", "x"))], 1, ["l.toml exists", "--overwrite"]),
    ("track-binary-calibration", lambda w, t: [
        "track", "--calibration", str(text(t, "c.toml", b"\x00\xff\xfe" * 30)), "--dlc", *map(str, w["dlc"]),
        "-o", str(t / "s")], 1, ["c.toml", "not a text file"]),
]  # fmt: skip


@pytest.mark.parametrize("case", CLI_CASES, ids=[c[0] for c in CLI_CASES])
def test_bad_command_line_exits_with_a_message(case, w, tmp_path, capsys):
    _, argv, code, words = case
    args = argv(w, tmp_path)
    before = set(tmp_path.iterdir())
    assert main(args) == code
    err = capsys.readouterr().err
    for word in words:
        assert re.search(re.escape(word), err), f"{word!r} not in: {err}"
    assert "Traceback" not in err and "allow_pickle" not in err
    made = {p for p in set(tmp_path.iterdir()) - before if not p.name.startswith(("c.", "p.", "f"))}
    assert not {p for p in made if p.suffix in (".trc", ".npz", ".c3d", ".csv", ".json")}, made


# ---- results: masks, metadata, permissions


def test_a_partial_point_keeps_its_observed_coordinates(w):
    X = w["X"].copy()
    X[20, 2, 0] = np.nan  # x missing, y and z observed
    res = fill(X, full_output=True, method="spline")
    assert res.filled[20, 2, 1] == X[20, 2, 1] and res.filled[20, 2, 2] == X[20, 2, 2]
    assert np.isfinite(res.filled[20, 2, 0])
    assert res.imputed[20, 2].tolist() == [True, False, False]
    obs = ~np.isnan(X)
    np.testing.assert_array_equal(res.filled[obs], X[obs])


@pytest.mark.parametrize("ext", ["c3d", "trc", "csv"])
def test_filled_values_are_marked_and_metadata_kept(w, tmp_path, capsys, ext):
    out = tmp_path / f"f.{ext}"
    src = w["d"] / ("good.c3d" if ext == "c3d" else "good.trc")
    assert main(["gapfill", str(src), "-o", str(out), "--method", "spline"]) == 0
    m = read(out)
    assert m.labels == w["labels"] and m.rate == 100.0 and m.units == "mm"
    assert m.filled is not None and m.filled.sum() == 4 and m.filled[10:14, 1].all()
    obs = ~np.isnan(w["X"])
    np.testing.assert_allclose(m.xyz[obs], w["X"][obs], rtol=1e-6 if ext == "c3d" else 0)


def test_c3d_to_csv_keeps_labels_rate_and_units(w, tmp_path):
    m = read(w["d"] / "good.c3d")
    write_like(tmp_path / "x.csv", m, m.xyz)
    back = read(tmp_path / "x.csv")
    assert (back.labels, back.rate, back.units) == (m.labels, 100.0, "mm")
    assert (tmp_path / "x.csv").read_text().startswith("m0_x,m0_y,m0_z,m1_x")


def test_c3d_residuals_tell_filled_from_measured(w, tmp_path):
    m = read(w["d"] / "good.c3d")
    filled = np.zeros(m.xyz.shape[:2], bool)
    filled[10:14, 1] = True
    xyz = np.nan_to_num(m.xyz, nan=1.0)
    xyz[0, 3] = np.nan
    write_like(tmp_path / "r.c3d", m, xyz, filled=filled)
    # residuals as the C3D specification stores them (ezc3d 1.7.2 swaps the bytes)
    res = read(tmp_path / "r.c3d").source["residual"]
    assert (res[10:14, 1] == 0).all() and res[0, 3] == -1
    measured = ~filled & ~np.isnan(xyz[:, :, 0])
    assert (res[measured] > 0).all()


def test_c3d_round_trips_200000_frames_exactly(tmp_path):
    n = 200_000
    X = (np.random.default_rng(3).normal(size=(n, 2, 3)) * 500).astype(np.float32).astype(float)
    X[65530:65540, 1] = np.nan
    write(tmp_path / "long.c3d", X, ["a", "b"], 1000.0)
    m = read_c3d(tmp_path / "long.c3d")
    assert m.xyz.shape == (n, 2, 3) and m.rate == 1000.0
    np.testing.assert_array_equal(m.xyz, X)
    c = ezc3d.c3d(str(tmp_path / "long.c3d"))
    assert c["parameters"]["POINT"]["LONG_FRAMES"]["value"][0] == n
    end = c["parameters"]["TRIAL"]["ACTUAL_END_FIELD"]["value"]
    assert int(end[1]) * 65536 + int(end[0]) == n
    # and a cut copy of the long file is refused, not read short
    with pytest.raises(ValueError, match=f"declares {n} frames"):
        read_c3d(cut(tmp_path / "long.c3d", tmp_path / "cut.c3d", 0.7))


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_outputs_get_the_permissions_of_a_normal_new_file(tmp_path, umask):
    old = os.umask(umask)
    try:
        for ext in ("c3d", "trc", "csv"):
            write(tmp_path / f"p.{ext}", _seq(5, 1), ["a"], 50.0)
        _pose_npz(tmp_path / "unused.npz")
        from acm_rs._io import atomic_write

        with atomic_write(tmp_path / "a.txt") as fh:
            fh.write("x")
    finally:
        os.umask(old)
    for name in ("p.c3d", "p.trc", "p.csv", "p.trc.acm.json", "a.txt"):
        assert (tmp_path / name).stat().st_mode & 0o777 == 0o666 & ~umask, name


# ---- interruption and exit codes


def test_ctrl_c_exits_130_and_writes_nothing(w, tmp_path, monkeypatch, capsys):
    import acm_rs.gapfill.filling as gf

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(gf, "fill", interrupted)
    assert main(_g(w, tmp_path, "-o", str(tmp_path / "o.trc"))) == 130
    assert "interrupted" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


@pytest.mark.filterwarnings("ignore:the best-detected frames")  # random detections
def test_interrupted_track_exits_130_marks_the_result_and_exports_nothing(
    w, tmp_path, monkeypatch, capsys
):
    import sys

    tr = sys.modules["acm_rs.tracking.any_length"]  # the command line's track()
    real = tr.track

    def stopped(*a, **k):
        res = real(*a, **k)
        res.info["interrupted"] = True  # as after Ctrl-C during EM
        return res

    monkeypatch.setattr(tr, "track", stopped)
    out = tmp_path / "s"
    argv = _track(w, tmp_path, "-o", str(out), "--export", "anipose", "--frames", "0:4")
    assert main(argv) == 130
    assert "interrupted" in capsys.readouterr().err
    assert not out.with_suffix(".npz").exists() and not (tmp_path / "s_3d.csv").exists()
    res = acm_rs.PoseResult.load(tmp_path / "s_interrupted.npz")
    assert res.info["interrupted"] is True


def test_a_bug_is_reported_as_an_internal_error_without_a_traceback(
    w, tmp_path, monkeypatch, capsys
):
    import acm_rs.gapfill.filling as gf

    def bug(*a, **k):
        raise KeyError("oops")

    monkeypatch.setattr(gf, "fill", bug)
    assert main(_g(w, tmp_path, "-o", str(tmp_path / "o.trc"))) == 1
    err = capsys.readouterr().err
    assert "internal error: KeyError" in err and "--debug" in err and "Traceback" not in err


def test_numerical_error_in_gapfill_is_one_line_and_debug_shows_the_traceback(
    w, tmp_path, monkeypatch, capsys
):
    import acm_rs.gapfill.filling as gf

    def broken(*a, **k):
        raise acm_rs.AcmNumericalError("covariance not positive definite")

    monkeypatch.setattr(gf, "fill", broken)
    assert main(_g(w, tmp_path, "-o", str(tmp_path / "o.trc"))) == 1
    err = capsys.readouterr().err
    assert "good.trc" in err and "spline" in err and "Traceback" not in err
    assert main(["--debug", *_g(w, tmp_path, "-o", str(tmp_path / "o.trc"))]) == 1
    assert "Traceback" in capsys.readouterr().err


# ---- workflow records


def test_step_records_notice_changes_and_interruptions(tmp_path):
    src, out = tmp_path / "in.txt", tmp_path / "out.txt"
    src.write_text("a")
    fresh = prov.fresh_record("s", {"in": src}, {"k": 1})
    assert prov.stale(out, fresh) == "out.txt does not exist yet"
    out.write_text("made outside")
    assert prov.stale(out, fresh) is None  # no record: kept
    prov.write_record(out, fresh)
    assert prov.stale(out, prov.fresh_record("s", {"in": src}, {"k": 1})) is None
    assert "settings changed: k" in prov.stale(out, prov.fresh_record("s", {"in": src}, {"k": 2}))
    src.write_text("b")
    assert "input(s) changed: in" in prov.stale(out, prov.fresh_record("s", {"in": src}, {"k": 1}))
    prov.write_record(out, fresh, interrupted=True)
    assert prov.stale(out, fresh) == "the last run was interrupted"
    # a re-made input (new run id, same bytes) invalidates what was made from it
    down = tmp_path / "down.txt"
    down.write_text("d")
    prov.write_record(out, fresh)
    prov.write_record(down, prov.fresh_record("d", {"out": out}, {}))
    assert prov.stale(down, prov.fresh_record("d", {"out": out}, {})) is None
    prov.write_record(out, fresh)
    assert "input(s) changed: out" in prov.stale(down, prov.fresh_record("d", {"out": out}, {}))


def test_export_refuses_a_pose_of_an_interrupted_track(tmp_path):
    from acm_rs import pipeline

    pose = _pose_npz(tmp_path / "pose.npz")
    prov.write_record(pose, prov.fresh_record("track s", {}, {}), interrupted=True)
    with pytest.raises(ValueError, match="interrupted track step; run track again"):
        pipeline._check_finished(pose, "export s")


def test_labels_of_several_cameras_with_a_cut_file(w, tmp_path):
    paths = [*w["dlc"][:-1], cut(w["dlc"][-1], tmp_path / "last.csv", 0.8)]
    with pytest.raises(ValueError, match=r"last\.csv: line \d+ has"):
        read_labels(paths)


# ---- the Rust binary acm-gapfill (skipped unless built: cargo build --release)

BIN_DIR = Path(
    os.environ.get("ACM_RS_BIN_DIR", Path(__file__).resolve().parents[1] / "target" / "release")
)


@pytest.mark.skipif(not (BIN_DIR / "acm-gapfill").exists(), reason="acm-gapfill not built")
def test_acm_gapfill_binary_follows_the_same_policy(w, tmp_path):
    import subprocess

    def run(*args):
        return subprocess.run(
            [str(BIN_DIR / "acm-gapfill"), *map(str, args)],
            capture_output=True,
            text=True,
            check=False,
        )

    src = w["d"] / "good.trc"
    X = w["X"].copy()
    X[20, 2, 0] = np.nan  # a partial point
    write(tmp_path / "p.trc", X, w["labels"], 100.0)
    cutf = cut(src, tmp_path / "cut.trc", 0.5)
    r = run(cutf, tmp_path / "o.csv")
    assert r.returncode == 1 and "cut.trc" in r.stderr and "no line end" in r.stderr
    assert not (tmp_path / "o.csv").exists()
    r = run(tmp_path / "p.trc", tmp_path / "keep.csv", "--method", "spline")  # TRC in, CSV out
    assert r.returncode == 0, r.stderr
    m = read(tmp_path / "keep.csv")  # a real CSV with the labels and the sidecar
    assert m.labels == w["labels"] and m.rate == 100.0
    obs = ~np.isnan(X)
    np.testing.assert_array_equal(m.xyz[obs], X[obs])
    assert m.filled[20, 2] and m.filled[10:14, 1].all() and m.filled.sum() == 5
    r = run(tmp_path / "p.trc", tmp_path / "keep.csv")
    assert r.returncode == 1 and "pass --overwrite" in r.stderr
    r = run(w["d"] / "plain.csv", tmp_path / "x.trc")
    assert r.returncode == 1 and "needs a frame rate" in r.stderr
    assert (tmp_path / "keep.csv").stat().st_mode & 0o777 == 0o666 & ~_umask()


def _umask() -> int:
    old = os.umask(0)
    os.umask(old)
    return old
