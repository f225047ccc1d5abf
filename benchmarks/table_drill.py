"""The thesis' drilling figures, reproduced: cells added by one hole in the eggshell, skull tets cut by two holes.

Run:  python benchmarks/table_drill.py [--eggshell-cellsize 0.12] [--head-cellsize 0.118]

* Eggshell (the thesis: 2,280 -> 2,400 cells, +5%, 120 new elements, for one
  hole): ``scenes.eggshell()`` meshed at a cell size where its 0.18 wall is
  two to three tets thick (0.12), drilled once through its bottom as
  ``scenarios.drill_eggshell`` does (radius 0.16, 16 wall segments), both as
  one stroke (the thesis' cutter: the stroke cut when it ends) and cut every
  frame of the 30-frame stroke (the progressive cutter: the stroke so far,
  its cut nodes kept cut).
* Skull (the thesis: 845 and 940 tets cut for the two holes of its 66K-tet
  skull): ``scenes.head_materials()`` meshed at 0.118 (66K skull tets),
  drilled at the craniotomy's two sites with bone-only drills
  (``materials={0}``), one stroke each.

Per cut: tets the cut replaced ("removed": the crossed tets and those
re-linked at a cut node), tets split by a table entry ("split"), tets
added, new cells per split tet, and the wall-clock ms of the cut (warm: a
first cut of a copy excluded). Writes benchmarks/results/table_drill.json.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import warpblob as wb  # noqa: E402
from warpblob.cut import SweepSurface, cut  # noqa: E402
from warpblob.mesh import TetStructure  # noqa: E402
from warpblob.scenarios._drilling import (  # noqa: E402
    APPROACH, CRANIOTOMY_SITES, DRILL_RADIUS, EGGSHELL_RADII, OVERSHOOT, _holes, _surface_height)
from _common import load_average, machine, speed_probe, table  # noqa: E402

FRAME, FRAMES = 1.0 / 60.0, 30


def _row(name, before, s, results, seconds):
    split = sum(r.split_cells for r in results)
    added = sum(r.split_added for r in results)
    return {"case": name, "cells_before": before, "cells_after": s.cell_count,
            "increase_percent": 100.0 * (s.cell_count - before) / before, "new_cells": s.cell_count - before,
            "removed": sum(r.tets_removed for r in results), "split": split,
            "new_per_split": added / split if split else 0.0, "cuts": len(results), "ms": 1e3 * seconds,
            "pieces": results[-1].components}  # fmt: skip


def eggshell(cellsize: float) -> list[dict]:
    mesh = wb.tetrahedralize(wb.scenes.eggshell(), cellsize=cellsize)
    (x, y), = _holes(1)
    outer, inner = EGGSHELL_RADII
    near, far = max(np.hypot(x, y) - DRILL_RADIUS, 0.0), np.hypot(x, y) + DRILL_RADIUS
    start, end = -np.sqrt(outer**2 - near**2) - APPROACH, -np.sqrt(inner**2 - far**2) + OVERSHOOT
    drill = wb.tools.Drill(DRILL_RADIUS, 0.6, segments=16)
    path = wb.tools.Path.line((x, y, start), (x, y, end), FRAMES * FRAME, align=True)
    rows = []
    whole = SweepSurface.from_path(drill, path, dt=FRAME)
    cut(TetStructure.from_tetmesh(mesh), whole)  # warm
    s = TetStructure.from_tetmesh(mesh)
    t = time.perf_counter()
    r = cut(s, whole, collect=False)
    rows.append(_row(f"eggshell h={cellsize}, one stroke", mesh.tet_count, s, [r], time.perf_counter() - t))
    s = TetStructure.from_tetmesh(mesh)
    limit, sticky, results, seconds = len(s.node_rest), np.zeros(0, np.int64), [], 0.0
    for k in range(1, FRAMES + 1):
        sweep = SweepSurface.from_path(drill, path, 0.0, k * FRAME, FRAME)
        t = time.perf_counter()
        r = cut(s, sweep, collect=False, configuration="rest", node_limit=limit, cut_nodes=sticky)
        seconds += time.perf_counter() - t
        sticky = r.stroke_cut_nodes(sticky)
        results.append(r)
    row = _row(f"eggshell h={cellsize}, a cut per frame", mesh.tet_count, s, results, seconds)
    row["ms"] = 1e3 * seconds / FRAMES  # per frame
    rows.append(row)
    return rows


def skull(cellsize: float) -> list[dict]:
    layers = wb.scenes.head_materials()
    mesh = wb.tetrahedralize(layers["skull"], cellsize=cellsize, materials=layers)
    high = float(mesh.nodes[:, 2].max()) + 0.5
    drill = wb.tools.Drill(0.2, 0.6, segments=16)
    sweeps = []
    for x, y in CRANIOTOMY_SITES:
        top = _surface_height(layers["skull"], x, y, high)
        inner = _surface_height(layers["cerebrospinal fluid"], x, y, high)
        path = wb.tools.Path.line((x, y, top + 0.1), (x, y, inner - cellsize), FRAMES * FRAME, align=True)
        sweeps.append(SweepSurface.from_path(drill, path, dt=FRAME))
    cut(TetStructure.from_tetmesh(mesh), sweeps[0], materials={0})  # warm
    s = TetStructure.from_tetmesh(mesh)
    skull_tets = int((mesh.material == 0).sum())
    rows = []
    for k, sweep in enumerate(sweeps):
        before = s.cell_count
        t = time.perf_counter()
        r = cut(s, sweep, collect=False, materials={0})
        row = _row(f"skull h={cellsize} ({skull_tets:,} skull tets), hole {k + 1}", before, s, [r],
                   time.perf_counter() - t)  # fmt: skip
        rows.append(row)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--eggshell-cellsize", type=float, default=0.12)
    ap.add_argument("--head-cellsize", type=float, default=0.118)
    ap.add_argument("--json", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                   "table_drill.json"))  # fmt: skip
    args = ap.parse_args(argv)
    load_before, speed_before = load_average(), speed_probe()
    rows = eggshell(args.eggshell_cellsize) + skull(args.head_cellsize)
    cols = [("case", "case", "s"), ("cells_before", "cells", ",d"), ("cells_after", "after", ",d"),
            ("increase_percent", "+%", ".1f"), ("new_cells", "new", ",d"), ("removed", "replaced", ",d"),
            ("split", "split", ",d"), ("new_per_split", "new/split", ".2f"), ("ms", "ms", ".1f"),
            ("pieces", "pieces", "d")]  # fmt: skip
    print(table(rows, cols))
    print("thesis: eggshell 2,280 -> 2,400 cells (+5%, 120 new) for one hole; skull 845 and 940 tets cut for two "
          "holes; ms: the cut (warm), per frame for the cut-per-frame row")  # fmt: skip
    payload = {"benchmark": "table_drill", "rows": rows, "load_average_before": load_before,
               "load_average_after": load_average(), "machine": machine(),
               "speed_probe": {"before": speed_before, "after": speed_probe()},
               "thesis": {"eggshell": {"before": 2280, "after": 2400}, "skull_tets_cut": [845, 940]}}  # fmt: skip
    import json

    tmp = args.json + ".tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, indent=1)
    os.replace(tmp, args.json)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
