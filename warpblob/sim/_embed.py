"""Embedding of a surface in the volume mesh by barycentric coordinates (the surface rides on the tets).

Each surface vertex is bound to the rest tet that contains it (the most
interior one when it lies on shared faces) or, outside the volume, to the
nearest tet, found by a ``wp.Bvh`` over the rest tets' bounding boxes; its
barycentric coordinates in that tet are kept unclamped, so the map from tet
corners to the vertex is affine and reproduces every rigid motion of the
tet exactly (the classic embedded-surface scheme of skinning and of
Müller et al. 2004, "Interactive virtual materials").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .._errors import SimulationError
from . import _kernels as k
from ._solver import NODE_GRAIN, split_launch

__all__ = ["Embedding", "embed"]


@dataclass(eq=False)
class Embedding:
    """A surface bound to the volume.

    Attributes:
        mesh: the bound :class:`~warpblob.mesh.SurfaceMesh` (its rest shape).
        tet: (V,) int32 tet of each vertex.
        bary: (V, 4) float32 barycentric coordinates in that tet (sum 1;
            negative entries for vertices outside the volume).
        distance: (V,) float32 rest distance from the vertex to its tet (0 inside).
    """

    mesh: object
    tet: np.ndarray
    bary: np.ndarray
    distance: np.ndarray
    _tet_wp: wp.array = None
    _bary_wp: wp.array = None
    _out: wp.array = None


def embed(elements, mesh, *, threads=None) -> Embedding:
    """Bind ``mesh`` (a SurfaceMesh, or anything with (V, 3) ``vertices``) to the rest tets of ``elements``.

    Raises:
        SimulationError: ``mesh`` has no (V, 3) finite vertices, or no tet is alive.
    """
    vertices = getattr(mesh, "vertices", None)
    if vertices is None:
        raise SimulationError(f"surface: expected a SurfaceMesh (with vertices), got {type(mesh).__name__}")
    pts = np.asarray(vertices, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise SimulationError(f"surface: vertices must have shape (V, 3), got {pts.shape}")
    bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if bad.size:
        raise SimulationError(f"surface: vertex {bad[0]} = {pts[bad[0]].tolist()} is not finite")
    e, dev = elements, elements.device
    if not e.alive_host.any():
        raise SimulationError("surface: the volume has no live tet to embed in")
    T, V = e.tet_count, len(pts)
    lowers = wp.empty(T, dtype=wp.vec3, device=dev)
    uppers = wp.empty(T, dtype=wp.vec3, device=dev)
    split_launch(k.tet_bounds_kernel, T, [e.rest, e.tets, e.volume], [lowers, uppers], dev, threads, NODE_GRAIN)
    bvh = wp.Bvh(lowers, uppers)
    # start the search at the median tet size: most vertices are found in the first round
    live = e.alive_host & (e.volume.numpy() > 0)
    extent = (uppers.numpy()[live] - lowers.numpy()[live]).max(axis=1)
    radius = float(max(np.median(extent), 1e-12)) * 0.5
    points = wp.array(pts, dtype=wp.vec3, device=dev)
    tet = wp.empty(V, dtype=wp.int32, device=dev)
    bary = wp.empty(V, dtype=wp.vec4, device=dev)
    distance = wp.empty(V, dtype=float, device=dev)
    split_launch(k.embed_points_kernel, V, [bvh.id, points, e.rest, e.tets, e.dm_inv, radius], [tet, bary, distance],
                 dev, threads, 512)  # fmt: skip
    # host sync: the binding is returned as numpy arrays
    return Embedding(mesh, tet.numpy().copy(), bary.numpy().copy(), distance.numpy().copy(), tet, bary,
                     wp.empty(V, dtype=wp.vec3, device=dev))  # fmt: skip


def interpolate(embedding: Embedding, elements, x: wp.array, *, threads=None) -> np.ndarray:
    """The embedded vertices at node positions ``x`` (one kernel), (V, 3) float32."""
    V = len(embedding.tet)
    split_launch(k.interpolate_points_kernel, V, [x, elements.tets, embedding._tet_wp, embedding._bary_wp],
                 [embedding._out], elements.device, threads, NODE_GRAIN)  # fmt: skip
    return embedding._out.numpy().copy()
