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
* ``corner``: ``SweepSurface.plane`` through (0.4, 0.4, 0.4) with normal
  (1, 1, 1), cutting a corner off the box (a few tets to a few thousand:
  the cost of a small cut, where a cut does work near its sweep and VTK's
  clip still passes over every cell); the mesh falls into two pieces;
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

Peer, same mesh, same plane (``plane`` and ``corner`` cases): VTK's table-based clip,
``pyvista.UnstructuredGrid.clip(normal, origin, crinkle=False,
return_clipped=True)``, both sides in one call. Its output is tets plus
wedges and pyramids; ``.triangulate()`` of both sides makes it all tets and
is timed separately. The share of inverted (signed volume <= 0) tets among
those it makes from the crossed tets is reported, next to warpblob's count
of inverted tets over the whole cut mesh (checked: zero).

Scalpel in a simulation (``sim`` rows): one ``wb.Simulation`` of each box and
the scalpel's frames one after the other (``stroke_step(frame)``, frame 0 the
``stroke`` case's strip, each next one 1/6 cm further along the heading):
each frame's strip is cut (``collect=False``) and the simulation follows it
(``apply_cut``: the FEM rebuild); median ms of the cut, of the rebuild and of
both, over the frames after the first, of the fastest of ``SIM_RUNS`` (3) such
simulations by that median (the JSON keeps every run's median frame).

Scalpel and probe (``sim_contact`` rows): the same frames in a simulation
that also has a contact tool, a probe of radius 0.4 cm pressing the box's
top 0.1 cm deep near a corner (at x = y = 0.8 cm, away from the strip; a
``wb.Box`` of radius 0.3 whose surface is the box's as the contact's model,
no gravity), stepped 6 times before
the first frame: each rebuild then also follows the contact's k-ring
spread, boundary layer and median edge over the cut (``Contact.bind``).

Scalpel in a stepping simulation (``sim_step`` rows, up to 200K tets): the
``sim`` frames with one simulation step after each cut (3 kPa, gravity,
nothing held), as an interactive loop runs them: the median step, the
median whole frame (cut, rebuild, step), and the number of frames whose step
rebuilt the coarse factor (a cut's rebuild keeps it: only the solver's own
schedule, every 10 steps, or a new aggregation refreshes it).

Drill (``drill`` rows; issue 15): a bone plate ``box_tetmesh`` of
[0, 4] x [0, 4] x [0, 0.6] (cm; about 10K, 66K, the thesis skull's size, and
500K tets) and a trephine (``wb.tools.Drill``, radius 0.5 cm, N = 8, 16, 32
wall segments) boring straight down through it in 30 frames of 1/60 s, from
0.1 above the plate to 0.1 below it. Each frame is one drill step as the
simulator's progressive cutter makes it (``Cutter``, ``mode="progressive"``):
the whole stroke so far, cut in the rest frame against the edges the plate
had when the stroke began (``node_limit``), the nodes its earlier steps
snapped to kept cut (``cut_nodes``). The ``skull`` rows drill
the layered head's skull (``scenes.head_materials()`` at cell size 0.118:
66K skull tets, the thesis' size, in 237K tets) at the craniotomy's first
site, bone only (``materials={0}``), radius 0.2 cm, from 0.1 above the skull
to a cell below its inner surface. Reported: the median and the
largest ms per step over the 30 steps of a second, warm stroke (the first
stroke on another copy compiles), tets split in all, pieces at the end (2:
the plug is free).

As the ``warpblob`` command does, the objects alive after the imports are
kept out of Python's garbage collections (``gc.freeze()``): a full
collection over Warp's kernels' syntax trees takes 0.1-0.2 s, which would
land in whichever frame Python starts one.

Timing (``benchmarks/_common.py``): wall clock around each whole call,
warm (one call first, not timed, so kernel compilation is excluded), best of
``--repeat``; a fresh mesh structure is built before every call, untimed.
``--quick``: 10K and 100K tets, 2 repeats, no JSON unless ``--json``.
Writes benchmarks/results/bench_cut.json with the load average.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import warpblob as wb  # noqa: E402
from warpblob.cut import STAGES, SweepSurface, cut  # noqa: E402
from warpblob.cut._sim import apply_cut  # noqa: E402
from warpblob.mesh import TetStructure, box_tetmesh  # noqa: E402
from warpblob.tree import ISO_DISTANCE  # noqa: E402
from _common import Run, arguments, table, wall_time  # noqa: E402

#: the box, model units (cm)
SIDE = 4.0
ORIGIN, NORMAL = (2.013, 2.007, 2.011), (0.3, 0.2, 1.0)
#: the ``corner`` case's plane: a corner of the box cut off
CORNER_ORIGIN, CORNER_NORMAL = (0.4, 0.4, 0.4), (1.0, 1.0, 1.0)
#: blade speed (cm/s), frame time (s), cutting edge length (cm), how far above the top face it starts (cm)
SPEED, FRAME, EDGE, ABOVE = 10.0, 1.0 / 60.0, 2.0, 0.5
#: direction of travel from the x axis and lean of the edge back from the vertical (degrees): off the lattice
HEADING, LEAN = 20.0, 15.0
#: table kinds that split a tet (the others keep it whole)
SPLIT_KINDS = ("A", "B", "X", "Y", "C", "D", "E")


def box(tets: int) -> wb.TetMesh:
    n = max(1, round((tets / 6) ** (1 / 3)))
    return box_tetmesh((0, 0, 0), (SIDE,) * 3, (n, n, n))


def stroke_step(frame: int = 0) -> SweepSurface:
    """The strip frame ``frame`` of the blade sweeps (module docstring; frame 0 through the box's middle,
    each later one a frame further along the heading)."""
    heading = np.radians(HEADING)
    d = np.array([np.cos(heading), np.sin(heading), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    back = EDGE * (np.cos(np.radians(LEAN)) * up - np.sin(np.radians(LEAN)) * d)  # tip to back of the edge
    centre = np.array([0.5 * SIDE, 0.5 * SIDE, SIDE + ABOVE - back[2]]) + frame * SPEED * FRAME * d
    tip = centre + np.outer([-0.5, 0.5], SPEED * FRAME * d)
    return SweepSurface.from_blade(tip, tip + back)


#: frames of the scalpel in a simulation (``sim`` rows), the first of them not timed
SIM_FRAMES = 9
#: simulations per ``sim`` row (each a fresh one over the same frames): the row is the one whose median frame
#: is fastest, as the other rows take the best of their repeats (a single simulation's 8 frames swing by 40%
#: between runs on this shared machine)
SIM_RUNS = 3


#: the largest mesh of the ``sim_step`` rows (a step of a 1M-tet simulation takes seconds)
SIM_STEP_MAX = 200_000

#: the ``sim_contact`` rows' probe: radius (cm), where it presses the top face (x, y; away from the strip),
#: from how far above to how deep (cm), over how long (s), its stiffness, and the steps before the first frame
PROBE_RADIUS, PROBE_AT, PROBE_FROM, PROBE_DEPTH, PROBE_TIME, PROBE_STIFFNESS, PROBE_STEPS = (
    0.4, (0.8, 0.8), 0.02, 0.1, 0.2, 1e4, 6)


#: the radius of the ``sim_contact`` rows' box model (cm)
BOX_RADIUS = 0.3


def _with_probe(sim: wb.Simulation) -> int:
    """The ``sim_contact`` rows' probe on ``sim`` (pressing the box's top near a corner, away from the
    scalpel's strip), stepped until it presses: every later rebuild binds the contact to the cut mesh. The
    nodes in contact after those steps."""
    x, y = PROBE_AT
    path = wb.tools.Path.line((x, y, SIDE + PROBE_FROM), (x, y, SIDE - PROBE_DEPTH), PROBE_TIME)
    sim.add_tool(wb.tools.Probe(PROBE_RADIUS), path, stiffness=PROBE_STIFFNESS)
    sim.step(PROBE_STEPS)
    return len(sim.contact_nodes())


def run_sim_stroke(mesh: wb.TetMesh, runs: int = SIM_RUNS, contact: bool = False, simulate: bool = False) -> dict:
    """The scalpel's frames in a simulation of the mesh: per frame the strip it sweeps is cut
    (``collect=False``) and the simulation follows the cut (``apply_cut``), frame after frame on one
    simulation; medians over the frames after the first (ms), of the fastest of ``runs`` simulations (by
    the median frame; every run's median frame is kept too). ``contact``: a probe presses the box too
    (:func:`_with_probe`), so each rebuild also follows the contact's spread and boundary layer over the cut
    (the ``sim_contact`` rows). ``simulate``: each frame also steps the simulation once after its cut (the
    ``sim_step`` rows: ``sim_step_ms_median`` that step, ``frame_ms_median`` cut, rebuild and step,
    ``refresh_frames`` the frames whose step refreshed the coarse factor)."""
    rows = []
    for _ in range(runs):
        s = TetStructure.from_tetmesh(mesh)
        pressed = 0
        if contact:  # (the contact's field: a box model whose surface is the mesh's, its skeleton inside by
            # the iso distance of its radius)
            inner = 0.5 * SIDE - ISO_DISTANCE * BOX_RADIUS
            sim = wb.Simulation(s, young=3e3, poisson=0.45, density=1000.0, gravity=(0, 0, 0),
                                model=wb.Box((0.5 * SIDE,) * 3, (inner,) * 3, BOX_RADIUS))  # fmt: skip
            pressed = _with_probe(sim)
        else:
            sim = wb.Simulation(s, young=3e3, poisson=0.45, density=1000.0)
        cut_ms, fem_ms, sim_ms, refreshed = [], [], [], 0
        for frame in range(SIM_FRAMES):
            sweep = stroke_step(frame)
            t0 = time.perf_counter()
            result = cut(s, sweep, collect=False)
            t1 = time.perf_counter()
            apply_cut(sim, result)
            t2 = time.perf_counter()
            if simulate:
                sim.step()
            t3 = time.perf_counter()
            if frame:
                cut_ms.append(1e3 * (t1 - t0))
                fem_ms.append(1e3 * (t2 - t1))
                sim_ms.append(1e3 * (t3 - t2))
                refreshed += simulate and sim.stats["coarse_refreshes"] > 0
        total = np.add(cut_ms, fem_ms)
        case = "sim_contact" if contact else "sim_step" if simulate else "sim"
        rows.append({"case": case, "tets": mesh.tet_count, "frames": SIM_FRAMES - 1,
                     "cut_ms_median": float(np.median(cut_ms)), "fem_ms_median": float(np.median(fem_ms)),
                     "step_ms_median": float(np.median(total)), "step_ms_max": float(total.max()),
                     "tets_after": sim.tet_count,
                     **({"contact_nodes": pressed} if contact else {}),
                     **({"sim_step_ms_median": float(np.median(sim_ms)),
                         "frame_ms_median": float(np.median(np.add(total, sim_ms))),
                         "refresh_frames": int(refreshed)} if simulate else {})})  # fmt: skip
    key = "frame_ms_median" if simulate else "step_ms_median"
    best = min(rows, key=lambda row: row[key])
    return {**best, "runs": runs, f"runs_{key}": [row[key] for row in rows]}


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


def run_vtk(mesh: wb.TetMesh, repeat: int, origin=ORIGIN, normal=NORMAL) -> dict:
    grid = vtk_grid(mesh)
    clip_s, sides = wall_time(
        lambda: grid.clip(normal=normal, origin=origin, crinkle=False, return_clipped=True), repeat
    )
    tri_s, tets = wall_time(lambda: [side.triangulate() for side in sides], repeat)
    n = np.asarray(normal) / np.linalg.norm(normal)
    d = (mesh.nodes.astype(np.float64) - origin) @ n
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


#: the drill case: plate (cm), drill radius (cm), frames per stroke, start above / end below the plate (cm)
PLATE, DRILL_RADIUS, DRILL_FRAMES, DRILL_MARGIN = (4.0, 4.0, 0.6), 0.5, 30, 0.1


def plate(tets: int) -> wb.TetMesh:
    """The bone plate in cubes of six tets, about ``tets`` of them."""
    n = max(2, round((tets / 6 * PLATE[0] / PLATE[2]) ** (1 / 3)))
    m = max(1, round(n * PLATE[2] / PLATE[0]))
    return box_tetmesh((0, 0, 0), PLATE, (n, n, m))


def drill_stroke(mesh: wb.TetMesh, segments: int, path=None, radius: float = DRILL_RADIUS,
                 materials=None) -> tuple[dict, TetStructure]:  # fmt: skip
    """One stroke through ``mesh``, a cut per frame as the progressive cutter makes it: per-step ms and counts."""
    drill = wb.tools.Drill(radius, 1.0, segments=segments)
    if path is None:
        centre = (0.5 * PLATE[0] + 0.013, 0.5 * PLATE[1] - 0.007)
        path = wb.tools.Path.line((*centre, PLATE[2] + DRILL_MARGIN), (*centre, -DRILL_MARGIN),
                                  DRILL_FRAMES * FRAME, align=True)  # fmt: skip
    s = TetStructure.from_tetmesh(mesh)
    limit, sticky = len(s.node_rest), np.zeros(0, dtype=np.int64)
    ms, split, result = [], 0, None
    for k in range(1, DRILL_FRAMES + 1):
        sweep = SweepSurface.from_path(drill, path, path.t0, path.t0 + k * FRAME, FRAME)
        t = time.perf_counter()
        result = cut(s, sweep, collect=False, configuration="rest", node_limit=limit, cut_nodes=sticky,
                     materials=materials)  # fmt: skip
        ms.append(1e3 * (time.perf_counter() - t))
        split += result.split_cells
        sticky = result.stroke_cut_nodes(sticky)  # as Cutter keeps them
    return {"step_ms_median": float(np.median(ms)), "step_ms_max": float(np.max(ms)), "tets_split": split,
            "components": result.components, "tets_after": s.cell_count}, s  # fmt: skip


def run_drill(size: int, segments: int) -> dict:
    mesh = plate(size)
    drill_stroke(mesh, segments)  # warm: compiles, fills caches
    row, s = drill_stroke(mesh, segments)
    inverted = int((s.to_tetmesh().volumes() <= 0).sum())
    return {"case": "drill", "tets": mesh.tet_count, "segments": segments, **row, "wb_inverted": inverted}


def run_skull(cellsize: float, segments: int) -> dict:
    """The layered head's skull (``scenes.head_materials``, 66K skull tets at 0.118) drilled at the
    craniotomy's first site by a bone-only drill (radius 0.2), a cut per frame."""
    from warpblob.scenarios._drilling import CRANIOTOMY_SITES, _surface_height

    layers = wb.scenes.head_materials()
    mesh = wb.tetrahedralize(layers["skull"], cellsize=cellsize, materials=layers)
    high = float(mesh.nodes[:, 2].max()) + 0.5
    (x, y) = CRANIOTOMY_SITES[0]
    top, inner = _surface_height(layers["skull"], x, y, high), _surface_height(layers["cerebrospinal fluid"], x, y, high)
    path = wb.tools.Path.line((x, y, top + 0.1), (x, y, inner - cellsize), DRILL_FRAMES * FRAME, align=True)
    drill_stroke(mesh, segments, path, 0.2, {0})  # warm
    row, s = drill_stroke(mesh, segments, path, 0.2, {0})
    inverted = int((s.to_tetmesh().volumes() <= 0).sum())
    return {"case": "skull", "tets": int((mesh.material == 0).sum()), "all_tets": mesh.tet_count,
            "segments": segments, **row, "wb_inverted": inverted}  # fmt: skip


FULL = {"sizes": "10000,100000,1000000", "repeat": 5, "drill_sizes": "10000,66000,500000", "segments": "8,16,32",
        "skull": 0.118}
QUICK = {"sizes": "10000,100000", "repeat": 2, "drill_sizes": "10000", "segments": "16", "skull": 0.0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", help=f"comma-separated tet counts (default {FULL['sizes']})")
    ap.add_argument("--drill-sizes", dest="drill_sizes",
                    help=f"plate tet counts for the drill case, '' for none (default {FULL['drill_sizes']})")
    ap.add_argument("--segments", help=f"drill wall segments (default {FULL['segments']})")
    ap.add_argument("--skull", type=float, help="cell size of the layered head whose skull is drilled, 0 for none "
                    f"(default {FULL['skull']}: 66K skull tets)")  # fmt: skip
    args = arguments(ap, FULL, QUICK, argv)
    gc.freeze()  # the imports' objects out of the garbage collections, as the warpblob command does
    bench = Run("cut", "cutting benchmark: ms per cut, warm, collect=False (gc timed apart)", args)
    planes = {"plane": (ORIGIN, NORMAL), "corner": (CORNER_ORIGIN, CORNER_NORMAL)}
    rows = []
    for size in (int(s) for s in args.sizes.split(",") if s):
        mesh = box(size)
        for case in ("plane", "corner", "stroke"):
            sweep = SweepSurface.plane(*planes[case], SIDE) if case in planes else stroke_step()
            row = {"case": case, "tets": mesh.tet_count, **run_warpblob(mesh, sweep, args.repeat)}
            if case in planes:
                row.update(run_vtk(mesh, args.repeat, *planes[case]))
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
    sims = [run_sim_stroke(box(int(size)), contact=contact) for contact in (False, True)
            for size in args.sizes.split(",") if size]  # fmt: skip
    stepped = [run_sim_stroke(box(int(size)), simulate=True) for size in args.sizes.split(",")
               if size and int(size) <= SIM_STEP_MAX]  # fmt: skip
    print(table(sims, [("case", "case", "s"), ("tets", "tets", ",d"), ("frames", "frames", "d"),
                       ("cut_ms_median", "cut ms", ".1f"), ("fem_ms_median", "fem ms", ".1f"),
                       ("step_ms_median", "cut + fem ms", ".1f"), ("step_ms_max", "max", ".1f")]))  # fmt: skip
    print(f"sim: the scalpel's frames in a simulation of the box ({SIM_FRAMES - 1} frames after a first): each "
          f"frame's strip cut, then apply_cut; medians of the fastest of {SIM_RUNS} simulations (every run's median "
          "frame in the JSON); sim_contact: the same with a probe pressing the box's top (each rebuild also "
          "follows the contact over the cut)")  # fmt: skip
    rows += sims
    if stepped:
        print(table(stepped, [("case", "case", "s"), ("tets", "tets", ",d"), ("cut_ms_median", "cut ms", ".1f"),
                              ("fem_ms_median", "fem ms", ".1f"), ("sim_step_ms_median", "step ms", ".1f"),
                              ("frame_ms_median", "frame ms", ".1f"), ("refresh_frames", "refreshed", "d")]))
        print(f"sim_step: the sim frames with a simulation step after each cut (up to {SIM_STEP_MAX:,} tets); "
              "refreshed: frames whose step rebuilt the coarse factor")  # fmt: skip
    rows += stepped
    drills = [run_drill(int(size), int(n)) for size in args.drill_sizes.split(",") if size
              for n in args.segments.split(",")]  # fmt: skip
    if args.skull:
        drills += [run_skull(args.skull, int(n)) for n in args.segments.split(",")]
    if drills:
        print(table(drills, [("case", "case", "s"), ("tets", "bone tets", ",d"), ("segments", "N", "d"),
                             ("step_ms_median", "ms/step (median)", ".1f"), ("step_ms_max", "max", ".1f"),
                             ("tets_split", "split", "d"), ("components", "pieces", "d"),
                             ("wb_inverted", "inv", "d")]))  # fmt: skip
        print(f"drill: {DRILL_FRAMES} steps of a stroke through the plate, each the whole stroke so far "
              "(the progressive cutter); warm (a first stroke on another copy excluded)")  # fmt: skip
    rows += drills
    print("gc: collect_garbage after the cut, timed apart (not in wb ms); inv: tets with signed volume <= 0 "
          "(wb: whole mesh; vtk: of those made from crossed tets, after triangulate)")  # fmt: skip
    bench.finish({"rows": rows, "box_side": SIDE, "plane": {"origin": ORIGIN, "normal": NORMAL},
                  "corner": {"origin": CORNER_ORIGIN, "normal": CORNER_NORMAL},
                  "stroke": {"speed": SPEED, "frame": FRAME, "edge": EDGE, "above": ABOVE},
                  "drill": {"plate": PLATE, "radius": DRILL_RADIUS, "frames": DRILL_FRAMES,
                            "margin": DRILL_MARGIN}})  # fmt: skip


if __name__ == "__main__":
    main()
