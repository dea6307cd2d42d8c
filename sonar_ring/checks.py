"""Argument checks of the core's public functions, shared so that they all refuse alike.

Bad *data* (NaN, infinite, negative or absurd values) never raises in the
core: it is flagged per entry.  What these checks refuse with
:class:`ValueError` is a wrong *call* -- non-numeric types, shapes that do
not fit, settings outside their range -- with the caller and the argument
named in the message.
"""

from __future__ import annotations

import functools
import math

import numpy as np


def quiet(function):
    """Run ``function`` without floating-point warnings.

    Entries that divide by zero or go invalid are reported through the
    functions' reason codes or NaN, so numpy's warnings about them would only be noise.
    """

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        with np.errstate(all="ignore"):
            return function(*args, **kwargs)

    return wrapper


def real_array(name: str, value, caller: str) -> np.ndarray:
    """``value`` as a float64 array (no copy when it is one); ``ValueError`` unless it holds real numbers."""
    array = np.asarray(value)
    if array.dtype.kind not in "iuf":
        raise ValueError(f"{caller}: '{name}' must be real numbers, got dtype {array.dtype}")
    return array.astype(np.float64, copy=False)


def points(name: str, value, caller: str) -> np.ndarray:
    """``value`` as float64 positions (..., 2), m; ``ValueError`` unless it holds real numbers of that shape."""
    array = real_array(name, value, caller)
    if array.ndim == 0 or array.shape[-1] != 2:
        raise ValueError(f"{caller}: '{name}' must be (..., 2) positions (x, y) in m, got shape {array.shape}")
    return array


def broadcast_shape(caller: str, point_names=(), **arrays) -> tuple:
    """The broadcast shape of the entries of ``arrays``; those named in ``point_names`` contribute their leading shape.

    ``ValueError`` naming every argument's shape when they do not broadcast.
    """
    shapes = {name: a.shape[:-1] if name in point_names else a.shape for name, a in arrays.items()}
    try:
        return np.broadcast_shapes(*shapes.values())
    except ValueError:
        listing = ", ".join(f"{name} {shape}" for name, shape in shapes.items())
        raise ValueError(f"{caller}: leading shapes do not broadcast: {listing}") from None


def flat_copies(shape: tuple, *arrays) -> list[np.ndarray]:
    """Each array broadcast to ``shape``, flattened, as a new (writable) float64 array.

    Writable always: numba compiles a read-only array as another type, so one
    signature serves every caller and none compiles again at its first call.
    """
    return [np.array(np.broadcast_to(array, shape), dtype=np.float64).ravel() for array in arrays]


def positive_finite(name: str, value) -> np.ndarray:
    """``value`` as a float array; ``ValueError`` unless every entry is finite and > 0."""
    array = np.asarray(value, dtype=float)
    if not ((array > 0).all() and np.isfinite(array).all()):  # methods: numpy's wrappers cost more than the test
        raise ValueError(f"{name} must be finite and > 0, got {value!r}")
    return array


def positive_number(name: str, value) -> float:
    """``value`` as a float; ``ValueError`` unless it is one finite number > 0.

    Numbers are checked without numpy, whose calls cost more than the check.
    """
    number = _one_number(value)
    if not (math.isfinite(number) and number > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return number


def non_negative_number(name: str, value) -> float:
    """``value`` as a float; ``ValueError`` unless it is one finite number >= 0 (as :func:`positive_number`)."""
    number = _one_number(value)
    if not (math.isfinite(number) and number >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return number


def _one_number(value) -> float:
    """``value`` as a float where it is one real number (a Python or a numpy scalar), else NaN."""
    if isinstance(value, float | int):
        return float(value)
    numeric = isinstance(value, np.generic | np.ndarray) and value.ndim == 0 and value.dtype.kind in "biuf"
    return float(value) if numeric else math.nan
