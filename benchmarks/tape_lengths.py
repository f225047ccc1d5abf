"""Per-block tape lengths: how much a block-pruned tape would drop, on the reference models.

Run:  python benchmarks/tape_lengths.py [--models towers,medusa] [--cellsizes 0.14,0.05] [--quick]

Issue 18 asks for per-block tapes: the primitives whose boxes miss a block
dropped for the samples, roots and normals in it. This measures what such a
tape would hold before anyone builds it. For each polygonizer block (8^3
cells) that holds surface vertices it counts the primitives whose boxes meet
the block (the pruned tape's leaves: what an array-mode root step, one tree
walk per block for all its vertices, would box-test per vertex), against the
primitives whose boxes hold a vertex (what a point-mode root step evaluates
after its per-cell operand lists have pruned the rest), sampled over 20,000
vertices. Boxes are the linearized model's (``lower`` / ``upper`` of the
leaves, world frame: the models have no warps). No timing: counts only, so
the load does not matter. Writes benchmarks/results/bench_tape_lengths.json.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

import warpblob as wb  # noqa: E402
from _common import Run, arguments, table  # noqa: E402
from warpblob.polygonize._kernels import BLOCK  # noqa: E402
from warpblob.tree import _kinds  # noqa: E402

FULL = {"models": "tumor,mug,medusa,towers", "cellsizes": "0.14,0.05", "repeat": 1}
QUICK = {"models": "tumor", "cellsizes": "0.14", "repeat": 1}
SAMPLED_VERTICES = 20_000


def boxes_meeting(lo: np.ndarray, hi: np.ndarray, leaf_lo: np.ndarray, leaf_hi: np.ndarray, chunk: int = 256):
    """Per query box ``(lo[i], hi[i])`` ((n, 3) each), how many leaf boxes it meets (closed boxes)."""
    out = np.zeros(len(lo), dtype=np.int64)
    for s in range(0, len(lo), chunk):
        a, b = lo[s : s + chunk, None], hi[s : s + chunk, None]
        out[s : s + chunk] = np.all((leaf_lo[None] <= b) & (leaf_hi[None] >= a), axis=2).sum(axis=1)
    return out


def measure(name: str, h: float) -> dict:
    lm = wb.linearize(wb.scenes.ALL[name]())
    mesh = wb.polygonize(lm, cellsize=h, relax=False)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    origin = np.asarray(lm.bounds[0], dtype=np.float64) - 0.5 * h  # the polygonizer's grid origin
    leaf = np.nonzero(lm.kind < _kinds.PRIMITIVE_KIND_END)[0]
    leaf_lo, leaf_hi = lm.lower[leaf].astype(np.float64), lm.upper[leaf].astype(np.float64)
    side = BLOCK * h
    keys, inverse, per_block_vertices = np.unique(
        np.floor((v - origin) / side).astype(np.int64), axis=0, return_inverse=True, return_counts=True
    )
    block_lo = origin + keys * side
    tape = boxes_meeting(block_lo, block_lo + side, leaf_lo, leaf_hi)
    rng = np.random.default_rng(0)
    pick = rng.choice(len(v), size=min(SAMPLED_VERTICES, len(v)), replace=False)
    holding = boxes_meeting(v[pick], v[pick], leaf_lo, leaf_hi)
    return {
        "model": name,
        "cellsize": h,
        "nodes": int(lm.node_count),
        "leaves": int(len(leaf)),
        "vertices": int(len(v)),
        "blocks_with_vertices": int(len(keys)),
        "vertices_per_block_mean": float(per_block_vertices.mean()),
        "tape_leaves_mean": float(tape.mean()),
        "tape_leaves_max": int(tape.max()),
        # what an array-mode root step box-tests per vertex: its block's tape
        "tape_leaves_per_vertex": float(np.average(tape, weights=per_block_vertices)),
        "leaves_holding_vertex_mean": float(holding.mean()),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", help=f"comma-separated scene names (default {FULL['models']})")
    ap.add_argument("--cellsizes", help=f"comma-separated (default {FULL['cellsizes']})")
    args = arguments(ap, FULL, QUICK, argv)
    bench = Run("tape_lengths", "per-block tape lengths of the polygonizer's blocks (counts, no timing)", args)
    rows = []
    for name in args.models.split(","):
        for h in (float(c) for c in args.cellsizes.split(",")):
            rows.append(measure(name, h))
            print(f"  {name} h = {h}: done", flush=True)
    cols = [
        ("model", "model", "s"), ("cellsize", "h", ".2f"), ("leaves", "leaves", "d"),
        ("blocks_with_vertices", "blocks", "d"), ("vertices_per_block_mean", "vertices/block", ".0f"),
        ("tape_leaves_mean", "tape leaves/block", ".1f"), ("tape_leaves_max", "max", "d"),
        ("tape_leaves_per_vertex", "tape leaves/vertex", ".1f"),
        ("leaves_holding_vertex_mean", "leaves holding a vertex", ".2f"),
    ]  # fmt: skip
    print(table(rows, cols))
    bench.finish({"rows": rows})


if __name__ == "__main__":
    main()
