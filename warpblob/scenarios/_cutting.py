"""The scalpel showcase as a ready simulation: the tumor on the ground, cut three times, its pieces settling.

A :class:`~warpblob.tools.Scalpel` with its cutting edge upright (taller
than the tumor) is drawn straight across the tumor three times, one stroke
after another: two strokes along y, then one along x. Each stroke cuts when
it ends (``mode="on_release"``, the thesis' cutter, Shirazian 2014, chapter
6; :class:`~warpblob.cut._sim.Cutter`), so the pieces it severs become
independent bodies from the next step on and settle on the ground under
gravity. The cuts are vertical because the simulator has no contact between
pieces: a piece cut off the top would fall through the one below it.

Units as in :mod:`warpblob.scenarios._scenarios` (a model unit is a metre
for the SI constants).
"""

from __future__ import annotations

import numpy as np

from ..mesh import TetStructure
from ..scenes import tumor
from ..sim import Simulation
from ..tetrahedralize import tetrahedralize
from ..tools import Path, Scalpel
from ._scenarios import TUMOR_YOUNG, _check

__all__ = ["cut_tumor", "STROKE_STEPS", "SETTLE_STEPS"]

#: steps of 1/60 s per stroke, and the steps after the last one
STROKE_STEPS, SETTLE_STEPS = 24, 36
#: the tissues' Young's moduli over the probe's (:data:`~warpblob.scenarios._scenarios.TUMOR_YOUNG`): at a
#: metre per model unit the 2 m tumor would slump under its own weight (rho g h / E near 1); 30x stiffer it
#: sags a few per cent
YOUNG_SCALE = 30.0
#: where the strokes pass, as fractions of the tumor's box: (axis the blade travels along, position across)
STROKES = (("y", 0.36), ("y", 0.67), ("x", 0.52))


def cut_tumor(cellsize: float = 0.2, *, poisson: float = 0.45, device=None, threads: int | None = None,
              **options) -> Simulation:  # fmt: skip
    """The tumor standing on the ground, cut by three upright scalpel strokes into (about) six pieces.

    The tumor is meshed at ``cellsize`` by isosurface stuffing and simulated
    on a :class:`~warpblob.mesh.TetStructure` (three tissues of 10, 30 and 60
    kPa times :data:`YOUNG_SCALE`, density 1000, gravity, the ground at its lowest point, no fixed
    node). Each stroke (:data:`STROKE_STEPS` steps) draws a scalpel (edge
    0.3 longer than the tumor is high, its tip below the ground) from 0.2
    outside the tumor's box to 0.2 beyond it; the third crosses the first two.
    Play ``3 * STROKE_STEPS + SETTLE_STEPS`` steps (:func:`~warpblob.scenarios.total_steps`).

    Args:
        cellsize: tet size, model units.
        poisson: Poisson's ratio.
        device, threads: as :class:`~warpblob.Simulation`.
        options: more :class:`~warpblob.Simulation` arguments.

    Returns:
        The simulation at time 0; ``sim.cutters`` are the three strokes.

    Example:
        >>> from warpblob.scenarios import cut_tumor, total_steps
        >>> sim = cut_tumor(0.4)
        >>> sim.step(total_steps(sim))
        >>> sim.stats["components"] > 3  # six where the tumor fills every cell of the three planes
        True
    """
    cellsize, _ = _check("cut_tumor", cellsize, 2)
    model = tumor()
    volume = tetrahedralize(model, cellsize=cellsize, device=device)
    nodes = volume.nodes.astype(np.float64)
    low, high = nodes.min(axis=0), nodes.max(axis=0)
    settings = {"damping": (4.0, 0.0), **options}
    young = {m: YOUNG_SCALE * e for m, e in TUMOR_YOUNG.items()}
    sim = Simulation(TetStructure.from_tetmesh(volume), young=young, poisson=poisson, density=1000.0,
                     ground=(float(low[2]), 0.8), model=model, device=device, threads=threads,
                     **settings)  # fmt: skip
    height = float(high[2] - low[2])
    blade = Scalpel(height + 0.3, 0.3)
    duration = STROKE_STEPS * sim.dt
    for k, (axis, where) in enumerate(STROKES):
        along, across = (1, 0) if axis == "y" else (0, 1)
        start, end = np.zeros(3), np.zeros(3)
        start[across] = end[across] = low[across] + where * (high[across] - low[across])
        start[along], end[along] = low[along] - 0.2, high[along] + 0.2
        start[2] = end[2] = low[2] - 0.1
        path = Path.line(start, end, duration, align=True, t0=k * duration)
        sim.add_tool(blade, path, cut=True, mode="on_release")
    sim.stats["scenario"] = {"name": "cut_tumor", "strokes": len(STROKES), "after": SETTLE_STEPS}
    return sim
