"""Gap filling a long TRC and marker CSV through the command line, against the same C3D.

Usage: python benches/bench_text_io.py [--c3d PATH] [--frames 200000] [--gaps 2400]
                                       [--max-gap 300] [--formats trc,csv,c3d] [--keep DIR]
                                       [--read-only]

CMU 135_02 (41 markers, 120 Hz) tiled to ``--frames`` frames (alternately reversed, as
``bench_gapfill_long.py``) with ``--gaps`` gaps of 1 to ``--max-gap`` frames (seed 0; the
defaults remove about 4.4 % of the marker-frames). The same data are written as TRC, CSV (with
its sidecar) and C3D by ``acm_rs.gapfill.io.write``; then, for each format, in a child process
(peak RSS from ``wait4``):

* ``read``: ``acm_rs.gapfill.io.read(IN)`` alone;
* ``gapfill``: ``acm-rs gapfill IN -o OUT`` (same format out).

The filled files are read back and scored on the removed values (RMSE, mm): the three formats
must give the same figure.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gapfill_long import DEFAULT, make  # noqa: E402

from acm_rs.gapfill.io import read, write  # noqa: E402


def child(cmd: list[str]) -> tuple[float, float]:
    """(wall time s, peak RSS MB) of a command run under ``/usr/bin/time``.

    Not ``os.wait4`` on a child of this process: Linux starts a forked child's peak RSS at the
    pages it shares with its parent, so the figure would include this process's arrays."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as rep:
        t0 = time.perf_counter()
        proc = subprocess.run(["/usr/bin/time", "-o", rep.name, "-f", "%M"] + cmd)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed (status {proc.returncode})")
        return wall, int(rep.read().split()[-1]) / 1024


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--c3d", default=str(DEFAULT))
    ap.add_argument("--frames", type=int, default=200_000)
    ap.add_argument("--gaps", type=int, default=2400)
    ap.add_argument("--max-gap", type=int, default=300)
    ap.add_argument("--formats", default="trc,csv,c3d")
    ap.add_argument("--keep", help="folder for the input and output files (default: temporary)")
    ap.add_argument("--read-only", action="store_true", help="time only the readers")
    a = ap.parse_args()
    full, Y, labels, rate = make(Path(a.c3d), a.frames, a.gaps, a.max_gap)
    gap = np.isnan(Y)
    print(
        f"{a.frames:,} frames x {Y.shape[1]} markers, {a.gaps} gaps of 1-{a.max_gap} frames "
        f"({gap.any(axis=2).mean():.2%} of marker-frames missing); {os.cpu_count()} CPUs",
        flush=True,
    )
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(a.keep or tmp)
        d.mkdir(parents=True, exist_ok=True)
        for ext in a.formats.split(","):
            src, out = d / f"long_in.{ext}", d / f"long_out.{ext}"
            if not src.exists():
                t0 = time.perf_counter()
                write(src, Y, labels, rate)
                mib = src.stat().st_size / 2**20
                print(
                    f"{ext}: wrote {src.name} ({mib:.0f} MiB) in {time.perf_counter() - t0:.1f} s"
                )
            code = f"from acm_rs.gapfill.io import read; read({str(src)!r})"
            wall, rss = child([sys.executable, "-c", code])
            print(f"{ext}: read {wall:.1f} s, peak RSS {rss:.0f} MB", flush=True)
            if a.read_only:
                continue
            cmd = [sys.executable, "-m", "acm_rs.cli", "gapfill", str(src), "-o", str(out)]
            wall, rss = child(cmd + ["--overwrite"])
            back = read(out).xyz
            err = np.linalg.norm(back - full, axis=2)[gap.any(axis=2)]
            print(
                f"{ext}: acm-rs gapfill {wall:.1f} s, peak RSS {rss:.0f} MB; gap RMSE "
                f"{np.sqrt(np.mean(err**2)):.3f} mm, unfilled {int(np.isnan(err).sum())}",
                flush=True,
            )


if __name__ == "__main__":
    main()
