"""Second poses with the same markers (acm_rs.tracking.ambiguity).

The truth is plain geometry: a knee that no marker pins swings about the hip-ankle axis, and
its mirror position lies at twice its distance from that axis (computed here with NumPy, not
with the product's forward kinematics).
"""

import dataclasses
import warnings

import numpy as np
import pytest

import acm_rs
from acm_rs.tracking.ambiguity import search, widen

NAMES = ["pelvis", "hip", "knee", "ankle", "toe"]
PARENTS = [-1, 0, 1, 2, 3]
REST = np.array(
    [[0.0, 0.0, 10.0], [1.0, 0.0, 9.0], [1.6, 1.2, 5.5], [1.0, 0.2, 2.0], [1.0, 1.7, 1.8]]
)


def leg(knee_marker: bool, joint_limits=None, units: str = "cm") -> acm_rs.Skeleton:
    markers = {
        "pelvis_a": ("pelvis", REST[0] + [0.5, 0.0, 0.0]),
        "pelvis_b": ("pelvis", REST[0] + [0.0, 0.5, 0.0]),
        "pelvis_c": ("pelvis", REST[0] + [0.0, 0.0, 0.5]),
        "hip": ("hip", REST[1]),
        "ankle": ("ankle", REST[3]),
        "toe": ("toe", REST[4]),
        "toe_side": ("toe", REST[4] + [0.3, 0.0, 0.0]),
    }
    if knee_marker:
        markers["knee"] = ("knee", REST[2])
    return acm_rs.Skeleton.from_rest_pose(
        NAMES,
        PARENTS,
        REST,
        list(markers),
        [j for j, _ in markers.values()],
        np.array([p for _, p in markers.values()]),
        joint_limits=joint_limits,
        name="leg",
        units=units,
    )


def mirror_distance(hip, knee, ankle) -> float:
    """Twice the knee's distance from the hip-ankle line."""
    n = (ankle - hip) / np.linalg.norm(ankle - hip)
    v = knee - hip
    return 2.0 * float(np.linalg.norm(v - n * (n @ v)))


def test_a_knee_no_marker_pins_has_a_mirror_pose():
    sk = leg(knee_marker=False)
    r = np.zeros((1, sk.n_bones, 3))
    found = search(sk, REST[:1], r, marker_std=1e-5)
    names = [name for name, *_ in found.ambiguous()]
    assert names == ["knee"]
    knee = NAMES.index("knee")
    assert found.distance[0, knee] == pytest.approx(mirror_distance(*REST[1:4]), rel=1e-5)
    assert "knee" in found.summary() and " cm)" in found.summary()


def test_the_summary_names_a_unit_when_the_skeleton_declares_none():
    sk = leg(knee_marker=False, units="")
    found = search(sk, REST[:1], np.zeros((1, sk.n_bones, 3)), marker_std=1e-5)
    assert [name for name, *_ in found.ambiguous()] == ["knee"]
    assert " world units)" in found.summary() and " )" not in found.summary()


def test_a_marker_on_the_knee_decides_it():
    sk = leg(knee_marker=True)
    found = search(sk, REST[:1], np.zeros((1, sk.n_bones, 3)), marker_std=1e-5)
    assert found.ambiguous() == []
    assert np.isnan(found.distance).all()
    assert found.summary().startswith("no second pose")


def test_second_poses_outside_the_joint_limits_do_not_count():
    # limits of +-1e-6 rad hold the tracked pose (all zeros) and no pose that moves the knee
    # by more than the search's floor (2.3e-5 cm here)
    limit = np.tile([-1e-6, 1e-6], (3, 1))
    sk = leg(knee_marker=False, joint_limits=dict.fromkeys(NAMES[1:], limit))
    r = np.zeros((1, sk.n_bones, 3))
    assert search(sk, REST[:1], r, marker_std=1e-5, within_limits=True).ambiguous() == []
    unbounded = search(sk, REST[:1], r, marker_std=1e-5, within_limits=False)
    assert [name for name, *_ in unbounded.ambiguous()] == ["knee"]


def test_a_joint_inside_its_uncertainty_is_not_reported():
    sk = leg(knee_marker=False)
    d = mirror_distance(*REST[1:4])
    std = np.zeros((1, len(NAMES), 3))
    std[0, NAMES.index("knee")] = d / 1.96 / np.sqrt(3) * 1.01  # 1.96 |SD| just beyond d
    found = search(sk, REST[:1], np.zeros((1, sk.n_bones, 3)), marker_std=1e-5, joints_std=std)
    assert found.ambiguous() == []


def test_bad_bounds_are_refused():
    sk = leg(knee_marker=False)
    r = np.zeros((1, sk.n_bones, 3))
    with pytest.raises(ValueError, match="chi2"):
        search(sk, REST[:1], r, marker_std=1e-5, chi2=0.0)
    with pytest.raises(ValueError, match="marker_std"):
        search(sk, REST[:1], r, marker_std=np.nan)


def leg_recording(sk: acm_rs.Skeleton, n: int = 30):
    """The demo rig and a small swing of ``sk`` seen through it (0.5 px noise), the first 10
    frames without detections."""
    from acm_rs.demo import demo_rig

    rig = demo_rig()
    rng = np.random.default_rng(3)
    r = 0.05 * np.sin(np.linspace(0, 3, n))[:, None, None] * rng.normal(size=(1, sk.n_bones, 3))
    t = np.tile(REST[0], (n, 1))
    _, markers = sk.forward(t, r)
    det = rig.project(markers) + rng.normal(scale=0.5, size=(len(rig), n, sk.n_markers, 2))
    det[:, :10] = np.nan  # the search keeps to frames with detections
    return rig, det


def test_track_names_the_joint_its_markers_leave_open():
    results = {}
    for knee_marker in (False, True):
        sk = leg(knee_marker)
        rig, det = leg_recording(sk)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = acm_rs.track(rig, sk, det, max_iter=5, second_solutions=2, misfit="off")
        said = [str(w.message) for w in caught if "do not decide" in str(w.message)]
        results[knee_marker] = (res.info["second_solutions"], said)
        if not knee_marker:
            res_open = res
    found, said = results[False]
    assert "knee" in found["joints"] and found["frames"] == [15, 25]
    assert len(said) == 1 and "knee" in said[0] and "widened" in said[0]
    assert "do not decide" in res_open.summary() and "knee" in res_open.summary()
    found, said = results[True]
    assert found["joints"] == {} and said == []
    with pytest.raises(ValueError, match="second_solutions"):
        acm_rs.track(rig, sk, det, second_solutions=-1)


def test_the_widening_is_sqrt_f_times_the_distance_over_1_96():
    sk = leg(knee_marker=False)
    d = mirror_distance(*REST[1:4])
    # two frames of the same pose; in the second the knee's SD already holds the mirror pose
    std = np.zeros((2, len(NAMES), 3))
    std[1, NAMES.index("knee")] = d
    found = search(sk, REST[[0, 0]], np.zeros((2, sk.n_bones, 3)), marker_std=1e-5, joints_std=std)
    expected = np.zeros(len(NAMES))
    expected[NAMES.index("knee")] = np.sqrt(0.5) * d / 1.96
    np.testing.assert_allclose(found.widening(), expected, rtol=1e-5)


def test_track_widens_the_open_joint_by_what_the_search_found_and_nothing_else():
    sk = leg(knee_marker=False)
    rig, det = leg_recording(sk)
    knee = NAMES.index("knee")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = acm_rs.track(rig, sk, det, max_iter=5, second_solutions=0, misfit="off")
        res = acm_rs.track(rig, sk, det, max_iter=5, second_solutions=2, misfit="off")
    assert "joints_std_widening" not in plain.info
    added = res.info["joints_std_widening"]
    found = res.info["second_solutions"]["joints"]["knee"]
    assert added[knee] == pytest.approx(np.sqrt(found["fraction"]) * found["distance"] / 1.96)
    assert found["widened_sd"] == pytest.approx(added[knee])
    assert np.count_nonzero(added) == 1
    # the same EM, the same Gaussian posterior: only the knee's SDs grow, by exactly `added`
    np.testing.assert_allclose(res.joints, plain.joints)
    expected = np.sqrt(plain.joints_std**2 + added[None, :, None] ** 2)
    np.testing.assert_allclose(res.joints_std, expected, rtol=1e-12)
    # the search found the mirror pose in both frames: the 95 % interval about the tracked knee
    # reaches it in every frame
    assert found["fraction"] == 1.0
    assert (1.96 * res.joints_std[:, knee] >= found["distance"] * (1 - 1e-9)).all()
    # a second search of the widened result measures against the Gaussian SDs: it finds
    # what the first found, and replaces the widening rather than adding to it
    again = acm_rs.second_solutions(res, frames=[15, 25])
    np.testing.assert_allclose(again.widening(), added, rtol=1e-9)
    widen(res, again)
    np.testing.assert_allclose(
        res.joints_std, np.sqrt(plain.joints_std**2 + again.widening()[None, :, None] ** 2)
    )
    renamed = dataclasses.replace(again, joint_names=tuple(n + "_" for n in NAMES))
    with pytest.raises(ValueError, match="another skeleton"):
        widen(res, renamed)


def test_the_bounded_memory_path_widens_the_open_joint_too():
    sk = leg(knee_marker=False)
    rig, det = leg_recording(sk, n=60)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = acm_rs.track(rig, sk, det, max_iter=5, second_solutions=2, memory_limit=1e5)
    assert res.info["bounded_memory"]
    found = res.info["second_solutions"]["joints"]
    assert list(found) == ["knee"] and found["knee"]["fraction"] == 1.0
    added = res.info["joints_std_widening"]
    assert np.flatnonzero(added).tolist() == [NAMES.index("knee")]
    knee_sd = res.joints_std[:, NAMES.index("knee")]
    assert (1.96 * knee_sd >= found["knee"]["distance"] * (1 - 1e-9)).all()
