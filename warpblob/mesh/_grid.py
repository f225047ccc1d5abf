"""Structured tet meshes of boxes: the analytic test bodies of the simulator (beams, blocks).

Each grid cube is split into six tets around its main diagonal (Kuhn's
triangulation, Freudenthal 1942): the tets are the monotone lattice paths
from the cube's lowest corner to its highest, so neighbouring cubes cut
their shared faces along the same diagonal and the mesh is conforming.
"""

from __future__ import annotations

import itertools

import numpy as np

from .._errors import MeshError
from ._tetmesh import TetMesh

__all__ = ["box_tetmesh"]


def box_tetmesh(lower, upper, shape) -> TetMesh:
    """The box ``[lower, upper]`` as a grid of ``shape`` cubes (cuboids), six positive tets each.

    Args:
        lower, upper: (3,) opposite corners, ``lower < upper`` on every axis.
        shape: (3,) positive cell counts along x, y, z.

    Returns:
        A conforming :class:`TetMesh` with ``prod(shape + 1)`` nodes (x
        fastest) and ``6 prod(shape)`` tets.

    Raises:
        MeshError: bad corners or cell counts (the message shows the value).

    Example:
        >>> from warpblob.mesh import box_tetmesh
        >>> mesh = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (5, 1, 1))
        >>> mesh.node_count, mesh.tet_count, round(mesh.volume(), 6), mesh.is_conforming()
        (24, 30, 0.04, True)
    """
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    finite = lo.shape == hi.shape == (3,) and np.isfinite(lo).all() and np.isfinite(hi).all()
    if not finite or np.any(hi <= lo):
        raise MeshError(f"box_tetmesh: need finite (3,) corners with lower < upper, got {lower!r}, {upper!r}")
    n = np.asarray(shape)
    if n.shape != (3,) or not np.issubdtype(n.dtype, np.integer) or np.any(n < 1):
        raise MeshError(f"box_tetmesh: shape must be three positive integers, got {shape!r}")
    nx, ny, nz = (int(a) for a in n)
    axes = [np.linspace(lo[d], hi[d], int(n[d]) + 1) for d in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    nodes = np.stack([x, y, z], axis=-1).reshape(-1, 3)
    ids = np.arange((nx + 1) * (ny + 1) * (nz + 1)).reshape(nz + 1, ny + 1, nx + 1)
    k, j, i = (a.ravel() for a in np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij"))
    # corner b of a cube: bit 0 steps x, bit 1 y, bit 2 z
    corner = np.stack([ids[k + (b >> 2 & 1), j + (b >> 1 & 1), i + (b & 1)] for b in range(8)], axis=-1)
    tets = []
    for steps in itertools.permutations((1, 2, 4)):
        path = np.cumsum((0, *steps))
        tet = corner[:, path]
        # a path's orientation is the parity of its axis order
        if np.linalg.det(np.eye(3)[[int(np.log2(s)) for s in steps]]) < 0:
            tet = tet[:, [0, 2, 1, 3]]
        tets.append(tet)
    return TetMesh(nodes.astype(np.float32), np.stack(tets, axis=1).reshape(-1, 4).astype(np.int32))
