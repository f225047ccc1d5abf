"""The ``warpblob`` command line: ``demo``, ``info``, ``field``, ``polygonize``, ``tetrahedralize``, ``quality``,
``simulate``, ``scenario``, ``slice``, ``cut``."""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time

import numpy as np

from . import __version__
from ._errors import WarpblobError
from .io._scene import USD_SUFFIXES, load_scene

__all__ = ["main"]


#: what the mesh writers write (a .usdz package is read, never written)
_MESH_SUFFIXES = (".usda", ".usdc", ".usd")


def _info(model) -> dict:
    from ._linearize import linearize

    lm = linearize(model)
    lo, hi = lm.bounds
    return {
        "primitives": lm.primitive_count,
        "operators": lm.operator_count,
        "depth": lm.depth,
        "evaluation_nodes": lm.node_count,
        "registers": lm.registers,
        "bounds": [lo.round(4).tolist(), hi.round(4).tolist()],
        "nbytes": lm.nbytes,
        "bytes": lm.nbytes_by_part(),
    }


def _prepare_outputs(*outputs: tuple[str, str, tuple[str, ...] | None]) -> None:
    """Check every output path before any work, then make the folders they need.

    Each output is ``(path, option, suffixes)``: a file ending in one of
    ``suffixes``, or a folder when ``suffixes`` is None. The nearest existing
    folder above it must be writable; missing folders below it are created.

    Raises:
        WarpblobError: an unknown suffix, a file where a folder is wanted (or
            the other way round), or a folder that cannot be written; the
            message names the option and the path.
    """
    folders = []
    for path, option, suffixes in outputs:
        if suffixes is None:
            folder = os.path.abspath(path)
            if os.path.exists(folder) and not os.path.isdir(folder):
                raise WarpblobError(f"{option} {path!r} is a file, not a folder")
        else:
            if os.path.splitext(path)[1] not in suffixes:
                raise WarpblobError(f"{option} must be a {', '.join(suffixes)} file, got {path!r}")
            if os.path.isdir(path):
                raise WarpblobError(f"{option} {path!r} is a folder, not a file name")
            folder = os.path.dirname(os.path.abspath(path))
        existing = folder
        while not os.path.exists(existing):
            existing = os.path.dirname(existing)
        if not os.path.isdir(existing):
            raise WarpblobError(f"{option} {path!r}: {existing!r} is a file, so no folder can be made below it")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise WarpblobError(f"{option} {path!r}: folder {existing!r} is not writable")
        folders.append(folder)
    for folder in folders:
        os.makedirs(folder, exist_ok=True)


def _write_text(path: str, text: str) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def cmd_info(args) -> int:
    info = _info(load_scene(args.scene))
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for key, value in info.items():
            print(f"{key:>17}: {value}")
    return 0


def cmd_field(args) -> int:
    from .field import field

    out = args.out or os.path.splitext(args.points)[0] + "_field.npy"
    _prepare_outputs((out, "--out", (".npy",)))
    try:
        points = np.load(args.points, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise WarpblobError(f"cannot read points from {args.points!r}: {exc}") from None
    values = field(load_scene(args.scene), points, device=args.device)
    tmp = out + ".tmp.npy"
    np.save(tmp, values)
    os.replace(tmp, out)
    print(f"wrote {len(values)} field values to {out}")
    return 0


#: demo polygonization cell sizes (default 0.05). The head's layers are 0.023 apart at their
#: closest, so the head needs 0.02 or its layers merge through the gaps. The towers' floor plates
#: are thinner (0.09) than their 0.1 cells: resolving them would take 0.02 and about 12 million
#: triangles, so the demo keeps 0.1 and its summary shows the volume that costs
_DEMO_CELLSIZE = {"towers": 0.1, "medusa": 0.05, "head": 0.02}
#: points of each model's Monte Carlo volume estimate: a standard error near 0.1% of the box
_DEMO_SAMPLES = 1_000_000
#: ``--quick`` cell sizes: every model coarse (the head's layers merge at 0.05: its picture shows it)
_QUICK_CELLSIZE = {"head": 0.05, "towers": 0.12, "medusa": 0.1}


def _demo_model(name: str):
    """The model the demo shows as ``name``, its label, and how to picture it (options of ``render_mesh``)."""
    from . import scenes

    if name == "head":
        # cut open so that the layers show, and seen from the front right, where the cut faces look
        return scenes.head(cut_away=True), "head (cut away)", {"view": (1.0, -1.0, 0.8), "legend": scenes.HEAD_TISSUES}
    return scenes.ALL[name](), name, {}


def cmd_demo(args) -> int:
    from . import scenes
    from .field import monte_carlo_volume
    from ._progress import progress
    from ._render import render_mesh
    from ._slices import save_slices
    from .polygonize import polygonize

    if args.scene != "all" and args.scene not in scenes.ALL:
        raise WarpblobError(f"--scene must be all or a built-in scene ({', '.join(scenes.ALL)}), got {args.scene!r}")
    _prepare_outputs((args.out, "--out", None))
    start = time.perf_counter()
    names = list(scenes.ALL) if args.scene == "all" else [args.scene]
    if args.quick:  # a smoke run: coarse models, few points
        args.samples = min(args.samples, 20_000)
        args.resolution = min(args.resolution, 48)
    rng = np.random.default_rng(0)
    summary, meshes = {}, {}
    for name in progress(names, desc="demo"):
        model, label, picture = _demo_model(name)
        info = {"model": label, **_info(model)}
        estimate = monte_carlo_volume(model, samples=args.samples, rng=rng, device=args.device)
        info["points_per_second"] = round(args.samples / estimate.seconds)
        info["inside_fraction"] = round(estimate.inside_fraction, 6)
        info["volume_monte_carlo"] = {
            "samples": estimate.samples,
            "volume": round(estimate.volume, 6),
            "standard_error": round(estimate.standard_error, 6),
        }
        save_slices(model, os.path.join(args.out, f"{name}_slices.png"), name=name, resolution=args.resolution, device=args.device)
        h = args.cellsize or (_QUICK_CELLSIZE.get(name, 0.1) if args.quick else _DEMO_CELLSIZE.get(name, 0.05))
        t0 = time.perf_counter()
        mesh = polygonize(model, cellsize=h, device=args.device)
        shells = mesh.shell_count()
        info["polygonize"] = {
            "cellsize": h,
            "seconds": round(time.perf_counter() - t0, 4),
            "triangles": mesh.face_count,
            "vertices": mesh.vertex_count,
            "shells": shells,
            "closed_manifold": mesh.is_closed_manifold(),
            "area": round(mesh.area(), 5),
            "volume": round(mesh.volume(), 5),
        }
        title = f"{label}: {mesh.face_count:,} triangles, {shells} shell{'s' * (shells != 1)}, h = {h}"
        render_mesh(mesh, os.path.join(args.out, f"{name}_mesh.png"), title=title, **picture)
        info["pictures"] = [f"{name}_slices.png", f"{name}_mesh.png"]
        summary[name] = info
        meshes[name] = mesh
    models = dict(summary)
    scenarios = {}
    if args.scene == "all" and args.pipeline:
        from ._demo import run_pipeline

        pipeline = run_pipeline(args.out, quick=args.quick, device=args.device)
        scenarios = {name: os.path.join(args.out, file) for name, file in pipeline.pop("stages").items()}
        summary = {"models": models, "pipeline": pipeline}
    stage_path = _write_demo_stage(meshes, os.path.join(args.out, "warpblob_demo.usdc"), scenarios)
    _write_text(os.path.join(args.out, "summary.json"), json.dumps(summary, indent=2) + "\n")
    lines = _summary_lines(models, args.samples)
    if scenarios:
        lines += _pipeline_lines(summary["pipeline"])
    _write_text(os.path.join(args.out, "summary.txt"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(
        f"wrote {stage_path}, the pictures, summary.json and summary.txt to {args.out} "
        f"in {time.perf_counter() - start:.1f} s"
    )
    return 0


def _pipeline_lines(pipeline: dict) -> list[str]:
    """summary.txt: the pipeline's stages, one line each."""
    lines = ["", "pipeline (seconds: " + ", ".join(f"{k} {v:g}" for k, v in pipeline["seconds"].items()) + ")"]
    for name, t in pipeline["tetrahedralize"].items():
        lines.append(f"  tetrahedralize {name}: {t['tets']:,} tets at h = {t['cellsize']}, dihedral angles "
                     f"{t['dihedral_min']:.1f}-{t['dihedral_max']:.1f} deg, {t['seconds']:.2f} s")  # fmt: skip
    for name in ("probe_tumor", "cut_tumor", "drill_eggshell"):
        r = pipeline[name]
        cuts = r.get("cuts")
        extra = (f", {cuts['count']} cuts ({cuts['tets_cut']} tets cut, {cuts['cut_ms_median']} ms median)"
                 if cuts else "")  # fmt: skip
        lines.append(f"  {name}: {r['tets']:,} tets, {r['steps']} steps, {r['ms_per_step']} ms per step, "
                     f"{r['pieces']} piece(s), volume {r['volume_change_percent']:+.3f}%{extra}; {r['stage']}, "
                     f"{r['gif']}")  # fmt: skip
    sl = pipeline["slice"]
    lines.append(f"  slice mug: halves closed {sl['closed']}, {sl['section_loops']} section loop(s), "
                 f"{sl['slice_seconds']} s; {sl['picture']}")  # fmt: skip
    lines.append("  tet_quality.png: dihedral-angle and aspect-ratio histograms of the tet meshes")
    return lines


def _summary_lines(summary: dict, samples: int) -> list[str]:
    """summary.txt: one row per model, then what the columns mean."""
    lines = [
        f"{'model':<12}{'prims':>6}{'ops':>6}{'depth':>6}{'Mpts/s':>8}{'tris':>9}{'mesh s':>8}{'shells':>7}"
        f"{'closed':>8}{'mesh volume':>13}{'MC volume':>11}{'+- s.e.':>9}{'off/s.e.':>9}"
    ]
    notes = []
    for name, info in summary.items():
        poly, mc = info["polygonize"], info["volume_monte_carlo"]
        off = (poly["volume"] - mc["volume"]) / mc["standard_error"] if mc["standard_error"] else float("nan")
        lines.append(
            f"{name:<12}{info['primitives']:>6}{info['operators']:>6}{info['depth']:>6}"
            f"{info['points_per_second'] / 1e6:>8.2f}{poly['triangles']:>9}{poly['seconds']:>8.3f}{poly['shells']:>7}"
            f"{str(poly['closed_manifold']):>8}{poly['volume']:>13.4f}{mc['volume']:>11.4f}{mc['standard_error']:>9.4f}"
            f"{off:>+9.1f}"
        )
        if abs(off) > 3.0 and mc["volume"]:
            notes.append(
                f"{name}: the mesh's volume is {100.0 * (poly['volume'] / mc['volume'] - 1.0):+.1f}% off at cellsize "
                f"{poly['cellsize']}, more than 3 s.e.: the usual cause is features thinner than the cells "
                "(a finer --cellsize resolves them)"
            )
    lines += notes
    lines += [
        "shells: connected components of the mesh (a solid with k cavities has k + 1).",
        "closed: every edge in two faces, once each way, and one closed fan of faces around every vertex.",
        f"MC volume: {samples:,} points uniform in the model's box, inside where F >= 0.5, +- one standard error.",
        "off/s.e.: (mesh volume - MC volume) / s.e., within +-3 when the mesh encloses the model's volume.",
    ]
    return lines


def _write_demo_stage(meshes: dict, path: str, scenarios: dict | None = None) -> str:
    """One USD stage holding every demo mesh on a grid, and the recorded scenarios beside them, animated."""
    from ._demo import compose_stage

    return str(compose_stage(path, meshes, scenarios or {}))


def cmd_polygonize(args) -> int:
    from .io.usd import save_mesh
    from .polygonize import polygonize

    outputs = [(args.out, "--out", _MESH_SUFFIXES)]
    if args.png:
        outputs.append((args.png, "--png", (".png",)))
    _prepare_outputs(*outputs)
    model = load_scene(args.scene)
    mesh = polygonize(model, cellsize=args.cellsize, device=args.device, progress=True, relax=args.relax)
    try:
        save_mesh(mesh, args.out)
    except OSError as exc:
        raise WarpblobError(str(exc)) from None
    s = mesh.stats
    print(
        f"{mesh.face_count} triangles, {mesh.vertex_count} vertices, closed 2-manifold: {mesh.is_closed_manifold()}, "
        f"{s.get('total_seconds', 0.0):.3f} s, {s.get('field_evaluations', 0)} field evaluations; wrote {args.out}"
    )
    if args.png:
        from ._render import render_mesh

        render_mesh(mesh, args.png, title=f"{args.scene}: {mesh.face_count} triangles")
        print(f"wrote {args.png}")
    return 0


def cmd_tetrahedralize(args) -> int:
    from .io.usd import save_tetmesh
    from .tetrahedralize import tetrahedralize

    _prepare_outputs((args.out, "--out", _MESH_SUFFIXES))
    model = load_scene(args.scene)
    mesh = tetrahedralize(model, cellsize=args.cellsize, interior_cellsize=args.interior_cellsize, device=args.device, progress=True)
    try:
        save_tetmesh(mesh, args.out)
    except OSError as exc:
        raise WarpblobError(str(exc)) from None
    q = mesh.quality()
    print(
        f"{mesh.tets.shape[0]} tets, {mesh.nodes.shape[0]} nodes, dihedral angles "
        f"[{q.dihedral_min:.2f}, {q.dihedral_max:.2f}] deg; wrote {args.out}"
    )
    return 0


def cmd_quality(args) -> int:
    from .io._recorder import load_tetmesh_at
    from .mesh import format_quality

    mesh = load_tetmesh_at(args.file, prim_path=args.prim)
    print(format_quality(mesh.quality()))
    return 0


def cmd_view(args) -> int:
    from .io._movie import render_gif, view

    if args.gif:
        out = render_gif(args.file, args.gif, frames=args.frames, progress=True)
        print(f"wrote {out} and its frames in {out.with_name(out.stem + '_frames')}")
        return 0
    text = view(args.file, window=False if args.no_window else None)
    if text:
        print(text)
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="warpblob", description="BlobTree modelling of soft tissue on NVIDIA Warp.")
    p.add_argument("--version", action="version", version=f"warpblob {__version__}")
    p.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="the whole pipeline: models, meshes, tets, probe, cuts, drilling, slicing; "
                       "one animated USD stage, pictures, GIFs and a summary")  # fmt: skip
    d.add_argument("--out", default="out", help="output folder (default: out)")
    d.add_argument("--scene", default="all", help="one built-in scene, or all (default)")
    d.add_argument("--resolution", type=int, default=256, help="pixels per slice side (default 256)")
    d.add_argument("--cellsize", type=float, default=None, help="polygonization cell size (default: per model)")
    d.add_argument(
        "--samples", type=int, default=_DEMO_SAMPLES,
        help=f"points of each model's Monte Carlo volume estimate (default {_DEMO_SAMPLES:,})",
    )  # fmt: skip
    d.add_argument("--quick", action="store_true", help="small sizes and few frames: the whole pipeline in seconds")
    d.add_argument("--no-pipeline", dest="pipeline", action="store_false",
                   help="only the models (no tetrahedralization, probe, cuts, drilling or slicing)")
    d.set_defaults(func=cmd_demo)

    pg = sub.add_parser("polygonize", help="polygonize a scene into a watertight coloured UsdGeom.Mesh")
    pg.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    pg.add_argument("--cellsize", type=float, required=True, help="grid cell size, model units")
    pg.add_argument("--out", required=True, help="output .usda/.usdc/.usd file")
    pg.add_argument("--png", default=None, help="also render a picture to this PNG file")
    pg.add_argument(
        "--no-relax", dest="relax", action="store_false",
        help="keep every vertex on its grid edge (skip the relaxation of triangles under 10 degrees)",
    )  # fmt: skip
    pg.set_defaults(func=cmd_polygonize)

    tt = sub.add_parser("tetrahedralize", help="fill a scene with tetrahedra (isosurface stuffing) into a UsdGeom.TetMesh")
    tt.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    tt.add_argument("--cellsize", type=float, required=True, help="lattice spacing at the boundary, model units")
    tt.add_argument("--interior-cellsize", type=float, default=None, help="coarser interior spacing (graded meshes)")
    tt.add_argument("--out", required=True, help="output .usda/.usdc/.usd file")
    tt.set_defaults(func=cmd_tetrahedralize)

    qu = sub.add_parser("quality", help="quality report of a UsdGeom.TetMesh file")
    qu.add_argument("file", help="USD file holding a TetMesh")
    qu.add_argument("--prim", default=None, help="TetMesh prim path (default: the default prim)")
    qu.set_defaults(func=cmd_quality)

    vw = sub.add_parser("view", help="open a USD stage or mesh file in a PyVista window with a time slider")
    vw.add_argument("file", help=".usd/.usda/.usdc/.usdz stage or .stl/.obj/.ply/.vtk/.vtp/.vtu mesh")
    vw.add_argument("--no-window", action="store_true", help="print the summary and how to open it instead")
    vw.add_argument("--gif", default=None, help="render the stage off screen to this animated .gif (and PNG frames)")
    vw.add_argument("--frames", type=int, default=60, help="at most this many frames in the GIF")
    vw.set_defaults(func=cmd_view)

    i = sub.add_parser("info", help="counts, depth, box and bytes of a scene's linearized form")
    i.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    i.add_argument("--json", action="store_true", help="print JSON")
    i.set_defaults(func=cmd_info)

    f = sub.add_parser("field", help="field values of a scene at points from an (N, 3) .npy file")
    f.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    f.add_argument("--points", required=True, help="(N, 3) float .npy file")
    f.add_argument("--out", default=None, help="output .npy (default: POINTS_field.npy)")
    f.set_defaults(func=cmd_field)
    from .sim._command import add_simulate_parser

    add_simulate_parser(sub)
    from .scenarios._command import add_scenario_parser

    add_scenario_parser(sub)
    from .slice._command import add_slice_parser

    add_slice_parser(sub)
    from .cut._command import add_cut_parser

    add_cut_parser(sub)
    return p


def main(argv=None) -> int:
    """Entry point of the ``warpblob`` command; returns the exit code."""
    args = _parser().parse_args(argv)
    if getattr(args, "resolution", 64) < 8:
        print("warpblob: error: --resolution must be at least 8", file=sys.stderr)
        return 2
    if getattr(args, "samples", 2) < 2:
        print("warpblob: error: --samples must be at least 2", file=sys.stderr)
        return 2
    if argv is None:  # the process is the command: its imports are done; keep their objects (Warp's kernels'
        # syntax trees, about 220K) out of the garbage collections, which would stall a frame loop for 0.1-0.2 s
        # now and then (docs/sim.md); not when a program calls main() with its arguments: its objects are its own
        gc.freeze()
    try:
        return args.func(args)
    except WarpblobError as exc:
        print(f"warpblob: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
