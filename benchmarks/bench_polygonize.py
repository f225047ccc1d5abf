"""Polygonization benchmark: model in, mesh out, warpblob vs Warp's extractors and VTK.

Run:  python benchmarks/bench_polygonize.py [--models tumor,mug,medusa,towers] [--cellsizes 0.14,0.1,0.05,0.03]
      [--repeat 3] [--quick]

Peers, all fed the same model through warpblob's own field kernel on the same
grid (origin at the model box minus half a cell):

* ``sparse_mc``: ``warp.geometry.sparse_marching_cubes`` with the field as a
  batched Warp callable and the Lipschitz bound below;
* ``dense_warp_mc``: the field on the dense grid by warpblob's fastest grid
  evaluator (``warpblob.field.grid_field``: one tree walk per 8^3 block of
  nodes, the same array mode the polygonizer samples with), then Warp's
  ``IsoSurfaceMarchingCubes``;
* ``dense_vtk_fe``: the same dense field, then VTK flying edges (PyVista
  ``contour`` on ``ImageData``);
* ``dense_vtk_fe_eval``: the peer a user would build for warpblob's output
  (normals and colours on every vertex): ``dense_vtk_fe`` followed by one
  ``wb.evaluate`` of every output vertex for the analytic gradient (normal
  ``-grad F / |grad F|``) and colour. Its vertices are still linearly
  interpolated (off the surface), so it does less than warpblob.

Lipschitz bound for sparse MC (it must bound |grad F| everywhere): a Wyvill
primitive has ``|dF/dx| <= max_x 6x(1-x^2)^2 / R = 1.7173 / R`` times the
stretch of its inverse transform; max, min and ``1 - F`` keep the bound of
their operands, a sum (blend; and a smooth blend, whose gradient is a
sub-unit-weighted sum) adds them. For wide operators only operands whose
supports overlap matter, so the sum is taken per grid cell of the operator
and the largest cell sum is used. Models with warps are not benchmarked here.

Every tool is timed the same way: the wall clock around its whole call,
model in, triangles out (dense peers include the dense field evaluation),
warm (a first call excluded: compilation), best of ``--repeat`` (see
``benchmarks/_common.py``); warpblob's ``stats`` seconds per stage of its
fastest call are kept as the breakdown, and its field evaluations by kind
(grid samples, root steps and their number per placed vertex, relaxation,
interval bounds) as ``warpblob_evaluations``. warpblob runs with its defaults
(vertices refined to |F - 0.5| <= 1e-4, skinny triangles relaxed). A peer
whose package is missing is skipped with a note. Triangle quality: the share
of triangles with a smallest angle under 10 degrees, warpblob against Warp's
IsoSurfaceMarchingCubes on the same grid. ``--quick``: tumor and mug at 0.14
and 0.1. Writes benchmarks/results/bench_polygonize.json with the load
average before and after.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
import warp as wp
import warp.geometry  # noqa: F401  (peers)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import warpblob as wb  # noqa: E402
from warpblob.field import grid_field  # noqa: E402
from _common import Run, arguments, table, wall_time  # noqa: E402
from warpblob.mesh._surface import triangle_min_angles  # noqa: E402
from warpblob.tree import _kinds  # noqa: E402

THESIS_MEDUSA_MS = {0.01: 5220, 0.03: 3441, 0.05: 1071, 0.10: 264, 0.14: 108}  # one core, AVX (SPEC 2.4)
WYVILL_SLOPE = 6.0 / 5.0**0.5 * (4.0 / 5.0) ** 2  # max of 6x(1-x^2)^2 at x = 1/sqrt(5)


def lipschitz_bound(lm) -> float:
    """Upper bound of |grad F| over space for a linearized model without warps."""
    n = lm.node_count
    bound = np.zeros(n)
    for i in range(n - 1, -1, -1):
        k = lm.kind[i]
        if k < _kinds.PRIMITIVE_KIND_END:
            r = lm.ref[i]
            bound[i] = WYVILL_SLOPE / lm.radius[r] * lm.stretch[r]
            continue
        if k in _kinds.WARP_KINDS:
            raise ValueError("models with warps have no simple Lipschitz bound")
        kids = np.nonzero(lm.parent == i)[0]
        if k in (_kinds.BLEND, _kinds.SMOOTH_BLEND):
            if lm.ref[i] >= 0:  # wide: largest sum over one grid cell
                g = lm.ref[i]
                cells = np.prod(lm.grid_dims[g])
                offs = lm.cell_offsets[lm.grid_base[g] : lm.grid_base[g] + cells + 1]
                csum = np.concatenate([[0.0], np.cumsum(bound[lm.cell_items[offs[0] : offs[-1]]])])
                bound[i] = float(np.max(csum[offs[1:] - offs[0]] - csum[offs[:-1] - offs[0]]))
            else:
                bound[i] = bound[kids].sum()
        else:
            bound[i] = bound[kids].max()
    return float(bound[0])


def grid_of(lm, h):
    lo, hi = lm.bounds
    lo = lo - 0.5 * h
    cells = np.maximum(np.ceil((hi + 0.5 * h - lo) / h).astype(int), 1)
    return lo, cells + 1  # nodes per axis


def dense_field(lm, lo, nodes, h):
    return grid_field(lm, lo, h, tuple(int(n) for n in nodes))


SKINNY_DEGREES = 10.0


def skinny_share(vertices, faces) -> float:
    """Share of triangles whose smallest angle is under 10 degrees."""
    return float(np.mean(triangle_min_angles(vertices, faces) < SKINNY_DEGREES)) if len(faces) else 0.0


def run_warpblob(lm, h, quality=None):
    """(triangles, field and interval evaluations, stats) of one whole ``wb.polygonize`` call."""
    mesh = wb.polygonize(lm, cellsize=h)
    if quality is not None:
        quality["warpblob"] = skinny_share(mesh.vertices, mesh.faces)
    return mesh.face_count, mesh.stats["field_evaluations"] + mesh.stats["interval_evaluations"], mesh.stats


def run_sparse(lm, h, lip):
    lo, nodes = grid_of(lm, h)
    hi = lo + h * (nodes - 1)
    count = [0]

    def fn(points):
        count[0] += points.shape[0]
        return wb.field(lm, points)

    verts, faces = wp.geometry.sparse_marching_cubes(
        fn, int(nodes[0]), int(nodes[1]), int(nodes[2]), lower=tuple(lo), upper=tuple(hi), threshold=0.5,
        lipschitz_bound=lip,
    )  # fmt: skip
    return faces.shape[0] // 3, count[0], None


def run_dense_warp(lm, h, quality=None):
    lo, nodes = grid_of(lm, h)
    f = dense_field(lm, lo, nodes, h)
    hi = lo + h * (nodes - 1)
    mc = wp.geometry.IsoSurfaceMarchingCubes(int(nodes[0]), int(nodes[1]), int(nodes[2]), tuple(lo), tuple(hi))
    mc.surface(wp.array(f, dtype=wp.float32), 0.5)
    if quality is not None:
        quality["dense_warp_mc"] = skinny_share(mc.verts.numpy(), mc.indices.numpy().reshape(-1, 3))
    return mc.indices.shape[0] // 3, int(np.prod(nodes)), None


def run_dense_vtk(lm, h, shade=False):
    """Dense field plus VTK flying edges; with ``shade``, one ``wb.evaluate`` of
    every output vertex for its normal and colour (the fair peer)."""
    import pyvista as pv

    lo, nodes = grid_of(lm, h)
    f = dense_field(lm, lo, nodes, h)
    img = pv.ImageData(dimensions=tuple(int(n) for n in nodes), spacing=(h, h, h), origin=tuple(lo))
    img.point_data["F"] = f.ravel(order="F")
    surf = img.contour([0.5], scalars="F", method="flying_edges")
    evaluations = int(np.prod(nodes))
    if shade and surf.n_points:
        _, grad, colors = wb.evaluate(lm, np.asarray(surf.points, dtype=np.float32))
        norm = np.linalg.norm(grad, axis=1, keepdims=True)
        surf.point_data["Normals"] = -grad / np.where(norm > 0.0, norm, 1.0)
        surf.point_data["colors"] = colors
        evaluations += surf.n_points
    return surf.n_cells, evaluations, None


#: every peer, in the order of the table
PEERS = ("sparse_mc", "dense_warp_mc", "dense_vtk_fe", "dense_vtk_fe_eval")
FULL = {"models": "tumor,mug,medusa,towers", "cellsizes": "0.14,0.1,0.05,0.03", "repeat": 3}
QUICK = {"models": "tumor,mug", "cellsizes": "0.14,0.1", "repeat": 2}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", help=f"comma-separated scene names (default {FULL['models']})")
    ap.add_argument("--cellsizes", help=f"comma-separated (default {FULL['cellsizes']})")
    ap.add_argument("--skip-dense-above", type=float, default=4e7, help="skip dense peers above this many nodes")
    args = arguments(ap, FULL, QUICK, argv)
    cellsizes = [float(c) for c in args.cellsizes.split(",")]
    rows = []
    bench = Run("polygonize", "polygonization benchmark: model in, mesh out, seconds", args)
    for name in args.models.split(","):
        lm = wb.linearize(wb.scenes.ALL[name]())
        lip = lipschitz_bound(lm)
        for h in cellsizes:
            _, nodes = grid_of(lm, h)
            dense_ok = np.prod(nodes) <= args.skip_dense_above
            row = {"model": name, "cellsize": h, "lipschitz": lip, "grid_nodes": int(np.prod(nodes))}
            peers = {
                "warpblob": lambda: run_warpblob(lm, h),
                "sparse_mc": lambda: run_sparse(lm, h, lip),
                "dense_warp_mc": (lambda: run_dense_warp(lm, h)) if dense_ok else None,
                "dense_vtk_fe": (lambda: run_dense_vtk(lm, h)) if dense_ok else None,
                "dense_vtk_fe_eval": (lambda: run_dense_vtk(lm, h, shade=True)) if dense_ok else None,
            }
            quality = {}
            run_warpblob(lm, h, quality)
            if dense_ok:
                run_dense_warp(lm, h, quality)
            row["warpblob_skinny"] = quality["warpblob"]
            row["dense_warp_mc_skinny"] = quality.get("dense_warp_mc")
            for key, fn in peers.items():
                if fn is None:
                    continue
                try:
                    seconds, (tris, evals, stats) = wall_time(fn, args.repeat)
                except ImportError as err:
                    print(f"  {name} h={h}: {key} skipped ({err})", flush=True)
                    continue
                row[f"{key}_s"] = seconds
                row[f"{key}_tris"] = tris
                row[f"{key}_fvept"] = evals / max(tris, 1)
                if stats is not None:
                    row[f"{key}_stats_seconds"] = stats["seconds"]
                    row[f"{key}_stats_total_s"] = stats["total_seconds"]
                    # where the field evaluations go: grid samples, root search (per vertex), relaxation
                    placed = stats["vertices"] + stats["welded_vertices"]  # every vertex placed (a few: loop centres)
                    row[f"{key}_evaluations"] = {
                        "grid": stats["grid_evaluations"], "root": stats["root_evaluations"],
                        "root_per_vertex": stats["root_evaluations"] / max(placed, 1),
                        "relax": stats["relax_evaluations"], "interval": stats["interval_evaluations"],
                        "dense_sampling": stats["dense_sampling"],
                    }  # fmt: skip
            peer_seconds = [row[f"{k}_s"] for k in PEERS if f"{k}_s" in row]
            row["speedup_vs_fastest_peer"] = min(peer_seconds) / row["warpblob_s"] if peer_seconds else None
            if "dense_vtk_fe_eval_s" in row:
                row["speedup_vs_fair_peer"] = row["dense_vtk_fe_eval_s"] / row["warpblob_s"]
            if name == "medusa" and h in THESIS_MEDUSA_MS:
                row["thesis_1core_avx_s"] = THESIS_MEDUSA_MS[h] / 1000.0
            rows.append(row)
            speedup = row["speedup_vs_fastest_peer"]
            versus = "" if speedup is None else f", x{speedup:.1f} vs fastest peer"
            stages = f"stages {row['warpblob_stats_total_s']:.3f} s"
            print(f"  {name} h={h}: warpblob {row['warpblob_s']:.3f} s ({stages}){versus}", flush=True)
    cols = [("model", "model", "s"), ("cellsize", "h", ".2f")]
    labels = {"warpblob": "wb", "sparse_mc": "sparseMC", "dense_warp_mc": "warpMC", "dense_vtk_fe": "vtkFE",
              "dense_vtk_fe_eval": "vtkFE+eval"}
    for key, label in labels.items():
        cols += [(f"{key}_s", f"{label} s", ".3f"), (f"{key}_fvept", f"{label} FVEPT", ".1f")]
    cols += [("warpblob_tris", "wb tris", "d"), ("speedup_vs_fastest_peer", "speedup", ".1f")]
    cols += [("speedup_vs_fair_peer", "vs fair", ".1f")]
    cols += [("thesis_1core_avx_s", "thesis s", ".3f")]
    cols += [("warpblob_skinny", "wb <10deg", ".3f"), ("dense_warp_mc_skinny", "warpMC <10deg", ".3f")]
    print(table(rows, cols))
    bench.finish({"rows": rows})


if __name__ == "__main__":
    main()
