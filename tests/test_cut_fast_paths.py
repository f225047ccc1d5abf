"""The cutter's fast paths against their plain counterparts: the few-triangle intersection against the BVH's,
the packed-sort uniques against numpy's, the component kernel against a graph library."""

import numpy as np
import pytest
import warp as wp
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from warpblob._errors import WarpblobError
from warpblob.cut import SweepSurface, cut
from warpblob.cut import _kernels as k
from warpblob.cut._cut import _boxes, _planes
from warpblob.mesh import TetStructure, box_tetmesh
from warpblob.mesh import _structure as structure_module
from warpblob.mesh._structure import _group_keys, _unique_first, _unique_inverse, vec6i


def _intersect(kernel, edges, positions, sweep, device, unrolled=False):
    """The hits of ``kernel`` ("sides": the few-triangle kernel from the nodes' sides); ``unrolled``: the
    few-triangle kernels with their loop unrolled for the sweep's triangle count (``FEW_KERNELS``)."""
    (lowers, uppers), corners = _boxes(sweep, device)
    few, node_sides = k.intersect_edges_few_kernel, k.node_sides_kernel
    if unrolled:
        node_sides, few = k.FEW_KERNELS[sweep.triangle_count]
        kernel = few if kernel is k.intersect_edges_few_kernel else kernel
    n = len(edges)
    inputs = [wp.array(edges, dtype=wp.vec2i, device=device), wp.ones(n, dtype=wp.uint8, device=device),
              wp.array(positions, dtype=wp.vec3, device=device)]  # fmt: skip
    bvh = None
    if kernel is k.intersect_edges_kernel:
        bvh = wp.Bvh(lowers, uppers)
        inputs += [bvh.id, corners, 0]
    elif kernel == "sides":  # the few-triangle kernel from the nodes' sides, taken first (a plane through the mesh)
        kernel = few
        normals, slack = _planes(sweep, device)
        sides = wp.empty((len(positions), sweep.triangle_count), dtype=wp.vec2, device=device)
        wp.launch(node_sides, dim=len(positions), inputs=[inputs[2], corners, normals, 0, sides],
                  device=device)  # fmt: skip
        inputs += [lowers, uppers, corners, normals, slack, sides, 0]
    else:
        inputs += [lowers, uppers, corners, *_planes(sweep, device), wp.empty((0, 0), dtype=wp.vec2, device=device), 0]
    out = [wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device),
           wp.empty(n, dtype=wp.int32, device=device)]  # fmt: skip
    wp.launch(kernel, dim=n, inputs=inputs + out, device=device)
    return [a.numpy() for a in out]


def assert_same_hits(few, tree):
    """The same edges hit, at the same parameter in [0, 1], by the same triangle (the few-triangle kernel
    writes the parameter and triangle at hits only; the BVH kernel -1 elsewhere)."""
    np.testing.assert_array_equal(few[2], tree[2])
    hit = few[2] != 0
    for x, y in zip(few[:2], tree[:2]):
        np.testing.assert_array_equal(x[hit], y[hit])
    np.testing.assert_array_equal(tree[2], (tree[0] >= 0).astype(np.int32))
    assert np.all((few[0][hit] >= 0) & (few[0][hit] <= 1))


def test_few_triangle_intersection_is_the_bvh_one(device):
    """Random edges against a curved 14-triangle strip: the same first hits, parameters and flags (the few-triangle
    kernel writes the parameter and triangle at hits only)."""
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
    assert_same_hits(few, tree)
    assert_same_hits(_intersect("sides", edges, positions, sweep, device), tree)


@pytest.mark.parametrize("scale", [1.0, 1e3])
def test_same_side_skip_keeps_every_hit(device, scale):
    """Edges with an end on, or a hair's breadth (1e-9..1e-3 of the edge) either side of, a tilted plane's
    triangles, edges in the plane, and edges with both ends near it (1e-7..1e-1 of its size, around the
    skip's slack): the few-triangle kernel (which passes over edges clearly on one side) gives the BVH
    kernel's hits, parameters and flags exactly."""
    rng = np.random.default_rng(11)
    origin, normal = np.array([0.4, 0.5, 0.45]) * scale, np.array([0.3, -0.2, 1.0])
    sweep = SweepSurface.plane(origin, normal, 3.0 * scale)
    u = np.cross(normal, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(normal / np.linalg.norm(normal), u)
    m = 3000
    on = origin + scale * (rng.uniform(-1, 1, (m, 1)) * u + rng.uniform(-1, 1, (m, 1)) * w)  # on the plane
    direction = rng.normal(size=(m, 3))
    length = scale * rng.uniform(0.01, 0.2, (m, 1))
    far = on + length * direction / np.linalg.norm(direction, axis=1, keepdims=True)
    nudge = rng.choice([0.0, 1e-9, -1e-9, 1e-7, -1e-7, 1e-5, -1e-5, 1e-3, -1e-3], (m, 1)) * length
    near = on + nudge * normal / np.linalg.norm(normal)
    across = np.cross(direction, normal)
    flat = on + length * across / np.linalg.norm(across, axis=1, keepdims=True)  # in the plane
    # both ends off the plane, 1e-7..1e-1 of its size away, either side: around the skip's slack
    off = scale * rng.choice([-1, 1], (m, 1)) * 10.0 ** rng.uniform(-7, -1, (m, 1))
    lifted = on + off * normal / np.linalg.norm(normal)
    positions = np.concatenate([near, far, flat, lifted]).astype(np.float32)
    i = np.arange(m)
    edges = np.concatenate([np.stack([i, m + i], 1), np.stack([m + i, i], 1), np.stack([i, 2 * m + i], 1),
                            np.stack([3 * m + i, 3 * m + np.roll(i, 1)], 1)])  # fmt: skip
    few = _intersect(k.intersect_edges_few_kernel, edges.astype(np.int32), positions, sweep, device)
    tree = _intersect(k.intersect_edges_kernel, edges.astype(np.int32), positions, sweep, device)
    assert 0.3 * len(edges) < few[2].sum() < len(edges)  # hits and misses both
    assert_same_hits(few, tree)
    # the same test from each node's sides, taken once (a sweep over most of the mesh)
    assert_same_hits(_intersect("sides", edges.astype(np.int32), positions, sweep, device), tree)
    # and both by the kernels whose loop over the plane's two triangles is unrolled
    for kernel in (k.intersect_edges_few_kernel, "sides"):
        assert_same_hits(_intersect(kernel, edges.astype(np.int32), positions, sweep, device, unrolled=True), tree)


@pytest.mark.parametrize("count", [1, 2, 3, 4])
def test_unrolled_few_triangle_kernels_are_the_bvh_one(device, count):
    """A curved strip of 1 to 4 triangles (the unrolled kernels' counts) against random edges: the unrolled
    kernels, from the nodes' sides or not, give the BVH kernel's first hits, parameters and flags."""
    rng = np.random.default_rng(20 + count)
    s = np.linspace(0, 1, count + 1)
    a = np.column_stack([s, 0.3 * np.sin(3 * s), np.zeros_like(s)])
    sweep = SweepSurface(SweepSurface.from_blade(a, a + (0.1, 0.2, 1.0)).triangles[:count])  # (its first ones)
    assert sweep.triangle_count == count
    positions = rng.uniform(-0.2, 1.2, (400, 3)).astype(np.float32)
    edges = rng.integers(0, 400, (3000, 2)).astype(np.int32)
    edges = edges[edges[:, 0] != edges[:, 1]]
    tree = _intersect(k.intersect_edges_kernel, edges, positions, sweep, device)
    assert tree[2].sum() > 20
    for kernel in (k.intersect_edges_few_kernel, "sides"):
        assert_same_hits(_intersect(kernel, edges, positions, sweep, device, unrolled=True), tree)


def test_unique_inverse_is_numpys():
    """Keys of a small range (the marks), narrow keys (the packed sort), wide and negative ones (the argsort):
    numpy's unique and inverse."""
    rng = np.random.default_rng(5)
    for keys in (rng.integers(0, 1_000, 5000), rng.integers(0, 60_000, 60), rng.integers(0, 1 << 40, 5000),
                 rng.integers(0, 1 << 60, 5000), rng.integers(-50, 50, 300),
                 np.zeros(0, np.int64), np.array([7])):  # fmt: skip
        keys = np.concatenate([keys, keys[: len(keys) // 3]]).astype(np.int64)
        want = np.unique(keys, return_inverse=True)
        got = _unique_inverse(keys)
        for x, y in zip(want, got):
            np.testing.assert_array_equal(np.ravel(x), y)
            assert np.ravel(x).dtype == y.dtype


def test_key_groups_are_first_occurrence_order():
    """A batch edit's face and edge matching (one kernel thread through a hash table): per key its group,
    numbered by first occurrence, as a numpy reference gives it; per group the first key from ``old`` on in
    it and how many are; the pooled table EMPTY again after each call, kept and grown between calls of
    several sizes (a later, smaller batch in a larger table), keys wide and narrow, many sharing a slot."""
    rng = np.random.default_rng(8)
    for keys, old in ((rng.integers(0, 1 << 40, 5000), 1000), (rng.integers(0, 1 << 53, 20000), 0),
                      (rng.integers(0, 1 << 62, 3000), 3000), (rng.integers(0, 50, 4000), 100),
                      (np.zeros(0, np.int64), 0), (np.array([1 << 55]), 0)):  # fmt: skip
        keys = np.concatenate([keys, keys[::7], keys[: len(keys) // 3]]).astype(np.int64)
        rng.shuffle(keys)
        count, groups, first, uses = _group_keys(keys, old)
        assert all(np.all(table[:, 0] == -1) for table in structure_module._KEY_TABLES)
        uniq, index, want = np.unique(keys, return_index=True, return_inverse=True)
        rank = np.empty(len(uniq), dtype=np.int64)
        rank[np.argsort(index)] = np.arange(len(uniq))  # groups by first occurrence
        assert count == len(uniq)
        np.testing.assert_array_equal(groups, rank[want.ravel()])
        later = groups[old:]
        np.testing.assert_array_equal(uses, np.bincount(later, minlength=count))
        has = uses > 0
        want_first = np.full(count, -1)
        want_first[later[::-1]] = np.arange(len(later))[::-1]  # (the last write of a reversed scatter: the first)
        np.testing.assert_array_equal(first[has], want_first[has])


@pytest.mark.parametrize("top", [1_000, 1 << 50])
def test_packed_unique_is_numpys(top):
    """Small keys take the packed sort, keys too wide for it take numpy's own unique: the same triple."""
    keys = np.random.default_rng(3).integers(0, top, 5000).astype(np.int64)
    want = np.unique(keys, return_index=True, return_inverse=True)
    got = _unique_first(keys, len(keys))
    for x, y in zip(want, got):
        np.testing.assert_array_equal(np.ravel(x), np.ravel(y))


@pytest.mark.parametrize("cells_per_range", [1 << 30, 97])
def test_components_match_a_graph_reference(cells_per_range, monkeypatch):
    """Two crossing planar cuts: the kernels' labels are the connected components of the face graph, numbered
    by lowest cell, -1 for the dead cells; the count alone agrees. Whole (one range) and in ranges of 97
    cells run side by side (many faces between ranges, the cut's new cells in the last ones)."""
    monkeypatch.setattr(structure_module, "_COMPONENT_RANGE", cells_per_range)
    monkeypatch.setattr(structure_module, "thread_count", lambda: 8)
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


def _edges_in_use(s: TetStructure, device) -> np.ndarray:
    """The cut's own marking pass: 1 for every edge slot a live cell uses."""
    out = wp.zeros(len(s.edge_nodes), dtype=wp.uint8, device=device)
    wp.launch(k.mark_edges_in_use_kernel, dim=len(s.cell_nodes), device=device,
              inputs=[wp.array(np.asarray(s.cell_edges), dtype=vec6i, device=device),
                      wp.array(np.asarray(s.cell_alive).view(np.uint8), dtype=wp.uint8, device=device), 0,
                      out])  # fmt: skip
    return out.numpy()


def test_edges_used_flag_only_when_every_edge_is_used(device):
    """The structure's "every edge a live cell's" flag (a cut then skips its marking pass) holds after a build
    and a compaction, and is dropped by anything that can leave an edge unused; whenever it holds, the
    marking pass marks every slot."""
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (3, 3, 3)))
    states = [s._edges_used]
    assert _edges_in_use(s, device).all()
    cut(s, SweepSurface.plane((0.51, 0.5, 0.5), (1.0, 0.2, 0.1), 3.0), collect=False)
    states.append(s._edges_used)  # split edges stay, unused, until the compaction
    assert not _edges_in_use(s, device).all()
    s.collect_garbage()
    states.append(s._edges_used)
    assert _edges_in_use(s, device).all()
    s.insert_edge(0, int(np.asarray(s.edge_nodes).max()))  # an edge alone
    states.append(s._edges_used)
    s.collect_garbage()
    s.remove_cell(0)
    states.append(s._edges_used)
    assert states == [True, False, True, False, False]


def _cut_twice(mesh):
    s = TetStructure.from_tetmesh(mesh)
    cut(s, SweepSurface.plane((0.51, 0.5, 0.5), (1, 0.1, 0), 3.0), collect=False)
    cut(s, SweepSurface.plane((0.5, 0.5, 0.49), (0, 0.1, 1), 3.0))
    return s


def test_edges_beside_the_face_matching_change_nothing(monkeypatch):
    """A batch edit puts a large batch's new edges in the lookup table on a pool thread while it matches the
    faces: every array of the structure, and its table, the same as in turn."""
    mesh = box_tetmesh((0, 0, 0), (1, 1, 1), (5, 5, 5))
    monkeypatch.setattr(structure_module, "_SIDE_EDGES", 1 << 40)
    inline = _cut_twice(mesh)
    monkeypatch.setattr(structure_module, "_SIDE_EDGES", 1)
    side = _cut_twice(mesh)
    for kind, store in inline._stores.items():
        for name in store.arrays:
            np.testing.assert_array_equal(store[name], side._stores[kind][name], err_msg=f"{kind}.{name}")
    for name in ("_table_keys", "_table_values", "_table_bits", "_table_used", "_table_node_bound"):
        np.testing.assert_array_equal(getattr(inline, name), getattr(side, name), err_msg=name)


@pytest.mark.parametrize("side_edges", [1, 1 << 40])
def test_a_refused_batch_leaves_the_edge_table_as_it_was(side_edges, monkeypatch):
    """A batch whose new cells would give a face three cells is refused after its new edges went into the
    lookup table beside the face matching: the table then finds exactly the edges there were (none of the
    refused batch's), and a valid batch after it works."""
    monkeypatch.setattr(structure_module, "_SIDE_EDGES", side_edges)
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2)))
    counts = {kind: store.count for kind, store in s._stores.items()}
    bound = s._table_node_bound
    # three new cells on new nodes round one new face (a, b, p): it would have three cells
    a, b = s.edge_nodes[0].tolist()
    p, q1, q2, q3 = s.insert_nodes(np.array([[3.0, 3.0, 3.0], [4.0, 3.0, 3.0], [3.0, 4.0, 3.0], [3.0, 3.0, 4.0]]))
    with pytest.raises(WarpblobError, match="would have 3 cells"):
        s.replace_cells(np.zeros(0, np.int64), np.array([[a, b, p, q1], [a, b, p, q2], [a, b, p, q3]]), 0)
    assert {kind: store.count for kind, store in s._stores.items() if kind != "node"} == {
        kind: n for kind, n in counts.items() if kind != "node"}
    assert s._table_node_bound == bound
    e = np.asarray(s.edge_nodes, dtype=np.int64)
    used = s._table_keys >= 0
    assert dict(zip(s._table_keys[used].tolist(), s._table_values[used].tolist())) == dict(
        zip(((e.max(axis=1) << 32) | e.min(axis=1)).tolist(), range(len(e))))
    assert s.find_edge(a, p) == -1
    s.check()
    # a valid batch: the corner cell's four corners as they are, re-made (no new edge) and one on the new node
    q = int(np.argmin(s.node_rest[: counts["node"]].sum(axis=1)))
    corner = np.flatnonzero(np.any(s.cell_nodes == q, axis=1))[0]
    s.replace_cells(np.array([corner]), s.cell_nodes[corner][None], 0)
    s.check()


def test_rest_grid_finds_every_cell_a_box_meets():
    """The rest-frame grid's query holds every live cell whose rest box meets a query box (brute force), for
    boxes, points and boxes off the mesh; its answer is ascending and has no dead cells."""
    rng = np.random.default_rng(4)
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (2, 1, 1), (20, 10, 8)))
    cut(s, SweepSurface.plane((1.01, 0.5, 0.5), (1, 0.2, 0.1), 3.0), collect=False)  # dead cells, newer ones
    corners = np.asarray(s.node_rest)[np.asarray(s.cell_nodes)]
    lo_c, hi_c = corners.min(axis=1), corners.max(axis=1)
    live = np.asarray(s.cell_alive)
    for _ in range(20):
        a, b = rng.uniform(-0.3, 2.3, (2, 3))
        lower, upper = np.minimum(a, b), np.minimum(np.minimum(a, b) + rng.uniform(0, 0.2, 3), np.maximum(a, b))
        for lo, hi in ((lower, upper), (lower, lower)):
            got = s._cells_near(lo, hi)
            want = np.flatnonzero(live & np.all((lo_c <= hi) & (hi_c >= lo), axis=1))
            assert got is not None and np.all(np.diff(got) > 0) and live[got].all()
            assert np.isin(want, got).all()
    assert len(s._cells_near((5, 5, 5), (6, 6, 6))) == len(s.cell_nodes) - s._rest_grid.cells  # only newer ones
    assert s._cells_near((-1, -1, -1), (3, 3, 3)) is None  # the whole mesh: a pass over everything pays


def _drill(mesh, near_search, monkeypatch):
    """A progressive drill stroke as the simulator's cutter makes it (rest frame, node limit, kept cut nodes)."""
    import warpblob as wb
    from warpblob.cut import _cut as cut_module

    monkeypatch.setattr(cut_module, "_NEAR_SEARCH", near_search)
    drill = wb.tools.Drill(0.2, 1.0, segments=8)
    path = wb.tools.Path.line((1.01, 0.98, 0.5), (1.01, 0.98, -0.1), 10 / 60, align=True)
    s = TetStructure.from_tetmesh(mesh)
    limit, sticky, pieces = len(s.node_rest), np.zeros(0, np.int64), []
    for k in range(1, 11):
        sweep = SweepSurface.from_path(drill, path, path.t0, path.t0 + k / 60, 1 / 60)
        r = cut(s, sweep, collect=False, configuration="rest", node_limit=limit, cut_nodes=sticky)
        sticky = r.stroke_cut_nodes(sticky)
        pieces.append(r.components)
    return s, pieces


def test_rest_frame_local_search_cuts_the_same(monkeypatch):
    """A progressive drill through a plate with the search of the cells near the sweep (every mesh) and
    without it (none): every array of the structure the same, and the piece counts (counted round the new
    cells while nothing is severed) equal a count of the whole mesh after every step."""
    mesh = box_tetmesh((0, 0, 0), (2, 2, 0.4), (20, 20, 4))
    local, pieces = _drill(mesh, 0, monkeypatch)
    whole, whole_pieces = _drill(mesh, 1 << 40, monkeypatch)
    for kind, store in local._stores.items():
        for name in store.arrays:
            np.testing.assert_array_equal(store[name], whole._stores[kind][name], err_msg=f"{kind}.{name}")
    assert pieces == whole_pieces and pieces[-1] == 2  # the plug comes free at the end
    local._pieces = None  # forget the remembered count: count every cell
    assert local._component_count() == 2 == int(local.components().max()) + 1


def test_piece_count_round_new_cells_is_the_whole_count(monkeypatch):
    """Random strokes and planes, several per mesh: after every cut the count the cutter reports (round the
    new cells where that shows nothing was severed) equals the count of a union-find over every cell."""
    rng = np.random.default_rng(12)
    for trial in range(6):
        s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (6, 6, 6)))
        s._component_count()  # known before the first cut: the local count is tried from the first one
        for _ in range(4):
            if rng.random() < 0.5:
                a = rng.uniform(0, 1, (2, 3)) + [0, 0, 0.6]
                sweep = SweepSurface.from_blade(a, a - [0, 0, rng.uniform(0.3, 1.5)])
            else:
                sweep = SweepSurface.plane(rng.uniform(0.2, 0.8, 3), rng.normal(size=3), rng.uniform(0.3, 2.0))
            r = cut(s, sweep, collect=bool(rng.random() < 0.3))
            labels = s.components()  # all cells, labels (not the remembered count)
            assert r.components == int(labels.max()) + 1, trial


def _face_graph_labels(s):
    """Component of every live cell by a graph library (faces joining two live cells), -1 for dead ones."""
    fc = np.asarray(s._stores["face"]["cells"])
    alive = np.asarray(s.cell_alive)
    both = (fc >= 0).all(axis=1)
    both[both] = alive[fc[both]].all(axis=1)
    n = len(alive)
    graph = coo_matrix((np.ones(both.sum()), (fc[both, 0], fc[both, 1])), shape=(n, n))
    _, ref = connected_components(graph, directed=False)
    return np.where(alive, ref, -1)


def _full_counts(monkeypatch) -> list:
    """A list that gets a False each time every cell of a structure is counted (for a piece count)."""
    counted = []
    real = TetStructure._components
    monkeypatch.setattr(TetStructure, "_components", lambda self, label: counted.append(label) or real(self, label))
    return counted


def test_flood_counts_the_pieces_its_seeds_lie_in():
    """The flood from labelled seed cells (each its own label) against a graph library: the number of
    distinct components among the seeds, for seed sets in one, two and three of a mesh's pieces; a budget
    below what the flood needs gives None, and the scratch marks are all reset after either."""
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (6, 6, 6)))
    for origin, normal in (((0.5, 0.5, 0.5), (1, 0.2, 0.1)), ((0.3, 0.6, 0.4), (0.1, 1, 0.3))):
        cut(s, SweepSurface.plane(origin, normal, 3.0), collect=False)
    ref = _face_graph_labels(s)
    assert len(np.unique(ref[ref >= 0])) == 4
    rng = np.random.default_rng(5)
    live = np.flatnonzero(ref >= 0)
    for trial in range(20):
        pieces = rng.choice(4, size=rng.integers(1, 4), replace=False)
        pool = live[np.isin(ref[live], np.unique(ref[live])[pieces])]
        seeds = np.unique(rng.choice(pool, size=min(len(pool), int(rng.integers(1, 40))), replace=False))
        failed, got, roots = s._flood_pieces(seeds.astype(np.int32), len(live) + 16)
        assert not failed and got == len(np.unique(ref[seeds])), trial
        # joined labels are those in one piece, and only those (here every label has closed or met the one left)
        same_root = roots[:, None] == roots[None, :]
        same_piece = ref[seeds][:, None] == ref[seeds][None, :]
        np.testing.assert_array_equal(same_root, same_piece)
        assert np.all(s._flood_mark == -1)
        if len(np.unique(ref[seeds])) > 1:  # the flood must pass one piece whole: too small a budget fails
            failed, _, roots = s._flood_pieces(seeds.astype(np.int32), len(seeds))
            assert failed
            assert np.all(ref[seeds][roots] == ref[seeds])  # what was joined before it stopped is joined
            assert np.all(s._flood_mark == -1)


def test_cutting_off_corners_counts_by_the_flood(monkeypatch):
    """Corners cut off one after another (each cut severs a small piece; the last one a corner of a piece
    made by an earlier cut, so the count before it is above one): the count reported is a graph library's,
    and it came from the flood, not from a count of every cell; with a flood budget too small for the
    pieces the whole count is taken instead, with the same result."""
    flood = TetStructure._flood_pieces
    counted = _full_counts(monkeypatch)
    for floods in (True, False):
        if not floods:  # the least budget: the seeds themselves
            monkeypatch.setattr(TetStructure, "_flood_pieces", lambda self, seeds, budget: flood(self, seeds, len(seeds)))
        s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (14, 14, 14)))
        s._component_count()
        counted.clear()
        corners = [((0.12, 0.12, 0.12), (1, 1, 1)), ((0.88, 0.1, 0.1), (-1, 1, 1)), ((0.1, 0.9, 0.1), (1, -1, 1))]
        for k, (origin, normal) in enumerate(corners):
            r = cut(s, SweepSurface.plane(origin, normal, 0.6), collect=False)
            ref = _face_graph_labels(s)
            assert r.components == len(np.unique(ref[ref >= 0])) == k + 2
        # the big piece of the first cut split in two by a plane across it, then a corner of one half cut off
        r = cut(s, SweepSurface.plane((0.5, 0.5, 0.55), (0, 0, 1), 3.0), collect=False)
        assert r.components == 5
        r = cut(s, SweepSurface.plane((0.9, 0.9, 0.9), (1, 1, 1), 0.6), collect=False)
        ref = _face_graph_labels(s)
        assert r.components == len(np.unique(ref[ref >= 0])) == 6
        full_counts = [c for c in counted if c is False]
        if floods:  # only the plane across the whole mesh (a batch above 1/64 of the cells) counted every cell
            assert len(full_counts) == 1
        else:
            assert len(full_counts) == 5


def test_stroke_across_two_pieces_keeps_the_count_by_the_flood(monkeypatch):
    """A box cut in two, then strokes across the gap (the removed cells in two clusters, one per piece) that
    sever nothing, then one that cuts a corner off: the counts are a graph library's, and only the plane
    through the whole box counted every cell (the strokes' joins show each cluster still joined); then
    strips cut off both halves of another box at once, counted over every cell."""
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (12, 12, 12)))
    counted = _full_counts(monkeypatch)
    s._component_count()
    counted.clear()
    r = cut(s, SweepSurface.plane((0.51, 0.5, 0.5), (1, 0.05, 0.02), 3.0), collect=False)
    assert r.components == 2
    for y in (0.31, 0.6, 0.73):
        blade = np.array([[0.3, y, 1.1], [0.72, y + 0.02, 1.1]])
        r = cut(s, SweepSurface.from_blade(blade, blade - (0, 0, 0.35)), collect=False)
        ref = _face_graph_labels(s)
        assert r.components == len(np.unique(ref[ref >= 0])) == 2
    r = cut(s, SweepSurface.plane((0.1, 0.1, 0.12), (1, 1, 1), 0.6), collect=False)
    ref = _face_graph_labels(s)
    assert r.components == len(np.unique(ref[ref >= 0])) == 3
    assert [c for c in counted if c is False] == [False]
    # strips cut off both pieces at once (removed cells in two clusters, something severed): the joins cannot
    # show the count kept, so every cell is counted, and the counts are the graph library's
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (8, 8, 8)))
    s._component_count()
    cut(s, SweepSurface.plane((0.51, 0.5, 0.5), (1, 0.05, 0.02), 3.0), collect=False)
    counted.clear()
    for origin, normal, pieces in (((0.5, 0.1, 0.11), (0, 1, 1), 4), ((0.5, 0.9, 0.11), (0, -1, 1), 6)):
        r = cut(s, SweepSurface.plane(origin, normal, 3.0), collect=False)
        ref = _face_graph_labels(s)
        assert r.components == len(np.unique(ref[ref >= 0])) == pieces
    assert [c for c in counted if c is False] == [False, False]


def _moved_cuts(mesh, near_search, monkeypatch):
    from warpblob.cut import _cut as cut_module

    monkeypatch.setattr(cut_module, "_NEAR_SEARCH", near_search)
    s = TetStructure.from_tetmesh(mesh)
    s.set_positions((mesh.nodes + 0.04 * np.sin(3.0 * mesh.nodes[:, [1, 2, 0]])).astype(np.float32))
    blade = np.array([[0.1, 0.52, 1.1], [0.6, 0.55, 1.1]])
    for sweep in (SweepSurface.from_blade(blade, blade - (0, 0, 0.7)),
                  SweepSurface.from_blade(blade + (0.35, 0, 0), blade + (0.35, 0.0, -0.5))):  # fmt: skip
        cut(s, sweep, collect=False)
    return s


def test_local_search_in_the_current_frame_cuts_the_same(monkeypatch):
    """Nodes moved off their rest positions, two strokes cut where the nodes are: with the search of the
    cells near the sweep (the rest grid's boxes grown by how far the nodes moved) every array is as with
    the passes over everything, and the search was used."""
    mesh = box_tetmesh((0, 0, 0), (1, 1, 1), (16, 16, 16))
    found = []
    real = TetStructure._cells_near
    monkeypatch.setattr(TetStructure, "_cells_near", lambda self, lo, hi: found.append(real(self, lo, hi)) or found[-1])
    local = _moved_cuts(mesh, 0, monkeypatch)
    assert any(f is not None for f in found)
    whole = _moved_cuts(mesh, 1 << 40, monkeypatch)
    for kind, store in local._stores.items():
        for name in store.arrays:
            np.testing.assert_array_equal(store[name], whole._stores[kind][name], err_msg=f"{kind}.{name}")
    assert local.cell_count > mesh.tet_count


def test_piece_count_is_remembered_until_the_cells_change():
    """The count is known after a build, kept by a compaction, forgotten by any cell edit (counted anew
    then), and always equal to the count of a union-find over every cell."""
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (4, 4, 4)))
    assert s._known_pieces() == 1
    cut(s, SweepSurface.plane((0.51, 0.5, 0.5), (1, 0.1, 0), 3.0), collect=False)
    assert s._known_pieces() == 2
    s.collect_garbage()
    assert s._known_pieces() == 2 == int(s.components().max()) + 1
    c = int(np.flatnonzero(np.asarray(s.cell_alive))[0])
    s.remove_cell(c)
    assert s._known_pieces() is None
    assert s._component_count() == int(s.components().max()) + 1


def test_rest_grid_of_far_apart_pieces_stays_small(monkeypatch):
    """Two boxes a thousand units apart: the grid's buckets stay within four per cell (its side grows), a
    box query still holds every cell it meets, and a stroke cuts the same with and without the search."""
    from warpblob.cut import _cut as cut_module
    from warpblob.mesh import TetMesh

    a = box_tetmesh((0, 0, 0), (1, 1, 1), (6, 6, 6))
    b = box_tetmesh((1000, 1000, 1000), (1001, 1001, 1001), (6, 6, 6))
    mesh = TetMesh(np.concatenate([a.nodes, b.nodes]), np.concatenate([a.tets, b.tets + a.node_count]))
    results = []
    for near_search in (0, 1 << 40):
        monkeypatch.setattr(cut_module, "_NEAR_SEARCH", near_search)
        s = TetStructure.from_tetmesh(mesh)
        grid = s._rest_grid
        assert np.prod(grid.dims) <= 4 * grid.cells + 64
        got = s._cells_near((1000.2, 1000.2, 1000.2), (1000.3, 1000.3, 1000.3))
        assert got is None or np.isin(np.arange(a.tet_count, 2 * a.tet_count)[
            (mesh.nodes[b.tets + a.node_count].min(axis=1) <= 1000.3).all(axis=1)
            & (mesh.nodes[b.tets + a.node_count].max(axis=1) >= 1000.2).all(axis=1)], got).all()  # fmt: skip
        blade = np.array([[0.1, 0.52, 1.1], [0.8, 0.55, 1.1]])
        r = cut(s, SweepSurface.from_blade(blade, blade - (0, 0, 0.6)), collect=False)
        results.append((r.tets_added, np.asarray(s.cell_nodes).copy()))
    assert results[0][0] == results[1][0] > 0
    np.testing.assert_array_equal(results[0][1], results[1][1])


def _look_ahead_reference(state, rows_nodes, rows_edges, own, code_ok, hits, t_hit, edge_nodes, node_cut, dropped,
                          moved, rounds=64):  # fmt: skip
    """The look-ahead in numpy, pass by pass (the rules of :class:`~warpblob.cut._cut._LookAhead`): returns
    node_cut, dropped, the locked nodes and the hits kept at the last pass's start."""
    node_cut, dropped, locked = node_cut.copy(), dropped.copy(), state.is_protected.copy()
    corners, ge, code = state.active_rows()
    slot = {int(e): i for i, e in enumerate(hits)}
    bits6, bits4 = 1 << np.arange(6), 1 << np.arange(4)
    keep = np.zeros(len(hits), dtype=bool)
    for _ in range(rounds):
        mark = np.zeros(len(node_cut), dtype=bool)
        mark[moved] = True
        keep = (node_cut[edge_nodes[hits, 0]] == 0) & (node_cut[edge_nodes[hits, 1]] == 0) & ~dropped
        edge_cut = np.zeros(len(edge_nodes), dtype=bool)
        edge_cut[hits] = keep
        rows = []
        for i in np.flatnonzero(own & mark[rows_nodes].any(axis=1)):
            cut = edge_cut[rows_edges[i]]
            if cut.any() and not code_ok[cut @ bits6, (node_cut[rows_nodes[i]] != 0) @ bits4]:
                rows.append(rows_edges[i][cut])
        stuck = []
        for r in np.flatnonzero(mark[corners].any(axis=1) if len(corners) else []):
            cut = (ge[r] >= 0) & edge_cut[np.maximum(ge[r], 0)]
            corner_cut = node_cut[corners[r]] != 0
            if (cut.any() or corner_cut.any()) and not code_ok[code[r] | cut @ bits6, corner_cut @ bits4]:
                if cut.any():
                    rows.append(ge[r][cut])
                else:
                    stuck.extend(corners[r][corner_cut].tolist())
        if not rows and not stuck:
            break
        node_cut[stuck] = 0
        locked[stuck] = True
        moved = list(stuck)
        for edges in rows:
            t = t_hit[[slot[int(e)] for e in edges]]
            j = int(np.argmin(np.minimum(t, 1.0 - t)))
            target = edge_nodes[edges[j], 0 if t[j] < 0.5 else 1]
            if locked[target]:
                dropped[slot[int(edges[j])]] = True
                moved.extend(edge_nodes[edges[j]].tolist())
            else:
                node_cut[target] = 1
                moved.append(int(target))
    return node_cut, dropped, locked, keep


def test_look_ahead_follows_the_snap_rule(device):
    """The classification's look-ahead kernel (cells on their codes, progressive records on their accumulated
    codes) leaves the cut nodes, dropped hits, locked nodes and kept hits of a numpy reference of its rules,
    from random cut states of a mesh with progressive records."""
    from warpblob.cut._cut import _LookAhead, _ParentState, _table_arrays, cut_tables

    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (5, 5, 5)))
    ys = np.linspace(-0.5, 0.43, 12)  # the blade stops inside the box: progressive records
    a = np.column_stack([np.full_like(ys, 0.5), ys, np.full_like(ys, -0.5)])
    cut(s, SweepSurface.from_blade(a, a + (0, 0, 2.0)), device=device)
    edge_nodes = np.asarray(s.edge_nodes)
    cells = np.flatnonzero(np.asarray(s.cell_alive))
    rows_nodes, rows_edges = np.asarray(s.cell_nodes)[cells], np.asarray(s.cell_edges)[cells]
    code_ok = _table_arrays(cut_tables(), device)["code_ok"]
    rng = np.random.default_rng(5)
    snapped = 0
    for trial in range(30):
        state = _ParentState(s, edge_nodes)
        assert state.active.size > 3
        own = state.record_of(cells) < 0
        hits = np.unique(rng.choice(len(edge_nodes), size=len(edge_nodes) // 3, replace=False)).astype(np.int32)
        t_hit = rng.choice([0.25, 0.3, 0.7, 0.75], len(hits))  # (ties between ends: the first edge wins)
        node_cut = (rng.random(len(s.node_rest)) < 0.05).astype(np.uint8)
        node_cut[state.protected] = 0
        dropped = rng.random(len(hits)) < 0.1
        moved = rng.choice(len(s.node_rest), size=20, replace=False)
        expected = _look_ahead_reference(state, rows_nodes, rows_edges, own, code_ok, hits, t_hit, edge_nodes,
                                         node_cut, dropped, moved)  # fmt: skip
        slots = np.zeros(len(edge_nodes), dtype=np.int32)
        slots[hits] = np.arange(1, len(hits) + 1)
        edge_cut = np.zeros(len(edge_nodes), dtype=np.uint8)
        before = node_cut.copy()
        _LookAhead(state, rows_nodes, rows_edges, own, code_ok, hits, t_hit, slots, edge_nodes, node_cut, edge_cut,
                   dropped).run(moved)  # fmt: skip
        np.testing.assert_array_equal(node_cut, expected[0])
        np.testing.assert_array_equal(dropped, expected[1])
        np.testing.assert_array_equal(state.is_protected, expected[2])
        np.testing.assert_array_equal(state.protected, np.flatnonzero(expected[2]))
        np.testing.assert_array_equal(edge_cut[hits] != 0, expected[3])
        snapped += int((node_cut != before).sum())
    assert snapped > 0  # the trials snapped and unlocked nodes


def test_a_round_reduction_returns_every_node_it_changed(device):
    """A round's reduction (``_reduce``) of its bad units: a cell with a new cut edge snaps it onto the end
    nearest its split point, a snap onto a protected end drops the hit instead, and a progressive record with
    no new edge keeps its cut corners uncut (protected from then on); the nodes it returns for the look-ahead
    are the new cut node, both ends of the dropped hit and the corners kept uncut (their edges are cut again,
    so the codes round them change too)."""
    from warpblob.cut._cut import _ParentState, _reduce

    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (5, 5, 5)))
    ys = np.linspace(-0.5, 0.43, 12)  # the blade stops inside the box: progressive records
    a = np.column_stack([np.full_like(ys, 0.5), ys, np.full_like(ys, -0.5)])
    cut(s, SweepSurface.from_blade(a, a + (0, 0, 2.0)), device=device)
    edge_nodes = np.asarray(s.edge_nodes)
    state = _ParentState(s, edge_nodes)
    assert state.active.size
    record = int(state.active[0])
    corners = s._parents["corners"][record].astype(np.int64)
    free = ~state.is_protected
    # two cells away from the records' nodes, each with an edge cut now: one snaps, one meets a protected end
    cells = [c for c in np.flatnonzero(np.asarray(s.cell_alive))
             if free[np.asarray(s.cell_nodes)[c]].all() and s.cell_parent[c] < 0][:40:39]  # fmt: skip
    e1, e2 = (int(np.asarray(s.cell_edges)[c][0]) for c in cells)
    split_t = np.full(len(edge_nodes), -1.0)
    split_t[[e1, e2]] = 0.3, 0.8  # nearest the first end of e1, the second end of e2
    state.is_protected[edge_nodes[e2, 1]] = True
    node_cut = np.zeros(len(s.node_rest), dtype=np.uint8)
    node_cut[corners[1]] = 1  # the record's corner cut, with no new edge of its own: it stays uncut
    hits = np.array(sorted([e1, e2]), dtype=np.int32)
    dropped = np.zeros(2, dtype=bool)
    none = [-1] * 6
    units = {
        "new_edges": np.array([[e1, *none[1:]], [e2, *none[1:]], none], dtype=np.int64),
        "parent": np.array([-1, -1, record], dtype=np.int64),
        "corners": np.vstack([np.asarray(s.cell_nodes)[cells], corners]).astype(np.int64),
        "cell": np.array([*cells, -1], dtype=np.int64),
    }
    moved = _reduce(units, np.ones(3, dtype=bool), split_t, edge_nodes, node_cut, dropped, hits, state)
    assert node_cut[edge_nodes[e1, 0]] == 1 and node_cut[edge_nodes[e2, 1]] == 0 and node_cut[corners[1]] == 0
    np.testing.assert_array_equal(dropped, hits == e2)
    assert state.is_protected[corners[1]] and corners[1] in state.protected
    assert set(moved.tolist()) == {int(edge_nodes[e1, 0]), *edge_nodes[e2].tolist(), int(corners[1])}


def _stroke_frame(frame: int, side: float = 4.0) -> SweepSurface:
    """Frame ``frame`` of a scalpel stroke through the middle of a box of side ``side`` (cm): a 2 cm cutting edge
    leaning 15 degrees back, moving at 10 cm/s heading 20 degrees off the x axis, 1/60 s a frame; its tip ends
    inside the box, so the frames leave and continue progressive records."""
    heading, lean = np.radians(20.0), np.radians(15.0)
    d = np.array([np.cos(heading), np.sin(heading), 0.0])
    back = 2.0 * (np.cos(lean) * np.array([0.0, 0.0, 1.0]) - np.sin(lean) * d)
    step = 10.0 / 60.0
    centre = np.array([0.5 * side, 0.5 * side, side + 0.5 - back[2]]) + frame * step * d
    tip = centre + np.outer([-0.5, 0.5], step * d)
    return SweepSurface.from_blade(tip, tip + back)


def test_codes_the_tables_lack_snap_before_classification(monkeypatch, device):
    """Tets whose codes the tables lack (the tet ahead of the last frame's front) are snapped from their codes
    alone, before the classification: frame after frame the mesh is the one the classification's reduction
    round makes (the check turned off), in fewer rounds."""
    import warpblob.cut._cut as cut_module

    mesh = box_tetmesh((0, 0, 0), (4.0, 4.0, 4.0), (12, 12, 12))
    check = cut_module._lacking_corners
    fast, slow = TetStructure.from_tetmesh(mesh), TetStructure.from_tetmesh(mesh)
    rounds = {"fast": 0, "slow": 0}
    lacking = 0
    for frame in range(9):
        sweep = _stroke_frame(frame)
        monkeypatch.setattr(cut_module, "_lacking_corners", lambda *a: np.zeros(0, dtype=np.int64))
        rounds["slow"] += cut(slow, sweep, collect=False, device=device).reductions
        found = []

        def recorded(*args, found=found):
            found.append(check(*args))
            return found[-1]

        monkeypatch.setattr(cut_module, "_lacking_corners", recorded)
        rounds["fast"] += cut(fast, sweep, collect=False, device=device).reductions
        lacking += sum(len(c) > 0 for c in found)
        for name in ("cell_nodes", "cell_alive", "node_rest", "edge_nodes"):
            np.testing.assert_array_equal(np.asarray(getattr(fast, name)), np.asarray(getattr(slow, name)))
    fast.check()
    assert lacking > 0  # some frame had codes the tables lack
    assert rounds["fast"] < rounds["slow"]


def test_the_codes_found_lacking_are_those_the_classification_rejects(device):
    """Every (edge code, node code) of a well-shaped tet cut at its edges' middles: the classification kernel
    (table entry, then the sub-tets' shapes) rejects exactly the codes ``_lacking_corners`` finds from the codes
    alone, and for a progressive record the same from its accumulated code."""
    from warpblob.cut._cut import _classify_units, _lacking_corners, _table_arrays, cut_tables

    tables = cut_tables()
    rest = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
    edge, node = np.meshgrid(np.arange(1, 64), np.arange(16), indexing="ij")
    edge, node = edge.ravel(), node.ravel()
    n = len(edge)
    units = {"corners": np.tile(np.arange(4), (n, 1)), "edge_code": edge, "node_code": node, "t": np.full((n, 6), 0.5)}
    rejected = _classify_units(tables, units, rest, wp.get_device(device), None)[3]
    assert 0 < rejected.sum() < n
    code_ok = _table_arrays(tables, wp.get_device(device))["code_ok"]
    corners = np.arange(4 * n).reshape(n, 4)  # (distinct corners: a unit's are found by its row)
    for as_cells in (True, False):
        if as_cells:
            found = _lacking_corners(code_ok, edge | node << 6, corners, None)
        else:
            parents = {"edge_code": edge, "node_code": node, "corners": corners}
            found = _lacking_corners(code_ok, np.zeros(0, dtype=np.int64), np.zeros((0, 4), dtype=np.int64), parents)
        lacking = np.zeros(n, dtype=bool)
        lacking[found // 4] = True
        np.testing.assert_array_equal(lacking, rejected)


def test_cut_node_pairing_leaves_the_pooled_tables_empty():
    """The cut-node copies pair their faces through the batch edits' pooled hash table: after a cut with cut
    nodes every pooled table is EMPTY again, and the same cut of a fresh structure (the table now warm from
    the first) gives the same structure, array for array."""
    mesh = box_tetmesh((0, 0, 0), (1, 1, 1), (4, 4, 4))
    sweep = SweepSurface.plane((0.5, 0.51, 0.49), (1.0, 0.02, -0.01), 3.0)  # (through the nodes at x = 0.5)
    made = []
    for _ in range(2):
        s = TetStructure.from_tetmesh(mesh)
        r = cut(s, sweep, collect=False)
        assert r.nodes_cut > 0 and r.components == 2
        assert structure_module._KEY_TABLES
        assert all(np.all(table[:, 0] == -1) for table in structure_module._KEY_TABLES)
        s.check()
        made.append(s)
    for name in ("node_rest", "edge_nodes", "face_nodes", "face_cells", "cell_nodes", "cell_faces", "cell_alive"):
        np.testing.assert_array_equal(getattr(made[0], name), getattr(made[1], name), err_msg=name)


def test_a_key_table_left_by_an_error_does_not_go_back_to_the_pool():
    """The pooled hash table goes back to the pool only when its block ends normally (a kernel stopped midway
    may leave keys in it): after an error inside the block the pool is as before, and the next table is
    EMPTY."""
    with structure_module._key_table(100) as (table, _bits):
        pass
    before = len(structure_module._KEY_TABLES)
    with pytest.raises(RuntimeError, match="midway"):
        with structure_module._key_table(100) as (table, _bits):
            table.numpy()[0] = 7  # (a key left behind)
            raise RuntimeError("stopped midway")
    assert len(structure_module._KEY_TABLES) == before - 1
    with structure_module._key_table(100) as (table, bits):
        assert np.all(table.numpy()[0 : 2 << bits : 2] == -1)
