"""Rodrigues rotations (ACM supplement section 1, eqs. 1-3), vectorised over leading axes."""

from __future__ import annotations

import numpy as np

from . import _native
from ._arrays import as_float_array


def rodrigues(r: np.ndarray) -> np.ndarray:
    """Rotation matrices of Rodrigues vectors (eq. 2, ``f_{r->R}``).

    Parameters
    ----------
    r : array_like, shape (..., 3)
        Rodrigues vectors ``theta * axis`` in radians.

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3)
        Rotation matrices; the zero vector gives the identity.
    """
    arr = as_float_array(r, "r", (3,))
    out = _native.rodrigues(arr.reshape(-1, 3))
    return out.reshape(arr.shape[:-1] + (3, 3))


def rodrigues_inverse(matrices: np.ndarray) -> np.ndarray:
    """Rodrigues vectors of rotation matrices (inverse of eq. 2), stable near 0 and pi.

    Parameters
    ----------
    matrices : array_like, shape (..., 3, 3)
        Proper rotation matrices (``max |R^T R - I| <= 1e-6``, ``det R > 0``).

    Returns
    -------
    numpy.ndarray, shape (..., 3)
        Rodrigues vectors with angle in [0, pi] (radians).

    Raises
    ------
    ValueError
        If a matrix is not a rotation or contains NaN.
    """
    arr = as_float_array(matrices, "matrices", (3, 3))
    out = _native.rodrigues_log(arr.reshape(-1, 3, 3))
    return out.reshape(arr.shape[:-2] + (3,))


def rodrigues_jacobian(r: np.ndarray) -> np.ndarray:
    """Exact derivative of the rotation matrix with respect to the Rodrigues vector.

    Parameters
    ----------
    r : array_like, shape (..., 3)
        Rodrigues vectors (radians).

    Returns
    -------
    numpy.ndarray, shape (..., 3, 3, 3)
        ``out[..., a, b, k] = dR_ab / dr_k``; exact at ``r = 0`` (the generators of so(3)).
    """
    arr = as_float_array(r, "r", (3,))
    out = _native.rodrigues_jacobian(arr.reshape(-1, 3))
    return out.reshape(arr.shape[:-1] + (3, 3, 3))


def wrap_rotation_vectors(r: np.ndarray, beyond: float = 1.5 * np.pi) -> np.ndarray:
    """The same rotations with short Rodrigues vectors: each vector longer than ``beyond``
    (rad) becomes the shortest one of its rotation (norm <= pi, same axis line,
    ``r (1 - 2 pi k / |r|)``); shorter ones are returned unchanged. A vector that is 0 in a
    component stays 0 there. ``(..., 3)`` -> ``(..., 3)``.

    An unbounded per-frame fit can end at ``|r|`` of many pi (the same rotation); near
    ``|r| = 2 pi k`` the map ``r -> R`` is singular and a filter started there cannot move
    the bone (a tracked ear stuck 10-25 px off for 40 frames). The default leaves vectors up
    to 1.5 pi alone (a quarter turn from the singularity)."""
    r = np.asarray(r, dtype=np.float64)
    theta = np.linalg.norm(r, axis=-1, keepdims=True)
    wrapped = theta - 2.0 * np.pi * np.round(theta / (2.0 * np.pi))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(theta > beyond, r * (wrapped / theta), r)
    return out
