"""Warp kernels of the cutter: edge-sweep intersection, hit flags, per-tet cut codes."""

from __future__ import annotations

import warp as wp

from ..mesh._structure import vec6i

__all__ = [
    "mark_edges_in_use_kernel",
    "to_rest_kernel",
    "cell_codes_kernel",
    "flag_positive_kernel",
    "intersect_edges_kernel",
    "segment_triangle",
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
):
    """Per edge: its first crossing of the sweep (the lowest triangle index, i.e. the earliest sample)."""
    e = wp.tid() + offset
    hit_t[e] = -1.0
    hit_tri[e] = -1
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


@wp.kernel(enable_backward=False)
def flag_positive_kernel(values: wp.array(dtype=float), offset: int, flags: wp.array(dtype=wp.int32)):
    i = wp.tid() + offset
    flags[i] = wp.where(values[i] >= 0.0, 1, 0)


@wp.kernel(enable_backward=False)
def cell_codes_kernel(
    cell_nodes: wp.array(dtype=wp.vec4i),
    cell_edges: wp.array(dtype=vec6i),
    cell_alive: wp.array(dtype=wp.uint8),
    edge_cut: wp.array(dtype=wp.uint8),
    node_cut: wp.array(dtype=wp.uint8),
    offset: int,
    code: wp.array(dtype=wp.int32),
    changed: wp.array(dtype=wp.int32),
):
    """Per cell: ``edge_code | node_code << 6`` (6 cut-edge bits in TET_EDGES order, 4 cut-node bits)."""
    c = wp.tid() + offset
    value = int(0)
    if cell_alive[c] != wp.uint8(0):
        for j in range(6):
            if edge_cut[cell_edges[c][j]] != wp.uint8(0):
                value = value | (1 << j)
        for k in range(4):
            if node_cut[cell_nodes[c][k]] != wp.uint8(0):
                value = value | (1 << (6 + k))
    code[c] = value
    changed[c] = wp.where(value != 0, 1, 0)


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
