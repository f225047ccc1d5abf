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

from .._errors import CutError, SimulationError
from ._cut import CutResult, cut
from ._sweep import SweepSurface

__all__ = ["apply_cut", "Cutter", "CUT_MODES"]

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
    if new.size:
        v_old = sim.velocities
        fixed_old = np.zeros(old_n, dtype=bool)
        fixed_old[sim.fixed] = True
        a, b = result.node_sources[:, 0].astype(np.int64), result.node_sources[:, 1].astype(np.int64)
        w = result.node_weights.astype(np.float64)[:, None]
        v_new[new - old_n] = (1.0 - w) * v_old[a] + w * v_old[b]
        fixed_new[new - old_n] = (a == b) & fixed_old[a]  # a copy of a fixed node stays fixed
    sim.rebuild(np.concatenate([result.removed, result.added]).astype(np.int64), new_velocities=v_new,
                new_fixed=fixed_new)  # fmt: skip
    sim.stats["components"] = result.components


class Cutter:
    """A cutting tool on its path in a simulation (:meth:`warpblob.Simulation.add_tool` with ``cut=True``).

    Args:
        tool: a :class:`~warpblob.tools.Scalpel` or :class:`~warpblob.tools.Drill`.
        path: its :class:`~warpblob.tools.Path`.
        mode: "on_release" (cut once at the path's end) or "progressive" (cut every step; see
            :meth:`warpblob.Simulation.add_tool` for its limits).
        snap: the cut's snapping fraction (:func:`~warpblob.cut.cut`).
        samples: blade samples per step for the swept strip (>= 1).

    Attributes:
        results: every :class:`~warpblob.cut.CutResult`, in order.
    """

    def __init__(self, tool, path, *, mode: str = "on_release", snap: float = 0.2, samples: int = 2):
        if mode not in CUT_MODES:
            raise CutError(f"cut mode must be one of {', '.join(CUT_MODES)}, got {mode!r}")
        if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
            raise CutError(f"samples must be a positive integer, got {samples!r}")
        self.tool, self.path, self.mode, self.snap, self.samples = tool, path, mode, float(snap), int(samples)
        self.results: list[CutResult] = []
        self._done = False
        self._triangles: list[np.ndarray] = []  # the stroke so far, in the rest frame
        self._node_limit: int | None = None  # nodes before the stroke: only their edges are cut

    def step(self, sim, t0: float, t1: float) -> CutResult | None:
        """Cut for the blade's motion from ``t0`` to ``t1`` (seconds); the result, or None when nothing was cut.

        The strip swept in ``[t0, t1]`` is carried back to the rest frame by
        the displacement of the nearest node (so the tissue may move while
        it is cut) and added to the stroke's rest-frame sweep, which is cut
        (in the rest frame) at the path's end, or every step in progressive
        mode.
        """
        if self._done or t1 <= self.path.t0:
            return None
        structure = sim._structure
        a, b = max(t0, self.path.t0), min(t1, self.path.t1)
        if b > a:
            x = np.asarray(sim.positions, dtype=np.float64)
            box = np.stack([x.min(axis=0), x.max(axis=0)])
            strip = SweepSurface.from_path(self.tool, self.path, a, b, (t1 - t0) / self.samples, bounds=box)
            if strip.triangle_count:
                self._triangles.append(_to_rest(strip.triangles, structure, sim))
        if t1 >= self.path.t1:
            self._done = True
        elif self.mode == "on_release":
            return None
        if not self._triangles:
            return None
        sweep = SweepSurface(np.concatenate(self._triangles))
        structure.set_positions(sim.positions)
        if self._node_limit is None:
            self._node_limit = len(structure.node_rest)
        result = cut(structure, sweep, snap=self.snap, collect=False, configuration="rest",
                     node_limit=self._node_limit, device=sim.device, threads=sim.threads)  # fmt: skip
        apply_cut(sim, result)
        self.results.append(result)
        return result


def _to_rest(triangles: np.ndarray, structure, sim) -> np.ndarray:
    """(M, 3, 3) world triangles carried to the rest frame by the nearest node's displacement (a hash grid)."""
    import warp as wp

    from .._parallel import launch
    from . import _kernels as k

    dev = sim.device
    x = np.asarray(sim.positions, dtype=np.float32)
    rest = np.asarray(structure.node_rest, dtype=np.float32)
    en = np.asarray(structure.edge_nodes)[np.asarray(structure.edge_alive)]
    edge = float(np.median(np.linalg.norm(rest[en[:, 0]] - rest[en[:, 1]], axis=1))) if len(en) else 1.0
    radius = 2.0 * edge
    pos = wp.array(x, dtype=wp.vec3, device=dev)
    grid = wp.HashGrid(64, 64, 64, device=dev)
    grid.build(pos, radius)
    pts = wp.array(triangles.reshape(-1, 3).astype(np.float32), dtype=wp.vec3, device=dev)
    out = wp.empty_like(pts)
    launch(k.to_rest_kernel, pts.shape[0], [grid.id, pts, pos, wp.array(rest, dtype=wp.vec3, device=dev), radius],
           [out], dev, sim.threads)  # fmt: skip
    return out.numpy().astype(np.float64).reshape(-1, 3, 3)
