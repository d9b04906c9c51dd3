"""The exact streaming smoother of long recordings (issue 16 item 1): checkpointed filtered
states with recomputation, or with the filtered moments spilled to disk, must reproduce the
smoother of the whole recording, restart where the filter has lost the animal, and never
leave a partial file or a spill behind."""

from __future__ import annotations

import os

import numpy as np
import pytest
from conftest import long_recording_case

import acm_rs
from acm_rs.tracking import long as L
from acm_rs.tracking import streaming as S

N = 500


@pytest.fixture(scope="module")
def case():
    # a camera out across two segment boundaries
    return long_recording_case(N, seed=14, outage=(150, 330))


def _stream(case, path, det=None, **kw):
    src = L._Source(case["det"] if det is None else det, case["lik"])
    return S.smooth_streaming(case["model"], src, path, **kw)


@pytest.mark.parametrize("spill", [True, False])
def test_segments_reproduce_the_smoother_of_the_whole_recording(case, tmp_path, spill):
    # one window over the whole recording is the exact smoother; the segments' checkpoints
    # and backward starts must give the same numbers (boundaries at 130, 260, 390 cut
    # through the camera outage), with the filtered moments spilled or filtered again
    whole = L.smooth_window(case["model"], case["det"], case["lik"])
    info = _stream(case, tmp_path / "s.h5", segment=130, poor_fit=None, spill=spill)
    out = acm_rs.read_chunked(tmp_path / "s.h5")
    assert info["n_segments"] == 4
    assert info["spill"] is spill
    assert [p.name for p in tmp_path.iterdir()] == ["s.h5"]  # the spill is gone
    for k in ("joints", "joints_std", "markers", "markers_std"):
        np.testing.assert_allclose(out[k], whole[k], rtol=0, atol=1e-9, err_msg=k)
    np.testing.assert_array_equal(out["status"], whole["status"])
    assert info["stats"]["used"] == whole["stats"]["used"]
    err = np.linalg.norm(out["joints"] - case["truth"], axis=-1).mean()
    assert err < 0.2  # cm: the smoother actually tracks


def test_spill_is_the_same_bit_for_bit(case, tmp_path):
    # the spilled moments are the filter's own (lower triangles of exactly symmetric
    # matrices): the backward pass must not see a difference
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    a = _stream(case, tmp_path / "a.h5", segment=170, poor_fit=None, spill=scratch)
    b = _stream(case, tmp_path / "b.h5", segment=170, poor_fit=None, spill=False)
    ns, n_x = np.size(case["model"].params["mu0"]), 2 * len(case["rig"]) * case["sk"].n_markers
    assert a["spill"] and a["spill_bytes"] == S.spill_bytes(N, ns, n_x, n_segments=3)
    assert not b["spill"] and b["no_spill_reason"] == "spill=False"
    assert list(scratch.iterdir()) == []
    ra, rb = (acm_rs.read_chunked(tmp_path / f) for f in ("a.h5", "b.h5"))
    for k in ("joints", "joints_std", "markers", "markers_std", "t", "r", "status"):
        np.testing.assert_array_equal(ra[k], rb[k], err_msg=k)


def test_spill_where_the_disk_has_room(case, tmp_path, monkeypatch):
    # "auto" spills only where the disk keeps SPILL_RESERVE free; otherwise it filters
    # again and says why
    monkeypatch.setattr(S, "SPILL_RESERVE", 2**62)
    info = _stream(case, tmp_path / "r.h5", segment=250, poor_fit=None)
    assert not info["spill"] and "GB free" in info["no_spill_reason"]
    with pytest.raises(ValueError, match="does not exist"):
        _stream(case, tmp_path / "x.h5", spill=tmp_path / "missing")
    with pytest.raises(ValueError, match="spill must be"):
        _stream(case, tmp_path / "x.h5", spill=3)
    assert [p.name for p in tmp_path.iterdir()] == ["r.h5"]  # no partial file


def test_output_in_a_new_folder(case, tmp_path):
    # the default spill goes beside the output, whose folder may not exist yet
    out = tmp_path / "new" / "deeper" / "s.h5"
    info = _stream(case, out, segment=250, poor_fit=None)
    assert info["spill"]
    assert [p.name for p in out.parent.iterdir()] == ["s.h5"]


def test_poorly_fit_stretches_are_reported(case, tmp_path):
    # every camera's detections shifted by 40 px in frames 300-360 (as if the rig had been
    # bumped): no pose fits them, and it must be said, with the frames
    det = case["det"].copy()
    det[:, 300:360] += 40.0
    with pytest.warns(UserWarning, match="reproject"):
        info = _stream(case, tmp_path / "u.h5", det=det, segment=200, typical_px=2.0)
    (a, b), *_ = info["poor_fit"]
    assert 295 <= a <= 305 and 355 <= b <= 375, info["poor_fit"]
    px = acm_rs.read_chunked(tmp_path / "u.h5")["info"]
    assert px["poor_fit"] == [list(s) for s in info["poor_fit"]]
    # the clean recording has none
    info = _stream(case, tmp_path / "c.h5", segment=200, typical_px=2.0)
    assert info["poor_fit"] == []


def test_restart_where_the_filter_lost_the_animal(case, tmp_path):
    # every camera 40 px off in frames 300-360: the filtered poses stop fitting at 300, so a
    # new sequence starts there with a fresh single-frame fit. The sequences are smoothed
    # on their own: frames before 300 are those of the recording cut at 300, frames from 300
    # those of the recording starting at 300 (bit for bit).
    det = case["det"].copy()
    det[:, 300:360] += 40.0
    kw = {"segment": 200, "typical_px": 2.0}
    with pytest.warns(UserWarning, match="reproject"):
        info = _stream(case, tmp_path / "r.h5", det=det, **kw)
    assert info["restarts"] == [300] and info["n_restarts"] == 1
    whole = acm_rs.read_chunked(tmp_path / "r.h5")
    src = L._Source
    S.smooth_streaming(case["model"], src(det[:, :300], case["lik"][:, :300]),
                       tmp_path / "a.h5", **kw)  # fmt: skip
    with pytest.warns(UserWarning, match="reproject"):
        S.smooth_streaming(case["model"], src(det[:, 300:], case["lik"][:, 300:]),
                           tmp_path / "b.h5", **kw)  # fmt: skip
    a, b = (acm_rs.read_chunked(tmp_path / f) for f in ("a.h5", "b.h5"))
    for k in ("joints", "joints_std"):
        np.testing.assert_array_equal(whole[k][:300], a[k], err_msg=k)
        np.testing.assert_array_equal(whole[k][300:], b[k], err_msg=k)
    np.testing.assert_array_equal(whole["status"], np.concatenate([a["status"], b["status"]], 1))
    # restart=False keeps one sequence
    with pytest.warns(UserWarning, match="reproject"):
        info = _stream(case, tmp_path / "n.h5", det=det, restart=False, **kw)
    assert info["restarts"] == []


def test_a_poor_stretch_across_a_segment_boundary_counts_whole(case, tmp_path):
    # 15 poor frames, 7 before the boundary at 200 and 8 after: neither part alone is a
    # stretch of POOR_FRAMES (10), together they are; the new sequence starts at the
    # boundary (the earliest frame of the segment being filtered)
    assert S.POOR_FRAMES == 10
    det = case["det"].copy()
    det[:, 193:208] += 40.0
    with pytest.warns(UserWarning, match="reproject"):
        info = _stream(case, tmp_path / "x.h5", det=det, segment=200, typical_px=2.0)
    assert info["restarts"] == [200], info["restarts"]
    (a, b), *_ = info["poor_fit"]
    assert a <= 195 and b >= 205, info["poor_fit"]


def test_restart_where_most_entries_are_gated(case, tmp_path):
    # a quarter of the markers 25 px off in every camera from frame 250 on: the gate rejects
    # them frame after frame (> 5 % of the entries for 50+ frames), which restarts the filter
    # even where the frames' reprojection test (poor_fit, here out of reach) does not
    det = case["det"].copy()
    det[:, 250:, :10] += 25.0
    info = _stream(case, tmp_path / "g.h5", det=det, segment=200, poor_fit=1000.0)
    assert len(info["restarts"]) >= 1 and 250 <= info["restarts"][0] <= 256, info["restarts"]
    assert _stream(case, tmp_path / "c.h5", segment=200, poor_fit=1000.0)["restarts"] == []


def test_gated_fraction():
    mask = np.zeros((3, 2, 2, 2), np.uint8)  # frames, cameras, markers, (u, v)
    mask[0] = 1
    mask[0, 0, 0] = 2  # 2 of 8 entries gated
    mask[1, 1] = 1  # 4 measured, none gated; frame 2: nothing measured
    np.testing.assert_allclose(S.gated_fraction(mask), [0.25, 0.0, 0.0])


def test_poor_stretches():
    px = np.array([1, 9, 9, 9, 1, 9, 9, np.nan, 9, 9, 9, 9], float)
    assert S.poor_stretches(px, 5.0, run=3) == [(1, 4), (8, 12)]
    assert S.poor_stretches(px, 10.0, run=1) == []


def test_frames_before_any_detections_are_nan(case, tmp_path):
    det = case["det"].copy()
    det[:, :120] = np.nan
    _stream(case, tmp_path / "e.h5", det=det, segment=100, poor_fit=None)
    out = acm_rs.read_chunked(tmp_path / "e.h5")
    assert np.isnan(out["joints"][:100]).all() and np.isfinite(out["joints"][100:]).all()


def test_failure_leaves_no_file(case, tmp_path, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("boom")

    monkeypatch.setattr(S, "frame_px", boom)
    with pytest.raises(RuntimeError, match="boom"):
        _stream(case, tmp_path / "f.h5", segment=200)
    assert list(tmp_path.iterdir()) == []
    # a failure in the backward pass (after the spill is written) leaves nothing either
    monkeypatch.undo()
    monkeypatch.setattr(S, "_finish", boom)
    with pytest.raises(RuntimeError, match="boom"):
        _stream(case, tmp_path / "g.h5", segment=200, spill=True)
    assert list(tmp_path.iterdir()) == []


def test_bad_arguments_are_refused(case, tmp_path):
    with pytest.raises(ValueError, match="segment"):
        _stream(case, tmp_path / "a.h5", segment=1)
    with pytest.raises(ValueError, match="poor_fit"):
        _stream(case, tmp_path / "a.h5", poor_fit=0.5)
    with pytest.raises(ValueError, match="Dask"):
        acm_rs.track_long(case["rig"], case["sk"], case["det"], tmp_path / "x.h5",
                          method="streaming", client="tcp://nowhere:1")  # fmt: skip


def _mapped_kb(path) -> int:
    """Resident kB of this process's mappings of ``path`` (Linux /proc/self/smaps)."""
    total, inside = 0, False
    for line in open("/proc/self/smaps"):
        first = line.split(maxsplit=1)[0]
        if "-" in first and not first.endswith(":"):  # a mapping's header line
            inside = line.rstrip().endswith(str(path))
        elif inside and first == "Rss:":
            total += int(line.split()[1])
    return total


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps"), reason="Linux /proc needed")
def test_memory_mapped_input_pages_are_released(tmp_path):
    # a 40 MB memory-mapped input read window by window: the windows are right, and the
    # pages read do not pile up in the process's resident memory
    n = 20_000
    det = np.lib.format.open_memmap(tmp_path / "d.npy", "w+", np.float32, (4, n, 64, 2))
    det[:] = np.arange(n, dtype=np.float32)[None, :, None, None]
    det.flush()
    del det
    src = L._Source(np.load(tmp_path / "d.npy", mmap_mode="r"), None)
    for a in range(0, n, 1000):
        win, _ = src.window(a, a + 1000)
        assert win.shape == (4, 1000, 64, 2)
        assert win[0, 0, 0, 0] == a and win[3, -1, 63, 1] == a + 999
    assert _mapped_kb(tmp_path / "d.npy") < 4 * 1024  # of 40,960 kB read


@pytest.mark.parametrize("spill", [True, False])
def test_recycled_buffers_change_nothing(case, tmp_path, monkeypatch, spill):
    # the run's trackers hand their covariances on (src/tracking/buffers.rs): later segments
    # filter and smooth in vectors that held an earlier segment's moments, and must give
    # the numbers of fresh vectors bit for bit
    a = _stream(case, tmp_path / "a.h5", segment=100, poor_fit=None, spill=spill)
    monkeypatch.setattr(S, "BUFFERS", 0)  # a pool that keeps nothing: every vector fresh
    b = _stream(case, tmp_path / "b.h5", segment=100, poor_fit=None, spill=spill)
    assert a["n_segments"] == b["n_segments"] == 5
    ra, rb = (acm_rs.read_chunked(tmp_path / f) for f in ("a.h5", "b.h5"))
    for k in ("joints", "joints_std", "markers", "markers_std", "t", "r", "status"):
        np.testing.assert_array_equal(ra[k], rb[k], err_msg=k)


def test_a_dropped_tracker_gives_its_covariances_to_the_next(case):
    from dataclasses import replace

    from acm_rs import _native
    from acm_rs.tracking import windows as W

    pool = _native.NativeBufferPool(2)
    model = replace(case["model"], buffers=pool)
    p = model.params
    det = model.detections(case["det"][:, :200], case["lik"][:, :200])
    x, mu0 = W._normalized(model.norm, det), W._window_prior(model, det)

    def moments(m):
        native = m.tracker(x)
        native.e_step(mu0, model.prior_cov, p["Vz"], p["Vx_diag"], model.gate)
        return native, native.means().copy(), native.covs().copy()

    first, m1, c1 = moments(model)
    assert len(pool) == 0  # (its vector is in use)
    del first
    assert len(pool) == 1
    second, m2, c2 = moments(model)  # in the first one's vector
    assert len(pool) == 0
    _, m3, c3 = moments(case["model"])  # no pool
    np.testing.assert_array_equal(m2, m3)
    np.testing.assert_array_equal(c2, c3)
    np.testing.assert_array_equal(c1, c3)
    del second
    assert len(pool) == 1
