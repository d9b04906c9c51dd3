"""Batch runs on a 2-worker Dask LocalCluster: failures are isolated, reruns resume."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("distributed")
import cloudpickle  # noqa: E402

from acm_rs import batch  # noqa: E402

# the workers cannot import this test module: ship its functions by value
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def track_session(session: Path, out: Path) -> dict:
    """A small real job: read the session's numbers, write an export, return a summary."""
    data = np.array((session / "data.txt").read_text().split(), dtype=float)
    if data.size == 0:
        raise ValueError(f"{session.name}: data.txt is empty")
    np.save(out / "mean.npy", data.mean())
    (out / "pid.txt").write_text(str(os.getpid()))
    return {"n": int(data.size), "mean": float(data.mean()),
            "rayon": os.environ.get("RAYON_NUM_THREADS")}  # fmt: skip


@pytest.fixture
def sessions(tmp_path):
    rng = np.random.default_rng(0)
    out = []
    for i in range(4):
        s = tmp_path / f"s{i}"
        s.mkdir()
        np.savetxt(s / "data.txt", rng.normal(size=5 + i) if i != 2 else np.zeros(0))
        out.append(s)
    return out


@pytest.fixture(scope="module")
def client():
    from distributed import Client, LocalCluster

    cluster = LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0"
    )
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()


def test_failure_isolated_and_resume(sessions, client):
    res = batch.run(sessions, track_session, client, progress=False)
    assert [r.session for r in res] == ["s0", "s1", "s2", "s3"]
    assert [r.status for r in res] == ["done", "done", "failed", "done"]
    bad = res[2]
    assert "ValueError: s2: data.txt is empty" in bad.error and "track_session" in bad.traceback
    assert not (sessions[2] / "acm-rs").exists()  # no half-written output
    assert json.loads((sessions[2] / ".acm-rs.failed.json").read_text())["status"] == "failed"
    for r, s in zip(res, sessions, strict=True):
        if r.ok:
            want = np.loadtxt(s / "data.txt").mean()
            assert np.load(s / "acm-rs" / "mean.npy") == pytest.approx(want)
            assert r.result["mean"] == pytest.approx(want) and r.seconds > 0
            marker = json.loads((s / "acm-rs" / batch.DONE_MARKER).read_text())
            assert marker["status"] == "done" and marker["result"]["n"] == r.result["n"]
    assert not list(sessions[0].glob(".acm-rs.partial-*"))
    assert "1 failed" in batch.summary(res) and "FAILED s2: ValueError" in batch.summary(res)

    # fix the broken session and rerun: finished sessions are skipped, s2 runs now
    np.savetxt(sessions[2] / "data.txt", np.ones(3))
    before = (sessions[0] / "acm-rs" / "pid.txt").stat().st_mtime_ns
    res2 = batch.run(sessions, track_session, client, progress=False)
    assert [r.status for r in res2] == ["skipped", "skipped", "done", "skipped"]
    assert res2[0].result == res[0].result  # from the marker
    assert (sessions[0] / "acm-rs" / "pid.txt").stat().st_mtime_ns == before
    assert not (sessions[2] / ".acm-rs.failed.json").exists()

    # overwrite reruns everything and replaces the old outputs
    (sessions[1] / "acm-rs" / "stale.txt").write_text("old")
    res3 = batch.run(sessions, track_session, client, overwrite=True, progress=False)
    assert all(r.status == "done" for r in res3)
    assert not (sessions[1] / "acm-rs" / "stale.txt").exists()


def test_killed_run_leaves_staging_that_is_cleaned(sessions, client):
    """A staging folder left by a killed job is removed; the session runs again."""
    stale = sessions[0] / ".acm-rs.partial-deadbeef"
    stale.mkdir()
    (stale / "half.npy").write_bytes(b"x")
    res = batch.run(sessions[:1], track_session, client, progress=False)
    assert res[0].status == "done" and not stale.exists()


def test_local_cluster_default_and_missing_session(sessions, tmp_path):
    """client=None starts a 2-worker LocalCluster; a missing folder is a reported failure."""
    res = batch.run([sessions[0], tmp_path / "nope"], track_session, progress=False, output="out")
    assert res[0].status == "done" and res[0].result["rayon"] == "1"
    assert (sessions[0] / "out" / batch.DONE_MARKER).is_file()
    assert res[1].status == "failed" and "does not exist" in res[1].error
    report = batch.write_report(tmp_path / "batch.json", res)
    assert [r["status"] for r in json.loads(report.read_text())] == ["done", "failed"]


def test_duplicate_sessions_rejected(sessions):
    with pytest.raises(ValueError, match="sessions listed twice"):
        batch.run([sessions[0], sessions[0]], track_session, progress=False)
    assert batch.run([], track_session) == []
