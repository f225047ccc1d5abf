"""Host helpers shared by the kernel pipelines: stage clocks, memory checks, prefix sums, compaction, kept buffers."""

from __future__ import annotations

import os
import time

import numpy as np
import warp as wp

from ._errors import ResourceError
from ._parallel import launch

__all__ = ["StageClock", "available_memory", "check_memory", "scan", "scans", "compact", "room", "column_bounds", "rows_any", "rows_all"]

#: grid cells from which ``progress=None`` shows a bar (a job of seconds on 2 CPU cores)
PROGRESS_CELLS = 8_000_000


class StageClock:
    """Seconds per pipeline stage (the device is synchronized at each lap),
    with a stage progress bar on a terminal.

    Args:
        device: Warp device the stages run on.
        desc: the bar's label (the pipeline's name).
        stages: number of laps a full run takes.
        show: whether to show the bar (only ever on a terminal).
        start: ``time.perf_counter()`` when the first stage began (default: now),
            so that work done before the clock can exist (sizing the job to
            decide on the bar) is still timed.
    """

    def __init__(self, device, desc: str, stages: int, show: bool = False, start: float | None = None):
        self.device = device
        self.seconds: dict[str, float] = {}
        self._t0 = time.perf_counter() if start is None else start
        self._bar = None
        if show:
            from ._progress import progress

            bar = progress(range(stages), desc=desc, total=stages, mininterval=0.0)  # a handful of steps: draw each
            self._bar = bar if hasattr(bar, "update") else None

    def lap(self, name: str) -> None:
        """Close stage ``name``: wait for its kernels and record its seconds."""
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        self.seconds[name] = now - self._t0
        self._t0 = now
        if self._bar is not None:
            self._bar.set_postfix_str(name, refresh=False)
            self._bar.update(1)
            if self._bar.n >= self._bar.total:
                self.close()

    def __del__(self):
        self.close()

    def close(self) -> None:
        """Remove the bar (also done at the last stage, and when the clock is dropped)."""
        bar = getattr(self, "_bar", None)
        if bar is not None:
            bar.close()
            self._bar = None


def available_memory(device) -> int:
    """Bytes that can still be allocated on ``device`` (host RAM for the CPU)."""
    device = wp.get_device(device)
    if device.is_cuda:
        return int(device.free_memory)
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))


def format_bytes(n: float) -> str:
    """``n`` bytes in the largest binary unit that keeps it at 1 or more (``"512 B"``, ``"3.2 MiB"``)."""
    for unit, size in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


def check_memory(who: str, stage: str, need: int, limit: int) -> None:
    """Raise :class:`ResourceError` with the estimate when ``need`` bytes exceed ``limit``."""
    if need > limit:
        raise ResourceError(
            f"{who}: the {stage} stage needs an estimated {format_bytes(need)}, "
            f"more than the {format_bytes(limit)} available; use a larger cellsize or smaller bounds"
        )


def scan(counts: wp.array) -> tuple[wp.array, int]:
    """Exclusive prefix sum of int32 ``counts`` and the total (one host sync)."""
    (offsets,), (total,) = scans(counts)
    return offsets, total


def scans(*counts: wp.array) -> tuple[list[wp.array], list[int]]:
    """Exclusive prefix sums of several int32 ``counts`` arrays and their
    totals, with one host sync for all of them (:func:`scan` takes one each)."""
    device = counts[0].device
    ends = wp.zeros(2 * len(counts), dtype=wp.int32, device=device)
    offsets = []
    for k, c in enumerate(counts):
        o = wp.empty_like(c)
        n = c.shape[0]
        if n:
            wp.utils.array_scan(c, o, inclusive=False)
            wp.copy(ends, o, dest_offset=2 * k, src_offset=n - 1, count=1)
            wp.copy(ends, c, dest_offset=2 * k + 1, src_offset=n - 1, count=1)
        offsets.append(o)
    e = ends.numpy()  # host sync: the totals size the next stage's allocations
    return offsets, [int(e[2 * k]) + int(e[2 * k + 1]) for k in range(len(counts))]


@wp.kernel(enable_backward=False)
def mark_heads_kernel(keys: wp.array(dtype=wp.int64), offset: int, heads: wp.array(dtype=wp.int32)):
    """1 where a run of equal sorted keys starts."""
    i = wp.tid() + offset
    head = int(1)
    if i > 0:
        if keys[i] == keys[i - 1]:
            head = 0
    heads[i] = head


@wp.kernel(enable_backward=False)
def compact_kernel(
    flags: wp.array(dtype=wp.int32), scanned: wp.array(dtype=wp.int32), offset: int, out: wp.array(dtype=wp.int32)
):
    """``out[scanned[i]] = i`` for every flagged ``i`` (exclusive scan)."""
    tid = wp.tid() + offset
    if flags[tid] != 0:
        out[scanned[tid]] = tid


def compact(flags: wp.array, device, threads=None) -> wp.array:
    """Indices of the non-zero entries of int32 ``flags``, ascending."""
    offsets, total = scan(flags)
    out = wp.empty(total, dtype=wp.int32, device=device)
    launch(compact_kernel, flags.shape[0], [flags, offsets], [out], device, threads)
    return out


#: a buffer kept between rebuilds gets this fraction more room than it needs when it is made (a cut adds tets)
ROOM = 1 / 8


def room(base: wp.array | None, n: int, dtype, device) -> tuple[wp.array, wp.array]:
    """``(base, view)``: a view of the first ``n`` items of ``base`` where it is a 1-D array of ``dtype``
    on ``device`` with room for them (kept: its values stay where they are), else of a new uninitialized
    base with :data:`ROOM` more.

    Example:
        >>> base, view = room(None, 10, wp.float32, "cpu")
        >>> view.shape, room(base, 8, wp.float32, "cpu")[0] is base, room(base, 9, float, "cpu")[0] is base
        ((10,), True, True)
    """
    dtype = {float: wp.float32, int: wp.int32}.get(dtype, dtype)  # (Python's types as Warp stores them)
    if base is None or base.dtype != dtype or base.device != wp.get_device(device) or base.shape[0] < n:
        base = wp.empty(max(1, n + int(n * ROOM)), dtype=dtype, device=device)
    return base, base[:n]


def column_bounds(points) -> tuple:
    """``(low, high)``: the per-column minima and maxima of an (n, k) array, each (k,) of its dtype.

    One reduction per column: numpy's reduction along the rows of a narrow array (``points.min(axis=0)``)
    takes about 15 times as long (0.7 ms for 20K points here). The values are the same.

    Example:
        >>> import numpy as np
        >>> column_bounds(np.array([[0.0, 5.0], [2.0, -1.0]]))
        (array([ 0., -1.]), array([2., 5.]))
    """
    points = np.asarray(points)
    low = np.array([points[:, j].min() for j in range(points.shape[1])], dtype=points.dtype)
    high = np.array([points[:, j].max() for j in range(points.shape[1])], dtype=points.dtype)
    return low, high


#: per row width, the unsigned type of that many bytes (a row of a 1-byte array read as one word)
_WORDS = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}


def _as_words(a: np.ndarray):
    """An (n, k) C-contiguous array of 1-byte items as (n,) words of k bytes, or None where that view fails."""
    if a.ndim == 2 and a.dtype.itemsize == 1 and a.shape[1] in _WORDS and a.flags.c_contiguous:
        return a.view(_WORDS[a.shape[1]]).reshape(-1)
    return None


def rows_any(a) -> np.ndarray:
    """(n,) bool: whether each row of an (n, k) array has a nonzero entry (``a.any(axis=1)``, the same values).

    A row of 1, 2, 4 or 8 one-byte items (bool, uint8 masks) is read as one word; other arrays are reduced
    column by column. numpy's reduction along the short axis takes far longer here (an (n, 4) bool array:
    2.8 ms for 100K rows, against 0.02 ms as words).

    Example:
        >>> rows_any(np.array([[False, True], [False, False]]))
        array([ True, False])
    """
    a = np.asarray(a)
    words = _as_words(a)
    if words is not None:
        return words != 0
    out = np.zeros(len(a), dtype=bool)
    for j in range(a.shape[1]):
        out |= a[:, j] != 0
    return out


def rows_all(a) -> np.ndarray:
    """(n,) bool: whether every entry of each row of an (n, k) array is nonzero (``a.all(axis=1)``, the same
    values); a bool row of 1, 2, 4 or 8 items is read as one word (see :func:`rows_any`).

    Example:
        >>> rows_all(np.array([[True, True], [True, False]]))
        array([ True, False])
    """
    a = np.asarray(a)
    words = _as_words(a) if a.dtype == bool else None
    if words is not None:
        return words == words.dtype.type(int.from_bytes(b"\x01" * a.shape[1], "little"))
    out = np.ones(len(a), dtype=bool)
    for j in range(a.shape[1]):
        out &= a[:, j] != 0
    return out
