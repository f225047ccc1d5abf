"""The edge-based tet structure (SPEC section 4): build, links both ways, lookup, rings, edits, events, GC.

Invariants are checked by brute force written here (Python loops over every
entity of small meshes), independently of :meth:`TetStructure.check`.
"""

import time
from collections import deque

import numpy as np
import pytest
import warp as wp
from test_tetmesh import canonical, cube_mesh, grid_mesh, positive

import warpblob as wb
from warpblob.mesh._structure import DELETED, TetStructure, TetStructureArrays, lookup_edge
from warpblob.mesh._tetmesh import TET_EDGES, TET_FACES, TetMesh

# ---------------------------------------------------------------------------
# brute-force references
# ---------------------------------------------------------------------------


def live(s, kind):
    return [int(i) for i in np.flatnonzero(getattr(s, f"{kind}_alive"))]


def assert_consistent(s):
    """Every link both ways, no dangling reference, lookup of every live edge and of no dead one."""
    nodes, edges, faces, cells = (set(live(s, k)) for k in ("node", "edge", "face", "cell"))
    node_edges = {v: set() for v in nodes}
    edge_faces = {e: set() for e in edges}
    face_cells = {f: set() for f in faces}
    for e in edges:
        a, b = s.edge_nodes[e].tolist()
        assert a != b and {a, b} <= nodes, f"edge {e}"
        assert s.find_edge(a, b) == e and s.find_edge(b, a) == e
        node_edges[a].add(e)
        node_edges[b].add(e)
    for f in faces:
        fn, fe = s.face_nodes[f].tolist(), s.face_edges[f].tolist()
        assert set(fn) <= nodes and len(set(fn)) == 3 and set(fe) <= edges, f"face {f}"
        for j in range(3):
            assert set(s.edge_nodes[fe[j]].tolist()) == {fn[j], fn[(j + 1) % 3]}, f"face {f} edge {j}"
            edge_faces[fe[j]].add(f)
    for c in cells:
        cn, cf, ce = s.cell_nodes[c].tolist(), s.cell_faces[c].tolist(), s.cell_edges[c].tolist()
        assert set(cn) <= nodes and set(cf) <= faces and set(ce) <= edges, f"cell {c}"
        for k in range(4):
            assert set(s.face_nodes[cf[k]].tolist()) == set(cn) - {cn[k]}, f"cell {c} face {k}"
            face_cells[cf[k]].add(c)
        for j, (a, b) in enumerate(TET_EDGES):
            assert set(s.edge_nodes[ce[j]].tolist()) == {cn[a], cn[b]}, f"cell {c} edge {j}"
    for v in nodes:
        assert s.edges_of_node(v).tolist() == sorted(node_edges[v]), f"node {v}"
    for e in edges:
        assert s.faces_of_edge(e).tolist() == sorted(edge_faces[e]), f"edge {e}"
    for f in faces:
        slots = s.face_cells[f].tolist()
        assert sorted(s.cells_of_face(f).tolist()) == sorted(face_cells[f]) and len(face_cells[f]) <= 2
        assert slots[0] >= 0 or slots[1] < 0, f"face {f} slots {slots}"
    for e in set(range(len(s.edge_alive))) - edges:
        a, b = s.edge_nodes[e].tolist()
        assert s.find_edge(a, b) != e, f"dead edge {e} still found"


def bfs_ring(s, start, k):
    adjacency = {}
    for e in live(s, "edge"):
        a, b = s.edge_nodes[e].tolist()
        adjacency.setdefault(a, set()).add(b)
        adjacency.setdefault(b, set()).add(a)
    depth = {start: 0}
    queue = deque([start])
    while queue:
        u = queue.popleft()
        if depth[u] == k:
            continue
        for w in adjacency.get(u, ()):
            if w not in depth:
                depth[w] = depth[u] + 1
                queue.append(w)
    return sorted(set(depth) - {start})


def euler(s):
    return s.node_count - s.edge_count + s.face_count - s.cell_count


# ---------------------------------------------------------------------------
# building
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("make", [cube_mesh, lambda: grid_mesh(3)])
def test_build_matches_the_mesh(make, device):
    mesh = make()
    s = TetStructure.from_tetmesh(mesh, device=device)
    assert_consistent(s)
    s.check()
    np.testing.assert_array_equal(s.cell_nodes, mesh.tets)
    np.testing.assert_array_equal(s.node_rest, mesh.nodes)
    np.testing.assert_array_equal(s.node_position, mesh.nodes)
    np.testing.assert_array_equal(s.cell_material, mesh.material if mesh.material is not None else 0)
    assert euler(s) == 1  # a ball
    faces = mesh.tets[:, TET_FACES].reshape(-1, 3)
    assert s.face_count == len({tuple(sorted(f)) for f in faces.tolist()})
    assert s.edge_count == len({tuple(sorted(e)) for e in mesh.tets[:, TET_EDGES].reshape(-1, 2).tolist()})
    # boundary faces (one cell) are the mesh's surface, oriented outward from their cell
    boundary = np.flatnonzero(s.face_cells[:, 1] < 0)
    assert canonical(s.face_nodes[boundary]) == canonical(mesh.surface_faces())
    # every face is oriented outward from its first cell
    for f in range(s.face_count):
        c = s.face_cells[f, 0]
        k = s.cell_faces[c].tolist().index(f)
        assert canonical([s.face_nodes[f]]) == canonical([mesh.tets[c][TET_FACES[k]]])


def test_structured_grid_counts():
    n = 10
    s = TetStructure.from_tetmesh(grid_mesh(n))
    assert (s.node_count, s.cell_count) == ((n + 1) ** 3, 6 * n**3)
    # edges: 3 n (n+1)^2 axis edges, one diagonal per square face, one per cube
    assert s.edge_count == 3 * n * (n + 1) ** 2 + 3 * n * n * (n + 1) + n**3
    assert euler(s) == 1
    s.check()


def test_build_100k_tets_is_fast():
    TetStructure.from_tetmesh(grid_mesh(2))  # kernels compiled outside the timing
    mesh = grid_mesh(26)  # 105,456 tets
    start = time.perf_counter()
    s = TetStructure.from_tetmesh(mesh)
    seconds = time.perf_counter() - start
    assert s.cell_count == 105_456 and euler(s) == 1
    assert seconds < 2.0, f"building the structure of 105,456 tets took {seconds:.2f} s"
    assert s.stats["seconds"] <= seconds


def test_split_launches_build_the_same_structure():
    mesh = grid_mesh(8)  # 3,072 tets: every stage is split across threads
    one, two = TetStructure.from_tetmesh(mesh, threads=1), TetStructure.from_tetmesh(mesh, threads=2)
    for name in ("edge_nodes", "face_nodes", "face_edges", "face_cells", "cell_faces", "cell_edges"):
        np.testing.assert_array_equal(getattr(one, name), getattr(two, name))
    two.check()


def test_empty_mesh_builds_an_empty_structure():
    s = TetStructure.from_tetmesh(TetMesh(np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int32)))
    assert (s.node_count, s.edge_count, s.face_count, s.cell_count) == (0, 0, 0, 0)
    s.check()
    assert s.find_edge(0, 1) == -1 and s.collect_garbage()["cell"].shape == (0,)


def test_non_manifold_face_is_refused():
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [0.2, 0.2, 0.5]], dtype=np.float32)
    mesh = TetMesh(nodes, positive(nodes, [[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 2, 5]]))
    with pytest.raises(wb.WarpblobError, match="shared by 3 tets"):
        TetStructure.from_tetmesh(mesh)


def test_empty_structure_grows_by_inserts():
    s = TetStructure()
    assert (s.node_count, s.edge_count, s.face_count, s.cell_count) == (0, 0, 0, 0)
    mesh = grid_mesh(2)
    for p in mesh.nodes:
        s.insert_node(p)
    for tet in mesh.tets:  # 48 cells, 98 edges: the lookup table and every store grow several times
        s.insert_cell(*tet.tolist())
    assert_consistent(s)
    s.check()
    assert euler(s) == 1 and s.cell_count == 48
    built = TetStructure.from_tetmesh(mesh)
    assert (s.edge_count, s.face_count) == (built.edge_count, built.face_count)


# ---------------------------------------------------------------------------
# lookup and rings
# ---------------------------------------------------------------------------


@wp.kernel
def lookup_kernel(s: TetStructureArrays, pairs: wp.array(dtype=wp.vec2i), found: wp.array(dtype=wp.int32)):
    i = wp.tid()
    found[i] = lookup_edge(s, pairs[i][1], pairs[i][0])


def test_edge_lookup_host_and_kernel(device):
    s = TetStructure.from_tetmesh(grid_mesh(4))
    pairs = s.edge_nodes.copy()
    ids = np.arange(len(pairs), dtype=np.int32)
    assert [s.find_edge(a, b) for a, b in pairs.tolist()] == ids.tolist()
    np.testing.assert_array_equal(s.find_edges(pairs[:, ::-1], device=device), ids)
    arrays = s.to_warp(device)
    found = wp.empty(len(pairs), dtype=wp.int32, device=device)
    wp.launch(lookup_kernel, len(pairs), inputs=[arrays, wp.array(pairs, dtype=wp.vec2i, device=device), found])
    np.testing.assert_array_equal(found.numpy(), ids)
    # node pairs that are no edge: the other diagonal of a cube and of a square (node (x, y, z) is
    # 25 x + 5 y + z), opposite corners of the box, a node with itself
    non = np.array([[25, 6], [25, 5], [0, 124], [3, 3]], dtype=np.int32)
    assert [s.find_edge(a, b) for a, b in non.tolist()] == [-1] * 4
    np.testing.assert_array_equal(s.find_edges(non, device=device), [-1] * 4)
    assert s.edge_key(7, 3) == s.edge_key(3, 7) == (7 << 32) | 3


def test_rings_match_breadth_first_search():
    s = TetStructure.from_tetmesh(grid_mesh(4))
    rng = np.random.default_rng(3)
    for v in rng.choice(s.node_count, 6, replace=False).tolist():
        assert s.one_ring(v).tolist() == bfs_ring(s, v, 1)
        for k in (0, 2, 3):
            ring = s.k_ring(v, k)
            assert ring.dtype == np.int32 and ring.tolist() == bfs_ring(s, v, k)
    assert s.k_ring(0, 12).size == s.node_count - 1
    with pytest.raises(wb.WarpblobError, match="k must be a non-negative integer"):
        s.k_ring(0, -1)


def test_views_read_the_arrays():
    s = TetStructure.from_tetmesh(cube_mesh())
    c = s.cell(4)
    assert c.alive and c.material == 1 and c.nodes.tolist() == s.cell_nodes[4].tolist()
    f = s.face(int(c.faces[0]))
    assert 4 in f.cells.tolist() and set(f.nodes.tolist()) == set(c.nodes.tolist()[1:])
    e = s.edge(int(f.edges[0]))
    assert int(f.index) in e.faces.tolist()
    v = s.node(int(e.nodes[0]))
    assert e.index in v.edges.tolist() and v.rest.tolist() == v.position.tolist()
    s.update_node(v.index, position=(5, 5, 5))
    assert v.position.tolist() == [5, 5, 5] and v.rest.tolist() != [5, 5, 5]
    with pytest.raises(ValueError):
        s.node_position[0, 0] = 1.0  # the truth is edited through the methods
    assert s.ids("cell").tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(wb.WarpblobError, match="kind must be one of"):
        s.ids("tet")
    with pytest.raises(wb.WarpblobError, match="cell 9 does not exist"):
        s.cell(9)


# ---------------------------------------------------------------------------
# edits
# ---------------------------------------------------------------------------


def record(s):
    events = []
    s.subscribe(lambda kind, action, index: events.append((kind, action, index)))
    return events


def test_events_fire_for_every_edit():
    s = TetStructure.from_tetmesh(cube_mesh())
    events = record(s)
    N, E, F, C = (len(getattr(s, f"{k}_alive")) for k in ("node", "edge", "face", "cell"))

    v = s.insert_node((2, 0, 0))
    assert events == [("node", "insert", N)]
    events.clear()
    # a tet on a boundary face of the x = 1 side (oriented outward, so (a, b, c, v) is positive)
    face = next(f for f in np.flatnonzero(s.face_cells[:, 1] < 0) if set(s.face_nodes[f].tolist()) <= {1, 3, 5, 7})
    a, b, c = s.face_nodes[face].tolist()
    cell = s.insert_cell(a, b, c, v)
    # faces in local order (b, c, v), (a, v, c), (a, b, v), each after its missing edges; (a, c, b) exists
    assert events == [
        ("edge", "insert", E),
        ("edge", "insert", E + 1),
        ("face", "insert", F),
        ("edge", "insert", E + 2),
        ("face", "insert", F + 1),
        ("face", "insert", F + 2),
        ("cell", "insert", C),
    ]
    assert cell == C and s.to_tetmesh().volumes().min() > 0
    events.clear()

    s.update_node(v, rest=(2, 0.5, 0))
    s.update_cell(cell, a, b, c, v, material=3)
    assert events == [("node", "update", v), ("cell", "update", cell)]
    events.clear()

    e = s.find_edge(a, v)
    m1, m2, e2 = s.split_edge(e, 0.25)
    assert events == [("node", "insert", m1), ("node", "insert", m2), ("edge", "update", e), ("edge", "insert", e2)]
    events.clear()

    s.remove_cell(cell)
    assert events == [("cell", "remove", cell)] and s.pending["cell"] == (cell,)
    events.clear()

    maps = s.collect_garbage()
    removes = [x for x in events if x[1] == "remove"]
    compacts = [x for x in events if x[1] == "compact"]
    assert compacts == [(k, "compact", n) for k, n in zip(("node", "edge", "face", "cell"), (N, E, F, C))]
    # the faces, edges and nodes the removed cell and the split left unused, each announced once: one batch
    # event per kind listing them
    dead = {k: np.flatnonzero(m < 0).tolist() for k, m in maps.items()}
    announced = sorted((k, int(i)) for k, _, ids in removes for i in np.atleast_1d(ids))
    assert announced == sorted((k, i) for k in ("face", "edge", "node") for i in dead[k])
    assert len({k for k, _, _ in removes}) == len(removes)
    assert dead["node"] == [v, m1, m2] and dead["cell"] == [cell]
    assert s.pending == {"node": (), "edge": (), "face": (), "cell": ()}


def test_events_for_direct_edits():
    s = TetStructure()
    events = record(s)
    for p in [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]:
        s.insert_node(p)
    assert s.insert_edge(0, 1) == 0
    assert s.insert_face(0, 1, 2) == 0  # inserts edges 1 = (1, 2) and 2 = (2, 0)
    s.update_face(0, 0, 1, 3)  # inserts edges 3 = (1, 3) and 4 = (3, 0)
    s.remove_face(0)
    s.update_edge(1, 2, 3)
    assert s.find_edge(1, 2) == -1 and s.find_edge(3, 2) == 1
    s.remove_edge(1)
    s.remove_edge(2)
    assert s.find_edge(2, 3) == -1 and s.find_edge(0, 2) == -1
    s.remove_node(2)
    assert events == [
        *[("node", "insert", i) for i in range(4)],
        ("edge", "insert", 0),
        ("edge", "insert", 1),
        ("edge", "insert", 2),
        ("face", "insert", 0),
        ("edge", "insert", 3),
        ("edge", "insert", 4),
        ("face", "update", 0),
        ("face", "remove", 0),
        ("edge", "update", 1),
        ("edge", "remove", 1),
        ("edge", "remove", 2),
        ("node", "remove", 2),
    ]
    assert s.pending == {"node": (2,), "edge": (1, 2), "face": (0,), "cell": ()}
    assert_consistent(s)
    events.clear()
    maps = s.collect_garbage()  # with no cell, every face, edge and node is unreferenced
    assert s.node_count == s.edge_count == s.face_count == 0
    purged = [("edge", "remove", i) for i in (0, 3, 4)] + [("node", "remove", i) for i in (0, 1, 3)]
    assert sorted((k, a, int(i)) for k, a, ids in events[:-4] for i in np.atleast_1d(ids)) == sorted(purged)
    assert all(np.all(m == -1) for m in maps.values())


def test_unsubscribe():
    s = TetStructure.from_tetmesh(cube_mesh())
    events = []
    callback = s.subscribe(lambda *event: events.append(event))
    s.unsubscribe(callback)
    s.insert_node((0, 0, 0))
    assert events == []


def test_refused_edits_change_nothing():
    s = TetStructure.from_tetmesh(cube_mesh())
    events = record(s)
    before = {k: getattr(s, k).copy() for k in ("edge_nodes", "face_nodes", "face_cells", "cell_nodes")}
    interior = int(np.flatnonzero(s.face_cells[:, 1] >= 0)[0])
    with pytest.raises(wb.WarpblobError, match="is used by cells"):
        s.remove_face(interior)
    with pytest.raises(wb.WarpblobError, match="is used by faces"):
        s.remove_edge(0)
    with pytest.raises(wb.WarpblobError, match="is used by edges"):
        s.remove_node(0)
    with pytest.raises(wb.WarpblobError, match="already joined by edge"):
        s.insert_edge(*s.edge_nodes[0].tolist())
    with pytest.raises(wb.WarpblobError, match="already make face"):
        s.insert_face(*s.face_nodes[0].tolist())
    with pytest.raises(wb.WarpblobError, match="already has two cells"):
        s.insert_cell(*s.face_nodes[interior].tolist(), 0 if 0 not in s.face_nodes[interior] else 7)
    with pytest.raises(wb.WarpblobError, match="distinct live nodes"):
        s.insert_cell(0, 1, 1, 2)
    with pytest.raises(wb.WarpblobError, match="node 99 does not exist"):
        s.insert_edge(0, 99)
    with pytest.raises(wb.WarpblobError, match="strictly between 0 and 1"):
        s.split_edge(0, 1.0)
    with pytest.raises(wb.WarpblobError, match="rest must be 3 finite numbers"):
        s.insert_node((0, np.inf, 0))
    assert events == []
    for k, v in before.items():
        np.testing.assert_array_equal(getattr(s, k), v)
    s.remove_cell(0)
    with pytest.raises(wb.WarpblobError, match="cell 0 was removed"):
        s.remove_cell(0)


def split_through(s, e, t):
    """Split edge ``e`` and every cell around it into two (both halves keep their orientation).

    The cells' faces on the edge are removed first; the two halves of a cell
    (a, b, ...) are (a, first new node, ...) and (second new node, b, ...),
    so the split separates the two sides at the new nodes: a crack.
    """
    a, b = s.edge_nodes[e].tolist()
    faces = s.faces_of_edge(e).tolist()
    cells = sorted({c for f in faces for c in s.cells_of_face(f).tolist()})
    old = [(s.cell_nodes[c].tolist(), int(s.cell_material[c])) for c in cells]
    for c in cells:
        s.remove_cell(c)
    for f in faces:
        s.remove_face(f)
    m1, m2, e2 = s.split_edge(e, t)
    for nodes, material in old:
        s.insert_cell(*[m1 if n == b else n for n in nodes], material=material)
        s.insert_cell(*[m2 if n == a else n for n in nodes], material=material)
    assert s.find_edge(a, b) == -1 and s.find_edge(a, m1) == e and s.find_edge(m2, b) == e2
    return len(cells)


def attach(s, rng):
    """A new tet on a random boundary face, outside it; returns its volume."""
    boundary = np.flatnonzero(s.face_alive & (s.face_cells[:, 0] >= 0) & (s.face_cells[:, 1] < 0))
    f = int(rng.choice(boundary))
    p, q, r = s.face_nodes[f].tolist()
    x = s.node_rest.astype(np.float64)
    normal = np.cross(x[q] - x[p], x[r] - x[p])
    apex = (set(s.cell_nodes[s.face_cells[f, 0]].tolist()) - {p, q, r}).pop()
    if np.dot(normal, x[apex] - x[p]) > 0:
        q, r, normal = r, q, -normal
    size = np.sqrt(np.linalg.norm(normal))
    tip = (x[p] + x[q] + x[r]) / 3 + 0.5 * size * normal / np.linalg.norm(normal)
    v = s.insert_node(tip)
    s.insert_cell(p, q, r, v)
    return np.dot(np.cross(x[q] - x[p], x[r] - x[p]), tip - x[p]) / 6


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_random_edits_keep_links_consistent(seed):
    rng = np.random.default_rng(seed)
    s = TetStructure.from_tetmesh(grid_mesh(3))
    volume = s.to_tetmesh(rest=True).volume()
    kinds = ("node", "edge", "face", "cell")
    slots = {k: len(getattr(s, f"{k}_alive")) for k in kinds}
    events = record(s)
    splits = 0
    for step in range(60):
        op = rng.choice(["split", "attach", "remove", "move"], p=[0.4, 0.3, 0.2, 0.1])
        if op == "split":
            e = int(rng.choice(s.ids("edge")))
            splits += split_through(s, e, float(rng.uniform(0.2, 0.8)))
        elif op == "attach":
            volume += attach(s, rng)
        elif op == "remove":
            c = int(rng.choice(s.ids("cell")))
            volume -= s.to_tetmesh(rest=True).volumes()[np.searchsorted(s.ids("cell"), c)]
            s.remove_cell(c)
        else:
            v = int(rng.choice(s.ids("node")))
            s.update_node(v, position=s.node_position[v] + 0.01)
        if step % 8 == 0:
            assert_consistent(s)
            for v in rng.choice(s.ids("node"), 3).tolist():
                assert s.k_ring(int(v), 2).tolist() == bfs_ring(s, int(v), 2)
    assert_consistent(s)
    assert splits > 0
    # every new slot was announced once, every removal once, and only removed cells are dead
    for k in kinds:
        inserted = [i for kind, action, i in events if (kind, action) == (k, "insert")]
        assert inserted == list(range(slots[k], len(getattr(s, f"{k}_alive"))))
        removed = [i for kind, action, i in events if (kind, action) == (k, "remove")]
        assert sorted(removed) == sorted(s.pending[k])
    assert sorted(s.pending["cell"]) == np.flatnonzero(~s.cell_alive).tolist()
    before = {
        "edge_nodes": s.edge_nodes.copy(),
        "cell_nodes": s.cell_nodes.copy(),
        "cell_faces": s.cell_faces.copy(),
        "node_rest": s.node_rest.copy(),
        "alive": {k: getattr(s, f"{k}_alive").copy() for k in ("node", "edge", "face", "cell")},
    }
    events.clear()

    maps = s.collect_garbage()
    assert_consistent(s)
    s.check()
    # nothing dead is left, nothing unreferenced either
    for kind in ("node", "edge", "face", "cell"):
        assert getattr(s, f"{kind}_alive").all()
        assert maps[kind].shape == before["alive"][kind].shape
        assert np.all((maps[kind] >= 0) <= before["alive"][kind])  # only live entities survive
    assert np.all(s.face_cells[:, 0] >= 0)
    assert np.array_equal(np.unique(s.face_edges), np.arange(s.edge_count))
    assert np.array_equal(np.unique(s.edge_nodes), np.arange(s.node_count))
    # every link was remapped: survivors have the same content under new numbers
    keep = maps["cell"] >= 0
    np.testing.assert_array_equal(s.cell_nodes, maps["node"][before["cell_nodes"][keep]])
    np.testing.assert_array_equal(s.cell_faces, maps["face"][before["cell_faces"][keep]])
    keep = maps["edge"] >= 0
    np.testing.assert_array_equal(s.edge_nodes, maps["node"][before["edge_nodes"][keep]])
    keep = maps["node"] >= 0
    np.testing.assert_array_equal(s.node_rest, before["node_rest"][keep])
    # purged edges are not found (an edge is the only one on its two nodes)
    purged = before["edge_nodes"][(maps["edge"] < 0) & before["alive"]["edge"]]
    assert len(purged) > 0
    for a, b in maps["node"][purged].tolist():
        assert a < 0 or b < 0 or s.find_edge(a, b) == -1
    # geometry: splits and attached tets keep every tet positive; the volume is what was added and removed
    mesh = s.to_tetmesh(rest=True)
    assert np.all(mesh.volumes() > 0) and mesh.is_conforming()
    assert mesh.volume() == pytest.approx(volume, rel=1e-5)
    assert ("cell", "compact", s.cell_count) in events


def test_attached_tets_keep_a_ball():
    rng = np.random.default_rng(5)
    s = TetStructure.from_tetmesh(grid_mesh(2))
    for _ in range(10):
        attach(s, rng)
    s.collect_garbage()
    assert euler(s) == 1
    s.check()


def test_split_edge_interpolates_and_relinks():
    s = TetStructure.from_tetmesh(cube_mesh())
    s.update_node(7, position=(2.0, 2.0, 2.0))
    e = s.find_edge(0, 1)
    n0, n1 = s.edge_nodes[e].tolist()
    m1, m2, e2 = s.split_edge(e, 0.25)
    expected_rest = s.node_rest[n0] + 0.25 * (s.node_rest[n1] - s.node_rest[n0])
    np.testing.assert_allclose(s.node_rest[m1], expected_rest)
    np.testing.assert_array_equal(s.node_rest[m1], s.node_rest[m2])  # co-located
    np.testing.assert_array_equal(s.node_position[m1], s.node_position[m2])
    assert s.edge_nodes[e].tolist() == [n0, m1] and s.edge_nodes[e2].tolist() == [m2, n1]
    assert s.edges_of_node(m1).tolist() == [e] and s.edges_of_node(m2).tolist() == [e2]
    assert e not in s.edges_of_node(n1).tolist() and e2 in s.edges_of_node(n1).tolist()
    s7 = s.find_edge(3, 7)
    a, b = s.edge_nodes[s7].tolist()
    m1, _, _ = s.split_edge(s7, 0.5)
    np.testing.assert_allclose(s.node_position[m1], (s.node_position[a] + s.node_position[b]) / 2)
    np.testing.assert_allclose(s.node_rest[m1], (s.node_rest[a] + s.node_rest[b]) / 2)


def test_update_cell_moves_between_faces():
    s = TetStructure.from_tetmesh(cube_mesh())
    corner = int(np.flatnonzero((s.cell_nodes == 0).any(axis=1))[0])  # the corner tet at node 0
    old_faces = s.cell_faces[corner].tolist()
    nodes = s.cell_nodes[corner].tolist()
    v = s.insert_node(s.node_rest[0] - 0.5)
    s.update_cell(corner, *[v if n == 0 else n for n in nodes])
    assert 0 not in s.cell_nodes[corner].tolist()
    # the three faces at node 0 lost their only cell; the face opposite node 0 kept it (and the central tet)
    for f in old_faces:
        in_use = sorted(s.cells_of_face(f).tolist())
        assert in_use == ([corner, 4] if 0 not in s.face_nodes[f].tolist() else [])
    assert_consistent(s)
    maps = s.collect_garbage()
    assert maps["node"][0] == -1 and s.node_count == 8
    assert np.all(s.to_tetmesh().volumes() > 0)


def test_remove_and_reinsert_reuse_the_lookup():
    s = TetStructure.from_tetmesh(cube_mesh())
    c = 0
    nodes = s.cell_nodes[c].tolist()
    s.remove_cell(c)
    for f in s.cell_faces[c].tolist():
        if s.cells_of_face(f).size == 0:
            s.remove_face(f)
    for e in s.cell_edges[c].tolist():
        if s.faces_of_edge(e).size == 0:
            s.remove_edge(e)
    dead_pairs = [tuple(s.edge_nodes[e]) for e in s.pending["edge"]]
    assert dead_pairs and all(s.find_edge(a, b) == -1 for a, b in dead_pairs)
    assert_consistent(s)
    new = s.insert_cell(*nodes)
    assert_consistent(s)
    assert s.cell_count == 5 and new == 5
    s.collect_garbage()
    assert s.cell_count == 5 and euler(s) == 1
    s.check()


def test_to_warp_arrays(device):
    s = TetStructure.from_tetmesh(grid_mesh(2))
    s.split_edge(0, 0.5)  # leaves the links to be rebuilt
    arrays = s.to_warp(device)
    assert arrays.node_rest.shape[0] == len(s.node_alive) == arrays.node_edge_offsets.shape[0] - 1
    assert arrays.cell_edges.shape[0] == len(s.cell_alive)
    offsets, lists = arrays.node_edge_offsets.numpy(), arrays.node_edge_list.numpy()
    for v in range(len(s.node_alive)):
        assert lists[offsets[v] : offsets[v + 1]].tolist() == s.edges_of_node(v).tolist()
    offsets, lists = arrays.edge_face_offsets.numpy(), arrays.edge_face_list.numpy()
    for e in range(len(s.edge_alive)):
        assert lists[offsets[e] : offsets[e + 1]].tolist() == s.faces_of_edge(e).tolist()
    np.testing.assert_array_equal(arrays.face_cells.numpy(), s.face_cells)
    np.testing.assert_array_equal(arrays.cell_edges.numpy(), s.cell_edges)


def test_check_reports_a_broken_structure():
    s = TetStructure.from_tetmesh(cube_mesh())
    s.check()
    s._stores["cell"].arrays["edges"][0, [0, 1]] = s._stores["cell"].arrays["edges"][0, [1, 0]]
    with pytest.raises(wb.WarpblobError, match="a cell's edges are not those of its nodes"):
        s.check()


def test_repr_is_a_short_summary():
    n = 4
    s = TetStructure.from_tetmesh(grid_mesh(n))
    text = repr(s)
    assert len(text) < 400 and len(text.splitlines()) <= 3
    # counts of a Kuhn grid (see test_structured_grid_counts)
    edges = 3 * n * (n + 1) ** 2 + 3 * n * n * (n + 1) + n**3
    assert f"{(n + 1) ** 3:,} nodes" in text and f"{edges:,} edges" in text and f"{6 * n**3:,} cells" in text
    assert "0 removals pending" in text and "x [0, 1]" in text
    s.remove_cell(0)
    assert f"{6 * n**3 - 1:,} cells" in repr(s) and "1 removals pending" in repr(s)
    assert repr(s.cell(3)) == "CellView(index=3)" and repr(s.node(0)) == "NodeView(index=0)"


def _table_contents(s):
    """The lookup table as {key: edge} (deleted and empty slots left out)."""
    used = s._table_keys >= 0
    return dict(zip(s._table_keys[used].tolist(), s._table_values[used].tolist()))


def _own_table(s):
    """What the lookup table must hold: each live edge's key ``max << 32 | min`` -> its index."""
    e = np.asarray(s.edge_nodes, dtype=np.int64)
    return dict(zip(((e.max(axis=1) << 32) | e.min(axis=1)).tolist(), range(len(e))))


def _fresh_table(s):
    fresh = TetStructure.from_tetmesh(TetMesh(s.node_rest, s.cell_nodes[s.cell_alive]))
    return fresh, _table_contents(fresh)


def _split_edge(s, e):
    """Split edge ``e`` at its midpoint in one batch edit (each cell round it into two); its two nodes."""
    a, b = s.edge_nodes[e].tolist()
    ring = np.flatnonzero(np.any(s.cell_nodes == a, axis=1) & np.any(s.cell_nodes == b, axis=1) & s.cell_alive)
    rest, position = s.node_rest[[a, b]].mean(axis=0), s.node_position[[a, b]].mean(axis=0)
    mid = s.insert_nodes(rest[None], position[None])
    new = []
    for c in ring.tolist():
        for end in (a, b):
            t = s.cell_nodes[c].copy()
            t[t == end] = int(mid[0])
            new.append(t)
    s.replace_cells(ring, np.array(new), 0)
    return a, b


def test_a_built_structure_takes_a_cut_without_copying_its_columns():
    """A structure just built reserves room for as many more entities of each kind as it has (address space:
    the spare slots are not written until taken): a cut through it appends in place, every column of every
    kind the same array as before, and the structure stays valid; an edit past that room grows them."""
    s = TetStructure.from_tetmesh(grid_mesh(6))
    columns = lambda: {kind: {name: id(a) for name, a in store.arrays.items()} for kind, store in s._stores.items()}
    before, counts = columns(), {kind: store.count for kind, store in s._stores.items()}
    r = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.51, 0.49, 0.5), (0.3, 0.2, 1.0), 3.0), collect=False)
    assert r.components == 2 and r.tets_added > r.tets_removed
    assert all(s._stores[kind].count > counts[kind] for kind in ("node", "edge", "face", "cell"))
    assert columns() == before
    s.check()
    cells = np.asarray(s.cell_nodes)[np.asarray(s.cell_alive)].copy()
    for _ in range(2):  # the same cells again, twice: the cell store passes twice its built count
        s.replace_cells(np.flatnonzero(s.cell_alive), cells, 0)
    assert id(s._stores["cell"].arrays["nodes"]) != before["cell"]["nodes"]
    s.check()


def test_batch_edges_reuse_deleted_slots_and_grow_the_table():
    """A batch edit's new edges go into the lookup table as they are numbered: after a compaction left
    deleted slots, the new edges of the next batch (some of whose keys probe past a deleted slot) are all
    found under their indices, nothing else is, and the slots counted as used grow by at most the new edges;
    a batch with more new edges than the table has room for builds it anew, larger, with every edge in it."""
    s = TetStructure.from_tetmesh(grid_mesh(3))
    rng = np.random.default_rng(2)
    for _ in range(3):  # split a random interior edge, compact (its slot is marked deleted), again
        e = next(e for e in rng.permutation(s.ids("edge")) if s.faces_of_edge(e).size == 6)
        used, edges = s._table_used, len(s.edge_nodes)
        _split_edge(s, e)
        assert _table_contents(s) == _own_table(s)  # (the split edge stays until the compaction)
        assert s._table_used - used <= len(s.edge_nodes) - edges
        s.collect_garbage()
        assert (s._table_keys == -2).any()  # deleted slots for the next batch to pass or reuse
        assert _table_contents(s) == _own_table(s)
    s.check()
    # a batch larger than the table's room: 200 separate tets on new nodes
    size = len(s._table_keys)
    nodes = s.insert_nodes(rng.uniform(5, 6, (800, 3)))
    cells = nodes.reshape(-1, 4)
    p = s.node_rest[cells]
    flip = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) < 0
    cells[flip] = cells[flip][:, [1, 0, 2, 3]]
    s.replace_cells(np.zeros(0, np.int64), cells, 0)
    assert len(s._table_keys) > size
    assert _table_contents(s) == _own_table(s)
    s.check()


def test_compaction_keeps_the_lookup_table_when_no_node_goes():
    """A compaction that removes edges but keeps every node (a cut's) follows the table in place: the
    same arrays, every live edge under its new index, removed ones not found, the same pairs as a table
    built afresh; one that removes a node builds it anew."""
    s = TetStructure.from_tetmesh(grid_mesh(3))
    # the cells at one interior edge's nodes go, then cells that split it come back (every node stays used)
    e = next(e for e in s.ids("edge") if s.faces_of_edge(e).size == 6)  # an interior edge
    a, b = _split_edge(s, e)
    keys, values = s._table_keys, s._table_values
    old_pairs = {tuple(sorted(s.edge_nodes[i].tolist())) for i in s.ids("edge")}
    maps = s.collect_garbage()
    assert maps["node"].min() >= 0 and (maps["edge"] < 0).sum() == 1  # the split edge alone went
    assert s._table_keys is keys and s._table_values is values  # followed in place, not rebuilt
    assert _table_contents(s) == _own_table(s)  # (before check(), whose queries may build it again)
    # an edge exactly in the slots that hold a key (the removed edge's slot marked deleted, its edge gone):
    # the next compaction reads the values alone
    np.testing.assert_array_equal(s._table_values >= 0, s._table_keys >= 0)
    assert np.count_nonzero(s._table_keys == DELETED) >= 1
    s.check()
    assert_consistent(s)
    assert s.find_edge(a, b) == -1
    _, fresh = _fresh_table(s)
    # every live edge under its new index, and the same edges as a table built afresh (whose numbering may
    # differ: a batch edit numbers its new edges by first use)
    assert _table_contents(s) == _own_table(s) and set(_table_contents(s)) == set(fresh)
    assert {tuple(sorted(p)) for p in s.edge_nodes.tolist()} == old_pairs - {tuple(sorted((a, b)))}
    # a compaction that removes a node builds the table anew
    corner = int(np.argmin(s.node_rest.sum(axis=1)))  # the box's corner at the origin: only its cube's tets hold it
    s.replace_cells(np.flatnonzero(np.any(s.cell_nodes == corner, axis=1)), np.zeros((0, 4), np.int32), 0)
    keys = s._table_keys
    maps = s.collect_garbage()
    assert maps["node"][corner] == -1 and s._table_keys is not keys
    s.check()
    assert _table_contents(s) == _own_table(s) and set(_table_contents(s)) == set(_fresh_table(s)[1])
