"""Gap filling: known answers, the NumPy reference of Burke & Lasenby Alg. 1, ground-truth
recovery on a seeded synthetic sequence, I/O round trips, CLI, and bad input."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from acm_rs.gapfill import METHODS, FillResult, fill
from acm_rs.gapfill.evaluate import evaluate, insert_gaps, run_lengths
from acm_rs.gapfill.io import read, read_c3d, read_csv, read_trc, write, write_like

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(__file__).resolve().parents[2] / "shared"
MOCAP = SHARED / "data" / "mocap"
sys.path.insert(0, str(ROOT / "benches"))
from gapfill_numpy_reference import lowdim_paper  # noqa: E402


def synthetic(n_frames: int = 400, n_markers: int = 12, seed: int = 0) -> np.ndarray:
    """Rigid-ish multi-segment motion: markers are fixed combinations of 4 smooth latent
    trajectories (a low-dimensional sequence, mm), plus 0.1 mm noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / 100.0
    latent = np.stack(
        [
            np.sin(2 * np.pi * f * t + p)
            for f, p in zip([0.5, 0.8, 1.3, 0.3], rng.uniform(0, 6, 4), strict=True)
        ],
        axis=1,
    )
    mix = rng.normal(0, 100, (4, n_markers * 3))
    offset = rng.uniform(-500, 500, n_markers * 3)
    X = latent @ mix + offset + rng.normal(0, 0.1, (n_frames, n_markers * 3))
    return X.reshape(n_frames, n_markers, 3)


@pytest.fixture(scope="module")
def seq() -> np.ndarray:
    return synthetic()


def gapped(X: np.ndarray, seed: int = 1) -> np.ndarray:
    G = X.copy()
    rng = np.random.default_rng(seed)
    for _ in range(25):
        m = rng.integers(X.shape[1])
        L = int(rng.integers(1, 40))
        s = int(rng.integers(1, X.shape[0] - L - 1))
        G[s : s + L, m] = np.nan
    return G


@pytest.mark.parametrize("method", METHODS)
def test_every_method_fills_and_keeps_observed(seq, method):
    G = gapped(seq)
    F = fill(G, method=method)
    assert F.shape == G.shape and np.isfinite(F).all()
    obs = ~np.isnan(G)
    np.testing.assert_array_equal(F[obs], G[obs])


def test_lowdim_recovers_low_rank_ground_truth(seq):
    G = gapped(seq)
    miss = np.isnan(G[:, :, 0])
    err = np.linalg.norm(fill(G) - seq, axis=2)[miss]
    err_lin = np.linalg.norm(fill(G, method="linear") - seq, axis=2)[miss]
    assert np.median(err) < 2.0  # mm, data spans ~±300 mm
    assert err.mean() < 0.25 * err_lin.mean()


def test_linear_and_spline_known_answers():
    t = np.arange(20.0)
    X = np.stack([np.stack([t, t**2, t**3], axis=1)] * 2, axis=1)
    G = X.copy()
    G[5:9, 0] = np.nan
    np.testing.assert_allclose(fill(G, method="linear")[5:9, 0, 0], t[5:9])
    # a natural spline reproduces lines exactly and quadratics closely inside
    F = fill(G, method="spline")
    np.testing.assert_allclose(F[5:9, 0, 0], t[5:9], atol=1e-9)
    np.testing.assert_allclose(F[5:9, 0, 1], t[5:9] ** 2, rtol=2e-2)
    # rw smoother with tiny R is the Brownian-bridge mean: linear interpolation
    np.testing.assert_allclose(fill(G, method="rw")[5:9, 0, 0], t[5:9], atol=1e-6)
    # cv smoother follows a line exactly
    np.testing.assert_allclose(fill(G, method="cv")[5:9, 0, 0], t[5:9], atol=1e-4)


def test_paper_method_equals_numpy_reference(seq):
    G = gapped(seq, seed=3)
    T = G.shape[0]
    ref = lowdim_paper(G.reshape(T, -1)).reshape(G.shape)
    ours = fill(G, method="lowdim-paper", memo_tol=0.0)
    # Equal after the first frames; there the reference's covariance form loses precision with
    # P0 = 1e12 I ((I - K H) P cancels), the information form does not.
    np.testing.assert_allclose(ours[10:], ref[10:], atol=1e-5)
    miss = np.isnan(G[:10, :, 0])
    e_ours = np.linalg.norm(ours[:10] - seq[:10], axis=2)[miss]
    e_ref = np.linalg.norm(ref[:10] - seq[:10], axis=2)[miss]
    assert e_ours.max() <= e_ref.max() + 1e-6


def test_low_rank_states_equal_the_dense_smoother(seq):
    # The published r puts the filter in the small-gain regime: the final pass uses low-rank
    # states (memo_tol > 0, no std requested) and must agree with the exact dense recursion.
    from acm_rs import _native

    G = gapped(seq, seed=5)
    fast = fill(G, method="lowdim-paper")
    exact = fill(G, method="lowdim-paper", memo_tol=0.0)
    scale = np.abs(seq).max()
    np.testing.assert_allclose(fast, exact, rtol=0, atol=1e-6 * scale)

    def info(method, r, memo_tol):
        args = (G.reshape(len(G), -1), method, 0.9975, "singular-values", None, r, 0, True, 0)
        rest = (36, "none", None, True, False, memo_tol, 0)
        return _native.gapfill_fill(*args, *rest)[2]

    assert info("lowdim-paper", 1e-3, 1e-6)["low_rank"]
    assert not info("lowdim-paper", 1e-3, 0.0)["low_rank"]
    # With large gains (r far above the frame-to-frame motion) the dense smoother runs.
    assert not info("lowdim", 1e3, 1e-6)["low_rank"]


def test_paper_q_is_used_when_the_subspace_is_iterated(seq):
    G = gapped(seq)
    G[::2, 0] = np.nan
    G[1::2, 1] = np.nan  # no complete frame: impute, SVD, smooth
    a = fill(G, em_iters=0, full_output=True).info
    b = fill(G, em_iters=0, paper_q=True, full_output=True).info
    assert a["iterated_subspace"] and b["iterated_subspace"]
    assert not np.isclose(a["q_trace"], b["q_trace"], rtol=1e-3)


def test_printed_gain_is_worse_than_rts_gain(seq):
    G = gapped(seq, seed=4)
    T = G.shape[0]
    miss = np.isnan(G[:, :, 0])
    a = lowdim_paper(G.reshape(T, -1)).reshape(G.shape)
    b = lowdim_paper(G.reshape(T, -1), printed_gain=True).reshape(G.shape)
    ea = np.linalg.norm(a - seq, axis=2)[miss].mean()
    eb = np.linalg.norm(b - seq, axis=2)[miss].mean()
    assert ea <= eb + 1e-9


def test_full_output_std_and_mask(seq):
    G = gapped(seq)
    res = fill(G, full_output=True)
    assert isinstance(res, FillResult)
    np.testing.assert_array_equal(res.imputed, np.isnan(G))
    assert res.std is not None
    assert (res.std[~res.imputed] == 0).all() and (res.std[res.imputed] > 0).all()
    # calibration: most errors lie within 3 predicted standard deviations
    z = np.abs(res.filled - seq)[res.imputed] / res.std[res.imputed]
    assert np.mean(z < 3) > 0.8
    assert res.info["dim"] >= 1 and res.info["r"] > 0


def test_no_complete_frames_and_all_missing_frames(seq):
    G = gapped(seq)
    G[::2, 0] = np.nan  # markers 0 and 1 missing in alternate frames: no complete frame left
    G[1::2, 1] = np.nan
    G[100:103] = np.nan  # every marker missing in three frames
    assert not (~np.isnan(G).any(axis=(1, 2))).any()
    res = fill(G, full_output=True)
    assert np.isfinite(res.filled).all() and res.info["iterated_subspace"]
    err = np.linalg.norm(res.filled - seq, axis=2)[np.isnan(G[:, :, 0])]
    assert np.median(err) < 5.0
    with pytest.raises(ValueError, match="complete frames"):
        fill(G, method="lowdim-paper")


def test_fewer_frames_than_markers():
    X = synthetic(n_frames=8, n_markers=12)
    G = X.copy()
    G[3:5, 2] = np.nan
    for method in METHODS:
        if method == "lowdim-paper":
            continue
        assert np.isfinite(fill(G, method=method)).all()


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (np.zeros((10, 4)), "shape"),
        (np.zeros((10, 4, 2)), "shape"),
        (np.zeros((1, 4, 3)), "at least 2 frames"),
        (np.full((10, 4, 3), np.inf), "infinity"),
        (np.full((10, 4, 3), np.nan), "every marker"),
        ("abc", "numeric"),
    ],
)
def test_bad_input(bad, match):
    with pytest.raises(ValueError, match=match):
        fill(bad)


def test_all_nan_marker_error_or_skip(seq):
    G = gapped(seq)
    G[:, 3] = np.nan
    with pytest.raises(ValueError, match=r"marker\(s\) \[3\]"):
        fill(G)
    res = fill(G, empty="skip", full_output=True)
    assert np.isnan(res.filled[:, 3]).all() and not res.imputed[:, 3].any()
    others = np.delete(res.filled, 3, axis=1)
    assert np.isfinite(others).all()


def test_bad_options(seq):
    with pytest.raises(ValueError, match="unknown method"):
        fill(seq, method="magic")
    with pytest.raises(ValueError, match="unknown option"):
        fill(seq, sigma=3)
    with pytest.raises(ValueError, match="gamma"):
        fill(gapped(seq), gamma=1.5)
    with pytest.raises(ValueError, match="combine"):
        fill(gapped(seq), combine="best")


def test_input_is_not_modified_and_partial_markers_keep_observed_coordinates(seq):
    G = gapped(seq)
    G[5, 2, 1] = np.nan  # one coordinate only: estimated as missing, observed x, z kept
    before = G.copy()
    res = fill(G, full_output=True)
    np.testing.assert_array_equal(G, before)  # NaN-aware: the caller's array is untouched
    assert res.imputed[5, 2].tolist() == [False, True, False] and np.isfinite(res.filled).all()
    assert res.filled[5, 2, 0] == G[5, 2, 0] and res.filled[5, 2, 2] == G[5, 2, 2]
    assert res.std[5, 2, 0] == 0 and res.std[5, 2, 1] > 0
    obs = ~np.isnan(G)
    np.testing.assert_array_equal(res.filled[obs], G[obs])  # no observed value changes


def test_no_gaps_is_identity(seq):
    np.testing.assert_array_equal(fill(seq), seq)


def independent_smooth(n_frames: int = 600, n_markers: int = 10, seed: int = 0) -> np.ndarray:
    """Every coordinate an independent sum of 3 slow sinusoids (mm) + 0.1 mm noise: no
    low-dimensional structure, so a subspace smoother cannot beat a spline on short gaps."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)[:, None] / 100.0
    cols = [
        (
            rng.normal(0, 50, 3)
            * np.sin(2 * np.pi * rng.uniform(0.2, 1.5, 3) * t + rng.uniform(0, 6, 3))
        ).sum(axis=1)
        + rng.uniform(-500, 500)
        for _ in range(3 * n_markers)
    ]
    X = np.stack(cols, axis=1) + rng.normal(0, 0.1, (n_frames, 3 * n_markers))
    return X.reshape(n_frames, n_markers, 3)


def mean_error(F: np.ndarray, X: np.ndarray, G: np.ndarray) -> float:
    mask = np.isnan(G[:, :, 0])
    return float(np.linalg.norm(F - X, axis=2)[mask].mean())


def test_auto_combination_keeps_the_smoother_where_it_wins(seq):
    # Exact low rank + 0.1 mm noise: the smoother (0.2 mm) beats the spline (several mm) at
    # every gap length, so the calibrated threshold stays (almost) 0 and the default equals
    # the border-residual fill.
    G = gapped(seq)
    auto = fill(G, full_output=True)
    residual = fill(G, combine="residual")
    assert auto.info["options"]["combine"] == "auto"
    assert auto.info["short_gap"] <= 1
    assert mean_error(auto.filled, seq, G) <= 1.05 * mean_error(residual, seq, G) + 1e-9
    assert mean_error(auto.filled, seq, G) < 0.3
    assert mean_error(fill(G, method="spline"), seq, G) > 1.0


def test_auto_combination_takes_the_spline_where_it_wins():
    # Independent smooth coordinates with short gaps (1-9 frames): the spline wins, the
    # calibration must find a threshold that covers these gaps and the fill must follow it.
    X = independent_smooth()
    G = X.copy()
    rng = np.random.default_rng(5)
    for _ in range(40):
        m, L = rng.integers(X.shape[1]), int(rng.integers(1, 10))
        s = int(rng.integers(1, X.shape[0] - L - 1))
        G[s : s + L, m] = np.nan
    auto = fill(G, full_output=True)
    residual = fill(G, combine="residual")
    spline = fill(G, method="spline")
    assert auto.info["short_gap"] >= 9
    np.testing.assert_allclose(auto.filled, spline, atol=1e-9)
    assert mean_error(auto.filled, X, G) < 0.6 * mean_error(residual, X, G)
    # an explicit threshold overrides the calibration
    assert fill(G, full_output=True, short_gap=0).info["short_gap"] == 0
    np.testing.assert_allclose(fill(G, short_gap=0), residual, atol=1e-9)


def test_evaluation_protocol(seq, tmp_path):
    G = insert_gaps(seq, 100.0, np.random.default_rng(0))
    assert np.isnan(G).any() and (np.isnan(G[:, :, 0]).sum(axis=0) <= seq.shape[0] - 2).all()
    lengths = run_lengths(np.array([[1, 0], [1, 1], [0, 1], [1, 1]], dtype=bool))
    np.testing.assert_array_equal(lengths, [[2, 0], [2, 3], [0, 3], [1, 3]])
    res = evaluate(seq, 100.0, methods=["lowdim", "spline"], repeats=2, seed=0)
    s = res.summary()
    assert set(s) == {"lowdim", "spline"} and all(v["max"] >= v["median"] for v in s.values())
    res.save_json(tmp_path / "e.json")
    res.plot(tmp_path / "e.png")
    assert (tmp_path / "e.png").stat().st_size > 1000
    assert "| lowdim |" in res.table()


def test_trc_csv_round_trip(seq, tmp_path):
    G = gapped(seq)
    labels = [f"m{i}" for i in range(G.shape[1])]
    for ext in ("trc", "csv"):
        p = tmp_path / f"a.{ext}"
        write(p, G, labels, 100.0)
        m = read(p)
        np.testing.assert_allclose(m.xyz, G, equal_nan=True)
        if ext == "trc":
            assert m.labels == labels and m.rate == 100.0


def test_c3d_round_trip_and_corrupt(seq, tmp_path):
    pytest.importorskip("ezc3d")
    G = gapped(seq)
    labels = [f"m{i}" for i in range(G.shape[1])]
    p = tmp_path / "a.c3d"
    write(p, G, labels, 100.0)
    m = read_c3d(p)
    assert m.labels == labels and m.rate == 100.0
    np.testing.assert_allclose(m.xyz, G, equal_nan=True, atol=1e-3)
    bad = tmp_path / "bad.c3d"
    bad.write_bytes(b"not a c3d file" * 10)
    with pytest.raises(ValueError, match="C3D"):
        read_c3d(bad)
    with pytest.raises(ValueError):
        read_trc(bad)
    (tmp_path / "r.csv").write_text("1,2\n3,4\n")
    with pytest.raises(ValueError, match="multiple of 3"):
        read_csv(tmp_path / "r.csv")


def test_cli_gapfill(seq, tmp_path):
    from acm_rs.cli import main

    G = gapped(seq)
    src = tmp_path / "in.trc"
    write(src, G, [f"m{i}" for i in range(G.shape[1])], 100.0)
    out = tmp_path / "out.trc"
    assert main(["gapfill", str(src), "-o", str(out), "--method", "spline"]) == 0
    assert np.isfinite(read(out).xyz).all()
    assert main(["gapfill", str(src), "-o", str(out)]) == 1  # exists, no --overwrite


def test_cli_gapfill_sds_are_opt_in(seq, tmp_path, monkeypatch, capsys):
    import acm_rs.gapfill.filling as gf
    from acm_rs.cli import main

    calls = []
    real = gf.fill

    def spy(X, **kw):
        calls.append(kw.get("full_output", False))
        return real(X, **kw)

    monkeypatch.setattr(gf, "fill", spy)
    G = gapped(seq)
    src = tmp_path / "in.trc"
    write(src, G, [f"m{i}" for i in range(G.shape[1])], 100.0)
    assert main(["gapfill", str(src), "-o", str(tmp_path / "a.trc")]) == 0
    assert calls == [False]  # no posterior SDs unless asked for
    err = capsys.readouterr().err
    assert "read" in err and "filling" in err and "filled" in err  # one line per stage
    assert (
        main(["gapfill", str(src), "-o", str(tmp_path / "b.trc"), "--std", str(tmp_path / "s.trc")])
        == 0
    )
    assert calls == [False, True]
    assert "posterior standard deviations (mm)" in capsys.readouterr().out
    std = read(tmp_path / "s.trc").xyz
    gaps = np.isnan(G).any(axis=2)
    assert np.all(std[gaps] > 0) and np.all(std[~gaps] == 0)
    # the same fill either way (to rounding: the smoother with SDs sums in another order)
    np.testing.assert_allclose(
        read(tmp_path / "a.trc").xyz, read(tmp_path / "b.trc").xyz, rtol=1e-6, atol=1e-6
    )


@pytest.mark.skipif(not MOCAP.is_dir(), reason="../shared data not available")
def test_real_c3d_copy_preserves_metadata(tmp_path):
    src = MOCAP / "85_02.c3d"
    m = read_c3d(src)
    G = insert_gaps(m.xyz, m.rate, np.random.default_rng(0))
    res = fill(G)
    out = tmp_path / "filled.c3d"
    write_like(out, m, res)
    back = read_c3d(out)
    assert back.labels == m.labels and back.rate == m.rate and back.units == m.units
    miss = np.isnan(G[:, :, 0])
    err = np.linalg.norm(back.xyz - m.xyz, axis=2)[miss]
    err_lin = np.linalg.norm(fill(G, method="linear") - m.xyz, axis=2)[miss]
    assert np.median(err) < np.median(err_lin)


@pytest.mark.skipif(not MOCAP.is_dir(), reason="../shared data not available")
def test_real_gaps_csv():
    m = read_csv(MOCAP / "gait-raw.csv")
    assert np.isnan(m.xyz).any()
    res = fill(m.xyz, full_output=True)
    assert np.isfinite(res.filled).all() and res.imputed.any()
