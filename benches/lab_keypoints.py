"""A lab's own keypoints on real files (issue 28): rigid vs elastic segments on the real
Label3D / DANNCE file, and the calibration refined on keypoints on the real SLEAP session,
with their figures of record.

    python benches/lab_keypoints.py

Truth: the Label3D file's own 3D labels (read with scipy.io, not by acm-rs) for the segment
SDs; the human labels of the held-out camera for the leave-one-camera-out errors. Both files
are in ``tests/data/real`` with their provenance.
"""

from __future__ import annotations

import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from acm_rs.calibration import read_label3d_calibration
from acm_rs.elastic import add_stretch
from acm_rs.evaluate import evaluate, evaluate_refined
from acm_rs.lab_skeleton import read_keypoint_graph, skeleton_from_labels
from acm_rs.learning import learn_skeleton
from acm_rs.sleap_session import read_sleap_session

REAL = Path(__file__).resolve().parents[1] / "tests" / "data" / "real"
sys.path.insert(0, str(REAL.parents[1]))

from label3d_labels import read_labels  # noqa: E402


def label3d():
    path = REAL / "dannce" / "label3d_voltest_dannce_m1.mat"
    rig = read_label3d_calibration(path)
    graph = read_keypoint_graph(REAL / "dannce" / "mouse22_skeleton.mat")
    names = list(graph.keypoints)
    lab2, lab3 = read_labels(path)
    return rig, graph, names, lab2, lab3


def learned(rig, graph, names, lab2):
    sk = skeleton_from_labels(graph, rig, lab2, bodyparts=names, joint_limits=False).skeleton
    lab = lab2[:, :, [names.index(k) for k in sk.marker_names]]
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rigid = learn_skeleton(rig, sk, lab, progress=False)
    t1 = time.perf_counter()
    elastic, fit = add_stretch(rigid)
    return rigid, elastic, fit, t1 - t0, time.perf_counter() - t1


def main() -> None:
    print(f"machine: {platform.machine()}, Python {platform.python_version()}")
    rig, graph, names, lab2, lab3 = label3d()
    rng = np.random.default_rng(0)
    print("Label3D file (6 cameras, 10 frames, 22 keypoints), leave-one-camera-out mean px:")
    print("| 2D labels | rigid (learned) | elastic | DLT | elastic EM its | learn s + EM s |")
    print("|---|---|---|---|---|---|")
    for noise in (0.0, 1.0, 3.0):
        lab = lab2 + (rng.normal(0, noise, lab2.shape) if noise else 0.0)
        rigid, elastic, fit, s_rigid, s_em = learned(rig, graph, names, lab)
        r = evaluate(rig, rigid.skeleton, lab, bodyparts=names).per_camera.loc["all"]
        e = evaluate(rig, elastic.skeleton, lab, bodyparts=names).per_camera.loc["all"]
        what = "as in the file (reprojections of 3D)" if not noise else f"+ {noise:g} px noise"
        print(
            f"| {what} | {r['model_px']:.2f} | {e['model_px']:.2f} | "
            f"{e['triangulation_px']:.2f} | {fit.iterations} | {s_rigid:.1f} + {s_em:.2f} |"
        )
        if not noise:
            sk, jn = elastic.skeleton, elastic.skeleton.joint_names
            truth = np.array([
                np.nanstd(np.linalg.norm(lab3[:, names.index(jn[b])] - lab3[:, names.index(jn[a])],
                                         axis=-1)) for a, b in sk.bones
            ])  # fmt: skip
            ratio = fit.length_sd() / truth
            print(
                f"  learned segment SD / 3D labels' SD: {ratio.min():.2f}-{ratio.max():.2f} "
                f"(median {np.median(ratio):.2f}; true SDs {truth.min():.2f}-{truth.max():.2f} mm)"
            )
    path = REAL / "sleap" / "min_session_user_labeled.slp"
    ses = read_sleap_session(path, individual="track_0")
    graph = read_keypoint_graph(path)
    rigid, elastic, _, _, _ = learned(ses.rig, graph, list(ses.labels.bodyparts), ses.labels.points)
    print("\nreal SLEAP session (8 cameras, 3 frames, 15 nodes), leave-one-camera-out mean px:")
    for tag, sk in (("rigid", rigid.skeleton), ("elastic", elastic.skeleton)):
        print(f"  {tag}: {evaluate(ses.rig, sk, ses.labels).summary()}")
    t0 = time.perf_counter()
    ref = evaluate_refined(ses.rig, rigid.skeleton, ses.labels)
    print(f"  calibration refined on keypoints ({time.perf_counter() - t0:.1f} s):")
    print("  " + ref.summary().replace("\n", "\n  "))


if __name__ == "__main__":
    main()
