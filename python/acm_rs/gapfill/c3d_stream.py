"""C3D files too large for ezc3d's in-memory model, read and written in blocks (issue 16).

ezc3d holds every point of every frame as an object: reading 65,535 frames x 41 markers costs
1.3 GB, writing 200,000 frames more than 2 GB. For files whose data section is larger than
:data:`STREAM_BYTES` (Intel floating-point format, the format of Vicon, Qualisys and CMU
files and of every file ezc3d writes) acm-rs keeps ezc3d for what it does well, the header and
the parameter section, and moves the frames itself:

* **Reading.** ezc3d parses a copy of the file cut after its first frame; the frames are read
  from the file through a memory map, :data:`BLOCK` frames at a time, and decoded as ezc3d
  decodes them: coordinates as stored; a negative fourth word marks a missing point; otherwise
  its high byte times ``|POINT:SCALE|`` is the residual (its low 7 bits are the camera mask).
* **Writing.** ezc3d writes a one-frame file with the output's parameters; its header and
  parameter section are kept, the frame counts patched in place (header word 5 and
  POINT:FRAMES, both 16-bit and saturated at 65535 as ezc3d writes them; POINT:LONG_FRAMES and
  TRIAL:ACTUAL_END_FIELD carry longer counts) and the frames appended block by block, encoded
  as ezc3d encodes them. Analog words are copied from the source file unchanged (their
  parameters are the source's, so ezc3d would write the same words).

The result is byte for byte the file ezc3d writes (``tests/test_c3d_stream.py``), in memory
of one block.
"""

from __future__ import annotations

import contextlib
import os
import struct
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

#: Data sections above this size (bytes) are read and written in blocks (64 MiB: about
#: 25,000 frames of 41 markers, which ezc3d reads in ~0.5 GB).
STREAM_BYTES = 64 * 2**20
#: Frames per block.
BLOCK = 8192
#: The processor byte of the parameter section for Intel (little-endian IEEE) files.
_INTEL = 84


def header_layout(p: Path) -> dict[str, Any] | None:
    """The raw header of a C3D: data offset (bytes), points, analog words per frame, scale,
    processor, first and last frame (words 4 and 5); None when the file is too short for a
    header (the readers refuse it later)."""
    with open(p, "rb") as fh:
        head = fh.read(512)
        if len(head) < 512 or head[0] < 2:
            return None
        fh.seek((head[0] - 1) * 512)
        params = fh.read(4)
    if len(params) < 4:
        return None
    order = ">" if params[3] == 86 else "<"
    n_points, n_analog, first, last = struct.unpack(order + "4H", head[2:10])
    scale = struct.unpack(order + "f", head[12:16])[0] if params[3] == _INTEL else 0.0
    data_block = struct.unpack(order + "H", head[16:18])[0]
    return {
        "offset": (data_block - 1) * 512,
        "n_points": n_points,
        "words": 4 * n_points + n_analog,
        "scale": scale,
        "processor": params[3],
        "first": first,
        "last": last,
    }


def wants_streaming(p: Path) -> bool:
    """True when a C3D's data section exceeds :data:`STREAM_BYTES` and its format (Intel
    floating point) can be read in blocks."""
    h = header_layout(p)
    if h is None or h["processor"] != _INTEL or not h["scale"] < 0 or h["offset"] < 512:
        return False
    return p.stat().st_size - h["offset"] > STREAM_BYTES


#: The parameters that say how many frames a file has, with the value that says "one frame"
#: (ezc3d reads as many frames as they say, and crashes when a file holds fewer).
_FRAME_COUNTS = (("POINT", "FRAMES"), ("POINT", "LONG_FRAMES"), ("TRIAL", "ACTUAL_END_FIELD"))


def read_parameters(p: Path):
    """The ezc3d object of a C3D's header and parameters, read from a copy cut after its first
    frame (so ezc3d reads one frame, not all); the copy is deleted.

    The copy's frame counts (header word 5, POINT:FRAMES, POINT:LONG_FRAMES,
    TRIAL:ACTUAL_END_FIELD) say one frame; the object gets the original values back."""
    import ezc3d

    h = header_layout(p)
    with open(p, "rb") as fh:
        # one frame, and some bytes more in case the parameters size a frame larger than the
        # header does (ezc3d then reads past it; past the end of a file it would crash)
        head = bytearray(fh.read(h["offset"] + 8 * h["words"] + 512))
    head[8:10] = struct.pack("<H", h["first"])  # last frame = first frame
    base = (head[0] - 1) * 512
    sec = bytes(head[base : h["offset"]])
    original = {}
    for group, name in _FRAME_COUNTS:
        found = _find_parameter(sec, group, name)
        if found is None:
            continue
        at, kind, count = found
        at += base
        dtype = {1: "<i1", 2: "<i2", 4: "<f4"}.get(kind)
        if dtype is None or count < 1:
            continue
        value = np.frombuffer(bytes(head[at : at + abs(kind) * count]), dtype=dtype).copy()
        original[(group, name)] = value
        one = value.copy()
        if name == "ACTUAL_END_FIELD":
            start = _find_parameter(sec, "TRIAL", "ACTUAL_START_FIELD")
            if start is None or start[1] != kind or start[2] != count:
                one[:] = 0
                one[0] = 1  # frame 1
            else:
                one = np.frombuffer(sec[start[0] : start[0] + abs(kind) * count], dtype=dtype)
        else:
            one[0] = 1
        head[at : at + abs(kind) * count] = one.astype(dtype).tobytes()
    fd, tmp = tempfile.mkstemp(suffix=".c3d")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(head)
        c = ezc3d.c3d(tmp)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
    for (group, name), value in original.items():
        c["parameters"][group][name]["value"] = value.astype(np.float64 if value.dtype.kind
                                                             == "f" else np.int64)  # fmt: skip
    return c


def decode_residuals(word: np.ndarray, scale: float) -> np.ndarray:
    """Residuals from the fourth word of each point (float format), as ezc3d reads them:
    -1 where the word is negative (missing point), else ``high byte × |scale|``."""
    w = word.astype(np.int64)
    res = ((np.abs(w) >> 8) & 0xFF) * abs(float(scale))
    return np.where(word < 0, -1.0, res)


def encode_residuals(residual: np.ndarray, scale: float) -> np.ndarray:
    """The fourth word of each point as ezc3d writes it: -1 for a missing point (negative
    residual), else ``(int(residual / |scale|) & 0xFF) << 8`` (camera mask 0)."""
    q = (np.floor(np.maximum(residual, 0.0) / abs(float(scale))).astype(np.int64) & 0xFF) << 8
    return np.where(residual < 0, -1.0, q.astype(np.float64))


def read_points(
    p: Path, offset: int, words: int, n_points: int, n_frames: int, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Points of a float-format C3D through a memory map, in blocks.

    Returns
    -------
    xyz : ndarray, shape (n_frames, n_points, 3)
        Coordinates as stored (NaN where the point is missing).
    residual : ndarray, shape (n_frames, n_points)
        Residuals in POINT:UNITS, -1 where missing.
    """
    raw = np.memmap(p, dtype="<f4", mode="r", offset=offset, shape=(n_frames, words))
    xyz = np.empty((n_frames, n_points, 3))
    residual = np.empty((n_frames, n_points))
    for a in range(0, n_frames, BLOCK):
        b = min(n_frames, a + BLOCK)
        blk = np.asarray(raw[a:b, : 4 * n_points]).reshape(b - a, n_points, 4)
        xyz[a:b] = blk[:, :, :3]
        residual[a:b] = decode_residuals(blk[:, :, 3], scale)
        xyz[a:b][residual[a:b] < 0] = np.nan
    del raw
    return xyz, residual


def _find_parameter(sec: bytes, group: str, name: str) -> tuple[int, int, int] | None:
    """(byte offset of the value, type, number of values) of a parameter in a little-endian
    parameter section, None if absent."""
    pos, groups, found = 4, {}, []
    while pos + 2 <= len(sec):
        n_chars = abs(int.from_bytes(sec[pos : pos + 1], "little", signed=True))
        if n_chars == 0:
            break
        ident = int.from_bytes(sec[pos + 1 : pos + 2], "little", signed=True)
        body = pos + 2 + n_chars
        label = bytes(sec[pos + 2 : body]).decode("latin-1").upper()
        step = int.from_bytes(sec[body : body + 2], "little", signed=True)
        if ident < 0:
            groups[-ident] = label
        elif label == name:
            q = body + 2
            kind = int.from_bytes(sec[q : q + 1], "little", signed=True)
            dims = list(sec[q + 2 : q + 2 + sec[q + 1]])
            found.append((ident, q + 2 + sec[q + 1], kind, int(np.prod(dims, dtype=np.int64))))
        if step == 0:
            break
        pos = body + step
    for ident, at, kind, count in found:
        if groups.get(ident) == group:
            return at, kind, count
    return None


def write_streamed(
    path: Path,
    c,
    xyz: np.ndarray,
    residual: np.ndarray,
    analog: dict[str, Any] | None,
) -> None:
    """Write a float-format C3D in blocks: ezc3d's header and parameters of ``c`` (made for
    ``len(xyz)`` frames), then the frames; atomically (a temporary file renamed over ``path``).

    Parameters
    ----------
    path : Path
        The output ``.c3d``.
    c : ezc3d.c3d
        Parameters of the output (labels, rate, units, analog channels, ...); its data are
        replaced by one frame.
    xyz : ndarray, shape (n_frames, n_points, 3)
        Coordinates (NaN = missing).
    residual : ndarray, shape (n_frames, n_points)
        Residuals, -1 = missing.
    analog : dict or None
        Where the source's analog words are: ``{"path", "offset", "words", "n_points",
        "n_frames"}`` (from :func:`acm_rs.gapfill.io.read_c3d`); needed when ``c`` has analog
        channels.
    """
    from .._io import new_file_mode

    n_frames, n_points, _ = xyz.shape
    old = np.asarray(c["data"]["points"])
    analogs = np.asarray(c["data"]["analogs"])
    if analogs.size:  # keep one frame's analog samples (the words come from the source)
        per_frame = analogs.shape[2] // max(1, old.shape[2] if old.ndim == 3 else 1)
        c["data"]["analogs"] = analogs[:, :, :per_frame].copy()
    pts = np.ones((4, n_points, 1))
    pts[:3, :, 0] = np.nan_to_num(xyz[0].T, nan=0.0)
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {
        "residuals": residual[:1].T[None].copy(),
        "camera_masks": np.zeros((7, n_points, 1), dtype=bool),
    }
    set_c3d_frame_count(c, n_frames)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, one = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".c3d", dir=path.parent)
    os.close(fd)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".c3d", dir=path.parent)
    os.close(fd)
    try:
        c.write(one)
        h = header_layout(Path(one))
        with open(one, "rb") as fh:
            head = bytearray(fh.read(h["offset"]))
        os.unlink(one)
        n_analog = h["words"] - 4 * n_points
        if n_analog and (
            analog is None
            or analog["n_frames"] != n_frames
            or analog["words"] - 4 * analog["n_points"] != n_analog
        ):
            raise ValueError(
                "this C3D has analog channels, which a long copy takes from its source file; "
                "write it from the Markers that read_c3d returned for the same frames"
            )
        if int(np.asarray(_value(c, "ROTATION", "USED", [0])).ravel()[0] or 0):
            raise ValueError("a long C3D copy cannot carry rotation data (ROTATION:USED > 0)")
        data_bytes = 4 * h["words"] * n_frames
        _patch_frames(head, h["first"], n_frames, h["offset"] // 512 + 1 + -(-data_bytes // 512))
        scale = float(np.asarray(_value(c, "POINT", "SCALE", [-1.0])).ravel()[0])
        src = None
        if n_analog:
            src = np.memmap(analog["path"], dtype="<f4", mode="r", offset=analog["offset"],
                            shape=(n_frames, analog["words"]))  # fmt: skip
        with open(tmp, "wb") as fh:
            fh.write(head)
            for a in range(0, n_frames, BLOCK):
                b = min(n_frames, a + BLOCK)
                blk = np.empty((b - a, h["words"]), dtype="<f4")
                P = blk[:, : 4 * n_points].reshape(b - a, n_points, 4)
                res = np.where(np.isnan(xyz[a:b]).any(axis=2), -1.0, residual[a:b])
                P[:, :, :3] = np.where(res[:, :, None] < 0, 0.0, xyz[a:b])
                P[:, :, 3] = encode_residuals(res, scale)
                if n_analog:
                    blk[:, 4 * n_points :] = src[a:b, 4 * analog["n_points"] :]
                fh.write(blk.tobytes())
            fh.write(b"\0" * (-data_bytes % 512))  # the last block is padded, as ezc3d does
        del src
        os.chmod(tmp, new_file_mode())
        os.replace(tmp, path)
    except BaseException:
        for f in (one, tmp):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(f)
        raise


def set_param(c, group: str, name: str, value) -> None:
    """Set (or add) parameter ``group:name`` of an ezc3d object."""
    params = c["parameters"]
    if group in params and name in params[group]:
        params[group][name]["value"] = value
    else:
        c.add_parameter(group, name, value)


def set_c3d_frame_count(c, n_frames: int) -> None:
    """Record a length over 65535 frames in an ezc3d object the ways C3D readers look for it.

    POINT:FRAMES is a 16-bit count (ezc3d writes 65535); longer recordings also get
    POINT:LONG_FRAMES (the count, float) and TRIAL:ACTUAL_START_FIELD / ACTUAL_END_FIELD (first
    and last frame as low and high 16-bit words), which :func:`read_c3d` reads back.
    """
    if n_frames > 65535:
        set_param(c, "POINT", "LONG_FRAMES", [float(n_frames)])
        set_param(c, "TRIAL", "ACTUAL_START_FIELD", [1, 0])
        set_param(c, "TRIAL", "ACTUAL_END_FIELD", [n_frames & 0xFFFF, n_frames >> 16])


def _value(c, group: str, name: str, default):
    try:
        return c["parameters"][group][name]["value"]
    except KeyError:
        return default


def _patch_frames(head: bytearray, first: int, n_frames: int, after_data: int) -> None:
    """Set what depends on the number of frames in a header and parameter section that ezc3d
    wrote for one frame: header word 5 (last frame) and POINT:FRAMES, 16-bit and saturated at
    65535 as ezc3d writes them, and ROTATION:DATA_START (the 512-byte block after the data)."""
    last = min(first + n_frames - 1, 65535)
    head[8:10] = struct.pack("<H", last)
    base = (head[0] - 1) * 512
    sec = bytes(head[base:])
    rot = _find_parameter(sec, "ROTATION", "DATA_START")
    if rot is not None and rot[2] == 1:
        if rot[1] != 2:
            raise ValueError(f"ROTATION:DATA_START of type {rot[1]}")
        head[base + rot[0] : base + rot[0] + 2] = struct.pack("<H", min(after_data, 65535))
    found = _find_parameter(sec, "POINT", "FRAMES")
    if found is None:
        raise ValueError("ezc3d wrote no POINT:FRAMES parameter")
    at, kind, _ = found
    at += base
    if kind == 2:
        head[at : at + 2] = struct.pack("<H", min(n_frames, 65535))
    elif kind == 4:
        head[at : at + 4] = struct.pack("<f", float(n_frames))
    else:
        raise ValueError(f"POINT:FRAMES of type {kind}")
