"""``acm-rs track`` and ``acm-rs export`` end to end on tiny generated files."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.cli import main
from acm_rs.demo import demo_rig


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    d = tmp_path_factory.mktemp("proj")
    sk = datasets.individual_skeleton(models.rat(), seed=8)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, 30, seed=9)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=10)
    rig.save(d / "calibration.toml")
    sk.save(d / "skeleton.toml")
    dlc = []
    for c, cam in enumerate(rig):
        cols = pd.MultiIndex.from_tuples(
            [("DLC_net", bp, co) for bp in sk.marker_names for co in ("x", "y", "likelihood")],
            names=["scorer", "bodyparts", "coords"],
        )
        data = np.concatenate([det[c], lik[c, :, :, None]], axis=-1).reshape(30, -1)
        p = d / f"{cam.name}DLC_net.csv"
        pd.DataFrame(data, columns=cols).to_csv(p)
        dlc.append(str(p))
    return d, sk, rig, t, r, dlc


def test_track_then_export(project, capsys):
    d, sk, rig, t, r, dlc = project
    out = d / "out" / "session"
    code = main([
        "track", "--calibration", str(d / "calibration.toml"), "--skeleton",
        str(d / "skeleton.toml"), "--dlc", *dlc, "--max-iter", "3", "--frames", "0:25",
        "--export", "anipose", "-o", str(out), "--second-solutions", "2",
    ])  # fmt: skip
    assert code == 0
    res = acm_rs.PoseResult.load(out.with_suffix(".npz"))
    assert res.joints.shape == (25, sk.n_joints, 3)
    truth, _ = sk.forward(t[:25], r[:25])
    assert np.mean(np.linalg.norm(res.joints - truth, axis=-1)) < 0.3  # cm
    csv = pd.read_csv(d / "out" / "session_3d.csv")
    assert len(csv) == 25 and f"{sk.joint_names[0]}_x" in csv
    assert main(["export", str(out.with_suffix(".npz")), "--format", "c3d", "--rate", "100"]) == 0
    import ezc3d

    c3d = ezc3d.c3d(str(out.with_suffix(".c3d")))
    assert c3d["data"]["points"].shape[2] == 25
    printed = capsys.readouterr().out
    assert "wrote" in printed
    assert "in the 2 searched frames" in printed  # the joint limits decide the rat's joints


def test_track_errors_name_the_problem(project, capsys):
    d, _, _, _, _, dlc = project
    args = ["track", "--calibration", str(d / "calibration.toml"), "-o", str(d / "x")]
    assert main([*args, "--dlc", *dlc[:3]]) == 1
    assert "3 DeepLabCut files for 4 cameras" in capsys.readouterr().err
    assert main([*args, "--dlc", *dlc, "--skeleton", "horse"]) == 1
    assert "neither a bundled model" in capsys.readouterr().err
    assert main([*args, "--dlc", *dlc, "--frames", "a:b"]) == 1
    assert "START:END" in capsys.readouterr().err


def test_bundle_mode_writes_an_acm_smooth_input(project):
    d, _, _, _, _, dlc = project
    out = d / "b" / "s"
    code = main([
        "track", "--calibration", str(d / "calibration.toml"), "--skeleton",
        str(d / "skeleton.toml"), "--dlc", *dlc, "--bundle", "-o", str(out),
    ])  # fmt: skip
    assert code == 0
    b = np.load(d / "b" / "s.bundle.npz")
    assert b["detections"].shape[:2] == (4, 30) and np.isfinite(b["mu0"]).all()


def test_track_matches_files_to_cameras_by_name(project, capsys):
    d, sk, rig, t, r, dlc = project
    out = d / "out" / "shuffled"
    shuffled = [dlc[2], dlc[0], dlc[3], dlc[1]]  # not the calibration's order
    code = main([
        "track", "--calibration", str(d / "calibration.toml"), "--skeleton",
        str(d / "skeleton.toml"), "--dlc", *shuffled, "--max-iter", "3", "--frames", "0:25",
        "-o", str(out), "--overrelax", "0",
    ])  # fmt: skip
    assert code == 0
    printed = capsys.readouterr().out
    assert "cameras matched by the names in the files" in printed
    assert "cam2    cam2         exact  cam2DLC_net.csv" in printed
    res = acm_rs.PoseResult.load(out.with_suffix(".npz"))
    assert res.rig.names == ["cam2", "cam0", "cam3", "cam1"]
    # --overrelax 0: plain EM (Alg. 11)
    assert res.em_history and all(h["step"] == 1.0 for h in res.em_history)
    truth, _ = sk.forward(t[:25], r[:25])
    assert np.mean(np.linalg.norm(res.joints - truth, axis=-1)) < 0.3  # cm
