"""Cutting a running simulation: the FEM data follow the topology, a scalpel cuts as it moves.

:func:`apply_cut` is what :meth:`warpblob.Simulation.apply_cut` runs after a
:func:`~warpblob.cut.cut` of the simulation's own
:class:`~warpblob.mesh.TetStructure`: element data (``Dm^-1``, volumes,
masses, incidence) are rebuilt for the removed and added tets only
(:meth:`warpblob.Simulation.rebuild`), new nodes take the velocity of the
points they were made at (split points interpolate their edge's ends,
copies take their node's), copies of fixed nodes stay fixed. Pieces the cut
separated share no node any more, so they are independent bodies of the
same system: a piece with no fixed node falls under gravity.

:class:`Cutter` drives a scalpel or drill along its path inside
:meth:`warpblob.Simulation.step`. The stroke is recorded in the rest frame
(each step's strip carried back by the local displacement, so the tissue may
move under the blade): ``mode="on_release"`` (the default, the thesis'
non-progressive cutter) cuts once when the path ends; ``mode="progressive"``
cuts every step with the whole stroke so far, meeting only the edges the
mesh had when the stroke began, with the tets earlier steps left partly cut
continued through their records (docs/cut.md gives how close it comes to
one stroke).
"""

from __future__ import annotations

import numpy as np

from .._device import resolve_device
from .._errors import CutError, SimulationError
from .._stages import column_bounds
from ._cut import CutResult, _materials, cut
from ._sweep import SweepSurface, cutting_edges

__all__ = ["apply_cut", "Cutter", "CUT_MODES", "warm_up"]

CUT_MODES = ("progressive", "on_release")


def apply_cut(sim, result: CutResult) -> None:
    """Rebuild ``sim``'s element data after ``result`` (a cut of ``sim``'s structure made with ``collect=False``).

    Raises:
        SimulationError: the simulation was not built on a TetStructure, or the
            cut compacted the structure (``collect=True`` renumbers every
            node: the simulation's state would no longer match).
    """
    structure = getattr(sim, "_structure", None)
    if structure is None:
        raise SimulationError("apply_cut: the simulation was built on a TetMesh; build it on the TetStructure you cut")
    if not isinstance(result, CutResult):
        raise SimulationError(f"apply_cut: result must be a CutResult, got {type(result).__name__}")
    if result.remap is not None:
        raise SimulationError("apply_cut: the cut ran the garbage collection (collect=True), which renumbers the "
                              "nodes; cut a simulated structure with collect=False")  # fmt: skip
    if not result.tets_removed and not result.tets_added:
        return
    old_n = sim.node_count
    new = result.new_nodes.astype(np.int64)
    if new.size and new.min() < old_n:
        raise SimulationError("apply_cut: the result's new nodes are older than the simulation (applied twice?)")
    grow = len(structure.node_rest) - old_n
    v_new = np.zeros((grow, 3))
    fixed_new = np.zeros(grow, dtype=bool)
    sources = np.full(grow, -1, dtype=np.int64)  # the old node each new one was made from (the coarse space's)
    if new.size:
        v_old = sim.velocities
        fixed_old = np.zeros(old_n, dtype=bool)
        fixed_old[sim.fixed] = True
        a, b = result.node_sources[:, 0].astype(np.int64), result.node_sources[:, 1].astype(np.int64)
        w = result.node_weights.astype(np.float64)[:, None]
        v_new[new - old_n] = (1.0 - w) * v_old[a] + w * v_old[b]
        fixed_new[new - old_n] = (a == b) & fixed_old[a]  # a copy of a fixed node stays fixed
        sources[new - old_n] = np.where(w[:, 0] < 0.5, a, b)  # a split point's nearer end, a copy's node
    sim.rebuild(np.concatenate([result.removed, result.added]).astype(np.int64), new_velocities=v_new,
                new_fixed=fixed_new, new_sources=None if (sources < 0).any() else sources)  # fmt: skip
    sim.stats["components"] = result.components


#: the devices :func:`warm_up` has run on in this process
_WARMED: set = set()


def warm_up(device=None, threads: int | None = None) -> bool:
    """Run the cutter's path once on a 48-tet box, once per process and device; True where it ran now.

    A cut's first frame in a process loads the cutter's Warp modules and the
    parts of numpy they call that numpy imports on first use: at 100K tets
    that first frame's cut took 38 ms against 9-12 for the next ones (2 cores).
    :meth:`warpblob.Simulation.add_tool` with ``cut=True`` calls this, so that
    the first frame a scalpel cuts is not the one that pays (0.05-0.2 s, at
    add_tool instead). It cuts a structure of its own, twice progressively in
    the rest frame as :class:`Cutter` does, and follows each cut in a
    simulation of that structure: nothing of the caller's is touched.

    Example:
        >>> import warpblob as wb
        >>> _ = wb.cut.warm_up()  # (True the first time in a process, on this device)
        >>> wb.cut.warm_up()
        False
    """
    from ..mesh import TetStructure, box_tetmesh
    from ..sim import Simulation

    key = str(resolve_device(device))
    if key in _WARMED:
        return False
    structure = TetStructure.from_tetmesh(box_tetmesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2)))
    sim = Simulation(structure, young=1e3, poisson=0.3, density=1000.0, device=device, threads=threads)
    _to_rest(np.full((2, 3), 0.5), structure, sim, _search_radius(structure))
    cut_nodes, limit = np.zeros(0, dtype=np.int64), len(structure.node_rest)
    for reach in (0.3, 0.7):  # a vertical blade stopped inside (progressive records), then on through them
        a = np.array([[0.3, -0.5, -0.5], [0.3, reach, -0.5]])
        sweep = SweepSurface.from_blade(a, a + (0.05, 0.0, 2.0))
        result = cut(structure, sweep, collect=False, configuration="rest", node_limit=limit, cut_nodes=cut_nodes,
                     device=device, threads=threads)  # fmt: skip
        cut_nodes = result.stroke_cut_nodes(cut_nodes)
        apply_cut(sim, result)
    _WARMED.add(key)
    return True


class Cutter:
    """A cutting tool on its path in a simulation (:meth:`warpblob.Simulation.add_tool` with ``cut=True``).

    Args:
        tool: a :class:`~warpblob.tools.Scalpel` or :class:`~warpblob.tools.Drill`.
        path: its :class:`~warpblob.tools.Path`.
        mode: "on_release" (cut once at the path's end) or "progressive" (cut every step; see
            :meth:`warpblob.Simulation.add_tool` for its limits).
        snap: the cut's snapping fraction (:func:`~warpblob.cut.cut`).
        samples: blade samples per step for the swept strip (>= 1).
        materials: cut only tets of these material ids (:func:`~warpblob.cut.cut`; default: every tet).

    Attributes:
        results: every :class:`~warpblob.cut.CutResult`, in order.
    """

    def __init__(self, tool, path, *, mode: str = "on_release", snap: float = 0.2, samples: int = 2,
                 materials=None):  # fmt: skip
        if mode not in CUT_MODES:
            raise CutError(f"cut mode must be one of {', '.join(CUT_MODES)}, got {mode!r}")
        if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
            raise CutError(f"samples must be a positive integer, got {samples!r}")
        self.tool, self.path, self.mode, self.snap, self.samples = tool, path, mode, float(snap), int(samples)
        self.materials = None if materials is None else _materials(materials)
        self.results: list[CutResult] = []
        self._done = False
        # the stroke so far in the rest frame: rows of cutting-edge end points, (S, 3) each, one per sample
        self._rows_a: list[np.ndarray] = []
        self._rows_b: list[np.ndarray] = []
        self._last = None  # time of the last sample taken (recorded or not)
        self._node_limit: int | None = None  # nodes before the stroke: only their edges are cut
        self._cut_nodes = np.zeros(0, dtype=np.int64)  # nodes the stroke snapped to so far, and their copies
        self._radius: float | None = None

    def step(self, sim, t0: float, t1: float) -> CutResult | None:
        """Cut for the blade's motion from ``t0`` to ``t1`` (seconds); the result, or None when nothing was cut.

        The blade's cutting edges, sampled ``samples`` times in ``[t0, t1]``,
        are carried back to the rest frame by the displacement of the nearest
        node (so the tissue may move while it is cut) and appended to the
        stroke's rest-frame samples; each sample is carried once, when it is
        taken, so the strips of consecutive steps share their edge and the
        stroke's sweep has no gaps however the tissue moves. Recording starts
        with the sample before the blade's box first meets the tissue's box
        grown by 5% of its diagonal (SPEC 6.1). The stroke is cut (in the rest
        frame) at the path's end, or every step in progressive mode.
        """
        if self._done or t1 <= self.path.t0:
            return None
        structure = sim._structure
        a, b = max(t0, self.path.t0), min(t1, self.path.t1)
        if b > a:
            times = np.append(np.arange(a, b, (t1 - t0) / self.samples), b)
            if self._last is not None:
                times = times[times > self._last + 1e-12]
            if len(times):
                self._record(sim, structure, times)
        if t1 >= self.path.t1:
            self._done = True
        elif self.mode == "on_release":
            return None
        if len(self._rows_a) < 2:
            return None
        sweep = SweepSurface.from_edges(np.stack(self._rows_a), np.stack(self._rows_b))
        structure.set_positions(sim.positions)
        if self._node_limit is None:
            self._node_limit = len(structure.node_rest)
        result = cut(structure, sweep, snap=self.snap, collect=False, configuration="rest",
                     node_limit=self._node_limit, cut_nodes=self._cut_nodes, materials=self.materials,
                     device=sim.device, threads=sim.threads)  # fmt: skip
        self._cut_nodes = result.stroke_cut_nodes(self._cut_nodes)
        apply_cut(sim, result)
        self.results.append(result)
        return result

    def _record(self, sim, structure, times: np.ndarray) -> None:
        """Take the samples at ``times`` (after every sample taken so far) into the stroke, in the rest frame."""
        started = bool(self._rows_a)
        if not started:
            x = np.asarray(sim.positions, dtype=np.float64)
            low, high = column_bounds(x)
            grow = 0.05 * float(np.linalg.norm(high - low))
            tb = self.tool.bounds(self.path.pose(times))
            meets = np.all((tb[:, 0] <= high + grow) & (tb[:, 1] >= low - grow), axis=1)
            if not meets.any():
                self._last = float(times[-1])
                return
            first = int(np.argmax(meets))
            before = times[first - 1] if first else self._last  # the sample before the first that meets
            times = times[first:] if before is None else np.append(before, times[first:])
        edges_a, edges_b = cutting_edges(self.tool, self.path.pose(times), first=not started)
        rows, strips = edges_a.shape[:2]
        if self._radius is None:  # the search radius of the rest-frame lookup, once per stroke
            self._radius = _search_radius(structure)
        points = np.concatenate([edges_a, edges_b]).reshape(-1, 3)
        rest = _to_rest(points, structure, sim, self._radius).reshape(2, rows, strips, 3)
        self._rows_a.extend(rest[0])
        self._rows_b.extend(rest[1])
        self._last = float(times[-1])


def _search_radius(structure) -> float:
    """Twice the median live edge length at rest: how far the rest-frame lookup looks for a node."""
    rest = np.asarray(structure.node_rest, dtype=np.float32)
    en = np.asarray(structure.edge_nodes)[np.asarray(structure.edge_alive)]
    return 2.0 * float(np.median(np.linalg.norm(rest[en[:, 0]] - rest[en[:, 1]], axis=1))) if len(en) else 2.0


def _to_rest(points: np.ndarray, structure, sim, radius: float) -> np.ndarray:
    """(K, 3) world points carried to the rest frame by the displacement of the nearest node within ``radius``
    (a hash grid)."""
    import warp as wp

    from .._parallel import launch
    from . import _kernels as k

    dev = sim.device
    x = np.asarray(sim.positions, dtype=np.float32)
    rest = np.asarray(structure.node_rest, dtype=np.float32)
    pos = wp.array(x, dtype=wp.vec3, device=dev)
    grid = wp.HashGrid(64, 64, 64, device=dev)
    grid.build(pos, radius)
    pts = wp.array(np.asarray(points, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=dev)
    out = wp.empty_like(pts)
    launch(k.to_rest_kernel, pts.shape[0], [grid.id, pts, pos, wp.array(rest, dtype=wp.vec3, device=dev), radius],
           [out], dev, sim.threads)  # fmt: skip
    return out.numpy().astype(np.float64)
