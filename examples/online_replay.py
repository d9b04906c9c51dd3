"""Replay a recorded session frame by frame, as DeepLabCut-Live would deliver it.

Learns the tracking parameters offline on one synthetic recording, then feeds a second
recording camera by camera through the DeepLabCut-Live processors of ``acm_rs.tracking.live``
(one ``process(pose)`` call per camera and frame, poses of shape (n_bodyparts, 3)) and prints
the 3D pose of a few frames, the latency per frame and the error against the truth.

    python examples/online_replay.py [--frames 300] [--lag 10]

With DeepLabCut-Live: ``DLCLive(model_path, processor=live.processor(camera))`` per camera.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig
from acm_rs.tracking.live import LiveRig


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames to replay")
    ap.add_argument("--lag", type=int, default=10, help="fixed lag of the smoothed output")
    args = ap.parse_args(argv)
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, 300, seed=2)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, missing=0.15, outliers=0.01, seed=3)
    learned = acm_rs.track(rig, sk, det, likelihood=lik, motion="random_walk")
    print(f"learned offline: {len(learned.em_history)} EM iterations on 300 frames")

    t, r = datasets.smooth_motion(sk, args.frames, seed=7)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, missing=0.15, outliers=0.01, seed=8)
    truth, _ = sk.forward(t, r)
    online = acm_rs.OnlineTracker.from_result(learned, lag=args.lag)
    live = LiveRig(online, bodyparts=sk.marker_names)
    procs = [live.processor(c) for c in range(len(rig))]
    lagged = np.full_like(truth, np.nan)
    ms = []
    for f in range(args.frames):
        start = time.perf_counter()
        for c, proc in enumerate(procs):  # the cameras' networks deliver their poses
            proc.process(np.column_stack([det[c, f], lik[c, f]]))
        ms.append((time.perf_counter() - start) * 1e3)
        if online.frames:
            j, _, k = online.lagged()
            lagged[f - k] = j
        if f % 100 == 0 and live.latest is not None:
            _, joints, sd = live.latest
            print(f"frame {f:4d}: head at {np.round(joints[0], 2)} cm, SD {np.round(sd[0], 3)} cm")
    ms_a = np.array(ms[5:])
    filt_err = np.linalg.norm(live.latest[1] - truth[-1], axis=-1).mean() * 10
    lag_err = np.nanmean(np.linalg.norm(lagged - truth, axis=-1)) * 10
    print(
        f"per frame (4 process calls + 3D update): p50 {np.median(ms_a):.2f} ms, "
        f"p99 {np.percentile(ms_a, 99):.2f} ms; last frame's joints {filt_err:.2f} mm off; "
        f"lag-{args.lag} joints {lag_err:.2f} mm mean error"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
