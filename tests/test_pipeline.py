"""The project workflow (acm_rs.pipeline, ``acm-rs run-all``) on a tiny generated project."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.cli import main
from acm_rs.demo import demo_rig
from acm_rs.project import init_project


def write_dlc(folder, rig, sk, det, lik, prefix="rat"):
    folder.mkdir(parents=True, exist_ok=True)
    for c, cam in enumerate(rig):
        cols = pd.MultiIndex.from_tuples(
            [("DLC_net", bp, co) for bp in sk.marker_names for co in ("x", "y", "likelihood")],
            names=["scorer", "bodyparts", "coords"],
        )
        data = np.concatenate([det[c], lik[c, :, :, None]], axis=-1).reshape(det.shape[1], -1)
        pd.DataFrame(data, columns=cols).to_csv(folder / f"{prefix}-{cam.name}DLC_net.csv")


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    root = tmp_path_factory.mktemp("project")
    init_project(root, cameras={"regex": "(cam[0-9])"}, em={"max_iter": 3}, tracking={"fps": 50})
    rig = demo_rig()
    (root / "calibration").mkdir()
    rig.save(root / "calibration" / "calibration.toml")
    sk = models.rat()
    truth = {}
    for i, name in enumerate(["s1", "s2"]):
        t, r = datasets.smooth_motion(sk, 20, seed=10 + i)
        det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=20 + i)
        write_dlc(root / name / "pose-2d", rig, sk, det, lik)
        truth[name] = sk.forward(t, r)[0]
    (root / "broken" / "pose-2d").mkdir(parents=True)
    (root / "broken" / "pose-2d" / "rat-cam0DLC_net.csv").write_text("not a DLC file\n")
    return root, truth


def test_run_all_tracks_exports_plots_and_resumes(project, capsys):
    root, truth = project
    assert main(["run-all", str(root)]) == 1  # the broken session fails, the others run
    out = capsys.readouterr().out
    assert "session broken FAILED" in out and "2/3 sessions ok" in out
    for name in ("s1", "s2"):
        res = acm_rs.PoseResult.load(root / name / "acm-rs" / "pose.npz")
        err = np.linalg.norm(res.joints - truth[name], axis=-1)
        assert np.median(err) < 0.5  # cm, generic model = the animal here
        csv = pd.read_csv(root / name / "acm-rs" / "pose_3d.csv")
        assert len(csv) == 20
        assert (root / name / "acm-rs" / "pose.nwb").is_file()
        assert (root / name / "acm-rs" / "pose.c3d").is_file()
        assert (root / name / "acm-rs" / "plots" / "joint_traces.png").is_file()
    # no manual labels: nothing learned, so no skeleton.toml, and track says so loudly
    assert not (root / "skeleton.toml").exists()
    assert "no manual labels" in out and "tracking with the generic" in out
    logs = sorted((root / "logs").glob("acm-rs-*.log"))
    assert logs and "track s1" in logs[-1].read_text()
    pose = root / "s1" / "acm-rs" / "pose.npz"
    before = pose.stat().st_mtime_ns
    assert main(["run-all", str(root), "--steps", "track,export"]) == 1
    out = capsys.readouterr().out
    assert "is up to date (same inputs, settings, version), skipped" in out
    assert pose.stat().st_mtime_ns == before
    # a changed setting redoes track, and the new pose.npz (new run id) redoes export
    cfg = root / "config.toml"
    cfg.write_text(cfg.read_text().replace('pcutoff = "auto"', "pcutoff = 0.8"))
    assert main(["run-all", str(root), "--steps", "track,export"]) == 1
    out = capsys.readouterr().out
    assert "redoing" in out and "settings changed: tracking" in out
    assert "input(s) changed: pose" in out
    assert pose.stat().st_mtime_ns != before


def test_unknown_step_and_missing_calibration(project, tmp_path):
    root, _ = project
    with pytest.raises(ValueError, match="unknown step"):
        acm_rs.pipeline.run_all(root, steps=("track", "dance"))
    init_project(tmp_path, cameras={"regex": "(cam[0-9])"})
    rig = demo_rig()
    sk = models.rat()
    t, r = datasets.smooth_motion(sk, 5, seed=1)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=2)
    write_dlc(tmp_path / "s" / "pose-2d", rig, sk, det, lik)
    status = acm_rs.pipeline.run_all(tmp_path, steps=("track",))
    assert "no calibration file" in status["s"]


def test_batch_runs_the_default_session_pipeline(project, capsys):
    root, truth = project
    code = main(["batch", str(root), "--sessions", "s2", "--overwrite", "--workers", "2"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "1 sessions: 1 done, 0 skipped (finished before), 0 failed" in out
    res = acm_rs.PoseResult.load(root / "s2" / "acm-rs" / "pose.npz")
    assert np.median(np.linalg.norm(res.joints - truth["s2"], axis=-1)) < 0.5
    assert acm_rs.batch.is_done(root / "s2")


def test_step_commands_work_on_a_project_folder(project, capsys):
    root, _ = project
    csv = root / "s1" / "acm-rs" / "pose_3d.csv"
    before = csv.stat().st_mtime_ns
    # The broken session has no result to export: exit 1, the others are redone.
    assert main(["export", "--project", str(root), "--overwrite-step"]) == 1
    assert csv.stat().st_mtime_ns != before
    assert main(["track", "--project", str(root)]) == 1
    assert "is up to date (same inputs, settings, version), skipped" in capsys.readouterr().out
    assert main(["learn", "--calibration", "c.toml"]) == 1
    assert "needs --labels, --output (or --project DIR" in capsys.readouterr().err
    assert main(["calibrate", "--board", "b.toml", "-o", "c.toml"]) == 1
    assert "needs --videos or --images" in capsys.readouterr().err


def test_batch_without_a_learned_skeleton_says_so(project, capsys):
    root, _ = project
    assert not (root / "skeleton.toml").exists()
    assert main(["batch", str(root), "--sessions", "s2", "--workers", "1"]) == 0
    err = capsys.readouterr()
    assert "WARNING: no learned skeleton" in err.err and "GENERIC model" in err.out


def test_interrupted_track_is_not_done_and_is_redone(project, capsys, monkeypatch):
    # last in the file: it re-tracks the shared project
    import acm_rs.tracking as tracking

    root, _ = project
    real = tracking.track

    def stopped(*a, **k):
        res = real(*a, **k)
        res.info["interrupted"] = True  # as after Ctrl-C during EM
        return res

    monkeypatch.setattr(tracking, "track", stopped)
    assert main(["run-all", str(root), "--steps", "track,export", "--overwrite"]) == 130
    out = capsys.readouterr().out
    assert "session s1 interrupted; it is not done" in out
    pose = root / "s1" / "acm-rs" / "pose.npz"
    assert json.loads((root / "s1" / "acm-rs" / "pose.npz.step.json").read_text())["interrupted"]
    monkeypatch.setattr(tracking, "track", real)
    # export refuses the interrupted pose; track redoes it and says why
    assert acm_rs.pipeline.run_all(root, steps=("export",))["s1"].startswith("ValueError")
    before = pose.stat().st_mtime_ns
    acm_rs.pipeline.run_all(root, steps=("track",), verbose=True)
    assert "redoing" in capsys.readouterr().out and pose.stat().st_mtime_ns != before
    assert not json.loads((root / "s1" / "acm-rs" / "pose.npz.step.json").read_text())[
        "interrupted"
    ]
