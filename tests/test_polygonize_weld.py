"""Welding of short edges: the contraction rules on hand-made meshes, and no needles on the reference models."""

import numpy as np
import pytest
import warp as wp
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

import warpblob as wb
from warpblob.polygonize import _weld

H = 0.1  # the cell size the hand-made meshes are welded at
LIMIT = _weld.WELD * H


def fans_per_vertex(faces) -> np.ndarray:
    """How many separate fans of triangles meet at each vertex (1 on a 2-manifold)."""
    f = np.asarray(faces, dtype=np.int64)
    n = int(f.max()) + 1
    v, b, c = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1), f[:, [2, 0, 1]].reshape(-1)
    # the link of v has an edge b -> c for each of its triangles; its nodes are (v, neighbour)
    nodes, inverse = np.unique(np.concatenate([v * n + b, v * n + c]), return_inverse=True)
    graph = coo_matrix((np.ones(len(v)), (inverse[: len(v)], inverse[len(v) :])), shape=(len(nodes), len(nodes)))
    _, label = connected_components(graph, directed=False)
    return np.bincount(np.unique((nodes // n) * len(nodes) + label) // len(nodes), minlength=n)


def surface(vertices, faces) -> wb.SurfaceMesh:
    v = np.asarray(vertices, np.float32)
    return wb.SurfaceMesh(v, np.asarray(faces, np.int32), v, v)


def triangle_set(vertices, faces) -> set:
    """The triangles as rotation-normalized triples of corner positions (any vertex numbering)."""
    out = set()
    for t in faces:
        corners = [tuple(np.round(vertices[i], 9)) for i in t]
        k = corners.index(min(corners))
        out.add(tuple(corners[k:] + corners[:k]))
    return out


def sphere(levels: int = 2):
    """A unit icosphere-like mesh: an octahedron subdivided ``levels`` times, projected on the sphere."""
    v = [np.array(p, float) for p in [(0, 0, 1), (1, 0, 0), (0, 1, 0), (-1, 0, 0), (0, -1, 0), (0, 0, -1)]]
    f = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 1), (5, 2, 1), (5, 3, 2), (5, 4, 3), (5, 1, 4)]
    for _ in range(levels):
        middle, out = {}, []

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in middle:
                p = v[a] + v[b]
                v.append(p / np.linalg.norm(p))
                middle[key] = len(v) - 1
            return middle[key]

        for a, b, c in f:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            out += [(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)]
        f = out
    return np.array(v), np.array(f, dtype=np.int64)


def link(faces, a):
    """The neighbours of ``a`` in the order of its fan."""
    step = {}
    for t in faces:
        if a in t:
            k = list(t).index(a)
            step[t[(k + 1) % 3]] = t[(k + 2) % 3]
    start = next(iter(step))
    ring = [start]
    while step[ring[-1]] != start:
        ring.append(step[ring[-1]])
    return ring


def split(vertices, faces, a, offset, i, j):
    """Split vertex ``a`` into ``a`` and a new vertex ``b = a + offset``: ``b``
    takes the fan between the ``i``-th and ``j``-th neighbours, and two
    triangles join them (the opposite vertices of the new edge). The inverse
    of contracting that edge."""
    ring = link(faces, a)
    ni, nj = ring[i], ring[j]
    b = len(vertices)
    taken = {(ring[t], ring[(t + 1) % len(ring)]) for t in range(i, j)}
    out = []
    for t in faces:
        t = list(t)
        if a in t:
            k = t.index(a)
            if (t[(k + 1) % 3], t[(k + 2) % 3]) in taken:
                t[k] = b
        out.append(t)
    out += [[a, ni, b], [a, b, nj]]
    return np.vstack([vertices, vertices[a] + offset]), np.array(out, dtype=np.int64)


def weld(vertices, faces, device="cpu"):
    """The weld stage on a mesh whose normals are its positions and colours half of them."""
    data = (vertices, vertices, 0.5 * vertices)  # positions, normals, colours
    arrays = [wp.array(np.asarray(x, np.float32), dtype=wp.vec3, device=device) for x in data]
    tris = wp.array(np.asarray(faces, np.int32), dtype=wp.vec3i, device=device)
    tris, pos, nrm, col, welded = _weld.weld(tris, *arrays, H, device)
    mesh = wb.SurfaceMesh(pos.numpy(), tris.numpy().reshape(-1, 3), nrm.numpy(), col.numpy())
    return mesh, welded


def tangent(vertices, a, size):
    """A vector of length ``size`` in the tangent plane of the unit sphere at vertex ``a``."""
    t = np.cross(vertices[a], [0.3, 0.5, 0.8])
    return size * t / np.linalg.norm(t)


def assert_manifold(mesh):
    assert mesh.is_closed_manifold()
    assert np.all(fans_per_vertex(mesh.faces)[np.unique(mesh.faces)] == 1), "a vertex where two fans meet"
    v = mesh.vertices.astype(np.float64)
    f = mesh.faces
    assert np.all(np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1) > 0.0)


def test_a_split_vertex_is_welded_back(device):
    v, f = sphere()
    a = 0
    split_v, split_f = split(v, f, a, tangent(v, a, 0.3 * LIMIT), 0, 2)
    assert surface(split_v, split_f).is_closed_manifold()
    mesh, welded = weld(split_v, split_f, device)
    assert welded == 1 and mesh.vertex_count == len(v)
    assert triangle_set(mesh.vertices, mesh.faces) == triangle_set(v.astype(np.float32), f)
    np.testing.assert_array_equal(mesh.normals, mesh.vertices)  # vertex data stay with their vertices
    np.testing.assert_array_equal(mesh.colors, np.float32(0.5) * mesh.vertices)


def test_an_edge_just_over_the_weld_length_stays():
    v, f = sphere()
    split_v, split_f = split(v, f, 0, tangent(v, 0, 1.01 * LIMIT), 0, 2)
    mesh, welded = weld(split_v, split_f)
    assert welded == 0 and mesh.face_count == len(split_f)


def test_the_tip_of_a_fold_goes_with_the_edge():
    """A vertex with three neighbours opposite the short edge: once its ends
    meet, its other two triangles lie back to back, so it goes too."""
    v, f = sphere()
    a = 0
    v2, f2 = split(v, f, a, tangent(v, a, 0.3 * LIMIT), 0, 2)
    b = len(v)
    ni = link(f, a)[0]
    # a vertex at the middle of the new triangle (a, ni, b), which becomes three
    x = len(v2)
    v3 = np.vstack([v2, (v2[a] + v2[ni] + v2[b]) / 3.0])
    rest = [t for t in f2.tolist() if sorted(t) != sorted([a, ni, b])]
    f3 = np.array(rest + [[a, ni, x], [ni, b, x], [b, a, x]])
    mesh, welded = weld(v3, f3)
    assert welded == 2 and mesh.vertex_count == len(v)
    assert triangle_set(mesh.vertices, mesh.faces) == triangle_set(v.astype(np.float32), f)
    assert_manifold(mesh)


def test_a_closed_sliver_of_four_vertices_goes_whole():
    v, f = sphere()
    e = 0.5 * LIMIT
    sliver = np.array([[3, 0, 0], [3 + e, 0, 0], [3, 0.1, 0], [3, 0, 0.1]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]) + len(v)
    both_v, both_f = np.vstack([v, sliver]), np.vstack([f, faces])
    assert surface(both_v, both_f).is_closed_manifold()
    mesh, welded = weld(both_v, both_f)
    assert welded == 4
    assert triangle_set(mesh.vertices, mesh.faces) == triangle_set(v.astype(np.float32), f)


def test_a_neck_is_left_alone():
    """On the seven-vertex torus every two vertices are neighbours: the ends of
    any edge have five common neighbours, not just the two opposite ones, and
    contracting one would pinch the surface (the link condition fails)."""
    i = np.arange(7)
    faces = np.vstack([np.column_stack([i, (i + 1) % 7, (i + 3) % 7]), np.column_stack([i, (i + 3) % 7, (i + 2) % 7])])
    angle = 2 * np.pi * np.arange(7) / 7
    v = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(7)])
    v[1] = v[0] + [0.0, 0.0, 0.5 * LIMIT]
    torus = surface(v, faces)
    assert torus.is_closed_manifold() and len(torus.edge_face_counts()[0]) == 21
    mesh, welded = weld(v, faces)
    assert welded == 0
    np.testing.assert_array_equal(mesh.faces, faces)


def test_a_short_edge_on_a_boundary_is_left_alone():
    v, f = sphere()
    v2, f2 = split(v, f, 0, tangent(v, 0, 0.3 * LIMIT), 0, 2)
    # open the mesh at a triangle of vertex 0 that does not hold the new edge
    drop = next(k for k, t in enumerate(f2.tolist()) if 0 in t and len(v) not in t)
    opened = np.delete(f2, drop, axis=0)
    mesh, welded = weld(v2, opened)
    assert welded == 0 and mesh.face_count == len(opened)


def test_a_chain_of_short_edges_moves_no_vertex_farther_than_the_weld_length():
    """Three vertices in a row, 0.8 of the weld length apart: the first two
    weld (the third, 1.6 of it from the first, stays) or, when the tie of
    equal lengths puts the second edge first, both ends weld onto the middle
    one; either way every vertex that went has a kept one within the weld
    length."""
    v, f = sphere()
    a = 0
    d = tangent(v, a, 0.8 * LIMIT)
    v2, f2 = split(v, f, a, d, 0, 2)
    b = len(v)
    v3, f3 = split(v2, f2, b, d, 1, 3)
    mesh, welded = weld(v3, f3)
    assert welded in (1, 2)
    assert_manifold(mesh)
    kept = mesh.vertices.astype(np.float64)
    # every kept vertex is an original one, exactly
    assert cKDTree(v3.astype(np.float32)).query(kept)[0].max() == 0.0
    assert cKDTree(kept).query(v3.astype(np.float32))[0].max() <= LIMIT * (1 + 1e-6)


def test_many_clusters_at_once_stay_manifold():
    """Every vertex of a sphere split in a random direction: hundreds of
    contractions in rounds, each with its neighbours, give back the sphere."""
    rng = np.random.default_rng(1)
    v, f = sphere(3)
    sv, sf = v, f
    for a in rng.permutation(len(v))[:40]:
        ring = link(sf, a)
        i = int(rng.integers(0, len(ring)))
        j = i + int(rng.integers(2, len(ring) - 1))
        if j >= len(ring):
            continue
        sv, sf = split(sv, sf, a, tangent(v, a, rng.uniform(0.0, 0.9) * LIMIT), i, j)
    mesh, welded = weld(sv, sf)
    assert welded == len(sv) - len(v)
    assert triangle_set(mesh.vertices, mesh.faces) == triangle_set(v.astype(np.float32), f)


def reference_cases():
    """The reference models at the cell sizes the tests and the demo use, and head at 0.06."""
    cases = [(name, 0.14 if name in ("towers", "medusa") else 0.08) for name in wb.scenes.ALL]
    return cases + [("head", 0.06), ("mug", 0.05)]


@pytest.mark.parametrize("name, h", reference_cases())
def test_reference_models_have_no_needles(name, h, monkeypatch):
    """No triangle under 1 degree; closed and manifold at every vertex; every
    vertex on the surface; without relaxation, every vertex is one the root
    search placed (none moved) and every vertex the weld removed lies within
    the weld length of a kept one, or was the tip of a fold."""
    model = wb.scenes.ALL[name]()
    mesh = wb.polygonize(model, cellsize=h)
    assert mesh.min_angles().min() >= 1.0, f"{np.sum(mesh.min_angles() < 1.0)} triangles under 1 degree"
    assert_manifold(mesh)
    assert mesh.volume() > 0.0
    assert np.abs(wb.field(model, mesh.vertices) - 0.5).max() <= 1e-4
    welded = wb.polygonize(model, cellsize=h, relax=False)
    limit = _weld.WELD * h
    monkeypatch.setattr(_weld, "WELD", 0.0)  # coincident corners only
    raw = wb.polygonize(model, cellsize=h, relax=False)
    assert cKDTree(raw.vertices).query(welded.vertices)[0].max() == 0.0
    # the others are within the weld length of a kept vertex, or were the tip of a fold (or of
    # a closed sliver): three neighbours or fewer once those welded together (within twice the
    # weld length of each other) count as one
    far = np.flatnonzero(cKDTree(welded.vertices).query(raw.vertices)[0] > limit * (1 + 1e-5))
    for x in far:
        ring = np.unique(raw.faces[np.any(raw.faces == x, axis=1)])
        ring = ring[ring != x]
        gaps = np.linalg.norm(raw.vertices[ring][:, None] - raw.vertices[ring][None], axis=2)
        groups = connected_components(coo_matrix(gaps <= 2 * limit * (1 + 1e-5)), directed=False)[0]
        assert groups <= 3 and groups < len(ring), f"vertex {x} went with {len(ring)} neighbours in {groups} groups"


def test_the_weld_kernel_and_the_vectorized_rounds_weld_the_same_patch():
    """The one-thread kernel (contract_patch, what weld runs) and the
    vectorized rounds (contract) follow the same rules: both give back the
    sphere whose vertices were split, one fan at every vertex."""
    rng = np.random.default_rng(5)
    v, f = sphere(3)
    sv, sf = v, f
    for a in rng.permutation(len(v))[:30]:
        ring = link(sf, a)
        i = int(rng.integers(0, len(ring)))
        j = i + int(rng.integers(2, len(ring) - 1))
        if j >= len(ring):
            continue
        sv, sf = split(sv, sf, a, tangent(v, a, rng.uniform(0.0, 0.9) * LIMIT), i, j)
    valence = np.bincount(sf.reshape(-1), minlength=len(sv))
    candidate = np.ones(len(sv), dtype=bool)
    expected = triangle_set(v.astype(np.float32), f)
    for fn in (_weld.contract, _weld.contract_patch):
        corners, alive = fn(sf, sv, candidate, valence, LIMIT)
        kept = corners[alive]
        used, local = np.unique(kept, return_inverse=True)
        assert len(used) == len(v)
        assert triangle_set(sv[used].astype(np.float32), local.reshape(-1, 3)) == expected
        assert np.all(fans_per_vertex(local.reshape(-1, 3)) == 1)


def test_vertex_valence_counts_every_triangle_at_a_vertex(device):
    """The contraction's fan sizes against numpy's bincount, on a mesh large enough that the CPU's
    range-split launches would cut it into pieces (the count must not lose increments between threads)."""
    mesh = wb.polygonize(wb.scenes.mug(), cellsize=0.05, relax=False, device="cpu")
    faces = np.asarray(mesh.faces, np.int32)
    tris = wp.array(faces, dtype=wp.vec3i, device=device)
    valence = _weld.vertex_valence(tris, mesh.vertex_count, device).numpy()
    np.testing.assert_array_equal(valence, np.bincount(faces.reshape(-1), minlength=mesh.vertex_count))


def test_the_weld_leaves_its_inputs_alone_unless_told_and_gives_the_same_mesh_in_place(device):
    """Many clusters welded at once: by default the four input arrays keep their contents; ``in_place``
    edits them and returns views of them holding the same mesh as the copy."""
    rng = np.random.default_rng(7)
    v, f = sphere(3)
    sv, sf = v, f
    for a in rng.permutation(len(v))[:30]:
        ring = link(sf, a)
        j = 2 + int(rng.integers(0, len(ring) - 3))
        sv, sf = split(sv, sf, a, tangent(v, a, 0.5 * LIMIT), 0, j)
    data = [np.asarray(x, np.float32) for x in (sv, sv, 0.5 * sv)]

    def arrays():
        return (wp.array(np.asarray(sf, np.int32), dtype=wp.vec3i, device=device),
                *[wp.array(x, dtype=wp.vec3, device=device) for x in data])  # fmt: skip

    given = arrays()
    copy = _weld.weld(*given, H, device)
    np.testing.assert_array_equal(given[0].numpy(), np.asarray(sf, np.int32))
    for arr, x in zip(given[1:], data):
        np.testing.assert_array_equal(arr.numpy(), x)
    edited = arrays()
    inplace = _weld.weld(*edited, H, device, in_place=True)
    assert copy[4] == inplace[4] == len(sv) - len(v)
    for a, b in zip(copy[:4], inplace[:4]):
        np.testing.assert_array_equal(a.numpy(), b.numpy())
    assert inplace[1].ptr == edited[1].ptr  # a view of the array given, not a copy
