"""Warp kernels of the co-rotational finite element method (Müller & Gross 2004).

Per tet ``t`` with rest shape matrix ``Dm = [X1 - X0, X2 - X0, X3 - X0]``, the
gradients of the barycentric coordinates are the rows of ``Dm^-1``
(``g0 = -(g1 + g2 + g3)``). For a current shape matrix ``Ds`` the deformation
gradient is ``F = Ds Dm^-1`` and its rotation ``R`` comes from the polar
decomposition ``F = R S`` (:func:`polar_rotation`). The linear-elastic
stiffness is never stored as a 12x12 matrix: ``K u`` is applied in the
B-matrix form ``V B^T D B u`` (Müller & Gross 2004, section 3), that is

    grad u = Ds(u) Dm^-1,  eps = sym(grad u),  sigma = 2 mu eps + lambda tr(eps) I,
    (K u)_a = V sigma g_a,

from ``Dm^-1`` (9 floats), the volume and the Lamé parameters, which is
fewer bytes per tet than ``K`` and less arithmetic. The element force is
``f = -R K (R^T x - X)``, whose strain is ``sym(R^T F) - I``; it is exactly
minus the gradient of the co-rotated energy
``V (mu |S - I|^2 + lambda / 2 tr(S - I)^2)`` (McAdams et al. 2011). The
product with the lagged stiffness ``K' = R K R^T`` is formed in the world
frame from the rotated gradients ``Dm^-1 R^T`` that the element pass stores
(:func:`multiply_elements_kernel`).

Scattering per-corner results to nodes with atomics would sum in a racy
order on the CPU's concurrent launches, so every per-tet kernel writes its
four corners to a ``(4 T,)`` array and a per-node kernel gathers them through
the CSR node -> corner incidence in a fixed order: results are bit-identical
for any thread count.

Every kernel takes an ``offset`` right after its inputs and adds it to
``wp.tid()`` (:func:`warpblob._parallel.launch`).
"""

from __future__ import annotations

import warp as wp

#: node flags: a free node, a Dirichlet node, a node no live tet uses (no mass: it stays put), a node of a free
#: rigid body (:mod:`warpblob.sim._rigid`: its rows are projected onto the body's rigid velocities)
FREE = 0
FIXED = 1
INACTIVE = 2
RIGID = 3

_FREE = wp.constant(wp.uint8(FREE))
#: relative height above the ground plane within which a node counts as lying on it (float32 landings
#: put a node on the plane to about 1e-7 relative)
GROUND_TOLERANCE = wp.constant(1e-5)


@wp.func
def shape_matrix(x: wp.array(dtype=wp.vec3), tet: wp.vec4i) -> wp.mat33:
    """``[x1 - x0, x2 - x0, x3 - x0]`` as columns."""
    p0 = x[tet[0]]
    return wp.matrix_from_cols(x[tet[1]] - p0, x[tet[2]] - p0, x[tet[3]] - p0)


@wp.func
def polar_rotation(F: wp.mat33) -> wp.mat33:
    """The rotation ``R`` of ``F = R S``, a proper rotation even for inverted or flat ``F``.

    ``F = U diag(s) V^T`` by ``wp.svd3``; ``R = U V^T``, and when that is a
    reflection (``det < 0``: an inverted tet) the column of ``U`` of the
    smallest singular value is negated, which gives the rotation closest to
    ``F`` (Irving et al. 2004). A flat or collapsed ``F`` has a zero singular
    value whose direction ``svd3`` still completes to an orthonormal frame.
    """
    U = wp.mat33()
    s = wp.vec3()
    V = wp.mat33()
    wp.svd3(F, U, s, V)
    R = U * wp.transpose(V)
    if wp.determinant(R) < 0.0:
        k = int(0)
        if wp.abs(s[1]) < wp.abs(s[k]):
            k = 1
        if wp.abs(s[2]) < wp.abs(s[k]):
            k = 2
        d = wp.vec3(1.0, 1.0, 1.0)
        d[k] = -1.0
        R = U * wp.diag(d) * wp.transpose(V)
    return R


@wp.func
def linear_stress(G: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Cauchy stress of the small strain ``sym(G)``: ``2 mu eps + lambda tr(eps) I``."""
    eps = 0.5 * (G + wp.transpose(G))
    return 2.0 * mu * eps + lam * wp.trace(eps) * wp.identity(n=3, dtype=float)


@wp.kernel(enable_backward=False)
def check_tets_kernel(
    rest: wp.array(dtype=wp.vec3d),
    tets: wp.array(dtype=wp.vec4i),
    alive: wp.array(dtype=wp.uint8),
    ids: wp.array(dtype=wp.int32),
    flat: wp.float64,
    offset: int,
    code: wp.array(dtype=wp.int32),
    volume: wp.array(dtype=wp.float64),
    longest: wp.array(dtype=wp.float64),
):
    """The rest check of listed tet ``i`` (``t = ids[i]``), in float64: ``code[i]`` 0 (valid, or dead), 1 (a
    node outside ``[0, N)``), 2 (a node repeated), 3 (signed volume ``<= flat * longest edge^3``: inverted
    or flat), with its volume and longest edge where the nodes are valid."""
    i = wp.tid() + offset
    t = ids[i]
    code[i] = 0
    if alive[t] == wp.uint8(0):
        return
    n = tets[t]
    N = rest.shape[0]
    for a in range(4):
        if n[a] < 0 or n[a] >= N:
            code[i] = 1
            return
    if n[0] == n[1] or n[0] == n[2] or n[0] == n[3] or n[1] == n[2] or n[1] == n[3] or n[2] == n[3]:
        code[i] = 2
        return
    p0 = rest[n[0]]
    p1 = rest[n[1]]
    p2 = rest[n[2]]
    p3 = rest[n[3]]
    v = wp.dot(p1 - p0, wp.cross(p2 - p0, p3 - p0)) / wp.float64(6.0)
    sq = wp.max(wp.max(wp.length_sq(p1 - p0), wp.length_sq(p2 - p0)), wp.length_sq(p3 - p0))
    sq = wp.max(sq, wp.max(wp.max(wp.length_sq(p2 - p1), wp.length_sq(p3 - p1)), wp.length_sq(p3 - p2)))
    e = wp.sqrt(sq)
    volume[i] = v
    longest[i] = e
    if v <= flat * e * e * e:
        code[i] = 3


@wp.kernel(enable_backward=False)
def prepare_elements_kernel(
    rest: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    alive: wp.array(dtype=wp.uint8),
    ids: wp.array(dtype=wp.int32),
    offset: int,
    dm_inv: wp.array(dtype=wp.mat33),
    volume: wp.array(dtype=float),
):
    """``Dm^-1`` and the rest volume of tets ``ids`` (dead tets: zero, so they contribute nothing)."""
    t = ids[wp.tid() + offset]
    Dm = shape_matrix(rest, tets[t])
    det = wp.determinant(Dm)
    if alive[t] == wp.uint8(0) or det <= 0.0:
        dm_inv[t] = wp.mat33()
        volume[t] = 0.0
    else:
        dm_inv[t] = wp.inverse(Dm)
        volume[t] = det / 6.0


@wp.kernel(enable_backward=False)
def rotate_elements_kernel(
    ids: wp.array(dtype=wp.int32),
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    dm_inv: wp.array(dtype=wp.mat33),
    volume: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    offset: int,
    rotated: wp.array(dtype=wp.mat33),
    corner_force: wp.array(dtype=wp.vec3),
    corner_block: wp.array(dtype=wp.vec4),
    energy: wp.array(dtype=float),
    current_volume: wp.array(dtype=float),
):
    """The one element pass of a step at positions ``x``: every tet, or the tets ``ids`` lists where it
    is not empty (a topology change's).

    Per tet: the rotated gradients ``Dm^-1 R^T`` (rows ``R g_a``, which is all
    the product with ``K'`` needs of ``R``: :func:`multiply_elements_kernel`),
    the elastic energy, the current signed volume; per corner ``a``: the force
    ``f_a = -R K (R^T x - X)`` and the diagonal block of ``K'`` as ``(q, c)``
    with ``K'_aa = c I + q q^T`` (``c = V mu |g_a|^2``,
    ``q = sqrt(V (mu + lambda)) R g_a``).
    """
    t = wp.tid() + offset
    if ids.shape[0] > 0:
        t = ids[t]
    V = volume[t]
    if V == 0.0:
        rotated[t] = wp.mat33()
        energy[t] = 0.0
        current_volume[t] = 0.0
        for a in range(4):
            corner_force[4 * t + a] = wp.vec3()
            corner_block[4 * t + a] = wp.vec4()
        return
    B = dm_inv[t]
    F = shape_matrix(x, tets[t]) * B
    R = polar_rotation(F)
    G = wp.transpose(R) * F - wp.identity(n=3, dtype=float)
    m = mu[t]
    l = lam[t]
    eps = 0.5 * (G + wp.transpose(G))
    tr = wp.trace(eps)
    energy[t] = V * (m * wp.ddot(eps, eps) + 0.5 * l * tr * tr)
    current_volume[t] = V * wp.determinant(F)
    rotated[t] = B * wp.transpose(R)
    H = -V * R * linear_stress(G, m, l) * wp.transpose(B)
    f1 = wp.vec3(H[0, 0], H[1, 0], H[2, 0])
    f2 = wp.vec3(H[0, 1], H[1, 1], H[2, 1])
    f3 = wp.vec3(H[0, 2], H[1, 2], H[2, 2])
    corner_force[4 * t + 0] = -(f1 + f2 + f3)
    corner_force[4 * t + 1] = f1
    corner_force[4 * t + 2] = f2
    corner_force[4 * t + 3] = f3
    s = wp.sqrt(V * (m + l))
    for a in range(1, 4):
        g = wp.vec3(B[a - 1, 0], B[a - 1, 1], B[a - 1, 2])
        q = s * (R * g)
        corner_block[4 * t + a] = wp.vec4(q[0], q[1], q[2], V * m * wp.dot(g, g))
    g0 = -wp.vec3(B[0, 0] + B[1, 0] + B[2, 0], B[0, 1] + B[1, 1] + B[2, 1], B[0, 2] + B[1, 2] + B[2, 2])
    q0 = s * (R * g0)
    corner_block[4 * t] = wp.vec4(q0[0], q0[1], q0[2], V * m * wp.dot(g0, g0))


@wp.kernel(enable_backward=False)
def gather_elements_kernel(
    nodes: wp.array(dtype=wp.int32),
    node_range: wp.array(dtype=wp.vec2i),
    node_corners: wp.array(dtype=wp.int32),
    corner_force: wp.array(dtype=wp.vec3),
    corner_block: wp.array(dtype=wp.vec4),
    offset: int,
    node_force: wp.array(dtype=wp.vec3),
    node_block: wp.array(dtype=wp.mat33),
):
    """Per node, in incidence order: the elastic force and the diagonal block of ``K'``; of the listed
    ``nodes`` (a topology change's: the others keep theirs), or of every node where the list is empty."""
    i = wp.tid() + offset
    if nodes.shape[0] > 0:
        i = nodes[i]
    f = wp.vec3()
    D = wp.mat33()
    own = node_range[i]
    for k in range(own[0], own[1]):
        c = node_corners[k]
        f += corner_force[c]
        b = corner_block[c]
        q = wp.vec3(b[0], b[1], b[2])
        D += wp.outer(q, q) + b[3] * wp.identity(n=3, dtype=float)
    node_force[i] = f
    node_block[i] = D


@wp.kernel(enable_backward=False)
def gather_masses_kernel(
    nodes: wp.array(dtype=wp.int32),
    node_range: wp.array(dtype=wp.vec2i),
    node_corners: wp.array(dtype=wp.int32),
    volume: wp.array(dtype=float),
    density: wp.array(dtype=float),
    offset: int,
    mass: wp.array(dtype=float),
):
    """Lumped mass: a quarter of each incident tet's ``density * volume``, in incidence order; of the listed
    ``nodes``, or of every node where the list is empty."""
    i = wp.tid() + offset
    if nodes.shape[0] > 0:
        i = nodes[i]
    m = float(0.0)
    own = node_range[i]
    for k in range(own[0], own[1]):
        t = node_corners[k] // 4
        m += 0.25 * density[t] * volume[t]
    mass[i] = m


@wp.kernel(enable_backward=False)
def incidence_count_kernel(
    touched: wp.array(dtype=wp.int32),
    old_range: wp.array(dtype=wp.vec2i),
    old_corners: wp.array(dtype=wp.int32),
    changed: wp.array(dtype=wp.uint8),
    add_start: wp.array(dtype=wp.int32),
    offset: int,
    count: wp.array(dtype=wp.int32),
):
    """Per touched node: its old corners whose tet is unchanged plus its corners among the changed tets'
    (``add_start[u]..add_start[u + 1]``); a node past the old ones has no old list."""
    u = wp.tid() + offset
    i = touched[u]
    c = add_start[u + 1] - add_start[u]
    if i < old_range.shape[0]:
        own = old_range[i]
        for m in range(own[0], own[1]):
            if changed[old_corners[m] // 4] == wp.uint8(0):
                c += 1
    count[u] = c


@wp.kernel(enable_backward=False)
def incidence_merge_kernel(
    touched: wp.array(dtype=wp.int32),
    old_range: wp.array(dtype=wp.vec2i),
    old_corners: wp.array(dtype=wp.int32),
    changed: wp.array(dtype=wp.uint8),
    add_start: wp.array(dtype=wp.int32),
    add_corners: wp.array(dtype=wp.int32),
    scratch_start: wp.array(dtype=wp.int32),
    start: wp.array(dtype=wp.int32),
    scratch: wp.array(dtype=wp.int32),
    offset: int,
    corners: wp.array(dtype=wp.int32),
):
    """A touched node's list: its old corners of unchanged tets merged with its corners of changed tets
    (both ascending), ascending, as a sort of the whole incidence gives it; merged into the node's part of
    ``scratch`` (from ``scratch_start[u]``), then written from ``start[u]`` of ``corners``, which may be
    where the old list was (the slots of a node's list are its own: no other thread reads or writes them)."""
    u = wp.tid() + offset
    i = touched[u]
    m = int(0)
    m_end = int(0)
    if i < old_range.shape[0]:
        own = old_range[i]
        m = own[0]
        m_end = own[1]
    a = add_start[u]
    a_end = add_start[u + 1]
    d = scratch_start[u]
    while m < m_end or a < a_end:
        if m < m_end and changed[old_corners[m] // 4] != wp.uint8(0):
            m += 1
        elif a >= a_end or (m < m_end and old_corners[m] < add_corners[a]):
            scratch[d] = old_corners[m]
            d += 1
            m += 1
        else:
            scratch[d] = add_corners[a]
            d += 1
            a += 1
    s = start[u]
    for j in range(scratch_start[u], d):
        corners[s + j - scratch_start[u]] = scratch[j]


@wp.kernel(enable_backward=False)
def assemble_system_kernel(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    flags: wp.array(dtype=wp.uint8),
    target: wp.array(dtype=wp.vec3),
    node_force: wp.array(dtype=wp.vec3),
    node_block: wp.array(dtype=wp.mat33),
    external: wp.array(dtype=wp.vec3),
    contact_force: wp.array(dtype=wp.vec3),
    contact_weight: wp.array(dtype=float),
    contact_block: wp.array(dtype=wp.mat33),
    gravity: wp.vec3,
    h: float,
    c_mass: float,
    c_stiff: float,
    c_contact: float,
    ground: int,
    height: float,
    friction: float,
    offset: int,
    rhs: wp.array(dtype=wp.vec3),
    guess: wp.array(dtype=wp.vec3),
    prescribed: wp.array(dtype=wp.vec3),
    axes: wp.array(dtype=wp.vec3),
    coarse_axes: wp.array(dtype=wp.vec3),
    inverse_block: wp.array(dtype=wp.mat33),
):
    """The filtered system of a step, per node: free axes, prescribed velocities, right-hand side, warm start
    and block-Jacobi inverse.

    A node of a free rigid body (``RIGID``) gets the free node's ``b`` and
    warm start without the ground (its body handles contact), all axes in
    ``axes`` and none in ``coarse_axes`` (the coarse space leaves it out),
    and a zero block-Jacobi inverse: the body's rows are projected and
    preconditioned per body (:mod:`warpblob.sim._rigid`). Everywhere else
    ``coarse_axes`` equals ``axes``.

    A free node has ``b = M v + h (f + M g + f_ext)``. A fixed node has no free
    axis and the velocity ``(target - x) / h`` that lands it on its target.
    Ground contact, with the node's own predicted velocity
    ``v* = v + h (f + M g + f_ext) / m``: a node whose predicted position is
    below the plane is in contact when it lies on the plane (within
    :data:`GROUND_TOLERANCE`) or when its prediction without the elastic
    force ``f`` falls below it too (on a light node of a pre-stressed body
    just cut, ``f`` is large and balanced in the solve: it must not bring the
    node down from above the plane); its z velocity is constrained to
    ``v_c = (height - z) / h``, which puts it on the plane, and the ground
    thereby removes ``dv_n = v_c - v*_z`` of normal velocity. Coulomb
    friction: when the predicted tangential speed is at most
    ``friction * dv_n`` the node sticks (all axes constrained, tangential
    velocity 0), else it slides with the friction impulse
    ``-friction * m * dv_n`` along its predicted tangential direction added
    to ``b``. Contacts and friction thus act inside the implicit solve.

    Tool contact (with ``c_contact`` non-zero, on a node of positive
    ``contact_weight``): the contact force joins ``f`` and ``c_contact`` times
    its stiffness block joins the system (:func:`contact_row`); elsewhere no
    arithmetic changes, so an idle tool leaves every bit as it was.

    The filtered system is ``S A S + I - S`` with ``S = diag(axes)``; its
    right-hand side gets ``S b + (I - S) v_p`` here and ``- S A v_p`` from
    :func:`gather_products_kernel`.
    """
    i = wp.tid() + offset
    flag = flags[i]
    one = wp.identity(n=3, dtype=float)
    if flag == wp.uint8(RIGID):
        m = mass[i]
        force = node_force[i] + m * gravity + external[i]
        if c_contact != 0.0:
            if contact_weight[i] > 0.0:
                force = force + contact_force[i]
        rhs[i] = m * v[i] + h * force
        guess[i] = v[i]
        prescribed[i] = wp.vec3()
        axes[i] = wp.vec3(1.0, 1.0, 1.0)
        coarse_axes[i] = wp.vec3()
        inverse_block[i] = wp.mat33()
        return
    if flag != _FREE:
        vp = wp.vec3()
        if flag == wp.uint8(FIXED):
            vp = (target[i] - x[i]) / h
        rhs[i] = vp
        guess[i] = vp
        prescribed[i] = vp
        axes[i] = wp.vec3()
        coarse_axes[i] = wp.vec3()
        inverse_block[i] = one
        return
    m = mass[i]
    force = node_force[i] + m * gravity + external[i]
    touched = c_contact != 0.0 and contact_weight[i] > 0.0
    if touched:
        force = force + contact_force[i]
    b = m * v[i] + h * force
    s = wp.vec3(1.0, 1.0, 1.0)
    vp = wp.vec3()
    if ground != 0:
        predicted = v[i] + (h / m) * force
        # a node comes into contact when it falls onto the plane (its prediction without the elastic force)
        # or, lying on it, is pressed into it (with the elastic force: the load of the body above it). The
        # elastic force alone does not bring a node down from above the plane: on a light node of a
        # pre-stressed body just cut (a split point, a tiny mass) it is large, and is balanced in the solve
        falling = v[i] + (h / m) * (force - node_force[i])
        lying = x[i][2] <= height + GROUND_TOLERANCE * (1.0 + wp.abs(height))
        if x[i][2] + h * falling[2] < height or (lying and x[i][2] + h * predicted[2] < height):
            vc = (height - x[i][2]) / h
            dvn = wp.max(vc - predicted[2], 0.0)
            vp = wp.vec3(0.0, 0.0, vc)
            tangent = wp.vec3(predicted[0], predicted[1], 0.0)
            speed = wp.length(tangent)
            if speed <= friction * dvn:
                s = wp.vec3()
            else:
                s = wp.vec3(1.0, 1.0, 0.0)
                b = b - (friction * m * dvn / speed) * tangent
    S = wp.diag(s)
    rhs[i] = wp.cw_mul(s, b) + vp
    guess[i] = wp.cw_mul(s, v[i]) + vp
    prescribed[i] = vp
    axes[i] = s
    coarse_axes[i] = s
    constrained = wp.diag(wp.vec3(1.0, 1.0, 1.0) - s)
    D = c_mass * m * one + c_stiff * node_block[i]
    if touched:
        D = D + c_contact * contact_block[i]
    inverse_block[i] = wp.inverse(S * D * S + constrained)


@wp.kernel(enable_backward=False)
def multiply_elements_kernel(
    p: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    volume: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    rotated: wp.array(dtype=wp.mat33),
    axes: wp.array(dtype=wp.vec3),
    offset: int,
    corner_out: wp.array(dtype=wp.vec3),
):
    """Per corner ``(R K R^T S p)_a``, ``S = diag(axes)`` masking the constrained axes of the input.

    In the world frame: with ``M = Dm^-1 R^T`` (rows ``n_a = R g_a``), the
    rotated gradient is ``R (R^T Ds Dm^-1) R^T = Ds M``, its stress
    ``s = 2 mu sym(Ds M) + lambda tr(Ds M) I`` is ``R sigma R^T``, and
    ``(K' p)_a = V R sigma g_a = V s n_a``: the columns of ``V s M^T``. Half
    the arithmetic of rotating in and out, and one matrix read instead of two.
    """
    t = wp.tid() + offset
    V = volume[t]
    if V == 0.0:
        for a in range(4):
            corner_out[4 * t + a] = wp.vec3()
        return
    tet = tets[t]
    u0 = wp.cw_mul(axes[tet[0]], p[tet[0]])
    u1 = wp.cw_mul(axes[tet[1]], p[tet[1]])
    u2 = wp.cw_mul(axes[tet[2]], p[tet[2]])
    u3 = wp.cw_mul(axes[tet[3]], p[tet[3]])
    M = rotated[t]
    H = V * linear_stress(wp.matrix_from_cols(u1 - u0, u2 - u0, u3 - u0) * M, mu[t], lam[t]) * wp.transpose(M)
    y1 = wp.vec3(H[0, 0], H[1, 0], H[2, 0])
    y2 = wp.vec3(H[0, 1], H[1, 1], H[2, 1])
    y3 = wp.vec3(H[0, 2], H[1, 2], H[2, 2])
    corner_out[4 * t + 0] = -(y1 + y2 + y3)
    corner_out[4 * t + 1] = y1
    corner_out[4 * t + 2] = y2
    corner_out[4 * t + 3] = y3


@wp.func
def contact_row(
    i: int,
    Ap: wp.vec3,
    u: wp.vec3,
    s: wp.vec3,
    contact_weight: wp.array(dtype=float),
    contact_block: wp.array(dtype=wp.mat33),
    c_contact: float,
) -> wp.vec3:
    """``Ap + S c_contact K_c u`` on a node in tool contact, else ``Ap`` untouched (no rounding added).

    ``K_c`` is the node's contact stiffness block (a penalty inside the
    implicit solve, :mod:`warpblob.sim._contact`); it is block diagonal, so
    it acts on the node's own ``u`` only.
    """
    if c_contact != 0.0:
        if contact_weight[i] > 0.0:
            return Ap + wp.cw_mul(s, c_contact * (contact_block[i] * u))
    return Ap


@wp.func
def apply_row(
    i: int,
    node_range: wp.array(dtype=wp.vec2i),
    node_corners: wp.array(dtype=wp.int32),
    corner_out: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    axes: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    c_mass: float,
    c_stiff: float,
    contact_weight: wp.array(dtype=float),
    contact_block: wp.array(dtype=wp.mat33),
    c_contact: float,
) -> wp.vec3:
    """Row ``i`` of the filtered ``S (c_mass M + c_stiff K' + c_contact K_c) S p + (I - S) p`` from the
    per-corner products of ``S p``, summed in incidence order."""
    s = axes[i]
    Kp = wp.vec3()
    own = node_range[i]
    for k in range(own[0], own[1]):
        Kp += corner_out[node_corners[k]]
    pi = p[i]
    sp = wp.cw_mul(s, pi)
    Ap = wp.cw_mul(s, c_mass * mass[i] * sp + c_stiff * Kp) + wp.cw_mul(wp.vec3(1.0, 1.0, 1.0) - s, pi)
    return contact_row(i, Ap, sp, s, contact_weight, contact_block, c_contact)


@wp.kernel(enable_backward=False)
def gather_products_kernel(
    node_range: wp.array(dtype=wp.vec2i),
    node_corners: wp.array(dtype=wp.int32),
    corner_out: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    axes: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    y: wp.array(dtype=wp.vec3),
    c_mass: float,
    c_stiff: float,
    contact_weight: wp.array(dtype=float),
    contact_block: wp.array(dtype=wp.mat33),
    c_contact: float,
    alpha: float,
    beta: float,
    project: int,
    offset: int,
    z: wp.array(dtype=wp.vec3),
):
    """``z = alpha A' p + beta y``.

    With ``project``, ``A'`` is the filtered operator ``S A S + I - S`` (the
    corners hold products of ``S p``); without, it is ``S A`` (the corners
    hold products of the unmasked ``p``): the coupling of prescribed
    velocities taken off the free rows of the right-hand side.
    """
    i = wp.tid() + offset
    yi = wp.vec3()
    if beta != 0.0:
        yi = beta * y[i]
    s = axes[i]
    Ap = wp.vec3()
    if project != 0:
        Ap = apply_row(i, node_range, node_corners, corner_out, mass, axes, p, c_mass, c_stiff, contact_weight,
                       contact_block, c_contact)  # fmt: skip
    else:
        Kp = wp.vec3()
        own = node_range[i]
        for k in range(own[0], own[1]):
            Kp += corner_out[node_corners[k]]
        Ap = contact_row(i, wp.cw_mul(s, c_mass * mass[i] * p[i] + c_stiff * Kp), p[i], s, contact_weight,
                         contact_block, c_contact)  # fmt: skip
    z[i] = alpha * Ap + yi


# -- preconditioned conjugate gradients ------------------------------------------------------------
# The node kernels of CG run over ``blocks`` contiguous node ranges, one thread each, and write one
# partial dot product per block; the next kernel sums the partials in block order. The block count
# depends on the node count only, so the sums (and the solution) are the same for every thread count.
# Partial rows: 0 and 1 ``r.z`` (alternating by iteration parity), 2 ``r.r``, 3 ``b.b``, 4 ``p.Ap``.


@wp.func
def block_range(b: int, blocks: int, n: int) -> wp.vec2i:
    return wp.vec2i(b * n // blocks, (b + 1) * n // blocks)


@wp.func
def partial_sum(partials: wp.array2d(dtype=float), row: int) -> float:
    s = float(0.0)
    for b in range(partials.shape[1]):
        s += partials[row, b]
    return s


@wp.kernel(enable_backward=False)
def start_cg_kernel(
    node_range: wp.array(dtype=wp.vec2i),
    node_corners: wp.array(dtype=wp.int32),
    corner_out: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    axes: wp.array(dtype=wp.vec3),
    inverse_block: wp.array(dtype=wp.mat33),
    b_vec: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
    c_mass: float,
    c_stiff: float,
    contact_weight: wp.array(dtype=float),
    contact_block: wp.array(dtype=wp.mat33),
    c_contact: float,
    n: int,
    offset: int,
    r: wp.array(dtype=wp.vec3),
    z: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    partials: wp.array2d(dtype=float),
):
    """``r = b - A' x``, ``z = P r``, ``p = z``; partials ``r.z`` (row 0), ``r.r``, ``b.b``."""
    blk = wp.tid() + offset
    span = block_range(blk, partials.shape[1], n)
    rz = float(0.0)
    rr = float(0.0)
    bb = float(0.0)
    for i in range(span[0], span[1]):
        bi = b_vec[i]
        ri = bi - apply_row(i, node_range, node_corners, corner_out, mass, axes, x, c_mass, c_stiff, contact_weight,
                            contact_block, c_contact)  # fmt: skip
        zi = inverse_block[i] * ri
        r[i] = ri
        z[i] = zi
        p[i] = zi
        rz += wp.dot(ri, zi)
        rr += wp.dot(ri, ri)
        bb += wp.dot(bi, bi)
    partials[0, blk] = rz
    partials[2, blk] = rr
    partials[3, blk] = bb


@wp.kernel(enable_backward=False)
def product_cg_kernel(
    node_range: wp.array(dtype=wp.vec2i),
    node_corners: wp.array(dtype=wp.int32),
    corner_out: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    axes: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    c_mass: float,
    c_stiff: float,
    contact_weight: wp.array(dtype=float),
    contact_block: wp.array(dtype=wp.mat33),
    c_contact: float,
    n: int,
    offset: int,
    Ap: wp.array(dtype=wp.vec3),
    partials: wp.array2d(dtype=float),
):
    """``Ap = A' p``; partial ``p.Ap``."""
    blk = wp.tid() + offset
    span = block_range(blk, partials.shape[1], n)
    pAp = float(0.0)
    for i in range(span[0], span[1]):
        y = apply_row(i, node_range, node_corners, corner_out, mass, axes, p, c_mass, c_stiff, contact_weight,
                      contact_block, c_contact)  # fmt: skip
        Ap[i] = y
        pAp += wp.dot(p[i], y)
    partials[4, blk] = pAp


@wp.kernel(enable_backward=False)
def update_cg_kernel(
    inverse_block: wp.array(dtype=wp.mat33),
    p: wp.array(dtype=wp.vec3),
    Ap: wp.array(dtype=wp.vec3),
    parity: int,
    n: int,
    offset: int,
    x: wp.array(dtype=wp.vec3),
    r: wp.array(dtype=wp.vec3),
    z: wp.array(dtype=wp.vec3),
    partials: wp.array2d(dtype=float),
):
    """``alpha = r.z / p.Ap``; ``x += alpha p``, ``r -= alpha Ap``, ``z = P r``; partials: new ``r.z``, ``r.r``."""
    blk = wp.tid() + offset
    span = block_range(blk, partials.shape[1], n)
    pAp = partial_sum(partials, 4)
    alpha = float(0.0)
    if pAp > 0.0:
        alpha = partial_sum(partials, parity) / pAp
    rz = float(0.0)
    rr = float(0.0)
    for i in range(span[0], span[1]):
        x[i] = x[i] + alpha * p[i]
        ri = r[i] - alpha * Ap[i]
        zi = inverse_block[i] * ri
        r[i] = ri
        z[i] = zi
        rz += wp.dot(ri, zi)
        rr += wp.dot(ri, ri)
    partials[1 - parity, blk] = rz
    partials[2, blk] = rr


@wp.kernel(enable_backward=False)
def direction_cg_kernel(
    z: wp.array(dtype=wp.vec3),
    parity: int,
    n: int,
    offset: int,
    p: wp.array(dtype=wp.vec3),
    partials: wp.array2d(dtype=float),
):
    """``beta = r.z (new) / r.z (old)``; ``p = z + beta p``."""
    blk = wp.tid() + offset
    span = block_range(blk, partials.shape[1], n)
    old = partial_sum(partials, parity)
    beta = float(0.0)
    if old > 0.0:
        beta = partial_sum(partials, 1 - parity) / old
    for i in range(span[0], span[1]):
        p[i] = z[i] + beta * p[i]


@wp.kernel(enable_backward=False)
def precondition_kernel(
    inverse_block: wp.array(dtype=wp.mat33),
    r: wp.array(dtype=wp.vec3),
    y: wp.array(dtype=wp.vec3),
    alpha: float,
    beta: float,
    offset: int,
    z: wp.array(dtype=wp.vec3),
):
    """``z = alpha P r + beta y`` with the block-Jacobi ``P`` (the preconditioner as a ``LinearOperator``)."""
    i = wp.tid() + offset
    zi = alpha * (inverse_block[i] * r[i])
    if beta != 0.0:
        zi = zi + beta * y[i]
    z[i] = zi


@wp.kernel(enable_backward=False)
def advance_nodes_kernel(
    x: wp.array(dtype=wp.vec3),
    flags: wp.array(dtype=wp.uint8),
    target: wp.array(dtype=wp.vec3),
    axes: wp.array(dtype=wp.vec3),
    h: float,
    ground: int,
    height: float,
    offset: int,
    v: wp.array(dtype=wp.vec3),
    x_new: wp.array(dtype=wp.vec3),
    moved: wp.array(dtype=wp.vec3),
):
    """``x_new = x + h v`` after the solve: fixed nodes onto their targets, ground contacts onto the plane.

    A free node that the solve still carried below the plane is set onto it
    (without its downward velocity). ``moved`` is the displacement a
    constraint imposed (a fixed node's step, a contact's landing, a lift),
    for the divergence check's work estimate.
    """
    i = wp.tid() + offset
    flag = flags[i]
    if flag == wp.uint8(FIXED):
        x_new[i] = target[i]
        moved[i] = target[i] - x[i]
        return
    if flag == wp.uint8(INACTIVE):
        v[i] = wp.vec3()
        x_new[i] = x[i]
        moved[i] = wp.vec3()
        return
    if flag == wp.uint8(RIGID):
        # placed by its body's pose (:meth:`warpblob.sim._rigid.RigidBodies.advance`)
        moved[i] = wp.vec3()
        return
    xi = x[i]
    vi = v[i]
    p = xi + h * vi
    lift = wp.vec3()
    if ground != 0:
        if axes[i][2] == 0.0:
            lift = wp.vec3(0.0, 0.0, height - xi[2])
            p = wp.vec3(p[0], p[1], height)
        elif p[2] < height:
            lift = wp.vec3(0.0, 0.0, height - p[2])
            p = wp.vec3(p[0], p[1], height)
            vi = wp.vec3(vi[0], vi[1], wp.max(vi[2], 0.0))
    v[i] = vi
    x_new[i] = p
    moved[i] = lift


@wp.func
def tet_box(x: wp.array(dtype=wp.vec3), tet: wp.vec4i):
    """The box of tet ``tet`` at the positions ``x``: ``(lower, upper)``."""
    lo = x[tet[0]]
    hi = x[tet[0]]
    for a in range(1, 4):
        lo = wp.min(lo, x[tet[a]])
        hi = wp.max(hi, x[tet[a]])
    return lo, hi


@wp.kernel(enable_backward=False)
def tet_bounds_kernel(
    rest: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    volume: wp.array(dtype=float),
    offset: int,
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """Rest AABB of each tet; dead tets get a box far away that no query reaches."""
    t = wp.tid() + offset
    if volume[t] == 0.0:
        lowers[t] = wp.vec3(1.0e30, 1.0e30, 1.0e30)
        uppers[t] = wp.vec3(1.0e30, 1.0e30, 1.0e30)
        return
    lo, hi = tet_box(rest, tets[t])
    lowers[t] = lo
    uppers[t] = hi


@wp.func
def triangle_distance(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> float:
    """Distance from ``p`` to triangle ``abc`` (Ericson 2005, section 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.length(ap)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.length(bp)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return wp.length(ap - (d1 / (d1 - d3)) * ab)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.length(cp)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return wp.length(ap - (d2 / (d2 - d6)) * ac)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        return wp.length(bp - ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b))
    denom = 1.0 / (va + vb + vc)
    return wp.length(ap - (vb * denom) * ab - (vc * denom) * ac)


@wp.func
def barycentric(p: wp.vec3, rest: wp.array(dtype=wp.vec3), tet: wp.vec4i, B: wp.mat33) -> wp.vec4:
    """Barycentric coordinates of ``p`` in a rest tet (unclamped: outside, some are negative)."""
    b = B * (p - rest[tet[0]])
    return wp.vec4(1.0 - b[0] - b[1] - b[2], b[0], b[1], b[2])


@wp.kernel(enable_backward=False)
def embed_points_kernel(
    bvh: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    rest: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    dm_inv: wp.array(dtype=wp.mat33),
    radius: float,
    offset: int,
    point_tet: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    point_distance: wp.array(dtype=float),
):
    """The containing rest tet of each point (the most interior one), else the nearest.

    Boxes of radius ``radius`` around the point, doubled until they hold a
    tet within the radius: a tet nearer than the best one found overlaps
    the box, so the search is exact. Ties go to the smallest tet index, so
    the result does not depend on the traversal order.
    """
    i = wp.tid() + offset
    p = points[i]
    r = radius
    best = int(-1)
    best_d = float(1.0e30)
    best_in = float(-1.0e30)
    for _round in range(64):
        query = wp.bvh_query_aabb(bvh, p - wp.vec3(r, r, r), p + wp.vec3(r, r, r))
        t = int(0)
        while wp.bvh_query_next(query, t):
            tet = tets[t]
            b = barycentric(p, rest, tet, dm_inv[t])
            inside = wp.min(wp.min(b[0], b[1]), wp.min(b[2], b[3]))
            d = float(0.0)
            if inside < 0.0:
                x0 = rest[tet[0]]
                x1 = rest[tet[1]]
                x2 = rest[tet[2]]
                x3 = rest[tet[3]]
                d = wp.min(
                    wp.min(triangle_distance(p, x1, x2, x3), triangle_distance(p, x0, x3, x2)),
                    wp.min(triangle_distance(p, x0, x1, x3), triangle_distance(p, x0, x2, x1)),
                )
            better = d < best_d or (d == best_d and (inside > best_in or (inside == best_in and t < best)))
            if better:
                best = t
                best_d = d
                best_in = inside
        if best >= 0 and best_d <= r:
            break
        r = 2.0 * r
    point_tet[i] = best
    point_distance[i] = best_d
    if best >= 0:
        point_bary[i] = barycentric(p, rest, tets[best], dm_inv[best])
    else:
        point_bary[i] = wp.vec4()


@wp.kernel(enable_backward=False)
def interpolate_points_kernel(
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    point_tet: wp.array(dtype=wp.int32),
    point_bary: wp.array(dtype=wp.vec4),
    offset: int,
    out: wp.array(dtype=wp.vec3),
):
    """Deformed embedded points ``x0 + b1 (x1 - x0) + b2 (x2 - x0) + b3 (x3 - x0)`` (rounding scales with the tet)."""
    i = wp.tid() + offset
    tet = tets[point_tet[i]]
    b = point_bary[i]
    p0 = x[tet[0]]
    out[i] = p0 + b[1] * (x[tet[1]] - p0) + b[2] * (x[tet[2]] - p0) + b[3] * (x[tet[3]] - p0)


# -- two-level preconditioner (warpblob.sim._coarse) ----------------------------------------------
# Each node ``i`` of aggregate ``g`` carries the six rigid modes of ``g`` as the rows of
# ``Phi_i = [I, -[d_i]x]`` (3 x 6; ``d_i`` is its offset from the aggregate's centroid over the
# aggregate's size): ``Phi_i (t, w) = t + w x d_i``. Per-tet products go to per-tet slots and are
# gathered in a fixed order, like the corner arrays, so the coarse matrix is the same for any thread count.


@wp.func
def mode_row(d: wp.vec3, k: int) -> wp.spatial_vector:
    """Row ``k`` of ``Phi = [I, -[d]x]``: component ``k`` of the displacements of the six modes."""
    if k == 0:
        return wp.spatial_vector(1.0, 0.0, 0.0, 0.0, d[2], -d[1])
    if k == 1:
        return wp.spatial_vector(0.0, 1.0, 0.0, -d[2], 0.0, d[0])
    return wp.spatial_vector(0.0, 0.0, 1.0, d[1], -d[0], 0.0)


@wp.func
def mode_restrict(d: wp.vec3, s: wp.vec3, u: wp.vec3) -> wp.spatial_vector:
    """``Phi^T S u = (S u, d x S u)``: a node's vector restricted to its aggregate's modes."""
    v = wp.cw_mul(s, u)
    w = wp.cross(d, v)
    return wp.spatial_vector(v[0], v[1], v[2], w[0], w[1], w[2])


@wp.func
def mode_mass(d: wp.vec3, s: wp.vec3) -> wp.spatial_matrix:
    """``Phi^T S Phi``: a node's unit mass seen by its aggregate's modes."""
    out = wp.spatial_matrix()
    for k in range(3):
        if s[k] != 0.0:
            row = mode_row(d, k)
            out += wp.outer(row, row)
    return out


@wp.func
def corner_gradient(rotated: wp.mat33, a: int) -> wp.vec3:
    """``n_a = R g_a``: row ``a - 1`` of ``Dm^-1 R^T`` (``n_0 = -(n_1 + n_2 + n_3)``)."""
    if a == 0:
        return -(
            wp.vec3(rotated[0, 0], rotated[0, 1], rotated[0, 2])
            + wp.vec3(rotated[1, 0], rotated[1, 1], rotated[1, 2])
            + wp.vec3(rotated[2, 0], rotated[2, 1], rotated[2, 2])
        )
    return wp.vec3(rotated[a - 1, 0], rotated[a - 1, 1], rotated[a - 1, 2])


@wp.kernel(enable_backward=False)
def frame_aggregates_kernel(
    x: wp.array(dtype=wp.vec3),
    aggregate_offsets: wp.array(dtype=wp.int32),
    aggregate_nodes: wp.array(dtype=wp.int32),
    scale: float,
    offset: int,
    node_mode: wp.array(dtype=wp.vec3),
):
    """Per aggregate: its nodes' offsets ``d_i = (x_i - c) / scale`` from their centroid ``c``."""
    g = wp.tid() + offset
    lo = aggregate_offsets[g]
    hi = aggregate_offsets[g + 1]
    c = wp.vec3()
    for k in range(lo, hi):
        c += x[aggregate_nodes[k]]
    c = c / float(hi - lo)
    for k in range(lo, hi):
        i = aggregate_nodes[k]
        node_mode[i] = (x[i] - c) / scale


@wp.func
def _corner_groups(tets: wp.array(dtype=wp.vec4i), alive: wp.array(dtype=wp.uint8),
                   node_aggregate: wp.array(dtype=wp.int32), t: int) -> wp.vec4i:  # fmt: skip
    """Per corner of tet ``t``: the number of its aggregate among the tet's distinct aggregates in order of
    first appearance; ``-1`` everywhere for a dead tet or one with a corner in no aggregate."""
    c = tets[t]
    g = wp.vec4i(-1, -1, -1, -1)
    if alive[t] == wp.uint8(0):
        return g
    a = wp.vec4i(node_aggregate[c[0]], node_aggregate[c[1]], node_aggregate[c[2]], node_aggregate[c[3]])
    if a[0] < 0 or a[1] < 0 or a[2] < 0 or a[3] < 0:
        return g
    n = int(0)
    for i in range(4):
        for j in range(i + 1):
            if g[i] < 0:
                if j == i:
                    g[i] = n
                    n += 1
                elif a[j] == a[i]:
                    g[i] = g[j]
    return g


@wp.kernel(enable_backward=False)
def couple_tets_kernel(
    tets: wp.array(dtype=wp.vec4i),
    volume: wp.array(dtype=float),
    mu: wp.array(dtype=float),
    lam: wp.array(dtype=float),
    rotated: wp.array(dtype=wp.mat33),
    axes: wp.array(dtype=wp.vec3),
    node_mode: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=wp.uint8),
    node_aggregate: wp.array(dtype=wp.int32),
    slot_start: wp.array(dtype=wp.int64),
    c_stiff: float,
    offset: int,
    slots: wp.array(dtype=wp.spatial_matrix),
):
    """Per tet, ``c_stiff Phi_a^T S_a K'_ab S_b Phi_b`` for its 16 corner pairs, summed into its slots.

    The slot of corners ``(a, b)`` is ``slot_start[t] + g_a u + g_b``, with
    ``g`` the corners' groups (:func:`_corner_groups`) and ``u`` their count
    (:func:`tet_pair_slots_kernel`'s layout); a tet owns its slots (zeroed
    before), so the sums need no atomics. With ``K'_ab = V (mu (n_a . n_b) I + mu n_b n_a^T + lambda n_a n_b^T)``
    (:func:`multiply_elements_kernel`) and ``U = S Phi``, the block is
    ``V (mu (n_a . n_b) U_a^T U_b + mu (U_a^T n_b)(U_b^T n_a)^T + lambda (U_a^T n_a)(U_b^T n_b)^T)``;
    the pair ``(b, a)`` gets its transpose.
    """
    t = wp.tid() + offset
    V = volume[t]
    if V == 0.0:
        return
    g = _corner_groups(tets, alive, node_aggregate, t)
    u = wp.max(wp.max(g[0], g[1]), wp.max(g[2], g[3])) + 1
    if u == 0:
        return
    first = int(slot_start[t])
    tet = tets[t]
    M = rotated[t]
    m = mu[t]
    l = lam[t]
    for a in range(4):
        na = corner_gradient(M, a)
        da = node_mode[tet[a]]
        sa = axes[tet[a]]
        qa = mode_restrict(da, sa, na)
        for b in range(a, 4):
            nb = corner_gradient(M, b)
            db = node_mode[tet[b]]
            sb = axes[tet[b]]
            W = l * wp.outer(qa, mode_restrict(db, sb, nb)) + m * wp.outer(mode_restrict(da, sa, nb),
                                                                              mode_restrict(db, sb, na))  # fmt: skip
            c = m * wp.dot(na, nb)
            for k in range(3):
                if sa[k] * sb[k] != 0.0:
                    W += c * wp.outer(mode_row(da, k), mode_row(db, k))
            W = (c_stiff * V) * W
            ab = first + g[a] * u + g[b]
            slots[ab] = slots[ab] + W
            if b != a:
                ba = first + g[b] * u + g[a]
                slots[ba] = slots[ba] + wp.transpose(W)


@wp.kernel(enable_backward=False)
def assemble_coarse_kernel(
    pair_offsets: wp.array(dtype=wp.int32),
    pair_slots: wp.array(dtype=wp.int32),
    extra_offsets: wp.array(dtype=wp.int32),
    extra_slots: wp.array(dtype=wp.int32),
    pair_aggregates: wp.array(dtype=wp.vec2i),
    slots: wp.array(dtype=wp.spatial_matrix),
    aggregate_offsets: wp.array(dtype=wp.int32),
    aggregate_nodes: wp.array(dtype=wp.int32),
    mass: wp.array(dtype=float),
    axes: wp.array(dtype=wp.vec3),
    node_mode: wp.array(dtype=wp.vec3),
    c_mass: float,
    offset: int,
    coarse: wp.array2d(dtype=wp.spatial_matrix),
):
    """Block ``(g, h)`` of the coarse matrix ``P^T A' P``: its tets' slots in order (the aggregation's, then
    those of the tets added since), plus on the diagonal ``c_mass sum_i m_i Phi_i^T S_i Phi_i`` over the
    aggregate's nodes."""
    p = wp.tid() + offset
    gh = pair_aggregates[p]
    W = wp.spatial_matrix()
    for k in range(pair_offsets[p], pair_offsets[p + 1]):
        W += slots[pair_slots[k]]
    for k in range(extra_offsets[p], extra_offsets[p + 1]):
        W += slots[extra_slots[k]]
    if gh[0] == gh[1]:
        for k in range(aggregate_offsets[gh[0]], aggregate_offsets[gh[0] + 1]):
            i = aggregate_nodes[k]
            W += (c_mass * mass[i]) * mode_mass(node_mode[i], axes[i])
    coarse[gh[0], gh[1]] = W


@wp.kernel(enable_backward=False)
def count_changes_kernel(
    axes: wp.array(dtype=wp.vec3),
    reference: wp.array(dtype=wp.vec3),
    offset: int,
    count: wp.array(dtype=wp.int32),
):
    """``count[0] +=`` the nodes whose free axes differ from ``reference`` (an integer sum: any order gives it)."""
    i = wp.tid() + offset
    if wp.length_sq(axes[i] - reference[i]) != 0.0:
        wp.atomic_add(count, 0, 1)


@wp.kernel(enable_backward=False)
def restrict_kernel(
    aggregate_offsets: wp.array(dtype=wp.int32),
    aggregate_nodes: wp.array(dtype=wp.int32),
    axes: wp.array(dtype=wp.vec3),
    node_mode: wp.array(dtype=wp.vec3),
    r: wp.array(dtype=wp.vec3),
    offset: int,
    rc: wp.array(dtype=wp.spatial_vector),
):
    """``rc = P^T r``: per aggregate, ``sum_i Phi_i^T S_i r_i`` over its nodes in order."""
    g = wp.tid() + offset
    s = wp.spatial_vector()
    for k in range(aggregate_offsets[g], aggregate_offsets[g + 1]):
        i = aggregate_nodes[k]
        s += mode_restrict(node_mode[i], axes[i], r[i])
    rc[g] = s


@wp.kernel(enable_backward=False)
def cholesky_kernel(
    a: wp.array2d(dtype=wp.float64),
    first: wp.array(dtype=wp.int32),
    pivot: wp.float64,
    offset: int,
    lower: wp.array2d(dtype=wp.float64),
):
    """In one thread, the lower Cholesky factor of the symmetric ``a`` (n, n) inside its envelope (row ``i``'s
    entries from column ``first[i]`` on; Cholesky-Crout keeps it: no fill outside). A pivot at most ``pivot``
    (a column dependent on the ones before, to rounding) leaves its column zero."""
    n = a.shape[0]
    for i in range(n):
        fi = first[i]
        for j in range(fi, i + 1):
            t = a[i, j]
            for k in range(wp.max(fi, first[j]), j):
                t -= lower[i, k] * lower[j, k]
            if j < i:
                if lower[j, j] != wp.float64(0.0):
                    lower[i, j] = t / lower[j, j]
                else:
                    lower[i, j] = wp.float64(0.0)
            elif t > pivot:
                lower[i, i] = wp.sqrt(t)
            else:
                lower[i, i] = wp.float64(0.0)


@wp.kernel(enable_backward=False)
def solve_coarse_kernel(
    lower: wp.array2d(dtype=float),
    first: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=float),
    rc: wp.array(dtype=wp.spatial_vector),
    offset: int,
    work: wp.array(dtype=float),
    zc: wp.array(dtype=wp.spatial_vector),
):
    """In one thread, ``zc = diag(scale) L^-T L^-1 diag(scale) rc`` by forward and back substitution inside the
    envelope of ``L`` (the unknowns of zero pivots get zero)."""
    n = lower.shape[0]
    for i in range(n):
        t = scale[i] * rc[i // 6][i % 6]
        for k in range(first[i], i):
            t -= lower[i, k] * work[k]
        d = lower[i, i]
        if d != 0.0:
            work[i] = t / d
        else:
            work[i] = 0.0
    for ii in range(n):
        i = n - 1 - ii
        d = lower[i, i]
        x = float(0.0)
        if d != 0.0:
            x = work[i] / d
        work[i] = x
        for k in range(first[i], i):
            work[k] = work[k] - lower[i, k] * x
    for g in range(zc.shape[0]):
        z = wp.spatial_vector()
        for c in range(6):
            z[c] = scale[6 * g + c] * work[6 * g + c]
        zc[g] = z


@wp.kernel(enable_backward=False)
def prolong_cg_kernel(
    node_aggregate: wp.array(dtype=wp.int32),
    node_mode: wp.array(dtype=wp.vec3),
    axes: wp.array(dtype=wp.vec3),
    r: wp.array(dtype=wp.vec3),
    zc: wp.array(dtype=wp.spatial_vector),
    scale: float,
    row: int,
    set_p: int,
    n: int,
    offset: int,
    z: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
    partials: wp.array2d(dtype=float),
):
    """``z += scale S P zc`` (the coarse correction; with ``set_p`` also ``p = z``); adds ``r . (scale S P zc)``
    of the block to partial ``row`` (which then holds the two-level ``r.z``)."""
    blk = wp.tid() + offset
    span = block_range(blk, partials.shape[1], n)
    extra = float(0.0)
    for i in range(span[0], span[1]):
        g = node_aggregate[i]
        if g >= 0:
            c = zc[g]
            t = wp.vec3(c[0], c[1], c[2])
            w = wp.vec3(c[3], c[4], c[5])
            u = scale * wp.cw_mul(axes[i], t + wp.cross(w, node_mode[i]))
            zi = z[i] + u
            z[i] = zi
            if set_p != 0:
                p[i] = zi
            extra += wp.dot(r[i], u)
    partials[row, blk] = partials[row, blk] + extra


# -- divergence check ----------------------------------------------------------------------------
#: rows of the check's partial sums
CHECK_ROWS = ("kinetic", "elastic", "gravity", "external", "constraint", "contact")


@wp.kernel(enable_backward=False)
def check_step_kernel(
    x0: wp.array(dtype=wp.vec3),
    x1: wp.array(dtype=wp.vec3),
    v1: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    external: wp.array(dtype=wp.vec3),
    node_force: wp.array(dtype=wp.vec3),
    moved: wp.array(dtype=wp.vec3),
    contact_force: wp.array(dtype=wp.vec3),
    touching: int,
    gravity: wp.vec3,
    energy: wp.array(dtype=float),
    n: int,
    tet_count: int,
    offset: int,
    bad: wp.array(dtype=wp.int32),
    partials: wp.array2d(dtype=wp.float64),
):
    """Per fixed block of nodes (and of tets): the first node whose new position or velocity is not finite
    (-1: none) and float64 partial sums (rows :data:`CHECK_ROWS`) of the kinetic energy ``m |v|^2 / 2``,
    the elastic energy, the works ``m g . dx``, ``f_ext . dx``, ``|f . moved|`` (the constraints) and
    ``|f_c . dx|`` (the tools, with ``touching``), ``dx = x1 - x0``."""
    blk = wp.tid() + offset
    span = block_range(blk, partials.shape[1], n)
    first = int(-1)
    kinetic = wp.float64(0.0)
    weight = wp.float64(0.0)
    push = wp.float64(0.0)
    constraint = wp.float64(0.0)
    contact = wp.float64(0.0)
    for i in range(span[0], span[1]):
        xi = x1[i]
        vi = v1[i]
        if first < 0 and not (wp.isfinite(xi) and wp.isfinite(vi)):
            first = i
        dx = xi - x0[i]
        m = mass[i]
        kinetic += wp.float64(0.5 * m * wp.dot(vi, vi))
        weight += wp.float64(m * wp.dot(dx, gravity))
        push += wp.float64(wp.dot(external[i], dx))
        constraint += wp.float64(wp.abs(wp.dot(node_force[i], moved[i])))
        if touching != 0:
            contact += wp.float64(wp.abs(wp.dot(contact_force[i], dx)))
    tets = block_range(blk, partials.shape[1], tet_count)
    elastic = wp.float64(0.0)
    for t in range(tets[0], tets[1]):
        elastic += wp.float64(energy[t])
    bad[blk] = first
    partials[0, blk] = kinetic
    partials[1, blk] = elastic
    partials[2, blk] = weight
    partials[3, blk] = push
    partials[4, blk] = constraint
    partials[5, blk] = contact


@wp.kernel(enable_backward=False)
def tet_aggregate_counts_kernel(tets: wp.array(dtype=wp.vec4i), alive: wp.array(dtype=wp.uint8),
                                node_aggregate: wp.array(dtype=wp.int32), offset: int,
                                squares: wp.array(dtype=wp.int32)):  # fmt: skip
    """Per tet: ``u^2``, ``u`` the distinct aggregates of its corners (0 for a dead tet or one outside)."""
    t = wp.tid() + offset
    g = _corner_groups(tets, alive, node_aggregate, t)
    u = wp.max(wp.max(g[0], g[1]), wp.max(g[2], g[3])) + 1
    squares[t] = u * u


@wp.kernel(enable_backward=False)
def tet_pair_slots_kernel(tets: wp.array(dtype=wp.vec4i), alive: wp.array(dtype=wp.uint8),
                          node_aggregate: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int64),
                          aggregates: int, offset: int, slot_code: wp.array(dtype=wp.int64)):  # fmt: skip
    """Per tet, the code ``aggregate_a * G + aggregate_b`` of each of its slots: corners ``(a, b)`` take slot
    ``start[t] + g_a u + g_b`` (none for a dead tet or one outside; :func:`couple_tets_kernel` finds
    them the same way)."""
    t = wp.tid() + offset
    g = _corner_groups(tets, alive, node_aggregate, t)
    u = wp.max(wp.max(g[0], g[1]), wp.max(g[2], g[3])) + 1
    c = tets[t]
    if u > 0:
        for a in range(4):
            for b in range(4):
                slot = int(start[t]) + g[a] * u + g[b]
                slot_code[slot] = wp.int64(node_aggregate[c[a]]) * wp.int64(aggregates) + wp.int64(node_aggregate[c[b]])
