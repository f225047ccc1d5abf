"""Range-split launches: the CPU counterpart of the thesis' work stealing.

Warp's CPU device runs one launch on one thread; launches over disjoint index
ranges issued from a small thread pool run concurrently (the kernels release
the GIL). Every kernel launched through :func:`launch` takes an ``offset``
input right after its arrays and adds it to ``wp.tid()``.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import warp as wp

from ._errors import WarpblobError

__all__ = ["launch", "thread_count", "set_thread_count"]

_threads: int | None = None
_pool: ThreadPoolExecutor | None = None
_MIN_CHUNK = 1024


def thread_count() -> int:
    """Threads used by CPU launches: ``set_thread_count``, else ``WARPBLOB_THREADS``, else all cores."""
    if _threads is not None:
        return _threads
    env = os.environ.get("WARPBLOB_THREADS")
    if env:
        try:
            n = int(env)
        except ValueError:
            raise WarpblobError(f"WARPBLOB_THREADS must be a positive integer, got {env!r}") from None
        if n < 1:
            raise WarpblobError(f"WARPBLOB_THREADS must be a positive integer, got {env!r}")
        return n
    return max(1, os.cpu_count() or 1)


def set_thread_count(n: int | None) -> None:
    """Set the CPU thread count (``None`` restores the default)."""
    global _threads
    if n is not None and (not isinstance(n, int) or n < 1):
        raise WarpblobError(f"thread count must be a positive integer, got {n!r}")
    _threads = n


def _executor(n: int) -> ThreadPoolExecutor:
    global _pool
    if _pool is None or _pool._max_workers < n:
        _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="warpblob")
    return _pool


def launch(kernel, dim: int, before: list, after: list, device, threads: int | None = None) -> None:
    """Launch ``kernel`` over ``dim`` items as ``kernel(*before, offset, *after)``.

    On the CPU the range is split into ``threads`` contiguous chunks launched
    concurrently; on CUDA it is one launch. Results do not depend on the
    split (each item is computed by the same code independently).
    """
    if dim <= 0:
        return
    device = wp.get_device(device)
    n = threads if threads is not None else thread_count()
    if device.is_cuda or n <= 1 or dim < 2 * _MIN_CHUNK:
        wp.launch(kernel, dim=dim, inputs=[*before, 0, *after], device=device)
        return
    n = min(n, dim // _MIN_CHUNK)
    bounds = [dim * k // n for k in range(n + 1)]

    def run(k):
        wp.launch(kernel, dim=bounds[k + 1] - bounds[k], inputs=[*before, bounds[k], *after], device=device)

    list(_executor(n).map(run, range(n)))
