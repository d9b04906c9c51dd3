"""Skeleton learning and run-acm on ACM folders made in the authors' conventions (issue 13).

Writes folders with ``tests/acm_conformance.py`` (several individuals and body weights), runs
``acm_rs.run_acm`` on each and prints the bone-length and joint errors against the truth.
With ``--authors-python`` and ``--authors-src`` it also runs the authors' skeleton learning
(``python -m ACM FOLDER --calibration``, bbo-lab/ACM, needs torch; ~20 min per folder on 2
cores) on the first folder and compares both on the same data.

    python benches/acm_conformance.py --seeds 0-7 --weights 72 150 350 --manual 30
    python benches/acm_conformance.py --seeds 10 --weights 72 --manual 30 \\
        --authors-python /path/to/venv/bin/python --authors-src /path/to/ACM
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import acm_conformance as ac  # noqa: E402

from acm_rs.run_acm import run_acm  # noqa: E402


def _seeds(spec: str) -> list[int]:
    if "-" in spec:
        a, b = spec.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(v) for v in spec.split(",")]


def _authors_lengths(folder: Path) -> dict[str, float]:
    """Bone lengths of the authors' ``results/x_calib.npy`` (by end joint)."""
    m = np.load(folder / "model.npy", allow_pickle=True).item()
    jo = [n[len("joint_") :] for n in m["joint_order"]]
    edges = m["skeleton_edges"]
    x = np.load(folder / "results" / "x_calib.npy", allow_pickle=True)
    index: list[int] = []
    count = 0
    for _, e in edges:  # anatomy.get_bone_lengths_index: right bones share the left entry
        name = jo[e]
        if "right" in name:
            left = jo.index(name.replace("right", "left"))
            index.append(index[int(np.flatnonzero(edges[:, 1] == left)[0])])
        else:
            index.append(count)
            count += 1
    return {jo[e]: float(x[index[b]]) for b, (_, e) in enumerate(edges)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-7", help="individuals, e.g. 0-7 or 1,4")
    ap.add_argument("--weights", type=float, nargs="+", default=[72.0, 150.0, 350.0],
                    help="body weights (g)")  # fmt: skip
    ap.add_argument("--manual", type=int, default=30, help="manually labelled frames")
    ap.add_argument("--dlc", type=int, default=200, help="DeepLabCut frames (tracked every 2nd)")
    ap.add_argument("--authors-python", help="python with torch for the authors' tool")
    ap.add_argument("--authors-src", help="checkout of bbo-lab/ACM (its ACM package)")
    args = ap.parse_args()
    warnings.simplefilter("ignore", UserWarning)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in _seeds(args.seeds):
            for w in args.weights:
                folder = Path(tmp) / f"s{seed}_w{w:g}"
                c = ac.write_conformance_dataset(
                    folder, seed=seed, body_weight=w, n_manual=args.manual, n_dlc=args.dlc
                )
                t0 = time.perf_counter()
                res = run_acm(folder, Path(tmp) / f"out_s{seed}_w{w:g}", progress=False)
                total = time.perf_counter() - t0
                sk = res.learned.skeleton
                err = np.array(
                    [sk.bone_lengths[sk.bone_index(n)] - v for n, v in c.bone_lengths.items()]
                )
                pose = np.load(Path(tmp) / f"out_s{seed}_w{w:g}" / "pose.npy", allow_pickle=True)
                idx = np.searchsorted(c.frames, res.result.info["frames"])
                jerr = np.linalg.norm(pose.item()["joint_positions_3d"] - c.joints[idx], axis=-1)
                rows.append((seed, w, np.abs(err).mean(), np.abs(err).max(), jerr.mean(),
                             res.learned.rms, res.seconds["learn"], total))  # fmt: skip
                print(
                    f"seed {seed} {w:5g} g: bones mean |err| {rows[-1][2]:.3f} cm (max "
                    f"{rows[-1][3]:.3f}), joints mean {rows[-1][4]:.3f} cm, learning RMS "
                    f"{rows[-1][5]:.2f} px, learn {rows[-1][6]:.1f} s, run-acm {total:.1f} s",
                    flush=True,
                )
                if args.authors_python and len(rows) == 1:
                    t0 = time.perf_counter()
                    subprocess.run(
                        [args.authors_python, "-m", "ACM", str(folder), "--calibration"],
                        cwd=args.authors_src, check=False, stdin=subprocess.DEVNULL,
                        stdout=subprocess.DEVNULL,
                    )  # fmt: skip
                    sec = time.perf_counter() - t0
                    theirs = _authors_lengths(folder)
                    e2 = np.array([theirs[n] - v for n, v in c.bone_lengths.items()])
                    print(
                        f"  authors' tool (skeleton learning only): bones mean |err| "
                        f"{np.abs(e2).mean():.3f} cm (max {np.abs(e2).max():.3f}) in {sec:.0f} s"
                    )
    a = np.array(rows)
    print(
        f"\n{len(rows)} folders: bones mean |err| {a[:, 2].mean():.3f} cm (median "
        f"{np.median(a[:, 2]):.3f}; <= 0.05 in {np.mean(a[:, 2] <= 0.05):.0%}), worst bone "
        f"{a[:, 3].max():.2f} cm; joints mean {a[:, 4].mean():.3f} cm (median "
        f"{np.median(a[:, 4]):.3f}; <= 0.08 in {np.mean(a[:, 4] <= 0.08):.0%}); learning RMS "
        f"{np.median(a[:, 5]):.2f} px median; learn {np.median(a[:, 6]):.1f} s, run-acm "
        f"{np.median(a[:, 7]):.1f} s median"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
