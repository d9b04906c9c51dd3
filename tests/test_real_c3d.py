"""C3D semantics on real files (tests/data/real/c3d, see PROVENANCE.md): which points are
missing and why, which points are markers, which files are refused; each checked against
ezc3d and py-c3d, and through a gapfill round trip."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from acm_rs.gapfill.filling import fill_markers
from acm_rs.gapfill.io import MISSING_NEGATIVE, MISSING_ZERO, read_c3d, write_like

ezc3d = pytest.importorskip("ezc3d")

DATA = Path(__file__).parent / "data" / "real" / "c3d"


def _read(name: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_c3d(DATA / name)


def _ezc3d_xyz(path: Path) -> np.ndarray:
    """(n_frames, n_points, 3) as ezc3d reads it (NaN where its residual is negative)."""
    return np.asarray(ezc3d.c3d(str(path))["data"]["points"])[:3].transpose(2, 1, 0)


def _pyc3d_points(path: Path) -> np.ndarray:
    """(n_frames, n_points, 5) as py-c3d reads it (x, y, z, residual, cameras)."""
    c3d = pytest.importorskip("c3d")
    with open(path, "rb") as fh, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.array([p for _, p, _ in c3d.Reader(fh).read_frames()])


# -- item 1: gaps coded as (0, 0, 0) -------------------------------------------------------


def test_qualisys_zero_coded_gaps_are_missing():
    path = DATA / "Walking_Hybrid_1_1.c3d"
    m = _read("Walking_Hybrid_1_1.c3d")
    ref = _ezc3d_xyz(path)
    zero = (ref == 0).all(axis=2)
    assert zero.mean() == pytest.approx(0.232, abs=0.001)  # 3,902 of 16,800 marker-frames
    # both independent readers see these as valid points (a positive residual)...
    pts = _pyc3d_points(path)
    np.testing.assert_array_equal((pts[:, :, :3] == 0).all(axis=2), zero)
    assert (pts[:, :, 3][zero] > 0).all()
    # ...acm-rs reads them as missing and says why; every other value is ezc3d's
    assert np.isnan(m.xyz[zero]).all()
    np.testing.assert_array_equal(m.xyz[~zero], ref[~zero])
    total = sum(mask for mask in m.missing_reasons.values())
    np.testing.assert_array_equal(total.astype(bool), zero)
    assert (
        int(m.missing_reasons[MISSING_ZERO].sum() + m.missing_reasons[MISSING_NEGATIVE].sum())
        == 3902
    )


def test_qualisys_zero_coded_fill_has_no_jumps(tmp_path):
    m = _read("Walking_Hybrid_1_1.c3d")
    raw = _ezc3d_xyz(DATA / "Walking_Hybrid_1_1.c3d")
    jump_raw = np.nanmax(np.linalg.norm(np.diff(raw, axis=0), axis=2))
    assert jump_raw > 2000  # mm: a marker jumping to the origin and back
    res = fill_markers(m, method="spline")
    jump = np.nanmax(np.linalg.norm(np.diff(res.filled, axis=0), axis=2))
    assert jump < 60  # mm at 240 Hz
    out = tmp_path / "filled.c3d"
    write_like(out, m, res.filled, filled=res.imputed)
    back = read_c3d(out)
    np.testing.assert_allclose(back.xyz, res.filled.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_array_equal(back.filled, res.imputed.any(axis=2))


def test_one_zero_coordinate_is_a_value():
    """Only all three coordinates at exactly 0 are a gap; a marker on a lab plane is not."""
    from acm_rs.gapfill.io import _c3d_missing

    xyz = np.array([[[0.0, 0.0, 0.0], [0.0, 5.0, 0.0], [0.0, 0.0, 0.0]]])
    reasons = _c3d_missing(xyz, np.zeros((1, 3)), np.array([True, True, False]))
    np.testing.assert_array_equal(reasons[MISSING_ZERO], [[True, False, False]])
    assert np.isnan(xyz[0, 0]).all() and xyz[0, 1, 1] == 5.0
    assert (xyz[0, 2] == 0).all()  # not a marker: 0 is a value


# -- item 4: points that are not markers -----------------------------------------------------


def test_plugin_gait_outputs_are_not_markers():
    path = DATA / "PlugInC3D.c3d"
    m = _read("PlugInC3D.c3d")
    point = ezc3d.c3d(str(path))["parameters"]["POINT"]
    listed = {
        kind: {s.strip() for s in point[group]["value"]}
        for group, kind in (("ANGLES", "angle"), ("FORCES", "force"),
                            ("MOMENTS", "moment"), ("POWERS", "power"))
    }  # fmt: skip
    for lab, kind in zip(m.labels, m.kinds, strict=True):
        expect = next((k for k, names in listed.items() if lab.strip() in names), "marker")
        assert kind == expect, lab
    assert int(m.is_marker.sum()) == 54
    # powers at exactly 0 with residual 0 are values, not gaps
    ref = _ezc3d_xyz(path)
    power = np.array([k == "power" for k in m.kinds])
    zero_power = (ref[:, power] == 0).all(axis=2)
    assert zero_power.sum() > 1000
    np.testing.assert_array_equal(m.xyz[:, power][zero_power], 0.0)
    ok = np.isfinite(ref)
    np.testing.assert_array_equal(m.xyz[ok], ref[ok])
    np.testing.assert_array_equal(np.isnan(m.xyz), ~ok)


def test_gapfill_leaves_non_markers_as_read(tmp_path):
    m = _read("PlugInC3D.c3d")
    res = fill_markers(m, method="spline")
    other = ~m.is_marker
    assert sorted(res.skipped) == ["angle", "force", "moment", "power"]
    assert sum(len(v) for v in res.skipped.values()) == 32
    np.testing.assert_array_equal(res.filled[:, other], m.xyz[:, other])  # NaN included
    assert not res.imputed[:, other].any()
    assert res.imputed[:, m.is_marker].any()
    out = tmp_path / "filled.c3d"
    write_like(out, m, res.filled, filled=res.imputed)
    back = _ezc3d_xyz(out)
    np.testing.assert_array_equal(
        back[:, other], m.xyz[:, other].astype(np.float32).astype(np.float64)
    )
    # with the option the outputs are filled too
    every = fill_markers(m, method="spline", include_non_markers=True)
    assert every.imputed[:, other].any() and not every.skipped


def test_cli_output_lines(tmp_path, capsys):
    from acm_rs.cli import main

    main(["gapfill", str(DATA / "PlugInC3D.c3d"), "-o", str(tmp_path / "o.c3d"),
          "--method", "spline"])  # fmt: skip
    text = capsys.readouterr().out
    assert "read as missing: 5,295 marker-frames (negative residual: 5,295)" in text
    assert "skipped 32 non-marker points (angles: 10, forces: 8, moments: 8, powers: 6)" in text
    main(["gapfill", str(DATA / "Walking_Hybrid_1_1.c3d"), "-o", str(tmp_path / "q.c3d"),
          "--method", "spline"])  # fmt: skip
    text = capsys.readouterr().out
    assert "read as missing: 3,902 marker-frames (" in text
    assert "skipped" not in text


def test_model_outputs_only_file_is_refused_unless_asked(tmp_path, capsys):
    from acm_rs.cli import main

    m = _read("Analysis.c3d")
    assert not m.is_marker.any()
    assert main(["gapfill", str(DATA / "Analysis.c3d"), "-o", str(tmp_path / "o.c3d")]) != 0
    assert "Analysis.c3d holds no markers" in capsys.readouterr().err
    assert not (tmp_path / "o.c3d").exists()
    with pytest.raises(ValueError, match="include_non_markers"):
        fill_markers(m)


# -- item 10: more labels than points ---------------------------------------------------------


@pytest.mark.parametrize("name", ["sample02_pc_real.c3d", "sample02_pc_int.c3d"])
def test_labels_beyond_used_are_dropped_and_the_copy_writes(tmp_path, name):
    path = DATA / name
    c = ezc3d.c3d(str(path))
    all_labels = list(c["parameters"]["POINT"]["LABELS"]["value"])
    assert len(all_labels) == 75 and int(c["parameters"]["POINT"]["USED"]["value"][0]) == 36
    with pytest.warns(UserWarning, match="75 entries for 36 POINT:USED"):
        m = read_c3d(path)
    assert m.labels == all_labels[:36]
    ref = _ezc3d_xyz(path)
    np.testing.assert_array_equal(np.isnan(m.xyz), np.isnan(ref))
    np.testing.assert_array_equal(m.xyz[np.isfinite(ref)], ref[np.isfinite(ref)])
    pts = _pyc3d_points(path)
    valid = pts[:, :, 3] >= 0
    np.testing.assert_array_equal(valid, np.isfinite(m.xyz).all(axis=2))
    np.testing.assert_allclose(m.xyz[valid], pts[:, :, :3][valid], atol=1e-3)
    res = fill_markers(m, method="spline")
    out = tmp_path / "filled.c3d"
    write_like(out, m, res.filled, filled=res.imputed)
    back = ezc3d.c3d(str(out))
    assert list(back["parameters"]["POINT"]["LABELS"]["value"]) == all_labels[:36]
    got = np.asarray(back["data"]["points"])[:3].transpose(2, 1, 0)
    np.testing.assert_allclose(got, res.filled, atol=1e-3)


def test_float_and_integer_copies_agree():
    a, b = _read("sample02_pc_real.c3d"), _read("sample02_pc_int.c3d")
    np.testing.assert_array_equal(np.isnan(a.xyz), np.isnan(b.xyz))
    ok = np.isfinite(a.xyz)
    scale = abs(float(ezc3d.c3d(str(DATA / "sample02_pc_int.c3d"))["parameters"]["POINT"]
                      ["SCALE"]["value"][0]))  # fmt: skip
    assert np.abs(a.xyz[ok] - b.xyz[ok]).max() <= scale


# -- refused files ----------------------------------------------------------------------------


def test_header_and_parameters_disagree_refused():
    path = DATA / "sample28_type1.c3d"
    # the independent readers disagree on this file: ezc3d follows the parameters, py-c3d the
    # header, and their points differ by metres
    ref = _ezc3d_xyz(path)
    pts = _pyc3d_points(path)
    both = np.isfinite(ref).all(axis=2) & (pts[:, :, 3] >= 0)
    assert np.abs(ref[both] - pts[:, :, :3][both]).max() > 1000
    with pytest.raises(ValueError, match="header says 118 words per frame and the parameters 112"):
        read_c3d(path)


def test_a_marker_at_the_origin_in_an_acm_rs_file_is_a_measurement(tmp_path):
    """acm-rs codes its gaps by a negative fourth word, so its own files keep a marker at
    exactly (0, 0, 0) (the zero-coded-gap rule is for other writers' files)."""
    from acm_rs.gapfill.io import read, write

    xyz = np.array([[[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], [[np.nan] * 3, [0.0, 0.0, 0.0]]])
    p = tmp_path / "origin.c3d"
    write(p, xyz, ["a", "b"], 100.0)
    np.testing.assert_array_equal(read(p).xyz, xyz)
