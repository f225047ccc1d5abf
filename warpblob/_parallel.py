"""Range-split launches: the CPU counterpart of the thesis' work stealing.

Warp's CPU device runs one launch on one thread; launches over disjoint index
ranges issued from a small thread pool run concurrently (the kernels release
the GIL). Every kernel launched through :func:`launch` takes an ``offset``
input right after its arrays and adds it to ``wp.tid()``.
"""

from __future__ import annotations

import atexit
import concurrent.futures
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from . import _compile
from ._errors import WarpblobError

# the lowest module that every kernel-launching part of warpblob imports
_compile.install()

__all__ = ["launch", "submit", "thread_count", "set_thread_count", "check_threads"]

_threads: int | None = None
#: guards the pool and its size; submissions to the pool happen under it too
_pool_lock = threading.Lock()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_MIN_CHUNK = 1024
#: pieces per thread of a CPU launch, taken dynamically (load balance)
_PIECES = 8


#: the machine's cores, read once (``os.cpu_count`` costs microseconds a call, and every launch asks)
_CORES = max(1, os.cpu_count() or 1)


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
    return _CORES


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


def submit(work, n: int) -> list[concurrent.futures.Future]:
    """Run ``work`` on ``n`` pool threads, growing the pool to ``n`` if needed.

    Submitting under the lock means no caller can hold a pool that another
    one has begun to shut down. A replaced pool is shut down outside the
    lock: it finishes the work other callers gave it (they are not
    disturbed, and new launches go to the new pool meanwhile), and its
    threads have exited when this returns.
    """
    global _pool, _pool_size
    old = None
    with _pool_lock:
        if _pool is None or _pool_size < n:
            old = _pool
            _pool = ThreadPoolExecutor(max_workers=n, thread_name_prefix="warpblob")
            _pool_size = n
        futures = [_pool.submit(work) for _ in range(n)]
    if old is not None:
        old.shutdown(wait=True)
    return futures


@atexit.register
def _shutdown() -> None:
    """Stop the pool's threads at interpreter exit (and forget the pool)."""
    global _pool, _pool_size
    with _pool_lock:
        pool, _pool, _pool_size = _pool, None, 0
    if pool is not None:
        pool.shutdown(wait=True)


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
    (each item is computed by the same code independently). Warp's atomics
    on the CPU are plain read-modify-writes, not atomic across these
    threads: a kernel that accumulates into shared entries with
    ``wp.atomic_add`` is launched with ``threads=1`` (a flag that every
    writer sets to the same value needs no atomics).
    """
    threads = check_threads(threads)
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

    def work():
        # a thread packs the arguments once, for its first piece, and sets only the offset and the size for
        # the others (a recorded launch: 11 us a piece against 34 for a whole ``wp.launch`` of a kernel of
        # a dozen arguments); each thread has its own record
        record = None
        while True:
            with lock:
                k = next(queue, None)
            if k is None:
                return
            if record is None:
                record = wp.launch(kernel, dim=bounds[k + 1] - bounds[k], inputs=[*before, bounds[k], *after],
                                   device=device, record_cmd=True)  # fmt: skip
            else:
                record.set_param_at_index(len(before), bounds[k])
                record.set_dim(bounds[k + 1] - bounds[k])
            record.launch()

    # compile (or load from the cache) here, once: the first launch of every
    # thread would otherwise compile the same module concurrently, n times over
    wp.load_module(kernel.module, device=device)
    # the calling thread takes pieces too (n - 1 pool threads beside it): one hand-off fewer per launch
    futures = submit(work, n - 1)
    try:
        work()
    finally:
        done, _ = concurrent.futures.wait(futures)
    for f in done:
        f.result()
