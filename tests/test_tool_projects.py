"""Projects as the tools write them: a DeepLabCut project folder (single- and multi-animal),
SLEAP files and Lightning Pose CSVs, read and run through the project workflow.

The fixtures are written the way the tools write them: DeepLabCut's ``config.yaml``,
``labeled-data/<video>/CollectedData_<scorer>.h5`` (PyTables, key ``keypoints``) and ``.csv``
with a three-level image index, predictions ``<video>DLC_<net>shuffle1_<iters>.h5`` (key
``df_with_missing``) and ``.csv`` beside the videos with ``_filtered`` versions, labelled videos
and pickles; SLEAP files through sleap-io itself; Lightning Pose's DLC-style CSV with a frame
index.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.cli import main
from acm_rs.demo import demo_rig
from acm_rs.dlc import read_dlc_table, read_labels
from acm_rs.project import (
    find_manual_labels,
    find_sessions,
    load_config,
    match_cameras,
    pick_label_file,
)

pytest.importorskip("tables")
cv2 = pytest.importorskip("cv2")

SCORER = "Alice"
NET = "DLC_resnet50_ratJan1shuffle1_100000"
FPS = 100.0


def _dlc_columns(scorer, bodyparts, coords, individuals=None):
    if individuals is None:
        return pd.MultiIndex.from_product(
            [[scorer], bodyparts, coords], names=["scorer", "bodyparts", "coords"]
        )
    return pd.MultiIndex.from_product(
        [[scorer], individuals, bodyparts, coords],
        names=["scorer", "individuals", "bodyparts", "coords"],
    )


def write_predictions(folder, stem, det, lik, bodyparts, individuals=None, suffix=""):
    """``<stem>DLC_...h5`` and ``.csv`` as DeepLabCut's analyze_videos writes them; det (T, [I,]
    K, 2), lik (T, [I,] K)."""
    data = np.concatenate([det, lik[..., None]], axis=-1).reshape(det.shape[0], -1)
    cols = _dlc_columns(NET, bodyparts, ["x", "y", "likelihood"], individuals)
    df = pd.DataFrame(data, columns=cols)  # index: frame numbers 0..T-1
    name = folder / f"{stem}{NET}{suffix}"
    df.to_hdf(f"{name}.h5", key="df_with_missing", format="table", mode="w")
    df.to_csv(f"{name}.csv")


def write_collected(folder, stem, frames, pts, bodyparts, individuals=None):
    """labeled-data/<stem>/CollectedData_<scorer>.h5|.csv, DeepLabCut >= 2.2 (image index as
    three levels); pts (n, [I,] K, 2)."""
    sub = folder / stem
    sub.mkdir(parents=True)
    index = pd.MultiIndex.from_tuples([("labeled-data", stem, f"img{f:04d}.png") for f in frames])
    cols = _dlc_columns(SCORER, bodyparts, ["x", "y"], individuals)
    df = pd.DataFrame(pts.reshape(len(frames), -1), index=index, columns=cols)
    df.to_hdf(sub / f"CollectedData_{SCORER}.h5", key="keypoints", mode="w")  # fixed format
    df.to_csv(sub / f"CollectedData_{SCORER}.csv")
    for f in frames:
        (sub / f"img{f:04d}.png").write_bytes(b"")
    (sub / "machinelabels-iter0.h5").write_bytes(b"")


def write_video(path, n=3, fps=FPS):
    out = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (64, 48))
    for i in range(n):
        out.write(np.full((48, 64, 3), 40 * i, np.uint8))
    out.release()
    assert path.stat().st_size > 0


def write_config_yaml(root, bodyparts, multi=False, individuals=()):
    import yaml

    doc = {
        "Task": "rat",
        "scorer": SCORER,
        "date": "Jan1",
        "multianimalproject": multi,
        "identity": False if multi else None,
        "project_path": str(root),
        "video_sets": {
            str(root / "videos" / f"s1-cam{c}.mp4"): {"crop": "0, 64, 0, 48"} for c in range(4)
        },
        "start": 0,
        "stop": 1,
        "numframes2pick": 20,
        "pcutoff": 0.6,
        "default_net_type": "resnet_50",
        "TrainingFraction": [0.95],
        "iteration": 0,
    }
    if multi:
        doc.update(
            bodyparts="MULTI!",
            individuals=list(individuals),
            multianimalbodyparts=list(bodyparts),
            uniquebodyparts=[],
        )
    else:
        doc["bodyparts"] = list(bodyparts)
    (root / "config.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))


@pytest.fixture(scope="module")
def dlc_project(tmp_path_factory):
    """A single-animal DeepLabCut project of a 4-camera recording, plus a calibration."""
    root = tmp_path_factory.mktemp("dlc") / "rat-Alice-2024-01-01"
    root.mkdir()
    rig = demo_rig()  # cameras cam0..cam3
    sk = models.rat()
    bps = list(sk.marker_names)
    write_config_yaml(root, bps)
    videos = root / "videos"
    videos.mkdir()
    t, r = datasets.smooth_motion(sk, 25, seed=3)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=4)
    for c in range(4):
        write_video(videos / f"s1-cam{c}.mp4")
        write_predictions(videos, f"s1-cam{c}", det[c], lik[c], bps)
        # filterpredictions' output: here deliberately 50 px off, to see which one is used
        write_predictions(videos, f"s1-cam{c}", det[c] + 50.0, lik[c], bps, suffix="_filtered")
        (videos / f"s1-cam{c}{NET}_meta.pickle").write_bytes(b"")
        write_video(videos / f"s1-cam{c}{NET}_labeled.mp4")  # create_labeled_video
    # manual labels: 12 frames of another stretch, labelled in every camera
    t2, r2 = datasets.smooth_motion(sk, 12, seed=5)
    clean = sk.project(rig, t2, r2)  # (C, n, M, 2)
    frames = np.arange(0, 120, 10)
    for c in range(4):
        write_collected(root / "labeled-data", f"s1-cam{c}", frames, clean[c], bps)
    (root / "labeled-data" / "s1-cam0_labeled").mkdir()  # check_labels output: ignored
    (root / "calibration").mkdir()
    rig.save(root / "calibration" / "calibration.toml")
    truth = sk.forward(t, r)[0]
    return root, det, lik, truth


def test_dlc_project_files_are_found_and_chosen(dlc_project, capsys):
    root, det, _, _ = dlc_project
    (root / "config.toml").unlink(missing_ok=True)  # (another test may have run init)
    assert main(["init", str(root)]) == 0
    out = capsys.readouterr().out
    assert "for a DeepLabCut project" in out
    assert f"DeepLabCut project 'rat' (scorer '{SCORER}'): 43 body parts" in out
    assert "43 of them are markers of the model 'rat'" in out
    assert "frame rate 100 Hz from the metadata of 4 video(s)" in out
    cfg = load_config(root)
    assert cfg.tracking["fps"] == FPS
    assert cfg.paths["labels"] == cfg.paths["videos"] == "videos"
    (session,) = find_sessions(cfg)
    assert session.path == cfg.root and session.cameras == ["cam0", "cam1", "cam2", "cam3"]
    # the labelled videos are not recordings; the raw .h5 is preferred over .csv and _filtered
    assert session.videos["cam2"].name == "s1-cam2.mp4"
    assert session.labels["cam2"].name == f"s1-cam2{NET}.h5"
    ls = read_labels([session.labels[c] for c in session.cameras])
    np.testing.assert_allclose(ls.points, det)
    groups = find_manual_labels(root / "labeled-data", cfg.camera_regex, SCORER)
    assert list(groups) == ["s1-*"]  # the recording: the video stem without the camera
    assert {c: f.name for c, f in groups["s1-*"].items()} == {
        f"cam{c}": f"CollectedData_{SCORER}.h5" for c in range(4)
    }


def test_label_file_choice(tmp_path):
    names = [f"a{NET}.csv", f"a{NET}.h5", f"a{NET}_filtered.csv", f"a{NET}_filtered.h5"]
    files = [tmp_path / n for n in names]
    chosen, skipped = pick_label_file(files)
    assert chosen.name == f"a{NET}.h5" and len(skipped) == 3
    assert pick_label_file(files, prefer_filtered=True)[0].name == f"a{NET}_filtered.h5"
    # SLEAP: the analysis file and the .slp of one analysis
    assert (
        pick_label_file([tmp_path / "a.predictions.slp", tmp_path / "a.analysis.h5"])[0].name
        == "a.analysis.h5"
    )
    other = tmp_path / "aDLC_resnet50_ratJan1shuffle1_200000.h5"
    with pytest.raises(ValueError, match="different analyses.*paths.labels_filter"):
        pick_label_file(files + [other], camera="cam0")


def test_camera_names_match_the_calibration():
    cams = ["cam0", "cam1", "Cam_2"]
    m = match_cameras(cams, ["cam0", "cam1", "cam2"])
    assert m == {
        "cam0": ("cam0", "exact"),
        "cam1": ("cam1", "exact"),
        "Cam_2": ("cam2", "normalised"),
    }
    # the old default regex gave "0", "1", ...: still matched, not failed
    assert match_cameras(["0", "1"], ["cam0", "cam1"])["1"] == ("cam1", "normalised")
    with pytest.raises(ValueError, match=r"\['camA'\] match no single camera.*cameras.regex"):
        match_cameras(["cam0", "camA"], ["cam0", "cam1"], regex="cam[0-9A-Z]")


def test_dlc_project_runs_end_to_end(dlc_project, capsys):
    root, det, _, truth = dlc_project
    if not (root / "config.toml").exists():
        assert main(["init", str(root)]) == 0
    text = (root / "config.toml").read_text().replace("max_iter = 100", "max_iter = 4")
    (root / "config.toml").write_text(text)
    assert main(["run-all", str(root), "--steps", "learn,track,export", "--overwrite"]) == 0
    out = capsys.readouterr().out
    assert "using the generic" not in out
    assert "learn: 12 labelled frames of 1 recording(s)" in out
    # the table of which file is which calibrated camera
    assert "camera  calibration  match  video" in out
    assert f"cam3    cam3         exact  s1-cam3.mp4  s1-cam3{NET}.h5" in out
    res = acm_rs.PoseResult.load(root / "acm-rs" / "pose.npz")
    assert res.n_frames == 25
    # tracked from the raw predictions (the _filtered ones are 50 px off)
    err = np.linalg.norm(res.joints - truth, axis=-1)
    assert np.median(err) < 1.0  # cm
    assert (root / "acm-rs" / "pose.nwb").is_file()  # fps from the videos: NWB written
    try:
        import xarray as xr
    except ImportError:  # the optional extra [movement]: the export says it skipped the file
        assert "no movement file" in out
        return
    with xr.open_dataset(root / "acm-rs" / "pose_movement.nc") as ds:
        assert ds.attrs["fps"] == FPS and ds.sizes["time"] == 25


def test_calibration_named_differently_is_matched_or_explained(dlc_project, tmp_path):
    root, _, _, _ = dlc_project
    if not (root / "config.toml").exists():
        assert main(["init", str(root)]) == 0
    cfg = load_config(root)
    (session,) = find_sessions(cfg)
    from acm_rs.pipeline import _load_rig

    text = (root / "calibration" / "calibration.toml").read_text()
    assert 'name = "cam1"' in text
    calib = tmp_path / "calibration.toml"
    calib.write_text(text.replace('name = "cam', 'name = "Cam_'))
    session.calibration = calib
    got, mapping = _load_rig(cfg, session)
    assert [c.name for c in got] == ["Cam_0", "Cam_1", "Cam_2", "Cam_3"]
    assert mapping["cam1"] == ("Cam_1", "normalised")
    for c, n in enumerate("ABCD"):
        text = text.replace(f'name = "cam{c}"', f'name = "{n}"')
    calib.write_text(text)
    with pytest.raises(ValueError, match=r"cameras.regex '\(\?i\)cam.*calibration cameras: \['A'"):
        _load_rig(cfg, session)


# -- multi-animal DeepLabCut ----------------------------------------------------------------------
def test_multi_animal_files(tmp_path):
    rig = demo_rig()
    sk = models.rat()
    bps = list(sk.marker_names)
    t, r = datasets.smooth_motion(sk, 6, seed=7)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=8)
    other = det[0] + 300.0
    # (T, I, K, 2): rat1 is another animal, rat2 ours; "single" holds unique body parts
    both = np.stack([other, det[0]], axis=1)
    write_predictions(tmp_path, "s1-cam0", both, np.stack([lik[0], lik[0]], 1), bps,
                      individuals=["rat1", "rat2"], suffix="_el")  # fmt: skip
    path = tmp_path / f"s1-cam0{NET}_el.h5"
    with pytest.raises(ValueError, match=r"individuals \['rat1', 'rat2'\].*project.individual"):
        read_dlc_table(path)
    pts, lk, frames, names = read_dlc_table(path, individual="rat2")
    np.testing.assert_allclose(pts, det[0])
    assert names == bps and list(frames) == list(range(6))
    pts_csv = read_dlc_table(tmp_path / f"s1-cam0{NET}_el.csv", individual="rat2")[0]
    np.testing.assert_allclose(pts_csv, det[0])
    # manual labels of a multi-animal project (4 header rows, 3-level image index)
    write_collected(tmp_path / "labeled-data", "s1-cam0", [3, 8], both[:2], bps, ["rat1", "rat2"])
    for f in ("CollectedData_Alice.h5", "CollectedData_Alice.csv"):
        pts, lk, frames, _ = read_dlc_table(tmp_path / "labeled-data" / "s1-cam0" / f, "rat2")
        assert lk is None and list(frames) == [3, 8]
        np.testing.assert_allclose(pts, det[0, :2])


def test_multi_animal_project_needs_the_individual(tmp_path, capsys):
    root = tmp_path / "ma"
    root.mkdir()
    rig = demo_rig()
    sk = models.rat()
    bps = list(sk.marker_names)
    write_config_yaml(root, bps, multi=True, individuals=["rat1", "rat2"])
    t, r = datasets.smooth_motion(sk, 8, seed=9)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=10)
    (root / "videos").mkdir()
    for c in range(4):
        both = np.stack([det[c] + 300.0, det[c]], axis=1)
        write_predictions(root / "videos", f"s1-cam{c}", both, np.stack([lik[c], lik[c]], 1),
                          bps, individuals=["rat1", "rat2"], suffix="_el")  # fmt: skip
    (root / "calibration").mkdir()
    rig.save(root / "calibration" / "calibration.toml")
    assert main(["init", str(root), "--fps", "50"]) == 0
    assert "individuals ['rat1', 'rat2']" in capsys.readouterr().out
    text = (root / "config.toml").read_text().replace("max_iter = 100", "max_iter = 3")
    (root / "config.toml").write_text(text)
    status = acm_rs.pipeline.run_all(root, steps=("track",))
    assert "several individuals" in status[root.name] and "project.individual" in status[root.name]
    text = text.replace("# individual = ...", 'individual = "rat2"')
    (root / "config.toml").write_text(text)
    capsys.readouterr()
    status = acm_rs.pipeline.run_all(root, steps=("track",), overwrite=True)
    assert status == {root.name: "ok"}
    assert capsys.readouterr().out == ""  # the Python API is quiet; the log has the stages
    log = max((root / "logs").glob("acm-rs-*.log")).read_text()
    assert f"track {root.name}: tracked 8 frames" in log
    res = acm_rs.PoseResult.load(root / "acm-rs" / "pose.npz")
    assert np.median(np.linalg.norm(res.joints - sk.forward(t, r)[0], axis=-1)) < 1.0


# -- SLEAP and Lightning Pose -------------------------------------------------------------------
def _sleap_labels(pts, scores, nodes, video, tracks=("mouse1",)):
    sio = pytest.importorskip("sleap_io")
    sk = sio.Skeleton(list(nodes))
    vid = sio.Video(filename=video, open_backend=False)
    trk = [sio.Track(n) for n in tracks]
    lfs = []
    for f in range(pts.shape[0]):
        insts = [
            sio.PredictedInstance.from_numpy(
                pts[f, i], skeleton=sk, point_scores=scores[f, i], score=1.0, track=trk[i]
            )
            for i in range(len(tracks))
        ]
        lfs.append(sio.LabeledFrame(video=vid, frame_idx=f, instances=insts))
    return sio.Labels(lfs, skeletons=[sk], videos=[vid], tracks=trk)


def test_sleap_slp_and_analysis_h5(tmp_path):
    sio = pytest.importorskip("sleap_io")
    rng = np.random.default_rng(0)
    nodes = ["nose", "ear_l", "ear_r"]
    pts = rng.uniform(0, 500, (7, 2, 3, 2))  # (frames, tracks, nodes, xy)
    scores = rng.uniform(0.2, 1.0, (7, 2, 3))
    pts[2, 1, 1] = np.nan  # a node not predicted
    labels = _sleap_labels(pts, scores, nodes, "s1-cam0.mp4", tracks=("a", "b"))
    sio.save_slp(labels, str(tmp_path / "s1-cam0.predictions.slp"))
    sio.save_analysis_h5(labels, str(tmp_path / "s1-cam0.analysis.h5"))
    for name in ("s1-cam0.predictions.slp", "s1-cam0.analysis.h5"):
        with pytest.raises(ValueError, match=r"several tracks \['a', 'b'\]"):
            read_dlc_table(tmp_path / name)
        got, lk, frames, names = read_dlc_table(tmp_path / name, individual="b")
        assert names == nodes and list(frames) == list(range(7))
        np.testing.assert_allclose(got, pts[:, 1])
        ok = np.isfinite(pts[:, 1, :, 0])
        np.testing.assert_allclose(lk[ok], scores[:, 1][ok])
        assert np.isnan(lk[2, 1])
    # SLEAP and DeepLabCut files mix per camera
    write_predictions(tmp_path, "s1-cam1", pts[:, 1], scores[:, 1], nodes)
    ls = read_labels([tmp_path / "s1-cam0.analysis.h5", tmp_path / f"s1-cam1{NET}.csv"], "b")
    np.testing.assert_allclose(ls.points[0], ls.points[1])


def test_lightning_pose_csv(tmp_path):
    rng = np.random.default_rng(1)
    bps = ["nose", "tail"]
    data = rng.uniform(0, 1, (5, 2, 3))
    cols = pd.MultiIndex.from_product(
        [["heatmap_mhcrnn_tracker"], bps, ["x", "y", "likelihood"]],
        names=["scorer", "bodyparts", "coords"],
    )
    df = pd.DataFrame(data.reshape(5, -1), columns=cols, index=np.arange(40, 45))
    df[("set", "", "")] = "train"  # Lightning Pose marks the split of labelled frames
    df.to_csv(tmp_path / "s1_cam0.csv")  # Lightning Pose's predictions.csv layout
    pts, lk, frames, names = read_dlc_table(tmp_path / "s1_cam0.csv")
    assert names == bps and list(frames) == list(range(40, 45))
    np.testing.assert_allclose(pts, data[..., :2])
    np.testing.assert_allclose(lk, data[..., 2])


def test_batch_session_function_runs_in_a_dlc_project(dlc_project, tmp_path):
    root, _, _, truth = dlc_project
    if not (root / "config.toml").exists():
        assert main(["init", str(root)]) == 0
    text = (root / "config.toml").read_text()
    (root / "config.toml").write_text(text.replace("max_iter = 100", "max_iter = 3"))
    out = acm_rs.pipeline.run_session(root, tmp_path / "out")  # what acm-rs batch runs
    res = acm_rs.PoseResult.load(out["pose"])
    assert res.n_frames == 25
    assert np.median(np.linalg.norm(res.joints - truth, axis=-1)) < 1.0
