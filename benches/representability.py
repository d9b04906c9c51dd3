"""Can the forward model represent real motion? (issue 25)

The authors' published output for their example sequence, ``pose.npy`` of
``exampledata/table_1_20210511_test`` in bbo-lab/ACM (commit bbc99f6), holds the 3D joint
positions of a real rat over 240 time points (cm, arena frame). The file is not in this
repository (the developers keep no fetched data); point ``--pose`` or the environment
variable ``ACM_RS_AUTHORS_POSE`` at a copy.

The check: a skeleton with the animal's bone lengths and rest pose (its first frame), the
girdle bones (clavicles, pelvis halves) fixed as the rat model's joint limits fix them, is
fitted frame by frame to the noise-free joint positions (Levenberg-Marquardt on the exact
Jacobian of :meth:`acm_rs.Skeleton.forward_jacobian`). With the tree rule (a rotation moves
its bone and the bone's descendants) every joint must be reached to <= 0.01 mm; the literal
reading of Alg. 1 (siblings coupled) cannot: its girdles stay at one angle to the spine.

The file's joint order is the authors' ``joint_order`` of that dataset (their ``model.npy``
is not published). It follows from the data: the 28 pairs of joints at constant distance
whose distances are ``x_calib.npy``'s bone lengths form the rat's tree; left and right are
told apart by the side of the body (checked in :func:`load_authors_pose`).

Run::

    python benches/representability.py --pose path/to/pose.npy [--frames 240]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

import acm_rs
from acm_rs import acm_model

#: the authors' joint order in the example dataset, with each joint's parent
AUTHORS_TREE = [
    ("head_001", ""), ("spine_005", "head_001"), ("spine_004", "spine_005"),
    ("shoulder_left", "spine_004"), ("elbow_left", "shoulder_left"),
    ("shoulder_right", "spine_004"), ("elbow_right", "shoulder_right"),
    ("spine_003", "spine_004"), ("spine_002", "spine_003"), ("hip_left", "spine_002"),
    ("hip_right", "spine_002"), ("knee_left", "hip_left"), ("ankle_left", "knee_left"),
    ("knee_right", "hip_right"), ("ankle_right", "knee_right"),
    ("paw_hind_left", "ankle_left"), ("paw_hind_right", "ankle_right"),
    ("spine_001", "spine_002"), ("tail_005", "spine_001"), ("tail_004", "tail_005"),
    ("tail_003", "tail_004"), ("tail_002", "tail_003"), ("tail_001", "tail_002"),
    ("toe_left_002", "paw_hind_left"), ("toe_right_002", "paw_hind_right"),
    ("wrist_left", "elbow_left"), ("finger_left_002", "wrist_left"),
    ("wrist_right", "elbow_right"), ("finger_right_002", "wrist_right"),
]  # fmt: skip

#: bones whose rotation the rat model fixes on every axis (Supp. Table 1: [0, 0])
GIRDLES = ("shoulder_left", "shoulder_right", "hip_left", "hip_right")


def default_pose_path() -> Path | None:
    """``$ACM_RS_AUTHORS_POSE`` or ``../shared/data/acm/pose.npy`` when present."""
    env = os.environ.get("ACM_RS_AUTHORS_POSE")
    candidates = [Path(env)] if env else []
    candidates.append(Path(__file__).resolve().parents[2] / "shared/data/acm/pose.npy")
    return next((p for p in candidates if p.is_file()), None)


def load_authors_pose(path: str | Path) -> tuple[list[str], np.ndarray]:
    """The joint names and ``joint_positions_3d (T, 29, 3)`` (cm) of the authors' pose.npy.

    Raises
    ------
    ValueError
        If the file's joints do not fit :data:`AUTHORS_TREE`: a bone whose length varies by
        more than 1e-9 cm, or left and right swapped.
    """
    d = np.load(path, allow_pickle=True).item()
    joints = np.asarray(d["joint_positions_3d"], dtype=np.float64)
    names = [n for n, _ in AUTHORS_TREE]
    if joints.shape[1:] != (len(names), 3):
        raise ValueError(f"{path}: joint_positions_3d has shape {joints.shape}")
    for n, p in AUTHORS_TREE[1:]:
        d = np.linalg.norm(joints[:, names.index(n)] - joints[:, names.index(p)], axis=-1)
        if d.std() > 1e-9:
            raise ValueError(f"{path}: {p}-{n} is not a bone of this file (SD {d.std():.2e})")
    # left is on the left: (shoulder_left - spine_004) . (dorsal x forward) > 0, dorsal = +z
    i = {n: names.index(n) for n in names}
    fwd = joints[:, i["head_001"]] - joints[:, i["spine_004"]]
    left = np.cross([0.0, 0.0, 1.0], fwd)
    side = np.einsum("ti,ti->t", joints[:, i["shoulder_left"]] - joints[:, i["spine_004"]], left)
    if np.median(side) <= 0:
        raise ValueError(f"{path}: shoulder_left is on the animal's right")
    return names, joints


def skeleton_of(names: list[str], rest: np.ndarray, rule: str = "tree") -> acm_rs.Skeleton:
    """A skeleton (no markers) in the rest pose ``rest (29, 3)``; ``rule``: ``"tree"`` or
    ``"literal"`` (Alg. 1 line 5 as printed: siblings coupled)."""
    parents = [names.index(p) if p else -1 for _, p in AUTHORS_TREE]
    sk = acm_rs.Skeleton.from_rest_pose(
        names, parents, rest, [], [], np.zeros((0, 3)), up=(0, 0, 1)
    )
    if rule == "literal":
        sk = sk.with_links(acm_model.literal_alg1_links(sk.parents, sk.bones))
    elif rule != "tree":
        raise ValueError(f"rule must be 'tree' or 'literal', got {rule!r}")
    return sk


def fit_joints(sk: acm_rs.Skeleton, joints: np.ndarray, fixed: tuple[str, ...] = GIRDLES):
    """Per-frame least-squares fit of ``(t, r)`` to joint positions ``(T, J, 3)``, the bones
    ``fixed`` held at zero rotation; returns the residual distance ``(T, J)`` per frame and
    joint (see :func:`fit_poses` for the poses)."""
    return fit_poses(sk, joints, fixed)[0]


def fit_poses(sk: acm_rs.Skeleton, joints: np.ndarray, fixed: tuple[str, ...] = GIRDLES):
    """As :func:`fit_joints`; returns ``(residual (T, J), t (T, 3), r (T, n_bones, 3))``."""
    free = np.ones((sk.n_bones, 3), bool)
    free[[sk.bone_index(n) for n in fixed]] = False
    mask = np.concatenate([[True] * 3, free.ravel()])
    x = np.zeros(sk.n_pose)
    x[:3] = joints[0, 0]
    out = np.empty(joints.shape[:2])
    poses = np.empty((len(joints), sk.n_pose))
    for f, target in enumerate(joints):

        def pose(z, x=x):
            full = x.copy()
            full[mask] = z
            return full[:3], full[3:].reshape(-1, 3)

        def res(z, target=target, pose=pose):
            return (sk.forward(*pose(z))[0] - target).ravel()

        def jac(z, pose=pose):
            d = sk.forward_jacobian(*pose(z)).d_joints_d_pose
            return d.reshape(-1, sk.n_pose)[:, mask]

        sol = least_squares(res, x[mask], jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
        x[mask] = sol.x  # warm start of the next frame
        out[f] = np.linalg.norm(sol.fun.reshape(-1, 3), axis=-1)
        poses[f] = x
    return out, poses[:, :3], poses[:, 3:].reshape(len(joints), sk.n_bones, 3)


def dressed_skeleton(names: list[str], rest: np.ndarray) -> acm_rs.Skeleton:
    """The real animal (its bone lengths; rest pose = ``rest``, its first frame) wearing the
    rat model's 43 markers: each at the model's offset in its bone's frame (x right, y dorsal,
    z along the bone; dorsal = the arena's +z)."""
    rat = acm_rs.models.rat()
    bare = skeleton_of(names, rest)
    frames = bare.rest_frames
    root_bone = int(bare.root_bones[0])
    joint_of = [rat.joint_names[j] for j in rat.marker_joints]
    marker_rest = np.array(
        [
            rest[names.index(j)] + frames[bare.bone_index(j) if j != names[0] else root_bone] @ v
            for j, v in zip(joint_of, rat.marker_offsets, strict=True)
        ]
    )
    parents = [names.index(p) if p else -1 for _, p in AUTHORS_TREE]
    return acm_rs.Skeleton.from_rest_pose(
        names, parents, rest, rat.marker_names, joint_of, marker_rest, up=(0, 0, 1),
        symmetry=rat.symmetry, name="real_rat", units="cm",
    )  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--pose", type=Path, default=None, help="the authors' pose.npy")
    ap.add_argument("--frames", type=int, default=240)
    args = ap.parse_args(argv)
    path = args.pose or default_pose_path()
    if path is None:
        print("no pose.npy: pass --pose or set ACM_RS_AUTHORS_POSE", file=sys.stderr)
        return 2
    names, joints = load_authors_pose(path)
    joints = joints[: args.frames]
    print(f"{path}: {len(joints)} time points of the authors' example output")
    for rule in ("tree", "literal"):
        sk = skeleton_of(names, joints[0], rule)
        start = time.perf_counter()
        err_mm = fit_joints(sk, joints) * 10.0
        worst = [names[j] for j in np.argsort(err_mm.max(axis=0))[::-1][:4]]
        print(
            f"  {rule:8s} rule: joint residual max {err_mm.max():.2e} mm, p95 "
            f"{np.percentile(err_mm, 95):.2e} mm ({time.perf_counter() - start:.1f} s); "
            f"largest at {', '.join(worst)}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
