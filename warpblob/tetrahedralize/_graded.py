"""Warp kernels of the graded interior (see :mod:`warpblob.tetrahedralize`, "Graded interior").

One coarse level: coarse cubes of side ``r * cellsize`` (``r`` a power of two,
``r >= 2``) aligned with the fine lattice (coarse cube ``g`` covers the fine
cubes ``[g r, (g + 1) r)`` per axis). Every vertex used here is a fine lattice
point: coarse cube centres, coarse face centres and the points along coarse
edges and faces are fine black points, the apexes of the half-pyramids fine
red points. Orientation is decided in exact integer arithmetic on half-cell
coordinates.
"""

from __future__ import annotations

import warp as wp

from ._kernels import Lattice, cell_is_coarse, grid_coords, point_index

_INSIDE = wp.constant(1)


@wp.func
def half(red: int, c: wp.vec3i):
    return wp.vec3i(2 * c[0] + red, 2 * c[1] + red, 2 * c[2] + red)


@wp.func
def oriented(l: Lattice, r0: int, c0: wp.vec3i, r1: int, c1: wp.vec3i, r2: int, c2: wp.vec3i, r3: int, c3: wp.vec3i):
    """Point indices of the tet (colour, coords) x4, swapped to positive orientation."""
    x0 = half(r0, c0)
    a = half(r1, c1) - x0
    b = half(r2, c2) - x0
    d = half(r3, c3) - x0
    det = a[0] * (b[1] * d[2] - b[2] * d[1]) - a[1] * (b[0] * d[2] - b[2] * d[0]) + a[2] * (b[0] * d[1] - b[1] * d[0])
    p0 = point_index(l, r0, c0)
    p1 = point_index(l, r1, c1)
    p2 = point_index(l, r2, c2)
    p3 = point_index(l, r3, c3)
    if det < 0:
        return wp.vec4i(p0, p2, p1, p3)
    return wp.vec4i(p0, p1, p2, p3)


@wp.func
def axis_vec(a: int, v: int):
    e = wp.vec3i(0, 0, 0)
    e[a] = v
    return e


@wp.func
def face_point(a: int, base: wp.vec3i, u: int, v: int):
    """``base + u e_b + v e_c`` with ``(a, b, c)`` a cyclic permutation of the axes."""
    return base + axis_vec((a + 1) % 3, u) + axis_vec((a + 2) % 3, v)


@wp.func
def square_triangle(a: int, base: wp.vec3i, size: int, k: int, corner: int):
    """Corner ``corner`` (0-2) of triangle ``k`` (0-1) of the unit square at ``base`` in the
    plane normal to axis ``a``, split by the diagonal whose ends have an even coordinate
    sum (a rule that depends on the square alone, so both sides agree)."""
    shift = int(0)
    if (base[0] // size + base[1] // size + base[2] // size) % 2 != 0:
        shift = 1
    # cyclic corners (0,0), (1,0), (1,1), (0,1); diagonal q[shift] - q[shift + 2];
    # triangles (q[shift], q[shift + 1], q[shift + 2]) and (q[shift], q[shift + 2], q[shift + 3])
    q = shift + corner
    if k == 1 and corner > 0:
        q = shift + corner + 1
    q = q % 4
    u = int(0)
    v = int(0)
    if q == 1 or q == 2:
        u = 1
    if q >= 2:
        v = 1
    return face_point(a, base, u * size, v * size)


@wp.kernel(enable_backward=False)
def classify_coarse_kernel(
    l: Lattice,
    labels: wp.array(dtype=wp.int32),
    ratio: int,
    dims: wp.vec3i,
    offset: int,
    coarse: wp.array(dtype=wp.int32),
):
    """A coarse cube is coarse when every fine lattice point of the cube grown by one fine
    cube per side (black and red) has label ``+`` (inside, not warped): every lattice tet
    it replaces, and every lattice tet sharing a face with a half-pyramid, is then a whole
    ``+`` tet, and no cut tet is replaced."""
    tid = wp.tid() + offset
    g = grid_coords(dims, tid)
    first = wp.vec3i(g[0] * ratio - 1, g[1] * ratio - 1, g[2] * ratio - 1)
    last = wp.vec3i(first[0] + ratio + 2, first[1] + ratio + 2, first[2] + ratio + 2)  # inclusive, black
    state = int(1)
    if first[0] < 0 or first[1] < 0 or first[2] < 0:
        state = 0
    if last[0] > l.cells[0] or last[1] > l.cells[1] or last[2] > l.cells[2]:
        state = 0
    if state == 1:
        for k in range(first[2], last[2] + 1):
            for j in range(first[1], last[1] + 1):
                for i in range(first[0], last[0] + 1):
                    if labels[point_index(l, 0, wp.vec3i(i, j, k))] != 1:
                        state = 0
                    if (
                        i < last[0]
                        and j < last[1]
                        and k < last[2]
                        and labels[point_index(l, 1, wp.vec3i(i, j, k))] != 1
                    ):
                        state = 0
    coarse[tid] = state


@wp.func
def transition_cell(active: wp.array(dtype=wp.int32), l: Lattice, tid: int):
    """(cube i, j, k, face) of thread ``tid``: 8 cubes per active sub-block, 6 faces each."""
    a = tid // 48
    r = tid - a * 48
    local = r // 6
    s = grid_coords(l.subs, active[a])
    return wp.vec4i(s[0] * 2 + (local & 1), s[1] * 2 + ((local >> 1) & 1), s[2] * 2 + (local >> 2), r % 6)


@wp.kernel(enable_backward=False)
def count_transition_kernel(
    l: Lattice,
    active: wp.array(dtype=wp.int32),
    coarse: wp.array(dtype=wp.int32),
    dims: wp.vec3i,
    ratio: int,
    offset: int,
    counts: wp.array(dtype=wp.int32),
):
    """Two half-pyramid tets on every face between a fine cube and a coarse one."""
    tid = wp.tid() + offset
    t = transition_cell(active, l, tid)
    c = wp.vec3i(t[0], t[1], t[2])
    n = int(0)
    if cell_is_coarse(coarse, dims, ratio, c) == 0:
        a = t[3] % 3
        side = 1 - 2 * (t[3] // 3)
        if cell_is_coarse(coarse, dims, ratio, c + axis_vec(a, side)) == 1:
            n = 2
    counts[tid] = n


@wp.kernel(enable_backward=False)
def emit_transition_kernel(
    l: Lattice,
    active: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    tet_offsets: wp.array(dtype=wp.int32),
    offset: int,
    tets: wp.array(dtype=wp.vec4i),
):
    tid = wp.tid() + offset
    if counts[tid] == 0:
        return
    t = transition_cell(active, l, tid)
    c = wp.vec3i(t[0], t[1], t[2])
    a = t[3] % 3
    base = c + axis_vec(a, 1 - t[3] // 3)
    out = tet_offsets[tid]
    for k in range(2):
        tets[out + k] = oriented(
            l,
            1,
            c,
            0,
            square_triangle(a, base, 1, k, 0),
            0,
            square_triangle(a, base, 1, k, 1),
            0,
            square_triangle(a, base, 1, k, 2),
        )


@wp.func
def level_ge(
    flat: wp.array(dtype=wp.int32),
    offs: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec3i),
    n_levels: int,
    level: int,
    g: wp.vec3i,
):
    """1 when the region of level-``level`` cube ``g`` lies in a cube of level ``>= level``."""
    if level <= 0:
        return 1
    if level > n_levels:
        return 0
    d = dims[level - 1]
    if g[0] < 0 or g[1] < 0 or g[2] < 0 or g[0] >= d[0] or g[1] >= d[1] or g[2] >= d[2]:
        return 0
    return flat[offs[level - 1] + (g[2] * d[1] + g[1]) * d[0] + g[0]]


@wp.func
def half_down(g: wp.vec3i):
    return wp.vec3i(g[0] // 2, g[1] // 2, g[2] // 2)


@wp.kernel(enable_backward=False)
def classify_level_kernel(
    flat: wp.array(dtype=wp.int32),
    offs: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec3i),
    n_levels: int,
    level: int,
    offset: int,
    out: wp.array(dtype=wp.int32),
):
    """Level ``level >= 2``: a cube qualifies when the children of it and of its 26 neighbours
    all qualify at ``level - 1`` (so every cube touching a level-L cube is of level >= L - 1)."""
    tid = wp.tid() + offset
    g = grid_coords(dims[level - 1], tid)
    ok = int(1)
    for n in range(27):
        q = wp.vec3i(2 * (g[0] + n % 3 - 1), 2 * (g[1] + (n // 3) % 3 - 1), 2 * (g[2] + n // 9 - 1))
        for c in range(8):
            child = q + wp.vec3i(c & 1, (c >> 1) & 1, c >> 2)
            if level_ge(flat, offs, dims, n_levels, level - 1, child) == 0:
                ok = 0
    out[tid] = ok


@wp.func
def edge_refined(
    flat: wp.array(dtype=wp.int32),
    offs: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec3i),
    n_levels: int,
    level: int,
    g: wp.vec3i,
    a: int,
    side: int,
    e: int,
):
    """Whether edge ``e`` (0-3) of face (axis ``a``, ``side`` +-1) of level-``level`` cube ``g``
    meets a finer cube (one of the four level-``level`` positions around it is finer). Edges
    0/1: the low/high edge along ``e_c`` (offset along ``e_b``); 2/3: the low/high edge along
    ``e_b``."""
    o = (a + 1) % 3
    if e >= 2:
        o = (a + 2) % 3
    n = axis_vec(a, side)
    m = axis_vec(o, 2 * (e % 2) - 1)
    refined = int(0)
    if level_ge(flat, offs, dims, n_levels, level, g + n) == 0:
        refined = 1
    if level_ge(flat, offs, dims, n_levels, level, g + m) == 0:
        refined = 1
    if level_ge(flat, offs, dims, n_levels, level, g + n + m) == 0:
        refined = 1
    return refined


@wp.func
def face_kind(
    flat: wp.array(dtype=wp.int32),
    offs: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec3i),
    n_levels: int,
    level: int,
    g: wp.vec3i,
    f: int,
):
    """Kind of face ``f`` of level-``level`` cube ``g``: 0 not a leaf cube, 1 finer neighbour,
    2 coarser neighbour, 3 same level and no edge meets a finer cube, 4 same level otherwise."""
    if level_ge(flat, offs, dims, n_levels, level, g) == 0:
        return 0
    if level_ge(flat, offs, dims, n_levels, level + 1, half_down(g)) == 1:
        return 0
    a = f % 3
    side = 1 - 2 * (f // 3)
    nb = g + axis_vec(a, side)
    if level_ge(flat, offs, dims, n_levels, level, nb) == 0:
        return 1
    if level_ge(flat, offs, dims, n_levels, level + 1, half_down(nb)) == 1:
        return 2
    for e in range(4):
        if edge_refined(flat, offs, dims, n_levels, level, g, a, side, e) == 1:
            return 4
    return 3


@wp.kernel(enable_backward=False)
def count_coarse_kernel(
    flat: wp.array(dtype=wp.int32),
    offs: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec3i),
    n_levels: int,
    level: int,
    offset: int,
    counts: wp.array(dtype=wp.int32),
):
    tid = wp.tid() + offset
    g = grid_coords(dims[level - 1], tid // 6)
    f = tid % 6
    kind = face_kind(flat, offs, dims, n_levels, level, g, f)
    n = int(0)
    if kind == 1:
        n = 8
    elif kind == 2:
        n = 2
    elif kind == 3:
        if f < 3:
            n = 4
    elif kind == 4:
        a = f % 3
        side = 1 - 2 * (f // 3)
        for e in range(4):
            n += 1 + edge_refined(flat, offs, dims, n_levels, level, g, a, side, e)
    counts[tid] = n


@wp.kernel(enable_backward=False)
def emit_coarse_kernel(
    l: Lattice,
    flat: wp.array(dtype=wp.int32),
    offs: wp.array(dtype=wp.int32),
    dims: wp.array(dtype=wp.vec3i),
    n_levels: int,
    level: int,
    counts: wp.array(dtype=wp.int32),
    tet_offsets: wp.array(dtype=wp.int32),
    offset: int,
    tets: wp.array(dtype=wp.vec4i),
):
    """Face ``f`` of a leaf cube of side ``s = 2^level`` fine cubes (every vertex a fine black
    point): kind 1, the cone from the cube centre over the face's four half-size squares,
    each split by the parity rule; kind 2, the two half-pyramids over the face split by the
    parity rule; kind 3, whole BCC tets of the level's lattice across the face (owned by the
    lower cube); kind 4, the cone over the fan from the face centre to the face boundary,
    whose edges that meet a finer cube are split at their midpoint."""
    tid = wp.tid() + offset
    n = counts[tid]
    if n == 0:
        return
    g = grid_coords(dims[level - 1], tid // 6)
    f = tid % 6
    kind = face_kind(flat, offs, dims, n_levels, level, g, f)
    a = f % 3
    side = 1 - 2 * (f // 3)
    s = int(1) << level
    h2 = s // 2
    first = wp.vec3i(g[0] * s, g[1] * s, g[2] * s)
    centre = first + wp.vec3i(h2, h2, h2)
    face_base = first + axis_vec(a, s * (1 - f // 3))  # lowest corner of the face
    out = tet_offsets[tid]
    if kind == 1:
        k = int(0)
        for sq in range(4):
            base = face_point(a, face_base, (sq & 1) * h2, (sq >> 1) * h2)
            for t in range(2):
                tets[out + k] = oriented(
                    l, 0, centre,
                    0, square_triangle(a, base, h2, t, 0),
                    0, square_triangle(a, base, h2, t, 1),
                    0, square_triangle(a, base, h2, t, 2),
                )  # fmt: skip
                k += 1
        return
    if kind == 2:
        for t in range(2):
            tets[out + t] = oriented(
                l, 0, centre,
                0, square_triangle(a, face_base, s, t, 0),
                0, square_triangle(a, face_base, s, t, 1),
                0, square_triangle(a, face_base, s, t, 2),
            )  # fmt: skip
        return
    fc = face_point(a, face_base, h2, h2)
    other = centre + axis_vec(a, s * side)
    k = int(0)
    for e in range(4):
        u0 = int(0)
        v0 = int(0)
        du = int(0)
        dv = int(0)
        if e == 0:
            dv = 1  # u = 0 edge, along e_c
        elif e == 1:
            u0 = s
            dv = 1
        elif e == 2:
            du = 1  # v = 0 edge, along e_b
        else:
            v0 = s
            du = 1
        p = face_point(a, face_base, u0, v0)
        q = face_point(a, face_base, u0 + du * s, v0 + dv * s)
        if kind == 3:
            tets[out + k] = oriented(l, 0, centre, 0, other, 0, p, 0, q)
            k += 1
        elif edge_refined(flat, offs, dims, n_levels, level, g, a, side, e) == 1:
            mid = face_point(a, face_base, u0 + du * h2, v0 + dv * h2)
            tets[out + k] = oriented(l, 0, centre, 0, fc, 0, p, 0, mid)
            tets[out + k + 1] = oriented(l, 0, centre, 0, fc, 0, mid, 0, q)
            k += 2
        else:
            tets[out + k] = oriented(l, 0, centre, 0, fc, 0, p, 0, q)
            k += 1
