"""Tracking figures and overlay videos (acm_rs.plots): built from a small tracked session."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import acm_rs
from acm_rs import datasets, models, plots
from acm_rs.demo import demo_rig

cv2 = pytest.importorskip("cv2")
matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


@pytest.fixture(scope="module")
def result() -> acm_rs.PoseResult:
    sk = datasets.individual_skeleton(models.rat(), seed=1)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, 40, seed=2)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=3)
    return acm_rs.track(rig, sk, det, likelihood=lik, progress=False, max_iter=4)


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _first_frames(res: acm_rs.PoseResult, n: int) -> acm_rs.PoseResult:
    """The same result restricted to its first n frames."""
    info = dict(res.info, status=res.info["status"][:, :n])
    return dataclasses.replace(
        res,
        joints=res.joints[:n],
        joints_std=res.joints_std[:n],
        markers=res.markers[:n],
        t=res.t[:n],
        r=res.r[:n],
        state_mean=res.state_mean[:n],
        state_cov=res.state_cov[:n],
        detections=res.detections[:, :n],
        info=info,
    )


# -- figures -----------------------------------------------------------------------------------
def test_histograms_count_used_and_gated_detections_per_camera(result):
    status = result.info["status"]
    assert (status == 2).any(), "the session should contain gated outliers"
    fig = plots.reprojection_histograms(result)
    assert len(fig.axes) == len(result.rig)
    err = result.reprojection_error()
    for c, ax in enumerate(fig.axes):
        used = int((status[c] == 1).sum())
        gated = int((status[c] == 2).sum())
        assert np.isfinite(err[c][status[c] == 1]).all()
        assert sum(p.get_height() for p in ax.containers[0]) == used
        if gated:
            assert sum(p.get_height() for p in ax.containers[1]) == gated
        med = np.median(err[c][status[c] == 1])
        assert any(np.allclose(line.get_xdata(), med) for line in ax.lines)
        assert ax.get_xscale() == "log"


def test_joint_traces_band_is_four_std_wide(result):
    fig = plots.joint_traces(result, joints=["head_001", "tail_001"], frame_rate=100.0)
    assert len(fig.axes) == 6
    j = result.skeleton.joint_index("tail_001")
    frame = 17
    ax = fig.axes[3 + 2]  # tail_001, z
    np.testing.assert_allclose(ax.lines[0].get_ydata(), result.joints[:, j, 2])
    np.testing.assert_allclose(ax.lines[0].get_xdata(), np.arange(result.n_frames) / 100.0)
    verts = ax.collections[0].get_paths()[0].vertices
    ys = verts[np.isclose(verts[:, 0], frame / 100.0), 1]
    std = result.joints_std[frame, j, 2]
    assert std > 0
    np.testing.assert_allclose(ys.max() - ys.min(), 4 * std, rtol=1e-9)
    np.testing.assert_allclose(0.5 * (ys.max() + ys.min()), result.joints[frame, j, 2])
    assert fig.axes[-1].get_xlabel() == "time (s)"
    # default selection: root plus leaves, capped
    assert len(plots.joint_traces(result).axes) == 3 * plots.tracking.MAX_DEFAULT_JOINTS
    with pytest.raises(ValueError, match="unknown joint 'nose'"):
        plots.joint_traces(result, joints=["nose"])


def test_bone_angles_of_straight_and_right_angled_chains():
    # 0 -> 1 -> 2 -> 3, 2 -> 4: straight, then right angle, then folded back
    parents = [-1, 0, 1, 2, 2]
    joints = np.array([[0, 0, 0], [1, 0, 0], [3, 0, 0], [3, 2, 0], [2, 0, 0]], float)
    angles, ends = plots.bone_angles(joints, parents)
    assert ends == [2, 3, 4]
    np.testing.assert_allclose(angles, [0.0, 90.0, 180.0], atol=1e-6)
    # many frames, a rotation of the whole chain changes nothing; 45 degrees
    rot = acm_rs.rodrigues(np.array([0.3, -1.1, 0.7]))
    bent = np.array([[0, 0, 0], [1, 0, 0], [2, 1, 0], [2, 1, 5], [5, 4, 0]], float)
    stack = np.stack([joints, bent @ rot.T])
    angles, _ = plots.bone_angles(stack, parents, ends=[2, 4])
    np.testing.assert_allclose(angles, [[0.0, 180.0], [45.0, 0.0]], atol=1e-6)
    with pytest.raises(ValueError, match="without a parent bone"):
        plots.bone_angles(joints, parents, ends=[1])
    coincident = joints.copy()
    coincident[2] = coincident[1]
    assert np.isnan(plots.bone_angles(coincident, parents, ends=[2])[0][0])


def test_joint_angle_traces_show_known_angles(result):
    sk = result.skeleton
    joints = np.zeros_like(result.joints)
    head, s5, s4, sl = (
        sk.joint_index(n) for n in ("head_001", "spine_005", "spine_004", "shoulder_left")
    )
    assert list(sk.parents[[s5, s4, sl]]) == [head, s5, s4]
    joints[:, s5] = [1.0, 0.0, 0.0]
    joints[:, s4] = [2.0, 0.0, 0.0]  # spine_004 continues spine_005: 0 degrees
    joints[:, sl] = [2.0, 0.0, 1.5]  # shoulder_left at a right angle: 90 degrees
    fig = plots.joint_angle_traces(
        dataclasses.replace(result, joints=joints), bones=["spine_004", "shoulder_left"]
    )
    assert len(fig.axes) == 2
    np.testing.assert_allclose(fig.axes[0].lines[0].get_ydata(), 0.0, atol=1e-6)
    np.testing.assert_allclose(fig.axes[1].lines[0].get_ydata(), 90.0, atol=1e-6)
    # default: every bone with a parent bone and a free rotation
    lim = sk.joint_limits
    free = ~np.all(lim[..., 0] == lim[..., 1], axis=1)
    has_parent = sk.parents[sk.parents[sk.bones[:, 1]]] >= 0
    assert len(plots.joint_angle_traces(result).axes) == int((free & has_parent).sum())
    with pytest.raises(ValueError, match="without a parent bone"):
        plots.joint_angle_traces(result, bones=["spine_005"])


def test_skeleton_snapshots_top_and_side(result):
    frames = [0, 12, 39]
    fig = plots.skeleton_snapshots(result, frames=frames)
    assert len(fig.axes) == 2 * len(frames)
    s, e = result.skeleton.bones[0]
    for row, (a, b) in enumerate([(0, 1), (0, 2)]):
        for col, f in enumerate(frames):
            ax = fig.axes[row * len(frames) + col]
            assert ax.get_aspect() == 1.0
            bone = ax.lines[0]
            np.testing.assert_allclose(bone.get_xdata(), result.joints[f, [s, e], a])
            np.testing.assert_allclose(bone.get_ydata(), result.joints[f, [s, e], b])
            markers = ax.lines[-1]  # drawn last, green dots
            np.testing.assert_allclose(markers.get_xdata(), result.markers[f, :, a])
    assert len(plots.skeleton_snapshots(result).axes) == 8  # 4 default frames
    with pytest.raises(ValueError, match="out of range"):
        plots.skeleton_snapshots(result, frames=[result.n_frames])


def test_em_convergence_has_one_point_per_iteration(result):
    fig = plots.em_convergence(result)
    assert len(fig.axes) == 2
    ll_ax, time_ax = fig.axes
    hist = result.em_history
    kept = [h for h in hist if not h["rejected"]]
    # the default stop watches the log-likelihood: one point per iteration kept, crosses for
    # the over-relaxed steps that were replaced
    np.testing.assert_allclose(ll_ax.lines[0].get_ydata(), [h["log_likelihood"] for h in kept])
    assert len(ll_ax.lines) == (2 if len(kept) < len(hist) else 1)
    heights = [p.get_height() for p in time_ax.patches]
    np.testing.assert_allclose(heights, [h["seconds"] for h in hist])
    # Alg. 13's stop: its Δ on a log axis with the tolerance
    alg13 = dataclasses.replace(result, info={**result.info, "stop": "alg13"})
    delta_ax = plots.em_convergence(alg13).axes[0]
    np.testing.assert_allclose(delta_ax.lines[0].get_ydata(), [h["delta"] for h in hist])
    assert len(delta_ax.lines[0].get_xdata()) == len(hist)
    np.testing.assert_allclose(delta_ax.lines[1].get_ydata(), result.info["tol"])
    assert delta_ax.get_yscale() == "log"
    with pytest.raises(ValueError, match="no EM history"):
        plots.em_convergence(dataclasses.replace(result, em_history=[]))


# -- files -------------------------------------------------------------------------------------
def test_save_figure_writes_png_and_pdf_atomically(tmp_path):
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    written = plots.save_figure(fig, tmp_path / "sub" / "fig.png", pdf=True)
    assert written == [tmp_path / "sub" / "fig.png", tmp_path / "sub" / "fig.pdf"]
    image = matplotlib.image.imread(written[0])
    assert image.ndim == 3 and image.shape[0] > 100
    assert written[1].read_bytes().startswith(b"%PDF")
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["fig.pdf", "fig.png"]
    assert not plt.fignum_exists(fig.number)  # closed
    fig2, _ = plt.subplots()
    assert plots.save_figure(fig2, tmp_path / "run.v2") == [tmp_path / "run.v2.png"]


def test_plot_all_writes_stable_names(result, tmp_path):
    # a deterministic-like result: no status (all finite detections count) and no EM history
    det_like = dataclasses.replace(result, em_history=[], info={"method": "deterministic"})
    written = plots.plot_all(det_like, tmp_path / "plots")
    names = [p.name for p in written]
    assert names == [
        "reprojection_histograms.png",
        "joint_traces.png",
        "joint_angle_traces.png",
        "skeleton_snapshots.png",
    ]
    for p in written:
        assert p.read_bytes().startswith(b"\x89PNG")
    assert sorted(p.name for p in (tmp_path / "plots").iterdir()) == sorted(names)


# -- overlay video -----------------------------------------------------------------------------
def _black_videos(folder, n_cams, n_frames, size=(320, 256), fps=25.0):
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for c in range(n_cams):
        p = folder / f"cam{c}.mp4"
        writer = cv2.VideoWriter(str(p), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
        assert writer.isOpened()
        for _ in range(n_frames):
            writer.write(np.zeros((size[1], size[0], 3), np.uint8))
        writer.release()
        paths.append(p)
    return paths


def _read_all(path):
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, img = cap.read()
        if not ok:
            break
        frames.append(img)
    fps = cap.get(cv2.CAP_PROP_FPS)
    cap.release()
    return frames, fps


def test_overlay_video_draws_the_projected_markers(result, tmp_path):
    res = _first_frames(result, 10)
    videos = _black_videos(tmp_path, len(res.rig), 10)  # 1280x1024 cameras at 1/4 size
    out = plots.overlay_video(res, videos, tmp_path / "out" / "overlay", tile=False)
    assert [p.name for p in out] == [f"overlay_{cam.name}.mp4" for cam in res.rig]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(p.name for p in out)
    proj = res.projected()
    for c, path in enumerate(out):
        frames, fps = _read_all(path)
        assert len(frames) == 10
        assert frames[0].shape == (256, 320, 3)
        assert fps == pytest.approx(25.0)
        for f in (0, 9):
            img = frames[f].max(axis=2)
            px = np.round((proj[c, f] + 0.5) * 0.25 - 0.5).astype(int)
            inside = (px[:, 0] >= 2) & (px[:, 0] < 318) & (px[:, 1] >= 2) & (px[:, 1] < 254)
            assert inside.sum() > 10
            lit = [img[y - 1 : y + 2, x - 1 : x + 2].max() > 60 for x, y in px[inside]]
            assert np.mean(lit) > 0.95
            # outside the box around everything drawn, the frame stays black
            joints_px = res.rig.project(res.joints[f])[c]
            pts = np.concatenate([proj[c, f], joints_px, res.detections[c, f]]) * 0.25
            lo, hi = np.nanmin(pts, axis=0) - 8, np.nanmax(pts, axis=0) + 8
            ys, xs = np.mgrid[: img.shape[0], : img.shape[1]]
            box = (xs >= lo[0]) & (xs <= hi[0]) & (ys >= lo[1]) & (ys <= hi[1])
            assert img[~box].max() < 40
            assert (~box).mean() > 0.5


def test_overlay_video_tiles_and_selects_frames(result, tmp_path):
    res = _first_frames(result, 10)
    videos = _black_videos(tmp_path, len(res.rig), 10)
    by_name = {cam.name: v for cam, v in zip(res.rig, videos, strict=True)}
    (out,) = plots.overlay_video(res, by_name, tmp_path / "tiled.mp4", frames=[0, 3, 4], fps=5)
    frames, fps = _read_all(out)
    assert len(frames) == 3
    assert frames[0].shape == (512, 640, 3)  # 2 x 2 tiles of 320 x 256
    assert fps == pytest.approx(5.0)
    assert all(img.max() > 60 for img in frames)


def test_overlay_video_errors_name_the_problem(result, tmp_path):
    res = _first_frames(result, 10)
    videos = _black_videos(tmp_path, len(res.rig), 10)
    missing = tmp_path / "nope" / "cam2.mp4"
    with pytest.raises(ValueError, match=f"video not found: {missing}"):
        plots.overlay_video(res, videos[:2] + [missing] + videos[3:], tmp_path / "o.mp4")
    with pytest.raises(ValueError, match="got 2 video"):
        plots.overlay_video(res, videos[:2], tmp_path / "o.mp4")
    with pytest.raises(ValueError, match=r"no video for camera\(s\) \['cam3'\]"):
        plots.overlay_video(res, {"cam0": videos[0], "cam1": videos[1], "cam2": videos[2]}, "o")
    short = _first_frames(result, 8)
    with pytest.raises(ValueError, match="has 10 frames but the result has 8"):
        plots.overlay_video(short, videos, tmp_path / "o.mp4")
    wrong = _black_videos(tmp_path / "wrong", 1, 10, size=(320, 320))[0]
    with pytest.raises(ValueError, match="calibrated at 1280x1024"):
        plots.overlay_video(res, [wrong] * len(res.rig), tmp_path / "o.mp4")
    with pytest.raises(ValueError, match="increasing"):
        plots.overlay_video(res, videos, tmp_path / "o.mp4", frames=[3, 2])
    leftovers = [p.name for p in tmp_path.iterdir() if p.is_file() and p.suffix != ".mp4"]
    assert leftovers == []
    assert not (tmp_path / "o.mp4").exists()
