"""Latency and accuracy of the online tracker (issue 16 item 3).

Learns the parameters offline with ``acm_rs.track`` on one synthetic recording (rat model,
4 cameras, DeepLabCut-like detections), then replays a second recording of the same animal
frame by frame through ``acm_rs.OnlineTracker`` (Python call included in the timing) and
compares the filtered and fixed-lag poses with the offline smoother of that recording, with
the same Θ (the fixed-lag window over the whole recording) and with Θ learned on it by EM; and
the lag alone (Θ of that recording in the online tracker).

    python benches/bench_online.py [--frames 600] [--lag 10] [--motion random_walk] [--parallel]
        [--big] [--relinearize 10]

``--big``: the state size of a user's skeleton without joint limits (issue 29; 87 entries, 62
markers, ``bench_tracking.rat62_skeleton``).
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig


def recording(sk, rig, n, seed, moving=None):
    t, r = datasets.smooth_motion(sk if moving is None else moving, n, seed=seed)
    det, lik = datasets.dlc_like_detections(
        rig, sk, t, r, missing=0.15, outliers=0.01, seed=seed + 1
    )
    return det, lik, datasets.true_positions(sk, t, r)[0]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=600, help="frames of the replayed recording")
    ap.add_argument("--lag", type=int, default=10, help="fixed lag (frames)")
    ap.add_argument("--motion", default="random_walk", choices=["random_walk", "velocity"])
    ap.add_argument(
        "--parallel",
        action="store_true",
        help="OnlineTracker(serial=False): the steps shared with the thread pool",
    )
    ap.add_argument("--big", action="store_true", help="87 state entries, 62 markers")
    ap.add_argument("--relinearize", type=int, default=10, help="OnlineTracker(relinearize=)")
    args = ap.parse_args(argv)
    moving = None
    if args.big:
        from bench_tracking import rat62_skeleton

        sk, moving = rat62_skeleton(), rat62_skeleton(limits=True)
    else:
        sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    det0, lik0, _ = recording(sk, rig, 300, 2, moving)
    t0 = time.perf_counter()
    learned = acm_rs.track(
        rig, sk, det0, likelihood=lik0, motion=args.motion, joint_limits=not args.big
    )
    print(
        f"offline learning on 300 frames: {time.perf_counter() - t0:.1f} s "
        f"({learned.info['motion']}, {len(learned.em_history)} EM iterations)"
    )
    det, lik, truth = recording(sk, rig, args.frames, 7, moving)
    for lag in (0, args.lag):
        online = acm_rs.OnlineTracker.from_result(
            learned, lag=lag, serial=not args.parallel, relinearize=args.relinearize
        )
        filt = np.full_like(truth, np.nan)
        lagged = np.full_like(truth, np.nan)
        times = []
        for t in range(args.frames):
            s = time.perf_counter()
            filt[t], _ = online.update(det[:, t], lik[:, t])
            times.append(time.perf_counter() - s)
            if lag:
                s = time.perf_counter()
                j, _, k = online.lagged()
                times[-1] += time.perf_counter() - s
                lagged[t - k] = j
        ms = np.array(times[5:]) * 1e3  # the first frames include the initial fit
        err = np.linalg.norm((lagged if lag else filt) - truth, axis=-1) * 10  # mm
        print(
            f"lag {lag:2d}: update{' + lagged' if lag else ''} p50 {np.median(ms):.2f} ms, "
            f"p99 {np.percentile(ms, 99):.2f} ms, max {ms.max():.2f} ms; joints mean "
            f"{np.nanmean(err):.3f} mm, median {np.nanmedian(err):.3f} mm"
        )
    # The offline smoother with the same Θ: the fixed-lag window over the whole recording.
    whole = acm_rs.OnlineTracker.from_result(learned, lag=args.frames)
    for t in range(args.frames):
        whole.update(det[:, t], lik[:, t])
    e_fixed = np.linalg.norm(whole.lagged_window()[0] - truth, axis=-1) * 10
    print(
        f"offline smoother with the same Θ (lag = T): joints mean {e_fixed.mean():.3f} mm, "
        f"median {np.median(e_fixed):.3f} mm; lag {args.lag} / this: "
        f"{np.nanmean(err) / e_fixed.mean():.2f}x"
    )
    off = acm_rs.track(rig, sk, det, likelihood=lik, motion=args.motion, joint_limits=not args.big)
    e_off = np.linalg.norm(off.joints - truth, axis=-1) * 10
    print(
        f"offline smoother of the same recording (EM on it): joints mean {e_off.mean():.3f} mm, "
        f"median {np.median(e_off):.3f} mm; lag {args.lag} / this: "
        f"{np.nanmean(err) / e_off.mean():.2f}x"
    )
    # The cost of the lag alone: Θ of this recording, unshrunk, lag vs offline.
    own = acm_rs.OnlineTracker.from_result(off, lag=args.lag, vz_shrinkage=0.0)
    own_lag = np.full_like(truth, np.nan)
    for t in range(args.frames):
        own.update(det[:, t], lik[:, t])
        j, _, k = own.lagged()
        own_lag[t - k] = j
    e_own = np.linalg.norm(own_lag - truth, axis=-1) * 10
    print(
        f"lag {args.lag} with the Θ learned on this recording (no V_z shrinkage): joints mean "
        f"{np.nanmean(e_own):.3f} mm = {np.nanmean(e_own) / e_off.mean():.2f}x the offline EM"
    )
    print(f"machine: {platform.machine()}, {platform.python_version()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
