"""Cutting benchmark: a planar cut through a whole tet mesh and one scalpel stroke step, warpblob vs VTK's clip.

Run:  python benchmarks/bench_cut.py [--sizes 10000,100000,1000000] [--repeat 5] [--quick]

Meshes: ``warpblob.mesh.box_tetmesh`` of the box [0, 4]^3 (model units, cm)
in n^3 cubes of six tets each, n chosen for about the given tet counts
(12^3 x 6 = 10,368; 26^3 x 6 = 105,456; 55^3 x 6 = 998,250). The box is
regular, so the plane is tilted and off the lattice's symmetry planes.

Cases:

* ``plane``: ``SweepSurface.plane`` through (2.013, 2.007, 2.011) with normal
  (0.3, 0.2, 1.0), a square wider than the box: every tet it crosses is split,
  the mesh falls into two pieces;
* ``stroke``: one frame (1/60 s) of a scalpel moving at 10 cm/s through the
  middle of the box, heading 20 degrees from the x axis: its cutting edge, a
  2 cm segment leaning 15 degrees back from the vertical, from 0.5 cm above
  the top face down to about 1.5 cm inside, sweeps a 1/6 cm x 2 cm strip
  (``SweepSurface.from_blade`` of the edge's two ends at the frame's start
  and end). The blade stops inside the tets at its tip and at its leading
  and trailing edges: those are progressive (partial) cuts.

Each case is cut with ``collect=False`` (the simulator keeps indices and
compacts later); the garbage collection (``collect_garbage``) of the cut
mesh is timed on its own (``gc``), and so is the FEM rebuild a simulation
on the mesh then runs (``fem``: ``apply_cut``, element data of the changed
tets, masses and incidence). Per stage: the seconds of the fastest
call (``CutResult.seconds``). "split / ms": tets replaced by a split table
entry (A, B, X, Y, C, D, E; not the intact ones re-linked at a cut node) per
millisecond of the whole call.

Peer, same mesh, same plane (``plane`` case): VTK's table-based clip,
``pyvista.UnstructuredGrid.clip(normal, origin, crinkle=False,
return_clipped=True)``, both sides in one call. Its output is tets plus
wedges and pyramids; ``.triangulate()`` of both sides makes it all tets and
is timed separately. The share of inverted (signed volume <= 0) tets among
those it makes from the crossed tets is reported, next to warpblob's count
of inverted tets over the whole cut mesh (checked: zero).

Timing (``benchmarks/_common.py``): wall clock around each whole call,
warm (one call first, not timed, so kernel compilation is excluded), best of
``--repeat``; a fresh mesh structure is built before every call, untimed.
``--quick``: 10K and 100K tets, 2 repeats, no JSON unless ``--json``.
Writes benchmarks/results/bench_cut.json with the load average.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import warpblob as wb  # noqa: E402
from warpblob.cut import STAGES, SweepSurface, cut  # noqa: E402
from warpblob.cut._sim import apply_cut  # noqa: E402
from warpblob.mesh import TetStructure, box_tetmesh  # noqa: E402
from _common import Run, arguments, table, wall_time  # noqa: E402

#: the box, model units (cm)
SIDE = 4.0
ORIGIN, NORMAL = (2.013, 2.007, 2.011), (0.3, 0.2, 1.0)
#: blade speed (cm/s), frame time (s), cutting edge length (cm), how far above the top face it starts (cm)
SPEED, FRAME, EDGE, ABOVE = 10.0, 1.0 / 60.0, 2.0, 0.5
#: direction of travel from the x axis and lean of the edge back from the vertical (degrees): off the lattice
HEADING, LEAN = 20.0, 15.0
#: table kinds that split a tet (the others keep it whole)
SPLIT_KINDS = ("A", "B", "X", "Y", "C", "D", "E")


def box(tets: int) -> wb.TetMesh:
    n = max(1, round((tets / 6) ** (1 / 3)))
    return box_tetmesh((0, 0, 0), (SIDE,) * 3, (n, n, n))


def stroke_step() -> SweepSurface:
    """The strip one frame of the blade sweeps (module docstring)."""
    heading = np.radians(HEADING)
    d = np.array([np.cos(heading), np.sin(heading), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    back = EDGE * (np.cos(np.radians(LEAN)) * up - np.sin(np.radians(LEAN)) * d)  # tip to back of the edge
    centre = np.array([0.5 * SIDE, 0.5 * SIDE, SIDE + ABOVE - back[2]])
    tip = centre + np.outer([-0.5, 0.5], SPEED * FRAME * d)
    return SweepSurface.from_blade(tip, tip + back)


def run_warpblob(mesh: wb.TetMesh, sweep: SweepSurface, repeat: int) -> dict:
    seconds, (result, structure) = wall_time(
        lambda s: (cut(s, sweep, collect=False), s), repeat, setup=lambda: TetStructure.from_tetmesh(mesh)
    )
    cut_mesh = structure.to_tetmesh()
    gc_seconds, _ = wall_time(lambda s: s.collect_garbage(), repeat, setup=lambda: _cut_copy(mesh, sweep))
    fem_seconds, _ = wall_time(lambda pair: apply_cut(*pair), min(repeat, 2), setup=lambda: _simulated_cut(mesh, sweep))
    split = sum(result.tets_split.get(k, 0) for k in SPLIT_KINDS)
    return {
        "wb_ms": 1e3 * seconds,
        **{f"{stage}_ms": 1e3 * result.seconds[stage] for stage in STAGES if stage != "gc"},
        "gc_ms": 1e3 * gc_seconds,
        "fem_rebuild_ms": 1e3 * fem_seconds,
        "split": split,
        "split_per_ms": split / (1e3 * seconds),
        "tets_added": result.tets_added,
        "components": result.components,
        "kinds": dict(result.tets_split),
        "wb_inverted": int((cut_mesh.volumes() <= 0).sum()),
    }


def _cut_copy(mesh, sweep) -> TetStructure:
    s = TetStructure.from_tetmesh(mesh)
    cut(s, sweep, collect=False)
    return s


def _simulated_cut(mesh, sweep):
    """A simulation on a fresh structure, and a cut of it (collect=False): the input of ``apply_cut``."""
    s = TetStructure.from_tetmesh(mesh)
    sim = wb.Simulation(s, young=3e3, poisson=0.45, density=1000.0)
    return sim, cut(s, sweep, collect=False)


def vtk_grid(mesh: wb.TetMesh):
    import pyvista as pv

    grid = pv.UnstructuredGrid({pv.CellType.TETRA: mesh.tets.astype(np.int64)}, mesh.nodes.astype(np.float64))
    grid.cell_data["cell"] = np.arange(mesh.tet_count)  # to tell the crossed tets' pieces apart, not used by clip
    return grid


def run_vtk(mesh: wb.TetMesh, repeat: int) -> dict:
    grid = vtk_grid(mesh)
    clip_s, sides = wall_time(
        lambda: grid.clip(normal=NORMAL, origin=ORIGIN, crinkle=False, return_clipped=True), repeat
    )
    tri_s, tets = wall_time(lambda: [side.triangulate() for side in sides], repeat)
    n = np.asarray(NORMAL) / np.linalg.norm(NORMAL)
    d = (mesh.nodes.astype(np.float64) - ORIGIN) @ n
    dt = d[mesh.tets]
    crossed = (dt.min(axis=1) < 0) & (dt.max(axis=1) > 0)
    made = inverted = 0
    for side in tets:  # the tets it made out of crossed tets: their cell data names a crossed input tet
        cells = side.cells.reshape(-1, 5)[:, 1:]
        p = np.asarray(side.points)[cells]
        vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
        new = crossed[np.asarray(side.cell_data["cell"])]
        made += int(new.sum())
        inverted += int((vol[new] <= 0).sum())
    return {
        "vtk_clip_ms": 1e3 * clip_s,
        "vtk_triangulate_ms": 1e3 * tri_s,
        "vtk_cells": sum(s.n_cells for s in sides),
        "vtk_new_tets": made,
        "vtk_inverted_share": inverted / made if made else None,
    }


FULL = {"sizes": "10000,100000,1000000", "repeat": 5}
QUICK = {"sizes": "10000,100000", "repeat": 2}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", help=f"comma-separated tet counts (default {FULL['sizes']})")
    args = arguments(ap, FULL, QUICK, argv)
    bench = Run("cut", "cutting benchmark: ms per cut, warm, collect=False (gc timed apart)", args)
    plane = SweepSurface.plane(ORIGIN, NORMAL, SIDE)
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        mesh = box(size)
        for case, sweep in (("plane", plane), ("stroke", stroke_step())):
            row = {"case": case, "tets": mesh.tet_count, **run_warpblob(mesh, sweep, args.repeat)}
            if case == "plane":
                row.update(run_vtk(mesh, args.repeat))
                row["speedup_vs_vtk_clip"] = row["vtk_clip_ms"] / row["wb_ms"]
                vtk_all_tets = row["vtk_clip_ms"] + row["vtk_triangulate_ms"]
                row["speedup_vs_vtk_clip_triangulated"] = vtk_all_tets / row["wb_ms"]
            rows.append(row)
            print(f"  {case} {mesh.tet_count:,} tets: {row['wb_ms']:.1f} ms, {row['split']} split, "
                  f"kinds {row['kinds']}", flush=True)  # fmt: skip
    cols = [("case", "case", "s"), ("tets", "tets", ",d"), ("wb_ms", "wb ms", ".1f")]
    cols += [(f"{stage}_ms", stage[:5], ".1f") for stage in STAGES]
    cols += [("fem_rebuild_ms", "fem", ".1f")]
    cols += [("split", "split", "d"), ("split_per_ms", "split/ms", ".1f"), ("wb_inverted", "inv", "d")]
    cols += [("vtk_clip_ms", "vtk clip ms", ".1f"), ("vtk_triangulate_ms", "+tri ms", ".1f")]
    cols += [("vtk_inverted_share", "vtk inv", ".1%"), ("speedup_vs_vtk_clip", "x clip", ".2f")]
    cols += [("speedup_vs_vtk_clip_triangulated", "x clip+tri", ".2f")]
    print(table(rows, cols))
    print("gc: collect_garbage after the cut, timed apart (not in wb ms); inv: tets with signed volume <= 0 "
          "(wb: whole mesh; vtk: of those made from crossed tets, after triangulate)")  # fmt: skip
    bench.finish({"rows": rows, "box_side": SIDE, "plane": {"origin": ORIGIN, "normal": NORMAL},
                  "stroke": {"speed": SPEED, "frame": FRAME, "edge": EDGE, "above": ABOVE}})  # fmt: skip


if __name__ == "__main__":
    main()
