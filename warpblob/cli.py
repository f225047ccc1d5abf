"""The ``warpblob`` command line: ``demo``, ``info``, ``field``, ``polygonize``, ``tetrahedralize``, ``quality``."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from . import __version__
from ._errors import WarpblobError

__all__ = ["main"]


_USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def _load(scene: str):
    """A built-in scene by name, or a model from a USD file."""
    from . import scenes

    if scene in scenes.ALL:
        return scenes.ALL[scene]()
    if scene.lower().endswith(_USD_SUFFIXES) or os.path.sep in scene:
        from .io.usd import load_model

        try:
            return load_model(scene)
        except FileNotFoundError:
            raise WarpblobError(f"scene file {scene!r} does not exist") from None
    names = ", ".join(scenes.ALL)
    raise WarpblobError(f"unknown scene {scene!r}; give a USD file or one of the built-in scenes: {names}")


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


def _write_text(path: str, text: str) -> None:
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def cmd_info(args) -> int:
    info = _info(_load(args.scene))
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        for key, value in info.items():
            print(f"{key:>17}: {value}")
    return 0


def cmd_field(args) -> int:
    from .field import field

    model = _load(args.scene)
    try:
        points = np.load(args.points, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise WarpblobError(f"cannot read points from {args.points!r}: {exc}") from None
    values = field(model, points, device=args.device)
    out = args.out or os.path.splitext(args.points)[0] + "_field.npy"
    tmp = out + ".tmp.npy"
    np.save(tmp, values)
    os.replace(tmp, out)
    print(f"wrote {len(values)} field values to {out}")
    return 0


# demo cell sizes: fine enough to look right, a fraction of a second each
_DEMO_CELLSIZE = {"towers": 0.1, "medusa": 0.05, "head": 0.06}


def cmd_demo(args) -> int:
    from . import scenes
    from ._progress import progress
    from ._render import render_mesh
    from ._slices import save_slices
    from .field import field
    from .polygonize import polygonize

    os.makedirs(args.out, exist_ok=True)
    names = list(scenes.ALL) if args.scene == "all" else [args.scene]
    rng = np.random.default_rng(0)
    summary, meshes = {}, {}
    for name in progress(names, desc="demo"):
        model = _load(name)
        info = _info(model)
        lo, hi = np.array(info["bounds"][0]), np.array(info["bounds"][1])
        pts = rng.uniform(lo, hi, (200_000, 3)).astype(np.float32)
        field(model, pts[:1000], device=args.device)  # compile / warm up
        t0 = time.perf_counter()
        values = field(model, pts, device=args.device)
        seconds = time.perf_counter() - t0
        info["points_per_second"] = round(len(pts) / seconds)
        info["inside_fraction"] = round(float(np.mean(values >= 0.5)), 4)
        save_slices(model, os.path.join(args.out, f"{name}_slices.png"), name=name, resolution=args.resolution, device=args.device)
        h = args.cellsize or _DEMO_CELLSIZE.get(name, 0.05)
        t0 = time.perf_counter()
        mesh = polygonize(model, cellsize=h, device=args.device)
        info["polygonize"] = {
            "cellsize": h,
            "seconds": round(time.perf_counter() - t0, 4),
            "triangles": mesh.face_count,
            "vertices": mesh.vertex_count,
            "closed_manifold": mesh.is_closed_manifold(),
            "area": round(mesh.area(), 5),
            "volume": round(mesh.volume(), 5),
        }
        render_mesh(mesh, os.path.join(args.out, f"{name}_mesh.png"), title=f"{name}: {mesh.face_count} triangles, h = {h}")
        info["pictures"] = [f"{name}_slices.png", f"{name}_mesh.png"]
        summary[name] = info
        meshes[name] = mesh
    stage_path = _write_demo_stage(meshes, os.path.join(args.out, "warpblob_demo.usdc"))
    _write_text(os.path.join(args.out, "summary.json"), json.dumps(summary, indent=2) + "\n")
    lines = [f"{'model':<12}{'prims':>7}{'ops':>7}{'depth':>6}{'Mpts/s':>9}{'tris':>10}{'mesh s':>9}  closed"]
    for name, info in summary.items():
        poly = info["polygonize"]
        lines.append(
            f"{name:<12}{info['primitives']:>7}{info['operators']:>7}{info['depth']:>6}"
            f"{info['points_per_second'] / 1e6:>9.2f}{poly['triangles']:>10}{poly['seconds']:>9.3f}  {poly['closed_manifold']}"
        )
    _write_text(os.path.join(args.out, "summary.txt"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {stage_path}, {2 * len(summary)} pictures, summary.json and summary.txt to {args.out}")
    return 0


def _write_demo_stage(meshes: dict, path: str) -> str:
    """One USD stage holding every demo mesh, laid out on a grid so they do not overlap."""
    import pathlib

    from pxr import UsdGeom

    from .io.usd import author_mesh, export_atomically, new_stage

    stage = new_stage(default_prim="Demo")
    columns = 3
    pitch = 1.2 * max((np.ptp(m.vertices, axis=0)[:2].max() for m in meshes.values() if m.vertex_count), default=1.0)
    for k, (name, mesh) in enumerate(meshes.items()):
        xform = UsdGeom.Xform.Define(stage, f"/Demo/{name}")
        center = mesh.vertices.mean(axis=0) if mesh.vertex_count else np.zeros(3)
        offset = np.array([(k % columns) * pitch, -(k // columns) * pitch, 0.0]) - np.array([center[0], center[1], 0.0])
        xform.AddTranslateOp().Set(tuple(float(x) for x in offset))
        author_mesh(stage, f"/Demo/{name}/surface", mesh)
    return str(export_atomically(stage.GetRootLayer(), pathlib.Path(path), "demo"))


def cmd_polygonize(args) -> int:
    from .io.usd import save_mesh
    from .polygonize import polygonize

    model = _load(args.scene)
    if not args.out.lower().endswith(_USD_SUFFIXES[:3]):
        raise WarpblobError(f"--out must be a .usda, .usdc or .usd file, got {args.out!r}")
    mesh = polygonize(model, cellsize=args.cellsize, device=args.device, progress=True, relax=args.relax)
    try:
        save_mesh(mesh, args.out)
    except (OSError, ValueError) as exc:
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
    from .tetrahedralize import tetrahedralize

    model = _load(args.scene)
    if not args.out.lower().endswith(_USD_SUFFIXES[:3]):
        raise WarpblobError(f"--out must be a .usda, .usdc or .usd file, got {args.out!r}")
    mesh = tetrahedralize(model, cellsize=args.cellsize, interior_cellsize=args.interior_cellsize, device=args.device, progress=True)
    try:
        mesh.to_usd(args.out)
    except (OSError, ValueError) as exc:
        raise WarpblobError(str(exc)) from None
    q = mesh.quality()
    print(
        f"{mesh.tets.shape[0]} tets, {mesh.nodes.shape[0]} nodes, dihedral angles "
        f"[{q.dihedral_min:.2f}, {q.dihedral_max:.2f}] deg; wrote {args.out}"
    )
    return 0


def cmd_quality(args) -> int:
    from .mesh import TetMesh, format_quality

    if not os.path.exists(args.file):
        raise WarpblobError(f"file {args.file!r} does not exist")
    mesh = TetMesh.from_usd(args.file, prim_path=args.prim)
    print(format_quality(mesh.quality()))
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="warpblob", description="BlobTree modelling of soft tissue on NVIDIA Warp.")
    p.add_argument("--version", action="version", version=f"warpblob {__version__}")
    p.add_argument("--device", default=None, help="Warp device, e.g. cpu or cuda:0 (default: Warp's default)")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="polygonize the reference models into one USD stage, with pictures and a summary")
    d.add_argument("--out", default="out", help="output folder (default: out)")
    d.add_argument("--scene", default="all", help="one built-in scene, or all (default)")
    d.add_argument("--resolution", type=int, default=256, help="pixels per slice side (default 256)")
    d.add_argument("--cellsize", type=float, default=None, help="polygonization cell size (default: per model)")
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

    i = sub.add_parser("info", help="counts, depth, box and bytes of a scene's linearized form")
    i.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    i.add_argument("--json", action="store_true", help="print JSON")
    i.set_defaults(func=cmd_info)

    f = sub.add_parser("field", help="field values of a scene at points from an (N, 3) .npy file")
    f.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    f.add_argument("--points", required=True, help="(N, 3) float .npy file")
    f.add_argument("--out", default=None, help="output .npy (default: POINTS_field.npy)")
    f.set_defaults(func=cmd_field)
    return p


def main(argv=None) -> int:
    """Entry point of the ``warpblob`` command; returns the exit code."""
    args = _parser().parse_args(argv)
    if getattr(args, "resolution", 64) < 8:
        print("warpblob: error: --resolution must be at least 8", file=sys.stderr)
        return 2
    try:
        return args.func(args)
    except WarpblobError as exc:
        print(f"warpblob: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
