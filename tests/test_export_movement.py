"""movement export: the dataset movement builds, written as netCDF and read back by movement."""

from __future__ import annotations

import numpy as np
import pytest
from acm_fixture import synthetic_result

from acm_rs import export

xr = pytest.importorskip("xarray")


@pytest.fixture(scope="module")
def result():
    res = synthetic_result(n_frames=12, seed=5)
    res.info["frames"] = np.arange(100, 100 + 2 * res.n_frames, 2)  # every 2nd frame tracked
    return res


def test_layout_units_and_time(result):
    ds = export.to_movement(result, fps=50.0)
    assert ds["position"].dims == ("time", "space", "keypoints", "individuals")
    assert ds["confidence"].dims == ("time", "keypoints", "individuals")
    assert ds.sizes == {"time": 12, "space": 3, "keypoints": result.skeleton.n_joints,
                        "individuals": 1}  # fmt: skip
    assert list(ds["keypoints"].values) == list(result.joint_names)
    # position[t, :, j] is joint j of frame t; the SD is the posterior SD
    np.testing.assert_array_equal(ds["position"].values[:, :, 3, 0], result.joints[:, 3])
    np.testing.assert_allclose(ds["position_std"].values[:, :, 3, 0], result.joints_std[:, 3])
    # time from the frame numbers: frame 100 at 50 Hz is 2 s; fps is that of the tracked frames
    np.testing.assert_allclose(ds["time"].values, np.arange(100, 124, 2) / 50.0)
    assert ds.attrs["fps"] == 25.0 and ds.attrs["time_unit"] == "seconds"
    assert ds.attrs["source_software"] == "acm-rs" and ds.attrs["ds_type"] == "poses"
    assert ds.attrs["units"] == result.skeleton.units == ds["position"].attrs["units"]
    conf = ds["confidence"].values
    assert np.all((conf >= 0) & (conf <= 1))
    markers = export.to_movement(result, points="markers")
    assert markers.sizes["keypoints"] == result.skeleton.n_markers
    assert markers.attrs["time_unit"] == "frames" and "fps" not in markers.attrs
    np.testing.assert_array_equal(markers["time"].values, np.arange(100, 124, 2))
    with pytest.raises(ValueError, match="fps must be a positive"):
        export.to_movement(result, fps=0.0)


def test_netcdf_round_trip_through_movement(result, tmp_path):
    pytest.importorskip("movement")
    from movement.validators.datasets import ValidPosesInputs

    path = export.to_movement_file(result, tmp_path / "pose_movement.nc", fps=50.0)
    assert [p.name for p in tmp_path.iterdir()] == ["pose_movement.nc"]  # no temporary left
    with xr.open_dataset(path) as ds:
        ds = ds.load()
    ValidPosesInputs.validate(ds)  # movement's own check of a poses dataset
    np.testing.assert_array_equal(ds["position"].values[..., 0], result.joints.transpose(0, 2, 1))
    assert ds.attrs["fps"] == 25.0
    # movement's own functions accept it: kinematics and filtering work on the loaded dataset
    from movement.kinematics import compute_velocity

    vel = compute_velocity(ds["position"])
    expect = np.gradient(result.joints[:, 0, 0], np.arange(100, 124, 2) / 50.0)
    np.testing.assert_allclose(vel.values[:, 0, 0, 0], expect, rtol=1e-9, atol=1e-9)
    # and movement can build the same dataset from the arrays (same dims, coords, attrs)
    from movement.io import load_poses

    ref = load_poses.from_numpy(
        result.joints.transpose(0, 2, 1)[..., None], ds["confidence"].values,
        individual_names=["individual_0"], keypoint_names=list(result.joint_names), fps=25.0,
        source_software="acm-rs",
    )  # fmt: skip
    assert ref["position"].dims == ds["position"].dims
    assert list(ref["keypoints"].values) == list(ds["keypoints"].values)
