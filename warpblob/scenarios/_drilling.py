"""The thesis' drilling showcase as ready simulations: the eggshell drilled, the head's skull opened.

A trephine (:class:`~warpblob.tools.Drill`, a tube whose side wall cuts)
bores through a shell; the cut is made every step from the whole stroke so
far (:class:`~warpblob.cut._sim.Cutter`, ``mode="progressive"``): the tets
the bit ring stops in are partly cut (the progressive tables) and completed
by the next steps, so when the bit leaves the far side of the shell the plug
comes free as one closed piece and falls under gravity (Shirazian 2014,
chapter 6, the drill tool; SPEC section 6).

* :func:`drill_eggshell`: the eggshell (:func:`warpblob.scenes.eggshell`,
  0.18 thick) held by its top cap and drilled from below, straight up, so
  each plug drops out of its own hole onto the ground; ``holes=6`` is the
  thesis' stress test (one hole at the bottom, five around it).
* :func:`craniotomy`: the layered head (:func:`warpblob.scenes.head_materials`,
  one conforming mesh of skull, CSF, grey and white matter and ventricles),
  its skull rigid and anchored at the back of its base, drilled twice from
  above by drills that cut bone only (``materials={0}``, each cutting once
  its stroke is done, :data:`DRILL_MODE`): each bone plug
  comes free of the skull as a free rigid body, still resting on the CSF
  under it (the interface faces the drill did not cross stay joined). Then a
  scalpel cuts across the front of the head through every tissue, and the
  front falls away under gravity, showing the layers in its cut face.

Units as in :mod:`warpblob.scenarios._scenarios`: one model unit is one
metre for the SI constants. The shell is stiff (``young`` 1e8 Pa by default:
it barely sags under its own weight) and every step records the cut's
statistics (:func:`drill_steps`).
"""

from __future__ import annotations

import numpy as np

from .._errors import WarpblobError
from ..mesh import TetStructure
from ..scenes import HEAD_TISSUES, eggshell
from ..sim import Simulation
from ..tetrahedralize import tetrahedralize
from ..tools import Drill, Path
from ._scenarios import _check

__all__ = ["drill_eggshell", "craniotomy", "drill_steps", "total_steps", "HEAD_YOUNG", "HEAD_COLORS", "EGGSHELL_RADII", "HOLE_STEPS", "FALL_STEPS"]

#: the eggshell's outer and inner radii (model units; :func:`warpblob.scenes.eggshell`)
EGGSHELL_RADII = (1.362, 1.181)
#: steps of 1/60 s a hole takes to drill, and the steps the plugs then fall
HOLE_STEPS, FALL_STEPS = 30, 45
#: drill radius, wall segments, and how far it starts below and ends past the shell (model units)
DRILL_RADIUS, DRILL_SEGMENTS, APPROACH, OVERSHOOT = 0.16, 16, 0.08, 0.1


def _holes(holes: int) -> np.ndarray:
    """(holes, 2) the drill axes' (x, y): one near the bottom pole, the others on a ring around it."""
    centre = np.array([[0.013, -0.009]])  # off the lattice's symmetry planes
    if holes == 1:
        return centre
    angle = 2 * np.pi * np.arange(holes - 1) / (holes - 1) + 0.1
    ring = 0.62 * np.column_stack([np.cos(angle), np.sin(angle)])
    return np.concatenate([centre, ring + centre])


def drill_eggshell(cellsize: float = 0.12, *, holes: int = 1, rigid: bool = True, young: float = 1e8,
                   poisson: float = 0.3, segments: int = DRILL_SEGMENTS, device=None, threads: int | None = None,
                   **options) -> Simulation:  # fmt: skip
    """The eggshell held by its top cap, drilled straight up from below ``holes`` times, one hole after another.

    The shell (outer radius 1.362, 0.18 thick) is meshed by isosurface
    stuffing at ``cellsize`` (0.12: about 31K tets, the shell two to three
    tets thick; coarser than 0.14 the thin wall pinches, see
    :func:`warpblob.tetrahedralize`) and simulated on a
    :class:`~warpblob.mesh.TetStructure`, held by its nodes above ``z = 1.0``
    (anchors of the rigid shell, or fixed nodes of an elastic one), the
    ground at ``z = -1.9``. Eggshell is stiff (tens of GPa): by default it is
    rigid (every material id, :meth:`~warpblob.Simulation` ``rigid=``), as
    the thesis modelled bone, so each plug falls as a free rigid body; an
    elastic shell (``rigid=False``) at ``young`` makes the drill's small
    split tets stiff and light, and CG needs hundreds of iterations a step
    once the plug is free (measured at cell size 0.12). Each drill (radius 0.16, ``segments``
    wall quads) rises along z from 0.08 below the shell to 0.1 past its
    inside in :data:`HOLE_STEPS` steps; hole ``k`` starts when hole ``k - 1``
    ends. Run ``holes * HOLE_STEPS + FALL_STEPS`` steps to see every plug
    fall (:func:`total_steps`).

    Args:
        cellsize: tet size, model units.
        holes: holes to drill, 1 to 12 (6 is the thesis' stress test).
        rigid: the shell rigid (anchored at its top cap) rather than elastic.
        young, poisson: an elastic shell's Young's modulus (Pa) and Poisson's ratio.
        segments: the drill's wall quads (>= 3).
        device, threads: as :class:`~warpblob.Simulation`.
        options: more :class:`~warpblob.Simulation` arguments.

    Returns:
        The simulation at time 0; ``sim.cutters`` are the drills in order
        (each one's ``results`` are its steps' cuts, :func:`drill_steps`).

    Raises:
        WarpblobError: a bad cellsize or number of holes.

    Example:
        >>> from warpblob.scenarios import drill_eggshell, total_steps
        >>> sim = drill_eggshell(0.14)
        >>> sim.step(total_steps(sim))
        >>> sim.stats["components"]  # the shell and its plug
        2
    """
    cellsize, _ = _check("drill_eggshell", cellsize, 2)
    if isinstance(holes, bool) or not isinstance(holes, (int, np.integer)) or not 1 <= holes <= 12:
        raise WarpblobError(f"drill_eggshell: holes must be an integer in [1, 12], got {holes!r}")
    volume = tetrahedralize(eggshell(), cellsize=cellsize, device=device)
    structure = TetStructure.from_tetmesh(volume)
    nodes = volume.nodes.astype(np.float64)
    settings = {"damping": (2.0, 0.0), **options}
    held = nodes[:, 2] > 1.0
    hold = {"rigid": set(np.unique(volume.material).tolist()), "anchors": held} if rigid else {"fixed": held}
    sim = Simulation(structure, young=young, poisson=poisson, density=1000.0, ground=(-1.9, 0.5), model=eggshell(),
                     device=device, threads=threads, **hold, **settings)  # fmt: skip
    outer, inner = EGGSHELL_RADII
    drill = Drill(DRILL_RADIUS, 0.6, segments=segments)
    duration = HOLE_STEPS * sim.dt
    for k, (x, y) in enumerate(_holes(int(holes))):
        near, far = max(float(np.hypot(x, y)) - DRILL_RADIUS, 0.0), float(np.hypot(x, y)) + DRILL_RADIUS
        start = -np.sqrt(outer**2 - near**2) - APPROACH  # below the shell's lowest point under the drill
        end = -np.sqrt(inner**2 - far**2) + OVERSHOOT  # past the inside's highest point under it
        path = Path.line((x, y, start), (x, y, end), duration, align=True, t0=k * duration)
        sim.add_tool(drill, path, cut=True, mode="progressive")
    sim.stats["scenario"] = {"name": "drill_eggshell", "holes": int(holes), "after": FALL_STEPS}
    return sim


#: Young's moduli (Pa) of the head's soft tissues by material id (:data:`warpblob.scenes.HEAD_MATERIALS`; the
#: skull, id 0, is rigid): stiff for brain, so that the 2 m model (a metre per model unit) does not slump
HEAD_YOUNG = {0: 1e9, 1: 1.5e5, 2: 4e5, 3: 6e5, 4: 1.5e5}
#: the head's tissue colours by material id (:data:`warpblob.scenes.HEAD_TISSUES`; the ventricles hold CSF)
HEAD_COLORS = dict(enumerate([*HEAD_TISSUES.values(), HEAD_TISSUES["cerebrospinal fluid"]]))
#: how the craniotomy's drills cut (:class:`~warpblob.cut._sim.Cutter`): once, when each stroke ends (the
#: thesis' cutter). Cutting every step leaves, on this skull about one cell thick, a few bone slivers of
#: 5-7 nodes beside the plugs as free bodies (measured at cell sizes 0.2-0.3); one stroke leaves none
DRILL_MODE = "on_release"
#: the craniotomy's drill sites (x, y) on the top of the skull, and the front cut's plane y
CRANIOTOMY_SITES, FRONT_CUT = ((0.35, 0.1), (-0.35, 0.3)), -0.55


def _surface_height(model, x: float, y: float, high: float) -> float:
    """The highest z <= ``high`` at which the vertical line through (x, y) is inside ``model`` (sampled)."""
    from ..field import field

    z = np.linspace(high, -high, 8001)
    values = np.asarray(field(model, np.column_stack([np.full_like(z, x), np.full_like(z, y), z])))
    return float(z[int(np.argmax(values >= 0.5))])


def craniotomy(cellsize: float = 0.2, *, cross_section: bool = True, young=None, poisson: float = 0.45,
               segments: int = DRILL_SEGMENTS, device=None, threads: int | None = None,
               **options) -> Simulation:  # fmt: skip
    """The layered head, its rigid skull drilled twice from above, then cut across the front (module docstring).

    The head is meshed by :func:`~warpblob.tetrahedralize` with
    ``materials=scenes.head_materials()`` at ``cellsize`` (0.2: about 50K
    tets, 14K of them skull, the skull about one cell thick on top; 0.118
    gives the thesis' 66K skull tets) and simulated on a
    :class:`~warpblob.mesh.TetStructure` under gravity with the skull
    (material 0) rigid and anchored by its nodes in the lowest 15% of the
    head's height behind its middle (``y > 0``). Drill ``k`` (radius 0.2,
    ``segments`` wall quads, ``materials={0}``) goes straight down at
    ``CRANIOTOMY_SITES[k]`` from 0.1 above the skull to a cell below its
    inner surface (the drill cuts bone only) in :data:`HOLE_STEPS` steps, one after the other; then,
    with ``cross_section``, an upright scalpel (edge taller than the head)
    crosses it along x at ``y = -0.55`` (:data:`FRONT_CUT`) in
    :data:`~warpblob.scenarios._cutting.STROKE_STEPS` steps and cuts every
    tissue there when its stroke ends.

    Args:
        cellsize: tet size, model units.
        cross_section: add the scalpel's front cut after the drilling.
        young: soft tissues' Young's moduli by material id (default :data:`HEAD_YOUNG`).
        poisson: Poisson's ratio.
        segments: the drills' wall quads.
        device, threads: as :class:`~warpblob.Simulation`.
        options: more :class:`~warpblob.Simulation` arguments.

    Returns:
        The simulation at time 0; ``sim.cutters`` are the two drills (and the scalpel).

    Example:
        >>> from warpblob.scenarios import craniotomy, total_steps
        >>> sim = craniotomy(0.3, cross_section=False)
        >>> sim.step(total_steps(sim))
        >>> sim.stats["rigid"]["free"]  # the two bone plugs
        2
    """
    from ..scenes import head_materials
    from ..tools import Scalpel
    from ._cutting import STROKE_STEPS

    cellsize, _ = _check("craniotomy", cellsize, 2)
    layers = head_materials()
    volume = tetrahedralize(layers["skull"], cellsize=cellsize, materials=layers, device=device)
    nodes = volume.nodes.astype(np.float64)
    low, high = nodes.min(axis=0), nodes.max(axis=0)
    skull_nodes = np.zeros(volume.node_count, dtype=bool)
    skull_nodes[volume.tets[volume.material == 0].ravel()] = True
    anchors = skull_nodes & (nodes[:, 2] < low[2] + 0.15 * (high[2] - low[2])) & (nodes[:, 1] > 0.0)
    settings = {"damping": (4.0, 0.0), **options}
    sim = Simulation(TetStructure.from_tetmesh(volume), young=HEAD_YOUNG if young is None else young,
                     poisson=poisson, density=1000.0, rigid={0}, anchors=anchors, model=layers["skull"],
                     device=device, threads=threads, **settings)  # fmt: skip
    drill = Drill(0.2, 0.6, segments=segments)
    duration = HOLE_STEPS * sim.dt
    for k, (x, y) in enumerate(CRANIOTOMY_SITES):
        top = _surface_height(layers["skull"], x, y, float(high[2]) + 0.5)
        inner = _surface_height(layers["cerebrospinal fluid"], x, y, float(high[2]) + 0.5)
        # on past the inner surface by a cell: the mesh's skull-CSF faces lie within about half a cell of it
        path = Path.line((x, y, top + 0.1), (x, y, inner - cellsize), duration, align=True, t0=k * duration)
        sim.add_tool(drill, path, cut=True, mode=DRILL_MODE, materials={0})
    if cross_section:
        t0 = len(CRANIOTOMY_SITES) * duration
        blade = Scalpel(float(high[2] - low[2]) + 0.4, 0.3)
        start = (float(low[0]) - 0.2, FRONT_CUT, float(low[2]) - 0.2)
        end = (float(high[0]) + 0.2, FRONT_CUT, float(low[2]) - 0.2)
        sim.add_tool(blade, Path.line(start, end, STROKE_STEPS * sim.dt, align=True, t0=t0), cut=True,
                     mode="on_release")  # fmt: skip
    sim.stats["scenario"] = {"name": "craniotomy", "holes": len(CRANIOTOMY_SITES), "cross_section": cross_section,
                             "after": FALL_STEPS}
    return sim


def total_steps(sim: Simulation) -> int:
    """Steps that play a cutting or drilling scenario to its end: every cutter's path, then the steps the
    scenario gives its pieces to fall (``sim.stats["scenario"]["after"]``: :data:`FALL_STEPS` for drilling,
    :data:`~warpblob.scenarios._cutting.SETTLE_STEPS` for the scalpel)."""
    last = max((c.path.t1 for c in sim.cutters), default=0.0)
    return int(round(last / sim.dt)) + int(sim.stats.get("scenario", {}).get("after", FALL_STEPS))


def drill_steps(sim: Simulation) -> list[dict]:
    """The statistics of every drill step so far: per step, the drill, its cut's counts and milliseconds by stage.

    Each row: ``drill`` (its index in ``sim.cutters``), ``step`` (the
    drill's own step), ``tets_cut`` (tets a table entry split), ``tets_added``,
    ``tets_removed``, ``components`` and ``ms`` (per stage of
    :func:`warpblob.cut.cut`, and ``total``).
    """
    rows = []
    for d, cutter in enumerate(sim.cutters):
        for i, r in enumerate(cutter.results):
            ms = {stage: 1e3 * s for stage, s in r.seconds.items()}
            ms["total"] = sum(ms.values())
            rows.append({"drill": d, "step": i, "tets_cut": r.split_cells, "tets_added": r.tets_added,
                         "tets_removed": r.tets_removed, "components": r.components, "ms": ms})  # fmt: skip
    return rows
