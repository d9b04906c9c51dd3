"""Tracker benchmark (ACM supp. sec. 4): EM on 200 frames, E-step throughput, scaling in T.

Rat model (n_z = 50), 4 cameras (n_x = 344), DeepLabCut-like synthetic detections (2 px noise,
15 % missing in bursts, 1 % confident outliers). Run from the repository root:

    python benches/bench_tracking.py            # 200-frame EM + throughput at T = 1e3, 1e4
    python benches/bench_tracking.py --large    # ... and T = 1e5 (about 3 min, ~5 GB)

Prints a table; figures go to benches/README.md by hand.
"""

from __future__ import annotations

import argparse
import platform
import resource
import time

import numpy as np

import acm_rs
from acm_rs import _native, datasets, models
from acm_rs.demo import demo_rig
from acm_rs.tracking.track import default_normalization


def session(n_frames: int, seed: int = 0):
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, n_frames, seed=seed + 2)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=seed + 3)
    return sk, rig, t, r, det, lik


def rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def em_200() -> None:
    sk, rig, t, r, det, lik = session(200)
    truth, _ = datasets.true_positions(sk, t, r)
    for method in ("ukf", "deterministic"):
        t0 = time.perf_counter()
        res = acm_rs.track(rig, sk, det, likelihood=lik, method=method, progress=False)
        wall = time.perf_counter() - t0
        err = np.linalg.norm(res.joints - truth, axis=-1) * 10  # cm -> mm
        extra = ""
        if method == "ukf":
            h = res.em_history
            extra = (
                f", {len(h)} EM iterations ({np.mean([x['seconds'] for x in h]):.3f} s each), "
                f"init {res.info['seconds_init']:.2f} s"
            )
        print(
            f"200 frames, {method:13s}: {wall:6.2f} s wall{extra}; joint error mean "
            f"{err.mean():.2f} mm, median {np.median(err):.2f} mm"
        )


def throughput(n_frames: int, reps: int = 2) -> None:
    sk, rig, t, r, det, lik = session(n_frames)
    det[lik < 0.9] = np.nan
    norm = default_normalization(rig, sk)
    sm = acm_rs.StateMap(sk, norm)
    x = np.ascontiguousarray(norm.normalize_pixels(det).transpose(1, 0, 2, 3))
    lim = sk.joint_limits
    native = _native.NativeTracker(
        sk._native, rig.get_params(), np.ascontiguousarray(lim[..., 0]),
        np.ascontiguousarray(lim[..., 1]), norm._tuple(), True, x,
    )  # fmt: skip
    n = native.n_state
    mu0 = sm.from_pose(t[0], r[0])
    v = np.eye(n) * 1e-3
    vx = np.full(x[0].size, 1e-5)
    best = {"filter": np.inf, "e_step": np.inf, "m_step": np.inf}
    gate = -2 * np.log1p(-0.999)
    for _ in range(reps):
        t0 = time.perf_counter()
        native.e_step(mu0, v, v, vx, gate, False)
        t1 = time.perf_counter()
        native.e_step(mu0, v, v, vx, gate, True)
        t2 = time.perf_counter()
        native.m_step(mu0, v, v, vx)
        t3 = time.perf_counter()
        best["filter"] = min(best["filter"], t1 - t0)
        best["e_step"] = min(best["e_step"], t2 - t1)
        best["m_step"] = min(best["m_step"], t3 - t2)
    rate = {k: n_frames / s for k, s in best.items()}
    print(
        f"T = {n_frames:>6}: filter {rate['filter']:7.0f} fr/s, E-step {rate['e_step']:7.0f} "
        f"fr/s ({best['e_step']:.2f} s), M-step {rate['m_step']:7.0f} fr/s; EM iteration "
        f"{best['e_step'] + best['m_step']:.2f} s; peak RSS {rss_gb():.2f} GB"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--large", action="store_true", help="also T = 100,000")
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, numpy {np.__version__}")
    em_200()
    for n in (1_000, 10_000) + ((100_000,) if args.large else ()):
        throughput(n, reps=2 if n <= 10_000 else 1)


if __name__ == "__main__":
    main()
