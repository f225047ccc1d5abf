"""Warp kernels of the block-sparse polygonizer (see :mod:`warpblob.polygonize`)."""

from __future__ import annotations

import warp as wp

from ..field._kernels import (
    BLOCK_POINTS, SUB_BLOCKS, ModelArrays, block_result, block_rows, cubic_guess, make_evaluate, make_segment_root,
    points_cube, sub_bounds, vec7,
)  # fmt: skip
from ._tables import APEX

BLOCK = 8  # cells per block side
CELLS = BLOCK * BLOCK * BLOCK
assert CELLS == BLOCK_POINTS  # array-mode evaluation works on whole blocks
MAX_LOOP = 12
# Smallest pieces of CPU launches (warpblob._parallel.launch). A launch split
# over the thread pool costs about 0.15 ms more than one piece, plus 20-35 us
# per piece (a trivial kernel over 4,096 items: 22 us in one piece, 150-240 us
# in four; over 65,536: 150 us against 400-700 us in sixteen), so a piece must
# carry about half a millisecond of work to pay: tumor at h = 0.14 took 6.5 ms
# on 2 threads with the old pieces and 4.2 ms on one.
#: items that each run a root search (0.3-3 us each)
HEAVY_CHUNK = 1024
#: cells of the counting and face kernels (about 30 ns each), triangles of the
#: angle and length tests of the weld and relaxation (10-15 ns each)
CELL_CHUNK = 1 << 14
#: blocks of an array-mode walk (15-60 us each)
BLOCK_CHUNK = 16
#: items that each take a few nanoseconds (a lookup, a compare, a copy: the
#: weld's and relaxation's bookkeeping)
LIGHT_CHUNK = 1 << 18

_BLOCK = wp.constant(BLOCK)
_CELLS = wp.constant(CELLS)
_APEX = wp.constant(APEX)
SUB = 2  # cells per sub-block side
SUB_SIDE = BLOCK // SUB  # sub-blocks per block side
_SUB = wp.constant(SUB)
_SUB_SIDE = wp.constant(SUB_SIDE)
_SUBS = wp.constant(SUB_SIDE * SUB_SIDE * SUB_SIDE)
assert SUB_SIDE**3 == SUB_BLOCKS  # bounds rows cover a block's sub-blocks

vec12i = wp.types.vector(length=MAX_LOOP, dtype=wp.int32)
vec8 = wp.types.vector(length=8, dtype=wp.float32)


@wp.struct
class Grid:
    origin: wp.vec3  # position of global vertex (0, 0, 0)
    h: float  # cell size
    cells: wp.vec3i  # cells per axis; vertices run 0..cells
    blocks: wp.vec3i  # blocks per axis


@wp.func
def vertex_position(g: Grid, gx: int, gy: int, gz: int):
    return g.origin + g.h * wp.vec3(float(gx), float(gy), float(gz))


@wp.func
def block_coords(g: Grid, b: int):
    return wp.vec3i(b % g.blocks[0], (b // g.blocks[0]) % g.blocks[1], b // (g.blocks[0] * g.blocks[1]))


@wp.func
def active_cell(g: Grid, active: wp.array(dtype=wp.int32), cell: int):
    """(active block a, its block coordinates, block-local (i, j, k)) of cell
    (or owned vertex) ``cell = a * 512 + l`` of the active blocks."""
    a = cell // _CELLS
    return a, block_coords(g, active[a]), local_cell(cell - a * _CELLS)


@wp.func
def local_cell(l: int):
    """Block-local (i, j, k) of cell (or owned vertex) ``l`` in [0, 512)."""
    return wp.vec3i(l % _BLOCK, (l // _BLOCK) % _BLOCK, l // (_BLOCK * _BLOCK))


@wp.func
def sub_state(
    g: Grid,
    gs: wp.vec3i,
    block_map: wp.array(dtype=wp.int32),
    block_states: wp.array(dtype=wp.int32),
    states: wp.array(dtype=wp.int32),
):
    """State of the sub-block at global sub-block coordinates ``gs``: 0 may hold
    surface, 1 inside, 2 outside (from its block when the block was rejected),
    -1 outside the grid of blocks."""
    bx = gs[0] // _SUB_SIDE
    by = gs[1] // _SUB_SIDE
    bz = gs[2] // _SUB_SIDE
    if bx >= g.blocks[0] or by >= g.blocks[1] or bz >= g.blocks[2]:
        return -1
    b = (bz * g.blocks[1] + by) * g.blocks[0] + bx
    a = block_map[b]
    if a < 0:
        return block_states[b]
    ls = ((gs[2] - bz * _SUB_SIDE) * _SUB_SIDE + (gs[1] - by * _SUB_SIDE)) * _SUB_SIDE + (gs[0] - bx * _SUB_SIDE)
    return states[a * _SUBS + ls]


@wp.func
def sample_at(
    g: Grid,
    a: int,
    b: wp.vec3i,
    li: int,
    lj: int,
    lk: int,
    iso: float,
    samples: wp.array(dtype=wp.float32),
    block_map: wp.array(dtype=wp.int32),
    block_states: wp.array(dtype=wp.int32),
):
    """Sample at block-local vertex (li, lj, lk) in [-1, 9]^3 (inside the grid) of active block ``a``
    at block coordinates ``b``: its own, a neighbour's, or a rejected
    neighbour's stand-in."""
    if li >= 0 and lj >= 0 and lk >= 0 and li < _BLOCK and lj < _BLOCK and lk < _BLOCK:
        return samples[a * _CELLS + (lk * _BLOCK + lj) * _BLOCK + li]
    gx = b[0] * _BLOCK + li
    gy = b[1] * _BLOCK + lj
    gz = b[2] * _BLOCK + lk
    bx = gx // _BLOCK
    by = gy // _BLOCK
    bz = gz // _BLOCK
    if bx >= g.blocks[0] or by >= g.blocks[1] or bz >= g.blocks[2]:
        return iso - 0.5
    nb = (bz * g.blocks[1] + by) * g.blocks[0] + bx
    na = block_map[nb]
    if na < 0:
        return wp.where(block_states[nb] == 1, iso + 0.5, iso - 0.5)
    return samples[na * _CELLS + ((gz - bz * _BLOCK) * _BLOCK + (gy - by * _BLOCK)) * _BLOCK + (gx - bx * _BLOCK)]


@wp.func
def vertex_need(
    g: Grid,
    v: wp.vec3i,
    block_map: wp.array(dtype=wp.int32),
    block_states: wp.array(dtype=wp.int32),
    states: wp.array(dtype=wp.int32),
):
    """(needed, proven) for grid vertex ``v``: needed (1) when it touches a
    sub-block that may hold surface (in its block or a neighbour), else the
    proven side (1 inside, 2 outside) of a sub-block it touches."""
    needed = int(0)
    proven = int(0)
    for dk in range(2):
        zk = v[2] - 1 + dk
        if zk >= 0 and (dk == 0 or zk // _SUB != (v[2] - 1) // _SUB or v[2] == 0):
            for dj in range(2):
                zj = v[1] - 1 + dj
                if zj >= 0 and (dj == 0 or zj // _SUB != (v[1] - 1) // _SUB or v[1] == 0):
                    for di in range(2):
                        zi = v[0] - 1 + di
                        if zi >= 0 and (di == 0 or zi // _SUB != (v[0] - 1) // _SUB or v[0] == 0):
                            st = sub_state(g, wp.vec3i(zi // _SUB, zj // _SUB, zk // _SUB), block_map, block_states, states)
                            if st == 0:
                                needed = 1
                            elif st > 0:
                                proven = st
    return wp.vec2i(needed, proven)


@wp.func
def proven_side(r: vec7, iso: float):
    """0 when the bounds (F_min, F_max) in ``r`` straddle ``iso``, 1 when all
    inside (``F >= iso``), 2 when all outside."""
    if r[0] >= iso:
        return 1
    if r[1] < iso:
        return 2
    return 0


@wp.func
def store_vertex(
    out: int,
    x: wp.vec3,
    r: vec7,
    count: int,
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    evaluations: wp.array(dtype=wp.int32),
):
    """Write vertex ``out`` at ``x`` with the normal (-grad F, unit) and colour of evaluation ``r``."""
    positions[out] = x
    normals[out] = -wp.normalize(wp.vec3(r[1], r[2], r[3]))
    colors[out] = wp.vec3(r[4], r[5], r[6])
    evaluations[out] = count


@wp.func
def smallest_angle_cosine(p0: wp.vec3, p1: wp.vec3, p2: wp.vec3):
    """The cosine of a triangle's smallest interior angle (the largest of
    its three cosines): comparing these orders triangles as their
    smallest angles do, without an arccosine."""
    e0 = wp.normalize(p1 - p0)
    e1 = wp.normalize(p2 - p1)
    e2 = wp.normalize(p0 - p2)
    c0 = -wp.dot(e2, e0)
    c1 = -wp.dot(e0, e1)
    c2 = -wp.dot(e1, e2)
    return wp.clamp(wp.max(wp.max(c0, c1), c2), -1.0, 1.0)


@wp.func
def inside(v: float, iso: float):
    return v >= iso


@wp.kernel(enable_backward=False)
def count_kernel(
    g: Grid,
    iso: float,
    active: wp.array(dtype=wp.int32),
    samples: wp.array(dtype=wp.float32),
    block_map: wp.array(dtype=wp.int32),
    block_states: wp.array(dtype=wp.int32),
    states: wp.array(dtype=wp.int32),
    table: wp.array2d(dtype=wp.int32),
    faces: wp.array(dtype=wp.vec4i),
    offset: int,
    edge_masks: wp.array(dtype=wp.int32),
    vertex_counts: wp.array(dtype=wp.int32),
    entries: wp.array(dtype=wp.int32),
    triangle_counts: wp.array(dtype=wp.int32),
    centre_counts: wp.array(dtype=wp.int32),
):
    """Per cell (and owned vertex) of the active blocks: its crossed edges
    (+x, +y, +z from its lower corner, a 3-bit mask), the table entry of its
    configuration and face decisions, and its triangle and centre counts."""
    tid = wp.tid() + offset
    a, c, lc = active_cell(g, active, tid)
    i = lc[0]
    j = lc[1]
    k = lc[2]
    gx = c[0] * _BLOCK + i
    gy = c[1] * _BLOCK + j
    gz = c[2] * _BLOCK + k
    # crossed edges owned by vertex (i, j, k): +x, +y, +z, inside the grid
    mask = int(0)
    entry = int(0)
    count = int(0)
    centres = int(0)
    # a cell of a proven sub-block has corners of one sign: nothing to count
    proven = states[a * _SUBS + ((k // _SUB) * _SUB_SIDE + j // _SUB) * _SUB_SIDE + i // _SUB] != 0
    if proven:
        pass
    elif gx < g.cells[0] and gy < g.cells[1] and gz < g.cells[2]:
        # a cell of the grid: its corners give the owned edges (corner 0 to 1, 2, 4) and its configuration
        vals = vec8()
        config = int(0)
        for n in range(8):
            v = sample_at(g, a, c, i + (n & 1), j + ((n >> 1) & 1), k + ((n >> 2) & 1), iso, samples, block_map, block_states) - iso
            vals[n] = v
            if v >= 0.0:
                config = config | (1 << n)
        b0 = config & 1
        mask = (((config >> 1) & 1) ^ b0) | ((((config >> 2) & 1) ^ b0) << 1) | ((((config >> 4) & 1) ^ b0) << 2)
        bits = int(0)
        # corners of one sign (most cells): no face to decide, no loop (entry 0 or 255 * 64)
        for f in range(wp.where(config == 0 or config == 255, 0, 6)):
            q = faces[f]
            v0 = vals[q[0]]
            v1 = vals[q[1]]
            v2 = vals[q[2]]
            v3 = vals[q[3]]
            if (v0 >= 0.0) == (v2 >= 0.0) and (v1 >= 0.0) == (v3 >= 0.0) and (v0 >= 0.0) != (v1 >= 0.0):
                # asymptotic decider: the inside pair is joined when the bilinear
                # saddle is inside, i.e. its product is at least the outside pair's
                p_in = v0 * v2
                p_out = v1 * v3
                if v1 >= 0.0:
                    p_in = v1 * v3
                    p_out = v0 * v2
                if p_in >= p_out:
                    bits = bits | (1 << f)
        entry = config * 64 + bits
        for lp in range(table[entry, 1]):
            n = table[entry, 2 + lp]
            if table[entry, _APEX + lp] != 0:
                count += n - 2
            else:
                count += n
                centres += 1
    elif gx <= g.cells[0] and gy <= g.cells[1] and gz <= g.cells[2]:
        # a vertex on the grid's upper faces: its edges along them
        s0 = inside(sample_at(g, a, c, i, j, k, iso, samples, block_map, block_states), iso)
        if gx < g.cells[0] and inside(sample_at(g, a, c, i + 1, j, k, iso, samples, block_map, block_states), iso) != s0:
            mask = mask | 1
        if gy < g.cells[1] and inside(sample_at(g, a, c, i, j + 1, k, iso, samples, block_map, block_states), iso) != s0:
            mask = mask | 2
        if gz < g.cells[2] and inside(sample_at(g, a, c, i, j, k + 1, iso, samples, block_map, block_states), iso) != s0:
            mask = mask | 4
    edge_masks[tid] = mask
    vertex_counts[tid] = (mask & 1) + ((mask >> 1) & 1) + ((mask >> 2) & 1)
    entries[tid] = entry
    triangle_counts[tid] = count
    centre_counts[tid] = centres


@wp.func
def edge_vertex(
    g: Grid,
    b: wp.vec3i,
    li: int,
    lj: int,
    lk: int,
    axis: int,
    block_map: wp.array(dtype=wp.int32),
    edge_masks: wp.array(dtype=wp.int32),
    vertex_offsets: wp.array(dtype=wp.int32),
):
    """Index of the vertex on the edge owned by block-local vertex (li, lj, lk)."""
    gx = b[0] * _BLOCK + li
    gy = b[1] * _BLOCK + lj
    gz = b[2] * _BLOCK + lk
    bx = gx // _BLOCK
    by = gy // _BLOCK
    bz = gz // _BLOCK
    a = block_map[(bz * g.blocks[1] + by) * g.blocks[0] + bx]
    o = a * _CELLS + ((gz - bz * _BLOCK) * _BLOCK + (gy - by * _BLOCK)) * _BLOCK + (gx - bx * _BLOCK)
    mask = edge_masks[o]
    below = mask & ((1 << axis) - 1)
    return vertex_offsets[o] + (below & 1) + ((below >> 1) & 1)


@wp.func
def loop_ids(
    g: Grid,
    b: wp.vec3i,
    i: int,
    j: int,
    k: int,
    table: wp.array2d(dtype=wp.int32),
    entry: int,
    first: int,
    n: int,
    edge_info: wp.array(dtype=wp.vec4i),
    block_map: wp.array(dtype=wp.int32),
    edge_masks: wp.array(dtype=wp.int32),
    vertex_offsets: wp.array(dtype=wp.int32),
):
    """Vertex indices of one loop of cell (i, j, k) of block ``b``."""
    ids = vec12i()
    for t in range(n):
        e = edge_info[table[entry, 6 + first + t]]
        ids[t] = edge_vertex(g, b, i + e[0], j + e[1], k + e[2], e[3], block_map, edge_masks, vertex_offsets)
    return ids


@wp.kernel(enable_backward=False)
def face_kernel(
    g: Grid,
    active: wp.array(dtype=wp.int32),
    block_map: wp.array(dtype=wp.int32),
    entries: wp.array(dtype=wp.int32),
    triangle_counts: wp.array(dtype=wp.int32),
    triangle_offsets: wp.array(dtype=wp.int32),
    centre_offsets: wp.array(dtype=wp.int32),
    first_centre: int,
    table: wp.array2d(dtype=wp.int32),
    edge_info: wp.array(dtype=wp.vec4i),
    edge_masks: wp.array(dtype=wp.int32),
    vertex_offsets: wp.array(dtype=wp.int32),
    positions: wp.array(dtype=wp.vec3),
    offset: int,
    triangles: wp.array(dtype=wp.vec3i),
):
    """The triangles of each cell's loops: fanned from the allowed apex that
    maximizes the smallest angle, or around the loop's centre vertex."""
    tid = wp.tid() + offset
    if triangle_counts[tid] == 0:
        return
    a, b, lc = active_cell(g, active, tid)
    i = lc[0]
    j = lc[1]
    k = lc[2]
    entry = entries[tid]
    out = triangle_offsets[tid]
    centre = first_centre + centre_offsets[tid]
    first = int(0)
    for lp in range(table[entry, 1]):
        n = table[entry, 2 + lp]
        apexes = table[entry, _APEX + lp]
        ids = loop_ids(g, b, i, j, k, table, entry, first, n, edge_info, block_map, edge_masks, vertex_offsets)
        if apexes == 0:
            for t in range(n):
                triangles[out] = wp.vec3i(ids[t], ids[(t + 1) % n], centre)
                out += 1
            centre += 1
        else:
            # fan from the allowed apex that maximizes the smallest angle
            # (minimizes the largest smallest-angle cosine)
            apex = int(-1)
            best = float(2.0)
            if n == 3:
                # one triangle whatever the apex: the first allowed one (every
                # apex gives the same cosines, a tie kept by the strict test below)
                for s in range(3):
                    if apex < 0 and (apexes >> s) & 1 != 0:
                        apex = s
            # a loop of four has two fans, not four: apexes s and s + 2 make the same two triangles
            # (the same cosines, bit for bit), so each pair is tried once, from its first allowed apex
            quad = n == 4
            for s in range(wp.where(n == 3, 0, wp.where(quad, 2, n))):
                allowed = (apexes >> s) & 1
                first_apex = s
                if quad and allowed == 0:
                    allowed = (apexes >> (s + 2)) & 1
                    first_apex = s + 2
                if allowed != 0:
                    worst = float(-2.0)
                    for t in range(1, n - 1):
                        c = smallest_angle_cosine(
                            positions[ids[first_apex]], positions[ids[(first_apex + t) % n]],
                            positions[ids[(first_apex + t + 1) % n]],
                        )  # fmt: skip
                        worst = wp.max(worst, c)
                    # the smallest largest-cosine; a tie goes to the lower apex, as in ascending order
                    if worst < best or apex < 0 or (worst == best and first_apex < apex):
                        best = worst
                        apex = first_apex
            for t in range(1, n - 1):
                triangles[out] = wp.vec3i(ids[apex], ids[(apex + t) % n], ids[(apex + t + 1) % n])
                out += 1
        first += n


def make_project(value):
    """Newton steps along the gradient onto the surface, with the point-mode
    traversal ``value`` (:func:`make_evaluate` with derivatives): used by the
    loop centres and by relaxation."""

    @wp.func(inline=True)
    def project(m: ModelArrays, x0: wp.vec3, iso: float, tolerance: float, max_iterations: int, max_step: float):
        """Newton steps along the gradient from ``x0`` onto the surface, each at
        most ``max_step`` long: (evaluation r, its point, evaluations, whether
        ``|F - iso| <= tolerance`` there)."""
        x = x0
        at = x0
        r = vec7()
        count = int(0)
        ok = bool(False)
        for _it in range(max_iterations):
            r = value(m, x, 0.0)
            at = x
            count += 1
            ft = r[0] - iso
            grad = wp.vec3(r[1], r[2], r[3])
            gg = wp.dot(grad, grad)
            if wp.abs(ft) <= tolerance:
                ok = True
                break
            if gg <= 0.0:
                break
            # Newton in falloff space: for one Wyvill primitive x = sqrt(1 - F^(1/3))
            # is the distance over R, linear along the gradient near a point or a face
            fv = r[0]
            gap = ft
            if fv > 0.0 and fv < 1.0 and iso > 0.0 and iso < 1.0:
                c = wp.cbrt(fv)
                x_here = wp.sqrt(wp.max(1.0 - c, 0.0))
                if x_here > 0.0:
                    dxdf = -1.0 / (6.0 * c * c * x_here)
                    gap = (x_here - wp.sqrt(1.0 - wp.cbrt(iso))) / dxdf
            step = -(gap / gg) * grad
            length = wp.length(step)
            if length > max_step:
                step = step * (max_step / length)
            x = x + step
        return r, at, count, ok

    return project


def make_classify_kernels(bound, block_bounds) -> dict:
    """Block and sub-block rejection by interval bounds: point by point with
    the cube bound ``bound``, or a whole block at a time with the bounds rows
    ``block_bounds`` (array mode)."""

    @wp.kernel(enable_backward=False, module="unique")
    def classify_blocks_kernel(
        m: ModelArrays, g: Grid, iso: float, offset: int, flags: wp.array(dtype=wp.int32),
        block_states: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """A block is active (flag 1, state 0) unless every point of it is
        provably inside (state 1) or outside (state 2), by bounds over its cube."""
        b = wp.tid() + offset
        c = block_coords(g, b)
        half = 0.5 * float(_BLOCK) * g.h
        center = g.origin + g.h * float(_BLOCK) * wp.vec3(float(c[0]), float(c[1]), float(c[2])) + wp.vec3(half)
        r = bound(m, center, half * 1.0001)
        state = proven_side(r, iso)
        flags[b] = wp.where(state == 0, 1, 0)
        block_states[b] = state

    @wp.kernel(enable_backward=False, module="unique")
    def classify_subblocks_kernel(
        m: ModelArrays, g: Grid, iso: float, active: wp.array(dtype=wp.int32), offset: int,
        states: wp.array(dtype=wp.int32),
    ):  # fmt: skip
        """State of each sub-block (2^3 cells) of the active blocks: 0 may hold
        surface, 1 provably all inside, 2 provably all outside. (A coarser
        first level of 4^3 cells saved evaluations but not time: bigger balls
        cost more to bound.)"""
        tid = wp.tid() + offset
        a = tid // _SUBS
        sb = tid - a * _SUBS
        c = block_coords(g, active[a])
        si = sb % _SUB_SIDE
        sj = (sb // _SUB_SIDE) % _SUB_SIDE
        sk = sb // (_SUB_SIDE * _SUB_SIDE)
        half = 0.5 * float(_SUB)
        corner = wp.vec3(
            float(c[0] * _BLOCK + _SUB * si) + half,
            float(c[1] * _BLOCK + _SUB * sj) + half,
            float(c[2] * _BLOCK + _SUB * sk) + half,
        )
        r = bound(m, g.origin + g.h * corner, half * g.h * 1.0001)
        state = proven_side(r, iso)
        states[tid] = state

    @wp.kernel(enable_backward=False, module="unique")
    def classify_block_rows_kernel(
        m: ModelArrays,
        g: Grid,
        iso: float,
        supers: wp.vec3i,
        first_block: int,
        rows: wp.array(dtype=wp.float32),
        result_slot: int,
        offset: int,
        flags: wp.array(dtype=wp.int32),
        block_states: wp.array(dtype=wp.int32),
    ):
        """The flags and states of ``classify_blocks_kernel``, one thread per
        super-block of 4^3 blocks: bounds rows on the grid of spacing 4 h,
        whose 2-cell sub-blocks are our blocks, with the same balls."""
        t = wp.tid() + offset
        s = first_block + t
        sc = wp.vec3i(s % supers[0], (s // supers[0]) % supers[1], s // (supers[0] * supers[1]))
        scale = _BLOCK // _SUB
        ctx = block_rows(rows, t, result_slot, g.origin, g.h * float(scale), wp.vec3i(sc[0] * _BLOCK, sc[1] * _BLOCK, sc[2] * _BLOCK))
        r = block_bounds(m, ctx)
        for sb in range(_SUBS):
            bx = sc[0] * scale + sb % _SUB_SIDE
            by = sc[1] * scale + (sb // _SUB_SIDE) % _SUB_SIDE
            bz = sc[2] * scale + sb // (_SUB_SIDE * _SUB_SIDE)
            if bx < g.blocks[0] and by < g.blocks[1] and bz < g.blocks[2]:
                b = (bz * g.blocks[1] + by) * g.blocks[0] + bx
                state = proven_side(sub_bounds(ctx, r, sb), iso)
                flags[b] = wp.where(state == 0, 1, 0)
                block_states[b] = state

    @wp.kernel(enable_backward=False, module="unique")
    def classify_subblock_rows_kernel(
        m: ModelArrays,
        g: Grid,
        iso: float,
        active: wp.array(dtype=wp.int32),
        first_block: int,
        rows: wp.array(dtype=wp.float32),
        result_slot: int,
        offset: int,
        states: wp.array(dtype=wp.int32),
    ):
        """The states of ``classify_subblocks_kernel``, one thread per active
        block: one tree walk bounds all 64 sub-block balls (bounds rows), so
        the traversal and the wide operators' grid walks are shared."""
        t = wp.tid() + offset
        a = first_block + t
        c = block_coords(g, active[a])
        ctx = block_rows(rows, t, result_slot, g.origin, g.h, wp.vec3i(c[0] * _BLOCK, c[1] * _BLOCK, c[2] * _BLOCK))
        r = block_bounds(m, ctx)
        for sb in range(_SUBS):
            states[a * _SUBS + sb] = proven_side(sub_bounds(ctx, r, sb), iso)

    return {
        "classify": classify_blocks_kernel,
        "classify_rows": classify_block_rows_kernel,
        "classify_sub": classify_subblocks_kernel,
        "classify_sub_rows": classify_subblock_rows_kernel,
    }


def make_sample_kernels(value_only, block_value) -> dict:
    """Grid samples of the active blocks: point by point with ``value_only``, or
    one tree walk per block with the array-mode ``block_value``."""

    @wp.kernel(enable_backward=False, module="unique")
    def sample_blocks_kernel(
        m: ModelArrays,
        g: Grid,
        iso: float,
        active: wp.array(dtype=wp.int32),
        block_map: wp.array(dtype=wp.int32),
        block_states: wp.array(dtype=wp.int32),
        states: wp.array(dtype=wp.int32),
        dense: int,
        offset: int,
        samples: wp.array(dtype=wp.float32),
        evaluated: wp.array(dtype=wp.int32),
    ):
        """Field at the vertices each active block owns (local [0, 8)^3), where
        the vertex touches a sub-block that may hold surface (in this block or
        a neighbour); elsewhere a stand-in value on the proven side of ``iso``.
        Every grid vertex has one owner, so every cell sees the same values.
        With ``dense`` (no sub-block bounds: every sub-block of an active
        block may hold surface) every owned vertex is sampled."""
        tid = wp.tid() + offset
        a, c, lc = active_cell(g, active, tid)
        v = wp.vec3i(c[0] * _BLOCK + lc[0], c[1] * _BLOCK + lc[1], c[2] * _BLOCK + lc[2])
        need = wp.vec2i(1, 0)
        if dense == 0:
            need = vertex_need(g, v, block_map, block_states, states)
        if need[0] != 0:
            samples[tid] = value_only(m, vertex_position(g, v[0], v[1], v[2]), 0.0)[0]
            evaluated[tid] = 1
        else:
            samples[tid] = wp.where(need[1] == 1, iso + 0.5, iso - 0.5)
            evaluated[tid] = 0

    @wp.kernel(enable_backward=False, module="unique")
    def sample_rows_kernel(
        m: ModelArrays,
        g: Grid,
        iso: float,
        active: wp.array(dtype=wp.int32),
        block_map: wp.array(dtype=wp.int32),
        block_states: wp.array(dtype=wp.int32),
        states: wp.array(dtype=wp.int32),
        dense: int,
        first_block: int,
        rows: wp.array(dtype=wp.float32),
        result_slot: int,
        offset: int,
        samples: wp.array(dtype=wp.float32),
        evaluated: wp.array(dtype=wp.int32),
        tape: wp.array(dtype=wp.int32),
    ):
        """The same samples as ``sample_blocks_kernel``, one thread per block:
        the tree is walked once for the block's 512 vertices (array mode), so
        its traversal cost is shared instead of paid per point; ``evaluated``
        holds one count per block (the points it sampled), ``tape`` the leaves
        its walk reached (the tape pruned over the block)."""
        t = wp.tid() + offset
        a = first_block + t
        c = block_coords(g, active[a])
        ctx = block_rows(rows, t, result_slot, g.origin, g.h, wp.vec3i(c[0] * _BLOCK, c[1] * _BLOCK, c[2] * _BLOCK))
        want = ctx.base + (result_slot + 1) * _CELLS
        count = int(0)
        for l in range(_CELLS):
            lc = local_cell(l)
            need = wp.vec2i(1, 0)
            if dense == 0:
                need = vertex_need(g, wp.vec3i(ctx.corner[0] + lc[0], ctx.corner[1] + lc[1], ctx.corner[2] + lc[2]), block_map, block_states, states)
            rows[want + l] = float(need[0])
            samples[a * _CELLS + l] = wp.where(need[1] == 1, iso + 0.5, iso - 0.5)
            count += need[0]
        evaluated[a] = count
        r = block_value(m, ctx)
        tape[a] = int(r[7])
        for l in range(_CELLS):
            if rows[want + l] != 0.0:
                samples[a * _CELLS + l] = block_result(ctx, r, l)

    return {"sample": sample_blocks_kernel, "sample_rows": sample_rows_kernel}


def make_vertex_kernels(value, project) -> dict:
    """The surface vertices: one per crossed edge (the root search of
    :func:`make_segment_root` over ``value``) and one per loop centre (``project``)."""
    segment_root = make_segment_root(value, falloff_space=True)

    @wp.kernel(enable_backward=False, module="unique")
    def edge_vertex_kernel(
        m: ModelArrays,
        g: Grid,
        iso: float,
        tolerance: float,
        max_iterations: int,
        active: wp.array(dtype=wp.int32),
        samples: wp.array(dtype=wp.float32),
        block_map: wp.array(dtype=wp.int32),
        block_states: wp.array(dtype=wp.int32),
        crossed: wp.array(dtype=wp.int32),
        offset: int,
        positions: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        colors: wp.array(dtype=wp.vec3),
        evaluations: wp.array(dtype=wp.int32),
    ):
        """The vertex of crossed edge ``tid`` (``crossed[tid] = 4 * cell + axis``,
        the edge leaving the cell's lower corner along ``axis``), on the
        surface to ``|F - iso| <= tolerance``: the safeguarded search started
        at the root of the cubic through the four samples on the edge's line
        (the linear guess at the grid's border)."""
        tid = wp.tid() + offset
        code = crossed[tid]
        cell = code // 4
        axis = code - 4 * cell
        a, c, lc = active_cell(g, active, cell)
        i = lc[0]
        j = lc[1]
        k = lc[2]
        p0 = vertex_position(g, c[0] * _BLOCK + i, c[1] * _BLOCK + j, c[2] * _BLOCK + k)
        f0 = sample_at(g, a, c, i, j, k, iso, samples, block_map, block_states) - iso
        step = wp.vec3(0.0)
        step[axis] = g.h
        d = wp.vec3i(0)
        d[axis] = 1
        f1 = sample_at(g, a, c, i + d[0], j + d[1], k + d[2], iso, samples, block_map, block_states) - iso
        t0 = float(-1.0)
        gv = wp.vec3i(c[0] * _BLOCK + i, c[1] * _BLOCK + j, c[2] * _BLOCK + k)
        if gv[axis] >= 1 and gv[axis] + 2 <= g.cells[axis]:
            fm = sample_at(g, a, c, i - d[0], j - d[1], k - d[2], iso, samples, block_map, block_states) - iso
            f2 = sample_at(g, a, c, i + 2 * d[0], j + 2 * d[1], k + 2 * d[2], iso, samples, block_map, block_states) - iso
            t0 = cubic_guess(fm, f0, f1, f2)
        r, t, count = segment_root(m, p0, step, f0, f1, t0, iso, tolerance, max_iterations)
        store_vertex(tid, p0 + t * step, r, count, positions, normals, colors, evaluations)

    @wp.kernel(enable_backward=False, module="unique")
    def centre_kernel(
        m: ModelArrays,
        g: Grid,
        iso: float,
        tolerance: float,
        max_iterations: int,
        active: wp.array(dtype=wp.int32),
        block_map: wp.array(dtype=wp.int32),
        entries: wp.array(dtype=wp.int32),
        centre_counts: wp.array(dtype=wp.int32),
        centre_offsets: wp.array(dtype=wp.int32),
        first_centre: int,
        table: wp.array2d(dtype=wp.int32),
        edge_info: wp.array(dtype=wp.vec4i),
        edge_masks: wp.array(dtype=wp.int32),
        vertex_offsets: wp.array(dtype=wp.int32),
        offset: int,
        positions: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        colors: wp.array(dtype=wp.vec3),
        evaluations: wp.array(dtype=wp.int32),
    ):
        """A vertex for each loop that no fan can triangulate: the loop's
        centroid, moved onto the surface by Newton steps along the gradient."""
        tid = wp.tid() + offset
        if centre_counts[tid] == 0:
            return
        a, b, lc = active_cell(g, active, tid)
        i = lc[0]
        j = lc[1]
        k = lc[2]
        entry = entries[tid]
        out = first_centre + centre_offsets[tid]
        first = int(0)
        for lp in range(table[entry, 1]):
            n = table[entry, 2 + lp]
            if table[entry, _APEX + lp] == 0:
                ids = loop_ids(g, b, i, j, k, table, entry, first, n, edge_info, block_map, edge_masks, vertex_offsets)
                x = wp.vec3(0.0)
                for t in range(n):
                    x += positions[ids[t]]
                r, at, count, ok = project(m, x / float(n), iso, tolerance, max_iterations, 0.5 * g.h)
                store_vertex(out, at, r, count, positions, normals, colors, evaluations)
                out += 1
            first += n

    return {"edge_vertex": edge_vertex_kernel, "centre": centre_kernel}


def make_tape_kernel(counted) -> dict:
    """The per-block tape lengths of ``stats`` where the samples are taken
    point by point (on a GPU): ``counted`` is the interval traversal over a
    cube that counts the leaves it reaches (:func:`make_evaluate` with
    ``count``); on the CPU the array-mode walk of the samples counts them."""

    @wp.kernel(enable_backward=False, module="unique")
    def block_tape_kernel(m: ModelArrays, g: Grid, active: wp.array(dtype=wp.int32), offset: int,
                          tape: wp.array(dtype=wp.int32)):  # fmt: skip
        """Leaves of the tape pruned over active block ``tid``'s cube: the cube
        an array-mode walk of its samples prunes by
        (:func:`~warpblob.field._kernels.points_cube`), by the same boxes and
        grid cells."""
        tid = wp.tid() + offset
        c = block_coords(g, active[tid])
        centre, half = points_cube(g.origin, g.h, wp.vec3i(c[0] * _BLOCK, c[1] * _BLOCK, c[2] * _BLOCK))
        tape[tid] = int(counted(m, centre, half)[7])

    return {"tape": block_tape_kernel}


def make_kernels() -> dict:
    """Build the polygonizer kernels that close over the field evaluators
    (compiled once per process and device), by name; relaxation's is
    :func:`warpblob.polygonize._relax.make_relax_kernel`."""
    value = make_evaluate(True)
    return {
        **make_classify_kernels(make_evaluate(True, interval=True, cube=True), make_evaluate(True, interval=True, array=True)),
        **make_sample_kernels(
            make_evaluate(True, derivatives=False), make_evaluate(True, derivatives=False, array=True, count=True)
        ),
        **make_vertex_kernels(value, make_project(value)),
        **make_tape_kernel(make_evaluate(True, interval=True, cube=True, count=True)),
    }


@wp.kernel(enable_backward=False)
def block_map_kernel(active: wp.array(dtype=wp.int32), offset: int, block_map: wp.array(dtype=wp.int32)):
    tid = wp.tid() + offset
    block_map[active[tid]] = tid


@wp.kernel(enable_backward=False)
def crossed_edges_kernel(
    edge_masks: wp.array(dtype=wp.int32),
    vertex_offsets: wp.array(dtype=wp.int32),
    offset: int,
    crossed: wp.array(dtype=wp.int32),
):
    """``crossed[v] = 4 * cell + axis`` for the vertex ``v`` of each crossed edge."""
    tid = wp.tid() + offset
    mask = edge_masks[tid]
    out = vertex_offsets[tid]
    for axis in range(3):
        if (mask >> axis) & 1 != 0:
            crossed[out] = 4 * tid + axis
            out += 1
