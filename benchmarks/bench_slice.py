"""Slicing benchmark: one plane through a closed mesh, both halves capped, warpblob vs trimesh, PyVista, manifold3d.

Run:  python benchmarks/bench_slice.py [--sizes 100000,1000000,5000000] [--models torus,mug,medusa]
      [--repeat 3] [--quick]

Meshes: a grid torus with a hole (cut in its equatorial plane: the section is
an annulus, a loop nested in a loop) and polygonized reference models cut
through the middle (the mug through its handle: the handle's ring is a
hole), at about the given triangle counts.

Peers, each given the same vertices and faces:

* ``trimesh``: ``Trimesh.slice_plane(origin, normal, cap=True)`` with its
  default triangulation engine, once for each half (its call keeps one);
* ``pyvista``: ``PolyData.clip_closed_surface(normal, origin)``, once for
  each half;
* ``manifold3d``: ``Manifold.split_by_plane`` (both halves in one call) and
  ``to_mesh`` of each; the time to build the ``Manifold`` from the arrays is
  reported beside it (``manifold_build_s``).

Every tool is timed the same way (``benchmarks/_common.py``): the wall clock
around the whole job (arrays in, both capped halves out), warm, best of
``--repeat``. A peer whose package is missing is skipped with a note.

Correctness, next to the time: whether each half is a closed, consistently
oriented 2-manifold (after merging points at the same position, which some
peers leave apart at the cap's rim); the relative error of the part below's
volume and of its cap area against an independent reference (each triangle
clipped in float64: the volume by the divergence theorem from a point of the
plane, the section area as minus the sum of the clipped triangles' area
vectors along the normal). A cap drawn over a hole shows as a cap area too
large; a hole left open as a half that is not closed.

``--quick``: 100K triangles, torus and mug, 2 repeats. Writes
benchmarks/results/bench_slice.json with the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import warpblob as wb  # noqa: E402
from warpblob.mesh import SurfaceMesh  # noqa: E402
from warpblob.slice import SNAP  # noqa: E402
from warpblob.slice import slice as slice_mesh  # noqa: E402
from _common import Run, arguments, table, wall_time  # noqa: E402

#: triangles of the mug, medusa at cell size 0.1 / 0.05 (the counts scale as 1 / h^2)
_BASE = {"mug": (0.1, 11_426), "medusa": (0.05, 52_294)}
#: where each mesh is cut: (origin, normal)
PLANES = {
    "torus": ((0.0, 0.0, 0.0123), (0.0, 0.0, 1.0)),
    "mug": ((0.0, 0.0, 1.4), (0.0, 1.0, 0.0)),
    "medusa": (None, (0.3, 0.2, 1.0)),
}


def torus(triangles: int, big: float = 1.0, small: float = 0.4) -> SurfaceMesh:
    """A grid torus about z with about ``triangles`` triangles (2 nu nv, nu = 2 nv)."""
    nv = max(8, int(round(np.sqrt(triangles / 4))))
    nu = 2 * nv
    u, v = np.meshgrid(2 * np.pi * np.arange(nu) / nu, 2 * np.pi * np.arange(nv) / nv, indexing="ij")
    radius = big + small * np.cos(v)
    points = np.stack([radius * np.cos(u), radius * np.sin(u), small * np.sin(v)], -1).reshape(-1, 3)
    normals = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, (i + 1) % nu * nv + j
    c, d = (i + 1) % nu * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    p = points.astype(np.float32)
    return SurfaceMesh(p, faces.astype(np.int32), normals.astype(np.float32), np.full_like(p, 0.8))


def model_mesh(name: str, triangles: int) -> SurfaceMesh:
    h0, n0 = _BASE[name]
    return wb.polygonize(wb.scenes.ALL[name](), cellsize=h0 * float(np.sqrt(n0 / triangles)))


def reference(vertices, faces, origin, normal) -> tuple[float, float]:
    """(volume below, section area) by clipping every triangle in float64."""
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    tri = vertices.astype(np.float64)[faces] - np.asarray(origin, dtype=np.float64)
    d = tri @ n
    whole = np.all(d <= 0, axis=1)
    a, b, c = tri[whole, 0], tri[whole, 1], tri[whole, 2]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    flux = (np.cross(b - a, c - a) @ n).sum() / 2
    for k in np.flatnonzero(~whole & np.any(d < 0, axis=1)):
        poly = []
        for i in range(3):
            p, q, dp, dq = tri[k, i], tri[k, (i + 1) % 3], d[k, i], d[k, (i + 1) % 3]
            if dp <= 0:
                poly.append(p)
            if (dp < 0 < dq) or (dq < 0 < dp):
                poly.append(p + dp / (dp - dq) * (q - p))
        for i in range(1, len(poly) - 1):
            volume += poly[0] @ np.cross(poly[i], poly[i + 1]) / 6
            flux += np.cross(poly[i] - poly[0], poly[i + 1] - poly[0]) @ n / 2
    return float(volume), float(-flux)


def judge(halves, origin, normal, diagonal: float) -> dict:
    """Closedness of both halves, and the part below's volume and cap area: the area of its faces
    within twice warpblob's snap distance of the plane (its caps use vertices within that distance)."""
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    closed = []
    for v, f in halves:
        unique, inverse = np.unique(np.asarray(v, dtype=np.float64), axis=0, return_inverse=True)
        f = inverse.reshape(-1)[np.asarray(f, dtype=np.int64)]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
        u = unique.astype(np.float32)
        closed.append(bool(len(f)) and SurfaceMesh(u, f.astype(np.int32), u, u).is_closed_manifold())
    v, f = halves[0]
    tri = np.asarray(v, dtype=np.float64)[np.asarray(f, dtype=np.int64)]
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    flat = np.all(np.abs((tri - np.asarray(origin)) @ n) <= 2 * SNAP * diagonal, axis=1)
    cap = 0.5 * np.linalg.norm(np.cross(tri[flat, 1] - tri[flat, 0], tri[flat, 2] - tri[flat, 0]), axis=1).sum()
    return {"closed": all(closed), "volume": float(volume), "cap_area": float(cap)}


def run_warpblob(mesh, origin, normal):
    below, above = slice_mesh(mesh, origin, normal)
    return [(below.vertices, below.faces), (above.vertices, above.faces)], below.stats


def run_trimesh(mesh, origin, normal):
    import trimesh

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    n = np.asarray(normal, dtype=np.float64)
    # slice_plane keeps the side the normal points to
    halves = [tm.slice_plane(origin, -n, cap=True), tm.slice_plane(origin, n, cap=True)]
    return [(h.vertices, h.faces) for h in halves], None


def run_pyvista(mesh, origin, normal):
    poly = mesh.to_pyvista()
    n = np.asarray(normal, dtype=np.float64)
    # clip_closed_surface keeps the side the normal points away from
    halves = [poly.clip_closed_surface(normal=tuple(side), origin=origin) for side in (n, -n)]
    return [(np.asarray(h.points), h.triangulate().regular_faces) for h in halves], None


def manifold_of(mesh):
    import manifold3d

    return manifold3d.Manifold(manifold3d.Mesh(vert_properties=mesh.vertices, tri_verts=mesh.faces.astype(np.uint32)))


def run_manifold(solid, origin, normal):
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    above, below = solid.split_by_plane(tuple(n), float(np.dot(n, origin)))
    halves = []
    for part in (below, above):
        m = part.to_mesh()
        halves.append((np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts)))
    return halves, None


FULL = {"sizes": "100000,1000000,5000000", "models": "torus,mug,medusa", "repeat": 3}
QUICK = {"sizes": "100000", "models": "torus,mug", "repeat": 2}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", help=f"comma-separated triangle counts (default {FULL['sizes']})")
    ap.add_argument("--models", help=f"comma-separated: torus and scene names (default {FULL['models']})")
    ap.add_argument("--skip-peers-above", type=int, default=6_000_000, help="skip peers above this many triangles")
    args = arguments(ap, FULL, QUICK, argv)
    bench = Run("slice", "slicing benchmark: one plane, both halves capped, seconds", args)
    rows = []
    for name in args.models.split(","):
        for size in (int(s) for s in args.sizes.split(",")):
            mesh = torus(size) if name == "torus" else model_mesh(name, size)
            origin, normal = PLANES[name]
            if origin is None:
                origin = tuple(float(x) for x in mesh.vertices.mean(axis=0))
            diagonal = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
            volume, section = reference(mesh.vertices, mesh.faces, origin, normal)
            row = {"model": name, "triangles": mesh.face_count, "section_area": section}
            peers = {
                "warpblob": lambda: run_warpblob(mesh, origin, normal),
                "trimesh": lambda: run_trimesh(mesh, origin, normal),
                "pyvista": lambda: run_pyvista(mesh, origin, normal),
            }
            solid = None
            try:
                t0 = time.perf_counter()
                solid = manifold_of(mesh)
                row["manifold_build_s"] = time.perf_counter() - t0
                peers["manifold3d"] = lambda: run_manifold(solid, origin, normal)
            except ImportError as err:
                print(f"  {name} {size}: manifold3d skipped ({err})", flush=True)
            for key, fn in peers.items():
                if key != "warpblob" and mesh.face_count > args.skip_peers_above:
                    continue
                try:
                    seconds, (halves, stats) = wall_time(fn, args.repeat)
                except ImportError as err:
                    print(f"  {name} {size}: {key} skipped ({err})", flush=True)
                    continue
                facts = judge(halves, origin, normal, diagonal)
                row[f"{key}_s"] = seconds
                row[f"{key}_closed"] = facts["closed"]
                row[f"{key}_volume_error"] = abs(facts["volume"] - volume) / abs(mesh.volume())
                row[f"{key}_cap_error"] = abs(facts["cap_area"] - section) / section if section else None
                if stats is not None:
                    row["warpblob_stages"] = stats["seconds"]
                    row["loops"], row["holes"] = stats["section_loops"], stats["section_holes"]
                print(
                    f"  {name} {mesh.face_count:,} triangles: {key} {seconds:.4f} s, closed {facts['closed']}, "
                    f"cap area error {row[f'{key}_cap_error']:.2e}",
                    flush=True,
                )
            peer_names = ("trimesh", "pyvista", "manifold3d")
            correct = [k for k in peer_names if row.get(f"{k}_closed") and (row.get(f"{k}_cap_error") or 0) < 1e-3]
            fastest = min((row[f"{k}_s"] for k in correct), default=None)
            row["speedup_vs_fastest_correct_peer"] = fastest / row["warpblob_s"] if fastest else None
            rows.append(row)
    cols = [("model", "model", "s"), ("triangles", "tris", "d"), ("loops", "loops", "d"), ("holes", "holes", "d")]
    for key, label in (("warpblob", "wb"), ("trimesh", "trimesh"), ("pyvista", "pyvista"), ("manifold3d", "manifold")):
        cols += [(f"{key}_s", f"{label} s", ".4f"), (f"{key}_closed", "closed", "")]
        cols += [(f"{key}_cap_error", "cap err", ".1e")]
    cols += [("manifold_build_s", "manifold build s", ".3f"), ("speedup_vs_fastest_correct_peer", "speedup", ".1f")]
    print(table(rows, cols))
    bench.finish({"rows": rows})


if __name__ == "__main__":
    main()
