"""Project config: init writes a commented, valid config; load_config explains mistakes."""

from __future__ import annotations

import pytest

from acm_rs import project as pj


def test_init_then_load_defaults(tmp_path):
    path = pj.init_project(tmp_path / "proj")
    text = path.read_text()
    assert text.startswith("# acm-rs project configuration")
    assert "# anipose calibration.toml" in text and "# body_weight = ..." in text
    cfg = pj.load_config(tmp_path / "proj")
    assert cfg.root == (tmp_path / "proj").resolve()
    assert cfg.project["model"] == "rat" and cfg.project["body_weight"] is None
    assert cfg.tracking["pcutoff"] == "auto" and cfg.em == {"max_iter": 100, "tol": 0.05}
    board = cfg.board()
    assert board["board_type"] == "charuco" and board["board_size"] == [10, 7]
    assert board["legacy_pattern"] is False and board["board_marker_dict_number"] == 50
    with pytest.raises(FileExistsError, match="overwrite=True"):
        pj.init_project(tmp_path / "proj")
    pj.init_project(tmp_path / "proj", overwrite=True, project={"model": "mouse"})
    assert pj.load_config(tmp_path / "proj").project["model"] == "mouse"


def test_init_rejects_bad_override(tmp_path):
    with pytest.raises(ValueError, match=r"tracking.pcutoff = 2 is invalid"):
        pj.init_project(tmp_path, tracking={"pcutoff": 2})
    assert not (tmp_path / "config.toml").exists()


def _edit(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


@pytest.mark.parametrize(
    "old, new, match",
    [
        (
            'pcutoff = "auto"',
            "pcutof = 0.9",
            r"unknown key tracking.pcutof; did you mean 'pcutoff'\?",
        ),
        ("[em]", "[emm]", r"unknown section \[emm\]; did you mean 'em'\?"),
        ("max_iter = 100", "max_iter = 1.5", r"em.max_iter must be an integer, got float 1.5"),
        (
            'pcutoff = "auto"',
            'pcutoff = "high"',
            r"tracking.pcutoff = 'high' is invalid: expected a likelihood in \[0, 1\] or \"auto\"",
        ),
        ('pcutoff = "auto"', "pcutoff = true", r"tracking.pcutoff must be"),
        ("legacy_pattern = false", "legacy_pattern = 0", r"legacy_pattern must be true/false"),
        ("max_iter = 100", "max_iter = true", r"em.max_iter must be an integer, got bool"),
        ("board_size = [10, 7]", "board_size = [10]", r"board_size = \[10\] is invalid: expected"),
        ('regex = "', 'regex = "(', r"cameras.regex = .* is invalid"),
        ('pcutoff = "auto"', "pcutoff = 0.9\npcutoff = 0.8", r"invalid TOML"),
    ],
)
def test_load_config_messages(tmp_path, old, new, match):
    path = pj.init_project(tmp_path)
    _edit(path, old, new)
    with pytest.raises(ValueError, match=match):
        pj.load_config(path)


def test_load_config_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="acm-rs init"):
        pj.load_config(tmp_path)


def test_int_accepted_for_float(tmp_path):
    path = pj.init_project(tmp_path)
    _edit(path, "tol = 0.05", "tol = 1")
    cfg = pj.load_config(path)
    assert cfg.em["tol"] == 1.0 and isinstance(cfg.em["tol"], float)


# -- sessions -------------------------------------------------------------------------------------
def _touch(folder, *names):
    folder.mkdir(parents=True, exist_ok=True)
    for n in names:
        (folder / n).write_bytes(b"")


@pytest.fixture
def project(tmp_path):
    pj.init_project(tmp_path)
    for s in ("s01", "s02"):
        _touch(tmp_path / s / "videos", "rat-camA.mp4", "rat-camB.mp4", "notes.txt")
        _touch(
            tmp_path / s / "pose-2d",
            "rat-camADLC_resnet50_x.h5",
            "rat-camADLC_resnet50_x.csv",
            "rat-camBDLC_resnet50_x.h5",
        )
    _touch(tmp_path / "calibration", "calibration.toml")
    _touch(tmp_path / "s02" / "calibration", "calibration.toml")
    _touch(tmp_path / "unrelated")
    return tmp_path


def test_find_sessions(project):
    cfg = pj.load_config(project)
    sessions = pj.find_sessions(cfg)
    assert [s.name for s in sessions] == ["s01", "s02"]
    s1, s2 = sessions
    assert s1.cameras == ["camA", "camB"]  # the default regex keeps the whole name
    assert s1.videos["camB"].name == "rat-camB.mp4"
    assert s1.labels["camA"].name == "rat-camADLC_resnet50_x.h5"  # .h5 preferred over .csv
    assert s1.calibration == cfg.root / "calibration" / "calibration.toml"
    assert s2.calibration == s2.path / "calibration" / "calibration.toml"
    assert s1.output == s1.path / "acm-rs"


def test_camera_names_order_and_missing(project):
    path = project / "config.toml"
    _edit(path, "names = []", 'names = ["camB", "camA"]')
    assert pj.find_sessions(pj.load_config(path))[0].cameras == ["camB", "camA"]
    _edit(path, 'names = ["camB", "camA"]', 'names = ["camB", "camA", "camC"]')
    with pytest.raises(
        ValueError, match=r"camera 'camC' \(cameras.names\) matches no file.*\['camA', 'camB'\]"
    ):
        pj.find_sessions(pj.load_config(path))
    _edit(path, 'names = ["camB", "camA", "camC"]', 'names = ["camA"]')
    with pytest.raises(ValueError, match=r"rat-camB.mp4 is camera 'camB', which is not in"):
        pj.find_sessions(pj.load_config(path))


def test_session_errors(project, tmp_path):
    _touch(project / "s01" / "videos", "overview.mp4")
    with pytest.raises(ValueError, match=r"overview.mp4: no camera name matches cameras.regex"):
        pj.find_sessions(pj.load_config(project))
    (project / "s01" / "videos" / "overview.mp4").unlink()
    _touch(project / "s01" / "videos", "rat-camC.mp4")
    with pytest.raises(ValueError, match=r"videos name cameras \['camA', 'camB', 'camC'\] but"):
        pj.find_sessions(pj.load_config(project))
    _touch(project / "s01" / "videos", "rat2-camC.avi")
    with pytest.raises(ValueError, match="two files for camera 'camC'"):
        pj.find_sessions(pj.load_config(project))
    empty = tmp_path / "empty"
    pj.init_project(empty)
    with pytest.raises(FileNotFoundError, match="no sessions"):
        pj.find_sessions(pj.load_config(empty))


def test_init_subcommand(tmp_path, capsys):
    import argparse

    parser = argparse.ArgumentParser()
    pj.add_subcommands(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["init", str(tmp_path / "p"), "--model", "mouse"])
    with pytest.raises(ValueError, match="no video with a frame rate.*--fps HZ"):
        args.func(args)  # nothing to read the frame rate from: it must be given
    args = parser.parse_args(["init", str(tmp_path / "p"), "--model", "mouse", "--fps", "100"])
    assert args.func(args) == 0
    assert "wrote" in capsys.readouterr().out
    cfg = pj.load_config(tmp_path / "p")
    assert cfg.project["model"] == "mouse" and cfg.tracking["fps"] == 100.0
    args = parser.parse_args(["init", str(tmp_path / "p"), "--fps", "100"])
    with pytest.raises(FileExistsError):
        args.func(args)
