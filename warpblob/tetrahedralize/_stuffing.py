"""Host side of isosurface stuffing: arguments, stages, memory checks, statistics."""

from __future__ import annotations

import numpy as np
import warp as wp

from .._errors import ResourceError, WarpblobError
from .._linearize import linearize
from .._parallel import launch
from .._stages import PROGRESS_CELLS, StageClock, available_memory, check_memory, compact, scan
from .._device import resolve_device
from ..field._engine import model_arrays
from ..mesh._tetmesh import TetMesh
from ..tree import ISO_VALUE
from . import _graded, _kernels, _tables

__all__ = ["ALPHA_LONG", "ALPHA_SHORT", "tetrahedralize"]

ALPHA_LONG = 0.24999
ALPHA_SHORT = 0.41189
_WHO = "tetrahedralize"
_TOLERANCE = 1e-4  # largest |F - iso| of a cut point
_ROOT_ITERATIONS = 32
_WARP_ROUNDS = 4  # rounds of warp decisions per host sync (chains of violations are short)

_CACHE: dict = {}


def _kernel_set():
    if "kernels" not in _CACHE:
        _CACHE["kernels"] = _kernels.make_kernels()
    return _CACHE["kernels"]


def _device_tables(device):
    key = ("tables", str(device))
    if key not in _CACHE:
        counts, refs = _tables.build_stencils()
        owners, slots = _tables.edge_table()
        _CACHE[key] = {
            "vertices": wp.array(_tables.vertex_table(), dtype=wp.vec4i, device=device),
            "edge_owners": wp.array(owners, dtype=wp.vec4i, device=device),
            "edge_slots": wp.array(slots, dtype=wp.int32, device=device),
            "counts": wp.array(counts, dtype=wp.int32, device=device),
            "refs": wp.array(refs, dtype=wp.vec4i, device=device),
        }
    return _CACHE[key]


def _positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise WarpblobError(f"tetrahedralize: {name} must be a positive number, got {value!r}") from None
    if not (np.isfinite(v) and v > 0.0):
        raise WarpblobError(f"tetrahedralize: {name} must be a positive number, got {value!r}")
    return v


def _alpha(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not (0.0 < v < 0.5):
        raise WarpblobError(f"tetrahedralize: {name} must lie in (0, 0.5), got {value!r}")
    return v


def tetrahedralize(
    model,
    *,
    cellsize: float,
    interior_cellsize: float | None = None,
    device=None,
    alpha_long: float = ALPHA_LONG,
    alpha_short: float = ALPHA_SHORT,
    max_memory: int | None = None,
    threads: int | None = None,
    progress: bool | None = None,
):
    """Fill ``model`` with tetrahedra by isosurface stuffing (Labelle & Shewchuk 2007).

    See :mod:`warpblob.tetrahedralize` for the method and its guarantees.

    Args:
        model: a model (:class:`~warpblob.Node`) or its :class:`~warpblob.LinearModel`.
        cellsize: side of the body-centred cubic lattice's cubes (its long
            edge length), model units, > 0.
        interior_cellsize: largest cube side of the graded interior, rounded
            down to ``2^n cellsize``; coarse cubes of side ``2 cellsize`` ..
            ``2^n cellsize`` fill the inside away from the surface (see
            :mod:`warpblob.tetrahedralize`). ``None`` or less than ``2 cellsize``
            give the uniform lattice; must be ``>= cellsize``.
        device: Warp device (default: Warp's default device).
        alpha_long: warping threshold on long (axis-parallel) edges, as a
            fraction of the edge; in (0, 0.5).
        alpha_short: warping threshold on short (diagonal) edges; in (0, 0.5).
            The defaults are the paper's pair with dihedral angles in
            [10.7 deg, 164.8 deg].
        max_memory: bytes the call may allocate (default: what is available).
        threads: CPU threads (default: :func:`warpblob.thread_count`).
        progress: show a bar of the stages on a terminal (``None``: for
            lattices of 8 million cells and more, jobs of seconds).

    Returns:
        :class:`~warpblob.mesh.TetMesh` with positively oriented tets,
        ``material`` (the tissue of each tet: the primitive colour nearest the
        model's colour at its centroid, an index into ``stats["materials"]``,
        see :func:`material_ids`), and ``stats``: ``cellsize``,
        ``lattice_points``, ``field_evaluations`` (lattice samples plus
        root-search steps, counted in the kernels), ``lattice_evaluations``,
        ``root_evaluations``, ``interval_evaluations`` (block bounds),
        ``blocks_total``, ``sub_blocks_total``, ``sub_blocks_active`` (not
        proven outside), ``sub_blocks_inside`` (proven inside: tets without
        field evaluation), ``sub_blocks_outside``,
        ``cut_points``, ``warped_points``, ``tets``, ``nodes``, ``seconds``
        per stage and ``total_seconds``; ``interior_cellsize`` (the rounded
        value, ``cellsize`` when uniform), ``coarse_levels`` (0 when
        uniform), ``stencil_tets``, ``transition_tets`` (fine half-pyramids)
        and ``coarse_tets``: the tets come in that order.

    Raises:
        WarpblobError: bad arguments (``interior_cellsize < cellsize``
            included). ResourceError: the estimated memory exceeds ``max_memory``.

    Example:
        >>> import warpblob as wb
        >>> from warpblob.tetrahedralize import tetrahedralize
        >>> mesh = tetrahedralize(wb.Point((0, 0, 0), 1.0), cellsize=0.1)
        >>> bool(mesh.volumes().min() > 0), mesh.is_conforming()
        (True, True)
    """
    h = _positive("cellsize", cellsize)
    ratio = 0  # fine cubes per coarse cube side; 0: uniform lattice
    if interior_cellsize is not None:
        hi_cell = _positive("interior_cellsize", interior_cellsize)
        if hi_cell < h * (1.0 - 1e-9):
            raise WarpblobError(
                f"tetrahedralize: interior_cellsize must be >= cellsize, got {interior_cellsize!r} < {cellsize!r}"
            )
        # rounded down to a power of two times cellsize (levels of 2, 4, ... cellsize, see the module docs)
        ratio = 2 ** int(np.floor(np.log2(hi_cell / h) + 1e-9))
        if ratio < 2:
            ratio = 0
    a_long = _alpha("alpha_long", alpha_long)
    a_short = _alpha("alpha_short", alpha_short)
    if threads is not None and (not isinstance(threads, int) or isinstance(threads, bool) or threads < 1):
        raise WarpblobError(f"tetrahedralize: threads must be a positive integer, got {threads!r}")
    dev = resolve_device(device)
    lm = linearize(model)
    limit = available_memory(dev) if max_memory is None else int(max_memory)
    iso = float(ISO_VALUE)
    stats: dict = {
        "cellsize": h,
        "interior_cellsize": h * ratio if ratio else h,
        "alpha_long": a_long,
        "alpha_short": a_short,
    }
    lo, hi = lm.bounds
    if np.any(lo > hi):
        stats.update(tets=0, nodes=0, field_evaluations=0, seconds={}, total_seconds=0.0)
        return TetMesh(np.zeros((0, 3), np.float32), np.zeros((0, 4), np.int32), np.zeros(0, np.int32), stats)

    # one empty cube of margin on every side: the outermost points see F = 0, so the
    # tets that would reach past the lattice are outside anyway and the boundary closes
    cells = np.ceil((hi - lo) / h).astype(np.int64) + 2
    blocks = -(-cells // _kernels.BLOCK)
    subs = -(-cells // _kernels.SUB)
    n_black = int(np.prod(cells + 1))
    n_points = n_black + int(np.prod(cells))
    n_blocks, n_subs = int(np.prod(blocks)), int(np.prod(subs))
    if n_points >= np.iinfo(np.int32).max // 2 or n_subs * _kernels.SUB_CELLS * _kernels.TETS_PER_CELL >= 2**31:
        raise ResourceError(
            f"tetrahedralize: {n_points} lattice points exceed the int32 index range; use a larger cellsize"
        )
    check_memory(_WHO, "lattice", n_points * 40 + n_subs * 16 + n_blocks * 4, limit)
    show = bool(progress) or (progress is None and n_points >= PROGRESS_CELLS)
    clock = StageClock(dev, "tetrahedralize", 7 if ratio else 6, show=show)
    lap = clock.lap
    lat = _kernels.Lattice()
    lat.origin = wp.vec3(*(lo - h).astype(np.float32))
    lat.h = h
    lat.cells = wp.vec3i(*cells.astype(np.int32))
    lat.black = n_black
    lat.blocks = wp.vec3i(*blocks.astype(np.int32))
    lat.subs = wp.vec3i(*subs.astype(np.int32))
    kernels = _kernel_set()
    tables = _device_tables(dev)
    m = model_arrays(lm, dev)

    # 1. empty-space and full-space rejection: interval bounds of F on blocks, then sub-blocks
    block_states = wp.empty(n_blocks, dtype=wp.int32, device=dev)
    launch(kernels["classify_blocks"], n_blocks, [m, lat, iso], [block_states], dev, threads)
    sub_states = wp.empty(n_subs, dtype=wp.int32, device=dev)
    bounded = wp.empty(n_subs, dtype=wp.int32, device=dev)
    launch(kernels["classify_subs"], n_subs, [m, lat, iso, block_states], [sub_states, bounded], dev, threads)
    flags = wp.empty(n_subs, dtype=wp.int32, device=dev)
    launch(_kernels.active_flags_kernel, n_subs, [sub_states], [flags], dev, threads)
    active = compact(flags, dev, threads)
    n_active = active.shape[0]
    lap("classify")

    # 2. the field at the lattice points that a tet of a mixed sub-block uses
    values = wp.empty(n_points, dtype=wp.float32, device=dev)
    evaluated = wp.empty(n_points, dtype=wp.int32, device=dev)
    launch(kernels["sample"], n_points, [m, lat, iso, sub_states], [values, evaluated], dev, threads)
    lap("sample")

    # 3. cut points on the crossed lattice edges
    masks = wp.empty(n_points, dtype=wp.int32, device=dev)
    cut_counts = wp.empty(n_points, dtype=wp.int32, device=dev)
    launch(_kernels.count_cuts_kernel, n_points, [lat, iso, values], [masks, cut_counts], dev, threads)
    cut_offsets, n_cuts = scan(cut_counts)
    check_memory(_WHO, "cut point", n_cuts * 28, limit)
    cut_positions = wp.empty(n_cuts, dtype=wp.vec3, device=dev)
    cut_params = wp.empty(n_cuts, dtype=wp.float32, device=dev)
    root_steps = wp.empty(n_cuts, dtype=wp.int32, device=dev)
    launch(
        kernels["cut"],
        n_points,
        [m, lat, iso, _TOLERANCE, _ROOT_ITERATIONS, values, masks, cut_offsets],
        [cut_positions, cut_params, root_steps],
        dev,
        threads,
    )
    lap("cut")

    # 4. warping: lattice points too close to a cut point move onto it. Which violated points
    # move is settled first so that no point moves onto a cut point whose other end moves too
    # (rounds of forced decisions until none changes; one host sync per _WARP_ROUNDS rounds)
    warp_args = [lat, a_long, a_short, masks, cut_offsets, cut_params]
    states = wp.empty(n_points, dtype=wp.int32, device=dev)
    launch(_kernels.violated_kernel, n_points, warp_args, [states], dev, threads)
    spare = wp.empty(n_points, dtype=wp.int32, device=dev)
    changed = wp.zeros(1, dtype=wp.int32, device=dev)
    rounds = 0
    while True:
        for r in range(_WARP_ROUNDS):
            if r == _WARP_ROUNDS - 1:
                changed.zero_()
            launch(_kernels.resolve_kernel, n_points, [*warp_args, states], [spare, changed], dev, threads)
            states, spare = spare, states
        rounds += _WARP_ROUNDS
        if int(changed.numpy()[0]) == 0:
            break
    labels = wp.empty(n_points, dtype=wp.int32, device=dev)
    targets = wp.empty(n_points, dtype=wp.int32, device=dev)
    launch(
        _kernels.warp_points_kernel,
        n_points,
        [lat, iso, a_long, a_short, values, masks, cut_offsets, cut_params, states],
        [labels, targets],
        dev,
        threads,
    )
    lap("warp")

    # 4b. graded interior: level-1 cubes (2 fine cubes a side) whose lattice points, one fine
    # cube around included, are all +; level L >= 2 where a level-(L-1) cube and all its
    # neighbours qualify (2:1 balance). Per-level bookkeeping (a few sizes) in numpy.
    level_dims: list = []
    if ratio:
        d = cells // 2
        while len(level_dims) < int(np.log2(ratio)) and np.all(d >= 1):
            level_dims.append(d.copy())
            d = d // 2
    n_levels = len(level_dims)
    level_sizes = [int(np.prod(d)) for d in level_dims]
    level_offs = np.concatenate([[0], np.cumsum(level_sizes)]).astype(np.int32) if n_levels else np.zeros(1, np.int32)
    flat = wp.zeros(max(int(level_offs[-1]), 1), dtype=wp.int32, device=dev)
    offs_arr = wp.array(level_offs[: max(n_levels, 1)], dtype=wp.int32, device=dev)
    dims_arr = wp.array(np.array(level_dims or [np.ones(3)], dtype=np.int32), dtype=wp.vec3i, device=dev)
    level1_dims = wp.vec3i(*(level_dims[0] if n_levels else np.ones(3)).astype(np.int32))
    for lv in range(1, n_levels + 1):
        part = wp.empty(level_sizes[lv - 1], dtype=wp.int32, device=dev)
        if lv == 1:
            launch(_graded.classify_coarse_kernel, level_sizes[0], [lat, labels, 2, level1_dims], [part], dev, threads)
        else:
            launch(_graded.classify_level_kernel, level_sizes[lv - 1], [flat, offs_arr, dims_arr, n_levels, lv],
                   [part], dev, threads)  # fmt: skip
        wp.copy(flat, part, dest_offset=int(level_offs[lv - 1]), count=level_sizes[lv - 1])
    fine_ratio = 2 if n_levels else 0  # level-1 cubes, as seen from the fine cubes
    if n_levels:
        lap("coarse")

    # 5. stencils: count, scan, emit
    n_threads = n_active * _kernels.SUB_CELLS * _kernels.TETS_PER_CELL
    check_memory(_WHO, "stencil", n_threads * 12, limit)
    patterns = wp.empty(n_threads, dtype=wp.int32, device=dev)
    tet_counts = wp.empty(n_threads, dtype=wp.int32, device=dev)
    launch(
        _kernels.count_tets_kernel,
        n_threads,
        [lat, labels, tables["vertices"], tables["counts"], active, flat, level1_dims, fine_ratio],
        [patterns, tet_counts],
        dev,
        threads,
    )
    tet_offsets, n_stencil = scan(tet_counts)
    n_transition = n_coarse_tets = 0
    coarse_parts = []
    if n_levels:
        # half-pyramids on fine faces against a level-1 cube; per level, the leaf cubes' tets
        n_faces = n_active * _kernels.SUB_CELLS * 6
        check_memory(_WHO, "transition", (n_faces + 6 * sum(level_sizes)) * 8, limit)
        trans_counts = wp.empty(n_faces, dtype=wp.int32, device=dev)
        launch(_graded.count_transition_kernel, n_faces, [lat, active, flat, level1_dims, 2], [trans_counts],
               dev, threads)  # fmt: skip
        trans_offsets, n_transition = scan(trans_counts)
        for lv in range(1, n_levels + 1):
            level_counts = wp.empty(6 * level_sizes[lv - 1], dtype=wp.int32, device=dev)
            launch(_graded.count_coarse_kernel, 6 * level_sizes[lv - 1], [flat, offs_arr, dims_arr, n_levels, lv],
                   [level_counts], dev, threads)  # fmt: skip
            level_offsets, n_level = scan(level_counts)
            coarse_parts.append((lv, level_counts, level_offsets, n_level))
            n_coarse_tets += n_level
    n_raw = n_stencil + n_transition + n_coarse_tets
    check_memory(_WHO, "tet", n_raw * 32 + (n_points + n_cuts) * 8, limit)
    raw = wp.empty(n_raw, dtype=wp.vec4i, device=dev)
    launch(
        _kernels.emit_tets_kernel,
        n_threads,
        [lat, n_points, tables["vertices"], tables["edge_owners"], tables["edge_slots"], tables["refs"], masks,
         cut_offsets, active, patterns, tet_counts, tet_offsets],
        [raw],
        dev,
        threads,
    )  # fmt: skip
    if n_transition:
        part = wp.empty(n_transition, dtype=wp.vec4i, device=dev)
        launch(_graded.emit_transition_kernel, n_faces, [lat, active, trans_counts, trans_offsets], [part], dev,
               threads)  # fmt: skip
        wp.copy(raw, part, dest_offset=n_stencil, count=n_transition)
    at = n_stencil + n_transition
    for lv, level_counts, level_offsets, n_level in coarse_parts:
        if n_level:
            part = wp.empty(n_level, dtype=wp.vec4i, device=dev)
            launch(_graded.emit_coarse_kernel, level_counts.shape[0],
                   [lat, flat, offs_arr, dims_arr, n_levels, lv, level_counts, level_offsets], [part], dev,
                   threads)  # fmt: skip
            wp.copy(raw, part, dest_offset=at, count=n_level)
            at += n_level
    lap("stencil")

    # 6. nodes: keep the points and cut points that a tet uses, renumbered by a scan
    used = wp.zeros(n_points + n_cuts, dtype=wp.int32, device=dev)
    launch(_kernels.mark_nodes_kernel, n_raw, [raw], [used], dev, threads)
    node_ids, n_nodes = scan(used)
    nodes = wp.empty(n_nodes, dtype=wp.vec3, device=dev)
    launch(
        _kernels.write_nodes_kernel,
        n_points + n_cuts,
        [lat, n_points, targets, cut_positions, used, node_ids],
        [nodes],
        dev,
        threads,
    )
    tets = wp.empty(n_raw, dtype=wp.vec4i, device=dev)
    launch(_kernels.renumber_tets_kernel, n_raw, [node_ids, raw], [tets], dev, threads)
    lap("nodes")

    states = sub_states.numpy()
    lattice_evaluations = int(evaluated.numpy().sum())
    root_evaluations = int(root_steps.numpy().sum()) if n_cuts else 0
    stats.update(
        lattice_points=n_points,
        blocks_total=n_blocks,
        sub_blocks_total=n_subs,
        sub_blocks_active=n_active,
        sub_blocks_inside=int(np.count_nonzero(states == _kernels.INSIDE)),
        sub_blocks_outside=int(np.count_nonzero(states == _kernels.OUTSIDE)),
        lattice_evaluations=lattice_evaluations,
        root_evaluations=root_evaluations,
        field_evaluations=lattice_evaluations + root_evaluations,
        interval_evaluations=n_blocks + int(bounded.numpy().sum()),
        cut_points=n_cuts,
        coarse_levels=n_levels,
        stencil_tets=n_stencil,
        transition_tets=n_transition,
        coarse_tets=n_coarse_tets,
        warped_points=int(np.count_nonzero(targets.numpy() >= 0)),
        warp_rounds=rounds,
        tets=n_raw,
        nodes=n_nodes,
        seconds=clock.seconds,
        total_seconds=sum(clock.seconds.values()),
    )
    node_array = nodes.numpy().reshape(-1, 3)
    tet_array = tets.numpy().reshape(-1, 4)
    material, palette = material_ids(lm, node_array[tet_array].mean(axis=1), device=dev, threads=threads)
    stats["materials"] = palette.tolist()
    stats["material_evaluations"] = len(tet_array)  # one colour evaluation per tet centroid
    return TetMesh(node_array, tet_array, material, stats)


def material_ids(model, points, *, device=None, threads=None):
    """A material id per point: the index of the primitive colour nearest the
    model's colour there (tissues are told apart by colour, as in the head's
    skull / CSF / grey / white matter layers).

    Args:
        model: a model or its LinearModel.
        points: (N, 3) positions, model units (tet centroids).

    Returns:
        ``(ids (N,) int32, palette (M, 3) float32)``: the distinct primitive
        colours, sorted, and for each point the row of the nearest one.
    """
    from ..field import color

    lm = linearize(model)
    palette = np.unique(lm.color.reshape(-1, 3), axis=0)
    if len(points) == 0 or len(palette) == 0:
        return np.zeros(len(points), dtype=np.int32), palette
    rgb = color(lm, np.asarray(points, dtype=np.float32), device=device, threads=threads)
    # nearest palette colour, one palette row at a time: (N,) memory, not (N, M, 3)
    ids = np.zeros(len(rgb), dtype=np.int32)
    best = np.full(len(rgb), np.inf, dtype=np.float32)
    for k, c in enumerate(palette):
        d = ((rgb - c) ** 2).sum(axis=1)
        closer = d < best
        ids[closer], best[closer] = k, d[closer]
    return ids, palette
