"""Host side of the polygonizer: stages, memory checks, statistics."""

from __future__ import annotations

import warnings

import numpy as np
import warp as wp

from .._errors import ResourceError, WarpblobError
from .._stages import PROGRESS_CELLS, StageClock, available_memory, check_memory, compact, scans
from .._linearize import linearize
from .._parallel import check_threads, launch
from .._device import resolve_device
from ..field._engine import block_chunk, launch_blocks, model_arrays
from ..mesh import SurfaceMesh
from ..tree import ISO_VALUE
from . import _kernels, _relax, _tables, _weld

__all__ = ["polygonize", "available_memory"]

_CACHE: dict = {}
#: grid sampling: "rows" walks the tree once per block for its 512 vertices
#: (array mode: the traversal cost is shared, best for CPU threads), "points"
#: once per vertex (one GPU thread each), "auto" picks by device
SAMPLING = "auto"
#: sub-block rejection: "bounds" bounds the 64 sub-blocks of every active block
#: and samples only next to undecided ones, "dense" samples every vertex of the
#: active blocks (no sub-block bounds), "auto" picks by the cost model of
#: :func:`_dense_sampling`; the mesh does not depend on the choice
SUBBLOCKS = "auto"


def _use_rows(device) -> bool:
    if SAMPLING == "auto":
        return device.is_cpu
    return SAMPLING == "rows"


#: the cost model's threshold: sample densely in array mode when the tape has
#: at least this many nodes
DENSE_NODES = 32


def _dense_sampling(node_count: int, rows: bool) -> bool:
    """Whether to sample every vertex of the active blocks instead of bounding
    their 64 sub-blocks first (see :data:`SUBBLOCKS`).

    The cost model: bounding a block's sub-blocks is one tree walk of bounds
    rows, about the cost of sampling the block; what it saves is the samples
    of the vertices it proves away. In array mode (the CPU) a sample left
    out saves only its primitive evaluations, not the walk, so on a long tape
    the bounds cost more than they save, whatever the share of blocks the
    surface fills (2 cores, best of 5, bounds -> dense: medusa h = 0.14 27.3
    -> 22.8 ms, 0.05 120 -> 108 ms, 0.03 312 -> 286 ms with 16% of the blocks
    active; head 0.1 127 -> 120 ms, 0.05 574 -> 538 ms; towers 0.14 181 ->
    164 ms, 0.05 the same within 2%), and real samples instead of stand-ins
    around the edges give the root search better starts (mug h = 0.05:
    28,817 -> 23,997 root evaluations). On a short tape (tumor, mug: up to
    11 nodes) both take the same time and the bounds keep the field
    evaluations per triangle at half (tumor h = 0.14: 2.9 against 7.2). In
    point mode (a GPU thread per vertex) every sample costs a walk, so the
    bounds always pay. Dense sampling is taken in array mode on tapes of
    :data:`DENSE_NODES` nodes or more."""
    if SUBBLOCKS != "auto":
        return SUBBLOCKS == "dense"
    return rows and node_count >= DENSE_NODES


def _kernel_set():
    if "kernels" not in _CACHE:
        _CACHE["kernels"] = {**_kernels.make_kernels(), "relax": _relax.make_relax_kernel()}
    return _CACHE["kernels"]


def _device_tables(device):
    key = ("tables", str(device))
    if key not in _CACHE:
        if "loop_table" not in _CACHE:
            _CACHE["loop_table"] = _tables.build_loop_table()
        table = wp.array(_CACHE["loop_table"], dtype=wp.int32, device=device)
        faces = wp.array(np.array([f[2] for f in _tables.FACES], dtype=np.int32), dtype=wp.vec4i, device=device)
        info = np.column_stack([_tables.EDGE_ORIGIN, _tables.EDGE_AXIS]).astype(np.int32)
        edges = wp.array(info, dtype=wp.vec4i, device=device)
        _CACHE[key] = (table, faces, edges)
    return _CACHE[key]


def _grid(lm, cellsize, bounds):
    if bounds is None:
        lo, hi = lm.bounds
        if np.any(lo > hi):
            return None
        # half a cell of margin: the outermost vertices see F = 0, so the mesh closes
        lo = lo - 0.5 * cellsize
        hi = hi + 0.5 * cellsize
    else:
        try:
            lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in bounds)
        except (TypeError, ValueError):
            raise WarpblobError(f"polygonize: bounds must be (lower (3,), upper (3,)), got {bounds!r}") from None
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)):
            raise WarpblobError(f"polygonize: bounds must be finite with upper > lower, got {bounds!r}")
    cells = np.maximum(np.ceil((hi - lo) / cellsize).astype(np.int64), 1)
    blocks = cells // _kernels.BLOCK + 1  # the vertex layer at index `cells` needs a block too
    g = _kernels.Grid()
    g.origin = wp.vec3(*lo.astype(np.float32))
    g.h = float(cellsize)
    g.cells = wp.vec3i(*cells.astype(np.int32))
    g.blocks = wp.vec3i(*blocks.astype(np.int32))
    return g, cells, blocks


def polygonize(
    model,
    *,
    cellsize: float,
    bounds=None,
    device=None,
    iso: float = ISO_VALUE,
    tolerance: float = 1e-4,
    max_memory: int | None = None,
    threads: int | None = None,
    progress: bool | None = None,
    relax: bool = True,
) -> SurfaceMesh:
    """Polygonize ``model`` into a closed, coloured, shared-vertex triangle mesh.

    The pipeline follows the thesis' GPU design (SPEC 2.1) on a block-sparse
    grid: blocks of 8^3 cells are rejected when interval bounds of the field
    prove them to lie wholly inside or outside (exact: no surface is ever
    dropped, see :func:`warpblob.field.bound_blocks`); the remaining blocks are
    sampled, crossed edges counted and prefix-summed (``wp.utils.array_scan``),
    one vertex is placed per crossed edge by a bracketed Newton-Hermite
    search to ``|F - iso| <= tolerance``, with its normal from the
    analytic gradient and its colour, and faces come from a generated table
    that resolves ambiguous faces by the asymptotic decider, so neighbouring
    cells always agree (no cracks). Each stage is a Warp kernel with at most
    one host sync (for the size of the next allocation).

    Args:
        model: a model or its :class:`~warpblob.LinearModel`.
        cellsize: grid spacing, model units, finite and > 0.
        bounds: ``(lower, upper)`` box to polygonize, two finite (3,)
            points with upper > lower on every axis (default: the model's box
            plus half a cell, which closes the surface).
        device: Warp device (default: Warp's default device).
        iso: iso-value (default 0.5), finite and > 0: the field is 0 outside
            the model's box, so at 0 or below all of space would be inside.
            A Wyvill primitive's field is at most 1, but blends sum, so there
            is no fixed upper limit; see Warns.
        tolerance: largest ``|F(v) - iso|`` accepted for a vertex, > 0 and
            below ``iso``.
        max_memory: bytes the call may allocate, > 0 (default: what is available).
        threads: CPU threads, a positive integer (default: all cores).
        progress: show a bar of the stages on a terminal (``None``: for
            grids of 8 million cells and more, jobs of seconds).
        relax: improve the triangles with a smallest angle under 10 degrees:
            the ends of their shortest edge move halfway to the centroid of
            their neighbours in the tangent plane and back onto the surface
            (Newton along the gradient, to the same tolerance); a move that
            turns a triangle over or makes it skinnier is undone. Vertices
            then no longer lie on grid edges; the connectivity is unchanged.

    Returns:
        :class:`~warpblob.mesh.SurfaceMesh`; ``stats`` holds
        ``field_evaluations`` (point evaluations counted in the kernels: grid
        samples plus root-search steps), ``interval_evaluations`` (block
        bounds), ``triangles``, ``vertices``, ``blocks_total``,
        ``blocks_rejected``, ``seconds`` per stage and ``fvept``.

    Raises:
        WarpblobError: bad arguments, named with the value received.
        ResourceError: the estimated memory exceeds ``max_memory``.

    Warns:
        UserWarning: ``cellsize`` is larger than the smallest side of the
            model's box (the mesh is empty or far coarser than the model), or,
            with the default bounds, the mesh is empty: ``iso`` is above the
            field's upper bound over every block of the box, or no grid edge
            crosses the level (the surface is smaller than a cell).

    Example:
        >>> import warpblob as wb
        >>> mesh = wb.polygonize(wb.scenes.peanut(), cellsize=0.1)
        >>> mesh.is_closed_manifold()
        True
    """
    h = _positive("cellsize", cellsize)
    iso = _positive("iso", iso)
    tolerance = _positive("tolerance", tolerance)
    if tolerance >= iso:
        # a point where F = 0, far outside, would pass for a vertex
        raise WarpblobError(f"polygonize: tolerance must be below iso={iso!r}, got {tolerance!r}")
    limit = None if max_memory is None else int(_positive("max_memory", max_memory))
    threads = check_threads(threads, "polygonize: threads")
    if not isinstance(relax, (bool, np.bool_)):
        raise WarpblobError(f"polygonize: relax must be True or False, got {relax!r}")
    if progress is not None and not isinstance(progress, (bool, np.bool_)):
        raise WarpblobError(f"polygonize: progress must be True, False or None, got {progress!r}")
    dev = resolve_device(device)
    if limit is None:
        limit = available_memory(dev)
    lm = linearize(model)
    stats = {"cellsize": h}
    grid = _grid(lm, h, bounds)
    if grid is None:
        return _empty(stats)
    g, cells, blocks = grid
    lo, hi = lm.bounds
    side = float(np.min(hi - lo)) if np.all(hi >= lo) else np.inf  # (an empty model has no box)
    if h > side:
        warnings.warn(
            f"polygonize: cellsize={h!r} is larger than the model box's smallest side ({side:.4g}; "
            f"box {_box(lo, hi)}): features thinner than a cell are missed, so the mesh is empty or much "
            "coarser than the model",
            stacklevel=2,
        )
    n_blocks = int(np.prod(blocks))
    show = bool(progress) or (progress is None and n_blocks * _kernels.CELLS >= PROGRESS_CELLS)
    clock = StageClock(dev, "polygonize", 7 if relax else 6, show=show)
    try:
        mesh = _run(lm, g, n_blocks, blocks, dev, iso, tolerance, limit, threads, clock, stats, relax)
    finally:
        clock.close()
    if mesh.face_count == 0 and bounds is None and h <= side:
        # the grid's outermost vertices see F = 0, so blocks all proven to hold no surface are all outside
        if mesh.stats["blocks_rejected"] == n_blocks:
            why = f"iso={iso!r} is above the field's upper bound over every block of the model box {_box(lo, hi)}"
        else:
            why = (
                f"no grid edge of cellsize={h!r} crosses the level iso={iso!r} in the model box {_box(lo, hi)}: "
                "the surface is smaller than a cell, or absent"
            )
        warnings.warn(f"polygonize: the mesh is empty: {why}", stacklevel=2)
    return mesh


def _positive(name: str, value) -> float:
    """``value`` as a float if it is a finite number > 0, else WarpblobError naming it."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise WarpblobError(f"polygonize: {name} must be a positive number, got {value!r}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise WarpblobError(f"polygonize: {name} must be a positive number, got {value!r}") from None
    if not (np.isfinite(x) and x > 0.0):
        raise WarpblobError(f"polygonize: {name} must be a finite number > 0, got {value!r}")
    return x


def _box(lo: np.ndarray, hi: np.ndarray) -> str:
    return f"[{', '.join(f'{v:.4g}' for v in lo)}] to [{', '.join(f'{v:.4g}' for v in hi)}]"


def _empty(stats: dict) -> SurfaceMesh:
    points = np.zeros((0, 3), np.float32)
    empty = SurfaceMesh(points, np.zeros((0, 3), np.int32), points.copy(), points.copy())
    empty.stats = {**stats, "triangles": 0, "vertices": 0, "field_evaluations": 0}
    return empty


def _run(lm, g, n_blocks, blocks, dev, iso, tolerance, limit, threads, clock, stats, relax) -> SurfaceMesh:
    """The stages of :func:`polygonize` on grid ``g`` (arguments checked)."""
    lap = clock.lap
    check_memory("polygonize", "block classification", n_blocks * 16, limit)
    if n_blocks > np.iinfo(np.int32).max // _kernels.CELLS:
        raise ResourceError(f"polygonize: {n_blocks} blocks exceed the int32 index range; use a larger cellsize")
    kernels = _kernel_set()
    table, faces, edge_info = _device_tables(dev)
    m = model_arrays(lm, dev)

    # 1. block rejection by interval bounds
    flags = wp.empty(n_blocks, dtype=wp.int32, device=dev)
    block_states = wp.empty(n_blocks, dtype=wp.int32, device=dev)
    if _use_rows(dev):
        # one thread per 4^3 blocks bounds them all in one tree walk
        supers = -(-blocks // _kernels.SUB_SIDE)
        n_supers = int(np.prod(supers))
        check_memory("polygonize", "block bounds", block_chunk(lm, n_supers)[1], limit)
        inputs = [m, g, float(iso), wp.vec3i(*supers.astype(np.int32))]
        launch_blocks(
            kernels["classify_rows"], n_supers, inputs, [flags, block_states], lm, dev, threads,
            min_chunk=_kernels.BLOCK_CHUNK,
        )  # fmt: skip
    else:
        launch(kernels["classify"], n_blocks, [m, g, float(iso)], [flags, block_states], dev, threads)
    active = compact(flags, dev, threads)
    n_active = active.shape[0]
    block_map = wp.full(n_blocks, -1, dtype=wp.int32, device=dev)
    launch(_kernels.block_map_kernel, n_active, [active], [block_map], dev, threads, min_chunk=_kernels.LIGHT_CHUNK)
    lap("classify")
    stats.update(blocks_total=n_blocks, blocks_rejected=n_blocks - n_active)

    # 2. field at the vertices of active blocks
    n_samples = n_active * _kernels.CELLS  # one sample per owned vertex
    n_cells = n_active * _kernels.CELLS
    if 4 * n_cells > np.iinfo(np.int32).max:  # crossed edges are coded as 4 * cell + axis
        raise ResourceError(f"polygonize: {n_active} blocks hold surface, over the int32 index range; use a larger cellsize")
    check_memory("polygonize", "sampling", n_samples * 4 + n_cells * 4 * 6, limit)
    n_subs = n_active * _kernels.SUB_SIDE**3
    dense = _dense_sampling(lm.node_count, _use_rows(dev))
    if dense:
        # every sub-block undecided: each vertex of the active blocks is sampled
        states = wp.zeros(n_subs, dtype=wp.int32, device=dev)
    else:
        states = wp.empty(n_subs, dtype=wp.int32, device=dev)
    if dense:
        pass
    elif _use_rows(dev):
        # one thread per block bounds its 64 sub-blocks in one tree walk
        check_memory("polygonize", "sub-block bounds", block_chunk(lm, n_active)[1], limit)
        launch_blocks(
            kernels["classify_sub_rows"], n_active, [m, g, float(iso), active], [states], lm, dev, threads,
            min_chunk=_kernels.BLOCK_CHUNK,
        )  # fmt: skip
    else:
        launch(kernels["classify_sub"], n_subs, [m, g, float(iso), active], [states], dev, threads)
    lap("classify_subblocks")
    samples = wp.empty(n_samples, dtype=wp.float32, device=dev)
    # samples taken: one count per block in array mode, a 0 or 1 per vertex in point mode
    evaluated = wp.empty(n_active if _use_rows(dev) else n_samples, dtype=wp.int32, device=dev)
    # per active block, the leaves of the tape pruned over it (stats): counted by the array-mode walk, or by
    # an interval walk over the block's cube where the samples are taken point by point
    tape = wp.empty(n_active, dtype=wp.int32, device=dev)
    if _use_rows(dev):
        # one thread per block walks the tree once for its 512 vertices
        check_memory("polygonize", "block sampling", block_chunk(lm, n_active)[1], limit)
        inputs = [m, g, float(iso), active, block_map, block_states, states, int(dense)]
        launch_blocks(
            kernels["sample_rows"], n_active, inputs, [samples, evaluated, tape], lm, dev, threads,
            min_chunk=_kernels.BLOCK_CHUNK,
        )  # fmt: skip
    else:
        inputs = [m, g, float(iso), active, block_map, block_states, states, int(dense)]
        launch(kernels["sample"], n_samples, inputs, [samples, evaluated], dev, threads)
        launch(kernels["tape"], n_active, [m, g, active], [tape], dev, threads, min_chunk=_kernels.HEAVY_CHUNK)
    lap("sample")

    # 3. crossed edges, cell configurations, counts and prefix sums
    edge_masks = wp.empty(n_cells, dtype=wp.int32, device=dev)
    vertex_counts = wp.empty(n_cells, dtype=wp.int32, device=dev)
    entries = wp.empty(n_cells, dtype=wp.int32, device=dev)
    triangle_counts = wp.empty(n_cells, dtype=wp.int32, device=dev)
    centre_counts = wp.empty(n_cells, dtype=wp.int32, device=dev)
    launch(
        _kernels.count_kernel,
        n_cells,
        [g, float(iso), active, samples, block_map, block_states, states, table, faces],
        [edge_masks, vertex_counts, entries, triangle_counts, centre_counts],
        dev,
        threads,
        min_chunk=_kernels.CELL_CHUNK,
    )
    (vertex_offsets, triangle_offsets, centre_offsets), (n_edge_vertices, n_triangles, n_centres) = scans(
        vertex_counts, triangle_counts, centre_counts
    )
    n_vertices = n_edge_vertices + n_centres
    lap("count")

    # 4. one vertex per crossed edge, on the surface (then loop centres)
    check_memory("polygonize", "output", n_vertices * 44 + n_triangles * 24, limit)
    positions = wp.empty(n_vertices, dtype=wp.vec3, device=dev)
    normals = wp.empty(n_vertices, dtype=wp.vec3, device=dev)
    colors = wp.empty(n_vertices, dtype=wp.vec3, device=dev)
    evaluations = wp.empty(n_vertices, dtype=wp.int32, device=dev)
    iterations = 40  # bisection alone reaches 1e-12 of the edge; Newton usually stops after 1-3
    crossed = wp.empty(n_edge_vertices, dtype=wp.int32, device=dev)
    launch(
        _kernels.crossed_edges_kernel, n_cells, [edge_masks, vertex_offsets], [crossed],
        dev, threads, min_chunk=_kernels.LIGHT_CHUNK,
    )  # fmt: skip
    launch(
        kernels["edge_vertex"],
        n_edge_vertices,
        [m, g, float(iso), float(tolerance), iterations, active, samples, block_map, block_states, crossed],
        [positions, normals, colors, evaluations],
        dev,
        threads,
        min_chunk=_kernels.HEAVY_CHUNK,
    )
    if n_centres:
        launch(
            kernels["centre"],
            n_cells,
            [m, g, float(iso), float(tolerance), iterations, active, block_map, entries, centre_counts, centre_offsets,
             n_edge_vertices, table, edge_info, edge_masks, vertex_offsets],
            [positions, normals, colors, evaluations],
            dev,
            threads,
            min_chunk=_kernels.CELL_CHUNK,
        )  # fmt: skip
    lap("vertices")

    # 5. faces from the table, no field evaluation
    triangles = wp.empty(n_triangles, dtype=wp.vec3i, device=dev)
    launch(
        _kernels.face_kernel,
        n_cells,
        [g, active, block_map, entries, triangle_counts, triangle_offsets, centre_offsets, n_edge_vertices, table,
         edge_info, edge_masks, vertex_offsets, positions],
        [triangles],
        dev,
        threads,
        min_chunk=_kernels.CELL_CHUNK,
    )  # fmt: skip
    # 6. weld the ends of edges shorter than a small fraction of the cell
    triangles, positions, normals, colors, n_welded = _weld.weld(
        triangles, positions, normals, colors, g.h, dev, threads, in_place=True
    )
    n_kept = triangles.shape[0]
    lap("faces")

    # 7. relax the vertices of skinny triangles along the surface
    relax_steps = relaxed = 0
    if relax and n_kept:
        positions, normals, colors, relaxed, relax_steps = _relax.relax(
            kernels["relax"], m, triangles, positions, normals, colors, iso, tolerance, g.h, limit, dev, threads
        )
        lap("relax")

    root_steps = int(evaluations.numpy().sum()) if n_vertices else 0
    grid_evaluations = int(evaluated.numpy().sum(dtype=np.int64)) if n_samples else 0
    interval_evaluations = n_blocks + (0 if dense else n_subs)
    tape_np = tape.numpy() if n_active else np.zeros(0, np.int32)
    field_evaluations = grid_evaluations + root_steps + relax_steps
    stats.update(
        vertices=positions.shape[0],  # after welding
        centre_vertices=n_centres,
        triangles=n_kept,
        degenerate_removed=n_triangles - n_kept,
        welded_vertices=n_welded,
        relaxed_vertices=relaxed,
        relax_evaluations=relax_steps,
        grid_evaluations=grid_evaluations,
        dense_sampling=dense,
        root_evaluations=root_steps,
        field_evaluations=field_evaluations,
        interval_evaluations=interval_evaluations,
        fvept=field_evaluations / max(n_kept, 1),
        fvept_with_intervals=(field_evaluations + interval_evaluations) / max(n_kept, 1),
        tape_leaves=int(lm.primitive_count),
        block_tape_mean=float(tape_np.mean()) if n_active else 0.0,
        block_tape_max=int(tape_np.max()) if n_active else 0,
        block_tapes={"blocks": active.numpy().astype(np.int32), "leaves": tape_np},
        seconds=clock.seconds,
        total_seconds=sum(clock.seconds.values()),
    )
    return SurfaceMesh(
        positions.numpy().reshape(-1, 3),
        triangles.numpy().reshape(-1, 3).astype(np.int32),
        normals.numpy().reshape(-1, 3),
        colors.numpy().reshape(-1, 3),
        stats,
    )
