"""Side-by-side evaluation against anipose (issue 12, item 7).

The peer is aniposelib's ``CameraGroup.triangulate_optim`` (what a careful anipose user runs:
likelihood cutoff, then triangulation refined with temporal smoothness and rigid-length
constraints); acm-rs is :func:`acm_rs.track` given the true skeleton. Both see the SAME
synthetic DeepLabCut-like detections of a synthetic individual rat (4 cameras, 1280x1024),
and both are scored against ground truth made by independent code (:mod:`acm_rs.truth`, the
authors' forward model and projection in plain NumPy, sharing nothing with acm-rs's forward
model; the detections are projected by it too):

* marker error: the peer's triangulated 3D markers, acm-rs's ``result.markers``;
* joint error: acm-rs's ``result.joints``; anipose has no joints, so the true skeleton is fitted
  frame by frame to its 3D markers (acm-rs's per-frame fit, ``method="deterministic"``, on the
  noise-free projections of those markers into the rig; on the true markers this returns the
  true joints to 1e-12 mm). Its time is reported apart from the peer's;
* 95 % interval coverage (acm-rs only): fraction of true joint coordinates within
  ``+-1.96 * result.joints_std``, and of true marker coordinates within
  ``+-1.96 * result.info["markers_std"]`` with the markers' model misfit (``track``'s
  ``misfit``) and without it (``info["markers_fk"]``, ``info["markers_std_fk"]``, with their
  errors); EM iterations (acm-rs) and wall times;
* joint errors (and coverage) over the frames that make a case hard: the camera outage, the
  gap and the 40 frames after it, the speed burst. Warnings acm-rs raises are printed.
* the joints the markers do not decide (acm-rs only, ``--second-solutions N``, 10 frames):
  :func:`acm_rs.second_solutions` on the result, and the joints' coverage split between
  those joints and the others.

Cases (240 frames by default; ``--quick``: 120):

``dlc``      2 px noise, 15 % missing in bursts of 1-20 frames (likelihood < 0.5), 2 % confident
             outliers (30-150 px off, likelihood 0.95-1);
``hard``     3 px noise, 38 % missing in bursts, 3 % outliers, camera 1 out for 40 frames;
``gap``      ``dlc`` plus 40 consecutive frames without any detection;
``burst``    ``dlc`` detections of a motion time-warped so that it runs at 2.5x its median speed
             for 25 frames;
``mm``       ``dlc`` with the rig and the skeleton in mm (same pixels);
``squares``  ``dlc`` with the rig and the skeleton in board squares of 6.5 cm (same pixels);
``real``     real rat motion: the authors' published output for their example sequence
             (``pose.npy`` of bbo-lab/ACM at bbc99f6, up to 240 time points, 29 joints; not
             kept in this repository: ``--pose`` or ``ACM_RS_AUTHORS_POSE``), the animal's own
             bones wearing the rat model's 43 markers (``benches/representability.py``),
             posed by the exact per-frame fit of its joints (3e-11 mm), ``dlc`` detections; no
             joint limits. Skipped without the file.
``real-hard``, ``real-gap``, ``real-mm``, ``real-squares``: the real motion with the
             detections of ``hard``, ``gap``, ``mm``, ``squares``.

Peer settings: ``scale_smooth=4, scale_length=2`` (issue 12), rigid constraints between every
pair of markers on the same joint (``skeleton.marker_joints``), and anipose's defaults for the
rest (``reproj_error_threshold=5``, ``n_deriv_smooth=3``, ``score_threshold=0.8``);
``init_ransac=True`` is not usable (see ``benches/README.md``). The calibration given to
anipose is in mm for the cm cases (anipose writes mm), in the case's units otherwise.

Run from the repository root (needs ``pip install aniposelib`` or the ``bench`` extra;
``--no-peer`` runs acm-rs alone)::

    python benches/compare_anipose.py [--cases dlc hard gap burst mm squares real real-hard
        real-gap real-mm real-squares]
        [--frames 240] [--seed 0] [--quick] [--no-peer] [--json PATH] [--pose PATH]
        [--motion M] [--misfit auto|isotropic|full|off] [--inject-misfit MM]

``--inject-misfit MM`` moves every true marker off the model by ``N(0, s_k² I₃)`` per frame
(``s_k`` uniform in 0.5-1.5 x MM mm per marker) before projecting: a known model misfit.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig

SYNTHETIC_CASES = ("dlc", "hard", "gap", "burst", "mm", "squares")
#: Real motion with the detections of a synthetic case (``real`` = ``real-dlc``).
REAL_CASES = ("real", "real-hard", "real-gap", "real-mm", "real-squares")
CASES = SYNTHETIC_CASES + REAL_CASES
SQUARE_CM = 6.5
#: Peer options: issue 12 for the first two, anipose's DEFAULT_CONFIG for the others.
PEER_OPTIONS = {
    "scale_smooth": 4,
    "scale_length": 2,
    "reproj_error_threshold": 5,
    "n_deriv_smooth": 3,
}
PEER_SCORE_THRESHOLD = 0.8  # anipose's triangulation.score_threshold default


# -- synthetic cases -------------------------------------------------------------------------
@dataclass
class Case:
    """One synthetic recording with its ground truth (in the case's length units)."""

    name: str
    description: str
    rig: acm_rs.CameraRig
    skeleton: acm_rs.Skeleton
    detections: np.ndarray  # (C, T, M, 2) px
    likelihood: np.ndarray  # (C, T, M)
    joints: np.ndarray  # (T, J, 3) truth
    markers: np.ndarray  # (T, M, 3) truth
    mm_per_unit: float
    cm_skeleton: acm_rs.Skeleton  # the same animal in cm (for the peer's skeleton fit)
    cm_rig: acm_rs.CameraRig
    windows: list[tuple[str, np.ndarray]] = field(default_factory=list)  # (label, frames)
    notes: list[str] = field(default_factory=list)


def bursty_detections(
    rig: acm_rs.CameraRig,
    skeleton: acm_rs.Skeleton,
    t: np.ndarray,
    r: np.ndarray,
    noise_px: float,
    missing: float,
    outliers: float,
    seed: int,
    max_burst: int = 20,
) -> tuple[np.ndarray, np.ndarray]:
    """DeepLabCut-like detections: :func:`acm_rs.datasets.dlc_like_detections` for the noise
    and the confident outliers, then occlusion bursts of 1..``max_burst`` frames (uniform) per
    camera and marker until a fraction ``missing`` is covered; their likelihood is < 0.5 (the
    pixel guess stays, as DeepLabCut reports one)."""
    det, lik = datasets.dlc_like_detections(
        rig, skeleton, t, r, noise_px=noise_px, missing=0.0, outliers=outliers, seed=seed
    )
    rng = np.random.default_rng(seed + 1000)
    n_cams, n_frames, n_markers = lik.shape
    hidden = np.zeros(lik.shape, bool)
    need = int(round(missing * n_frames))
    for c in range(n_cams):
        for m in range(n_markers):
            row = hidden[c, :, m]
            for _ in range(100 * n_frames):
                left = need - int(row.sum())
                if left <= 0:
                    break
                length = min(int(rng.integers(1, max_burst + 1)), left)
                start = int(rng.integers(0, n_frames - length + 1))
                # separate bursts (one visible frame between them) while there is room
                if not row[max(start - 1, 0) : start + length + 1].any():
                    row[start : start + length] = True
    lik[hidden] = rng.uniform(0.0, 0.5, int(hidden.sum()))
    return det, lik


def warped_motion(
    skeleton: acm_rs.Skeleton,
    n_frames: int,
    seed: int,
    start: int,
    length: int = 25,
    factor: float = 2.5,
    fine: int = 10,
) -> tuple[np.ndarray, np.ndarray]:
    """``smooth_motion`` whose clock runs ``factor`` times faster for ``length`` frames from
    ``start``. Sampled from a ``fine`` times denser copy (``speed=1/fine`` gives the same
    trajectory: every period scales with the sampling), so the warp needs no interpolation."""
    steps = np.full(n_frames, fine)
    steps[0] = 0
    steps[start + 1 : start + 1 + length] = round(factor * fine)
    idx = np.cumsum(steps)
    t, r = datasets.smooth_motion(skeleton, int(idx[-1]) + 1, seed=seed, speed=1.0 / fine)
    return t[idx], r[idx]


def unit_copy(skeleton: acm_rs.Skeleton, units: str, factor: float) -> acm_rs.Skeleton:
    """The same animal declared in ``units``, lengths and offsets times ``factor``."""
    sk = acm_rs.Skeleton.from_dict(skeleton.to_dict() | {"units": units})
    return sk.with_parameters(sk.bone_lengths * factor, sk.marker_offsets * factor)


def marker_speed(skeleton: acm_rs.Skeleton, t: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(T - 1,) mean marker displacement from one frame to the next."""
    _, markers = datasets.true_positions(skeleton, t, r)
    return np.linalg.norm(np.diff(markers, axis=0), axis=-1).mean(axis=1)


def burst_motion(
    skeleton: acm_rs.Skeleton, n_frames: int, seed: int, start: int, length: int, target: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """A warped ``smooth_motion`` whose speed over the burst is ``target`` x its median speed
    (the warp factor is adjusted twice: the local speed of the motion varies)."""
    factor = target
    for _ in range(3):
        t, r = warped_motion(skeleton, n_frames, seed, start, length, factor)
        speed = marker_speed(skeleton, t, r)
        ratio = speed[start : start + length].mean() / np.median(speed)
        factor = float(np.clip(factor * target / ratio, 1.0, 6.0))
    return t, r, ratio


def real_motion(path, n_frames: int) -> tuple[acm_rs.Skeleton, np.ndarray, np.ndarray]:
    """The real rat of the authors' ``pose.npy`` wearing the rat model's markers and its
    poses ``t, r`` (first ``n_frames`` time points, centred on the arena's origin)."""
    import representability as rp

    names, joints = rp.load_authors_pose(path)
    joints = joints[:n_frames]
    sk = rp.dressed_skeleton(names, joints[0])
    err, t, r = rp.fit_poses(sk, joints)
    if err.max() > 1e-4:  # cm
        raise RuntimeError(f"the real motion is not reproduced ({err.max() * 10:.2g} mm)")
    centre = joints.reshape(-1, 3).mean(axis=0) * [1.0, 1.0, 0.0]
    return sk, t - centre, r


def make_case(name: str, n_frames: int, seed: int, pose_path=None) -> Case:
    """Build one case (``dlc``, ``gap``, ``mm`` and ``squares`` share the animal, the motion
    and the detections: only the missing frames or the units differ)."""
    real = name.startswith("real")
    if real:
        name = name.partition("-")[2] or "dlc"
    sk = datasets.individual_skeleton(models.rat(), seed=seed + 1)
    rig = demo_rig()
    frames = np.arange(n_frames)
    windows = []
    notes: list[str] = []
    n_window = min(40, n_frames // 6)
    if name == "burst":
        start, length = int(0.6 * n_frames), min(25, n_frames // 8)
        t, r, ratio = burst_motion(sk, n_frames, seed + 2, start, length, 2.5)
        windows.append((f"burst ({length} fr.)", (frames > start) & (frames <= start + length)))
        notes.append(f"marker speed over the burst: {ratio:.2f} x the median speed")
    elif real:
        sk, t, r = real_motion(pose_path, n_frames)
        notes.append(f"real rat motion: {len(t)} time points of the authors' pose.npy")
        n_frames, frames = len(t), np.arange(len(t))
        n_window = min(40, n_frames // 6)
    else:
        t, r = datasets.smooth_motion(sk, n_frames, seed=seed + 2)
    if name == "hard":
        det, lik = bursty_detections(rig, sk, t, r, 3.0, 0.38, 0.03, seed + 4)
        desc = "3 px noise, {miss} missing in bursts of 1-20 frames, 3 % confident outliers"
    else:
        det, lik = bursty_detections(rig, sk, t, r, 2.0, 0.15, 0.02, seed + 3)
        desc = "2 px noise, {miss} missing in bursts of 1-20 frames, 2 % confident outliers"
    desc = desc.format(miss=f"{100 * np.mean(lik < 0.9):.1f} %")
    if name == "hard":
        out = (frames >= n_frames // 4) & (frames < n_frames // 4 + n_window)
        det[1, out] = np.nan
        lik[1, out] = 0.0
        windows.append((f"cam 1 out ({n_window} fr.)", out))
        desc += f", camera 1 out for {n_window} frames ({100 * np.mean(lik < 0.9):.1f} % in all)"
    elif name == "gap":
        gap = (frames >= int(0.42 * n_frames)) & (frames < int(0.42 * n_frames) + n_window)
        det[:, gap] = np.nan
        lik[:, gap] = 0.0
        windows.append((f"gap ({n_window} fr.)", gap))
        after = np.roll(gap, n_window) & ~gap
        windows.append((f"after the gap ({n_window} fr.)", after))
        desc += f", no detection at all in frames {gap.argmax()}-{gap.argmax() + n_window - 1}"
    joints, markers = datasets.true_positions(sk, t, r)
    label = f"real-{name}" if real and name != "dlc" else ("real" if real else name)
    case = Case(label, desc, rig, sk, det, lik, joints, markers, 10.0, sk, rig, windows, notes)
    if name == "mm":
        case.skeleton, case.rig = unit_copy(sk, "mm", 10.0), rig.scaled(10.0, units="mm")
        case.joints, case.markers, case.mm_per_unit = joints * 10, markers * 10, 1.0
        case.description += "; rig and skeleton in mm"
    elif name == "squares":
        f = 1.0 / SQUARE_CM
        case.skeleton, case.rig = unit_copy(sk, "squares", f), rig.scaled(f, units="squares")
        case.joints, case.markers, case.mm_per_unit = joints * f, markers * f, 10 * SQUARE_CM
        case.description += f"; rig and skeleton in board squares of {SQUARE_CM} cm"
    return case


def inject_misfit(case: Case, mm: float, seed: int) -> None:
    """A known model misfit: every true marker moves by ``N(0, s_k² I₃)`` per frame
    (independent over frames), ``s_k`` uniform in ``0.5-1.5 x mm`` per marker; the
    detections move by the projections' difference (noise and outliers kept)."""
    rng = np.random.default_rng(seed + 77)
    n_markers = case.markers.shape[1]
    sd = rng.uniform(0.5, 1.5, n_markers) * mm / case.mm_per_unit
    delta = rng.normal(size=case.markers.shape) * sd[None, :, None]
    case.detections = case.detections + (
        case.rig.project(case.markers + delta) - case.rig.project(case.markers)
    )
    case.markers = case.markers + delta
    case.description += f"; markers off the model by {mm:g} mm (0.5-1.5 x per marker)"
    median = np.median(sd) * case.mm_per_unit
    case.notes.append(f"injected misfit SD per marker: median {median:.2f} mm")


# -- metrics ---------------------------------------------------------------------------------
def stats(err_mm: np.ndarray) -> dict:
    """Median / p95 / max of an error array (mm), NaN entries counted apart."""
    ok = np.isfinite(err_mm)
    if not ok.any():
        return {"median": np.nan, "p95": np.nan, "max": np.nan, "n_nan": int(err_mm.size)}
    e = err_mm[ok]
    return {
        "median": float(np.median(e)),
        "p95": float(np.percentile(e, 95)),
        "max": float(e.max()),
        "n_nan": int((~ok).sum()),
    }


def errors(case: Case, markers: np.ndarray, joints: np.ndarray | None) -> dict:
    """Marker and joint errors (mm) of estimates in the case's units."""
    out = {"marker": np.linalg.norm(markers - case.markers, axis=-1) * case.mm_per_unit}
    if joints is not None:
        out["joint"] = np.linalg.norm(joints - case.joints, axis=-1) * case.mm_per_unit
    return out


def summarise(case: Case, err: dict, **extra) -> dict:
    row = {f"{k}_error_mm": stats(v) for k, v in err.items()}
    if "joint" in err:
        row["windows"] = [
            {"label": label, "joint_error_mm": stats(err["joint"][mask])}
            for label, mask in case.windows
        ]
    return row | extra


# -- the two methods -------------------------------------------------------------------------
def _track(case: Case, **kwargs) -> tuple[acm_rs.PoseResult, float, list[str]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        res = acm_rs.track(
            case.rig,
            case.skeleton,
            case.detections,
            likelihood=case.likelihood,
            progress=False,
            **kwargs,
        )
        wall = time.perf_counter() - t0
    return res, wall, [str(w.message) for w in caught]


def run_acm(case: Case, second: int = 0, **options) -> dict:
    """acm_rs.track with the true skeleton and default options (or ``options``); with
    ``second`` > 0, :func:`acm_rs.second_solutions` at that many frames of the result."""
    refused = None
    try:
        res, wall, warned = _track(case, **options)
    except ValueError as exc:
        if "unit" not in str(exc):
            raise
        # A unit acm-rs does not know: report it, then give the sec. 3.3 constants through
        # the documented ``normalization`` argument (c_t = 50 cm in the model's unit).
        refused = str(exc)
        norm = acm_rs.Normalization.for_units("cm", [cam.size for cam in case.rig])
        norm = dataclasses.replace(norm, translation=50.0 / (case.mm_per_unit / 10.0))
        res, wall, warned = _track(case, normalization=norm, **options)
    err = errors(case, res.markers, res.joints)
    inside = np.abs(res.joints - case.joints) <= 1.96 * res.joints_std
    info = res.info
    fk, fk_std = info.get("markers_fk", res.markers), info.get("markers_std_fk")
    if fk_std is None:
        fk_std = info["markers_std"]
    sd = np.asarray(info.get("misfit_sd", np.zeros(case.markers.shape[1]))) * case.mm_per_unit
    row = summarise(
        case,
        err,
        coverage95=float(inside.mean()),
        marker_coverage95=float(
            (np.abs(res.markers - case.markers) <= 1.96 * info["markers_std"]).mean()
        ),
        marker_error_fk_mm=stats(errors(case, fk, None)["marker"]),
        marker_coverage95_fk=float((np.abs(fk - case.markers) <= 1.96 * fk_std).mean()),
        misfit=info.get("misfit", "-"),
        misfit_sd_mm={"median": float(np.median(sd)), "max": float(sd.max())},
        em_iterations=len(res.em_history),
        motion=res.info["motion"],
        motion_note=res.info["motion_note"],
        em_iterations_by_model={
            m: sum(h["motion"] == m for h in res.em_history) for m in ("random_walk", "velocity")
        },
        returned_iteration=res.info.get("returned_iteration"),
        em_last_delta=float(res.em_history[-1]["delta"]) if res.em_history else None,
        converged=bool(res.info.get("converged")),
        wall_s=wall,
        gated=int((np.asarray(res.info.get("status")) == 2).sum()),
        warnings=warned,
    )
    for w, (_, mask) in zip(row["windows"], case.windows, strict=True):
        w["coverage95"] = float(inside[mask].mean())
    if second > 0:
        t0 = time.perf_counter()
        found = acm_rs.second_solutions(res, frames=second)
        amb = found.ambiguous()
        ambiguous = np.isin(res.joint_names, [name for name, *_ in amb])
        row["second_solutions"] = {
            "frames": int(len(found.frames)),
            "seconds": time.perf_counter() - t0,
            "chi2": found.chi2,
            "joints": [
                {"joint": n, "fraction": f, "median_distance_mm": d * case.mm_per_unit}
                for n, f, d in amb
            ],
            "coverage95_ambiguous": float(inside[:, ambiguous].mean()) if ambiguous.any() else None,
            "coverage95_decided": float(inside[:, ~ambiguous].mean())
            if (~ambiguous).any()
            else None,
        }
    if refused is not None:
        row["refused"] = refused
        row["normalization"] = f"normalization=Normalization(translation={norm.translation:.4g})"
    return row


def anipose_group(rig: acm_rs.CameraRig):
    from aniposelib.cameras import Camera, CameraGroup

    return CameraGroup(
        [
            Camera(matrix=c.matrix, dist=c.dist, size=c.size, rvec=c.rvec, tvec=c.tvec, name=c.name)
            for c in rig
        ]
    )


def rigid_pairs(skeleton: acm_rs.Skeleton) -> list[list[int]]:
    """Every pair of markers attached to the same joint (constant distance)."""
    groups: dict[int, list[int]] = {}
    for m, j in enumerate(skeleton.marker_joints):
        groups.setdefault(int(j), []).append(m)
    return [[a, b] for g in groups.values() for i, a in enumerate(g) for b in g[i + 1 :]]


def peer_rig(case: Case) -> tuple[acm_rs.CameraRig, float]:
    """The calibration anipose gets and its mm per unit (mm for the cm cases)."""
    if case.mm_per_unit == 10.0:
        return case.rig.scaled(10.0), 1.0
    return case.rig, case.mm_per_unit


def run_peer(case: Case) -> dict:
    """anipose: likelihood cutoff, then CameraGroup.triangulate_optim."""
    rig, mm = peer_rig(case)
    group = anipose_group(rig)
    points = case.detections.copy()
    points[case.likelihood < PEER_SCORE_THRESHOLD] = np.nan
    t0 = time.perf_counter()
    p3d = group.triangulate_optim(
        points, init_ransac=False, constraints=rigid_pairs(case.skeleton), **PEER_OPTIONS
    )
    wall = time.perf_counter() - t0
    markers_mm = np.asarray(p3d, float) * mm
    # Joints: fit the true skeleton (cm) frame by frame to the peer's markers.
    markers_cm = markers_mm / 10.0
    t1 = time.perf_counter()
    fit = acm_rs.track(
        case.cm_rig,
        case.cm_skeleton,
        case.cm_rig.project(markers_cm),
        method="deterministic",
        progress=False,
    )
    fit_s = time.perf_counter() - t1
    unit = 10.0 / case.mm_per_unit  # cm -> case units
    err = errors(case, markers_mm / case.mm_per_unit, fit.joints * unit)
    err_fit = errors(case, fit.markers * unit, None)["marker"]
    return summarise(
        case,
        err,
        wall_s=wall,
        skeleton_fit_s=fit_s,
        fitted_marker_error_mm=stats(err_fit),
        calibration_units={1.0: "mm", 10.0: "cm"}.get(mm, f"{mm:g} mm"),
    )


def warm_up_peer(case: Case) -> float:
    """JAX and numba compile on first use; do it once on 20 frames, outside the timings."""
    rig, _ = peer_rig(case)
    group = anipose_group(rig)
    points = case.detections[:, :20].copy()
    points[case.likelihood[:, :20] < PEER_SCORE_THRESHOLD] = np.nan
    t0 = time.perf_counter()
    group.triangulate_optim(points, constraints=rigid_pairs(case.skeleton), **PEER_OPTIONS)
    return time.perf_counter() - t0


# -- report ----------------------------------------------------------------------------------
def _fmt(v: float | None, spec: str = ".2f") -> str:
    return "-" if v is None or not np.isfinite(v) else format(v, spec)


def _ratio(a: float | None, b: float | None) -> str:
    if a is None or b is None or not (np.isfinite(a) and np.isfinite(b)) or b == 0:
        return "-"
    return f"{a / b:.2f}"


def print_case(case: Case, acm: dict, peer: dict | None) -> None:
    n_frames = case.joints.shape[0]
    print(f"\n== {case.name}: {n_frames} frames, {case.description} ==")
    for note in case.notes:
        print(f"   {note}")
    if "refused" in acm:
        print(f"   acm-rs refused the default: {acm['refused']}")
        print(f"   -> tracked with {acm['normalization']}")
    for w in acm["warnings"]:
        print(f"   acm-rs warned: {w}")
    if peer is None:
        print("   anipose: skipped")
    print(f"   {'':36s} {'anipose':>10s} {'acm-rs':>10s} {'acm/anipose':>12s}")
    for what in ("marker", "joint"):
        for s in ("median", "p95", "max"):
            a = acm[f"{what}_error_mm"][s]
            p = peer[f"{what}_error_mm"][s] if peer else None
            label = f"{what} error {s} (mm)"
            print(f"   {label:36s} {_fmt(p):>10s} {_fmt(a):>10s} {_ratio(a, p):>12s}")
    for k, w in enumerate(acm["windows"]):
        for st in ("median", "max"):
            a = w["joint_error_mm"][st]
            p = peer["windows"][k]["joint_error_mm"][st] if peer else None
            label = f"  {w['label']}: joint {st}"
            print(f"   {label:36s} {_fmt(p):>10s} {_fmt(a):>10s} {_ratio(a, p):>12s}")
    fk = acm["marker_error_fk_mm"]
    print(
        f"   {'markers without the misfit (mm)':36s} {'-':>10s} {'':>10s}   (median "
        f"{fk['median']:.2f}, p95 {fk['p95']:.2f}, max {fk['max']:.2f}; 95 % coverage "
        f"{100 * acm['marker_coverage95_fk']:.1f} %)"
    )
    sd = acm["misfit_sd_mm"]
    print(
        f"   {'markers: misfit SD (mm)':36s} {'-':>10s} {sd['median']:>10.2f}   (max "
        f"{sd['max']:.2f}; misfit={acm['misfit']})"
    )
    cov = f"{100 * acm['marker_coverage95']:.1f} %"
    print(f"   {'95 % coverage of markers':36s} {'-':>10s} {cov:>10s}")
    cov = f"{100 * acm['coverage95']:.1f} %"
    print(f"   {'95 % coverage of joints':36s} {'-':>10s} {cov:>10s}")
    for w in acm["windows"]:
        cov = f"{100 * w['coverage95']:.1f} %"
        label = f"  ... {w['label']}"
        print(f"   {label:36s} {'-':>10s} {cov:>10s}")
    second = acm.get("second_solutions")
    if second:
        names = ", ".join(
            f"{j['joint']} {100 * j['fraction']:.0f} % {j['median_distance_mm']:.1f} mm"
            for j in second["joints"]
        )
        print(
            f"   {'joints with a second pose':36s} {'-':>10s} {len(second['joints']):>10d}   "
            f"(markers within Δχ² {second['chi2']:g}, {second['frames']} frames "
            f"searched in {second['seconds']:.1f} s{': ' + names if names else ''})"
        )
        for key, label in (("ambiguous", "those joints"), ("decided", "the other joints")):
            value = second[f"coverage95_{key}"]
            if value is not None:
                cov = f"{100 * value:.1f} %"
                print(f"   {'  ... coverage of ' + label:36s} {'-':>10s} {cov:>10s}")
    em = f"{acm['em_iterations']}{'' if acm['converged'] else ' (max)'}"
    by = acm["em_iterations_by_model"]
    print(
        f"   {'motion model':36s} {'-':>10s} {acm['motion']:>10s}   (EM iterations: random "
        f"walk {by['random_walk']}, velocity {by['velocity']}"
        + (f"; {acm['motion_note']}" if acm["motion_note"] else "")
        + ")"
    )
    print(
        f"   {'EM iterations':36s} {'-':>10s} {em:>10s}   (last delta "
        f"{_fmt(acm['em_last_delta'], '.3f')}; {acm['gated']} detections gated)"
    )
    p = peer["wall_s"] if peer else None
    ratio = _ratio(acm["wall_s"], p)
    print(f"   {'wall time (s)':36s} {_fmt(p, '.1f'):>10s} {acm['wall_s']:>10.1f} {ratio:>12s}")
    if peer:
        fm = peer["fitted_marker_error_mm"]
        print(
            f"   anipose joints: true skeleton fitted per frame in {peer['skeleton_fit_s']:.1f} s"
            f" (its markers: median {fm['median']:.2f}, p95 {fm['p95']:.2f}, max "
            f"{fm['max']:.2f} mm); anipose calibration in {peer['calibration_units']}"
        )
        n_nan = peer["marker_error_mm"]["n_nan"]
        if n_nan:
            print(f"   anipose left {n_nan} marker positions NaN (not counted above)")


def print_summary(rows: list[tuple[Case, dict, dict | None]]) -> None:
    print("\n== summary (errors in mm: anipose / acm-rs, ratio acm-rs/anipose) ==")
    head = (
        f"{'case':12s} {'marker median':>20s} {'joint median':>20s} {'joint p95':>20s} "
        f"{'joint max':>22s} {'cover':>6s} {'m.cov':>6s} {'EM':>4s} {'wall s':>16s}"
    )
    print(head)

    def cell(what: str, s: str, acm: dict, peer: dict | None, width: int = 20) -> str:
        a = acm[f"{what}_error_mm"][s]
        p = peer[f"{what}_error_mm"][s] if peer else None
        return f"{_fmt(p)}/{_fmt(a)} ({_ratio(a, p)})".rjust(width)

    for case, acm, peer in rows:
        wall = f"{_fmt(peer['wall_s'] if peer else None, '.1f')}/{acm['wall_s']:.1f}"
        em = f"{acm['em_iterations']}{'' if acm['converged'] else '!'}"
        print(
            f"{case.name:12s} {cell('marker', 'median', acm, peer)} "
            f"{cell('joint', 'median', acm, peer)} {cell('joint', 'p95', acm, peer)} "
            f"{cell('joint', 'max', acm, peer, 22)} {100 * acm['coverage95']:5.1f}% "
            f"{100 * acm['marker_coverage95']:5.1f}% {em:>4s} "
            f"{wall:>16s}"
        )


def source_version() -> str:
    """Commit of the working tree (and whether python/ or src/ differ from it)."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(
            ["git", "-C", root, "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", root, "status", "--porcelain", "--", "python", "src"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown commit"
    return f"commit {head}" + (" + local changes" if dirty else "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="120 frames (unless --frames is given)")
    ap.add_argument("--no-peer", action="store_true", help="acm-rs only")
    ap.add_argument("--json", help="write every number to this file")
    ap.add_argument("--pose", help="the authors' pose.npy for the 'real' case")
    ap.add_argument("--motion", help="acm-rs's motion model (default: track's default)")
    ap.add_argument("--misfit", help="acm-rs's marker misfit (default: track's default)")
    ap.add_argument(
        "--overrelax",
        help="acm-rs's over-relaxed EM growth factor, or 'none' for plain EM (default: "
        "track's default)",
    )
    ap.add_argument(
        "--second-solutions",
        type=int,
        default=10,
        metavar="N",
        help="search N frames of acm-rs's result for second poses that fit its markers as "
        "well (acm_rs.second_solutions; 0: skip)",
    )
    ap.add_argument(
        "--inject-misfit",
        type=float,
        default=0.0,
        metavar="MM",
        help="move every true marker off the model by N(0, s_k^2 I) per frame, s_k uniform "
        "in 0.5-1.5 x MM (mm) per marker, before projecting (a known model misfit)",
    )
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import representability

    pose_path = args.pose or representability.default_pose_path()
    if pose_path is None and set(args.cases) & set(REAL_CASES):
        print("real-motion cases skipped: no pose.npy (--pose or ACM_RS_AUTHORS_POSE)")
        args.cases = [c for c in args.cases if c not in REAL_CASES]
    n_frames = args.frames
    if args.quick and "--frames" not in (argv if argv is not None else sys.argv):
        n_frames = 120
    if n_frames < 60:
        ap.error("--frames must be >= 60")

    peer_ok = not args.no_peer
    peer_version = None
    if peer_ok:
        try:
            import aniposelib

            peer_version = getattr(aniposelib, "__version__", None)
            if peer_version is None:
                from importlib.metadata import version

                peer_version = version("aniposelib")
        except ImportError as exc:
            print(f"anipose skipped: cannot import aniposelib ({exc}); pip install aniposelib")
            peer_ok = False
    print(
        f"acm-rs {acm_rs.__version__} ({source_version()}) vs aniposelib "
        f"{peer_version or '(skipped)'}; "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, Python "
        f"{platform.python_version()}, numpy {np.__version__}; {n_frames} frames, seed "
        f"{args.seed}"
    )
    if peer_ok:
        print(f"anipose options: {PEER_OPTIONS}, score_threshold {PEER_SCORE_THRESHOLD}")

    rows = []
    report: dict = {
        "frames": n_frames,
        "seed": args.seed,
        "aniposelib": peer_version,
        "acm_rs": acm_rs.__version__,
        "acm_rs_source": source_version(),
        "peer_options": PEER_OPTIONS,
        "cases": {},
    }
    warmed = False
    for name in args.cases:
        case = make_case(name, n_frames, args.seed, pose_path)
        if args.inject_misfit > 0:
            inject_misfit(case, args.inject_misfit, args.seed)
        peer = None
        if peer_ok:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # numba's object-mode deprecation warnings
                if not warmed:
                    report["peer_warm_up_s"] = warm = warm_up_peer(case)
                    print(f"anipose warm-up (JAX + numba compilation): {warm:.1f} s")
                    warmed = True
                peer = run_peer(case)
        options = {"motion": args.motion, "misfit": args.misfit}
        options = {k: v for k, v in options.items() if v}
        if args.overrelax is not None:
            options["overrelax"] = None if args.overrelax == "none" else float(args.overrelax)
        acm = run_acm(case, second=args.second_solutions, **options)
        print_case(case, acm, peer)
        rows.append((case, acm, peer))
        report["cases"][name] = {
            "description": case.description,
            "notes": case.notes,
            "acm_rs": acm,
            "anipose": peer,
        }
    print_summary(rows)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=1, default=float)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
