"""Second poses with the same markers (acm_rs.tracking.ambiguity).

The truth is plain geometry: a knee that no marker pins swings about the hip-ankle axis, and
its mirror position lies at twice its distance from that axis (computed here with NumPy, not
with the product's forward kinematics).
"""

import numpy as np
import pytest

import acm_rs
from acm_rs.tracking.ambiguity import search

NAMES = ["pelvis", "hip", "knee", "ankle", "toe"]
PARENTS = [-1, 0, 1, 2, 3]
REST = np.array(
    [[0.0, 0.0, 10.0], [1.0, 0.0, 9.0], [1.6, 1.2, 5.5], [1.0, 0.2, 2.0], [1.0, 1.7, 1.8]]
)


def leg(knee_marker: bool) -> acm_rs.Skeleton:
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
        name="leg",
        units="cm",
    )


def mirror_distance(hip, knee, ankle) -> float:
    """Twice the knee's distance from the hip-ankle line."""
    n = (ankle - hip) / np.linalg.norm(ankle - hip)
    v = knee - hip
    return 2.0 * float(np.linalg.norm(v - n * (n @ v)))


def test_a_knee_no_marker_pins_has_a_mirror_pose():
    sk = leg(knee_marker=False)
    r = np.zeros((1, sk.n_bones, 3))
    found = search(sk, REST[:1], r, tolerance=1e-5)
    names = [name for name, *_ in found.ambiguous()]
    assert names == ["knee"]
    knee = NAMES.index("knee")
    assert found.distance[0, knee] == pytest.approx(mirror_distance(*REST[1:4]), rel=1e-5)
    assert "knee" in found.summary()


def test_a_marker_on_the_knee_decides_it():
    sk = leg(knee_marker=True)
    found = search(sk, REST[:1], np.zeros((1, sk.n_bones, 3)), tolerance=1e-5)
    assert found.ambiguous() == []
    assert np.isnan(found.distance).all()
    assert found.summary().startswith("no second pose")


def test_a_joint_inside_its_uncertainty_is_not_reported():
    sk = leg(knee_marker=False)
    d = mirror_distance(*REST[1:4])
    std = np.zeros((1, len(NAMES), 3))
    std[0, NAMES.index("knee")] = d / 1.96 / np.sqrt(3) * 1.01  # 1.96 |SD| just beyond d
    found = search(sk, REST[:1], np.zeros((1, sk.n_bones, 3)), tolerance=1e-5, joints_std=std)
    assert found.ambiguous() == []


def test_bad_tolerance_is_refused():
    sk = leg(knee_marker=False)
    with pytest.raises(ValueError, match="tolerance"):
        search(sk, REST[:1], np.zeros((1, sk.n_bones, 3)), tolerance=0.0)
