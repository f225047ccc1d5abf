"""The coarse space of the two-level preconditioner: aggregates of nodes carrying their rigid-body modes.

Block-Jacobi reaches only the high-frequency error of the implicit system
``A = c_mass M + c_stiff K'``; when stiffness dominates (a stiff beam at
``dt = 1/60``) the slow error is the bending of the whole body, which CG
then needs hundreds of iterations to resolve. The coarse space captures
it: nodes are grouped into aggregates (the cells of a lattice over their
rest positions, each cell split by connected piece, :func:`aggregate`:
after a cut severs the body, an aggregate across the cut would tie the
two sides' modes together; split, the cut tumor of ``warpblob demo`` takes
26% fewer CG iterations over its 108 steps, 7,544 -> 5,605), and each aggregate carries its six
rigid modes, three translations and three linearized rotations about its
centroid, as in smoothed aggregation (Vanek, Mandel & Brezina 1996, here
unsmoothed). A bent body is, aggregate by aggregate, nearly rigid, so its
low-energy modes lie close to this space. The preconditioner is additive
(two-level additive Schwarz, Toselli & Widlund 2005, chapter 2):

    z = D^-1 r + P Ac^-1 P^T r,   Ac = P^T A' P,

with ``D`` the block diagonal of the filtered ``A'`` and ``P`` the
``(3 N, 6 G)`` prolongation (node ``i`` of aggregate ``g`` gets
``S_i (t_g + w_g x d_i)``), symmetric positive definite for any SPD
``D`` and any ``P``, so standard PCG applies. Fixed and ground-constrained
axes are filtered as in ``A'``: the rows of ``P`` take the step's
``S = diag(axes)``, so the correction never moves a constrained axis.

``Ac`` is assembled by kernels from the per-tet lagged stiffness
``R K R^T`` and the lumped mass (per-tet blocks written to per-tet slots
and gathered in a fixed order, so it is the same for any thread count),
then factored (:func:`factor`): scaled to a unit diagonal (a zero
diagonal, a mode that moves nothing such as the rotations of a one-node
aggregate, is left out), shifted by :data:`SHIFT` (modes that nearly move
nothing, as of a two-node aggregate, stay bounded), Cholesky ``L L^T``
by a float64 kernel inside the matrix's envelope (aggregates are numbered
along the longest axis first, so the envelope is about one slab of
aggregates wide and the factorization costs ``n b^2``, not ``n^3``), and
applied by forward and back substitution in one thread: ``(L L^T)^-1`` is
positive definite for any stored ``L``, whatever the rounding. (numpy's LAPACK was tried first: ``eigh`` and ``cholesky`` take 3
ms and 0.2 ms at 216 unknowns, but with another process on one of the two
cores OpenBLAS' threads wait for it, and they took 160-640 ms and 76 ms.)
It is *lagged*: rebuilt with the mode geometry
(centroids and offsets ``d_i`` at the current positions) every
:data:`COARSE_EVERY` steps, whenever the system's coefficients, the fixed
nodes or the state (set by the caller) change, and when more than
:data:`FILTER_CHANGES` of the nodes changed their free axes (ground
contacts landing or lifting); in between, the rotations, the positions of
the modes, a few contacts' filter and the tools' stiffness move on without
it. A lagged ``Ac`` is still a fixed SPD preconditioner within each solve,
so CG converges to the same tolerance; only the iteration count drifts.

A cut does not aggregate anew unless it severs a piece
(:meth:`CoarseSpace.follow`, which :meth:`warpblob.Simulation.rebuild`
takes when given the new nodes' sources, as ``apply_cut`` gives them): the
nodes keep their aggregates, each new node joins its source's, the dead
tets keep their (zero) slots and the new ones take slots after the last,
their pair lists merged into the old ones. Any aggregation gives a valid
preconditioner; this one differs from a fresh lattice only along the cut,
and it is made anew once the nodes have grown by :data:`FOLLOW_GROWTH`
since it was (or when a cut severs a piece). On the 110K-tet box of
``benchmarks/bench_cut.py``'s scalpel frames the set-up went from 12-14 ms
to about 2 ms a frame. CG iterations over twelve scalpel frames (one step
after each cut, the box fixed at its base, Young's modulus 1e7: stiff, where
the coarse space matters most): 20K tets 652 aggregating anew every frame,
696 carried over every frame, 666 with the 5% rule; 110K tets 695 and 701
(5% rule); at 3 kPa 84 against 85 and 139 against 140.
A followed space also keeps its factor (:meth:`CoarseSpace.carry_modes`):
the coarse matrix of the last refresh, on the same aggregates, each added
node with its source's offset, is a symmetric positive semi-definite
correction for the system after the cut too, so the solver refreshes it on
its own schedule (every :data:`COARSE_EVERY` steps, when the coefficients
change or the filter drifts, or when an old node's flag changes other than
by leaving the system), not at the first step after each cut. A refresh is
about a step's cost at 100K tets (coupling 75 ms, factor 38 ms on two
cores), which a scalpel cutting every frame paid every frame; the step
after a cut of the 110K-tet box went from 160-210 ms to 65-90 ms, with the
same CG iterations (2-3 at 3 kPa; 18 against 18 on the test's stiffer box).
Tool contact (``c_contact K_c``) stays out of ``Ac`` and enters the
block-Jacobi part, as in the one-level preconditioner.

Measured (Warp 1.19, one CPU thread, the 10K-tet beam of
``benchmarks/bench_fem.py``: 2304 nodes, 36 aggregates, 216 coarse
unknowns): about 30 CG iterations per step instead of more than 200, 0.27
ms per iteration instead of 0.23, a rebuild 3 ms (2 of them the per-tet
coupling, 0.4 the factorization). Aggregates of 16 to 40 nodes (600 to 750
unknowns) save no iterations on that beam and cost more per iteration; of
125 nodes (144 unknowns), twice the iterations. At 50K tets (810 unknowns,
the :data:`MAX_AGGREGATES` cap) the beam takes 38 iterations instead of the
cap of 200, 80 ms per step instead of 267, a rebuild 25 ms.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from .._parallel import launch
from .._stages import ROOM, column_bounds, device_array, device_empty, room, set_rows, shared_array
from ..mesh._structure import _connected, _unique_inverse
from . import _kernels as k

__all__ = ["CoarseSpace", "aggregate", "factor", "node_pieces"]

#: nodes per aggregate the lattice aims at, and the most aggregates (6 coarse unknowns each, stored dense)
AGGREGATE_NODES = 64
MAX_AGGREGATES = 160
#: steps between rebuilds of the coarse matrix (see the module docstring)
COARSE_EVERY = 10
#: the coarse matrix is also rebuilt when this fraction of the aggregated nodes changed their free axes since
#: (a landing or a release: a stale filter there makes the correction overshoot; a few flickering contacts do not)
FILTER_CHANGES = 0.02
#: shift of the unit-diagonal coarse matrix before its Cholesky factorization (its smallest eigenvalue on the
#: 10K-tet beam is 6e-4: the shift changes the softest coarse mode by 0.2%)
SHIFT = 1e-6
#: a cut's rebuild carries the aggregates over (:meth:`CoarseSpace.follow`) until the nodes have grown by this
#: fraction since they were last made, then aggregates anew
FOLLOW_GROWTH = 0.05
#: tets per piece of the coupling launch (a heavy kernel: 16 corner pairs of 6 x 6 blocks per tet)
COUPLE_GRAIN = 1024


def aggregate(rest: np.ndarray, active: np.ndarray, *, nodes: int, limit: int,
              pieces: np.ndarray | None = None) -> tuple[np.ndarray, int, float]:  # fmt: skip
    """Group the ``active`` nodes by the cell of a cubic lattice over their rest positions, and by piece.

    The cell size is set so that about ``active.sum() / nodes`` aggregates
    are made (at most ``limit``). With ``pieces`` an aggregate holds the
    nodes of one cell and one piece: a cell that a cut crosses gives one
    aggregate per side, whose rigid modes move the two sides apart (one
    aggregate across both would tie their modes together, and CG needs
    about twice the iterations once the pieces move apart).

    Args:
        rest: (N, 3) rest positions.
        active: (N,) bool, the nodes that take part (the others get -1).
        nodes: nodes per aggregate to aim at.
        limit: most aggregates.
        pieces: (N,) int, the connected piece of each active node (>= 0), or None (one piece).

    Returns:
        ``(node_aggregate (N,) int32, aggregate_count, cell_size)``; aggregates
        are numbered in lexicographic order of their cells, the longest axis first
        (then by piece).
    """
    out = np.full(len(rest), -1, dtype=np.int32)
    # (np.compress and per-column bounds: numpy's boolean row selection and reductions along the rows of a
    # narrow array take several times as long)
    pts = np.compress(active, np.asarray(rest, dtype=np.float64), axis=0)
    if len(pts) == 0:
        return out, 0, 1.0
    piece = np.zeros(len(pts), dtype=np.int64) if pieces is None else np.asarray(pieces, dtype=np.int64)[active]
    count = int(piece.max()) + 1
    lo, hi = column_bounds(pts)
    span = hi - lo
    extent = float(span.max()) or 1.0
    want = int(np.clip(round(len(pts) / nodes), 1, limit))
    size = float(np.prod(np.maximum(span, 1e-3 * extent)) / want) ** (1.0 / 3.0)

    # the longest axis first: the cells are numbered lexicographically, so consecutive aggregates sweep along
    # it and the coarse matrix's envelope spans one cross-section of cells
    axes = np.argsort(-span, kind="stable")

    def cells(h):
        c = np.floor((pts[:, axes] - lo[axes]) / h).astype(np.int64)
        width = column_bounds(c)[1] + 1
        return _unique_inverse(((c[:, 0] * width[1] + c[:, 1]) * width[2] + c[:, 2]) * count + piece)

    # the occupied cells of a lattice scale about as size^-3: two corrections land near the aim
    for _ in range(2):
        occupied = len(cells(size)[0])
        size *= (occupied / want) ** (1.0 / 3.0)
    uniq, inverse = cells(size)
    while len(uniq) > limit:
        size *= 1.1
        uniq, inverse = cells(size)
    out[active] = inverse.ravel().astype(np.int32)
    return out, int(inverse.max()) + 1, size


def node_pieces(tets: np.ndarray, node_count: int) -> np.ndarray:
    """(N,) int32 connected piece of every node, nodes joined through ``tets`` ((T, 4) node indices; -1 for a
    node in none of them), numbered by lowest node (:func:`~warpblob.mesh._structure._connected`)."""
    sub = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
    used = np.zeros(node_count, dtype=bool)
    used[sub.ravel()] = True
    return _connected(node_count, np.repeat(sub[:, 0], 3), sub[:, 1:].ravel(), used)


def factor(A: np.ndarray, first: np.ndarray, device) -> tuple[np.ndarray, np.ndarray]:
    """``(L, s)`` with ``diag(s) (L L^T)^-1 diag(s)`` the (regularized) inverse of the symmetric positive
    semi-definite ``A`` (n, n) whose row ``i`` is zero left of column ``first[i]``.

    ``s = diag(A)^-1/2`` (0 where the diagonal is not positive: that unknown
    is left out) and ``L L^T = diag(s) A diag(s) + SHIFT I``, factored inside
    the envelope by a float64 kernel (no LAPACK: see the module docstring);
    a column that rounding leaves dependent on the ones before is left out.
    """
    n = len(A)
    d = np.diag(A)
    s = np.where(d > 0, 1.0 / np.sqrt(np.where(d > 0, d, 1.0)), 0.0)
    scaled = s[:, None] * (0.5 * (A + A.T)) * s[None, :]
    scaled[np.diag_indices_from(scaled)] = np.where(d > 0, 1.0, 0.0) + SHIFT
    a = device_array(scaled, wp.float64, device)
    lower = wp.zeros((n, n), dtype=wp.float64, device=device)
    wp.launch(k.cholesky_kernel, 1, inputs=[a, device_array(first, wp.int32, device), wp.float64(0.5 * SHIFT),
                                            0, lower], device=device)  # fmt: skip
    # host sync: the factor comes back, to be stored in float32
    return lower.numpy(), s


class CoarseSpace:
    """The aggregates, their coarse matrix and its Cholesky factor (the correction's launches are the solver's).

    Built by :class:`~warpblob.sim._solver.ImplicitSolver` with the element
    data (a topology change builds a new one: :meth:`Simulation.rebuild`).

    Args:
        elements: the :class:`~warpblob.sim._elements.Elements`.
        axes: (N,) vec3 the free axes of the step's filter (``S``), written by the assembly.
        threads: CPU threads (None: the default).
        pieces: the number of connected pieces the live tets are known to form (the structure counted
            them), or None: at 1 the aggregates are not split by piece and the pieces are not counted
            (:func:`node_pieces`); :meth:`follow` compares it with the count after a cut.

    Attributes:
        aggregate_count: G; ``size`` = 6 G coarse unknowns; ``cell``: the lattice's cell size (the mode
            offsets ``d_i`` are in its units).
        node_aggregate: (N,) int32 Warp array, the aggregate of each node (-1: none).
        node_mode: (N,) vec3 the offsets ``d_i`` of the last :meth:`refresh`.
        setup_seconds: seconds of the aggregation and slot set-up; ``refresh_seconds`` of the last
            :meth:`refresh`, ``refreshes`` their count.
        followed: made by :meth:`follow` (the aggregates carried over a cut), not aggregated anew;
            ``pieces`` and ``made_nodes``: the piece count and the node count when they were made.
    """

    def __init__(self, elements, axes: wp.array, threads=None, pieces: int | None = None):
        t0 = time.perf_counter()
        e = elements
        mass = e.mass.numpy()
        labels = None if pieces == 1 else node_pieces(e.tets_host[e.alive_host], e.node_count)
        node_aggregate, G, cell = aggregate(e.rest_host, mass > 0, nodes=AGGREGATE_NODES, limit=MAX_AGGREGATES,
                                            pieces=labels)  # fmt: skip
        self._layout(e, axes, threads, node_aggregate, G, cell)
        self.pieces, self.made_nodes = pieces, e.node_count
        self.setup_seconds = time.perf_counter() - t0

    @classmethod
    def laid_out(cls, elements, axes: wp.array, node_aggregate: np.ndarray, aggregate_count: int, cell: float,
                 threads=None) -> CoarseSpace:  # fmt: skip
        """A coarse space on given aggregates ((N,) ints, -1: none; ``cell`` the unit of the mode offsets):
        the layout :meth:`follow` extends, built from scratch (the reference its tests compare with)."""
        c = cls.__new__(cls)
        t0 = time.perf_counter()
        c._layout(elements, axes, threads, np.asarray(node_aggregate, dtype=np.int32), int(aggregate_count),
                  float(cell))  # fmt: skip
        c.pieces, c.made_nodes = None, elements.node_count
        c.setup_seconds = time.perf_counter() - t0
        return c

    def _layout(self, e, axes: wp.array, threads, node_aggregate: np.ndarray, G: int, cell: float) -> None:
        """The aggregates' node lists, the per-tet slots and their grouping by aggregate pair, and the buffers."""
        dev = e.device
        self.elements, self.axes, self.threads, self.cell = e, axes, threads, cell
        T = e.tet_count
        self.aggregate_count, self.size = G, 6 * G
        # per tet, one slot per pair of the distinct aggregates of its corners (u of them: u^2 slots, mostly 1),
        # numbered by the aggregates' order of first appearance among the corners; slots grouped by pair
        # (kernels: a tet's groups are its corners' aggregates numbered by first appearance)
        tets_wp, alive_wp = e.tets, e.alive
        aggregate_wp = device_array(node_aggregate, wp.int32, dev)
        squares = device_empty(T, wp.int32, dev)
        launch(k.tet_aggregate_counts_kernel, T, [tets_wp, alive_wp, aggregate_wp], [squares], dev, threads,
               min_chunk=COUPLE_GRAIN * 16)  # fmt: skip
        # (in a host buffer with room: a followed space appends its added tets' starts in place)
        start = np.zeros(T + 1 + int(T * ROOM), dtype=np.int64)[: T + 1]
        np.cumsum(squares.numpy(), out=start[1:])
        slot_code = np.empty(int(start[-1]), dtype=np.int64)
        start_wp = self._array(start, wp.int64)
        launch(k.tet_pair_slots_kernel, T, [tets_wp, alive_wp, aggregate_wp, start_wp, int(G)],
               [device_array(slot_code, wp.int64, dev, copy=False)], dev, threads,
               min_chunk=COUPLE_GRAIN * 16)  # fmt: skip
        pairs, pair_of_slot = _unique_inverse(slot_code)  # (np.unique's; codes below G^2: by marks)
        pair_offsets = np.zeros(len(pairs) + 1, dtype=np.int64)
        pair_offsets[1:] = np.cumsum(np.bincount(pair_of_slot, minlength=len(pairs)))
        # (a stable sort of narrow keys: numpy's radix sort where they fit 16 bits)
        narrow = pair_of_slot.astype(np.uint16) if len(pairs) <= 1 << 16 else pair_of_slot
        pair_slots = np.argsort(narrow, kind="stable").astype(np.int32)
        self._set_slots(e, node_aggregate, start, start_wp, alive_wp, pairs, pair_offsets, pair_slots, {})
        self.pair_aggregates = self._array(np.stack([pairs // G, pairs % G], axis=1).astype(np.int32), wp.vec2i)
        # (G, G) blocks of 6 x 6: block (g, h) couples the modes of aggregates g and h
        self.coarse = wp.zeros((G, G), dtype=wp.spatial_matrix, device=dev)
        # the envelope of the coarse matrix: aggregates are numbered along the longest axis first, so a row of
        # blocks reaches back only over about one slab of aggregates
        first_block = np.full(G, G, dtype=np.int64)
        np.minimum.at(first_block, pairs // G, pairs % G)
        self.first_host = np.repeat(6 * np.minimum(first_block, np.arange(G)), 6).astype(np.int32)
        self.first = self._array(self.first_host)
        self.lower = wp.zeros((self.size, self.size), dtype=float, device=dev)
        self.scale = wp.zeros(self.size, dtype=float, device=dev)
        self.work = wp.zeros(self.size, dtype=float, device=dev)
        self.rc = wp.zeros(G, dtype=wp.spatial_vector, device=dev)
        self.zc = wp.zeros(G, dtype=wp.spatial_vector, device=dev)

    def _array(self, a: np.ndarray, dtype=wp.int32) -> wp.array:
        # (on the CPU these fresh host arrays are used in place, not copied)
        dev = self.elements.device
        return shared_array(a, dtype, dev)

    def _set_slots(self, e, node_aggregate, start, start_wp, alive_wp, pairs, pair_offsets, pair_slots,
                   kept: dict, order: np.ndarray | None = None, extra: tuple | None = None,
                   kept_rows: int = 0) -> None:  # fmt: skip
        """Store the aggregates, the slot layout and its grouping (kept on the host too, for :meth:`follow`),
        and make the per-node and per-slot buffers (in the bases ``kept``, the space followed from, where
        they have room: fresh pages cost more than the writes). ``order``: the aggregated nodes by aggregate,
        then by index (default: sorted here). ``extra``: ``(offsets, slots)``, the slots of the tets added
        since the aggregation, grouped by pair as ``pair_slots`` are, each pair's in slot order (default:
        none); a pair's sum takes its ``pair_slots`` and then these, which is the order of its slots.
        ``kept_rows``: the nodes whose rows of the per-node buffers a refresh writes before anything reads
        them (a followed space's old nodes: their rows are kept as they are where the base is)."""
        dev, N, G = e.device, e.node_count, self.aggregate_count
        if order is None:
            order = np.argsort(node_aggregate, kind="stable")
            order = order[node_aggregate[order] >= 0]
        offsets = np.zeros(G + 1, dtype=np.int32)
        # (each aggregate's nodes counted: the aggregated ones are those ``order`` lists)
        offsets[1:] = np.cumsum(np.bincount(node_aggregate + 1, minlength=G + 1)[1:])
        if extra is None:
            extra = (np.zeros(len(pairs) + 1, dtype=np.int64), np.zeros(0, dtype=np.int32))
        self._host = {"aggregate": node_aggregate, "start": start, "pairs": pairs, "pair_offsets": pair_offsets,
                      "pair_slots": pair_slots, "order": order, "offsets": offsets, "extra_offsets": extra[0],
                      "extra_slots": extra[1]}  # fmt: skip
        self.node_aggregate = self._array(node_aggregate)
        self.aggregate_offsets, self.aggregate_nodes = self._array(offsets), self._array(order.astype(np.int32))
        # a tet's slots are found again from these by the coupling kernel (no (16 T,) table of them)
        self.slot_start, self.tet_alive = start_wp, alive_wp
        self.pair_offsets, self.pair_slots = self._array(pair_offsets.astype(np.int32)), self._array(pair_slots)
        self.extra_offsets = self._array(extra[0].astype(np.int32))
        self.extra_slots = self._array(extra[1] if len(extra[1]) else np.zeros(1, dtype=np.int32))
        self._bases = {}
        # (slots: zeroed by each refresh)
        self._bases["slots"], self.slots = room(kept.get("slots"), int(start[-1]), wp.spatial_matrix, dev)
        for name in ("node_mode", "reference"):
            self._bases[name], view = room(kept.get(name), N, wp.vec3, dev)
            set_rows(view, kept_rows if self._bases[name] is kept.get(name) else 0, 0.0)
            setattr(self, name, view)
        self._changes = wp.zeros(1, dtype=wp.int32, device=dev)
        self._aggregated = len(order)
        self.refreshes, self.refresh_seconds = 0, 0.0
        self.followed, self.modes_kept, self._sources = False, False, None

    def follow(self, elements, axes: wp.array, sources: np.ndarray, pieces: int | None) -> CoarseSpace | None:
        """This coarse space carried over a cut: the same aggregates, with every added node in its source's.

        For an edit that only killed tets and appended tets and nodes (a cut
        or a drill's, :meth:`warpblob.Simulation.rebuild`): nodes keep their
        aggregates (a node left in no live tet leaves its own), each added node
        joins the aggregate of ``sources[i]``, the old node it was made from
        (a split point: the nearer end of its edge; a copy: its node); the
        dead tets keep their slots, which stay zero, and the added ones take
        slots after the last. A new tet's corners then lie in aggregates of its
        parent's corners, so no new aggregate pair appears and the coarse
        matrix keeps its size and envelope; its pair lists are merged, not
        sorted again. The coarse matrix is the one :meth:`laid_out` gives on
        the same aggregates, bit for bit (its sums meet the dead tets' slots
        as zeros). The aggregates are not split again by piece, so a cut that
        severed a piece (``pieces`` differs from the count they were made
        with, or either is unknown) is worth a new aggregation (see the module
        docstring), and so are nodes grown by more than :data:`FOLLOW_GROWTH`.

        Args:
            elements: the rebuilt :class:`~warpblob.sim._elements.Elements` (the same object, edited).
            axes: (N,) vec3 the new solver's free axes.
            sources: (K,) int, per node added since (in order), an old node.
            pieces: the structure's piece count after the edit (None: not known).

        Returns:
            The new :class:`CoarseSpace`, or None where it should be made anew (a piece severed, the nodes
            grown too much) or the edit is not of that kind (fewer tets or nodes than before, a source out
            of range, an aggregate pair that did not exist): build one from scratch then.
        """
        t0 = time.perf_counter()
        e, dev, host, G = elements, elements.device, self._host, self.aggregate_count
        old_n, old_t = len(host["aggregate"]), len(host["start"]) - 1
        N, T = e.node_count, e.tet_count
        sources = np.asarray(sources, dtype=np.int64).ravel()
        if pieces is None or pieces != self.pieces or N > (1.0 + FOLLOW_GROWTH) * self.made_nodes:
            return None
        if N < old_n or T < old_t or len(sources) != N - old_n or (sources.size and (sources.min() < 0
                                                                                   or sources.max() >= old_n)):
            return None
        node_aggregate = np.concatenate([host["aggregate"], host["aggregate"][sources]])
        node_aggregate[e.mass.numpy() <= 0] = -1
        alive_wp = e.alive
        aggregate_wp = device_array(node_aggregate, wp.int32, dev)
        added = T - old_t
        # the old tets' slot starts stay where they are (the host buffer's room), the added ones' follow
        start = host["start"]
        if start.base is None or len(start.base) < T + 1:
            start = np.concatenate([start, np.zeros(T - old_t + int(T * ROOM), dtype=np.int64)])
        start = (start if start.base is None else start.base)[: T + 1]
        pairs, pair_offsets, pair_slots = host["pairs"], host["pair_offsets"], host["pair_slots"]
        extra = (host["extra_offsets"], host["extra_slots"])
        if added:
            # the added tets' slots (one launch each over them alone: a cut adds a few thousand)
            squares = device_empty(T, wp.int32, dev)
            wp.launch(k.tet_aggregate_counts_kernel, added, inputs=[e.tets, alive_wp, aggregate_wp, old_t, squares],
                      device=dev)  # fmt: skip
            np.cumsum(squares.numpy()[old_t:], out=start[old_t + 1 :])
            start[old_t + 1 :] += start[old_t]
        start_wp = c_start = self._array(start, wp.int64)
        first_new, total = int(start[old_t]), int(start[-1])
        if total > first_new:
            codes = device_empty(total, wp.int64, dev)
            wp.launch(k.tet_pair_slots_kernel, added, inputs=[e.tets, alive_wp, aggregate_wp, start_wp, int(G), old_t,
                                                              codes], device=dev)  # fmt: skip
            code = codes.numpy()[first_new:]
            pair = np.searchsorted(pairs, code)
            if pair.max() >= len(pairs) or (pairs[pair] != code).any():
                return None  # a pair of aggregates the coarse matrix has no block for
            # merged grouping: each pair's slots added before, then its new ones in slot order, apart from the
            # aggregation's (which stay as they are: merging into them would copy 16 T entries a cut)
            order = np.argsort(pair, kind="stable")
            added_per_pair = np.bincount(pair, minlength=len(pairs))
            before = np.zeros(len(pairs) + 1, dtype=np.int64)
            np.cumsum(added_per_pair, out=before[1:])
            # (np.insert places equal positions in the order given)
            merged = np.insert(extra[1], extra[0][1:][pair[order]], (first_new + order).astype(np.int32))
            extra = (extra[0] + before, merged)
        c = CoarseSpace.__new__(CoarseSpace)
        c.elements, c.axes, c.threads, c.cell = e, axes, self.threads, self.cell
        c.aggregate_count, c.size = G, self.size
        # the nodes by aggregate, merged rather than sorted again: the old ones in their order (less those left
        # without mass), each added one after its aggregate's old ones (its index is past theirs)
        added_nodes = np.arange(old_n, N)[node_aggregate[old_n:] >= 0]
        added_nodes = added_nodes[np.argsort(node_aggregate[added_nodes], kind="stable")]
        if np.array_equal(node_aggregate[:old_n], host["aggregate"]):  # (no old node left without mass)
            kept = host["order"]
            at = host["offsets"][node_aggregate[added_nodes] + 1]  # (after its aggregate's old nodes)
        else:
            kept = host["order"][node_aggregate[host["order"]] >= 0]
            at = np.searchsorted(node_aggregate[kept], node_aggregate[added_nodes], side="right")
        c._set_slots(e, node_aggregate, start, c_start, alive_wp, pairs, pair_offsets, pair_slots, self._bases,
                     np.insert(kept, at, added_nodes), extra, old_n)  # fmt: skip
        # the coarse matrix keeps its blocks and envelope: its buffers are reused (each refresh rewrites them)
        for name in ("pair_aggregates", "coarse", "first_host", "first", "lower", "scale", "work", "rc", "zc"):
            setattr(c, name, getattr(self, name))
        c.followed, c.pieces, c.made_nodes = True, self.pieces, self.made_nodes
        # the last refresh's offsets and filter kept for the old nodes (their bases had room): the factor can
        # serve on (:meth:`carry_modes`)
        c.modes_kept = all(c._bases[name] is self._bases.get(name) for name in ("node_mode", "reference"))
        c._sources = sources
        c.setup_seconds = time.perf_counter() - t0
        return c

    def carry_modes(self) -> None:
        """Keep the factor of the space followed from (:meth:`follow`) until the next refresh: each added
        node takes its source's offset ``d_i`` and reference filter axes. Restriction and prolongation read
        the same offsets, so the correction stays symmetric positive semi-definite, and the factor of the
        coarse matrix before the cut (the same aggregates, size and envelope) is a preconditioner for the
        system after it; the solver refreshes it on its schedule (:data:`COARSE_EVERY` steps, or when the
        filter drifted), not at the first step after every cut."""
        sources = self._sources
        old_n = self.elements.node_count - len(sources)
        for name in ("node_mode", "reference"):
            rows = getattr(self, name)
            values = rows.numpy()  # (the array's own memory on the CPU, a copy on a GPU)
            values[old_n:] = values[sources]
            if not rows.device.is_cpu:
                rows.assign(values)

    def drifted(self) -> bool:
        """Whether more than :data:`FILTER_CHANGES` of the aggregated nodes changed their free axes since the
        last :meth:`refresh`."""
        e = self.elements
        self._changes.zero_()
        # one launch, not split: the count is an atomic sum, safe only within one CPU launch
        wp.launch(k.count_changes_kernel, e.node_count, inputs=[self.axes, self.reference, 0, self._changes],
                  device=e.device)  # fmt: skip
        # host sync: one integer decides the refresh
        return int(self._changes.numpy()[0]) > FILTER_CHANGES * self._aggregated

    def matrix(self) -> np.ndarray:
        """The coarse matrix of the last :meth:`refresh` as a dense (6 G, 6 G) float64 array (aggregate-major)."""
        G = self.aggregate_count
        return self.coarse.numpy().astype(np.float64).transpose(0, 2, 1, 3).reshape(6 * G, 6 * G)

    def refresh(self, x: wp.array, rotated: wp.array, c_mass: float, c_stiff: float) -> None:
        """Rebuild the modes at positions ``x``, the coarse matrix ``P^T A' P`` with the rotations ``rotated``
        and the step's filter, and its Cholesky factor (:func:`factor`)."""
        t0 = time.perf_counter()
        e, dev, th, G = self.elements, self.elements.device, self.threads, self.aggregate_count
        wp.launch(k.frame_aggregates_kernel, G, inputs=[x, self.aggregate_offsets, self.aggregate_nodes,
                                                        float(self.cell), 0, self.node_mode], device=dev)  # fmt: skip
        wp.copy(self.reference, self.axes)
        self.slots.zero_()
        launch(k.couple_tets_kernel, e.tet_count,
               [e.tets, e.volume, e.mu, e.lam, rotated, self.axes, self.node_mode, self.tet_alive,
                self.node_aggregate, self.slot_start, float(c_stiff)],
               [self.slots], dev, th, min_chunk=COUPLE_GRAIN)  # fmt: skip
        wp.launch(k.assemble_coarse_kernel, self.pair_aggregates.shape[0],
                  inputs=[self.pair_offsets, self.pair_slots, self.extra_offsets, self.extra_slots,
                          self.pair_aggregates, self.slots, self.aggregate_offsets,
                          self.aggregate_nodes, e.mass, self.axes, self.node_mode, float(c_mass), 0, self.coarse],
                  device=dev)  # fmt: skip
        # host sync: the coarse matrix is scaled on the host, then factored by a kernel
        lower, scale = factor(self.matrix(), self.first_host, dev)
        self.lower.assign(lower.astype(np.float32))
        self.scale.assign(scale.astype(np.float32))
        self.refreshes += 1
        self.refresh_seconds = time.perf_counter() - t0
