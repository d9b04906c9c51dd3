"""Bundles for the standalone smoother: Python writer -> Rust reader/EM/writer -> Python reader,
against the in-process tracker on the same data (and the ``acm-smooth`` binary if built)."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import acm_rs
from acm_rs import acm_model, datasets, models
from acm_rs.demo import demo_rig
from acm_rs.tracking import read_smoothed, smooth_bundle, write_bundle

BIN_DIR = os.environ.get("ACM_RS_BIN_DIR", Path(__file__).resolve().parents[1] / "target/release")
BINARY = Path(BIN_DIR) / "acm-smooth"


@pytest.fixture(scope="module")
def data():
    sk = datasets.individual_skeleton(models.rat(), seed=4)
    rig = demo_rig()
    t, r = datasets.smooth_motion(sk, 40, seed=5)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=6)
    return sk, rig, det, lik


@pytest.mark.parametrize("links", ["tree", "explicit"])
def test_bundle_smoothing_equals_the_in_process_tracker(data, tmp_path, links):
    sk, rig, det, lik = data
    if links == "explicit":  # an ACM model.npy's link matrix (here: the literal Alg. 1 one)
        lk = acm_model.literal_alg1_links(sk.parents, sk.bones)
        # the global rotation (bone 0) first, as in the authors' files, the rest reversed
        sk = sk.with_links(lk, np.r_[0, np.arange(1, sk.n_bones)[::-1]])
        assert "bone_links" in np.load(write_bundle(tmp_path / "l.npz", rig, sk, det[:, :3]))
    opts = {"max_iter": 4, "tol": 0.05}
    # the acm-smooth binary runs the paper's random walk (no position-velocity state yet)
    ref = acm_rs.track(rig, sk, det, likelihood=lik, progress=False, motion="random_walk", **opts)
    path = write_bundle(tmp_path / "s1.npz", rig, sk, det, likelihood=lik, **opts)
    out, summary = smooth_bundle(path)
    assert out == tmp_path / "s1.smoothed.npz" and summary["n_frames"] == 40
    assert summary["iterations"] == len(ref.em_history)
    res = read_smoothed(out, rig, sk, path)
    np.testing.assert_allclose(res.joints, ref.joints, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.joints_std, ref.joints_std, rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(res.state_cov, ref.state_cov, rtol=1e-7, atol=1e-14)
    np.testing.assert_array_equal(res.info["status"], ref.info["status"])
    err = np.nanmean(ref.reprojection_error()[ref.info["status"] == 1])
    assert summary["mean_reprojection_px"] == pytest.approx(err, rel=1e-9)
    _, _ = smooth_bundle(path, tmp_path / "nocov.npz", keep_cov=False)
    assert "state_cov" not in np.load(tmp_path / "nocov.npz")


def test_bad_bundles_are_clear_errors(data, tmp_path):
    sk, rig, det, lik = data
    path = write_bundle(tmp_path / "b.npz", rig, sk, det[:, :5], likelihood=lik[:, :5])
    arrays = dict(np.load(path))
    del arrays["mu0"]
    np.savez(tmp_path / "nomu.npz", **arrays)
    with pytest.raises(ValueError, match="no array 'mu0'"):
        smooth_bundle(tmp_path / "nomu.npz")
    arrays = dict(np.load(path))
    arrays["cameras"] = arrays["cameras"][:, :10]
    np.savez(tmp_path / "cams.npz", **arrays)
    with pytest.raises(ValueError, match="'cameras' has shape"):
        smooth_bundle(tmp_path / "cams.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="not an NPZ archive"):
        smooth_bundle(tmp_path / "junk.npz")
    arrays = dict(np.load(path))
    arrays["detections"] = np.full_like(arrays["detections"], np.nan)
    np.savez(tmp_path / "empty.npz", **arrays)
    with pytest.raises(ValueError, match="no detection is usable"):
        smooth_bundle(tmp_path / "empty.npz")
    # an explicit link matrix needs its order, of bone indices
    n = sk.n_bones
    arrays = dict(np.load(path)) | {"bone_links": np.eye(n)}
    np.savez(tmp_path / "noorder.npz", **arrays)
    with pytest.raises(ValueError, match="no array 'link_order'"):
        smooth_bundle(tmp_path / "noorder.npz")
    for bad, match in ((np.full(n, 0.5), "bone indices"), (np.zeros(n), "permutation")):
        np.savez(tmp_path / "order.npz", **(arrays | {"link_order": bad}))
        with pytest.raises(ValueError, match=match):
            smooth_bundle(tmp_path / "order.npz")


@pytest.mark.skipif(not BINARY.exists(), reason="acm-smooth not built (cargo build --release)")
def test_binary_processes_many_files_and_reports_failures(data, tmp_path):
    sk, rig, det, lik = data
    a = write_bundle(tmp_path / "a.npz", rig, sk, det[:, :20], likelihood=lik[:, :20], max_iter=2)
    b = write_bundle(tmp_path / "b.npz", rig, sk, det[:, 20:], likelihood=lik[:, 20:], max_iter=2)
    shutil.copy(a, tmp_path / "c.npz")
    (tmp_path / "bad.npz").write_bytes(b"nope")
    run = subprocess.run(
        [str(BINARY), "-q", "-o", str(tmp_path / "out"), str(a), str(b), str(tmp_path / "bad.npz")],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert run.returncode == 1 and "bad.npz" in run.stderr
    for stem in ("a", "b"):
        res = np.load(tmp_path / "out" / f"{stem}.smoothed.npz")
        assert res["joints"].shape == (20, sk.n_joints, 3)
    ok = subprocess.run([str(BINARY), "--help"], capture_output=True, text=True, check=True)
    assert "detections (C,T,M,2)" in ok.stdout
