"""C3D in blocks (acm_rs.gapfill.c3d_stream): the same values and bytes as the whole-file path."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ezc3d = pytest.importorskip("ezc3d")

from acm_rs.gapfill import c3d_stream  # noqa: E402
from acm_rs.gapfill.io import read_c3d, write, write_like  # noqa: E402

MOCAP = Path(__file__).resolve().parents[2] / "shared/data/mocap"


def _make(path: Path, n_frames=60, n_points=3, analog_ratio=4, seed=0) -> None:
    """A C3D as ezc3d writes it: residuals of several sizes, missing points, camera masks,
    3 analog channels sampled ``analog_ratio`` times per frame with non-unit scales."""
    rng = np.random.default_rng(seed)
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = [f"m{i}" for i in range(n_points)]
    c["parameters"]["POINT"]["SCALE"]["value"] = [-0.1]
    pts = np.ones((4, n_points, n_frames))
    pts[:3] = rng.normal(size=(3, n_points, n_frames)) * 300
    res = rng.choice([0.0, 0.5, 1.2, 3.0, 17.3], size=(1, n_points, n_frames))
    gap = min(1, n_points - 1)  # the marker with a gap
    res[0, gap, 10:20] = -1.0
    pts[:3, gap, 10:20] = np.nan
    masks = rng.random((7, n_points, n_frames)) < 0.3
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {"residuals": res, "camera_masks": masks}
    if analog_ratio:
        c["parameters"]["ANALOG"]["RATE"]["value"] = [100.0 * analog_ratio]
        c["parameters"]["ANALOG"]["LABELS"]["value"] = ["fx", "fy", "fz"]
        c["parameters"]["ANALOG"]["USED"]["value"] = [3]
        c["data"]["analogs"] = rng.normal(size=(1, 3, n_frames * analog_ratio))
    c.write(str(path))
    if analog_ratio:  # non-unit channel scales, as force plates have
        c = ezc3d.c3d(str(path))
        c["parameters"]["ANALOG"]["SCALE"]["value"] = [0.5, 2.0, 0.25]
        c.write(str(path))


@pytest.fixture
def streamed(monkeypatch):
    """Make every C3D go through the block reader and writer."""
    monkeypatch.setattr(c3d_stream, "STREAM_BYTES", 0)


def _sources(tmp_path):
    _make(tmp_path / "made.c3d")
    yield tmp_path / "made.c3d"
    for name in ("135_02.c3d", "85_02.c3d"):  # real CMU files, when ../shared is there
        if (MOCAP / name).is_file():
            yield MOCAP / name


def test_block_reader_reads_what_ezc3d_reads(tmp_path, monkeypatch):
    for src in _sources(tmp_path):
        whole = read_c3d(src)
        assert whole.source["frames_at"] is None  # small files: ezc3d whole
        monkeypatch.setattr(c3d_stream, "STREAM_BYTES", 0)
        blocks = read_c3d(src)
        monkeypatch.undo()
        assert blocks.source["frames_at"] is not None
        np.testing.assert_array_equal(blocks.xyz, whole.xyz)
        np.testing.assert_array_equal(blocks.source["residual"], whole.source["residual"])
        assert (blocks.labels, blocks.rate, blocks.units) == (whole.labels, whole.rate, whole.units)


def test_block_writer_writes_the_bytes_ezc3d_writes(tmp_path, monkeypatch):
    for i, src in enumerate(_sources(tmp_path)):
        m = read_c3d(src)
        xyz = m.xyz.copy()
        xyz[3:7, 0] = np.nan  # a new gap
        filled = np.zeros(xyz.shape[:2], bool)
        filled[1:3, 2] = True
        xyz[40:44, 1] = 5.0  # a value that was missing, now filled
        filled[40:44, 1] = True
        write_like(tmp_path / f"e{i}.c3d", m, xyz, filled=filled)
        monkeypatch.setattr(c3d_stream, "STREAM_BYTES", 0)
        write_like(tmp_path / f"s{i}.c3d", read_c3d(src), xyz, filled=filled)
        monkeypatch.undo()
        a = (tmp_path / f"e{i}.c3d").read_bytes()
        b = (tmp_path / f"s{i}.c3d").read_bytes()
        assert len(a) == len(b) and a == b, src


def test_file_read_in_blocks_for_its_analogs_is_written_in_blocks(tmp_path, monkeypatch):
    """Few points, many analog words: the data section is over the threshold, the points
    alone are not; the copy must still take the frames (and analogs) from the source."""
    _make(tmp_path / "a.c3d", n_frames=60, n_points=1, analog_ratio=4)  # 960 + 2880 bytes
    m = read_c3d(tmp_path / "a.c3d")
    write_like(tmp_path / "e.c3d", m, m.xyz)
    monkeypatch.setattr(c3d_stream, "STREAM_BYTES", 1000)
    s = read_c3d(tmp_path / "a.c3d")
    assert s.source["frames_at"] is not None
    write_like(tmp_path / "s.c3d", s, s.xyz)
    assert (tmp_path / "s.c3d").read_bytes() == (tmp_path / "e.c3d").read_bytes()
    back = ezc3d.c3d(str(tmp_path / "s.c3d"))
    np.testing.assert_array_equal(
        back["data"]["analogs"], ezc3d.c3d(str(tmp_path / "a.c3d"))["data"]["analogs"]
    )


def test_fourth_words_follow_the_c3d_specification():
    """Camera mask in the high byte, residual (x |POINT:SCALE|) in the low byte (C3D User
    Guide: 0x3E10 = cameras 2-6, residual 16 x 0.0833); negative = invalid; 0 = computed."""
    words = np.array([0x3E10, 0x0001, 0x7F0C, 0.0, -1.0, 0x00FF])
    res, mask = c3d_stream.decode_point_words(words, -0.08333333)
    np.testing.assert_allclose(res, [16 / 12, 1 / 12, 1.0, 0, -1, 255 / 12], rtol=1e-6)
    assert mask.tolist() == [0x3E, 0, 0x7F, 0, 0, 0]
    back = c3d_stream.encode_point_words(res, -0.08333333, mask)
    np.testing.assert_array_equal(back, words)
    # a measured residual never becomes 0 (computed); missing stays -1, computed 0
    np.testing.assert_array_equal(
        c3d_stream.encode_point_words(np.array([0.01, 0.0, -1.0, 3.0]), -1.0), [1, 0, -1, 3]
    )
    # files of older acm-rs versions (and ezc3d 1.7.2): residual in the high byte
    res, mask = c3d_stream.decode_point_words(np.array([0x0205]), -1.0, legacy=True)
    assert res.tolist() == [2.0] and mask.tolist() == [5]


def test_long_copy_keeps_measured_and_filled_apart(tmp_path):
    """Over 65535 frames (always in blocks): residual 0 marks only what was filled."""
    n = 70_000
    rng = np.random.default_rng(1)
    X = (rng.normal(size=(n, 2, 3)) * 500).astype(np.float32).astype(float)
    X[100:110, 0] = np.nan
    write(tmp_path / "a.c3d", X, ["a", "b"], 200.0)
    m = read_c3d(tmp_path / "a.c3d")
    assert ezc3d.c3d(str(tmp_path / "a.c3d"))["data"]["points"].shape[2] == n  # ezc3d: all
    Y = m.xyz.copy()
    Y[100:110, 0] = 1.0
    filled = np.zeros((n, 2), bool)
    filled[100:110, 0] = True
    write_like(tmp_path / "b.c3d", m, Y, filled=filled)
    back = read_c3d(tmp_path / "b.c3d")
    np.testing.assert_array_equal(back.xyz, Y)
    np.testing.assert_array_equal(back.filled, filled)
    assert (back.source["residual"][~filled] > 0).all()


def test_long_copy_of_a_file_with_analogs_needs_its_source(tmp_path, streamed):
    _make(tmp_path / "a.c3d")
    m = read_c3d(tmp_path / "a.c3d")
    m.source["frames_at"] = None
    with pytest.raises(ValueError, match="analog channels"):
        write_like(tmp_path / "b.c3d", m, m.xyz)
    assert not (tmp_path / "b.c3d").exists()
    assert not list(tmp_path.glob(".b.*"))  # no temporary file left behind


def test_cut_file_is_refused_by_the_block_reader(tmp_path, streamed):
    _make(tmp_path / "a.c3d", analog_ratio=0)
    data = (tmp_path / "a.c3d").read_bytes()
    (tmp_path / "cut.c3d").write_bytes(data[: len(data) - 700])
    with pytest.raises(ValueError, match="incomplete C3D"):
        read_c3d(tmp_path / "cut.c3d")
