"""Host side of the field engine: arrays in, field values, gradients and colours out."""

from __future__ import annotations

import operator

import numpy as np
import warp as wp

from .._device import resolve_device
from .._errors import ModelError
from .._linearize import LinearModel, linearize
from .._parallel import check_threads, launch
from . import _kernels

__all__ = [
    "field", "gradient", "color", "evaluate", "bound_balls", "bound_blocks", "grid_field", "model_arrays",
]  # fmt: skip

_KERNELS: dict = {}


def _kernel(prune: bool, derivatives: bool):
    key = (prune, derivatives)
    if key not in _KERNELS:
        _KERNELS[key] = _kernels.make_kernel(prune, derivatives)
    return _KERNELS[key]


def bound_balls(model, centers, radii, *, device=None, threads: int | None = None):
    """Bounds ``(F_min, F_max)`` of the field over balls, (N, 2) float32.

    Guaranteed: every point ``p`` with ``|p - centers[i]| <= radii[i]`` has
    ``F_min <= F(p) <= F_max`` (conservative: F_max may be large where warps
    or sketched primitives make the bound unknown).

    Args:
        centers: (N, 3) ball centres (numpy or Warp vec3 array).
        radii: (N,) ball radii >= 0, model units (numpy or Warp float32 array).

    Raises:
        ModelError: a centre or radius is not finite (or a radius negative),
            naming it and its index.
    """
    threads = check_threads(threads)
    lm = linearize(model)
    pts, dev, was_numpy = _as_points(centers, device, "centers")
    rad = _as_radii(radii, dev)
    n = pts.shape[0]
    if rad.shape[0] != n:
        raise ModelError(f"radii: expected {n} values, got {rad.shape[0]}")
    out = wp.empty(n, dtype=wp.vec2, device=dev)
    if "interval" not in _KERNELS:
        _KERNELS["interval"] = _kernels.make_interval_kernel()
    launch(_KERNELS["interval"], n, [model_arrays(lm, dev), pts, rad], [out], dev, threads)
    return out.numpy().reshape(n, 2) if was_numpy else out


def bound_blocks(model, origin, cellsize: float, blocks, *, device=None, threads: int | None = None) -> np.ndarray:
    """Bounds ``(F_min, F_max)`` of the field over the sub-blocks of grid blocks, (N, 64, 2) float32.

    The grid has points ``origin + cellsize * (i, j, k)``; block ``b`` is the
    8^3 cells from grid index ``8 * blocks[b]``, cut into 4^3 sub-blocks of
    2^3 cells. ``bounds[b, (sk * 4 + sj) * 4 + si]`` holds for every point of
    the cube of sub-block ``(si, sj, sk)`` (side ``2 * cellsize``). They are
    never looser than :func:`bound_balls` at the cube's circumscribed ball and
    much tighter near flat parts of convex skeletons (a distance to a convex
    set lies above its tangent plane, so over a cube it drops by at most the
    half side times the 1-norm of its gradient, not the half diagonal). All
    64 come from one tree walk per block (bounds rows: each primitive bounds
    only the sub-blocks its box meets, operators fold whole rows), which is
    how the polygonizer rejects empty sub-blocks on the CPU.

    Args:
        origin: (3,) position of grid point (0, 0, 0), model units.
        cellsize: grid spacing, > 0.
        blocks: (N, 3) integer block coordinates.

    Raises:
        ModelError: a bad origin, cellsize or block, naming the value.

    Example:
        >>> import numpy as np, warpblob as wb
        >>> from warpblob.field import bound_blocks
        >>> b = bound_blocks(wb.Point((0, 0, 0), 1.0), (-0.8, -0.8, -0.8), 0.2, [[0, 0, 0]])
        >>> b.shape, bool(b[0, 0, 1] < 0.5 <= b[0, 21, 1])
        ((1, 64, 2), True)
    """
    threads = check_threads(threads)
    lm = linearize(model)
    o, h = _grid_frame("bound_blocks", origin, cellsize)
    try:
        coords = np.asarray(blocks)
    except (TypeError, ValueError, OverflowError):
        raise ModelError(f"bound_blocks: blocks must be an (N, 3) integer array, got {blocks!r}") from None
    if coords.ndim != 2 or coords.shape[1] != 3 or not np.issubdtype(coords.dtype, np.integer):
        raise ModelError(f"bound_blocks: blocks must be an (N, 3) integer array, got {coords.dtype} {coords.shape}")
    if coords.size:
        # the kernel indexes grid points 8 * (blocks + 1) in int32 and places them in float32
        for end in (coords.min(axis=0).astype(np.float64) - 1.0, coords.max(axis=0).astype(np.float64) + 1.0):
            _check_grid_extent("bound_blocks", o, h, _kernels.BLOCK_SIDE * end, "blocks")
    dev = resolve_device(device)
    n = coords.shape[0]
    out = wp.empty(n * _kernels.SUB_BLOCKS, dtype=wp.vec2, device=dev)
    if "blocks" not in _KERNELS:
        _KERNELS["blocks"] = _kernels.make_block_bounds_kernel()
    inputs = [model_arrays(lm, dev), wp.vec3(*o.astype(np.float32)), h, wp.array(coords.astype(np.int32), dtype=wp.vec3i, device=dev)]
    launch_blocks(_KERNELS["blocks"], n, inputs, [out], lm, dev, threads)
    return out.numpy().reshape(n, _kernels.SUB_BLOCKS, 2)


def model_arrays(lm: LinearModel, device) -> _kernels.ModelArrays:
    """The device copy of ``lm`` (made once per device and cached on ``lm``)."""
    device = wp.get_device(device)
    key = str(device)
    cached = lm._device_cache.get(key)
    if cached is not None:
        return cached
    s = _kernels.ModelArrays()
    s.kind = wp.array(lm.kind, dtype=wp.int32, device=device)
    s.skip = wp.array(lm.skip, dtype=wp.int32, device=device)
    s.parent = wp.array(lm.parent, dtype=wp.int32, device=device)
    s.ref = wp.array(lm.ref, dtype=wp.int32, device=device)
    s.lower = wp.array(lm.lower, dtype=wp.vec3, device=device)
    s.upper = wp.array(lm.upper, dtype=wp.vec3, device=device)
    s.params = wp.array(lm.params, dtype=wp.vec4, device=device)
    s.inverse = wp.array(lm.inverse, dtype=_kernels.mat34, device=device)
    s.stretch = wp.array(lm.stretch, dtype=wp.float32, device=device)
    s.radius = wp.array(lm.radius, dtype=wp.float32, device=device)
    s.color = wp.array(lm.color, dtype=wp.vec3, device=device)
    s.data_start = wp.array(lm.data_start, dtype=wp.int32, device=device)
    s.data = wp.array(lm.data, dtype=wp.float32, device=device)
    s.grid_lower = wp.array(lm.grid_lower, dtype=wp.vec3, device=device)
    s.grid_inv_cell = wp.array(lm.grid_inv_cell, dtype=wp.vec3, device=device)
    s.grid_dims = wp.array(lm.grid_dims, dtype=wp.vec3i, device=device)
    s.grid_base = wp.array(lm.grid_base, dtype=wp.int32, device=device)
    s.cell_offsets = wp.array(lm.cell_offsets, dtype=wp.int32, device=device)
    s.cell_items = wp.array(lm.cell_items, dtype=wp.int32, device=device)
    lm._device_cache[key] = s
    return s


#: largest finite float32: the kernels see every coordinate in float32
_F32_MAX = float(np.finfo(np.float32).max)


def _first_bad(values: np.ndarray, lowest: float) -> tuple | None:
    """Index of the first entry of ``values`` that is NaN, infinite, beyond
    float32's range or below ``lowest``; None when there is none."""
    if values.size == 0:
        return None
    # two reductions and no temporaries in the common case (NaN fails both comparisons)
    if values.min() >= lowest and values.max() <= _F32_MAX:
        return None
    bad = ~((values >= lowest) & (values <= _F32_MAX))
    return np.unravel_index(int(np.argmax(bad)), values.shape)


def _host_values(values, name: str, what: str) -> np.ndarray:
    """``values`` as a float32 or float64 numpy array without rounding them to
    float32 yet, so that a check can report the number the caller passed."""
    try:
        arr = np.asarray(values)
        if arr.dtype != np.float32:
            arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise ModelError(f"{name}: expected {what}, got {_not_a_number(values)}") from None
    return arr


def _not_a_number(values) -> str:
    """What a caller passed that numpy cannot read as float64: the first such
    entry and its index when ``values`` is a regular nest of sequences."""
    try:
        entries = np.asarray(values, dtype=object)
    except ValueError:  # ragged
        return type(values).__name__
    for index, v in np.ndenumerate(entries):
        try:
            float(v)
        except (TypeError, ValueError, OverflowError):
            shown = repr(v) if len(repr(v)) <= 40 else repr(v)[:37] + "..."
            return f"{shown} at index {list(index)}"
    return type(values).__name__


def _fmt(values: np.ndarray) -> str:
    # numpy scalars print the shortest repr of their own precision (0.1, 1e+39, nan)
    return "[" + ", ".join(str(v) for v in values) + "]" if values.ndim else str(values)


def _check_device_values(arr: wp.array, name: str, label: str, lowest: float, rule: str) -> None:
    """ModelError naming the first entry of Warp array ``arr`` (vec3 or float32)
    that is not finite or is below ``lowest``, found on the array's device."""
    n = arr.shape[0]
    if n == 0:
        return
    first = wp.full(1, n, dtype=wp.int32, device=arr.device)
    # one launch, not range-split: the CPU pool's concurrent launches would race on the atomic
    wp.launch(_kernels.find_bad_entry_kernel, dim=n, inputs=[arr, lowest], outputs=[first], device=arr.device)
    # host sync: the check's one read-back
    i = int(first.numpy()[0])
    if i < n:
        value = arr[i : i + 1].numpy()[0]
        raise ModelError(f"{name}: {label} {i} is {_fmt(value)}; {rule}")


def _as_points(points, device, name: str = "points"):
    """(warp vec3 array, device, was_numpy) from numpy-like or Warp input, or
    ModelError naming a coordinate that is not finite (or, for numpy-like
    input, that float32 cannot hold) and its row."""
    if isinstance(points, wp.array):
        if points.dtype == wp.vec3 and points.ndim == 1:
            pts = points
        elif points.dtype == wp.float32 and points.ndim == 2 and points.shape[1] == 3:
            pts = points.view(dtype=wp.vec3).reshape((points.shape[0],))
        else:
            raise ModelError(
                f"{name}: expected a Warp array of vec3 or (N, 3) float32, got {points.dtype} {points.shape}"
            )
        _check_device_values(pts, name, "row", -np.inf, "coordinates must be finite")
        return pts, pts.device, False
    arr = _host_values(points, name, "an (N, 3) array of numbers")
    if arr.ndim == 1 and arr.shape == (3,):
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ModelError(f"{name}: expected shape (N, 3), got {arr.shape}")
    bad = _first_bad(arr, -_F32_MAX)
    if bad is not None:
        raise ModelError(
            f"{name}: row {bad[0]} is {_fmt(arr[bad[0]])}; coordinates must be finite and within float32's range "
            "(|x| <= 3.4e38)"
        )
    device = resolve_device(device)
    return wp.array(np.ascontiguousarray(arr, dtype=np.float32), dtype=wp.vec3, device=device), device, True


def _as_radii(radii, device) -> wp.array:
    """Ball radii as a float32 Warp array on ``device`` (Warp input stays on its
    own), or ModelError naming one that is negative or not finite."""
    if isinstance(radii, wp.array):
        if radii.dtype != wp.float32 or radii.ndim != 1:
            raise ModelError(f"radii: expected a 1-D Warp float32 array, got {radii.dtype} {radii.shape}")
        _check_device_values(radii, "radii", "entry", 0.0, "radii must be finite and >= 0")
        return radii
    arr = _host_values(radii, "radii", "an (N,) array of numbers")
    if arr.ndim != 1:
        raise ModelError(f"radii: expected shape (N,), got {arr.shape}")
    bad = _first_bad(arr, 0.0)
    if bad is not None:
        raise ModelError(
            f"radii: entry {bad[0]} is {_fmt(arr[bad[0]])}; radii must be finite, >= 0 and within float32's range"
        )
    return wp.array(arr.astype(np.float32), dtype=wp.float32, device=device)


def _grid_frame(fn: str, origin, cellsize) -> tuple[np.ndarray, float]:
    """(origin float64 (3,), cellsize) of a grid, or ModelError naming the bad value."""
    o = _host_values(origin, f"{fn}: origin", "3 numbers")
    if o.size != 3:
        raise ModelError(f"{fn}: origin must be 3 numbers, got {origin!r}")
    o = o.reshape(3).astype(np.float64)
    if _first_bad(o, -_F32_MAX) is not None:
        raise ModelError(f"{fn}: origin must be finite and within float32's range, got {_fmt(o)}")
    try:
        h = float(cellsize)
    except (TypeError, ValueError, OverflowError):
        raise ModelError(f"{fn}: cellsize must be a number > 0, got {cellsize!r}") from None
    if not (0.0 < h <= _F32_MAX):
        raise ModelError(f"{fn}: cellsize must be > 0 and within float32's range, got {cellsize!r}")
    return o, h


def _check_grid_extent(fn: str, origin: np.ndarray, h: float, index, what: str) -> None:
    """ModelError unless grid index ``index`` (3,) fits int32 and its point float32."""
    index = np.asarray(index, dtype=np.float64)  # no integer wrap-around while checking
    reach = origin + h * index
    if np.any(np.abs(index) >= 2**31) or _first_bad(reach, -_F32_MAX) is not None:
        shown = "[" + ", ".join(f"{v:.0f}" for v in index) + "]"
        raise ModelError(f"{fn}: {what} reach grid index {shown} at {_fmt(reach)}, beyond int32 or float32's range")


def evaluate(model, points, *, device=None, derivatives: bool = True, prune: bool = True, threads: int | None = None):
    """Field values (N,), gradients (N, 3) and colours (N, 3) at ``points``.

    Args:
        model: a model (:class:`~warpblob.tree.Node`) or its :class:`LinearModel`.
        points: (N, 3) numpy-like or Warp array (vec3 or (N, 3) float32).
        device: Warp device for numpy input (default: Warp's default device);
            Warp input is evaluated on its own device.
        derivatives: also compute gradients and colours.
        prune: skip subtrees whose box excludes the point (``False``: the
            plain full traversal, for comparison; results are identical).
        threads: CPU threads for this call (default :func:`warpblob.thread_count`).

    Returns:
        ``(values, gradients, colors)``; numpy arrays for numpy input, Warp
        arrays on the input's device for Warp input; gradients and colours
        are ``None`` when ``derivatives`` is False.

    Raises:
        ModelError: a point has a NaN or infinite coordinate (or, for numpy
            input, one float32 cannot hold), naming the point and its row;
            Warp input is checked on its own device with one host sync.
        WarpblobError: ``threads`` is not a positive integer or None.
    """
    threads = check_threads(threads)
    lm = linearize(model)
    pts, dev, was_numpy = _as_points(points, device)
    n = pts.shape[0]
    values = wp.empty(n, dtype=wp.float32, device=dev)
    if derivatives:
        grads = wp.empty(n, dtype=wp.vec3, device=dev)
        cols = wp.empty(n, dtype=wp.vec3, device=dev)
    else:
        grads = cols = wp.empty(0, dtype=wp.vec3, device=dev)
    launch(_kernel(prune, derivatives), n, [model_arrays(lm, dev), pts], [values, grads, cols], dev, threads)
    if not derivatives:
        grads = cols = None
    if was_numpy:
        # host sync: copy results back for numpy callers
        values = values.numpy()
        if derivatives:
            grads, cols = grads.numpy().reshape(n, 3), cols.numpy().reshape(n, 3)
    return values, grads, cols


def field(model, points, *, device=None, prune: bool = True, threads: int | None = None):
    """Field values ``F(p)`` at (N, 3) ``points`` → (N,) float32.

    Example:
        >>> import warpblob as wb
        >>> f = wb.field(wb.Point((0, 0, 0), 1.0), [[0.0, 0.0, 0.0], [0.4541, 0.0, 0.0], [2.0, 0.0, 0.0]])
        >>> [round(float(v), 3) for v in f]
        [1.0, 0.5, 0.0]
    """
    return evaluate(model, points, device=device, derivatives=False, prune=prune, threads=threads)[0]


def gradient(model, points, *, device=None, prune: bool = True, threads: int | None = None):
    """Analytic gradients ``grad F(p)`` at (N, 3) ``points`` → (N, 3) float32 (1 / model unit).

    Example:
        >>> import warpblob as wb
        >>> g = wb.gradient(wb.Point((0, 0, 0), 1.0), [[0.5, 0.0, 0.0]])
        >>> bool(g[0, 0] < 0.0)
        True
    """
    return evaluate(model, points, device=device, derivatives=True, prune=prune, threads=threads)[1]


def color(model, points, *, device=None, prune: bool = True, threads: int | None = None):
    """Colours (N, 3) RGB in [0, 1] at (N, 3) ``points`` (black where ``F = 0``).

    Example:
        >>> import warpblob as wb
        >>> c = wb.color(wb.Point((0, 0, 0), 1.0, color=(1, 0, 0)), [[0.1, 0.0, 0.0]])
        >>> c[0].tolist()
        [1.0, 0.0, 0.0]
    """
    return evaluate(model, points, device=device, derivatives=True, prune=prune, threads=threads)[2]


#: scratch of one array-mode launch (per-block register rows)
ROWS_BYTES = 64 << 20


def block_chunk(lm: LinearModel, n_blocks: int) -> tuple[int, int]:
    """(blocks per array-mode launch, scratch bytes of one launch) for ``n_blocks``
    blocks: a block's rows take (registers + 2) x 512 floats, a launch at most
    :data:`ROWS_BYTES` (at least one block)."""
    row_bytes = (lm.registers + 2) * _kernels.BLOCK_POINTS * 4
    chunk = max(1, min(n_blocks, ROWS_BYTES // row_bytes))
    return chunk, chunk * row_bytes


def launch_blocks(
    kernel, n_blocks: int, inputs: list, outputs: list, lm: LinearModel, device, threads=None, *, min_chunk: int = 2
):
    """Launch an array-mode kernel over ``n_blocks`` blocks in chunks of
    :func:`block_chunk`; the kernel takes ``inputs``, then ``first_block``,
    the scratch ``rows`` and the result slot, then ``offset`` and ``outputs``.
    ``min_chunk``: the fewest blocks a CPU thread takes at a time (see
    :func:`warpblob._parallel.launch`)."""
    chunk, nbytes = block_chunk(lm, n_blocks)
    rows = wp.zeros(nbytes // 4, dtype=wp.float32, device=device)
    for first in range(0, n_blocks, chunk):
        count = min(chunk, n_blocks - first)
        launch(kernel, count, [*inputs, first, rows, lm.registers], outputs, device, threads, min_chunk=min_chunk)


def grid_field(model, origin, cellsize: float, shape, *, device=None, threads: int | None = None) -> np.ndarray:
    """F on a regular grid, ``values[i, j, k] = F(origin + cellsize * (i, j, k))``.

    Evaluated in array mode: one thread walks the tree once for a block of
    8^3 grid points and evaluates each primitive only at the points inside
    its box, so the traversal cost is shared by the block (about 3.6x fewer
    seconds than :func:`field` at the same points on towers at h = 0.05).
    Values equal :func:`field`'s up to the rounding of sums taken in another
    operand order.

    Args:
        origin: (3,) position of grid point (0, 0, 0), model units.
        cellsize: grid spacing, > 0.
        shape: (nx, ny, nz) points per axis, each an integer >= 1.

    Returns:
        float32 array of ``shape``.

    Raises:
        ModelError: a bad origin, cellsize or shape, naming the value.

    Example:
        >>> import warpblob as wb
        >>> from warpblob.field import grid_field
        >>> v = grid_field(wb.Point((0, 0, 0), 1.0), (-1, -1, -1), 0.5, (5, 5, 5))
        >>> float(v[2, 2, 2])
        1.0
    """
    threads = check_threads(threads)
    lm = linearize(model)
    o, h = _grid_frame("grid_field", origin, cellsize)
    try:
        dims = tuple(operator.index(n) for n in shape)
    except TypeError:
        raise ModelError(f"grid_field: shape must be 3 integers >= 1, got {shape!r}") from None
    if len(dims) != 3 or min(dims) < 1:
        raise ModelError(f"grid_field: shape must be 3 integers >= 1, got {shape!r}")
    _check_grid_extent("grid_field", o, h, dims, "shape")
    dev = resolve_device(device)
    blocks = [-(-n // _kernels.BLOCK_SIDE) for n in dims]
    n_blocks = int(np.prod(blocks))
    values = wp.empty(dims, dtype=wp.float32, device=dev)
    if "grid" not in _KERNELS:
        _KERNELS["grid"] = _kernels.make_grid_kernel()
    inputs = [model_arrays(lm, dev), wp.vec3(*o.astype(np.float32)), h, wp.vec3i(*dims), wp.vec3i(*blocks)]
    launch_blocks(_KERNELS["grid"], n_blocks, inputs, [values], lm, dev, threads)
    return values.numpy()
