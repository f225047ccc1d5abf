"""The ``warpblob slice`` command: cut a mesh file or a polygonized scene by planes, write the capped pieces."""

from __future__ import annotations

import argparse
import os
import time

from .._errors import SceneError, WarpblobError

__all__ = ["add_slice_parser", "run_slice"]

#: cell size of scenes polygonized for slicing when --cellsize is not given
DEFAULT_CELLSIZE = 0.05


def _plane(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6:
        raise argparse.ArgumentTypeError(f"--plane takes ox,oy,oz,nx,ny,nz (six numbers), got {text!r}")
    return tuple(values[:3]), tuple(values[3:])


def add_slice_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``slice`` subcommand to the ``warpblob`` parser's ``subparsers``."""
    sl = subparsers.add_parser(
        "slice", help="cut a mesh file or a scene by planes into closed, capped pieces (USD files, and a picture)"
    )
    sl.add_argument(
        "source", metavar="MESH_OR_SCENE", help="mesh file (.stl/.obj/.ply/.vtk/.vtp/.usd*), USD scene or scene name"
    )
    sl.add_argument(
        "--plane", type=_plane, action="append", required=True, metavar="OX,OY,OZ,NX,NY,NZ",
        help="a point of the plane and its normal; give it again for more planes",
    )  # fmt: skip
    sl.add_argument(
        "--cellsize", type=float, default=None,
        help=f"polygonization cell size for scenes (default {DEFAULT_CELLSIZE}); not for mesh files",
    )  # fmt: skip
    sl.add_argument("--out", required=True, help="output folder: one .usda per piece")
    sl.add_argument("--png", action="store_true", help="also render the pieces pulled apart to OUT/slice.png")
    sl.add_argument("--no-cap", dest="cap", action="store_false", help="cut without caps (open meshes too)")
    sl.set_defaults(func=run_slice)
    return sl


def _source(args):
    """(mesh, model or None, how it was made) for ``args.source``."""
    from .. import scenes
    from ..io._meshfile import MESH_SUFFIXES, load_mesh

    name = args.source
    suffix = os.path.splitext(name)[1].lower()
    model = None
    if name in scenes.ALL:
        model = scenes.ALL[name]()
    elif suffix in MESH_SUFFIXES:
        if args.cellsize is not None:
            raise WarpblobError(f"--cellsize is for scenes, not for the mesh file {name!r}")
        return load_mesh(name), None, "read"
    elif suffix in (".usd", ".usda", ".usdc", ".usdz"):
        from ..io.usd import load_model

        try:
            return load_mesh(name), None, "read"
        except SceneError as mesh_error:
            try:
                model = load_model(name)
            except SceneError as model_error:
                raise WarpblobError(f"{name}: neither a mesh ({mesh_error}) nor a scene ({model_error})") from None
    else:
        known = ", ".join(scenes.ALL)
        raise WarpblobError(f"unknown source {name!r}: give a mesh file, a USD file or a built-in scene ({known})")
    from ..polygonize import polygonize

    h = args.cellsize if args.cellsize is not None else DEFAULT_CELLSIZE
    if not h > 0:
        raise WarpblobError(f"--cellsize must be positive, got {h}")
    return polygonize(model, cellsize=h, device=args.device), model, f"polygonized at h = {h}"


def run_slice(args) -> int:
    """Run ``warpblob slice``; returns the exit code."""
    from ..io.usd import save_mesh
    from ._slice import slice as slice_mesh

    out = args.out
    if os.path.exists(out) and not os.path.isdir(out):
        raise WarpblobError(f"--out {out!r} is a file, not a folder")
    os.makedirs(out, exist_ok=True)
    mesh, model, made = _source(args)
    t0 = time.perf_counter()
    if len(args.plane) == 1:
        pieces = list(slice_mesh(mesh, *args.plane[0], cap=args.cap, model=model, device=args.device))
        names = ["below", "above"]
    else:
        pieces = slice_mesh(mesh, planes=args.plane, cap=args.cap, model=model, device=args.device)
        names = [f"piece_{k}" for k in range(len(pieces))]
    seconds = time.perf_counter() - t0
    print(f"{args.source}: {mesh.face_count} triangles ({made}), cut by {len(args.plane)} plane(s) in {seconds:.3f} s")
    for name, piece in zip(names, pieces):
        path = os.path.join(out, f"{name}.usda")
        try:
            save_mesh(piece, path)
        except OSError as exc:
            raise WarpblobError(str(exc)) from None
        caps = int(piece.is_cap.sum())
        print(
            f"  {name}: {piece.face_count} triangles ({caps} in caps), closed 2-manifold: "
            f"{piece.is_closed_manifold()}, volume {piece.volume():.6g}; wrote {path}"
        )
    if args.png:
        from ._picture import render_pieces

        png = os.path.join(out, "slice.png")
        normal = args.plane[0][1] if len(args.plane) == 1 else None
        title = f"{args.source}: {len(pieces)} pieces, caps in their own colour"
        render_pieces(pieces, png, normal=normal, title=title)
        print(f"wrote {png}")
    return 0
