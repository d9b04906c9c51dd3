"""Long recordings (issue 16 items 1-2): EM on a subset of windows + the chunked smoother,
input from a memory-mapped file, output to HDF5; frames/s, peak RSS, and (optionally) the
difference to the smoother of the whole recording with the same parameters.

    python benches/bench_long.py [--frames 40000] [--subset 10000] [--windows 10]
                                 [--chunk 2000] [--burn-in 100] [--method chunked]
                                 [--compare] [--track] [--overrelax A|none]

The synthetic rat (4 cameras, DeepLabCut-like detections with 15 % missing and 1 % confident
outliers, one camera out for 5 % of the recording) is generated in blocks straight into a
``.npy`` memmap, so the input never sits in memory.
"""

from __future__ import annotations

import argparse
import multiprocessing
import platform
import resource
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig
from acm_rs.tracking import long as L
from acm_rs.tracking.streaming import smooth_streaming


def make_recording(folder: Path, sk, rig, n: int, block: int = 5000):
    """Detections/likelihoods/truth memmaps of ``n`` frames, generated block by block."""
    c, m = len(rig), sk.n_markers
    det = np.lib.format.open_memmap(folder / "det.npy", "w+", np.float32, (c, n, m, 2))
    lik = np.lib.format.open_memmap(folder / "lik.npy", "w+", np.float32, (c, n, m))
    truth = np.lib.format.open_memmap(folder / "truth.npy", "w+", np.float32, (n, sk.n_joints, 3))
    for k, a in enumerate(range(0, n, block)):
        b = min(n, a + block)
        t, r = datasets.smooth_motion(sk, b - a, seed=100, start=a)  # one sequence
        d, lk = datasets.dlc_like_detections(
            rig, sk, t, r, missing=0.15, outliers=0.01, seed=200 + k
        )
        det[:, a:b], lik[:, a:b] = d, lk
        truth[a:b] = datasets.true_positions(sk, t, r)[0]
    out = slice(n // 2, n // 2 + n // 20)
    det[1, out] = np.nan  # one camera out for 5 % of the recording
    for arr in (det, lik, truth):
        arr.flush()
    return (np.load(folder / f, mmap_mode="r") for f in ("det.npy", "lik.npy", "truth.npy"))


def _generate(folder: Path, n: int) -> None:
    """The recording of :func:`make_recording` for the rat and rig of this bench."""
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    make_recording(folder, sk, demo_rig(), n)


def model_from_file(res: dict, info: dict, rig, sk) -> L._Model:
    """The smoother's model from the parameters stored in a track_long file."""
    from acm_rs.tracking.track import DEFAULT_GATE, gate_threshold

    p = dict(res["params"])
    rw = {k[3:]: p.pop(k) for k in list(p) if k.startswith("rw_")}
    pc, rpc = p.pop("window_prior_cov"), rw.pop("window_prior_cov", None)
    return L._Model(
        rig, sk, acm_rs.tracking.default_normalization(rig, sk), True, 10,
        gate_threshold(DEFAULT_GATE), 2 if info["motion"] == "velocity" else 1, p, pc,
        0.9, None, rw or None, rpc,
    )  # fmt: skip


def report(name: str, res: dict, truth) -> None:
    """Joint error (mm) against the truth, overall and per block of 1,000 frames."""
    err = np.linalg.norm(res["joints"] - truth, axis=-1) * 10  # mm
    per = np.nanmean(err, axis=1)
    blocks = [np.nanmean(per[a : a + 1000]) for a in range(0, len(per), 1000)]
    print(
        f"  {name}: joints mean {np.nanmean(err):.3f} mm, median {np.nanmedian(err):.3f} mm; "
        f"per 1,000 frames: {' '.join(f'{b:.2f}' for b in blocks)}"
    )


def _track(rig, sk, det, lik, truth, rss0: float, frames: int, **options) -> int:
    """``acm_rs.track`` with its defaults (or ``options``) on the memory-mapped recording:
    end-to-end time, peak RSS and the joints' error."""
    t0 = time.perf_counter()
    res = acm_rs.track(rig, sk, det, likelihood=lik, **options)
    total = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    info = res.info
    print(
        f"acm_rs.track: bounded memory {info.get('bounded_memory', False)}, motion "
        f"{info.get('motion')}, EM {len(res.em_history)} iterations; total {total:.0f} s = "
        f"{frames / total:.0f} frames/s end to end; peak RSS {rss:.0f} MB (before tracking "
        f"{rss0:.0f} MB); EM {info.get('seconds_em', float('nan')):.0f} s, smoothing "
        f"{info.get('seconds_smoothing', float('nan')):.0f} s"
    )
    report("track", {"joints": res.joints}, truth)
    print(f"machine: {platform.machine()}, {platform.python_version()}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40_000)
    ap.add_argument("--subset", type=int, default=L.DEFAULT_SUBSET)
    ap.add_argument("--windows", type=int, default=L.DEFAULT_WINDOWS)
    ap.add_argument("--chunk", type=int, default=L.DEFAULT_CHUNK)
    ap.add_argument("--burn-in", type=int, default=L.DEFAULT_BURN_IN)
    ap.add_argument("--tol", type=float, default=None,
                    help="chunked: seam tolerance in posterior SDs")  # fmt: skip
    ap.add_argument("--motion", default="auto", choices=["auto", "velocity", "random_walk"])
    ap.add_argument("--method", default="chunked", choices=["chunked", "streaming"])
    ap.add_argument("--compare", action="store_true",
                    help="also the other smoother with the same parameters")  # fmt: skip
    ap.add_argument("--keep", help="keep the inputs and outputs in this folder")
    ap.add_argument(
        "--track",
        action="store_true",
        help="call acm_rs.track with its defaults on the memmap instead (issue 29 "
        "item 1: it chooses the bounded-memory path itself)",
    )
    ap.add_argument(
        "--overrelax",
        help="over-relaxed EM's growth factor, or 'none' for plain EM (default: the default)",
    )
    args = ap.parse_args(argv)
    options = {}
    if args.overrelax is not None:
        options["overrelax"] = None if args.overrelax == "none" else float(args.overrelax)
    warnings.simplefilter("default")
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        # generated in a child process, so that the peak RSS below is the tracker's own
        child = multiprocessing.get_context("spawn").Process(
            target=_generate, args=(folder, args.frames)
        )
        child.start()
        child.join()
        if child.exitcode != 0:
            raise SystemExit(f"generating the recording failed ({child.exitcode})")
        det, lik, truth = (np.load(folder / f, mmap_mode="r")
                           for f in ("det.npy", "lik.npy", "truth.npy"))  # fmt: skip
        print(f"generated {args.frames} frames in {time.perf_counter() - t0:.0f} s (memmap)")
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        if args.track:
            return _track(rig, sk, det, lik, truth, rss0, args.frames, **options)
        t0 = time.perf_counter()
        info = acm_rs.track_long(
            rig, sk, det, folder / "poses.h5", likelihood=lik, subset=args.subset,
            n_windows=args.windows, chunk=args.chunk, burn_in=args.burn_in, tol=args.tol,
            motion=args.motion, overwrite=True, method=args.method, **options,
        )  # fmt: skip
        total = time.perf_counter() - t0
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        res = acm_rs.read_chunked(folder / "poses.h5")
        smooth_s = info["seconds_smoothing"]
        print(
            f"{args.method}: motion {info['motion']}, EM {len(info['em_history'])} iterations "
            f"on {len(info['em_windows'])} windows: {info['seconds_em']:.0f} s; smoothing "
            f"{smooth_s:.0f} s = {args.frames / smooth_s:.0f} frames/s; total {total:.0f} s; "
            f"peak RSS {rss:.0f} MB (before tracking {rss0:.0f} MB)"
        )
        if args.method == "chunked":
            print(f"  {info['windows_recomputed']} windows recomputed; seam difference max "
                  f"{info['seam_difference_max']:.4f} SD, median "
                  f"{np.median(res['seam_difference']):.4f} SD")  # fmt: skip
        else:
            print(f"  forward pass {info['seconds_forward']:.0f} s; poorly fit frames "
                  f"{info['poor_fit_frames']} {info['poor_fit'][:3]}")  # fmt: skip
        report(args.method, res, truth)
        if args.compare:
            other = "chunked" if args.method == "streaming" else "streaming"
            model = model_from_file(res, info, rig, sk)
            (folder / "other.h5").unlink(missing_ok=True)
            t0 = time.perf_counter()
            if other == "chunked":
                L.smooth_chunked(model, L._Source(det, lik), folder / "other.h5",
                                 chunk=args.chunk, burn_in=args.burn_in)  # fmt: skip
            else:
                smooth_streaming(model, L._Source(det, lik), folder / "other.h5",
                                 segment=args.chunk,
                                 typical_px=info["em_typical_px"])  # fmt: skip
            ot = acm_rs.read_chunked(folder / "other.h5")
            print(f"{other} with the same parameters: {time.perf_counter() - t0:.0f} s")
            report(other, ot, truth)
            ex, ch = (res, ot) if args.method == "streaming" else (ot, res)
            rel = np.abs(ex["joints"] - ch["joints"]) / ex["joints_std"]
            print(
                f"chunked - streaming: max {np.nanmax(rel):.4f} SD, 99.9th percentile "
                f"{np.nanpercentile(rel, 99.9):.4f} SD, frames with a joint > 1 % SD: "
                f"{np.mean(np.nanmax(rel, axis=(1, 2)) > 0.01) * 100:.2f} %"
            )
    print(f"machine: {platform.machine()}, {platform.python_version()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
