"""The thesis' tool-contact experiments as ready simulations (Shirazian 2014, chapter 6; SPEC section 5.2).

Three set-ups from the thesis' FEM chapter: a probe pushing the tumor down
from the top, three slabs pushed sideways with the green one fixed to a
wall, a cake on the ground compressed from above. Each function meshes the
reference model (:mod:`warpblob.scenes`) by isosurface stuffing, binds the
polygonized surface, adds the tool on its path and returns the
:class:`~warpblob.Simulation` at time 0; running ``steps`` steps plays the
experiment (the tool moves in over the first 60% of them and then holds, so
the tissue settles under it).

Units: the models are simulated at the size they are authored, one model
unit taken as one metre for the SI material constants (as ``warpblob
simulate`` does), so forces are in newtons and the recorded stages have
``metersPerUnit = 1``. At the models' nominal centimetre a 2 cm tumor at
60 steps per second is nearly static: its stiffness outweighs its mass by
about 1000x per step and CG needs about 20x the iterations (measured: 350
against 17 per step at cell size 0.25). The contact stiffness (N/m^3, per
unit tool area, :meth:`~warpblob.Simulation.add_tool`) defaults to
``200 E / size`` (``E`` the stiffest tissue, ``size`` the probe's side): the
probe face then stands about 200 times stiffer than the tissue under it.
The thesis' ``contact="nearest"`` reads the rest field, whose depth does not
fall as the tissue gives way: its force is a load, not a spring, and the
tissue yields until its elastic force balances ``s A depth``. It defaults to
``E / size``, the tissue's own scale; at the field contact's stiffness it
crushes the tumor (measured: -35% volume, inverted tets).
"""

from __future__ import annotations

import numpy as np

from .._errors import WarpblobError
from ..polygonize import polygonize
from ..scenes import cake, three_slabs, tumor
from ..sim import Simulation
from ..tetrahedralize import tetrahedralize
from ..tools import Path, Probe

__all__ = ["probe_tumor", "push_three_slabs", "press_cake", "CONTACT", "GREEN"]

#: the colour of the slab fixed to the wall in ``push_three_slabs``
GREEN = (0.2, 0.75, 0.3)
#: Young's moduli (Pa) of the tumor's three tones (materials sorted by colour), as in the volume tests
TUMOR_YOUNG = {0: 3e4, 1: 1e4, 2: 6e4}
#: fraction of the steps over which the tool moves in; it holds for the rest
PRESS = 0.6
#: default contact stiffness over (stiffest Young's modulus / probe side), per contact mode
STIFFNESS_RATIO = {"field": 200.0, "nearest": 1.0}


def _check(name: str, cellsize, steps) -> tuple[float, int]:
    number = isinstance(cellsize, (int, float, np.integer, np.floating)) and not isinstance(cellsize, bool)
    if not number or not np.isfinite(cellsize) or cellsize <= 0:
        raise WarpblobError(f"{name}: cellsize must be a positive number (model units, cm), got {cellsize!r}")
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 2:
        raise WarpblobError(f"{name}: steps must be an integer >= 2, got {steps!r}")
    return float(cellsize), int(steps)


def _simulation(model, volume, cellsize: float, **options) -> Simulation:
    """A simulation of ``volume`` (meshed from ``model``) with the polygonized surface (half the cell size) bound."""
    sim = Simulation(volume, model=model, density=1000.0, **options)
    sim.surface(polygonize(model, cellsize=0.5 * cellsize, device=options.get("device")))
    return sim


def _probe(sim: Simulation, size: float, path: Path, young: float, stiffness, kring: int, contact: str) -> None:
    # an unknown mode gets the field's ratio here and its error from add_tool
    s = STIFFNESS_RATIO.get(contact, STIFFNESS_RATIO["field"]) * young / size if stiffness is None else stiffness
    sim.add_tool(Probe(size), path, stiffness=s, kring=kring, contact=contact)


def _stroke(start, end, steps: int, dt: float, *, align: bool = False) -> Path:
    """A straight stroke over the first ``PRESS`` of ``steps`` steps of ``dt``, then a hold to the end."""
    duration = steps * dt
    line = Path.line(start, end, PRESS * duration, align=align)
    return Path([0.0, PRESS * duration, duration], [start, end, end], np.repeat(line.rotations[:1], 3, axis=0))


def probe_tumor(cellsize: float = 0.25, steps: int = 120, *, poisson: float = 0.45, contact: str = "field",
                stiffness: float | None = None, kring: int = 2, device=None, threads: int | None = None,
                **options) -> Simulation:  # fmt: skip
    """A cube probe pushes the tumor down from the top: the thesis' volume check under compression.

    The tumor (about 2.2 units across, three tissues of 10, 30 and 60 kPa)
    is held at its base (the nodes in the lowest 10% of its height) and
    carries no weight (a support under it, no gravity), so the probe is its
    only load. A probe of 35% of its width comes down over the highest point
    of the tumor from 0.1 above it and presses 6% of its height. The
    thesis reports a volume change under 1% at nu = 0.45 at every cell size.

    Args:
        cellsize: tet size at the boundary, model units.
        steps: steps of 1/60 s the experiment lasts (>= 2).
        poisson: Poisson's ratio.
        contact: ``"field"`` or the thesis' ``"nearest"`` (see :meth:`~warpblob.Simulation.add_tool`).
        stiffness: contact stiffness, N/m^3 (default ``200 E / size``, ``E / size`` for ``"nearest"``; see the module).
        kring: rings the contact force spreads over.
        device, threads: as :class:`~warpblob.Simulation`.
        options: more :class:`~warpblob.Simulation` arguments (``damping``, ``linear_solver``...).

    Returns:
        The simulation at time 0 (run ``sim.step(steps)``); ``sim.tools[0]`` is the probe.

    Raises:
        WarpblobError: a bad cellsize or steps; others as :class:`~warpblob.Simulation` and ``add_tool``.

    Example:
        >>> from warpblob.scenarios import probe_tumor
        >>> sim = probe_tumor(0.5, 30)
        >>> rest = sim.volume()
        >>> sim.step(30)
        >>> bool(sim.contact_force(0)[2] > 0), abs(sim.volume() - rest) / rest < 0.01
        (True, True)
    """
    cellsize, steps = _check("probe_tumor", cellsize, steps)
    model = tumor()
    volume = tetrahedralize(model, cellsize=cellsize, device=device)
    nodes = volume.nodes.astype(np.float64)
    low, high = nodes.min(axis=0), nodes.max(axis=0)
    size = high - low
    settings = {"damping": (4.0, 0.0), **options}
    sim = _simulation(model, volume, cellsize, young=TUMOR_YOUNG, poisson=poisson, gravity=(0.0, 0.0, 0.0),
                      fixed=nodes[:, 2] < low[2] + 0.1 * size[2], device=device, threads=threads,
                      **settings)  # fmt: skip
    top = nodes[np.argmax(nodes[:, 2])]
    path = _stroke((top[0], top[1], high[2] + 0.1), (top[0], top[1], high[2] - 0.06 * size[2]), steps, sim.dt)
    _probe(sim, 0.35 * float(size[:2].mean()), path, max(TUMOR_YOUNG.values()), stiffness, kring, contact)
    return sim


def push_three_slabs(cellsize: float = 0.2, steps: int = 120, *, poisson: float = 0.45, contact: str = "field",
                     stiffness: float | None = None, kring: int = 2, device=None, threads: int | None = None,
                     **options) -> Simulation:  # fmt: skip
    """Three slabs side by side pushed horizontally towards the green one, which is fixed to a wall.

    The slabs (0.9 x 2 x 0.4 skeletons, 20 kPa) lie on a frictionless table
    (no gravity); every node of the green slab's tets is fixed. A probe of
    side 1, travelling along -x face first, pushes the middle of the outer
    (blue) slab's end face 0.3 in: the blue and red slabs compress against
    the green one.

    Args:
        cellsize, steps, poisson, contact, stiffness, kring, device, threads, options: as :func:`probe_tumor`.

    Returns:
        The simulation at time 0; ``sim.tools[0]`` is the probe and
        ``sim.fixed`` the green slab's nodes.

    Example:
        >>> from warpblob.scenarios import push_three_slabs
        >>> sim = push_three_slabs(0.4, 6)
        >>> wall = sim.positions[sim.fixed]
        >>> sim.step(6)
        >>> bool((sim.positions[sim.fixed] == wall).all())
        True
    """
    cellsize, steps = _check("push_three_slabs", cellsize, steps)
    model = three_slabs()
    volume = tetrahedralize(model, cellsize=cellsize, device=device)
    colors = np.asarray(volume.stats["materials"], dtype=np.float64)
    green = int(np.argmin(np.linalg.norm(colors - np.asarray(GREEN), axis=1)))
    fixed = np.zeros(volume.node_count, dtype=bool)
    fixed[volume.tets[volume.material == green].ravel()] = True
    settings = {"damping": (4.0, 0.0), **options}
    young = 2e4
    sim = _simulation(model, volume, cellsize, young=young, poisson=poisson, gravity=(0.0, 0.0, 0.0), fixed=fixed,
                      device=device, threads=threads, **settings)  # fmt: skip
    nodes = volume.nodes.astype(np.float64)
    high = nodes.max(axis=0)
    middle = 0.5 * (nodes.min(axis=0) + high)
    start = (high[0] + 0.1, middle[1], middle[2])
    path = _stroke(start, (high[0] - 0.3, middle[1], middle[2]), steps, sim.dt, align=True)
    _probe(sim, 1.0, path, young, stiffness, kring, contact)
    return sim


def press_cake(cellsize: float = 0.4, steps: int = 120, *, poisson: float = 0.45, contact: str = "field",
               stiffness: float | None = None, kring: int = 2, device=None, threads: int | None = None,
               **options) -> Simulation:  # fmt: skip
    """The three-tier cake on the ground, compressed from above by a plate-sized probe.

    The cake (5.2 across, 3.3 tall: sponge 1 MPa, icing 0.5 MPa, stiff
    enough to stand under its weight at this size) stands under gravity on a
    frictional ground (the plane through its lowest node, Coulomb
    coefficient 0.5). A probe of side 2.6, wider than the top tier, comes
    down from 0.1 above the top and presses 0.4.

    Args:
        cellsize, steps, poisson, contact, stiffness, kring, device, threads, options: as :func:`probe_tumor`.

    Returns:
        The simulation at time 0; ``sim.ground`` is the floor, ``sim.tools[0]`` the probe.

    Example:
        >>> from warpblob.scenarios import press_cake
        >>> sim = press_cake(0.6, 6)
        >>> sim.step(6)
        >>> bool(sim.positions[:, 2].min() >= sim.ground[0] - 1e-6)
        True
    """
    cellsize, steps = _check("press_cake", cellsize, steps)
    model = cake()
    volume = tetrahedralize(model, cellsize=cellsize, device=device)
    nodes = volume.nodes.astype(np.float64)
    settings = {"damping": (4.0, 0.0), **options}
    young = {0: 1e6, 1: 5e5}
    sim = _simulation(model, volume, cellsize, young=young, poisson=poisson, ground=(float(nodes[:, 2].min()), 0.5),
                      device=device, threads=threads, **settings)  # fmt: skip
    high = nodes[:, 2].max()
    path = _stroke((0.0, 0.0, high + 0.1), (0.0, 0.0, high - 0.4), steps, sim.dt)
    _probe(sim, 2.6, path, max(young.values()), stiffness, kring, contact)
    return sim


#: the tool-contact scenarios by name
CONTACT = {"probe_tumor": probe_tumor, "push_three_slabs": push_three_slabs, "press_cake": press_cake}
