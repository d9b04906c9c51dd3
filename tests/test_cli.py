"""The ``acm-rs`` command line, the demo job and atomic outputs."""

from __future__ import annotations

import numpy as np
import pytest

import acm_rs
from acm_rs._io import atomic_write
from acm_rs.cli import main
from acm_rs.demo import demo_pose, demo_rig


def test_demo_writes_pictures_and_consistent_projections(tmp_path, capsys):
    argv = ["demo", "--out", str(tmp_path), "--frames", "2000", "--learn-frames", "30"]
    assert main([*argv, "--track-frames", "60"]) == 0
    out = capsys.readouterr().out
    assert "2,000 poses" in out and "skeleton learning from 30 labelled frames" in out
    assert "calibration from" in out and "tracking 60 frames" in out
    learned = acm_rs.Skeleton.load(tmp_path / "learned_rat.toml")
    assert learned.n_bones == 28
    rig = acm_rs.CameraRig.load(tmp_path / "calibration.toml")
    assert rig.names == demo_rig().names
    # The calibrated rig (world frame from the board on the floor) is close to the truth.
    for cal, true in zip(rig, demo_rig(), strict=True):
        assert np.linalg.norm(cal.center - true.center) < 0.5  # cm
    res = acm_rs.PoseResult.load(tmp_path / "pose.npz")
    assert res.joints.shape == (60, 29, 3)
    for name in ("pose_3d.csv", "pose.nwb", "pose.c3d", "plots/joint_traces.png"):
        assert (tmp_path / name).is_file()
    for name in (
        "rat_model.png",
        "camera_views.png",
        "calibration_qc.png",
        "learn_reprojection.png",
        "learn_skeleton.png",
    ):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    saved = np.load(tmp_path / "projections.npz")
    rat = acm_rs.models.rat()
    rig = demo_rig()
    np.testing.assert_allclose(saved["camera_params"], rig.get_params())
    _, markers = rat.forward(saved["t"][:5], saved["r"][:5])
    np.testing.assert_allclose(saved["pixels"][:, :5], rig.project(markers), atol=1e-9)
    assert list(saved["marker_names"]) == list(rat.marker_names)
    assert not list(tmp_path.glob(".*.tmp"))


def test_demo_pose_is_in_view_of_every_camera():
    rat = acm_rs.models.rat()
    rig = demo_rig()
    t, r = demo_pose(rat)
    px = rat.project(rig, t, r)
    assert np.isfinite(px).all()
    assert (px[..., 0] > 0).all() and (px[..., 0] < 1280).all()
    assert (px[..., 1] > 0).all() and (px[..., 1] < 1024).all()


def test_model_command(tmp_path, capsys):
    assert main(["model"]) == 0
    assert "mouse" in capsys.readouterr().out
    toml_path, png = tmp_path / "rat.toml", tmp_path / "rat.png"
    assert main(["model", "rat", "--save", str(toml_path), "--plot", str(png)]) == 0
    assert "50" in capsys.readouterr().out
    again = acm_rs.Skeleton.load(toml_path)
    np.testing.assert_allclose(again.bone_lengths, acm_rs.models.rat().bone_lengths)
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert main(["model", "horse"]) == 1
    assert "unknown model 'horse'" in capsys.readouterr().err


def test_bad_arguments(capsys):
    assert main(["demo", "--frames", "0"]) == 2
    with pytest.raises(SystemExit):
        main(["no-such-command"])


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    target = tmp_path / "f.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(target) as fh:
        fh.write("new, half written")
        raise RuntimeError("crash")
    assert target.read_text() == "old"
    assert list(tmp_path.iterdir()) == [target]
    with atomic_write(target) as fh:
        fh.write("new")
    assert target.read_text() == "new"
