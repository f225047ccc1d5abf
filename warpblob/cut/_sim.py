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
:meth:`warpblob.Simulation.step`: ``mode="progressive"`` cuts every step
with the strip the blade swept during it; ``mode="on_release"`` records the
stroke and cuts once when the path ends (the thesis' non-progressive cutter).
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
    v_old = sim.velocities
    fixed_old = np.zeros(old_n, dtype=bool)
    fixed_old[sim.fixed] = True
    sim.rebuild(np.concatenate([result.removed, result.added]).astype(np.int64))
    new = result.new_nodes.astype(np.int64)
    if new.size:
        if new.min() < old_n:
            raise SimulationError("apply_cut: the result's new nodes are older than the simulation (applied twice?)")
        a, b = result.node_sources[:, 0].astype(np.int64), result.node_sources[:, 1].astype(np.int64)
        w = result.node_weights.astype(np.float64)[:, None]
        v = sim.velocities
        v[new] = (1.0 - w) * v_old[a] + w * v_old[b]
        sim.velocities = v
        copies = (a == b) & fixed_old[a]
        if copies.any():
            sim.fixed = np.concatenate([sim.fixed, new[copies]])
    sim.stats["components"] = result.components


class Cutter:
    """A cutting tool on its path in a simulation (:meth:`warpblob.Simulation.add_tool` with ``cut=True``).

    Args:
        tool: a :class:`~warpblob.tools.Scalpel` or :class:`~warpblob.tools.Drill`.
        path: its :class:`~warpblob.tools.Path`.
        mode: "progressive" (cut every step) or "on_release" (cut once at the path's end).
        snap: the cut's snapping fraction (:func:`~warpblob.cut.cut`).
        samples: blade samples per step for the swept strip (>= 1).

    Attributes:
        results: every :class:`~warpblob.cut.CutResult`, in order.
    """

    def __init__(self, tool, path, *, mode: str = "progressive", snap: float = 0.2, samples: int = 2):
        if mode not in CUT_MODES:
            raise CutError(f"cut mode must be one of {', '.join(CUT_MODES)}, got {mode!r}")
        if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
            raise CutError(f"samples must be a positive integer, got {samples!r}")
        self.tool, self.path, self.mode, self.snap, self.samples = tool, path, mode, float(snap), int(samples)
        self.results: list[CutResult] = []
        self._done = False

    def step(self, sim, t0: float, t1: float) -> CutResult | None:
        """Cut for the blade's motion from ``t0`` to ``t1`` (seconds); the result, or None when nothing was cut."""
        if self._done or t1 <= self.path.t0:
            return None
        structure = sim._structure
        if self.mode == "on_release":
            if t1 < self.path.t1:
                return None
            a, b = self.path.t0, self.path.t1
            self._done = True
            dt = min(sim.dt, (b - a) / 2)
        else:
            a, b = max(t0, self.path.t0), min(t1, self.path.t1)
            if b <= a:
                self._done = t0 >= self.path.t1
                return None
            dt = (b - a) / self.samples
        lo = np.asarray(structure.node_position).min(axis=0)
        hi = np.asarray(structure.node_position).max(axis=0)
        sweep = SweepSurface.from_path(self.tool, self.path, a, b, dt, bounds=np.stack([lo, hi]))
        if sweep.triangle_count == 0:
            return None
        structure.set_positions(sim.positions)
        result = cut(structure, sweep, snap=self.snap, collect=False, device=sim.device, threads=sim.threads)
        apply_cut(sim, result)
        self.results.append(result)
        return result
