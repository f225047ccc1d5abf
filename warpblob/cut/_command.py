"""The ``warpblob cut`` command: tetrahedralize a scene, cut it by planes, write the pieces and a picture."""

from __future__ import annotations

import argparse
import time

import numpy as np

from .._errors import CutError, WarpblobError
from ..slice._command import _plane

__all__ = ["add_cut_parser", "run_cut"]

#: half-width of each cutting square, in box diagonals of the model (it is centred on the model)
EXTENT = 2.0


def add_cut_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``cut`` subcommand to the ``warpblob`` parser's ``subparsers``."""
    ct = subparsers.add_parser(
        "cut", help="tetrahedralize a scene and cut it by planes (TetMesh and coloured boundary to USD, a picture)"
    )
    ct.add_argument("scene", help="USD file (.usda/.usdc/.usd) or built-in scene name")
    ct.add_argument("--cellsize", type=float, required=True, help="tetrahedralization cell size, model units")
    ct.add_argument(
        "--plane", type=_plane, action="append", required=True, metavar="OX,OY,OZ,NX,NY,NZ",
        help="a point of the cutting plane and its normal; give it again for more cuts, made in order",
    )  # fmt: skip
    ct.add_argument(
        "--snap", type=float, default=0.2, help="snap distance, fraction of an edge, in [0, 0.5) (default 0.2)"
    )
    ct.add_argument("--out", required=True, help="output .usda/.usdc/.usd: /Cut/Volume (TetMesh) and /Cut/Surface")
    ct.add_argument("--png", default=None, help="also render the pieces pulled apart to this PNG file")
    ct.set_defaults(func=run_cut)
    return ct


def _checked_planes(planes) -> list[tuple[np.ndarray, np.ndarray]]:
    """The ``--plane`` values as float64 (origin, unit normal) pairs.

    Raises:
        CutError: a value that is not finite or a zero normal; the message shows the plane.
    """
    out = []
    for origin, normal in planes:
        o, n = np.asarray(origin, dtype=np.float64), np.asarray(normal, dtype=np.float64)
        text = ",".join(f"{x:g}" for x in (*origin, *normal))
        if not (np.all(np.isfinite(o)) and np.all(np.isfinite(n))):
            raise CutError(f"--plane {text}: every number must be finite")
        if not np.linalg.norm(n) > 0:
            raise CutError(f"--plane {text}: the normal (last three numbers) must not be zero")
        out.append((o, n / np.linalg.norm(n)))
    return out


def _sweep(origin: np.ndarray, normal: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """A square of the plane centred on the foot of the box centre, EXTENT box diagonals wide each way."""
    from ._sweep import SweepSurface

    centre = 0.5 * (lo + hi)
    foot = centre - float((centre - origin) @ normal) * normal
    return SweepSurface.plane(foot, normal, EXTENT * max(float(np.linalg.norm(hi - lo)), 1e-6))


def _line(k: int, plane, result) -> str:
    """One printed line per cut: what was split, what was added, the pieces and the ms per stage."""
    from ._cut import STAGES

    (o, n) = plane
    kinds = ", ".join(f"{kind} {count}" for kind, count in sorted(result.tets_split.items()) if kind != "touch")
    touch = result.tets_split.get("touch", 0)
    ms = ", ".join(f"{stage} {1e3 * result.seconds[stage]:.1f}" for stage in STAGES)
    where = ",".join(f"{x:.4g}" for x in (*o, *n))
    return (
        f"  cut {k} (plane {where}): {result.edges_cut} edges and {result.nodes_cut} nodes cut; "
        f"tets split: {kinds or 'none'} ({touch} touched at a cut node); {result.tets_added} tets added, "
        f"{result.tets_removed} removed; {result.components} components; ms: {ms}"
    )


def _write_stage(path: str, structure, surface) -> None:
    """One stage, default prim /Cut: the tets (/Cut/Volume) and their boundary (/Cut/Surface), atomically.

    Both carry the uniform int primvar ``piece`` (the connected piece of each
    tet, of each face); the surface carries ``isCut`` on the faces the cuts made.
    """
    from pxr import Sdf, UsdGeom, Vt

    from ..io.usd import author_mesh, author_tetmesh, export_atomically, new_stage
    from ._picture import face_pieces

    stage = new_stage(default_prim="Cut")
    cell_piece = structure.components()[np.asarray(structure.cell_alive)]
    for geom, values in (
        (author_tetmesh(stage, "/Cut/Volume", structure.to_tetmesh()), cell_piece),
        (author_mesh(stage, "/Cut/Surface", surface), face_pieces(structure, surface)),
    ):
        primvar = UsdGeom.PrimvarsAPI(geom).CreatePrimvar("piece", Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform)
        primvar.Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(values, dtype=np.int32)))
    try:
        export_atomically(stage.GetRootLayer(), path, "warpblob cut")
    except OSError as exc:
        raise WarpblobError(str(exc)) from None


def run_cut(args) -> int:
    """Run ``warpblob cut``; returns the exit code (errors are raised as :class:`WarpblobError`)."""
    from .._progress import progress
    from ..cli import _MESH_SUFFIXES, _prepare_outputs
    from ..io._scene import load_scene
    from ..mesh import TetStructure
    from ..tetrahedralize import tetrahedralize
    from ._cut import cut

    if not (np.isfinite(args.cellsize) and args.cellsize > 0):
        raise WarpblobError(f"--cellsize must be a positive number, got {args.cellsize}")
    if not 0.0 <= args.snap < 0.5:
        raise CutError(f"--snap must be in [0, 0.5), got {args.snap}")
    planes = _checked_planes(args.plane)
    outputs = [(args.out, "--out", _MESH_SUFFIXES)]
    if args.png:
        outputs.append((args.png, "--png", (".png",)))
    _prepare_outputs(*outputs)
    model = load_scene(args.scene)
    t0 = time.perf_counter()
    mesh = tetrahedralize(model, cellsize=args.cellsize, device=args.device, progress=True)
    if mesh.tet_count == 0:
        raise WarpblobError(f"--cellsize {args.cellsize} gives no tets for {args.scene!r}: take a smaller cell size")
    structure = TetStructure.from_tetmesh(mesh)
    print(
        f"{args.scene}: {mesh.tet_count} tets, {mesh.node_count} nodes (tetrahedralized at h = {args.cellsize} "
        f"in {time.perf_counter() - t0:.2f} s), cut by {len(planes)} plane(s)"
    )
    lo, hi = mesh.nodes.min(axis=0).astype(np.float64), mesh.nodes.max(axis=0).astype(np.float64)
    for k, plane in enumerate(progress(planes, desc="cut", mininterval=0.0), start=1):
        result = cut(structure, _sweep(*plane, lo, hi), snap=args.snap, device=args.device)
        print(_line(k, plane, result), flush=True)
    surface = structure.surface(model=model)
    volume = structure.to_tetmesh().volume()
    _write_stage(args.out, structure, surface)
    print(
        f"{structure.cell_count} tets, {structure.node_count} nodes in {result.components} pieces, volume "
        f"{volume:.6g} (before {mesh.volume():.6g}); boundary {surface.face_count} triangles, "
        f"{int(surface.is_cut.sum())} cut; wrote {args.out}"
    )
    if args.png:
        from ._picture import render_cut

        title = f"{args.scene}: {structure.cell_count:,} tets after {len(planes)} cut(s), {result.components} pieces"
        render_cut(structure, args.png, model=model, planes=planes, title=title)
        print(f"wrote {args.png}")
    return 0
