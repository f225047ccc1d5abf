"""Field-engine benchmark: every reference model, pruned vs full traversal vs numpy, 1 vs 2 threads.

Run:  python benchmarks/bench_field.py [--points 1000000] [--models tumor,towers] [--repeat 3] [--quick]

Each figure times whole calls of ``warpblob.field`` (numpy points in, numpy
values out) by the wall clock, warm (a first call excluded), best of
``--repeat`` (see ``benchmarks/_common.py``). The full traversal and the
numpy reference evaluator visit every node for every point, so they are timed
on a subset of the points (``--slow-points``, ``--numpy-points``) and every
figure is reported as points per second. ``--quick``: 10^5 points, three
models. Writes benchmarks/results/bench_field.json with the load average
before and after.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import warpblob as wb  # noqa: E402
from _common import Run, arguments, table, wall_time  # noqa: E402
from reference import reference_evaluate  # noqa: E402

THESIS_BYTES = {"per_primitive": 96 + 48, "per_operator": 64}


def run(models, n_points: int, n_slow: int, n_numpy: int, repeat: int) -> list[dict]:
    rng = np.random.default_rng(1)
    rows = []
    for name in models:
        model = wb.scenes.ALL[name]()
        lm = wb.linearize(model)
        lo, hi = lm.bounds
        pts = rng.uniform(lo, hi, (n_points, 3)).astype(np.float32)
        slow = pts[:n_slow]
        t_pruned_1, _ = wall_time(lambda: wb.field(lm, pts, threads=1), repeat)
        t_pruned_2, _ = wall_time(lambda: wb.field(lm, pts, threads=2), repeat)
        t_full_2, _ = wall_time(lambda: wb.field(lm, slow, prune=False, threads=2), repeat)
        t_numpy, _ = wall_time(lambda: reference_evaluate(model, pts[:n_numpy].astype(np.float64)), repeat)
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


FULL = {"points": 1_000_000, "slow_points": 20_000, "numpy_points": 20_000, "models": ",".join(wb.scenes.ALL),
        "repeat": 3}  # fmt: skip
QUICK = {"points": 100_000, "slow_points": 2_000, "numpy_points": 2_000, "models": "peanut,tumor,cake", "repeat": 2}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, help="points per model (default 10^6)")
    ap.add_argument("--slow-points", type=int, help="points for the full traversal (default 20000)")
    ap.add_argument("--numpy-points", type=int, help="points for the numpy evaluator (default 20000)")
    ap.add_argument("--models", help="comma-separated scene names (default all)")
    args = arguments(ap, FULL, QUICK, argv)
    models = [m for m in args.models.split(",") if m]
    bench = Run("field", f"field benchmark, {args.points} random points per model in its box", args)
    rows = run(models, args.points, args.slow_points, args.numpy_points, args.repeat)
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
    bench.finish(
        {
            "points": args.points,
            "slow_points": args.slow_points,
            "numpy_points": args.numpy_points,
            "thesis_bytes": THESIS_BYTES,
            "rows": rows,
        }
    )


if __name__ == "__main__":
    main()
