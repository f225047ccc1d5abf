"""Warp kernels of the planar slicer: classification, section segments, loop chaining, output.

The passes over the mesh run one thread per block of :data:`BLOCK` vertices
or faces: a thread counts its block in registers (count pass, which also
keeps one code byte per face for the later passes), the block counts are
prefix-summed, and the emit pass walks the same block again from its offset,
so no per-face count array is written and the output order is the input
order whatever the thread split. Every kernel takes ``offset``
right after its arrays (see :func:`warpblob._parallel.launch`).

Sides: a vertex is below (-1) where its signed distance ``d`` to the plane is
under ``-epsilon``, above (+1) over ``epsilon``, and on the plane (0) in
between. A face is BELOW or ABOVE when it has vertices on one side only
(a face lying in the plane goes to the side its normal points away from),
SPLIT_EDGES when one vertex is alone on its side, and SPLIT_VERTEX when the
plane passes through one vertex and between the other two.

Section points are coded as int64 keys: ``lo * V + hi`` for the crossing
point of edge ``(lo, hi)``, ``lo < hi``, and ``v * V + v`` for vertex ``v`` on
the plane. A section segment runs the way the below piece of its face walks
the plane (face order), so around a closed section every point is the end of
one segment and the start of the next.
"""

from __future__ import annotations

import itertools

import numpy as np
import warp as wp

#: vertices or faces per thread of the block passes
BLOCK = 1024

BELOW = wp.constant(0)
ABOVE = wp.constant(1)
SPLIT_EDGES = wp.constant(2)
SPLIT_VERTEX = wp.constant(3)


def face_codes() -> np.ndarray:
    """The face code of every side pattern, (27,) int8, indexed by ``9 (s0 + 1) + 3 (s1 + 1) + s2 + 1``.

    A code is ``kind | corner << 2 | flag << 4`` (kinds in the module
    docstring); -1 for the face lying in the plane, which its normal decides.
    """
    table = np.empty(27, dtype=np.int8)
    for s in itertools.product((-1, 0, 1), repeat=3):
        pos, neg = sum(x > 0 for x in s), sum(x < 0 for x in s)
        if pos and neg:
            if pos + neg == 3:
                corner = next(k for k in range(3) if s[k] != s[(k + 1) % 3] and s[k] != s[(k + 2) % 3])
                code = int(SPLIT_EDGES) | corner << 2 | int(s[corner] < 0) << 4
            else:
                corner = s.index(0)
                code = int(SPLIT_VERTEX) | corner << 2 | int(s[(corner + 1) % 3] < 0) << 4
        elif pos:
            code = int(ABOVE)
        elif neg:
            code = int(BELOW)
        else:
            code = -1
        table[9 * (s[0] + 1) + 3 * (s[1] + 1) + s[2] + 1] = code
    return table


@wp.func
def face_print(a: int, b: int, c: int) -> wp.uint64:
    """Sum over the edges x -> y of face (a, b, c) of an antisymmetric hash of the
    directed edge, ``h(x) g(y) - h(y) g(x)`` mod 2^64.

    Summed over a closed, consistently oriented mesh every edge meets its
    reverse and the sum is 0; a boundary edge, or an edge run the same way by
    two faces, leaves a term that cancels only by a 64-bit coincidence. Over
    one face the three terms are the cross product of the points (h, g) of
    its corners, taken relative to the first: two products instead of six.
    """
    # a multiply-xorshift hash (bijective on 64 bits) is enough: a closed mesh sums to 0 whatever the
    # hash, and an open one that slips through still has its open edges checked where the plane cuts them
    k1 = wp.uint64(0x9E3779B97F4A7C15)
    ha = wp.uint64(a) * k1
    hb = wp.uint64(b) * k1
    hc = wp.uint64(c) * k1
    ha = ha ^ (ha >> wp.uint64(29))
    hb = hb ^ (hb >> wp.uint64(29))
    hc = hc ^ (hc >> wp.uint64(29))
    k2 = wp.uint64(0x2545F4914F6CDD1D)
    ga = (ha ^ (ha >> wp.uint64(32))) * k2
    gb = (hb ^ (hb >> wp.uint64(32))) * k2
    gc = (hc ^ (hc >> wp.uint64(32))) * k2
    return (hb - ha) * (gc - ga) - (gb - ga) * (hc - ha)


@wp.func
def side_of(d: float, epsilon: float) -> int:
    s = int(0)
    if d > epsilon:
        s = 1
    elif d < -epsilon:
        s = -1
    return s


@wp.func
def point_key(a: int, b: int, n: int) -> wp.int64:
    """Key of the crossing point of edge (a, b), or of vertex a when a == b."""
    lo = wp.min(a, b)
    hi = wp.max(a, b)
    return wp.int64(lo) * wp.int64(n) + wp.int64(hi)


@wp.func
def code_kind(code: int) -> int:
    return code & 3


@wp.func
def code_corner(code: int) -> int:
    return (code >> 2) & 3


@wp.func
def code_flag(code: int) -> int:
    return code >> 4


@wp.func
def piece_counts(code: int) -> wp.vec2i:
    """Triangles a face of ``code`` gives the part below and the part above."""
    kind = code_kind(code)
    below = int(0)
    above = int(0)
    if kind == BELOW:
        below = 1
    elif kind == ABOVE:
        above = 1
    elif kind == SPLIT_VERTEX:
        below = 1
        above = 1
    elif code_flag(code) == 1:
        below = 1
        above = 2
    else:
        below = 2
        above = 1
    return wp.vec2i(below, above)


@wp.kernel(enable_backward=False)
def distance_kernel(
    positions: wp.array(dtype=wp.vec3),
    origin: wp.vec3d,
    normal: wp.vec3d,
    offset: int,
    distances: wp.array(dtype=wp.float32),
    lower: wp.array(dtype=wp.vec3),
    upper: wp.array(dtype=wp.vec3),
    bad: wp.array(dtype=wp.int32),
):
    """Signed distances to the plane (float64 arithmetic); each block's box and first non-finite vertex."""
    block = wp.tid() + offset
    start = block * BLOCK
    end = wp.min(start + BLOCK, positions.shape[0])
    lo = positions[start]
    hi = positions[start]
    first_bad = int(-1)
    for i in range(start, end):
        p = positions[i]
        if not wp.isfinite(p):
            if first_bad < 0:
                first_bad = i
        lo = wp.min(lo, p)
        hi = wp.max(hi, p)
        distances[i] = wp.float32(wp.dot(wp.vec3d(p) - origin, normal))
    lower[block] = lo
    upper[block] = hi
    bad[block] = first_bad


@wp.kernel(enable_backward=False)
def classify_kernel(
    triangles: wp.array(dtype=wp.vec3i),
    distances: wp.array(dtype=wp.float32),
    positions: wp.array(dtype=wp.vec3),
    table: wp.array(dtype=wp.int8),
    normal: wp.vec3d,
    epsilon: float,
    offset: int,
    codes: wp.array(dtype=wp.int8),
    below_counts: wp.array(dtype=wp.int32),
    above_counts: wp.array(dtype=wp.int32),
    segment_counts: wp.array(dtype=wp.int32),
    record_counts: wp.array(dtype=wp.int32),
    used_below: wp.array(dtype=wp.int8),
    used_above: wp.array(dtype=wp.int8),
    prints: wp.array(dtype=wp.uint64),
    bad: wp.array(dtype=wp.int32),
):
    """Count pass over a block of faces: each face's code (:func:`face_codes`),
    triangles for each part, section segments, in-plane edges; marks which part
    uses each vertex on the plane (every writer stores 1, so concurrent writes
    agree); sums the face prints; the block's first bad face."""
    block = wp.tid() + offset
    start = block * BLOCK
    end = wp.min(start + BLOCK, triangles.shape[0])
    n = distances.shape[0]
    n_below = int(0)
    n_above = int(0)
    n_segments = int(0)
    n_records = int(0)
    total = wp.uint64(0)
    first_bad = int(-1)
    for f in range(start, end):
        t = triangles[f]
        valid = t[0] >= 0 and t[1] >= 0 and t[2] >= 0 and t[0] < n and t[1] < n and t[2] < n
        if valid:
            valid = t[0] != t[1] and t[1] != t[2] and t[2] != t[0]
        if not valid:
            if first_bad < 0:
                first_bad = f
            codes[f] = wp.int8(BELOW)
            continue
        total += face_print(t[0], t[1], t[2])
        s0 = side_of(distances[t[0]], epsilon)
        s1 = side_of(distances[t[1]], epsilon)
        s2 = side_of(distances[t[2]], epsilon)
        code = int(table[(s0 + 1) * 9 + (s1 + 1) * 3 + s2 + 1])
        if code < 0:
            # in the plane: the solid lies behind the face, so a face turned up closes the part below
            a = positions[t[0]]
            up = wp.dot(wp.vec3d(wp.cross(positions[t[1]] - a, positions[t[2]] - a)), normal)
            code = wp.where(up >= wp.float64(0.0), BELOW, ABOVE)
        codes[f] = wp.int8(code)
        counts = piece_counts(code)
        n_below += counts[0]
        n_above += counts[1]
        kind = code_kind(code)
        if kind >= SPLIT_EDGES:
            n_segments += 1
            if kind == SPLIT_VERTEX:
                z = t[code_corner(code)]
                used_below[z] = wp.int8(1)
                used_above[z] = wp.int8(1)
        elif s0 == 0 or s1 == 0 or s2 == 0:
            s = wp.vec3i(s0, s1, s2)
            for k in range(3):
                if s[k] == 0:
                    if kind == BELOW:
                        used_below[t[k]] = wp.int8(1)
                    else:
                        used_above[t[k]] = wp.int8(1)
                    if s[(k + 1) % 3] == 0:
                        n_records += 1
    below_counts[block] = n_below
    above_counts[block] = n_above
    segment_counts[block] = n_segments
    record_counts[block] = n_records
    prints[block] = total
    bad[block] = first_bad


@wp.kernel(enable_backward=False)
def keep_count_kernel(
    distances: wp.array(dtype=wp.float32),
    used_below: wp.array(dtype=wp.int8),
    used_above: wp.array(dtype=wp.int8),
    epsilon: float,
    offset: int,
    below_counts: wp.array(dtype=wp.int32),
    above_counts: wp.array(dtype=wp.int32),
    on_plane_counts: wp.array(dtype=wp.int32),
):
    """Vertices each part keeps, per block: its own side, and those on the plane
    that it uses; and how many vertices lie on the plane."""
    block = wp.tid() + offset
    start = block * BLOCK
    end = wp.min(start + BLOCK, distances.shape[0])
    n_below = int(0)
    n_above = int(0)
    n_on = int(0)
    for i in range(start, end):
        s = side_of(distances[i], epsilon)
        if s == 0:
            n_on += 1
        if s < 0 or (s == 0 and used_below[i] != wp.int8(0)):
            n_below += 1
        if s > 0 or (s == 0 and used_above[i] != wp.int8(0)):
            n_above += 1
    below_counts[block] = n_below
    above_counts[block] = n_above
    on_plane_counts[block] = n_on


@wp.kernel(enable_backward=False)
def section_kernel(
    triangles: wp.array(dtype=wp.vec3i),
    codes: wp.array(dtype=wp.int8),
    distances: wp.array(dtype=wp.float32),
    epsilon: float,
    segment_counts: wp.array(dtype=wp.int32),
    segment_offsets: wp.array(dtype=wp.int32),
    record_counts: wp.array(dtype=wp.int32),
    record_offsets: wp.array(dtype=wp.int32),
    records: int,
    offset: int,
    starts: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int64),
    record_keys: wp.array(dtype=wp.int64),
    record_edges: wp.array(dtype=wp.vec3i),
):
    """Emit pass over a block of faces that the plane meets: the section segment of
    every split face (``starts``/``ends`` keys), and with ``records`` 1 every
    in-plane edge of a whole face (``record_keys``; ``record_edges`` = from, to,
    part of the face). Blocks with neither are left at once."""
    block = wp.tid() + offset
    wanted = segment_counts[block]
    if records != 0:
        wanted += record_counts[block]
    if wanted == 0:
        return
    start = block * BLOCK
    end = wp.min(start + BLOCK, triangles.shape[0])
    n = distances.shape[0]
    seg = segment_offsets[block]
    rec = record_offsets[block]
    for f in range(start, end):
        code = int(codes[f])
        kind = code_kind(code)
        if kind < SPLIT_EDGES and records == 0:
            continue
        t = triangles[f]
        r = code_corner(code)
        a = t[r]
        b = t[(r + 1) % 3]
        c = t[(r + 2) % 3]
        if kind == SPLIT_EDGES:
            x = point_key(a, b, n)
            y = point_key(c, a, n)
            if code_flag(code) == 1:
                starts[seg] = x
                ends[seg] = y
            else:
                starts[seg] = y
                ends[seg] = x
            seg += 1
        elif kind == SPLIT_VERTEX:
            x = point_key(b, c, n)
            z = point_key(a, a, n)
            if code_flag(code) == 1:
                starts[seg] = x
                ends[seg] = z
            else:
                starts[seg] = z
                ends[seg] = x
            seg += 1
        else:
            for k in range(3):
                u = t[k]
                v = t[(k + 1) % 3]
                if side_of(distances[u], epsilon) == 0 and side_of(distances[v], epsilon) == 0:
                    record_keys[rec] = point_key(u, v, n)
                    record_edges[rec] = wp.vec3i(u, v, kind)
                    rec += 1


@wp.kernel(enable_backward=False)
def plane_edge_kernel(
    keys: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
    edges: wp.array(dtype=wp.vec3i),
    n_records: int,
    offset: int,
    boundary: wp.array(dtype=wp.int32),
    bad: wp.array(dtype=wp.int32),
):
    """Pair ``i`` of the sorted in-plane edges: ``boundary`` 1 where its two faces
    lie in different parts (the section runs along it); the smallest ``i`` whose
    edge has other than two faces goes to ``bad``."""
    i = wp.tid() + offset
    k = 2 * i
    paired = False
    if k + 1 < n_records:
        paired = keys[k] == keys[k + 1]
    if k + 2 < n_records:
        if keys[k + 2] == keys[k]:
            paired = False
    if k > 0:
        if keys[k - 1] == keys[k]:
            paired = False
    if not paired:
        wp.atomic_min(bad, 0, i)
        boundary[i] = 0
    else:
        boundary[i] = wp.where(edges[order[k]][2] != edges[order[k + 1]][2], 1, 0)


@wp.kernel(enable_backward=False)
def plane_segment_kernel(
    pairs: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
    edges: wp.array(dtype=wp.vec3i),
    n: int,
    first: int,
    offset: int,
    starts: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int64),
):
    """The section segment along in-plane edge pair ``pairs[i]``, the way its face below runs it."""
    i = wp.tid() + offset
    e0 = edges[order[2 * pairs[i]]]
    e1 = edges[order[2 * pairs[i] + 1]]
    e = wp.where(e0[2] == BELOW, e0, e1)
    starts[first + i] = point_key(e[0], e[0], n)
    ends[first + i] = point_key(e[1], e[1], n)


@wp.kernel(enable_backward=False)
def endpoint_kernel(
    starts: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int64),
    offset: int,
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
):
    """Both ends of segment ``s`` as sort entries ``s`` (start) and ``S + s`` (end)."""
    s = wp.tid() + offset
    count = starts.shape[0]
    keys[s] = starts[s]
    keys[count + s] = ends[s]
    values[s] = s
    values[count + s] = count + s


@wp.kernel(enable_backward=False)
def point_heads_kernel(
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
    n: int,
    segments: int,
    offset: int,
    heads: wp.array(dtype=wp.int32),
    crossing_heads: wp.array(dtype=wp.int32),
    is_start: wp.array(dtype=wp.int32),
):
    """Flags of sorted entry ``k``: the first of its key (a new point), a new crossing
    point (not a vertex), and whether it is a segment's start."""
    k = wp.tid() + offset
    head = int(1)
    if k > 0:
        if keys[k] == keys[k - 1]:
            head = 0
    heads[k] = head
    key = keys[k]
    crossing = key / wp.int64(n) != key % wp.int64(n)
    crossing_heads[k] = wp.where(head == 1 and crossing, 1, 0)
    is_start[k] = wp.where(values[k] < segments, 1, 0)


@wp.kernel(enable_backward=False)
def point_ids_kernel(
    keys: wp.array(dtype=wp.int64),
    values: wp.array(dtype=wp.int32),
    heads: wp.array(dtype=wp.int32),
    head_offsets: wp.array(dtype=wp.int32),
    crossing_heads: wp.array(dtype=wp.int32),
    crossing_offsets: wp.array(dtype=wp.int32),
    start_offsets: wp.array(dtype=wp.int32),
    segments: int,
    offset: int,
    start_point: wp.array(dtype=wp.int32),
    end_point: wp.array(dtype=wp.int32),
    point_keys: wp.array(dtype=wp.int64),
    crossing_rank: wp.array(dtype=wp.int32),
    start_order: wp.array(dtype=wp.int32),
    end_order: wp.array(dtype=wp.int32),
):
    """Point id of sorted entry ``k`` into its segment's start or end; each point's
    key and rank among crossing points (-1 for vertices); segments in order of
    their start (``start_order``) and of their end (``end_order``)."""
    k = wp.tid() + offset
    p = head_offsets[k] + heads[k] - 1
    if heads[k] == 1:
        point_keys[p] = keys[k]
        crossing_rank[p] = wp.where(crossing_heads[k] == 1, crossing_offsets[k], -1)
    v = values[k]
    if v < segments:
        start_point[v] = p
        start_order[start_offsets[k]] = v
    else:
        end_point[v - segments] = p
        end_order[k - start_offsets[k]] = v - segments


@wp.kernel(enable_backward=False)
def link_kernel(
    starts: wp.array(dtype=wp.int64),
    ends: wp.array(dtype=wp.int64),
    start_order: wp.array(dtype=wp.int32),
    end_order: wp.array(dtype=wp.int32),
    n: int,
    offset: int,
    previous: wp.array(dtype=wp.int32),
    bad: wp.array(dtype=wp.int32),
    pinched: wp.array(dtype=wp.int32),
):
    """The ``j``-th segment by end key runs into the ``j``-th by start key. Where
    the keys differ a point has unequal numbers of segments in and out (an open
    section), and a crossing point met twice has an edge of four or more faces:
    the smallest such ``j`` goes to ``bad``. A vertex met twice (the section
    touches itself there) sets ``pinched``: such pairs are made again by angle."""
    j = wp.tid() + offset
    s = start_order[j]
    e = end_order[j]
    key = starts[s]
    ok = key == ends[e]
    if j + 1 < starts.shape[0]:
        if starts[start_order[j + 1]] == key:
            if key / wp.int64(n) != key % wp.int64(n):
                ok = False
            else:
                pinched[0] = 1
    if not ok:
        wp.atomic_min(bad, 0, j)
    previous[s] = e


@wp.kernel(enable_backward=False)
def jump_kernel(
    previous: wp.array(dtype=wp.int32),
    label: wp.array(dtype=wp.int32),
    distance: wp.array(dtype=wp.int32),
    step: int,
    offset: int,
    previous_out: wp.array(dtype=wp.int32),
    label_out: wp.array(dtype=wp.int32),
    distance_out: wp.array(dtype=wp.int32),
):
    """One pointer-jumping round over the loops (Wyllie 1979): with ``label``
    the smallest segment among the ``step`` before each one and ``distance``
    how far back the first of them lies, double both windows."""
    s = wp.tid() + offset
    p = previous[s]
    own = label[s]
    other = label[p]
    if other < own:
        label_out[s] = other
        distance_out[s] = distance[p] + step
    else:
        label_out[s] = own
        distance_out[s] = distance[s]
    previous_out[s] = previous[p]


@wp.kernel(enable_backward=False)
def point_kernel(
    point_keys: wp.array(dtype=wp.int64),
    crossing_rank: wp.array(dtype=wp.int32),
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    origin: wp.vec3d,
    normal: wp.vec3d,
    axis_u: wp.vec3d,
    axis_v: wp.vec3d,
    below_first: int,
    above_first: int,
    offset: int,
    below_positions: wp.array(dtype=wp.vec3),
    below_normals: wp.array(dtype=wp.vec3),
    below_colors: wp.array(dtype=wp.vec3),
    above_positions: wp.array(dtype=wp.vec3),
    above_normals: wp.array(dtype=wp.vec3),
    above_colors: wp.array(dtype=wp.vec3),
    plane_coords: wp.array(dtype=wp.vec2d),
):
    """A new vertex at each crossing point, in both parts: position where the edge
    meets the plane (float64 arithmetic), normal and colour interpolated; and the
    plane coordinates of every section point (of the stored float32 position)."""
    p = wp.tid() + offset
    key = point_keys[p]
    n = wp.int64(positions.shape[0])
    a = int(key / n)
    b = int(key % n)
    x = wp.vec3d(positions[a])
    rank = crossing_rank[p]
    if rank >= 0:
        y = wp.vec3d(positions[b])
        da = wp.dot(x - origin, normal)
        db = wp.dot(y - origin, normal)
        t = da / (da - db)
        q = wp.vec3(x + t * (y - x))
        tf = wp.float32(t)
        m = normals[a] + tf * (normals[b] - normals[a])
        length = wp.length(m)
        if length > wp.float32(0.0):
            m = m / length
        col = colors[a] + tf * (colors[b] - colors[a])
        below_positions[below_first + rank] = q
        below_normals[below_first + rank] = m
        below_colors[below_first + rank] = col
        above_positions[above_first + rank] = q
        above_normals[above_first + rank] = m
        above_colors[above_first + rank] = col
        x = wp.vec3d(q)
    plane_coords[p] = wp.vec2d(wp.dot(x - origin, axis_u), wp.dot(x - origin, axis_v))


@wp.kernel(enable_backward=False)
def keep_kernel(
    distances: wp.array(dtype=wp.float32),
    used_below: wp.array(dtype=wp.int8),
    used_above: wp.array(dtype=wp.int8),
    positions: wp.array(dtype=wp.vec3),
    normals: wp.array(dtype=wp.vec3),
    colors: wp.array(dtype=wp.vec3),
    epsilon: float,
    below_offsets: wp.array(dtype=wp.int32),
    above_offsets: wp.array(dtype=wp.int32),
    offset: int,
    below_map: wp.array(dtype=wp.int32),
    above_map: wp.array(dtype=wp.int32),
    below_positions: wp.array(dtype=wp.vec3),
    below_normals: wp.array(dtype=wp.vec3),
    below_colors: wp.array(dtype=wp.vec3),
    above_positions: wp.array(dtype=wp.vec3),
    above_normals: wp.array(dtype=wp.vec3),
    above_colors: wp.array(dtype=wp.vec3),
):
    """Emit pass over a block of vertices: each kept vertex copied into its part(s),
    and its new index there (-1 where the part does not keep it)."""
    block = wp.tid() + offset
    start = block * BLOCK
    end = wp.min(start + BLOCK, distances.shape[0])
    ob = below_offsets[block]
    oa = above_offsets[block]
    for i in range(start, end):
        s = side_of(distances[i], epsilon)
        mb = int(-1)
        ma = int(-1)
        if s < 0 or (s == 0 and used_below[i] != wp.int8(0)):
            mb = ob
            below_positions[ob] = positions[i]
            below_normals[ob] = normals[i]
            below_colors[ob] = colors[i]
            ob += 1
        if s > 0 or (s == 0 and used_above[i] != wp.int8(0)):
            ma = oa
            above_positions[oa] = positions[i]
            above_normals[oa] = normals[i]
            above_colors[oa] = colors[i]
            oa += 1
        below_map[i] = mb
        above_map[i] = ma


@wp.func
def new_vertex(point: int, crossing_rank: wp.array(dtype=wp.int32), first: int) -> int:
    return first + crossing_rank[point]


@wp.kernel(enable_backward=False)
def face_kernel(
    triangles: wp.array(dtype=wp.vec3i),
    codes: wp.array(dtype=wp.int8),
    positions: wp.array(dtype=wp.vec3),
    below_offsets: wp.array(dtype=wp.int32),
    above_offsets: wp.array(dtype=wp.int32),
    segment_offsets: wp.array(dtype=wp.int32),
    below_map: wp.array(dtype=wp.int32),
    above_map: wp.array(dtype=wp.int32),
    start_point: wp.array(dtype=wp.int32),
    end_point: wp.array(dtype=wp.int32),
    crossing_rank: wp.array(dtype=wp.int32),
    below_first: int,
    above_first: int,
    below_vertices: wp.array(dtype=wp.vec3),
    track: int,
    offset: int,
    below_faces: wp.array(dtype=wp.vec3i),
    above_faces: wp.array(dtype=wp.vec3i),
    below_sources: wp.array(dtype=wp.int32),
    above_sources: wp.array(dtype=wp.int32),
):
    """Emit pass over a block of faces: whole faces re-indexed into their part, split
    faces cut into a triangle and a quad (two triangles, split along the shorter
    diagonal) or into two triangles; with ``track`` 1 the input face of each
    output face goes to ``*_sources``."""
    block = wp.tid() + offset
    start = block * BLOCK
    end = wp.min(start + BLOCK, triangles.shape[0])
    ob = below_offsets[block]
    oa = above_offsets[block]
    seg = segment_offsets[block]
    for f in range(start, end):
        t = triangles[f]
        code = int(codes[f])
        kind = code_kind(code)
        if kind == BELOW:
            below_faces[ob] = wp.vec3i(below_map[t[0]], below_map[t[1]], below_map[t[2]])
            if track != 0:
                below_sources[ob] = f
            ob += 1
        elif kind == ABOVE:
            above_faces[oa] = wp.vec3i(above_map[t[0]], above_map[t[1]], above_map[t[2]])
            if track != 0:
                above_sources[oa] = f
            oa += 1
        else:
            r = code_corner(code)
            lone_below = code_flag(code) == 1
            a = t[r]
            b = t[(r + 1) % 3]
            c = t[(r + 2) % 3]
            if kind == SPLIT_VERTEX:
                # triangle (a, b, x) on b's side, (a, x, c) on c's side; x on edge b-c
                px = start_point[seg]
                if not lone_below:
                    px = end_point[seg]
                xb = new_vertex(px, crossing_rank, below_first)
                xa = new_vertex(px, crossing_rank, above_first)
                if lone_below:
                    below_faces[ob] = wp.vec3i(below_map[a], below_map[b], xb)
                    above_faces[oa] = wp.vec3i(above_map[a], xa, above_map[c])
                else:
                    above_faces[oa] = wp.vec3i(above_map[a], above_map[b], xa)
                    below_faces[ob] = wp.vec3i(below_map[a], xb, below_map[c])
                if track != 0:
                    below_sources[ob] = f
                    above_sources[oa] = f
                ob += 1
                oa += 1
            else:
                # x on edge a-b, y on edge c-a: triangle (a, x, y) on a's side, quad (x, b, c, y) on the other
                px = start_point[seg]
                py = end_point[seg]
                if not lone_below:
                    px = end_point[seg]
                    py = start_point[seg]
                xb = new_vertex(px, crossing_rank, below_first)
                yb = new_vertex(py, crossing_rank, below_first)
                xa = new_vertex(px, crossing_rank, above_first)
                ya = new_vertex(py, crossing_rank, above_first)
                diagonal_xc = wp.length_sq(below_vertices[xb] - positions[c])
                short_xc = diagonal_xc <= wp.length_sq(below_vertices[yb] - positions[b])
                if lone_below:
                    below_faces[ob] = wp.vec3i(below_map[a], xb, yb)
                    if track != 0:
                        below_sources[ob] = f
                    ob += 1
                    mb = above_map[b]
                    mc = above_map[c]
                    if short_xc:
                        above_faces[oa] = wp.vec3i(xa, mb, mc)
                        above_faces[oa + 1] = wp.vec3i(xa, mc, ya)
                    else:
                        above_faces[oa] = wp.vec3i(xa, mb, ya)
                        above_faces[oa + 1] = wp.vec3i(mb, mc, ya)
                    if track != 0:
                        above_sources[oa] = f
                        above_sources[oa + 1] = f
                    oa += 2
                else:
                    above_faces[oa] = wp.vec3i(above_map[a], xa, ya)
                    if track != 0:
                        above_sources[oa] = f
                    oa += 1
                    mb = below_map[b]
                    mc = below_map[c]
                    if short_xc:
                        below_faces[ob] = wp.vec3i(xb, mb, mc)
                        below_faces[ob + 1] = wp.vec3i(xb, mc, yb)
                    else:
                        below_faces[ob] = wp.vec3i(xb, mb, yb)
                        below_faces[ob + 1] = wp.vec3i(mb, mc, yb)
                    if track != 0:
                        below_sources[ob] = f
                        below_sources[ob + 1] = f
                    ob += 2
            seg += 1


@wp.kernel(enable_backward=False)
def point_index_kernel(
    point_keys: wp.array(dtype=wp.int64),
    crossing_rank: wp.array(dtype=wp.int32),
    below_map: wp.array(dtype=wp.int32),
    above_map: wp.array(dtype=wp.int32),
    below_first: int,
    above_first: int,
    offset: int,
    below_index: wp.array(dtype=wp.int32),
    above_index: wp.array(dtype=wp.int32),
):
    """Vertex index of each section point in each part."""
    p = wp.tid() + offset
    rank = crossing_rank[p]
    if rank >= 0:
        below_index[p] = below_first + rank
        above_index[p] = above_first + rank
    else:
        v = int(point_keys[p] / wp.int64(below_map.shape[0]))
        below_index[p] = below_map[v]
        above_index[p] = above_map[v]


@wp.kernel(enable_backward=False)
def nesting_kernel(
    coords: wp.array(dtype=wp.vec2d),
    loop_starts: wp.array(dtype=wp.int32),
    lower: wp.array(dtype=wp.vec2d),
    upper: wp.array(dtype=wp.vec2d),
    areas: wp.array(dtype=wp.float64),
    offset: int,
    depth: wp.array(dtype=wp.int32),
    parent: wp.array(dtype=wp.int32),
):
    """How many loops enclose loop ``i`` (even-odd rule: a ray from a point of it
    crosses an enclosing loop an odd number of times) and the smallest of them.

    The point is the midpoint of the loop's first segment: loops of a section
    never cross, and where two touch they share vertices, not segments, so the
    point lies on no other loop.
    """
    i = wp.tid() + offset
    n_loops = loop_starts.shape[0] - 1
    first = loop_starts[i]
    q = wp.float64(0.5) * (coords[first] + coords[first + 1])
    count = int(0)
    best = int(-1)
    best_area = wp.float64(0.0)
    for j in range(n_loops):
        if j == i:
            continue
        lo = lower[j]
        hi = upper[j]
        if q[0] < lo[0] or q[0] > hi[0] or q[1] < lo[1] or q[1] > hi[1]:
            continue
        inside = int(0)
        s0 = loop_starts[j]
        s1 = loop_starts[j + 1]
        for k in range(s0, s1):
            a = coords[k]
            b = coords[wp.where(k + 1 < s1, k + 1, s0)]
            if (a[1] > q[1]) != (b[1] > q[1]):
                x = a[0] + (q[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
                if q[0] < x:
                    inside = 1 - inside
        if inside == 1:
            count += 1
            area = wp.abs(areas[j])
            if best < 0 or area < best_area:
                best = j
                best_area = area
    depth[i] = count
    parent[i] = best
