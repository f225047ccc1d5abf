"""Field-engine benchmark: every reference model, pruned vs full traversal vs numpy, 1 vs 2 threads.

Run:  python benchmarks/bench_field.py [--points 1000000] [--models tumor,towers]

All timings are warm: every kernel is compiled and run once before timing, and
each figure is the best of three runs. The full traversal and the numpy
reference evaluator visit every node for every point, so they are timed on a
subset of the points (``--slow-points``) and reported as points per second.
Writes benchmarks/results/bench_field.json.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import warpblob as wb  # noqa: E402
from _common import best_of, machine, table, write_json  # noqa: E402
from reference import reference_evaluate  # noqa: E402

THESIS_BYTES = {"per_primitive": 96 + 48, "per_operator": 64}


def run(models, n_points: int, n_slow: int, n_numpy: int) -> list[dict]:
    rng = np.random.default_rng(1)
    rows = []
    for name in models:
        model = wb.scenes.ALL[name]()
        lm = wb.linearize(model)
        lo, hi = lm.bounds
        pts = rng.uniform(lo, hi, (n_points, 3)).astype(np.float32)
        slow = pts[:n_slow]
        for prune, threads in ((True, 1), (True, 2), (False, 2)):
            wb.field(lm, pts[:4096], prune=prune, threads=threads)  # compile and warm up
        t_pruned_1 = best_of(lambda: wb.field(lm, pts, threads=1))
        t_pruned_2 = best_of(lambda: wb.field(lm, pts, threads=2))
        t_full_2 = best_of(lambda: wb.field(lm, slow, prune=False, threads=2), repeat=1)
        t_numpy = best_of(lambda: reference_evaluate(model, pts[:n_numpy].astype(np.float64)), repeat=1)
        assert np.array_equal(wb.field(lm, slow), wb.field(lm, slow, prune=False)), name
        part = lm.nbytes_by_part()
        row = {
            "model": name,
            "primitives": lm.primitive_count,
            "operators": lm.operator_count,
            "depth": lm.depth,
            "pruned_2t": n_points / t_pruned_2,
            "pruned_1t": n_points / t_pruned_1,
            "full_2t": n_slow / t_full_2,
            "numpy": n_numpy / t_numpy,
            "bytes_per_primitive": part["per_primitive"],
            "bytes_per_operator": part["per_operator"],
            "nbytes": lm.nbytes,
        }
        row["pruned_over_full"] = row["pruned_2t"] / row["full_2t"]
        row["threads_2_over_1"] = row["pruned_2t"] / row["pruned_1t"]
        row["pruned_over_numpy"] = row["pruned_2t"] / row["numpy"]
        rows.append(row)
        print(f"  {name}: {row['pruned_2t'] / 1e6:.2f} M points/s", flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000, help="points per model (default 10^6)")
    ap.add_argument("--slow-points", type=int, default=20_000, help="points for the full traversal")
    ap.add_argument("--numpy-points", type=int, default=20_000, help="points for the numpy evaluator")
    ap.add_argument("--models", default=",".join(wb.scenes.ALL), help="comma-separated scene names")
    args = ap.parse_args(argv)
    models = [m for m in args.models.split(",") if m]
    print(f"field benchmark, {args.points} random points per model in its box, warm, best of 3")
    rows = run(models, args.points, args.slow_points, args.numpy_points)
    cols = [
        ("model", "model", "s"),
        ("primitives", "prims", "d"),
        ("operators", "ops", "d"),
        ("pruned_2t", "pruned 2t pts/s", ".3g"),
        ("pruned_1t", "pruned 1t pts/s", ".3g"),
        ("full_2t", "full 2t pts/s", ".3g"),
        ("numpy", "numpy pts/s", ".3g"),
        ("pruned_over_full", "pruned/full", ".1f"),
        ("threads_2_over_1", "2t/1t", ".2f"),
        ("pruned_over_numpy", "pruned/numpy", ".1f"),
        ("bytes_per_primitive", "B/prim", "d"),
        ("bytes_per_operator", "B/op", "d"),
    ]
    print(table(rows, cols))
    print(
        f"bytes per primitive / operator: thesis GPU layout {THESIS_BYTES['per_primitive']} B "
        f"(96 B + 48 B inverse matrix) / {THESIS_BYTES['per_operator']} B"
    )
    path = write_json(
        "bench_field.json",
        {
            "benchmark": "field",
            "warm": True,
            "points": args.points,
            "slow_points": args.slow_points,
            "numpy_points": args.numpy_points,
            "machine": machine(),
            "thesis_bytes": THESIS_BYTES,
            "rows": rows,
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
