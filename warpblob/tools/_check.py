"""Validation of tool and path parameters: every failure is a ToolError naming the value."""

from __future__ import annotations

import numpy as np

from .._errors import ToolError


def shown(value) -> str:
    """``value`` as a short string for an error message (long arrays are elided)."""
    if isinstance(value, np.ndarray):
        # small arrays as Python lists ([0.0, inf, 0.0]), without numpy's column padding
        small = value.size <= 16
        text = repr(value.tolist()) if small else np.array2string(value, threshold=12, edgeitems=2, separator=", ")
    else:
        text = repr(value)
    return text if len(text) <= 160 else text[:157] + "..."


def scalar(owner: str, name: str, value, *, positive: bool = False) -> float:
    """``value`` as a finite float, optionally required to be > 0."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ToolError(f"{owner}: {name} must be a number, got {shown(value)}") from None
    if not np.isfinite(x):
        raise ToolError(f"{owner}: {name} must be finite, got {shown(value)}")
    if positive and not x > 0.0:
        raise ToolError(f"{owner}: {name} must be positive, got {shown(value)}")
    return x


def rows(owner: str, name: str, value, width: int, *, single: bool = False, batch: bool = True) -> np.ndarray:
    """``value`` as a finite float64 copy of shape ``(width,)`` (if ``single``) or ``(N, width)`` (if ``batch``).

    A non-finite entry is reported with its row, so a NaN in a long path
    names the key it is in.
    """
    shapes = " or ".join(s for s, ok in ((f"({width},)", single), (f"(N, {width})", batch)) if ok)
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ToolError(f"{owner}: {name} must be numbers of shape {shapes}, got {shown(value)}") from None
    if not ((single and arr.shape == (width,)) or (batch and arr.ndim == 2 and arr.shape[1] == width)):
        raise ToolError(f"{owner}: {name} must have shape {shapes}, got shape {arr.shape}: {shown(value)}")
    bad = ~np.isfinite(arr).reshape(-1, width).all(axis=1)
    if bad.any():
        if arr.ndim == 1:
            raise ToolError(f"{owner}: {name} must be finite, got {shown(arr)}")
        i = int(np.argmax(bad))
        raise ToolError(f"{owner}: {name}[{i}] must be finite, got {shown(arr[i])}")
    return arr


def unit_quaternions(owner: str, name: str, value, *, single: bool = False, batch: bool = True) -> np.ndarray:
    """``value`` as quaternions (x, y, z, w) scaled to unit length; a (near) zero one is refused."""
    q = rows(owner, name, value, 4, single=single, batch=batch)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    small = norm[..., 0] < 1e-12
    if small.any():
        if q.ndim == 1:
            raise ToolError(f"{owner}: {name} must be a non-zero quaternion (x, y, z, w), got {shown(q)}")
        i = int(np.argmax(small))
        raise ToolError(f"{owner}: {name}[{i}] must be a non-zero quaternion (x, y, z, w), got {shown(q[i])}")
    return q / norm


def frozen(arr: np.ndarray) -> np.ndarray:
    """``arr`` marked read-only, so cached data derived from it never goes stale."""
    arr.setflags(write=False)
    return arr
