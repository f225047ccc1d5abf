"""Tangential relaxation of the vertices of skinny triangles (see :func:`relax`).

The vertices are projected back onto the surface by Newton steps along the
gradient, the projection of Hartmann, *A marching method for the
triangulation of surfaces*, CAGD 1998.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .._parallel import launch
from .._stages import check_memory, scan
from ..field._kernels import ModelArrays, make_evaluate
from . import _weld
from ._kernels import CELL_CHUNK, HEAVY_CHUNK, LIGHT_CHUNK, make_project, smallest_angle_cosine

#: relaxation: triangles whose smallest angle is under this (degrees) are improved
RELAX_ANGLE = 10.0
#: the fraction of the way to the neighbours' centroid a vertex moves
RELAX_AMOUNT = 0.5


def make_relax_kernel():
    """The relaxation move (compiled once per process and device), over its
    own point-mode traversal and Newton projection (:func:`make_project`)."""
    project = make_project(make_evaluate(True))

    @wp.kernel(enable_backward=False, module="unique")
    def relax_kernel(
        m: ModelArrays,
        iso: float,
        tolerance: float,
        amount: float,
        reach: float,
        positions: wp.array(dtype=wp.vec3),
        normals: wp.array(dtype=wp.vec3),
        triangles: wp.array(dtype=wp.vec3i),
        corner_vertex: wp.array(dtype=wp.int32),
        corner_triangle: wp.array(dtype=wp.int32),
        n_corners: int,
        offset: int,
        new_positions: wp.array(dtype=wp.vec3),
        new_normals: wp.array(dtype=wp.vec3),
        new_colors: wp.array(dtype=wp.vec3),
        moved: wp.array(dtype=wp.int32),
        evaluations: wp.array(dtype=wp.int32),
    ):
        """Move one vertex of a skinny triangle ``amount`` of the way to the
        centroid of its neighbours, within its tangent plane, then back onto
        the surface by Newton steps along the gradient until ``|F - iso| <=
        tolerance`` (the vertex stays where it was if they do not get there,
        or wander farther than ``reach``). The corners are sorted by vertex;
        the thread of a vertex's first corner does the work, the others stop.
        A move is written at the corner (``new_*[corner]``), and ``moved[v]``
        is that corner + 1 (0: not moved)."""
        tid = wp.tid() + offset
        evaluations[tid] = 0
        v = corner_vertex[tid]
        if tid > 0:
            if corner_vertex[tid - 1] == v:
                return
        first = tid
        last = tid + 1
        while last < n_corners:
            if corner_vertex[last] != v:
                break
            last += 1
        x0 = positions[v]
        n = normals[v]
        acc = wp.vec3(0.0)
        rise = float(0.0)
        spread = float(0.0)
        for q in range(first, last):
            t = triangles[corner_triangle[q]]
            for c in range(3):
                e = positions[t[c]] - x0
                en = wp.dot(e, n)
                acc = acc + e
                rise += en
                spread += wp.dot(e, e) - en * en
        centroid = x0 + acc / (2.0 * float(last - first))
        d = centroid - x0
        step = amount * (d - wp.dot(d, n) * n)
        # the neighbours' mean height over the tangent plane, ~ kappa s^2 / 2, predicts
        # where the surface is at the moved point (one Newton step fewer, usually)
        bend = float(0.0)
        if spread > 0.0:
            bend = rise / spread * wp.dot(step, step)
        r, x, count, ok = project(m, x0 + step + bend * n, iso, tolerance, 8, 0.5 * reach)
        if ok and wp.length(x - x0) <= reach:
            new_positions[tid] = x
            new_normals[tid] = -wp.normalize(wp.vec3(r[1], r[2], r[3]))
            new_colors[tid] = wp.vec3(r[4], r[5], r[6])
            moved[v] = tid + 1
        evaluations[tid] = count

    return relax_kernel


@wp.kernel(enable_backward=False)
def skinny_vertices_kernel(
    positions: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.vec3i),
    cos_limit: float,
    offset: int,
    flags: wp.array(dtype=wp.int32),
):
    """Flag the two ends of the shortest edge of each triangle whose smallest
    angle is under acos(cos_limit) (every writer stores 1, so concurrent
    writes agree)."""
    tid = wp.tid() + offset
    t = triangles[tid]
    p0 = positions[t[0]]
    p1 = positions[t[1]]
    p2 = positions[t[2]]
    if smallest_angle_cosine(p0, p1, p2) > cos_limit:
        # the ends of its shortest edge: pulling them apart mends a needle, and
        # moves fewer vertices than taking all three (towers h = 0.14: 20,226 -> 14,949)
        l0 = wp.length_sq(p1 - p0)
        l1 = wp.length_sq(p2 - p1)
        l2 = wp.length_sq(p0 - p2)
        if l0 <= l1 and l0 <= l2:
            flags[t[0]] = 1
            flags[t[1]] = 1
        elif l1 <= l2:
            flags[t[1]] = 1
            flags[t[2]] = 1
        else:
            flags[t[2]] = 1
            flags[t[0]] = 1


@wp.kernel(enable_backward=False)
def flagged_corners_kernel(
    triangles: wp.array(dtype=wp.vec3i), flags: wp.array(dtype=wp.int32), offset: int, counts: wp.array(dtype=wp.int32)
):
    tid = wp.tid() + offset
    t = triangles[tid]
    counts[tid] = flags[t[0]] + flags[t[1]] + flags[t[2]]


@wp.kernel(enable_backward=False)
def emit_corners_kernel(
    triangles: wp.array(dtype=wp.vec3i),
    flags: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    offset: int,
    corner_vertex: wp.array(dtype=wp.int32),
    corner_triangle: wp.array(dtype=wp.int32),
):
    """(vertex, triangle) of each corner at a flagged vertex, in triangle order."""
    tid = wp.tid() + offset
    t = triangles[tid]
    o = offsets[tid]
    for c in range(3):
        if flags[t[c]] != 0:
            corner_vertex[o] = t[c]
            corner_triangle[o] = tid
            o += 1


@wp.func
def moved_to(
    positions: wp.array(dtype=wp.vec3), new_positions: wp.array(dtype=wp.vec3), moved: wp.array(dtype=wp.int32), v: int
):
    """Vertex ``v``'s position with its move, if it has one (see ``relax_kernel``)."""
    if moved[v] != 0:
        return new_positions[moved[v] - 1]
    return positions[v]


@wp.kernel(enable_backward=False)
def flipped_kernel(
    positions: wp.array(dtype=wp.vec3),
    new_positions: wp.array(dtype=wp.vec3),
    triangles: wp.array(dtype=wp.vec3i),
    moved: wp.array(dtype=wp.int32),
    cos_floor: float,
    weld_length: float,
    offset: int,
    revert: wp.array(dtype=wp.int32),
):
    """Flag for reverting the moved corners of a triangle the moves turned over
    (normal against the old one, unless an old edge was under ``weld_length``),
    collapsed, or left with a smaller smallest angle than ``acos(cos_floor)``
    when it had a larger one."""
    tid = wp.tid() + offset
    t = triangles[tid]
    if moved[t[0]] == 0 and moved[t[1]] == 0 and moved[t[2]] == 0:
        return
    a = positions[t[0]]
    b = positions[t[1]]
    c = positions[t[2]]
    a1 = moved_to(positions, new_positions, moved, t[0])
    b1 = moved_to(positions, new_positions, moved, t[1])
    c1 = moved_to(positions, new_positions, moved, t[2])
    n0 = wp.cross(b - a, c - a)
    n1 = wp.cross(b1 - a1, c1 - a1)
    # an edge the weld left (the ends could not merge without changing the topology) is
    # too short for its triangles' orientation to mean anything: pulling it apart may turn them
    shortest = wp.min(wp.min(wp.length(b - a), wp.length(c - b)), wp.length(a - c))
    turned = wp.dot(n0, n1) <= 0.0 and shortest >= weld_length
    worse = smallest_angle_cosine(a1, b1, c1) > wp.max(cos_floor, smallest_angle_cosine(a, b, c))
    if turned or wp.length_sq(n1) == 0.0 or worse:
        for k in range(3):
            if moved[t[k]] != 0:
                revert[t[k]] = 1


@wp.kernel(enable_backward=False)
def revert_kernel(revert: wp.array(dtype=wp.int32), offset: int, moved: wp.array(dtype=wp.int32)):
    """A flagged vertex's move is dropped."""
    tid = wp.tid() + offset
    if revert[tid] != 0:
        moved[tid] = 0


@wp.kernel(enable_backward=False)
def commit_kernel(
    corner_vertex: wp.array(dtype=wp.int32),
    moved: wp.array(dtype=wp.int32),
    new_positions: wp.array(dtype=wp.vec3),
    new_normals: wp.array(dtype=wp.vec3),
    new_colors: wp.array(dtype=wp.vec3),
    offset: int,
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    committed: wp.array(dtype=wp.int32),
):
    """The kept moves written at their vertices (the corner that holds each), 1 in ``committed`` there."""
    tid = wp.tid() + offset
    v = corner_vertex[tid]
    committed[tid] = 0
    if moved[v] == tid + 1:
        positions[v] = new_positions[tid]
        normals[v] = new_normals[tid]
        colors[v] = new_colors[tid]
        committed[tid] = 1


def relax(
    relax_kernel, m, triangles, positions, normals, colors, iso: float, tolerance: float, h: float, limit: int, device,
    threads=None,
):  # fmt: skip
    """Tangential relaxation of the vertices of skinny triangles (see
    :func:`~warpblob.polygonize.polygonize`'s ``relax``) with the kernel of
    :func:`make_relax_kernel` over model arrays ``m``. The moves are written
    into the (V,) vec3 ``positions``, ``normals`` and ``colors`` given (the
    pipeline's own arrays); returns them, the number of vertices that moved
    and the field evaluations it took; ``h`` (model units) bounds a move,
    ``limit`` the bytes it may allocate.

    The corners at flagged vertices are listed as (vertex, triangle) pairs,
    sorted by vertex (``wp.utils.radix_sort_pairs``, stable), so each vertex
    reads its own triangles without atomics; the thread of a vertex's first
    corner moves it, into that corner's slot of per-corner buffers (no copy
    of the mesh's arrays). Moves are then checked per triangle (none turned
    over, unless it has an edge the weld left, none collapsed or made
    skinnier than both before and the angle limit) and the moved corners of
    a failing triangle are put back, until every triangle passes; the kept
    moves are then written at their vertices."""
    n_vertices = positions.shape[0]
    n_triangles = triangles.shape[0]
    cos_limit = float(np.cos(np.radians(RELAX_ANGLE)))
    flags = wp.zeros(n_vertices, dtype=wp.int32, device=device)
    launch(
        skinny_vertices_kernel, n_triangles, [positions, triangles, cos_limit], [flags],
        device, threads, min_chunk=CELL_CHUNK,
    )  # fmt: skip
    counts = wp.empty(n_triangles, dtype=wp.int32, device=device)
    launch(flagged_corners_kernel, n_triangles, [triangles, flags], [counts], device, threads, min_chunk=LIGHT_CHUNK)
    offsets, n_corners = scan(counts)
    if n_corners == 0:
        return positions, normals, colors, 0, 0
    check_memory("polygonize", "relaxation", n_corners * 60 + n_vertices * 4, limit)
    corner_vertex = wp.empty(2 * n_corners, dtype=wp.int32, device=device)
    corner_triangle = wp.empty(2 * n_corners, dtype=wp.int32, device=device)
    launch(
        emit_corners_kernel, n_triangles, [triangles, flags, offsets], [corner_vertex, corner_triangle],
        device, threads, min_chunk=LIGHT_CHUNK,
    )  # fmt: skip
    wp.utils.radix_sort_pairs(corner_vertex, corner_triangle, n_corners)
    new = [wp.empty(n_corners, dtype=wp.vec3, device=device) for _ in range(3)]
    moved = flags  # the flags are read no more: from here 0, or the corner holding the vertex's move + 1
    moved.zero_()
    evaluations = wp.empty(n_corners, dtype=wp.int32, device=device)
    launch(
        relax_kernel, n_corners,
        [m, float(iso), float(tolerance), RELAX_AMOUNT, float(h), positions, normals, triangles, corner_vertex,
         corner_triangle, n_corners],
        [*new, moved, evaluations], device, threads, min_chunk=HEAVY_CHUNK,
    )  # fmt: skip
    revert = wp.empty(n_vertices, dtype=wp.int32, device=device)
    for _ in range(8):
        revert.zero_()
        inputs = [positions, new[0], triangles, moved, cos_limit, float(_weld.WELD * h)]
        launch(flipped_kernel, n_triangles, inputs, [revert], device, threads, min_chunk=CELL_CHUNK)
        _, n_revert = scan(revert)
        if n_revert == 0:
            break
        launch(revert_kernel, n_vertices, [revert], [moved], device, threads, min_chunk=LIGHT_CHUNK)
    else:  # pragma: no cover - the moves never settled: keep none of them
        return positions, normals, colors, 0, int(evaluations.numpy().sum())
    committed = wp.empty(n_corners, dtype=wp.int32, device=device)
    launch(commit_kernel, n_corners, [corner_vertex, moved, *new], [positions, normals, colors, committed], device,
           threads, min_chunk=LIGHT_CHUNK)  # fmt: skip
    _, n_moved = scan(committed)
    return positions, normals, colors, n_moved, int(evaluations.numpy().sum())
