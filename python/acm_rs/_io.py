"""Atomic file output: write to a temporary file in the target folder, then rename."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO


def new_file_mode() -> int:
    """The permission bits of a normal new file: ``0o666`` minus the process umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "w") -> Iterator[IO]:
    """Open a temporary file next to ``path``; on success it replaces ``path`` atomically.

    A crash or exception leaves any previous ``path`` untouched and removes the temporary file.
    """
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write {target}: {exc.strerror}") from None
    # mkstemp creates 0600 files; give the result the permissions of a normal new file.
    os.chmod(tmp, new_file_mode())
    try:
        encoding = None if "b" in mode else "utf-8"
        with os.fdopen(fd, mode, encoding=encoding) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def check_output_path(
    path: str | os.PathLike[str], overwrite: bool = False, what: str = "output"
) -> Path:
    """Check, before any work, that ``path`` may be written: it does not exist (unless
    ``overwrite``), is not a folder, and its folder (or the nearest existing parent) is a
    writable folder (probed by creating and removing a temporary file).

    Raises
    ------
    ValueError
        Naming the path and the fix (``--overwrite``, another folder).
    """
    p = Path(path)
    if p.is_dir():
        raise ValueError(f"{what} {p} is a folder; give a file name")
    if p.exists() and not overwrite:
        raise ValueError(f"{what} {p} exists; pass --overwrite to replace it")
    parent = p.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"cannot write {what} {p}: {parent} is not a folder")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".acm-rs-probe.", dir=parent)
        os.close(fd)
        os.unlink(tmp)
    except OSError as exc:
        raise ValueError(
            f"cannot write {what} {p}: the folder {parent} is not writable ({exc.strerror}); "
            "choose another output folder"
        ) from None
    return p
