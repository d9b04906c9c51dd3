"""What a workflow step was made from: a small record next to its output.

A step of the project workflow writes ``<output>.step.json`` (for a folder output:
``<folder>/.step.json``) once its output is complete. The record holds the step name, the
package version, the settings used and a digest of every input file, with the ``run`` id of
the record of each input that has one. A later run compares a fresh record with the stored one
and re-runs the step when anything differs, so a changed input, setting or code version, or a
re-made upstream output (a new ``run`` id), invalidates the steps after it. An output without a
record was made outside the workflow (e.g. a calibration copied in) and is kept.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ._io import atomic_write
from ._version import __version__

__all__ = [
    "RECORD_FORMAT",
    "digest",
    "fresh_record",
    "read_record",
    "record_path",
    "stale",
    "write_record",
]

RECORD_FORMAT = "acm-rs-step"
_BIG = 64 << 20  # files above 64 MiB (videos) are fingerprinted, not hashed whole
_CHUNK = 1 << 20


def record_path(output: str | os.PathLike[str]) -> Path:
    """Where the record of ``output`` lives: ``<file>.step.json`` or ``<folder>/.step.json``."""
    p = Path(output)
    if p.is_dir() or not p.suffix:
        return p / ".step.json"
    return p.with_name(p.name + ".step.json")


def digest(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes; of the names and digests of a folder's files (recursively,
    hidden files excluded); for files over 64 MiB of the size and the first and last MiB."""
    p = Path(path)
    h = hashlib.sha256()
    if p.is_dir():
        for f in sorted(q for q in p.rglob("*") if q.is_file() and not q.name.startswith(".")):
            h.update(f.relative_to(p).as_posix().encode() + b"\0" + digest(f).encode())
        return "dir:" + h.hexdigest()
    size = p.stat().st_size
    with open(p, "rb") as fh:
        if size > _BIG:
            h.update(str(size).encode() + b"\0" + fh.read(_CHUNK))
            fh.seek(size - _CHUNK)
            h.update(fh.read(_CHUNK))
            return "head-tail:" + h.hexdigest()
        for block in iter(lambda: fh.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def read_record(output: str | os.PathLike[str]) -> dict | None:
    """The stored record of ``output``, or None (none, or unreadable)."""
    rp = record_path(output)
    try:
        rec = json.loads(rp.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return rec if isinstance(rec, dict) and rec.get("format") == RECORD_FORMAT else None


def fresh_record(
    step: str, inputs: Mapping[str, str | os.PathLike[str] | None], settings: Mapping[str, Any]
) -> dict:
    """The record a run of ``step`` would write now (without its ``run`` id).

    Parameters
    ----------
    step : str
        Step name.
    inputs : mapping name -> path or None
        The files/folders the step reads (None: not used).
    settings : mapping
        JSON-serialisable settings that change the result.
    """
    ins: dict[str, Any] = {}
    for name, path in sorted(inputs.items()):
        if path is None:
            ins[name] = None
            continue
        p = Path(path)
        if not p.exists():
            ins[name] = "missing"
            continue
        up = read_record(p)
        ins[name] = {"digest": digest(p), "run": up.get("run") if up else None}
    return {
        "format": RECORD_FORMAT,
        "step": step,
        "version": __version__,
        "settings": json.loads(json.dumps(settings, sort_keys=True, default=str)),
        "inputs": ins,
    }


def stale(output: str | os.PathLike[str], fresh: dict) -> str | None:
    """Why ``output`` must be (re)made, or None when it is up to date.

    A missing output, a record of an interrupted run, another version, changed settings or
    a changed input each give a reason; an output without a record is kept (None).
    """
    p = Path(output)
    if not p.exists():
        return f"{p.name} does not exist yet"
    old = read_record(p)
    if old is None:
        return None
    if old.get("interrupted"):
        return "the last run was interrupted"
    if old.get("version") != fresh["version"]:
        return f"made by acm-rs {old.get('version')}, this is {fresh['version']}"
    if old.get("settings") != fresh["settings"]:
        a, b = old.get("settings") or {}, fresh["settings"]
        keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        return f"settings changed: {', '.join(keys)}"
    a, b = old.get("inputs") or {}, fresh["inputs"]
    changed = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
    if changed:
        return f"input(s) changed: {', '.join(changed)}"
    return None


def write_record(output: str | os.PathLike[str], fresh: dict, interrupted: bool = False) -> dict:
    """Store ``fresh`` (with a new ``run`` id) as the record of the finished ``output``."""
    rec = {**fresh, "run": uuid.uuid4().hex, "interrupted": bool(interrupted)}
    with atomic_write(record_path(output)) as fh:
        json.dump(rec, fh, indent=1, sort_keys=True)
        fh.write("\n")
    return rec
