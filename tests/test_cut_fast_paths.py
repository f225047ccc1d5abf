"""The cutter's fast paths against their plain counterparts: the few-triangle intersection against the BVH's,
the packed-sort unique against numpy's, the component kernel against a graph library."""

import numpy as np
import pytest
import warp as wp
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from warpblob.cut import SweepSurface, cut
from warpblob.cut import _kernels as k
from warpblob.cut._cut import _boxes
from warpblob.mesh import TetStructure, box_tetmesh
from warpblob.mesh._structure import _unique_first


def _intersect(kernel, edges, positions, sweep, device):
    (lowers, uppers), corners = _boxes(sweep, device)
    n = len(edges)
    inputs = [wp.array(edges, dtype=wp.vec2i, device=device), wp.ones(n, dtype=wp.uint8, device=device),
              wp.array(positions, dtype=wp.vec3, device=device)]  # fmt: skip
    bvh = None
    if kernel is k.intersect_edges_kernel:
        bvh = wp.Bvh(lowers, uppers)
        inputs += [bvh.id, corners, 0]
    else:
        inputs += [lowers, uppers, corners, 0]
    out = [wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device),
           wp.empty(n, dtype=wp.int32, device=device)]  # fmt: skip
    wp.launch(kernel, dim=n, inputs=inputs + out, device=device)
    return [a.numpy() for a in out]


def test_few_triangle_intersection_is_the_bvh_one(device):
    """Random edges against a curved 14-triangle strip: the same first hits, parameters and flags."""
    rng = np.random.default_rng(7)
    s = np.linspace(0, 1, 8)
    a = np.column_stack([s, 0.3 * np.sin(3 * s), np.zeros_like(s)])
    sweep = SweepSurface.from_blade(a, a + (0.1, 0.2, 1.0))
    assert sweep.triangle_count == 14
    positions = rng.uniform(-0.2, 1.2, (600, 3)).astype(np.float32)
    edges = rng.integers(0, 600, (4000, 2)).astype(np.int32)
    edges = edges[edges[:, 0] != edges[:, 1]]
    few = _intersect(k.intersect_edges_few_kernel, edges, positions, sweep, device)
    tree = _intersect(k.intersect_edges_kernel, edges, positions, sweep, device)
    assert few[2].sum() > 50  # many hits
    for x, y in zip(few, tree):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(few[2], (few[0] >= 0).astype(np.int32))


@pytest.mark.parametrize("top", [1_000, 1 << 50])
def test_packed_unique_is_numpys(top):
    """Small keys take the packed sort, keys too wide for it take numpy's own unique: the same triple."""
    keys = np.random.default_rng(3).integers(0, top, 5000).astype(np.int64)
    want = np.unique(keys, return_index=True, return_inverse=True)
    got = _unique_first(keys, len(keys))
    for x, y in zip(want, got):
        np.testing.assert_array_equal(np.ravel(x), np.ravel(y))


def test_components_match_a_graph_reference():
    """Two crossing planar cuts: the kernel's labels are the connected components of the face graph, numbered
    by lowest cell, -1 for the dead cells; the count alone agrees."""
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (4, 4, 4)))
    cut(s, SweepSurface.plane((0.51, 0.5, 0.5), (1, 0.1, 0), 3.0), collect=False)
    cut(s, SweepSurface.plane((0.5, 0.5, 0.49), (0, 0.1, 1), 3.0), collect=False)
    labels = s.components()
    alive = np.asarray(s.cell_alive)
    fc = np.asarray(s.face_cells)[np.asarray(s.face_alive)]
    fc = fc[(fc >= 0).all(axis=1)]
    C = len(alive)
    graph = coo_matrix((np.ones(len(fc)), (fc[:, 0], fc[:, 1])), shape=(C, C))
    _, ref = connected_components(graph, directed=False)
    assert np.all(labels[~alive] == -1)
    live = np.flatnonzero(alive)
    # same partition of the live cells, pieces numbered in the order of their lowest cell
    _, first = np.unique(ref[live], return_index=True)
    order = np.argsort(first)
    renumber = np.empty(len(order), dtype=np.int64)
    renumber[order] = np.arange(len(order))
    _, ref_dense = np.unique(ref[live], return_inverse=True)
    np.testing.assert_array_equal(labels[live], renumber[ref_dense.ravel()])
    assert labels.max() + 1 == 4 == s._component_count()
