"""Run many sessions in parallel on a Dask distributed cluster, resumably.

Each session runs in a worker process. Its outputs go to a staging folder that replaces the
session's output folder only when the session function returned; a ``DONE.json`` marker is
written last. A rerun skips sessions with a marker (unless ``overwrite``), so a killed batch
loses only the sessions that were running. One failing session never stops the others: its
error and traceback are in the returned status and in ``<session>/.<output>.failed.json``.
See ``docs/project.md`` for clusters (``LocalCluster``, a scheduler address, SLURM via
dask-jobqueue).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import time
import traceback
import uuid
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ._io import atomic_write

__all__ = [
    "DONE_MARKER",
    "SessionStatus",
    "default_session_func",
    "is_done",
    "run",
    "summary",
    "write_report",
]

DONE_MARKER = "DONE.json"

SessionFunc = Callable[[Path, Path], Any]


@dataclass
class SessionStatus:
    """What happened to one session.

    Attributes
    ----------
    session : str
        Session folder name.
    path : str
        Session folder.
    status : str
        ``"done"`` (ran now), ``"skipped"`` (finished before: done-marker present) or
        ``"failed"``.
    seconds : float
        Wall time of the session function (0 when skipped).
    output : str
        The session's output folder.
    result : Any
        JSON-able value returned by the session function (from the marker when skipped).
    error : str
        ``"<ExceptionType>: message"`` for a failed session, else ``""``.
    traceback : str
        Formatted traceback of a failure.
    worker : str
        Address of the worker that ran it.
    """

    session: str
    path: str
    status: str
    seconds: float = 0.0
    output: str = ""
    result: Any = None
    error: str = ""
    traceback: str = ""
    worker: str = field(default="", repr=False)

    @property
    def ok(self) -> bool:
        """True unless the session failed."""
        return self.status != "failed"


def is_done(session: str | Path, output: str = "acm-rs") -> bool:
    """Whether a session has a done-marker (finished in an earlier run)."""
    return (Path(session) / output / DONE_MARKER).is_file()


def default_session_func(session: Path, out: Path) -> Any:
    """The standard pipeline for a project session (``acm_rs.pipeline.run_session``).

    Pass ``func`` to :func:`run` to run your own per-session function instead.
    """
    try:
        from .pipeline import run_session  # type: ignore[import-not-found]
    except ImportError:
        raise ValueError(
            "no default per-session pipeline is available in this version of acm-rs; pass "
            "func=your_function(session_dir, out_dir) to acm_rs.batch.run"
        ) from None
    return run_session(session, out)


def _jsonable(v: Any) -> Any:
    try:
        json.dumps(v)
        return v
    except (TypeError, ValueError):
        return repr(v)


def _run_one(
    session: str, func: SessionFunc, output: str, overwrite: bool, worker_env: dict
) -> dict:
    """Worker side: run one session with staging, marker and failure capture."""
    for k, v in worker_env.items():
        os.environ.setdefault(k, v)
    path = Path(session)
    out = path / output
    marker = out / DONE_MARKER
    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):
        worker = ""
    base = {"session": path.name, "path": str(path), "output": str(out), "worker": worker}
    if marker.is_file() and not overwrite:
        try:
            prev = json.loads(marker.read_text(encoding="utf-8")).get("result")
        except (OSError, ValueError):
            prev = None
        return base | {"status": "skipped", "result": prev}
    failed = path / f".{output}.failed.json"
    # stale staging folders of killed runs
    for stale in path.glob(f".{output}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    staging = path / f".{output}.partial-{uuid.uuid4().hex[:8]}"
    start = time.perf_counter()
    try:
        if not path.is_dir():
            raise FileNotFoundError(f"{path}: session folder does not exist")
        staging.mkdir()
        result = _jsonable(func(path, staging))
        seconds = time.perf_counter() - start
        record = {
            "session": path.name,
            "status": "done",
            "seconds": seconds,
            "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "result": result,
        }
        with atomic_write(staging / DONE_MARKER, "w") as fh:
            json.dump(record, fh, indent=2)
        old = None
        if out.exists():
            old = path / f".{output}.old-{uuid.uuid4().hex[:8]}"
            os.replace(out, old)
        os.replace(staging, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        with contextlib.suppress(FileNotFoundError):
            failed.unlink()
        return base | {"status": "done", "seconds": seconds, "result": result}
    except BaseException as exc:  # noqa: BLE001 - every failure is reported, never raised
        if isinstance(exc, KeyboardInterrupt | SystemExit):
            raise
        seconds = time.perf_counter() - start
        shutil.rmtree(staging, ignore_errors=True)
        info = base | {
            "status": "failed",
            "seconds": seconds,
            "error": f"{type(exc).__name__}: {exc}",
            "traceback": traceback.format_exc(),
        }
        with contextlib.suppress(OSError):
            with atomic_write(failed, "w") as fh:
                json.dump(info, fh, indent=2)
        return info


def _session_path(s: Any) -> str:
    p = getattr(s, "path", s)
    return str(Path(p).resolve())


def run(
    sessions: Iterable[str | Path | Any],
    func: SessionFunc | None = None,
    client: Any = None,
    *,
    overwrite: bool = False,
    output: str = "acm-rs",
    n_workers: int = 2,
    threads_per_worker: int = 1,
    progress: bool | None = False,
) -> list[SessionStatus]:
    """Run ``func(session_dir, out_dir)`` for every session on a Dask cluster.

    Parameters
    ----------
    sessions : iterable of path or :class:`acm_rs.project.Session`
        Session folders.
    func : callable, optional
        ``func(session_dir: Path, out_dir: Path) -> JSON-able summary``; writes its files into
        ``out_dir`` (a staging folder renamed to ``<session>/<output>`` when ``func`` returns).
        Must be picklable (a module-level function). Default :func:`default_session_func`.
    client : None, str or distributed.Client
        None: a ``LocalCluster(n_workers, threads_per_worker)`` started and closed here;
        a string: the address of a running scheduler (``"tcp://host:8786"``); or a Client
        (e.g. of a ``dask_jobqueue.SLURMCluster``).
    overwrite : bool
        Rerun sessions that have a done-marker (their old output is replaced atomically).
    output : str
        Name of the output folder inside each session.
    n_workers, threads_per_worker : int
        Size of the local cluster (ignored with ``client``). Each worker's Rust thread pool is
        limited to ``threads_per_worker`` threads (``RAYON_NUM_THREADS``) to avoid
        oversubscription.
    progress : bool or None
        Show a progress bar (tqdm); None: only when stderr is a terminal; default quiet.

    Returns
    -------
    list of SessionStatus
        One per session, in input order. Failures are reported here, never raised.
    """
    from distributed import Client, LocalCluster, as_completed

    func = default_session_func if func is None else func
    paths = [_session_path(s) for s in sessions]
    if len(set(paths)) != len(paths):
        dup = sorted({p for p in paths if paths.count(p) > 1})
        raise ValueError(f"sessions listed twice: {dup}")
    if not paths:
        return []
    env = {
        "RAYON_NUM_THREADS": str(threads_per_worker),
        "OMP_NUM_THREADS": str(threads_per_worker),
    }
    cluster = None
    own_client = False
    if client is None:
        cluster = LocalCluster(
            n_workers=n_workers,
            threads_per_worker=threads_per_worker,
            processes=True,
            dashboard_address=":0",
            env=env,
        )
        client = Client(cluster)
        own_client = True
    elif isinstance(client, str):
        client = Client(client)
        own_client = True
    results: dict[str, SessionStatus] = {}
    token = uuid.uuid4().hex[:8]  # fresh task keys: never reuse results of an earlier run
    try:
        futures = {
            client.submit(
                _run_one, p, func, output, overwrite, env, key=f"acm-rs-{Path(p).name}-{i}-{token}"
            ): p
            for i, p in enumerate(paths)
        }
        bar = None
        if progress is not False:
            from tqdm.auto import tqdm

            bar = tqdm(
                total=len(futures), desc="sessions", unit="session",
                disable=None if progress is None else False,
            )  # fmt: skip
        for fut in as_completed(futures):
            p = futures[fut]
            try:
                rec = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. the worker died (KilledWorker)
                rec = {
                    "session": Path(p).name,
                    "path": p,
                    "status": "failed",
                    "output": str(Path(p) / output),
                    "error": f"{type(exc).__name__}: {exc}",
                    "traceback": "".join(traceback.format_exception(exc)),
                }
            results[p] = SessionStatus(**rec)
            if bar is not None:
                bar.update(1)
                bar.set_postfix_str(f"{Path(p).name}: {rec['status']}")
        if bar is not None:
            bar.close()
    finally:
        if own_client:
            client.close()
        if cluster is not None:
            cluster.close()
    return [results[p] for p in paths]


def summary(statuses: Iterable[SessionStatus]) -> str:
    """A short report: counts per status and every failure with its error."""
    st = list(statuses)
    counts = {k: sum(s.status == k for s in st) for k in ("done", "skipped", "failed")}
    lines = [
        f"{len(st)} sessions: {counts['done']} done, {counts['skipped']} skipped (finished "
        f"before), {counts['failed']} failed"
    ]
    lines += [f"  FAILED {s.session}: {s.error}" for s in st if s.status == "failed"]
    return "\n".join(lines)


def write_report(path: str | Path, statuses: Iterable[SessionStatus]) -> Path:
    """Write the statuses as JSON (atomically), e.g. ``<project>/batch-<time>.json``."""
    with atomic_write(path, "w") as fh:
        json.dump([asdict(s) for s in statuses], fh, indent=2, default=repr)
    return Path(path)


# -- command line ---------------------------------------------------------------------------------
def _cmd_batch(args) -> int:
    from .project import find_sessions, load_config

    config = load_config(args.project)
    sessions = find_sessions(config)
    if args.sessions:
        wanted = set(args.sessions)
        unknown = sorted(wanted - {s.name for s in sessions})
        if unknown:
            raise ValueError(f"unknown sessions {unknown}; sessions: {[s.name for s in sessions]}")
        sessions = [s for s in sessions if s.name in wanted]
    print(f"acm-rs batch: {len(sessions)} sessions of {config.root}")
    generic = not (config.root / "skeleton.toml").is_file()
    warning = (
        f"acm-rs batch: WARNING: no learned skeleton ({config.root / 'skeleton.toml'}): every "
        f"session is tracked with the generic {config.project['model']} model, whose bones "
        "are not the animal's; run `acm-rs run-all --steps learn` with manual labels first"
    )
    if generic:
        print(warning, file=sys.stderr, flush=True)
    statuses = run(
        sessions,
        client=args.scheduler,
        overwrite=args.overwrite,
        output=config.paths["output"],
        n_workers=args.workers,
        threads_per_worker=args.threads,
        progress=None,
    )
    report = write_report(config.root / f"batch-{time.strftime('%Y%m%d-%H%M%S')}.json", statuses)
    print(summary(statuses) + (" (GENERIC model, nothing learned)" if generic else ""))
    print(f"  report: {report}")
    if generic:
        print(warning, file=sys.stderr)
    return 0 if all(s.ok for s in statuses) else 1


def add_subcommands(sub) -> None:
    """Add ``acm-rs batch`` to an argparse subparsers object."""
    p = sub.add_parser("batch", help="run every session of a project on a Dask cluster")
    p.add_argument("project", nargs="?", default=".", help="project folder (config.toml)")
    p.add_argument("--sessions", nargs="+", help="only these sessions (folder names)")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://host:8786)")
    p.add_argument("--workers", type=int, default=2, help="local workers (default 2)")
    p.add_argument("--threads", type=int, default=1, help="threads per local worker")
    p.add_argument("--overwrite", action="store_true", help="rerun finished sessions")
    p.set_defaults(func=_cmd_batch)
