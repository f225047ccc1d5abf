"""Rigid tools pressing the simulated tissue: contact through the implicit field, carried by the deformation.

The source thesis (Shirazian 2014, chapter 6; SPEC section 5.2) detects
contact with the model's field: a tool vertex where ``F >= 0.5`` penetrates,
by the inverse falloff ``dist(F)``, and pushes with
``CF = normalize(grad F + T) * dist * s`` at the nearest volume node, spread
over its first and second rings with decreasing weights. The thesis reads
the field of the *rest* model at the vertex's world position, so once the
tissue has moved the contact no longer matches it. Here (``contact="field"``,
the default) the field is carried by the deformation instead:

1. **Samples.** A tool's vertices are too sparse for a coarse probe on a
   fine mesh, so its faces are sampled at the mesh's edge length (the median
   rest edge of the live tets): :meth:`~warpblob.tools.Tool.sample_surface`
   (every vertex, points dividing every edge, the interior nodes of a
   barycentric grid on every face). Each sample stands for an equal share
   of the area of every face it lies on (:func:`sample_areas`), so the
   forces do not depend on the sampling density.
2. **Location.** Each step the tool moves to ``path.pose(t + dt)`` (the
   pose at the end of the step, which the implicit step solves for); each
   sample is located in the deformed tets (a ``wp.Bvh`` over the current
   boxes of the boundary layer, the tets with a node on the boundary,
   refit each step: a tool presses the surface and the penalty keeps its
   samples within a fraction of an edge of it, so the layer, at least an
   edge deep, holds every sample in contact, at a cost that grows with the
   surface, not the volume; a sample that sinks deeper in one step is not
   found) and mapped to rest space by its barycentric coordinates; a
   sample just outside the tets (within half an edge) maps through its
   nearest tet, since the tets' flat boundary faces lie inside the model's
   curved surface and the contact must not jump there.
3. **Field.** The model's field and gradient at the rest point
   (:func:`warpblob.field.evaluate`); the gradient is pushed forward by the
   tet's deformation gradient (``F^-T grad F``), so the contact surface is
   the deformed surface.
4. **Force.** A sample with ``F >= 0.5`` penetrates by ``depth`` (model
   units: the inverse falloff of SPEC 1.1 scaled by the radius of the lone
   primitive with that field value and slope,
   :func:`~warpblob.sim._contact_kernels.signed_depth`; negative outside);
   its force on the tissue is ``CF = normalize(n + T) * psi(depth) * s * a``
   with ``n`` the unit deformed gradient, ``T`` the tool's unit travel over
   the step, ``s`` the stiffness and ``a`` the sample's area. The contact
   law ``psi`` is the depth, its onset smoothed over the first ``2 band``
   of depth (``band`` a tenth of the mesh's edge length;
   :func:`~warpblob.sim._contact_kernels.penalty`, C1, zero outside), so
   samples join and leave the contact gradually. The force goes to the
   containing tet's nodes by (clamped) barycentric weights.
5. **Spread.** Each node's share is spread over its k-ring (the nodes
   within ``k`` edges, the rings of :meth:`warpblob.mesh.TetStructure.k_ring`):
   a node ``r`` edges away gets the weight ``(k + 1 - r) / (k + 1)`` (1, 2/3,
   1/3 for ``k = 2``), normalized over the ring so that the force is kept.
   The CSR of the spread is built once per topology (:func:`ring_spread`) and
   applied by a gather kernel; after a cut's rebuild it, the boundary layer
   and the median edge follow the edit round its touched nodes
   (:func:`ring_spread_after`, :meth:`Contact.bind`), the same arrays, bit
   for bit, as a bind anew.

``contact="nearest"`` is the thesis' variant, for comparison: the rest field
at the sample's world position (no deformation map), the force at the
nearest node (of the boundary layer's, by a ``wp.Bvh`` over them), then the
same spread. Its depth does not fall as the tissue gives way, so its force
is a load rather than a spring: the tissue yields until its elastic force
balances ``s A depth``, and a stiffness that holds the field contact at the
surface crushes the tissue under it (the scenarios give it the tissue's own
scale, :mod:`warpblob.scenarios`).

**Stiffness and the implicit step.** ``s`` is a stiffness per unit area, N
per model unit of penetration per model unit squared of tool surface (N/m^3
in SI units): a flat probe face of area ``A`` pressed ``d`` into the tissue
pushes back with about ``s A d``. A penalty that stiff would be unstable
as an explicit force at ``dt = 1/60`` (``dt^2 s a / m`` is far above 1 on
the surface nodes), so it goes inside the implicit solve (as Müller &
Gross 2004 treat the elastic forces): each sample adds the stiffness
``s a psi' d d^T`` along its force direction ``d`` (lumped onto its nodes
by the same weights and spread alike); the step solves with
``f_c - K_c h v'``, the contact force linearized at the end of the step,
and stays stable for any ``s`` (the tests run ``1e5`` times the tissue's
own stiffness at ``dt = 1/60``). Without the smoothed onset, a stiff
penalty switched on at the surface makes nearly static tissue (backward
Euler is close to a static solve when the tissue's stiffness outweighs its
mass over a step) alternate between two states from step to step, one
pressed out of the tool and one relaxed into it. Nodes without contact see
no change in any arithmetic: a tool that never touches the tissue leaves
the simulation bit-identical.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from .._errors import SimulationError, ToolError
from .._linearize import linearize
from .._parallel import launch, thread_count
from .._stages import device_array, host_array, room, rows_any
from ..field import evaluate
from ..mesh import TetMesh
from ..tools import Path, Tool
from . import _contact_kernels as ck
from . import _kernels as k
from ._solver import NODE_GRAIN, split_launch

__all__ = ["ToolContact", "Contact", "CONTACT_MODES", "HIGHLIGHT", "highlight", "sample_areas", "ring_spread"]

#: the contact law's onset band, in edge lengths
BAND = 0.1
#: how far outside the deformed volume a sample still reads the field through its nearest tet, in edge lengths
MARGIN = 0.5
#: colour of the contact area in pictures and recorded stages
HIGHLIGHT = np.array([1.0, 0.82, 0.1])
#: the contact modes of :meth:`~warpblob.Simulation.add_tool`
CONTACT_MODES = {"field": ck.FIELD, "nearest": ck.NEAREST}
#: samples per launch piece: a sample costs well under a microsecond, a split launch tens of microseconds
_SAMPLE_GRAIN = 2048


def highlight(colors: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(V, 3) float32 ``colors`` turned towards :data:`HIGHLIGHT` where the contact ``weight`` (V,) in [0, 1] is.

    The square root of the weight mixes, so the faint rim of the spread
    still shows.
    """
    a = np.sqrt(np.clip(weight, 0.0, 1.0))[:, None] * 0.9
    return ((1.0 - a) * np.asarray(colors, dtype=np.float64) + a * HIGHLIGHT).astype(np.float32)


def sample_areas(tool: Tool, points: np.ndarray) -> np.ndarray:
    """(S,) area each sample stands for: every face's area shared equally by the samples lying on it.

    A sample on an edge or at a corner takes shares of every face it lies
    on; the shares add up to the tool's surface area.
    """
    v = tool.vertices
    f = tool.faces.astype(np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cross = np.cross(b - a, c - a)
    twice = np.linalg.norm(cross, axis=1)
    normal = cross / twice[:, None]
    size = float(np.ptp(v, axis=0).max())
    # barycentric coordinates of every sample in every face's plane, (S, F)
    rel = points[:, None, :] - a[None]
    height = np.abs(np.einsum("sfi,fi->sf", rel, normal))
    u = np.einsum("sfi,fi->sf", np.cross(c - b, points[:, None, :] - b[None]), normal) / twice
    w = np.einsum("sfi,fi->sf", np.cross(a - c, points[:, None, :] - c[None]), normal) / twice
    tol = 1e-9
    on = (height <= tol * size) & (u >= -tol) & (w >= -tol) & (u + w <= 1 + tol)
    count = on.sum(axis=0)
    return (on * np.where(count > 0, 0.5 * twice / np.maximum(count, 1), 0.0)).sum(axis=1)


def _tets_at(incidence: tuple, nodes: np.ndarray, live: np.ndarray) -> np.ndarray:
    """The live tets at ``nodes`` (int64), ascending, from an incidence ``(offsets, corners)``
    (:meth:`~warpblob.sim._elements.Elements.incidence`) or ``(ranges, lists)``
    (:meth:`~warpblob.sim._elements.Elements.incidence_lists`: (N, 2) ranges, the lists where they are kept)."""
    first, corners = incidence
    if first.ndim == 2:
        begin, end = first[nodes, 0].astype(np.int64), first[nodes, 1]
    else:
        begin, end = first[nodes].astype(np.int64), first[nodes + 1]
    count = end - begin
    start = np.repeat(begin - (np.cumsum(count) - count), count)
    t = _unique(corners[start + np.arange(int(count.sum()))] // 4)
    return t[live[t]]


def _edge_lengths(rest: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(K, 6) float32 edge lengths of the (K, 4) ``tets`` (each length computed on its own: the same bits
    whatever the batch)."""
    edges = rest[tets[:, [1, 2, 3, 2, 3, 3]]] - rest[tets[:, [0, 0, 0, 1, 1, 2]]]
    return np.linalg.norm(edges, axis=2)


def _sorted_after(ordered: np.ndarray, gone: np.ndarray, came: np.ndarray) -> np.ndarray | None:
    """``ordered`` (ascending) with the values ``gone`` taken out and ``came`` put in, ascending (two
    vectorized passes: the slots taken out dropped, the values put in inserted at their places); None where
    a value of ``gone`` is not in ``ordered`` (then sort anew). Equal values are interchangeable, so each
    one taken out is any of its equals, each one put in goes before the first value not below it."""
    gone, came = np.sort(gone), np.sort(came).astype(ordered.dtype, copy=False)
    n = len(ordered)
    # each value taken out at its own slot among its equals
    at = np.searchsorted(ordered, gone) + (np.arange(len(gone)) - np.searchsorted(gone, gone))
    if len(gone) and (at[-1] >= n or np.any(ordered[np.minimum(at, n - 1)] != gone)):
        return None
    kept = np.delete(ordered, at) if len(at) else ordered
    return np.insert(kept, np.searchsorted(kept, came), came) if len(came) else kept.copy()


class _SortedLengths:
    """A sorted multiset of float32 values with the changes of the last edits pending: ``base`` (ascending)
    less ``gone`` plus ``came`` (both ascending; ``gone`` is part of ``base``, ``came`` of the multiset), so
    that an edit costs a merge of the pending values, not a pass over every value (they are spliced into
    ``base`` by :func:`_sorted_after` once they outgrow 1/:data:`_PENDING` of it). Order statistics are
    searches: the count at or below a value is ``base``'s less ``gone``'s plus ``came``'s."""

    __slots__ = ("base", "came", "gone")

    def __init__(self, ordered: np.ndarray):
        self.base = ordered
        self.gone = self.came = np.zeros(0, dtype=np.float32)

    def __len__(self) -> int:
        return len(self.base) - len(self.gone) + len(self.came)

    def edit(self, gone: np.ndarray, came: np.ndarray) -> bool:
        """Take the values ``gone`` out and put ``came`` in; False (nothing changed) where a value of
        ``gone`` is not in the multiset (then make it anew)."""
        gone = np.sort(np.asarray(gone, dtype=np.float32))
        came = np.sort(np.asarray(came, dtype=np.float32))
        pending = self.came
        # a value taken out that a pending one put in: that one goes (each at its own slot among its equals)
        if len(pending) and len(gone):
            at = np.searchsorted(pending, gone) + (np.arange(len(gone)) - np.searchsorted(gone, gone))
            hit = at < len(pending)
            hit[hit] = pending[at[hit]] == gone[hit]
            pending, gone = np.delete(pending, at[hit]), gone[~hit]
        # the others out of ``base``: no value more often out than it is there
        out = _merged(self.gone, gone)
        if len(gone):
            values = np.unique(gone)
            n_out = np.searchsorted(out, values, side="right") - np.searchsorted(out, values)
            n_base = np.searchsorted(self.base, values, side="right") - np.searchsorted(self.base, values)
            if np.any(n_out > n_base):
                return False
        self.gone, self.came = out, _merged(pending, came)
        if _PENDING * (len(self.gone) + len(self.came)) > len(self.base):
            self.base = _sorted_after(self.base, self.gone, self.came)
            self.gone = self.came = np.zeros(0, dtype=np.float32)
        return True

    def sorted(self) -> np.ndarray:
        """Every value, ascending (a new array where changes are pending)."""
        if not len(self.gone) and not len(self.came):
            return self.base
        return _sorted_after(self.base, self.gone, self.came)

    def _at_most(self, values: np.ndarray) -> np.ndarray:
        """How many values are at or below each of ``values``."""
        return (np.searchsorted(self.base, values, side="right") - np.searchsorted(self.gone, values, side="right")
                + np.searchsorted(self.came, values, side="right"))  # fmt: skip

    def _first_above(self, values: np.ndarray, lo: int, hi: int, k: int) -> int:
        """The least ``i`` in ``[lo, hi)`` with more than ``k`` values at or below ``values[i]`` (``hi`` if
        none; ``values`` ascending): a search that probes 64 places a round (a round's three searches cost
        what one place's would)."""
        while lo < hi:
            probe = np.linspace(lo, hi - 1, min(hi - lo, _PROBES)).astype(np.int64)
            above = self._at_most(values[probe]) > k
            if not above[-1]:
                return hi
            j = int(np.argmax(above))
            if j == 0:
                return lo
            lo, hi = int(probe[j - 1]) + 1, int(probe[j])
        return lo

    def kth(self, k: int) -> np.float32:
        """The ``k``-th smallest value (0-based): the least value with more than ``k`` at or below it, found
        in ``base`` and in ``came``. In ``base`` it lies at or before place ``k`` plus the values gone (more
        than ``k`` lie at or below that one) and at or after place ``k`` less the values come, but for equals
        of the one there (the value found is the same); a value of ``base`` that is all gone counts the same
        as the next one below it that is there, so the lesser of the two finds is there."""
        best = None
        n = len(self.base)
        for values, lo, hi in ((self.base, max(0, k - len(self.came)), min(n, k + len(self.gone) + 1)),
                               (self.came, 0, len(self.came))):  # fmt: skip
            i = self._first_above(values, lo, hi, k)
            if i < hi and (best is None or values[i] < best):
                best = values[i]
        return best

    def median(self) -> float:
        """The median as ``np.median`` takes it: the mean of the middle one or two values (float32)."""
        n = len(self)
        middle = [self.kth(n // 2)] if n % 2 else [self.kth(n // 2 - 1), self.kth(n // 2)]
        return float(np.mean(np.array(middle, dtype=np.float32)))


#: pending changes of a :class:`_SortedLengths` are spliced into its base beyond 1/_PENDING of it
_PENDING = 32
#: places a round of :meth:`_SortedLengths._first_above` probes
_PROBES = 64


def _merged(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Two ascending arrays as one, ascending (a copy of each, not a sort)."""
    if not len(b):
        return a
    if not len(a):
        return b
    return np.insert(a, np.searchsorted(a, b, side="right"), b)


def _unique(keys: np.ndarray) -> np.ndarray:
    """Sorted distinct ``keys`` by a sort (numpy's hashing ``np.unique`` is several times slower on these)."""
    keys = np.sort(keys)
    return keys[np.concatenate([[True], keys[1:] != keys[:-1]])] if len(keys) else keys


def ring_spread(tets: np.ndarray, alive: np.ndarray, node_count: int, k: int):
    """The k-ring spread as a CSR by target node: ``(offsets (N + 1,), nodes, weights)`` (int32, int32, float32).

    Row ``j`` lists, in ascending order, every node ``c`` within ``k`` edges
    of ``j`` (``j`` itself included: the rings of
    :meth:`~warpblob.mesh.TetStructure.k_ring` over the live tets' edges) with
    ``W[j, c] = w(r) / Z_c``: ``w(r) = (k + 1 - r) / (k + 1)`` for ``r`` the
    ring of ``j`` around ``c`` and ``Z_c = sum_j w(r(j, c))``, so each
    node's force is spread without loss. Rings are symmetric, so row ``c``
    also lists the nodes ``c`` spreads to. A breadth-first search from each
    node over the live tets round it, in a kernel (:func:`_rings_near`: a
    set-up cost, paid again only when the topology changes;
    :func:`ring_spread_after` follows a local edit).
    """
    return _ring_spread(tets, alive, node_count, k).packed()[:3]


class _Spread:
    """A k-ring spread kept as rows with room (as the elements keep their incidence), so that a local edit
    rewrites only the rows it changes.

    Row ``j``'s entries are ``nodes``/``weights``/``rings`` ``[ranges[j, 0], ranges[j, 1])`` (int32,
    float32, uint8: the nodes of its rings, ``W[j, c]`` and the ring of each); its slot holds ``room[j]``
    entries from ``ranges[j, 0]``; entries from ``tail`` on are free. ``total``: (N,) float64 the sums ``Z``.
    Made packed by :func:`_ring_spread`, followed in place by :func:`ring_spread_after`.
    """

    __slots__ = ("nodes", "ranges", "rings", "room", "search", "tail", "total", "weights")

    def __init__(self, offsets: np.ndarray, nodes: np.ndarray, weights: np.ndarray, total: np.ndarray,
                 rings: np.ndarray, search: _RingSearch | None = None):  # fmt: skip
        self.ranges = np.ascontiguousarray(np.stack([offsets[:-1], offsets[1:]], axis=1), dtype=np.int32)
        self.room = np.diff(offsets).astype(np.int32)
        self.nodes, self.weights, self.rings, self.total = nodes, weights, rings, total
        self.tail = len(nodes)
        # (the search that made the rows, with its stamps, for the follows; else one sized by the rows)
        self.search = search if search is not None else _RingSearch(int(self.room.max()) if len(self.room) else 0)

    def packed(self) -> tuple:
        """The spread as a packed CSR: ``(offsets (N + 1,) int32, nodes, weights, total, rings)``."""
        r = self.ranges
        count = r[:, 1] - r[:, 0]
        offsets = np.zeros(len(r) + 1, dtype=np.int32)
        np.cumsum(count, out=offsets[1:])
        at = np.repeat(r[:, 0].astype(np.int64) - offsets[:-1], count) + np.arange(int(offsets[-1]))
        return offsets, self.nodes[at], self.weights[at], self.total, self.rings[at]


def _ring_spread(tets, alive, node_count: int, k: int, threads=None) -> _Spread:
    """:func:`ring_spread` with the (N,) float64 sums ``Z`` and the ring of each entry, as a :class:`_Spread`."""
    N = int(node_count)
    if k == 0:
        nodes = np.arange(N, dtype=np.int32)
        return _Spread(np.arange(N + 1, dtype=np.int32), nodes, np.ones(N, dtype=np.float32), np.ones(N),
                       np.zeros(N, dtype=np.uint8))  # fmt: skip
    # every node's row from the incidence of every tet (the search passes the dead ones): the corners
    # ``4 * tet + i`` by node, in order
    tets = np.ascontiguousarray(tets, dtype=np.int32)
    corners = np.argsort(tets.ravel(), kind="stable").astype(np.int32)
    offsets = np.zeros(N + 1, dtype=np.int64)
    np.cumsum(np.bincount(tets.ravel(), minlength=N), out=offsets[1:])
    search = _RingSearch(0)  # (no room: rows counted, then written at their places)
    count, cols, rings = _rings_near(search, (offsets, corners), tets, alive, np.arange(N), N, k, threads)
    rows = np.repeat(np.arange(N), count)
    w = (k + 1 - rings) / (k + 1)
    total = np.bincount(rows, weights=w, minlength=N)
    offsets = np.zeros(N + 1, dtype=np.int32)
    np.cumsum(count, out=offsets[1:])
    # (the search's room a row is the largest row and a quarter now, as a spread's own would be)
    return _Spread(offsets, cols, (w / total[cols]).astype(np.float32), total, rings, search)


def ring_spread_after(spread: _Spread, tets: np.ndarray, alive: np.ndarray, node_count: int, k: int,
                      touched: np.ndarray, incidence: tuple, threads=None) -> _Spread:  # fmt: skip
    """:func:`_ring_spread` after an edit that changed only tets whose corners (old and new, and every added
    node) are ``touched``, from ``spread`` (its result before the edit), recomputing only what can change;
    ``spread`` is edited in place and returned (or, after an edit of much of the mesh, a new one made).

    The edit changes edges between touched nodes only, and a node's edge distance to them is the same
    before and after it (a shortest path to them needs no edge between two of them). So a row's ring
    structure (its nodes and their rings) changes only within ``k`` edges of them: those rows are found
    again by the same search, from those nodes only, over the live tets round them (``incidence``: the live
    tets' incidence, packed or as kept: :func:`_tets_at`), which gives their sums ``Z`` too, and written in
    their slots (or, where they outgrew them, at the tail with room to grow). The rows within ``2 k`` hold
    such a node and keep their structure: their weights ``w(r) / Z_c`` are taken again from their rings and
    the new sums, in place (:func:`~warpblob.sim._contact_kernels.reweigh_rows_kernel`). No other row is
    touched. The result is :func:`_ring_spread`'s, bit for bit (:meth:`_Spread.packed`; the sums are taken
    in the same order).
    """
    N = int(node_count)
    n_old = len(spread.ranges)
    if k == 0 or n_old > N or 8 * len(touched) > N:  # (an edit of much of the mesh: made anew)
        return _ring_spread(tets, alive, N, k, threads)
    tets = np.asarray(tets)
    alive = np.asarray(alive, dtype=bool)
    # the nodes by edge distance from the touched ones, up to 2 k (one search from all of them)
    order, level_end = _levels(spread.search, incidence, tets, alive, np.unique(touched), N, 2 * k)
    redo = np.sort(order[: level_end[k]]).astype(np.int64)
    count, cols, rings = _rings_near(spread.search, incidence, tets, alive, redo, N, k, threads)
    rows = np.repeat(redo, count)
    w = (k + 1 - rings) / (k + 1)
    # the per-row arrays grown to the added nodes (their rows are redone: every added node is touched)
    if N > n_old:
        spread.ranges = np.concatenate([spread.ranges, np.zeros((N - n_old, 2), dtype=np.int32)])
        spread.room = np.concatenate([spread.room, np.zeros(N - n_old, dtype=np.int32)])
        spread.total = np.concatenate([spread.total, np.zeros(N - n_old)])
    total = spread.total
    total[redo] = np.bincount(rows, weights=w, minlength=N)[redo]
    # the redone rows (every one holds its own node: rows ascend through redo) in their slots where they fit,
    # else at the tail with half as much room again
    moved = spread.room[redo] < count
    size = count[moved] + count[moved] // 2 + 4
    start = spread.ranges[redo, 0].astype(np.int64)
    start[moved] = spread.tail + np.cumsum(size) - size
    tail = spread.tail + int(size.sum())
    if tail > len(spread.nodes):  # (room for a while: the entries' arrays grow by half)
        capacity = max(tail, len(spread.nodes) + len(spread.nodes) // 2)
        for name in ("nodes", "weights", "rings"):
            grown = np.empty(capacity, dtype=getattr(spread, name).dtype)
            grown[: spread.tail] = getattr(spread, name)[: spread.tail]
            setattr(spread, name, grown)
    spread.ranges[redo, 0] = start
    spread.ranges[redo, 1] = start + count
    spread.room[redo[moved]] = size
    spread.tail = tail
    at = np.repeat(start - (np.cumsum(count) - count), count) + np.arange(len(rows))
    spread.nodes[at] = cols
    spread.weights[at] = (w / total[cols]).astype(np.float32)
    spread.rings[at] = rings
    # the rows within 2 k weighed again by the new sums
    again = order[level_end[k] : level_end[2 * k]]
    launch(ck.reweigh_rows_kernel, len(again),
           [host_array(again, wp.int32), host_array(spread.ranges, wp.vec2i), host_array(spread.nodes, wp.int32),
            host_array(spread.rings, wp.uint8), host_array(total, wp.float64), int(k)],
           [host_array(spread.weights, wp.float32)], "cpu", threads, min_chunk=_ROW_GRAIN)  # fmt: skip
    return spread


#: rows of a spread per launch piece when they are weighed again (a row is some tens of entries)
_ROW_GRAIN = 1024


class _RingSearch:
    """What :func:`_rings_near` and :func:`_levels` keep between calls: each CPU thread's node and tet stamps
    (a search's tags are new each time, so they are never cleared), the last tag, and the room a row gets
    (the largest row met so far and a quarter; 0: the rows are counted first)."""

    __slots__ = ("row_hint", "stamps", "tag")

    def __init__(self, largest: int):
        self.stamps, self.tag = None, 0
        self.row_hint = largest + largest // 4 if largest else 0

    def stamps_for(self, pieces: int, N: int, T: int, tags: int) -> tuple:
        """The (pieces, >= N) node and (pieces, >= T) tet stamps, with ``tags`` new tags from ``self.tag`` on
        (made anew, zero, where too small or the tags would overflow)."""
        st = self.stamps
        if (st is None or st[0].shape[0] < pieces or st[0].shape[1] < N or st[1].shape[1] < T
                or self.tag + tags >= np.iinfo(np.int32).max):  # fmt: skip
            self.stamps = (np.zeros((pieces, N + N // 8), dtype=np.int32), np.zeros((pieces, T + T // 8), np.int32))
            self.tag = 0
        return self.stamps


def _search_arrays(incidence: tuple, tets: np.ndarray, alive: np.ndarray) -> list:
    """The incidence (as :func:`_tets_at` takes it: its ranges made from packed offsets), the (T, 4) int32
    ``tets`` and ``alive`` as the search kernels read them."""
    first, corners = incidence
    if first.ndim == 2:
        ranges = np.ascontiguousarray(first, dtype=np.int32)
    else:
        ranges = np.ascontiguousarray(np.stack([first[:-1], first[1:]], axis=1), dtype=np.int32)
    return [host_array(ranges, wp.vec2i), host_array(np.ascontiguousarray(corners, dtype=np.int32), wp.int32),
            host_array(tets, wp.vec4i), host_array(np.ascontiguousarray(alive).view(np.uint8), wp.uint8)]


def _levels(search: _RingSearch, incidence: tuple, tets: np.ndarray, alive: np.ndarray, sources: np.ndarray,
            N: int, depth: int) -> tuple:  # fmt: skip
    """The nodes within ``depth`` edges of ``sources`` (distinct) over the live tets, by level: ``(order
    (M,) int32, level_end (depth + 1,) int32)``, level ``d`` the nodes ``order[level_end[d - 1]:level_end[d]]``
    (the sources first); one search from all of them (:func:`~warpblob.sim._contact_kernels.
    node_levels_kernel`, one thread, with the first thread's stamps of ``search``)."""
    tets = np.ascontiguousarray(tets, dtype=np.int32)
    stamps = search.stamps_for(1, N, len(tets), 1)
    order, level = np.empty((1, N), dtype=np.int32), np.empty((1, N), dtype=np.uint8)
    level_end = np.empty(depth + 1, dtype=np.int32)
    wp.launch(ck.node_levels_kernel, dim=1, device="cpu",
              inputs=[host_array(np.ascontiguousarray(sources, dtype=np.int32), wp.int32),
                      *_search_arrays(incidence, tets, alive), int(depth), search.tag + 1, 0,
                      *(wp.array(a, dtype=t, copy=False) for a, t in ((stamps[0], wp.int32), (stamps[1], wp.int32),
                                                                       (order, wp.int32), (level, wp.uint8))),
                      host_array(level_end, wp.int32)])  # fmt: skip
    search.tag += 1
    return order[0, : int(level_end[-1])], level_end


def _rings_near(search: _RingSearch, incidence: tuple, tets: np.ndarray, alive: np.ndarray, sources: np.ndarray,
                N: int, k: int, threads=None) -> tuple:  # fmt: skip
    """The k-ring rows of ``sources`` (ascending node ids): ``(count (R,) int64, nodes (sum,) int32, rings
    (sum,) uint8)``, each row the nodes within ``k`` edges of its source over the live tets, ascending, with
    their rings, the rows in source order. A breadth-first search per source over the live tets round each
    node (``incidence`` as :func:`_tets_at` takes it) in :func:`~warpblob.sim._contact_kernels.
    ring_rows_kernel`, each CPU thread its own share of the rows with its own stamps (``search``); the rows
    are written one after the other in room for ``search.row_hint`` entries a row, and where that was too
    little, written again at their places, the sizes known."""
    R = len(sources)
    if R == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.uint8)
    tets = np.ascontiguousarray(tets, dtype=np.int32)
    P = max(1, min(thread_count() if threads is None else int(threads), R))
    stamps = search.stamps_for(P, N, len(tets), 2 * R)
    per = -(-R // P)
    room = per * search.row_hint
    found, found_ring = np.empty((P, N), dtype=np.int32), np.empty((P, N), dtype=np.uint8)
    count = np.empty(R, dtype=np.int32)
    nodes, rings = np.empty(P * room, np.int32), np.empty(P * room, np.uint8)
    args = [host_array(np.ascontiguousarray(sources, dtype=np.int32), wp.int32),
            *_search_arrays(incidence, tets, alive), int(k), per]  # fmt: skip
    scratch = [wp.array(stamps[0], dtype=wp.int32, copy=False), wp.array(stamps[1], dtype=wp.int32, copy=False),
               wp.array(found, dtype=wp.int32, copy=False), wp.array(found_ring, dtype=wp.uint8, copy=False),
               host_array(count, wp.int32)]  # fmt: skip
    launch(ck.ring_rows_kernel, P, [*args, search.tag, host_array(np.zeros(0, np.int32), wp.int32), room],
           [*scratch, host_array(nodes, wp.int32), host_array(rings, wp.uint8)], "cpu", threads, min_chunk=1)
    search.tag += R
    size = np.abs(count)
    search.row_hint = max(search.row_hint, int(size.max()) + int(size.max()) // 4)
    if count.min() > 0:  # (every row in its piece's room: the pieces' rows one after the other)
        used = np.add.reduceat(size, np.arange(0, R, per))
        keep = np.concatenate([np.arange(p * room, p * room + u) for p, u in enumerate(used.tolist())])
        return size.astype(np.int64), nodes[keep], rings[keep]
    first = np.zeros(R, dtype=np.int32)
    np.cumsum(size[:-1], out=first[1:])
    nodes, rings = np.empty(int(size.sum()), np.int32), np.empty(int(size.sum()), np.uint8)
    launch(ck.ring_rows_kernel, P, [*args, search.tag, host_array(first, wp.int32), 0],
           [*scratch, host_array(nodes, wp.int32), host_array(rings, wp.uint8)], "cpu", threads, min_chunk=1)
    search.tag += R
    return size.astype(np.int64), nodes, rings


@dataclass(frozen=True, eq=False)
class ToolContact:
    """A tool added to a simulation (:meth:`~warpblob.Simulation.add_tool`).

    Attributes:
        tool: the :class:`~warpblob.tools.Tool`.
        path: its :class:`~warpblob.tools.Path`.
        stiffness: N per model unit of penetration per model unit squared of tool surface.
        kring: rings the force spreads over.
        contact: ``"field"`` or ``"nearest"``.
        spacing: sample spacing, model units.
        samples: (S, 3) float64 local sample points.
        area: (S,) float64 tool area per sample, model units squared.
    """

    tool: Tool
    path: Path
    stiffness: float
    kring: int
    contact: str
    spacing: float
    samples: np.ndarray
    area: np.ndarray

    def pose(self, t: float):
        """The tool's :class:`~warpblob.tools.Pose` at time ``t`` (s)."""
        return self.path.pose(t)


def check_tool(tool, path, stiffness, kring, contact) -> tuple[float, int]:
    """ToolError naming the first bad argument of ``add_tool``; returns (stiffness, kring)."""
    # a Tool is closed and a Path finite and increasing once made (their constructors refuse the rest, naming
    # the value), and both are immutable
    if not isinstance(tool, Tool):
        raise ToolError(f"add_tool: tool must be a warpblob.tools.Tool (Probe, Scalpel, Drill...), got {tool!r}")
    if not isinstance(path, Path):
        raise ToolError(f"add_tool: path must be a warpblob.tools.Path, got {path!r}")
    number = isinstance(stiffness, (int, float, np.integer, np.floating)) and not isinstance(stiffness, bool)
    if not number or not np.isfinite(stiffness) or stiffness <= 0:
        raise ToolError(f"add_tool: stiffness must be a finite number > 0, got {stiffness!r}")
    if isinstance(kring, bool) or not isinstance(kring, (int, np.integer)) or kring < 0:
        raise ToolError(f"add_tool: kring must be a non-negative integer, got {kring!r}")
    if contact not in CONTACT_MODES:
        raise ToolError(f"add_tool: contact must be one of {', '.join(CONTACT_MODES)}, got {contact!r}")
    return float(stiffness), int(kring)


class Contact:
    """The contact state of one simulation: its tools, their samples, the search structures and buffers.

    Args:
        elements: the simulation's :class:`~warpblob.sim.Elements`.
        model: the model whose field the contact reads.
        threads: CPU threads (None: the default).
    """

    def __init__(self, elements, model, threads=None):
        self.model = model
        self.threads = threads
        self.tools: list[ToolContact] = []
        lm = linearize(model)
        placed = lm.radius > 0
        lower, upper = lm.bounds
        self.model_bounds = np.stack([lower, upper])
        # the longest penetration length: twice the widest primitive (its radius over its map's stretch), or
        # the model's diagonal without radii
        widest = (lm.radius[placed] / lm.stretch[placed]).max() if placed.any() else 0.5 * np.linalg.norm(upper - lower)
        self.reach = float(2.0 * widest)
        self.forces = np.zeros((0, 3))
        self.counts = np.zeros(0, dtype=np.int64)
        self.deepest = np.zeros(0)
        self.active = False
        self.stats = {"seconds": {"locate": 0.0, "field": 0.0, "spread": 0.0}, "samples": 0, "penetrating": 0}
        # what _build_buffers keeps between binds: the key of the tools its arrays were made for, and the
        # state arrays' bases with room
        self._tools_key = None
        self._zero_bases: dict = {}
        self.bind(elements)

    # -- set-up ----------------------------------------------------------------

    def bind(self, elements) -> None:
        """(Re)bind to the element data: after a topology change the rings and search structures are rebuilt."""
        self.elements = elements
        e = elements
        self.device = e.device
        live = e.alive_host & (e.volume.numpy() > 0)
        if not live.any():
            raise SimulationError("contact: the volume has no live tet")
        # a local edit (a cut's rebuild: the element data's next revision, with its touched nodes) is followed
        # from the state before it where that can be done exactly; anything else is bound anew
        local = (e is getattr(self, "_bound", (None, 0))[0] and e.revision == self._bound[1] + 1
                 and e.touched_nodes is not None and len(self._near) <= e.node_count
                 and len(self._layer_mask) <= e.tet_count and e.node_count < 2_000_000)  # fmt: skip
        # (the face keys below take three node indices in an int64)
        self._incidence = e.incidence_lists() if local else None
        # the boundary layer (the tets with a node on the boundary) and every tet's edge lengths (T, 6)
        # (the live tets' edge lengths are kept as a sorted multiset with the changes of the last edits
        # pending: a local edit's median is then a search, not a selection over all of them again)
        # (the lengths are kept in a base with room, rows of new tets appended in place)
        T = e.tet_count
        sorted_lengths = None
        if local:
            near, mask, around = self._layer_after(live, e.touched_nodes, self._incidence)
            T0 = len(self._lengths)
            if T > len(self._lengths_base):
                grown = np.empty((T + T // 2, 6), dtype=np.float32)
                grown[:T0] = self._lengths
                self._lengths_base = grown
            lengths = self._lengths_base[:T]
            # the rows of the tets round the touched nodes, the changed ones and the new ones (no other tet
            # changed or was born or died): the live tets whose rows changed give their old lengths back and
            # their new ones in, the tets that died their old lengths back, the new live tets theirs in
            changed = e.changed_tets
            redo = np.union1d(np.union1d(around, changed[changed < T0]), np.arange(T0, T))
            stay = redo[redo < T0]
            before = lengths[stay]
            lengths[redo] = _edge_lengths(e.rest_host, e.tets_host[redo])
            was, now = self._live[stay], live[stay]
            both = was & now
            differ = np.any(before[both] != lengths[stay[both]], axis=1)
            new = redo[len(stay) :]
            gone = np.concatenate([before[was & ~now].ravel(), before[both][differ].ravel()])
            came = np.concatenate([lengths[stay[~was & now]].ravel(), lengths[stay[both][differ]].ravel(),
                                   lengths[new[live[new]]].ravel()])  # fmt: skip
            sorted_lengths = self._sorted_lengths
            if not sorted_lengths.edit(gone, came):
                sorted_lengths = None
        else:
            t = e.tets_host[live]
            near = np.zeros(e.node_count, dtype=bool)
            near[TetMesh(e.rest_host, t).surface_faces().ravel()] = True
            mask = np.zeros(T, dtype=bool)
            mask[live] = rows_any(near[t])
            self._lengths_base = np.empty((T + T // 8 + 16, 6), dtype=np.float32)
            lengths = self._lengths_base[:T]
            lengths[:] = _edge_lengths(e.rest_host, e.tets_host)
        if sorted_lengths is None:
            sorted_lengths = _SortedLengths(np.sort(lengths[live], axis=None))
        self._near, self._layer_mask, self._lengths, self._live = near, mask, lengths, live
        self._sorted_lengths = sorted_lengths
        # the median of the live tets' edges, as ``np.median`` takes it: the mean of the middle one or two
        self.edge = sorted_lengths.median()
        self.band = BAND * self.edge
        layer = np.flatnonzero(mask).astype(np.int32)
        self._layer, self.layer_count = layer, len(layer)  # (ascending, on the host)
        self._place_layer(layer, mask, local)
        # the k-ring spreads, made on first use; after a local edit followed from the ones before it
        rings = getattr(self, "_rings", {})
        self._rings_before = rings if local else {}
        self._follow = e.touched_nodes if local else None
        self._bound = (e, e.revision)
        self._rings: dict[int, _Spread] = {}
        self._node_bvh = None
        self._build_buffers()

    def _place_layer(self, layer: np.ndarray, mask: np.ndarray, local: bool) -> None:
        """The layer's tets in the trees that locate the tool's points (:meth:`_refit`): a main tree's slots
        (``_slots``, tet ids, -1 for an empty slot) and a small second tree of the tets that joined the layer
        since the main one was built (``_extra``).

        Over a local edit (a cut) the main tree is kept: the slots of the tets that left the layer (dead, or
        no longer at the boundary) are emptied (their boxes made empty, which a refit's unions ignore and no
        query meets) and the tets that joined go to the second tree, which is built anew (a cut's few
        hundred tets). A tree over every layer tet is built instead where there is none yet, the edit is not
        local, the second tree would hold over an eighth of the main one's slots, or a quarter of those are
        empty: building a tree over the layer costs 31 ms for 40K tets and 167 ms for 180K here, a refit
        1.6 and 18. A point's tet is the same either way (the kernel takes the best candidate of both trees,
        ties to the smaller tet)."""
        slots, extra = getattr(self, "_slots", None), layer[:0]
        keep = local and slots is not None and getattr(self, "_tet_bvh", None) is not None
        if keep:
            slots = slots.copy()
            stay = slots >= 0
            stay[stay] = mask[slots[stay]]
            slots[~stay] = -1
            held = np.zeros(len(mask), dtype=bool)
            held[slots[stay]] = True
            extra = layer[~held[layer]]
            keep = 8 * len(extra) <= len(slots) and 4 * int((~stay).sum()) <= len(slots)
        if not keep:
            slots, extra = layer, layer[:0]
            self._tet_bvh = None
        self._slots, self._extra = slots, extra
        self._cells = wp.array(np.concatenate([slots, extra]).astype(np.int32), dtype=wp.int32, device=self.device)
        self._extra_bvh = None
        self._trees = None

    def _layer_after(self, live: np.ndarray, touched: np.ndarray, incidence: tuple) -> tuple:
        """The boundary flags (N,), the layer's mask (T,) and the live tets at the touched nodes after a local
        edit, from those before it.

        A face changes sides (boundary or inner) only where a tet that holds it changed, and all its corners
        are then ``touched``; so only the touched nodes' flags can change, each found from the faces at it
        (a face at a node is held only by tets at that node: the live tets at the touched nodes count every
        such face fully), and only the tets at them, or that died, change their place in the layer.
        """
        e = self.elements
        N, T = e.node_count, e.tet_count
        near = np.zeros(N, dtype=bool)
        near[: len(self._near)] = self._near
        mask = np.zeros(T, dtype=bool)
        mask[: len(self._layer_mask)] = self._layer_mask
        mask &= live
        touched = np.asarray(touched, dtype=np.int64)
        around = _tets_at(incidence, touched, live)
        faces = np.sort(e.tets_host[around].astype(np.int64)[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], axis=2)
        keys = ((faces[..., 0] * N + faces[..., 1]) * N + faces[..., 2]).ravel()
        order = np.argsort(keys, kind="stable")
        ks = keys[order]
        single = np.ones(len(ks), dtype=bool)
        same = ks[1:] == ks[:-1]
        single[1:] &= ~same
        single[:-1] &= ~same
        at = np.zeros(N, dtype=bool)
        at[touched] = True
        boundary = faces.reshape(-1, 3)[order[single]]
        boundary = boundary[rows_any(at[boundary])]  # (a face at a touched node is counted fully)
        near[touched] = False
        near[boundary.ravel()] = True
        mask[around] = rows_any(near[e.tets_host[around]])
        return near, mask, around

    def add(self, tool, path, *, stiffness, kring, contact, spacing=None) -> ToolContact:
        """Check and sample a tool (:meth:`~warpblob.Simulation.add_tool` says what the arguments are)."""
        stiffness, kring = check_tool(tool, path, stiffness, kring, contact)
        if spacing is None:
            spacing = self.edge
        elif (isinstance(spacing, bool) or not isinstance(spacing, (int, float, np.integer, np.floating))
              or not np.isfinite(spacing) or spacing <= 0):  # fmt: skip
            raise ToolError(f"add_tool: spacing must be a finite number > 0, got {spacing!r}")
        samples = tool.sample_surface(float(spacing))
        record = ToolContact(tool, path, stiffness, kring, contact, float(spacing), samples,
                             sample_areas(tool, samples))  # fmt: skip
        self.tools.append(record)
        self._build_buffers()
        return record

    def _ring(self, k: int) -> _Spread:
        """The k-ring spread (:func:`ring_spread`, with its sums), followed over the last rebuild from the one
        before it where that was a local edit of the element data this contact was bound to (:meth:`bind`)."""
        if k not in self._rings:
            e, live = self.elements, self._live
            before = self._rings_before.get(k)
            if before is not None and self._follow is not None:
                self._rings[k] = ring_spread_after(before, e.tets_host, live, e.node_count, k, self._follow,
                                                   self._incidence, self.threads)  # fmt: skip
            else:
                self._rings[k] = _ring_spread(e.tets_host, live, e.node_count, k, self.threads)
        return self._rings[k]

    def _build_buffers(self) -> None:
        dev, e = self.device, self.elements
        N = e.node_count
        tools = self.tools
        K = len(tools)
        sizes = [len(r.samples) for r in tools]
        S = int(sum(sizes))
        self.sample_count = S
        krings = sorted({r.kring for r in tools})
        self.group_count = max(1, len(krings))
        # the tools' own arrays, made again only when the tools or the device change
        key = (dev, tuple(id(r) for r in tools))
        if self._tools_key != key:
            self._tools_key = key
            self._tool_first = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int32)
            self._local = wp.array(np.concatenate([r.samples for r in tools]).astype(np.float32) if S else
                                   np.zeros((0, 3), np.float32), dtype=wp.vec3, device=dev)  # fmt: skip
            self._area = wp.array(np.concatenate([r.area for r in tools]).astype(np.float32) if S else
                                  np.zeros(0, np.float32), dtype=float, device=dev)  # fmt: skip
            self._point_tool = wp.array(np.repeat(np.arange(K, dtype=np.int32), sizes), dtype=wp.int32, device=dev)
            self._tool_first_wp = wp.array(self._tool_first, dtype=wp.int32, device=dev)
            self._modes = wp.array(np.array([CONTACT_MODES[r.contact] for r in tools] or [0], np.int32),
                                   dtype=wp.int32, device=dev)  # fmt: skip
            self._groups = wp.array(np.array([krings.index(r.kring) for r in tools] or [0], np.int32),
                                    dtype=wp.int32, device=dev)  # fmt: skip
            self._stiffness = wp.array(np.array([r.stiffness for r in tools] or [0.0], np.float32), dtype=float,
                                       device=dev)  # fmt: skip
        # the state arrays zeroed, in kept bases with room (a cut's rebind adds a few nodes)
        bases = self._zero_bases

        def zeros(name: str, n: int, dtype) -> wp.array:
            bases[name], view = room(bases.get(name), n, dtype, dev)
            view.zero_()
            return view

        K1 = max(K, 1)
        self._poses = zeros("poses", K1, wp.transform)
        self._travel = zeros("travel", K1, wp.vec3)
        self._world, self._query = zeros("world", S, wp.vec3), zeros("query", S, wp.vec3)
        self._cell = zeros("cell", S, wp.int32)
        self._bary = zeros("bary", S, wp.vec4)
        self._depth = zeros("depth", S, float)
        self._law = zeros("law", S, wp.vec2)
        self._direction = zeros("direction", S, wp.vec3)
        self._entry_node = zeros("entry_node", 4 * S, wp.int32)
        self._entry_weight = zeros("entry_weight", 4 * S, float)
        # radix sort buffers: twice the entries
        self._keys = zeros("keys", 8 * S, wp.int32)
        self._entries = zeros("entries", 8 * S, wp.int32)
        G = self.group_count
        rings = [self._ring(kr) for kr in krings] or [self._ring(0)]
        # (one group: the spread's own arrays, shared on the CPU, not copied; a follow rewrites them in place
        # before the next bind makes these again)
        if len(rings) == 1:
            ranges, nodes, weights = rings[0].ranges, rings[0].nodes, rings[0].weights
        else:
            base = np.cumsum([0] + [r.tail for r in rings[:-1]])
            ranges = np.concatenate([r.ranges + b for r, b in zip(rings, base)]).astype(np.int32)
            nodes = np.concatenate([r.nodes[: r.tail] for r in rings])
            weights = np.concatenate([r.weights[: r.tail] for r in rings])
        self._ring_ranges = device_array(ranges, wp.vec2i, dev, copy=False)
        self._ring_nodes = device_array(nodes, wp.int32, dev, copy=False)
        self._ring_weights = device_array(weights, float, dev, copy=False)
        self._source_force = zeros("source_force", G * N, wp.vec3)
        self._source_block = zeros("source_block", G * N, wp.mat33)
        self._source_weight = zeros("source_weight", G * N, float)
        self._mark = zeros("mark", N, wp.uint8)
        self._totals = zeros("totals", K1, wp.vec3)
        self._counts = zeros("counts", K1, wp.int32)
        self._deepest = zeros("deepest", K1, float)
        self.forces = np.zeros((K, 3))
        self.counts = np.zeros(K, dtype=np.int64)
        self.deepest = np.zeros(K)
        self.stats["samples"] = S

    def _refit(self, x: wp.array) -> None:
        """Boxes of the current tets (and nodes, for the nearest mode) and their BVHs, built once and refit."""
        e, dev, th = self.elements, self.device, self.threads
        modes = {r.contact for r in self.tools}
        if "field" in modes:
            # the main tree over its slots, the second over the tets that joined since (:meth:`_place_layer`)
            n0, n1 = len(self._slots), len(self._extra)
            main, extra = self._tet_bvh, self._extra_bvh
            if n0:
                self._tet_bvh, self._tet_box = self._tree(main, getattr(self, "_tet_box", None), x, 0, n0)
            if n1:
                self._extra_bvh, self._extra_box = self._tree(extra, getattr(self, "_extra_box", None), x, n0, n1)
            if self._trees is None or self._tet_bvh is not main or self._extra_bvh is not extra:
                ids = [t.id if t is not None else 0 for t in (self._tet_bvh, self._extra_bvh)]
                self._trees = wp.array(np.array(ids, dtype=np.uint64), dtype=wp.uint64, device=dev)
        if "nearest" in modes:
            if self._node_bvh is None:
                self._node_lowers = wp.empty(e.node_count, dtype=wp.vec3, device=dev)
                self._node_uppers = wp.empty(e.node_count, dtype=wp.vec3, device=dev)
                # the nearest-node search sees the layer's nodes only (the others get boxes far away)
                layer_nodes = np.zeros(e.node_count, dtype=bool)
                layer_nodes[e.tets_host[self._layer].ravel()] = True
                self._layer_mass = wp.array(np.where(layer_nodes, e.mass.numpy(), 0.0).astype(np.float32),
                                            dtype=float, device=dev)  # fmt: skip
            split_launch(ck.node_bounds_kernel, e.node_count, [x, self._layer_mass],
                         [self._node_lowers, self._node_uppers], dev, th, NODE_GRAIN)  # fmt: skip
            if self._node_bvh is None:
                self._node_bvh = wp.Bvh(self._node_lowers, self._node_uppers)
            else:
                self._node_bvh.refit()

    def _tree(self, tree, box, x: wp.array, first: int, size: int) -> tuple:
        """The boxes of the tets ``_cells[first:first + size]`` at ``x`` and the tree over them: ``tree``
        refit where there is one (``box``: its (lowers, uppers)), else a new one over new boxes; returns
        ``(tree, box)``."""
        dev = self.device
        if tree is None:
            box = (wp.empty(size, dtype=wp.vec3, device=dev), wp.empty(size, dtype=wp.vec3, device=dev))
        split_launch(ck.cell_bounds_kernel, size, [x, self.elements.tets, self._cells, first], list(box), dev,
                     self.threads, NODE_GRAIN)  # fmt: skip
        if tree is None:
            return wp.Bvh(*box), box
        tree.refit()
        return tree, box

    def _locate(self, x: wp.array, point_tool, local, poses, modes, world, query, cell, bary) -> None:
        e = self.elements
        # a nearest-mode-only simulation has no tet BVH, and its kernel branch never queries one
        if self._trees is None:
            self._trees = wp.zeros(2, dtype=wp.uint64, device=self.device)
        split_launch(ck.locate_points_kernel, local.shape[0],
                     [self._trees, self._cells, len(self._slots), local, point_tool, poses, modes, x, e.rest, e.tets,
                      e.volume, MARGIN * self.edge],
                     [world, query, cell, bary], self.device, self.threads, _SAMPLE_GRAIN)  # fmt: skip

    # -- per step --------------------------------------------------------------

    def _sync(self) -> float:
        if self.device.is_cuda:
            wp.synchronize_device(self.device)
        return time.perf_counter()

    def update(self, x: wp.array, solver, t: float, h: float) -> bool:
        """Move the tools to their poses at ``t + h`` and write the contact forces and stiffness into ``solver``.

        Returns whether any tool may touch the tissue this step (its box,
        grown by the sample spacing, meets the tissue's current box, or the
        model's box for the nearest mode); when none does, nothing runs and
        the contact arrays are zero.
        """
        t0 = self._sync()
        after = [r.pose(t + h) for r in self.tools]
        before = [r.pose(t) for r in self.tools]
        # host sync: the tissue's box for the broad phase (SPEC 5.2: AABB of tool vs model)
        xs = x.numpy()
        # column by column: numpy reduces an (N, 3) array over axis 0 about 20x slower
        tissue = np.array([[c.min() for c in xs.T], [c.max() for c in xs.T]]) if len(xs) else np.zeros((2, 3))
        near = False
        for r, pose in zip(self.tools, after):
            box = r.tool.bounds(pose) + np.array([[-1.0], [1.0]]) * r.spacing
            other = tissue if r.contact == "field" else self.model_bounds
            near |= bool(np.all(box[0] <= other[1]) and np.all(other[0] <= box[1]))
        if not near:
            self.clear(solver)
            self.stats["seconds"] = {"locate": 0.0, "field": 0.0, "spread": 0.0}
            return False
        self._poses.assign(np.array([p.numpy() for p in after], dtype=np.float32))
        step = np.array([a.position - b.position for a, b in zip(after, before)])
        length = np.linalg.norm(step, axis=1, keepdims=True)
        self._travel.assign(np.divide(step, length, out=np.zeros_like(step), where=length > 0).astype(np.float32))
        self._refit(x)
        self._locate(x, self._point_tool, self._local, self._poses, self._modes, self._world, self._query, self._cell,
                     self._bary)  # fmt: skip
        t1 = self._sync()
        values, gradients, _ = evaluate(self.model, self._query, threads=self.threads)
        t2 = self._sync()
        if self._node_bvh is not None:
            split_launch(ck.nearest_nodes_kernel, self.sample_count,
                         [self._node_bvh.id, self._world, values, self._point_tool, self._modes, x, self.edge],
                         [self._cell], self.device, self.threads, _SAMPLE_GRAIN)  # fmt: skip
        t3 = self._sync()
        self._spread(x, values, gradients, solver)
        t4 = self._sync()
        self.active = True
        # the nearest-node search (after the field) is location too
        self.stats["seconds"] = {"locate": (t1 - t0) + (t3 - t2), "field": t2 - t1, "spread": t4 - t3}
        return True

    def _spread(self, x, values, gradients, solver) -> None:
        e, dev, th = self.elements, self.device, self.threads
        N, S, G = e.node_count, self.sample_count, self.group_count
        split_launch(ck.sample_forces_kernel, S,
                     [self._point_tool, self._cell, self._bary, values, gradients, self._area, self._modes,
                      self._groups, self._stiffness, self._travel, x, e.tets, e.dm_inv, self.reach, self.band, G,
                      N],
                     [self._depth, self._law, self._direction, self._entry_node, self._entry_weight, self._keys,
                      self._entries], dev, th, _SAMPLE_GRAIN)  # fmt: skip
        wp.utils.radix_sort_pairs(self._keys, self._entries, 4 * S)
        self._source_weight.zero_()
        self._mark.zero_()
        split_launch(ck.gather_sources_kernel, 4 * S,
                     [self._keys, self._entries, self._entry_weight, self._law, self._direction, self._ring_ranges,
                      self._ring_nodes, 4 * S, N, G * N],
                     [self._source_force, self._source_block, self._source_weight, self._mark], dev, th,
                     _SAMPLE_GRAIN)  # fmt: skip
        split_launch(ck.spread_forces_kernel, N,
                     [self._mark, self._ring_ranges, self._ring_nodes, self._ring_weights, self._source_force,
                      self._source_block, self._source_weight, G, N],
                     [solver.contact_force, solver.contact_block, solver.contact_weight], dev, th,
                     NODE_GRAIN)  # fmt: skip
        solver.contact_zero = False

    def finish(self, v: wp.array, h: float) -> None:
        """The force on each tool at the end of the step, from the new velocities ``v`` (one host sync)."""
        K = len(self.tools)
        split_launch(ck.tool_forces_kernel, K,
                     [self._tool_first_wp, self._depth, self._law, self._direction, self._entry_node,
                      self._entry_weight, v, float(h)],
                     [self._totals, self._counts, self._deepest], self.device, self.threads, 1)  # fmt: skip
        # host sync: the tools' forces (what a haptic device renders)
        self.forces = self._totals.numpy()[:K].astype(np.float64)
        self.counts = self._counts.numpy()[:K].astype(np.int64)
        self.deepest = self._deepest.numpy()[:K].astype(np.float64)
        self.stats["penetrating"] = int(self.counts.sum())

    def clear(self, solver) -> None:
        """Zero the contact arrays after a step with contact (an idle step then changes nothing)."""
        if self.active:
            solver.contact_force.zero_()
            solver.contact_block.zero_()
            solver.contact_weight.zero_()
            solver.contact_zero = True
            self._depth.fill_(-1.0e30)
            self.forces = np.zeros((len(self.tools), 3))
            self.counts = np.zeros(len(self.tools), dtype=np.int64)
            self.deepest = np.zeros(len(self.tools))
            self.stats["penetrating"] = 0
        self.active = False

    # -- queries ---------------------------------------------------------------

    def penetrating(self, tool: int | None = None) -> np.ndarray:
        """(P, 3) float32 world positions of the samples (of one tool, or all) penetrating this step."""
        if not self.active:
            return np.zeros((0, 3), dtype=np.float32)
        inside = self._depth.numpy() > 0
        if tool is not None:
            keep = np.zeros_like(inside)
            keep[self._tool_first[tool] : self._tool_first[tool + 1]] = True
            inside &= keep
        return self._world.numpy()[inside].copy()

    def field(self, x: wp.array, points: np.ndarray, threads=None) -> tuple[np.ndarray, np.ndarray]:
        """The deformation-mapped field and its gradient at world ``points`` (0 outside the deformed volume)."""
        dev, e = self.device, self.elements
        n = len(points)
        # a BVH of its own: a query leaves the contact state as the last step left it
        lowers = wp.empty(e.tet_count, dtype=wp.vec3, device=dev)
        uppers = wp.empty(e.tet_count, dtype=wp.vec3, device=dev)
        split_launch(k.tet_bounds_kernel, e.tet_count, [x, e.tets, e.volume], [lowers, uppers], dev, threads,
                     NODE_GRAIN)  # fmt: skip
        bvh = wp.Bvh(lowers, uppers)
        local = wp.array(points.astype(np.float32), dtype=wp.vec3, device=dev)
        pose = wp.array(np.array([[0, 0, 0, 0, 0, 0, 1]], np.float32), dtype=wp.transform, device=dev)
        zeros = wp.zeros(n, dtype=wp.int32, device=dev)
        world, query = wp.empty(n, dtype=wp.vec3, device=dev), wp.empty(n, dtype=wp.vec3, device=dev)
        cell, bary = wp.empty(n, dtype=wp.int32, device=dev), wp.empty(n, dtype=wp.vec4, device=dev)
        trees = wp.array(np.array([bvh.id, 0], dtype=np.uint64), dtype=wp.uint64, device=dev)
        split_launch(ck.locate_points_kernel, n,
                     [trees, wp.array(np.arange(e.tet_count, dtype=np.int32), dtype=wp.int32, device=dev), e.tet_count,
                      local, zeros, pose, wp.zeros(1, dtype=wp.int32, device=dev), x, e.rest, e.tets, e.volume, 0.0],
                     [world, query, cell, bary], dev, threads, _SAMPLE_GRAIN)  # fmt: skip
        values, gradients, _ = evaluate(self.model, query, threads=threads)
        split_launch(ck.map_gradients_kernel, n, [x, e.tets, e.dm_inv, cell], [values, gradients], dev, threads,
                     _SAMPLE_GRAIN)  # fmt: skip
        # host sync: results as numpy
        return values.numpy().copy(), gradients.numpy().reshape(n, 3).copy()
