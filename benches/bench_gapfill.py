"""Gap-filling benchmark: acm_rs vs the straightforward NumPy reference of the paper.

Usage: python benches/bench_gapfill.py [--c3d PATH] [--repeats R] [--numpy-repeats R]
                                       [--long-frames N]

The held-out recordings of issue 29 (CMU 85_12 and HDM05 ``HDM_bd_05-01_01_120`` from
numediart/MocapRecovery ``data/``, not kept here): ``--c3d FILE --long-frames 0 --numpy-repeats 3``.

1. 135_02 (5202 frames x 41 markers) with gaps from the evaluation protocol: the faithful
   method ('lowdim-paper') in Rust vs ``gapfill_numpy_reference.lowdim_paper``, same errors.
2. A 25,000-frame x 47-marker sequence (the paper's size, built by tiling 135_02 and adding 6
   virtual markers) filled with the default 'lowdim' and with 'lowdim-paper'.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gapfill_numpy_reference import lowdim_paper  # noqa: E402

from acm_rs.gapfill import fill  # noqa: E402
from acm_rs.gapfill.evaluate import insert_gaps  # noqa: E402
from acm_rs.gapfill.io import read_c3d  # noqa: E402

DEFAULT = Path(__file__).resolve().parents[2] / "shared/data/mocap/135_02.c3d"


def best(f, repeats, warmup=True):
    """(best, median) wall time of ``repeats`` calls (after one untimed warm-up call: first
    touches of memory, thread-pool start) and the last output."""
    if warmup:
        f()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = f()
        times.append(time.perf_counter() - t0)
    return (min(times), float(np.median(times))), out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--c3d", default=str(DEFAULT))
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--numpy-repeats", type=int, default=2)
    ap.add_argument("--long-frames", type=int, default=25_000)
    a = ap.parse_args()
    m = read_c3d(a.c3d)
    X = m.xyz
    G = insert_gaps(X, m.rate, np.random.default_rng(0))
    mask = np.isnan(G[:, :, 0])
    T, N, _ = X.shape
    print(f"{Path(a.c3d).name}: {T} frames x {N} markers, {mask.mean():.1%} marker-frames removed")
    (t_np, _), f_np = best(
        lambda: lowdim_paper(G.reshape(T, -1)).reshape(T, N, 3), a.numpy_repeats, warmup=False
    )
    (t_rs, m_rs), f_rs = best(lambda: fill(G, method="lowdim-paper"), a.repeats)
    (t_ld, m_ld), f_ld = best(lambda: fill(G), a.repeats)
    err = {
        k: np.linalg.norm(v - X, axis=2)[mask]
        for k, v in [("numpy", f_np), ("rust", f_rs), ("lowdim", f_ld)]
    }
    e_np = err["numpy"].mean()
    # The same reference with a well-conditioned prior (P0 = 1e6 I: the same limit; 1e12 I loses
    # digits in NumPy's covariance form in the first frames).
    f_np6 = lowdim_paper(G.reshape(T, -1), p0_scale=1e6).reshape(T, N, 3)
    print(f"  NumPy reference (paper)  {t_np:8.3f} s (best)  mean error {e_np:.3f} mm")
    print(
        f"  acm_rs lowdim-paper      {t_rs:8.4f} s (median {m_rs:.4f})  mean error "
        f"{err['rust'].mean():.3f} mm  speed-up {t_np / t_rs:,.0f}x (median {t_np / m_rs:,.0f}x)"
        f"  max |diff| {np.abs(f_np - f_rs).max():.2e} mm "
        f"(vs the reference with P0 = 1e6 I: {np.abs(f_np6 - f_rs).max():.2e} mm)"
    )
    print(
        f"  acm_rs lowdim (default)  {t_ld:8.4f} s (median {m_ld:.4f})  mean error "
        f"{err['lowdim'].mean():.3f} mm  speed-up {t_np / t_ld:,.1f}x (median {t_np / m_ld:,.1f}x)"
    )
    if a.long_frames <= 0:
        return
    # Paper-size sequence.
    reps = -(-a.long_frames // T)
    tiles = [X if i % 2 == 0 else X[::-1] for i in range(reps)]
    L = np.concatenate(tiles)[: a.long_frames]
    extra = 0.5 * (L[:, :6] + L[:, 6:12])
    L = np.concatenate([L, extra], axis=1)
    GL = insert_gaps(L, m.rate, np.random.default_rng(1))
    for meth in ("lowdim", "lowdim-paper"):
        (t, med), out = best(lambda meth=meth: fill(GL, method=meth), a.repeats)
        e = np.linalg.norm(out - L, axis=2)[np.isnan(GL[:, :, 0])]
        print(
            f"  {L.shape[0]} x {L.shape[1]} {meth:13s} {t:7.3f} s (median {med:.3f})  "
            f"mean error {e.mean():.2f} mm"
        )


if __name__ == "__main__":
    main()
