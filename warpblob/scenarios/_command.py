"""The ``warpblob scenario`` subcommand: run a thesis experiment, write its USD stage and pictures.

``cli.py`` wires it in with ``add_scenario_parser(sub)`` (the parser) and
dispatches to :func:`run_scenario` through the parser's ``func`` default.
"""

from __future__ import annotations

import pathlib
import time

import numpy as np

from .._errors import WarpblobError

__all__ = ["add_scenario_parser", "run_scenario"]

#: per scenario: the default cell size (model units) and the camera direction of its pictures
_SETTINGS = {
    "probe_tumor": (0.25, (1.0, -1.6, 1.1)),
    "push_three_slabs": (0.2, (0.9, -1.5, 1.1)),
    "press_cake": (0.4, (1.0, -1.5, 0.9)),
    "cut_tumor": (0.2, (1.0, -1.5, 1.0)),
    "drill_eggshell": (0.12, (0.7, -1.0, -0.9)),
    "craniotomy": (0.2, (0.45, -1.4, 0.9)),
}
#: the scenarios that cut: their own arguments, pictures of the cut mesh and per-step cut statistics
_CUTTING = ("cut_tumor", "drill_eggshell", "craniotomy")


def add_scenario_parser(subparsers):
    """Add ``scenario NAME --out DIR [--cellsize H] [--steps N] [options]`` to an argparse subparsers object."""
    p = subparsers.add_parser(
        "scenario",
        help="run a thesis experiment (tool contact, scalpel cuts, drilling): an animated USD stage and PNG frames",
    )
    p.add_argument("name", choices=sorted(_SETTINGS), help="the experiment")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    p.add_argument("--cellsize", type=float, default=None, help="tet size at the boundary, model units "
                   "(default: 0.25 probe_tumor, 0.2 slabs, cut_tumor and craniotomy, 0.4 cake, 0.12 eggshell)")  # fmt: skip
    p.add_argument("--steps", type=int, default=None,
                   help="steps of 1/60 s (default 120; cutting and drilling: until every piece has fallen)")
    p.add_argument("--holes", type=int, default=1, help="drill_eggshell: holes to drill, 1-12 (default 1; 6 is "
                   "the thesis' stress test)")  # fmt: skip
    p.add_argument("--no-cross-section", action="store_true",
                   help="craniotomy: drill only (no scalpel cut across the front)")
    p.add_argument("--every", type=int, default=1, help="record every N-th step in the stage (default 1)")
    p.add_argument("--frames", type=int, default=8, help="PNG frames, evenly spaced, 0 for none (default 8)")
    p.add_argument("--contact", choices=("field", "nearest"), default="field",
                   help="contact through the deformed field (default) or the thesis' nearest node")  # fmt: skip
    p.add_argument("--poisson", type=float, default=None,
                   help="Poisson's ratio (default 0.45; the eggshell 0.3)")
    p.add_argument("--usdc", action="store_true", help="write the stage as .usdc (default .usda)")
    p.set_defaults(func=run_scenario)
    return p


def _wanted(frame_count: int, frames: int) -> set:
    """The indices of ``frames`` recorded frames, evenly spaced over ``frame_count``, to picture."""
    return set(np.linspace(0, frame_count - 1, frames).round().astype(int).tolist()) if frames else set()


def _record(sim, out: pathlib.Path, args, steps: int, on_frame, **options) -> tuple[pathlib.Path, float]:
    """Record ``steps`` steps of ``sim`` into ``out/NAME.usda|usdc``; the stage and the seconds it took."""
    stage = out / f"{args.name}.{'usdc' if args.usdc else 'usda'}"
    began = time.perf_counter()
    try:
        sim.record(stage, steps, every=args.every, progress=True, on_frame=on_frame, **options)
    except OSError as exc:
        raise WarpblobError(str(exc)) from None
    return stage, time.perf_counter() - began


def run_scenario(args) -> int:
    """Run the ``scenario`` subcommand; returns the exit code (errors are raised as WarpblobError)."""
    from . import ALL
    from ._frames import FrameCamera, render_frame

    if args.steps is not None and args.steps < 2:
        raise WarpblobError(f"--steps must be an integer >= 2, got {args.steps}")
    if args.every < 1:
        raise WarpblobError(f"--every must be a positive integer, got {args.every}")
    if args.frames < 0:
        raise WarpblobError(f"--frames must be >= 0, got {args.frames}")
    out = pathlib.Path(args.out)
    if out.exists() and not out.is_dir():
        raise WarpblobError(f"--out must be a folder, got the file {str(out)!r}")
    out.mkdir(parents=True, exist_ok=True)
    cellsize, direction = _SETTINGS[args.name]
    cellsize = cellsize if args.cellsize is None else args.cellsize
    device = getattr(args, "device", None)
    if args.name in _CUTTING:
        return _run_cutting(args, out, cellsize, direction, device)
    args.steps = 120 if args.steps is None else args.steps
    args.poisson = 0.45 if args.poisson is None else args.poisson
    sim = ALL[args.name](cellsize, args.steps, poisson=args.poisson, contact=args.contact, device=device)
    rest = sim.volume()
    start_nodes = sim.positions
    # the volume's box with room for the tool's working end around it
    low, high = start_nodes.min(axis=0), start_nodes.max(axis=0)
    camera = FrameCamera(low - 0.25 * (high - low), high + 0.25 * (high - low), direction)
    frame_count = 1 + args.steps // args.every
    wanted = _wanted(frame_count, args.frames)
    pictures = []
    peak = [0.0]

    def on_frame(index: int) -> None:
        force = float(np.linalg.norm(sim.contact_force(0)))
        peak[0] = max(peak[0], force)
        if index in wanted:
            change = 100.0 * (sim.volume() - rest) / rest
            title = f"{args.name}  t = {sim.time:.3f} s   contact force {force:.4g} N   volume {change:+.2f}%"
            pictures.append(render_frame(sim, str(out / f"{args.name}_{index:04d}.png"), camera, title=title))

    stage, seconds = _record(sim, out, args, args.steps, on_frame)
    x = sim.positions
    c = sim.stats["contact"]["seconds_total"]
    per_step = {name: 1e3 * value / args.steps for name, value in c.items()}
    print(
        f"{args.name}: {sim.tet_count} tets, {sim.node_count} nodes, {args.steps} steps of {sim.dt:.4g} s in "
        f"{seconds:.2f} s ({sim.stats['cg_iterations_total'] / args.steps:.1f} CG iterations per step); contact "
        f"{sum(per_step.values()):.2f} ms per step (locate {per_step['locate']:.2f}, field {per_step['field']:.2f}, "
        f"spread {per_step['spread']:.2f}); peak contact force {peak[0]:.4g} N; volume change "
        f"{100 * (sim.volume() - rest) / rest:+.3f}%; largest displacement {np.abs(x - start_nodes).max():.4g}; "
        f"wrote {stage} ({frame_count} frames) and {len(pictures)} PNG frames"
    )
    return 0


def _run_cutting(args, out: pathlib.Path, cellsize: float, direction, device) -> int:
    """A cutting scenario: the stage, pictures of the cut mesh, and ``NAME_steps.json`` (the cut of every step)."""
    import json

    from . import ALL, drill_steps, total_steps
    from ._drilling import HEAD_COLORS
    from ._frames import FrameCamera, render_cut_frame

    options = {"holes": args.holes} if args.name == "drill_eggshell" else {}
    if args.name == "craniotomy":
        options["cross_section"] = not args.no_cross_section
    if args.poisson is not None:
        options["poisson"] = args.poisson
    sim = ALL[args.name](cellsize, device=device, **options)
    steps = total_steps(sim) if args.steps is None else args.steps
    rest = sim.volume()
    start = sim.positions
    low, high = start.min(axis=0), start.max(axis=0)
    low[2] = min(low[2], sim.ground[0]) if sim.ground is not None else low[2]
    camera = FrameCamera(low - 0.1 * (high - low), high + 0.1 * (high - low), direction)
    frame_count = 1 + steps // args.every
    wanted = _wanted(frame_count, args.frames)
    pictures = []
    colors = HEAD_COLORS if args.name == "craniotomy" else None  # the layered head in its tissues' colours

    def on_frame(index: int) -> None:
        if index in wanted:
            pieces = sim.stats.get("components", 1)
            title = f"{args.name}  t = {sim.time:.3f} s   {sim.tet_count:,} tets   {pieces} piece(s)"
            png = str(out / f"{args.name}_{index:04d}.png")
            pictures.append(render_cut_frame(sim, png, camera, material_colors=colors, title=title))

    stage, seconds = _record(sim, out, args, steps, on_frame, material_colors=colors)
    rows = drill_steps(sim)  # every cut (a drill's steps, a scalpel's strokes)
    table = out / f"{args.name}_steps.json"
    tmp = table.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({"scenario": args.name, "cellsize": cellsize, "holes": args.holes, "steps": rows},
                              indent=1))  # fmt: skip
    tmp.replace(table)
    ms = np.array([r["ms"]["total"] for r in rows]) if rows else np.zeros(1)
    print(
        f"{args.name}: {sim.tet_count} tets, {sim.node_count} nodes after {steps} steps of {sim.dt:.4g} s in "
        f"{seconds:.2f} s; {len(rows)} cuts: {sum(r['tets_cut'] for r in rows)} tets cut, "
        f"{sum(r['tets_added'] for r in rows)} added, cut {np.median(ms):.1f} ms per step (median; largest "
        f"{ms.max():.1f}); {sim.stats.get('components', 1)} pieces; volume change "
        f"{100 * (sim.volume() - rest) / rest:+.3f}%; wrote {stage} ({frame_count} frames), {table.name} and "
        f"{len(pictures)} PNG frames"
    )
    return 0
