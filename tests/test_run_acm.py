"""``acm-rs run-acm`` on a small dataset folder written in the authors' formats."""

from __future__ import annotations

import numpy as np
import pytest
from acm_fixture import write_acm_dataset

from acm_rs.cli import main


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return write_acm_dataset(tmp_path_factory.mktemp("acm") / "dataset")


def test_run_acm_writes_the_authors_layout_close_to_the_truth(dataset, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run-acm", str(dataset.folder), "-o", str(out)]) == 0
    assert "tracked" in capsys.readouterr().out
    pose = np.load(out / "pose.npy", allow_pickle=True).item()
    cfg = dataset.config
    n_t = (cfg["end"] - cfg["start"]) // cfg["dt"]
    assert pose["joint_positions_3d"].shape == (n_t, 29, 3)
    assert pose["marker_positions_2d"].shape == (n_t, 4, 43, 2)
    # Truth in the arena frame (cm), in ACM's joint order.
    frames = cfg["start"] + cfg["dt"] * np.arange(n_t)
    idx = np.searchsorted(dataset.frames, frames)
    joints, _ = dataset.skeleton.forward(dataset.t[idx], dataset.r[idx])
    order = [dataset.skeleton.joint_index(n) for n in dataset.acm_joint_names]
    err = np.linalg.norm(pose["joint_positions_3d"] - joints[:, order], axis=-1)
    assert np.median(err) < 0.3, np.median(err)  # cm
    # Normalised 2D positions reproject the 3D markers: |v| <= ~1 inside the sensor.
    assert np.nanmax(np.abs(pose["marker_positions_2d"])) < 1.5
    save = np.load(out / "save_dict.npy", allow_pickle=True).item()
    assert save["mu_uks"].shape[0] == n_t + 1 and save["var_uks"].shape[0] == n_t + 1
    assert (out / "acm-rs" / "pose.npz").is_file() and (out / "acm-rs" / "skeleton.toml").is_file()


def test_run_acm_names_a_missing_file(tmp_path, capsys):
    (tmp_path / "ds").mkdir()
    assert main(["run-acm", str(tmp_path / "ds"), "-o", str(tmp_path / "o")]) == 1
    assert "configuration.py: missing" in capsys.readouterr().err
