"""Warp kernels of isosurface stuffing (see :mod:`warpblob.tetrahedralize`).

Lattice points are numbered densely: black points (cube corners) ``(i, j, k)``
with ``0 <= i <= cells[0]`` first, then red points (cube centres) with
``0 <= i < cells[0]``. Every lattice edge is owned by one point and named by
``(owner, slot)``: slots 0-2 are the long edges to the next point of the same
colour along +x, +y, +z, slots 3-10 (red points only) the short edges to the
eight corners of the point's cube, corner ``(dx, dy, dz)`` at slot
``3 + dx + 2 dy + 4 dz``. A per-point bit mask of crossed owned edges and an
exclusive scan of its bit counts give every cut point a unique index without
hashing: ``cut_offsets[owner] + popcount(mask[owner] & ((1 << slot) - 1))``.
"""

from __future__ import annotations

import warp as wp

from ..field._kernels import (
    BLOCK_POINTS,
    SUB_BLOCK_SIDE,
    SUB_BLOCKS,
    ModelArrays,
    block_result,
    block_rows,
    cubic_guess,
    make_evaluate,
    make_segment_root,
    sub_bounds,
    vec7,
)  # fmt: skip
from ._tables import MAX_STENCIL

BLOCK = 8  # cubes per side of a coarse block (first interval test)
SUB = 2  # cubes per side of a sub-block (second interval test, the unit of tet work)
SUB_CELLS = SUB * SUB * SUB
TETS_PER_CELL = 12

_BLOCK = wp.constant(BLOCK)
_SUB = wp.constant(SUB)
_SUB_CELLS = wp.constant(SUB_CELLS)
_TETS_PER_CELL = wp.constant(TETS_PER_CELL)
_MAX_STENCIL = wp.constant(MAX_STENCIL)
_BLOCK_POINTS = wp.constant(BLOCK_POINTS)
assert BLOCK // SUB == SUB_BLOCK_SIDE  # a block's sub-blocks are the bounds rows' 4^3
_ROW_SUBS = wp.constant(SUB_BLOCKS)
_ROW_SIDE = wp.constant(SUB_BLOCK_SIDE)
#: a sub-block's box in bounds rows: its tets reach one cube further along +x, +y, +z, so 3 cubes a side,
#: as :func:`box_state` bounds it (half side 1.5 cubes plus 1e-4, and the ball around that cube)
_ROW_HALF = wp.constant(1.5 * 1.0001)
_ROW_BALL = wp.constant(1.7320509 * 1.5 * 1.0001)
_SHORT = wp.constant(0.8660254037844386)  # short edge / long edge = sqrt(3) / 2
_HALF_SIDE = wp.constant(0.5 * 1.0001)  # half side / box side, with margin

MIXED = 0
INSIDE = 1
OUTSIDE = 2
_MIXED = wp.constant(MIXED)
_INSIDE = wp.constant(INSIDE)
_OUTSIDE = wp.constant(OUTSIDE)


vec10i = wp.types.vector(length=10, dtype=wp.int32)


@wp.struct
class Lattice:
    origin: wp.vec3  # position of black point (0, 0, 0)
    h: float  # cube side = long edge length
    cells: wp.vec3i  # cubes per axis
    black: int  # number of black points
    blocks: wp.vec3i  # coarse blocks per axis
    subs: wp.vec3i  # sub-blocks per axis


@wp.func
def grid_coords(n: wp.vec3i, index: int):
    return wp.vec3i(index % n[0], (index // n[0]) % n[1], index // (n[0] * n[1]))


@wp.func
def point_index(l: Lattice, red: int, c: wp.vec3i):
    """Index of the black (red = 0) or red point ``c``, or -1 outside the lattice."""
    n = l.cells
    if red == 0:
        if c[0] < 0 or c[1] < 0 or c[2] < 0 or c[0] > n[0] or c[1] > n[1] or c[2] > n[2]:
            return -1
        return (c[2] * (n[1] + 1) + c[1]) * (n[0] + 1) + c[0]
    if c[0] < 0 or c[1] < 0 or c[2] < 0 or c[0] >= n[0] or c[1] >= n[1] or c[2] >= n[2]:
        return -1
    return l.black + (c[2] * n[1] + c[1]) * n[0] + c[0]


@wp.func
def point_coords(l: Lattice, p: int):
    """(red, i, j, k) of point index ``p``."""
    n = l.cells
    if p < l.black:
        c = grid_coords(wp.vec3i(n[0] + 1, n[1] + 1, n[2] + 1), p)
        return wp.vec4i(0, c[0], c[1], c[2])
    c = grid_coords(n, p - l.black)
    return wp.vec4i(1, c[0], c[1], c[2])


@wp.func
def colour_origin(l: Lattice, red: int):
    """Position of point (0, 0, 0) of the black (red = 0) or red points."""
    return l.origin + l.h * wp.vec3(0.5 * float(red))


@wp.func
def point_position(l: Lattice, q: wp.vec4i):
    """Position of point ``q`` (red, i, j, k): its colour's origin plus ``h (i, j, k)``, as an array-mode
    walk over that colour's points computes it (bit for bit)."""
    return colour_origin(l, q[0]) + l.h * wp.vec3(float(q[1]), float(q[2]), float(q[3]))


@wp.func
def edge_end(q: wp.vec4i, slot: int):
    """The other end of owned edge ``slot`` of point ``q`` (red, i, j, k)."""
    if slot < 3:
        e = wp.vec4i(q[0], q[1], q[2], q[3])
        e[1 + slot] = e[1 + slot] + 1
        return e
    corner = slot - 3
    return wp.vec4i(0, q[1] + (corner & 1), q[2] + ((corner >> 1) & 1), q[3] + (corner >> 2))


@wp.func
def line_neighbours(q: wp.vec4i, slot: int):
    """The lattice points one edge before ``q`` and one edge past the other end of its owned edge
    ``slot``, on the edge's line: lattice lines hold equally spaced points (a long edge's neighbours
    have its colour; a short edge's line alternates red and black), as (red, i, j, k) each."""
    if slot < 3:
        before = wp.vec4i(q[0], q[1], q[2], q[3])
        after = wp.vec4i(q[0], q[1], q[2], q[3])
        before[1 + slot] = before[1 + slot] - 1
        after[1 + slot] = after[1 + slot] + 2
        return before, after
    corner = slot - 3
    dx = corner & 1
    dy = (corner >> 1) & 1
    dz = corner >> 2
    before = wp.vec4i(0, q[1] + 1 - dx, q[2] + 1 - dy, q[3] + 1 - dz)
    after = wp.vec4i(1, q[1] + 2 * dx - 1, q[2] + 2 * dy - 1, q[3] + 2 * dz - 1)
    return before, after


@wp.func
def sampled_value(l: Lattice, values: wp.array(dtype=wp.float32), evaluated: wp.array(dtype=wp.int32), q: wp.vec4i):
    """(F at point ``q``, 1) where it was evaluated; (0, 0) for a stand-in or a point outside the lattice."""
    p = point_index(l, q[0], wp.vec3i(q[1], q[2], q[3]))
    if p < 0:
        return 0.0, 0
    if evaluated[p] == 0:
        return 0.0, 0
    return values[p], 1


@wp.func
def bits_below(mask: int, slot: int):
    """Number of set bits of ``mask`` below bit ``slot``."""
    count = int(0)
    for b in range(11):
        if b < slot and (mask >> b) & 1 != 0:
            count += 1
    return count


@wp.func
def cell_state(l: Lattice, sub_states: wp.array(dtype=wp.int32), c: wp.vec3i):
    """State of the sub-block of cube ``c``; cubes outside the lattice are outside."""
    if c[0] < 0 or c[1] < 0 or c[2] < 0 or c[0] >= l.cells[0] or c[1] >= l.cells[1] or c[2] >= l.cells[2]:
        return _OUTSIDE
    s = wp.vec3i(c[0] // _SUB, c[1] // _SUB, c[2] // _SUB)
    return sub_states[(s[2] * l.subs[1] + s[1]) * l.subs[0] + s[0]]


@wp.func
def label_of(value: float, iso: float):
    if value > iso:
        return 1
    if value < iso:
        return -1
    return 0


@wp.func
def proven_state(bounds: vec7, iso: float):
    """INSIDE where the bounds (F_min, F_max, ...) prove ``F > iso``, OUTSIDE where they prove ``F < iso``,
    else MIXED."""
    if bounds[0] > iso:
        return _INSIDE
    if bounds[1] < iso:
        return _OUTSIDE
    return _MIXED


@wp.func
def point_need(l: Lattice, sub_states: wp.array(dtype=wp.int32), q: wp.vec4i):
    """(needed, proven inside) of point ``q``: whether a tet of a mixed sub-block uses it, and else
    whether the sub-blocks around it are proven inside (all tets using the point agree on the side)."""
    c = wp.vec3i(q[1], q[2], q[3])
    needed = int(0)
    proven = int(0)
    if q[0] == 0:
        # a cube corner is used by tets owned by the 8 cubes around it
        for d in range(8):
            st = cell_state(l, sub_states, c - wp.vec3i(d & 1, (d >> 1) & 1, d >> 2))
            if st == _MIXED:
                needed = 1
            elif st == _INSIDE:
                proven = 1
    else:
        # a cube centre is used by its own cube's tets and by those of the cube before it on each axis
        for d in range(4):
            back = wp.vec3i(0)
            if d > 0:
                back[d - 1] = 1
            st = cell_state(l, sub_states, c - back)
            if st == _MIXED:
                needed = 1
            elif st == _INSIDE:
                proven = 1
    return wp.vec2i(needed, proven)


def make_kernels():
    """Build the kernels that evaluate the field (compiled once per process and device)."""
    bound = make_evaluate(True, interval=True, cube=True)
    value = make_evaluate(True)
    block_value = make_evaluate(True, derivatives=False, array=True)
    block_bounds = make_evaluate(True, interval=True, array=True)
    segment_root = make_segment_root(value, falloff_space=True)

    @wp.func
    def box_state(m: ModelArrays, l: Lattice, iso: float, first: wp.vec3i, side: int):
        """Proven state of the box of cubes [first, first + side + 1) per axis: the cubes'
        own tets reach at most one cube further along +x, +y, +z."""
        extent = float(side + 1) * l.h
        corner = l.origin + l.h * wp.vec3(float(first[0]), float(first[1]), float(first[2]))
        return proven_state(bound(m, corner + wp.vec3(0.5 * extent), extent * _HALF_SIDE), iso)

    @wp.kernel(enable_backward=False, module="unique")
    def classify_blocks_kernel(
        m: ModelArrays, l: Lattice, iso: float, offset: int, block_states: wp.array(dtype=wp.int32)
    ):
        b = wp.tid() + offset
        c = grid_coords(l.blocks, b)
        block_states[b] = box_state(m, l, iso, wp.vec3i(c[0] * _BLOCK, c[1] * _BLOCK, c[2] * _BLOCK), _BLOCK)

    @wp.kernel(enable_backward=False, module="unique")
    def classify_subs_kernel(
        m: ModelArrays,
        l: Lattice,
        iso: float,
        block_states: wp.array(dtype=wp.int32),
        offset: int,
        sub_states: wp.array(dtype=wp.int32),
        bounded: wp.array(dtype=wp.int32),
    ):
        """A sub-block inherits a proven block state, else gets its own interval test."""
        s = wp.tid() + offset
        c = grid_coords(l.subs, s)
        first = wp.vec3i(c[0] * _SUB, c[1] * _SUB, c[2] * _SUB)
        b = wp.vec3i(first[0] // _BLOCK, first[1] // _BLOCK, first[2] // _BLOCK)
        state = block_states[(b[2] * l.blocks[1] + b[1]) * l.blocks[0] + b[0]]
        bounded[s] = 0
        if state == _MIXED:
            state = box_state(m, l, iso, first, _SUB)
            bounded[s] = 1
        sub_states[s] = state

    @wp.kernel(enable_backward=False, module="unique")
    def classify_subs_rows_kernel(
        m: ModelArrays,
        l: Lattice,
        iso: float,
        block_states: wp.array(dtype=wp.int32),
        first_block: int,
        rows: wp.array(dtype=wp.float32),
        result_slot: int,
        offset: int,
        sub_states: wp.array(dtype=wp.int32),
        bounded: wp.array(dtype=wp.int32),
    ):
        """``classify_subs_kernel``, one thread per block: the 64 sub-blocks of a mixed block bounded by one
        tree walk (bounds rows: the traversal and the wide operators' grid walks shared, the tape pruned
        over the block), over the same boxes of 3 cubes a side (the rows' origin half a cube on, so that
        their 2-cube spacing puts each box's centre 1.5 cubes past its first cube)."""
        t = wp.tid() + offset
        b = first_block + t
        c = grid_coords(l.blocks, b)
        state = block_states[b]
        ctx = block_rows(rows, t, result_slot, colour_origin(l, 1), l.h, wp.vec3i(c[0] * _BLOCK, c[1] * _BLOCK, c[2] * _BLOCK))
        ctx.half = _ROW_HALF
        ctx.ball = _ROW_BALL
        r = vec7()
        if state == _MIXED:
            r = block_bounds(m, ctx)
        for sb in range(_ROW_SUBS):
            sx = c[0] * _ROW_SIDE + sb % _ROW_SIDE
            sy = c[1] * _ROW_SIDE + (sb // _ROW_SIDE) % _ROW_SIDE
            sz = c[2] * _ROW_SIDE + sb // (_ROW_SIDE * _ROW_SIDE)
            if sx < l.subs[0] and sy < l.subs[1] and sz < l.subs[2]:
                s = (sz * l.subs[1] + sy) * l.subs[0] + sx
                if state == _MIXED:
                    sub_states[s] = proven_state(sub_bounds(ctx, r, sb), iso)
                    bounded[s] = 1
                else:
                    sub_states[s] = state
                    bounded[s] = 0

    @wp.kernel(enable_backward=False, module="unique")
    def sample_points_kernel(
        m: ModelArrays,
        l: Lattice,
        iso: float,
        sub_states: wp.array(dtype=wp.int32),
        offset: int,
        values: wp.array(dtype=wp.float32),
        evaluated: wp.array(dtype=wp.int32),
    ):
        """The field at every point used by a tet of a mixed sub-block; a stand-in on the
        proven side of ``iso`` elsewhere (all tets using the point agree on the side)."""
        p = wp.tid() + offset
        q = point_coords(l, p)
        need = point_need(l, sub_states, q)
        if need[0] != 0:
            values[p] = value(m, point_position(l, q), 0.0)[0]
            evaluated[p] = 1
        else:
            values[p] = wp.where(need[1] != 0, iso + 0.5, iso - 0.5)
            evaluated[p] = 0

    @wp.kernel(enable_backward=False, module="unique")
    def sample_rows_kernel(
        m: ModelArrays,
        l: Lattice,
        iso: float,
        sub_states: wp.array(dtype=wp.int32),
        red: int,
        point_blocks: wp.vec3i,
        first_block: int,
        rows: wp.array(dtype=wp.float32),
        result_slot: int,
        offset: int,
        values: wp.array(dtype=wp.float32),
        evaluated: wp.array(dtype=wp.int32),
    ):
        """The samples of ``sample_points_kernel`` for the points of one colour, one thread per block of
        8^3 of them (``point_blocks`` per axis): one array-mode tree walk for the block's needed points
        (the tape pruned over the block), none for a block that needs none."""
        t = wp.tid() + offset
        c = grid_coords(point_blocks, first_block + t)
        corner = wp.vec3i(c[0] * 8, c[1] * 8, c[2] * 8)
        ctx = block_rows(rows, t, result_slot, colour_origin(l, red), l.h, corner)
        want = ctx.base + (result_slot + 1) * _BLOCK_POINTS
        count = int(0)
        for j in range(_BLOCK_POINTS):
            q = wp.vec4i(red, corner[0] + j % 8, corner[1] + (j // 8) % 8, corner[2] + j // 64)
            p = point_index(l, red, wp.vec3i(q[1], q[2], q[3]))
            rows[want + j] = 0.0
            if p >= 0:
                need = point_need(l, sub_states, q)
                rows[want + j] = float(need[0])
                values[p] = wp.where(need[1] != 0, iso + 0.5, iso - 0.5)
                evaluated[p] = need[0]
                count += need[0]
        if count > 0:
            r = block_value(m, ctx)
            for j in range(_BLOCK_POINTS):
                if rows[want + j] != 0.0:
                    p = point_index(l, red, wp.vec3i(corner[0] + j % 8, corner[1] + (j // 8) % 8, corner[2] + j // 64))
                    values[p] = block_result(ctx, r, j)

    @wp.kernel(enable_backward=False, module="unique")
    def cut_edges_kernel(
        m: ModelArrays,
        l: Lattice,
        iso: float,
        tolerance: float,
        max_iterations: int,
        values: wp.array(dtype=wp.float32),
        evaluated: wp.array(dtype=wp.int32),
        masks: wp.array(dtype=wp.int32),
        cut_offsets: wp.array(dtype=wp.int32),
        offset: int,
        cut_positions: wp.array(dtype=wp.vec3),
        cut_params: wp.array(dtype=wp.float32),
        evaluations: wp.array(dtype=wp.int32),
    ):
        """A cut point on every crossed edge owned by point ``p``: the shared
        safeguarded Newton search (:func:`~warpblob.field._kernels.make_segment_root`, in falloff
        space first) until ``|F - iso| <= tolerance``, started at the root of the cubic through the four
        samples on the edge's line where the two beyond its ends were evaluated (the linear guess
        elsewhere: a stand-in is not a value of F)."""
        p = wp.tid() + offset
        mask = masks[p]
        if mask == 0:
            return
        q = point_coords(l, p)
        p0 = point_position(l, q)
        f0 = values[p] - iso
        out = cut_offsets[p]
        # a runtime bound keeps Warp from unrolling the loop: unrolled, the inlined
        # root search and traversal were compiled 11 times (32 s of a 75 s cold build)
        for slot in range(int(11)):
            if (mask >> slot) & 1 != 0:
                e = edge_end(q, slot)
                step = point_position(l, e) - p0
                f1 = values[point_index(l, e[0], wp.vec3i(e[1], e[2], e[3]))] - iso
                before, after = line_neighbours(q, slot)
                fm, has_m = sampled_value(l, values, evaluated, before)
                f2, has_2 = sampled_value(l, values, evaluated, after)
                t0 = float(-1.0)
                if has_m != 0 and has_2 != 0:
                    t0 = cubic_guess(fm - iso, f0, f1, f2 - iso)
                r, tx, count = segment_root(m, p0, step, f0, f1, t0, iso, tolerance, max_iterations)
                cut_positions[out] = p0 + tx * step
                cut_params[out] = tx
                evaluations[out] = count
                out += 1

    return {
        "classify_blocks": classify_blocks_kernel,
        "classify_subs": classify_subs_kernel,
        "classify_subs_rows": classify_subs_rows_kernel,
        "sample": sample_points_kernel,
        "sample_rows": sample_rows_kernel,
        "cut": cut_edges_kernel,
    }


@wp.kernel(enable_backward=False)
def count_cuts_kernel(
    l: Lattice,
    iso: float,
    values: wp.array(dtype=wp.float32),
    evaluated: wp.array(dtype=wp.int32),
    offset: int,
    masks: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """Bit mask and number of the owned edges of ``p`` whose ends are strictly on opposite sides.

    A point that was not evaluated owns none: every tet using it lies in a sub-block proven inside or
    outside over the box its tets reach, and every lattice edge at the point is an edge of such a tet,
    so both ends of each lie on the proven side (the stand-in's side). Its edges are not looked at."""
    p = wp.tid() + offset
    mask = int(0)
    count = int(0)
    s = int(0)
    if evaluated[p] != 0:
        s = label_of(values[p], iso)
    if s != 0:
        q = point_coords(l, p)
        slots = wp.where(q[0] == 0, 3, 11)
        for slot in range(slots):
            e = edge_end(q, slot)
            other = point_index(l, e[0], wp.vec3i(e[1], e[2], e[3]))
            if other >= 0 and label_of(values[other], iso) == -s:
                mask = mask | (1 << slot)
                count += 1
    masks[p] = mask
    counts[p] = count


@wp.func
def incident_edge(l: Lattice, q: wp.vec4i, k: int):
    """Edge ``k`` (0-13) of point ``q`` as (owner index or -1, slot, 1 if ``q`` owns it)."""
    c = wp.vec3i(q[1], q[2], q[3])
    if k < 3:
        return wp.vec3i(point_index(l, q[0], c), k, 1)
    if k < 6:
        back = wp.vec3i(0)
        back[k - 3] = 1
        return wp.vec3i(point_index(l, q[0], c - back), k - 3, 0)
    d = k - 6
    if q[0] == 1:
        return wp.vec3i(point_index(l, 1, c), 3 + d, 1)
    return wp.vec3i(point_index(l, 1, c - wp.vec3i(d & 1, (d >> 1) & 1, d >> 2)), 3 + d, 0)


UNDECIDED = 0
KEEP = 1  # the point stays where it is
MOVE = 2  # the point is warped onto a cut point
_UNDECIDED = wp.constant(UNDECIDED)
_KEEP = wp.constant(KEEP)
_MOVE = wp.constant(MOVE)


@wp.func
def violator(
    l: Lattice,
    q: wp.vec4i,
    k: int,
    alpha_long: float,
    alpha_short: float,
    masks: wp.array(dtype=wp.int32),
    cut_offsets: wp.array(dtype=wp.int32),
    cut_params: wp.array(dtype=wp.float32),
):
    """Cut point on edge ``k`` (0-13) of point ``q`` that violates ``q``, as (cut index, other end)
    with its distance from ``q``; cut index -1 when there is none."""
    e = incident_edge(l, q, k)
    out = wp.vec2i(-1, -1)
    d = float(0.0)
    if e[0] >= 0:
        mask = masks[e[0]]
        if (mask >> e[1]) & 1 != 0:
            cut = cut_offsets[e[0]] + bits_below(mask, e[1])
            t = cut_params[cut]
            other = e[0]
            if e[2] == 1:
                f = edge_end(q, e[1])
                other = point_index(l, f[0], wp.vec3i(f[1], f[2], f[3]))
            else:
                t = 1.0 - t
            alpha = alpha_long
            length = l.h
            if e[1] >= 3:
                alpha = alpha_short
                length = l.h * _SHORT
            if t < alpha:
                out = wp.vec2i(cut, other)
                d = t * length
    return out, d


@wp.kernel(enable_backward=False)
def violated_kernel(
    l: Lattice,
    alpha_long: float,
    alpha_short: float,
    masks: wp.array(dtype=wp.int32),
    cut_offsets: wp.array(dtype=wp.int32),
    cut_params: wp.array(dtype=wp.float32),
    evaluated: wp.array(dtype=wp.int32),
    offset: int,
    states: wp.array(dtype=wp.int32),
):
    """A point with no violating cut point keeps its place; a violated one is undecided. A point that
    was not evaluated has no cut point on its edges (see :func:`count_cuts_kernel`) and keeps its place."""
    p = wp.tid() + offset
    state = _KEEP
    if evaluated[p] != 0:
        q = point_coords(l, p)
        for k in range(14):
            v, d = violator(l, q, k, alpha_long, alpha_short, masks, cut_offsets, cut_params)
            if v[0] >= 0:
                state = _UNDECIDED
    states[p] = state


@wp.kernel(enable_backward=False)
def resolve_kernel(
    l: Lattice,
    alpha_long: float,
    alpha_short: float,
    masks: wp.array(dtype=wp.int32),
    cut_offsets: wp.array(dtype=wp.int32),
    cut_params: wp.array(dtype=wp.float32),
    states: wp.array(dtype=wp.int32),
    offset: int,
    next_states: wp.array(dtype=wp.int32),
    changed: wp.array(dtype=wp.int32),
):
    """One round of the forced decisions: an undecided point with a violating cut point whose
    other end stays moves (onto such a cut point); one whose violating cut points all lead
    to moving points stays (they all disappear). Decisions never change once made."""
    p = wp.tid() + offset
    state = states[p]
    if state == _UNDECIDED:
        q = point_coords(l, p)
        any_keep = bool(False)
        all_move = bool(True)
        for k in range(14):
            v, d = violator(l, q, k, alpha_long, alpha_short, masks, cut_offsets, cut_params)
            if v[0] >= 0:
                s = states[v[1]]
                if s == _KEEP:
                    any_keep = True
                if s != _MOVE:
                    all_move = False
        if any_keep:
            state = _MOVE
        elif all_move:
            state = _KEEP
        if state != _UNDECIDED:
            wp.atomic_add(changed, 0, 1)
    next_states[p] = state


@wp.kernel(enable_backward=False)
def warp_points_kernel(
    l: Lattice,
    iso: float,
    alpha_long: float,
    alpha_short: float,
    values: wp.array(dtype=wp.float32),
    masks: wp.array(dtype=wp.int32),
    cut_offsets: wp.array(dtype=wp.int32),
    cut_params: wp.array(dtype=wp.float32),
    states: wp.array(dtype=wp.int32),
    offset: int,
    labels: wp.array(dtype=wp.int32),
    targets: wp.array(dtype=wp.int32),
):
    """Warping. Points left undecided by the forced rounds (cycles of violations) are settled
    by sign: inside ones stay, outside ones move. A moving point goes to its closest violating
    cut point whose other end stays, and gets label 0 (on the surface)."""
    p = wp.tid() + offset
    s = label_of(values[p], iso)
    state = states[p]
    if state == _UNDECIDED:
        state = wp.where(s > 0, _KEEP, _MOVE)
    target = int(-1)
    if state == _MOVE:
        q = point_coords(l, p)
        best = float(1.0e30)
        for k in range(14):
            v, d = violator(l, q, k, alpha_long, alpha_short, masks, cut_offsets, cut_params)
            if v[0] >= 0:
                so = states[v[1]]
                if so == _UNDECIDED:
                    so = wp.where(label_of(values[v[1]], iso) > 0, _KEEP, _MOVE)
                # ties go to the smaller cut index, so the result does not depend on the edge order
                if so == _KEEP and (d < best or (d == best and v[0] < target)):
                    best = d
                    target = v[0]
        if target >= 0:
            s = 0
    labels[p] = s
    targets[p] = target


@wp.func
def coarse_at(coarse: wp.array(dtype=wp.int32), dims: wp.vec3i, g: wp.vec3i):
    """1 when coarse cube ``g`` is in the coarse region (0 outside the coarse grid)."""
    if g[0] < 0 or g[1] < 0 or g[2] < 0 or g[0] >= dims[0] or g[1] >= dims[1] or g[2] >= dims[2]:
        return 0
    return coarse[(g[2] * dims[1] + g[1]) * dims[0] + g[0]]


@wp.func
def cell_is_coarse(coarse: wp.array(dtype=wp.int32), dims: wp.vec3i, ratio: int, c: wp.vec3i):
    """1 when fine cube ``c`` lies in a coarse cube (never when ``ratio`` is 0: uniform lattice)."""
    if ratio <= 0 or c[0] < 0 or c[1] < 0 or c[2] < 0:
        return 0
    return coarse_at(coarse, dims, wp.vec3i(c[0] // ratio, c[1] // ratio, c[2] // ratio))


@wp.func
def tet_vertex(l: Lattice, cell: wp.vec3i, v: wp.vec4i):
    """Point index of a tet vertex ``(red, dx, dy, dz)`` relative to its owning cube (-1 outside)."""
    return point_index(l, v[0], cell + wp.vec3i(v[1], v[2], v[3]))


@wp.func
def tet_cell(l: Lattice, active: wp.array(dtype=wp.int32), tid: int):
    """(cube i, j, k, tet type) of thread ``tid`` over the active sub-blocks."""
    a = tid // (_SUB_CELLS * _TETS_PER_CELL)
    r = tid - a * (_SUB_CELLS * _TETS_PER_CELL)
    local = r // _TETS_PER_CELL
    s = grid_coords(l.subs, active[a])
    return wp.vec4i(
        s[0] * _SUB + (local & 1), s[1] * _SUB + ((local >> 1) & 1), s[2] * _SUB + (local >> 2), r % _TETS_PER_CELL
    )


@wp.kernel(enable_backward=False)
def count_tets_kernel(
    l: Lattice,
    labels: wp.array(dtype=wp.int32),
    vertex_table: wp.array2d(dtype=wp.vec4i),
    stencil_counts: wp.array2d(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    coarse: wp.array(dtype=wp.int32),
    coarse_dims: wp.vec3i,
    ratio: int,
    offset: int,
    patterns: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """Sign pattern (3^4) of each lattice tet of the active sub-blocks and its stencil's size.

    With a graded interior (``ratio > 0``) a lattice tet whose cube or whose neighbour across
    the straddled face lies in a coarse cube is left out (see :mod:`._graded`)."""
    tid = wp.tid() + offset
    t = tet_cell(l, active, tid)
    cell = wp.vec3i(t[0], t[1], t[2])
    pattern = int(0)
    scale = int(1)
    inside = bool(True)
    if ratio > 0:
        across = wp.vec3i(cell[0], cell[1], cell[2])
        axis = t[3] // 4
        across[axis] = across[axis] + 1
        if cell_is_coarse(coarse, coarse_dims, ratio, cell) == 1:
            inside = False
        if cell_is_coarse(coarse, coarse_dims, ratio, across) == 1:
            inside = False
    for v in range(4):
        p = tet_vertex(l, cell, vertex_table[t[3], v])
        if p < 0:
            inside = False
        else:
            pattern += scale * (labels[p] + 1)
        scale *= 3
    if inside:
        patterns[tid] = pattern
        counts[tid] = stencil_counts[t[3], pattern]
    else:
        patterns[tid] = 0
        counts[tid] = 0


@wp.kernel(enable_backward=False)
def emit_tets_kernel(
    l: Lattice,
    n_points: int,
    vertex_table: wp.array2d(dtype=wp.vec4i),
    edge_owners: wp.array2d(dtype=wp.vec4i),
    edge_slots: wp.array2d(dtype=wp.int32),
    stencil_refs: wp.array3d(dtype=wp.vec4i),
    masks: wp.array(dtype=wp.int32),
    cut_offsets: wp.array(dtype=wp.int32),
    active: wp.array(dtype=wp.int32),
    patterns: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    tet_offsets: wp.array(dtype=wp.int32),
    offset: int,
    tets: wp.array(dtype=wp.vec4i),
):
    """The stencil's tets over provisional node ids: points first, then cut points."""
    tid = wp.tid() + offset
    n = counts[tid]
    if n == 0:
        return
    t = tet_cell(l, active, tid)
    cell = wp.vec3i(t[0], t[1], t[2])
    nodes = wp.vec4i()
    refs = vec10i()
    for v in range(4):
        refs[v] = tet_vertex(l, cell, vertex_table[t[3], v])
    for e in range(6):
        o = edge_owners[t[3], e]
        owner = point_index(l, o[0], cell + wp.vec3i(o[1], o[2], o[3]))
        mask = masks[owner]
        slot = edge_slots[t[3], e]
        refs[4 + e] = -1
        if (mask >> slot) & 1 != 0:
            refs[4 + e] = n_points + cut_offsets[owner] + bits_below(mask, slot)
    out = tet_offsets[tid]
    for k in range(_MAX_STENCIL):
        if k < n:
            r = stencil_refs[t[3], patterns[tid], k]
            for i in range(4):
                nodes[i] = refs[r[i]]
            tets[out + k] = nodes


@wp.kernel(enable_backward=False)
def mark_nodes_kernel(tets: wp.array(dtype=wp.vec4i), offset: int, used: wp.array(dtype=wp.int32)):
    tid = wp.tid() + offset
    t = tets[tid]
    for i in range(4):
        # every writer stores the same 1: the race is benign
        used[t[i]] = 1


@wp.kernel(enable_backward=False)
def write_nodes_kernel(
    l: Lattice,
    n_points: int,
    targets: wp.array(dtype=wp.int32),
    cut_positions: wp.array(dtype=wp.vec3),
    used: wp.array(dtype=wp.int32),
    node_ids: wp.array(dtype=wp.int32),
    offset: int,
    nodes: wp.array(dtype=wp.vec3),
):
    """Final node positions: lattice points (warped ones at their cut point), then cut points."""
    u = wp.tid() + offset
    if used[u] == 0:
        return
    out = node_ids[u]
    if u >= n_points:
        nodes[out] = cut_positions[u - n_points]
    elif targets[u] >= 0:
        nodes[out] = cut_positions[targets[u]]
    else:
        nodes[out] = point_position(l, point_coords(l, u))


@wp.kernel(enable_backward=False)
def renumber_tets_kernel(
    node_ids: wp.array(dtype=wp.int32), tets: wp.array(dtype=wp.vec4i), offset: int, out: wp.array(dtype=wp.vec4i)
):
    tid = wp.tid() + offset
    t = tets[tid]
    out[tid] = wp.vec4i(node_ids[t[0]], node_ids[t[1]], node_ids[t[2]], node_ids[t[3]])


@wp.kernel(enable_backward=False)
def active_flags_kernel(sub_states: wp.array(dtype=wp.int32), offset: int, flags: wp.array(dtype=wp.int32)):
    tid = wp.tid() + offset
    flags[tid] = wp.where(sub_states[tid] == _OUTSIDE, 0, 1)


@wp.kernel(enable_backward=False)
def average_nodes_kernel(
    nodes: wp.array(dtype=wp.vec3), tets: wp.array(dtype=wp.vec4i), offset: int, centroids: wp.array(dtype=wp.vec3)
):
    """Centroid of every tet, model units."""
    tid = wp.tid() + offset
    t = tets[tid]
    # summed in node order, then quartered (exact): the float32 result of a numpy mean over the
    # four nodes, so a material id never depends on where the centroid was computed
    s = nodes[t[0]] + nodes[t[1]]
    s = s + nodes[t[2]]
    s = s + nodes[t[3]]
    centroids[tid] = s * 0.25


@wp.kernel(enable_backward=False)
def match_colors_kernel(
    colors: wp.array(dtype=wp.vec3), palette: wp.array(dtype=wp.vec3), offset: int, ids: wp.array(dtype=wp.int32)
):
    """Row of ``palette`` nearest ``colors[tid]`` in squared RGB distance, ties to the lower row
    (0 for an empty palette)."""
    tid = wp.tid() + offset
    c = colors[tid]
    best = float(wp.inf)
    nearest = int(0)
    for k in range(palette.shape[0]):
        d = c - palette[k]
        # one rounding per product and per sum, left to right (no fused multiply-add): the float32
        # result of numpy's ((c - p) ** 2).sum(axis=1), so near-ties break the same way everywhere
        dx = d[0] * d[0]
        dy = d[1] * d[1]
        dz = d[2] * d[2]
        dist = dx + dy
        dist = dist + dz
        if dist < best:
            best = dist
            nearest = k
    ids[tid] = nearest
