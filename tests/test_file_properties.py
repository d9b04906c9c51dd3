# ruff: noqa: E501 - one strategy per line
"""Property-based tests (hypothesis) of the file readers and writers (issue 14): round trips
of random marker data through C3D, TRC and CSV; every truncation of a marker file or a pose
NPZ, and random byte corruption of a pose NPZ, is refused or reads back complete and equal.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("hypothesis")
pytest.importorskip("ezc3d")

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra.numpy import arrays  # noqa: E402

from acm_rs.gapfill.io import read, write  # noqa: E402
from acm_rs.tracking.result_npz import NPZ_FORMAT, read_npz  # noqa: E402


def cut(src, dst, frac: float):
    """A copy of ``src`` with only the first ``frac`` of its bytes."""
    b = src.read_bytes()
    dst.write_bytes(b[: int(len(b) * frac)])
    return dst


def _pose_npz(path):
    """The smallest file :func:`read_npz` accepts, with a (50, 4, 3) ``joints`` array."""
    np.savez_compressed(
        path, format=np.array(NPZ_FORMAT), version=np.array(1), units=np.array("cm"),
        skeleton_toml=np.array(""), calibration_toml=np.array(""), info_json=np.array("{}"),
        joints=np.arange(600.0).reshape(50, 4, 3),
    )  # fmt: skip
    return path


_finite = st.floats(-1e6, 1e6, allow_nan=False, width=32)
_markers = arrays(
    np.float64, st.tuples(st.integers(2, 12), st.integers(1, 4), st.just(3)),
    elements=st.one_of(_finite, st.just(np.nan)),
)  # fmt: skip
_names = st.lists(
    st.text("abcdefghijklmnopqrstuvwxyz_0123456789", min_size=1, max_size=8).filter(
        lambda s: not s[0].isdigit()
    ),
    min_size=4, max_size=4, unique=True,
)  # fmt: skip
_settings = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@_settings
@given(
    X=_markers,
    names=_names,
    rate=st.floats(1, 2000, allow_nan=False),
    ext=st.sampled_from(["trc", "csv", "c3d"]),
)
def test_marker_files_round_trip(tmp_path, X, names, rate, ext):
    labels = names[: X.shape[1]]
    p = tmp_path / f"h.{ext}"
    write(p, X, labels, rate)
    m = read(p)
    assert m.labels == labels and m.units == "mm"
    assert m.rate == pytest.approx(rate, rel=1e-6 if ext == "c3d" else 1e-12)
    if ext == "c3d":  # a C3D point is valid or not as a whole: partial points are missing
        X = np.where(np.isnan(X).any(axis=2, keepdims=True), np.nan, X)
    np.testing.assert_array_equal(m.xyz, X)  # float32-exact values, NaN where missing


@_settings
@given(
    X=_markers,
    frac=st.floats(0.0, 1.0, exclude_max=True),
    ext=st.sampled_from(["trc", "csv", "c3d"]),
)
def test_every_truncation_is_refused_or_complete(tmp_path, X, frac, ext):
    labels = [f"m{i}" for i in range(X.shape[1])]
    p = tmp_path / f"t.{ext}"
    write(p, X, labels, 100.0)
    full = read(p)
    q = cut(p, tmp_path / f"cut.{ext}", frac)
    if ext != "c3d" and (tmp_path / f"t.{ext}.acm.json").exists():
        (tmp_path / f"cut.{ext}.acm.json").write_text((tmp_path / f"t.{ext}.acm.json").read_text())
    try:
        m = read(q)
    except ValueError:
        return
    # C3D files are padded to 512-byte blocks: a cut inside the padding keeps every frame
    np.testing.assert_array_equal(m.xyz, full.xyz)


@_settings
@given(
    frac=st.floats(0.0, 1.0, exclude_max=True), pos=st.integers(0, 10**6), byte=st.integers(0, 255)
)
def test_pose_npz_truncated_or_corrupted_is_refused_or_identical(tmp_path, frac, pos, byte):
    p = _pose_npz(tmp_path / "pose.npz")
    full = read_npz(p)
    with pytest.raises(ValueError):
        read_npz(cut(p, tmp_path / "cut.npz", frac))
    b = bytearray(p.read_bytes())
    b[pos % len(b)] = byte
    (tmp_path / "bad.npz").write_bytes(bytes(b))
    try:
        got = read_npz(tmp_path / "bad.npz")
    except ValueError:
        return
    np.testing.assert_array_equal(got["joints"], full["joints"])


@_settings
@given(pos=st.integers(0, 1535), byte=st.integers(0, 255))
def test_a_corrupted_c3d_header_or_parameter_byte_never_crashes(tmp_path, pos, byte):
    # ezc3d crashes the process on some damaged parameter sections; read_c3d checks the
    # header, the section links, types, sizes and group ids before handing the file over
    X = np.arange(30.0).reshape(5, 2, 3)
    write(tmp_path / "c.c3d", X, ["a", "b"], 100.0)
    b = bytearray((tmp_path / "c.c3d").read_bytes())
    b[pos] = byte
    (tmp_path / "bad.c3d").write_bytes(bytes(b))
    try:
        m = read(tmp_path / "bad.c3d")
    except ValueError:
        return
    assert m.xyz.ndim == 3 and m.xyz.shape[2] == 3
