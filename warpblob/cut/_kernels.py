"""Warp kernels of the cutter: edge-sweep intersection, hit flags, per-tet cut codes, the changed tets' table
entries and positivity, their sub-tets, and the pairing of sub-tet faces at cut nodes."""

from __future__ import annotations

import warp as wp

from ..mesh._structure import _EMPTY_WP, _pair_slot, vec6i
from ..mesh._structure import _join
from ..mesh._tetmesh import TET_EDGES_WP, TET_FACES_WP
from ..sim._elements import DEGENERATE_VOLUME

__all__ = [
    "cell_codes_kernel",
    "cells_at_nodes_kernel",
    "classify_units_kernel",
    "emit_subtets_kernel",
    "few_crossing",
    "FEW_KERNELS",
    "FEW_UNROLLED",
    "flag_positive_kernel",
    "intersect_edges_few_kernel",
    "intersect_edges_kernel",
    "mark_edges_in_use_kernel",
    "node_side",
    "node_sides_kernel",
    "pair_faces_kernel",
    "segment_triangle",
    "subtet_faces_kernel",
    "to_rest_kernel",
    "unchanged_kernel",
    "unit_splits_kernel",
]  # fmt: skip

#: barycentric slack: an edge through a sweep triangle's edge or corner is found by both triangles there
_BARY = wp.constant(1e-6)
#: |det| below this fraction of |d| |e1 x e2| is a segment parallel to the triangle (in its plane or beside it)
_PARALLEL = wp.constant(1e-7)


@wp.func
def segment_triangle(p: wp.vec3, q: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """Parameter ``t`` in [0, 1] where segment p -> q crosses triangle abc (Moller & Trumbore 1997), or -1.

    A segment parallel to the triangle (in its plane too) does not cross it:
    its end points meet the sweep through the edges that do cross, and snap.
    """
    d = q - p
    e1 = b - a
    e2 = c - a
    pv = wp.cross(d, e2)
    det = wp.dot(e1, pv)
    if wp.abs(det) <= _PARALLEL * wp.length(d) * wp.length(wp.cross(e1, e2)):
        return -1.0
    inv = 1.0 / det
    s = p - a
    u = wp.dot(s, pv) * inv
    if u < -_BARY or u > 1.0 + _BARY:
        return -1.0
    qv = wp.cross(s, e1)
    v = wp.dot(d, qv) * inv
    if v < -_BARY or u + v > 1.0 + _BARY:
        return -1.0
    t = wp.dot(e2, qv) * inv
    if t < 0.0 or t > 1.0:
        return -1.0
    return t


@wp.kernel(enable_backward=False)
def intersect_edges_kernel(
    edge_nodes: wp.array(dtype=wp.vec2i),
    edge_ok: wp.array(dtype=wp.uint8),
    positions: wp.array(dtype=wp.vec3),
    bvh: wp.uint64,
    corners: wp.array(dtype=wp.vec3),
    offset: int,
    hit_t: wp.array(dtype=float),
    hit_tri: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """Per edge: its first crossing of the sweep (the lowest triangle index, i.e. the earliest sample); flag 1
    where it has one."""
    e = wp.tid() + offset
    hit_t[e] = -1.0
    hit_tri[e] = -1
    flags[e] = 0
    if edge_ok[e] == wp.uint8(0):
        return
    p = positions[edge_nodes[e][0]]
    q = positions[edge_nodes[e][1]]
    query = wp.bvh_query_aabb(bvh, wp.min(p, q), wp.max(p, q))
    i = int(0)
    best = int(-1)
    best_t = float(-1.0)
    while wp.bvh_query_next(query, i):
        if best < 0 or i < best:
            t = segment_triangle(p, q, corners[3 * i], corners[3 * i + 1], corners[3 * i + 2])
            if t >= 0.0:
                best = i
                best_t = t
    hit_t[e] = best_t
    hit_tri[e] = best
    flags[e] = wp.where(best_t >= 0.0, 1, 0)


@wp.func
def node_side(p: wp.vec3, c0: wp.vec3, n: wp.vec3):
    """(the side ``n . (p - c0)`` of point ``p`` of a sweep triangle's plane, the L1 length of ``p - c0``):
    a node's terms of :func:`intersect_edges_few_kernel`'s same-side test."""
    sp = p - c0
    return wp.vec2(wp.dot(n, sp), wp.abs(sp[0]) + wp.abs(sp[1]) + wp.abs(sp[2]))


@wp.func
def few_crossing(
    i: int,
    u: int,
    w: int,
    positions: wp.array(dtype=wp.vec3),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    corners: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    slack: wp.array(dtype=float),
    sides: wp.array2d(dtype=wp.vec2),
) -> float:
    """The parameter where edge ``(u, w)`` crosses sweep triangle ``i``, -1 where it does not: passed over
    where its ends lie on the same side of the triangle's plane by more than the slack, or its box misses
    the triangle's (:func:`intersect_edges_few_kernel`), else :func:`segment_triangle`."""
    a = wp.vec2()
    b = wp.vec2()
    if sides.shape[0] == 0:
        a = node_side(positions[u], corners[3 * i], normals[i])
        b = node_side(positions[w], corners[3 * i], normals[i])
    else:
        a = sides[u, i]
        b = sides[w, i]
    tol = slack[i] * (a[1] + b[1])
    if (a[0] > tol and b[0] > tol) or (a[0] < -tol and b[0] < -tol):
        return -1.0
    p = positions[u]
    q = positions[w]
    lo = wp.min(p, q)
    hi = wp.max(p, q)
    lb = lowers[i]
    ub = uppers[i]
    if lo[0] > ub[0] or lo[1] > ub[1] or lo[2] > ub[2] or hi[0] < lb[0] or hi[1] < lb[1] or hi[2] < lb[2]:
        return -1.0
    return segment_triangle(p, q, corners[3 * i], corners[3 * i + 1], corners[3 * i + 2])


@wp.kernel(enable_backward=False)
def node_sides_kernel(positions: wp.array(dtype=wp.vec3), corners: wp.array(dtype=wp.vec3),
                      normals: wp.array(dtype=wp.vec3), offset: int, sides: wp.array2d(dtype=wp.vec2)):  # fmt: skip
    """Per node ``v`` and sweep triangle ``i``: :func:`node_side`, once per node (the ``sides`` of
    :func:`intersect_edges_few_kernel` for a sweep over most of the mesh)."""
    v = wp.tid() + offset
    p = positions[v]
    for i in range(normals.shape[0]):
        sides[v, i] = node_side(p, corners[3 * i], normals[i])


@wp.kernel(enable_backward=False)
def intersect_edges_few_kernel(
    edge_nodes: wp.array(dtype=wp.vec2i),
    edge_ok: wp.array(dtype=wp.uint8),
    positions: wp.array(dtype=wp.vec3),
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
    corners: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    slack: wp.array(dtype=float),
    sides: wp.array2d(dtype=wp.vec2),
    offset: int,
    hit_t: wp.array(dtype=float),
    hit_tri: wp.array(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """:func:`intersect_edges_kernel` for a sweep of a few triangles: each triangle's box (the boxes the BVH
    holds) against the edge's, in index order, without the tree: the same candidates, the same first hit.

    Before the exact test, an edge whose two ends lie on the same side of a triangle's plane by more than
    ``slack`` (per triangle: 1e-4 |e1| |e2|, times the ends' L1 distances to its first corner; the
    rounding of :func:`segment_triangle` is below 1e-6 of that) is passed over: there its ``t`` is outside
    [0, 1] by more than 1e-4, so the test would give -1 too (the same hits, bit for bit, at a fraction
    of the cost where a plane's box holds every edge). The ends' terms of that test are :func:`node_side`,
    read from the rows of ``sides`` ((nodes, triangles), :func:`node_sides_kernel`: a sweep over most of
    the mesh, each node's terms once instead of once per edge, an edge's positions loaded only where a
    plane may cross it) or, where ``sides`` is empty, computed here (:func:`few_crossing`). For 1 to
    :data:`FEW_UNROLLED` triangles, :data:`FEW_KERNELS` gives the same two kernels with their loop over the
    triangles unrolled (a loop as long as an array's shape costs Warp's CPU code 2-3x as much)."""
    e = wp.tid() + offset
    flags[e] = 0  # hit_t and hit_tri are written at hits only (read there only)
    if edge_ok[e] == wp.uint8(0):
        return
    ends = edge_nodes[e]
    for i in range(lowers.shape[0]):
        t = few_crossing(i, ends[0], ends[1], positions, lowers, uppers, corners, normals, slack, sides)
        if t >= 0.0:
            hit_t[e] = t
            hit_tri[e] = i
            flags[e] = 1
            return


def _few_kernels(count: int) -> tuple[wp.Kernel, wp.Kernel]:
    """:func:`node_sides_kernel` and :func:`intersect_edges_few_kernel` for a sweep of exactly ``count``
    triangles, their loops over the triangles unrolled (the same values)."""

    def node_sides(positions, corners, normals, offset, sides):
        v = wp.tid() + offset
        p = positions[v]
        for i in range(wp.static(count)):
            sides[v, i] = node_side(p, corners[3 * i], normals[i])

    def intersect(edge_nodes, edge_ok, positions, lowers, uppers, corners, normals, slack, sides, offset, hit_t,
                  hit_tri, flags):  # fmt: skip
        e = wp.tid() + offset
        flags[e] = 0
        if edge_ok[e] == wp.uint8(0):
            return
        ends = edge_nodes[e]
        for i in range(wp.static(count)):
            t = few_crossing(i, ends[0], ends[1], positions, lowers, uppers, corners, normals, slack, sides)
            if t >= 0.0:
                hit_t[e] = t
                hit_tri[e] = i
                flags[e] = 1
                return

    # (the argument types as objects: this module's annotations are strings, read without the closure)
    for f, kernel in ((node_sides, node_sides_kernel), (intersect, intersect_edges_few_kernel)):
        f.__annotations__ = dict(kernel.adj.arg_types)
    return (wp.kernel(node_sides, enable_backward=False, name=f"node_sides{count}_kernel", module=__name__),
            wp.kernel(intersect, enable_backward=False, name=f"intersect_edges{count}_kernel", module=__name__))  # fmt: skip


#: the most triangles :data:`FEW_KERNELS` has kernels for (a plane's two, a stroke frame's two, a few strips)
FEW_UNROLLED = 4
#: per triangle count 1 .. FEW_UNROLLED: (node sides, intersection) kernels with the loop unrolled
FEW_KERNELS = {count: _few_kernels(count) for count in range(1, FEW_UNROLLED + 1)}


@wp.kernel(enable_backward=False)
def flag_positive_kernel(values: wp.array(dtype=float), offset: int, flags: wp.array(dtype=wp.int32)):
    i = wp.tid() + offset
    flags[i] = wp.where(values[i] >= 0.0, 1, 0)


@wp.func
def _tet_code(
    nodes: wp.vec4i, edges: vec6i, edge_cut: wp.array(dtype=wp.uint8), node_cut: wp.array(dtype=wp.uint8)
) -> int:
    """A tet's ``edge_code | node_code << 6``: its cut edges (an edge -1 is not cut) and cut nodes."""
    value = int(0)
    for j in range(6):
        if edges[j] >= 0:  # noqa: SIM102 (a kernel does not short-circuit: edge_cut[-1] would be read)
            if edge_cut[edges[j]] != wp.uint8(0):
                value = value | (1 << j)
    for m in range(4):
        if node_cut[nodes[m]] != wp.uint8(0):
            value = value | (1 << (6 + m))
    return value


@wp.func
def _marked(mark: wp.array(dtype=wp.uint8), nodes: wp.vec4i) -> bool:
    return mark[nodes[0]] + mark[nodes[1]] + mark[nodes[2]] + mark[nodes[3]] != wp.uint8(0)


@wp.kernel(enable_backward=False)
def cell_codes_kernel(
    cell_nodes: wp.array(dtype=wp.vec4i),
    cell_edges: wp.array(dtype=vec6i),
    edge_cut: wp.array(dtype=wp.uint8),
    node_cut: wp.array(dtype=wp.uint8),
    offset: int,
    code: wp.array(dtype=wp.int32),
):
    """Per cell (the rows of the cells a cut may code, gathered once): ``edge_code | node_code << 6`` (6
    cut-edge bits in TET_EDGES order, 4 cut-node bits)."""
    i = wp.tid() + offset
    code[i] = _tet_code(cell_nodes[i], cell_edges[i], edge_cut, node_cut)


@wp.kernel(enable_backward=False)
def cells_at_nodes_kernel(
    cell_nodes: wp.array(dtype=wp.vec4i),
    cell_alive: wp.array(dtype=wp.uint8),
    node_mark: wp.array(dtype=wp.uint8),
    offset: int,
    flags: wp.array(dtype=wp.int32),
):
    """1 for every live cell with a marked node."""
    c = wp.tid() + offset
    f = int(0)
    if cell_alive[c] != wp.uint8(0):
        for k in range(4):
            if node_mark[cell_nodes[c][k]] != wp.uint8(0):
                f = 1
    flags[c] = f


@wp.kernel(enable_backward=False)
def to_rest_kernel(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    positions: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    radius: float,
    offset: int,
    out: wp.array(dtype=wp.vec3),
):
    """A world point carried back to the rest frame by its nearest node's displacement (itself if none is near)."""
    i = wp.tid() + offset
    p = points[i]
    best = float(radius * radius)
    node = int(-1)
    query = wp.hash_grid_query(grid, p, radius)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        d = wp.length_sq(positions[j] - p)
        if d < best:
            best = d
            node = j
    if node >= 0:
        out[i] = p - (positions[node] - rest[node])
    else:
        out[i] = p


@wp.kernel(enable_backward=False)
def mark_edges_in_use_kernel(
    cell_edges: wp.array(dtype=vec6i), cell_alive: wp.array(dtype=wp.uint8), offset: int,
    in_use: wp.array(dtype=wp.uint8),
):  # fmt: skip
    """1 for every edge of a live cell (a split edge stays alive, unused, until the garbage collection)."""
    c = wp.tid() + offset
    if cell_alive[c] != wp.uint8(0):
        for j in range(6):
            in_use[cell_edges[c][j]] = wp.uint8(1)


@wp.func
def _snap_edge(edges: vec6i, bits: int, hit_of: wp.array(dtype=wp.int32), t_hit: wp.array(dtype=wp.float64)) -> int:
    """The snap rule's edge: of the cut edges of a tet (``bits`` over ``edges``), the one whose split point lies
    nearest an end (the first in edge order on a tie)."""
    best = int(-1)
    best_d = wp.float64(2.0)
    for j in range(6):
        if ((bits >> j) & 1) != 0:
            st = t_hit[hit_of[edges[j]] - 1]
            d = wp.min(st, wp.float64(1.0) - st)
            if d < best_d:
                best_d = d
                best = edges[j]
    return best


@wp.kernel(enable_backward=False)
def look_ahead_kernel(
    rows_nodes: wp.array(dtype=wp.vec4i),
    rows_edges: wp.array(dtype=vec6i),
    own: wp.array(dtype=wp.uint8),
    rec_corners: wp.array(dtype=wp.vec4i),
    rec_edges: wp.array(dtype=vec6i),
    rec_code: wp.array(dtype=wp.int32),
    code_ok: wp.array(dtype=wp.uint8),
    hits: wp.array(dtype=wp.int32),
    t_hit: wp.array(dtype=wp.float64),
    hit_of: wp.array(dtype=wp.int32),
    edge_nodes: wp.array(dtype=wp.vec2i),
    rounds: int,
    node_cut: wp.array(dtype=wp.uint8),
    edge_cut: wp.array(dtype=wp.uint8),
    dropped: wp.array(dtype=wp.uint8),
    locked: wp.array(dtype=wp.uint8),
    mark: wp.array(dtype=wp.uint8),
    moved: wp.array(dtype=wp.int32),
    moved_count: wp.array(dtype=wp.int32),
    chosen: wp.array(dtype=wp.int32),
    stuck: wp.array(dtype=wp.int32),
):
    """The classification's look-ahead, one thread: until no tet round the ``moved`` nodes (``mark``) lacks a
    table entry for its code (cells cut on their own, ``own``; progressive records on their accumulated
    codes), each one that does snaps by the snap rule, all at once per pass: the cut edge whose split point
    lies nearest an end makes that end a cut node, or, where the end may not be cut (``locked``), drops
    its hit; a record with no edge cut now keeps its cut corners uncut (and locked). The nodes a pass
    changed are the next pass's ``moved`` (``moved_count``: their count, and the corners kept uncut in all);
    ``edge_cut`` holds the hits kept at the last pass's start."""
    count = int(moved_count[0])
    for _pass in range(rounds):
        for h in range(hits.shape[0]):
            ends = edge_nodes[hits[h]]
            keep = wp.uint8(0)
            if node_cut[ends[0]] == wp.uint8(0) and node_cut[ends[1]] == wp.uint8(0) and dropped[h] == wp.uint8(0):
                keep = wp.uint8(1)
            edge_cut[hits[h]] = keep
        rows = int(0)
        for i in range(rows_nodes.shape[0]):
            if own[i] != wp.uint8(0) and _marked(mark, rows_nodes[i]):
                code = _tet_code(rows_nodes[i], rows_edges[i], edge_cut, node_cut)
                ebits, nbits = code & 63, code >> 6
                if ebits != 0 and code_ok[ebits * 16 + nbits] == wp.uint8(0):
                    chosen[rows] = _snap_edge(rows_edges[i], ebits, hit_of, t_hit)
                    rows += 1
        stuck_count = int(0)
        for r in range(rec_corners.shape[0]):
            cn = rec_corners[r]
            if _marked(mark, cn):
                code = _tet_code(cn, rec_edges[r], edge_cut, node_cut)
                ebits, nbits = code & 63, code >> 6
                if code != 0 and code_ok[(rec_code[r] | ebits) * 16 + nbits] == wp.uint8(0):
                    if ebits != 0:
                        chosen[rows] = _snap_edge(rec_edges[r], ebits, hit_of, t_hit)
                        rows += 1
                    else:
                        for m in range(4):
                            if ((nbits >> m) & 1) != 0:
                                stuck[stuck_count] = cn[m]
                                stuck_count += 1
        if rows == 0 and stuck_count == 0:
            break
        moved_count[1] = moved_count[1] + stuck_count
        for q in range(count):
            mark[moved[q]] = wp.uint8(0)
        count = int(0)
        for q in range(stuck_count):
            node_cut[stuck[q]] = wp.uint8(0)
            locked[stuck[q]] = wp.uint8(1)
            moved[count] = stuck[q]
            count += 1
        for q in range(rows):
            e = chosen[q]
            ends = edge_nodes[e]
            target = ends[1]
            if t_hit[hit_of[e] - 1] < wp.float64(0.5):
                target = ends[0]
            if locked[target] == wp.uint8(0):
                node_cut[target] = wp.uint8(1)
                moved[count] = target
                count += 1
            else:
                dropped[hit_of[e] - 1] = wp.uint8(1)
                moved[count] = ends[0]
                moved[count + 1] = ends[1]
                count += 2
        for q in range(count):
            mark[moved[q]] = wp.uint8(1)
    moved_count[0] = count


# -- classification of the changed tets: table entry, rank permutation, rest volume, positivity -------------------

#: a sub-tet is flat below this x the cube of its longest edge: ten times the simulator's degenerate volume (so
#: every tet a cut makes can be simulated; float32 storage would invert a flatter one)
_FLAT = wp.constant(wp.float64(10.0 * DEGENERATE_VOLUME))


@wp.func
def _corner64(rest: wp.array(dtype=wp.vec3), cn: wp.vec4i, k: int) -> wp.vec3d:
    p = rest[cn[k]]
    return wp.vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2]))


@wp.func
def _ref_point(rest: wp.array(dtype=wp.vec3), cn: wp.vec4i, t: wp.array(dtype=wp.float64), u: int, r: int) -> wp.vec3d:
    """Rest position (float64) of reference ``r`` of unit ``u`` (split points at the unit's parameters ``t``)."""
    if r < 4:
        return _corner64(rest, cn, r)
    if r < 16:
        j = (r - 4) // 2
        a = _corner64(rest, cn, TET_EDGES_WP[j, 0])
        b = _corner64(rest, cn, TET_EDGES_WP[j, 1])
        return a + t[6 * u + j] * (b - a)
    if r < 24:
        return _corner64(rest, cn, (r - 16) // 2)
    if r < 28:
        f = r - 24
        s = _corner64(rest, cn, TET_FACES_WP[f, 0]) + _corner64(rest, cn, TET_FACES_WP[f, 1])
        s = s + _corner64(rest, cn, TET_FACES_WP[f, 2])
        return s / wp.float64(3.0)
    s = _corner64(rest, cn, 0) + _corner64(rest, cn, 1)
    s = s + _corner64(rest, cn, 2)
    s = s + _corner64(rest, cn, 3)
    return s / wp.float64(4.0)


@wp.func
def _volume6(a: wp.vec3d, b: wp.vec3d, c: wp.vec3d, d: wp.vec3d) -> wp.float64:
    return wp.dot(wp.cross(b - a, c - a), d - a) / wp.float64(6.0)


@wp.kernel(enable_backward=False)
def classify_units_kernel(
    corners: wp.array(dtype=wp.vec4i),
    edge_code: wp.array(dtype=wp.int32),
    node_code: wp.array(dtype=wp.int32),
    t: wp.array(dtype=wp.float64),
    rest: wp.array(dtype=wp.vec3),
    table_entry: wp.array(dtype=wp.int32),
    table_count: wp.array(dtype=wp.int32),
    table_refs: wp.array(dtype=wp.int32),
    table_kind: wp.array(dtype=wp.int32),
    rank_lookup: wp.array(dtype=wp.int32),
    xp_kind: int,
    offset: int,
    entry: wp.array(dtype=wp.int32),
    perm: wp.array(dtype=wp.int32),
    rest_volume: wp.array(dtype=wp.float64),
    bad: wp.array(dtype=wp.int32),
):
    """Per changed tet: its table entry and rank permutation, its rest volume, and whether its entry is bad
    (a code the tables lack, the progressive code with a cut node, or a sub-tet that is not positive at the
    actual split points: flat below ``_FLAT`` x its longest edge cubed)."""
    u = wp.tid() + offset
    cn = corners[u]
    code = int(0)
    for k in range(4):
        rank = int(0)
        for m in range(4):
            if cn[m] < cn[k]:
                rank += 1
        code += rank << (2 * k)
    p = rank_lookup[code]
    e = table_entry[edge_code[u] * 16 + node_code[u]]
    entry[u] = e
    perm[u] = p
    rest_volume[u] = _volume6(_corner64(rest, cn, 0), _corner64(rest, cn, 1), _corner64(rest, cn, 2),
                              _corner64(rest, cn, 3))  # fmt: skip
    flag = int(0)
    if e < 0:  # noqa: SIM114 (a kernel does not short-circuit: table_kind[-1] would be read)
        flag = 1
    elif table_kind[e] == xp_kind:
        flag = 1
    else:
        n = table_count[e * 24 + p]
        if n > 1:
            for s in range(n):
                base = ((e * 24 + p) * 16 + s) * 4
                a = _ref_point(rest, cn, t, u, table_refs[base])
                b = _ref_point(rest, cn, t, u, table_refs[base + 1])
                c = _ref_point(rest, cn, t, u, table_refs[base + 2])
                d = _ref_point(rest, cn, t, u, table_refs[base + 3])
                vol = _volume6(a, b, c, d)
                longest = wp.max(wp.max(wp.max(wp.length_sq(a - b), wp.length_sq(a - c)),
                                        wp.max(wp.length_sq(a - d), wp.length_sq(b - c))),
                                 wp.max(wp.length_sq(b - d), wp.length_sq(c - d)))  # fmt: skip
                longest = wp.sqrt(longest)
                if not (vol > _FLAT * wp.pow(longest, wp.float64(3.0))):
                    flag = 1
    bad[u] = flag


# -- subdivision: sub-tets from the tables, the faces at cut nodes ----------------------------------------------


@wp.kernel(enable_backward=False)
def emit_subtets_kernel(
    entry: wp.array(dtype=wp.int32),
    perm: wp.array(dtype=wp.int32),
    corners: wp.array(dtype=wp.vec4i),
    split_of: wp.array(dtype=wp.int32),
    first_row: wp.array(dtype=wp.int32),
    table_count: wp.array(dtype=wp.int32),
    table_refs: wp.array(dtype=wp.int32),
    offset: int,
    unit_of: wp.array(dtype=wp.int32),
    refs: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
):
    """The sub-tets of each changed tet, one row each from ``first_row[u]``: their references and the nodes
    of those that are corners or split points (``split_of``: 12 per unit, copy ``e`` of local edge ``j`` at
    ``2 j + e``); -1 for the others (cut-node copies, crack fronts), filled on the host."""
    u = wp.tid() + offset
    e = entry[u]
    p = perm[u]
    cn = corners[u]
    row0 = first_row[u]
    for s in range(table_count[e * 24 + p]):
        row = row0 + s
        unit_of[row] = u
        for c in range(4):
            r = table_refs[((e * 24 + p) * 16 + s) * 4 + c]
            refs[4 * row + c] = r
            v = int(-1)
            if r >= 0 and r < 4:
                v = cn[r]
            elif r >= 4 and r < 16:
                v = split_of[12 * u + r - 4]
            ids[4 * row + c] = v


@wp.kernel(enable_backward=False)
def subtet_faces_kernel(
    rows: wp.array(dtype=wp.int32),
    unit_of: wp.array(dtype=wp.int32),
    refs: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
    corners: wp.array(dtype=wp.vec4i),
    key_base: wp.int64,
    offset: int,
    row_elem: wp.array(dtype=wp.int32),
    face_key: wp.array(dtype=wp.int64),
    face_elem: wp.array(dtype=wp.vec3i),
    face_flag: wp.array(dtype=wp.int32),
):
    """The faces of sub-tets that hold a cut node: per corner the node it stands for (a cut node's copy
    stands for the node) and its provisional copy ``(unit * 4 + k) * 2 + group`` (-1 for other corners),
    sorted by node; the face key; flags: 1 a corner is a copy, 2 every corner is (the face lies on the
    sweep). ``row_elem``: the provisional copy at each corner of the sub-tet."""
    i = wp.tid() + offset
    row = rows[i]
    u = unit_of[row]
    cn = corners[u]
    for c in range(4):
        r = refs[4 * row + c]
        el = int(-1)
        if r >= 16 and r < 24:
            el = (u * 4 + (r - 16) // 2) * 2 + (r - 16) % 2
        row_elem[4 * i + c] = el
    for f in range(4):
        n0 = int(0)
        n1 = int(0)
        n2 = int(0)
        e0 = int(0)
        e1 = int(0)
        e2 = int(0)
        for m in range(3):
            c = TET_FACES_WP[f, m]
            r = refs[4 * row + c]
            node = ids[4 * row + c]
            el = int(-1)
            if r >= 16 and r < 24:
                node = cn[(r - 16) // 2]
                el = (u * 4 + (r - 16) // 2) * 2 + (r - 16) % 2
            if m == 0:
                n0 = node
                e0 = el
            elif m == 1:
                n1 = node
                e1 = el
            else:
                n2 = node
                e2 = el
        # sort the three by node (distinct), the copies alongside
        if n0 > n1:
            n0, n1 = n1, n0
            e0, e1 = e1, e0
        if n1 > n2:
            n1, n2 = n2, n1
            e1, e2 = e2, e1
        if n0 > n1:
            n0, n1 = n1, n0
            e0, e1 = e1, e0
        face_key[4 * i + f] = (wp.int64(n0) * key_base + wp.int64(n1)) * key_base + wp.int64(n2)
        face_elem[4 * i + f] = wp.vec3i(e0, e1, e2)
        flag = int(0)
        if e0 >= 0 or e1 >= 0 or e2 >= 0:
            flag = 1
        if e0 >= 0 and e1 >= 0 and e2 >= 0:
            flag = 3
        face_flag[4 * i + f] = flag


@wp.kernel(enable_backward=False)
def pair_faces_kernel(
    face_key: wp.array(dtype=wp.int64),
    face_elem: wp.array(dtype=wp.vec3i),
    face_flag: wp.array(dtype=wp.int32),
    bits: int,
    table: wp.array(dtype=wp.int64),
    used: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    sweep_pairs: wp.array(dtype=wp.vec2i),
    sweep_count: wp.array(dtype=wp.int32),
):
    """One thread, faces in order: a face meets its earlier twin (the same key) in an open-addressing table
    of ``2**bits`` slots, each a key and its face side by side (``table`` flat, every key EMPTY on entry and
    again on exit; ``used`` scratch of a slot per face). A pair off the sweep joins the two sides' copies of
    each shared cut node (union by lower root, path halving); a pair on the sweep is listed ``(earlier,
    later)`` for the host (slivers)."""
    taken = int(0)
    for i in range(face_key.shape[0]):
        flag = face_flag[i]
        if flag != 0:
            key = face_key[i]
            s = _pair_slot(table, bits, key)
            if table[2 * s] != key:
                table[2 * s] = key
                table[2 * s + 1] = wp.int64(i)
                used[taken] = s
                taken += 1
            else:
                j = int(table[2 * s + 1])
                if face_flag[j] == 3:
                    n = sweep_count[0]
                    sweep_pairs[n] = wp.vec2i(j, i)
                    sweep_count[0] = n + 1
                else:
                    for m in range(3):
                        a = face_elem[j][m]
                        b = face_elem[i][m]
                        if a >= 0 and b >= 0:
                            _join(parent, a, b)
    for j in range(taken):
        table[2 * used[j]] = _EMPTY_WP


@wp.kernel(enable_backward=False)
def unit_splits_kernel(
    corners: wp.array(dtype=wp.vec4i),
    new_edges: wp.array(dtype=wp.int32),
    old_split: wp.array(dtype=wp.int32),
    edge_nodes: wp.array(dtype=wp.vec2i),
    position: wp.array(dtype=wp.int32),
    first_id: int,
    cut_count: int,
    offset: int,
    split_of: wp.array(dtype=wp.int32),
):
    """Per unit and local edge (12 per unit, ``2 j + e``): the split copy joined to its local first (``e`` 0)
    and second end. An edge this stroke cuts (``new_edges``, the ``position``-th cut edge) has copies
    ``first_id + position`` (joined to the edge's first node) and ``first_id + cut_count + position``; the
    others keep ``old_split``."""
    u = wp.tid() + offset
    cn = corners[u]
    for j in range(6):
        e = new_edges[6 * u + j]
        if e >= 0:
            p = position[e]
            s0 = first_id + p
            s1 = first_id + cut_count + p
            if edge_nodes[e][0] == cn[TET_EDGES_WP[j, 0]]:
                split_of[12 * u + 2 * j] = s0
                split_of[12 * u + 2 * j + 1] = s1
            else:
                split_of[12 * u + 2 * j] = s1
                split_of[12 * u + 2 * j + 1] = s0
        else:
            split_of[12 * u + 2 * j] = old_split[12 * u + 2 * j]
            split_of[12 * u + 2 * j + 1] = old_split[12 * u + 2 * j + 1]


@wp.kernel(enable_backward=False)
def unchanged_kernel(
    units: wp.array(dtype=wp.int32),
    first_row: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
    corners: wp.array(dtype=wp.vec4i),
    offset: int,
    same: wp.array(dtype=wp.uint8),
):
    """1 where the single sub-tet of unit ``units[i]`` has the unit's own four nodes (in any order)."""
    i = wp.tid() + offset
    u = units[i]
    cn = corners[u]
    r = first_row[u]
    flag = wp.uint8(1)
    for c in range(4):
        v = ids[4 * r + c]
        if v != cn[0] and v != cn[1] and v != cn[2] and v != cn[3]:
            flag = wp.uint8(0)
    same[i] = flag
