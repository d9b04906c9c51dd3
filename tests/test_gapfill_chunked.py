"""Gap filling of long recordings window by window (issue 16 item 4)."""

from __future__ import annotations

import numpy as np
import pytest
from test_gapfill import gapped, synthetic

from acm_rs.gapfill import fill
from acm_rs.gapfill.chunked import fill_chunked, longest_gap


@pytest.fixture(scope="module")
def long_case():
    X = synthetic(n_frames=3000, n_markers=12, seed=3)
    G = X.copy()
    rng = np.random.default_rng(4)
    for _ in range(60):
        m, L = rng.integers(12), int(rng.integers(1, 60))
        s = int(rng.integers(1, 3000 - L - 1))
        G[s : s + L, m] = np.nan
    return X, G


def test_longest_gap_counts_runs_across_blocks():
    G = np.zeros((50, 2, 3))
    G[10:30, 1] = np.nan
    G[40:45, 0, 2] = np.nan
    assert longest_gap(G, block=7) == 20
    assert longest_gap(np.zeros((5, 1, 3))) == 0


def test_chunked_fill_is_as_accurate_as_the_whole_and_keeps_observed(long_case):
    X, G = long_case
    whole = fill(G)
    parts = fill_chunked(G, chunk=700, margin=300)
    gaps = np.isnan(G)
    obs = ~gaps
    np.testing.assert_array_equal(parts[obs], G[obs])
    assert np.isfinite(parts).all()
    rmse = lambda Y: np.sqrt(np.mean((Y - X)[gaps] ** 2))  # noqa: E731
    assert rmse(parts) < 1.25 * rmse(whole)
    # a window covering the recording is the whole fill (to 0.1 µm: the path that also
    # computes the posterior std rounds differently, by up to 7e-6 mm here)
    np.testing.assert_allclose(fill_chunked(G, chunk=3000, margin=300), whole, atol=1e-4)


def test_chunked_fill_writes_into_a_memmap_and_reports_windows(long_case, tmp_path):
    _, G = long_case
    src = np.lib.format.open_memmap(tmp_path / "in.npy", "w+", np.float64, G.shape)
    src[:] = G
    out = np.lib.format.open_memmap(tmp_path / "out.npy", "w+", np.float64, G.shape)
    res = fill_chunked(src, chunk=1000, full_output=True, out=out)
    assert res.filled is out and len(res.info["windows"]) == 3
    assert res.info["margin"] >= 2 * longest_gap(G)
    assert (res.std[~np.isnan(G)] == 0).all() and (res.std[res.imputed] > 0).all()


def test_a_margin_shorter_than_a_gap_is_refused():
    G = gapped(synthetic())
    with pytest.raises(ValueError, match="longest gap"):
        fill_chunked(G, chunk=100, margin=2)


def test_windowed_fill_equals_one_pass(long_case):
    """fill(window=...): the model from the whole sequence, the smoothing window by window."""
    X, G = long_case
    one = fill(G, window=None, full_output=True)
    win = fill(G, window=500, full_output=True)
    assert (one.info["windows"], win.info["windows"]) == (1, 6)
    assert win.info["window_margin"] >= longest_gap(G)
    assert (win.info["dim"], win.info["r"]) == (one.info["dim"], one.info["r"])
    scale = np.nanmax(np.abs(G))
    # the memoised smoother shares covariances within memo_tol (1e-6) and the windows share
    # different ones: differences at that level, far below any marker error
    np.testing.assert_allclose(win.filled, one.filled, rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(win.std, one.std, rtol=0, atol=1e-5 * np.max(one.std))
    exact = dict(memo_tol=0.0)
    np.testing.assert_allclose(
        fill(G, window=500, **exact), fill(G, window=None, **exact), rtol=0, atol=1e-9 * scale
    )
    # "auto" windows only long sequences
    assert fill(G, full_output=True).info["windows"] == 1


@pytest.mark.parametrize("bad", [0, -5, 2.5, "big", True])
def test_window_must_be_a_positive_number_of_frames(long_case, bad):
    with pytest.raises(ValueError, match="window must be"):
        fill(long_case[1], window=bad)


def test_command_line_fills_in_windows(long_case, tmp_path):
    from acm_rs.cli import main
    from acm_rs.gapfill.io import read, write

    _, G = long_case
    labels = [f"m{k}" for k in range(G.shape[1])]
    write(tmp_path / "in.trc", G, labels, rate=100.0)
    src = read(tmp_path / "in.trc").xyz
    assert main(["gapfill", str(tmp_path / "in.trc"), "-o", str(tmp_path / "out.trc"),
                 "--window", "700"]) == 0  # fmt: skip
    got = read(tmp_path / "out.trc").xyz
    want = fill(src, window=None, empty="skip")  # the windows give the one-pass fill
    np.testing.assert_allclose(got, want, atol=1e-3)  # TRC keeps a few decimals
