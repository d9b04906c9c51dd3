"""Tracker benchmark (ACM supp. sec. 4): EM on 200 frames, E-step throughput, scaling in T.

Rat model (n_z = 50), 4 cameras (n_x = 344), DeepLabCut-like synthetic detections (2 px noise,
15 % missing in bursts, 1 % confident outliers). Run from the repository root:

    python benches/bench_tracking.py            # 200-frame EM + throughput at T = 1e3, 1e4
    python benches/bench_tracking.py --large    # ... and T = 1e5 (about 3 min, ~5 GB)
    python benches/bench_tracking.py --big      # E-step/EM throughput, both motion models, for
                                                # the rat (50 entries) and a user's skeleton
                                                # without joint limits (87 entries, 62 markers)

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


def rat62_skeleton(limits: bool = False, n_extra: int = 19) -> acm_rs.Skeleton:
    """The state size of a user's skeleton without joint limits (issue 29): the individual
    rat's 29 joints, no limits (3 + 28 * 3 = 87 state entries), its 43 markers and one more
    on each of the ``n_extra`` joints with the fewest (62 markers). ``limits=True``: the same
    body with the rat's joint limits (to generate plausible motion)."""
    base = datasets.individual_skeleton(models.rat(), seed=1)
    joints, markers = base.rest_pose()
    rng = np.random.default_rng(101)
    counts = np.bincount(base.marker_joints, minlength=base.n_joints)
    extra = np.argsort(counts, kind="stable")[:n_extra]
    return acm_rs.Skeleton.from_rest_pose(
        base.joint_names, base.parents, joints,
        list(base.marker_names) + [f"extra_{k:02d}" for k in range(n_extra)],
        list(base.marker_joints) + list(extra),
        np.vstack([markers, joints[extra] + rng.normal(0.0, 0.4, (n_extra, 3))]),
        joint_limits=base.joint_limits if limits else None, name="rat62",
    )  # fmt: skip


def session(n_frames: int, seed: int = 0, big: bool = False):
    """Skeleton, rig, motion and DLC-like detections; ``big``: :func:`rat62_skeleton` (its
    motion that of the same body with the rat's joint limits)."""
    sk = rat62_skeleton() if big else datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    moving = rat62_skeleton(limits=True) if big else sk
    t, r = datasets.smooth_motion(moving, n_frames, seed=seed + 2)
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


def learned_throughput(big: bool, motion: str, n_frames: int = 1000, reps: int = 2) -> None:
    """E-step, M-step and EM-iteration throughput with the parameters ``acm_rs.track`` learned
    on 240 frames of the same animal, on a second recording of ``n_frames``."""
    sk, rig, t, r, det, lik = session(240, big=big)
    learned = acm_rs.track(rig, sk, det, likelihood=lik, motion=motion, joint_limits=not big)
    p = learned.info["params"]
    sk, rig, t, r, det, lik = session(n_frames, seed=7, big=big)
    det[lik < 0.9] = np.nan
    norm = default_normalization(rig, sk)
    x = np.ascontiguousarray(norm.normalize_pixels(det).transpose(1, 0, 2, 3))
    lim = sk.joint_limits
    native = _native.NativeTracker(
        sk._native, rig.get_params(), np.ascontiguousarray(lim[..., 0]),
        np.ascontiguousarray(lim[..., 1]), norm._tuple(), not big, x,
        order=1 if motion == "random_walk" else 2,
    )  # fmt: skip
    args = (p["mu0"], p["V0"], p["Vz"], p["Vx_diag"])
    gate = -2 * np.log1p(-0.999)
    best = {"smooth": np.inf, "e_step": np.inf, "m_step": np.inf}
    for _ in range(reps):
        t0 = time.perf_counter()
        native.e_step(*args, gate, True, False)
        t1 = time.perf_counter()
        native.e_step(*args, gate, True)
        t2 = time.perf_counter()
        native.m_step(*args)
        t3 = time.perf_counter()
        best["smooth"] = min(best["smooth"], t1 - t0)
        best["e_step"] = min(best["e_step"], t2 - t1)
        best["m_step"] = min(best["m_step"], t3 - t2)
    rate = {k: n_frames / s for k, s in best.items()}
    em = n_frames / (best["e_step"] + best["m_step"])
    print(
        f"{'87 entries, 62 markers' if big else '50 entries, 43 markers'}, {motion:11s}: "
        f"smooth {rate['smooth']:6.0f}, E-step {rate['e_step']:6.0f}, M-step "
        f"{rate['m_step']:6.0f}, EM iteration {em:6.0f} frames/s (T = {n_frames})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--large", action="store_true", help="also T = 100,000")
    ap.add_argument(
        "--big", action="store_true", help="learned-parameter throughput, 50 and 87 entries"
    )
    args = ap.parse_args()
    print(f"machine: {platform.processor() or platform.machine()}, numpy {np.__version__}")
    if args.big:
        for big in (False, True):
            for motion in ("random_walk", "velocity"):
                learned_throughput(big, motion)
        return
    em_200()
    for n in (1_000, 10_000) + ((100_000,) if args.large else ()):
        throughput(n, reps=2 if n <= 10_000 else 1)


if __name__ == "__main__":
    main()
