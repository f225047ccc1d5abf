"""Host side of the polygonizer: stages, memory checks, statistics."""

from __future__ import annotations

import numpy as np
import warp as wp

from .._errors import ResourceError, WarpblobError
from .._stages import PROGRESS_CELLS, StageClock, available_memory, check_memory, compact, scan, scans
from .._stages import compact_kernel
from .._linearize import linearize
from .._parallel import launch
from .._device import resolve_device
from ..field._engine import block_chunk, launch_blocks, model_arrays
from ..mesh import SurfaceMesh
from ..tree import ISO_VALUE
from . import _kernels, _tables

__all__ = ["polygonize", "available_memory"]

_CACHE: dict = {}
#: grid sampling: "rows" walks the tree once per block for its 512 vertices
#: (array mode: the traversal cost is shared, best for CPU threads), "points"
#: once per vertex (one GPU thread each), "auto" picks by device
SAMPLING = "auto"
#: smallest piece of a CPU launch whose items each run a root search (microseconds each)
HEAVY_CHUNK = 64
#: corners of a zero-area triangle closer than WELD cells are welded
WELD = 1.0e-4


def _use_rows(device) -> bool:
    if SAMPLING == "auto":
        return device.is_cpu
    return SAMPLING == "rows"


def _kernel_set():
    if "kernels" not in _CACHE:
        _CACHE["kernels"] = _kernels.make_kernels()
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
        cellsize: grid spacing, model units, > 0.
        bounds: ``(lower, upper)`` box to polygonize (default: the model's box
            plus half a cell, which closes the surface).
        device: Warp device (default: Warp's default device).
        iso: iso-value (default 0.5).
        tolerance: largest ``|F(v) - iso|`` accepted for a vertex.
        max_memory: bytes the call may allocate (default: what is available).
        threads: CPU threads (default: all cores).
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
        WarpblobError: bad arguments. ResourceError: the estimated memory
            exceeds ``max_memory``.

    Example:
        >>> import warpblob as wb
        >>> mesh = wb.polygonize(wb.scenes.peanut(), cellsize=0.1)
        >>> mesh.is_closed_manifold()
        True
    """
    try:
        h = float(cellsize)
    except (TypeError, ValueError):
        raise WarpblobError(f"polygonize: cellsize must be a positive number, got {cellsize!r}") from None
    if not (np.isfinite(h) and h > 0.0):
        raise WarpblobError(f"polygonize: cellsize must be a positive number, got {cellsize!r}")
    if not (np.isfinite(tolerance) and tolerance > 0.0):
        raise WarpblobError(f"polygonize: tolerance must be positive, got {tolerance!r}")
    dev = resolve_device(device)
    lm = linearize(model)
    limit = available_memory(dev) if max_memory is None else int(max_memory)
    stats = {"cellsize": h}
    grid = _grid(lm, h, bounds)
    empty = SurfaceMesh(
        np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    )
    if grid is None:
        empty.stats = {**stats, "triangles": 0, "vertices": 0, "field_evaluations": 0}
        return empty
    g, cells, blocks = grid
    n_blocks = int(np.prod(blocks))
    show = bool(progress) or (progress is None and n_blocks * _kernels.CELLS >= PROGRESS_CELLS)
    clock = StageClock(dev, "polygonize", 7 if relax else 6, show=show)
    try:
        return _run(lm, g, n_blocks, blocks, dev, float(iso), float(tolerance), limit, threads, clock, stats, relax)
    finally:
        clock.close()


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
        launch_blocks(kernels["classify_rows"], n_supers, inputs, [flags, block_states], lm, dev, threads)
    else:
        launch(kernels["classify"], n_blocks, [m, g, float(iso)], [flags, block_states], dev, threads)
    active = compact(flags, dev, threads)
    n_active = active.shape[0]
    block_map = wp.full(n_blocks, -1, dtype=wp.int32, device=dev)
    launch(_kernels.block_map_kernel, n_active, [active], [block_map], dev, threads)
    lap("classify")
    stats.update(blocks_total=n_blocks, blocks_rejected=n_blocks - n_active)

    # 2. field at the vertices of active blocks
    n_samples = n_active * _kernels.CELLS  # one sample per owned vertex
    n_cells = n_active * _kernels.CELLS
    if 4 * n_cells > np.iinfo(np.int32).max:  # crossed edges are coded as 4 * cell + axis
        raise ResourceError(f"polygonize: {n_active} blocks hold surface, over the int32 index range; use a larger cellsize")
    check_memory("polygonize", "sampling", n_samples * 4 + n_cells * 4 * 7, limit)
    n_subs = n_active * _kernels.SUB_SIDE**3
    states = wp.empty(n_subs, dtype=wp.int32, device=dev)
    if _use_rows(dev):
        # one thread per block bounds its 64 sub-blocks in one tree walk
        check_memory("polygonize", "sub-block bounds", block_chunk(lm, n_active)[1], limit)
        launch_blocks(kernels["classify_sub_rows"], n_active, [m, g, float(iso), active], [states], lm, dev, threads)
    else:
        launch(kernels["classify_sub"], n_subs, [m, g, float(iso), active], [states], dev, threads)
    lap("classify_subblocks")
    samples = wp.empty(n_samples, dtype=wp.float32, device=dev)
    evaluated = wp.empty(n_samples, dtype=wp.int32, device=dev)
    if _use_rows(dev):
        # one thread per block walks the tree once for its 512 vertices
        check_memory("polygonize", "block sampling", block_chunk(lm, n_active)[1], limit)
        inputs = [m, g, float(iso), active, block_map, block_states, states]
        launch_blocks(kernels["sample_rows"], n_active, inputs, [samples, evaluated], lm, dev, threads)
    else:
        launch(
            kernels["sample"], n_samples, [m, g, float(iso), active, block_map, block_states, states], [samples, evaluated], dev, threads
        )
    lap("sample")

    # 3. crossed edges, cell configurations, counts and prefix sums
    edge_masks = wp.empty(n_cells, dtype=wp.int32, device=dev)
    vertex_counts = wp.empty(n_cells, dtype=wp.int32, device=dev)
    entries = wp.empty(n_cells, dtype=wp.int32, device=dev)
    triangle_counts = wp.empty(n_cells, dtype=wp.int32, device=dev)
    centre_counts = wp.empty(n_cells, dtype=wp.int32, device=dev)
    launch(
        kernels["count"],
        n_cells,
        [g, float(iso), active, samples, block_map, block_states, states, table, faces],
        [edge_masks, vertex_counts, entries, triangle_counts, centre_counts],
        dev,
        threads,
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
    launch(_kernels.crossed_edges_kernel, n_cells, [edge_masks, vertex_offsets], [crossed], dev, threads)
    launch(
        kernels["edge_vertex"],
        n_edge_vertices,
        [m, g, float(iso), float(tolerance), iterations, active, samples, block_map, block_states, crossed],
        [positions, normals, colors, evaluations],
        dev,
        threads,
        min_chunk=HEAVY_CHUNK,
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
        )  # fmt: skip
    lap("vertices")

    # 5. faces from the table, no field evaluation
    triangles = wp.empty(n_triangles, dtype=wp.vec3i, device=dev)
    launch(
        kernels["face"],
        n_cells,
        [g, active, block_map, entries, triangle_counts, triangle_offsets, centre_offsets, n_edge_vertices, table,
         edge_info, edge_masks, vertex_offsets, positions],
        [triangles],
        dev,
        threads,
    )  # fmt: skip
    # 6. drop zero-area triangles, welding coincident corners first
    triangles, positions, normals, colors, n_welded = _drop_degenerate(triangles, positions, normals, colors, g.h, dev, threads)
    n_kept = triangles.shape[0]
    lap("faces")

    # 7. relax the vertices of skinny triangles along the surface
    relax_steps = relaxed = 0
    if relax and n_kept:
        positions, normals, colors, relaxed, relax_steps = _relax(
            m, triangles, positions, normals, colors, iso, tolerance, g.h, limit, dev, threads
        )
        lap("relax")

    root_steps = int(evaluations.numpy().sum()) if n_vertices else 0
    grid_evaluations = int(evaluated.numpy().sum()) if n_samples else 0
    interval_evaluations = n_blocks + n_subs
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
        root_evaluations=root_steps,
        field_evaluations=field_evaluations,
        interval_evaluations=interval_evaluations,
        fvept=field_evaluations / max(n_kept, 1),
        fvept_with_intervals=(field_evaluations + interval_evaluations) / max(n_kept, 1),
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


def _drop_degenerate(triangles, positions, normals, colors, h: float, device, threads=None):
    """Remove zero-area triangles from a closed mesh and keep it closed.

    Zero-area triangles appear where the surface passes through a grid
    vertex: several edge vertices land on it and the triangles between them
    collapse. Their coincident corners are welded first (:func:`_weld`), so
    dropping them leaves no hole; vertices no triangle uses any more are
    removed. Returns (triangles, positions, normals, colors, welded vertices).
    The usual case, no zero-area triangle, costs one kernel and one scan."""
    degenerate = _kernel_set()["degenerate"]
    n = triangles.shape[0]
    keep = wp.empty(n, dtype=wp.int32, device=device)
    launch(degenerate, n, [positions, triangles], [keep], device, threads)
    offsets, n_kept = scan(keep)
    if n_kept == n:
        return triangles, positions, normals, colors, 0
    triangles, n_welded = _weld(triangles, keep, positions, h, device, threads)
    launch(degenerate, n, [positions, triangles], [keep], device, threads)
    offsets, n_kept = scan(keep)
    kept = wp.empty(n_kept, dtype=wp.vec3i, device=device)
    launch(_kernels.compact_triangles_kernel, n, [triangles, keep, offsets], [kept], device, threads)
    return (*_drop_unused(kept, positions, normals, colors, device, threads), n_welded)


def _weld(triangles, keep, positions, h: float, device, threads):
    """Triangles with the coincident corners of the zero-area ones welded, and
    how many vertices were welded away.

    A zero-area triangle's edges shorter than ``WELD * h`` join their corners
    (the surface passed through a grid vertex and several edge vertices landed
    on it); each connected group becomes its lowest-numbered vertex. Only the
    few zero-area triangles (``keep`` 0) are read back to the host; a zero-area
    triangle without a short edge (three distinct collinear corners) is just
    dropped."""
    flags = wp.empty(keep.shape[0], dtype=wp.int32, device=device)
    launch(_kernels.dropped_kernel, keep.shape[0], [keep], [flags], device, threads)
    dropped = compact(flags, device, threads).numpy()
    tris = triangles.numpy().reshape(-1, 3)[dropped]
    p = positions.numpy().reshape(-1, 3).astype(np.float64)
    a = tris.reshape(-1)
    b = tris[:, [1, 2, 0]].reshape(-1)
    short = np.linalg.norm(p[a] - p[b], axis=1) <= WELD * h
    a, b = a[short], b[short]
    if len(a) == 0:
        return triangles, 0
    # connected groups by label propagation (the graph has a handful of nodes)
    nodes, inv = np.unique(np.concatenate([a, b]), return_inverse=True)
    ia, ib = inv[: len(a)], inv[len(a) :]
    label = np.arange(len(nodes))
    while True:
        low = np.minimum(label[ia], label[ib])
        new = label.copy()
        np.minimum.at(new, ia, low)
        np.minimum.at(new, ib, low)
        new = new[new]
        if np.array_equal(new, label):
            break
        label = new
    weld = np.arange(positions.shape[0], dtype=np.int32)
    weld[nodes] = nodes[label]
    out = wp.empty_like(triangles)
    launch(
        _kernels.remap_triangles_kernel, triangles.shape[0], [triangles, wp.array(weld, dtype=wp.int32, device=device)],
        [out], device, threads,
    )  # fmt: skip
    return out, int(np.count_nonzero(nodes[label] != nodes))


def _drop_unused(triangles, positions, normals, colors, device, threads):
    """Remove the vertices no triangle uses and renumber the triangles."""
    n = positions.shape[0]
    used = wp.zeros(n, dtype=wp.int32, device=device)
    launch(_kernels.used_vertices_kernel, triangles.shape[0], [triangles], [used], device, threads)
    new_index, n_used = scan(used)
    if n_used == n:
        return triangles, positions, normals, colors
    kept = wp.empty(n_used, dtype=wp.int32, device=device)
    launch(compact_kernel, n, [used, new_index], [kept], device, threads)
    out = [wp.empty(n_used, dtype=wp.vec3, device=device) for _ in range(3)]
    launch(_kernels.gather_vertices_kernel, n_used, [kept, positions, normals, colors], out, device, threads)
    renumbered = wp.empty_like(triangles)
    launch(_kernels.remap_triangles_kernel, triangles.shape[0], [triangles, new_index], [renumbered], device, threads)
    return (renumbered, *out)


#: relaxation: triangles whose smallest angle is under this are improved
RELAX_ANGLE = 10.0
#: the fraction of the way to the neighbours' centroid a vertex moves
RELAX_AMOUNT = 0.5


def _relax(m, triangles, positions, normals, colors, iso, tolerance, h, limit, device, threads):
    """Tangential relaxation of the vertices of skinny triangles (see
    :func:`polygonize`'s ``relax``). Returns new (positions, normals, colors),
    the number of vertices that moved and the field evaluations it took.

    The corners at flagged vertices are listed as (vertex, triangle) pairs,
    sorted by vertex (``wp.utils.radix_sort_pairs``, stable), so each vertex
    reads its own triangles without atomics; the thread of a vertex's first
    corner moves it.
    Moves are then checked per triangle (no triangle turned over, collapsed,
    or made skinnier than both before and the angle limit) and the moved
    corners of a failing triangle are put back, until every triangle passes."""
    n_vertices = positions.shape[0]
    n_triangles = triangles.shape[0]
    kernels = _kernel_set()
    cos_limit = float(np.cos(np.radians(RELAX_ANGLE)))
    flags = wp.zeros(n_vertices, dtype=wp.int32, device=device)
    launch(_kernels.skinny_vertices_kernel, n_triangles, [positions, triangles, cos_limit], [flags], device, threads)
    counts = wp.empty(n_triangles, dtype=wp.int32, device=device)
    launch(_kernels.flagged_corners_kernel, n_triangles, [triangles, flags], [counts], device, threads)
    offsets, n_corners = scan(counts)
    if n_corners == 0:
        return positions, normals, colors, 0, 0
    check_memory("polygonize", "relaxation", n_corners * 20 + n_vertices * 40, limit)
    corner_vertex = wp.empty(2 * n_corners, dtype=wp.int32, device=device)
    corner_triangle = wp.empty(2 * n_corners, dtype=wp.int32, device=device)
    launch(_kernels.emit_corners_kernel, n_triangles, [triangles, flags, offsets], [corner_vertex, corner_triangle], device, threads)
    wp.utils.radix_sort_pairs(corner_vertex, corner_triangle, n_corners)
    new = [wp.clone(a) for a in (positions, normals, colors)]
    moved = wp.zeros(n_vertices, dtype=wp.int32, device=device)
    evaluations = wp.empty(n_corners, dtype=wp.int32, device=device)
    launch(
        kernels["relax"], n_corners,
        [m, float(iso), float(tolerance), RELAX_AMOUNT, float(h), positions, normals, triangles, corner_vertex,
         corner_triangle, n_corners],
        [*new, moved, evaluations], device, threads, min_chunk=HEAVY_CHUNK,
    )  # fmt: skip
    revert = wp.empty(n_vertices, dtype=wp.int32, device=device)
    for _ in range(8):
        revert.zero_()
        launch(_kernels.flipped_kernel, n_triangles, [positions, new[0], triangles, moved, cos_limit], [revert], device, threads)
        _, n_revert = scan(revert)
        if n_revert == 0:
            break
        launch(_kernels.revert_kernel, n_vertices, [revert, positions, normals, colors], [*new, moved], device, threads)
    else:  # pragma: no cover - the moves never settled: keep none of them
        return positions, normals, colors, 0, int(evaluations.numpy().sum())
    _, n_moved = scan(moved)
    return (*new, n_moved, int(evaluations.numpy().sum()))
