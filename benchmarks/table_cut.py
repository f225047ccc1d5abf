"""Reproduction of the thesis' Table 6.4 (SPEC section 6): peanut and tumor before and after three planar cuts.

Run:  python benchmarks/table_cut.py [--json PATH]

Each model is tetrahedralized (isosurface stuffing, uniform lattice) at the
cell size whose tet count is nearest the thesis' mesh (peanut 18,124 cells,
tumor 32,911; the cell sizes were found by bisection and are fixed below),
then cut three times through the centre of its box: horizontally (normal z),
vertically (normal x) and diagonally (normal (1, 1, 1)), each plane a square
wider than the model (the ``warpblob cut`` command's), snap 0.2 (the thesis'
h = 20%). Printed as a markdown table next to the thesis' figures:

* nodes / edges / faces / cells of the ``TetStructure`` (live ones);
* Vmax/Vmin (tet volumes), lmax/lmin (the longest edge over the shortest);
* min aspect ratio: the thesis' figure, a measure that is 1 for a regular
  tet and falls to 0 as it flattens; here ``1 / beta`` of the worst tet
  (``beta = CR / (3 IR)``, :mod:`warpblob.mesh._quality`), and beta itself;
* the smallest dihedral angle;
* new cells per intersected cell: the sub-tets the split tets were replaced
  by, over the split tets (A, B, X, Y and the progressive kinds; not the
  intact tets re-linked to a cut node's copy), over all three cuts.

Writes benchmarks/results/table_cut.json.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import warpblob as wb  # noqa: E402
from warpblob.cut import cut  # noqa: E402
from warpblob.cut._command import _sweep  # noqa: E402
from _common import RESULTS, load_average, machine, speed_probe, write_json  # noqa: E402
from bench_cut import SPLIT_KINDS  # noqa: E402

#: cell size giving a tet count nearest the thesis' mesh, and the thesis' figures (SPEC section 6)
MODELS = {
    "peanut": (0.0865, {
        "before": {"nodes": 4437, "edges": 25420, "faces": 39108, "cells": 18124, "volume_ratio": 84.9,
                   "edge_ratio": 42.4, "aspect_ratio": 3e-7},
        "after": {"nodes": 8933, "edges": 46466, "faces": 67388, "cells": 28322, "volume_ratio": 58.3,
                  "edge_ratio": 47.5, "aspect_ratio": 3e-7},
    }),
    "tumor": (0.114, {
        "before": {"nodes": 8035, "edges": 46121, "faces": 70998, "cells": 32911, "volume_ratio": 316.9,
                   "edge_ratio": 40.0, "aspect_ratio": 1e-6},
        "after": {"nodes": 15821, "edges": 82711, "faces": 120212, "cells": 50605, "volume_ratio": 287.6,
                  "edge_ratio": 130.6, "aspect_ratio": 1e-6},
    }),
}  # fmt: skip
#: the thesis' new cells per intersected cell, averaged over its cuts
THESIS_NEW_PER_CUT = 3.6
NORMALS = {"horizontal": (0.0, 0.0, 1.0), "vertical": (1.0, 0.0, 0.0), "diagonal": (1.0, 1.0, 1.0)}
SNAP = 0.2


def measure(structure: wb.TetStructure) -> dict:
    """Counts and quality of the live mesh."""
    q = structure.to_tetmesh().quality()
    return {
        "nodes": structure.node_count, "edges": structure.edge_count, "faces": structure.face_count,
        "cells": structure.cell_count, "volume_ratio": q.volume_ratio, "edge_ratio": q.edge_ratio,
        "aspect_ratio": 1.0 / q.aspect_ratio_max, "beta_max": q.aspect_ratio_max, "dihedral_min": q.dihedral_min,
        "inverted": q.inverted_count, "volume": q.volume,
    }  # fmt: skip


def reproduce(name: str) -> dict:
    h, _ = MODELS[name]
    mesh = wb.tetrahedralize(wb.scenes.ALL[name](), cellsize=h)
    structure = wb.TetStructure.from_tetmesh(mesh)
    lo, hi = mesh.nodes.min(axis=0).astype(np.float64), mesh.nodes.max(axis=0).astype(np.float64)
    centre = 0.5 * (lo + hi)
    before = measure(structure)
    cuts, split, made = [], 0, 0
    for label, normal in NORMALS.items():
        n = np.asarray(normal) / np.linalg.norm(normal)
        r = cut(structure, _sweep(centre, n, lo, hi), snap=SNAP)
        k = sum(r.tets_split.get(kind, 0) for kind in SPLIT_KINDS)
        sub = r.tets_added - (r.tets_removed - k)  # every intact tet that was re-linked comes back as one
        split, made = split + k, made + sub
        cuts.append({"plane": label, "normal": n.tolist(), "split": k, "sub_tets": sub, **r.summary()})
    after = measure(structure)
    return {"cellsize": h, "centre": centre.tolist(), "before": before, "after": after, "cuts": cuts,
            "new_per_cut": made / split if split else None, "components": cuts[-1]["components"]}  # fmt: skip


ROWS = [
    ("nodes", "nodes", ",d"), ("edges", "edges", ",d"), ("faces", "faces", ",d"), ("cells", "cells", ",d"),
    ("volume_ratio", "Vmax/Vmin", ".1f"), ("edge_ratio", "lmax/lmin", ".1f"),
    ("aspect_ratio", "min aspect ratio (1/beta)", ".2g"), ("beta_max", "beta max (1 = regular)", ".3g"),
    ("dihedral_min", "min dihedral (deg)", ".1f"),
]  # fmt: skip


def markdown(results: dict) -> str:
    """The table: one column pair (ours, thesis) per model and state."""
    heads, columns = [], []
    for name, res in results.items():
        for state, title in (("before", name), ("after", f"{name}, 3 cuts")):
            heads += [title, "thesis"]
            columns.append((res[state], MODELS[name][1][state]))
    lines = ["| | " + " | ".join(heads) + " |", "|---" * (len(heads) + 1) + "|"]
    for key, label, fmt in ROWS:
        cells = []
        for ours, thesis in columns:
            cells += [format(ours[key], fmt), format(thesis[key], fmt) if key in thesis else ""]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    cells = []
    for name, res in results.items():
        cells += ["", "", f"{res['new_per_cut']:.2f}", f"{THESIS_NEW_PER_CUT}"]
    lines.append("| new cells per intersected cell | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", default=os.path.join(RESULTS, "table_cut.json"), help="results file")
    args = ap.parse_args(argv)
    load_before, speed_before = load_average(), speed_probe()
    results = {name: reproduce(name) for name in MODELS}
    print(markdown(results))
    for name, res in results.items():
        b, a = res["before"], res["after"]
        print(f"{name}: h = {res['cellsize']}, {res['components']} pieces, inverted tets {a['inverted']}, volume "
              f"{b['volume']:.6g} -> {a['volume']:.6g}; per cut (split, sub-tets, kinds): "
              + "; ".join(f"{c['plane']} {c['split']}, {c['sub_tets']}, {c['tets_split']}" for c in res["cuts"]))  # fmt: skip
    write_json(args.json, {"table": "thesis Table 6.4", "snap": SNAP, "machine": machine(), "models": results,
                           "load_average_before": load_before, "load_average_after": load_average(),
                           "speed_probe": {"before": speed_before, "after": speed_probe()},
                           "thesis": {n: m[1] for n, m in MODELS.items()}, "thesis_new_per_cut": THESIS_NEW_PER_CUT})  # fmt: skip
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
