"""Warp kernels of tool contact through the implicit field (SPEC section 5.2; the thesis' chapter 6 contact).

Per tool sample: its world position (the tool's pose applied in the
kernel), the deformed tet holding it (a ``wp.Bvh`` over the current tets
of the boundary layer) or, for the thesis' variant, the nearest node (a
``wp.Bvh`` over the layer's nodes); the field there (:func:`warpblob.field.evaluate`, between the
kernels); the signed penetration depth from the inverse falloff, the
contact law, the force ``CF = normalize(n + T) * psi(depth) * s * a`` and
its stiffness; then the forces are summed per node and spread over the
k-rings. Every sum runs in a fixed
order (a stable sort groups the samples' corners by node, the spread
gathers per node through a CSR), never with atomics, so results are
bit-identical for any CPU thread count.

Every kernel takes an ``offset`` right after its inputs and adds it to
``wp.tid()`` (:func:`warpblob._parallel.launch`).
"""

from __future__ import annotations

import warp as wp

from ..tree import ISO_DISTANCE, ISO_VALUE
from ._kernels import polar_rotation, shape_matrix, tet_box, triangle_distance

#: contact modes: the field carried by the deformation, the thesis' nearest node in the rest field
FIELD = 0
NEAREST = 1

_ISO_DISTANCE = wp.constant(float(ISO_DISTANCE))
_ISO_VALUE = wp.constant(float(ISO_VALUE))
#: a point within this barycentric margin of a tet counts as inside (points on shared faces)
_INSIDE = wp.constant(-1.0e-6)
#: a deformed tet whose volume is below this fraction of its rest volume cannot map points back
_FLAT = wp.constant(1.0e-6)


@wp.func
def signed_depth(f: float, slope: float, reach: float) -> float:
    """Signed penetration (model units; > 0 inside) of a point with field ``f`` and gradient length ``slope``.

    The inverse falloff of SPEC 1.1 gives the normalized distance
    ``dist(f) = x - x*`` with ``x = sqrt(1 - f^(1/3))`` (``f`` clamped to
    [0, 1]: a blend's sum exceeds 1 deep inside); the length that turns it
    into model units is the radius of the lone primitive with this value
    and slope, ``l = |g'(x)| / |grad F|`` (``g'(x) = -6 x (1 - x^2)^2``),
    exact for a single primitive of any radius and scale. ``x`` is held in
    ``[x* / 2, x*]`` inside ``g'`` (``g'`` vanishes at the skeleton and far
    outside; held, the depth rises monotonically with ``f``) and ``l`` is
    capped at ``reach`` (where the gradient itself vanishes).
    """
    x = wp.sqrt(wp.max(1.0 - wp.pow(wp.clamp(f, 0.0, 1.0), 1.0 / 3.0), 0.0))
    held = wp.clamp(x, 0.5 * _ISO_DISTANCE, _ISO_DISTANCE)
    q = 1.0 - held * held
    length = reach
    if slope > 0.0:
        length = wp.min(6.0 * held * q * q / slope, reach)
    return (_ISO_DISTANCE - x) * length


@wp.func
def penalty(s: float, band: float) -> wp.vec2:
    """The contact law ``(psi(s), psi'(s))`` of a signed depth ``s``: C1, zero outside, ``s - band`` deep inside.

    ``psi = s^2 / (4 band)`` over the first ``2 band`` of depth: the force
    and its stiffness grow from zero at the surface, so the set of samples
    in contact changes gradually from step to step instead of flipping (a
    penalty with its full stiffness from ``s = 0`` makes the nearly static
    tissue alternate between two states, pressed out of the tool and relaxed
    into it).
    """
    if s <= 0.0:
        return wp.vec2(0.0, 0.0)
    if s >= 2.0 * band:
        return wp.vec2(s - band, 1.0)
    return wp.vec2(s * s / (4.0 * band), s / (2.0 * band))


@wp.func
def pushed_gradient(x: wp.array(dtype=wp.vec3), tet: wp.vec4i, B: wp.mat33, g: wp.vec3) -> wp.vec3:
    """A rest-space gradient carried into the deformed tet: ``F^-T g`` with ``F = Ds Dm^-1``.

    The deformed field is ``F_def(x) = F(phi^-1(x))`` and ``phi`` is affine
    on a tet, so its gradient is ``F^-T`` times the rest gradient (normals
    transform by the inverse transpose). A flat or inverted tet has no
    inverse worth using: its rotation ``R`` carries the gradient instead.
    """
    Fd = shape_matrix(x, tet) * B
    if wp.determinant(Fd) > _FLAT:
        return wp.transpose(wp.inverse(Fd)) * g
    return polar_rotation(Fd) * g


@wp.kernel(enable_backward=False)
def node_bounds_kernel(
    x: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    offset: int,
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """A point box per node at its current position; a node given no mass (no live tet, or off the layer) far away."""
    i = wp.tid() + offset
    p = x[i]
    if mass[i] == 0.0:
        p = wp.vec3(1.0e30, 1.0e30, 1.0e30)
    lowers[i] = p
    uppers[i] = p


@wp.kernel(enable_backward=False)
def cell_bounds_kernel(
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    cells: wp.array(dtype=wp.int32),
    first: int,
    offset: int,
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """Box of the tet ``cells[first + i]`` at the positions ``x``; an empty slot (-1) gets an empty box
    (lower above upper), which a refit's unions ignore and no query meets."""
    i = wp.tid() + offset
    t = cells[first + i]
    if t < 0:
        lowers[i] = wp.vec3(1.0e30, 1.0e30, 1.0e30)
        uppers[i] = wp.vec3(-1.0e30, -1.0e30, -1.0e30)
        return
    lo, hi = tet_box(x, tets[t])
    lowers[i] = lo
    uppers[i] = hi


@wp.func
def mapping_tet(
    cells: wp.array(dtype=wp.int32),
    slot: int,
    tets: wp.array(dtype=wp.vec4i),
    x: wp.array(dtype=wp.vec3),
    volume: wp.array(dtype=float),
) -> int:
    """The tet in slot ``slot`` of a locate tree's ``cells``, or -1 for an empty slot or a tet too flat at
    ``x`` (below :data:`_FLAT` of its rest volume) to map points back (:func:`locate_points_kernel`)."""
    t = cells[slot]
    if t < 0:
        return -1
    if wp.determinant(shape_matrix(x, tets[t])) <= _FLAT * 6.0 * volume[t]:
        return -1
    return t


@wp.kernel(enable_backward=False)
def locate_points_kernel(
    trees: wp.array(dtype=wp.uint64),
    cells: wp.array(dtype=wp.int32),
    split: int,
    local: wp.array(dtype=wp.vec3),
    point_tool: wp.array(dtype=wp.int32),
    poses: wp.array(dtype=wp.transform),
    modes: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    volume: wp.array(dtype=float),
    margin: float,
    offset: int,
    world: wp.array(dtype=wp.vec3),
    query: wp.array(dtype=wp.vec3),
    point_cell: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
):
    """Each point placed by its tool's pose, then located; ``query`` is where the field is evaluated.

    The items of the two BVHs ``trees`` (an id 0: none) are the tets
    ``cells`` (the boundary layer during contact: the first tree's from
    ``cells[0]``, the second's from ``cells[split]``; -1 an empty slot). Nearest mode leaves ``point_cell`` to :func:`nearest_nodes_kernel`
    (after the field: only penetrating samples need a node). Field mode:
    the deformed tet holding the point (the most interior one
    when it lies on shared faces, ties to the smaller index, so the result
    does not depend on the traversal), its barycentric coordinates there
    and the rest point with the same coordinates (``query``). A point
    outside the volume but within ``margin`` of it takes the nearest tet
    and its extrapolated coordinates (-1 and the world point when none is
    that near): the tets' flat boundary faces cut inside the model's curved
    surface by up to a few percent of an edge, and a tool sample passing
    from outside every tet into one would otherwise jump from no depth to
    that gap's. Nearest mode (the thesis): the world point itself as
    ``query``, the rest field being used as it is.
    """
    i = wp.tid() + offset
    p = wp.transform_point(poses[point_tool[i]], local[i])
    world[i] = p
    query[i] = p
    if modes[point_tool[i]] == NEAREST:
        point_cell[i] = -1
        point_bary[i] = wp.vec4(1.0, 0.0, 0.0, 0.0)
        return
    best = int(-1)
    best_in = float(-1.0e30)
    best_b = wp.vec3()
    item = int(0)
    for tree in range(2):
        if trees[tree] == wp.uint64(0):
            continue
        q = wp.bvh_query_aabb(trees[tree], p, p)
        while wp.bvh_query_next(q, item):
            t = mapping_tet(cells, tree * split + item, tets, x, volume)
            if t < 0:
                continue
            tet = tets[t]
            Ds = shape_matrix(x, tet)
            b = wp.inverse(Ds) * (p - x[tet[0]])
            inside = wp.min(wp.min(1.0 - b[0] - b[1] - b[2], b[0]), wp.min(b[1], b[2]))
            if inside >= _INSIDE and (inside > best_in or (inside == best_in and t < best)):
                best = t
                best_in = inside
                best_b = b
    held = best >= 0  # (a tet holds the point: no nearest tet sought)
    best_d = margin
    for tree in range(2):
        if held or margin <= 0.0 or trees[tree] == wp.uint64(0):
            continue
        q = wp.bvh_query_aabb(trees[tree], p - wp.vec3(margin, margin, margin), p + wp.vec3(margin, margin, margin))
        while wp.bvh_query_next(q, item):
            t = mapping_tet(cells, tree * split + item, tets, x, volume)
            if t < 0:
                continue
            tet = tets[t]
            Ds = shape_matrix(x, tet)
            x0 = x[tet[0]]
            x1 = x[tet[1]]
            x2 = x[tet[2]]
            x3 = x[tet[3]]
            d = wp.min(
                wp.min(triangle_distance(p, x1, x2, x3), triangle_distance(p, x0, x3, x2)),
                wp.min(triangle_distance(p, x0, x1, x3), triangle_distance(p, x0, x2, x1)),
            )
            if d < best_d or (d == best_d and t < best):
                best = t
                best_d = d
                best_b = wp.inverse(Ds) * (p - x0)
    point_cell[i] = best
    if best >= 0:
        tet = tets[best]
        point_bary[i] = wp.vec4(1.0 - best_b[0] - best_b[1] - best_b[2], best_b[0], best_b[1], best_b[2])
        query[i] = rest[tet[0]] + wp.matrix_from_cols(rest[tet[1]] - rest[tet[0]], rest[tet[2]] - rest[tet[0]],
                                                      rest[tet[3]] - rest[tet[0]]) * best_b  # fmt: skip
    else:
        point_bary[i] = wp.vec4()


@wp.kernel(enable_backward=False)
def nearest_nodes_kernel(
    node_bvh: wp.uint64,
    world: wp.array(dtype=wp.vec3),
    values: wp.array(dtype=float),
    point_tool: wp.array(dtype=wp.int32),
    modes: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    radius: float,
    offset: int,
    point_cell: wp.array(dtype=wp.int32),
):
    """The thesis' nearest node of each penetrating sample of a nearest-mode tool (``F >= 0.5`` in the rest field).

    Boxes of ``radius`` around the point, doubled until one holds a node,
    then one box of the distance to the nearest found, which holds every
    nearer node: the search is exact. Ties to the smaller index.
    """
    i = wp.tid() + offset
    if modes[point_tool[i]] != NEAREST or values[i] < _ISO_VALUE:
        return
    p = world[i]
    r = radius
    best = int(-1)
    best_d = float(1.0e30)
    for _round in range(64):
        q = wp.bvh_query_aabb(node_bvh, p - wp.vec3(r, r, r), p + wp.vec3(r, r, r))
        n = int(0)
        while wp.bvh_query_next(q, n):
            d = wp.length(x[n] - p)
            if d < best_d or (d == best_d and n < best):
                best = n
                best_d = d
        if best >= 0:
            if best_d <= r:
                break
            r = best_d
        else:
            r = 2.0 * r
    point_cell[i] = best


@wp.kernel(enable_backward=False)
def map_gradients_kernel(
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    dm_inv: wp.array(dtype=wp.mat33),
    point_cell: wp.array(dtype=wp.int32),
    offset: int,
    values: wp.array(dtype=float),
    gradients: wp.array(dtype=wp.vec3),
):
    """The deformation-mapped field at located points: rest gradients pushed forward; 0 outside the volume."""
    i = wp.tid() + offset
    t = point_cell[i]
    if t < 0:
        values[i] = 0.0
        gradients[i] = wp.vec3()
        return
    gradients[i] = pushed_gradient(x, tets[t], dm_inv[t], gradients[i])


@wp.kernel(enable_backward=False)
def sample_forces_kernel(
    point_tool: wp.array(dtype=wp.int32),
    point_cell: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    values: wp.array(dtype=float),
    gradients: wp.array(dtype=wp.vec3),
    area: wp.array(dtype=float),
    modes: wp.array(dtype=wp.int32),
    groups: wp.array(dtype=wp.int32),
    stiffness: wp.array(dtype=float),
    travel: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    dm_inv: wp.array(dtype=wp.mat33),
    reach: float,
    band: float,
    group_count: int,
    node_count: int,
    offset: int,
    depth: wp.array(dtype=float),
    law: wp.array(dtype=wp.vec2),
    direction: wp.array(dtype=wp.vec3),
    entry_node: wp.array(dtype=wp.int32),
    entry_weight: wp.array(dtype=float),
    keys: wp.array(dtype=wp.int32),
    entries: wp.array(dtype=wp.int32),
):
    """Per sample: signed depth, contact law, force direction; per corner entry: the node and its share.

    A located sample has the signed depth :func:`signed_depth` (> 0: it
    penetrates, ``F > 0.5``; the gradient pushed forward in field mode) and
    acts when it penetrates: its force on the tissue is
    ``CF = normalize(n + T) * psi(depth) * s * a`` (:func:`penalty`) with
    ``n`` the unit deformed gradient (into the tissue), ``T`` the tool's
    unit travel, ``s`` the stiffness, ``a`` the sample's area: the thesis'
    ``normalize(grad F + T) * dist * s`` with the gradient made unit first,
    so that the average does not depend on the field's scale, and ``n``
    alone when the sum vanishes (a tool pulled straight out). ``law`` holds
    ``(psi, psi')``. Its four corner entries carry the clamped barycentric
    weights times ``s a`` (field mode) or the whole to the nearest node; the
    sort key is ``group * N + node``, or the sentinel ``group_count * N``
    for a sample that does not act. ``depth`` is -inf for an unlocated sample.
    """
    i = wp.tid() + offset
    k = point_tool[i]
    c = point_cell[i]
    sentinel = group_count * node_count
    n = wp.vec3()
    d = float(-1.0e30)
    psi = wp.vec2()
    if c >= 0:
        g = gradients[i]
        if modes[k] == FIELD:
            g = pushed_gradient(x, tets[c], dm_inv[c], g)
        slope = wp.length(g)
        if slope > 0.0:
            n = g / slope
        d = signed_depth(values[i], slope, reach)
        u = n + travel[k]
        if wp.length(u) > 1.0e-6:
            n = wp.normalize(u)
        if wp.length(n) > 0.0:
            psi = penalty(d, band)
    depth[i] = d
    law[i] = psi
    direction[i] = n
    acts = psi[1] > 0.0
    strength = stiffness[k] * area[i]
    b = point_bary[i]
    if modes[k] == FIELD and c >= 0:
        b = wp.vec4(wp.max(b[0], 0.0), wp.max(b[1], 0.0), wp.max(b[2], 0.0), wp.max(b[3], 0.0))
        b = b / (b[0] + b[1] + b[2] + b[3])
    for a in range(4):
        e = 4 * i + a
        node = int(-1)
        if c >= 0:
            if modes[k] == FIELD:
                node = tets[c][a]
            elif a == 0:
                node = c
        entry_node[e] = node
        entry_weight[e] = b[a] * strength
        entries[e] = e
        if acts and node >= 0:
            keys[e] = groups[k] * node_count + node
        else:
            keys[e] = sentinel


@wp.kernel(enable_backward=False)
def gather_sources_kernel(
    keys: wp.array(dtype=wp.int32),
    entries: wp.array(dtype=wp.int32),
    entry_weight: wp.array(dtype=float),
    law: wp.array(dtype=wp.vec2),
    direction: wp.array(dtype=wp.vec3),
    ring_ranges: wp.array(dtype=wp.vec2i),
    ring_nodes: wp.array(dtype=wp.int32),
    count: int,
    node_count: int,
    sentinel: int,
    offset: int,
    source_force: wp.array(dtype=wp.vec3),
    source_block: wp.array(dtype=wp.mat33),
    source_weight: wp.array(dtype=float),
    mark: wp.array(dtype=wp.uint8),
):
    """Per run of equal keys in the sorted entries (one node of one ring group): its summed force
    ``sum w psi d``, stiffness block ``sum w psi' d d^T`` and stiffness ``sum w psi'``, in entry order; marks
    every node of its k-ring as a target.

    The stable sort leaves each run in entry order, so the sums do not
    depend on the thread count. Marking writes the same value from any
    thread that reaches a node, so the order does not matter there either.
    """
    e = wp.tid() + offset
    key = keys[e]
    if key >= sentinel:
        return
    if e > 0:
        if keys[e - 1] == key:
            return
    f = wp.vec3()
    K = wp.mat33()
    w = float(0.0)
    j = e
    while j < count:
        if keys[j] != key:
            break
        entry = entries[j]
        v = entry // 4
        s = entry_weight[entry]
        n = direction[v]
        psi = law[v]
        f += (s * psi[0]) * n
        K += (s * psi[1]) * wp.outer(n, n)
        w += s * psi[1]
        j += 1
    source_force[key] = f
    source_block[key] = K
    source_weight[key] = w
    group = key // node_count
    node = key - group * node_count
    span = ring_ranges[group * node_count + node]
    for r in range(span[0], span[1]):
        mark[ring_nodes[r]] = wp.uint8(1)


@wp.kernel(enable_backward=False)
def spread_forces_kernel(
    mark: wp.array(dtype=wp.uint8),
    ring_ranges: wp.array(dtype=wp.vec2i),
    ring_nodes: wp.array(dtype=wp.int32),
    ring_weights: wp.array(dtype=float),
    source_force: wp.array(dtype=wp.vec3),
    source_block: wp.array(dtype=wp.mat33),
    source_weight: wp.array(dtype=float),
    group_count: int,
    node_count: int,
    offset: int,
    contact_force: wp.array(dtype=wp.vec3),
    contact_block: wp.array(dtype=wp.mat33),
    contact_weight: wp.array(dtype=float),
):
    """Per node: the k-ring spread ``sum_c W[j, c] source[c]`` of every ring group, gathered in CSR order."""
    j = wp.tid() + offset
    f = wp.vec3()
    K = wp.mat33()
    w = float(0.0)
    if mark[j] != wp.uint8(0):
        for g in range(group_count):
            span = ring_ranges[g * node_count + j]
            for r in range(span[0], span[1]):
                c = g * node_count + ring_nodes[r]
                if source_weight[c] > 0.0:
                    W = ring_weights[r]
                    f += W * source_force[c]
                    K += W * source_block[c]
                    w += W * source_weight[c]
    contact_force[j] = f
    contact_block[j] = K
    contact_weight[j] = w


@wp.kernel(enable_backward=False)
def tool_forces_kernel(
    tool_first: wp.array(dtype=wp.int32),
    depth: wp.array(dtype=float),
    law: wp.array(dtype=wp.vec2),
    direction: wp.array(dtype=wp.vec3),
    entry_node: wp.array(dtype=wp.int32),
    entry_weight: wp.array(dtype=float),
    v: wp.array(dtype=wp.vec3),
    h: float,
    offset: int,
    totals: wp.array(dtype=wp.vec3),
    counts: wp.array(dtype=wp.int32),
    deepest: wp.array(dtype=float),
):
    """Per tool, over its samples in order: the force on the tool at the end of the step, penetrating count, depth.

    A sample's end-of-step force is the contact law linearized as in the
    solve, ``s a (psi - psi' h d . u)`` (``u`` the new velocity interpolated
    at the sample with the force's weights), never pulling. The tool feels
    minus the sum. ``counts`` are the samples with a positive depth,
    ``deepest`` the largest depth (0 without).
    """
    k = wp.tid() + offset
    total = wp.vec3()
    count = int(0)
    most = float(0.0)
    for i in range(tool_first[k], tool_first[k + 1]):
        psi = law[i]
        if psi[1] <= 0.0:
            continue
        u = wp.vec3()
        strength = float(0.0)
        for a in range(4):
            node = entry_node[4 * i + a]
            if node >= 0:
                u += entry_weight[4 * i + a] * v[node]
                strength += entry_weight[4 * i + a]
        n = direction[i]
        end = wp.max(strength * psi[0] - psi[1] * h * wp.dot(n, u), 0.0)
        total -= end * n
        if depth[i] > 0.0:
            count += 1
            most = wp.max(most, depth[i])
    totals[k] = total
    counts[k] = count
    deepest[k] = most


@wp.kernel(enable_backward=False)
def reweigh_rows_kernel(
    rows: wp.array(dtype=wp.int32),
    ranges: wp.array(dtype=wp.vec2i),
    nodes: wp.array(dtype=wp.int32),
    rings: wp.array(dtype=wp.uint8),
    total: wp.array(dtype=wp.float64),
    k: int,
    offset: int,
    weights: wp.array(dtype=wp.float32),
):
    """Row ``rows[i]`` of a k-ring spread weighed again in place by new sums (its nodes and rings kept,
    :func:`warpblob.sim._contact.ring_spread_after`): ``w(r) / Z_c`` in float64 rounded to float32, numpy's
    operations, the same bits."""
    row = rows[wp.tid() + offset]
    span = ranges[row]
    for j in range(span[0], span[1]):
        w = wp.float64(k + 1 - int(rings[j])) / wp.float64(k + 1)
        weights[j] = wp.float32(w / total[nodes[j]])


@wp.func
def search_level(
    ranges: wp.array(dtype=wp.vec2i),
    corners: wp.array(dtype=wp.int32),
    tets: wp.array(dtype=wp.vec4i),
    live: wp.array(dtype=wp.uint8),
    p: int,
    tag: int,
    ring: int,
    start: int,
    end: int,
    size: int,
    node_stamp: wp.array2d(dtype=wp.int32),
    tet_stamp: wp.array2d(dtype=wp.int32),
    found: wp.array2d(dtype=wp.int32),
    found_ring: wp.array2d(dtype=wp.uint8),
) -> int:
    """One level of a breadth-first search over the live tets (row ``p`` of the stamps and of ``found``): the
    nodes of the tets round ``found[p, start:end]`` not yet stamped ``tag`` appended to ``found[p]`` from
    ``size`` on with ring ``ring``, each tet looked at once; the new size. ``ranges``/``corners``: the
    incidence lists, corner ``4 * tet + i`` (:func:`ring_rows_kernel`, :func:`node_levels_kernel`)."""
    n = size
    for f in range(start, end):
        span = ranges[found[p, f]]
        for c in range(span[0], span[1]):
            t = corners[c] // 4
            if live[t] != wp.uint8(0) and tet_stamp[p, t] != tag:
                tet_stamp[p, t] = tag
                tet = tets[t]
                for m in range(4):
                    b = tet[m]
                    if node_stamp[p, b] != tag:
                        node_stamp[p, b] = tag
                        found[p, n] = b
                        found_ring[p, n] = wp.uint8(ring)
                        n += 1
    return n


@wp.kernel(enable_backward=False)
def ring_rows_kernel(
    sources: wp.array(dtype=wp.int32),
    ranges: wp.array(dtype=wp.vec2i),
    corners: wp.array(dtype=wp.int32),
    tets: wp.array(dtype=wp.vec4i),
    live: wp.array(dtype=wp.uint8),
    k: int,
    per_piece: int,
    tag_base: int,
    first: wp.array(dtype=wp.int32),
    room: int,
    offset: int,
    node_stamp: wp.array2d(dtype=wp.int32),
    tet_stamp: wp.array2d(dtype=wp.int32),
    found: wp.array2d(dtype=wp.int32),
    found_ring: wp.array2d(dtype=wp.uint8),
    count: wp.array(dtype=wp.int32),
    nodes: wp.array(dtype=wp.int32),
    rings: wp.array(dtype=wp.uint8),
):
    """The k-ring rows of sources ``[p * per_piece, (p + 1) * per_piece)`` for piece ``p`` (one thread, with
    its own row of the stamps and of the scratch ``found``/``found_ring``), by a breadth-first search over
    the live tets round each node (``ranges``/``corners``: the incidence lists, corner ``4 * tet + i``),
    each tet's corners looked at once a row. Source ``i``'s nodes and tets get the tag ``tag_base + i + 1``
    (the stamps are never cleared). Row ``i``'s size goes to ``count[i]``, and its nodes, ascending, with
    their rings to ``nodes``/``rings`` from ``first[i]`` where ``first`` is given, else from where the
    piece's earlier rows ended in its ``room`` entries from ``p * room`` (from the first row that does not
    fit on, its size negated in ``count`` and the row not written: the rows are then written again from
    ``first``; :func:`warpblob.sim._contact._rings_near`)."""
    p = wp.tid() + offset
    lo = p * per_piece
    hi = wp.min(lo + per_piece, sources.shape[0])
    at = p * room
    end = at + room
    for i in range(lo, hi):
        tag = tag_base + i + 1
        s = sources[i]
        found[p, 0] = s
        found_ring[p, 0] = wp.uint8(0)
        node_stamp[p, s] = tag
        size = int(1)
        level_start = int(0)
        for ring in range(1, k + 1):
            level_end = size
            size = search_level(ranges, corners, tets, live, p, tag, ring, level_start, level_end, size, node_stamp,
                                tet_stamp, found, found_ring)  # fmt: skip
            level_start = level_end
        start = at
        if first.shape[0] > 0:
            start = first[i]
        elif at + size > end:
            at = end + 1  # (no row after this one is written in the room either)
            count[i] = -size
            continue
        count[i] = size
        at += size
        # insertion sort by node (a row is some tens of nodes), then out
        for j in range(1, size):
            b = found[p, j]
            r = found_ring[p, j]
            m = j
            while m > 0:
                if found[p, m - 1] < b:
                    break
                found[p, m] = found[p, m - 1]
                found_ring[p, m] = found_ring[p, m - 1]
                m -= 1
            found[p, m] = b
            found_ring[p, m] = r
        for j in range(size):
            nodes[start + j] = found[p, j]
            rings[start + j] = found_ring[p, j]


@wp.kernel(enable_backward=False)
def node_levels_kernel(
    sources: wp.array(dtype=wp.int32),
    ranges: wp.array(dtype=wp.vec2i),
    corners: wp.array(dtype=wp.int32),
    tets: wp.array(dtype=wp.vec4i),
    live: wp.array(dtype=wp.uint8),
    depth: int,
    tag: int,
    offset: int,
    node_stamp: wp.array2d(dtype=wp.int32),
    tet_stamp: wp.array2d(dtype=wp.int32),
    order: wp.array2d(dtype=wp.int32),
    level: wp.array2d(dtype=wp.uint8),
    level_end: wp.array(dtype=wp.int32),
):
    """The nodes within ``depth`` edges of the ``sources`` (distinct) over the live tets, level by level
    (one thread: a breadth-first search from all of them at once, with row 0 of the stamps, marked
    ``tag``): ``order[0]`` holds them by level (``level[0]`` each one's), the sources first, level ``d``
    ending at ``level_end[d]`` (:func:`warpblob.sim._contact.ring_spread_after`)."""
    size = int(0)
    for i in range(sources.shape[0]):
        s = sources[i]
        node_stamp[0, s] = tag
        order[0, size] = s
        level[0, size] = wp.uint8(0)
        size += 1
    level_end[0] = size
    level_start = int(0)
    for d in range(1, depth + 1):
        end = size
        size = search_level(ranges, corners, tets, live, 0, tag, d, level_start, end, size, node_stamp, tet_stamp,
                            order, level)  # fmt: skip
        level_end[d] = size
        level_start = end
