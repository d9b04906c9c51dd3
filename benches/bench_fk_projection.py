"""Benchmark: forward kinematics (Alg. 1) + camera projection, acm_rs vs. pure NumPy.

Builds the ACM rat model, a 4-camera rig (1280 x 1024 px, fx ~ 1200, small radial distortion,
cameras 60-100 cm from the origin looking at it) and random poses, then

(a) checks that acm_rs (``Skeleton.forward`` then ``CameraRig.project``) and the NumPy
    reference (``benches/numpy_reference.py``) give the same pixels;
(b) times both for ``--frames`` poses (best of ``--repeats``, ``time.perf_counter``);
(c) times 101 poses (one set of sigma points of the 50-dimensional tracker state) through the
    fused ``Skeleton.project`` and through the NumPy reference.

Usage::

    python benches/bench_fk_projection.py [--frames 100000] [--repeats 5] [--json PATH]

Poses: the root (snout tip) is placed 10 cm in front of the origin along -z (so the body,
which extends along +z in the rest pose, is centred near the origin) plus a uniform offset of
+-3 cm; every Rodrigues component is uniform in the middle half of its joint limits, with
unbounded limits replaced by +-0.3 rad and fixed components (``[b, b]``) set to ``b``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

import acm_rs

sys.path.insert(0, str(Path(__file__).resolve().parent))
from numpy_reference import (  # noqa: E402
    fk_plan,
    forward_np,
    forward_np_simple,
    project_np,
    project_np_simple,
)

#: World "up" of the benchmark scene: the model's dorsal direction (rest-pose body frame).
WORLD_UP = np.array([0.0, 1.0, 0.0])
#: Root position around which poses are drawn (cm): centres the rat's body on the origin.
ROOT_CENTER = np.array([0.0, 0.0, -10.0])
N_SIGMA = 101  # 2 * 50 + 1 sigma points of the 50-dimensional state


def look_at(
    center: np.ndarray, target: np.ndarray, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(rvec, tvec)`` of a camera at ``center`` looking at ``target``.

    Parameters
    ----------
    center, target : numpy.ndarray, shape (3,)
        Camera centre and looked-at point (world units).
    up : numpy.ndarray, shape (3,)
        World direction that appears upwards in the image (OpenCV camera axes: x right,
        y down, z forward).

    Returns
    -------
    rvec : numpy.ndarray, shape (3,)
        Rodrigues vector of the world-to-camera rotation.
    tvec : numpy.ndarray, shape (3,)
        World-to-camera translation ``-R center``.
    """
    z = np.asarray(target, float) - np.asarray(center, float)
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)  # image right = down x forward
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image down
    rot = np.stack([x, y, z])  # rows: camera axes in world coordinates
    return acm_rs.rodrigues_inverse(rot), -rot @ np.asarray(center, float)


def make_rig() -> acm_rs.CameraRig:
    """Four cameras 60-100 cm from the origin, above the animal, looking at the origin.

    Returns
    -------
    acm_rs.CameraRig
        Cameras ``cam0``..``cam3``: 1280 x 1024 px, fx ~ 1200 px, small k1/k2 distortion.
    """
    distance = [65.0, 80.0, 95.0, 72.0]  # cm
    azimuth = np.radians([20.0, 110.0, 200.0, 290.0])  # around the up axis
    elevation = np.radians([35.0, 25.0, 45.0, 30.0])  # above the horizontal plane
    cams = []
    for i in range(4):
        d, az, el = distance[i], azimuth[i], elevation[i]
        center = d * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        rvec, tvec = look_at(center, np.zeros(3), WORLD_UP)
        fx = 1200.0 + 15.0 * i
        matrix = [[fx, 0.0, 640.0 + 3.0 * i], [0.0, fx * 1.001, 512.0 - 2.0 * i], [0.0, 0.0, 1.0]]
        dist = [-0.06 + 0.01 * i, 0.02 - 0.005 * i]
        cams.append(acm_rs.Camera(matrix, dist, rvec, tvec, size=(1280, 1024), name=f"cam{i}"))
    return acm_rs.CameraRig(cams)


def pose_ranges(skeleton: acm_rs.Skeleton, unbounded: float = 0.3) -> tuple[np.ndarray, ...]:
    """``(low, high)``, each ``(n_bones, 3)``: the middle half of every joint-limit interval.

    Unbounded limits are replaced by ``+-unbounded`` rad; fixed entries give ``low == high``.
    """
    lim = np.array(skeleton.joint_limits, dtype=float)  # (n_bones, 3, 2)
    lo = np.where(np.isfinite(lim[..., 0]), lim[..., 0], -unbounded)
    hi = np.where(np.isfinite(lim[..., 1]), lim[..., 1], unbounded)
    mid, half = 0.5 * (lo + hi), 0.25 * (hi - lo)
    return mid - half, mid + half


def random_poses(
    skeleton: acm_rs.Skeleton, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Random poses ``t (n, 3)`` (cm) and ``r (n, n_bones, 3)`` (rad) as described above."""
    t = ROOT_CENTER + rng.uniform(-3.0, 3.0, size=(n, 3))
    lo, hi = pose_ranges(skeleton)
    r = lo + (hi - lo) * rng.uniform(size=(n, skeleton.n_bones, 3))
    return t, r


def best_time(fn: Callable[[], object], repeats: int, number: int = 1) -> float:
    """Best wall time per call over ``repeats`` runs of ``number`` calls (seconds)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def machine_info() -> dict[str, object]:
    """Processor, core count and library versions of this run."""
    proc = platform.processor()
    if not proc:
        try:
            with open("/proc/cpuinfo") as fh:
                proc = next(
                    (ln.split(":", 1)[1].strip() for ln in fh if ln.startswith("model name")),
                    "",
                )
        except OSError:
            proc = ""
    return {
        "processor": proc or platform.machine(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "acm_rs": acm_rs.__version__,
    }


def max_abs_diff(a: np.ndarray, b: np.ndarray) -> float:
    """Max ``|a - b|``; requires the same NaN pattern (points behind a camera)."""
    na, nb = np.isnan(a), np.isnan(b)
    if not np.array_equal(na, nb):
        raise AssertionError(f"NaN patterns differ ({na.sum()} vs {nb.sum()} NaN entries)")
    return float(np.max(np.abs(a[~na] - b[~nb]), initial=0.0))


def main(argv: list[str] | None = None) -> dict[str, object]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=100_000, help="poses to time (default 1e5)")
    parser.add_argument("--repeats", type=int, default=5, help="timing repeats (best is kept)")
    parser.add_argument("--json", type=Path, default=None, help="also write results here")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.repeats < 1:
        parser.error("--frames and --repeats must be >= 1")

    skeleton = acm_rs.models.rat()
    rig = make_rig()
    params = rig.get_params()
    plan = fk_plan(skeleton)  # structure set up once, as the Rust skeleton holds it
    rng = np.random.default_rng(0)
    t, r = random_poses(skeleton, args.frames, rng)

    def run_acm() -> np.ndarray:
        _, markers = skeleton.forward(t, r)
        return rig.project(markers)

    def run_np() -> np.ndarray:
        _, markers = forward_np(skeleton, t, r, plan=plan)
        return project_np(params, markers)

    # (a) agreement
    joints_acm, markers_acm = skeleton.forward(t, r)
    joints_np, markers_np = forward_np(skeleton, t, r, plan=plan)
    px_acm, px_np = run_acm(), run_np()
    diff_3d = max(max_abs_diff(joints_acm, joints_np), max_abs_diff(markers_acm, markers_np))
    diff_px = max_abs_diff(px_acm, px_np)
    n_nan = int(np.isnan(px_acm[..., 0]).sum())
    print(
        f"rat model: {skeleton.n_joints} joints, {skeleton.n_bones} bones, "
        f"{skeleton.n_markers} markers; {len(rig)} cameras; {args.frames} random poses"
    )
    print(
        f"(a) max |acm_rs - numpy|: {diff_3d:.3e} cm (joints, markers), {diff_px:.3e} px "
        f"({n_nan} of {px_acm[..., 0].size} projections behind a camera)"
    )
    assert diff_px < 1e-6, f"acm_rs and the NumPy reference differ by {diff_px} px"
    assert diff_3d < 1e-9, f"acm_rs and the NumPy reference differ by {diff_3d} cm"

    _, markers_simple = forward_np_simple(skeleton, t, r)
    diff_simple = max_abs_diff(project_np_simple(params, markers_simple), px_np)
    assert diff_simple < 1e-6, f"the straightforward NumPy version differs by {diff_simple} px"

    # (b) timing, best of repeats
    timings = {
        "forward kinematics": (
            best_time(lambda: forward_np(skeleton, t, r, plan=plan), args.repeats),
            best_time(lambda: skeleton.forward(t, r), args.repeats),
        ),
        "projection": (
            best_time(lambda: project_np(params, markers_np), args.repeats),
            best_time(lambda: rig.project(markers_acm), args.repeats),
        ),
        "FK + projection": (
            best_time(run_np, args.repeats),
            best_time(run_acm, args.repeats),
        ),
        "fused FK+projection": (
            best_time(run_np, args.repeats),
            best_time(lambda: skeleton.project(rig, t, r), args.repeats),
        ),
    }
    simple_s = best_time(
        lambda: project_np_simple(params, forward_np_simple(skeleton, t, r)[1]),
        max(1, args.repeats // 2),
    )
    info = machine_info()
    print(
        f"\n(b) {args.frames} frames, best of {args.repeats} "
        f"({skeleton.n_markers} markers x {len(rig)} cameras = "
        f"{args.frames * skeleton.n_markers * len(rig)} projected points)"
    )
    header = f"{'frames':>8}  {'stage':<19} {'NumPy s':>9} {'acm_rs s':>9} {'speed-up':>9}"
    print(header)
    print("-" * len(header))
    rows = []
    for stage, (t_np, t_acm) in timings.items():
        print(f"{args.frames:>8}  {stage:<19} {t_np:>9.4f} {t_acm:>9.4f} {t_np / t_acm:>8.1f}x")
        rows.append(
            {"frames": args.frames, "stage": stage, "numpy_s": t_np, "acm_rs_s": t_acm,
             "speedup": t_np / t_acm}
        )  # fmt: skip
    fused_s = timings["fused FK+projection"][1]
    print(
        f"{args.frames:>8}  {'straightforward NumPy FK+projection':<35} {simple_s:>9.4f} s "
        f"(fused acm_rs is {simple_s / fused_s:.1f}x faster)"
    )
    rows.append(
        {"frames": args.frames, "stage": "straightforward NumPy FK + projection",
         "numpy_s": simple_s, "acm_rs_s": fused_s, "speedup": simple_s / fused_s}
    )  # fmt: skip
    print(
        f"machine: {info['processor']} ({info['machine']}), {info['cpu_count']} CPUs, "
        f"Python {info['python']}, NumPy {info['numpy']}, acm_rs {info['acm_rs']}"
    )

    # (c) one set of sigma points through the fused native path
    ts, rs = random_poses(skeleton, N_SIGMA, rng)

    def sigma_np() -> np.ndarray:
        _, m = forward_np(skeleton, ts, rs, plan=plan)
        return project_np(params, m)

    px_fused = skeleton.project(rig, ts, rs)  # (C, N, M, 2)
    diff_sigma = max_abs_diff(px_fused, sigma_np())
    assert diff_sigma < 1e-6, f"Skeleton.project and the NumPy reference differ by {diff_sigma} px"
    number = 50
    us_fused = 1e6 * best_time(lambda: skeleton.project(rig, ts, rs), args.repeats, number)
    us_np = 1e6 * best_time(sigma_np, args.repeats, number)
    print(
        f"\n(c) {N_SIGMA} poses (sigma points of the 50-dim state) -> "
        f"{N_SIGMA}x{len(rig)}x{skeleton.n_markers} pixels, best of {args.repeats}x{number} "
        f"(max diff {diff_sigma:.1e} px)"
    )
    print(f"    NumPy reference (forward_np + project_np): {us_np:10.1f} us")
    print(f"    acm_rs Skeleton.project (fused, Python):   {us_fused:10.1f} us")
    print(f"    speed-up:                                  {us_np / us_fused:10.1f}x")

    results = {
        "machine": info,
        "frames": args.frames,
        "repeats": args.repeats,
        "max_abs_diff_px": diff_px,
        "max_abs_diff_world": diff_3d,
        "timings": rows,
        "sigma_points": {
            "poses": N_SIGMA,
            "numpy_us": us_np,
            "acm_rs_project_us": us_fused,
            "speedup": us_np / us_fused,
            "max_abs_diff_px": diff_sigma,
        },
    }
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
        print(f"\nwrote {args.json}")
    return results


if __name__ == "__main__":
    main()
