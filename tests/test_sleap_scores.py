"""SLEAP scores as likelihoods (issue 27 items 2 and 9): point scores above 1 are normal
(confidence-map peaks), points of user (proofread) instances carry no score, and a cutoff
made for DeepLabCut that drops most of a camera's points is said.

The analysis file is written here with h5py in the layout SLEAP writes (``tracks``
``(n_tracks, 2, n_nodes, n_frames)``, ``point_scores`` ``(n_tracks, n_nodes, n_frames)``,
``node_names``, ``track_names``); a test on SLEAP's own files is issue 27's corpus.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from acm_rs.dlc import concat_labels, read_labels
from acm_rs.labels import PCUTOFF_BY_SOURCE, default_pcutoff, mask_by_likelihood
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


REAL = Path(__file__).parent / "data" / "real"


def test_each_source_gets_its_own_default_cutoff():
    assert default_pcutoff(["sleap", "sleap", None])[0] == PCUTOFF_BY_SOURCE["sleap"] == 0.2
    assert default_pcutoff(["deeplabcut"])[0] == PCUTOFF_BY_SOURCE["deeplabcut"] == 0.9
    assert default_pcutoff([None])[0] == 0.9  # nothing known: DeepLabCut's
    with pytest.raises(ValueError, match="different scales.*explicitly"):
        default_pcutoff(["deeplabcut", "sleap"])
    with pytest.raises(ValueError, match="different scales"):
        default_pcutoff(["deeplabcut+sleap"])  # one camera, two recordings from two tools


def test_real_files_get_the_cutoff_of_their_tool_and_sleap_keeps_its_points():
    """On the real proofread sleap-anipose views (predicted points with scores), the SLEAP
    default keeps most predicted points where DeepLabCut's 0.9 would drop most of them."""
    folder = REAL / "sleap" / "sleap_anipose"
    views = [folder / f"minimal_{v}_proofread.slp" for v in ("mid", "top")]
    dlc = REAL / "dlc" / "CollectedData_Mackenzie.h5"
    if not all(p.exists() for p in [*views, dlc]):
        pytest.skip("the real-file corpus is not present")
    ls = read_labels(views)
    assert ls.sources == ["sleap", "sleap"]
    cut, why = ls.resolve_pcutoff(None)
    assert cut == 0.2 and "SLEAP" in why
    assert ls.resolve_pcutoff("auto") == (0.2, why) and ls.resolve_pcutoff(0.5)[0] == 0.5
    lik = ls.likelihood
    present = np.isfinite(ls.points).all(axis=-1)
    kept = lambda c: np.mean(lik[present] >= c)  # noqa: E731
    assert kept(cut) > 0.8 > 0.4 > kept(0.9)
    d = read_labels([dlc])
    assert d.sources == ["deeplabcut"] and d.resolve_pcutoff(None)[0] == 0.9
    assert concat_labels([ls, ls]).sources == ["sleap", "sleap"]


def test_project_pcutoff_is_auto_by_default_and_checked(tmp_path):
    from acm_rs.project import init_project, load_config

    cfg = load_config(init_project(tmp_path / "p"))
    assert cfg.tracking["pcutoff"] == "auto"
    bad = tmp_path / "q"
    init_project(bad, tracking={"pcutoff": 0.5})
    assert load_config(bad / "config.toml").tracking["pcutoff"] == 0.5
    text = (bad / "config.toml").read_text().replace("pcutoff = 0.5", 'pcutoff = "high"')
    (bad / "config.toml").write_text(text)
    with pytest.raises(ValueError, match="pcutoff"):
        load_config(bad / "config.toml")
