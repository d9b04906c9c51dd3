"""Leave-one-camera-out accuracy (acm_rs.evaluate, issue 28 item 4): exact on noise-free
synthetic labels, the triangulation baseline recomputed with OpenCV, and the real SLEAP
multi-camera session of tests/data/real/sleap with its own skeleton."""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from acm_rs import CameraRig
from acm_rs import lab_skeleton as ls
from acm_rs.cli import main
from acm_rs.evaluate import evaluate
from acm_rs.learning import learn_skeleton

SESSION = Path(__file__).parent / "data" / "real" / "sleap" / "min_session_user_labeled.slp"


@pytest.fixture(scope="module")
def session():
    from acm_rs.sleap_session import read_sleap_session

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return read_sleap_session(SESSION, individual="track_0")


def _subset(session, cams):
    from acm_rs.dlc import LabelSet

    idx = [[c.name for c in session.rig].index(n) for n in cams]
    lab = session.labels
    return CameraRig([session.rig[i] for i in idx]), LabelSet(
        lab.points[idx], None, lab.frames, lab.bodyparts, ["sleap"] * len(idx)
    )


def test_noise_free_labels_give_zero_error(rig, small_skeleton, rng):
    sk = small_skeleton
    n = 6
    t = rng.normal(scale=0.5, size=(n, 3))
    r = rng.normal(scale=0.15, size=(n, sk.n_bones, 3))
    r[:, sk.fixed_pose_mask[3:].reshape(-1, 3)] = 0.0
    px = sk.project(rig, t, r)
    ev = evaluate(rig, sk, px, bodyparts=list(sk.marker_names))
    assert ev.per_camera.loc["all", "n"] == np.isfinite(px[..., 0]).sum()
    assert ev.per_camera.loc["all", "model_px"] < 1e-3
    assert ev.per_camera.loc["all", "triangulation_px"] < 1e-3
    # one camera's labels 5 px off: its held-out error says so, the others barely move
    bad = px.copy()
    bad[2] += np.array([3.0, 4.0])
    ev = evaluate(rig, sk, bad, bodyparts=list(sk.marker_names))
    assert ev.per_camera.loc["cam2", "triangulation_px"] > 4.0
    assert ev.per_camera.loc["cam2", "model_px"] > 4.0


def test_triangulation_baseline_matches_opencv(session):
    """Held-out error of the DLT baseline with 2 remaining cameras, recomputed with
    cv2.triangulatePoints on undistorted points."""
    rig, labels = _subset(session, ["backL", "midL", "topL"])
    res = ls.skeleton_from_labels(SESSION, rig, labels)
    ev = evaluate(rig, res.skeleton, labels)
    lab = labels.points[:, :, [labels.bodyparts.index(m) for m in res.skeleton.marker_names]]
    held, a, b = 0, 1, 2
    ok = np.isfinite(lab[a]).all(-1) & np.isfinite(lab[b]).all(-1) & np.isfinite(lab[held]).all(-1)
    pa, pb = (cv2.undistortPoints(lab[c][ok].reshape(-1, 1, 2), rig[c].matrix, rig[c].dist)
              .reshape(-1, 2).T for c in (a, b))  # fmt: skip
    proj = [np.hstack([rig[c].rotation_matrix, rig[c].tvec[:, None]]) for c in (a, b)]
    h = cv2.triangulatePoints(proj[0], proj[1], pa, pb)
    x = (h[:3] / h[3]).T
    err = np.linalg.norm(rig[held].project(x) - lab[held][ok], axis=-1)
    np.testing.assert_allclose(ev.triangulation_error[held][ok], err, rtol=1e-5, atol=1e-4)


def test_real_session_three_cameras(session):
    """With 2 cameras left, the skeleton beats triangulation on the labels both predict and
    places keypoints that the other cameras see only once."""
    rig, labels = _subset(session, ["backL", "midL", "topL"])
    res = ls.skeleton_from_labels(SESSION, rig, labels)
    learned = learn_skeleton(rig, res.skeleton, labels.points, marker_names=labels.bodyparts)
    ev = evaluate(rig, learned.skeleton, labels)
    a = ev.per_camera.loc["all"]
    assert a["model_px"] < a["triangulation_px"]
    assert a["n_model_only"] > 0
    assert a["n"] == ev.per_camera.drop(index="all")["n"].sum()
    assert a["n"] == ev.per_keypoint.drop(index="all")["n"].sum()
    held = np.isfinite(ev.model_error) | np.isfinite(ev.triangulation_error)
    assert held.sum() == a["n"] + a["n_model_only"]
    text = ev.table()
    assert "per held-out camera" in text and "Shoulder_left" in text


def test_relearn_and_errors(session, rig, small_skeleton):
    rig3, labels = _subset(session, ["back", "backL", "mid", "midL"])
    res = ls.skeleton_from_labels(SESSION, rig3, labels)
    ev = evaluate(rig3, res.skeleton, labels, relearn=True)
    assert ev.info["relearn"] and np.isfinite(ev.per_camera.loc["all", "model_px"])
    two = CameraRig([rig[0], rig[1]])
    px = np.zeros((2, 1, small_skeleton.n_markers, 2))
    with pytest.raises(ValueError, match=">= 3 cameras"):
        evaluate(two, small_skeleton, px, bodyparts=list(small_skeleton.marker_names))
    with pytest.raises(ValueError, match="no label column"):
        evaluate(rig3, small_skeleton, labels)


def test_cli_from_labels_then_evaluate(tmp_path, capsys):
    out = tmp_path / "lab.toml"
    args = ["--session", str(SESSION), "--individual", "track_0"]
    assert main(["model", "from-labels", str(SESSION), *args, "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "rooted at 'Head'" in text and out.is_file()
    assert main(["model", "from-labels", str(SESSION), *args, "-o", str(out)]) == 1  # exists
    capsys.readouterr()
    assert main(["evaluate", "--model", str(out), *args, "-o", str(tmp_path / "ev")]) == 0
    text = capsys.readouterr().out
    assert "leave-one-camera-out" in text
    for f in ("ev_keypoints.csv", "ev_cameras.csv", "ev.png"):
        assert (tmp_path / f).stat().st_size > 0
    import pandas as pd

    table = pd.read_csv(tmp_path / "ev_cameras.csv", index_col=0)
    assert list(table.index)[-1] == "all" and table.loc["all", "n"] == 320
