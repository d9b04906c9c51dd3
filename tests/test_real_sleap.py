"""SLEAP's own files (tests/data/real/sleap, provenance in its PROVENANCE.md): what acm-rs reads
against independent readers (h5py on the raw tables, SLEAP's own analysis export, tomllib,
OpenCV, and sleap-io when installed), and the round trips where acm-rs writes.

Issue 27: item 3 (a track never gets another track's points), items 2 and 9 on real scores,
item 12 (sleap-anipose's board.toml) and item 13 (multi-camera sessions).
"""

from __future__ import annotations

import json
import shutil
import tomllib
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

from acm_rs.calibration.board import BoardSpec
from acm_rs.camera import CameraRig
from acm_rs.sleap import read_sleap_analysis, read_slp
from acm_rs.sleap_session import read_sleap_session, write_session_views

DATA = Path(__file__).parent / "data" / "real" / "sleap"
SA = DATA / "sleap_anipose"
SESSIONS = ["min_session.slp", "min_session_frame_groups.slp", "min_session_user_labeled.slp"]
READABLE = SESSIONS + [
    "clip.predictions.slp", "clip.2node.slp", "small_robot_siv.slp", "small_robot_minimal.slp",
    "sleap_anipose/minimal_mid_proofread.slp", "sleap_anipose/minimal_top_proofread.slp",
]  # fmt: skip
REFUSED = {
    "minimal_instance.slp": "2 untracked instances in frame 0",
    "minimal_instance_centroid_pr.slp": "2 untracked instances in frame 1",
}


def _raw(path: Path) -> dict:
    """The raw tables, read with h5py only."""
    with h5py.File(path, "r") as f:
        meta = json.loads(f["metadata"].attrs["json"])
        skel = meta["skeletons"][0].get("nx_graph", meta["skeletons"][0])
        return {
            "nodes": [meta["nodes"][n["id"]]["name"] for n in skel["nodes"]],
            "tracks": [json.loads(t)[1] for t in f["tracks_json"][()]],
            "frames": f["frames"][()], "instances": f["instances"][()],
            "points": f["points"][()], "pred": f["pred_points"][()],
        }  # fmt: skip


def _raw_track(raw: dict, video: int, track: int | None):
    """Points/scores of one track in one video from the raw tables: a user instance of the
    track is taken before a predicted one (SLEAP's rule), one instance per frame."""
    fr, ins = raw["frames"], raw["instances"]
    n = int(fr["frame_idx"][fr["video"] == video].max()) + 1
    K = len(raw["nodes"])
    pts, sc = np.full((n, K, 2), np.nan), np.full((n, K), np.nan)
    for row in fr[fr["video"] == video]:
        cand = ins[row["instance_id_start"] : row["instance_id_end"]]
        if track is not None:
            cand = cand[cand["track"] == track]
        cand = cand[np.argsort(cand["instance_type"], kind="stable")]  # user (0) first
        if len(cand) == 0:
            continue
        i = cand[0]
        table = raw["points"] if i["instance_type"] == 0 else raw["pred"]
        p = table[i["point_id_start"] : i["point_id_end"]]
        xy = np.stack([p["x"], p["y"]], 1).astype(float)
        xy[~p["visible"].astype(bool)] = np.nan
        pts[row["frame_idx"]] = xy
        if i["instance_type"] == 1:
            sc[row["frame_idx"]] = np.where(np.isfinite(xy[:, 0]), p["score"], np.nan)
    return pts, sc


def _cases():
    for name in READABLE:
        raw = _raw(DATA / name)
        n_videos = int(raw["frames"]["video"].max()) + 1
        for v in range(n_videos):
            for t in raw["tracks"] or [None]:
                yield pytest.param(name, v, t, id=f"{name}-v{v}-{t}")


@pytest.mark.parametrize(("name", "video", "track"), list(_cases()))
def test_slp_reads_as_the_raw_tables_say(name, video, track):
    raw = _raw(DATA / name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracks absent from a view: tested below
        pts, lik, frames, nodes = read_slp(
            DATA / name, individual=track, video=video if n_videos(raw) > 1 else None
        )
    ref, sc = _raw_track(raw, video, raw["tracks"].index(track) if track else None)
    assert nodes == raw["nodes"]
    np.testing.assert_array_equal(pts, ref)
    np.testing.assert_array_equal(frames, np.arange(len(ref)))
    seen = np.isfinite(ref[..., 0])
    expect = np.where(seen, np.clip(np.where(np.isnan(sc), 1.0, sc), 0, 1), np.nan)
    np.testing.assert_array_equal(lik, expect)


def n_videos(raw: dict) -> int:
    return int(raw["frames"]["video"].max()) + 1


@pytest.mark.parametrize("name", READABLE)
def test_slp_agrees_with_sleap_io(name):
    sio = pytest.importorskip("sleap_io")
    labels = sio.load_slp(str(DATA / name))
    names = [t.name for t in labels.tracks] or [None]
    for v, video in enumerate(labels.videos):
        for t in names:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                pts, lik, _, nodes = read_slp(
                    DATA / name, individual=t, video=v if len(labels.videos) > 1 else None
                )
            assert nodes == list(labels.skeletons[0].node_names)
            ref = np.full_like(pts, np.nan)
            for lf in labels.find(video):
                mine = [i for i in lf.instances if (i.track.name if i.track else None) == t]
                users = [i for i in mine if not hasattr(i, "score")]
                if users or mine:
                    ref[lf.frame_idx] = (users or mine)[0].numpy()
            np.testing.assert_array_equal(pts, ref, err_msg=f"video {v} track {t}")


@pytest.mark.parametrize(("name", "words"), REFUSED.items())
def test_several_untracked_instances_per_frame_are_refused(name, words):
    with pytest.raises(ValueError, match=words) as err:
        read_slp(DATA / name)
    assert "track them in SLEAP" in str(err.value) and "\n" not in str(err.value)


def test_track_choice_is_required_and_checked():
    with pytest.raises(ValueError, match=r"several tracks \['female', 'male'\]"):
        read_slp(DATA / "clip.predictions.slp")
    with pytest.raises(ValueError, match=r"no track 'pup'; tracks: \['female', 'male'\]"):
        read_slp(DATA / "clip.predictions.slp", individual="pup")
    with pytest.raises(ValueError, match="no tracks .* cannot be chosen"):
        read_slp(DATA / "small_robot_minimal.slp", individual="track_0")


# -- issue 27 item 3: a track never gets another track's points -------------------------------
def test_a_track_absent_from_a_view_is_nan_with_a_warning():
    # min_session.slp: video 2 (sideL) holds one instance per frame, all of track_0; sleap-io's
    # array export switches to untracked mode there and the old reader raised IndexError
    with pytest.warns(UserWarning, match=r"track 'track_1' has no instance in video 2"):
        pts, lik, _, _ = read_slp(DATA / "min_session.slp", individual="track_1", video=2)
    assert np.isnan(pts).all() and np.isnan(lik).all()
    pts0, _, _, _ = read_slp(DATA / "min_session.slp", individual="track_0", video=2)
    assert np.isfinite(pts0).any()


def _swap_prone(tmp_path: Path) -> Path:
    """min_session.slp with the tracks of video 2 alternating: one instance per frame,
    track_1 in frames 0 and 2, track_0 in frame 1."""
    out = tmp_path / "swap.slp"
    shutil.copy(DATA / "min_session.slp", out)
    with h5py.File(out, "r+") as f:
        fr, ins = f["frames"][()], f["instances"][()]
        for row in fr[fr["video"] == 2]:
            assert row["instance_id_end"] - row["instance_id_start"] == 1
            ins["track"][row["instance_id_start"]] = 0 if row["frame_idx"] == 1 else 1
        f["instances"][...] = ins
    return out


def test_one_instance_per_frame_with_alternating_tracks_is_not_swapped(tmp_path):
    path = _swap_prone(tmp_path)
    raw = _raw(path)
    both, _ = _raw_track(raw, 2, None)  # the only instance of each frame
    p0, _, _, _ = read_slp(path, individual="track_0", video=2)
    p1, _, _, _ = read_slp(path, individual="track_1", video=2)
    np.testing.assert_array_equal(p0[1], both[1])
    assert np.isnan(p0[[0, 2]]).all()
    np.testing.assert_array_equal(p1[[0, 2]], both[[0, 2]])
    assert np.isnan(p1[1]).all()


def test_a_track_without_any_instance_is_one_clear_line(tmp_path):
    out = tmp_path / "absent.slp"
    shutil.copy(DATA / "clip.predictions.slp", out)
    with h5py.File(out, "r+") as f:
        ins = f["instances"][()]
        ins["track"][ins["track"] == 1] = 0
        f["instances"][...] = ins
    with pytest.raises(ValueError) as err:
        read_slp(out, individual="male")
    msg = str(err.value)
    assert "track 'male' has no instance" in msg and "['female']" in msg and "\n" not in msg


# -- issue 27 items 2 and 9 on real files -----------------------------------------------------
def test_real_scores_above_one_are_clipped():
    raw = _raw(DATA / "clip.predictions.slp")
    assert np.nanmax(raw["pred"]["score"]) > 1.7  # sleap-track wrote peaks above 1
    _, lik, _, _ = read_slp(DATA / "clip.predictions.slp", individual="male")
    assert np.nanmax(lik) == 1.0 and np.nanmin(lik) >= 0.0


def test_proofread_user_points_are_certain():
    pts, lik, _, _ = read_slp(DATA / "clip.2node.slp", individual="female")
    seen = np.isfinite(pts[..., 0])
    assert seen.sum() > 1000 and (lik[seen] == 1.0).all() and np.isnan(lik[~seen]).all()


def test_real_analysis_file_with_user_and_predicted_instances():
    # SLEAP's analysis export: frames 0 and 2 user instances (no score), frame 1 predicted
    path = DATA / "small_robot_3_frame.analysis.h5"
    with h5py.File(path, "r") as f:
        tracks, scores = f["tracks"][()], f["point_scores"][()]
    pts, lik, _, nodes = read_sleap_analysis(path)
    assert nodes == ["top", "front", "rear"]
    np.testing.assert_array_equal(pts, tracks[0].transpose(2, 1, 0))
    assert np.isnan(scores[0][:, [0, 2]]).all() and (lik[[0, 2]] == 1.0).all()
    assert scores[0, 1:, 1].max() > 1.0
    np.testing.assert_array_equal(lik[1], np.clip(scores[0, :, 1], 0, 1))


@pytest.mark.parametrize("view", ["mid", "top"])
def test_slp_equals_sleaps_own_analysis_export(view):
    # sleap-anipose's session: SLEAP wrote the .slp and exported its analysis .h5
    a = read_sleap_analysis(SA / f"minimal_{view}_proofread.analysis.h5")
    s = read_slp(SA / f"minimal_{view}_proofread.slp")
    for x, y in zip(a, s, strict=True):
        np.testing.assert_array_equal(x, y)
    with h5py.File(SA / f"minimal_{view}_proofread.analysis.h5", "r") as f:
        assert np.nanmax(f["point_scores"][()]) > 1.0  # clipped in both readers
    assert np.nanmax(a[1]) == 1.0


# -- issue 27 item 12: sleap-anipose's board.toml ---------------------------------------------
def test_sleap_anipose_board_files():
    doc = tomllib.loads((SA / "board.toml").read_text())
    b = BoardSpec.load(SA / "board.toml")
    assert b.board_type == "charuco" and b.squares == (doc["board_x"], doc["board_y"])
    assert b.square_length == doc["square_length"] and b.marker_length == doc["marker_length"]
    assert (b.marker_bits, b.dict_number) == (doc["marker_bits"], doc["dict_size"])
    assert b.board_points.shape == ((doc["board_x"] - 1) * (doc["board_y"] - 1), 3)
    doc = tomllib.loads((SA / "board_checker.toml").read_text())
    c = BoardSpec.load(SA / "board_checker.toml")
    assert c.board_type == "checkerboard" and c.squares == (doc["board_x"], doc["board_y"])
    assert c.square_length == doc["square_length"]
    # round trip through anipose's keys
    assert BoardSpec.from_dict(b.to_dict()) == b and BoardSpec.from_dict(c.to_dict()) == c
    with pytest.raises(ValueError, match="mixes sleap-anipose keys"):
        BoardSpec.from_dict(
            {**tomllib.loads((SA / "board.toml").read_text()), "board_size": [8, 11]}
        )


def test_sleap_anipose_calibration_toml():
    cv2 = pytest.importorskip("cv2")
    doc = tomllib.loads((SA / "calibration.toml").read_text())
    rig = CameraRig.load(SA / "calibration.toml")
    assert rig.names == [doc[f"cam_{i}"]["name"] for i in range(4)]
    rng = np.random.default_rng(0)
    for cam, i in zip(rig, range(4), strict=True):
        t = doc[f"cam_{i}"]
        z = rng.uniform(50, 300, 20)
        xc = np.stack([rng.uniform(-0.4, 0.4, 20) * z, rng.uniform(-0.3, 0.3, 20) * z, z], 1)
        X = (xc - np.array(t["translation"])) @ cam.rotation_matrix
        ref, _ = cv2.projectPoints(X, np.array(t["rotation"]), np.array(t["translation"]),
                                   np.array(t["matrix"]), np.array(t["distortions"]))  # fmt: skip
        assert cam.in_front(X).all()
        np.testing.assert_allclose(cam.project(X), ref[:, 0], atol=1e-9, rtol=0)


# -- issue 27 item 13: multi-camera sessions --------------------------------------------------
@pytest.mark.parametrize("name", SESSIONS)
def test_session_calibration_is_the_embedded_one(name):
    cv2 = pytest.importorskip("cv2")
    with h5py.File(DATA / name, "r") as f:
        doc = json.loads(f["sessions_json"][0])
        videos = [json.loads(v)["backend"]["filename"] for v in f["videos_json"][()]]
    with pytest.warns(UserWarning, match="has no instance of track 'track_1'"):
        sess = read_sleap_session(DATA / name, individual="track_1")
    calib = doc["calibration"]
    keys = [k for k in calib if k != "metadata"]
    assert sess.rig.names == [calib[k]["name"] for k in keys]
    # the same rig as SLEAP's calibration.toml of this session
    toml_rig = CameraRig.load(DATA / "min_session_calibration.toml")
    np.testing.assert_array_equal(sess.rig.get_params(), toml_rig.get_params())
    # each camera's video is the file named after it (min_session_<camera>.mp4)
    for cam, v in zip(sess.rig, sess.videos, strict=True):
        assert videos[v].endswith(f"min_session_{cam.name}.mp4")
    rng = np.random.default_rng(1)
    for cam, k in zip(sess.rig, keys, strict=True):
        t = calib[k]
        # points in the camera's field of view (camera frame -> world)
        z = rng.uniform(200, 800, 30)
        xc = np.stack([rng.uniform(-0.4, 0.4, 30) * z, rng.uniform(-0.3, 0.3, 30) * z, z], 1)
        X = (xc - cam.tvec) @ cam.rotation_matrix
        ref, _ = cv2.projectPoints(X, np.array(t["rotation"]), np.array(t["translation"]),
                                   np.array(t["matrix"]), np.array(t["distortions"]))  # fmt: skip
        assert cam.in_front(X).all()
        np.testing.assert_allclose(cam.project(X), ref[:, 0], atol=1e-9, rtol=0)
    # per-view tracks: the single-view reader on each camera's video
    for c, v in enumerate(sess.videos):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pts, lik, _, nodes = read_slp(DATA / name, individual="track_1", video=v)
        np.testing.assert_array_equal(sess.labels.points[c, : len(pts)], pts)
        np.testing.assert_array_equal(sess.labels.likelihood[c, : len(pts)], lik)
        assert nodes == sess.labels.bodyparts
    assert "8 cameras" in sess.summary() and "track 'track_1'" in sess.summary()


def test_session_instance_groups_must_agree_with_tracks(tmp_path):
    sess = read_sleap_session(DATA / "min_session_frame_groups.slp", individual="track_0")
    assert sess.n_groups == 6
    out = tmp_path / "mixed.slp"
    shutil.copy(DATA / "min_session_frame_groups.slp", out)
    with h5py.File(out, "r+") as f:
        doc = json.loads(f["sessions_json"][0])
        members = doc["frame_group_dicts"][0]["instance_groups"][0][
            "camcorder_to_lf_and_inst_idx_map"
        ]
        other = doc["frame_group_dicts"][0]["instance_groups"][1][
            "camcorder_to_lf_and_inst_idx_map"
        ]
        members["0"] = other["0"]  # camera back: link the other animal
        del f["sessions_json"]
        f["sessions_json"] = np.array([json.dumps(doc).encode()])
    with pytest.raises(ValueError, match="links instances of different tracks") as err:
        read_sleap_session(out, individual="track_0")
    assert "back: track_1" in str(err.value)


def test_session_files_without_a_session_are_refused():
    with pytest.raises(ValueError, match="no recording session"):
        read_sleap_session(DATA / "clip.predictions.slp", individual="male")


def test_session_views_round_trip(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        files = write_session_views(DATA / "min_session_frame_groups.slp", tmp_path)
        for t in ("track_0", "track_1"):
            sess = read_sleap_session(DATA / "min_session_frame_groups.slp", individual=t)
            for c, f in enumerate(files):
                pts, lik, _, nodes = read_sleap_analysis(f, individual=t)
                np.testing.assert_array_equal(pts, sess.labels.points[c])
                np.testing.assert_array_equal(lik, sess.labels.likelihood[c])
    with h5py.File(files[0], "r") as f:  # SLEAP's layout, read back with h5py
        assert f["tracks"].shape == (2, 2, 15, 3)
        assert [n.decode() for n in f["track_names"][()]] == ["track_0", "track_1"]


def test_session_written_by_sleap_io_columnar_format(tmp_path):
    sio = pytest.importorskip("sleap_io")
    labels = sio.load_slp(str(DATA / "min_session_frame_groups.slp"))
    out = tmp_path / "resaved.slp"
    sio.save_slp(labels, str(out))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = read_sleap_session(DATA / "min_session_frame_groups.slp", individual="track_1")
        b = read_sleap_session(out, individual="track_1")
    np.testing.assert_array_equal(a.rig.get_params(), b.rig.get_params())
    np.testing.assert_array_equal(a.labels.points, b.labels.points)
    assert b.n_groups == a.n_groups == 6


def test_cli_init_from_a_sleap_session(tmp_path, capsys):
    from acm_rs.cli import main
    from acm_rs.dlc import read_labels
    from acm_rs.project import find_sessions, load_config

    root = tmp_path / "proj"
    argv = ["init", str(root), "--fps", "30", "--from-sleap-session",
            str(DATA / "min_session.slp")]  # fmt: skip
    assert main(argv) == 1
    assert "several tracks" in capsys.readouterr().err
    with pytest.warns(UserWarning, match="no instance of track 'track_1'"):
        assert main(argv + ["--individual", "track_1"]) == 0
    out = capsys.readouterr().out
    assert "8 cameras" in out and "track 'track_1'" in out
    cfg = load_config(root)
    (session,) = find_sessions(cfg)
    assert session.cameras == ["back", "backL", "mid", "midL", "side", "sideL", "top", "topL"]
    rig = CameraRig.load(session.calibration)
    np.testing.assert_array_equal(
        rig.get_params(), CameraRig.load(DATA / "min_session_calibration.toml").get_params()
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sess = read_sleap_session(DATA / "min_session.slp", individual="track_1")
    lab = read_labels([session.labels[c] for c in session.cameras], cfg.project["individual"])
    np.testing.assert_array_equal(lab.points, sess.labels.points)
