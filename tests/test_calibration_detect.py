"""Board detection on rendered images, the detection cache and ``acm-rs calibrate``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from calib_synthetic import render_views

import acm_rs
from acm_rs.calibration import BoardSpec, detect, detect_board
from acm_rs.calibration import detection as detect_mod
from acm_rs.cli import main

CHECKER = BoardSpec("checkerboard", (9, 6), 30.0)
CHARUCO = BoardSpec("charuco", (7, 5), 30.0, 22.0, 4, 50)


def _write_images(rendered, root):
    import cv2

    dirs = []
    for i, frames in enumerate(rendered.images):
        d = root / f"cam{i}"
        d.mkdir()
        for f, img in enumerate(frames):
            cv2.imwrite(str(d / f"frame{f}.png"), img)
        dirs.append(d)
    return dirs


@pytest.mark.parametrize("spec", [CHECKER, CHARUCO], ids=["checkerboard", "charuco"])
def test_detects_rendered_boards_at_the_true_corners(spec):
    rendered = render_views(spec, n_cams=2, n_frames=4, seed=2)
    found = 0
    for i in range(2):
        for f in range(4):
            got = detect_board(rendered.images[i][f], spec)
            ok = np.isfinite(got[:, 0])
            if not ok.any():
                continue
            found += 1
            err = np.linalg.norm(got[ok] - rendered.pixels[i, f, ok], axis=1)
            assert np.median(err) < 0.4 and err.max() < 1.5, (i, f, err.max())
    assert found >= 6


def test_board_spec_toml_and_errors(tmp_path):
    p = tmp_path / "board.toml"
    p.write_text(
        'board_type = "charuco"\nboard_size = [7, 5]\nboard_square_side_length = 30.0\n'
        "board_marker_length = 22.0\nboard_marker_bits = 4\nboard_marker_dict_number = 50\n"
        "legacy_pattern = true\n"
    )
    spec = BoardSpec.load(p)
    assert spec.legacy_pattern and spec.cv_board().getLegacyPattern()
    assert spec.board_points.shape == (24, 3)
    assert BoardSpec.from_dict(spec.to_dict()) == spec
    # anipose config.toml: keys inside [calibration]
    q = tmp_path / "config.toml"
    q.write_text(
        '[calibration]\nboard_type = "checkerboard"\nboard_size = [9, 6]\n'
        "board_square_side_length = 25\n"
    )
    cb = BoardSpec.load(q)
    assert cb.board_points.shape == (40, 3) and cb.board_points[1, 0] == 25.0
    with pytest.raises(ValueError, match="board_marker_length"):
        BoardSpec("charuco", (7, 5), 30.0)
    with pytest.raises(ValueError, match="only 50"):
        BoardSpec("charuco", (12, 12), 30.0, 20.0, 4, 50)
    with pytest.raises(ValueError, match="board_type"):
        BoardSpec("circles", (7, 5), 30.0)
    with pytest.raises(ValueError, match="unknown ArUco dictionary"):
        BoardSpec("charuco", (7, 5), 30.0, 20.0, 9, 50)


def test_zero_boards_message_names_what_to_check(tmp_path):
    rendered = render_views(CHARUCO, n_cams=2, n_frames=2, seed=1)
    dirs = _write_images(rendered, tmp_path)
    wrong_dict = BoardSpec("charuco", (7, 5), 30.0, 22.0, 5, 50)
    with pytest.raises(ValueError, match="0 boards detected.*dictionary.*legacy_pattern"):
        detect(dirs, wrong_dict, progress=False)
    with pytest.raises(ValueError, match="0 boards detected.*board_size"):
        detect(dirs, BoardSpec("checkerboard", (9, 7), 30.0), progress=False)


def test_images_to_calibration_cli_with_cache(tmp_path, monkeypatch, capsys):
    rendered = render_views(CHECKER, n_cams=3, n_frames=10, seed=4)
    dirs = _write_images(rendered, tmp_path)
    board = tmp_path / "board.toml"
    board.write_text(
        'board_type = "checkerboard"\nboard_size = [9, 6]\nboard_square_side_length = 30.0\n'
    )
    out = tmp_path / "calibration.toml"
    argv = ["calibrate", "--images", *map(str, dirs), "--board", str(board), "-o", str(out),
            "--no-progress"]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "rms px" in text and "cam2" in text
    rig = acm_rs.CameraRig.load(out, names=["cam0", "cam1", "cam2"])
    for ct, ce in zip(rendered.rig, rig, strict=True):
        np.testing.assert_allclose(ce.params[6:8], ct.params[6:8], rtol=0.01)
        assert np.linalg.norm(ce.center - ct.center) < 5.0  # mm, cameras ~0.5 m away
    for suffix in (".report.json", ".qc.png", ".detections.npz"):
        assert (tmp_path / f"calibration{suffix}").exists()
    rep = json.loads((tmp_path / "calibration.report.json").read_text())
    assert rep["plausibility"]["ok"], rep["plausibility"]
    assert rep["summary"]["rms_px"] < 0.6
    # An existing output is kept unless --overwrite.
    assert main(argv) == 1
    assert "--overwrite" in capsys.readouterr().err

    # The re-run reads the cache: detection must not run again.
    def boom(*a, **k):
        raise AssertionError("detection ran despite the cache")

    monkeypatch.setattr(detect_mod, "detect_board", boom)
    assert main([*argv, "--overwrite"]) == 0


def test_video_sources_with_stride(tmp_path):
    import cv2

    rendered = render_views(CHARUCO, n_cams=2, n_frames=6, seed=3)
    paths = []
    for i, frames in enumerate(rendered.images):
        path = tmp_path / f"cam{i}.avi"
        vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (640, 480))
        assert vw.isOpened()
        for img in frames:
            vw.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        vw.release()
        paths.append(path)
    det = detect(paths, CHARUCO, stride=2, progress=False)
    assert det.corners.shape == (2, 3, 24, 2)
    assert det.camera_names == ["cam0", "cam1"]
    assert tuple(det.image_sizes[0]) == (640, 480)
    ok = np.isfinite(det.corners[..., 0])
    err = np.linalg.norm(det.corners - rendered.pixels[:, ::2], axis=-1)[ok]
    assert ok.sum() > 30 and np.median(err) < 0.6


def test_charuco_images_calibrate_end_to_end():
    rendered = render_views(CHARUCO, n_cams=3, n_frames=10, seed=6)
    corners = np.stack(
        [np.stack([detect_board(img, CHARUCO) for img in frames]) for frames in rendered.images]
    )
    res = acm_rs.calibrate(corners, CHARUCO.board_points, (640, 480))
    assert res.rms < 0.6
    assert res.plausibility()["ok"]
    for ct, ce in zip(rendered.rig, res.rig, strict=True):
        np.testing.assert_allclose(ce.params[6:8], ct.params[6:8], rtol=0.02)
        assert np.linalg.norm(ce.center - ct.center) < 6.0
