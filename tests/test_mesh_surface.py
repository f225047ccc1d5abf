"""SurfaceMesh topology: closed 2-manifold (edges and vertex fans), shells (connected components), repr.

The references are written here independently of the library: a per-vertex
walk around each fan in plain Python, and scipy's connected components (or
a breadth-first search) over the face adjacency.
"""

from collections import deque

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

import warpblob as wb
from warpblob.mesh import SurfaceMesh
from warpblob.mesh._surface import _components

# ---------------------------------------------------------------------------
# small closed meshes, counter-clockwise seen from outside
# ---------------------------------------------------------------------------

TET_VERTICES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
TET_FACES = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
# a unit cube: corner b has coordinates (b & 1, b >> 1 & 1, b >> 2 & 1); two triangles per side
CUBE_VERTICES = np.array([[b & 1, b >> 1 & 1, b >> 2 & 1] for b in range(8)], dtype=np.float32)
CUBE_FACES = np.array(
    [[0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6], [0, 1, 5], [0, 5, 4],
     [2, 6, 7], [2, 7, 3], [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5]]
)  # fmt: skip


def mesh_of(vertices, faces):
    v = np.asarray(vertices, dtype=np.float32)
    return SurfaceMesh(v, np.asarray(faces, dtype=np.int32), np.zeros_like(v), np.ones_like(v))


def joined(*parts):
    """One mesh holding every (vertices, faces) part, vertices renumbered."""
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(np.asarray(f) + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


def welded(vertices, faces):
    """Merge coincident vertices (how two solids come to share a corner)."""
    unique, inverse = np.unique(np.round(vertices, 6), axis=0, return_inverse=True)
    return unique.astype(np.float32), inverse.reshape(-1)[faces]


def reference_closed_manifold(vertices, faces) -> bool:
    """Brute force: every directed edge once with its reverse once, and one fan per used vertex."""
    faces = [tuple(int(x) for x in f) for f in faces]
    if not faces or any(len(set(f)) < 3 for f in faces):
        return False
    directed = {}
    for i, (a, b, c) in enumerate(faces):
        for u, w in ((a, b), (b, c), (c, a)):
            if (u, w) in directed:
                return False
            directed[(u, w)] = i
    if any((w, u) not in directed for (u, w) in directed):
        return False
    # around v: from the face (v, a, b) go to the face holding v -> b; count the closed loops
    corners = {}
    for a, b, c in faces:
        corners.setdefault(a, []).append((b, c))
        corners.setdefault(b, []).append((c, a))
        corners.setdefault(c, []).append((a, b))
    for v, fan in corners.items():
        next_of = {a: b for a, b in fan}
        start = fan[0][0]
        seen, a = 0, start
        while True:
            a = next_of[a]
            seen += 1
            if a == start:
                break
        if seen != len(fan):
            return False
    return True


def reference_shells(faces) -> int:
    """Breadth-first search over faces sharing an edge."""
    by_edge = {}
    for i, f in enumerate(faces.tolist()):
        for u, w in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            by_edge.setdefault((min(u, w), max(u, w)), []).append(i)
    seen = np.zeros(len(faces), dtype=bool)
    count = 0
    for s in range(len(faces)):
        if seen[s]:
            continue
        count += 1
        seen[s] = True
        queue = deque([s])
        while queue:
            f = faces[queue.popleft()].tolist()
            for u, w in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
                for g in by_edge[(min(u, w), max(u, w))]:
                    if not seen[g]:
                        seen[g] = True
                        queue.append(g)
    return count


# ---------------------------------------------------------------------------
# closed 2-manifold
# ---------------------------------------------------------------------------


def pinched_tetrahedra():
    """Two tets touching at one corner: every edge in two faces, yet the corner is two fans."""
    mirrored = -TET_VERTICES
    return welded(*joined((TET_VERTICES, TET_FACES), (mirrored, TET_FACES[:, ::-1])))


def cubes_sharing_a_corner():
    """Two unit cubes meeting at the corner (1, 1, 1) only."""
    return welded(*joined((CUBE_VERTICES, CUBE_FACES), (CUBE_VERTICES + 1.0, CUBE_FACES)))


def test_closed_solids_are_manifold():
    for vertices, faces in ((TET_VERTICES, TET_FACES), (CUBE_VERTICES, CUBE_FACES)):
        assert reference_closed_manifold(vertices, faces)
        assert mesh_of(vertices, faces).is_closed_manifold()
    # two disjoint cubes: two shells, each a manifold
    two = joined((CUBE_VERTICES, CUBE_FACES), (CUBE_VERTICES + 3.0, CUBE_FACES))
    assert mesh_of(*two).is_closed_manifold()


@pytest.mark.parametrize("make, corners", [(pinched_tetrahedra, 4), (cubes_sharing_a_corner, 8)])
def test_pinched_vertex_is_not_a_manifold(make, corners):
    vertices, faces = make()
    assert len(vertices) == 2 * corners - 1, "test set-up: the two solids share exactly one vertex"
    mesh = mesh_of(vertices, faces)
    # every edge is in exactly two faces, once each way: the edge test alone would accept it
    _, counts = mesh.edge_face_counts()
    assert np.all(counts == 2)
    assert not reference_closed_manifold(vertices, faces)
    assert not mesh.is_closed_manifold()


@pytest.mark.parametrize(
    "edit",
    [
        lambda f: f[1:],  # a hole
        lambda f: np.concatenate([f[:1, ::-1], f[1:]]),  # one face turned over
        lambda f: np.concatenate([f, f[:1]]),  # a face twice
        lambda f: np.concatenate([f[:-1], [[f[-1, 0], f[-1, 0], f[-1, 1]]]]),  # a degenerate face
        lambda f: f[:0],  # no faces
    ],
    ids=["hole", "flipped", "duplicate", "degenerate", "empty"],
)
def test_broken_cube_is_not_a_closed_manifold(edit):
    faces = edit(CUBE_FACES.copy())
    assert not reference_closed_manifold(CUBE_VERTICES, faces)
    assert not mesh_of(CUBE_VERTICES, faces).is_closed_manifold()


def test_unused_vertices_are_ignored_and_inputs_untouched():
    vertices = np.concatenate([CUBE_VERTICES, [[5.0, 5.0, 5.0]]]).astype(np.float32)
    faces = CUBE_FACES.astype(np.int32)
    before = faces.copy()
    mesh = mesh_of(vertices, faces)
    assert mesh.is_closed_manifold() and mesh.shell_count() == 1
    np.testing.assert_array_equal(mesh.faces, before)


@pytest.mark.parametrize("name, cellsize", [("tumor", 0.1), ("eggshell", 0.1), ("mug", 0.08), ("head", 0.1)])
def test_polygonized_scenes_agree_with_the_reference(name, cellsize):
    mesh = wb.polygonize(wb.scenes.ALL[name](), cellsize=cellsize)
    assert mesh.is_closed_manifold()
    if mesh.face_count < 60_000:  # the reference is plain Python
        assert reference_closed_manifold(mesh.vertices, mesh.faces)


def test_random_pinches_of_a_polygonized_mesh_are_found():
    """Weld a vertex of one sphere onto a vertex of another: a pinched vertex the fans must reveal."""
    sphere = wb.polygonize(wb.Point((0, 0, 0), 1.0), cellsize=0.15)
    top = int(np.argmax(sphere.vertices[:, 2]))
    bottom = int(np.argmin(sphere.vertices[:, 2]))
    shift = sphere.vertices[top] - sphere.vertices[bottom]
    vertices, faces = joined((sphere.vertices, sphere.faces), (sphere.vertices + shift, sphere.faces))
    n = sphere.vertex_count
    faces = np.where(faces == n + bottom, top, faces)  # the second sphere's bottom is the first one's top
    assert not reference_closed_manifold(vertices, faces)
    assert not mesh_of(vertices, faces).is_closed_manifold()


# ---------------------------------------------------------------------------
# shells
# ---------------------------------------------------------------------------


def test_components_match_scipy():
    rng = np.random.default_rng(3)
    for count, edges in ((1, 0), (50, 0), (1000, 600), (1000, 990), (5000, 20000)):
        a, b = rng.integers(0, count, (2, edges))
        graph = coo_matrix((np.ones(edges), (a, b)), shape=(count, count))
        n, expected = connected_components(graph, directed=False)
        label = _components(count, a, b)
        assert np.unique(label).size == n
        # the same partition: labels map one to one
        pairs = np.unique(np.stack([label, expected]), axis=1)
        assert pairs.shape[1] == n
        assert np.all(label <= np.arange(count)) and np.all(label[label] == label)  # smallest member names it
    # a long path numbered backwards: the worst order for hooking to the smaller root
    count = 100_000
    path = np.arange(count - 1, 0, -1)
    assert np.all(_components(count, path, path - 1) == 0)


def test_shells_of_solids():
    assert mesh_of(CUBE_VERTICES, CUBE_FACES).shell_count() == 1
    three = joined(*[(CUBE_VERTICES + 2.0 * k, CUBE_FACES) for k in range(3)])
    mesh = mesh_of(*three)
    assert mesh.shell_count() == 3
    np.testing.assert_array_equal(mesh.shells(), np.repeat([0, 1, 2], len(CUBE_FACES)))
    assert mesh_of(CUBE_VERTICES, CUBE_FACES[:0]).shell_count() == 0
    # pinched solids touch at a vertex only: two shells (faces join across edges)
    assert mesh_of(*cubes_sharing_a_corner()).shell_count() == 2


@pytest.mark.parametrize("name, cellsize", [("eggshell", 0.2), ("head", 0.1), ("towers", 0.14)])
def test_shells_match_scipy_on_polygonized_scenes(name, cellsize):
    """Scenes with many spurious shells at a coarse cell size (eggshell, head) or many real ones (towers)."""
    mesh = wb.polygonize(wb.scenes.ALL[name](), cellsize=cellsize)
    f = mesh.faces.astype(np.int64)
    # faces -> vertices incidence; faces sharing a vertex are linked (the same as sharing an edge on a manifold)
    rows = np.repeat(np.arange(mesh.face_count), 3)
    incidence = coo_matrix((np.ones(rows.size), (rows, f.ravel())), shape=(mesh.face_count, mesh.vertex_count))
    n, _ = connected_components((incidence @ incidence.T).tocsr(), directed=False)
    assert mesh.is_closed_manifold()
    assert mesh.shell_count() == n > 1
    if mesh.face_count < 40_000:
        assert reference_shells(mesh.faces) == n


# ---------------------------------------------------------------------------
# repr
# ---------------------------------------------------------------------------


def test_repr_is_a_short_summary():
    mesh = wb.polygonize(wb.scenes.tumor(), cellsize=0.08)
    text = repr(mesh)
    assert len(text) < 400 and len(text.splitlines()) <= 4
    assert f"{mesh.vertex_count:,} vertices" in text and f"{mesh.face_count:,} triangles" in text
    lo, hi = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    assert f"x [{lo[0]:.4g}, {hi[0]:.4g}]" in text and f"z [{lo[2]:.4g}, {hi[2]:.4g}]" in text
    assert "0 vertices, 0 triangles" in repr(mesh_of(np.zeros((0, 3)), np.zeros((0, 3), dtype=int)))
