"""Real DeepLabCut and anipose files (tests/data/real/dlc, tests/data/real/anipose): what acm-rs
reads is compared with independent readers (pandas, the csv module, tomllib, aniposelib,
OpenCV), and what it writes is read back. Provenance: each folder's PROVENANCE.md.

Issue 27 items 7 (DLC-3D camera names), 8 (empty first CSV row, 3D files), 11 (anipose
projects, crop offsets) and 15 (the [metadata] table of calibration.toml).
"""

from __future__ import annotations

import csv
import re
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pytest

from acm_rs.camera import CameraRig
from acm_rs.dlc import read_dlc_table, read_labels, shift_labels
from acm_rs.project import (
    dlc_bodyparts,
    find_sessions,
    init_project,
    load_config,
    read_dlc_config,
    rig_for_files,
)

pd = pytest.importorskip("pandas")

REAL = Path(__file__).parent / "data" / "real"
DLC = REAL / "dlc"
ANIPOSE = REAL / "anipose"
PRED = "m3v1mp4shortDLC_effnet_b0_multi_mouseApr12shuffle1_5_el_filtered"
# (stem, individuals to read: None for single-animal files)
DLC_FILES = [
    ("CollectedData_Mackenzie", [None]),  # single animal, index: one column of image paths
    ("CollectedData_shaokai", [None]),  # single animal, index: 3 columns
    ("CollectedData_dlc_team", ["individual1", "individual3", "single"]),  # multi, 3 columns
    (PRED, ["individual1", "individual2", "individual3"]),  # multi predictions, frame numbers
]
CALIBRATIONS = sorted(ANIPOSE.glob("*_calibration.toml"))


# -- independent readers ---------------------------------------------------------------------------
def _csv_reference(path: Path, individual: str | None):
    """The csv module's reading of a DeepLabCut CSV: (points, likelihood, frames, bodyparts)."""
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    multi = rows[1][0] == "individuals"
    head = rows[:4] if multi else rows[:3]
    body = rows[len(head) :]
    coords = head[-1]
    n_index = next(i for i, v in enumerate(coords) if v in ("x", "y", "likelihood"))
    cols = {}
    for j in range(n_index, len(coords)):
        ind = head[1][j] if multi else None
        if ind != individual:
            continue
        cols[(head[-2][j], coords[j])] = j
    bodyparts = list(dict.fromkeys(bp for bp, _ in cols))

    def num(v):
        return float(v) if v != "" else np.nan

    pts = np.array([[[num(r[cols[(bp, c)]]) for c in "xy"] for bp in bodyparts] for r in body])
    lik = None
    if (bodyparts[0], "likelihood") in cols:
        lik = np.array([[num(r[cols[(bp, "likelihood")]]) for bp in bodyparts] for r in body])
    frames = np.array([int(re.findall(r"\d+", r[n_index - 1])[-1]) for r in body])
    return pts, lik, frames, bodyparts


def _h5_reference(path: Path, individual: str | None):
    """pandas' reading of a DeepLabCut .h5 (PyTables): the same four arrays."""
    pytest.importorskip("tables")
    df = pd.read_hdf(path)
    if df.columns.nlevels == 4:
        df = df.xs(individual, axis=1, level="individuals")
    df.columns = df.columns.droplevel("scorer")  # one scorer per file
    bodyparts = list(dict.fromkeys(df.columns.get_level_values("bodyparts")))
    pts = np.stack([df[[(bp, "x"), (bp, "y")]].to_numpy() for bp in bodyparts], axis=1)
    lik = None
    if "likelihood" in set(df.columns.get_level_values("coords")):
        lik = np.stack([df[(bp, "likelihood")].to_numpy() for bp in bodyparts], axis=1)
    labels = [i[-1] if isinstance(i, tuple) else i for i in df.index]
    frames = np.array([i if isinstance(i, int | np.integer) else
                       int(re.findall(r"\d+", str(i))[-1]) for i in labels])  # fmt: skip
    return pts, lik, frames, bodyparts


def _same(got, want):
    pts, lik, frames, bps = got
    assert bps == want[3]
    np.testing.assert_array_equal(frames, want[2])
    np.testing.assert_array_equal(pts, want[0])  # exact: the same decimal text / float64
    if want[1] is None:
        assert lik is None
    else:
        np.testing.assert_array_equal(lik, want[1])


# -- DeepLabCut files ------------------------------------------------------------------------------
@pytest.mark.parametrize("stem,individuals", DLC_FILES)
def test_dlc_csv_and_h5_read_exactly(stem, individuals):
    for ind in individuals:
        csv_read = read_dlc_table(DLC / f"{stem}.csv", individual=ind)
        _same(csv_read, _csv_reference(DLC / f"{stem}.csv", ind))
        h5_read = read_dlc_table(DLC / f"{stem}.h5", individual=ind)
        _same(h5_read, _h5_reference(DLC / f"{stem}.h5", ind))
        _same(csv_read, h5_read)  # DeepLabCut wrote both from one DataFrame


@pytest.mark.parametrize("ext", ["csv", "h5"])
def test_dlc_multi_animal_without_individual_is_refused(ext):
    if ext == "h5":
        pytest.importorskip("tables")
    with pytest.raises(ValueError, match=r"several individuals \['individual1', 'individual2', "
                       r"'individual3'\]; choose one"):  # fmt: skip
        read_dlc_table(DLC / f"CollectedData_dlc_team.{ext}")


def test_dlc_config_yaml_matches_the_labels(tmp_path):
    yaml = pytest.importorskip("yaml")
    shutil.copy(DLC / "config_multi_mouse.yaml", tmp_path / "config.yaml")
    doc = read_dlc_config(tmp_path)  # a DeepLabCut project folder
    ref = yaml.safe_load((DLC / "config_multi_mouse.yaml").read_text())
    assert doc == ref
    assert dlc_bodyparts(doc) == ref["multianimalbodyparts"] + ref["uniquebodyparts"]
    labelled = read_dlc_table(DLC / "CollectedData_dlc_team.csv", "individual1")[3]
    unique = read_dlc_table(DLC / "CollectedData_dlc_team.csv", "single")[3]
    assert labelled + unique == dlc_bodyparts(doc)


def _blank_first_row(src: Path, dst: Path) -> int:
    """DeepLabCut's writer (DataFrame.to_csv) on the real table with an empty first frame."""
    pytest.importorskip("tables")
    df = pd.read_hdf(src)
    df.iloc[0] = np.nan
    df.to_csv(dst)
    return len(df)


@pytest.mark.parametrize("stem,individual", [
    ("CollectedData_Mackenzie", None), ("CollectedData_dlc_team", "individual2"),
    (PRED, "individual3"),
])  # fmt: skip
def test_dlc_csv_with_an_empty_first_row_keeps_every_frame(tmp_path, stem, individual):
    path = tmp_path / f"{stem}.csv"
    n = _blank_first_row(DLC / f"{stem}.h5", path)
    pts, lik, frames, bps = read_dlc_table(path, individual=individual)
    ref = read_dlc_table(DLC / f"{stem}.h5", individual=individual)
    assert len(frames) == n  # pandas' multi-row header read gives n - 1
    np.testing.assert_array_equal(frames, ref[2])  # no frame shifted
    assert np.isnan(pts[0]).all()
    np.testing.assert_array_equal(pts[1:], ref[0][1:])
    assert bps == ref[3]
    # the csv module agrees
    _same((pts, lik, frames, bps), _csv_reference(path, individual))


def test_dlc_csv_header_only_and_index_names_row(tmp_path):
    src = (DLC / "CollectedData_Mackenzie.csv").read_text().splitlines()
    # a named index: pandas writes a row of index names after the header; it is not a frame
    named = tmp_path / "named.csv"
    named.write_text("\n".join(src[:3] + ["image" + "," * 10] + src[3:]) + "\n")
    got = read_dlc_table(named)
    _same(got, read_dlc_table(DLC / "CollectedData_Mackenzie.csv"))


def _dlc3d_frame():
    cols = pd.MultiIndex.from_product(
        [["DLC_resnet50_3D"], ["snout", "tail"], ["x", "y", "z"]],
        names=["scorer", "bodyparts", "coords"],
    )
    return pd.DataFrame(np.arange(12.0).reshape(2, 6), columns=cols)


@pytest.mark.parametrize("ext", ["csv", "h5"])
def test_dlc_3d_file_is_refused_where_2d_is_expected(tmp_path, ext):
    path = tmp_path / f"vid1_DLC_3D.{ext}"
    df = _dlc3d_frame()
    if ext == "h5":
        pytest.importorskip("tables")
        df.to_hdf(path, key="df_with_missing", format="table")
    else:
        df.to_csv(path)
    with pytest.raises(ValueError, match=r"a 3D file \(coords x, y, z.*2D predictions"):
        read_dlc_table(path)


# -- camera names (item 7) -------------------------------------------------------------------------
def _two_camera_calibration(tmp_path: Path, names=("camera-1", "camera-2")) -> Path:
    rig = CameraRig.load(ANIPOSE / "allen7_calibration.toml")
    cams = [rig[i] for i in range(2)]
    for c, n in zip(cams, names, strict=True):
        c.name = n
    path = tmp_path / "calibration.toml"
    CameraRig(cams).save(path)
    return path


def _dlc3d_named_files(tmp_path: Path) -> list[Path]:
    """DeepLabCut 3D's 2D outputs: <video>DLC_<network>.h5 of videos vid1_camera-1, -2."""
    out = []
    for cam, ind in (("camera-1", "individual1"), ("camera-2", "individual2")):
        p = tmp_path / f"vid1_{cam}DLC_resnet50_3dtestJan1shuffle1_5.csv"
        df = pd.read_csv(DLC / f"{PRED}.csv", header=[0, 1, 2, 3], index_col=0)
        df.xs(ind, axis=1, level="individuals", drop_level=False).to_csv(p)
        out.append(p)
    return out


def test_dlc3d_camera_names_match_the_calibration_in_any_order(tmp_path):
    calib = _two_camera_calibration(tmp_path)
    files = _dlc3d_named_files(tmp_path)
    rig, table = rig_for_files(calib, files)
    assert rig.names == ["camera-1", "camera-2"]
    rig_rev, table_rev = rig_for_files(calib, files[::-1])
    assert rig_rev.names == ["camera-2", "camera-1"]  # by name, never by order
    np.testing.assert_array_equal(rig_rev[0].params, rig[1].params)
    assert "camera-2" in table_rev.splitlines()[1]


def test_names_a_regex_maps_to_one_camera_are_refused(tmp_path):
    calib = _two_camera_calibration(tmp_path)
    files = _dlc3d_named_files(tmp_path)
    # the former default regex takes "camera" from both names
    with pytest.raises(ValueError, match=r"do not give one camera each.*vid1_camera-1DLC.*"
                       r"-> 'camera', .*--cam-regex"):  # fmt: skip
        rig_for_files(calib, files, regex=r"(?i)cam[-_]?[a-z0-9]+")
    # the same in a project session: named, not "two files from different analyses"
    root = tmp_path / "proj"
    init_project(root, cameras={"regex": r"(?i)cam[-_]?[a-z0-9]+"}, tracking={"fps": 50.0})
    (root / "s1" / "pose-2d").mkdir(parents=True)
    for f in files:
        shutil.copy(f, root / "s1" / "pose-2d" / f.name)
    with pytest.raises(ValueError, match=r"two files for camera 'camera' by cameras.regex .*"
                       r"if they are different cameras, change cameras.regex"):  # fmt: skip
        find_sessions(load_config(root))
    init_project(root, overwrite=True, tracking={"fps": 50.0})  # the default regex
    (s,) = find_sessions(load_config(root))
    assert s.cameras == ["camera-1", "camera-2"]


def test_files_without_camera_names_are_said_to_go_in_calibration_order(tmp_path):
    calib = _two_camera_calibration(tmp_path)
    files = [tmp_path / "left.csv", tmp_path / "right.csv"]
    with pytest.warns(UserWarning, match=r"taken in the calibration's order \['camera-1', "
                      r"'camera-2'\]; give --camera-names"):  # fmt: skip
        rig, table = rig_for_files(calib, files)
    assert table is None


# -- anipose calibration files (item 15) ----------------------------------------------------------
@pytest.mark.parametrize("path", CALIBRATIONS, ids=lambda p: p.name)
def test_anipose_calibration_reads_exactly_and_projects_as_opencv(path):
    cv2 = pytest.importorskip("cv2")
    doc = tomllib.loads(path.read_text())
    rig = CameraRig.load(path)
    tables = sorted((k for k in doc if k.startswith("cam_")), key=lambda k: int(k[4:]))
    assert rig.names == [doc[k]["name"] for k in tables]
    rng = np.random.default_rng(0)
    for cam, k in zip(rig, tables, strict=True):
        t = doc[k]
        np.testing.assert_array_equal(cam.matrix, t["matrix"])
        np.testing.assert_array_equal(cam.dist, t["distortions"])
        np.testing.assert_array_equal(cam.rvec, t["rotation"])
        np.testing.assert_array_equal(cam.tvec, t["translation"])
        assert list(cam.size) == t["size"]
        # points in front of the camera, spread over its view
        depth = np.linalg.norm(t["translation"]) + 1.0
        uv = rng.uniform(0.1, 0.9, (200, 2)) * t["size"]
        ray = np.c_[(uv - cam.matrix[:2, 2]) / np.diag(cam.matrix)[:2], np.ones(200)]
        pts = (ray * depth * rng.uniform(0.5, 1.5, (200, 1)) - cam.tvec) @ cam.rotation_matrix
        ref, _ = cv2.projectPoints(pts, cam.rvec, cam.tvec, cam.matrix, cam.dist)
        np.testing.assert_allclose(cam.project(pts), ref[:, 0], rtol=0, atol=1e-9)


@pytest.mark.parametrize("path", CALIBRATIONS, ids=lambda p: p.name)
def test_anipose_calibration_round_trip_keeps_metadata(tmp_path, path):
    doc = tomllib.loads(path.read_text())
    rig = CameraRig.load(path)
    out = tmp_path / "calibration.toml"
    rig.save(out)
    back = CameraRig.load(out)
    np.testing.assert_array_equal(back.get_params(), rig.get_params())
    assert back.names == rig.names and [c.size for c in back] == [c.size for c in rig]
    written = tomllib.loads(out.read_text())
    assert written["metadata"] == doc["metadata"]  # adjusted, error; an empty table stays
    for k in doc:
        if k.startswith("cam_"):
            assert written[k] == doc[k]
    # aniposelib reads what acm-rs writes (it orders cam_10 before cam_2: compare by name)
    aniposelib = pytest.importorskip("aniposelib")
    group = aniposelib.cameras.CameraGroup.load(str(out))
    assert group.metadata == doc["metadata"]
    by_name = {c.get_name(): c for c in group.cameras}
    for cam in rig:
        np.testing.assert_array_equal(by_name[cam.name].get_camera_matrix(), cam.matrix)


def test_units_and_metadata_together(tmp_path):
    rig = CameraRig.load(ANIPOSE / "allen7_calibration.toml")
    mm = rig.scaled(1.0, units="mm")
    mm.save(tmp_path / "c.toml", metadata={"note": "x"})
    meta = tomllib.loads((tmp_path / "c.toml").read_text())["metadata"]
    assert meta == {"adjusted": True, "error": 1.6680509250648916, "units": "mm", "note": "x"}
    back = CameraRig.load(tmp_path / "c.toml")
    assert back.units == "mm" and back.metadata == {
        "adjusted": True,
        "error": 1.6680509250648916,
        "note": "x",
    }


def test_fisheye_camera_is_refused(tmp_path):
    text = (ANIPOSE / "motobs7_calibration.toml").read_text()
    bad = tmp_path / "fish.toml"
    bad.write_text(text.replace('name = "cam088"', 'name = "cam088"\nfisheye = true', 1))
    with pytest.raises(ValueError, match=r"\[cam_0\]: fisheye = true.*does not support"):
        CameraRig.load(bad)


# -- anipose project config (item 11) --------------------------------------------------------------
@pytest.mark.parametrize("name", ["allen7_config.toml", "flypose_config.toml"])
def test_anipose_config_is_read(name):
    doc = tomllib.loads((ANIPOSE / name).read_text())
    cfg = load_config(ANIPOSE / name)
    tri, cal, pipe = doc["triangulation"], doc["calibration"], doc.get("pipeline", {})
    assert cfg.cameras["regex"] == tri["cam_regex"]
    for k in ("board_type", "board_size", "board_marker_bits", "board_marker_dict_number",
              "board_marker_length", "board_square_side_length"):  # fmt: skip
        assert cfg.calibration[k] == cal[k]
    assert cfg.paths["videos"] == pipe.get("videos_raw", "videos-raw")
    assert cfg.paths["labels"] == pipe.get("pose_2d", "pose-2d")
    assert cfg.paths["calibration"] == pipe.get("calibration_results", "calibration") + (
        "/calibration.toml"
    )
    assert cfg.crop_offsets == {
        n: (float(t["offset"][0]), float(t["offset"][1])) for n, t in doc["cameras"].items()
    }
    assert cfg.anipose["constraints"] == [tuple(c) for c in tri.get("constraints", [])]
    assert cfg.anipose["constraints_weak"] == [tuple(c) for c in tri.get("constraints_weak", [])]
    assert cfg.anipose["nesting"] == doc["nesting"]


def _anipose_project(tmp_path: Path, extra: str = "") -> Path:
    root = tmp_path / "anipose_proj"
    root.mkdir()
    (root / "config.toml").write_text((ANIPOSE / "allen7_config.toml").read_text() + extra)
    (root / "calibration-videos").mkdir()
    shutil.copy(
        ANIPOSE / "allen7_calibration.toml", root / "calibration-videos" / "calibration.toml"
    )
    return root


def _dlc_frame(points: np.ndarray, bodyparts: list[str]):
    cols = pd.MultiIndex.from_product([["DLC_resnet50_mouseJan1shuffle1_5"], bodyparts,
                                       ["x", "y", "likelihood"]],
                                      names=["scorer", "bodyparts", "coords"])  # fmt: skip
    data = np.concatenate([points, np.ones(points.shape[:2] + (1,))], axis=2)
    return pd.DataFrame(data.reshape(len(points), -1), columns=cols)


def test_anipose_crop_offsets_shift_points_into_the_calibrated_image(tmp_path, monkeypatch):
    root = _anipose_project(tmp_path)
    cfg = load_config(root)
    rig = CameraRig.load(root / "calibration-videos" / "calibration.toml")
    world = np.random.default_rng(1).normal(0.0, 20.0, (6, 2, 3))  # 6 frames, 2 body parts
    (root / "pose-2d").mkdir()
    for cam in rig:
        full = cam.project(world)  # pixels of the full (calibrated) image
        ox, oy = cfg.crop_offsets[cam.name]
        cropped = full - [ox, oy]  # what DeepLabCut finds in the cropped video
        _dlc_frame(cropped, ["nose", "tail"]).to_csv(root / "pose-2d" / f"rec1_{cam.name}_v.csv")
    (session,) = find_sessions(cfg)  # nesting = 0: the project folder is the session
    assert session.cameras == sorted(rig.names)
    ls = read_labels([session.labels[c] for c in session.cameras])
    shifted = shift_labels(ls, cfg.offsets_for(session.cameras))
    want = CameraRig.load(root / "calibration-videos" / "calibration.toml",
                          names=session.cameras).project(world)  # fmt: skip
    np.testing.assert_allclose(shifted.points, want, rtol=0, atol=1e-9)
    assert not np.allclose(ls.points, want)  # unshifted points are 120, 140 px off
    # the project's track step tracks the shifted points
    import acm_rs.pipeline as pipeline
    import acm_rs.tracking as tracking

    seen = {}

    class Stop(Exception):
        pass

    def fake_track(rig_, skeleton, points, **kw):
        seen["points"], seen["names"] = points, rig_.names
        raise Stop

    monkeypatch.setattr(tracking, "track", fake_track)
    with pytest.raises(Stop):
        pipeline.step_track(cfg, session, overwrite=True)
    np.testing.assert_allclose(seen["points"], want, rtol=0, atol=1e-9)
    assert seen["names"] == session.cameras


@pytest.mark.parametrize("edit,message", [
    ("nesting = 0", "nesting = 2"),
    ('board_type = "charuco"', "board_type = \"aruco\""),
    ("offset = [ 120, 140, 1200, 800,]", "offset = [ 120,]"),
])  # fmt: skip
def test_anipose_config_refusals(tmp_path, edit, message):
    root = _anipose_project(tmp_path)
    text = (root / "config.toml").read_text()
    (root / "config.toml").write_text(text.replace(edit, message, 1))
    want = {
        "nesting": r"anipose nesting = 2: .*move the session folders",
        "board_type": r"board_type 'aruco': .*anipose calibrate",
        "offset": r"cameras.cam088.offset must be \[x, y\] or \[x, y, width, height\]",
    }
    with pytest.raises(ValueError, match=want[message.split(" ")[0]]):
        load_config(root)


def test_anipose_config_takes_acm_rs_settings_and_is_never_overwritten(tmp_path):
    from acm_rs.cli import main

    root = _anipose_project(tmp_path, '\n[acm_rs.project]\nmodel = "mouse"\n'
                                      "[acm_rs.tracking]\npcutoff = 0.6\n")  # fmt: skip
    cfg = load_config(root)
    assert cfg.project["model"] == "mouse" and cfg.tracking["pcutoff"] == 0.6
    before = (root / "config.toml").read_text()
    with pytest.raises(FileExistsError, match=r"anipose project's config.*\[acm_rs.<section>\]"):
        init_project(root, overwrite=True)
    assert main(["init", str(root), "--overwrite", "--fps", "30"]) == 1
    assert (root / "config.toml").read_text() == before
    (root / "config.toml").write_text(before.replace("pcutoff = 0.6", "pcutof = 0.6"))
    with pytest.raises(ValueError, match=r"unknown key tracking.pcutof; did you mean 'pcutoff'"):
        load_config(root)
