"""Calibration refined on the animal's labelled keypoints (issue 28).

Truth from independent code: keypoints from ``tests/elastic_truth.py`` (plain NumPy), pixels
from OpenCV's ``projectPoints`` through the true cameras; the starting rig is the true one with
a camera turned by 1 deg and another moved by 9 mm. And the real SLEAP session of
``tests/data/real/sleap/`` with its own calibration.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import acm_rs
from acm_rs.calibration import refine_on_keypoints
from acm_rs.calibration.keypoints import _problem
from acm_rs.learning import triangulate

sys.path.insert(0, str(Path(__file__).parent))
from elastic_truth import cameras, project, synthetic  # noqa: E402

cv2 = pytest.importorskip("cv2")
SESSION = Path(__file__).parent / "data" / "real" / "sleap" / "min_session_user_labeled.slp"


@pytest.fixture(scope="module")
def case():
    pts, _ = synthetic(80, seed=3)
    cams = cameras()
    truth = acm_rs.CameraRig(
        [acm_rs.Camera(k, d, rv, tv, (1280, 1024), name=f"c{i}") for i, (k, d, rv, tv) in
         enumerate(cams)], units="mm",
    )  # fmt: skip
    labels = project(cams, pts) + np.random.default_rng(0).normal(0, 0.5, (4, 80, 9, 2))
    p = truth.get_params().copy()
    turn = cv2.Rodrigues(np.array([0.0, np.radians(1.0), 0.0]))[0]
    p[2, :3] = cv2.Rodrigues(cv2.Rodrigues(p[2, :3])[0] @ turn)[0].ravel()
    p[3, 3:6] += np.array([8.0, -4.0, 0.0])
    return truth, truth.set_params(p), labels


def loo_dlt(rig, labels):
    """Mean leave-one-camera-out error (px) of DLT triangulation, per held-out camera."""
    out = []
    for c in range(len(rig)):
        others = labels.copy()
        others[c] = np.nan
        px = rig.project(triangulate(rig, others))[c]
        out.append(np.nanmean(np.linalg.norm(px - labels[c], axis=-1)))
    return np.array(out)


@pytest.mark.parametrize("intrinsics", [False, True])
def test_jacobian_matches_central_differences(case, intrinsics):
    _, bad, labels = case
    pr = _problem(bad, labels[:, :4], intrinsics, 2.0, 2.0, None, 2)
    x = pr.x0 + 1e-3 * np.random.default_rng(1).normal(size=pr.x0.size)
    jac = pr.jac(x).toarray()
    fd = np.empty_like(jac)
    for i in range(x.size):
        h = 1e-6 * max(1.0, abs(x[i]))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        fd[:, i] = (pr.fun(xp) - pr.fun(xm)) / (2 * h)
    assert np.abs(jac - fd).max() < 1e-6 * max(1.0, np.abs(fd).max())


def test_refinement_restores_a_disturbed_rig_on_held_out_frames(case):
    truth, bad, labels = case
    train, held = labels[:, :40], labels[:, 40:]
    ref = refine_on_keypoints(bad, train)
    assert ref.rms_before > 3.0 and ref.rms_after < 0.7  # 0.5 px noise per coordinate
    before, after, best = loo_dlt(bad, held), loo_dlt(ref.rig, held), loo_dlt(truth, held)
    assert np.all(before > 2.5 * best)
    np.testing.assert_allclose(after, best, rtol=0.1)  # as good as the true cameras
    assert "c3" in ref.summary() and ref.info["frames"] == 40
    # (only the rig's relative geometry is seen: the prior shares the correction among the
    # cameras, so no camera need return to its true place)


def test_refinement_refuses_what_it_cannot_use(case):
    _, bad, labels = case
    few = np.full_like(labels[:, :2], np.nan)
    few[:2, 0, :2] = labels[:2, 0, :2]
    with pytest.raises(ValueError, match="keypoints are labelled in >= 2 cameras"):
        refine_on_keypoints(bad, few)
    alone = labels[:, :10].copy()
    alone[3, :, :] = np.nan
    alone[3, 0, 0] = labels[3, 0, 0]
    alone[:3, 0, 0] = np.nan
    with pytest.raises(ValueError, match=r"\['c3'\] share no labelled keypoint"):
        refine_on_keypoints(bad, alone)


def test_real_session_held_out_frame_improves():
    """The real SLEAP session (8 cameras, 3 frames): refined on frames 0 and 2, the held-out
    frame 1 reprojects better into each left-out camera, with the model and with DLT."""
    import warnings

    from acm_rs.evaluate import evaluate_refined
    from acm_rs.lab_skeleton import read_keypoint_graph, skeleton_from_labels
    from acm_rs.learning import learn_skeleton
    from acm_rs.sleap_session import read_sleap_session

    ses = read_sleap_session(SESSION, individual="track_0")
    sk = skeleton_from_labels(read_keypoint_graph(SESSION), ses.rig, ses.labels).skeleton
    idx = [list(ses.labels.bodyparts).index(m) for m in sk.marker_names]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        learned = learn_skeleton(ses.rig, sk, ses.labels.points[:, :, idx], progress=False)
    res = evaluate_refined(ses.rig, learned.skeleton, ses.labels)
    assert list(res.train_frames) == [0, 2] and list(res.test_frames) == [1]
    b, a = res.before.per_camera.loc["all"], res.after.per_camera.loc["all"]
    assert a["model_px"] < 0.85 * b["model_px"]
    assert a["triangulation_px"] < 0.85 * b["triangulation_px"]
    assert res.refinement.rms_after < res.refinement.rms_before
    assert "held-out frames (1; trained on 2)" in res.summary()
