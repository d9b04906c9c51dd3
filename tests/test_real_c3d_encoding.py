"""C3D bytes as the specification puts them, checked with two independent readers.

The fourth word of a C3D point holds the camera mask in its high byte and the residual
(x |POINT:SCALE|) in its low byte (C3D User Guide; py-c3d, BTK/Mokka and Vicon read it so).
ezc3d 1.7.2 reads the two bytes the other way round, so where the two readers differ they must
differ exactly by that swap. Real files: ``tests/data/real/c3d/`` (PROVENANCE.md).
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

ezc3d = pytest.importorskip("ezc3d")
c3d = pytest.importorskip("c3d")  # py-c3d

from acm_rs.gapfill import c3d_stream  # noqa: E402
from acm_rs.gapfill.io import read_c3d, write, write_like  # noqa: E402

REAL = Path(__file__).resolve().parent / "data" / "real" / "c3d"


def pyc3d(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """py-c3d's reading: xyz (n_frames, n_points, 3) NaN where invalid, residual (-1 invalid),
    camera byte, POINT:RATE, header scale (py-c3d refuses a header scale unlike POINT:SCALE)."""
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "No analog data found in file."
        r = c3d.Reader(fh)
        frames = np.array([p for _, p, _ in r.read_frames()])
        rate, scale = float(r.point_rate), float(r.header.scale_factor)
    xyz = frames[:, :, :3].astype(np.float64)
    res = frames[:, :, 3].astype(np.float64)
    xyz[res < 0] = np.nan
    return xyz, res, frames[:, :, 4].astype(np.int64), rate, scale


def ezc(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """ezc3d's reading: xyz, residual, camera mask (as an integer), POINT:RATE, POINT:SCALE."""
    c = ezc3d.c3d(str(path))
    xyz = c["data"]["points"][:3].transpose(2, 1, 0)
    res = c["data"]["meta_points"]["residuals"][0].T
    bits = c["data"]["meta_points"]["camera_masks"].astype(np.int64)  # (7, points, frames)
    mask = (bits << np.arange(7)[:, None, None]).sum(axis=0).T
    p = c["parameters"]["POINT"]
    return xyz, res, mask, float(p["RATE"]["value"][0]), float(p["SCALE"]["value"][0])


def words(path: Path) -> np.ndarray:
    """The raw fourth words (float values) of an Intel float C3D, (n_frames, n_points)."""
    h = c3d_stream.header_layout(path)
    n = (path.stat().st_size - h["offset"]) // (4 * h["words"])
    raw = np.fromfile(path, "<f4", count=n * h["words"], offset=h["offset"]).reshape(n, -1)
    return raw[:, 3 : 4 * h["n_points"] : 4].astype(np.float64)


def assert_readers_agree(path: Path, n_frames: int) -> None:
    """ezc3d and py-c3d: the same frames, points, validity and rate; the header's scale word is
    POINT:SCALE; residual and camera mask the same bytes, which ezc3d reads swapped."""
    pxyz, pres, pcam, prate, hscale = pyc3d(path)
    exyz, eres, emask, erate, scale = ezc(path)
    assert pxyz.shape == exyz.shape == (n_frames, pxyz.shape[1], 3)
    assert prate == erate and hscale == np.float32(scale)
    np.testing.assert_array_equal(np.isnan(pxyz), np.isnan(exyz))
    np.testing.assert_array_equal(np.nan_to_num(pxyz), np.nan_to_num(exyz))
    ok = pres >= 0
    np.testing.assert_array_equal(eres < 0, ~ok)
    # the same two bytes: py-c3d (by the spec) residual = low byte, camera = high byte
    np.testing.assert_allclose(eres[ok], pcam[ok] * abs(scale), rtol=1e-6)
    np.testing.assert_array_equal(emask[ok], np.rint(pres[ok] / abs(scale)).astype(int) & 0x7F)
    # and acm-rs reads what py-c3d reads
    m = read_c3d(path)
    np.testing.assert_array_equal(np.isnan(m.xyz), np.isnan(pxyz))
    np.testing.assert_allclose(m.source["residual"], pres, rtol=1e-6)
    np.testing.assert_array_equal(m.source["camera_mask"][ok], pcam[ok])


# ---- real files ----------------------------------------------------------------------------


@pytest.mark.filterwarnings("ignore:.*LABELS has")  # the sample lists spare labels
def test_c3d_org_sample_is_read_by_the_specification():
    """Eb015pr.c3d (c3d.org, Intel float): point 1 of frame 1 is the User Guide's example word
    0x3E10 (cameras 2-6, residual 16 x 0.0833 = 1.333); acm-rs reads every word as py-c3d."""
    p = REAL / "Eb015pr.c3d"
    w = words(p)
    assert int(w[0, 0]) == 0x3E10
    m = read_c3d(p)
    assert m.source["camera_mask"][0, 0] == 0x3E
    assert m.source["residual"][0, 0] == pytest.approx(16 * 0.0833333, rel=1e-5)
    _, pres, pcam, _, _ = pyc3d(p)
    ok = pres >= 0
    assert ok.sum() > 10_000 and (pcam[ok] > 0).mean() > 0.9  # measured points with cameras
    np.testing.assert_allclose(m.source["residual"], pres, rtol=1e-6)
    np.testing.assert_array_equal(m.source["camera_mask"][ok], pcam[ok])
    # ezc3d 1.7.2 reads the same word swapped: residual 62 x 0.0833, camera bit 4 (0x10)
    _, eres, emask, _, _ = ezc(p)
    assert eres[0, 0] == pytest.approx(62 * 0.0833333, rel=1e-5) and emask[0, 0] == 0x10


def test_big_endian_c3d_is_refused_in_one_line():
    """Eb015sr.c3d is the same recording in SGI/MIPS (big-endian) format: py-c3d reads it (the
    same points as the Intel file), ezc3d 1.7.2 cannot, and acm-rs says so in one line."""
    pxyz, pres, _, _, _ = pyc3d(REAL / "Eb015sr.c3d")
    ixyz, ires, _, _, _ = pyc3d(REAL / "Eb015pr.c3d")
    np.testing.assert_array_equal(np.nan_to_num(pxyz), np.nan_to_num(ixyz))
    np.testing.assert_array_equal(pres, ires)
    with pytest.raises(ValueError, match=r"big-endian \(SGI/MIPS") as e:
        read_c3d(REAL / "Eb015sr.c3d")
    assert "\n" not in str(e.value)


def test_gap_filled_qualisys_file_keeps_measured_residuals_and_masks_bit_for_bit(tmp_path):
    """Qualisys.c3d (QTM, ezc3d's test files): measured residuals 0.08-4.8 mm in the low byte
    (ezc3d 1.7.2 reads them all as 0). Gap-filled and written back: every measured point keeps
    its fourth word bit for bit, filled points get word 0 (C3D: computed, no camera), and both
    readers agree on the output."""
    src = REAL / "Qualisys.c3d"
    m = read_c3d(src)
    res0 = m.source["residual"]
    measured = res0 > 0
    assert measured.mean() > 0.5 and res0[measured].max() == pytest.approx(4.8, abs=0.1)
    assert (ezc(src)[1][measured] == 0).all()  # what ezc3d 1.7.2 makes of them
    xyz = m.xyz.copy()
    j = int(np.flatnonzero(measured.all(axis=0))[0])  # a marker measured in every frame
    xyz[100:120, j] = np.nan  # a gap ...
    t = np.arange(100, 120)
    for k in range(3):  # ... filled by a straight line
        xyz[t, j, k] = np.interp(t, [99, 120], xyz[[99, 120], j, k])
    filled = np.zeros(xyz.shape[:2], bool)
    filled[100:120, j] = True
    out = tmp_path / "filled.c3d"
    write_like(out, m, xyz, filled=filled)
    keep = measured & ~filled
    np.testing.assert_array_equal(words(out)[keep], words(src)[keep])
    assert (words(out)[filled] == 0).all()
    assert_readers_agree(out, m.xyz.shape[0])
    back = read_c3d(out)
    np.testing.assert_array_equal(back.filled, filled)
    np.testing.assert_array_equal(back.source["camera_mask"][keep], m.source["camera_mask"][keep])
    np.testing.assert_array_equal(back.source["residual"][keep], res0[keep])


# ---- every writer ----------------------------------------------------------------------------


def _markers(n_frames: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = (rng.normal(size=(n_frames, 2, 3)) * 300).astype(np.float32).astype(np.float64)
    x[3:7, 1] = np.nan
    return x


def test_new_file_is_read_alike_by_ezc3d_and_py_c3d(tmp_path):
    x = _markers(50)
    write(tmp_path / "a.c3d", x, ["a", "b"], 120.0)
    assert_readers_agree(tmp_path / "a.c3d", 50)
    pxyz, pres, pcam, _, _ = pyc3d(tmp_path / "a.c3d")
    np.testing.assert_array_equal(np.nan_to_num(pxyz), np.nan_to_num(x))
    # measured, residual unknown: 1 (POINT:SCALE -1), no camera; missing: -1
    assert set(np.unique(pres)) == {-1.0, 1.0} and (pcam[pres > 0] == 0).all()


@pytest.mark.parametrize("blocks", [False, True])
def test_copy_with_fills_is_read_alike(tmp_path, monkeypatch, blocks):
    """write_like, whole (ezc3d writes, acm-rs rewrites the fourth words) and in blocks."""
    x = _markers(40, seed=1)
    write(tmp_path / "a.c3d", x, ["a", "b"], 100.0)
    if blocks:
        monkeypatch.setattr(c3d_stream, "STREAM_BYTES", 0)
    m = read_c3d(tmp_path / "a.c3d")
    assert (m.source["frames_at"] is not None) == blocks
    y = np.nan_to_num(m.xyz, nan=5.0)
    filled = np.isnan(m.xyz[:, :, 0])
    write_like(tmp_path / "b.c3d", m, y, filled=filled)
    assert_readers_agree(tmp_path / "b.c3d", 40)
    _, pres, _, _, _ = pyc3d(tmp_path / "b.c3d")
    np.testing.assert_array_equal(pres == 0, filled)
    np.testing.assert_array_equal(read_c3d(tmp_path / "b.c3d").filled, filled)


def test_export_to_c3d_is_read_alike(tmp_path):
    from acm_fixture import synthetic_result

    from acm_rs import export

    res = synthetic_result(n_frames=6, seed=3)
    res.markers[2, 4] = np.nan
    res.detections[:, 0, 1] = np.nan  # marker 1 unseen in frame 0 -> placed by the model
    path = export.to_c3d(res, tmp_path / "t.c3d", rate=60.0, joints=True)
    assert_readers_agree(path, 6)
    _, pres, _, _, _ = pyc3d(path)
    assert pres[0, 1] == 0 and pres[0, 0] == 1 and pres[2, 4] == -1


# ---- long files ------------------------------------------------------------------------------


def test_70000_frames_are_read_whole_by_ezc3d_and_py_c3d(tmp_path):
    """ezc3d 1.7.2 read acm-rs's long files as 65,535 frames (issue 27 item 6). Now both
    readers get every frame and every value (write, and a gap-filled write_like copy)."""
    n = 70_000
    x = _markers(n, seed=2)
    x[65530:65540, 0] = np.nan
    write(tmp_path / "a.c3d", x, ["a", "b"], 200.0)
    exyz = ezc(tmp_path / "a.c3d")[0]
    assert exyz.shape == (n, 2, 3)
    np.testing.assert_array_equal(np.nan_to_num(exyz), np.nan_to_num(x))
    m = read_c3d(tmp_path / "a.c3d")
    y = np.nan_to_num(m.xyz, nan=7.0)
    filled = np.isnan(m.xyz[:, :, 0])
    write_like(tmp_path / "b.c3d", m, y, filled=filled)
    assert_readers_agree(tmp_path / "b.c3d", n)
    np.testing.assert_array_equal(ezc(tmp_path / "b.c3d")[0], y)
    np.testing.assert_array_equal(read_c3d(tmp_path / "b.c3d").filled, filled)


# ---- files of older acm-rs versions ----------------------------------------------------------


def test_file_of_an_older_acm_rs_is_still_decoded_right(tmp_path):
    """acm-rs before ACM_RS:WORD4 wrote through ezc3d (residual in the high byte) with
    ACM_RS:FILLED_RESIDUAL: such a file reads back with its residuals and filled points."""
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = ["a", "b"]
    pts = np.ones((4, 2, 5))
    pts[:3] = np.arange(30).reshape(3, 2, 5) + 1.0
    res = np.array([[[1.0, 0.0, 1.0, 3.0, 1.0], [1.0, 1.0, -1.0, 0.0, 2.0]]])
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {"residuals": res, "camera_masks": np.zeros((7, 2, 5), bool)}
    c.add_parameter("ACM_RS", "FILLED_RESIDUAL", [0.0])
    c.write(str(tmp_path / "old.c3d"))
    assert int(words(tmp_path / "old.c3d")[3, 0]) == 3 << 8  # the old layout
    m = read_c3d(tmp_path / "old.c3d")
    np.testing.assert_array_equal(m.source["residual"], res[0].T)
    np.testing.assert_array_equal(m.filled, res[0].T == 0)


def test_header_scale_word_is_point_scale(tmp_path):
    """ezc3d writes -1 in the header whatever POINT:SCALE says; py-c3d then refuses the file."""
    m = read_c3d(REAL / "Qualisys.c3d")
    write_like(tmp_path / "q.c3d", m, m.xyz)
    head = (tmp_path / "q.c3d").read_bytes()[:16]
    scale = ezc(tmp_path / "q.c3d")[4]
    assert struct.unpack("<f", head[12:16])[0] == np.float32(scale) and scale < 0
    assert scale == pytest.approx(-0.0762322545)
