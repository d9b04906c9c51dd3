"""C3D point words (the fourth word of each point) and C3D files too large for ezc3d's in-memory
model, read and written in blocks (issue 16).

**The fourth word.** The C3D specification (C3D User Guide, "3D point data"; c3d.org
"3D Data - Integer/Floating-point Format") stores, per point and frame, after X, Y, Z a fourth
word read as a signed 16-bit integer (in float files: the float converted to an integer):
negative = invalid point; else the *high* byte holds the camera contribution mask (bits 0-6,
cameras 1-7) and the *low* byte the residual in units of ``|POINT:SCALE|``; a word of 0
(residual 0, no camera) marks a point that was interpolated, filtered or otherwise computed.
py-c3d, BTK/Mokka and Vicon read it so; the c3d.org sample ``Eb015pr.c3d`` holds word 0x3E10
(cameras 2-6, residual 16 x 0.0833 = 1.33), the specification's own example.
ezc3d 1.7.2 reads and writes the two bytes the other way round (residual in the high byte;
ezc3d issue #386), and acm-rs before this change wrote them as ezc3d does. acm-rs now decodes
and encodes every fourth word itself, by the specification (:func:`decode_point_words`,
:func:`encode_point_words`); files written by older acm-rs versions (parameter
``ACM_RS:FILLED_RESIDUAL`` without ``ACM_RS:WORD4``) are still decoded the old way.

**Long and large files.** ezc3d holds every point of every frame as an object: reading 65,535
frames x 41 markers costs 1.3 GB, writing 200,000 frames more than 2 GB. For files whose data
section is larger than :data:`STREAM_BYTES` (Intel floating-point format) acm-rs keeps ezc3d for
the header and the parameter section and moves the frames itself:

* **Reading.** ezc3d parses a copy of the file cut after its first frame; the frames are read
  from the file through a memory map, :data:`BLOCK` frames at a time (coordinates as stored,
  the fourth word by the specification).
* **Writing.** ezc3d writes a one-frame file with the output's parameters; its header and
  parameter section are kept, the frame counts patched in place and the frames appended block
  by block. Analog words are copied from the source file unchanged.
* **Over 65,535 frames**, written so that ezc3d 1.7.2 reads every frame: ezc3d takes the
  frame count from the 16-bit header words and, when they say 65,535 frames (first frame 1,
  last 65535), reads to the end of the file unless the file has a ROTATION group (ezc3d
  ``Data::Data``; issues #308, #372, PR #373). acm-rs's long files therefore have header words
  1 and 65535, no ROTATION group and no padding after the last frame, and also carry the
  counts other readers use: POINT:LONG_FRAMES (float) and TRIAL:ACTUAL_START_FIELD /
  ACTUAL_END_FIELD (two 16-bit integers each, Vicon's convention, read by py-c3d and acm-rs).
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


#: The processor byte of the parameter section for DEC (VAX) and SGI/MIPS (big-endian) files.
_DEC, _MIPS = 85, 86


def decode_point_words(
    word: np.ndarray, scale: float, legacy: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Residual and camera mask from the fourth word of each point, by the C3D specification.

    Parameters
    ----------
    word : ndarray
        The fourth words as stored: float values (float files) or 16-bit integers (integer
        files); any shape.
    scale : float
        POINT:SCALE (its magnitude is the residual unit).
    legacy : bool
        Decode the layout of acm-rs before the ``ACM_RS:WORD4`` marker (and of ezc3d 1.7.2):
        residual in the high byte, camera mask in the low 7 bits.

    Returns
    -------
    residual : ndarray of float, shape of ``word``
        ``low byte x |scale|`` in POINT:UNITS; 0 for a computed point; -1 where the word is
        negative or not finite (invalid point).
    mask : ndarray of uint8, shape of ``word``
        Camera contribution mask (high byte, bits 0-6 = cameras 1-7); 0 for invalid points.
    """
    v = np.asarray(word, dtype=np.float64)
    bad = ~np.isfinite(v) | (v < 0)
    # a float word is "converted to a signed integer" (C3D User Guide): truncated, as py-c3d
    w = np.trunc(np.where(bad, 0.0, v)).astype(np.int64) & 0xFFFF
    res_byte, mask = (w >> 8) & 0xFF, (w >> 8) & 0x7F
    if not legacy:
        res_byte = w & 0xFF
    else:
        mask = w & 0x7F
    residual = np.where(bad, -1.0, res_byte * abs(float(scale)))
    return residual, np.where(bad, 0, mask).astype(np.uint8)


def encode_point_words(
    residual: np.ndarray, scale: float, mask: np.ndarray | None = None
) -> np.ndarray:
    """The fourth word of each point by the C3D specification, as the value of a float word.

    ``-1`` where ``residual < 0`` (invalid point); ``0`` (residual 0, no camera) where
    ``residual == 0`` (a computed point, C3D's "interpolated or otherwise modified"); else
    ``mask << 8 | r`` with ``r = round(residual / |scale|)`` kept in 1..255 (a measured point
    never becomes "computed"). Residuals decoded from a file with the same POINT:SCALE come
    back as the same byte.

    Parameters
    ----------
    residual : ndarray of float
        Residuals in POINT:UNITS (-1 missing, 0 computed).
    scale : float
        POINT:SCALE of the file written.
    mask : ndarray of int, optional
        Camera masks (7 bits), same shape; 0 when omitted.
    """
    import warnings

    r = np.asarray(residual, dtype=np.float64)
    q = np.rint(np.where(r > 0, r, 0.0) / abs(float(scale)))
    if (q > 255).any():
        warnings.warn(
            f"{int((q > 255).sum())} residuals exceed 255 x |POINT:SCALE| = "
            f"{255 * abs(float(scale)):g}, the largest a C3D can store; written as that",
            stacklevel=2,
        )
    q = np.clip(q, 1, 255).astype(np.int64)
    m = np.zeros(r.shape, np.int64) if mask is None else np.asarray(mask, np.int64) & 0x7F
    out = np.where(r > 0, (m << 8) | q, 0).astype(np.float64)
    return np.where(r < 0, -1.0, out)


def read_fourth_words(
    p: Path, offset: int, words: int, n_points: int, n_frames: int, processor: int, is_float: bool
) -> np.ndarray:
    """The fourth word of every point of a C3D's data section, as numbers.

    Intel and DEC files, float or integer (the formats ezc3d reads). Returns an array of shape
    (n_frames, n_points): float values (float files, DEC floats converted to IEEE) or 16-bit
    signed integers (integer files).
    """
    if processor not in (_INTEL, _DEC):
        raise ValueError(f"{p}: C3D processor type {processor} (only Intel and DEC are read)")
    if is_float:
        raw = np.memmap(p, dtype="<u4", mode="r", offset=offset, shape=(n_frames, words))
        u = np.asarray(raw[:, 3 : 4 * n_points : 4])
        del raw
        if processor == _DEC:  # DEC F-float: 16-bit halves swapped, exponent bias 2 higher
            u = ((u >> 16) | (u << 16)) & 0xFFFFFFFF
            return u.astype("<u4").view("<f4").astype(np.float64) / 4.0
        return u.astype("<u4").view("<f4").astype(np.float64)
    raw = np.memmap(p, dtype="<i2", mode="r", offset=offset, shape=(n_frames, words))
    out = np.asarray(raw[:, 3 : 4 * n_points : 4]).astype(np.float64)
    del raw
    return out


def read_points(
    p: Path,
    offset: int,
    words: int,
    n_points: int,
    n_frames: int,
    scale: float,
    legacy: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points of an Intel float-format C3D through a memory map, in blocks.

    Returns
    -------
    xyz : ndarray, shape (n_frames, n_points, 3)
        Coordinates as stored (NaN where the point is invalid).
    residual : ndarray, shape (n_frames, n_points)
        Residuals in POINT:UNITS, -1 where invalid (:func:`decode_point_words`).
    mask : ndarray of uint8, shape (n_frames, n_points)
        Camera masks.
    """
    raw = np.memmap(p, dtype="<f4", mode="r", offset=offset, shape=(n_frames, words))
    xyz = np.empty((n_frames, n_points, 3))
    residual = np.empty((n_frames, n_points))
    mask = np.empty((n_frames, n_points), np.uint8)
    for a in range(0, n_frames, BLOCK):
        b = min(n_frames, a + BLOCK)
        blk = np.asarray(raw[a:b, : 4 * n_points]).reshape(b - a, n_points, 4)
        xyz[a:b] = blk[:, :, :3]
        residual[a:b], mask[a:b] = decode_point_words(blk[:, :, 3], scale, legacy)
        xyz[a:b][residual[a:b] < 0] = np.nan
    del raw
    return xyz, residual, mask


def patch_point_words(
    p: Path, residual: np.ndarray, scale: float, mask: np.ndarray | None = None
) -> None:
    """Rewrite, in a float-format C3D that ezc3d wrote, the fourth word of every point by the
    C3D specification (:func:`encode_point_words`) and the header's scale word (words 7-8) to
    POINT:SCALE; in place.

    Parameters
    ----------
    p : Path
        The file (Intel float format, as ezc3d writes).
    residual : ndarray, shape (n_frames, n_points)
        Residuals in POINT:UNITS (-1 missing, 0 computed).
    scale : float
        POINT:SCALE of the file (negative).
    mask : ndarray, shape (n_frames, n_points), optional
        Camera masks.
    """
    h = header_layout(p)
    n_frames, n_points = residual.shape
    if h is None or h["processor"] != _INTEL or h["n_points"] != n_points:
        raise ValueError(f"{p}: not the Intel float C3D of {n_points} points that was written")
    with open(p, "r+b") as fh:
        fh.seek(12)
        fh.write(struct.pack("<f", -abs(float(scale))))
    if n_frames == 0 or n_points == 0:
        return
    raw = np.memmap(p, dtype="<f4", mode="r+", offset=h["offset"], shape=(n_frames, h["words"]))
    for a in range(0, n_frames, BLOCK):
        b = min(n_frames, a + BLOCK)
        m = None if mask is None else mask[a:b]
        raw[a:b, 3 : 4 * n_points : 4] = encode_point_words(residual[a:b], scale, m)
    raw.flush()
    del raw


def check_processor(p: Path) -> None:
    """Refuse, in one line, a C3D that ezc3d cannot read: SGI/MIPS (big-endian) files."""
    h = header_layout(p)
    if h is not None and h["processor"] == _MIPS:
        raise ValueError(
            f"{p}: big-endian (SGI/MIPS, processor type 86) C3D file, which ezc3d cannot read; "
            "convert it to the Intel format (e.g. with Mokka, Vicon or py-c3d) and read the copy"
        )


def _records(sec: bytes):
    """The records of a little-endian parameter section, in order: ``(start, ident, link,
    label)`` with ``link`` the offset of the record's link word (after its name) and
    ``label`` its upper-case name; groups have a negative ``ident``."""
    pos = 4
    while pos + 2 <= len(sec):
        n_chars = abs(int.from_bytes(sec[pos : pos + 1], "little", signed=True))
        if n_chars == 0:
            return
        ident = int.from_bytes(sec[pos + 1 : pos + 2], "little", signed=True)
        link = pos + 2 + n_chars
        yield pos, ident, link, bytes(sec[pos + 2 : link]).decode("latin-1").upper()
        step = int.from_bytes(sec[link : link + 2], "little", signed=True)
        if step == 0:
            return
        pos = link + step


def _find_parameter(sec: bytes, group: str, name: str) -> tuple[int, int, int] | None:
    """(byte offset of the value, type, number of values) of a parameter in a little-endian
    parameter section, None if absent."""
    groups, found = {}, []
    for _, ident, body, label in _records(sec):
        if ident < 0:
            groups[-ident] = label
        elif label == name:
            q = body + 2
            kind = int.from_bytes(sec[q : q + 1], "little", signed=True)
            dims = list(sec[q + 2 : q + 2 + sec[q + 1]])
            found.append((ident, q + 2 + sec[q + 1], kind, int(np.prod(dims, dtype=np.int64))))
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
    mask: np.ndarray | None = None,
) -> None:
    """Write a float-format C3D in blocks: ezc3d's header and parameters of ``c`` (made for
    ``len(xyz)`` frames), then the frames; atomically (a temporary file renamed over ``path``).
    Fourth words by the C3D specification (:func:`encode_point_words`); over 65,535 frames in
    the layout ezc3d reads whole (module docstring).

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
        Residuals in POINT:UNITS, -1 = missing, 0 = computed (filled).
    analog : dict or None
        Where the source's analog words are: ``{"path", "offset", "words", "n_points",
        "n_frames"}`` (from :func:`acm_rs.gapfill.io.read_c3d`); needed when ``c`` has analog
        channels.
    mask : ndarray of int, shape (n_frames, n_points), optional
        Camera masks of the measured points (0 when omitted).
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
        long = n_frames > 65535
        if long:  # ezc3d 1.7.2 stops at 65,535 frames when a ROTATION group exists
            _drop_group(head, "ROTATION")
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
        first = 1 if long else h["first"]  # ezc3d reads to the end after header words 1, 65535
        _patch_frames(head, first, n_frames, h["offset"] // 512 + 1 + -(-data_bytes // 512))
        scale = float(np.asarray(_value(c, "POINT", "SCALE", [-1.0])).ravel()[0])
        head[12:16] = struct.pack("<f", -abs(scale))  # the header's scale word = POINT:SCALE
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
                P[:, :, 3] = encode_point_words(res, scale, None if mask is None else mask[a:b])
                if n_analog:
                    blk[:, 4 * n_points :] = src[a:b, 4 * analog["n_points"] :]
                fh.write(blk.tobytes())
            if not long:  # padded to a 512-byte block, as ezc3d does; a long file is not (ezc3d
                fh.write(b"\0" * (-data_bytes % 512))  # would read the padding as frames)
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
    and last frame as low and high 16-bit words, integer parameters as Vicon writes them; py-c3d
    reads them as 16-bit integers), which :func:`read_c3d` reads back.
    """
    if n_frames > 65535:
        set_param(c, "POINT", "LONG_FRAMES", [float(n_frames)])
        for name, frame in (("ACTUAL_START_FIELD", 1), ("ACTUAL_END_FIELD", n_frames)):
            lo, hi = frame & 0xFFFF, frame >> 16
            set_param(c, "TRIAL", name, [0.0, 0.0])
            c["parameters"]["TRIAL"][name]["type"] = 2  # INT (ezc3d makes a list of ints FLOAT)
            c["parameters"]["TRIAL"][name]["value"] = np.array([lo - (lo > 32767) * 65536, hi])


def _drop_group(head: bytearray, group: str) -> None:
    """Remove a group and its parameters from the (little-endian) parameter section in
    ``head``, in place; the groups after it are renumbered so that the ids stay 1..n (ezc3d
    lists a missing id as a group without name). The section keeps its number of blocks."""
    base = (head[0] - 1) * 512
    n_blocks = head[base + 2]
    sec = bytes(head[base : base + 512 * n_blocks])
    recs = list(_records(sec))  # (start, id, offset of the link word, name)
    gid = [-r[1] for r in recs if r[1] < 0 and r[3] == group]
    if not gid:
        return
    gid = gid[0]
    kept = [(k, r) for k, r in enumerate(recs) if abs(r[1]) != gid]
    out = bytearray(sec[:4])
    for j, (k, (start, ident, link, _)) in enumerate(kept):
        stop = recs[k + 1][0] if k + 1 < len(recs) else len(sec)
        rec = bytearray(sec[start:stop])
        if abs(ident) > gid:
            rec[1] = (ident + 1 if ident < 0 else ident - 1) & 0xFF
        rel = link - start
        rec[rel : rel + 2] = struct.pack("<h", 0 if j == len(kept) - 1 else len(rec) - rel)
        out += rec
    head[base : base + 512 * n_blocks] = bytes(out[: 512 * n_blocks]).ljust(512 * n_blocks, b"\0")


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
    head[6:10] = struct.pack("<2H", first, last)
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
