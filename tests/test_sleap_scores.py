"""SLEAP scores as likelihoods (issue 27 items 2 and 9): point scores above 1 are normal
(confidence-map peaks), points of user (proofread) instances carry no score, and a cutoff
made for DeepLabCut that drops most of a camera's points is said.

The analysis file is written here with h5py in the layout SLEAP writes (``tracks``
``(n_tracks, 2, n_nodes, n_frames)``, ``point_scores`` ``(n_tracks, n_nodes, n_frames)``,
``node_names``, ``track_names``); a test on SLEAP's own files is issue 27's corpus.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from acm_rs.labels import mask_by_likelihood
from acm_rs.sleap import read_sleap_analysis


def _analysis(path, scores: np.ndarray) -> None:
    n_tracks, n_nodes, n_frames = scores.shape
    rng = np.random.default_rng(0)
    tracks = rng.uniform(10, 500, (n_tracks, 2, n_nodes, n_frames))
    tracks[0, :, 1, 3] = np.nan  # node 1 not predicted in frame 3
    with h5py.File(path, "w") as f:
        f["tracks"] = tracks
        f["point_scores"] = scores
        f["node_names"] = np.array([b"nose", b"tail"])
        f["track_names"] = np.array([b"track_0"])


def test_scores_above_one_are_clipped_and_user_points_are_certain(tmp_path):
    scores = np.full((1, 2, 6), 0.95)
    scores[0, 0, 0] = 1.35  # a typical SLEAP peak above 1
    scores[0, :, 4] = np.nan  # a user instance: SLEAP writes no score
    _analysis(tmp_path / "a.analysis.h5", scores)
    points, lik, frames, nodes = read_sleap_analysis(tmp_path / "a.analysis.h5")
    assert nodes == ["nose", "tail"] and points.shape == (6, 2, 2)
    assert lik[0, 0] == 1.0  # clipped
    np.testing.assert_array_equal(lik[4], [1.0, 1.0])  # user-labelled: certain
    assert np.isnan(lik[3, 1]) and np.isnan(points[3, 1]).all()  # not predicted
    assert lik[1, 0] == 0.95
    # the user points survive any cutoff
    kept = mask_by_likelihood(points[None], lik[None], 0.99, warn=False)[0]
    assert np.isfinite(kept[4]).all() and np.isfinite(kept[0, 0]).all()


def test_unclipped_sleap_scores_get_the_right_advice():
    pts = np.zeros((1, 3, 2, 2))
    lik = np.full((1, 3, 2), 0.9)
    lik[0, 0, 0] = 1.35
    with pytest.raises(ValueError, match="SLEAP scores exceed 1") as err:
        mask_by_likelihood(pts, lik, 0.5)
    assert "divide by 100" not in str(err.value)
    lik[0, 0, 0] = 87.0
    with pytest.raises(ValueError, match="divide by 100"):
        mask_by_likelihood(pts, lik, 0.5)


def test_a_cutoff_that_drops_most_of_a_camera_is_said():
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 100, (2, 50, 4, 2))
    lik = np.full((2, 50, 4), 0.95)
    lik[1] = rng.uniform(0.3, 0.8, (50, 4))  # camera 1: scores on another scale
    lik[1, :5] = 0.95
    with pytest.warns(UserWarning, match=r"pcutoff 0.9 drops most of the detected points of "
                      r"camera 1: 90 %"):  # fmt: skip
        out = mask_by_likelihood(pts, lik, 0.9)
    assert np.isfinite(out[0]).all() and np.isfinite(out[1, :5]).all()
    assert np.isnan(out[1, 5:]).all()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mask_by_likelihood(pts, lik, 0.2)  # keeps everything: nothing to say
