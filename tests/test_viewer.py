"""acm-rs view: one self-contained HTML file, rendered in headless Chromium when present."""

from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest
from acm_fixture import synthetic_result

from acm_rs.cli import main

pytest.importorskip("plotly")


@pytest.fixture(scope="module")
def result_file(tmp_path_factory):
    res = synthetic_result(n_frames=30, seed=3)
    path = tmp_path_factory.mktemp("view") / "pose.npz"
    res.save(path)
    return res, path


def test_view_writes_one_offline_html(result_file, capsys):
    res, path = result_file
    assert main(["view", str(path), "--fps", "50", "--max-frames", "10"]) == 0
    assert "wrote" in capsys.readouterr().out
    html = path.with_suffix(".html").read_text()
    # plotly.js is embedded: no script or stylesheet is fetched from the network
    assert not re.search(r"<script[^>]+src=", html)
    assert not re.search(r"<link[^>]+href=\"?https?:", html)
    assert "Plotly.newPlot" in html or "Plotly.addFrames" in html
    # 30 frames at most 10 animated: every 3rd, one slider step per frame
    assert html.count('"name":"27"') >= 1 and '"name":"28"' not in html
    assert html.count('"method":"animate"') == 10 + 2  # slider steps + play + pause
    # the joint drop-down lists every joint; the SD colour bar carries the unit
    for name in res.joint_names:
        assert f'"label":"{name}"' in html
    assert "SD (cm)" in html
    assert (
        list(path.parent.iterdir()) == [path, path.with_suffix(".html")]
        or len(list(path.parent.glob(".*"))) == 0
    )  # no temporary file left


def _chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


def _screenshot(html, png, size=(1400, 800)):
    exe = _chromium()
    if exe is None:
        pytest.skip("headless Chromium (Debian package 'chromium') is not installed")
    cmd = [
        exe, "--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader", "--hide-scrollbars", f"--window-size={size[0]},{size[1]}",
        "--virtual-time-budget=15000", f"--screenshot={png}", html.as_uri(),
    ]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True, timeout=180)
    import cv2

    img = cv2.imread(str(png))
    assert img is not None, "no screenshot"
    return img[..., ::-1].astype(int)  # RGB


def _near(img, rgb, tol=40):
    return np.all(np.abs(img - np.array(rgb)) <= tol, axis=-1)


def test_view_renders_in_headless_chromium(result_file, tmp_path):
    from acm_rs.plots.viewer import view_html

    res, _ = result_file
    html = view_html(res, tmp_path / "view.html", fps=50)
    img = _screenshot(html, tmp_path / "shot.png")
    h, w, _ = img.shape
    assert img.std() > 20, "blank page"
    scene = img[: int(0.8 * h), : int(0.55 * w)]  # the 3D panel (the legend is on the right)
    bones = _near(scene, (255, 120, 0), tol=35).sum()
    floor = _near(scene, (225, 225, 225), tol=12).sum()
    # viridis joint colours (the SD colour bar is left of the scene: exclude its columns)
    joints = (
        _near(scene[:, 120:], (122, 209, 81), 60) | _near(scene[:, 120:], (253, 231, 37), 60)
    ).sum()
    # (measured: ~155 orange pixels with the bones, 0 without them)
    assert bones > 40, f"skeleton not drawn ({bones} orange pixels in the 3D panel)"
    assert floor > 5000, f"arena floor not drawn ({floor} grey pixels)"
    assert joints > 30, f"joints not drawn ({joints} viridis pixels)"
    # the trace panel: the x (blue) mean line
    trace = img[: int(0.8 * h), int(0.55 * w) : int(0.88 * w)]
    assert _near(trace, (31, 119, 180), 30).sum() > 200
    # a control: the same page without the skeleton has no orange in the scene
    text = html.read_text().replace("rgb(255,120,0)", "rgb(255,255,255)")
    (tmp_path / "control.html").write_text(text)
    ctrl = _screenshot(tmp_path / "control.html", tmp_path / "control.png")
    assert _near(ctrl[: int(0.8 * h), : int(0.55 * w)], (255, 120, 0), tol=35).sum() < bones / 10


def test_floor_is_under_the_animal_in_any_world_frame():
    from acm_rs.plots.viewer import _floor, _up

    rng = np.random.default_rng(0)
    animal = rng.normal(0, 5, (50, 3)) + [0, 0, 8]
    ring = [[60 * np.cos(a), 60 * np.sin(a), 45] for a in np.linspace(0, 6, 4)]
    cams = np.array(ring)
    assert np.array_equal(_up(animal, cams), [0, 0, 1])  # a floor-based world frame: z
    floor = _floor(animal, np.array([0.0, 0, 1]), pad=2.0)
    np.testing.assert_allclose(floor[:, 2], animal[:, 2].min())
    # the same scene seen in a tilted frame (e.g. the first camera's): up is the tilted z
    c, s = np.cos(0.9), np.sin(0.9)
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    up = _up(animal @ rot.T, cams @ rot.T)
    assert up @ (rot @ [0, 0, 1]) > 0.9  # close to the true up (not a world axis)
    floor = _floor(animal @ rot.T, up, pad=2.0)
    heights = floor @ up
    np.testing.assert_allclose(heights, heights[0])  # a plane perpendicular to up ...
    assert np.all((animal @ rot.T) @ up >= heights[0] - 1e-9)  # ... under every joint


def test_figure_content_and_decimation(result_file):
    from acm_rs.plots.viewer import view_figure

    res, _ = result_file
    fig = view_figure(res, fps=50.0, max_frames=7, max_trace_points=10)
    assert [f.name for f in fig.frames] == ["0", "5", "10", "15", "20", "25"]  # every 5th
    # frame 10: the joints and the bones of frame 10, the joints coloured by their total SD
    f10 = fig.frames[2]
    joints = f10.data[1]
    np.testing.assert_allclose(joints.x, res.joints[10, :, 0])
    np.testing.assert_allclose(joints.marker.color, np.linalg.norm(res.joints_std[10], axis=-1))
    a, b = res.skeleton.bones[0]
    assert f10.data[0].x[:2] == pytest.approx(
        [res.joints[10, a, 0], res.joints[10, b, 0]], abs=0.01
    )
    assert f10.data[2].x == (0.2, 0.2)  # the time cursor at 10 / 50 Hz
    # the trace panel: joint 0's x mean every 3rd frame (30 frames, at most 10 points)
    mean_x = fig.data[6]
    np.testing.assert_allclose(mean_x.x, np.arange(0, 30, 3) / 50.0)
    np.testing.assert_allclose(mean_x.y, res.joints[::3, 0, 0])
    band = fig.data[5]  # mean ± 2 SD, as one closed polygon
    np.testing.assert_allclose(band.y[:10], res.joints[::3, 0, 0] + 2 * res.joints_std[::3, 0, 0])
    # the drop-down shows joint j's six traces and hides the others'
    menu = fig.layout.updatemenus[1]
    vis = menu.buttons[2].args[0]["visible"]
    assert vis[5 + 12 : 5 + 18] == [True] * 6 and not any(vis[5:17]) and vis[-1]
    with pytest.raises(ValueError, match="max_frames"):
        view_figure(res, max_frames=0)
