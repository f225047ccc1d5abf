"""The ``warpblob simulate`` subcommand: a scene's tet mesh under gravity, written as a time-sampled USD stage.

``cli.py`` wires it in with ``add_simulate_parser(sub)`` (the parser) and
dispatches to :func:`run_simulate` through the parser's ``func`` default.
"""

from __future__ import annotations

import time

from .._errors import WarpblobError

__all__ = ["add_simulate_parser", "run_simulate"]

_SUFFIXES = (".usda", ".usdc", ".usd")


def add_simulate_parser(subparsers):
    """Add ``simulate SCENE --cellsize H --steps N --out FILE [options]`` to an argparse subparsers object."""
    p = subparsers.add_parser(
        "simulate",
        help="drop a scene under gravity (implicit co-rotational FEM) into a time-sampled UsdGeom.TetMesh and surface",
    )
    p.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    p.add_argument("--cellsize", type=float, required=True, help="tet lattice spacing at the boundary, model units")
    p.add_argument("--steps", type=int, required=True, help="number of time steps")
    p.add_argument("--out", required=True, help="output .usda/.usdc/.usd file")
    p.add_argument("--fix-below", type=float, default=None, metavar="Z", help="fix the nodes with z below Z")
    p.add_argument("--ground", type=float, default=None, metavar="Z", help="ground plane height (default: none)")
    p.add_argument("--friction", type=float, default=0.5, help="ground Coulomb friction coefficient (default 0.5)")
    p.add_argument("--dt", type=float, default=1.0 / 60.0, help="time step, seconds (default 1/60)")
    p.add_argument("--young", type=float, default=1e5, help="Young's modulus, Pa (default 1e5)")
    p.add_argument("--poisson", type=float, default=0.45, help="Poisson's ratio (default 0.45)")
    p.add_argument("--density", type=float, default=1000.0, help="density, kg/m^3 (default 1000)")
    p.add_argument("--every", type=int, default=1, help="record every N-th step (default 1)")
    p.add_argument("--surface-cellsize", type=float, default=None,
                   help="polygonization cell size of the embedded surface (default: cellsize / 2)")  # fmt: skip
    p.set_defaults(func=run_simulate)
    return p


def run_simulate(args) -> int:
    """Run the ``simulate`` subcommand; returns the exit code (errors are raised as WarpblobError)."""
    from ..io._scene import load_scene
    from ..polygonize import polygonize
    from ..tetrahedralize import tetrahedralize
    from ._simulation import Simulation

    if not str(args.out).lower().endswith(_SUFFIXES):
        raise WarpblobError(f"--out must be a .usda, .usdc or .usd file, got {args.out!r}")
    if args.steps < 1:
        raise WarpblobError(f"--steps must be a positive integer, got {args.steps}")
    if args.every < 1:
        raise WarpblobError(f"--every must be a positive integer, got {args.every}")
    device = getattr(args, "device", None)
    model = load_scene(args.scene)
    volume = tetrahedralize(model, cellsize=args.cellsize, device=device)
    surface = polygonize(model, cellsize=args.surface_cellsize or args.cellsize / 2, device=device)
    fixed = None if args.fix_below is None else volume.nodes[:, 2] < args.fix_below
    ground = None if args.ground is None else (args.ground, args.friction)
    sim = Simulation(volume, young=args.young, poisson=args.poisson, density=args.density, dt=args.dt, fixed=fixed,
                     ground=ground, device=device)  # fmt: skip
    sim.surface(surface)
    rest = sim.volume()
    start = time.perf_counter()
    try:
        sim.record(args.out, args.steps, every=args.every, progress=True)
    except OSError as exc:
        raise WarpblobError(str(exc)) from None
    seconds = time.perf_counter() - start
    frames = 1 + args.steps // args.every
    print(
        f"{sim.tet_count} tets, {sim.node_count} nodes ({len(sim.fixed)} fixed), {args.steps} steps of "
        f"{args.dt:.4g} s in {seconds:.2f} s ({sim.stats['cg_iterations_total'] / args.steps:.1f} CG iterations "
        f"per step), volume change {100 * (sim.volume() - rest) / rest:+.3f}%; wrote {args.out} ({frames} frames)"
    )
    return 0
