"""Backward Euler with a matrix-free, two-level (or block-Jacobi) preconditioned conjugate-gradient solve.

One step from ``(x, v)`` with ``h = dt`` (Müller & Gross 2004, section 4;
Baraff & Witkin 1998 for the velocity form): with the rotations ``R`` of the
tets at ``x`` held fixed for the step, the elastic force
``f(y) = -R K (R^T y - X)`` is linear in ``y``, so backward Euler

    M (v' - v) = h (f(x + h v') + M g + f_ext - C v'),   C = alpha M + beta K',

becomes the linear system

    ((1 + h alpha) M + (h beta + h^2) K') v' = M v + h (f(x) + M g + f_ext),

symmetric positive definite (``K' = R K R^T`` is positive semi-definite,
``M`` lumped and positive). Kept: the full linear-elastic ``K`` of each tet,
rotated by that tet's own ``R``, and the force's rest-shape term ``R K X``.
Lagged: ``R`` itself, computed once per step at ``x``. Dropped: the
derivative of ``R`` with respect to the positions (the stiffness-rotation
terms), which Müller & Gross also drop; it multiplies the stress, so near
any rigid motion ``K'`` is the exact stiffness.

Dirichlet nodes enter by the projection filter of Baraff & Witkin: with
``S`` zeroing fixed rows, CG solves ``(S A S + I - S) v' = S (b - A v_p) + v_p``,
whose fixed entries stay at their prescribed velocities ``v_p``.

Free rigid bodies (:mod:`warpblob.sim._rigid`) generalize the filter: their
rows are projected onto each body's six rigid velocities (``Pi A Pi`` and
``Pi b`` instead of ``S A S`` and ``S b``, one projection of ``A p`` per CG
iteration), which solves the reduced system ``P^T A P q = P^T b`` in the
same CG, and they are preconditioned by one exact 6 x 6 block per body in
place of block-Jacobi and the coarse space.

Tool contact (:mod:`warpblob.sim._contact`) adds its force to ``f_ext`` and
``h^2`` times its block-diagonal penalty stiffness ``K_c`` to the system: the
contact force at the end of the step is linearized as ``f_c - K_c h v'``, so
stiff contact is as stable as the elastic forces.

The solver is preconditioned CG (Saad 2003, algorithm 9.1) warm-started from
``v``, with a tolerance relative to the right-hand side and an iteration
cap, in four fused kernels per iteration: the per-tet product ``K' p``, then
three per-node passes that also form the dot products (partial sums per
fixed node block, summed in block order). The preconditioner is the
block-Jacobi inverse ``D^-1`` of the filtered system's 3 x 3 node blocks
(contact included), by default plus the additive coarse correction
``P Ac^-1 P^T`` of :mod:`warpblob.sim._coarse` (aggregates carrying their
rigid modes, Vanek, Mandel & Brezina 1996), which reaches the low-frequency
bending that Jacobi cannot: on a stiff beam it cuts the iterations about
tenfold. It costs three small launches per iteration (restriction, the coarse
solve by the triangular solves of its Cholesky factor, prolongation, which
adds its share of ``r.z`` to the partial sums) and a lagged rebuild of the coarse matrix (:mod:`warpblob.sim._coarse`
says when). ``linear_solver="warp"`` runs
``warp.optim.linear.cg`` instead, on a ``LinearOperator`` wrapping the same
product and a second one wrapping the same preconditioner (either kind), with
the same tolerance rule (and the same residual check: every iteration on
the CPU); it exists to compare, and takes the same iterations to the same
step. It does the same algebra, but per iteration it launches seven kernels
(resolving the generic ones' overloads each time) and forms its two dot
products with tile reductions, which on the CPU device run block by block;
here the launches are recorded once and replayed and the dot products are
fused into the node passes. Measured with Warp 1.19 on the CPU (10K-tet
tumor, one thread, per CG iteration, block-Jacobi): 0.23 ms here against
12.3 ms for ``warp.optim.linear.cg``, of which its dot products take about
11 ms; the two-level correction adds about 0.03 ms.
"""

from __future__ import annotations

import threading

import numpy as np
import warp as wp

from .._parallel import launch, submit, thread_count
from .._stages import device_array, room, set_rows
from . import _kernels as k
from ._coarse import COARSE_EVERY, CoarseSpace
from ._rigid import norm_blocks_kernel

__all__ = ["ElementState", "ImplicitSolver", "Prepared", "split_launch"]

#: items below which a launch is not worth splitting over threads: heavy per-tet kernels, light per-node ones
TET_GRAIN = 2048
NODE_GRAIN = 8192
#: the solver's per-node buffers that a step writes at every node before reading them (the assembly: the
#: right-hand side, the filter, the prescribed velocities and the block inverses; CG: its vectors) and that
#: nothing reads between steps, and ``ones``, which nothing writes: a rebuild keeps their old rows
_WRITTEN = frozenset({"rhs", "prescribed", "axes", "coarse_axes", "ones", "inverse_block", "r", "z", "p", "Ap"})

#: nodes per CG block (the unit of the deterministic partial sums); at most MAX_BLOCKS blocks on the CPU
BLOCK_NODES = 64
MAX_BLOCKS = 64


def block_count(n: int, device) -> int:
    """Blocks of the deterministic partial sums over ``n`` items: ``BLOCK_NODES`` each, at most ``MAX_BLOCKS``
    on the CPU (a count that depends on ``n`` only, never on the threads)."""
    blocks = max(1, -(-n // BLOCK_NODES))
    return blocks if device.is_cuda else min(blocks, MAX_BLOCKS)


def split_launch(kernel, dim: int, before: list, after: list, device, threads, grain: int) -> None:
    """:func:`~warpblob._parallel.launch` cut into one piece per thread (each at least ``grain`` items).

    The kernels of a step cost the same per item, so one contiguous piece
    per thread balances them and keeps the launch count (Python overhead,
    tens of microseconds each) at the thread count.
    """
    n = threads if threads is not None else thread_count()
    launch(kernel, dim, before, after, device, threads, min_chunk=max(grain, dim // max(n, 1)))


class Prepared:
    """A kernel over ``[0, dim)`` recorded once as one launch per piece, replayed by calling the object.

    The pieces are contiguous, one per thread (each at least ``grain`` items)
    as in :func:`split_launch`; replaying skips the argument packing and
    overload lookup of ``wp.launch``. :meth:`set` changes an argument (named
    as in the kernel's signature) in every piece; :meth:`rebind` gives the
    recorded launches new sizes and arguments (a rebuild's: cheaper than
    recording them anew).
    """

    def __init__(self, kernel, dim: int, before: list, after: list, device, threads, grain: int):
        self.kernel = kernel
        self._index = {arg.label: i for i, arg in enumerate(kernel.adj.args)}
        self._launches, self._args = [], []
        bounds = self._bounds(dim, device, threads, grain)
        for b0, b1 in zip(bounds[:-1], bounds[1:]):
            args = [*before, b0, *after]
            self._launches.append(wp.launch(kernel, dim=b1 - b0, inputs=args, device=device, record_cmd=True))
            self._args.append(args)

    @staticmethod
    def _bounds(dim: int, device, threads, grain: int) -> list:
        """The pieces' bounds ``[0, ..., dim]``: one piece per thread, each at least ``grain`` items (none where
        ``dim`` is 0)."""
        n = threads if threads is not None else thread_count()
        pieces = 1 if device.is_cuda or n <= 1 or dim < 2 * grain else min(n, dim // grain)
        return [dim * i // pieces for i in range(pieces + 1)] if dim > 0 else [0]

    @classmethod
    def reuse(cls, old: Prepared | None, kernel, dim: int, before: list, after: list, device, threads,
              grain: int) -> Prepared:  # fmt: skip
        """``old`` rebound to the new sizes and arguments (:meth:`rebind`) where it can be, else a new one."""
        if old is not None and old.rebind(kernel, dim, before, after, device, threads, grain):
            return old
        return cls(kernel, dim, before, after, device, threads, grain)

    def rebind(self, kernel, dim: int, before: list, after: list, device, threads, grain: int) -> bool:
        """Give the recorded launches ``dim`` items and the arguments ``before`` and ``after`` (only those that
        are not the objects recorded are packed again). False, nothing changed, where that needs another
        kernel, device or number of pieces."""
        bounds = self._bounds(dim, device, threads, grain)
        if (kernel is not self.kernel or len(bounds) - 1 != len(self._launches) or not self._launches
                or self._launches[0].device != device):  # fmt: skip
            return False
        for item, args, b0, b1 in zip(self._launches, self._args, bounds[:-1], bounds[1:]):
            for i, value in enumerate((*before, b0, *after)):
                if value is not args[i]:
                    item.set_param_at_index(i, value)
                    args[i] = value
            item.set_dim(b1 - b0)
        return True

    def set(self, name: str, value) -> None:
        index = self._index[name]
        for item, args in zip(self._launches, self._args):
            item.set_param_at_index(index, value)
            args[index] = value

    def __call__(self) -> None:
        if not self._launches:
            return
        first, *rest = self._launches
        if not rest:
            first.launch()
            return
        queue = iter(rest)
        lock = threading.Lock()

        def work():
            while True:
                with lock:
                    item = next(queue, None)
                if item is None:
                    return
                item.launch()

        # the calling thread runs the first piece while the pool runs the others
        futures = submit(work, len(rest))
        first.launch()
        for f in futures:
            f.result()


class ElementState:
    """The element pass at one set of positions: per-tet rotations, energies and volumes; per-node forces.

    Attributes (Warp arrays): ``rotated`` (T,) mat33 rotated gradients ``Dm^-1 R^T``, ``energy`` (T,)
    elastic energy, ``volume`` (T,) current signed volume, ``node_force``
    (N,) vec3 elastic force, ``node_block`` (N,) mat33 diagonal block of
    ``K'``; per corner (4 T,): ``corner_force`` and ``corner_block``.
    """

    def __init__(self, T: int, N: int, device, reuse: ElementState | None = None):
        """``reuse``: the state this one replaces (a rebuild's): its buffers are kept where they have room,
        their first entries in place (:meth:`compute`'s ``carry`` of that state then copies nothing)."""
        # not zeroed (35 MB at 100K tets): each :meth:`compute` writes every entry (every tet, dead ones
        # included, and every node), and a state is read only after a compute
        base = {} if reuse is None else reuse._base
        self._base = {}
        for name, n, dtype in (("rotated", T, wp.mat33), ("energy", T, float), ("volume", T, float),
                               ("corner_force", 4 * T, wp.vec3), ("corner_block", 4 * T, wp.vec4),
                               ("node_force", N, wp.vec3), ("node_block", N, wp.mat33)):  # fmt: skip
            self._base[name], view = room(base.get(name), n, dtype, device)
            setattr(self, name, view)
        self._every = wp.zeros(0, dtype=wp.int32, device=device)  # (no list: every tet)

    def compute(self, elements, x: wp.array, threads=None, *, carry=None) -> None:
        """Rotations, energies, volumes and node forces of ``elements`` at positions ``x``.

        ``carry``: ``(state, count, ids)`` or ``(state, count, ids, nodes)``, an earlier state at the same
        positions of the first ``count`` tets, of which only ``ids`` (int, any order) have changed since:
        the others' values are copied from it (the same values: the pass is per tet) and only ``ids`` and
        the tets past ``count`` recomputed (a topology change's rebuild, O(changed) instead of O(T)); the
        node forces are gathered anew at ``nodes`` (int, the nodes whose incidence changed, every new node
        among them: :attr:`Elements.touched_nodes`), the others' copied, or at every node without them.
        """
        e, dev = elements, elements.device
        out = [self.rotated, self.corner_force, self.corner_block, self.energy, self.volume]
        inputs = [x, e.tets, e.dm_inv, e.volume, e.mu, e.lam]
        if carry is None:
            split_launch(k.rotate_elements_kernel, e.tet_count, [self._every, *inputs], out, dev, threads, TET_GRAIN)
        else:
            old, count, ids, *nodes = carry
            count = min(int(count), e.tet_count)
            for a, b, per in zip(out, (old.rotated, old.corner_force, old.corner_block, old.energy, old.volume),
                                 (1, 4, 4, 1, 1)):  # fmt: skip
                if a.ptr != b.ptr:  # (a state rebuilt in its old buffers has them in place)
                    wp.copy(a, b, count=per * count)
            ids = np.asarray(ids, dtype=np.int64).ravel()
            # (the old tets listed, ascending, then every new one: np.union1d's result without its sort of both)
            ids = np.concatenate([np.unique(ids[(ids >= 0) & (ids < count)]), np.arange(count, e.tet_count)])
            ids = ids.astype(np.int32)
            if ids.size:
                split_launch(k.rotate_elements_kernel, len(ids), [device_array(ids, wp.int32, dev),
                             *inputs], out, dev, threads, TET_GRAIN)  # fmt: skip
        gather = [e.node_range, e.node_corners, self.corner_force, self.corner_block]
        nodes = nodes[0] if carry is not None and nodes and nodes[0] is not None else None
        if nodes is None:
            split_launch(k.gather_elements_kernel, e.node_count, [self._every, *gather],
                         [self.node_force, self.node_block], dev, threads, NODE_GRAIN)  # fmt: skip
            return
        kept = min(old.node_force.shape[0], e.node_count)
        for a, b in ((self.node_force, old.node_force), (self.node_block, old.node_block)):
            if a.ptr != b.ptr:
                wp.copy(a, b, count=kept)
        nodes = np.asarray(nodes, dtype=np.int32)
        if nodes.size:
            split_launch(k.gather_elements_kernel, len(nodes), [device_array(nodes, wp.int32, dev),
                         *gather], [self.node_force, self.node_block], dev, threads, NODE_GRAIN)  # fmt: skip


#: the linear solvers of ``Simulation(linear_solver=...)`` and the preconditioners of ``preconditioner=``
LINEAR_SOLVERS = ("pcg", "warp")
PRECONDITIONERS = ("two_level", "block_jacobi")


class ImplicitSolver:
    """The filtered linear system of a step and its preconditioned CG, with buffers and launches reused across steps.

    Args:
        elements: the :class:`~warpblob.sim._elements.Elements`.
        flags: (N,) uint8 node flags (:data:`~warpblob.sim._kernels.FREE`, ``FIXED``, ``INACTIVE``).
        states: the two :class:`ElementState` buffers whose rotations the products use.
        threads: CPU threads (None: the default).
        linear_solver: ``"pcg"`` (the fused kernels here) or ``"warp"`` (``warp.optim.linear.cg``).
        preconditioner: ``"two_level"`` (block-Jacobi plus the coarse correction of
            :mod:`warpblob.sim._coarse`) or ``"block_jacobi"``; both linear solvers use it.
        pieces: the number of pieces the live tets are known to form, or None (:class:`CoarseSpace`).
        previous: the solver this one replaces after a topology change (None: the first): its per-node and
            per-corner buffers are kept where they have room, and its recorded launches rebound; of the
            per-node ones, those a step writes before reading (``_WRITTEN``) keep their old rows, the
            contact arrays theirs while they are zero (``contact_zero``), and the rest are cleared.
        sources: with ``previous``, carry its coarse space over an edit that only killed and appended tets
            and appended nodes made from the old nodes ``sources`` ((K,) ints; :meth:`CoarseSpace.follow`)
            instead of building a new one (which it falls back to where follow declines).

    Attributes (Warp arrays the contact pass writes, zero without contact):
        ``contact_force`` (N,) vec3 node forces, ``contact_weight`` (N,) the
        stiffness each node takes (> 0 marks a node in contact),
        ``contact_block`` (N,) mat33 the penalty stiffness blocks ``K_c``; ``coarse``: the
        :class:`~warpblob.sim._coarse.CoarseSpace` (None for block-Jacobi).
    """

    def __init__(self, elements, flags: wp.array, states, threads=None, linear_solver: str = "pcg",
                 preconditioner: str = "two_level", pieces: int | None = None, previous=None,
                 sources: np.ndarray | None = None):  # fmt: skip
        self.elements = elements
        self.flags = flags
        self.threads = threads
        self.linear_solver = linear_solver
        self.preconditioner = preconditioner
        e, dev = elements, elements.device
        T, N = e.tet_count, e.node_count
        # per-node buffers in the previous solver's kept bases where they have room (fresh pages cost more
        # than the writes), set as new ones would be: zero, ``ones`` one. Those that every step's assembly
        # (and the CG it starts) writes at every node before anything reads them keep the previous solver's
        # rows as they are (only the added rows are set: a rebuild after a cut would otherwise clear every
        # node's rows of 13 buffers, 5 MB at 100K tets); the contact arrays keep theirs while they are zero
        # (no contact pass wrote them since they were cleared: ``contact_zero``), else are zeroed whole
        previous_bases, self._bases = getattr(previous, "_bases", {}), {}
        keep_contact = getattr(previous, "contact_zero", False)
        for name, dtype in (("contact_force", wp.vec3), ("contact_weight", float), ("contact_block", wp.mat33),
                            ("rhs", wp.vec3), ("prescribed", wp.vec3), ("axes", wp.vec3),
                            ("coarse_axes", wp.vec3), ("ones", wp.vec3), ("inverse_block", wp.mat33),
                            ("r", wp.vec3), ("z", wp.vec3), ("p", wp.vec3), ("Ap", wp.vec3)):  # fmt: skip
            base = previous_bases.get(name)
            self._bases[name], view = room(base, N, dtype, dev)
            keep = name in _WRITTEN or (keep_contact and name.startswith("contact_"))
            kept = getattr(previous, name).shape[0] if self._bases[name] is base and keep else 0
            set_rows(view, kept, 1.0 if name == "ones" else 0.0)
            setattr(self, name, view)
        #: whether the contact arrays are all zero (the contact pass sets it when it writes or clears them)
        self.contact_zero = True
        # (``coarse_axes``: the coarse space's filter, ``axes`` with the rigid bodies' nodes left out: they
        # have their own block)
        # (not zeroed: every product writes all of it before a node's row reads its live corners)
        self._bases["corners"], self.corner_out = room(previous_bases.get("corners"), 4 * T, wp.vec3, dev)
        blocks = block_count(N, dev)
        kept = getattr(previous, "partials", None)
        if kept is not None and kept.shape == (5, blocks) and kept.device == dev:
            self.partials = kept
            self.partials.zero_()
        else:
            self.partials = wp.zeros((5, blocks), dtype=float, device=dev)
        th, P = threads, self.partials
        # the recorded launches: the previous solver's rebound to the new sizes and arrays where they can be
        recorded, self._prepared = getattr(previous, "_prepared", {}), {}

        def prepare(key, kernel, dim, before, after, grain):
            self._prepared[key] = Prepared.reuse(recorded.get(key), kernel, dim, before, after, dev, th, grain)
            return self._prepared[key]

        # the recorded launches take the solver's own buffers whole, with their room (every kernel of them
        # reads and writes the first N nodes or 4 T corners only, by its sizes): the same objects over the
        # rebuilds that keep the bases, so a rebind packs only the element arrays and the sizes again
        w = self._bases
        elem = [e.tets, e.volume, e.mu, e.lam]
        rows = [e.node_range, e.node_corners, w["corners"], e.mass, w["axes"]]
        # per state (its rotations) the tet products of the solution guess (x, set per solve) and of p
        self._multiply = {
            id(s): {
                name: prepare(("multiply", i, name), k.multiply_elements_kernel, T,
                              [w["p"], *elem, s.rotated, w["axes"]], [w["corners"]], TET_GRAIN)  # fmt: skip
                for name in ("x", "p")
            }
            for i, s in enumerate(states)
        }
        # a block kernel is split over threads from NODE_GRAIN nodes a piece, like the per-node kernels
        grain = max(1, blocks * NODE_GRAIN // max(N, 1))
        contact = [w["contact_weight"], w["contact_block"], 0.0]
        self._start = prepare("start", k.start_cg_kernel, blocks,
                              [*rows, w["inverse_block"], w["rhs"], w["p"], 1.0, 0.0, *contact, N],
                              [w["r"], w["z"], w["p"], P], grain)  # fmt: skip
        self._product = prepare("product", k.product_cg_kernel, blocks, [*rows, w["p"], 1.0, 0.0, *contact, N],
                                [w["Ap"], P], grain)  # fmt: skip
        self._update = [prepare(("update", parity), k.update_cg_kernel, blocks,
                                [w["inverse_block"], w["p"], w["Ap"], parity, N], [w["p"], w["r"], w["z"], P], grain)
                        for parity in (0, 1)]  # fmt: skip
        self._direction = [prepare(("direction", parity), k.direction_cg_kernel, blocks, [w["z"], parity, N],
                                   [w["p"], P], grain) for parity in (0, 1)]  # fmt: skip
        self._coefficients = None
        self._grain = grain
        self.coarse = None
        if preconditioner == "two_level":
            if sources is not None and getattr(previous, "coarse", None) is not None:
                self.coarse = previous.coarse.follow(e, self.coarse_axes, sources, pieces)
            if self.coarse is None:
                self.coarse = CoarseSpace(e, self.coarse_axes, th, pieces)
        self.rigid = None
        self._coarse_key, self._coarse_age = None, 0
        # a followed space keeps the factor it was refreshed with, and the refresh its schedule: a cut's rebuild
        # does not make the next step refresh it (at 100K tets a refresh is about the cost of a step)
        if (self.coarse is not None and self.coarse.followed and self.coarse.modes_kept
                and getattr(previous, "_coarse_key", None) is not None):  # fmt: skip
            self.coarse.carry_modes()
            self._coarse_key, self._coarse_age = previous._coarse_key, previous._coarse_age
        if self.coarse is not None:
            # the start's correction also sets p = z; an iteration's adds its r.z to the new row
            self._start_coarse = [prepare(("start_coarse", i), *a) for i, a in
                                  enumerate(self._correction(w["r"], w["z"], row=0, set_p=1, wide=True))]  # fmt: skip
            self._update_coarse = [[prepare(("update_coarse", parity, i), *a) for i, a in
                                    enumerate(self._correction(w["r"], w["z"], row=1 - parity, wide=True))]
                                   for parity in (0, 1)]  # fmt: skip

    def _correction(self, r: wp.array, z: wp.array, *, row: int, set_p: int = 0, scale: float = 1.0,
                    wide: bool = False) -> list:  # fmt: skip
        """The launches ``(kernel, dim, before, after, grain)`` of ``z += scale S P Ac^-1 P^T S r`` in order:
        restriction, the coarse solve (one thread: the triangular solves are sequential), prolongation (which
        adds its part of ``r.z`` to partial ``row`` per CG block and, with ``set_p``, sets ``p = z``);
        ``wide``: with the solver's buffers whole (the recorded launches')."""
        c, N = self.coarse, self.elements.node_count
        axes, p, mode = ((self._bases["coarse_axes"], self._bases["p"], c._bases["node_mode"]) if wide
                         else (self.coarse_axes, self.p, c.node_mode))  # fmt: skip
        return [
            (k.restrict_kernel, c.aggregate_count,
             [c.aggregate_offsets, c.aggregate_nodes, axes, mode, r], [c.rc], 1 << 30),
            (k.solve_coarse_kernel, 1, [c.lower, c.first, c.scale, c.rc], [c.work, c.zc], 1),
            (k.prolong_cg_kernel, self.partials.shape[1],
             [c.node_aggregate, mode, axes, r, c.zc, float(scale), int(row), int(set_p), N],
             [z, p, self.partials], self._grain),
        ]  # fmt: skip

    def set_rigid(self, bodies) -> None:
        """Solve with the free rigid bodies ``bodies`` (a :class:`~warpblob.sim._rigid.RigidBodies`, or None):
        their rows filtered by the projector onto rigid velocities and preconditioned per body
        (:mod:`warpblob.sim._rigid`); their nodes must carry the ``RIGID`` flag."""
        self.rigid = bodies if bodies is not None and bodies.count else None
        if self.rigid is None:
            return
        b, P = self.rigid, self.partials
        self._rigid_ap = b.project_launches(self.Ap)
        self._rigid_start = [*b.project_launches(self.r),
                             wp.launch(norm_blocks_kernel, P.shape[1], inputs=[self.r, self.elements.node_count, 0, P],
                                       device=self.elements.device, record_cmd=True),
                             *b.precondition_launches(self.r, self.z, self.p, P, row=0, set_p=1)]  # fmt: skip
        self._rigid_update = [b.precondition_launches(self.r, self.z, self.p, P, row=1 - parity) for parity in (0, 1)]

    def invalidate(self) -> None:
        """Rebuild the coarse matrix at the next :meth:`assemble` (the fixed nodes or the state changed)."""
        self._coarse_key = None

    def precondition(self, r: wp.array, z: wp.array, alpha: float = 1.0, beta: float = 0.0,
                     y: wp.array | None = None) -> None:  # fmt: skip
        """``z = alpha M^-1 r + beta y`` (``y`` defaults to ``z``) with the preconditioner of the last
        :meth:`assemble`: block-Jacobi, plus the coarse correction for ``"two_level"``."""
        dev, N = r.device, r.shape[0]
        split_launch(k.precondition_kernel, N, [self.inverse_block, r, z if y is None else y, float(alpha),
                                                float(beta)], [z], dev, self.threads, NODE_GRAIN)  # fmt: skip
        if self.coarse is not None:
            # the prolongation's r.z partial lands in the solver's scratch row 0, unread here
            for kernel, dim, before, after, grain in self._correction(r, z, row=0, scale=alpha):
                split_launch(kernel, dim, before, after, dev, self.threads, grain)
        if self.rigid is not None:
            for item in self.rigid.precondition_launches(r, z, z, self.partials, row=0, scale=alpha):
                item.launch()

    def _set_coefficients(self, c_mass: float, c_stiff: float, c_contact: float) -> None:
        if self._coefficients != (c_mass, c_stiff, c_contact):
            for launch_ in (self._start, self._product):
                launch_.set("c_mass", c_mass)
                launch_.set("c_stiff", c_stiff)
                launch_.set("c_contact", c_contact)
            self._coefficients = (c_mass, c_stiff, c_contact)

    def multiply(self, state: ElementState, p: wp.array, out: wp.array, c_mass: float, c_stiff: float,
                 project: int = 1, alpha: float = 1.0, beta: float = 0.0, *, y: wp.array | None = None,
                 c_contact: float = 0.0, rigid: bool = True) -> None:  # fmt: skip
        """``out = alpha A' p + beta y`` (``y`` defaults to ``out``) with ``A = c_mass M + c_stiff K' +
        c_contact K_c``: with ``project`` the filtered ``A' = S A S + I - S`` of the last :meth:`assemble`
        (fixed rows identity; with ``rigid`` and free rigid bodies, their rows projected onto rigid
        velocities), else ``A' = S A``."""
        e, dev = self.elements, self.elements.device
        split_launch(k.multiply_elements_kernel, e.tet_count,
                     [p, e.tets, e.volume, e.mu, e.lam, state.rotated, self.axes if project else self.ones],
                     [self.corner_out], dev, self.threads, TET_GRAIN)  # fmt: skip
        split_launch(k.gather_products_kernel, e.node_count,
                     [e.node_range, e.node_corners, self.corner_out, e.mass, self.axes, p,
                      out if y is None else y, float(c_mass), float(c_stiff), self.contact_weight, self.contact_block,
                      float(c_contact), float(alpha), float(beta), project],
                     [out], dev, self.threads, NODE_GRAIN)  # fmt: skip
        if project and rigid and self.rigid is not None:
            # the rigid rows of the filtered operator: Pi (alpha A p + beta y), y in the subspace as CG keeps it
            self.rigid.project(out)

    def assemble(self, state, x, v, target, external, gravity, h, c_mass, c_stiff, guess, *, ground=None,
                 friction: float = 0.0, moving: bool = False, c_contact: float = 0.0) -> None:  # fmt: skip
        """Free axes, prescribed velocities, right-hand side, warm start ``guess`` and preconditioner of the
        filtered system ``c_mass M + c_stiff K' + c_contact K_c``
        (:func:`~warpblob.sim._kernels.assemble_system_kernel`); ``c_contact = 0`` leaves contact out.

        With ``moving`` (some fixed node has a target away from its position)
        or a ``ground`` height (landing contacts, with Coulomb ``friction``), the coupling ``S A v_p`` of
        the prescribed velocities is taken off the right-hand side by one
        unfiltered product.
        """
        e, dev = self.elements, self.elements.device
        split_launch(k.assemble_system_kernel, e.node_count,
                     [x, v, e.mass, self.flags, target, state.node_force, state.node_block, external,
                      self.contact_force, self.contact_weight, self.contact_block, wp.vec3(*gravity), float(h),
                      float(c_mass), float(c_stiff), float(c_contact), int(ground is not None), float(ground or 0.0),
                      float(friction)],
                     [self.rhs, guess, self.prescribed, self.axes, self.coarse_axes, self.inverse_block], dev,
                     self.threads, NODE_GRAIN)  # fmt: skip
        if moving or ground is not None:
            self.multiply(state, self.prescribed, self.rhs, c_mass, c_stiff, project=0, alpha=-1.0, beta=1.0,
                          c_contact=c_contact)  # fmt: skip
        if self.rigid is not None:
            # the rigid rows: P^T b (momentum and impulses) and a warm start in the bodies' rigid velocities
            self.rigid.prepare(e.mass, state.node_block, self.contact_weight, self.contact_block, c_mass, c_stiff,
                               c_contact)  # fmt: skip
            self.rigid.project(self.rhs)
            self.rigid.project(guess)
        if self.coarse is not None:
            key = (float(c_mass), float(c_stiff))
            if key != self._coarse_key or self._coarse_age >= COARSE_EVERY or self.coarse.drifted():
                self.coarse.refresh(x, state.rotated, c_mass, c_stiff)
                self._coarse_key, self._coarse_age = key, 0
            self._coarse_age += 1

    def solve(self, state: ElementState, x: wp.array, c_mass: float, c_stiff: float, tolerance: float, atol: float,
              max_iterations: int, c_contact: float = 0.0) -> tuple[int, float, float]:  # fmt: skip
        """Preconditioned CG on the assembled system, in place on the warm start ``x``.

        Stops when ``|r| <= max(tolerance |b|, atol)`` or after
        ``max_iterations``. Returns (iterations, ``|r|``, ``|b|``).
        """
        if self.linear_solver == "warp":
            return self._solve_warp(state, x, c_mass, c_stiff, tolerance, atol, max_iterations, c_contact)
        self._set_coefficients(float(c_mass), float(c_stiff), float(c_contact))
        multiply = self._multiply[id(state)]
        multiply["x"].set("p", x)
        self._start.set("x", x)
        for u in self._update:
            u.set("x", x)
        partials = self.partials.numpy() if not x.device.is_cuda else None
        check_every = 1 if partials is not None else 8

        def sums():
            # host sync: the convergence check (on the CPU a view of the partials, no copy)
            part = partials if partials is not None else self.partials.numpy()
            return float(part[2].astype(np.float64).sum()), float(part[3].astype(np.float64).sum())

        coarse = self.coarse is not None
        rigid = self.rigid is not None
        multiply["x"]()
        self._start()
        for launch_ in self._start_coarse if coarse else ():
            launch_()
        for item in self._rigid_start if rigid else ():
            item.launch()
        rr, bb = sums()
        limit = max(tolerance * np.sqrt(bb), atol) ** 2
        iterations = 0
        while rr > limit and iterations < max_iterations:
            parity = iterations & 1
            multiply["p"]()
            self._product()
            for item in self._rigid_ap if rigid else ():
                item.launch()
            self._update[parity]()
            iterations += 1
            if iterations % check_every == 0 or iterations == max_iterations:
                rr, _ = sums()
                if rr <= limit:
                    break
            for launch_ in self._update_coarse[parity] if coarse else ():
                launch_()
            for item in self._rigid_update[parity] if rigid else ():
                item.launch()
            self._direction[parity]()
        rr, _ = sums()
        return iterations, float(np.sqrt(rr)), float(np.sqrt(bb))

    def _solve_warp(self, state, x, c_mass, c_stiff, tolerance, atol, max_iterations, c_contact):
        """:meth:`solve` by ``warp.optim.linear.cg``: the same operator, preconditioner and stopping rule."""
        from warp.optim.linear import LinearOperator, cg

        dev, N = x.device, x.shape[0]

        def product(p, y, z, alpha, beta):
            self.multiply(state, p, z, c_mass, c_stiff, 1, float(alpha), float(beta), y=y, c_contact=c_contact)

        def precondition(r, y, z, alpha, beta):
            self.precondition(r, z, float(alpha), float(beta), y=y)

        A = LinearOperator((N, N), wp.mat33, dev, product)
        M = LinearOperator((N, N), wp.mat33, dev, precondition)
        # host sync: |b| for the caller's relative residual (cg keeps it to itself)
        b_norm = float(np.sqrt(np.sum(self.rhs.numpy().astype(np.float64) ** 2)))
        # the residual is checked as often as solve checks it: every iteration on the CPU, every 8th on CUDA
        iterations, residual, _ = cg(A, self.rhs, x, tol=tolerance, atol=atol, maxiter=max_iterations, M=M,
                                     check_every=8 if dev.is_cuda else 1)  # fmt: skip
        return int(iterations), float(residual), b_norm
