"""Input normalisation shared by the public wrappers (dtype, contiguity, shape, finiteness)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def as_float_array(
    x: object,
    name: str,
    tail: Sequence[int | None] = (),
    *,
    finite: bool = True,
) -> np.ndarray:
    """Return ``x`` as a C-contiguous float64 array whose trailing dims equal ``tail``.

    ``None`` in ``tail`` accepts any size. Raises ``ValueError`` naming ``name`` and the expected
    shape when the shape does not fit, and (with ``finite``) when a value is NaN or infinite.
    """
    try:
        arr = np.ascontiguousarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array: {exc}") from None
    nd = len(tail)
    want = ", ".join("n" if t is None else str(t) for t in tail)
    if arr.ndim < nd or any(
        t is not None and s != t
        for s, t in zip(arr.shape[arr.ndim - len(tail) :], tail, strict=True)
    ):
        raise ValueError(f"{name} must have shape (..., {want}), got {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ValueError(f"{name} contains NaN or infinity (first at index {tuple(bad)})")
    return arr


def as_index_array(x: object, name: str) -> np.ndarray:
    """Return ``x`` as a 1-D C-contiguous int64 array (rejecting non-integral values)."""
    arr = np.asarray(x)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if not np.all(np.equal(np.mod(arr, 1), 0)):
            raise ValueError(f"{name} must contain integers")
    return np.ascontiguousarray(arr, dtype=np.int64)
