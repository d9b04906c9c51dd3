"""Elastic segments against rigid bones, side by side in one run (issue 28 item 2).

Truth from independent code (``tests/elastic_truth.py``: a keypoint tree in plain NumPy with
6-12 % log-stretch SDs on five of eight segments, projected by OpenCV), 4 cameras, Gaussian
detection noise. For each seed: a skeleton from the lab's graph learned on 40 labelled frames
(rigidly, then ``add_stretch``), then ``acm_rs.track`` with the rigid and with the elastic
skeleton on the whole recording. Reports keypoint (joint) errors in mm, 95 % coverage, EM
iterations, wall time, and the learned stretch SDs over the true ones. With aniposelib
installed, the peer runs on the same detections in the same run: ``triangulate_optim`` with the
lab's skeleton edges as length constraints and ``compare_anipose.py``'s options (its 3D points
are the keypoints).

    python benches/elastic_tracking.py [--frames 240] [--seeds 1 2 3] [--noise 1.0] [--ar 0.9]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import acm_rs
from acm_rs.elastic import add_stretch
from acm_rs.lab_skeleton import KeypointGraph, skeleton_from_labels
from acm_rs.learning import learn_skeleton

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from elastic_truth import EDGES, NAMES, SD, cameras, project, synthetic  # noqa: E402


def run_peer(rig, det: np.ndarray, truth: np.ndarray, names: list[str]) -> dict | None:
    """aniposelib's triangulate_optim with the lab's edges as constraints (None without it)."""
    try:
        from compare_anipose import PEER_OPTIONS, anipose_group
    except ImportError:
        return None
    try:
        group = anipose_group(rig)
    except ImportError:
        return None
    constraints = [[names.index(a), names.index(b)] for a, b in EDGES]
    group.triangulate_optim(det[:, :20], constraints=constraints, **PEER_OPTIONS)  # JIT warm-up
    t0 = time.perf_counter()
    p3d = group.triangulate_optim(det, init_ransac=False, constraints=constraints, **PEER_OPTIONS)
    seconds = time.perf_counter() - t0
    e = np.linalg.norm(np.asarray(p3d, float) - truth, axis=-1)
    return {
        "model": "anipose", "median": np.nanmedian(e), "p95": np.nanpercentile(e, 95),
        "max": np.nanmax(e), "coverage": np.nan, "iterations": "-", "motion": "-",
        "seconds": seconds, "sd_ratio": "",
    }  # fmt: skip


def run(n_frames: int, seed: int, noise: float, ar: float) -> list[dict]:
    pts, stretch = synthetic(n_frames, seed, ar)
    cams = cameras()
    det = project(cams, pts) + np.random.default_rng(seed + 100).normal(
        0, noise, (4, n_frames, 9, 2)
    )
    rig = acm_rs.CameraRig(
        [acm_rs.Camera(k, d, rv, tv, (1280, 1024), name=f"c{i}") for i, (k, d, rv, tv) in
         enumerate(cams)], units="mm",
    )  # fmt: skip
    sk0 = skeleton_from_labels(
        KeypointGraph(NAMES, EDGES), rig, det[:, :40], bodyparts=NAMES, joint_limits=False
    ).skeleton
    order = [NAMES.index(m) for m in sk0.marker_names]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rigid = learn_skeleton(rig, sk0, det[:, :40][:, :, order], progress=False)
    elastic, _ = add_stretch(rigid)
    rows = []
    peer = run_peer(rig, det, pts, NAMES)
    if peer is not None:
        rows.append({"seed": seed} | peer)
    for tag, sk in (("rigid", rigid.skeleton), ("elastic", elastic.skeleton)):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = acm_rs.track(rig, sk, det[:, :, order])
        seconds = time.perf_counter() - t0
        names = list(sk.joint_names)
        idx = [names.index(m) for m in sk.marker_names]
        j, sd = res.joints[:, idx], res.joints_std[:, idx]
        e = np.linalg.norm(j - pts[:, order], axis=-1)
        row = {
            "seed": seed, "model": tag, "median": np.median(e), "p95": np.percentile(e, 95),
            "max": e.max(), "coverage": np.mean(np.abs(j - pts[:, order]) <= 1.96 * sd),
            "iterations": res.info["iterations"], "motion": res.info["motion"],
            "seconds": seconds, "sd_ratio": "",
        }  # fmt: skip
        if res.info.get("elastic"):
            ratios = []
            for b, (a, c) in enumerate(sk.bones):
                child = next(ch for p, ch in EDGES if {p, ch} == {names[a], names[c]})
                if SD[child] > 0:
                    ratios.append(res.info["stretch_sd"][b] / np.std(stretch[child]))
            row["sd_ratio"] = f"{min(ratios):.2f}-{max(ratios):.2f}"
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--noise", type=float, default=1.0, help="detection noise SD (px)")
    ap.add_argument("--ar", type=float, default=0.9, help="AR(1) coefficient of the stretch")
    a = ap.parse_args()
    print(f"{a.frames} frames, 4 cameras, {a.noise} px noise, stretch AR({a.ar}); joints in mm")
    print("| seed | model | median | p95 | max | 95 % coverage | EM its (motion) | s | "
          "learned / true stretch SD |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for seed in a.seeds:
        for r in run(a.frames, seed, a.noise, a.ar):
            cover = "-" if np.isnan(r["coverage"]) else f"{100 * r['coverage']:.1f} %"
            print(
                f"| {r['seed']} | {r['model']} | {r['median']:.2f} | {r['p95']:.2f} | "
                f"{r['max']:.2f} | {cover} | {r['iterations']} "
                f"({r['motion']}) | {r['seconds']:.1f} | {r['sd_ratio']} |"
            )


if __name__ == "__main__":
    main()
