"""Tetrahedral meshing benchmark: warpblob's isosurface stuffing vs fTetWild and TetGen.

Run:  python benchmarks/bench_tetrahedralize.py [--models tumor,peanut,cake,three_slabs] [--cellsize 0.1]
      [--peers pytetwild,tetgen] [--repeat 3] [--quick]

warpblob goes model in, mesh out (field evaluation included). The peers mesh
warpblob's own polygonized surface of the same model at the same cellsize
(``warpblob.polygonize``, a closed manifold); their seconds exclude the
polygonization (reported apart, it is milliseconds). Each peer is tuned to
about warpblob's node count: one run with a first guess of its size
parameter, then the timed runs with the parameter scaled by the cube root of
the node-count ratio.

* ``pytetwild`` (fTetWild, MPL-2.0): ``edge_length_abs``, first guess the cellsize;
* ``tetgen`` (TetGen, AGPL-3.0, benchmark-only peer, never imported by the
  library): quality mesh (``-q``, radius-edge ratio 2) with a volume bound
  (``-a``), first guess twice the BCC tet volume ``cellsize^3 / 12``. TetGen
  keeps the input triangles, and marching-cubes surfaces have skinny ones, so
  its boundary tets can be slivers and its node count has a floor set by the
  surface (the table shows what it reached).

A peer that is not installed is skipped with a note. Peer tets are
reoriented to positive volume before measuring (conventions differ); that is
not timed. Every mesh gets the thesis' measures (SPEC 3): counts, min/max
dihedral angle, Vmax/Vmin, lmax/lmin, worst aspect ratio, and its volume
against a Monte Carlo estimate of the implicit volume (``--samples`` points
of ``warpblob.field``). Every tool is timed the same way: the wall clock
around its whole call, warm (a first call with the same arguments excluded),
best of ``--repeat`` (see ``benchmarks/_common.py``); warpblob's ``stats``
seconds per stage of its fastest call are kept as the breakdown.
``--quick``: peanut at 0.14, one timed call per tool. Writes
benchmarks/results/bench_tetrahedralize.json with the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import Run, arguments, table, wall_time

import warpblob as wb
from warpblob.mesh._tetmesh import TetMesh
from warpblob.tetrahedralize import tetrahedralize

THESIS_TETS_AT_0_1 = {"tumor": 130_000, "three_slabs": 120_000, "cake": 85_000}  # SPEC 3


def positive(nodes: np.ndarray, tets: np.ndarray) -> TetMesh:
    p = nodes[tets]
    vol = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets = tets.copy()
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    return TetMesh(nodes.astype(np.float32), tets.astype(np.int32))


def measure(mesh: TetMesh, seconds: float, volume: float) -> dict:
    q = mesh.quality()
    return {
        "s": seconds,
        "tets": mesh.tet_count,
        "nodes": mesh.node_count,
        "dihedral_min": q.dihedral_min,
        "dihedral_max": q.dihedral_max,
        "volume_ratio": q.volume_ratio,
        "edge_ratio": q.edge_ratio,
        "aspect_max": q.aspect_ratio_max,
        "inverted": q.inverted_count,
        "volume_error": mesh.volume() / volume - 1.0,
    }


def run_pytetwild(surface, size):
    import pytetwild

    # fTetWild leaves a __tracked_surface.stl in the working folder: run it in a scratch one
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as scratch:
        os.chdir(scratch)
        try:
            return pytetwild.tetrahedralize(
                surface.vertices.astype(np.float64), surface.faces.astype(np.int32), edge_length_abs=size, quiet=True
            )
        finally:
            os.chdir(cwd)


def run_tetgen(surface, size):
    import tetgen

    gen = tetgen.TetGen(surface.vertices.astype(np.float64), surface.faces.astype(np.int32))
    nodes, tets, *_ = gen.tetrahedralize(quality=True, fixedvolume=True, maxvolume=size, quiet=True)
    return nodes, tets


#: name: (runner returning (nodes, tets), first size guess from the cellsize, size exponent in length units)
PEERS = {
    "pytetwild": (run_pytetwild, lambda h: h, 1.0),
    "tetgen": (run_tetgen, lambda h: 2.0 * h**3 / 12.0, 3.0),
}


def run_peer(name, surface, h, target_nodes, repeat):
    """(mesh, seconds, size): the peer tuned to ``target_nodes`` nodes, timed by :func:`wall_time`."""
    runner, guess, power = PEERS[name]
    size = guess(h)
    first = positive(*runner(surface, size))
    # node count ~ size^(-3 / power): scale the size to meet warpblob's node count
    size *= (first.node_count / target_nodes) ** (power / 3.0)
    seconds, (nodes, tets) = wall_time(lambda: runner(surface, size), repeat)
    return positive(nodes, tets), seconds, size


FULL = {"models": "tumor,peanut,cake,three_slabs", "cellsize": 0.1, "peers": "pytetwild,tetgen", "samples": 1_000_000,
        "repeat": 3}  # fmt: skip
QUICK = {"models": "peanut", "cellsize": 0.14, "peers": "pytetwild,tetgen", "samples": 200_000, "repeat": 1}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", help=f"comma-separated scene names (default {FULL['models']})")
    ap.add_argument("--cellsize", type=float, help=f"lattice cell size (default {FULL['cellsize']})")
    ap.add_argument("--peers", help=f"comma-separated, empty for none (default {FULL['peers']})")
    ap.add_argument("--samples", type=int, help="Monte Carlo points for the implicit volume (default 10^6)")
    args = arguments(ap, FULL, QUICK, argv)
    h = args.cellsize
    peers = [p for p in args.peers.split(",") if p]
    if set(peers) - set(PEERS):
        ap.error(f"--peers: unknown {sorted(set(peers) - set(PEERS))}, choose from {sorted(PEERS)}")
    rows = []
    bench = Run("tetrahedralize", f"tetrahedral meshing benchmark, cellsize {h}, peers on warpblob's surface", args)
    for name in args.models.split(","):
        model = wb.scenes.ALL[name]()
        lm = wb.linearize(model)
        volume = wb.monte_carlo_volume(model, samples=args.samples).volume
        seconds, mesh = wall_time(lambda lm=lm: tetrahedralize(lm, cellsize=h), args.repeat)
        st = mesh.stats
        rows.append(
            {"model": name, "cellsize": h, "tool": "warpblob", **measure(mesh, seconds, volume),
             "field_evaluations": st["field_evaluations"], "stats_seconds": st["seconds"],
             "stats_total_s": st["total_seconds"], "stats_wall_s": st["wall_seconds"],
             "thesis_tets": THESIS_TETS_AT_0_1.get(name)}
        )  # fmt: skip
        stages = f"stages {st['total_seconds']:.3f} s"
        print(f"  {name}: warpblob {seconds:.3f} s ({stages}), {mesh.tet_count} tets", flush=True)
        surface_s, surface = wall_time(lambda lm=lm: wb.polygonize(lm, cellsize=h), args.repeat)
        for peer in peers:
            try:
                peer_mesh, peer_s, size = run_peer(peer, surface, h, mesh.node_count, args.repeat)
            except ImportError as err:
                print(f"  {name}: {peer} skipped ({err})", flush=True)
                continue
            rows.append(
                {"model": name, "cellsize": h, "tool": peer, **measure(peer_mesh, peer_s, volume),
                 "size_parameter": size, "surface_s": surface_s, "surface_triangles": surface.face_count,
                 "speedup_of_warpblob": peer_s / seconds}
            )  # fmt: skip
            print(f"  {name}: {peer} {peer_s:.3f} s, {peer_mesh.tet_count} tets", flush=True)
    cols = [
        ("model", "model", "s"),
        ("tool", "tool", "s"),
        ("s", "seconds", ".3f"),
        ("tets", "tets", "d"),
        ("nodes", "nodes", "d"),
        ("dihedral_min", "min dih", ".1f"),
        ("dihedral_max", "max dih", ".1f"),
        ("volume_ratio", "Vmax/Vmin", ".3g"),
        ("edge_ratio", "lmax/lmin", ".3g"),
        ("aspect_max", "max beta", ".3g"),
        ("volume_error", "vol err", "+.2%"),
        ("speedup_of_warpblob", "wb speedup", ".0f"),
        ("thesis_tets", "thesis tets", "d"),
    ]
    print(table(rows, cols))
    bench.finish({"cellsize": h, "samples": args.samples, "rows": rows})


if __name__ == "__main__":
    main()
