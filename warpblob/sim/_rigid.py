"""Rigid materials: the nodes of rigid tets move as one rigid body per connected piece (reduced coordinates).

``Simulation(..., rigid={material_id, ...})`` marks materials rigid. Every
node of a live tet of a rigid material belongs to a rigid piece (a node it
shares with a soft tet too: the soft tet is then attached to the body at
that node), and the pieces are the connected sets of rigid tets (joined
through shared nodes). A piece holding a fixed node or an anchor node
(``Simulation(anchors=...)``) is *anchored*: all its nodes are held where
they are, as Dirichlet nodes (the thesis' skull). Every other piece is a
*free* rigid body with six degrees of freedom.

Coupling (monolithic, in reduced coordinates). A free body ``b`` with centre
of mass ``c`` and orientation ``Q`` moves its nodes by ``x_i = c + Q r0_i``
(``r0_i`` the body-frame offsets fixed when the piece was formed), so their
velocities are ``v_i = V + W x r_i = Phi_i q`` with ``q = (V, W)``,
``r_i = Q r0_i`` and ``Phi_i = [I, -[r_i]x]``. Substituting ``v = P q`` into
the backward-Euler system of :mod:`warpblob.sim._solver` and multiplying by
``P^T`` gives the reduced system

    [A_ss, A_sr P; P^T A_rs, P^T A_rr P] [v_s; q] = [b_s; P^T b_r],

the standard way to couple rigid and deformable bodies in one implicit
solve (reduced or "generalized" coordinates for the rigid part: Shabana,
*Dynamics of Multibody Systems*, 2005; in graphics, Jansson & Vergeest 2003,
"Combining deformable- and rigid-body mechanics simulation", and Lenoir &
Fonteneau 2004, "Mixing deformable and rigid-body mechanics simulation").
Here ``P^T A_rr P`` holds the body's mass matrix ``P^T M P`` (its lumped node
masses: total mass and inertia tensor about the centre of mass), ``P^T b_r``
its momentum plus ``h`` times gravity, the external forces and the forces of
the soft tets attached to it (force and torque), and ``A_sr P`` the implicit
stiffness of those attachments. The whole system stays symmetric positive
definite, so the rigid body and the soft tissue are integrated together,
unconditionally stable like the soft solve alone (a staggered scheme, where
the soft solve sees the body at a predicted pose and the body then takes the
reaction, is only conditionally stable: a small bone fragment on stiff
tissue blows up at ``h^2 k / m > 4``; Felippa, Park & Farhat 2001,
"Partitioned analysis of coupled mechanical systems").

The reduced system is solved by the same preconditioned CG in the full node
space, with the rigid rows filtered by the orthogonal projector
``Pi = P (P^T P)^-1 P^T`` onto the rigid velocities of each body (the
generalization of Baraff & Witkin's axis filter to a six-dimensional
subspace, as in the filtered CG of Ascher & Boxerman 2003): the operator is
``Pi A Pi`` on the rigid rows, the right-hand side ``Pi b``, and CG's
iterates stay in the subspace, which makes ``Pi A Pi v = Pi b`` exactly
``P^T A P q = P^T b``. The rigid part of the preconditioner is exact per
body, ``P (P^T D P)^-1 P^T`` with ``D`` the rows' 3 x 3 diagonal blocks
(mass, attached stiffness and tool contact), an additive Schwarz term next
to block-Jacobi on the soft nodes and the coarse space (which leaves the
rigid nodes out). Rigid tets are not assembled as elastic (their Lamé
parameters are zero): they give the body its mass and nothing else, so
nothing stiff enters the system and PCG's conditioning is that of the soft
part plus a few well-scaled 6 x 6 blocks.

After the solve the body's ``q`` is read back by the projection, ground
contact acts on it (below), and its pose advances: ``c += h V``,
``Q = exp(h [W]x) Q`` (a unit quaternion), every node is placed at
``c + Q r0_i`` (rigid to float rounding, whatever the step) and given the
velocity ``V + W x r_i``. Lagged over a step, like the element rotations:
the offsets ``r_i`` and the inertia (the gyroscopic term ``W x I W`` is
dropped; it vanishes for a body spinning about a principal axis).

Ground contact of a free body (``Simulation(ground=...)``): velocity-level
impulses with Coulomb friction, solved per body by projected Gauss-Seidel
over its nodes (Catto 2005, "Iterative dynamics with temporal coherence";
inelastic, the normal target lands each node on the plane, as for soft
nodes), after the coupled solve: the soft tissue attached to a body feels
its contact one step late (a dissipative correction, so stability is kept).
A body still below the plane after its pose update is lifted onto it.

Every per-node and per-body loop is a Warp kernel: per-body sums run one
thread per body over its node list in order (deterministic; a handful of
bodies), per-node broadcasts one thread per node, and the 6 x 6 inverses a
float64 Cholesky per body in a kernel (no host round trip, no LAPACK).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import _kernels as k

__all__ = ["RigidBodies", "PGS_ITERATIONS"]

#: projected Gauss-Seidel sweeps of a body's ground contact per step
PGS_ITERATIONS = 8
#: relative shift of the unit-diagonal 6 x 6 blocks before their Cholesky factorization, and the pivot below
#: which a column is left out
SHIFT = 1e-10
_SHIFT = wp.constant(wp.float64(SHIFT))
_PIVOT = wp.constant(wp.float64(0.5 * SHIFT))

_mat66d = wp.types.matrix(shape=(6, 6), dtype=wp.float64)


@wp.func
def _rows(r: wp.vec3, u: wp.vec3) -> wp.spatial_vector:
    """``Phi^T u = (u, r x u)`` for ``Phi = [I, -[r]x]``."""
    w = wp.cross(r, u)
    return wp.spatial_vector(u[0], u[1], u[2], w[0], w[1], w[2])


@wp.func
def _apply(r: wp.vec3, q: wp.spatial_vector) -> wp.vec3:
    """``Phi q = V + W x r``."""
    return wp.vec3(q[0], q[1], q[2]) + wp.cross(wp.vec3(q[3], q[4], q[5]), r)


@wp.func
def _sandwich(r: wp.vec3, D: wp.mat33) -> wp.spatial_matrix:
    """``Phi^T D Phi``."""
    out = wp.spatial_matrix()
    for a in range(3):
        ra = k.mode_row(r, a)
        for b in range(3):
            if D[a, b] != 0.0:
                out += D[a, b] * wp.outer(ra, k.mode_row(r, b))
    return out


@wp.kernel(enable_backward=False)
def prepare_bodies_kernel(
    offsets: wp.array(dtype=wp.int32),
    nodes: wp.array(dtype=wp.int32),
    body: wp.array(dtype=wp.vec3),
    orient: wp.array(dtype=wp.quat),
    mass: wp.array(dtype=float),
    node_block: wp.array(dtype=wp.mat33),
    contact_weight: wp.array(dtype=float),
    contact_block: wp.array(dtype=wp.mat33),
    c_mass: float,
    c_stiff: float,
    c_contact: float,
    offset: int,
    lever: wp.array(dtype=wp.vec3),
    gram: wp.array(dtype=wp.spatial_matrix),
    inertia: wp.array(dtype=wp.spatial_matrix),
    system: wp.array(dtype=wp.spatial_matrix),
):
    """Per body, over its nodes in order: the offsets ``r_i = Q r0_i``, ``P^T P``, the mass matrix
    ``P^T M P`` and the preconditioner block ``P^T D P`` (``D`` the rows' diagonal blocks)."""
    b = wp.tid() + offset
    Q = orient[b]
    G = wp.spatial_matrix()
    Mb = wp.spatial_matrix()
    H = wp.spatial_matrix()
    for s in range(offsets[b], offsets[b + 1]):
        i = nodes[s]
        r = wp.quat_rotate(Q, body[s])
        lever[s] = r
        unit = k.mode_mass(r, wp.vec3(1.0, 1.0, 1.0))
        m = mass[i]
        G += unit
        Mb += m * unit
        D = c_stiff * node_block[i]
        if c_contact != 0.0:
            if contact_weight[i] > 0.0:
                D = D + c_contact * contact_block[i]
        H += (c_mass * m) * unit + _sandwich(r, D)
    gram[b] = G
    inertia[b] = Mb
    system[b] = H


@wp.kernel(enable_backward=False)
def invert_blocks_kernel(blocks: wp.array(dtype=wp.spatial_matrix), offset: int,
                         inverse: wp.array(dtype=wp.spatial_matrix)):  # fmt: skip
    """Per body, the inverse of a symmetric positive semi-definite 6 x 6 block by a float64 Cholesky factor of
    its unit-diagonal scaling (plus :data:`SHIFT`); a zero diagonal or a dependent column is left out."""
    b = wp.tid() + offset
    A = blocks[b]
    s = wp.vector(length=6, dtype=wp.float64)
    for i in range(6):
        d = wp.float64(A[i, i])
        s[i] = wp.float64(0.0)
        if d > wp.float64(0.0):
            s[i] = wp.float64(1.0) / wp.sqrt(d)
    L = _mat66d()
    for i in range(6):
        for j in range(i + 1):
            t = s[i] * wp.float64(0.5 * (A[i, j] + A[j, i])) * s[j]
            if i == j:
                t = wp.float64(0.0)
                if s[i] > wp.float64(0.0):
                    t = wp.float64(1.0)
                t = t + _SHIFT
            for m in range(j):
                t -= L[i, m] * L[j, m]
            if j < i:
                if L[j, j] != wp.float64(0.0):
                    L[i, j] = t / L[j, j]
            elif t > _PIVOT:
                L[i, i] = wp.sqrt(t)
    out = wp.spatial_matrix()
    for c in range(6):
        y = wp.vector(length=6, dtype=wp.float64)
        for i in range(6):
            t = wp.float64(0.0)
            if i == c:
                t = s[i]
            for m in range(i):
                t -= L[i, m] * y[m]
            y[i] = wp.float64(0.0)
            if L[i, i] != wp.float64(0.0):
                y[i] = t / L[i, i]
        for ii in range(6):
            i = 5 - ii
            t = y[i]
            for m in range(i + 1, 6):
                t -= L[m, i] * y[m]
            y[i] = wp.float64(0.0)
            if L[i, i] != wp.float64(0.0):
                y[i] = t / L[i, i]
        for i in range(6):
            out[i, c] = float(s[i] * y[i])
    inverse[b] = out


@wp.kernel(enable_backward=False)
def restrict_bodies_kernel(
    offsets: wp.array(dtype=wp.int32),
    nodes: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3),
    inverse: wp.array(dtype=wp.spatial_matrix),
    u: wp.array(dtype=wp.vec3),
    offset: int,
    coef: wp.array(dtype=wp.spatial_vector),
):
    """Per body ``coef = inverse P^T u`` (with ``inverse = (P^T P)^-1``: the coordinates of ``Pi u``)."""
    b = wp.tid() + offset
    w = wp.spatial_vector()
    for s in range(offsets[b], offsets[b + 1]):
        w += _rows(lever[s], u[nodes[s]])
    coef[b] = inverse[b] * w


@wp.kernel(enable_backward=False)
def broadcast_bodies_kernel(
    nodes: wp.array(dtype=wp.int32),
    slot_body: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3),
    coef: wp.array(dtype=wp.spatial_vector),
    offset: int,
    u: wp.array(dtype=wp.vec3),
):
    """Per rigid node ``u_i = Phi_i coef_b`` (with :func:`restrict_bodies_kernel`: ``u <- Pi u``)."""
    s = wp.tid() + offset
    u[nodes[s]] = _apply(lever[s], coef[slot_body[s]])


@wp.kernel(enable_backward=False)
def precondition_bodies_kernel(
    offsets: wp.array(dtype=wp.int32),
    nodes: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3),
    inverse: wp.array(dtype=wp.spatial_matrix),
    r: wp.array(dtype=wp.vec3),
    scale: float,
    row: int,
    offset: int,
    coef: wp.array(dtype=wp.spatial_vector),
    partials: wp.array2d(dtype=float),
):
    """In one thread, every body in order: ``coef_b = scale (P^T D P)^-1 P^T r``; adds their ``r . P coef`` to
    partial ``row`` (block 0), the rigid part of CG's ``r.z``."""
    total = float(0.0)
    for b in range(coef.shape[0]):
        w = wp.spatial_vector()
        for s in range(offsets[b], offsets[b + 1]):
            w += _rows(lever[s], r[nodes[s]])
        q = scale * (inverse[b] * w)
        coef[b] = q
        total += wp.dot(q, w)
    partials[row, 0] = partials[row, 0] + total


@wp.kernel(enable_backward=False)
def prolong_bodies_kernel(
    nodes: wp.array(dtype=wp.int32),
    slot_body: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3),
    coef: wp.array(dtype=wp.spatial_vector),
    set_p: int,
    offset: int,
    z: wp.array(dtype=wp.vec3),
    p: wp.array(dtype=wp.vec3),
):
    """Per rigid node ``z_i += Phi_i coef_b`` (with ``set_p`` also ``p_i = z_i``)."""
    s = wp.tid() + offset
    i = nodes[s]
    zi = z[i] + _apply(lever[s], coef[slot_body[s]])
    z[i] = zi
    if set_p != 0:
        p[i] = zi


@wp.kernel(enable_backward=False)
def norm_blocks_kernel(r: wp.array(dtype=wp.vec3), n: int, offset: int, partials: wp.array2d(dtype=float)):
    """Partial ``r.r`` (row 2) per CG block, after the rigid rows of ``r`` were projected."""
    blk = wp.tid() + offset
    span = k.block_range(blk, partials.shape[1], n)
    rr = float(0.0)
    for i in range(span[0], span[1]):
        rr += wp.dot(r[i], r[i])
    partials[2, blk] = rr


@wp.kernel(enable_backward=False)
def ground_bodies_kernel(
    offsets: wp.array(dtype=wp.int32),
    nodes: wp.array(dtype=wp.int32),
    lever: wp.array(dtype=wp.vec3),
    mass_inverse: wp.array(dtype=wp.spatial_matrix),
    x: wp.array(dtype=wp.vec3),
    h: float,
    height: float,
    friction: float,
    iterations: int,
    offset: int,
    coef: wp.array(dtype=wp.spatial_vector),
    impulse: wp.array(dtype=wp.vec3),
):
    """Per body, ground contact by projected Gauss-Seidel over its nodes in order (sequential impulses).

    Node ``i`` at ``x_i`` with velocity ``u = V + W x r_i`` wants the normal
    velocity ``v_c = (height - z_i) / h`` (which lands it on the plane); its
    accumulated normal impulse ``l_n >= 0`` (complementarity: a node above
    the plane takes none) and its tangential impulse, clamped to the Coulomb
    disc ``|l_t| <= friction l_n``, act on the body through its inverse mass
    matrix. ``impulse`` holds ``(l_t, l_n)`` per node.
    """
    b = wp.tid() + offset
    q = coef[b]
    V = wp.vec3(q[0], q[1], q[2])
    W = wp.vec3(q[3], q[4], q[5])
    Minv = mass_inverse[b]
    im = Minv[0, 0]
    Iinv = wp.mat33(Minv[3, 3], Minv[3, 4], Minv[3, 5], Minv[4, 3], Minv[4, 4], Minv[4, 5], Minv[5, 3], Minv[5, 4],
                    Minv[5, 5])  # fmt: skip
    lo = offsets[b]
    hi = offsets[b + 1]
    touching = int(0)
    for s in range(lo, hi):
        impulse[s] = wp.vec3()
        r = lever[s]
        u = V + wp.cross(W, r)
        if x[nodes[s]][2] + h * u[2] < height:
            touching = 1
    if touching == 0:
        return
    ez = wp.vec3(0.0, 0.0, 1.0)
    ex = wp.vec3(1.0, 0.0, 0.0)
    ey = wp.vec3(0.0, 1.0, 0.0)
    for it in range(iterations):
        for s in range(lo, hi):
            r = lever[s]
            acc = impulse[s]
            u = V + wp.cross(W, r)
            vc = (height - x[nodes[s]][2]) / h
            cz = wp.cross(r, ez)
            kn = im + wp.dot(cz, Iinv * cz)
            ln = wp.max(acc[2] + (vc - u[2]) / kn, 0.0)
            dn = ln - acc[2]
            V = V + (im * dn) * ez
            W = W + Iinv * (dn * cz)
            lt = wp.vec2(acc[0], acc[1])
            if ln > 0.0 or acc[0] != 0.0 or acc[1] != 0.0:
                u = V + wp.cross(W, r)
                cx = wp.cross(r, ex)
                cy = wp.cross(r, ey)
                lx = acc[0] - u[0] / (im + wp.dot(cx, Iinv * cx))
                ly = acc[1] - u[1] / (im + wp.dot(cy, Iinv * cy))
                lt = wp.vec2(lx, ly)
                cap = friction * ln
                size = wp.length(lt)
                if size > cap:
                    lt = lt * (cap / size)
                J = wp.vec3(lt[0] - acc[0], lt[1] - acc[1], 0.0)
                V = V + im * J
                W = W + Iinv * wp.cross(r, J)
            impulse[s] = wp.vec3(lt[0], lt[1], ln)
    coef[b] = wp.spatial_vector(V[0], V[1], V[2], W[0], W[1], W[2])


@wp.kernel(enable_backward=False)
def pose_bodies_kernel(
    offsets: wp.array(dtype=wp.int32),
    body: wp.array(dtype=wp.vec3),
    coef: wp.array(dtype=wp.spatial_vector),
    h: float,
    ground: int,
    height: float,
    offset: int,
    centre: wp.array(dtype=wp.vec3),
    orient: wp.array(dtype=wp.quat),
):
    """Per body ``c += h V``, ``Q = exp(h [W]x) Q``; with a ground, lifted onto it if a node is below."""
    b = wp.tid() + offset
    q = coef[b]
    W = wp.vec3(q[3], q[4], q[5])
    c = centre[b] + h * wp.vec3(q[0], q[1], q[2])
    Q = orient[b]
    angle = h * wp.length(W)
    if angle > 0.0:
        Q = wp.normalize(wp.quat_from_axis_angle(wp.normalize(W), angle) * Q)
    if ground != 0:
        low = float(1e30)
        for s in range(offsets[b], offsets[b + 1]):
            low = wp.min(low, c[2] + wp.quat_rotate(Q, body[s])[2])
        if low < height:
            c = c + wp.vec3(0.0, 0.0, height - low)
    centre[b] = c
    orient[b] = Q


@wp.kernel(enable_backward=False)
def place_bodies_kernel(
    nodes: wp.array(dtype=wp.int32),
    slot_body: wp.array(dtype=wp.int32),
    body: wp.array(dtype=wp.vec3),
    centre: wp.array(dtype=wp.vec3),
    orient: wp.array(dtype=wp.quat),
    coef: wp.array(dtype=wp.spatial_vector),
    offset: int,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    moved: wp.array(dtype=wp.vec3),
):
    """Per rigid node ``x_i = c + Q r0_i``, ``v_i = V + W x (x_i - c)``."""
    s = wp.tid() + offset
    b = slot_body[s]
    i = nodes[s]
    r = wp.quat_rotate(orient[b], body[s])
    x[i] = centre[b] + r
    v[i] = _apply(r, coef[b])
    moved[i] = wp.vec3()


class RigidBodies:
    """The free rigid bodies of a simulation: node lists, poses and the per-step 6 x 6 blocks (Warp arrays).

    Built by :class:`~warpblob.sim.Simulation` whenever the rigid pieces may
    have changed (set-up, :attr:`~warpblob.sim.Simulation.rigid`, fixed
    nodes, anchors, a rebuild, a new state). The body frame is the centre of
    mass of its nodes' lumped masses, with ``Q = 1`` at that moment; the
    nodes' velocities are replaced by the rigid velocity of the same linear
    and angular momentum.

    Args:
        pieces: list of (n_b,) int node index arrays, one per free body.
        positions, velocities: (N, 3) current node state.
        mass: (N,) lumped node masses.
        device: Warp device.

    Attributes:
        count: F bodies; ``node_count``: R nodes in them. ``centre`` (F,) vec3,
        ``orient`` (F,) quat, ``coef`` (F,) spatial_vector (the last ``(V, W)``),
        ``nodes`` (R,) int32 node of each slot, ``slot_body`` (R,) its body,
        ``offsets`` (F + 1,), ``body`` (R,) the offsets ``r0``, ``lever`` (R,)
        ``Q r0`` of the last :meth:`prepare`.
    """

    def __init__(self, pieces, positions, velocities, mass, device):
        self.device = dev = device
        F = len(pieces)
        self.count = F
        nodes = np.concatenate([np.asarray(p, dtype=np.int64) for p in pieces]) if F else np.zeros(0, np.int64)
        self.node_count = len(nodes)
        offsets = np.zeros(F + 1, dtype=np.int32)
        offsets[1:] = np.cumsum([len(p) for p in pieces])
        slot_body = np.repeat(np.arange(F, dtype=np.int32), np.diff(offsets))
        x = np.asarray(positions, dtype=np.float64)[nodes]
        v = np.asarray(velocities, dtype=np.float64)[nodes]
        m = np.asarray(mass, dtype=np.float64)[nodes]
        total = np.add.reduceat(m, offsets[:-1]) if F else np.zeros(0)
        centre = np.add.reduceat(m[:, None] * x, offsets[:-1]) / total[:, None] if F else np.zeros((0, 3))
        r = x - centre[slot_body]
        # the rigid velocity with the nodes' linear and angular momentum about the centre of mass
        coef = np.zeros((F, 6))
        for b in range(F):  # a handful of bodies: 6 x 6 host solves at set-up
            sl = slice(offsets[b], offsets[b + 1])
            rb, mb, vb = r[sl], m[sl], v[sl]
            inertia = (mb[:, None, None] * ((rb**2).sum(axis=1)[:, None, None] * np.eye(3)
                                            - rb[:, :, None] * rb[:, None, :])).sum(axis=0)  # fmt: skip
            momentum = (mb[:, None] * vb).sum(axis=0)
            angular = (mb[:, None] * np.cross(rb, vb)).sum(axis=0)
            coef[b, :3] = momentum / total[b]
            coef[b, 3:] = np.linalg.lstsq(inertia, angular, rcond=1e-12)[0]
        self.rigid_velocities = coef[slot_body, :3] + np.cross(coef[slot_body, 3:], r)

        def array(a, dtype):
            return wp.array(a, dtype=dtype, device=dev)

        self.nodes_host = nodes.astype(np.int32)
        self.offsets = array(offsets, wp.int32)
        self.nodes = array(self.nodes_host, wp.int32)
        self.slot_body = array(slot_body, wp.int32)
        self.body = array(r.astype(np.float32), wp.vec3)
        self.lever = wp.clone(self.body)
        self.centre = array(centre.astype(np.float32), wp.vec3)
        self.orient = array(np.tile(np.array([0.0, 0.0, 0.0, 1.0], np.float32), (F, 1)), wp.quat)
        self.coef = array(coef.astype(np.float32), wp.spatial_vector)
        self.work = wp.zeros(F, dtype=wp.spatial_vector, device=dev)
        self.impulse = wp.zeros(self.node_count, dtype=wp.vec3, device=dev)
        names = ("gram", "inertia", "system")
        self._blocks = {name: wp.zeros(F, dtype=wp.spatial_matrix, device=dev) for name in names}
        self.inverse = {name: wp.zeros(F, dtype=wp.spatial_matrix, device=dev) for name in self._blocks}

    def save(self) -> None:
        """Keep the poses and velocities (a step that fails puts them back with :meth:`restore`)."""
        self._saved = [wp.clone(a) for a in (self.centre, self.orient, self.coef)]

    def restore(self) -> None:
        """The poses and velocities of the last :meth:`save`."""
        for a, b in zip((self.centre, self.orient, self.coef), self._saved):
            wp.copy(a, b)

    # -- per step --------------------------------------------------------------------------------------------

    def prepare(self, mass, node_block, contact_weight, contact_block, c_mass: float, c_stiff: float,
                c_contact: float) -> None:  # fmt: skip
        """Offsets at the current orientation, ``(P^T P)^-1``, ``(P^T M P)^-1`` and ``(P^T D P)^-1`` per body."""
        dev, F = self.device, self.count
        B = self._blocks
        wp.launch(prepare_bodies_kernel, F,
                  inputs=[self.offsets, self.nodes, self.body, self.orient, mass, node_block, contact_weight,
                          contact_block, float(c_mass), float(c_stiff), float(c_contact), 0,
                          self.lever, B["gram"], B["inertia"], B["system"]], device=dev)  # fmt: skip
        for name, blocks in B.items():
            wp.launch(invert_blocks_kernel, F, inputs=[blocks, 0, self.inverse[name]], device=dev)

    def project_launches(self, u: wp.array) -> list:
        """Recorded launches of ``u <- Pi u`` on the rigid rows (restriction, then broadcast)."""
        dev = self.device
        return [
            wp.launch(restrict_bodies_kernel, self.count,
                      inputs=[self.offsets, self.nodes, self.lever, self.inverse["gram"], u, 0, self.work],
                      device=dev, record_cmd=True),
            wp.launch(broadcast_bodies_kernel, self.node_count,
                      inputs=[self.nodes, self.slot_body, self.lever, self.work, 0, u], device=dev, record_cmd=True),
        ]  # fmt: skip

    def precondition_launches(self, r, z, p, partials, *, row: int, set_p: int = 0, scale: float = 1.0) -> list:
        """Recorded launches of ``z += scale P (P^T D P)^-1 P^T r`` (its ``r.z`` added to partial ``row``)."""
        dev = self.device
        return [
            wp.launch(precondition_bodies_kernel, 1,
                      inputs=[self.offsets, self.nodes, self.lever, self.inverse["system"], r, float(scale), int(row),
                              0, self.work, partials], device=dev, record_cmd=True),
            wp.launch(prolong_bodies_kernel, self.node_count,
                      inputs=[self.nodes, self.slot_body, self.lever, self.work, int(set_p), 0, z, p], device=dev,
                      record_cmd=True),
        ]  # fmt: skip

    def project(self, u: wp.array) -> None:
        """``u <- Pi u`` on the rigid rows, now."""
        for item in self.project_launches(u):
            item.launch()

    def advance(self, x0: wp.array, x1: wp.array, v1: wp.array, moved: wp.array, h: float, ground=None) -> None:
        """After the solve: read each body's ``(V, W)`` from ``v1`` (the projection), apply ground contact
        (``ground = (height, friction)``), advance the poses and place the nodes in ``x1`` / ``v1``."""
        dev, F, R = self.device, self.count, self.node_count
        wp.launch(restrict_bodies_kernel, F,
                  inputs=[self.offsets, self.nodes, self.lever, self.inverse["gram"], v1, 0, self.coef],
                  device=dev)  # fmt: skip
        height, friction = ground if ground is not None else (0.0, 0.0)
        if ground is not None:
            wp.launch(ground_bodies_kernel, F,
                      inputs=[self.offsets, self.nodes, self.lever, self.inverse["inertia"], x0, float(h),
                              float(height), float(friction), PGS_ITERATIONS, 0, self.coef, self.impulse],
                      device=dev)  # fmt: skip
        wp.launch(pose_bodies_kernel, F,
                  inputs=[self.offsets, self.body, self.coef, float(h), int(ground is not None), float(height), 0,
                          self.centre, self.orient], device=dev)  # fmt: skip
        wp.launch(place_bodies_kernel, R,
                  inputs=[self.nodes, self.slot_body, self.body, self.centre, self.orient, self.coef, 0, x1, v1,
                          moved], device=dev)  # fmt: skip

    def state(self) -> dict:
        """Host copies: ``centre`` (F, 3), ``orientation`` (F, 4) quaternions (x, y, z, w), ``velocity`` and
        ``angular_velocity`` (F, 3), ``nodes`` (list of node index arrays)."""
        off = self.offsets.numpy()
        coef = self.coef.numpy()
        return {
            "centre": self.centre.numpy().copy(),
            "orientation": self.orient.numpy().copy(),
            "velocity": coef[:, :3].copy(),
            "angular_velocity": coef[:, 3:].copy(),
            "nodes": [self.nodes_host[off[b] : off[b + 1]].copy() for b in range(self.count)],
        }
