"""Cutting a tetrahedral mesh along a swept surface (SPEC section 6; Shirazian 2014, VolCut).

One call of :func:`cut`:

1. **intersection** (kernel, one thread per edge): the edges of the cells
   near the sweep (found in the structure's grid of rest boxes, grown by how
   far the nodes moved; every live edge where that would be most of the
   mesh) at their current positions against the sweep triangles found by a
   ``wp.Bvh``
   (a sweep of a few triangles, a plane or one stroke step, tests each
   triangle's box in turn: the same candidates without the tree),
   Moller-Trumbore; an edge keeps its first hit (lowest triangle, the
   earliest sample of the stroke). Hit edges are compacted (on CUDA by
   ``wp.utils.array_scan``, on the CPU by one pass over the flags).
2. **classification**: a hit within ``snap`` x edge length of an end makes
   that node a *cut node* (the sweep snaps to the node, which does not move:
   no volume is made or lost) and drops every edge at a cut node from the
   cut list; a kernel gives each tet its 6-bit cut-edge and 4-bit cut-node
   code. Codes the tables do not have (a sweep curved or folded inside one
   tet: three cut edges on a face, say), the progressive code with a cut node
   (``Xp``), and tets whose sub-tets would not all be positive at the actual
   split points (a kernel per changed tet: its table entry, rank
   permutation and every sub-tet's volume) are reduced: the cut edge whose hit is nearest an end snaps
   to that end, and the codes are recomputed (a few rounds at most; each
   round removes cut edges, and a code without cut edges is always valid).
   Between rounds, the cells round the nodes a round changed whose codes
   alone the tables lack snap by the same rule at once (a look-ahead: the
   snap at a blade's front most often makes the next front tet such a code);
   before a round classifies anything, the tets whose codes the tables lack
   snap the same way, from their corners (a scalpel's frame meets the tet
   ahead of the last frame's front with such a code: its classification
   would be a round the reduction repeats).
3. **subdivision** by the generated tables (:mod:`warpblob.cut._tables`):
   every cut edge gets two co-located nodes, one joined to each end (SPEC
   section 4); progressive tets get their crack-front points (cell centre,
   face centres). Cut nodes are duplicated where the blade separated their
   star: the sub-tet groups around a cut node are joined through every face
   at the node that the blade did not pass (a face with an uncut corner), a
   union-find over the node's star; each resulting set gets its own copy,
   so a node at the end of a partial cut, whose star stays connected, is not
   duplicated. A tet face whose three corners are all cut nodes lies on the
   sweep and separates its two tets. Kernels write the sub-tets (one flat
   list, tet by tet in table order) and list the faces at cut nodes; one
   thread pairs equal faces through a hash table and runs the union-find.
4. **topology**: one batch edit of the :class:`~warpblob.mesh.TetStructure`
   (:meth:`~warpblob.mesh.TetStructure.replace_cells`: deferred removal,
   faces and edges found or made in vectorized passes), then
5. **gc**: the pieces (a flood from the new cells and their kept
   neighbours until at most one label can grow, else a count over every
   cell), and
   :meth:`~warpblob.mesh.TetStructure.collect_garbage` (optional).

Everything is validated before the structure changes: a cut that raises
leaves it as it was.

Progressive cuts (beyond the thesis, after Bielser, Glardon, Teschner &
Gross 2003 and Mor & Kanade 2000): a blade that stops inside a tet leaves it
with 1-3 cut edges (C, D, E); the tables split it so that the swept faces
separate and the rest stays joined through the crack front (face and cell
centres). The tet's cut state is kept as a record (its corners, the split
points of its cut edges, its code, its front points;
``TetStructure.cell_parent`` names the record of each piece). A later
stroke cuts such a tet through its record: hits on its pieces' inner edges
are ignored, its nodes are not snapped onto, and when the stroke cuts more of
its own edges it is split again from the accumulated code with the same
split points, so a cut completed in two strokes has exactly the cells of the
same cut made in one (tested); front points shared by two such tets across
a face are reused.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .._device import resolve_device
from .._errors import CutError
from .._parallel import launch
from .._stages import column_bounds, compact, device_array, device_empty, host_array, rows_all, rows_any
from ..mesh._structure import (
    NODE_ORIGINS,
    TetStructure,
    _key_table,
    _shared,
    _unique_first,
    union_find_kernel,
    vec6i,
)
from ..mesh._tetmesh import TET_EDGES, TET_FACES
from . import _kernels as k
from ._sweep import SweepSurface
from ._tables import _RANK_LOOKUP, REF_CELL, REF_FACE, REF_NODE, cut_tables

__all__ = ["CutResult", "cut"]

STAGES = ("intersection", "classification", "subdivision", "topology", "gc")
#: reduction rounds before a cut gives up (each removes at least one cut edge per bad tet)
_ROUNDS = 64
#: bit weights of a tet's six edges and four corners (codes from (n, 6) and (n, 4) flags)
_BITS6, _BITS4 = 1 << np.arange(6), 1 << np.arange(4)
#: sweeps of at most this many triangles are intersected without a BVH (each triangle's box tested in turn)
_FEW_TRIANGLES = 16
#: sweep triangles up to which a sweep over most of the mesh (as many edges tested as nodes) takes each node's
#: sides once (``node_sides_kernel``): a plane's two, a few strips
_FEW_SIDES = 4
#: items per piece of a range-split launch of a kernel doing a few loads and stores per item (a piece is a
#: launch: smaller ones cost more in overhead than they save)
_CHEAP = 16384


@dataclass
class CutResult:
    """What one :func:`cut` did.

    Attributes:
        edges_cut: edges split (each into two co-located nodes).
        nodes_cut: nodes the sweep snapped to.
        tets_split: per table kind ("A", "B", "X", "Y", "C", "D", "E", "Z", "touch"), tets replaced.
        tets_removed, tets_added: cells removed and inserted.
        nodes_added: nodes inserted (split points, cut-node copies, crack fronts).
        components: connected pieces after the cut.
        seconds: per stage (:data:`STAGES`), wall clock.
        removed: (R,) int32 cells removed (indices before garbage collection).
        added: (C,) int32 new cells (indices before garbage collection).
        new_nodes: (K,) int32 nodes added (before garbage collection).
        node_sources: (K, 2) int32 the two nodes each new node lies between
            (the same node twice for a copy; the edge ends for a split point;
            for a crack-front point two corners of its face or cell).
        node_weights: (K,) float32 ``w``: the new node is ``(1 - w) a + w b`` of its sources
            (exact for split points and copies, the mean's weight for fronts).
        remap: per kind the old -> new index map of the garbage collection, or None.
        reductions: rounds the classification needed to make every code valid.
        split_cells, split_added: tets the cut split into several, and the sub-tets they became.
        cut_nodes: (Q,) int32 the nodes the sweep snapped to (before their copies were made).
    """

    edges_cut: int = 0
    nodes_cut: int = 0
    tets_split: dict = field(default_factory=dict)
    tets_removed: int = 0
    tets_added: int = 0
    nodes_added: int = 0
    components: int = 0
    seconds: dict = field(default_factory=dict)
    removed: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    added: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    new_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    node_sources: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int32))
    node_weights: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    remap: dict | None = None
    reductions: int = 0
    split_cells: int = 0
    split_added: int = 0
    cut_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))

    @property
    def new_cells_per_cut_cell(self) -> float:
        """Sub-tets per tet the cut split (the thesis reports 3.6 on average).

        Counts the sub-tets of tets whose entry splits them (A, B, X, Y, C, D,
        E, and progressive records split again), not the intact tets that are
        only re-linked to a cut node's copy.
        """
        return self.split_added / self.split_cells if self.split_cells else 0.0

    def stroke_cut_nodes(self, previous=None) -> np.ndarray:
        """The cut nodes a stroke cut step by step carries on (``cut(..., cut_nodes=)`` of its next step):
        ``previous``, this cut's :attr:`cut_nodes` and the copies it made of them, as a sorted int64 array."""
        copies = self.new_nodes[self.node_sources[:, 0] == self.node_sources[:, 1]]
        kept = np.zeros(0, np.int64) if previous is None else np.asarray(previous, np.int64)
        return np.union1d(kept, np.concatenate([self.cut_nodes, copies]).astype(np.int64))

    def summary(self) -> dict:
        """The counts and seconds as plain numbers (for JSON)."""
        return {
            "edges_cut": self.edges_cut, "nodes_cut": self.nodes_cut, "tets_split": dict(self.tets_split),
            "tets_removed": self.tets_removed, "tets_added": self.tets_added, "nodes_added": self.nodes_added,
            "components": self.components, "reductions": self.reductions,
            "new_cells_per_cut_cell": self.new_cells_per_cut_cell, "seconds": dict(self.seconds),
        }  # fmt: skip


def _boxes(sweep: SweepSurface, device) -> tuple[tuple[wp.array, wp.array], wp.array]:
    """The sweep triangles' boxes (lowers, uppers: what the BVH is built on) and their corners."""
    tri = sweep.triangles
    low, high = column_bounds(tri.reshape(-1, 3))
    pad = 1e-6 * max(float(np.linalg.norm(high - low)), 1e-12)
    # (elementwise over the three corners: numpy's reduction along that short axis is several times slower)
    lowers = device_array(np.minimum(np.minimum(tri[:, 0], tri[:, 1]), tri[:, 2]) - pad, wp.vec3, device)
    uppers = device_array(np.maximum(np.maximum(tri[:, 0], tri[:, 1]), tri[:, 2]) + pad, wp.vec3, device)
    corners = device_array(tri.reshape(-1, 3).astype(np.float32), wp.vec3, device)
    return (lowers, uppers), corners


def _planes(sweep: SweepSurface, device) -> tuple[wp.array, wp.array]:
    """Per sweep triangle: its normal ``e1 x e2`` and the slack of the same-side test of
    ``intersect_edges_few_kernel`` (1e-4 |e1| |e2|), from the float32 corners the kernels read."""
    tri = sweep.triangles.astype(np.float32).astype(np.float64)
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    normals = np.cross(e1, e2).astype(np.float32)
    slack = (1e-4 * np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)).astype(np.float32)
    return device_array(normals, wp.vec3, device), device_array(slack, float, device)


#: per device, the empty ``sides`` of ``intersect_edges_few_kernel`` (its terms computed per edge), made once
_NO_SIDES: dict = {}


def _no_sides(device) -> wp.array:
    key = str(device)
    if key not in _NO_SIDES:
        _NO_SIDES[key] = wp.empty((0, 0), dtype=wp.vec2, device=device)
    return _NO_SIDES[key]


def _compact(flags: wp.array, device, threads) -> np.ndarray:
    """Indices of the non-zero flags, ascending, on the host: on the CPU one pass over the flags' own memory;
    on CUDA an exclusive scan, then a kernel writes each at its place."""
    if flags.shape[0] == 0:
        return np.zeros(0, dtype=np.int32)
    if not device.is_cuda:
        return np.flatnonzero(flags.numpy() != 0).astype(np.int32)  # (a bool pass: 4x faster than on int32)
    return compact(flags, device, threads).numpy()


def cut(structure: TetStructure, sweep: SweepSurface, *, snap: float = 0.2, collect: bool = True,
        configuration: str = "current", node_limit: int | None = None, cut_nodes=None, materials=None,
        device=None, threads: int | None = None) -> CutResult:  # fmt: skip
    """Cut ``structure`` along ``sweep`` (module docstring); the structure is edited in place.

    Args:
        structure: the tet mesh (a :class:`~warpblob.mesh.TetStructure`); cut at its current positions.
        sweep: the blade's swept surface (:class:`SweepSurface`).
        snap: fraction of an edge's length within which a hit snaps to the
            nearer end, in [0, 0.5) (the thesis uses 0.2).
        collect: run the garbage collection after the edit (indices change; the
            maps are in ``result.remap``). A simulation keeps its indices with
            ``collect=False`` and compacts later.
        configuration: "current" (the sweep is where the nodes are now) or
            "rest" (the sweep is given in the rest frame: a cut defined in
            material coordinates, as a simulation's scalpel accumulates it).
        node_limit: intersect only edges between nodes below this index: a
            stroke re-applied whole (a simulation's progressive scalpel) then
            meets only the edges that were there when it began, not those its
            earlier steps made, and gives the cells of one stroke.
        cut_nodes: nodes that are cut nodes whatever the hits (the nodes the
            earlier steps of a stroke re-applied whole snapped to, and their
            copies: ``CutResult.cut_nodes``): their edges are not split
            again beside the sweep they already lie on (which would leave
            slivers between the snapped and the exact surface), and a front
            node the stroke has now passed is duplicated.
        materials: cut only tets of these material ids (an int or an iterable
            of ints; default: every tet). Tets of other materials, and their
            nodes, are left exactly as they were: an edge or node they share
            with a cut tet is split or duplicated for the cut tet only, so
            where the blade crossed an interface the cut tets' sub-tets no
            longer share its faces (those faces become boundary on both
            sides), and everywhere else the interface stays joined (the
            skull drilled, the tissue under it untouched).
        device: Warp device of the kernels (default: Warp's default).
        threads: CPU threads.

    Returns:
        A :class:`CutResult`.

    Raises:
        CutError: ``snap`` outside [0, 0.5), a sweep that is not a SweepSurface
            or has no triangles, a cut tet that is inverted or flat at rest,
            or a cut the reduction cannot make valid. Nothing has changed then.

    Example:
        >>> import warpblob as wb
        >>> s = wb.TetStructure.from_tetmesh(wb.mesh.box_tetmesh((0, 0, 0), (1, 1, 1), (3, 3, 3)))
        >>> r = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.5, 0.5, 0.5), (1, 1, 0), 2.0))
        >>> r.components, round(s.to_tetmesh().volume(), 6)
        (2, 1.0)
    """
    if not isinstance(structure, TetStructure):
        raise CutError(f"cut: structure must be a TetStructure, got {type(structure).__name__}")
    if not isinstance(sweep, SweepSurface):
        raise CutError(f"cut: sweep must be a SweepSurface, got {type(sweep).__name__}")
    if isinstance(snap, bool) or not isinstance(snap, (int, float, np.floating)) or not 0.0 <= float(snap) < 0.5:
        raise CutError(f"cut: snap must be a number in [0, 0.5), got {snap!r}")
    snap = float(snap)
    if configuration not in ("current", "rest"):
        raise CutError(f"cut: configuration must be 'current' or 'rest', got {configuration!r}")
    selected = _materials(materials)
    dev = resolve_device(device)
    result = CutResult(seconds=dict.fromkeys(STAGES, 0.0))
    if sweep.triangle_count == 0:
        result.components = structure._component_count()
        return result
    t_start = time.perf_counter()
    tables = cut_tables()

    # -- 1. intersection ------------------------------------------------------------------------
    edge_nodes_np = np.asarray(structure.edge_nodes)
    E, N, C = len(edge_nodes_np), len(structure.node_rest), len(structure.cell_nodes)
    positions_np = np.asarray(structure.node_position)
    boxes, corners = _boxes(sweep, dev)
    edge_nodes = _shared(edge_nodes_np, wp.vec2i, dev)
    # edges live cells use (a split edge stays alive, unused, until the garbage collection)
    cell_edges_wp = _shared(np.asarray(structure.cell_edges), vec6i, dev)
    cell_alive_np = np.asarray(structure.cell_alive).view(np.uint8)
    if selected is not None:  # only the chosen materials' cells take part (their edges, their codes)
        material = np.asarray(structure.cell_material)
        chosen = np.zeros(max(int(selected.max()), int(material.max()) if len(material) else 0) + 1, dtype=np.uint8)
        chosen[selected[selected >= 0]] = 1  # a lookup table: a gather, not isin's sort
        cell_alive_np = cell_alive_np & chosen[np.maximum(material, 0)] & (material >= 0).view(np.uint8)
    cell_alive_wp = _shared(cell_alive_np, wp.uint8, dev)
    frame = positions_np if configuration == "current" else np.asarray(structure.node_rest)
    positions = _shared(frame, wp.vec3, dev)
    sticky = None if cut_nodes is None else np.asarray(cut_nodes, dtype=np.int64).ravel()
    if sticky is not None and sticky.size and (sticky.min() < 0 or sticky.max() >= N):
        raise CutError(f"cut: cut_nodes must be node indices in [0, {N}), got {int(sticky.min())}.."
                       f"{int(sticky.max())}; the structure is unchanged")  # fmt: skip
    # a sweep meets only the cells near it: the edges of the cells whose boxes meet a triangle's (the
    # structure's grid of rest boxes, grown by how far the nodes moved), and later the cells whose boxes
    # hold a hit's end, instead of passes over every edge and cell (the same hits and cells: an edge's box
    # lies in its cells', a node in its cells')
    reach = np.zeros(3, np.float32)
    if configuration == "current" and len(structure.edge_nodes) >= _NEAR_SEARCH:
        rest_np = np.asarray(structure.node_rest)
        reach = np.array([np.abs(frame[:, i] - rest_np[:, i]).max() if N else 0.0 for i in range(3)], np.float32)
    near = _near_cells(structure, *[b.numpy() for b in boxes], cell_alive_np, reach)  # (triangle boxes as padded)
    if near is not None:
        mark = np.zeros(E, dtype=bool)  # (marks, not a sort)
        mark[np.asarray(structure.cell_edges)[near].ravel()] = True
        tested = np.flatnonzero(mark).astype(np.int32)
        if node_limit is not None:
            ends_t = edge_nodes_np[tested]
            tested = tested[np.maximum(ends_t[:, 0], ends_t[:, 1]) < int(node_limit)]
        tested_nodes = _shared(edge_nodes_np[tested], wp.vec2i, dev)
        edge_ok = wp.full(len(tested), 1, dtype=wp.uint8, device=dev)
    else:
        tested, tested_nodes = None, edge_nodes
        if selected is None and structure._edges_used:  # every edge slot is a live cell's (fresh or compacted)
            edge_ok = wp.full(E, 1, dtype=wp.uint8, device=dev)
        else:
            edge_ok = device_empty(E, wp.uint8, dev, zero=True)
            launch(k.mark_edges_in_use_kernel, C, [cell_edges_wp, cell_alive_wp], [edge_ok], dev, threads,
                   min_chunk=_CHEAP)  # fmt: skip
        if node_limit is not None:
            old = np.maximum(edge_nodes_np[:, 0], edge_nodes_np[:, 1]) < int(node_limit)  # (not .max(axis=1): 10x slower)
            edge_ok.assign(edge_ok.numpy() & old.view(np.uint8))
    T = len(tested) if tested is not None else E
    hit_t = device_empty(T, float, dev)
    hit_tri = device_empty(T, wp.int32, dev)
    flags = device_empty(T, wp.int32, dev)
    if len(boxes[0]) <= _FEW_TRIANGLES:  # a plane, a stroke step: the boxes themselves, no tree
        normals, slack = _planes(sweep, dev)
        sides = _no_sides(dev)
        # (for a plane's or a frame's two triangles, up to FEW_UNROLLED, the kernels with their loop unrolled)
        node_sides, intersect = k.FEW_KERNELS.get(len(boxes[0]), (k.node_sides_kernel, k.intersect_edges_few_kernel))
        if len(boxes[0]) <= _FEW_SIDES and T >= N:  # a sweep over most of the mesh: each node's sides once
            sides = wp.empty((N, len(boxes[0])), dtype=wp.vec2, device=dev)
            launch(node_sides, N, [positions, corners, normals], [sides], dev, threads, min_chunk=8192)
        launch(intersect, T, [tested_nodes, edge_ok, positions, *boxes, corners, normals, slack, sides],
               [hit_t, hit_tri, flags], dev, threads, min_chunk=8192)  # fmt: skip
    else:
        bvh = wp.Bvh(*boxes)
        launch(k.intersect_edges_kernel, T, [tested_nodes, edge_ok, positions, bvh.id, corners],
               [hit_t, hit_tri, flags], dev, threads, min_chunk=1024)  # fmt: skip
    hits = _compact(flags, dev, threads)
    t_hit = hit_t.numpy()[hits].astype(np.float64)
    if tested is not None:
        hits = tested[hits].astype(np.int32)  # (ascending: tested is)
    t1 = time.perf_counter()
    result.seconds["intersection"] = t1 - t_start

    # -- 2. classification ------------------------------------------------------------------------
    cell_nodes_np = np.asarray(structure.cell_nodes)
    cell_edges_np = np.asarray(structure.cell_edges)
    arrays = {"cell_nodes": _shared(cell_nodes_np, wp.vec4i, dev), "cell_edges": cell_edges_wp,
              "cell_alive": cell_alive_wp}  # fmt: skip
    rounds = 0
    state = _ParentState(structure, edge_nodes_np)
    sel = ~state.drop[hits]
    hits, t_hit = hits[sel], t_hit[sel]
    ends = edge_nodes_np[hits]
    node_cut = np.zeros(N, dtype=np.uint8)
    node_cut[ends[t_hit < snap, 0]] = 1
    node_cut[ends[t_hit > 1.0 - snap, 1]] = 1
    if sticky is not None:
        node_cut[sticky] = 1
    node_cut[state.protected] = 0
    dropped = np.zeros(len(hits), dtype=bool)
    # the cells that can get a code in any round: those at an end of a hit edge or at a given cut node (cut
    # nodes and the ends of cut edges are such nodes), found once (among the cells near those nodes, or by a
    # pass over every cell); each round codes only these
    at_hit = np.zeros(N, dtype=np.uint8)
    at_hit[ends.ravel()] = 1
    if sticky is not None:
        at_hit[sticky] = 1
    if near is not None:  # the cells whose boxes hold one of those nodes
        at = np.flatnonzero(at_hit)
        near = _near_cells(structure, frame[at], frame[at], cell_alive_np, reach)
    if near is not None:
        candidates = near[rows_any(at_hit[cell_nodes_np[near]])].astype(np.int32)
    else:
        flags_c = device_empty(C, wp.int32, dev)
        launch(k.cells_at_nodes_kernel, C, [arrays["cell_nodes"], arrays["cell_alive"],
               _shared(at_hit, wp.uint8, dev)], [flags_c], dev, threads, min_chunk=_CHEAP)  # fmt: skip
        candidates = _compact(flags_c, dev, threads)
    # their rows, gathered once: a round's codes read them in order (rows gathered from the whole mesh's
    # arrays each round would miss the cache on every one)
    rows_nodes, rows_edges = cell_nodes_np[candidates], cell_edges_np[candidates]
    candidate_rows = [_shared(rows_nodes, wp.vec4i, dev), _shared(rows_edges, vec6i, dev)]
    code_wp = device_empty(len(candidates), wp.int32, dev)
    # a cell's unit and its table entry depend on its code only (its corners, edges and their split points are
    # fixed within a cut): a round re-classifies the cells whose code changed, and the progressive parents
    M = len(candidates)
    own_c = state.record_of(candidates) < 0 if state.children.size else np.ones(M, dtype=bool)
    code_ok = _table_arrays(tables, dev)["code_ok"]
    stored_code = np.full(M, -1, dtype=np.int64)
    stored: dict = {}
    edge_cut = np.zeros(E, dtype=np.uint8)  # (written at the hit edges only, each round)
    hit_slots = _OnEdges(hits, E, -1.0)
    look = None  # (the look-ahead's arrays, wrapped when it first runs)

    def look_ahead(moved: np.ndarray) -> None:
        nonlocal look
        if look is None:
            look = _LookAhead(state, rows_nodes, rows_edges, own_c, code_ok, hits, t_hit, hit_slots.slots,
                              edge_nodes_np, node_cut, edge_cut, dropped)  # fmt: skip
        look.run(moved)

    looked = False  # (the codes were just settled by the look-ahead: classify them whatever they are)
    while True:
        keep = (node_cut[ends[:, 0]] == 0) & (node_cut[ends[:, 1]] == 0) & ~dropped
        edge_cut[hits] = keep
        split_t = hit_slots.at(np.where(keep, t_hit, -1.0))
        launch(k.cell_codes_kernel, M, [*candidate_rows, _shared(edge_cut, wp.uint8, dev),
               _shared(node_cut, wp.uint8, dev)], [code_wp], dev, threads, min_chunk=8192)  # fmt: skip
        codes = code_wp.numpy().astype(np.int64)
        # pieces of a progressive parent are cut through their parent
        changed = np.flatnonzero((codes != 0) & own_c)
        extra = _parent_units(state, edge_nodes_np, edge_cut, split_t, node_cut)
        # codes the tables lack are known from the codes alone: such tets snap by the round's rule (the
        # look-ahead from their corners) before any is classified, instead of a classification whose round
        # the reduction then repeats (a stroke's frames: the tet ahead of the last frame's front)
        if not looked:
            lacking = _lacking_corners(code_ok, codes[changed], rows_nodes[changed], extra)
            if lacking.size:
                look_ahead(lacking)
                looked = True
                continue
        looked = False
        stale = changed[stored_code[changed] != codes[changed]]
        fresh = _cell_units(candidates[stale], codes[stale], rows_nodes[stale], rows_edges[stale], edge_nodes_np,
                            split_t)  # fmt: skip
        rows = fresh if extra is None else {name: np.concatenate([fresh[name], extra[name]]) for name in fresh}
        rows.update(zip(_CLASSIFIED, _classify_units(tables, rows, structure.node_rest, dev, threads)))
        # the cells' units in candidate order, then the parents' (the first round: every coded cell's is new)
        if rounds:
            for name, a in rows.items():
                stored[name][stale] = a[: len(stale)]
            units = {name: np.concatenate([stored[name][changed], a[len(stale) :]]) for name, a in rows.items()}
        else:
            units = dict(rows)
        stored_code[stale] = codes[stale]
        entry, perm, rv, bad = (units.pop(name) for name in _CLASSIFIED)
        if np.any(rv <= 0):
            c0 = int(np.argmax(rv <= 0))
            raise CutError(f"cut: cell {int(units['cell'][c0])} is inverted or flat at rest (volume "
                           f"{float(rv[c0]):.3g}); the structure is unchanged")  # fmt: skip
        if not bad.any():
            break
        if not rounds:  # a second round: the first's units are kept, by candidate
            stored = {name: np.empty((M, *a.shape[1:]), dtype=a.dtype) for name, a in rows.items()}
            for name, a in rows.items():
                stored[name][stale] = a[: len(stale)]
        rounds += 1
        if rounds > _ROUNDS:
            raise CutError(f"cut: {int(bad.sum())} tets keep cut codes the tables cannot split after {_ROUNDS} "
                           f"reductions (first: cell {int(units['cell'][bad][0])}); the structure is "
                           "unchanged")  # fmt: skip
        moved = _reduce(units, bad, split_t, edge_nodes_np, node_cut, dropped, hits, state)
        # look-ahead on the codes alone: the cells and progressive records round the nodes this changed whose
        # codes the tables lack now (mostly a progressive code with a cut node: the next tet along the blade's
        # front, which the next round would snap the same way) snap by the same rule until none is left, so
        # that the next round (which also checks every sub-tet's shape) settles more than one tet of the front
        look_ahead(moved)
    result.reductions = rounds
    cut_edges = hits[keep]
    result.edges_cut, result.nodes_cut = len(cut_edges), int(node_cut.sum())
    result.cut_nodes = np.flatnonzero(node_cut).astype(np.int32)
    t2 = time.perf_counter()
    result.seconds["classification"] = t2 - t1

    # -- 3. subdivision ---------------------------------------------------------------------------------
    plan = _subdivide(structure, tables, state, units, entry, perm, cut_edges, split_t, node_cut, edge_nodes_np,
                      np.asarray(structure.node_rest), positions_np, dev, threads)  # fmt: skip
    per_kind = np.bincount(_table_arrays(tables, dev)["kind_np"][entry], minlength=len(_KIND_NAMES))
    result.tets_split = {kd: int(per_kind[_KIND_NAMES.index(kd)]) for kd in sorted(_KIND_NAMES)
                         if kd != "uncut" and per_kind[_KIND_NAMES.index(kd)]}  # fmt: skip
    t3 = time.perf_counter()
    result.seconds["subdivision"] = t3 - t2

    # -- 4. topology --------------------------------------------------------------------------------------
    node_count = len(structure.node_rest)
    pieces_before = structure._known_pieces()
    try:
        ids = [structure.insert_nodes(r, p, origin=NODE_ORIGINS[o]) for o, r, p in plan["nodes"]]
        structure._mark_origin(plan["separated"], NODE_ORIGINS["copy"])
        structure._mark_origin(plan["fronts"], NODE_ORIGINS["front"])
        added = structure.replace_cells(plan["remove"], plan["tets"], plan["material"], parent=plan["parent"])
    except Exception:
        structure._truncate_nodes(node_count)
        raise
    state.commit(plan)
    result.new_nodes = np.concatenate(ids) if ids else np.zeros(0, np.int32)
    result.node_sources, result.node_weights = plan["sources"], plan["weights"]
    result.split_cells, result.split_added = plan["split"]
    result.removed, result.added = plan["remove"].astype(np.int32), added
    result.tets_removed, result.tets_added, result.nodes_added = len(plan["remove"]), len(added), len(result.new_nodes)
    t4 = time.perf_counter()
    result.seconds["topology"] = t4 - t3

    # -- 5. garbage collection -------------------------------------------------------------------------
    # the pieces: a flood from the new cells and their kept neighbours (the small pieces cut off), else all
    result.components = structure._pieces_after(pieces_before, plan["remove"], added)
    if collect:
        result.remap = structure.collect_garbage()
    result.seconds["gc"] = time.perf_counter() - t4
    structure.stats["last_cut"] = result.summary()
    return result


#: edges from which a cut searches the cells near its sweep (below, passes over every edge and cell cost less)
_NEAR_SEARCH = 1 << 15


def _near_cells(structure, lower, upper, cell_alive, reach) -> np.ndarray | None:
    """The live (selected) cells whose rest boxes meet a box ``[lower[i] - reach, upper[i] + reach]``
    ((B, 3) each; ``reach`` (3,) the nodes' largest distance from rest, per axis: a cell's current box lies
    in its rest box grown by it), ascending, or None where a pass over every edge and cell is as cheap (a
    small mesh, boxes over much of it)."""
    if len(structure.edge_nodes) < _NEAR_SEARCH or not np.all(np.isfinite(reach)):
        return None
    near = structure._cells_near(np.asarray(lower) - reach, np.asarray(upper) + reach)
    return None if near is None else near[cell_alive[near] != 0]


#: what :func:`_classify_units` gives per unit, by name
_CLASSIFIED = ("entry", "perm", "rv", "bad")


def _materials(materials) -> np.ndarray | None:
    """The material ids a cut is restricted to, as a sorted int32 array (None: every material)."""
    if materials is None:
        return None
    values = [materials] if isinstance(materials, (int, np.integer)) else materials
    try:
        values = list(values)
    except TypeError:
        raise CutError(f"cut: materials must be an int or an iterable of ints, got {materials!r}") from None
    if not values or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in values):
        raise CutError(f"cut: materials must be a non-empty set of int material ids, got {materials!r}")
    return np.unique(np.asarray(values, dtype=np.int32))


#: table kinds by number (the kernels see numbers)
_KIND_NAMES = ("uncut", "touch", "Z", "A", "B", "X", "Y", "C", "D", "E", "Xp")
#: the progressive kinds' numbers (consecutive)
_PROGRESSIVE = np.array([_KIND_NAMES.index(k) for k in ("C", "D", "E")], dtype=np.int32)
_table_cache: dict = {}


def _table_arrays(tables, dev) -> dict:
    """The cut tables as flat int32 Warp arrays on ``dev`` (built once per device), and the kind numbers."""
    key = (id(tables), str(dev))
    if key not in _table_cache:
        kind = np.array([_KIND_NAMES.index(str(k)) for k in tables.kind], dtype=np.int32)
        flat = {
            "entry": tables.entry.astype(np.int32).ravel(), "count": tables.count.astype(np.int32).ravel(),
            "refs": tables.refs.astype(np.int32).ravel(), "kind": kind, "rank": _RANK_LOOKUP.astype(np.int32),
        }  # fmt: skip
        arrays = {name: device_array(v, wp.int32, dev) for name, v in flat.items()}
        arrays["kind_np"] = kind
        # per (edge code, node code) in a tet's own corner order: the tables split it (the same for every
        # order of the corners; the progressive code with a cut node counts as lacking)
        arrays["code_ok"] = (tables.entry >= 0) & (kind[np.maximum(tables.entry, 0)] != _KIND_NAMES.index("Xp"))
        _table_cache[key] = arrays
    return _table_cache[key]


def _classify_units(tables, units, rest, dev, threads) -> tuple:
    """Per unit (kernel): table entry (int64), rank permutation (int32), rest volume, bad entry (bool)."""
    n = len(units["corners"])
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0), np.zeros(0, bool)
    ta = _table_arrays(tables, dev)
    inputs = [
        _shared(np.ascontiguousarray(units["corners"], dtype=np.int32), wp.vec4i, dev),
        _shared(np.ascontiguousarray(units["edge_code"], dtype=np.int32), wp.int32, dev),
        _shared(np.ascontiguousarray(units["node_code"], dtype=np.int32), wp.int32, dev),
        _shared(np.ascontiguousarray(units["t"], dtype=np.float64).ravel(), wp.float64, dev),
        _shared(np.asarray(rest), wp.vec3, dev),
        ta["entry"], ta["count"], ta["refs"], ta["kind"], ta["rank"], _KIND_NAMES.index("Xp"),
    ]  # fmt: skip
    entry = device_empty(n, wp.int32, dev)
    perm = device_empty(n, wp.int32, dev)
    volume = device_empty(n, wp.float64, dev)
    bad = device_empty(n, wp.int32, dev)
    # one launch below 2048 units (a 10K-tet cut): waking the pool costs more than the second thread gives
    launch(k.classify_units_kernel, n, inputs, [entry, perm, volume, bad], dev, threads, min_chunk=1024)
    return entry.numpy().astype(np.int64), perm.numpy(), volume.numpy(), bad.numpy() != 0


def _lacking_corners(code_ok: np.ndarray, codes: np.ndarray, nodes: np.ndarray, parents: dict | None) -> np.ndarray:
    """The corners of the cells (``codes`` (c,), ``nodes`` (c, 4)) and progressive records (``parents``, the
    units of :func:`_parent_units`, or None) whose codes the tables lack (``code_ok`` (64, 16)), (k,) int."""
    lack = ((codes & 63) != 0) & ~code_ok[codes & 63, codes >> 6]  # (a cell with cut nodes only has nothing to snap)
    corners = [nodes[lack].ravel()]
    if parents is not None:
        lack = ~code_ok[parents["edge_code"], parents["node_code"]]
        corners.append(parents["corners"][lack].ravel())
    return np.concatenate(corners).astype(np.int64)


def _reduce(units: dict, bad: np.ndarray, split_t, edge_nodes: np.ndarray, node_cut: np.ndarray,
            dropped: np.ndarray, hits: np.ndarray, state: _ParentState) -> np.ndarray:
    """A round's reduction of its ``bad`` units, in place (``node_cut``, ``dropped``, the state's protected
    nodes); returns the nodes it changed, where the look-ahead starts.

    Each bad unit snaps its new cut edge nearest an end onto that end (:func:`_nearest_ends`), or, where
    that end may not be cut, drops the hit; a record left invalid by a cut node at a corner, with no new
    edge to snap, keeps its corners uncut. The nodes changed: the new cut nodes, both ends of each dropped
    hit and the corners kept uncut (the edges at them are cut again).
    """
    has, e_sel, target = _nearest_ends(units["new_edges"][bad], split_t, edge_nodes)
    stuck = (units["parent"][bad] >= 0) & ~has
    uncut = np.zeros(0, dtype=np.int64)
    if stuck.any():
        corners = units["corners"][bad][stuck].ravel()
        uncut = corners[node_cut[corners] != 0]
        node_cut[uncut] = 0
        state.is_protected[uncut] = True
        state.protected = np.union1d(state.protected, uncut)
    if not has.any() and not stuck.any():
        raise CutError(f"cut: cell {int(units['cell'][bad][0])} has no valid configuration (a bug); the "
                       "structure is unchanged")  # fmt: skip
    blocked = state.is_protected[target]
    node_cut[target[~blocked]] = 1
    dropped |= np.isin(hits, e_sel[blocked])
    return np.concatenate([target[~blocked], edge_nodes[e_sel[blocked]].ravel(), uncut])


def _nearest_ends(cand: np.ndarray, split_t, edge_nodes: np.ndarray) -> tuple:
    """The snap rule. Per row of ``cand`` ((b, 6) edges this cut cuts, -1 else; ``split_t`` their split
    parameters): whether it has one, and of the rows that do, the edge whose split point lies nearest an
    end and that end: ``(has (b,) bool, edges (h,), ends (h,))``."""
    st = np.where(cand >= 0, split_t[np.maximum(cand, 0)], -1.0)
    dist = np.where(cand >= 0, np.minimum(st, 1.0 - st), np.inf)
    j = np.argmin(dist, axis=1) if len(cand) else np.zeros(0, dtype=np.int64)
    has = np.isfinite(dist[np.arange(len(j)), j])
    edges = cand[np.arange(len(j)), j][has]
    t = split_t[edges]
    return has, edges, np.where(t < 0.5, edge_nodes[edges, 0], edge_nodes[edges, 1])


class _OnEdges:
    """Values on a cut's hit edges, ``fill`` on every other: indexed like an (E,) array (a gather at any shape
    of edge ids) without one filled per round. Made once per cut with the hits' slots (``slots``: (E,)
    int32, 1 + the hit's index, 0 elsewhere: zeroed pages are cheap, written only at the hits); each round
    takes its values (:meth:`at`)."""

    def __init__(self, edges: np.ndarray, count: int, fill: float):
        self.slots = np.zeros(count, dtype=np.int32)
        self.slots[edges] = np.arange(1, len(edges) + 1, dtype=np.int32)
        self.values, self.fill = np.zeros(0), fill

    def at(self, values: np.ndarray) -> _OnEdges:
        """This map with the hits' ``values`` ((hits,), in the order given)."""
        self.values = np.append(np.asarray(values, dtype=np.float64), self.fill)  # (slot 0: the fill)
        return self

    def __getitem__(self, index) -> np.ndarray:
        return self.values[self.slots[np.asarray(index)] - 1]


class _ParentState:
    """The progressive-cut records (tets a blade stopped in) this cut may continue.

    A parent's pieces are cut through the parent: hits on their edges other
    than the parent's own uncut edges are dropped (``drop``), none of their
    nodes may become a cut node (``protected``), and a parent whose uncut
    edges this stroke cuts is split again from its accumulated code, reusing
    its split points, so that a cut completed in two strokes has the topology
    of the same cut made in one.
    """

    def __init__(self, structure, edge_nodes: np.ndarray):
        self.structure = structure
        pr = structure._parents
        N, E = len(structure.node_rest), len(edge_nodes)
        self.drop = np.zeros(E, dtype=bool)
        self.is_protected = np.zeros(N, dtype=bool)
        self.protected = np.zeros(0, dtype=np.int64)
        self.edges = np.full((pr.count, 6), -1, dtype=np.int64)
        self.children = self.active = np.zeros(0, dtype=np.int64)
        self._rows = None
        self._live = pr["alive"].copy() if pr.count else np.zeros(0, dtype=bool)
        if self._live.any():
            # the pieces of live records (a piece of an ended record is an ordinary cell), from the structure's
            # index of pieces rather than a pass over every cell
            pieces = structure._cells_with_parent().astype(np.int64)
            pieces = pieces[np.asarray(structure.cell_alive)[pieces]]
            self.children = pieces[self._live[np.asarray(structure.cell_parent)[pieces]]]
            self.active = np.unique(np.asarray(structure.cell_parent)[self.children])
        if self.children.size:
            self.drop[np.asarray(structure.cell_edges)[self.children].ravel()] = True
            corners = pr["corners"][self.active]
            ge = structure.find_edges(corners[:, TET_EDGES].reshape(-1, 2), device="cpu").reshape(-1, 6)
            ge = np.where(pr["split"][self.active][:, :, 0] >= 0, -1, ge).astype(np.int64)
            self.drop[ge[ge >= 0]] = False
            self.edges[self.active] = ge
            # their inner nodes (split copies, front points) may not be snapped onto; their other corners
            # may: the record is then split again with that cut node. Nor may a corner on an edge the
            # record has cut (that edge would need un-cutting)
            self.is_protected[np.asarray(structure.cell_nodes)[self.children]] = True
            on_cut = np.zeros(corners.shape, dtype=bool)
            old_cut = pr["split"][self.active][:, :, 0] >= 0  # (a, 6)
            for j, (u, v) in enumerate(TET_EDGES):
                on_cut[:, u] |= old_cut[:, j]
                on_cut[:, v] |= old_cut[:, j]
            self.is_protected[corners] = False
            self.is_protected[corners[on_cut]] = True
            self.protected = np.flatnonzero(self.is_protected)

        # crack-front points on faces, by the face's corner triple: shared with the tet across the face
        live = np.flatnonzero(pr["alive"])
        fronts = pr["faces"][live]  # (P, 4)
        tri = pr["corners"][live][:, TET_FACES]  # (P, 4, 3)
        has = fronts >= 0
        self.key_base = N  # face keys of existing nodes
        self.front_keys = _triple_keys(tri[has], N)
        self.front_ids = fronts[has].astype(np.int64)
        order = np.argsort(self.front_keys)
        self.front_keys, self.front_ids = self.front_keys[order], self.front_ids[order]

    def active_rows(self) -> tuple:
        """The live records with pieces: corners (a, 4) int64, global edges (a, 6) (-1 where cut before) and
        accumulated edge codes (a,) int64, read once per cut."""
        if self._rows is None:
            pr = self.structure._parents
            self._rows = (pr["corners"][self.active].astype(np.int64), self.edges[self.active],
                          pr["code"][self.active].astype(np.int64))  # fmt: skip
        return self._rows

    def record_of(self, cells: np.ndarray) -> np.ndarray:
        """The live record each of ``cells`` is a piece of, -1 none."""
        cp = np.asarray(self.structure.cell_parent)[cells].astype(np.int64)
        return np.where((cp >= 0) & self._live[np.maximum(cp, 0)], cp, -1) if len(self._live) else np.full_like(cp, -1)

    def front_of(self, keys: np.ndarray) -> np.ndarray:
        """Existing crack-front node of each face key, -1 where none."""
        i = np.searchsorted(self.front_keys, keys)
        i = np.minimum(i, max(len(self.front_keys) - 1, 0))
        found = (len(self.front_keys) > 0) & (self.front_keys[i] == keys) if len(self.front_keys) else np.zeros(
            len(keys), bool)  # fmt: skip
        return np.where(found, self.front_ids[i] if len(self.front_ids) else -1, -1)

    def commit(self, plan: dict) -> None:
        """Write the records the cut made, changed and ended (after the topology edit succeeded)."""
        pr = self.structure._parents
        rec = plan["records"]
        pr.arrays["alive"][plan["ended"]] = False
        upd = rec["target"] >= 0
        for name in ("corners", "split", "t", "code", "faces", "centre"):
            pr.arrays[name][rec["target"][upd]] = rec[name][upd]
        fresh = ~upd
        if fresh.any():
            ids = pr.extend(int(fresh.sum()), **{name: rec[name][fresh] for name in
                                                 ("corners", "split", "t", "code", "faces", "centre")})  # fmt: skip
            assert np.array_equal(ids, plan["new_record_ids"])


class _LookAhead:
    """The classification's look-ahead between rounds (:func:`~warpblob.cut._kernels.look_ahead_kernel`, one
    thread on the CPU device whatever the cut's: a sequential pass over the host's arrays, which it edits in
    place): the tets round the nodes a round changed whose codes the tables lack snap by the snap rule, pass
    after pass, the cells cut on their own (``own``) on their codes and the live progressive records on
    their accumulated ones (the codes :func:`_parent_units` gives); a record with no edge cut now keeps its
    cut corners uncut, as the round would do. The arrays that stay fixed through a cut are wrapped once."""

    def __init__(self, state, rows_nodes, rows_edges, own, code_ok, hits, t_hit, hit_of, edge_nodes, node_cut,
                 edge_cut, dropped):  # fmt: skip
        cpu = wp.get_device("cpu")
        corners, ge, code = state.active_rows()
        self.state, self.node_cut = state, node_cut
        M, A = len(rows_nodes), len(corners)
        self.room = 2 * (M + A) + 4 * A
        self.fixed = [
            _shared(rows_nodes.astype(np.int32, copy=False), wp.vec4i, cpu),
            _shared(rows_edges.astype(np.int32, copy=False), vec6i, cpu),
            _shared(own.view(np.uint8), wp.uint8, cpu),
            _shared(corners.astype(np.int32).reshape(-1, 4), wp.vec4i, cpu),
            _shared(ge.astype(np.int32).reshape(-1, 6), vec6i, cpu),
            _shared(code.astype(np.int32), wp.int32, cpu),
            _shared(code_ok.view(np.uint8).ravel(), wp.uint8, cpu),
            _shared(hits.astype(np.int32, copy=False), wp.int32, cpu),
            _shared(t_hit, wp.float64, cpu),
            _shared(hit_of, wp.int32, cpu),
            _shared(edge_nodes, wp.vec2i, cpu),
            _ROUNDS,
        ]
        self.edited = [_shared(node_cut, wp.uint8, cpu), _shared(edge_cut, wp.uint8, cpu),
                       _shared(dropped.view(np.uint8), wp.uint8, cpu),
                       _shared(state.is_protected.view(np.uint8), wp.uint8, cpu)]  # fmt: skip
        self.chosen = device_empty(max(M + A, 1), wp.int32, cpu)
        self.stuck = device_empty(max(4 * A, 1), wp.int32, cpu)

    def run(self, moved: np.ndarray) -> None:
        """The look-ahead from the nodes ``moved`` (int) a round changed."""
        cpu = wp.get_device("cpu")
        mark = np.zeros(len(self.node_cut), dtype=np.uint8)
        mark[moved] = 1
        listed = np.zeros(max(self.room, len(moved), 1), dtype=np.int32)
        listed[: len(moved)] = moved
        count = np.array([len(moved), 0], dtype=np.int32)
        wp.launch(k.look_ahead_kernel, dim=1, device=cpu,
                  inputs=[*self.fixed, *self.edited, _shared(mark, wp.uint8, cpu), _shared(listed, wp.int32, cpu),
                          _shared(count, wp.int32, cpu), self.chosen, self.stuck])  # fmt: skip
        if count[1]:  # (corners kept uncut were protected)
            self.state.protected = np.flatnonzero(self.state.is_protected)


def _triple_keys(tri: np.ndarray, node_count: int) -> np.ndarray:
    t = np.sort(np.asarray(tri, dtype=np.int64).reshape(-1, 3), axis=1)
    n = max(int(node_count), 1) + 1
    return (t[:, 0] * n + t[:, 1]) * n + t[:, 2]


def _cell_units(cells, codes, nodes, edges, edge_nodes, split_t) -> dict:
    """The cells this cut changes as units (:func:`_parent_units`), given their codes, nodes and edges."""
    n = len(cells)
    cn, ce = nodes.astype(np.int64), edges.astype(np.int64)
    ecode = (codes & 63).astype(np.int64)
    bits = (ecode[:, None] >> np.arange(6)) & 1
    new_edges = np.where(bits == 1, ce, -1)
    # the split parameter from the cell's first corner of each cut edge (the others' stay -1)
    t = np.full(ce.shape, -1.0)
    cut_at = bits == 1
    e_cut = ce[cut_at]
    st = split_t[e_cut]
    forward = edge_nodes[e_cut, 0] == cn[:, TET_EDGES[:, 0]][cut_at]
    t[cut_at] = np.where(forward, st, 1.0 - st)
    return {
        "corners": cn, "edge_code": ecode, "node_code": (codes >> 6).astype(np.int64), "new_edges": new_edges,
        "old_split": np.full((n, 6, 2), -1, dtype=np.int64), "t": t, "parent": np.full(n, -1, dtype=np.int64),
        "cell": np.asarray(cells, dtype=np.int64),
    }  # fmt: skip


def _parent_units(state, edge_nodes, edge_cut, split_t, node_cut) -> dict | None:
    """The progressive parents whose own edges or corners this cut cuts, as units; None where there are none.

    A unit is a tet the cut changes (a whole cell, :func:`_cell_units`, or a parent). Its rows: corners
    (4 nodes), edge_code, node_code, new_edges (the global edge of each local edge this stroke cuts, -1
    else), old_split (split copies of edges cut before, -1 else), t (local split parameters), parent
    (record id, -1 for a cell), cell (the cell, -1 for a parent).
    """
    if not state.active.size:
        return None
    pr = state.structure._parents
    corners, ge, code = state.active_rows()
    cut_now = (ge >= 0) & (edge_cut[np.maximum(ge, 0)] == 1)
    corner_cut = node_cut[corners] != 0  # (a, 4)
    moved = rows_any(cut_now) | rows_any(corner_cut)
    if not moved.any():
        return None
    act, ge, cut_now, corner_cut = state.active[moved], ge[moved], cut_now[moved], corner_cut[moved]
    corners = corners[moved]
    old_split = pr["split"][act].astype(np.int64)
    old_t = pr["t"][act].astype(np.float64)
    code = code[moved] | cut_now @ _BITS6
    new_e = np.where(cut_now, ge, -1)
    forward = edge_nodes[np.maximum(ge, 0), 0] == corners[:, TET_EDGES[:, 0]]
    st_ = split_t[np.maximum(ge, 0)]
    t_par = np.where(cut_now, np.where(forward, st_, 1.0 - st_), old_t)
    return {
        "corners": corners, "edge_code": code, "node_code": corner_cut @ _BITS4,
        "new_edges": new_e,
        "old_split": old_split, "t": t_par, "parent": act.astype(np.int64), "cell": np.full(len(act), -1, np.int64),
    }  # fmt: skip


class _NewNodes:
    """New nodes in the order their ids are given: chunks of (origin, rest, position), with their sources."""

    def __init__(self, first_id: int, rest: np.ndarray, positions: np.ndarray):
        self.next_id = first_id
        self.rest, self.positions = rest, positions
        self.chunks: list[tuple[str, np.ndarray, np.ndarray]] = []
        self.sources: list[np.ndarray] = []
        self.weights: list[np.ndarray] = []

    def add(self, origin: str, a, b, w) -> np.ndarray:
        """Nodes at ``(1 - w) a + w b`` (rest and current); their ids."""
        a, b, w = np.asarray(a, np.int64), np.asarray(b, np.int64), np.asarray(w, np.float64)
        ra, rb = self.rest[a].astype(np.float64), self.rest[b].astype(np.float64)  # rest in float64
        r = ra + w[:, None] * (rb - ra)
        p = self.positions[a] + w[:, None] * (self.positions[b] - self.positions[a])
        return self._push(origin, r, p, np.stack([a, b], axis=1), w)

    def centres(self, corners: np.ndarray) -> np.ndarray:
        """Nodes at the mean of each row of ``corners`` ((M, 3) or (M, 4)); sources: its first two corners."""
        corners = np.asarray(corners, np.int64)
        w = np.full(len(corners), 1.0 / corners.shape[1])
        r, p = self.rest[corners].astype(np.float64).mean(axis=1), self.positions[corners].mean(axis=1)
        return self._push("front", r, p, corners[:, :2], w)

    def _push(self, origin, r, p, sources, w) -> np.ndarray:
        ids = np.arange(self.next_id, self.next_id + len(r), dtype=np.int64)
        self.next_id += len(r)
        if len(r):
            self.chunks.append((origin, r, p))
            self.sources.append(sources)
            self.weights.append(w)
        return ids


def _subdivide(structure, tables, state, units, entry, perm, cut_edges, split_t, node_cut, edge_nodes, rest,
               positions, dev, threads) -> dict:  # fmt: skip
    """New nodes, sub-tets and progressive records of the changed tets (module docstring, step 3).

    The sub-tets are one flat list, unit by unit in table order (a kernel writes their references and the
    nodes of their corners and split points); cut-node copies and crack fronts are filled in after.
    """
    cn = units["corners"]
    n = len(cn)
    ta = _table_arrays(tables, dev)
    counts = tables.count[entry, perm].astype(np.int64) if n else np.zeros(0, np.int64)
    new = _NewNodes(len(structure.node_rest), rest, positions)
    pr = structure._parents
    is_parent = units["parent"] >= 0

    # split points of this stroke: copy 0 joined to the edge's first node, copy 1 to its second
    cn32 = np.ascontiguousarray(cn, dtype=np.int32)
    cn_wp = _shared(cn32, wp.vec4i, dev)
    split_of = units["old_split"]  # (n, 6, 2) per unit and local edge, the copy joined to its local first / second end
    if len(cut_edges):
        a, b, t = edge_nodes[cut_edges, 0], edge_nodes[cut_edges, 1], split_t[cut_edges]
        ids0 = new.add("split", a, b, t)
        new.add("split", a, b, t)
        pos = np.empty(len(edge_nodes), dtype=np.int32)  # only read at the cut edges
        pos[cut_edges] = np.arange(len(cut_edges), dtype=np.int32)
        out = np.empty(12 * n, dtype=np.int32)
        launch(k.unit_splits_kernel, n,
               [cn_wp, device_array(np.ascontiguousarray(units["new_edges"], dtype=np.int32).ravel(), wp.int32, dev),
                _shared(np.ascontiguousarray(split_of, dtype=np.int32).ravel(), wp.int32, dev),
                _shared(edge_nodes, wp.vec2i, dev), _shared(pos, wp.int32, dev), int(ids0[0]), len(cut_edges)],
               [_out(out, wp.int32, dev)], dev, threads, min_chunk=4096)  # fmt: skip
        split_of = _back(out, dev).astype(np.int64).reshape(n, 6, 2)

    # the sub-tets (kernel): rows of unit u from first_row[u]
    total = int(counts.sum())
    first_row = np.zeros(n, dtype=np.int32)
    if n > 1:
        np.cumsum(counts[:-1], out=first_row[1:])
    unit_of = np.empty(total, dtype=np.int32)
    refs = np.empty(4 * total, dtype=np.int32)
    ids = np.empty(4 * total, dtype=np.int32)
    if n:
        launch(k.emit_subtets_kernel, n,
               [_shared(entry.astype(np.int32), wp.int32, dev),
                _shared(np.ascontiguousarray(perm, dtype=np.int32), wp.int32, dev), cn_wp,
                _shared(np.ascontiguousarray(split_of, dtype=np.int32).ravel(), wp.int32, dev),
                _shared(first_row, wp.int32, dev), ta["count"], ta["refs"]],
               [_out(unit_of, wp.int32, dev), _out(refs, wp.int32, dev), _out(ids, wp.int32, dev)], dev, threads,
               min_chunk=4096)  # fmt: skip
        unit_of, refs, ids = _back(unit_of, dev), _back(refs, dev).reshape(-1, 4), _back(ids, dev).reshape(-1, 4)
    else:
        refs, ids = refs.reshape(-1, 4), ids.reshape(-1, 4)
    ids = ids.astype(np.int64)
    kind = ta["kind_np"][entry] if n else np.zeros(0, np.int32)
    progressive = (kind >= _PROGRESSIVE[0]) & (kind <= _PROGRESSIVE[-1])

    # crack fronts: one per fanned face (shared with the tet across it: reused if it exists), one per cell
    face_front = np.full((n, 4), -1, dtype=np.int64)
    centre = np.full(n, -1, dtype=np.int64)
    if progressive.any():
        prog_rows = np.flatnonzero(progressive[unit_of])
        sub_refs = refs[prog_rows]
        m = (sub_refs >= REF_FACE) & (sub_refs < REF_CELL)
        if m.any():
            rr, cc = np.nonzero(m)
            f = sub_refs[rr, cc] - REF_FACE
            u = unit_of[prog_rows[rr]]
            tri = cn[u[:, None], TET_FACES[f]]
            keys = _triple_keys(tri, len(rest) + len(structure.node_rest))
            uniq, first, inv = np.unique(keys, return_index=True, return_inverse=True)
            found = state.front_of(uniq)
            need = found < 0
            if need.any():
                found[need] = new.centres(tri[first[need]])
            got = found[inv.ravel()]
            ids[prog_rows[rr], cc] = got
            face_front[u, f] = got
        m = sub_refs == REF_CELL
        if m.any():
            rr, cc = np.nonzero(m)
            u = unit_of[prog_rows[rr]]
            prog = np.unique(u)
            old = np.full(len(prog), -1, dtype=np.int64)
            back = is_parent[prog]
            old[back] = pr["centre"][units["parent"][prog][back]]
            need = old < 0
            if need.any():
                old[need] = new.centres(cn[prog[need]])
            centre[prog] = old
            ids[prog_rows[rr], cc] = centre[u]
    # cut nodes: one copy per set of sub-tet groups the blade separated
    separated = fronts = np.zeros(0, np.int64)
    node_rows = np.flatnonzero(rows_any((refs >= REF_NODE) & (refs < REF_FACE))) if total else np.zeros(0, int)
    if node_rows.size:
        separated, fronts = _cut_node_copies(structure, cn, node_rows, unit_of, refs, ids, new, dev, threads)

    # cells left exactly as they were (intact codes whose cut nodes kept their id) are not replaced
    same = ~is_parent & (counts == 1)
    one = np.flatnonzero(same).astype(np.int32)
    if one.size:
        flags = np.empty(len(one), dtype=np.uint8)
        launch(k.unchanged_kernel, len(one),
               [_shared(one, wp.int32, dev), _shared(first_row, wp.int32, dev),
                _shared(ids.astype(np.int32).ravel(), wp.int32, dev), cn_wp],
               [_out(flags, wp.uint8, dev)], dev, threads, min_chunk=8192)  # fmt: skip
        same[one] = _back(flags, dev) != 0
    replace = ~same
    # progressive units keep (or get) a record; parents that are no longer progressive end theirs
    fresh_rec = progressive & ~is_parent
    new_ids = np.arange(pr.count, pr.count + int(fresh_rec.sum()), dtype=np.int64)
    record = np.where(is_parent, units["parent"], -1)
    record[fresh_rec] = new_ids
    record[~progressive] = -1
    keep_rec = progressive
    records = {
        "target": np.where(is_parent, units["parent"], -1)[keep_rec],
        "corners": cn[keep_rec], "split": split_of[keep_rec], "t": units["t"][keep_rec],
        "code": units["edge_code"][keep_rec], "faces": face_front[keep_rec], "centre": centre[keep_rec],
    }  # fmt: skip
    # what goes: replaced cells, and every live piece of a parent split again
    parents_split = units["parent"][is_parent]
    children = np.zeros(0, np.int64)
    material_of = np.asarray(structure.cell_material)
    unit_material = np.where(is_parent, -1, material_of[np.maximum(units["cell"], 0)])
    if is_parent.any():
        children = state.children[np.isin(np.asarray(structure.cell_parent)[state.children], parents_split)]
        # a parent's material is its pieces' (all the same)
        of_record = np.zeros(pr.count, dtype=material_of.dtype)
        of_record[np.asarray(structure.cell_parent)[children]] = material_of[children]
        unit_material[is_parent] = of_record[parents_split]
    remove = np.concatenate([units["cell"][replace & ~is_parent], children]).astype(np.int64)
    counts_r = counts[replace]
    rows_r = replace[unit_of] if total else np.zeros(0, bool)
    return {
        "nodes": new.chunks,
        "separated": separated,
        "fronts": fronts,
        "remove": remove,
        "tets": ids[rows_r],
        "material": np.repeat(unit_material[replace], counts_r),
        "parent": np.repeat(record[replace], counts_r),
        "records": records,
        "new_record_ids": new_ids,
        "ended": parents_split[~progressive[is_parent]].astype(np.int64),
        "split": (int((counts_r > 1).sum()), int(counts_r[counts_r > 1].sum())),
        "sources": np.concatenate(new.sources).astype(np.int32) if new.sources else np.zeros((0, 2), np.int32),
        "weights": np.concatenate(new.weights).astype(np.float32) if new.weights else np.zeros(0, np.float32),
    }


def _out(values: np.ndarray, dtype, device) -> wp.array:
    """A kernel output array: ``values``' own memory on the CPU, a device array elsewhere (read back by _back)."""
    if device.is_cuda:
        return device_empty(len(values), dtype, device)
    return host_array(values, dtype)


def _back(arr: wp.array | np.ndarray, device) -> np.ndarray:
    return arr if isinstance(arr, np.ndarray) else arr.numpy()


def _cut_node_copies(structure, cn, node_rows, unit_of, refs, ids, new: _NewNodes, dev, threads) -> tuple:
    """Fill in the cut-node copies of the sub-tets ``node_rows`` (rows of ``ids``, in place); return the cut
    nodes the blade separated (duplicated) and those whose star stayed joined (crack fronts).

    Each (tet, corner, group) is a provisional copy. Two sub-tets (of any
    changed tets, partly cut records included) that share a face at a cut
    node join their copies of it; a face whose three corners are all cut
    nodes lies on the sweep and joins nothing (the blade passed there), and a
    face on the cut polygon holds split points of one side only, so it is
    shared by no sub-tet of the other side. Each connected set of a node's
    copies is one global copy, the first (lowest element) keeping the node's
    own id.

    Kernels: one thread per sub-tet lists its faces at cut nodes; one thread
    pairs equal faces through a hash table and joins their copies (a
    sequential union-find); slivers on the sweep are settled on the host.
    """
    n = len(cn)
    R = len(node_rows)
    cpu = dev
    key_base = int(max(int(ids.max()) if ids.size else 0, int(cn.max()) if n else 0)) + 1
    row_elem = np.empty(4 * R, dtype=np.int32)
    face_key = np.empty(4 * R, dtype=np.int64)
    face_elem = np.empty((4 * R, 3), dtype=np.int32)
    face_flag = np.empty(4 * R, dtype=np.int32)
    outs = [_out(row_elem, wp.int32, cpu), _out(face_key, wp.int64, cpu), _out(face_elem, wp.vec3i, cpu),
            _out(face_flag, wp.int32, cpu)]  # fmt: skip
    launch(k.subtet_faces_kernel, R,
           [_shared(node_rows.astype(np.int32), wp.int32, cpu),
            _shared(unit_of, wp.int32, cpu), _shared(refs.ravel(), wp.int32, cpu),
            _shared(ids.astype(np.int32).ravel(), wp.int32, cpu),
            _shared(np.ascontiguousarray(cn, dtype=np.int32), wp.vec4i, cpu), wp.int64(key_base)],
           outs, cpu, threads, min_chunk=2048)  # fmt: skip
    row_elem, face_key, face_elem, face_flag = (_back(a, cpu) for a in (outs[0], outs[1], outs[2], outs[3]))
    face_elem = face_elem.reshape(-1, 3)
    # pair equal faces, join copies off the sweep (one thread)
    parent = _shared(np.arange(n * 8, dtype=np.int32), wp.int32, cpu)
    sweep_pairs = device_empty(4 * R, wp.vec2i, cpu)
    sweep_count = device_empty(1, wp.int32, cpu, zero=True)
    with _key_table(4 * R, cpu) as (table, bits):  # (the batch edits' pooled table: no fresh pages each cut)
        wp.launch(k.pair_faces_kernel, dim=1, device=cpu,
                  inputs=[outs[1], outs[2], outs[3], bits, table, device_empty(4 * R, wp.int32, cpu), parent,
                          sweep_pairs, sweep_count])  # fmt: skip
    ns = int(sweep_count.numpy()[0])
    a = b = np.zeros(0, np.int32)
    if ns:
        pairs = sweep_pairs.numpy()[:ns]
        f1, f2 = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)
        # faces on the sweep: only each sliver's first shared one (by its own face number)
        sliver_of = rows_all(row_elem.reshape(-1, 4) >= 0)  # per sub-tet (all four corners cut-node copies)
        side_is_sliver = [sliver_of[f // 4] for f in (f1, f2)]
        owner = np.concatenate([f1[side_is_sliver[0]] // 4, f2[side_is_sliver[1]] // 4])
        rank = np.concatenate([f1[side_is_sliver[0]] % 4, f2[side_is_sliver[1]] % 4])
        which = np.concatenate([np.flatnonzero(side_is_sliver[0]), np.flatnonzero(side_is_sliver[1])])
        keep = np.zeros(ns, dtype=bool)
        if owner.size:
            o = np.lexsort((rank, owner))
            first = np.r_[True, owner[o][1:] != owner[o][:-1]]
            keep[which[o[first]]] = True
        f1, f2 = f1[keep], f2[keep]
        both = (face_elem[f1] >= 0) & (face_elem[f2] >= 0)
        a, b = face_elem[f1][both], face_elem[f2][both]
    # the remaining joins, and every item straight to its root (the lowest item of its set)
    wp.launch(union_find_kernel, dim=1, device=cpu,
              inputs=[_shared(np.ascontiguousarray(a, dtype=np.int32), wp.int32, cpu),
                      _shared(np.ascontiguousarray(b, dtype=np.int32), wp.int32, cpu), len(a),
                      parent])  # fmt: skip
    roots = parent.numpy()
    node_ref = row_elem >= 0
    used = np.zeros(n * 8, dtype=bool)
    used[row_elem[node_ref]] = True
    elem_ids = np.flatnonzero(used)
    is_root = np.zeros(n * 8, dtype=bool)
    is_root[elem_ids] = roots[elem_ids] == elem_ids
    dense = np.cumsum(is_root) - 1
    lab = dense[roots[elem_ids]]
    node = cn.reshape(-1)[elem_ids // 2]
    # per node, its distinct sets in order of their lowest element: the first keeps the id
    key = node.astype(np.int64) * (n * 8 + 1) + lab
    uniq, first, inv = _unique_first(key, len(key))
    set_node = node[first]
    order = np.lexsort((elem_ids[first], set_node))
    rank = np.empty(len(uniq), dtype=np.int64)
    sorted_nodes = set_node[order]
    starts = np.r_[True, sorted_nodes[1:] != sorted_nodes[:-1]] if len(order) else np.zeros(0, bool)
    run = np.cumsum(starts) - 1
    first_of_run = np.flatnonzero(starts)
    rank[order] = np.arange(len(order)) - first_of_run[run]
    target = set_node.astype(np.int64).copy()
    extra = rank > 0
    if extra.any():
        target[extra] = new.add("copy", set_node[extra], set_node[extra], np.zeros(int(extra.sum())))
    copy_of = np.full(n * 8, -1, dtype=np.int64)
    copy_of[elem_ids] = target[inv]
    # (the cut-node corners written through the flat view: a row gather and scatter of the sub-tets costs
    # numpy several times as long)
    ids.reshape(-1)[(4 * node_rows[:, None] + np.arange(4)).reshape(-1)[node_ref]] = copy_of[row_elem[node_ref]]
    separated = np.unique(set_node[extra])
    single = np.setdiff1d(np.unique(set_node), separated)
    origin = np.asarray(structure.node_origin)
    fronts = single[(origin[single] == 0) | (origin[single] == 3)]
    return separated, fronts
