"""The edge-based tetrahedral mesh structure that simulation and cutting work on (SPEC section 4).

Four entity kinds, each stored as flat arrays (structure of arrays) that
Warp kernels read directly (:meth:`TetStructure.to_warp`); the Python
objects (:class:`NodeView` and friends) are views onto those arrays.

- nodes: rest and current position;
- edges: two nodes;
- faces: three nodes and three edges (edge ``j`` joins nodes ``j`` and ``j + 1``)
  and the one or two cells on its sides;
- cells: four nodes (positive orientation), four faces (face ``k`` opposite
  node ``k``, :data:`~warpblob.mesh._tetmesh.TET_FACES`), six edges
  (:data:`~warpblob.mesh._tetmesh.TET_EDGES` order) and a material id.

Top-down links (cell -> faces, edges, nodes; face -> edges, nodes; edge ->
nodes) and the face -> cells slots are stored per entity and kept exact by
every operation. The other bottom-up links (node -> edges, edge -> faces) are
CSR arrays built by kernels (sort, then a binary search per row) and rebuilt
by :meth:`TetStructure.rebuild_links`; between rebuilds the Python side keeps
the incidences added since (a small dict of sets) and filters out stale
ones, so queries are always exact and the CSR never needs patching in place.

An edge is found in O(1) by the 64-bit key ``(max << 32) | min`` of its node
ids: an open-addressing hash table with linear probing in two flat arrays
(``keys`` int64, ``values`` int32; ``-1`` empty, ``-2`` deleted), built by a
kernel and probed by :func:`edge_table_find` in kernels and by the same
probe sequence in Python. Slots hold Fibonacci hashes of the key.

Removal is deferred (the thesis' VolCut, SPEC section 6): a removed entity is
flagged dead and listed as pending, indices stay valid until
:meth:`TetStructure.collect_garbage` purges unreferenced faces, edges and
nodes, compacts every kind and remaps every link. Every insert, update and
removal fires an event to the observers (:meth:`TetStructure.subscribe`).

What a cut needs of the whole mesh is kept so that a small cut costs what it
changes: a uniform grid of the cells' rest boxes (bucket side the largest box
side, cells sorted by the bucket of their lower corner: a counting sort in a
kernel), in which a cut finds the cells near its sweep; and the number of
connected pieces, counted by a union-find over the faces (one per range of
cells side by side, then the faces between ranges) and, after a batch edit,
settled round the new cells when they show that nothing was severed
(:meth:`TetStructure._pieces_after`). Both are kept until an edit makes them
stale (a cell's nodes or a rest position, any cell or face).
"""

from __future__ import annotations

import contextlib
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .._device import resolve_device
from .._errors import WarpblobError
from .._parallel import launch, submit, thread_count
from .._stages import device_array, device_empty, host_array, mark_heads_kernel, rows_all, rows_any, shared_array
from ._surface import bounds_text
from ._tetmesh import TET_EDGES, TET_EDGES_WP, TET_FACES, TET_FACES_WP, TET_LOCAL_EDGE_WP, TetMesh

__all__ = [
    "NODE_ORIGINS",
    "CellView",
    "EdgeView",
    "FaceView",
    "NodeView",
    "TetStructure",
    "TetStructureArrays",
    "csr",
    "edge_key",
    "edge_table_find",
    "lookup_edge",
]

KINDS = ("node", "edge", "face", "cell")
#: :attr:`TetStructure.node_origin` values: what made a node
NODE_ORIGINS = {"model": 0, "split": 1, "copy": 2, "front": 3}
EMPTY = -1  # hash slot never used
DELETED = -2  # hash slot whose edge was removed (probing continues past it)
_GOLDEN = 0x9E3779B97F4A7C15  # 2^64 / golden ratio: Fibonacci hashing
_MASK64 = (1 << 64) - 1

vec6i = wp.types.vector(length=6, dtype=wp.int32)
_EMPTY_WP = wp.constant(wp.int64(EMPTY))
_DELETED_WP = wp.constant(wp.int64(DELETED))
_GOLDEN_WP = wp.constant(wp.uint64(_GOLDEN))
#: items per piece of a range-split launch of a kernel doing a few loads and stores per item
_CHEAP = 16384
#: missing edges from which a batch edit puts them in the lookup table on a pool thread beside the faces'
#: matching (below, waking a thread costs more than it saves)
_SIDE_EDGES = 1 << 14
#: cells per range of the components' side-by-side union-find (fewer: one range, no second thread to wake)
_COMPONENT_RANGE = 65536
#: a flood after a batch edit may queue up to 1/_FLOOD_SHARE of the cells before every cell is counted
_FLOOD_SHARE = 16


# ---------------------------------------------------------------------------
# device functions and the arrays kernels see
# ---------------------------------------------------------------------------


@wp.func
def edge_key(a: int, b: int) -> wp.int64:
    """The 64-bit key ``(max << 32) | min`` of the edge joining nodes ``a`` and ``b``."""
    return (wp.int64(wp.max(a, b)) << wp.int64(32)) | wp.int64(wp.min(a, b))


@wp.func
def _edge_slot(key: wp.int64, bits: int) -> int:
    return int((wp.uint64(key) * _GOLDEN_WP) >> wp.uint64(64 - bits))


@wp.func
def _pair_slot(table: wp.array(dtype=wp.int64), bits: int, key: wp.int64) -> int:
    """The slot of ``key`` in an open-addressing table of ``2**bits`` slots, each a key and its value side by
    side (``table`` flat), or the EMPTY slot where it would go (linear probing from :func:`_edge_slot`)."""
    mask = (1 << bits) - 1
    s = _edge_slot(key, bits)
    while table[2 * s] != key and table[2 * s] != _EMPTY_WP:
        s = (s + 1) & mask
    return s


@wp.func
def edge_table_find(
    keys: wp.array(dtype=wp.int64), values: wp.array(dtype=wp.int32), bits: int, a: int, b: int
) -> int:
    """The edge joining nodes ``a`` and ``b`` in the hash table of ``2**bits`` slots, or -1."""
    key = edge_key(a, b)
    mask = (1 << bits) - 1
    s = _edge_slot(key, bits)
    while keys[s] != _EMPTY_WP:
        if keys[s] == key:
            return values[s]
        s = (s + 1) & mask
    return -1


@wp.struct
class TetStructureArrays:
    """The device copy of a :class:`TetStructure` (:meth:`TetStructure.to_warp`).

    Per-kind arrays cover every slot, dead ones included (``*_alive`` is 0);
    ``-1`` marks a missing link. CSR lists: the edges of node ``v`` are
    ``node_edge_list[node_edge_offsets[v] : node_edge_offsets[v + 1]]``, the
    faces of edge ``e`` likewise in ``edge_face_*``.
    """

    node_rest: wp.array(dtype=wp.vec3)
    node_position: wp.array(dtype=wp.vec3)
    node_alive: wp.array(dtype=wp.uint8)
    edge_nodes: wp.array(dtype=wp.vec2i)
    edge_alive: wp.array(dtype=wp.uint8)
    face_nodes: wp.array(dtype=wp.vec3i)
    face_edges: wp.array(dtype=wp.vec3i)
    face_cells: wp.array(dtype=wp.vec2i)
    face_alive: wp.array(dtype=wp.uint8)
    cell_nodes: wp.array(dtype=wp.vec4i)
    cell_faces: wp.array(dtype=wp.vec4i)
    cell_edges: wp.array(dtype=vec6i)
    cell_material: wp.array(dtype=wp.int32)
    cell_alive: wp.array(dtype=wp.uint8)
    node_edge_offsets: wp.array(dtype=wp.int32)
    node_edge_list: wp.array(dtype=wp.int32)
    edge_face_offsets: wp.array(dtype=wp.int32)
    edge_face_list: wp.array(dtype=wp.int32)
    edge_table_keys: wp.array(dtype=wp.int64)
    edge_table_values: wp.array(dtype=wp.int32)
    edge_table_bits: int


@wp.func
def lookup_edge(s: TetStructureArrays, a: int, b: int) -> int:
    """The edge joining nodes ``a`` and ``b`` of structure ``s``, or -1 (O(1) expected)."""
    return edge_table_find(s.edge_table_keys, s.edge_table_values, s.edge_table_bits, a, b)


# ---------------------------------------------------------------------------
# kernels: entities from tets (sort + scan), CSR links, the hash table
# ---------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def emit_edge_keys_kernel(
    tets: wp.array(dtype=wp.vec4i), offset: int, keys: wp.array(dtype=wp.int64), occurrences: wp.array(dtype=wp.int32)
):
    t = wp.tid() + offset
    for j in range(6):
        keys[6 * t + j] = edge_key(tets[t][TET_EDGES_WP[j, 0]], tets[t][TET_EDGES_WP[j, 1]])
        occurrences[6 * t + j] = 6 * t + j


@wp.kernel(enable_backward=False)
def emit_edges_kernel(
    keys: wp.array(dtype=wp.int64),
    groups: wp.array(dtype=wp.int32),
    occurrences: wp.array(dtype=wp.int32),
    offset: int,
    edge_nodes: wp.array(dtype=wp.vec2i),
    cell_edges: wp.array(dtype=wp.int32),
):
    """Edge ``groups[i] - 1`` (inclusive scan of heads) for sorted occurrence ``i``; (min, max) nodes."""
    i = wp.tid() + offset
    e = groups[i] - 1
    cell_edges[occurrences[i]] = e
    if i == 0 or groups[i - 1] != groups[i]:
        k = keys[i]
        edge_nodes[e] = wp.vec2i(int(k & wp.int64(0xFFFFFFFF)), int(k >> wp.int64(32)))


@wp.kernel(enable_backward=False)
def emit_face_keys_kernel(
    tets: wp.array(dtype=wp.vec4i),
    cell_edges: wp.array(dtype=wp.int32),
    offset: int,
    keys: wp.array(dtype=wp.int64),
    occurrences: wp.array(dtype=wp.int32),
):
    """Face key ``(edge of its two smallest nodes) << 32 | largest node``: unique, fits 63 bits."""
    t = wp.tid() + offset
    tet = tets[t]
    for k in range(4):
        l0 = TET_FACES_WP[k, 0]
        l1 = TET_FACES_WP[k, 1]
        l2 = TET_FACES_WP[k, 2]
        # put the local node with the largest global id last
        if tet[l0] > tet[l2] and tet[l0] > tet[l1]:
            l0, l2 = l2, l0
        elif tet[l1] > tet[l2]:
            l1, l2 = l2, l1
        e = cell_edges[6 * t + TET_LOCAL_EDGE_WP[l0, l1]]
        keys[4 * t + k] = (wp.int64(e) << wp.int64(32)) | wp.int64(tet[l2])
        occurrences[4 * t + k] = 4 * t + k


@wp.kernel(enable_backward=False)
def emit_faces_kernel(
    tets: wp.array(dtype=wp.vec4i),
    cell_edges: wp.array(dtype=wp.int32),
    groups: wp.array(dtype=wp.int32),
    occurrences: wp.array(dtype=wp.int32),
    offset: int,
    face_nodes: wp.array(dtype=wp.vec3i),
    face_edges: wp.array(dtype=wp.vec3i),
    face_first: wp.array(dtype=wp.int32),
    cell_faces: wp.array(dtype=wp.int32),
):
    """Face ``groups[i] - 1`` for sorted occurrence ``i``; the first occurrence (lowest cell,
    the sort is stable) writes the face, oriented outward from that cell."""
    i = wp.tid() + offset
    f = groups[i] - 1
    occ = occurrences[i]
    cell_faces[occ] = f
    if i == 0 or groups[i - 1] != groups[i]:
        t = occ // 4
        k = occ - 4 * t
        face_first[f] = i
        face_nodes[f] = wp.vec3i(tets[t][TET_FACES_WP[k, 0]], tets[t][TET_FACES_WP[k, 1]], tets[t][TET_FACES_WP[k, 2]])
        face_edges[f] = wp.vec3i(
            cell_edges[6 * t + TET_LOCAL_EDGE_WP[TET_FACES_WP[k, 0], TET_FACES_WP[k, 1]]],
            cell_edges[6 * t + TET_LOCAL_EDGE_WP[TET_FACES_WP[k, 1], TET_FACES_WP[k, 2]]],
            cell_edges[6 * t + TET_LOCAL_EDGE_WP[TET_FACES_WP[k, 2], TET_FACES_WP[k, 0]]],
        )


@wp.kernel(enable_backward=False)
def link_face_cells_kernel(
    groups: wp.array(dtype=wp.int32),
    occurrences: wp.array(dtype=wp.int32),
    face_first: wp.array(dtype=wp.int32),
    offset: int,
    face_cells: wp.array(dtype=wp.int32),
):
    """Slot ``i - first`` of the face's two cell slots (a third cell is caught on the host)."""
    i = wp.tid() + offset
    f = groups[i] - 1
    slot = i - face_first[f]
    if slot < 2:
        face_cells[2 * f + slot] = occurrences[i] // 4


@wp.kernel(enable_backward=False)
def emit_node_edges_kernel(
    edge_nodes: wp.array(dtype=wp.vec2i),
    edge_alive: wp.array(dtype=wp.uint8),
    sentinel: int,
    offset: int,
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
):
    """(node, edge) incidences; a dead edge's rows are ``sentinel`` (sorted past every real row)."""
    e = wp.tid() + offset
    for s in range(2):
        rows[2 * e + s] = sentinel
        if edge_alive[e] != wp.uint8(0):
            rows[2 * e + s] = edge_nodes[e][s]
        cols[2 * e + s] = e


@wp.kernel(enable_backward=False)
def emit_edge_faces_kernel(
    face_edges: wp.array(dtype=wp.vec3i),
    face_alive: wp.array(dtype=wp.uint8),
    sentinel: int,
    offset: int,
    rows: wp.array(dtype=wp.int32),
    cols: wp.array(dtype=wp.int32),
):
    """(edge, face) incidences; a dead face's rows are ``sentinel``."""
    f = wp.tid() + offset
    for s in range(3):
        rows[3 * f + s] = sentinel
        if face_alive[f] != wp.uint8(0):
            rows[3 * f + s] = face_edges[f][s]
        cols[3 * f + s] = f


@wp.kernel(enable_backward=False)
def lower_bound_kernel(
    sorted_rows: wp.array(dtype=wp.int32), count: int, offset: int, offsets: wp.array(dtype=wp.int32)
):
    """CSR offset of row ``r``: the first of the ``count`` sorted rows that is >= ``r``."""
    r = wp.tid() + offset
    lo = int(0)
    hi = count
    while lo < hi:
        mid = (lo + hi) // 2
        if sorted_rows[mid] < r:
            lo = mid + 1
        else:
            hi = mid
    offsets[r] = lo


@wp.kernel(enable_backward=False)
def insert_edge_ids_kernel(
    edge_nodes: wp.array(dtype=wp.vec2i),
    edge_ids: wp.array(dtype=wp.int32),
    bits: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    """Claim a slot (empty or deleted) for each listed edge by compare-and-swap, probing linearly."""
    i = wp.tid()
    e = edge_ids[i]
    key = edge_key(edge_nodes[e][0], edge_nodes[e][1])
    mask = (1 << bits) - 1
    s = _edge_slot(key, bits)
    placed = int(0)
    while placed == 0:
        old = keys[s]
        if old < wp.int64(0):
            if wp.atomic_cas(keys, s, old, key) == old:
                values[s] = e
                placed = 1
        else:
            s = (s + 1) & mask


@wp.kernel(enable_backward=False)
def add_edge_keys_kernel(
    edge_keys: wp.array(dtype=wp.int64),
    first_id: int,
    bits: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
    edge_of: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """A batch edit's missing edges (``edge_keys``, none in the table yet, each as often as new cells use it)
    put in the lookup table as they come (one thread, in order): a key met first gets edge ``first_id`` + the
    edges before it (in the first deleted slot its probe passed, else the empty one that ended it), a key
    met again the edge it got. Per key its edge (``edge_of``); per new edge the first key of it
    (``first``); ``count``: the new edges, and the empty slots they took."""
    n = edge_keys.shape[0]
    mask = (1 << bits) - 1
    g = int(0)
    fresh = int(0)
    for i in range(n):
        key = edge_keys[i]
        s = _edge_slot(key, bits)
        free = int(-1)
        while keys[s] != key and keys[s] != _EMPTY_WP:
            if keys[s] == _DELETED_WP and free < 0:
                free = s
            s = (s + 1) & mask
        if keys[s] != key:
            if free >= 0:
                s = free
            else:
                fresh += 1
            keys[s] = key
            values[s] = first_id + g
            first[g] = i
            g += 1
        edge_of[i] = values[s]
    count[0] = g
    count[1] = fresh


@wp.kernel(enable_backward=False)
def remap_table_kernel(edge_map: wp.array(dtype=wp.int32), offset: int, keys: wp.array(dtype=wp.int64),
                       values: wp.array(dtype=wp.int32)):  # fmt: skip
    """A compaction that kept every node's index, in the edge table: each used slot's edge through
    ``edge_map`` (old -> new index), a removed edge's slot marked deleted (its key stays where probing
    finds it: every other key keeps its slot)."""
    s = wp.tid() + offset
    v = values[s]
    if v >= 0:  # (a used slot: every writer keeps a value >= 0 exactly where a key is; keys are read only here)
        e = edge_map[v]
        if e < 0:
            keys[s] = _DELETED_WP
            values[s] = -1
        else:
            values[s] = e


@wp.func
def _find_root(parent: wp.array(dtype=wp.int32), i: int) -> int:
    r = i
    while parent[r] != r:
        parent[r] = parent[parent[r]]  # path halving
        r = parent[r]
    return r


@wp.func
def _join(parent: wp.array(dtype=wp.int32), a: int, b: int):
    """Union by lower root (path halving): a set's root stays its lowest item."""
    if parent[a] != parent[b]:  # the same parent: joined already
        ra = _find_root(parent, a)
        rb = _find_root(parent, b)
        if ra < rb:
            parent[rb] = ra
        elif rb < ra:
            parent[ra] = rb


@wp.kernel(enable_backward=False)
def union_find_kernel(a: wp.array(dtype=wp.int32), b: wp.array(dtype=wp.int32), count: int,
                      parent: wp.array(dtype=wp.int32)):  # fmt: skip
    """Join every pair (one thread, in order); then every item's root is the lowest item of its set."""
    for i in range(count):
        _join(parent, a[i], b[i])
    for i in range(parent.shape[0]):  # flatten: each item straight to its root (roots are lower, so done first)
        parent[i] = parent[parent[i]]


@wp.kernel(enable_backward=False)
def flood_pieces_kernel(
    face_cells: wp.array(dtype=wp.vec2i),
    cell_faces: wp.array(dtype=wp.vec4i),
    cell_alive: wp.array(dtype=wp.uint8),
    seeds: wp.array(dtype=wp.int32),
    budget: int,
    mark: wp.array(dtype=wp.int32),
    queue: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    pending: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.int32),
):
    """The pieces an edit touched, by a breadth-first flood from labelled seed cells (one thread).

    Every seed is queued with its own label (seed ``i``: label ``i``; ``parent`` and ``pending`` hold one
    entry per seed); each cell taken
    from the queue marks its unmarked live neighbours (across its faces) with its label's root and queues
    them, and joins its label with a neighbour's of another root (union by lower root). A label with no
    queued cell left has flooded its whole piece; the flood stops when at most one label still has queued
    cells (that one's piece can meet no finished one), or fails when ``budget`` cells are queued. Writes
    ``out = (failed, distinct roots among the labels, cells queued)`` and leaves ``parent[i]`` the root of
    label ``i`` (the joins made so far, when it failed); ``mark`` (-1 outside the flood on
    entry) holds a label at every queued cell, which the caller resets."""
    labels = seeds.shape[0]
    for i in range(labels):
        parent[i] = i
        pending[i] = 1
        mark[seeds[i]] = i
        queue[i] = seeds[i]
    tail = labels
    active = labels
    head = int(0)
    failed = int(0)
    while head < tail and active > 1 and failed == 0:
        c = queue[head]
        head += 1
        r = _find_root(parent, mark[c])
        pending[r] -= 1
        if pending[r] == 0:
            active -= 1
        for j in range(4):
            fc = face_cells[cell_faces[c][j]]
            o = fc[0]
            if o == c:
                o = fc[1]
            if o >= 0:
                if cell_alive[o] != wp.uint8(0):
                    if mark[o] < 0:
                        if tail < budget:
                            mark[o] = r
                            queue[tail] = o
                            tail += 1
                            pending[r] += 1
                            if pending[r] == 1:
                                active += 1
                        else:
                            failed = 1
                    else:
                        s = _find_root(parent, mark[o])
                        if s != r:
                            was = int(0)
                            if pending[r] > 0:
                                was += 1
                            if pending[s] > 0:
                                was += 1
                            lo = wp.min(r, s)
                            hi = wp.max(r, s)
                            parent[hi] = lo
                            pending[lo] = pending[r] + pending[s]
                            pending[hi] = 0
                            now = int(0)
                            if pending[lo] > 0:
                                now = 1
                            active -= was - now
                            r = lo
    distinct = int(0)
    for i in range(labels):  # each label straight to its root (roots are lower: done first), roots counted
        parent[i] = parent[parent[i]]
        if parent[i] == i:
            distinct += 1
    out[0] = failed
    out[1] = distinct
    out[2] = tail


@wp.kernel(enable_backward=False)
def components_ranges_kernel(
    face_cells: wp.array(dtype=wp.vec2i),
    face_alive: wp.array(dtype=wp.uint8),
    ranges: int,
    offset: int,
    parent: wp.array(dtype=wp.int32),
    cross: wp.array(dtype=wp.int32),
    cross_count: wp.array(dtype=wp.int32),
):
    """Range ``r`` of ``ranges`` (one thread each, run side by side): its slice of ``parent`` reset, then
    joined through the live two-cell faces of its face range whose cells both lie in its cell range; the
    other such faces are listed in ``cross`` from the range's first face on (``cross_count[r]`` of them;
    joined after by :func:`components_cross_kernel`). The ranges touch disjoint slices of ``parent``."""
    r = wp.tid() + offset
    cells = parent.shape[0]
    faces = face_cells.shape[0]
    c0 = cells * r // ranges
    c1 = cells * (r + 1) // ranges
    for i in range(c0, c1):
        parent[i] = i
    f0 = faces * r // ranges
    n = int(0)
    for f in range(f0, faces * (r + 1) // ranges):
        if face_alive[f] != wp.uint8(0):
            a = face_cells[f][0]
            b = face_cells[f][1]
            if a >= 0 and b >= 0:  # noqa: SIM102 (a kernel does not short-circuit: parent[-1] would be read)
                if a >= c0 and a < c1 and b >= c0 and b < c1:
                    _join(parent, a, b)
                else:
                    cross[f0 + n] = f
                    n += 1
    cross_count[r] = n


@wp.kernel(enable_backward=False)
def components_cross_kernel(
    face_cells: wp.array(dtype=wp.vec2i),
    cross: wp.array(dtype=wp.int32),
    cross_count: wp.array(dtype=wp.int32),
    cell_alive: wp.array(dtype=wp.uint8),
    parent: wp.array(dtype=wp.int32),
    dense: wp.array(dtype=wp.int32),
    labels: wp.array(dtype=wp.int32),
):
    """The listed faces between ranges joined (one thread); then, with a non-empty ``labels``, the cells
    numbered in the order of their root, the lowest cell of each piece (-1 for dead cells)."""
    ranges = cross_count.shape[0]
    faces = face_cells.shape[0]
    for r in range(ranges):
        f0 = faces * r // ranges
        for k in range(cross_count[r]):
            f = cross[f0 + k]
            _join(parent, face_cells[f][0], face_cells[f][1])
    if labels.shape[0] == 0:
        return
    pieces = int(0)
    for i in range(parent.shape[0]):
        r = _find_root(parent, i)
        if r == i and cell_alive[i] != wp.uint8(0):
            pieces += 1
        dense[i] = pieces - 1
        labels[i] = -1
        if cell_alive[i] != wp.uint8(0):
            labels[i] = dense[r]


@wp.kernel(enable_backward=False)
def live_roots_kernel(parent: wp.array(dtype=wp.int32), cell_alive: wp.array(dtype=wp.uint8), ranges: int,
                      offset: int, counts: wp.array(dtype=wp.int32)):  # fmt: skip
    """The live roots (pieces) among range ``r``'s cells, in ``counts[r]`` (one thread per range)."""
    r = wp.tid() + offset
    cells = parent.shape[0]
    n = int(0)
    for i in range(cells * r // ranges, cells * (r + 1) // ranges):
        if parent[i] == i and cell_alive[i] != wp.uint8(0):
            n += 1
    counts[r] = n


def _row_kernels(width: int) -> tuple[wp.Kernel, wp.Kernel]:
    """The compaction's two kernels over rows of ``width`` int32 references, read and written as one vector
    each with the loop over the row unrolled (a loop over a 2-D array's row as long as its shape costs
    Warp's CPU code 3-4x as much): ``mark_used`` and ``remap_rows``."""
    row = _ROW_TYPES[width]

    def mark_used(refs, alive, offset, used):
        """1 in ``used`` at every entity a live row of ``refs`` names (threads that mark one write the same)."""
        i = wp.tid() + offset
        if alive[i] != wp.uint8(0):
            r = refs[i]
            for j in range(wp.static(width)):
                if r[j] >= 0:
                    used[r[j]] = wp.uint8(1)

    def remap_rows(refs, rows, index_map, offset, out):
        """Row ``i`` of ``out``: row ``rows[i]`` of ``refs`` through ``index_map`` (-1 stays -1)."""
        i = wp.tid() + offset
        r = refs[rows[i]]
        o = row()
        for j in range(wp.static(width)):
            v = int(-1)
            if r[j] >= 0:
                v = index_map[r[j]]
            o[j] = v
        out[i] = o

    # (the argument types given as objects: this module's annotations are strings, read without the closure)
    ints, flags = wp.array(dtype=wp.int32), wp.array(dtype=wp.uint8)
    mark_used.__annotations__ = {"refs": wp.array(dtype=row), "alive": flags, "offset": int, "used": flags}
    remap_rows.__annotations__ = {"refs": wp.array(dtype=row), "rows": ints, "index_map": ints, "offset": int,
                                  "out": wp.array(dtype=row)}  # fmt: skip
    mark_used = wp.kernel(mark_used, enable_backward=False, name=f"mark_used_rows{width}_kernel", module=__name__)
    remap_rows = wp.kernel(remap_rows, enable_backward=False, name=f"remap_rows{width}_kernel", module=__name__)
    return mark_used, remap_rows


#: the row vectors of the structure's reference columns, by width
_ROW_TYPES = {2: wp.vec2i, 3: wp.vec3i, 4: wp.vec4i, 6: vec6i}
#: per width, :func:`_row_kernels` (made here, with the module's other kernels, not when first used)
_ROW_KERNELS = {width: _row_kernels(width) for width in _ROW_TYPES}


@wp.kernel(enable_backward=False)
def rest_boxes_kernel(rest: wp.array(dtype=wp.vec3), cell_nodes: wp.array(dtype=wp.vec4i), offset: int,
                      lower: wp.array(dtype=wp.vec3), upper: wp.array(dtype=wp.vec3)):  # fmt: skip
    """Per cell: the box of its four nodes' rest positions."""
    c = wp.tid() + offset
    t = cell_nodes[c]
    lo = rest[t[0]]
    hi = lo
    for k in range(1, 4):
        lo = wp.min(lo, rest[t[k]])
        hi = wp.max(hi, rest[t[k]])
    lower[c] = lo
    upper[c] = hi


@wp.kernel(enable_backward=False)
def bucket_keys_kernel(lower: wp.array(dtype=wp.vec3), origin: wp.vec3, spacing: float, dims: wp.vec3i,
                       offset: int, keys: wp.array(dtype=wp.int32)):  # fmt: skip
    """Per cell: the bucket (x fastest) of its box's lower corner in the grid at ``origin``."""
    c = wp.tid() + offset
    d = (lower[c] - origin) / spacing
    x = wp.clamp(int(wp.floor(d[0])), 0, dims[0] - 1)
    y = wp.clamp(int(wp.floor(d[1])), 0, dims[1] - 1)
    z = wp.clamp(int(wp.floor(d[2])), 0, dims[2] - 1)
    keys[c] = (z * dims[1] + y) * dims[0] + x


@wp.kernel(enable_backward=False)
def counting_sort_kernel(keys: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32),
                         order: wp.array(dtype=wp.int32)):  # fmt: skip
    """One thread: the items in the order of their keys (stable), and each key's run ``start[k]..start[k+1]``
    (``start`` has one more slot than there are keys; it arrives zeroed)."""
    n = keys.shape[0]
    for i in range(n):
        start[keys[i] + 1] += 1
    for k in range(1, start.shape[0]):
        start[k] += start[k - 1]
    for i in range(n):  # each key's next free place: start[k] itself, moved on, then moved back
        k = keys[i]
        order[start[k]] = i
        start[k] += 1
    for k in range(start.shape[0] - 1, 0, -1):
        start[k] = start[k - 1]
    start[0] = 0


@wp.func
def _triple_key(a: int, b: int, c: int, n: wp.int64) -> wp.int64:
    """Order-free key of three node ids below ``n`` (``n**3 < 2**63``): the sorted triple in base ``n``."""
    lo = wp.min(a, wp.min(b, c))
    hi = wp.max(a, wp.max(b, c))
    mid = a + b + c - lo - hi
    return (wp.int64(lo) * n + wp.int64(mid)) * n + wp.int64(hi)


@wp.kernel(enable_backward=False)
def triple_keys_kernel(tri: wp.array(dtype=wp.vec3i), n: wp.int64, offset: int, keys: wp.array(dtype=wp.int64)):
    i = wp.tid() + offset
    keys[i] = _triple_key(tri[i][0], tri[i][1], tri[i][2], n)


@wp.kernel(enable_backward=False)
def new_cells_kernel(
    cells: wp.array(dtype=wp.vec4i),
    node_alive: wp.array(dtype=wp.uint8),
    n: wp.int64,
    table_keys: wp.array(dtype=wp.int64),
    table_values: wp.array(dtype=wp.int32),
    bits: int,
    bound: int,
    offset: int,
    bad: wp.array(dtype=wp.int32),
    face_keys: wp.array(dtype=wp.int64),
    edges: wp.array(dtype=wp.int32),
    edge_keys: wp.array(dtype=wp.int64),
):
    """Per new cell of a batch edit: 1 if a node is missing or dead, 2 if a node repeats (else 0); the keys
    of its four faces (``n`` the key base, 0: none); its six edges found in the table (-1 missing) and the
    table's key of each missing one (:func:`edge_key`; -1 found)."""
    c = wp.tid() + offset
    t = cells[c]
    count = node_alive.shape[0]
    flag = int(0)
    for k in range(4):
        if t[k] < 0 or t[k] >= count:
            flag = 1
    if flag == 0:
        for k in range(4):
            if node_alive[t[k]] == wp.uint8(0):
                flag = 1
    if flag == 0:
        for k in range(4):
            for m in range(k + 1, 4):
                if t[k] == t[m]:
                    flag = 2
    bad[c] = flag
    for k in range(4):
        face_keys[4 * c + k] = wp.int64(-1)
        if flag == 0 and n > wp.int64(0):
            face_keys[4 * c + k] = _triple_key(t[TET_FACES_WP[k, 0]], t[TET_FACES_WP[k, 1]], t[TET_FACES_WP[k, 2]], n)
    for j in range(6):
        e = int(-1)
        key = wp.int64(-1)
        if flag == 0:
            a = t[TET_EDGES_WP[j, 0]]
            b = t[TET_EDGES_WP[j, 1]]
            if wp.max(a, b) < bound:  # a node at or above the bound has no edge yet
                e = edge_table_find(table_keys, table_values, bits, a, b)
            if e < 0:
                key = edge_key(a, b)
        edges[6 * c + j] = e
        edge_keys[6 * c + j] = key


@wp.kernel(enable_backward=False)
def edge_pairs_kernel(cells: wp.array(dtype=wp.vec4i), uses: wp.array(dtype=wp.int32), offset: int,
                      pairs: wp.array(dtype=wp.vec2i)):  # fmt: skip
    """The two nodes of edge use ``u`` (edge ``u % 6`` of new cell ``u // 6``, in its local order)."""
    i = wp.tid() + offset
    u = uses[i]
    t = cells[u // 6]
    pairs[i] = wp.vec2i(t[TET_EDGES_WP[u % 6, 0]], t[TET_EDGES_WP[u % 6, 1]])


@wp.kernel(enable_backward=False)
def group_keys_kernel(
    keys: wp.array(dtype=wp.int64),
    old: int,
    bits: int,
    table: wp.array(dtype=wp.int64),
    inverse: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    uses: wp.array(dtype=wp.int32),
    group_slot: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
):
    """Groups of equal non-negative keys, numbered in the order of their first occurrence (one thread, in
    order: deterministic), through an open-addressing table of ``2**bits`` slots, each a key and its group
    side by side (``table`` flat: one cache line a probe; every key EMPTY on entry and again on exit). Per
    key its group (``inverse``); per group the first of the keys from ``old`` on that is in it (``first``,
    counted from ``old``; a large value where none), how many of those are (``uses``) and its slot;
    ``count[0]`` the groups. A batch edit's face matching (the removed cells' faces, then the new cells'; a
    sort of the keys costs 2-3x this) and its missing edges. (Cut in two parts by hash, a thread each, it
    was no faster: the time goes to each key's random probe, not to the loop.)"""
    n = keys.shape[0]
    g = int(0)
    for i in range(n):
        key = keys[i]
        s = _pair_slot(table, bits, key)
        if table[2 * s] != key:
            table[2 * s] = key
            table[2 * s + 1] = wp.int64(g)
            first[g] = 2147483647
            uses[g] = 0
            group_slot[g] = s
            g += 1
        h = int(table[2 * s + 1])
        inverse[i] = h
        if i >= old:
            if uses[h] == 0:
                first[h] = i - old
            uses[h] = uses[h] + 1
    for j in range(g):
        table[2 * group_slot[j]] = _EMPTY_WP
    count[0] = g


@wp.kernel(enable_backward=False)
def new_faces_kernel(
    cells: wp.array(dtype=wp.vec4i),
    cell_edges: wp.array(dtype=vec6i),
    use: wp.array(dtype=wp.int32),
    offset: int,
    face_nodes: wp.array(dtype=wp.vec3i),
    face_edges: wp.array(dtype=wp.vec3i),
):
    """Nodes and edges of each created face from its first use (face ``k`` of a new cell: oriented as there;
    edge ``j`` joins its nodes ``j`` and ``j + 1``)."""
    i = wp.tid() + offset
    u = use[i]
    c = u // 4
    k = u - 4 * c
    t = cells[c]
    l0 = TET_FACES_WP[k, 0]
    l1 = TET_FACES_WP[k, 1]
    l2 = TET_FACES_WP[k, 2]
    face_nodes[i] = wp.vec3i(t[l0], t[l1], t[l2])
    ce = cell_edges[c]
    face_edges[i] = wp.vec3i(
        ce[TET_LOCAL_EDGE_WP[l0, l1]], ce[TET_LOCAL_EDGE_WP[l1, l2]], ce[TET_LOCAL_EDGE_WP[l2, l0]]
    )


@wp.kernel(enable_backward=False)
def link_new_cells_kernel(
    cell_faces: wp.array(dtype=wp.int32),
    inverse: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.int32),
    taken: wp.array(dtype=wp.int32),
    first_cell: int,
    offset: int,
    face_cells: wp.array(dtype=wp.int32),
):
    """Each use of a face by a new cell takes the face's next free slot: after its kept cell (``taken``),
    the face's first new use, then its second (``face_cells`` flat: two slots per face)."""
    i = wp.tid() + offset
    g = inverse[i]
    slot = wp.where(first[g] == i, 0, 1) + taken[g]
    face_cells[2 * cell_faces[i] + slot] = first_cell + i // 4


@wp.kernel(enable_backward=False)
def find_edges_kernel(
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
    bits: int,
    pairs: wp.array(dtype=wp.vec2i),
    offset: int,
    found: wp.array(dtype=wp.int32),
):
    i = wp.tid() + offset
    found[i] = edge_table_find(keys, values, bits, pairs[i][0], pairs[i][1])


# ---------------------------------------------------------------------------
# host helpers
# ---------------------------------------------------------------------------


def _group_sorted(keys: wp.array, count: int, device, threads) -> tuple[wp.array, int]:
    """Inclusive scan of run heads over ``count`` sorted keys (``i`` is in run ``groups[i] - 1``); number of runs."""
    heads = device_empty(count, wp.int32, device)
    launch(mark_heads_kernel, count, [keys], [heads], device, threads)
    groups = device_empty(count, wp.int32, device)
    if count == 0:
        return groups, 0
    wp.utils.array_scan(heads, groups, inclusive=True)
    # host sync: the number of distinct keys sizes the entity arrays
    return groups, int(groups[count - 1 : count].numpy()[0])


def csr(rows: wp.array, cols: wp.array, count: int, row_count: int, device, threads,
        order: wp.array | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """CSR of ``count`` (row, col) pairs (arrays of 2 ``count``, for the radix sort; ``cols`` None: the pair's
    index); lists keep col order. ``order``: on the CPU, an int32 array of ``count`` or more to write the
    sorted lists into (the returned lists are then a view of it; default: a new one).

    Rows are in ``[0, row_count]``; pairs of row ``row_count`` are left out
    (a dead entry's row). Sorting replaces the usual count / scan / fill on a
    GPU: filling needs an atomic cursor per row, and Warp's CPU atomics are
    not atomic across the concurrent range-split launches; the stable sort
    also leaves every list in ascending order, the same on every device. On
    the CPU the count / scan / fill runs on one thread
    (:func:`counting_sort_kernel`: stable too, so the lists are the same),
    which takes about a third of the radix sort's time (the element
    incidence of a 110K-tet mesh: 2.5 against 8 ms).
    """
    if not wp.get_device(device).is_cuda:
        if count == 0:
            return np.zeros(row_count + 1, dtype=np.int32), np.zeros(0, dtype=np.int32)
        start = device_empty(row_count + 2, wp.int32, device, zero=True)
        order = device_empty(count, wp.int32, device) if order is None else order[:count]
        wp.launch(counting_sort_kernel, 1, inputs=[rows[:count], start, order], device=device)
        off = start.numpy()[: row_count + 1]
        order = order.numpy()[: off[-1]]
        return off, order if cols is None else cols.numpy()[:count][order]
    if cols is None:
        cols = device_empty(2 * count, wp.int32, device)
        wp.copy(cols, wp.array(np.arange(count, dtype=np.int32), dtype=wp.int32, device=device), count=count)
    offsets = device_empty(row_count + 1, wp.int32, device)
    wp.utils.radix_sort_pairs(rows, cols, count)
    launch(lower_bound_kernel, row_count + 1, [rows, count], [offsets], device, threads)
    off = offsets.numpy()
    return off, cols.numpy()[: off[-1]].copy()


def _table_bits(live_edges: int) -> int:
    """log2 of the table size: at least four slots per edge (load <= 1/4 after a build, <= 1/2 ever)."""
    return max(4, int(4 * max(live_edges, 1) - 1).bit_length())


def _build_table(edge_nodes: wp.array, edge_alive: wp.array, live_edges: int, device) -> tuple:
    """The edge lookup table of the live edges: (keys (2^bits,) int64, values (2^bits,) int32, bits)."""
    bits = _table_bits(live_edges)
    keys = wp.full(1 << bits, EMPTY, dtype=wp.int64, device=device)
    values = wp.full(1 << bits, EMPTY, dtype=wp.int32, device=device)
    ids = np.flatnonzero(edge_alive.numpy()).astype(np.int32)
    _insert_edges(edge_nodes, ids, bits, keys, values, device)
    return keys.numpy(), values.numpy(), bits


def _insert_edges(edge_nodes: wp.array, ids: np.ndarray, bits: int, keys: wp.array, values: wp.array, device) -> None:
    """Put edges ``ids`` in the table ``keys``/``values`` (with room for them) in one kernel launch."""
    if len(ids):
        # Warp's CPU atomics are plain loads and stores: this launch must not be range-split across threads
        wp.launch(insert_edge_ids_kernel, dim=len(ids), device=device,
                  inputs=[edge_nodes, device_array(ids, wp.int32, device, copy=wp.get_device(device).is_cuda), bits,
                          keys, values])  # fmt: skip


def _face_keys(tri: np.ndarray, node_count: int) -> np.ndarray:
    """(F,) int64 order-free keys of (F, 3) node triples (unique for ``node_count < 2**21``, else a fallback)."""
    t = np.sort(np.asarray(tri, dtype=np.int64).reshape(-1, 3), axis=1)
    n = max(int(node_count), 1)
    if n < 1 << 21:
        return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]
    # rank the triples: equal triples get equal keys
    _, inverse = np.unique(t, axis=0, return_inverse=True)
    return inverse.astype(np.int64).ravel()


def _unique_first(keys: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``np.unique(keys, return_index=True, return_inverse=True)`` of non-negative int64 keys, by one value
    sort of ``key << b | position`` where that fits 63 bits (a value sort is several times faster than
    the argsort ``np.unique`` needs)."""
    bits = max(int(count - 1).bit_length(), 1)
    top = int(keys.max()) if len(keys) else 0
    if len(keys) == 0 or top.bit_length() + bits > 62:
        uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
        return uniq, first, inverse.ravel()
    packed = np.sort((keys << bits) | np.arange(len(keys), dtype=np.int64))
    k = packed >> bits
    pos = packed & ((1 << bits) - 1)
    heads = np.empty(len(k), dtype=bool)
    heads[0] = True
    np.not_equal(k[1:], k[:-1], out=heads[1:])
    inverse = np.empty(len(k), dtype=np.int64)
    inverse[pos] = np.cumsum(heads) - 1
    return k[heads], pos[heads], inverse


def _unique_inverse(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True)`` of 1-D int64 keys (the inverse flat): marks in a table where the
    keys are non-negative and below ``max(4 n, 2^16)``, else a value sort of ``key << b | position`` where
    that fits 63 bits, else one quicksort argsort (``np.unique`` with an inverse costs several times any of
    these on these sizes)."""
    keys = np.asarray(keys, dtype=np.int64).ravel()
    n = len(keys)
    if n == 0:
        return keys.copy(), np.zeros(0, dtype=np.int64)
    low, top = int(keys.min()), int(keys.max())
    if low >= 0 and top < max(4 * n, 1 << 16):  # keys of a small range (pairs of aggregates): marks, no sort
        present = np.zeros(top + 1, dtype=bool)
        present[keys] = True
        return np.flatnonzero(present), (np.cumsum(present) - 1)[keys]
    bits = max(int(n - 1).bit_length(), 1)
    heads = np.empty(n, dtype=bool)
    heads[0] = True
    inverse = np.empty(n, dtype=np.int64)
    if low >= 0 and top.bit_length() + bits <= 62:
        packed = np.sort((keys << bits) | np.arange(n, dtype=np.int64))
        k = packed >> bits
        np.not_equal(k[1:], k[:-1], out=heads[1:])
        inverse[packed & ((1 << bits) - 1)] = np.cumsum(heads) - 1
        return k[heads], inverse
    order = np.argsort(keys)
    k = keys[order]
    np.not_equal(k[1:], k[:-1], out=heads[1:])
    inverse[order] = np.cumsum(heads) - 1
    return k[heads], inverse


#: hash tables of :func:`_key_table` ((2^b, 2) int64: every key EMPTY, and its value), kept between the batch
#: edits' face groupings and the cuts' face pairings of any structure: a big table's fresh pages cost more
#: than the probes themselves
_KEY_TABLES: list[np.ndarray] = []


@contextlib.contextmanager
def _key_table(n: int, device="cpu"):
    """A hash table for ``n`` keys, every key EMPTY: ``(table, bits)``, ``table`` a flat int64 Warp array of
    at least ``2**bits`` slots (1.5-3 a key), each a key and its value side by side, of which the user probes
    only the first ``2**bits`` (:func:`_pair_slot`) and leaves every key EMPTY again. On the CPU it comes
    from :data:`_KEY_TABLES` (a larger one an earlier batch left: only its start is used, so a small batch's
    probes stay in cache) and goes back there when the block ends without an error; on CUDA it is new."""
    bits = max(int(n + n // 2).bit_length(), 4)
    if not wp.get_device(device).is_cpu:
        yield wp.full(2 << bits, EMPTY, dtype=wp.int64, device=device), bits
        return
    try:
        table = _KEY_TABLES.pop()
    except IndexError:  # (none free: this thread's first edit, or another thread's edit holds it)
        table = np.zeros((0, 2), dtype=np.int64)
    if len(table) < 1 << bits:
        table = np.full((1 << bits, 2), EMPTY, dtype=np.int64)
    yield host_array(table.reshape(-1), wp.int64), bits
    _KEY_TABLES.append(table)  # (not after an error: its keys may not be EMPTY)


def _group_keys(keys: np.ndarray, old: int = 0) -> tuple:
    """Groups of equal keys (``keys`` (n,) int64, non-negative; a batch edit's faces: the ``old`` faces of
    removed cells, then the new cells' four each; its missing edges), numbered in order of first occurrence
    (:func:`group_keys_kernel`, one CPU thread): (count, (n,) int32 group of each key, per group the first key
    from ``old`` on in it (counted from ``old``) and how many such keys it has), through a pooled
    :func:`_key_table`."""
    n = len(keys)
    inverse, first, uses, group_slot = (np.empty(n, dtype=np.int32) for _ in range(4))
    count = np.zeros(1, dtype=np.int32)
    if n:
        with _key_table(n) as (table, bits):
            wp.launch(group_keys_kernel, dim=1, device="cpu",
                      inputs=[host_array(np.ascontiguousarray(keys, dtype=np.int64), wp.int64), int(old), bits,
                              table, *[host_array(a, wp.int32) for a in (inverse, first, uses, group_slot,
                                                                          count)]])  # fmt: skip
    groups = int(count[0])
    return groups, inverse, first[:groups], uses[:groups]


def _connected(count: int, a: np.ndarray, b: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """Component labels of ``count`` items joined by pairs (a, b), numbered by lowest item; -1 where not alive.

    A sequential union-find (union by lower root, path halving) in one Warp
    kernel thread: near-linear, deterministic, and on these sizes (millions of
    pairs) a few milliseconds of compiled code where vectorized numpy hooking
    needs many passes.
    """
    parent = wp.array(np.arange(count, dtype=np.int32), dtype=wp.int32, device="cpu")
    a = np.ascontiguousarray(a, dtype=np.int32)
    b = np.ascontiguousarray(b, dtype=np.int32)
    if len(a):
        wp.launch(union_find_kernel, dim=1, device="cpu",
                  inputs=[host_array(a, wp.int32),
                          host_array(b, wp.int32), len(a), parent])  # fmt: skip
    roots = parent.numpy()
    alive = np.asarray(alive, dtype=bool)
    is_root = (roots == np.arange(count)) & alive
    dense = np.cumsum(is_root) - 1
    return np.where(alive, dense[roots], -1).astype(np.int32)


def _host_key(a: int, b: int) -> int:
    return (max(a, b) << 32) | min(a, b)


def _host_slot(key: int, bits: int) -> int:
    return ((key * _GOLDEN) & _MASK64) >> (64 - bits)


def _frozen(arr: np.ndarray) -> np.ndarray:
    view = arr.view()
    view.flags.writeable = False
    return view


def _remap(index_map: np.ndarray, refs: np.ndarray) -> np.ndarray:
    """``index_map[refs]`` with -1 kept as -1."""
    refs = np.asarray(refs)
    if not len(index_map):
        return np.full(refs.shape, -1, dtype=np.int32)
    return np.where(refs >= 0, index_map[np.maximum(refs, 0)], -1).astype(np.int32)


def _shared(values: np.ndarray, dtype=wp.int32, device="cpu") -> wp.array:
    """``values`` as a Warp array: its own memory on the CPU (no copy), a copy on CUDA."""
    return shared_array(values, dtype, device)


def _mark_used(used: np.ndarray, refs: np.ndarray, alive: np.ndarray) -> None:
    """``used[refs[alive]] = True`` (one kernel; ``used`` a bool array, written in place)."""
    width = refs.shape[1]
    launch(_ROW_KERNELS[width][0], len(refs),
           [_shared(refs, _ROW_TYPES[width]), _shared(alive.view(np.uint8), wp.uint8)],
           [_shared(used.view(np.uint8), wp.uint8)], "cpu", min_chunk=_CHEAP)  # fmt: skip


def _remap_rows(index_map: np.ndarray, refs: np.ndarray, rows: np.ndarray,
                out: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """:func:`_remap` of ``refs[rows]`` ((n, k) int32 refs, one kernel), written to ``out`` ((len(rows), k)
    int32, C-contiguous; new where None)."""
    if out is None:
        out = np.empty((len(rows), refs.shape[1]), dtype=np.int32)
    if len(rows):
        row = _ROW_TYPES[refs.shape[1]]
        launch(_ROW_KERNELS[refs.shape[1]][1], len(rows),
               [_shared(refs, row), _shared(rows), _shared(index_map.astype(np.int32, copy=False))],
               [_shared(out, row)], "cpu", min_chunk=_CHEAP)  # fmt: skip
    return out


class _RestCellGrid:
    """Cells ``[0, cells)`` bucketed by the grid cell of their rest box's lower corner (a uniform grid whose
    spacing is the largest box side, so a box meets a query box only if its corner's bucket is at most one
    bucket below the query's), sorted by bucket with each bucket's run (CSR): a query reads the runs of the
    buckets its boxes reach, each once."""

    def __init__(self, rest: np.ndarray, cell_nodes: np.ndarray, clock: int):
        self.clock, self.cells = clock, len(cell_nodes)
        cpu = wp.get_device("cpu")
        self.lower = np.empty((self.cells, 3), np.float32)
        self.upper = np.empty((self.cells, 3), np.float32)
        launch(rest_boxes_kernel, self.cells,
               [host_array(np.ascontiguousarray(rest, dtype=np.float32), wp.vec3),
                host_array(np.ascontiguousarray(cell_nodes, dtype=np.int32), wp.vec4i)],
               [host_array(self.lower, wp.vec3),
                host_array(self.upper, wp.vec3)], cpu, min_chunk=_CHEAP)  # fmt: skip
        if self.cells == 0:
            self.origin, self.spacing, self.dims = np.zeros(3), 1.0, np.ones(3, np.int64)
            self.order, self.start = np.zeros(0, np.int64), np.zeros(2, np.int64)
            return
        # (per column: numpy's reductions along the short axis of an (n, 3) array are several times slower)
        self.origin = np.array([self.lower[:, i].min() for i in range(3)], dtype=np.float64)
        top = np.array([self.upper[:, i].max() for i in range(3)], dtype=np.float64)
        span = np.maximum(top - self.origin, 0.0)
        # a bucket's side: the largest box side, or coarser where the cells are spread thin over their box
        # (clusters far apart): at most about four buckets per cell
        side = max(float((self.upper - self.lower).max()), 1e-12)
        side = max(side, float(np.prod(np.maximum(span, side)) / (4.0 * self.cells)) ** (1.0 / 3.0))
        while np.prod(np.floor(span / side) + 1) > 4 * self.cells + 64:
            side *= 1.25
        self.spacing = side
        self.dims = np.floor(span / self.spacing).astype(np.int64) + 1
        # (the grid has about as many buckets as cells at most: a bucket's side is the largest cell's)
        keys = wp.empty(self.cells, dtype=wp.int32, device=cpu)
        launch(bucket_keys_kernel, self.cells,
               [host_array(self.lower, wp.vec3), wp.vec3(*self.origin.tolist()),
                float(self.spacing), wp.vec3i(*self.dims.tolist())], [keys], cpu, min_chunk=_CHEAP)  # fmt: skip
        start = wp.zeros(int(np.prod(self.dims)) + 1, dtype=wp.int32, device=cpu)
        order = wp.empty(self.cells, dtype=wp.int32, device=cpu)
        wp.launch(counting_sort_kernel, dim=1, inputs=[keys, start, order], device=cpu)
        self.order, self.start = order.numpy().astype(np.int64), start.numpy().astype(np.int64)

    def _bucket(self, points: np.ndarray) -> np.ndarray:
        b = np.floor((np.asarray(points, np.float64) - self.origin) / self.spacing).astype(np.int64)
        return np.clip(b, 0, self.dims - 1)

    def _key(self, b: np.ndarray) -> np.ndarray:
        return (b[..., 2] * self.dims[1] + b[..., 1]) * self.dims[0] + b[..., 0]

    def query(self, lower: np.ndarray, upper: np.ndarray, most: int) -> np.ndarray | None:
        """The cells in the buckets that the boxes ``[lower[i], upper[i]]`` ((B, 3) each) reach, ascending:
        every cell whose box meets one of them, and some that do not; None if more than ``most``."""
        lower = np.asarray(lower, np.float64).reshape(-1, 3)
        upper = np.asarray(upper, np.float64).reshape(-1, 3)
        top = self.origin + self.dims * self.spacing
        inside = ~(rows_any(upper < self.origin) | rows_any(lower > top))
        lower, upper = lower[inside], upper[inside]
        if self.cells == 0 or len(lower) == 0:
            return np.zeros(0, np.int64)
        lo = self._bucket(lower - self.spacing)  # a box meeting the query has its corner's bucket here ...
        n = self._bucket(upper) - lo + 1  # ... up to the query's upper corner's
        count = n.prod(axis=1)
        if int(count.sum()) * self.cells > most * (len(self.start) - 1):  # about that many cells
            return None
        box = np.repeat(np.arange(len(lo)), count)  # every (box, bucket) pair
        k = np.arange(len(box)) - np.repeat(np.cumsum(count) - count, count)
        nb = n[box]
        offset = np.stack([k % nb[:, 0], (k // nb[:, 0]) % nb[:, 1], k // (nb[:, 0] * nb[:, 1])], axis=1)
        reached = np.zeros(len(self.start) - 1, dtype=bool)
        reached[self._key(lo[box] + offset)] = True
        buckets = np.flatnonzero(reached)
        first, last = self.start[buckets], self.start[buckets + 1]
        length = last - first
        total = int(length.sum())
        if total > most:
            return None
        at = np.repeat(first - np.cumsum(length) + length, length) + np.arange(total)
        return np.sort(self.order[at])


class _Store:
    """One entity kind as structure of arrays: slots ``[0, count)`` in use, capacity doubling.

    Slots past ``count`` are not initialized: every slot gets its values (or its column's fill) when it is
    taken, so growing copies only the slots in use and never writes the spare ones.
    """

    def __init__(self, columns: dict):
        self.columns = columns  # name -> (trailing shape, dtype, fill)
        self.count = 0
        self.arrays = {n: np.full((0, *shape), fill, dtype=dt) for n, (shape, dt, fill) in columns.items()}

    def load(self, **arrays) -> None:
        """Replace every column (all of the same length, which becomes the count; a missing one is filled).

        Capacity is twice the count: the spare slots are reserved address space, not memory (they are not
        written until taken), and the first cuts after a build then neither copy every column nor fault in
        fresh pages for the copy.
        """
        n = len(arrays["alive"])
        for name, column in self.fresh(n).items():
            if name in arrays:
                column[:] = np.asarray(arrays[name], dtype=column.dtype).reshape(column.shape)  # a copy: we own it
            else:
                column[:] = self.columns[name][2]

    def fresh(self, n: int) -> dict[str, np.ndarray]:
        """Replace every column by new, unwritten memory for ``n`` slots (the count) and as many spare ones
        (:meth:`load`); the ``[0, n)`` rows of each, for the caller to fill (a compaction writes its remapped
        rows straight into them). The old columns stay alive while the caller holds views of them."""
        self.count = n
        capacity = 2 * n + 16
        for name, (shape, dt, _) in self.columns.items():
            self.arrays[name] = np.empty((capacity, *shape), dtype=dt)
        return {name: column[:n] for name, column in self.arrays.items()}

    def _grow(self, size: int) -> None:
        for name, (shape, dt, _) in self.columns.items():
            grown = np.empty((size, *shape), dtype=dt)
            grown[: self.count] = self.arrays[name][: self.count]
            self.arrays[name] = grown

    def extend(self, n: int, **values) -> np.ndarray:
        """Append ``n`` slots at once (columns given as arrays of ``n`` rows, the rest filled); their indices."""
        start, capacity = self.count, len(self.arrays["alive"])
        if start + n > capacity:
            self._grow(max(16, 2 * capacity, start + n))
        for name, (_, _, fill) in self.columns.items():
            self.arrays[name][start : start + n] = values.get(name, fill)
        self.arrays["alive"][start : start + n] = True
        self.count = start + n
        return np.arange(start, start + n, dtype=np.int32)

    def append(self, **values) -> int:
        i = self.count
        capacity = len(self.arrays["alive"])
        if i == capacity:
            self._grow(max(16, 2 * capacity))
        for name, (_, _, fill) in self.columns.items():
            self.arrays[name][i] = values.get(name, fill)
        self.arrays["alive"][i] = True
        self.count = i + 1
        return i

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name][: self.count]


def _stores() -> dict:
    alive = ((), np.bool_, False)
    return {
        "node": _Store(
            {
                "rest": ((3,), np.float32, 0.0),
                "position": ((3,), np.float32, 0.0),
                "origin": ((), np.int8, 0),
                "alive": alive,
            }
        ),
        "edge": _Store({"nodes": ((2,), np.int32, -1), "alive": alive}),
        "face": _Store(
            {
                "nodes": ((3,), np.int32, -1),
                "edges": ((3,), np.int32, -1),
                "cells": ((2,), np.int32, -1),
                "alive": alive,
            }
        ),
        "cell": _Store(
            {
                "nodes": ((4,), np.int32, -1),
                "faces": ((4,), np.int32, -1),
                "edges": ((6,), np.int32, -1),
                "material": ((), np.int32, 0),
                "parent": ((), np.int32, -1),
                "alive": alive,
            }
        ),
    }


def _parent_store() -> _Store:
    """Cut state of the tets a blade stopped in (progressive cuts): one row per such parent tet.

    corners: its four nodes (positive); split: per local edge (TET_EDGES order) the split copies joined to
    the edge's local first and second end (-1 uncut); t: the split parameter from the first end; code: the
    6-bit cut-edge code; faces: the crack-front node of each face it fans (-1 none); centre: its cell-centre node.
    """
    return _Store(
        {
            "corners": ((4,), np.int32, -1),
            "split": ((6, 2), np.int32, -1),
            "t": ((6,), np.float32, -1.0),
            "code": ((), np.int32, 0),
            "faces": ((4,), np.int32, -1),
            "centre": ((), np.int32, -1),
            "alive": ((), np.bool_, False),
        }
    )


# ---------------------------------------------------------------------------
# views
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class NodeView:
    """A node of a :class:`TetStructure` (reads the structure's arrays; holds no data)."""

    structure: TetStructure = field(repr=False)  # its repr is several lines; the index says which
    index: int

    @property
    def alive(self) -> bool:
        return bool(self.structure.node_alive[self.index])

    @property
    def rest(self) -> np.ndarray:
        """(3,) rest position, model units."""
        return self.structure.node_rest[self.index]

    @property
    def position(self) -> np.ndarray:
        """(3,) current position, model units."""
        return self.structure.node_position[self.index]

    @property
    def edges(self) -> np.ndarray:
        """Incident live edges, sorted."""
        return self.structure.edges_of_node(self.index)


@dataclass(frozen=True)
class EdgeView:
    """An edge of a :class:`TetStructure`."""

    structure: TetStructure = field(repr=False)  # its repr is several lines; the index says which
    index: int

    @property
    def alive(self) -> bool:
        return bool(self.structure.edge_alive[self.index])

    @property
    def nodes(self) -> np.ndarray:
        return self.structure.edge_nodes[self.index]

    @property
    def faces(self) -> np.ndarray:
        """Incident live faces, sorted."""
        return self.structure.faces_of_edge(self.index)


@dataclass(frozen=True)
class FaceView:
    """A face of a :class:`TetStructure`."""

    structure: TetStructure = field(repr=False)  # its repr is several lines; the index says which
    index: int

    @property
    def alive(self) -> bool:
        return bool(self.structure.face_alive[self.index])

    @property
    def nodes(self) -> np.ndarray:
        return self.structure.face_nodes[self.index]

    @property
    def edges(self) -> np.ndarray:
        return self.structure.face_edges[self.index]

    @property
    def cells(self) -> np.ndarray:
        """The one or two live cells on its sides (none once they are removed)."""
        return self.structure.cells_of_face(self.index)


@dataclass(frozen=True)
class CellView:
    """A cell (tet) of a :class:`TetStructure`."""

    structure: TetStructure = field(repr=False)  # its repr is several lines; the index says which
    index: int

    @property
    def alive(self) -> bool:
        return bool(self.structure.cell_alive[self.index])

    @property
    def nodes(self) -> np.ndarray:
        return self.structure.cell_nodes[self.index]

    @property
    def faces(self) -> np.ndarray:
        return self.structure.cell_faces[self.index]

    @property
    def edges(self) -> np.ndarray:
        return self.structure.cell_edges[self.index]

    @property
    def material(self) -> int:
        return int(self.structure.cell_material[self.index])


# ---------------------------------------------------------------------------
# the structure
# ---------------------------------------------------------------------------


class TetStructure:
    """Nodes, edges, faces and cells with links both ways, edits, events and garbage collection.

    Build one with :meth:`from_tetmesh` (kernels) or start empty and insert.
    Array properties (``node_rest``, ``edge_nodes``, ``face_cells``, ...) are
    read-only views over every slot in use, dead ones included; edit through
    the methods, which keep every link correct and fire events.

    Example:
        >>> import numpy as np
        >>> from warpblob.mesh import TetMesh, TetStructure
        >>> s = TetStructure.from_tetmesh(TetMesh(np.eye(4, 3, k=-1), [[0, 1, 2, 3]]))
        >>> s.node_count, s.edge_count, s.face_count, s.cell_count
        (4, 6, 4, 1)
        >>> m1, m2, e = s.split_edge(s.find_edge(0, 1), 0.5)
        >>> s.node_rest[m1].tolist(), s.edge_nodes[e].tolist()
        ([0.5, 0.0, 0.0], [5, 1])
    """

    def __init__(self):
        self._stores = _stores()
        self._parents = _parent_store()
        self._observers: list[Callable[[str, str, int], None]] = []
        self._pending: dict[str, list[int]] = {k: [] for k in KINDS}
        self.last_remap: dict[str, np.ndarray] = {}
        self.stats: dict = {}
        #: grows on every change of the cells (insert, update, remove, compaction): a recorder's topology clock
        self.topology_version = 0
        # the piece count and the connectivity clock it was counted at (any cell or face event moves the clock)
        self._connectivity_version = 0
        self._flood_mark = None  # (capacity,) int32 scratch of the pieces' flood, -1 between floods
        self._pieces: tuple[int, int] | None = None
        # the cells' rest boxes in a uniform grid (cutting's local search), and the clock it was built at
        # (a cell's nodes or a rest position changed, or a compaction, moves the clock)
        self._rest_clock = 0
        self._rest_grid: _RestCellGrid | None = None
        self._table_keys = np.full(16, EMPTY, dtype=np.int64)
        self._table_values = np.full(16, EMPTY, dtype=np.int32)
        self._table_bits = 4
        self._table_used = 0  # live keys plus deleted slots
        self._table_node_bound = 0  # every node of a key in the table is below this (a node above has no edge)
        # every edge slot is used by a live cell (after a build or a compaction, until an edge is inserted
        # alone or a cell removed or changed): lets a cut skip its pass marking the edges in use
        self._edges_used = False
        # the cells that are pieces of a progressive-cut record, ascending (None: to be found by a pass)
        self._parented: np.ndarray | None = np.zeros(0, dtype=np.int32)
        self._clear_links()

    def _clear_links(self) -> None:
        self._node_edge_offsets = np.zeros(1, dtype=np.int32)
        self._node_edge_list = np.zeros(0, dtype=np.int32)
        self._edge_face_offsets = np.zeros(1, dtype=np.int32)
        self._edge_face_list = np.zeros(0, dtype=np.int32)
        self._new_node_edges: dict[int, set[int]] = {}
        self._new_edge_faces: dict[int, set[int]] = {}
        self._links_dirty = False
        self._links_stale = False  # a batch edit left the CSR lists behind: rebuild before using them

    # -- construction --------------------------------------------------------

    @classmethod
    def from_tetmesh(cls, tetmesh: TetMesh, *, device=None, threads: int | None = None) -> TetStructure:
        """Build every entity and link of ``tetmesh`` with Warp kernels.

        Edges: each tet emits the keys of its six edges, a radix sort groups
        equal keys, a scan of run heads numbers them. Faces: likewise with the
        key ``(edge of the two smallest nodes) << 32 | largest node``; the
        first tet of each group (the sort is stable) orients the face. Then the
        CSR links and the edge hash table (:meth:`rebuild_links`).

        Args:
            tetmesh: a conforming mesh (a face in three tets is an error).
            device: Warp device for the build (default: Warp's default device);
                the result lives on the host either way.
            threads: CPU threads (default: :func:`warpblob.thread_count`).

        Raises:
            WarpblobError: a face is shared by more than two tets.
        """

        start = time.perf_counter()
        dev = resolve_device(device)
        s = cls()
        T, N = tetmesh.tet_count, tetmesh.node_count
        tets = wp.array(tetmesh.tets, dtype=wp.vec4i, device=dev)

        keys = wp.empty(12 * T, dtype=wp.int64, device=dev)
        occurrences = wp.empty(12 * T, dtype=wp.int32, device=dev)
        launch(emit_edge_keys_kernel, T, [tets], [keys, occurrences], dev, threads)
        wp.utils.radix_sort_pairs(keys, occurrences, 6 * T)
        groups, E = _group_sorted(keys, 6 * T, dev, threads)
        edge_nodes = wp.empty(E, dtype=wp.vec2i, device=dev)
        cell_edges = wp.empty(6 * T, dtype=wp.int32, device=dev)
        launch(emit_edges_kernel, 6 * T, [keys, groups, occurrences], [edge_nodes, cell_edges], dev, threads)

        keys = wp.empty(8 * T, dtype=wp.int64, device=dev)
        occurrences = wp.empty(8 * T, dtype=wp.int32, device=dev)
        launch(emit_face_keys_kernel, T, [tets, cell_edges], [keys, occurrences], dev, threads)
        wp.utils.radix_sort_pairs(keys, occurrences, 4 * T)
        groups, F = _group_sorted(keys, 4 * T, dev, threads)
        face_nodes = wp.empty(F, dtype=wp.vec3i, device=dev)
        face_edges = wp.empty(F, dtype=wp.vec3i, device=dev)
        face_first = wp.empty(F, dtype=wp.int32, device=dev)
        cell_faces = wp.empty(4 * T, dtype=wp.int32, device=dev)
        launch(
            emit_faces_kernel, 4 * T, [tets, cell_edges, groups, occurrences],
            [face_nodes, face_edges, face_first, cell_faces], dev, threads,
        )  # fmt: skip
        face_cells = wp.full(2 * F, -1, dtype=wp.int32, device=dev)
        launch(link_face_cells_kernel, 4 * T, [groups, occurrences, face_first], [face_cells], dev, threads)
        sizes = np.diff(np.append(face_first.numpy(), 4 * T))
        if np.any(sizes > 2):
            f = int(np.argmax(sizes))
            raise WarpblobError(
                f"TetStructure.from_tetmesh: face {face_nodes.numpy()[f].tolist()} is shared by {sizes[f]} tets; "
                "a tet mesh face has one or two"
            )

        s._stores["node"].load(rest=tetmesh.nodes, position=tetmesh.nodes, alive=np.ones(N, dtype=bool))
        s._stores["edge"].load(nodes=edge_nodes.numpy(), alive=np.ones(E, dtype=bool))
        s._stores["face"].load(
            nodes=face_nodes.numpy(), edges=face_edges.numpy(), cells=face_cells.numpy(), alive=np.ones(F, dtype=bool)
        )
        material = tetmesh.material if tetmesh.material is not None else np.zeros(T, dtype=np.int32)
        s._stores["cell"].load(
            nodes=tetmesh.tets,
            faces=cell_faces.numpy(),
            edges=cell_edges.numpy(),
            material=material,
            alive=np.ones(T, dtype=bool),
        )
        s._rebuild(dev, threads)
        s._edges_used = True  # the edges are those of the cells
        # what a cut needs of the whole mesh, once: its pieces, and the grid of the cells' rest boxes in which
        # it finds the cells near its sweep (a few percent of the build)
        s._rest_grid = _RestCellGrid(s._stores["node"]["rest"], s._stores["cell"]["nodes"], s._rest_clock)
        s._remember_pieces(s._components(False)[1])
        s.stats = {"seconds": time.perf_counter() - start, "device": str(dev)}
        return s

    def rebuild_links(self, *, device=None, threads: int | None = None) -> None:
        """Rebuild the bottom-up CSR links and the edge hash table from the top-down links (kernels).

        Drops the Python-side record of incidences added since the last
        rebuild. :meth:`collect_garbage` and :meth:`to_warp` call it as needed.
        """

        self._rebuild(resolve_device(device), threads)

    def _rebuild(self, dev, threads) -> None:
        edges, faces = self._stores["edge"], self._stores["face"]
        E, F, N = edges.count, faces.count, self._stores["node"].count
        edge_nodes = wp.array(edges["nodes"], dtype=wp.vec2i, device=dev)
        edge_alive = wp.array(edges["alive"].view(np.uint8), dtype=wp.uint8, device=dev)
        face_edges = wp.array(faces["edges"], dtype=wp.vec3i, device=dev)
        face_alive = wp.array(faces["alive"].view(np.uint8), dtype=wp.uint8, device=dev)
        self._clear_links()

        rows = wp.empty(4 * E, dtype=wp.int32, device=dev)
        cols = wp.empty(4 * E, dtype=wp.int32, device=dev)
        launch(emit_node_edges_kernel, E, [edge_nodes, edge_alive, N], [rows, cols], dev, threads)
        self._node_edge_offsets, self._node_edge_list = csr(rows, cols, 2 * E, N, dev, threads)

        rows = wp.empty(6 * F, dtype=wp.int32, device=dev)
        cols = wp.empty(6 * F, dtype=wp.int32, device=dev)
        launch(emit_edge_faces_kernel, F, [face_edges, face_alive, E], [rows, cols], dev, threads)
        self._edge_face_offsets, self._edge_face_list = csr(rows, cols, 3 * F, E, dev, threads)

        self._build_table(dev, edge_nodes, edge_alive)

    def _build_table(self, dev, edge_nodes: wp.array | None = None, edge_alive: wp.array | None = None,
                     extra: int = 0) -> None:  # fmt: skip
        """The lookup table built anew from the live edges, sized for ``extra`` more to come."""
        edges = self._stores["edge"]
        if edge_nodes is None:
            edge_nodes = wp.array(edges["nodes"], dtype=wp.vec2i, device=dev)
            edge_alive = wp.array(edges["alive"].view(np.uint8), dtype=wp.uint8, device=dev)
        live = int(np.count_nonzero(edges["alive"]))
        self._table_keys, self._table_values, self._table_bits = _build_table(edge_nodes, edge_alive, live + extra,
                                                                              dev)  # fmt: skip
        self._table_used = live
        nodes = edges["nodes"]
        self._table_node_bound = int(nodes.max()) + 1 if len(nodes) else 0

    # -- array views ----------------------------------------------------------

    def _view(self, kind: str, column: str) -> np.ndarray:
        return _frozen(self._stores[kind][column])

    node_rest = property(lambda self: self._view("node", "rest"), doc="(N, 3) float32 rest positions.")
    node_position = property(lambda self: self._view("node", "position"), doc="(N, 3) float32 current positions.")
    node_alive = property(lambda self: self._view("node", "alive"), doc="(N,) bool.")
    node_origin = property(
        lambda self: self._view("node", "origin"),
        doc="(N,) int8 how each node was made: 0 the model's, 1 a split point, 2 a cut node (snapped onto a "
        "cut) or its copy, 3 a crack front point (:data:`NODE_ORIGINS`).",
    )
    edge_nodes = property(lambda self: self._view("edge", "nodes"), doc="(E, 2) int32 nodes of each edge.")
    edge_alive = property(lambda self: self._view("edge", "alive"), doc="(E,) bool.")
    face_nodes = property(lambda self: self._view("face", "nodes"), doc="(F, 3) int32 nodes of each face.")
    face_edges = property(lambda self: self._view("face", "edges"), doc="(F, 3) int32; edge j joins nodes j, j+1.")
    face_cells = property(lambda self: self._view("face", "cells"), doc="(F, 2) int32 cells on its sides, -1 none.")
    face_alive = property(lambda self: self._view("face", "alive"), doc="(F,) bool.")
    cell_nodes = property(lambda self: self._view("cell", "nodes"), doc="(C, 4) int32 nodes, positive order.")
    cell_faces = property(lambda self: self._view("cell", "faces"), doc="(C, 4) int32; face k opposite node k.")
    cell_edges = property(lambda self: self._view("cell", "edges"), doc="(C, 6) int32 in TET_EDGES order.")
    cell_material = property(lambda self: self._view("cell", "material"), doc="(C,) int32 material ids.")
    cell_alive = property(lambda self: self._view("cell", "alive"), doc="(C,) bool.")
    cell_parent = property(
        lambda self: self._view("cell", "parent"),
        doc="(C,) int32 the progressive-cut record (a tet a blade stopped in) each cell is a piece of, -1 none.",
    )

    def _count(self, kind: str) -> int:
        return int(np.count_nonzero(self._stores[kind]["alive"]))

    node_count = property(lambda self: self._count("node"), doc="Live nodes.")
    edge_count = property(lambda self: self._count("edge"), doc="Live edges.")
    face_count = property(lambda self: self._count("face"), doc="Live faces.")
    cell_count = property(lambda self: self._count("cell"), doc="Live cells.")

    def ids(self, kind: str) -> np.ndarray:
        """Indices (int32, ascending) of the live entities of ``kind`` ("node", "edge", "face" or "cell")."""
        self._check_kind(kind)
        return np.flatnonzero(self._stores[kind]["alive"]).astype(np.int32)

    def node(self, index: int) -> NodeView:
        return NodeView(self, self._check(index, "node", alive=False))

    def edge(self, index: int) -> EdgeView:
        return EdgeView(self, self._check(index, "edge", alive=False))

    def face(self, index: int) -> FaceView:
        return FaceView(self, self._check(index, "face", alive=False))

    def cell(self, index: int) -> CellView:
        return CellView(self, self._check(index, "cell", alive=False))

    @property
    def pending(self) -> dict[str, tuple[int, ...]]:
        """Entities removed since the last :meth:`collect_garbage`, per kind."""
        return {k: tuple(v) for k, v in self._pending.items()}

    def __repr__(self) -> str:
        pending = sum(len(v) for v in self._pending.values())
        alive = self._stores["node"]["alive"]
        return (
            f"TetStructure: {self.node_count:,} nodes, {self.edge_count:,} edges, {self.face_count:,} faces, "
            f"{self.cell_count:,} cells (live; {pending:,} removals pending)\n"
            + bounds_text(self._stores["node"]["position"][alive])
        )

    # -- checks -----------------------------------------------------------------

    @staticmethod
    def _check_kind(kind: str) -> None:
        if kind not in KINDS:
            raise WarpblobError(f"TetStructure: kind must be one of {', '.join(KINDS)}, got {kind!r}")

    def _check(self, index, kind: str, *, alive: bool = True) -> int:
        store = self._stores[kind]
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)):
            raise WarpblobError(f"TetStructure: {kind} index must be an integer, got {index!r}")
        i = int(index)
        if not 0 <= i < store.count:
            raise WarpblobError(f"TetStructure: {kind} {i} does not exist ({store.count} {kind} slots)")
        if alive and not store.arrays["alive"][i]:
            raise WarpblobError(f"TetStructure: {kind} {i} was removed")
        return i

    def _check_nodes(self, nodes, count: int) -> list[int]:
        ids = [self._check(n, "node") for n in nodes]
        if len(ids) != count or len(set(ids)) != count:
            raise WarpblobError(f"TetStructure: need {count} distinct live nodes, got {list(nodes)!r}")
        return ids

    @staticmethod
    def _point(value, name: str) -> np.ndarray:
        p = np.asarray(value, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise WarpblobError(f"TetStructure: {name} must be 3 finite numbers, got {value!r}")
        return p.astype(np.float32)

    # -- events -------------------------------------------------------------------

    def subscribe(self, callback: Callable[[str, str, int], None]) -> Callable[[str, str, int], None]:
        """Call ``callback(kind, action, index)`` on every change; returns ``callback``.

        ``kind`` is "node", "edge", "face" or "cell"; ``action`` is "insert",
        "update" or "remove" (``index`` the entity), or "compact" after
        :meth:`collect_garbage` (``index`` the live count; the old -> new map is
        ``last_remap[kind]``). Linking a cell to a face's cell slots is part of
        the cell's event, not a face update.
        """
        self._observers.append(callback)
        return callback

    def unsubscribe(self, callback) -> None:
        """Stop calling ``callback``."""
        self._observers.remove(callback)

    def _emit(self, kind: str, action: str, index: int) -> None:
        if kind == "cell" or action == "compact":
            self.topology_version += 1
        if kind in ("cell", "face") or action == "compact":
            self._connectivity_version += 1
        if (kind == "cell" and action == "update") or action == "compact":
            self._rest_clock += 1
        if kind != "node" and (action in ("remove", "update") or (kind == "edge" and action == "insert")):
            self._edges_used = False
        for callback in list(self._observers):
            callback(kind, action, index)

    # -- lookups and bottom-up links ------------------------------------------------

    @staticmethod
    def edge_key(a: int, b: int) -> int:
        """The 64-bit key ``(max << 32) | min`` of the edge joining nodes ``a`` and ``b``."""
        return _host_key(int(a), int(b))

    def find_edge(self, a: int, b: int) -> int:
        """The live edge joining nodes ``a`` and ``b`` (either order), or -1; O(1) expected."""
        key = _host_key(int(a), int(b))
        mask = (1 << self._table_bits) - 1
        s = _host_slot(key, self._table_bits)
        keys = self._table_keys
        while keys[s] != EMPTY:
            if keys[s] == key:
                return int(self._table_values[s])
            s = (s + 1) & mask
        return -1

    def find_edges(self, pairs, *, device=None, threads: int | None = None) -> np.ndarray:
        """Batch :meth:`find_edge` in a kernel: (M, 2) node pairs -> (M,) int32 edges, -1 where none."""

        pairs = np.ascontiguousarray(pairs, dtype=np.int32).reshape(-1, 2)
        dev = resolve_device(device)
        found = device_empty(len(pairs), wp.int32, dev)
        copy = dev.is_cuda  # on the CPU the kernel reads the table's own memory
        inputs = [
            device_array(self._table_keys, wp.int64, dev, copy=copy),
            device_array(self._table_values, wp.int32, dev, copy=copy),
            self._table_bits,
            device_array(pairs, wp.vec2i, dev, copy=copy),
        ]
        launch(find_edges_kernel, len(pairs), inputs, [found], dev, threads)
        return found.numpy()

    def find_face(self, a: int, b: int, c: int) -> int:
        """The live face on nodes ``a``, ``b``, ``c`` (any order), or -1 (through the faces of edge a-b)."""
        e = self.find_edge(a, b)
        if e < 0:
            return -1
        want = sorted((int(a), int(b), int(c)))
        nodes = self._stores["face"]["nodes"]
        for f in self.faces_of_edge(e):
            if sorted(nodes[f].tolist()) == want:
                return int(f)
        return -1

    def _incident(self, i: int, offsets, lists, added: dict, owner: np.ndarray, alive: np.ndarray) -> np.ndarray:
        base = lists[offsets[i] : offsets[i + 1]] if i + 1 < len(offsets) else lists[:0]
        extra = added.get(i)
        candidates = np.concatenate([base, np.fromiter(extra, dtype=np.int32, count=len(extra))]) if extra else base
        keep = alive[candidates] & (owner[candidates] == i).any(axis=1)
        return np.unique(candidates[keep]).astype(np.int32)

    def _fresh_links(self) -> None:
        if self._links_stale:
            self._rebuild(wp.get_device("cpu"), None)

    def edges_of_node(self, node: int) -> np.ndarray:
        """Live edges incident to ``node``, sorted (int32)."""
        v = self._check(node, "node", alive=False)
        self._fresh_links()
        edges = self._stores["edge"]
        return self._incident(
            v, self._node_edge_offsets, self._node_edge_list, self._new_node_edges, edges["nodes"], edges["alive"]
        )

    def faces_of_edge(self, edge: int) -> np.ndarray:
        """Live faces incident to ``edge``, sorted (int32)."""
        e = self._check(edge, "edge", alive=False)
        self._fresh_links()
        faces = self._stores["face"]
        return self._incident(
            e, self._edge_face_offsets, self._edge_face_list, self._new_edge_faces, faces["edges"], faces["alive"]
        )

    def cells_of_face(self, face: int) -> np.ndarray:
        """The live cells on the sides of ``face`` (0, 1 or 2; int32)."""
        f = self._check(face, "face", alive=False)
        cells = self._stores["face"]["cells"][f]
        return cells[cells >= 0].copy()

    def one_ring(self, node: int) -> np.ndarray:
        """Nodes joined to ``node`` by a live edge, sorted (int32)."""
        return self.k_ring(node, 1)

    def k_ring(self, node: int, k: int) -> np.ndarray:
        """Nodes within ``k`` edges of ``node`` (breadth-first search), itself excluded, sorted (int32)."""
        v = self._check(node, "node")
        if not isinstance(k, (int, np.integer)) or k < 0:
            raise WarpblobError(f"TetStructure.k_ring: k must be a non-negative integer, got {k!r}")
        edge_nodes = self._stores["edge"]["nodes"]
        seen = {v}
        frontier = [v]
        for _ in range(int(k)):
            following = []
            for u in frontier:
                for w in edge_nodes[self.edges_of_node(u)].ravel().tolist():
                    if w not in seen:
                        seen.add(w)
                        following.append(w)
            frontier = following
        seen.discard(v)
        return np.array(sorted(seen), dtype=np.int32)

    # -- hash table edits -----------------------------------------------------------

    def _table_insert(self, key: int, edge: int) -> None:
        if 2 * (self._table_used + 1) > len(self._table_keys):
            # too full (deleted slots count): rebuild with room, this edge included
            self._build_table("cpu")
            if self.find_edge(key >> 32, key & 0xFFFFFFFF) == edge:
                return
        mask = (1 << self._table_bits) - 1
        s = _host_slot(key, self._table_bits)
        while self._table_keys[s] >= 0:
            s = (s + 1) & mask
        if self._table_keys[s] == EMPTY:
            self._table_used += 1
        self._table_keys[s] = key
        self._table_values[s] = edge
        self._table_node_bound = max(self._table_node_bound, (key >> 32) + 1)

    def _remap_table(self, edge_map: np.ndarray, live: int) -> bool:
        """After a compaction that kept every node's index (a cut's, which makes nodes and removes none),
        the lookup table follows it in place: the keys (node pairs) keep their slots, the values go through
        ``edge_map`` and a removed edge's slot is marked deleted, one pass over the slots instead of a
        rebuild (which inserts every live edge again, one thread, into fresh memory: 3x the time at 1M
        tets). False, and nothing changed, where a rebuild is due: the table is more than half full of keys
        and deleted slots (the bound every insert keeps), or more than four times the size a build gives
        ``live`` edges (a build leaves it 1/8 to 1/4 full)."""
        if 2 * self._table_used > len(self._table_keys) or self._table_bits > _table_bits(live) + 2:
            return False
        launch(remap_table_kernel, len(self._table_keys), [host_array(edge_map.astype(np.int32, copy=False),
               wp.int32)], [host_array(self._table_keys, wp.int64), host_array(self._table_values, wp.int32)],
               "cpu", min_chunk=_CHEAP)  # fmt: skip
        return True

    def _table_remove(self, key: int) -> None:
        mask = (1 << self._table_bits) - 1
        s = _host_slot(key, self._table_bits)
        while self._table_keys[s] != key:
            if self._table_keys[s] == EMPTY:
                raise WarpblobError(f"TetStructure: edge key {key:#x} is not in the lookup table")
            s = (s + 1) & mask
        self._table_keys[s] = DELETED
        self._table_values[s] = EMPTY

    # -- inserts ---------------------------------------------------------------------

    def insert_node(self, rest, position=None) -> int:
        """A new node at ``rest`` (current position ``position``, default ``rest``); returns its index."""
        r = self._point(rest, "rest")
        p = r if position is None else self._point(position, "position")
        i = self._stores["node"].append(rest=r, position=p)
        self._emit("node", "insert", i)
        return i

    def insert_edge(self, a: int, b: int) -> int:
        """A new edge from node ``a`` to node ``b``; returns its index.

        Raises:
            WarpblobError: a node is missing or removed, ``a == b``, or the edge exists.
        """
        a, b = self._check_nodes((a, b), 2)
        e = self.find_edge(a, b)
        if e >= 0:
            raise WarpblobError(f"TetStructure.insert_edge: nodes {a} and {b} are already joined by edge {e}")
        i = self._stores["edge"].append(nodes=(a, b))
        self._table_insert(_host_key(a, b), i)
        self._note_edge(i, a, b)
        self._emit("edge", "insert", i)
        return i

    def _note_edge(self, e: int, a: int, b: int) -> None:
        self._new_node_edges.setdefault(a, set()).add(e)
        self._new_node_edges.setdefault(b, set()).add(e)
        self._links_dirty = True

    def _edge_for(self, a: int, b: int) -> int:
        e = self.find_edge(a, b)
        return e if e >= 0 else self.insert_edge(a, b)

    def insert_face(self, a: int, b: int, c: int) -> int:
        """A new face ``(a, b, c)``, inserting its missing edges; returns its index.

        Raises:
            WarpblobError: a node is missing, removed or repeated, or the face exists.
        """
        nodes = self._check_nodes((a, b, c), 3)
        f = self.find_face(*nodes)
        if f >= 0:
            raise WarpblobError(f"TetStructure.insert_face: nodes {nodes} already make face {f}")
        edges = [self._edge_for(nodes[j], nodes[(j + 1) % 3]) for j in range(3)]
        i = self._stores["face"].append(nodes=nodes, edges=edges)
        self._note_face(i, edges)
        self._emit("face", "insert", i)
        return i

    def _note_face(self, f: int, edges) -> None:
        for e in edges:
            self._new_edge_faces.setdefault(int(e), set()).add(f)
        self._links_dirty = True

    def _cell_faces_for(self, nodes: list[int], cell: int = -1) -> list[int]:
        """Check that each face of a cell on ``nodes`` has a free side (``cell`` itself may hold one)."""
        faces = []
        for k in range(4):
            f = self.find_face(*(nodes[j] for j in TET_FACES[k]))
            if f >= 0:
                others = [c for c in self._stores["face"]["cells"][f] if c >= 0 and c != cell]
                if len(others) == 2:
                    raise WarpblobError(
                        f"TetStructure: face {f} {self._stores['face']['nodes'][f].tolist()} already has two cells"
                    )
            faces.append(f)
        return faces

    def _link_cell(self, c: int, nodes: list[int], found: list[int]) -> None:
        """Find or insert the faces and edges of cell ``c`` on ``nodes`` and link it to its faces."""
        cells = self._stores["cell"]
        faces = [f if f >= 0 else self.insert_face(*(nodes[j] for j in TET_FACES[k])) for k, f in enumerate(found)]
        face_cells = self._stores["face"].arrays["cells"]
        for f in faces:
            slot = 0 if face_cells[f, 0] < 0 else 1
            face_cells[f, slot] = c
        cells.arrays["nodes"][c] = nodes
        cells.arrays["faces"][c] = faces
        cells.arrays["edges"][c] = [self.find_edge(nodes[i], nodes[j]) for i, j in TET_EDGES]

    def _unlink_cell(self, c: int) -> None:
        face_cells = self._stores["face"].arrays["cells"]
        for f in self._stores["cell"]["faces"][c]:
            if face_cells[f, 0] == c:
                face_cells[f] = (face_cells[f, 1], -1)
            elif face_cells[f, 1] == c:
                face_cells[f, 1] = -1

    def insert_cell(self, a: int, b: int, c: int, d: int, *, material: int = 0) -> int:
        """A new cell on nodes ``(a, b, c, d)`` (positive orientation is the caller's duty).

        Missing faces and edges are inserted (with their events, before the
        cell's); existing faces get the cell in their free slot.

        Raises:
            WarpblobError: a node is missing, removed or repeated, or a face
                already has a cell on both sides.
        """
        nodes = self._check_nodes((a, b, c, d), 4)
        found = self._cell_faces_for(nodes)
        i = self._stores["cell"].append(material=int(material))
        self._link_cell(i, nodes, found)
        self._emit("cell", "insert", i)
        return i

    # -- updates -------------------------------------------------------------------------

    def update_node(self, node: int, *, rest=None, position=None) -> None:
        """Move node ``node`` (rest and/or current position)."""
        v = self._check(node, "node")
        store = self._stores["node"].arrays
        if rest is not None:
            store["rest"][v] = self._point(rest, "rest")
            self._rest_clock += 1
        if position is not None:
            store["position"][v] = self._point(position, "position")
        self._emit("node", "update", v)

    def update_edge(self, edge: int, a: int, b: int) -> None:
        """Make edge ``edge`` join nodes ``a`` and ``b`` (faces using it are the caller's business).

        Raises:
            WarpblobError: the edge or a node is missing or removed, or another
                edge joins ``a`` and ``b``.
        """
        e = self._check(edge, "edge")
        a, b = self._check_nodes((a, b), 2)
        other = self.find_edge(a, b)
        if other >= 0 and other != e:
            raise WarpblobError(f"TetStructure.update_edge: nodes {a} and {b} are already joined by edge {other}")
        old = self._stores["edge"]["nodes"][e].tolist()
        self._stores["edge"].arrays["nodes"][e] = (a, b)
        if other != e:
            self._table_remove(_host_key(*old))
            self._table_insert(_host_key(a, b), e)
        self._note_edge(e, a, b)
        self._emit("edge", "update", e)

    def update_face(self, face: int, a: int, b: int, c: int) -> None:
        """Make face ``face`` span nodes ``(a, b, c)``, inserting missing edges (its cells are the caller's)."""
        f = self._check(face, "face")
        nodes = self._check_nodes((a, b, c), 3)
        other = self.find_face(*nodes)
        if other >= 0 and other != f:
            raise WarpblobError(f"TetStructure.update_face: nodes {nodes} already make face {other}")
        edges = [self._edge_for(nodes[j], nodes[(j + 1) % 3]) for j in range(3)]
        store = self._stores["face"].arrays
        store["nodes"][f] = nodes
        store["edges"][f] = edges
        self._note_face(f, edges)
        self._emit("face", "update", f)

    def update_cell(self, cell: int, a: int, b: int, c: int, d: int, *, material: int | None = None) -> None:
        """Give cell ``cell`` new nodes (and material): it leaves its old faces and joins (or makes) the new ones.

        Faces it leaves stay, for :meth:`collect_garbage` to purge once unused.
        """
        i = self._check(cell, "cell")
        nodes = self._check_nodes((a, b, c, d), 4)
        found = self._cell_faces_for(nodes, i)
        self._unlink_cell(i)
        self._link_cell(i, nodes, found)
        if material is not None:
            self._stores["cell"].arrays["material"][i] = int(material)
        self._emit("cell", "update", i)

    def split_edge(self, edge: int, t: float) -> tuple[int, int, int]:
        """Split ``edge`` = (n0, n1) at parameter ``t`` (SPEC section 4).

        Two co-located nodes are inserted at ``n0 + t (n1 - n0)`` (rest and
        current positions interpolated); the edge now runs n0 -> first new
        node and a new edge runs second new node -> n1. Nothing else changes:
        the faces and cells around the edge are the caller's business. Cutting
        (SPEC section 6) splits every cut edge this way, one node per side of
        the cut, then replaces each cut cell by its table's sub-tets
        (:meth:`update_cell`, :meth:`insert_cell`) and lets
        :meth:`collect_garbage` purge the faces left over.

        Args:
            edge: a live edge.
            t: split parameter, strictly between 0 and 1.

        Returns:
            (first new node, second new node, new edge).
        """
        e = self._check(edge, "edge")
        if not (isinstance(t, (int, float, np.floating)) and 0.0 < float(t) < 1.0):
            raise WarpblobError(f"TetStructure.split_edge: t must lie strictly between 0 and 1, got {t!r}")
        n0, n1 = self._stores["edge"]["nodes"][e].tolist()
        nodes = self._stores["node"].arrays
        t = float(t)
        rest = nodes["rest"][n0] + t * (nodes["rest"][n1] - nodes["rest"][n0])
        position = nodes["position"][n0] + t * (nodes["position"][n1] - nodes["position"][n0])
        first = self.insert_node(rest, position)
        second = self.insert_node(rest, position)
        self.update_edge(e, n0, first)
        return first, second, self.insert_edge(second, n1)

    # -- batch edits (cutting) ----------------------------------------------------------------

    def set_positions(self, positions) -> None:
        """Set every node's current position at once ((N, 3), e.g. a simulation's); one "update" event.

        Raises:
            WarpblobError: a shape other than (N, 3) or a value that is not finite.
        """
        p = np.asarray(positions, dtype=np.float32)
        store = self._stores["node"]
        if p.shape != (store.count, 3):
            raise WarpblobError(f"TetStructure.set_positions: need shape ({store.count}, 3), got {p.shape}")
        bad = np.flatnonzero(~np.isfinite(p).all(axis=1))
        if bad.size:
            raise WarpblobError(f"TetStructure.set_positions: node {bad[0]} position {p[bad[0]].tolist()} not finite")
        store.arrays["position"][: store.count] = p
        self._emit("node", "update", np.arange(store.count, dtype=np.int32))

    def insert_nodes(self, rest, position=None, *, origin: int = 0) -> np.ndarray:
        """Append many nodes at once; one "insert" event with the (K,) int32 array of their indices.

        Args:
            rest: (K, 3) rest positions.
            position: (K, 3) current positions (default ``rest``).
            origin: :data:`NODE_ORIGINS` value stored for them.
        """
        r = np.asarray(rest, dtype=np.float32).reshape(-1, 3)
        p = r if position is None else np.asarray(position, dtype=np.float32).reshape(-1, 3)
        if p.shape != r.shape:
            raise WarpblobError(f"TetStructure.insert_nodes: {len(r)} rest positions but {len(p)} positions")
        bad = np.flatnonzero(~(np.isfinite(r).all(axis=1) & np.isfinite(p).all(axis=1)))
        if bad.size:
            raise WarpblobError(f"TetStructure.insert_nodes: node {bad[0]} is not finite: {r[bad[0]].tolist()}")
        ids = self._stores["node"].extend(len(r), rest=r, position=p, origin=int(origin))
        if len(ids):
            self._emit("node", "insert", ids)
        return ids

    def replace_cells(self, remove, nodes, material, *, parent=None) -> np.ndarray:
        """Remove cells and insert others in one batch (kernels and vectorized numpy; the cutting path).

        Faces of the new cells that coincide with faces of the removed cells
        are reused (their cell slots re-linked), the others are created
        (numbered in the order their keys first occur among the new cells' faces),
        and so are missing edges (in the order of their first use; an edge at a node newer than
        every edge is not looked up);
        a kernel per new cell validates it, keys its faces and finds its
        edges in the table; removed cells are pending until
        :meth:`collect_garbage`, which also purges the faces, edges and nodes
        no longer used. Validated first: on an error nothing has changed.
        Fires one event per kind and action with the array of indices
        ("remove" cells, "insert" edges, faces, cells). Orientation is the
        caller's duty. The node -> edge and edge -> face lists are rebuilt on
        the next query that needs them.

        Args:
            remove: (R,) live cell indices.
            nodes: (C, 4) int node indices of the new cells.
            material: (C,) int material ids (or one id for all).
            parent: (C,) int progressive-cut parent record of each new cell (-1 none; cutting's state).

        Returns:
            (C,) int32 indices of the new cells.

        Raises:
            WarpblobError: a removed cell is not live or repeated, a node is
                missing, dead or repeated in a cell, or a face would have
                more than two cells.
        """
        st = self._stores
        cells, faces = st["cell"], st["face"]
        cpu = wp.get_device("cpu")
        remove = np.asarray(remove, dtype=np.int64).ravel()
        if remove.size and (remove.min() < 0 or remove.max() >= cells.count):
            raise WarpblobError(f"TetStructure.replace_cells: cell index out of range in {remove.tolist()[:8]}")
        if remove.size and (not cells["alive"][remove].all() or not (
                np.all(remove[1:] > remove[:-1]) or len(np.unique(remove)) == len(remove))):  # fmt: skip
            raise WarpblobError("TetStructure.replace_cells: the cells to remove must be live and distinct")
        new = np.asarray(nodes, dtype=np.int64).reshape(-1, 4)
        C = len(new)
        mat = np.broadcast_to(np.asarray(material, dtype=np.int32), (C,))
        N = st["node"].count
        if C and (new.min() < 0 or new.max() >= N):
            raise WarpblobError("TetStructure.replace_cells: a new cell names a missing or removed node")
        new = np.ascontiguousarray(new, dtype=np.int32)
        # per new cell (kernel): validity, face keys, the six edges found in the table and the missing ones' keys
        key_base = max(N, 1) if N < 1 << 21 else 0
        bad = np.empty(C, dtype=np.int32)
        new_keys = np.empty(4 * C, dtype=np.int64)
        found = np.empty(6 * C, dtype=np.int32)
        edge_keys = np.empty(6 * C, dtype=np.int64)
        new_wp = host_array(new, wp.vec4i)
        table = [host_array(self._table_keys, wp.int64),
                 host_array(self._table_values, wp.int32), self._table_bits,
                 self._table_node_bound]  # fmt: skip
        # one launch below 4096 new cells (a 10K-tet cut): waking the pool costs more than the second thread gives
        launch(new_cells_kernel, C,
               [new_wp, host_array(st["node"]["alive"].view(np.uint8), wp.uint8),
                wp.int64(key_base), *table],
               [host_array(a, t) for a, t in
                ((bad, wp.int32), (new_keys, wp.int64), (found, wp.int32), (edge_keys, wp.int64))], cpu,
               min_chunk=2048)  # fmt: skip
        if C and bad.any():
            if np.any(bad == 1):
                raise WarpblobError("TetStructure.replace_cells: a new cell names a missing or removed node")
            c = int(np.flatnonzero(bad)[0])
            raise WarpblobError(f"TetStructure.replace_cells: new cell {c} repeats a node: {new[c].tolist()}")

        missing = np.flatnonzero(found < 0)
        if remove.size:  # the faces of the removed cells, ascending (marks: no sort)
            marked = np.zeros(faces.count, dtype=bool)
            marked[cells["faces"][remove].ravel()] = True
            old_faces = np.flatnonzero(marked)
        else:
            old_faces = np.zeros(0, dtype=np.int64)
        slots = faces["cells"][old_faces].copy()
        gone = np.zeros(cells.count, dtype=bool)
        gone[remove] = True
        slots[(slots >= 0) & gone[np.maximum(slots, 0)]] = -1
        # the kept cell (if any) first
        slots = np.stack([np.maximum(slots[:, 0], slots[:, 1]), np.minimum(slots[:, 0], slots[:, 1])], axis=1)
        if key_base:
            old_keys = np.empty(len(old_faces), dtype=np.int64)
            launch(triple_keys_kernel, len(old_faces),
                   [_shared(faces["nodes"][old_faces], wp.vec3i),
                    wp.int64(key_base)], [host_array(old_keys, wp.int64)], cpu,
                   min_chunk=_CHEAP)  # fmt: skip
            keys = np.concatenate([old_keys, new_keys])
        else:
            keys = _face_keys(np.concatenate([faces["nodes"][old_faces], new[:, TET_FACES].reshape(-1, 3)]), N)
        # a large batch's new edges go into the lookup table on a pool thread while the faces are matched
        # here (both are one kernel thread's random probes; no range-split launch between the two, which
        # would wait for the pool); undone below if the faces refuse the batch
        table_before = self._table_node_bound
        add_edges = None
        if len(missing) >= _SIDE_EDGES:
            add_edges = submit(functools.partial(self._add_edge_keys, edge_keys[missing]), 1)[0]
        groups, inverse, first_use, uses = _group_keys(keys, len(old_faces))
        face_of = np.full(groups, -1, dtype=np.int64)
        face_of[inverse[: len(old_faces)]] = old_faces
        taken = np.zeros(groups, dtype=np.int32)
        taken[inverse[: len(old_faces)]] = (slots[:, 0] >= 0).astype(np.int32) + (slots[:, 1] >= 0)
        inv_new = inverse[len(old_faces) :]
        if np.any(taken + uses > 2):
            if add_edges is not None:  # the table as it was: built anew from the edges, which did not change
                add_edges.result()
                self._build_table(cpu)
                self._table_node_bound = table_before
            u = int(np.flatnonzero(taken + uses > 2)[0])
            f = new[np.flatnonzero(inv_new == u)[0] // 4][TET_FACES[np.flatnonzero(inv_new == u)[0] % 4]].tolist()
            raise WarpblobError(f"TetStructure.replace_cells: face {f} would have {taken[u] + uses[u]} cells")

        # -- commit -------------------------------------------------------------------------------
        edges_used = self._edges_used and not remove.size  # new cells use every edge they insert
        face_cells = faces.arrays["cells"]
        face_cells[old_faces] = slots
        cells.arrays["alive"][remove] = False
        self._pending["cell"].extend(remove.tolist())
        if remove.size:
            self._emit("cell", "remove", remove.astype(np.int32))

        # edges: the new cells' six, found in the table or appended (numbered in the order they are first used,
        # oriented by that use), put in the lookup table as they are numbered
        if missing.size:
            count, edge_of, first = (add_edges.result() if add_edges is not None
                                     else self._add_edge_keys(edge_keys[missing]))  # fmt: skip
            pairs = np.empty((count, 2), dtype=np.int32)
            launch(edge_pairs_kernel, count,
                   [new_wp, _shared(missing[first].astype(np.int32))],
                   [host_array(pairs, wp.vec2i)], cpu, min_chunk=_CHEAP)  # fmt: skip
            edge_ids = st["edge"].extend(count, nodes=pairs)
            found[missing] = edge_of
            self._emit("edge", "insert", edge_ids)
        cell_edges = found.reshape(C, 6)

        # faces: reuse or create (numbered in the order of their groups, oriented by the first new cell that has it)
        create = np.flatnonzero(face_of < 0)
        if create.size:
            use = np.ascontiguousarray(first_use[create])  # index into the (C, 4) faces of the new cells
            fn = np.empty((len(use), 3), dtype=np.int32)
            fe = np.empty((len(use), 3), dtype=np.int32)
            launch(new_faces_kernel, len(use),
                   [new_wp, host_array(cell_edges, vec6i),
                    host_array(use, wp.int32)],
                   [host_array(fn, wp.vec3i),
                    host_array(fe, wp.vec3i)], cpu, min_chunk=_CHEAP)  # fmt: skip
            face_ids = faces.extend(len(create), nodes=fn, edges=fe)
            face_of[create] = face_ids
            self._emit("face", "insert", face_ids)
        cell_faces = face_of[inv_new].astype(np.int32)

        par = np.full(C, -1, dtype=np.int32) if parent is None else np.broadcast_to(np.asarray(parent, np.int32), (C,))
        cell_ids = cells.extend(C, nodes=new, faces=cell_faces.reshape(C, 4), edges=cell_edges, material=mat,
                                parent=par)  # fmt: skip
        if self._parented is not None:
            self._parented = np.concatenate([self._parented, cell_ids[par >= 0].astype(np.int32)])
        # link: each use takes the next free slot of its face (kept cells first)
        if C:
            face_cells = faces.arrays["cells"]  # the extend above may have grown it
            launch(link_new_cells_kernel, 4 * C,
                   [host_array(cell_faces, wp.int32),
                    host_array(inv_new, wp.int32),
                    host_array(first_use, wp.int32),
                    host_array(taken, wp.int32), int(cell_ids[0])],
                   [host_array(face_cells.reshape(-1), wp.int32)], cpu,
                   min_chunk=_CHEAP)  # fmt: skip
            self._emit("cell", "insert", cell_ids)
        self._links_dirty = True
        self._links_stale = True
        self._edges_used = edges_used
        return cell_ids

    def _cells_with_parent(self) -> np.ndarray:
        """The cells (live or not) that are pieces of a progressive-cut record, ascending int32: kept by the
        edits that make them (a cut's :meth:`replace_cells`), found by one pass over the cells after a
        compaction renumbered them."""
        if self._parented is None:
            self._parented = np.flatnonzero(self._stores["cell"]["parent"] >= 0).astype(np.int32)
        return self._parented

    def _mark_origin(self, ids, origin: int) -> None:
        """Record how nodes were made (:data:`NODE_ORIGINS`), e.g. model nodes a cut snapped onto."""
        self._stores["node"].arrays["origin"][np.asarray(ids, dtype=np.int64)] = origin

    def _truncate_nodes(self, count: int) -> None:
        """Drop the nodes appended after slot ``count`` (undo of a batch whose later part failed)."""
        store = self._stores["node"]
        store.arrays["alive"][count : store.count] = False
        store.count = min(store.count, count)

    def _add_edge_keys(self, keys: np.ndarray) -> tuple:
        """Number a batch edit's missing edges from the next edge slot and put them in the lookup table
        (:func:`add_edge_keys_kernel`; ``keys`` (k,) int64 ``max << 32 | min``, none in the table, each once
        per use): (new edges, (k,) int32 edge of each key, per new edge the index of its first key). The edge
        store is the caller's to extend by them, at once."""
        if 2 * (self._table_used + len(keys)) > len(self._table_keys):  # (room for every key: a bound)
            self._build_table(wp.get_device("cpu"), extra=len(keys))
        edge_of, first = np.empty(len(keys), dtype=np.int32), np.empty(len(keys), dtype=np.int32)
        count = np.zeros(2, dtype=np.int32)
        wp.launch(add_edge_keys_kernel, dim=1, device="cpu",
                  inputs=[host_array(np.ascontiguousarray(keys, dtype=np.int64), wp.int64),
                          self._stores["edge"].count, self._table_bits, host_array(self._table_keys, wp.int64),
                          host_array(self._table_values, wp.int32), host_array(edge_of, wp.int32),
                          host_array(first, wp.int32), host_array(count, wp.int32)])  # fmt: skip
        self._table_used += int(count[1])
        self._table_node_bound = max(self._table_node_bound, int(keys.max() >> 32) + 1)
        return int(count[0]), edge_of, first[: int(count[0])]

    def components(self) -> np.ndarray:
        """(C,) int32 connected piece of every cell slot (cells joined through shared faces), -1 for dead cells.

        Pieces are numbered 0, 1, ... in the order of their lowest cell.
        A union-find over the shared faces: one per range of cells side by side, then the faces between
        ranges and the numbering in one Warp kernel thread.

        Example:
            >>> from warpblob.mesh import box_tetmesh
            >>> int(TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2))).components().max()) + 1
            1
        """
        labels, count = self._components(True)
        self._remember_pieces(count)
        return labels

    def _component_count(self) -> int:
        """The number of connected pieces (:meth:`components` without the labels; remembered until a cell or
        face changes)."""
        known = self._known_pieces()
        if known is None:
            known = self._components(False)[1]
            self._remember_pieces(known)
        return known

    def _known_pieces(self) -> int | None:
        """The piece count if it was counted since the last cell or face change, else None."""
        if self._pieces is not None and self._pieces[0] == self._connectivity_version:
            return self._pieces[1]
        return None

    def _remember_pieces(self, count: int) -> None:
        self._pieces = (self._connectivity_version, int(count))

    def _pieces_after(self, previous: int | None, removed, added) -> int:
        """The piece count after a batch edit that replaced the cells ``removed`` by the cells ``added``
        (indices before any compaction), ``previous`` the count before it (None: unknown).

        Local first, O(the edit and the pieces it cut off): the new cells and the kept neighbours of the
        removed ones (the live old cells across their faces) are flooded outwards, each from its own
        label, through the live cells (:func:`flood_pieces_kernel`); labels that meet join, and the
        flood stops when at most one label can still grow. Every piece the edit left in an old piece it
        touched holds one of these cells (a path from it to a removed cell passes a kept neighbour), and
        an edit never joins pieces. So where the edit touched one old piece (there was one piece, or the
        removed cells form one cluster joined through the faces they shared) the count is
        ``previous - 1`` plus the labels left; elsewhere (several clusters: a flood of a few rings'
        worth) or when the flood stopped early, where its joins show that each cluster's kept neighbours
        are still joined and every new cell is joined to one of them, nothing was severed and the count
        is ``previous``. Otherwise (a piece severed from a mesh in several pieces), for a batch
        of more than 1/64 of the cells (a plane through the mesh), or when the flood would queue more
        than 1/:data:`_FLOOD_SHARE` of the cells without that proof (a small edit that halves the mesh),
        all the cells are counted.
        """
        removed = np.asarray(removed, dtype=np.int64).ravel()
        added = np.asarray(added, dtype=np.int64).ravel()
        cells, faces = self._stores["cell"], self._stores["face"]
        big = max(1024, cells.count // 64)
        if previous is None or len(added) == 0 or len(removed) == 0 or len(added) + len(removed) > big:
            return self._component_count()
        face_cells, cell_faces, alive = faces["cells"], cells["faces"], cells["alive"]
        rf = cell_faces[removed]  # (R, 4) their faces (kept in the dead slots)
        across = face_cells[rf.ravel()].ravel()  # (8R,) their faces' cells now, removed cell j's at 8j..8j+7
        kept = (across >= 0) & (across < int(added.min()))
        kept[kept] = alive[across[kept]]
        seeds = np.union1d(added, across[kept]).astype(np.int32)
        cluster = None
        if previous != 1:  # the removed cells' clusters (joined through the faces they shared)
            order = np.argsort(rf.ravel(), kind="stable")
            fs = rf.ravel()[order]
            same = np.flatnonzero(fs[1:] == fs[:-1])
            cluster = _connected(len(removed), order[same] // 4, order[same + 1] // 4, np.ones(len(removed), bool))
        one = cluster is None or int(cluster.max()) == 0  # the edit touched one old piece
        # one old piece: flood until the pieces are known; several: a few rings' worth, for the joins
        budget = max(len(seeds) + 1024, cells.count // _FLOOD_SHARE) if one else 8 * len(seeds) + 1024
        failed, touched, roots = self._flood_pieces(seeds, budget)
        if failed and cluster is None:
            cluster = np.zeros(len(removed), dtype=np.int32)  # (one piece before: the removed cells in it)
        count = None
        if not failed and one:
            count = int(previous) - 1 + touched
        elif cluster is not None and np.any(kept):  # each cluster's kept neighbours joined, every new cell on them?
            kept_root = roots[np.searchsorted(seeds, across[kept])]
            owner = np.repeat(cluster, 8)[kept]
            lo = np.full(int(cluster.max()) + 1, np.iinfo(np.int32).max, dtype=np.int64)
            hi = np.full(int(cluster.max()) + 1, -1, dtype=np.int64)
            np.minimum.at(lo, owner, kept_root)
            np.maximum.at(hi, owner, kept_root)
            if np.all((hi < 0) | (lo == hi)) and np.isin(roots[np.searchsorted(seeds, added)], kept_root).all():
                count = int(previous)
        if count is None:
            return self._component_count()
        self._remember_pieces(count)
        return count

    def _flood_pieces(self, seeds: np.ndarray, budget: int) -> tuple[bool, int, np.ndarray]:
        """Flood from the (L,) distinct live cells ``seeds``, each its own label, by
        :func:`flood_pieces_kernel`, queueing at most ``budget`` cells: (failed, the number of pieces the
        seeds lie in (when not failed), (L,) int32 root of each seed's label)."""
        cells, faces = self._stores["cell"], self._stores["face"]
        cpu = wp.get_device("cpu")
        if self._flood_mark is None or len(self._flood_mark) < cells.count:
            self._flood_mark = np.full(cells.count + cells.count // 4 + 16, -1, dtype=np.int32)
        mark = self._flood_mark
        budget = max(int(budget), len(seeds))
        queue = np.empty(budget, dtype=np.int32)
        count = len(seeds)
        roots = np.empty(count, dtype=np.int32)
        out = np.zeros(3, dtype=np.int32)
        wp.launch(flood_pieces_kernel, dim=1, device=cpu, inputs=[
            host_array(faces["cells"], wp.vec2i),
            host_array(cells["faces"], wp.vec4i),
            host_array(cells["alive"].view(np.uint8), wp.uint8),
            device_array(seeds, wp.int32, cpu), budget,
            host_array(mark, wp.int32),
            host_array(queue, wp.int32),
            host_array(roots, wp.int32), device_empty(count, wp.int32, cpu),
            host_array(out, wp.int32)])  # fmt: skip
        mark[queue[: out[2]]] = -1  # back to unmarked for the next flood
        return bool(out[0]), int(out[1]), roots

    def _cells_near(self, lower, upper) -> np.ndarray | None:
        """The live cells whose rest boxes meet a box ``[lower[i], upper[i]]`` ((3,) or (B, 3), rest frame),
        ascending (and maybe some newer cells that do not); None where the boxes hold too much of the mesh
        for the search to pay (the caller then passes over every cell).

        The cells there were when the search was first needed are kept in a uniform grid of their rest
        boxes (built once, O(C), again when a cell's nodes or a rest position change, after a compaction,
        or when the cells made since are an eighth as many); those made since (a cut's) are all taken.
        """
        cells = self._stores["cell"]
        grid = self._rest_grid
        if (grid is None or grid.clock != self._rest_clock or grid.cells > cells.count
                or 8 * (cells.count - grid.cells) > grid.cells):  # fmt: skip
            grid = self._rest_grid = _RestCellGrid(self._stores["node"]["rest"], cells["nodes"], self._rest_clock)
        found = grid.query(lower, upper, cells.count // 4)
        if found is None:
            return None
        found = np.concatenate([found, np.arange(grid.cells, cells.count, dtype=np.int64)])
        return found[cells["alive"][found]]

    def _components(self, label: bool) -> tuple[np.ndarray, int]:
        st = self._stores
        cells, faces = st["cell"], st["face"]
        cpu = wp.get_device("cpu")
        C = cells.count
        labels = np.empty(C if label else 0, dtype=np.int32)
        if C == 0:
            return labels, 0
        dense = np.empty(C if label else 0, dtype=np.int32)
        # the kernels read the structure's own memory: a union-find per range of cells (side by side), the
        # faces between ranges in one thread, then the pieces counted per range or numbered in one thread
        # (near-linear, exact: the same pieces and numbering for any number of ranges)
        face_cells = host_array(faces["cells"], wp.vec2i)
        alive = host_array(cells["alive"].view(np.uint8), wp.uint8)
        parent = device_empty(C, wp.int32, cpu)
        cross = device_empty(len(faces["cells"]), wp.int32, cpu)
        ranges = max(1, min(thread_count(), C // _COMPONENT_RANGE))
        counts = device_empty(ranges, wp.int32, cpu)
        launch(components_ranges_kernel, ranges,
               [face_cells, host_array(faces["alive"].view(np.uint8), wp.uint8),
                ranges], [parent, cross, counts], cpu, min_chunk=1)  # fmt: skip
        wp.launch(components_cross_kernel, dim=1, device=cpu, inputs=[
            face_cells, cross, counts, alive, parent, host_array(dense, wp.int32),
            host_array(labels, wp.int32)])  # fmt: skip
        if label:
            return labels, int(dense[-1]) + 1
        launch(live_roots_kernel, ranges, [parent, alive, ranges], [counts], cpu, min_chunk=1)
        return labels, int(counts.numpy().sum())

    def surface(self, *, model=None, rest: bool = False):
        """The boundary of the live cells as a :class:`~warpblob.mesh.SurfaceMesh`, cut faces marked.

        Faces are oriented outwards; ``is_cut`` marks faces made by cutting
        (every corner a cut point, :attr:`node_origin` > 0: split points, cut
        nodes and their copies, crack front points). Colours: the BlobTree's colour field at the
        rest positions when ``model`` is given (the model knows what the
        inside looks like), else light grey. Normals are area-weighted face
        normals.

        Args:
            model: optional BlobTree node for colours.
            rest: vertices at rest positions instead of current ones.

        Returns:
            A SurfaceMesh on the nodes the boundary uses, with ``is_cut`` (F,)
            bool and ``stats["nodes"]`` the structure node of each vertex.
        """
        from ._surface import SurfaceMesh

        st = self._stores
        fc = st["face"]["cells"]
        outer = np.flatnonzero(st["face"]["alive"] & (fc[:, 0] >= 0) & (fc[:, 1] < 0))
        cell = fc[outer, 0]
        # orient from the cell: face k of a positive tet, TET_FACES order, is counter-clockwise from outside
        cn = st["cell"]["nodes"][cell]
        k = np.argmax(st["cell"]["faces"][cell] == outer[:, None], axis=1)
        tri = cn[np.arange(len(cell))[:, None], TET_FACES[k]]
        used, faces = np.unique(tri, return_inverse=True)
        faces = faces.reshape(-1, 3).astype(np.int32)
        pts = st["node"]["rest" if rest else "position"][used].astype(np.float32)
        on_cut = st["node"]["origin"][used] > 0
        is_cut = rows_all(on_cut[faces])
        normals = np.zeros_like(pts, dtype=np.float64)
        fnorm = np.cross(pts[faces[:, 1]] - pts[faces[:, 0]], pts[faces[:, 2]] - pts[faces[:, 0]]).astype(np.float64)
        for j in range(3):
            np.add.at(normals, faces[:, j], fnorm)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
        if model is not None:
            from ..field import evaluate

            colors = np.asarray(evaluate(model, st["node"]["rest"][used].astype(np.float32))[2], dtype=np.float32)
        else:
            colors = np.full((len(used), 3), 0.8, dtype=np.float32)
        return SurfaceMesh(
            pts, faces, normals.astype(np.float32), colors,
            stats={"source": "TetStructure", "nodes": used.astype(np.int32)}, is_cut=is_cut,
        )  # fmt: skip

    # -- removal and garbage collection -----------------------------------------------------

    def _remove(self, kind: str, i: int) -> None:
        self._stores[kind].arrays["alive"][i] = False
        self._pending[kind].append(i)
        self._emit(kind, "remove", i)

    def remove_cell(self, cell: int) -> None:
        """Remove ``cell``: flagged dead, unlinked from its faces, pending until :meth:`collect_garbage`."""
        c = self._check(cell, "cell")
        self._unlink_cell(c)
        self._remove("cell", c)

    def remove_face(self, face: int) -> None:
        """Remove ``face``, which no live cell may use."""
        f = self._check(face, "face")
        cells = self.cells_of_face(f)
        if cells.size:
            raise WarpblobError(f"TetStructure.remove_face: face {f} is used by cells {cells.tolist()}")
        self._links_dirty = True
        self._remove("face", f)

    def remove_edge(self, edge: int) -> None:
        """Remove ``edge``, which no live face may use; it leaves the lookup table at once."""
        e = self._check(edge, "edge")
        faces = self.faces_of_edge(e)
        if faces.size:
            raise WarpblobError(f"TetStructure.remove_edge: edge {e} is used by faces {faces.tolist()}")
        self._table_remove(_host_key(*self._stores["edge"]["nodes"][e].tolist()))
        self._links_dirty = True
        self._remove("edge", e)

    def remove_node(self, node: int) -> None:
        """Remove ``node``, which no live edge may use."""
        v = self._check(node, "node")
        edges = self.edges_of_node(v)
        if edges.size:
            raise WarpblobError(f"TetStructure.remove_node: node {v} is used by edges {edges.tolist()}")
        self._remove("node", v)

    def collect_garbage(self) -> dict[str, np.ndarray]:
        """Purge unreferenced entities, compact every kind and remap every link.

        Faces no live cell uses, then edges no live face or cell uses, then
        nodes no live edge, face or cell uses are removed (one "remove"
        event per kind with the array of their indices); live entities are renumbered in their old order, links
        rebuilt, the lookup table followed in place where every node kept its index (a cut's compaction:
        :meth:`_remap_table`) and rebuilt otherwise, the pending lists emptied, and a "compact" event fires
        per kind.

        Returns:
            Per kind, the (old slot count,) int32 map from old to new index
            (-1 for removed entities); also kept as :attr:`last_remap`.
        """
        st = self._stores
        cells, faces, edges, nodes = st["cell"], st["face"], st["edge"], st["node"]
        live_cells = cells["alive"]
        pieces = self._known_pieces()  # (a compaction renumbers; it joins and parts nothing)

        used = np.zeros(faces.count, dtype=bool)
        _mark_used(used, cells["faces"], live_cells)
        self._purge("face", faces["alive"] & ~used)

        used = np.zeros(edges.count, dtype=bool)
        _mark_used(used, faces["edges"], faces["alive"])
        _mark_used(used, cells["edges"], live_cells)
        self._purge("edge", edges["alive"] & ~used)

        used = np.zeros(nodes.count, dtype=bool)
        _mark_used(used, edges["nodes"], edges["alive"])
        _mark_used(used, faces["nodes"], faces["alive"])
        _mark_used(used, cells["nodes"], live_cells)
        self._purge("node", nodes["alive"] & ~used)

        keep = {kind: st[kind]["alive"].copy() for kind in KINDS}
        maps = {}
        for kind, alive in keep.items():
            maps[kind] = np.full(len(alive), -1, dtype=np.int32)
            maps[kind][alive] = np.arange(np.count_nonzero(alive), dtype=np.int32)
        n, e, f, c = (keep[kind] for kind in KINDS)
        rows = {kind: np.flatnonzero(keep[kind]).astype(np.int32) for kind in ("edge", "face", "cell")}
        nodes.load(
            rest=nodes["rest"][n], position=nodes["position"][n], origin=nodes["origin"][n],
            alive=np.ones(n.sum(), dtype=bool),
        )  # fmt: skip
        # the remapped rows go straight into the new columns (no copy of them after)
        old = {kind: {name: st[kind][name] for name in columns} for kind, columns in
               (("edge", ("nodes",)), ("face", ("nodes", "edges", "cells")))}  # fmt: skip
        new = edges.fresh(len(rows["edge"]))
        _remap_rows(maps["node"], old["edge"]["nodes"], rows["edge"], out=new["nodes"])
        new["alive"][:] = True
        new = faces.fresh(len(rows["face"]))
        for name, kind in (("nodes", "node"), ("edges", "edge"), ("cells", "cell")):
            _remap_rows(maps[kind], old["face"][name], rows["face"], out=new[name])
        new["alive"][:] = True
        # parent records of progressive cuts: those with a live child stay, renumbered, their nodes remapped
        pr = self._parents
        child_parent = cells["parent"][c]
        used = np.zeros(pr.count, dtype=bool)
        used[child_parent[child_parent >= 0]] = True
        used &= pr["alive"]
        pmap = np.full(pr.count, -1, dtype=np.int32)
        pmap[used] = np.arange(int(used.sum()), dtype=np.int32)
        pr.load(
            corners=_remap(maps["node"], pr["corners"][used]), split=_remap(maps["node"], pr["split"][used]),
            t=pr["t"][used], code=pr["code"][used], faces=_remap(maps["node"], pr["faces"][used]),
            centre=_remap(maps["node"], pr["centre"][used]), alive=np.ones(int(used.sum()), dtype=bool),
        )  # fmt: skip
        old = {name: cells[name] for name in ("nodes", "faces", "edges", "material")}
        new = cells.fresh(len(rows["cell"]))
        for name, kind in (("nodes", "node"), ("faces", "face"), ("edges", "edge")):
            _remap_rows(maps[kind], old[name], rows["cell"], out=new[name])
        new["material"][:] = old["material"][c]
        new["parent"][:] = _remap(pmap, child_parent)
        new["alive"][:] = True
        self._parented = None
        self._pending = {k: [] for k in KINDS}
        # the lookup table now; the CSR lists when a query first needs them
        self._clear_links()
        if not (n.all() and self._remap_table(maps["edge"], int(e.sum()))):
            self._build_table(wp.get_device("cpu"))
        self._links_dirty = self._links_stale = True
        self.last_remap = maps
        self._edges_used = True  # the edges left are those of live cells
        for kind in KINDS:
            self._emit(kind, "compact", st[kind].count)
        if pieces is not None:
            self._remember_pieces(pieces)
        return maps

    def _purge(self, kind: str, mask: np.ndarray) -> None:
        ids = np.flatnonzero(mask).astype(np.int32)
        self._stores[kind].arrays["alive"][ids] = False
        if ids.size:
            self._emit(kind, "remove", ids)

    # -- consistency, export -------------------------------------------------------------------

    def check(self) -> None:
        """Verify every invariant (vectorized); raise :class:`WarpblobError` listing the broken ones.

        Live entities reference only live entities; each face's edges join
        its nodes; each cell's faces and edges are those of its nodes; face
        cell slots and cell faces agree both ways; the CSR links equal the
        inverse of the top-down links; the lookup table finds every live edge
        and holds nothing else, with an edge exactly in the slots that hold a key.
        """
        if self._links_dirty:
            self.rebuild_links(device="cpu")
        st = self._stores
        problems = []

        def refs(kind, column, target):
            live = st[kind]["alive"]
            r = st[kind][column][live]
            ok = (r >= 0) & (r < st[target].count)
            ok[ok] = st[target]["alive"][r[ok]]
            if not ok.all():
                problems.append(f"{kind} {np.flatnonzero(live)[np.argmin(ok.all(axis=1))]}: {column} not all live")
            return r, live

        en, _ = refs("edge", "nodes", "node")
        fn, flive = refs("face", "nodes", "node")
        fe, _ = refs("face", "edges", "edge")
        cn, clive = refs("cell", "nodes", "node")
        cf, _ = refs("cell", "faces", "face")
        ce, _ = refs("cell", "edges", "edge")
        if problems:
            raise WarpblobError("TetStructure.check: " + "; ".join(problems))
        edge_nodes = st["edge"]["nodes"]
        if np.any(np.sort(edge_nodes[fe], axis=2) != np.sort(np.stack([fn, np.roll(fn, -1, axis=1)], axis=2), axis=2)):
            problems.append("a face's edges do not join its nodes")
        if np.any(np.sort(edge_nodes[ce], axis=2) != np.sort(cn[:, TET_EDGES], axis=2)):
            problems.append("a cell's edges are not those of its nodes")
        if np.any(np.sort(st["face"]["nodes"][cf], axis=2) != np.sort(cn[:, TET_FACES], axis=2)):
            problems.append("a cell's faces are not those of its nodes")
        fc = st["face"]["cells"][flive]
        cell_ids = np.flatnonzero(clive)
        if np.any((fc[:, 1] >= 0) & (fc[:, 0] < 0)) or np.any((fc >= 0) & ~st["cell"]["alive"][np.maximum(fc, 0)]):
            problems.append("a face's cell slots hold a removed cell or a gap")
        pairs_up = np.sort(np.flatnonzero(flive)[np.nonzero(fc >= 0)[0]] * 2**31 + fc[fc >= 0])
        pairs_down = np.sort(cf.ravel().astype(np.int64) * 2**31 + np.repeat(cell_ids, 4))
        if not np.array_equal(pairs_up, pairs_down):
            problems.append("face cell slots and cell faces disagree")
        edge_ids = np.flatnonzero(st["edge"]["alive"])
        expect = np.sort(en.ravel().astype(np.int64) * 2**31 + np.repeat(edge_ids, 2))
        got = np.repeat(np.arange(len(self._node_edge_offsets) - 1), np.diff(self._node_edge_offsets)) * 2**31
        if not np.array_equal(np.sort(got + self._node_edge_list), expect):
            problems.append("node -> edges links disagree with edge nodes")
        face_ids = np.flatnonzero(flive)
        expect = np.sort(fe.ravel().astype(np.int64) * 2**31 + np.repeat(face_ids, 3))
        got = np.repeat(np.arange(len(self._edge_face_offsets) - 1), np.diff(self._edge_face_offsets)) * 2**31
        if not np.array_equal(np.sort(got + self._edge_face_list), expect):
            problems.append("edge -> faces links disagree with face edges")
        if not np.array_equal(self._table_values >= 0, self._table_keys >= 0):  # (what its compaction reads)
            problems.append("the lookup table's values and keys disagree on the used slots")
        if not np.array_equal(self.find_edges(en, device="cpu"), edge_ids):
            problems.append("the lookup table misses a live edge")
        if np.count_nonzero(self._table_keys >= 0) != len(edge_ids):
            problems.append("the lookup table holds removed edges")
        if problems:
            raise WarpblobError("TetStructure.check: " + "; ".join(problems))

    def to_warp(self, device=None) -> TetStructureArrays:
        """The structure's arrays on ``device`` as a :class:`TetStructureArrays` (links rebuilt first if needed)."""

        dev = resolve_device(device)
        if self._links_dirty:
            self._rebuild(dev, None)
        st = self._stores
        out = TetStructureArrays()

        def put(values, dtype):
            return wp.array(np.ascontiguousarray(values), dtype=dtype, device=dev)

        out.node_rest = put(st["node"]["rest"], wp.vec3)
        out.node_position = put(st["node"]["position"], wp.vec3)
        out.node_alive = put(st["node"]["alive"].view(np.uint8), wp.uint8)
        out.edge_nodes = put(st["edge"]["nodes"], wp.vec2i)
        out.edge_alive = put(st["edge"]["alive"].view(np.uint8), wp.uint8)
        out.face_nodes = put(st["face"]["nodes"], wp.vec3i)
        out.face_edges = put(st["face"]["edges"], wp.vec3i)
        out.face_cells = put(st["face"]["cells"], wp.vec2i)
        out.face_alive = put(st["face"]["alive"].view(np.uint8), wp.uint8)
        out.cell_nodes = put(st["cell"]["nodes"], wp.vec4i)
        out.cell_faces = put(st["cell"]["faces"], wp.vec4i)
        out.cell_edges = put(st["cell"]["edges"], vec6i)
        out.cell_material = put(st["cell"]["material"], wp.int32)
        out.cell_alive = put(st["cell"]["alive"].view(np.uint8), wp.uint8)
        out.node_edge_offsets = put(self._node_edge_offsets, wp.int32)
        out.node_edge_list = put(self._node_edge_list, wp.int32)
        out.edge_face_offsets = put(self._edge_face_offsets, wp.int32)
        out.edge_face_list = put(self._edge_face_list, wp.int32)
        out.edge_table_keys = put(self._table_keys, wp.int64)
        out.edge_table_values = put(self._table_values, wp.int32)
        out.edge_table_bits = self._table_bits
        return out

    def to_tetmesh(self, *, rest: bool = False) -> TetMesh:
        """The live cells as a :class:`TetMesh` on the nodes they use (current positions, or rest ones)."""
        st = self._stores
        live = st["cell"]["alive"]
        used, tets = np.unique(st["cell"]["nodes"][live], return_inverse=True)
        points = st["node"]["rest" if rest else "position"][used]
        return TetMesh(points, tets.reshape(-1, 4), st["cell"]["material"][live], stats={"source": "TetStructure"})
