"""Validation of user parameters: every failure is a ModelError naming the value."""

from __future__ import annotations

import numpy as np

from .._errors import ModelError


def vector(owner: str, name: str, value, size: int = 3) -> np.ndarray:
    """Return ``value`` as a finite float64 vector of ``size`` entries."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ModelError(f"{owner}: {name} must be {size} numbers, got {value!r}") from None
    if arr.shape != (size,):
        raise ModelError(f"{owner}: {name} must be {size} numbers, got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"{owner}: {name} must be finite, got {value!r}")
    return arr


def direction(owner: str, name: str, value) -> np.ndarray:
    """Return ``value`` as a unit 3-vector; a zero-length vector is refused."""
    arr = vector(owner, name, value)
    length = float(np.linalg.norm(arr))
    if length < 1e-12:
        raise ModelError(f"{owner}: {name} must have non-zero length, got {value!r}")
    return arr / length


def scalar(owner: str, name: str, value, *, positive: bool = False, nonnegative: bool = False) -> float:
    """Return ``value`` as a finite float, optionally > 0 or >= 0."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ModelError(f"{owner}: {name} must be a number, got {value!r}") from None
    if not np.isfinite(x):
        raise ModelError(f"{owner}: {name} must be finite, got {value!r}")
    if positive and not x > 0.0:
        raise ModelError(f"{owner}: {name} must be positive, got {value!r}")
    if nonnegative and not x >= 0.0:
        raise ModelError(f"{owner}: {name} must be non-negative, got {value!r}")
    return x


def color(owner: str, value) -> np.ndarray:
    """Return an RGB colour with components in [0, 1]."""
    arr = vector(owner, "color", value)
    if np.any(arr < 0.0) or np.any(arr > 1.0):
        raise ModelError(f"{owner}: color components must lie in [0, 1], got {value!r}")
    return arr


def points(owner: str, name: str, value, dim: int, minimum: int) -> np.ndarray:
    """Return an ``(n, dim)`` finite float64 array with at least ``minimum`` rows."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ModelError(f"{owner}: {name} must be an (n, {dim}) array, got {value!r}") from None
    if arr.ndim != 2 or arr.shape[1] != dim or arr.shape[0] < minimum:
        raise ModelError(
            f"{owner}: {name} must be an (n, {dim}) array with n >= {minimum}, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ModelError(f"{owner}: {name} must be finite, got {value!r}")
    return arr
