"""Gap filling of a long C3D through the command line: peak memory, time, gap error.

Usage: python benches/bench_gapfill_long.py [--c3d PATH] [--frames 200000] [--gaps 600]
                                            [--max-gap 300] [--window N] [--keep DIR]

CMU 135_02 (41 markers, 120 Hz) tiled to ``--frames`` frames; ``--gaps`` gaps of 1 to
``--max-gap`` frames are cut at random places (seed 0). The file is written as C3D, then
``acm-rs gapfill in.c3d -o out.c3d`` runs in a child process, whose peak RSS (``wait4``) is
the figure of issue 16 (≤ 1.5 GB for 200,000 × 41). The filled file is read back and scored
on the removed values (RMSE, mm).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from acm_rs.gapfill.io import read_c3d, write

DEFAULT = Path(__file__).resolve().parents[2] / "shared/data/mocap/135_02.c3d"


def make(src: Path, n_frames: int, n_gaps: int, max_gap: int, seed: int = 0):
    """(complete tiled sequence, the same with gaps, labels, rate)."""
    m = read_c3d(src)
    X = m.xyz
    if not np.isfinite(X).all():
        X = X[:, np.isfinite(X).all(axis=(0, 2))]
    reps = -(-n_frames // len(X))
    # alternate forward and reversed copies so that the tiles join without a jump
    tiles = [X if i % 2 == 0 else X[::-1] for i in range(reps)]
    full = np.concatenate(tiles)[:n_frames]
    rng = np.random.default_rng(seed)
    Y = full.copy()
    for _ in range(n_gaps):
        length = int(rng.integers(1, max_gap + 1))
        a = int(rng.integers(0, n_frames - length))
        Y[a : a + length, int(rng.integers(0, full.shape[1]))] = np.nan
    return full, Y, m.labels[: full.shape[1]], m.rate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--c3d", default=str(DEFAULT))
    ap.add_argument("--frames", type=int, default=200_000)
    ap.add_argument("--gaps", type=int, default=600)
    ap.add_argument("--max-gap", type=int, default=300)
    ap.add_argument("--window", type=int, help="--window of the command (0: one pass)")
    ap.add_argument("--keep", help="folder for the input and output files (default: temporary)")
    a = ap.parse_args()
    full, Y, labels, rate = make(Path(a.c3d), a.frames, a.gaps, a.max_gap)
    gap = np.isnan(Y)
    print(
        f"{a.frames:,} frames x {Y.shape[1]} markers, {a.gaps} gaps of 1-{a.max_gap} frames "
        f"({gap.any(axis=2).mean():.2%} of marker-frames missing)"
    )
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(a.keep or tmp)
        d.mkdir(parents=True, exist_ok=True)
        src, out = d / "long_in.c3d", d / "long_out.c3d"
        t0 = time.perf_counter()
        write(src, Y, labels, rate)
        mib = src.stat().st_size / 2**20
        print(f"wrote {src} ({mib:.0f} MiB) in {time.perf_counter() - t0:.1f} s")
        cmd = [sys.executable, "-m", "acm_rs.cli", "gapfill", str(src), "-o", str(out)]
        cmd += ["--overwrite"] + ([] if a.window is None else ["--window", str(a.window)])
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        if status != 0:
            raise SystemExit(f"the command failed (status {status})")
        back = read_c3d(out).xyz
    err = np.linalg.norm(back - full, axis=2)[gap.any(axis=2)]
    print(
        f"acm-rs gapfill: {wall:.1f} s, peak RSS {usage.ru_maxrss / 1024:.0f} MB "
        f"({os.cpu_count()} CPUs); gap RMSE {np.sqrt(np.mean(err**2)):.2f} mm, "
        f"mean {err.mean():.2f} mm, unfilled {int(np.isnan(err).sum())}"
    )


if __name__ == "__main__":
    main()
