"""Benchmark of skeleton learning (ACM supp. sec. 3.2-3.4): 200 labelled frames of the rat
model in 4 cameras (2 px noise, 30 % unlabelled), learned from the generic model.

Reports the wall time of each stage, the accuracy against the synthetic truth, and the cost of
the exact Rust gradient against a finite-difference gradient (n + 1 objective evaluations).

    python benches/bench_learning.py [--frames 200] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

import acm_rs
from acm_rs import _native, datasets
from acm_rs.demo import demo_rig


def best(fn, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rat = acm_rs.models.rat()
    true = datasets.individual_skeleton(rat, seed=1)
    rig = demo_rig()
    t, r = datasets.random_poses(true, args.frames, seed=2)
    labels = datasets.noisy_labels(rig, true, t, r, 2.0, missing=0.3, seed=3)

    t0 = time.perf_counter()
    res = acm_rs.learn_skeleton(rig, rat, labels, progress=False)
    wall = time.perf_counter() - t0
    rel = np.abs(res.skeleton.bone_lengths / true.bone_lengths - 1)
    tail = np.array([n.startswith("tail") for n in rat.bone_names])
    off = np.linalg.norm(res.skeleton.marker_offsets - true.marker_offsets, axis=1)
    print(res.summary())
    print(f"\n{args.frames} frames, rat model, 4 cameras: learn_skeleton wall time {wall:.1f} s")
    whole = res.skeleton.bone_lengths[tail].sum() / true.bone_lengths[tail].sum() - 1
    print(
        f"  bone lengths: max error {100 * rel[~tail].max():.2f} % (non-tail), "
        f"{100 * rel[tail].max():.1f} % (single tail bones), whole tail {100 * abs(whole):.2f} %"
    )
    print(
        f"  marker offsets: median error {10 * np.median(off):.2f} mm, max {10 * off.max():.2f} mm"
    )

    # gradient cost: exact (Rust) vs forward differences (n + 1 objective evaluations)
    lab = np.ascontiguousarray(labels.transpose(1, 0, 2, 3))
    lim = rat.joint_limits
    e = np.zeros((0, 2), np.int64)
    p = _native.NativeLearning(
        rat._native, rig.get_params(), lab, np.ascontiguousarray(lim[..., 0]),
        np.ascontiguousarray(lim[..., 1]), acm_rs.Normalization()._tuple(), e, e, 1.0,
    )  # fmt: skip
    x = np.random.default_rng(0).normal(scale=0.1, size=p.n_params)
    x[: rat.n_bones] = rat.bone_lengths
    t_grad = best(lambda: p.value_and_grad(x))
    t_val = best(lambda: p.residuals(x))
    t_fd = (p.n_params + 1) * t_val
    print(f"  objective + exact gradient: {1e3 * t_grad:.2f} ms ({p.n_params} parameters)")
    print(f"  one objective value: {1e3 * t_val:.2f} ms -> finite-difference gradient "
          f"{t_fd:.1f} s; exact gradient is {t_fd / t_grad:,.0f}x faster")  # fmt: skip
    info = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs",
        "frames": args.frames, "wall_s": wall, "stages": res.info["stages"],
        "rms_px": res.rms, "max_rel_length_error_non_tail": float(rel[~tail].max()),
        "grad_ms": 1e3 * t_grad, "value_ms": 1e3 * t_val, "fd_grad_s": t_fd,
    }  # fmt: skip
    worst = rat.bone_names[int(np.argmax(np.where(tail, 0, rel)))]
    print(f"  worst non-tail bone: {worst}; machine: {info['machine']}")
    if args.json:
        args.json.write_text(json.dumps(info, indent=2, default=str) + "\n")


if __name__ == "__main__":
    main()
