"""Range-split launches: the CPU counterpart of the thesis' work stealing.

Warp's CPU device runs one launch on one thread; launches over disjoint index
ranges issued from a small thread pool run concurrently (the kernels release
the GIL). Every kernel launched through :func:`launch` takes an ``offset``
input right after its arrays and adds it to ``wp.tid()``.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from ._errors import WarpblobError

__all__ = ["launch", "thread_count", "set_thread_count", "check_threads"]

_threads: int | None = None
_pool: ThreadPoolExecutor | None = None
_MIN_CHUNK = 1024
#: pieces per thread of a CPU launch, taken dynamically (load balance)
_PIECES = 8


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


def check_threads(threads, name: str = "threads") -> int | None:
    """``threads`` if it is None or a positive integer, else WarpblobError naming the value.

    Every public function taking ``threads=`` calls this at its boundary, so a
    0 or -1 is refused the same way ``set_thread_count`` refuses it.
    """
    if threads is None:
        return None
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise WarpblobError(f"{name} must be a positive integer or None, got {threads!r}")
    return int(threads)


def set_thread_count(n: int | None) -> None:
    """Set the CPU thread count (``None`` restores the default)."""
    global _threads
    _threads = check_threads(n, "thread count")


def _executor(n: int) -> ThreadPoolExecutor:
    global _pool
    if _pool is None or _pool._max_workers < n:
        _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="warpblob")
    return _pool


def launch(
    kernel, dim: int, before: list, after: list, device, threads: int | None = None, min_chunk: int = _MIN_CHUNK
) -> None:
    """Launch ``kernel`` over ``dim`` items as ``kernel(*before, offset, *after)``.

    On the CPU the range is cut into up to :data:`_PIECES` contiguous pieces
    per thread (each at least ``min_chunk`` items: pass a small one when
    items are heavy, e.g. one per block of 512 points) and ``threads``
    workers take pieces as they finish the last one, so a range whose cost is
    uneven (surface in one half, empty space in the other) still keeps every
    core busy; on CUDA it is one launch. Results do not depend on the split
    (each item is computed by the same code independently).
    """
    if dim <= 0:
        return
    device = wp.get_device(device)
    n = threads if threads is not None else thread_count()
    min_chunk = max(1, int(min_chunk))
    if device.is_cuda or n <= 1 or dim < 2 * min_chunk:
        wp.launch(kernel, dim=dim, inputs=[*before, 0, *after], device=device)
        return
    pieces = min(n * _PIECES, dim // min_chunk)
    n = min(n, pieces)
    bounds = [dim * k // pieces for k in range(pieces + 1)]
    queue = iter(range(pieces))
    lock = threading.Lock()

    def work(_):
        while True:
            with lock:
                k = next(queue, None)
            if k is None:
                return
            wp.launch(kernel, dim=bounds[k + 1] - bounds[k], inputs=[*before, bounds[k], *after], device=device)

    list(_executor(n).map(work, range(n)))
