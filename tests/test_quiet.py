"""Progress output: the Python API is quiet unless asked; ``progress=None`` (what the command
line passes) shows bars and per-iteration lines only on a terminal."""

from __future__ import annotations

import io
import sys

import pytest

import acm_rs
from acm_rs import datasets, models
from acm_rs.demo import demo_rig


@pytest.fixture(scope="module")
def problem():
    rig = demo_rig()
    sk = models.rat()
    t, r = datasets.smooth_motion(sk, 12, seed=1)
    det, lik = datasets.dlc_like_detections(rig, sk, t, r, seed=2)
    labels = datasets.noisy_labels(rig, sk, t, r, 1.0, missing=0.2, seed=3)
    return rig, sk, det, lik, labels


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_track_is_quiet_unless_asked(problem, capsys, monkeypatch):
    rig, sk, det, lik, _ = problem
    acm_rs.track(rig, sk, det, likelihood=lik, max_iter=2)
    acm_rs.track(rig, sk, det, likelihood=lik, max_iter=2, progress=None)  # stderr: no tty
    assert capsys.readouterr() == ("", "")
    tty = _Tty()
    monkeypatch.setattr(sys, "stderr", tty)
    res = acm_rs.track(rig, sk, det, likelihood=lik, max_iter=2, progress=None)
    lines = tty.getvalue().splitlines()
    # one line per EM iteration (random walk, then the velocity model)
    assert sum(line.startswith("EM iteration") for line in lines) == len(res.em_history) >= 2
    assert any(line.startswith("tracked 12 frames") for line in lines)


def test_learning_bar_only_when_asked_or_on_a_terminal(problem, capsys):
    rig, sk, _, _, labels = problem
    fast = {"lm_iter": 3, "rounds": 1, "options": {"maxiter": 5}}
    # rounds=1: L-BFGS-B after Levenberg-Marquardt, the stage with the tqdm bar "skeleton"
    acm_rs.learn_skeleton(rig, sk, labels, **fast)
    acm_rs.learn_skeleton(rig, sk, labels, progress=None, **fast)  # tqdm(disable=None), no tty
    assert capsys.readouterr().err == ""
    acm_rs.learn_skeleton(rig, sk, labels, progress=True, **fast)
    assert "skeleton" in capsys.readouterr().err
