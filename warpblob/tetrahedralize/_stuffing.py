"""Host side of isosurface stuffing: arguments, one function per stage, memory checks, statistics.

:func:`tetrahedralize` checks its arguments, sizes the lattice and runs the
stages of :mod:`warpblob.tetrahedralize` in order (classification, sampling,
cutting, warping, the graded interior's levels, stencils, nodes, materials),
then builds the mesh. One :class:`~warpblob._stages.StageClock`, started at
the call's first line, times all of it, the mesh construction included, so
``stats["total_seconds"]`` is what the caller waits for.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .._device import resolve_device
from .._errors import ResourceError, WarpblobError
from .._linearize import LinearModel, linearize
from .._parallel import check_threads, launch
from .._stages import PROGRESS_CELLS, StageClock, available_memory, check_memory, compact, scan
from ..field import color
from ..field._engine import block_chunk, launch_blocks, model_arrays
from ..field._kernels import ModelArrays
from ..mesh._tetmesh import TetMesh
from ..tree import ISO_VALUE
from . import _graded, _kernels, _materials, _pinch, _tables
from ._pinch import PinchedBoundaryError, PinchedBoundaryWarning

__all__ = ["ALPHA_LONG", "ALPHA_SHORT", "PinchedBoundaryError", "PinchedBoundaryWarning", "tetrahedralize"]

ALPHA_LONG = 0.24999
ALPHA_SHORT = 0.41189
_WHO = "tetrahedralize"
_ISO = float(ISO_VALUE)
_TOLERANCE = 1e-4  # largest |F - iso| of a cut point
_ROOT_ITERATIONS = 32
_WARP_ROUNDS = 4  # rounds of warp decisions per host sync (chains of violations are short)
#: sub-block bounds and lattice sampling: "auto" (array mode on the CPU, point by point on a GPU), "rows" or
#: "points" (tests)
SAMPLING = "auto"
#: blocks (of 8^3 lattice cubes or points) a CPU thread takes at a time in array mode
_ROW_CHUNK = 16


def _use_rows(device) -> bool:
    """Whether the sub-block bounds and the lattice samples take array-mode walks on ``device``."""
    if SAMPLING == "auto":
        return device.is_cpu
    return SAMPLING == "rows"


_CACHE: dict = {}


def _kernel_set() -> dict:
    if "kernels" not in _CACHE:
        _CACHE["kernels"] = _kernels.make_kernels()
    return _CACHE["kernels"]


def _device_tables(device) -> dict:
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


def _interior_ratio(h: float, cellsize, interior_cellsize) -> int:
    """Fine cubes per side of the coarsest graded cube: ``interior_cellsize / cellsize`` rounded
    down to a power of two, 0 for the uniform lattice (``None`` or a ratio below 2)."""
    if interior_cellsize is None:
        return 0
    hi_cell = _positive("interior_cellsize", interior_cellsize)
    if hi_cell < h * (1.0 - 1e-9):
        raise WarpblobError(
            f"tetrahedralize: interior_cellsize must be >= cellsize, got {interior_cellsize!r} < {cellsize!r}"
        )
    ratio = 2 ** int(np.floor(np.log2(hi_cell / h) + 1e-9))
    return ratio if ratio >= 2 else 0


@dataclass
class _Run:
    """What every stage of one call shares: where it runs and the lattice it works on."""

    device: wp.context.Device
    threads: int | None
    limit: int  # bytes the call may allocate
    lattice: _kernels.Lattice
    n_points: int  # lattice points, black then red
    n_blocks: int  # coarse blocks of BLOCK^3 cubes
    n_subs: int  # sub-blocks of SUB^3 cubes
    model: ModelArrays
    kernels: dict  # the field-evaluating kernels (:func:`_kernels.make_kernels`)
    tables: dict  # the stencil and lattice tables on ``device``
    linear: LinearModel  # the model ``model`` holds (its register count sizes array-mode scratch)

    def launch(self, kernel, dim: int, before: list, after: list) -> None:
        launch(kernel, dim, before, after, self.device, self.threads)


def _lattice(lo: np.ndarray, hi: np.ndarray, h: float) -> tuple[_kernels.Lattice, np.ndarray, int, int, int]:
    """The BCC lattice of spacing ``h`` over the box ``[lo, hi]`` (model units).

    Returns:
        ``(lattice, cells, n_points, n_blocks, n_subs)``: the kernels' description,
        (3,) int64 cubes per axis, and the numbers of points, blocks and sub-blocks.

    Raises:
        ResourceError: the lattice's point or tet indices would not fit in int32.
    """
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
    lat = _kernels.Lattice()
    lat.origin = wp.vec3(*(lo - h).astype(np.float32))
    lat.h = h
    lat.cells = wp.vec3i(*cells.astype(np.int32))
    lat.black = n_black
    lat.blocks = wp.vec3i(*blocks.astype(np.int32))
    lat.subs = wp.vec3i(*subs.astype(np.int32))
    return lat, cells, n_points, n_blocks, n_subs


def _level_dims(cells: np.ndarray, ratio: int) -> list[np.ndarray]:
    """(3,) cubes per axis of each coarse level, level 1 (2 fine cubes a side) first; as many
    levels as ``ratio = 2^n`` asks for and the lattice has room for (none when uniform)."""
    dims: list[np.ndarray] = []
    if ratio:
        d = cells // 2
        while len(dims) < int(np.log2(ratio)) and np.all(d >= 1):
            dims.append(d.copy())
            d = d // 2
    return dims


@dataclass
class _Levels:
    """The graded interior's coarse levels: one flag per cube of every level, in one flat array."""

    sizes: list[int]  # cubes of each level
    offsets: np.ndarray  # (levels + 1,) int32 start of each level in ``flat``
    flat: wp.array  # int32 level flags (:func:`_graded.classify_coarse_kernel`), level 1 first
    offsets_wp: wp.array  # ``offsets`` on the device, at least one entry
    dims_wp: wp.array  # (levels,) vec3i cubes per axis, at least one entry
    level1_dims: wp.vec3i  # level 1's cubes per axis ((1, 1, 1) when uniform)

    @property
    def count(self) -> int:
        return len(self.sizes)

    @property
    def fine_ratio(self) -> int:
        """Fine cubes per level-1 cube side, 0 when uniform: how the fine stencils see level 1."""
        return 2 if self.sizes else 0


def _levels(run: _Run, dims: list[np.ndarray]) -> _Levels:
    """The level bookkeeping (a few integers per level, numpy) and the flag array for ``dims``."""
    sizes = [int(np.prod(d)) for d in dims]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32) if dims else np.zeros(1, np.int32)
    dev = run.device
    return _Levels(
        sizes=sizes,
        offsets=offsets,
        flat=wp.zeros(max(int(offsets[-1]), 1), dtype=wp.int32, device=dev),
        offsets_wp=wp.array(offsets[: max(len(dims), 1)], dtype=wp.int32, device=dev),
        dims_wp=wp.array(np.array(dims or [np.ones(3)], dtype=np.int32), dtype=wp.vec3i, device=dev),
        level1_dims=wp.vec3i(*(dims[0] if dims else np.ones(3)).astype(np.int32)),
    )


def _classify(run: _Run) -> tuple[wp.array, wp.array, wp.array]:
    """Stage 1, empty- and full-space rejection: interval bounds of F on blocks, then on sub-blocks.

    Returns:
        ``(sub_states, bounded, active)``: (S,) int32 MIXED / INSIDE / OUTSIDE per sub-block,
        (S,) int32 1 where a sub-block got its own interval test, and the ascending int32
        indices of the sub-blocks not proven outside.
    """
    dev, k, lat = run.device, run.kernels, run.lattice
    block_states = wp.empty(run.n_blocks, dtype=wp.int32, device=dev)
    run.launch(k["classify_blocks"], run.n_blocks, [run.model, lat, _ISO], [block_states])
    sub_states = wp.empty(run.n_subs, dtype=wp.int32, device=dev)
    bounded = wp.empty(run.n_subs, dtype=wp.int32, device=dev)
    if _use_rows(dev):
        # one bounds-rows walk per mixed block for its 64 sub-blocks
        check_memory(_WHO, "sub-block bounds", block_chunk(run.linear, run.n_blocks)[1], run.limit)
        launch_blocks(k["classify_subs_rows"], run.n_blocks, [run.model, lat, _ISO, block_states], [sub_states, bounded],
                      run.linear, dev, run.threads, min_chunk=_ROW_CHUNK)  # fmt: skip
    else:
        run.launch(k["classify_subs"], run.n_subs, [run.model, lat, _ISO, block_states], [sub_states, bounded])
    flags = wp.empty(run.n_subs, dtype=wp.int32, device=dev)
    run.launch(_kernels.active_flags_kernel, run.n_subs, [sub_states], [flags])
    return sub_states, bounded, compact(flags, dev, run.threads)


def _sample(run: _Run, sub_states: wp.array) -> tuple[wp.array, wp.array]:
    """Stage 2: F at the lattice points a tet of a mixed sub-block uses, a stand-in on the proven side elsewhere.

    Returns:
        ``(values, evaluated)``: (P,) float32 field values and (P,) int32 1 where F was evaluated.
    """
    values = wp.empty(run.n_points, dtype=wp.float32, device=run.device)
    evaluated = wp.empty(run.n_points, dtype=wp.int32, device=run.device)
    if not _use_rows(run.device):
        run.launch(run.kernels["sample"], run.n_points, [run.model, run.lattice, _ISO, sub_states], [values, evaluated])
        return values, evaluated
    # on the CPU, each colour's points in blocks of 8^3, one array-mode tree walk per block
    cells = np.array([run.lattice.cells[0], run.lattice.cells[1], run.lattice.cells[2]], dtype=np.int64)
    for red, dims in ((0, cells + 1), (1, cells)):
        blocks = -(-dims // 8)
        n = int(np.prod(blocks))
        check_memory(_WHO, "lattice sampling", block_chunk(run.linear, n)[1], run.limit)
        launch_blocks(
            run.kernels["sample_rows"], n, [run.model, run.lattice, _ISO, sub_states, red, wp.vec3i(*blocks)],
            [values, evaluated], run.linear, run.device, run.threads, min_chunk=_ROW_CHUNK,
        )  # fmt: skip
    return values, evaluated


@dataclass
class _Cuts:
    """Cut points: one per lattice edge whose ends lie strictly on opposite sides of the surface."""

    masks: wp.array  # (P,) int32 bit mask of each point's crossed owned edges
    offsets: wp.array  # (P,) int32 index of each point's first cut point
    positions: wp.array  # (C,) vec3 cut points, model units
    params: wp.array  # (C,) float32 position along the edge from its owner, in (0, 1)
    steps: wp.array  # (C,) int32 field evaluations of each root search
    count: int  # C


def _cut(run: _Run, values: wp.array, evaluated: wp.array) -> _Cuts:
    """Stage 3: the crossed lattice edges (masks and a scan number them) and a root on each."""
    dev = run.device
    masks = wp.empty(run.n_points, dtype=wp.int32, device=dev)
    counts = wp.empty(run.n_points, dtype=wp.int32, device=dev)
    run.launch(_kernels.count_cuts_kernel, run.n_points, [run.lattice, _ISO, values, evaluated], [masks, counts])
    offsets, n_cuts = scan(counts)
    check_memory(_WHO, "cut point", n_cuts * 28, run.limit)
    cuts = _Cuts(
        masks=masks,
        offsets=offsets,
        positions=wp.empty(n_cuts, dtype=wp.vec3, device=dev),
        params=wp.empty(n_cuts, dtype=wp.float32, device=dev),
        steps=wp.empty(n_cuts, dtype=wp.int32, device=dev),
        count=n_cuts,
    )
    run.launch(
        run.kernels["cut"],
        run.n_points,
        [run.model, run.lattice, _ISO, _TOLERANCE, _ROOT_ITERATIONS, values, evaluated, masks, offsets],
        [cuts.positions, cuts.params, cuts.steps],
    )
    return cuts


def _warp(
    run: _Run, values: wp.array, evaluated: wp.array, cuts: _Cuts, alpha_long: float, alpha_short: float
) -> tuple[wp.array, wp.array, int]:
    """Stage 4, warping: lattice points too close to a cut point move onto it.

    Which violated points move is settled first, so that no point moves onto a
    cut point whose other end moves too: rounds of forced decisions until none
    changes, with one host sync per ``_WARP_ROUNDS`` rounds.

    Returns:
        ``(labels, targets, rounds)``: (P,) int32 final labels (+1, -1, 0 on the
        surface), (P,) int32 the cut point each warped point sits on (-1: not
        warped), and the decision rounds run.
    """
    dev, lat = run.device, run.lattice
    warp_args = [lat, alpha_long, alpha_short, cuts.masks, cuts.offsets, cuts.params]
    states = wp.empty(run.n_points, dtype=wp.int32, device=dev)
    run.launch(_kernels.violated_kernel, run.n_points, [*warp_args, evaluated], [states])
    spare = wp.empty(run.n_points, dtype=wp.int32, device=dev)
    changed = wp.zeros(1, dtype=wp.int32, device=dev)
    rounds = 0
    while True:
        for r in range(_WARP_ROUNDS):
            if r == _WARP_ROUNDS - 1:
                changed.zero_()
            run.launch(_kernels.resolve_kernel, run.n_points, [*warp_args, states], [spare, changed])
            states, spare = spare, states
        rounds += _WARP_ROUNDS
        if int(changed.numpy()[0]) == 0:  # host sync: another batch of rounds, or done
            break
    labels = wp.empty(run.n_points, dtype=wp.int32, device=dev)
    targets = wp.empty(run.n_points, dtype=wp.int32, device=dev)
    run.launch(
        _kernels.warp_points_kernel,
        run.n_points,
        [lat, _ISO, alpha_long, alpha_short, values, cuts.masks, cuts.offsets, cuts.params, states],
        [labels, targets],
    )
    return labels, targets, rounds


def _coarsen(run: _Run, labels: wp.array, levels: _Levels) -> None:
    """Graded interior, after warping: fill ``levels.flat``. A level-1 cube qualifies when its
    lattice points, one fine cube around included, are all ``+``; a level-``L >= 2`` cube when
    the level-``(L - 1)`` cubes of it and its neighbours do (2:1 balance)."""
    for lv, size in enumerate(levels.sizes, start=1):
        part = wp.empty(size, dtype=wp.int32, device=run.device)
        if lv == 1:
            run.launch(_graded.classify_coarse_kernel, size, [run.lattice, labels, 2, levels.level1_dims], [part])
        else:
            run.launch(_graded.classify_level_kernel, size,
                       [levels.flat, levels.offsets_wp, levels.dims_wp, levels.count, lv], [part])  # fmt: skip
        wp.copy(levels.flat, part, dest_offset=int(levels.offsets[lv - 1]), count=size)


@dataclass
class _GradedPlan:
    """Counts and offsets of the graded tets (fine half-pyramids, then each level's leaf cubes)."""

    n_faces: int  # fine cube faces examined for half-pyramids
    transition_counts: wp.array | None
    transition_offsets: wp.array | None
    n_transition: int
    coarse_parts: list  # (level, (6 n,) int32 counts, offsets, tets) per level
    n_coarse: int


def _count_graded(run: _Run, active: wp.array, levels: _Levels) -> _GradedPlan:
    """Count the half-pyramids on fine faces against a level-1 cube and, per level, the leaf cubes' tets."""
    if not levels.count:
        return _GradedPlan(0, None, None, 0, [], 0)
    n_faces = active.shape[0] * _kernels.SUB_CELLS * 6
    check_memory(_WHO, "transition", (n_faces + 6 * sum(levels.sizes)) * 8, run.limit)
    trans_counts = wp.empty(n_faces, dtype=wp.int32, device=run.device)
    run.launch(_graded.count_transition_kernel, n_faces, [run.lattice, active, levels.flat, levels.level1_dims, 2],
               [trans_counts])  # fmt: skip
    trans_offsets, n_transition = scan(trans_counts)
    parts = []
    for lv, size in enumerate(levels.sizes, start=1):
        counts = wp.empty(6 * size, dtype=wp.int32, device=run.device)
        run.launch(_graded.count_coarse_kernel, 6 * size, [levels.flat, levels.offsets_wp, levels.dims_wp,
                   levels.count, lv], [counts])  # fmt: skip
        offsets, n_level = scan(counts)
        parts.append((lv, counts, offsets, n_level))
    return _GradedPlan(n_faces, trans_counts, trans_offsets, n_transition, parts, sum(p[3] for p in parts))


def _emit_graded(run: _Run, active: wp.array, levels: _Levels, plan: _GradedPlan, raw: wp.array, at: int) -> None:
    """Write the graded tets of ``plan`` into ``raw`` from row ``at`` on (half-pyramids, then level by level)."""
    if plan.n_transition:
        part = wp.empty(plan.n_transition, dtype=wp.vec4i, device=run.device)
        run.launch(_graded.emit_transition_kernel, plan.n_faces,
                   [run.lattice, active, plan.transition_counts, plan.transition_offsets], [part])  # fmt: skip
        wp.copy(raw, part, dest_offset=at, count=plan.n_transition)
        at += plan.n_transition
    for lv, counts, offsets, n_level in plan.coarse_parts:
        if n_level:
            part = wp.empty(n_level, dtype=wp.vec4i, device=run.device)
            run.launch(_graded.emit_coarse_kernel, counts.shape[0],
                       [run.lattice, levels.flat, levels.offsets_wp, levels.dims_wp, levels.count, lv, counts,
                        offsets], [part])  # fmt: skip
            wp.copy(raw, part, dest_offset=at, count=n_level)
            at += n_level


def _stencils(
    run: _Run, labels: wp.array, cuts: _Cuts, active: wp.array, levels: _Levels
) -> tuple[wp.array, int, _GradedPlan]:
    """Stage 5: count, scan, emit the tets in lattice-point and cut-point numbering.

    Returns:
        ``(raw, n_stencil, plan)``: (T,) vec4i tets, first the stencils of every
        lattice tet with a ``+`` vertex, then the graded tets of ``plan``.
    """
    dev, tables = run.device, run.tables
    n_threads = active.shape[0] * _kernels.SUB_CELLS * _kernels.TETS_PER_CELL
    check_memory(_WHO, "stencil", n_threads * 12, run.limit)
    patterns = wp.empty(n_threads, dtype=wp.int32, device=dev)
    tet_counts = wp.empty(n_threads, dtype=wp.int32, device=dev)
    run.launch(
        _kernels.count_tets_kernel,
        n_threads,
        [run.lattice, labels, tables["vertices"], tables["counts"], active, levels.flat, levels.level1_dims,
         levels.fine_ratio],
        [patterns, tet_counts],
    )  # fmt: skip
    tet_offsets, n_stencil = scan(tet_counts)
    plan = _count_graded(run, active, levels)
    n_raw = n_stencil + plan.n_transition + plan.n_coarse
    check_memory(_WHO, "tet", n_raw * 32 + (run.n_points + cuts.count) * 8, run.limit)
    raw = wp.empty(n_raw, dtype=wp.vec4i, device=dev)
    run.launch(
        _kernels.emit_tets_kernel,
        n_threads,
        [run.lattice, run.n_points, tables["vertices"], tables["edge_owners"], tables["edge_slots"], tables["refs"],
         cuts.masks, cuts.offsets, active, patterns, tet_counts, tet_offsets],
        [raw],
    )  # fmt: skip
    _emit_graded(run, active, levels, plan, raw, n_stencil)
    return raw, n_stencil, plan


def _nodes(
    run: _Run, raw: wp.array, labels: wp.array, targets: wp.array, cuts: _Cuts
) -> tuple[wp.array, wp.array, wp.array]:
    """Stage 6: keep the lattice and cut points a tet uses, renumbered by a scan.

    Returns:
        ``(nodes, tets, surface)``: (N,) vec3 positions, model units (warped points
        on their cut point), (T,) vec4i tets in that numbering, and (N,) int32 1
        for the nodes on the surface (cut points, warped points, lattice points
        with ``F = iso``).
    """
    dev, n_raw = run.device, raw.shape[0]
    used = wp.zeros(run.n_points + cuts.count, dtype=wp.int32, device=dev)
    run.launch(_kernels.mark_nodes_kernel, n_raw, [raw], [used])
    node_ids, n_nodes = scan(used)
    nodes = wp.empty(n_nodes, dtype=wp.vec3, device=dev)
    run.launch(
        _kernels.write_nodes_kernel,
        run.n_points + cuts.count,
        [run.lattice, run.n_points, targets, cuts.positions, used, node_ids],
        [nodes],
    )
    tets = wp.empty(n_raw, dtype=wp.vec4i, device=dev)
    run.launch(_kernels.renumber_tets_kernel, n_raw, [node_ids, raw], [tets])
    surface = wp.empty(n_nodes, dtype=wp.int32, device=dev)
    run.launch(_pinch.flag_surface_nodes_kernel, run.n_points + cuts.count, [run.n_points, labels, used, node_ids],
               [surface])  # fmt: skip
    return nodes, tets, surface


def _materials_by_color(run: _Run, lm: LinearModel, nodes: wp.array, tets: wp.array) -> tuple[wp.array, np.ndarray]:
    """Stage 7: a material id per tet, the primitive colour nearest the model's colour at its centroid.

    Returns:
        ``(ids, palette)``: (T,) int32 rows of ``palette``, the (M, 3) float32
        distinct primitive colours, sorted (RGB in [0, 1]).
    """
    n_tets = tets.shape[0]
    # bytes per tet: centroid 12, then value 4, gradient 12 and colour 12 (the colour evaluation
    # computes all three), id 4
    check_memory(_WHO, "material", n_tets * 44, run.limit)
    palette = np.unique(lm.color.reshape(-1, 3), axis=0)
    centroids = wp.empty(n_tets, dtype=wp.vec3, device=run.device)
    run.launch(_kernels.average_nodes_kernel, n_tets, [nodes, tets], [centroids])
    colors = color(lm, centroids, threads=run.threads)  # Warp in, Warp out: no host sync
    ids = wp.empty(n_tets, dtype=wp.int32, device=run.device)
    run.launch(_kernels.match_colors_kernel, n_tets, [colors, wp.array(palette, dtype=wp.vec3, device=run.device)],
               [ids])  # fmt: skip
    return ids, palette


def _clocked(mesh: TetMesh, clock: StageClock, start: float) -> TetMesh:
    """``mesh`` with the call's times in its stats: ``seconds`` per stage, their sum
    ``total_seconds``, and ``wall_seconds`` since ``start`` (``time.perf_counter``).
    Written after the last stage, which builds the mesh itself."""
    mesh.stats.update(seconds=clock.seconds, total_seconds=sum(clock.seconds.values()))
    mesh.stats["wall_seconds"] = time.perf_counter() - start
    return mesh


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
    materials=None,
    strict: bool = False,
) -> TetMesh:
    """Fill ``model`` with tetrahedra by isosurface stuffing (Labelle & Shewchuk 2007).

    See :mod:`warpblob.tetrahedralize` for the method and its guarantees.

    Args:
        model: a model (:class:`~warpblob.Node`) or its :class:`~warpblob.LinearModel`;
            with ``materials``, the domain to mesh (``None``: the union of the
            listed solids).
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
        materials: ``None`` (tissues by colour, below), or a sequence of
            solids ``[s0, s1, ...]`` or a mapping name -> solid: a
            multi-material mesh (:mod:`warpblob.tetrahedralize._materials`).
            The material of a point is the innermost listed solid containing
            it, the highest ``i`` with ``F_i >= 0.5`` (0 where none does);
            each tet takes the material of its centroid, ``material[t] = i``,
            and the nodes of the interfaces between materials are snapped
            towards the true interfaces under a quality guard. With
            ``interior_cellsize``, coarse cubes stay inside one material.
            ``stats["materials"]`` holds the names (the mapping's keys, else
            ``material0``, ``material1``, ...).
        strict: raise :class:`PinchedBoundaryError` instead of warning when the
            boundary is pinched (a wall or gap thinner than the cells).

    Returns:
        :class:`~warpblob.mesh.TetMesh` with positively oriented tets,
        ``material`` ((T,) int32, the tissue of each tet: the row of
        ``stats["materials"]``, the sorted distinct primitive colours, nearest
        in squared RGB distance the model's colour at the tet's centroid, ties
        to the lower row), and ``stats``: ``cellsize``,
        ``lattice_points``, ``field_evaluations`` (lattice samples plus
        root-search steps, counted in the kernels), ``lattice_evaluations``,
        ``root_evaluations``, ``interval_evaluations`` (block bounds),
        ``material_evaluations`` (one colour evaluation per tet centroid),
        ``blocks_total``, ``sub_blocks_total``, ``sub_blocks_active`` (not
        proven outside), ``sub_blocks_inside`` (proven inside: tets without
        field evaluation), ``sub_blocks_outside``,
        ``cut_points``, ``warped_points``, ``warp_rounds``, ``tets``, ``nodes``;
        ``interior_cellsize`` (the rounded value, ``cellsize`` when uniform),
        ``coarse_levels`` (0 when uniform), ``stencil_tets``,
        ``transition_tets`` (fine half-pyramids) and ``coarse_tets``: the tets
        come in that order. Times: ``seconds``, per stage (``setup``: the
        argument checks, the model's linearization and device copy, the
        lattice's size; ``classify``, ``sample``, ``cut``, ``warp``,
        ``coarse`` when graded, ``stencil``, ``nodes``, ``materials``,
        ``mesh``: the host copies, these statistics and the mesh object);
        ``total_seconds``, their sum, the whole call but for writing these
        times; and ``wall_seconds``, the whole call by ``time.perf_counter``.
        Thin walls: ``pinched_edges`` (boundary edges in more than two
        boundary faces) and ``pinched_vertices`` (boundary vertices whose
        faces form more than one fan), both 0 for a closed 2-manifold
        boundary; when either is not, ``pinch_thickness`` (the thinnest local
        thickness found at the pinched spots, model units, NaN when none
        could be measured) and ``pinch_cellsize`` (the suggested cell size,
        ``pinch_thickness / RESOLVING_FACTOR``, or half ``cellsize`` when no
        thickness was measured), and a :class:`PinchedBoundaryWarning`.
        With ``materials``: ``materials`` (names), ``tets_per_material``,
        ``interface_faces`` (``"a-b"`` -> count, ``a < b``),
        ``interface_nodes``, ``snap_candidates``, ``snapped_nodes``,
        ``interface_error`` and ``interface_error_unsnapped`` (``max`` and
        ``mean`` distance of the interface nodes from the true interfaces,
        in cell sizes, after and before snapping; after, also ``max_single``
        and ``mean_single`` over the nodes on one interface and off the
        boundary), ``dihedral_min_per_material``
        and ``dihedral_max_per_material`` (degrees, NaN for an empty
        material), ``interface_dihedral_min`` and ``interface_dihedral_max``
        (over the tets with a node on an interface).

    Raises:
        WarpblobError: bad arguments (``interior_cellsize < cellsize``
            included). ResourceError: the estimated memory exceeds ``max_memory``.
            PinchedBoundaryError: ``strict`` and the boundary is pinched.

    Example:
        >>> import warpblob as wb
        >>> from warpblob.tetrahedralize import tetrahedralize
        >>> mesh = tetrahedralize(wb.Point((0, 0, 0), 1.0), cellsize=0.1)
        >>> bool(mesh.volumes().min() > 0), mesh.is_conforming()
        (True, True)
        >>> s = mesh.stats
        >>> list(s["seconds"]), s["total_seconds"] <= s["wall_seconds"]
        (['setup', 'classify', 'sample', 'cut', 'warp', 'stencil', 'nodes', 'materials', 'mesh'], True)
    """
    start = time.perf_counter()
    h = _positive("cellsize", cellsize)
    ratio = _interior_ratio(h, cellsize, interior_cellsize)
    a_long = _alpha("alpha_long", alpha_long)
    a_short = _alpha("alpha_short", alpha_short)
    threads = check_threads(threads, f"{_WHO}: threads")
    dev = resolve_device(device)
    strict = bool(strict)
    names = solids = None
    if materials is not None:
        names, solids = _materials.parse_materials(materials)
        if model is None:
            model = _materials.domain_of(solids)
    lm = linearize(model)
    material_lms = None if solids is None else [linearize(s) for s in solids]
    limit = available_memory(dev) if max_memory is None else int(max_memory)
    stats: dict = {
        "cellsize": h,
        "interior_cellsize": h * ratio if ratio else h,
        "alpha_long": a_long,
        "alpha_short": a_short,
    }
    lo, hi = lm.bounds
    if np.any(lo > hi):
        clock = StageClock(dev, _WHO, 1, start=start)
        stats.update(tets=0, nodes=0, field_evaluations=0, pinched_edges=0, pinched_vertices=0)
        if names is not None:
            stats["materials"] = names
        mesh = TetMesh._trusted(np.zeros((0, 3), np.float32), np.zeros((0, 4), np.int32), np.zeros(0, np.int32), stats)
        clock.lap("mesh")
        return _clocked(mesh, clock, start)

    lat, cells, n_points, n_blocks, n_subs = _lattice(lo, hi, h)
    check_memory(_WHO, "lattice", n_points * 40 + n_subs * 16 + n_blocks * 4, limit)
    level_dims = _level_dims(cells, ratio)
    show = bool(progress) or (progress is None and n_points >= PROGRESS_CELLS)
    clock = StageClock(dev, _WHO, 10 if level_dims else 9, show=show, start=start)
    run = _Run(dev, threads, limit, lat, n_points, n_blocks, n_subs, model_arrays(lm, dev), _kernel_set(),
               _device_tables(dev), lm)  # fmt: skip
    levels = _levels(run, level_dims)
    clock.lap("setup")
    sub_states, bounded, active = _classify(run)
    clock.lap("classify")
    values, evaluated = _sample(run, sub_states)
    clock.lap("sample")
    cuts = _cut(run, values, evaluated)
    clock.lap("cut")
    labels, targets, rounds = _warp(run, values, evaluated, cuts, a_long, a_short)
    clock.lap("warp")
    if levels.count:
        # with materials, no coarse cube may straddle a material interface
        graded = labels if material_lms is None else _materials.coarse_labels(lat, labels, material_lms, dev, threads)
        _coarsen(run, graded, levels)
        clock.lap("coarse")
    raw, n_stencil, plan = _stencils(run, labels, cuts, active, levels)
    clock.lap("stencil")
    nodes, tets, surface = _nodes(run, raw, labels, targets, cuts)
    clock.lap("nodes")
    if material_lms is None:
        material, palette = _materials_by_color(run, lm, nodes, tets)
        nodes_np, material_np = None, None
    else:
        nodes_np, material_np, material_stats, interface_nodes = _multi_material(run, material_lms, nodes, tets,
                                                                                 surface)  # fmt: skip
    clock.lap("materials")

    # host sync: the mesh and its statistics are numpy (on a GPU the first read waits, the rest copy)
    states = sub_states.numpy()
    lattice_evaluations = int(evaluated.numpy().sum())
    root_evaluations = int(cuts.steps.numpy().sum()) if cuts.count else 0
    stats.update(
        lattice_points=n_points,
        blocks_total=n_blocks,
        sub_blocks_total=n_subs,
        sub_blocks_active=active.shape[0],
        sub_blocks_inside=int(np.count_nonzero(states == _kernels.INSIDE)),
        sub_blocks_outside=int(np.count_nonzero(states == _kernels.OUTSIDE)),
        lattice_evaluations=lattice_evaluations,
        root_evaluations=root_evaluations,
        field_evaluations=lattice_evaluations + root_evaluations,
        interval_evaluations=n_blocks + int(bounded.numpy().sum()),
        material_evaluations=tets.shape[0] * (1 if material_lms is None else len(material_lms)),
        cut_points=cuts.count,
        coarse_levels=levels.count,
        stencil_tets=n_stencil,
        transition_tets=plan.n_transition,
        coarse_tets=plan.n_coarse,
        warped_points=int(np.count_nonzero(targets.numpy() >= 0)),
        warp_rounds=rounds,
        tets=tets.shape[0],
        nodes=nodes.shape[0],
    )
    tets_np = tets.numpy().reshape(-1, 4)
    if material_lms is None:
        stats["materials"] = palette.tolist()
        nodes_np, material_np = nodes.numpy().reshape(-1, 3), material.numpy()
    # valid by construction (the tests check the invariants on every scene): not checked again
    mesh = TetMesh._trusted(nodes_np, tets_np, material_np, stats)
    if material_lms is not None:
        stats.update(materials=names, **material_stats, **_material_quality(mesh, len(names), interface_nodes))
    _check_pinches(run, lm, surface, tets, mesh, h, strict)
    clock.lap("mesh")
    return _clocked(mesh, clock, start)


def _multi_material(run: _Run, lms: list, nodes: wp.array, tets: wp.array, surface: wp.array):
    """Stage 7 with ``materials``: labels by centroid, then interface snapping (:mod:`._materials`).

    Returns:
        ``(nodes, material, stats, on)``: (N, 3) float32 snapped positions, (T,) int32
        material ids, the stage's statistics, and (N,) bool the interface nodes.
    """
    n_tets = tets.shape[0]
    check_memory(_WHO, "material", n_tets * (16 + 8 * len(lms)), run.limit)
    centroids = wp.empty(n_tets, dtype=wp.vec3, device=run.device)
    run.launch(_kernels.average_nodes_kernel, n_tets, [nodes, tets], [centroids])
    ids = _materials.label(lms, centroids, run.threads)
    # host glue over the interfaces (surface-sized work after one pass over the tets' faces)
    nodes_np = nodes.numpy().reshape(-1, 3)
    tets_np = tets.numpy().reshape(-1, 4)
    faces, pair, _ = _materials.interface_faces(tets_np, ids)
    h = run.lattice.h
    fixed = surface.numpy() != 0
    _, before = _materials.interface_distances(nodes_np, faces, pair, lms, h, run.threads, run.device)
    snapped, info = _materials.snap(nodes_np, tets_np, ids, lms, h, fixed, run.threads, faces, pair, run.device)
    incid, after = _materials.interface_distances(snapped, faces, pair, lms, h, run.threads, run.device)
    lo, hi, _ = _materials.node_targets(len(nodes_np), faces, pair)
    single = (lo == hi)[incid[:, 0]] & ~fixed[incid[:, 0]]
    keys, counts = np.unique(pair, axis=0, return_counts=True) if len(pair) else (np.zeros((0, 2), int), [])
    stats = {
        "tets_per_material": np.bincount(ids, minlength=len(lms)).tolist(),
        "interface_faces": {f"{a}-{b}": int(c) for (a, b), c in zip(keys.tolist(), list(counts))},
        **info,
        "interface_error": {**_error_summary(after, h),
                            **{f"{k}_single": v for k, v in _error_summary(after[single], h).items()}},
        "interface_error_unsnapped": _error_summary(before, h),
    }
    on = np.zeros(len(nodes_np), dtype=bool)
    on[faces.reshape(-1)] = True
    return snapped, ids, stats, on


def _error_summary(distances: np.ndarray, h: float) -> dict:
    """``max`` and ``mean`` of ``distances`` in cell sizes (0 for no interface)."""
    if not len(distances):
        return {"max": 0.0, "mean": 0.0}
    return {"max": float(distances.max() / h), "mean": float(distances.mean() / h)}


def _material_quality(mesh: TetMesh, n_materials: int, on: np.ndarray) -> dict:
    """Dihedral angle range per material and over the tets with a node on an interface (``on``, per node)."""
    q = mesh.quality()
    lo, hi, ids = q.tet_dihedral_min, q.tet_dihedral_max, mesh.material
    per_lo = [float(lo[ids == m].min()) if np.any(ids == m) else float("nan") for m in range(n_materials)]
    per_hi = [float(hi[ids == m].max()) if np.any(ids == m) else float("nan") for m in range(n_materials)]
    touching = on[mesh.tets].any(axis=1)
    return {
        "dihedral_min_per_material": per_lo,
        "dihedral_max_per_material": per_hi,
        "interface_dihedral_min": float(lo[touching].min()) if touching.any() else float("nan"),
        "interface_dihedral_max": float(hi[touching].max()) if touching.any() else float("nan"),
    }


#: most pinched spots probed for their thickness (spread evenly over the list)
_MAX_PROBES = 4096


def _check_pinches(run: _Run, lm: LinearModel, surface: wp.array, tets: wp.array, mesh: TetMesh, h: float,
                   strict: bool) -> None:  # fmt: skip
    """Thin walls: count the pinched edges and vertices of the boundary into ``mesh.stats``;
    when there are any, estimate the thinnest part, then warn (or raise when ``strict``)."""
    stats = mesh.stats
    if not mesh.tet_count:
        stats.update(pinched_edges=0, pinched_vertices=0)
        return
    candidates = _pinch.candidate_tets(surface, tets, run.device, run.threads)
    faces = _pinch.boundary_faces(mesh.tets[candidates], surface.numpy() != 0)
    edges, vertices = _pinch.find_pinches(faces)
    stats.update(pinched_edges=len(edges), pinched_vertices=len(vertices))
    if not (len(edges) or len(vertices)):
        return
    nodes = mesh.nodes.astype(np.float64)
    spots = np.concatenate([0.5 * (nodes[edges[:, 0]] + nodes[edges[:, 1]]), nodes[vertices]])
    if len(spots) > _MAX_PROBES:
        spots = spots[np.linspace(0, len(spots) - 1, _MAX_PROBES).astype(np.int64)]
    t = _pinch.thickness(lm, spots, h, device=run.device, threads=run.threads)
    thinnest = float(np.nanmin(t)) if np.any(np.isfinite(t)) else float("nan")
    suggested = thinnest / _pinch.RESOLVING_FACTOR if np.isfinite(thinnest) else 0.5 * h
    stats.update(pinch_thickness=thinnest, pinch_cellsize=suggested)
    where = spots[0].round(4).tolist()
    message = (
        f"tetrahedralize: the boundary is pinched at cellsize {h:g} ({len(edges)} edges in more than two "
        f"boundary faces, {len(vertices)} vertices with more than one fan, e.g. near {where}): a wall or gap "
        + (f"{thinnest:.4g} thick" if np.isfinite(thinnest) else "of unmeasured thickness")
        + f" is thinner than the cells; cellsize <= {suggested:.4g} resolves it"
    )
    if strict:
        raise _pinch.PinchedBoundaryError(message)
    warnings.warn(message, _pinch.PinchedBoundaryWarning, stacklevel=3)
