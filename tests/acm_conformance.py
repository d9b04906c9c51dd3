"""ACM dataset folders made in the authors' conventions, with ground truth (issue 13).

Written from the facts table of ``docs/models.md`` (the authors' ``anatomy.py``, ``model.py``,
``helper.py``, ``calibration.py`` of bbo-lab/ACM), in plain NumPy, without any acm-rs code, so
that a test of ``run-acm`` on these folders checks our reading of the authors' model rather than
our own assumptions:

* ``model.npy``: joints/markers in alphabetical order (``joint_*``, ``marker_*_start``), a
  posed mesh skeleton with unit bones whose girdles point sideways, ventrally and along the
  body (not as our bundled model draws them), ``skeleton_coords`` made as the authors'
  ``get_skeleton_coords`` makes them (float16 bone direction, minimal turn from +z, Euler
  x-y-z solution with the smaller norm), links as the authors' files hold them (a rotation
  moves its bone and the bone's descendants; or, on request, the literal reading of Alg. 1
  that also moves the siblings), a bone order unlike ours;
* the animal: the authors' forward model (``adjust_joint_marker_pos2``) -- every bone from
  the identity frame except the girdles' ``coords0``; rotations composed
  ``R0 R_i1 R_i2 ... coords0[b]`` over the bones whose links reach ``b``; markers on the bone
  ending at their joint, no offset on the root; offsets mirrored in x on the right;
* the rig: old-style ``A_fit`` ``[fx, cx, fy, cy]``, five OpenCV coefficients, calibration in
  board squares (``scale_factor`` cm each) in a frame moved by ``origin_coord.npy``; the
  projection of ``model.map_m``;
* labels: ``labels_manual.npz`` (``{frame: {"spot_<name>": (n_cams, 2)}}``, NaN where not
  labelled) and ``labels_dlc_*.npy`` (``(F, n_cams, 43, 3)`` with likelihoods).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

# -- the rat of the authors' model (names as in their files, without prefixes) ----------------
# (joint, parent) in a root-first order that is not acm-rs's breadth-first order
TREE = [
    ("head_001", ""), ("spine_005", "head_001"), ("spine_004", "spine_005"),
    ("spine_003", "spine_004"), ("spine_002", "spine_003"), ("spine_001", "spine_002"),
    ("tail_005", "spine_001"), ("tail_004", "tail_005"), ("tail_003", "tail_004"),
    ("tail_002", "tail_003"), ("tail_001", "tail_002"),
    ("shoulder_left", "spine_004"), ("elbow_left", "shoulder_left"),
    ("wrist_left", "elbow_left"), ("finger_left_002", "wrist_left"),
    ("shoulder_right", "spine_004"), ("elbow_right", "shoulder_right"),
    ("wrist_right", "elbow_right"), ("finger_right_002", "wrist_right"),
    ("hip_left", "spine_002"), ("knee_left", "hip_left"), ("ankle_left", "knee_left"),
    ("paw_hind_left", "ankle_left"), ("toe_left_002", "paw_hind_left"),
    ("hip_right", "spine_002"), ("knee_right", "hip_right"), ("ankle_right", "knee_right"),
    ("paw_hind_right", "ankle_right"), ("toe_right_002", "paw_hind_right"),
]  # fmt: skip

# marker -> joint it is attached to
MARKERS = {
    "head_001": "spine_005", "head_002": "spine_005", "head_003": "head_001",
    "spine_001": "spine_002", "spine_002": "spine_002", "spine_003": "spine_003",
    "spine_004": "spine_003", "spine_005": "spine_004", "spine_006": "spine_005",
    "tail_001": "tail_001", "tail_002": "tail_002", "tail_003": "tail_003",
    "tail_004": "tail_004", "tail_005": "tail_005", "tail_006": "spine_001",
}  # fmt: skip
for _s in ("left", "right"):
    MARKERS |= {
        f"shoulder_{_s}": f"shoulder_{_s}", f"elbow_{_s}": f"elbow_{_s}",
        f"paw_front_{_s}": f"wrist_{_s}", f"side_{_s}": "spine_003",
        f"hip_{_s}": f"hip_{_s}", f"knee_{_s}": f"knee_{_s}", f"ankle_{_s}": f"ankle_{_s}",
        f"paw_hind_{_s}": f"paw_hind_{_s}",
    }  # fmt: skip
    MARKERS |= {f"finger_{_s}_00{i}": f"finger_{_s}_002" for i in (1, 2, 3)}
    MARKERS |= {f"toe_{_s}_00{i}": f"toe_{_s}_002" for i in (1, 2, 3)}

INF = np.inf
# anatomy.get_bounds_markers for the left and central markers: {marker: [[lo, hi] x, y, z]}
_FREE = [-INF, INF]
MARKER_BOXES = {
    "shoulder_left": [[0, 0], [0, INF], [0, 0]],
    "elbow_left": [[-INF, 0], [0, 0], [0, 0]],
    "paw_front_left": [[0, 0], [-INF, 0], [0, 0]],
    "finger_left_001": [_FREE, [0, 0], _FREE],
    "finger_left_002": [[0, 0], [0, 0], [0, 0]],
    "finger_left_003": [_FREE, [0, 0], _FREE],
    "hip_left": [[0, 0], [0, INF], [0, INF]],
    "knee_left": [[-INF, 0], [0, 0], [0, 0]],
    "ankle_left": [[-INF, 0], [0, 0], [0, 0]],
    "paw_hind_left": [[0, 0], [-INF, 0], [0, 0]],
    "toe_left_001": [_FREE, [0, 0], _FREE],
    "toe_left_002": [[0, 0], [0, 0], [0, 0]],
    "toe_left_003": [_FREE, [0, 0], _FREE],
    "side_left": [[-INF, 0], _FREE, _FREE],
    "head_001": [[0, 0], [0, INF], _FREE],
    "head_002": [[0, 0], [0, INF], _FREE],
    "head_003": [[0, 0], [0, 0], [0, 0]],
    "spine_006": [[0, 0], [0, INF], [0, 0]],
    "tail_001": [[0, 0], [0, 0], [0, 0]],
}  # fmt: skip
for _n in ("spine_001", "spine_002", "spine_003", "spine_004", "spine_005"):
    MARKER_BOXES[_n] = [[0, 0], [0, INF], _FREE]
for _n in ("tail_002", "tail_003", "tail_004", "tail_005", "tail_006"):
    MARKER_BOXES[_n] = [[0, 0], [0, INF], _FREE]

# anatomy.get_bounds_pose: limits (deg) of the bone STARTING at each joint; spine/tail default
LIMITS_BY_START = {
    "shoulder_left": [[25, 205], [-85, 25], [-35, 35]],
    "shoulder_right": [[25, 205], [-25, 85], [-35, 35]],
    "elbow_left": [[2.5, 145], [0, 0], [-100, 45]],
    "elbow_right": [[2.5, 145], [0, 0], [-45, 100]],
    "wrist_left": [[-135, 35], [-12.5, 37.5], [0, 0]],
    "wrist_right": [[-135, 35], [-37.5, 12.5], [0, 0]],
    "hip_left": [[35, 195], [-65, 25], [-85, 40]],
    "hip_right": [[35, 195], [-25, 65], [-40, 85]],
    "knee_left": [[-145, 15], [0, 0], [0, 0]],
    "knee_right": [[-145, 15], [0, 0], [0, 0]],
    "ankle_left": [[-10, 145], [0, 0], [0, 0]],
    "ankle_right": [[-10, 145], [0, 0], [0, 0]],
    "paw_hind_left": [[0, 0], [0, 0], [-15, 35]],
    "paw_hind_right": [[0, 0], [0, 0], [-35, 15]],
}
SPINE_LIMITS = [[-90, 90], [-90, 90], [0, 0]]
GIRDLES = ("shoulder_left", "shoulder_right", "hip_left", "hip_right")  # fixed at 0

# anatomy.get_bounds_bones (rat): slope, sd per g; by the bone's END joint
PRIORS = {
    "elbow": (0.0075, 0.0005),  # humerus
    "wrist": (0.0069, 0.0004),  # radius
    "knee": (0.0102, 0.0006),  # femur
    "ankle": (0.0114, 0.0006),  # tibia
    "paw_hind": (0.0053, 0.0003),  # metatarsal
}

# typical lengths (cm) of a ~72 g rat for the other bones (RAT_MODEL.md)
OTHER_LENGTHS = {
    "spine_005": 2.8, "spine_004": 1.8, "spine_003": 4.5, "spine_002": 2.2, "spine_001": 3.8,
    "tail_005": 0.7, "tail_004": 1.8, "tail_003": 1.7, "tail_002": 1.7, "tail_001": 0.7,
    "shoulder": 1.3, "hip": 1.2, "finger": 1.2, "toe": 1.5,
}  # fmt: skip


def _side_free(name: str) -> str:
    return name.replace("_left", "").replace("_right", "")


def _base(name: str) -> str:
    """``finger_left_002`` -> ``finger``; ``elbow_right`` -> ``elbow``; ``spine_003`` kept."""
    b = _side_free(name)
    return b.rsplit("_", 1)[0] if b.startswith(("finger", "toe")) else b


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of a Rodrigues vector (``model.rodrigues2rotMat``)."""
    r = np.asarray(r, float)
    th = np.linalg.norm(r)
    if th < 2.0**-52:
        return np.eye(3)
    k = r / th
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx


def rodrigues_log(rot: np.ndarray) -> np.ndarray:
    """Rodrigues vector of a rotation (angle < pi)."""
    c = np.clip((np.trace(rot) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    if th < 1e-12:
        return np.zeros(3)
    w = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    return w * th / (2 * np.sin(th))


def _rxyz(a: float, b: float, c: float) -> np.ndarray:
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    rx = np.array([[1, 0, 0], [0, ca, -sa], [0, sa, ca]])
    ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    rz = np.array([[cc, -sc, 0], [sc, cc, 0], [0, 0, 1]])
    return rx @ ry @ rz


def _euler_options(rot: np.ndarray) -> list[np.ndarray]:
    out = []
    y1 = np.arcsin(np.clip(rot[0, 2], -1, 1))
    for y in (y1, np.pi - y1):
        cy = np.cos(y)
        x = np.arctan2(-rot[1, 2] / cy, rot[2, 2] / cy)
        z = np.arctan2(-rot[0, 1] / cy, rot[0, 0] / cy)
        out.append(np.array([x, y, z]))
    return out


def skeleton_coords_of(direction: np.ndarray) -> np.ndarray:
    """A bone frame as ``anatomy.get_skeleton_coords`` makes it from the bone direction."""
    z = np.asarray(direction, np.float16).astype(float)
    z = z / np.linalg.norm(z)
    flip = z[2] < 0
    if flip:
        z = rodrigues(np.array([np.pi, 0, 0])) @ z
    axis = np.cross([0.0, 0.0, 1.0], z)
    s = np.linalg.norm(axis)
    rot = np.eye(3) if s == 0 else rodrigues(np.arcsin(s) * axis / s)
    opts = _euler_options(rot)
    if flip:
        for o in opts:
            cand = np.array([o[0] + np.pi, o[0] - np.pi])
            o[0] = cand[np.argmin(np.abs(cand))]
    best = min(opts, key=lambda o: float(np.sum(o**2)))
    return _rxyz(*best)


def coords0_of(coords: np.ndarray) -> np.ndarray:
    """``r2R_xyz(recover_coord_xyz(I, coords))``: Euler angles rounded to float16."""
    opts = [o.astype(np.float16).astype(float) for o in _euler_options(coords)]
    best = opts[0] if np.sum(opts[0] ** 2) < np.sum(opts[1] ** 2) else opts[1]
    return _rxyz(*best)


@dataclass
class Conformance:
    """A written folder and its truth (arena frame, cm; ACM orders)."""

    folder: Path
    body_weight: float
    joint_order: list[str]  # without prefix
    marker_order: list[str]
    bone_lengths: dict[str, float]  # by end joint
    marker_offsets: dict[str, np.ndarray]  # by marker, in its bone frame
    joints: np.ndarray  # (F, 29, 3) of every labels_dlc frame, joint_order
    frames: np.ndarray  # labels_dlc frame numbers
    manual_frames: np.ndarray
    scale_factor: float


class AuthorsModel:
    """The authors' forward model for one model geometry (girdle turns, links)."""

    def __init__(self, rng: np.random.Generator, links: str = "tree"):
        self.names = [j for j, _ in TREE]
        self.parent = {j: p for j, p in TREE}
        self.bones = [(p, j) for j, p in TREE if p]  # file bone order = TREE order
        self.end = {j: b for b, (_, j) in enumerate(self.bones)}
        # posed mesh skeleton, unit bones: spine along +z, girdles sideways, ventrally and
        # along the body, limbs hanging; the shoulders slightly twisted about z vs the hips
        d = {}
        for j, _ in TREE[1:11]:
            d[j] = np.array([0.0, 0.05 * rng.normal(), 1.0])
        twist = rng.uniform(0.05, 0.2)
        for s, sx in (("left", -1.0), ("right", 1.0)):
            sh = np.array([sx * 0.6, -0.55, -0.35 + sx * twist])
            hp = np.array([sx * 0.55, -0.45, 0.5])
            d[f"shoulder_{s}"], d[f"hip_{s}"] = sh, hp
            for j in (f"elbow_{s}", f"wrist_{s}", f"finger_{s}_002"):
                d[j] = np.array([0.0, -1.0, 0.3])
            for j in (f"knee_{s}", f"ankle_{s}", f"paw_hind_{s}", f"toe_{s}_002"):
                d[j] = np.array([0.0, -1.0, -0.2])
        self.vertices = {"head_001": np.zeros(3)}
        for p, j in self.bones:
            u = d[j] / np.linalg.norm(d[j])
            self.vertices[j] = self.vertices[p] + u
        self.coords = np.array([skeleton_coords_of(d[j]) for _, j in self.bones])

        # anatomy.get_skeleton_coords0
        def xy(a, b):
            v = (self.vertices[b] - self.vertices[a])[:2]
            return v / np.linalg.norm(v)

        ang = np.arccos(
            np.clip(xy("shoulder_left", "shoulder_right") @ xy("hip_left", "hip_right"), -1, 1)
        )
        turn = rodrigues(np.array([0, 0, ang]))
        self.coords0 = np.tile(np.eye(3), (len(self.bones), 1, 1))
        for g in GIRDLES:
            c = self.coords[self.end[g]]
            self.coords0[self.end[g]] = coords0_of(turn @ c if g.startswith("shoulder") else c)
        # skeleton_vertices_links: "tree" (the authors' files): the rotation of bone i moves
        # bone j if j == i or end(j) descends from end(i); "literal" (Alg. 1 line 5 as
        # printed): if end(j) descends from start(i), siblings included
        if links not in ("tree", "literal"):
            raise ValueError(f"links must be 'tree' or 'literal', got {links!r}")
        n = len(self.bones)
        self.links = np.zeros((n, n), bool)
        for i, (si, ei) in enumerate(self.bones):
            for j, (_, ej) in enumerate(self.bones):
                a = ej if links == "tree" else self.parent[ej]
                stop = ei if links == "tree" else si
                while a and a != stop:
                    a = self.parent[a]
                self.links[i, j] = a == stop

    def limits(self) -> np.ndarray:
        """(n_bones, 3, 2) rad; bone 0 (the global rotation) unbounded."""
        out = []
        for b, (s, e) in enumerate(self.bones):
            if b == 0:
                out.append([[-INF, INF]] * 3)
            elif e in GIRDLES:
                out.append([[0, 0]] * 3)
            else:
                out.append(LIMITS_BY_START.get(s, SPINE_LIMITS))
        lim = np.array(out, float)
        return np.where(np.isfinite(lim), np.radians(lim), lim)

    def forward(self, t, r, lengths, offsets):
        """Joints ``{name: (3,)}`` and markers ``{name: (3,)}`` of one pose.

        ``r``: (n_bones, 3) Rodrigues vectors, ``r[0]`` the global rotation; ``lengths`` by
        bone; ``offsets`` {marker: (3,)} (right ones already mirrored)."""
        rots = [rodrigues(v) for v in r]
        frames = []
        for b in range(len(self.bones)):
            f = rots[0]
            for i in range(1, len(self.bones)):
                if self.links[i, b]:
                    f = f @ rots[i]
            frames.append(f @ self.coords0[b])
        joints = {"head_001": np.asarray(t, float)}
        for b, (s, e) in enumerate(self.bones):
            joints[e] = joints[s] + frames[b][:, 2] * lengths[b]
        markers = {}
        for m, j in MARKERS.items():
            v = offsets[m]
            markers[m] = joints[j] + (frames[self.end[j]] @ v if j in self.end else 0.0)
        return joints, markers


def authors_project(a_fit, k_fit, rot, tvec, points):
    """``model.map_m``: (n_cams, N, 2) pixels of arena points (N, 3) (rig in arena cm)."""
    out = []
    for a, k, rr, tt in zip(a_fit, k_fit, rot, tvec, strict=True):
        pc = points @ rr.T + tt
        m = pc[:, :2] / pc[:, 2:3]
        r2 = np.sum(m**2, axis=1)
        rad = 1 + k[0] * r2 + k[1] * r2**2 + k[4] * r2**3
        xy2 = 2 * m[:, 0] * m[:, 1]
        u = a[1] + a[0] * (m[:, 0] * rad + k[2] * xy2 + k[3] * (r2 + 2 * m[:, 0] ** 2))
        v = a[3] + a[2] * (m[:, 1] * rad + k[2] * (r2 + 2 * m[:, 1] ** 2) + k[3] * xy2)
        uv = np.stack([u, v], 1)
        uv[pc[:, 2] <= 0] = np.nan
        out.append(uv)
    return np.array(out)


def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of a camera at ``centre`` looking at ``target`` (z up)."""
    z = target - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


CONFIG = """\
import os
from datetime import datetime

dlc_index_frame_start = {dlc_start}
dlc_index_frame_end = {dlc_end}
index_frame_start = {start}
index_frame_end = {end}
mode = 4
pcutoff = 0.9
slope = 1.0
noise = 1e-4
videos = []
scale_factor = {scale_factor} # [cm]
use_rodrigues = True
use_reparameterization = False
num_tol = 2**-52
normalize_bone_lengths = 1.0
normalize_joint_marker_vec = 1.0
normalize_t0 = 50.0
normalize_r0 = 1.5707963267948966
normalize_camera_sensor_x = 1280.0
normalize_camera_sensor_y = 1024.0
plot_calib = False
sigma_factor = 10.0
body_weight = {body_weight}
dFrames_calib = 200
index_frames_calib = 'all'
opt_method_calib = 'L-BFGS-B'
opt_options_calib__disp = False
opt_options_calib__ftol = 2**-23
opt_options_calib__gtol = 0.0
opt_options_calib__maxiter = float('inf')
opt_options_calib__maxcor = 100
opt_options_calib__maxfun = float('inf')
opt_options_calib__iprint = -1
opt_options_calib__maxls = 200
plot_ini = False
index_frame_ini = index_frame_start
opt_method_ini = 'L-BFGS-B'
opt_options_ini__disp = False
opt_options_ini__ftol = 2**-23
opt_options_ini__gtol = 0.0
opt_options_ini__maxiter = float('inf')
opt_options_ini__maxcor = 100
opt_options_ini__maxfun = float('inf')
opt_options_ini__iprint = -1
opt_options_ini__maxls = 200
plot_recon = False
dt = {dt}
nT = int((index_frame_end - index_frame_start) / dt)
opt_method_fit = opt_method_ini
opt_options_fit__disp = False
opt_options_fit__ftol = 2**-23
opt_options_fit__gtol = opt_options_ini__gtol
opt_options_fit__maxiter = opt_options_ini__maxiter
opt_options_fit__maxcor = opt_options_ini__maxcor
opt_options_fit__maxfun = opt_options_ini__maxfun
opt_options_fit__iprint = opt_options_ini__iprint
opt_options_fit__maxls = opt_options_ini__maxls
use_cuda = False
slow_mode = True
sigma_point_scheme = 3
tol = 5e-2
iter_max = 100
folder_project = os.path.dirname(os.path.realpath(__file__))
job_name = os.path.basename(folder_project)
folder_save = os.path.join(folder_project, 'results')
folder_init = folder_save
folder_calib = folder_save
folder_reqFiles = folder_project
file_origin_coord = os.path.realpath(os.path.join(folder_reqFiles, 'origin_coord.npy'))
file_calibration = os.path.realpath(os.path.join(folder_reqFiles, 'multicalibration.npy'))
file_model = os.path.realpath(os.path.join(folder_reqFiles, 'model.npy'))
file_labelsDLC = os.path.realpath(os.path.join(folder_reqFiles, \
    f'labels_dlc_{{dlc_index_frame_start:06}}_{{dlc_index_frame_end:06}}.npy'))
file_labelsManual = os.path.realpath(os.path.join(folder_reqFiles, 'labels_manual.npz'))
"""


def _rig(rng: np.random.Generator, n_cams: int = 4, full_distortion: bool = False):
    """Arena rig (cm): cameras ~70 cm from the centre, ~55 cm up, 1280 x 1024 px; two radial
    distortion coefficients (the authors' initialisation asserts ``k[2:] == 0``) or all five."""
    a_fit, k_fit, rot, tvec = [], [], [], []
    for c in range(n_cams):
        az = 2 * np.pi * c / n_cams + np.pi / 4 + rng.normal(scale=0.1)
        centre = np.array([70 * np.cos(az), 70 * np.sin(az), 55 + rng.normal(scale=3)])
        rr = _look_at(centre, np.array([0.0, 0.0, 3.0]) + rng.normal(scale=2, size=3))
        f = rng.uniform(1450, 1650)
        a_fit.append([f, 640 + rng.normal(scale=8), f * (1 + rng.normal(scale=0.002)),
                      512 + rng.normal(scale=8)])  # fmt: skip
        k = [
            rng.uniform(-0.25, -0.1),
            rng.uniform(0.05, 0.2),
            rng.normal(scale=1e-3),
            rng.normal(scale=1e-3),
            rng.uniform(-0.05, 0.05),
        ]
        k_fit.append(k if full_distortion else k[:2] + [0.0, 0.0, 0.0])
        rot.append(rr)
        tvec.append(-rr @ centre)
    return np.array(a_fit), np.array(k_fit), np.array(rot), np.array(tvec)


def _poses(model: AuthorsModel, rng: np.random.Generator, n: int, smooth: bool):
    """(t, r) of ``n`` poses within the joint limits (smooth motion or independent poses)."""
    lim = model.limits()
    nb = len(model.bones)
    if smooth:
        tt = np.linspace(0, 1, n)
        phase = rng.uniform(0, 2 * np.pi, size=(nb, 3))
        freq = rng.uniform(0.5, 2.0, size=(nb, 3))
        u = 0.5 + 0.3 * np.sin(2 * np.pi * freq[None] * tt[:, None, None] + phase[None])
    else:
        u = rng.uniform(0.2, 0.8, size=(n, nb, 3))
    lo, hi = lim[..., 0], lim[..., 1]
    fin = np.isfinite(lo) & np.isfinite(hi)
    span = np.where(fin, hi - lo, 0.0)
    r = np.where(fin[None], np.where(fin, lo, 0.0)[None] + u * span[None], 0.0)
    # spine bends up to ~30 deg, the tail up to ~55 deg (of the naive +-90 deg limits)
    for b, (s, e) in enumerate(model.bones):
        if b > 0 and s not in LIMITS_BY_START and e not in GIRDLES:
            r[:, b, :2] *= 0.55 if s.startswith("tail") or s == "spine_001" else 0.3
    # global: the model's y (dorsal) up, its z (caudal) along a heading that turns
    # columns: images of the model's x (right), y (dorsal) and z (caudal) axes
    base = np.stack([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]], axis=1)
    if smooth:
        heading = np.cumsum(rng.normal(scale=0.03, size=n)) + rng.uniform(0, 2 * np.pi)
        pos = np.cumsum(rng.normal(scale=0.3, size=(n, 2)), axis=0)
        pos -= pos.mean(axis=0)
        pos += rng.uniform(-10, 10, size=2)
    else:
        heading = rng.uniform(0, 2 * np.pi, size=n)
        pos = rng.uniform(-15, 15, size=(n, 2))
    t = np.c_[pos, np.full(n, 4.0)]
    for f in range(n):
        tilt = rodrigues(rng.normal(scale=0.05, size=3)) if not smooth else np.eye(3)
        g = rodrigues(np.array([0, 0, heading[f]])) @ base @ tilt
        r[f, 0] = rodrigues_log(g)
    return t, r


def write_conformance_dataset(
    folder: str | Path,
    *,
    seed: int = 0,
    body_weight: float = 72.0,
    n_manual: int = 40,
    n_dlc: int = 200,
    dt: int = 2,
    scale_factor: float = 6.5,
    manual_noise: float = 1.0,
    dlc_noise: float = 2.0,
    dropout: float = 0.1,
    full_distortion: bool = False,
    links: str = "tree",
) -> Conformance:
    """Write an ACM dataset folder of one synthetic individual; return its truth.

    ``n_manual`` independent poses get manual labels (``manual_noise`` px, 10 % of the
    camera views unlabelled, except the head, spine and tail markers of the first frame,
    which the authors' initialisation triangulates); ``n_dlc`` frames of smooth motion get
    DeepLabCut labels (``dlc_noise`` px, a fraction ``dropout`` below the cutoff).
    ``links``: the rotation links of the model (``"tree"`` as in the authors' files, or
    ``"literal"`` Alg. 1 with coupled siblings).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    model = AuthorsModel(rng, links)
    size = (body_weight / 72.0) ** (1 / 3)

    # --- the individual: lengths (symmetric) and offsets (in their boxes, mirrored)
    lengths = np.zeros(len(model.bones))
    by_base: dict[str, float] = {}
    for b, (_, e) in enumerate(model.bones):
        base = _base(e)
        if base not in by_base:
            if base in PRIORS:
                slope, sd = PRIORS[base]
                by_base[base] = slope * body_weight * (1 + rng.normal(scale=0.04))
            else:
                by_base[base] = OTHER_LENGTHS[base] * size * (1 + rng.normal(scale=0.08))
        lengths[b] = by_base[base]
    offsets: dict[str, np.ndarray] = {}
    for m in MARKERS:
        if "right" in m:
            continue
        box = np.array(MARKER_BOXES[m], float)
        v = np.zeros(3)
        for ax in range(3):
            lo, hi = box[ax]
            if lo == hi:
                v[ax] = lo
            elif np.isinf(lo) and np.isinf(hi):
                v[ax] = rng.normal(scale=0.3 * size)
            else:
                mag = rng.uniform(0.15, 0.6) * size
                v[ax] = mag if hi > 0 else -mag
        offsets[m] = v
    for m in MARKERS:
        if "right" in m:
            left = offsets[m.replace("right", "left")]
            offsets[m] = left * np.array([-1.0, 1.0, 1.0])

    # --- rig in arena cm -> calibration in board squares in a moved frame
    a_fit, k_fit, rot, tvec = _rig(rng, full_distortion=full_distortion)
    coord = rodrigues(np.array([0.2, -0.1, 0.6]))
    origin = np.array([2.0, -1.0, 9.0])
    # arena -> calibration units: x_cal = coord @ (x_cm / s) + origin
    rot_cal = rot @ coord.T
    t_cal = tvec / scale_factor - np.einsum("nij,j->ni", rot_cal, origin)
    np.save(folder / "origin_coord.npy", {"origin": origin, "coord": coord}, allow_pickle=True)
    np.save(folder / "multicalibration.npy", {
        "nCameras": len(a_fit), "A_fit": a_fit, "k_fit": k_fit,
        "rX1_fit": np.array([rodrigues_log(x) for x in rot_cal]), "RX1_fit": rot_cal,
        "tX1_fit": t_cal,
    }, allow_pickle=True)  # fmt: skip

    # --- model.npy (alphabetical names)
    jorder = sorted(model.names)
    morder = sorted(MARKERS)
    ji = {n: i for i, n in enumerate(jorder)}
    np.save(folder / "model.npy", {
        "joint_order": ["joint_" + n for n in jorder],
        "joint_marker_order": ["marker_" + n + "_start" for n in morder],
        "joint_marker_index": np.array([ji[MARKERS[m]] for m in morder], np.int64),
        "skeleton_edges": np.array([[ji[s], ji[e]] for s, e in model.bones], np.int64),
        "skeleton_vertices": np.array([model.vertices[n] for n in jorder]),
        "skeleton_coords": model.coords,
        "skeleton_vertices_links": model.links,
        "bone_lengths": np.zeros(len(model.bones)),
        "joint_marker_vectors": np.zeros((len(morder), 3)),
        "skeleton_coords_index": np.zeros(len(model.bones), np.int64),
        "surface_triangles": np.zeros((0, 3), np.int32),
        "surface_vertices": np.zeros((0, 3)),
        "surface_vertices_weights": np.zeros((0, len(jorder))),
    }, allow_pickle=True)  # fmt: skip

    def render(t, r):
        js, ms = [], []
        for f in range(len(t)):
            j, m = model.forward(t[f], r[f], lengths, offsets)
            js.append([j[n] for n in jorder])
            ms.append([m[n] for n in morder])
        js, ms = np.array(js), np.array(ms)
        px = authors_project(a_fit, k_fit, rot, tvec, ms.reshape(-1, 3))
        px = px.reshape(len(a_fit), len(t), len(morder), 2)
        out = ~((px[..., 0] >= 0) & (px[..., 0] < 1280) & (px[..., 1] >= 0) & (px[..., 1] < 1024))
        px[out] = np.nan
        return js, px

    # --- manual labels: independent poses
    t_m, r_m = _poses(model, rng, n_manual, smooth=False)
    manual_frames = np.arange(n_manual) * 97 + 5
    _, px = render(t_m, r_m)
    px = px + rng.normal(scale=manual_noise, size=px.shape)
    manual = {}
    for i, fr in enumerate(manual_frames):
        entry = {}
        for k, m in enumerate(morder):
            xy = px[:, i, k].copy()
            drop = rng.random(len(a_fit)) < 0.1
            if i > 0 or not m.startswith(("head", "spine", "tail")):
                xy[drop] = np.nan
            if np.all(np.isnan(xy)):
                continue
            entry["spot_" + m] = xy
        manual[int(fr)] = entry
    np.savez(folder / "labels_manual.npz", manual)

    # --- DeepLabCut labels: smooth motion
    frames = np.arange(n_dlc, dtype=np.int64) + 10000
    t_d, r_d = _poses(model, rng, n_dlc, smooth=True)
    joints, px = render(t_d, r_d)
    px = px + rng.normal(scale=dlc_noise, size=px.shape)
    lik = rng.uniform(0.91, 1.0, size=px.shape[:-1])
    drop = rng.random(lik.shape) < dropout
    lik[drop] = rng.uniform(0.0, 0.5, size=int(drop.sum()))
    bad = ~np.all(np.isfinite(px), axis=-1)
    px[bad] = 0.0
    lik[bad] = 0.0
    labels_all = np.concatenate([px, lik[..., None]], axis=-1).transpose(1, 0, 2, 3)
    dlc_end = int(frames[-1]) + 1
    np.save(folder / f"labels_dlc_{int(frames[0]):06d}_{dlc_end:06d}.npy",
            {"file_save": "", "frame_list": frames, "labels_all": labels_all},
            allow_pickle=True)  # fmt: skip
    (folder / "configuration.py").write_text(CONFIG.format(
        dlc_start=int(frames[0]), dlc_end=dlc_end, start=int(frames[0]),
        end=int(frames[0]) + n_dlc - 1, scale_factor=scale_factor, body_weight=body_weight,
        dt=dt,
    ), encoding="utf-8")  # fmt: skip
    return Conformance(
        folder=folder,
        body_weight=body_weight,
        joint_order=jorder,
        marker_order=morder,
        bone_lengths={e: float(lengths[b]) for b, (_, e) in enumerate(model.bones)},
        marker_offsets=offsets,
        joints=joints,
        frames=frames,
        manual_frames=manual_frames,
        scale_factor=scale_factor,
    )
