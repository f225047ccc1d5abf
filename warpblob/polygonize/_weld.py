"""Welding of short edges: the one rule for the vertices the grid puts too close.

Where the surface passes close to a grid vertex, the vertices on the grid
edges around it (up to six) land next to each other, and the triangles
between them are needles (of zero area where two coincide). Relaxation
cannot mend these: both ends of the short edge have nearly the same
neighbours and move together. Every mesh edge shorter than ``WELD * h`` is
contracted instead (:func:`contract`): one end takes the other's place,
index, normal and colour, the triangles that collapse go, and the mesh stays
a closed 2-manifold. Kernels find the short edges (one kernel and one scan
when there is none, the usual case on smooth models); the few triangles at
their ends are read back and contracted by one thread of a CPU kernel, the
edges one after another, shortest first (:func:`contract_patch`; the rules
are those of :func:`contract`, the vectorized rounds that did it before and
stay as the readable reference the tests compare with), and written back by
kernels.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from .._parallel import launch
from .._stages import compact_kernel, scan
from ._kernels import CELL_CHUNK, LIGHT_CHUNK

#: mesh edges shorter than WELD cells are contracted. A triangle of the face
#: stage has its corners on one cell's edges, so no edge longer than the cell's
#: diagonal sqrt(3) h: if its smallest angle is under 1 degree and it is a needle
#: (not a flat cap), the edge opposite is under sqrt(3) h sin(1 degree) = 0.030 h.
#: The vertex that goes moves at most this far, onto a vertex the root search
#: placed, which does not move: every vertex still has |F - iso| <= tolerance.
WELD = 3.0e-2


@wp.kernel(enable_backward=False)
def short_edges_kernel(
    positions: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.vec3i),
    limit: float,
    offset: int,
    flags: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """``counts`` 1 for a triangle with an edge at most ``limit`` long, whose
    ends are flagged (every writer stores 1, so concurrent writes agree)."""
    tid = wp.tid() + offset
    t = triangles[tid]
    found = int(0)
    for k in range(3):
        a = t[k]
        b = t[(k + 1) % 3]
        if wp.length_sq(positions[a] - positions[b]) <= limit * limit:
            flags[a] = 1
            flags[b] = 1
            found = 1
    counts[tid] = found


@wp.kernel(enable_backward=False)
def valence_kernel(triangles: wp.array(dtype=wp.vec3i), offset: int, valence: wp.array(dtype=wp.int32)):
    """``valence[v] +=`` the triangles at each vertex ``v``. Warp's atomics on
    the CPU are plain read-modify-writes, so on the CPU this runs on one
    thread (see :func:`vertex_valence`)."""
    t = triangles[wp.tid() + offset]
    for k in range(3):
        wp.atomic_add(valence, t[k], 1)


def vertex_valence(triangles, n_vertices: int, device) -> wp.array:
    """(V,) int32 number of triangles at each vertex: integer sums, so the
    same whatever the order; one thread on the CPU (its atomics are not
    atomic across the range-split launcher's threads), one launch on CUDA."""
    valence = wp.zeros(n_vertices, dtype=wp.int32, device=device)
    launch(valence_kernel, triangles.shape[0], [triangles], [valence], device, threads=1)
    return valence


@wp.kernel(enable_backward=False)
def touching_kernel(
    triangles: wp.array(dtype=wp.vec3i),
    marks: wp.array(dtype=wp.int32),
    offset: int,
    touching: wp.array(dtype=wp.int32),
):
    """1 for a triangle with a marked corner."""
    tid = wp.tid() + offset
    t = triangles[tid]
    touching[tid] = wp.where(marks[t[0]] + marks[t[1]] + marks[t[2]] != 0, 1, 0)


@wp.kernel(enable_backward=False)
def gather_patch_kernel(
    triangles: wp.array(dtype=wp.vec3i),
    positions: wp.array(dtype=wp.vec3),
    flags: wp.array(dtype=wp.int32),
    valence: wp.array(dtype=wp.int32),
    ids: wp.array(dtype=wp.int32),
    offset: int,
    patch: wp.array(dtype=wp.vec3i),
    corners: wp.array2d(dtype=wp.vec3),
    corner_flags: wp.array(dtype=wp.vec3i),
    corner_valence: wp.array(dtype=wp.vec3i),
):
    """Triangle ``ids[i]``, its corners' positions, flags and valences."""
    tid = wp.tid() + offset
    t = triangles[ids[tid]]
    patch[tid] = t
    for k in range(3):
        corners[tid, k] = positions[t[k]]
    corner_flags[tid] = wp.vec3i(flags[t[0]], flags[t[1]], flags[t[2]])
    corner_valence[tid] = wp.vec3i(valence[t[0]], valence[t[1]], valence[t[2]])


@wp.kernel(enable_backward=False)
def scatter_triangles_kernel(
    ids: wp.array(dtype=wp.int32), patch: wp.array(dtype=wp.vec3i), offset: int, triangles: wp.array(dtype=wp.vec3i)
):
    tid = wp.tid() + offset
    triangles[ids[tid]] = patch[tid]


@wp.kernel(enable_backward=False)
def move_kernel(
    src: wp.array(dtype=wp.int32),
    dst: wp.array(dtype=wp.int32),
    data: wp.array(dtype=Any),
    offset: int,
    out: wp.array(dtype=Any),
):
    """``out[dst[i]] = data[src[i]]`` (``data`` may be ``out``: its sources and destinations are disjoint)."""
    tid = wp.tid() + offset
    out[dst[tid]] = data[src[tid]]


# the two uses, compiled with the module (not at a launch on a pool thread)
wp.overload(move_kernel, {"data": wp.array(dtype=wp.vec3i), "out": wp.array(dtype=wp.vec3i)})
wp.overload(move_kernel, {"data": wp.array(dtype=wp.vec3), "out": wp.array(dtype=wp.vec3)})


@wp.kernel(enable_backward=False)
def renumber_kernel(
    index: wp.array(dtype=wp.int32), first: int, offset: int, triangles: wp.array(dtype=wp.vec3i)
):
    """Corners ``v >= first`` renumbered ``index[v - first]``."""
    tid = wp.tid() + offset
    t = triangles[tid]
    if t[0] >= first or t[1] >= first or t[2] >= first:
        for k in range(3):
            if t[k] >= first:
                t[k] = index[t[k] - first]
        triangles[tid] = t


def weld(triangles, positions, normals, colors, h: float, device, threads=None, *, in_place: bool = False):
    """Contract the edges shorter than ``WELD * h`` of a closed mesh (see the
    module docstring), drop the collapsed triangles and the removed vertices.

    Args:
        triangles: (T,) vec3i vertex indices, consistently oriented.
        positions, normals, colors: (V,) vec3 vertex data.
        h: cell size, model units.
        in_place: edit the four arrays and return views of them (the
            pipeline's own arrays: no copy of the mesh); by default they are
            not modified.

    Returns:
        (triangles, positions, normals, colors, welded vertices). The usual
        case, no short edge, costs one kernel and one scan; otherwise only the
        triangles at the ends of short edges are read back to the host, and
        the triangles and vertices that go leave holes that the last ones
        fill (the order is otherwise kept; the moved vertices' corners are
        renumbered in one pass over the triangles).
    """
    n = triangles.shape[0]
    n_vertices = positions.shape[0]
    flags = wp.zeros(n_vertices, dtype=wp.int32, device=device)
    counts = wp.empty(n, dtype=wp.int32, device=device)
    launch(
        short_edges_kernel, n, [positions, triangles, float(WELD * h)], [flags, counts],
        device, threads, min_chunk=CELL_CHUNK,
    )  # fmt: skip
    _, n_short = scan(counts)  # host sync: whether any edge is short
    if n_short == 0:
        return triangles, positions, normals, colors, 0
    valence = vertex_valence(triangles, n_vertices, device)  # the contraction needs the fans' sizes
    touching = wp.empty(n, dtype=wp.int32, device=device)
    launch(touching_kernel, n, [triangles, flags], [touching], device, threads, min_chunk=LIGHT_CHUNK)
    scanned, n_patch = scan(touching)
    ids = wp.empty(n_patch, dtype=wp.int32, device=device)
    launch(compact_kernel, n, [touching, scanned], [ids], device, threads, min_chunk=LIGHT_CHUNK)
    patch = wp.empty(n_patch, dtype=wp.vec3i, device=device)
    corners = wp.empty((n_patch, 3), dtype=wp.vec3, device=device)
    corner_flags = wp.empty(n_patch, dtype=wp.vec3i, device=device)
    corner_valence = wp.empty(n_patch, dtype=wp.vec3i, device=device)
    launch(
        gather_patch_kernel, n_patch, [triangles, positions, flags, valence, ids],
        [patch, corners, corner_flags, corner_valence], device, threads, min_chunk=LIGHT_CHUNK,
    )  # fmt: skip
    tris = patch.numpy().reshape(-1, 3)  # host sync: the patch, about six triangles per end of a short edge
    vertices, local = np.unique(tris, return_inverse=True)
    local = local.reshape(-1, 3)
    points = np.zeros((len(vertices), 3))
    points[local.reshape(-1)] = corners.numpy().reshape(-1, 3)
    candidate = np.zeros(len(vertices), dtype=bool)
    candidate[local.reshape(-1)] = corner_flags.numpy().reshape(-1) != 0
    counts = np.zeros(len(vertices), dtype=np.int64)
    counts[local.reshape(-1)] = corner_valence.numpy().reshape(-1)
    corners, alive = contract_patch(local, points, candidate, counts, WELD * h)
    if np.all(alive):
        return triangles, positions, normals, colors, 0
    # a vertex goes when no triangle is left at it: none outside the patch, none alive in it
    outside = counts - np.bincount(local.reshape(-1), minlength=len(vertices))
    referenced = np.bincount(corners[alive].reshape(-1), minlength=len(vertices)) > 0
    removed = np.sort(vertices[(outside == 0) & ~referenced])
    patch_ids = ids.numpy()  # (host sync: n_patch entries)
    # the few triangles and vertices that go leave holes, filled from the end of the arrays: no pass
    # over the whole mesh but the renumbering of the moved vertices (the order is otherwise kept)
    t_holes, t_movers = _fill_from_end(np.sort(patch_ids[~alive]), n)
    v_holes, v_movers = _fill_from_end(removed, n_vertices)
    n_kept, n_used = n - int(np.count_nonzero(~alive)), n_vertices - len(removed)
    welded = triangles if in_place else wp.clone(triangles)
    live = np.flatnonzero(alive)
    launch(
        scatter_triangles_kernel, len(live),
        [_ints(patch_ids[live], device), wp.array(vertices[corners[live]].astype(np.int32), dtype=wp.vec3i, device=device)],
        [welded], device, threads, min_chunk=LIGHT_CHUNK,
    )  # fmt: skip
    launch(move_kernel, len(t_holes), [_ints(t_movers, device), _ints(t_holes, device), welded], [welded], device,
           threads, min_chunk=LIGHT_CHUNK)  # fmt: skip
    out = []
    movers, holes = _ints(v_movers, device), _ints(v_holes, device)
    for data in (positions, normals, colors):
        if in_place:
            moved = data
        else:
            moved = wp.empty(n_used, dtype=wp.vec3, device=device)
            wp.copy(moved, data, count=n_used)
        launch(move_kernel, len(v_holes), [movers, holes, data], [moved], device, threads, min_chunk=LIGHT_CHUNK)
        out.append(moved[:n_used])
    triangles = welded[:n_kept]
    if len(v_holes):
        # a moved vertex v >= n_used is renumbered index[v - n_used]
        index = np.full(n_vertices - n_used, -1, dtype=np.int32)
        index[v_movers - n_used] = v_holes
        launch(renumber_kernel, n_kept, [_ints(index, device), n_used], [triangles], device, threads,
               min_chunk=LIGHT_CHUNK)  # fmt: skip
    return (triangles, *out, len(removed))


def _fill_from_end(gone: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Compaction of ``n`` slots of which the sorted ``gone`` go: (holes, movers), the
    slots below the new size ``n - len(gone)`` that went and the kept slots at or above
    it that fill them, both ascending and of one length."""
    size = n - len(gone)
    tail = np.ones(len(gone), dtype=bool)
    tail[gone[gone >= size] - size] = False
    return gone[gone < size].astype(np.int32), (size + np.flatnonzero(tail)).astype(np.int32)


def _ints(values: np.ndarray, device) -> wp.array:
    return wp.array(np.ascontiguousarray(values, dtype=np.int32), dtype=wp.int32, device=device)


def contract(
    triangles: np.ndarray, points: np.ndarray, candidate: np.ndarray, valence: np.ndarray, limit: float
) -> tuple[np.ndarray, np.ndarray]:
    """The edge contractions that weld the short edges of a patch of a closed mesh.

    Contracting an edge ``(a, b)`` relabels ``b`` as ``a`` in their
    triangles; the two triangles on the edge collapse and go, and so does any
    pair that ends up back to back at the merged vertex (a fold of zero
    area: where a vertex opposite the edge had three neighbours, it goes
    with it). What is left around the merged vertex must be one fan of three
    triangles or more (the link condition of Dey, Edelsbrunner, Guha and
    Nekhayev, *Topology preserving edge contraction*, Publ. Inst. Math.
    Beograd 66(80), 1999, which keeps the topology), or nothing (a closed
    piece of four vertices, a sliver under ``limit`` thick, goes whole). It
    is refused where the ends have a further common neighbour (a neck: two
    sheets of the surface meet across the edge, and contracting it would
    pinch them), an end is on a boundary (where bounds clip the surface),
    another vertex would keep one or two triangles, a triangle would turn
    over, or a corner would end farther than ``limit`` from the vertex it had
    at the start: every corner moves by at most ``limit``, onto an original
    vertex.

    (The polygonizer runs :func:`contract_patch`, the same rules in a Warp
    kernel; this vectorized form is the reference its tests compare with.)
    Rounds of contractions, each of edges whose ends are at least two edges
    apart (so their stars are disjoint and the checks of one are not changed
    by another, but for the triangles a common neighbour loses), the
    shortest first, until no short edge can go.

    Args:
        triangles: (T, 3) indices into ``points``, consistently oriented:
            every triangle at a candidate (their stars are complete).
        points: (N, 3) positions, model units.
        candidate: (N,) bool, the vertices that may be welded (ends of short edges).
        valence: (N,) the triangles at each vertex in the whole mesh.
        limit: longest edge contracted, model units.

    Returns:
        (corners, alive): (T, 3) the triangles' corners after welding and
        (T,) bool, whether each is still there.
    """
    n = len(points)
    start = np.asarray(triangles, dtype=np.int64)
    cur = start.copy()
    alive = np.ones(len(cur), dtype=bool)
    live = np.arange(len(cur))
    loaded = candidate.copy()  # the candidates whose stars are all in ``live``
    inside = np.bincount(start.reshape(-1), minlength=n)
    outside = valence - inside  # each vertex's triangles not in the patch
    valence = outside + inside  # kept up to date as triangles go and change
    while True:
        tris = cur[live]
        frm, to = tris.reshape(-1), tris[:, [1, 2, 0]].reshape(-1)
        keys, uses = _unique_counts(np.minimum(frm, to) * n + np.maximum(frm, to))
        eu, ew = keys // n, keys % n  # undirected edges, eu < ew
        open_end = np.zeros(n, dtype=bool)
        open_end[eu[uses != 2]] = open_end[ew[uses != 2]] = True
        # lengths of the edges between loaded closed ends only (each row's norm is the same alone)
        c = np.flatnonzero(loaded[eu] & loaded[ew] & ~open_end[eu] & ~open_end[ew])
        length = np.linalg.norm(points[eu[c]] - points[ew[c]], axis=1)
        short = length <= limit
        c, length = c[short], length[short]
        if len(c) == 0:
            break
        keep, move = eu[c], ew[c]
        owner, row = _stars(tris, keep, move, n)
        before = tris[row]
        merged = np.where(before == move[owner, None], keep[owner, None], before)
        collapsed = (merged[:, 0] == merged[:, 1]) | (merged[:, 1] == merged[:, 2]) | (merged[:, 0] == merged[:, 2])
        # rotated to (k, u, w) with k the merged vertex: u -> w is an edge of its link
        slot = np.argmax(merged == keep[owner, None], axis=1)
        u = merged[np.arange(len(row)), (slot + 1) % 3]
        w = merged[np.arange(len(row)), (slot + 2) % 3]
        fan = (owner * n + u) * n + w
        fold = ~collapsed & _isin((owner * n + w) * n + u, fan[~collapsed])
        stay = ~collapsed & ~fold
        ok, order = _one_fan(owner, u, w, stay, n, len(c))
        node_owner = owner[order]
        # the merged vertex is the lower end, else the upper one, where no corner then ends farther
        # than limit from its first vertex (earlier rounds checked the others) and no triangle turns over
        # both choices at once: rows [0, m) onto the lower end, [m, 2m) onto the upper one
        m = len(order)
        slot_order = slot[order]
        merged_order = merged[order]
        origin = points[start[live[row[order]], slot_order]]
        n0 = _normals(points, before[order])
        flat = ~np.any(n0 != 0.0, axis=1)  # a zero-area triangle has no orientation to keep
        new = np.concatenate([merged_order, merged_order])
        moved = np.concatenate([keep[node_owner], move[node_owner]])
        new[np.arange(2 * m), np.concatenate([slot_order, slot_order])] = moved
        n1 = _normals(points, new)
        far = np.sum((points[moved] - np.concatenate([origin, origin])) ** 2, axis=1) > limit * limit
        turned = (np.einsum("ij,ij->i", np.concatenate([n0, n0]), n1) <= 0.0) & ~np.concatenate([flat, flat])
        bad = far | turned
        lower = np.bincount(node_owner[bad[:m]], minlength=len(c)) == 0
        upper = np.bincount(node_owner[bad[m:]], minlength=len(c)) == 0
        ok &= lower | upper
        after = np.where(lower[node_owner, None], new[:m], new[m:])
        # every other vertex keeps three triangles or none
        lost = (owner[~stay, None] * n + merged[~stay]).reshape(-1)
        lost = lost[merged[~stay].reshape(-1) != np.repeat(keep[owner[~stay]], 3)]
        pair, times = _unique_counts(lost)
        left = valence[pair % n] - times
        ok[(pair // n)[(left > 0) & (left < 3)]] = False
        go = np.flatnonzero(ok)
        if len(go) == 0:
            break
        chosen = np.zeros(len(c), dtype=bool)
        chosen[go[_apart(keys[c[go]], length[go], keep[go], move[go], eu, ew, n)]] = True
        # a vertex next to two of them loses triangles to both: it too keeps three or none
        while True:
            taken = chosen[pair // n]
            total = np.bincount(pair[taken] % n, weights=times[taken], minlength=n)[pair % n]
            rest = valence[pair % n] - total
            clash = taken & (total > times) & (rest > 0) & (rest < 3)
            if not np.any(clash):
                break
            chosen[(pair // n)[clash]] = False
        gone = live[row[~stay & chosen[owner]]]  # (the stars taken are disjoint: each row once)
        valence -= np.bincount(cur[gone].reshape(-1), minlength=n)  # (bincount: ufunc.at is slow)
        alive[gone] = False
        pick = chosen[node_owner]
        changed = live[row[order[pick]]]
        valence -= np.bincount(cur[changed].reshape(-1), minlength=n)
        cur[changed] = after[pick]
        valence += np.bincount(after[pick].reshape(-1), minlength=n)
        # a short edge next round has an end among this round's and the other a candidate next
        # to it: work on those candidates' stars only
        live = live[alive[live]]
        tris = cur[live]
        ends = np.zeros(n, dtype=bool)
        ends[keep] = ends[move] = True
        near = tris[np.any(ends[tris], axis=1)].reshape(-1)
        loaded[:] = False
        loaded[near] = candidate[near]
        live = live[np.any(loaded[tris], axis=1)]
    return cur, alive


def _stars(tris: np.ndarray, keep: np.ndarray, move: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The triangles at either end of each edge ``(keep[i], move[i])``, once
    each: (owner edge, row of ``tris``) pairs."""
    ends = np.zeros(n, dtype=bool)
    ends[keep] = ends[move] = True
    sub = np.flatnonzero(np.any(ends[tris], axis=1))  # the rows at an end, in order: the same stars
    corners = tris[sub].reshape(-1)
    by_vertex = np.argsort(corners, kind="stable")
    here = np.bincount(corners, minlength=n)
    first = np.cumsum(here) - here
    o1, at1 = _expand(first[keep], here[keep])
    o2, at2 = _expand(first[move], here[move])
    both = np.any(tris[sub[by_vertex[at2] // 3]] == keep[o2, None], axis=1)  # listed at the kept end already
    return np.concatenate([o1, o2[~both]]), sub[by_vertex[np.concatenate([at1, at2[~both]])] // 3]


def _one_fan(owner: np.ndarray, u: np.ndarray, w: np.ndarray, stay: np.ndarray, n: int, count: int):
    """Whether the link of each merged vertex (one edge ``u -> w`` per staying
    row, by owner) is one simple cycle of three edges or more, or nothing
    (a closed piece of four vertices going whole): (ok per owner, the staying
    rows sorted by their link edge's start)."""
    ok = np.ones(count, dtype=bool)
    order = np.flatnonzero(stay)[np.argsort(owner[stay] * n + u[stay], kind="stable")]
    node_owner = owner[order]
    starts, ends = node_owner * n + u[order], node_owner * n + w[order]
    ok[node_owner[_repeated_sorted(starts) | _repeated(ends) | ~_isin_sorted(ends, starts)]] = False
    succ = np.minimum(np.searchsorted(starts, ends), max(len(order) - 1, 0))
    succ = np.where(starts[succ] == ends, succ, np.arange(len(order)))  # (a broken link stays in its owner)
    label = np.arange(len(order))
    for _ in range(int(np.ceil(np.log2(max(len(order), 2)))) + 1):  # pointer doubling: the least edge of each cycle
        least = np.minimum(label, label[succ])
        if np.array_equal(least, label):
            # converged: on every cycle (the links that pass) each label is its cycle's least
            # already; what a broken link's rows get does not matter, its owner is refused
            break
        label = least
        succ = succ[succ]
    ok &= np.bincount(node_owner[label == np.arange(len(order))], minlength=count) <= 1
    ok[node_owner[np.bincount(label, minlength=len(order))[label] < 3]] = False
    return ok, order


def _apart(keys, length, keep, move, eu, ew, n: int) -> np.ndarray:
    """Which of the edges ``(keep[i], move[i])`` go this round: each that is
    the shortest of those with an end at or next to its own ends, so that
    the stars of the edges taken are disjoint. Equal lengths (coincident
    vertices, or a column of grid vertices the surface passes through, as on
    the mug) are ordered by a hash of the edge key, so that a row of them is
    not taken one per round (Luby's independent sets). The hash must mix
    (splitmix64's finalizer, :func:`_mix`): the keys along such a row are an
    arithmetic sequence, which a multiplicative hash keeps in order (mug at
    h = 0.05: 30 rounds with one, 7 with the mixer)."""
    rank = np.empty(len(keys), dtype=np.int64)
    rank[np.lexsort((_mix(keys), length))] = np.arange(len(keys))
    least = np.full(n, len(keys))
    np.minimum.at(least, keep, rank)
    np.minimum.at(least, move, rank)
    spread = least.copy()
    np.minimum.at(spread, eu, least[ew])
    np.minimum.at(spread, ew, least[eu])
    return (spread[keep] == rank) & (spread[move] == rank)


def _mix(keys: np.ndarray) -> np.ndarray:
    """splitmix64's finalizer (Steele, Lea & Flood, *Fast splittable
    pseudorandom number generators*, OOPSLA 2014) of int64 ``keys``: uint64
    values with no trace of the keys' order."""
    z = keys.astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _isin(query: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """Whether each of ``query`` is among ``keys`` (int64 arrays)."""
    if len(keys) == 0:
        return np.zeros(len(query), dtype=bool)
    keys = np.sort(keys)
    return keys[np.minimum(np.searchsorted(keys, query), len(keys) - 1)] == query


def _unique_counts(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_counts=True)`` for an int64 array, without its overhead."""
    keys = np.sort(keys)
    if len(keys) == 0:
        return keys, np.zeros(0, dtype=np.int64)
    first = np.empty(len(keys), dtype=bool)
    first[0] = True
    np.not_equal(keys[1:], keys[:-1], out=first[1:])
    at = np.flatnonzero(first)
    return keys[at], np.diff(at, append=len(keys))


def _isin_sorted(query: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """:func:`_isin` for ``keys`` sorted already."""
    if len(keys) == 0:
        return np.zeros(len(query), dtype=bool)
    return keys[np.minimum(np.searchsorted(keys, query), len(keys) - 1)] == query


def _repeated(keys: np.ndarray) -> np.ndarray:
    """Whether each of ``keys`` occurs more than once."""
    order = np.argsort(keys, kind="stable")
    out = np.empty(len(keys), dtype=bool)
    out[order] = _repeated_sorted(keys[order])
    return out


def _repeated_sorted(keys: np.ndarray) -> np.ndarray:
    """:func:`_repeated` for ``keys`` sorted already."""
    out = np.zeros(len(keys), dtype=bool)
    same = keys[1:] == keys[:-1]
    out[1:] |= same
    out[:-1] |= same
    return out


def _normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(T, 3) cross products (b - a) x (c - a) of the triangles ``(a, b, c)``,
    the same floating-point operations as ``np.cross`` without its overhead."""
    a = points[tris[:, 0]]
    e1 = points[tris[:, 1]] - a
    e2 = points[tris[:, 2]] - a
    out = np.empty_like(e1)
    out[:, 0] = e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1]
    out[:, 1] = e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2]
    out[:, 2] = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    return out


def _expand(first: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(owner, index): the indices ``first[i] .. first[i] + count[i] - 1`` of each ``i``, flat, with their ``i``."""
    owner = np.repeat(np.arange(len(first)), count)
    return owner, np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count) + first[owner]


# ---------------------------------------------------------------------------
# the contraction as one Warp kernel: the same rules as :func:`contract`, the
# edges taken one after another (each sees the mesh the previous ones left)
# ---------------------------------------------------------------------------


@wp.func
def _find(parent: wp.array(dtype=wp.int32), v: int):
    """The label vertex ``v`` now has (union-find root, paths compressed)."""
    r = v
    while parent[r] != r:
        r = parent[r]
    x = v
    while parent[x] != r:
        nx = parent[x]
        parent[x] = r
        x = nx
    return r


@wp.func
def _rotated(t: wp.vec3i, e: int):
    """(u, w): the corners after ``e`` in triangle ``t`` (u -> w is an edge of e's link); (-1, -1) without e."""
    out = wp.vec2i(-1, -1)
    for s in range(3):
        if t[s] == e:
            out = wp.vec2i(t[(s + 1) % 3], t[(s + 2) % 3])
    return out


@wp.func
def _closed_at(
    e: int,
    m: int,
    rows: wp.array(dtype=wp.int32),
    cur: wp.array(dtype=wp.vec3i),
    row_u: wp.array(dtype=wp.int32),
    row_w: wp.array(dtype=wp.int32),
):
    """Whether every edge at ``e`` among the triangles ``rows[:m]`` is used by
    exactly two of them (``row_u``, ``row_w``: scratch, overwritten)."""
    for i in range(m):
        r = _rotated(cur[rows[i]], e)
        row_u[i] = r[0]
        row_w[i] = r[1]
    ok = bool(True)
    for i in range(m):
        if row_u[i] >= 0:
            for side in range(2):
                x = wp.where(side == 0, row_u[i], row_w[i])
                uses = int(0)
                for j in range(m):
                    if row_u[j] == x:
                        uses += 1
                    if row_w[j] == x:
                        uses += 1
                if uses != 2:
                    ok = False
    return ok


@wp.func
def _normal(p: wp.array(dtype=wp.vec3), t: wp.vec3i):
    return wp.cross(p[t[1]] - p[t[0]], p[t[2]] - p[t[0]])


@wp.func
def _try_contract(
    k: int,
    o: int,
    qid: int,
    limit: float,
    start: wp.array(dtype=wp.vec3i),
    points: wp.array(dtype=wp.vec3),
    star_offsets: wp.array(dtype=wp.int32),
    star_items: wp.array(dtype=wp.int32),
    cur: wp.array(dtype=wp.vec3i),
    alive: wp.array(dtype=wp.int32),
    valence: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    chain_next: wp.array(dtype=wp.int32),
    chain_tail: wp.array(dtype=wp.int32),
    stamp: wp.array(dtype=wp.int32),
    rows: wp.array(dtype=wp.int32),
    row_u: wp.array(dtype=wp.int32),
    row_w: wp.array(dtype=wp.int32),
    row_state: wp.array(dtype=wp.int32),
    row_slot: wp.array(dtype=wp.int32),
):
    """Contract the edge between labels ``k`` and ``o`` (k < o) if the rules
    of :func:`contract` allow it; returns 1 when it did."""
    # the triangles at either end: those of every vertex merged into k or o so far
    m = int(0)
    for e in range(2):
        u = wp.where(e == 0, k, o)
        while u >= 0:
            for q in range(star_offsets[u], star_offsets[u + 1]):
                t = star_items[q]
                if alive[t] != 0 and stamp[t] != qid:
                    stamp[t] = qid
                    c = cur[t]
                    if c[0] == k or c[1] == k or c[2] == k or c[0] == o or c[1] == o or c[2] == o:
                        rows[m] = t
                        m += 1
            u = chain_next[u]
    # both ends closed (not on a boundary), and the edge on exactly two triangles
    if not (_closed_at(k, m, rows, cur, row_u, row_w) and _closed_at(o, m, rows, cur, row_u, row_w)):
        return 0
    n_collapsed = int(0)
    for i in range(m):
        c = cur[rows[i]]
        merged = c
        has_k = bool(False)
        has_o = bool(False)
        for s in range(3):
            if c[s] == k:
                has_k = True
            if c[s] == o:
                has_o = True
                merged[s] = k
        if has_k and has_o:
            row_state[i] = 0  # collapsed
            n_collapsed += 1
        else:
            row_state[i] = 2
            r = _rotated(merged, k)
            row_u[i] = r[0]
            row_w[i] = r[1]
            for s in range(3):
                if merged[s] == k:
                    row_slot[i] = s
    if n_collapsed != 2:
        return 0
    # folds: pairs back to back at the merged vertex
    for i in range(m):
        if row_state[i] != 0:
            for j in range(m):
                if row_state[j] != 0 and row_u[j] == row_w[i] and row_w[j] == row_u[i]:
                    row_state[i] = 1
    # the link of the merged vertex: one simple cycle of three edges or more, or nothing
    n_stay = int(0)
    first = int(-1)
    for i in range(m):
        if row_state[i] == 2:
            n_stay += 1
            if first < 0:
                first = i
            for j in range(m):
                if j != i and row_state[j] == 2 and (row_u[j] == row_u[i] or row_w[j] == row_w[i]):
                    return 0
    if n_stay > 0:
        if n_stay < 3:
            return 0
        steps = int(0)
        i = first
        while steps <= n_stay:
            nxt = int(-1)
            for j in range(m):
                if row_state[j] == 2 and row_u[j] == row_w[i]:
                    nxt = j
            if nxt < 0:
                return 0
            steps += 1
            i = nxt
            if i == first:
                break
        if steps != n_stay:
            return 0
    # every other vertex keeps three triangles or none
    for i in range(m):
        if row_state[i] != 2:
            c = cur[rows[i]]
            for s in range(3):
                x = c[s]
                if x != k and x != o:
                    times = int(0)
                    for j in range(m):
                        if row_state[j] != 2:
                            cj = cur[rows[j]]
                            for sj in range(3):
                                if cj[sj] == x:
                                    times += 1
                    left = valence[x] - times
                    if left > 0 and left < 3:
                        return 0
    # the merged vertex is k, else o: no corner farther than limit from its first vertex, none turned over
    chosen = int(-1)
    for e in range(2):
        if chosen < 0:
            cand = wp.where(e == 0, k, o)
            bad = bool(False)
            for i in range(m):
                if row_state[i] == 2:
                    t = rows[i]
                    before = cur[t]
                    after = before
                    for s in range(3):
                        if before[s] == k or before[s] == o:
                            after[s] = cand
                    n0 = _normal(points, before)
                    n1 = _normal(points, after)
                    flat = n0[0] == 0.0 and n0[1] == 0.0 and n0[2] == 0.0
                    if wp.dot(n0, n1) <= 0.0 and not flat:
                        bad = True
                    if wp.length_sq(points[cand] - points[start[t][row_slot[i]]]) > limit * limit:
                        bad = True
            if not bad:
                chosen = cand
    if chosen < 0:
        return 0
    other = wp.where(chosen == k, o, k)
    for i in range(m):
        t = rows[i]
        c = cur[t]
        for s in range(3):
            valence[c[s]] = valence[c[s]] - 1
        if row_state[i] == 2:
            for s in range(3):
                if c[s] == other:
                    c[s] = chosen
                valence[c[s]] = valence[c[s]] + 1
            cur[t] = c
        else:
            alive[t] = 0
    parent[other] = chosen
    chain_next[chain_tail[chosen]] = other
    chain_tail[chosen] = chain_tail[other]
    return 1


@wp.kernel(enable_backward=False)
def contract_kernel(
    start: wp.array(dtype=wp.vec3i),
    points: wp.array(dtype=wp.vec3),
    candidate: wp.array(dtype=wp.int32),
    star_offsets: wp.array(dtype=wp.int32),
    star_items: wp.array(dtype=wp.int32),
    edges: wp.array(dtype=wp.vec2i),
    limit: float,
    max_passes: int,
    cur: wp.array(dtype=wp.vec3i),
    alive: wp.array(dtype=wp.int32),
    valence: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
    chain_next: wp.array(dtype=wp.int32),
    chain_tail: wp.array(dtype=wp.int32),
    stamp: wp.array(dtype=wp.int32),
    rows: wp.array(dtype=wp.int32),
    row_u: wp.array(dtype=wp.int32),
    row_w: wp.array(dtype=wp.int32),
    row_state: wp.array(dtype=wp.int32),
    row_slot: wp.array(dtype=wp.int32),
):
    """One thread welds a patch: the short edges ``edges`` (sorted, shortest
    first) one after another, then passes over the triangles for short edges
    the contractions made, until a pass contracts none (at most ``max_passes``)."""
    qid = int(0)
    for q in range(edges.shape[0]):
        k = _find(parent, edges[q][0])
        o = _find(parent, edges[q][1])
        if k != o:
            lo = wp.min(k, o)
            hi = wp.max(k, o)
            if wp.length_sq(points[lo] - points[hi]) <= limit * limit:
                qid += 1
                _try_contract(lo, hi, qid, limit, start, points, star_offsets, star_items, cur, alive, valence,
                              parent, chain_next, chain_tail, stamp, rows, row_u, row_w, row_state, row_slot)
    for _p in range(max_passes):
        done = int(0)
        for t in range(cur.shape[0]):
            for s in range(3):
                if alive[t] != 0:
                    c = cur[t]
                    x = c[s]
                    y = c[(s + 1) % 3]
                    short = wp.length_sq(points[x] - points[y]) <= limit * limit
                    if x < y and candidate[x] != 0 and candidate[y] != 0 and short:
                        qid += 1
                        done += _try_contract(x, y, qid, limit, start, points, star_offsets, star_items, cur,
                                              alive, valence, parent, chain_next, chain_tail, stamp, rows,
                                              row_u, row_w, row_state, row_slot)
        if done == 0:
            break


def contract_patch(
    triangles: np.ndarray, points: np.ndarray, candidate: np.ndarray, valence: np.ndarray, limit: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`contract`'s welds by one Warp thread (:data:`contract_kernel`):
    the same arguments and results, the same rules, but the short edges are
    taken one after another, shortest first (ties in the order of the mixing
    hash of :func:`_apart`), each on the mesh the previous ones left, instead
    of in vectorized rounds of edges two apart: no round's bookkeeping, so
    about a millisecond where the rounds took 15 ms (towers h = 0.14). The
    patch's stars are listed once (vertex -> triangles, by a stable sort);
    a vertex merged into another keeps its list, chained to the other's.
    The patch is on the host already (read back by :func:`weld`), so the
    kernel runs on the CPU device whatever the pipeline's device: a GPU would
    run its one thread far slower, and the weld is the same on every device.

    Example:
        >>> import numpy as np
        >>> from warpblob.polygonize._weld import contract_patch
        >>> # a tetrahedron with one vertex split in two, 1e-3 apart
        >>> p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1e-3, 0, 0.999]], float)
        >>> t = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 4], [1, 4, 3], [2, 3, 4]])
        >>> corners, alive = contract_patch(t, p, np.ones(5, bool), np.bincount(t.ravel()), 0.01)
        >>> int(alive.sum())
        4
    """
    tris = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    n = len(points)
    n_tris = len(tris)
    frm, to = tris.reshape(-1), tris[:, [1, 2, 0]].reshape(-1)
    one = (frm < to) & candidate[frm] & candidate[to]  # each edge once (a closed mesh has both directions)
    eu, ew = frm[one], to[one]
    length = np.linalg.norm(points[eu] - points[ew], axis=1)
    short = length <= limit
    eu, ew, length = eu[short], ew[short], length[short]
    order = np.lexsort((_mix(eu * n + ew), length))
    edges = np.column_stack([eu[order], ew[order]]).astype(np.int32)
    corners = tris.reshape(-1)
    by_vertex = np.argsort(corners, kind="stable")
    offsets = np.zeros(n + 1, dtype=np.int32)
    np.cumsum(np.bincount(corners, minlength=n), out=offsets[1:])
    items = (by_vertex // 3).astype(np.int32)
    d = "cpu"

    def arr(x, dtype):
        return wp.array(x, dtype=dtype, device=d)

    ids = np.arange(n, dtype=np.int32)
    cur = arr(tris.astype(np.int32), wp.vec3i)
    alive = wp.full(n_tris, 1, dtype=wp.int32, device=d)
    scratch = [wp.empty(max(n_tris, 1), dtype=wp.int32, device=d) for _ in range(5)]
    wp.launch(
        contract_kernel, dim=1,
        inputs=[arr(tris.astype(np.int32), wp.vec3i), arr(points.astype(np.float32), wp.vec3),
                arr(candidate.astype(np.int32), wp.int32), arr(offsets, wp.int32), arr(items, wp.int32),
                arr(edges.reshape(-1, 2), wp.vec2i), float(limit), 32,
                cur, alive, arr(np.asarray(valence, dtype=np.int32), wp.int32), arr(ids, wp.int32),
                wp.full(n, -1, dtype=wp.int32, device=d), arr(ids, wp.int32),
                wp.zeros(max(n_tris, 1), dtype=wp.int32, device=d),
                *scratch],
        device=d,
    )  # fmt: skip
    return cur.numpy().reshape(-1, 3).astype(np.int64), alive.numpy() != 0
