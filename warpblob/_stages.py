"""Host helpers shared by the kernel pipelines: stage clocks, memory checks, prefix sums, compaction, kept buffers."""

from __future__ import annotations

import ctypes
import os
import time

import numpy as np
import warp as wp

from ._errors import ResourceError
from ._parallel import launch

__all__ = ["StageClock", "available_memory", "check_memory", "scan", "scans", "compact", "room", "host_array", "head",
           "device_array", "device_empty", "shared_array", "set_rows", "column_bounds", "rows_any", "rows_all"]

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


#: Python's types as Warp stores them
_PYTHON_TYPES = {float: wp.float32, int: wp.int32}

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
    dtype = _PYTHON_TYPES.get(dtype, dtype)
    if base is None or base.dtype != dtype or base.device != wp.get_device(device) or base.shape[0] < n:
        base = wp.empty(max(1, n + int(n * ROOM)), dtype=dtype, device=device)
    return base, head(base, n)


# Host arrays wrapped for kernels, fast. A cut's frame wraps a few hundred small numpy arrays and takes as many
# views of kept buffers; Warp's constructor checks and derives each one's state in 8-16 us on this machine
# (the pointer alone, through ``ndarray.ctypes``, 3 us), a fifth of a frame's host time. These helpers give an
# object with the state Warp's own constructor gives (its attributes, compared in the tests), copied from one
# made by Warp for the same kind of array with the fields that depend on the array set anew; a kind the fast
# path does not cover, or one whose first array it did not reproduce exactly, goes through Warp.

#: per (dtype, wrapped ndim, "wrap" | "head"): the attributes of a Warp-made array of that kind, or None (slow)
_TEMPLATES: dict = {}
#: per Warp dtype: (numpy scalar dtype, trailing shape), or None where numpy has no such scalar
_KINDS: dict = {}


def _on_cpu(device) -> bool:
    return device == "cpu" if isinstance(device, str) else device.is_cpu


def _kind(dtype):
    kind = _KINDS.get(dtype, False)
    if kind is False:
        inner = tuple(getattr(dtype, "_shape_", ()))
        try:
            kind = (np.dtype(wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype))), inner)
        except TypeError:
            kind = None
        _KINDS[dtype] = kind
    return kind


def _address(values: np.ndarray) -> int:
    try:  # (a writable buffer's address in 1 us; ``ndarray.ctypes.data`` takes 3)
        return ctypes.addressof(ctypes.c_char.from_buffer(values))
    except TypeError:
        return values.ctypes.data


def _fields(values: np.ndarray, dtype) -> dict | None:
    """The array-dependent attributes of ``wp.array(values, dtype=dtype, device="cpu", copy=False)``, or
    None where the fast path does not cover it (not C-contiguous, empty, other numpy dtype or trailing shape)."""
    kind = _kind(dtype)
    if kind is None or values.dtype != kind[0] or not values.flags.c_contiguous or not values.size:
        return None
    inner, shape, size = kind[1], values.shape, values.size
    if inner:
        k = len(inner)
        if len(shape) <= k or shape[-k:] != inner:
            return None
        shape = shape[:-k]
        for d in inner:
            size //= d
    return {"ptr": _address(values), "shape": shape, "strides": values.strides[: len(shape)], "size": size,
            "capacity": values.nbytes, "_ref": values}  # fmt: skip


def _from_template(key, fields: dict, make) -> wp.array:
    """The array of kind ``key`` with ``fields``: from the kind's template, or, the first time, ``make()``'s
    (Warp's own), which becomes the template where ``fields`` are its own attributes."""
    template = _TEMPLATES.get(key, False)
    if template:
        out = object.__new__(wp.array)  # (wp.array.__new__ sets two attributes the template sets too)
        out.__dict__ = {**template, **fields}
        return out
    made = make()
    if template is False:
        state = dict(vars(made))
        _TEMPLATES[key] = {**state, "_ref": None} if {**state, **fields} == state else None
    return made


def host_array(values: np.ndarray, dtype) -> wp.array:
    """``wp.array(values, dtype=dtype, device="cpu", copy=False)``: a Warp array over ``values``' own memory
    (kept alive by it), the object Warp's constructor makes, made in a fraction of its time.

    Example:
        >>> a = host_array(np.arange(8, dtype=np.int32).reshape(2, 4), wp.vec4i)
        >>> a.shape, a.numpy()[1].tolist()
        ((2,), [4, 5, 6, 7])
    """
    dtype = _PYTHON_TYPES.get(dtype, dtype)
    fields = _fields(values, dtype) if type(values) is np.ndarray else None
    make = lambda: wp.array(values, dtype=dtype, device="cpu", copy=False)
    if fields is None:
        return make()
    return _from_template((dtype, len(fields["shape"]), "wrap"), fields, make)


def head(base: wp.array, n: int) -> wp.array:
    """``base[:n]`` of a 1-D contiguous CPU array (Warp's slice, made in a fraction of its time); any other
    array is sliced by Warp.

    Example:
        >>> head(wp.zeros(10, dtype=wp.float32, device="cpu"), 3).shape
        (3,)
    """
    if base.ndim != 1 or not base.device.is_cpu or not base.is_contiguous or not 0 < n <= base.shape[0]:
        return base[:n]
    fields = {"ptr": base.ptr, "shape": (n,), "size": n, "capacity": n * base.strides[0], "_ref": base}
    return _from_template((base.dtype, 1, "head"), fields, lambda: base[:n])


def device_array(values, dtype, device, copy: bool = True) -> wp.array:
    """``wp.array(values, dtype=dtype, device=device, copy=copy)``; on the CPU a (copied where ``copy``)
    numpy array of the dtype's scalars wrapped by :func:`host_array`.

    Example:
        >>> device_array([1, 2, 3], wp.int32, "cpu").numpy().tolist()
        [1, 2, 3]
    """
    if _on_cpu(device):
        dtype = _PYTHON_TYPES.get(dtype, dtype)
        kind = _kind(dtype)
        np_dtype = None if kind is None else kind[0]
        if copy and np_dtype is not None:
            return host_array(np.array(values, dtype=np_dtype, order="C"), dtype)
        if isinstance(values, np.ndarray) and values.dtype == np_dtype and values.flags.c_contiguous:
            return host_array(values, dtype)  # (shared, as Warp shares it)
    return wp.array(values, dtype=dtype, device=device, copy=copy)


def device_empty(n: int, dtype, device, zero: bool = False) -> wp.array:
    """``wp.empty(n, dtype=dtype, device=device)`` (``wp.zeros`` with ``zero``); on the CPU a numpy array's
    memory wrapped by :func:`host_array` (numpy's allocator also hands back freed pages, where Warp's host
    allocator maps, and faults in, new ones for a large array).

    Example:
        >>> device_empty(3, wp.vec3, "cpu", zero=True).numpy().tolist()
        [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    """
    if n > 0 and _on_cpu(device):
        dtype = _PYTHON_TYPES.get(dtype, dtype)
        kind = _kind(dtype)
        if kind is not None:
            return host_array((np.zeros if zero else np.empty)((int(n), *kind[1]), kind[0]), dtype)
    return (wp.zeros if zero else wp.empty)(n, dtype=dtype, device=device)


def shared_array(values, dtype, device) -> wp.array:
    """``values`` (C-contiguous, converted where needed) as a Warp array: its own memory on the CPU, a
    copy on CUDA.

    Example:
        >>> a = np.arange(3, dtype=np.int32)
        >>> shared_array(a, wp.int32, "cpu").ptr == a.ctypes.data
        True
    """
    return device_array(np.ascontiguousarray(values), dtype, device, copy=not _on_cpu(device))


def set_rows(view: wp.array, start, value) -> None:
    """Set rows ``[start, n)`` of the 1-D array ``view`` to ``value``: a number (every component; 0 zeroes
    them) or an array of those rows.

    Example:
        >>> a = wp.array(np.arange(4, dtype=np.float32), device="cpu")
        >>> set_rows(a, 2, 0.0); set_rows(a, 3, [7.0]); a.numpy().tolist()
        [0.0, 1.0, 0.0, 7.0]
    """
    n = view.shape[0]
    if start >= n:
        return
    if view.device.is_cpu:  # (numpy's writes of the rows: no Warp view of them to make)
        view.numpy()[start:] = value
        return
    rows = view[start:]
    if np.ndim(value):
        rows.assign(np.asarray(value, dtype=_kind(view.dtype)[0]))
    elif value == 0.0:
        rows.zero_()
    else:
        rows.fill_(rows.dtype(*([value] * getattr(rows.dtype, "_length_", 1))))


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
