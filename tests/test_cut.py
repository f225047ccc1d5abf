"""Cutting a tet mesh along a sweep: invariants against independent references (VTK's clip, geometry)."""

import numpy as np
import pytest

import warpblob as wb
from warpblob.cut import CutError, SweepSurface, cut
from warpblob.mesh import TetStructure, box_tetmesh

SNAP = 0.2


def _box(n=4, jitter=0.0, seed=0):
    m = box_tetmesh((0, 0, 0), (1, 1, 1), (n, n, n))
    if jitter:
        rng = np.random.default_rng(seed)
        nodes = m.nodes.astype(np.float64).copy()
        inner = np.all((nodes > 1e-6) & (nodes < 1 - 1e-6), axis=1)
        nodes[inner] += rng.uniform(-jitter, jitter, (int(inner.sum()), 3)) / n
        m = wb.TetMesh(nodes, m.tets)
    return m


def _invariants(s: TetStructure, volume: float) -> wb.TetMesh:
    """Links consistent, no inverted or flat tets (rest and current), volume kept, faces shared by at most two."""
    s.check()
    tm = s.to_tetmesh()
    rest = s.to_tetmesh(rest=True)
    assert tm.volumes().min() > 0 and rest.volumes().min() > 0
    assert abs(rest.volume() - volume) <= 1e-6 * volume
    assert tm.is_conforming()
    return tm


def _clip_volume(tm: wb.TetMesh, origin, normal) -> float:
    """Volume of the mesh on the +normal side of a plane by VTK's exact table-based clip (an independent reference)."""
    g = tm.to_pyvista()
    part = g.clip(normal=[-x for x in normal], origin=list(origin), crinkle=False)  # keeps the -(-n) = +n side
    return float(part.compute_cell_sizes().cell_data["Volume"].sum()) if part.n_cells else 0.0


def _sides(tm: wb.TetMesh, origin, normal):
    """Signed distance range of each tet's corners to the plane, and each tet's longest edge."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    d = (tm.nodes.astype(np.float64) - origin) @ n
    dt = d[tm.tets]
    p = tm.nodes[tm.tets].astype(np.float64)
    longest = np.max([np.linalg.norm(p[:, i] - p[:, j], axis=1) for i in range(4) for j in range(i)], axis=0)
    return dt.min(axis=1), dt.max(axis=1), longest


@pytest.mark.parametrize("scene", ["box", "tumor"])
def test_planar_cut_through_the_model(scene, device):
    m = _box(5, jitter=0.3) if scene == "box" else wb.tetrahedralize(wb.scenes.tumor(), cellsize=0.2)
    lo, hi = m.nodes.min(axis=0), m.nodes.max(axis=0)
    origin, normal = (lo + hi) / 2 + 0.013, np.array([0.3, 0.2, 1.0])
    s = TetStructure.from_tetmesh(m)
    r = cut(s, SweepSurface.plane(origin, normal, 4 * float(np.max(hi - lo))), snap=SNAP, device=device)
    tm = _invariants(s, m.volume())
    assert r.components == 2 and r.edges_cut > 0 and r.tets_added > r.tets_removed
    labels = s.components()[np.asarray(s.cell_alive)]
    # every tet on one side of the plane, within the snapping bound (a snapped node is within snap x its edge)
    dmin, dmax, _ = _sides(tm, origin, normal)
    edge = float(np.max(_sides(m, origin, normal)[2]))
    assert np.all(np.minimum(dmax, -dmin) <= SNAP * edge + 1e-6)
    # each piece is one side: its volume is the exact clipped volume within section area x snap x longest edge
    vols = tm.volumes()
    up = (dmin + dmax) / 2 > 0
    assert len(np.unique(labels[up])) == 1 and len(np.unique(labels[~up])) == 1
    ref = _clip_volume(m, origin, normal)
    section = _clip_section_area(m, origin, normal)
    assert abs(vols[up].sum() - ref) <= section * SNAP * edge
    assert vols[up].sum() > 0 and vols[~up].sum() > 0


def _clip_section_area(tm, origin, normal) -> float:
    g = tm.to_pyvista()
    sec = g.slice(normal=list(normal), origin=list(origin))
    return float(sec.compute_cell_sizes().cell_data["Area"].sum())


def test_cut_surface_marks_cut_faces_and_is_closed():
    m = _box(4, jitter=0.25, seed=2)
    s = TetStructure.from_tetmesh(m)
    origin, normal = np.array([0.5, 0.47, 0.5]), np.array([0.1, 1.0, 0.0])
    cut(s, SweepSurface.plane(origin, normal, 3.0))
    surf = s.surface(model=wb.scenes.tumor())
    assert surf.is_closed_manifold() and surf.shell_count() == 2
    n = normal / np.linalg.norm(normal)
    d = np.abs((surf.vertices[surf.faces].astype(np.float64) - origin) @ n)  # (F, 3)
    edge = 1.0 / 4 * np.sqrt(3)
    assert surf.is_cut.any() and np.all(d[surf.is_cut] <= SNAP * edge + 1e-6)
    # the uncut faces are the box's own faces
    p = surf.vertices[surf.faces[~surf.is_cut]].astype(np.float64)
    on_box = np.any(np.all((np.abs(p) < 1e-6) | (np.abs(p - 1) < 1e-6), axis=1), axis=1)
    assert on_box.all()
    # the area of the cut faces is twice the section (two sides)
    tri = surf.vertices[surf.faces[surf.is_cut]].astype(np.float64)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert abs(area - 2 * _clip_section_area(m, origin, normal)) < 0.15 * area
    assert np.all((surf.colors >= 0) & (surf.colors <= 1))


def test_cut_through_lattice_nodes_and_faces():
    """A plane through a layer of nodes (in the plane of faces, along edges): all snaps, no edge split."""
    m = _box(5)
    s = TetStructure.from_tetmesh(m)
    r = cut(s, SweepSurface.plane((0.4, 0.5, 0.5), (1, 0, 0), 3.0))
    _invariants(s, 1.0)
    assert r.edges_cut == 0 and r.nodes_cut == 36 and r.components == 2
    tm = s.to_tetmesh()
    sides = tm.nodes[tm.tets].mean(axis=1)[:, 0] > 0.4
    labels = s.components()[np.asarray(s.cell_alive)]
    assert np.isclose(tm.volumes()[sides].sum(), 0.6) and len(np.unique(labels[sides])) == 1


def test_tangent_cut_changes_nothing_that_matters():
    m = _box(4)
    s = TetStructure.from_tetmesh(m)
    r = cut(s, SweepSurface.plane((0.0, 0.5, 0.5), (1, 0, 0), 3.0))  # the plane of the box's face
    _invariants(s, 1.0)
    assert r.components == 1 and r.edges_cut == 0 and s.cell_count == m.tet_count


def test_partial_stroke_leaves_one_piece_and_a_second_stroke_separates():
    m = _box(5)
    s = TetStructure.from_tetmesh(m)
    ys = np.linspace(-0.5, 0.5, 12)  # the blade stops inside the tets of the middle row
    a = np.column_stack([np.full_like(ys, 0.5), ys, np.full_like(ys, -0.5)])
    r = cut(s, SweepSurface.from_blade(a, a + (0, 0, 2.0)))
    _invariants(s, 1.0)
    assert r.components == 1
    assert sum(r.tets_split.get(k, 0) for k in ("C", "D", "E")) > 0  # progressive entries were used
    surf = s.surface()
    assert surf.is_closed_manifold() and surf.is_cut.sum() > 0  # a slit: two sheets joined at the front
    ys = np.linspace(0.45, 1.5, 12)
    a = np.column_stack([np.full_like(ys, 0.5), ys, np.full_like(ys, -0.5)])
    r = cut(s, SweepSurface.from_blade(a, a + (0, 0, 2.0)))
    tm = _invariants(s, 1.0)
    assert r.components == 2
    labels = s.components()[np.asarray(s.cell_alive)]
    left = tm.nodes[tm.tets].mean(axis=1)[:, 0] < 0.5
    # section area 1 x snap x longest edge: the second stroke snaps the first one's crack fronts onto its cut
    assert abs(tm.volumes()[left].sum() - 0.5) <= SNAP * 0.2 * np.sqrt(3) and len(np.unique(labels[left])) == 1


def test_snapped_partial_strokes_join():
    """Strokes that snap onto a node layer, the second starting where the first stopped: its snapping takes the
    first one's last nodes again, whose stars then come apart."""
    m = _box(5)
    s = TetStructure.from_tetmesh(m)
    for y0, y1 in ((-0.5, 0.45), (0.35, 1.5)):
        ys = np.linspace(y0, y1, 12)
        a = np.column_stack([np.full_like(ys, 0.43), ys, np.full_like(ys, -0.5)])
        r = cut(s, SweepSurface.from_blade(a, a + (0, 0, 2.0)))
        _invariants(s, 1.0)
        assert r.components == (1 if y0 < 0 else 2)


def test_second_cut_across_the_first():
    m = _box(4, jitter=0.2, seed=5)
    s = TetStructure.from_tetmesh(m)
    cut(s, SweepSurface.plane((0.5, 0.5, 0.5), (1, 0.1, 0), 3.0))
    r = cut(s, SweepSurface.plane((0.5, 0.5, 0.5), (0, 0.1, 1), 3.0))
    tm = _invariants(s, 1.0)
    assert r.components == 4
    c = tm.nodes[tm.tets].mean(axis=1) - 0.5
    quadrant = (c @ (1, 0.1, 0) > 0).astype(int) * 2 + (c @ (0, 0.1, 1) > 0)
    labels = s.components()[np.asarray(s.cell_alive)]
    assert all(len(np.unique(labels[quadrant == q])) == 1 for q in range(4))


def test_random_cut_sequences_keep_every_invariant():
    """1,000 random sequences of 1-5 cuts (planes and curved strokes, partial ones too) on small meshes."""
    rng = np.random.default_rng(12345)
    meshes = [_box(2), _box(3, jitter=0.3, seed=1), _box(3)]
    for trial in range(1000):
        m = meshes[trial % len(meshes)]
        s = TetStructure.from_tetmesh(m)
        for _ in range(int(rng.integers(1, 6))):
            o = rng.uniform(0.0, 1.0, 3)
            if rng.random() < 0.5:
                sweep = SweepSurface.plane(o, rng.normal(size=3), 3.0)
            else:  # a curved stroke: a circular arc of a vertical blade, maybe stopping inside
                th = np.linspace(0, rng.uniform(0.5, 3.0), 16) + rng.uniform(0, 6.3)
                radius = rng.uniform(0.2, 0.8)
                a = np.column_stack([o[0] + radius * np.cos(th), o[1] + radius * np.sin(th), np.full_like(th, -0.5)])
                sweep = SweepSurface.from_blade(a, a + (rng.normal() * 0.3, rng.normal() * 0.3, 2.0))
            cut(s, sweep, snap=float(rng.choice([0.0, 0.1, 0.2, 0.3])))
        tm = _invariants(s, 1.0)
        assert s.components().max() + 1 >= 1 and tm.tet_count >= m.tet_count


def test_cut_result_counts_and_table_kinds():
    m = _box(4, jitter=0.3, seed=3)
    s = TetStructure.from_tetmesh(m)
    r = cut(s, SweepSurface.plane((0.5, 0.5, 0.5), (0.2, 0.3, 1.0), 3.0), collect=False)
    assert r.tets_added == len(r.added) and r.tets_removed == len(r.removed)
    assert r.nodes_added == len(r.new_nodes) == len(r.node_sources) == len(r.node_weights)
    assert set(r.tets_split) <= {"A", "B", "X", "Y", "Z", "touch", "C", "D", "E"}
    assert set(r.seconds) == set(wb.cut.STAGES) and r.remap is None
    # split points lie where their sources say
    rest = np.asarray(s.node_rest, dtype=np.float64)
    a, b = r.node_sources[:, 0], r.node_sources[:, 1]
    split = np.asarray(s.node_origin)[r.new_nodes] == 1
    w = r.node_weights[split][:, None]
    assert np.allclose(rest[r.new_nodes[split]], (1 - w) * rest[a[split]] + w * rest[b[split]], atol=1e-6)
    assert 2 * r.edges_cut == split.sum()
    # a plane through everything splits completely: A 4, B 6, X 3, Y 2 sub-tets
    assert r.split_cells == sum(r.tets_split.get(kind, 0) for kind in ("A", "B", "X", "Y"))
    assert 2 <= r.new_cells_per_cut_cell <= 6 and r.split_added <= r.tets_added
    # deferred removal: the removed cells are pending until the garbage collection
    assert not np.asarray(s.cell_alive)[r.removed].any()
    maps = s.collect_garbage()
    assert (maps["cell"][r.removed] == -1).all()
    _invariants(s, 1.0)


def test_batch_edit_fires_one_event_per_kind():
    s = TetStructure.from_tetmesh(_box(2))
    events = []
    s.subscribe(lambda kind, action, index: events.append((kind, action, np.size(index))))
    cut(s, SweepSurface.plane((0.5, 0.5, 0.5), (1, 0.2, 0.1), 3.0), collect=False)
    actions = [(k, a) for k, a, _ in events]
    assert actions.count(("cell", "insert")) == 1 and actions.count(("cell", "remove")) == 1
    assert sum(n for k, a, n in events if (k, a) == ("cell", "insert")) == s.cell_count - (48 - sum(
        n for k, a, n in events if (k, a) == ("cell", "remove")))  # fmt: skip


def test_bad_input_is_refused_and_leaves_the_structure_alone():
    m = _box(2)
    s = TetStructure.from_tetmesh(m)
    before = {k: np.array(getattr(s, k)) for k in ("node_rest", "cell_nodes", "face_cells", "edge_nodes")}
    plane = SweepSurface.plane((0.5, 0.5, 0.5), (1, 0, 0), 2.0)
    for snap in (-0.1, 0.5, 0.7, float("nan"), "x", True):
        with pytest.raises(CutError, match="snap"):
            cut(s, plane, snap=snap)
    with pytest.raises(CutError, match="finite"):
        SweepSurface.from_blade([[0, 0, 0], [np.nan, 0, 0]], [[0, 0, 1], [1, 0, 1]])
    with pytest.raises(CutError, match="at least two"):
        SweepSurface.from_blade([[0, 0, 0]], [[0, 0, 1]])
    with pytest.raises(CutError, match="TetStructure"):
        cut(m, plane)
    with pytest.raises(CutError, match="normal"):
        SweepSurface.plane((0, 0, 0), (0, 0, 0), 1.0)
    # an inverted tet in the cut region
    nodes, tets = m.nodes.copy(), m.tets.copy()
    tets[0, [0, 1]] = tets[0, [1, 0]]
    bad = TetStructure.from_tetmesh(wb.TetMesh(nodes, tets))
    snapshot = np.array(bad.cell_nodes)
    with pytest.raises(CutError, match="inverted"):
        cut(bad, SweepSurface.plane(nodes[tets[0]].mean(axis=0), (1, 0.3, 0.2), 2.0))
    assert np.array_equal(np.array(bad.cell_nodes), snapshot) and bad.cell_count == m.tet_count
    for k, v in before.items():
        assert np.array_equal(np.array(getattr(s, k)), v)


def test_sweep_surfaces():
    p = SweepSurface.plane((1, 2, 3), (0, 0, 2), 1.5)
    assert np.allclose(p.normals(), [0, 0, 1]) and np.isclose(p.area(), 9.0)
    assert np.allclose(p.triangles[..., 2], 3.0)
    blade = wb.tools.Scalpel(1.0, 0.2)
    path = wb.tools.Path.line((-1, 0, 0), (1, 0, 0), 1.0, align=True)
    s = SweepSurface.from_path(blade, path, dt=0.1)
    tip, heel = blade.edge_points(path.pose(0.0))
    # a straight stroke sweeps a flat strip: every corner in the plane of the stroke and the blade
    n = np.cross(np.array([1.0, 0, 0]), heel - tip)
    n /= np.linalg.norm(n)
    assert np.allclose((s.triangles.reshape(-1, 3) - tip) @ n, 0, atol=1e-9)
    assert np.isclose(s.area(), 2.0 * np.linalg.norm(heel - tip))
    far = SweepSurface.from_path(blade, path, dt=0.1, bounds=[(10, 10, 10), (11, 11, 11)])
    assert far.triangle_count == 0
    drill = wb.tools.Drill(0.1, 0.5, segments=8)
    d = SweepSurface.from_path(drill, wb.tools.Path.line((0, 0, 1), (0, 0, 0), 1.0, align=True), dt=0.25)
    assert set(d.strips.tolist()) == set(range(8))
    # the drill's wall sweeps a cylinder of its radius
    r = np.linalg.norm(d.triangles.reshape(-1, 3)[:, :2], axis=1)
    assert np.allclose(r, 0.1, atol=1e-9)


def _cell_signature(s: TetStructure) -> np.ndarray:
    """Rest centroid and volume of every live cell, sorted: topology compared regardless of numbering."""
    tm = s.to_tetmesh(rest=True)
    sig = np.column_stack([tm.nodes[tm.tets].mean(axis=1), tm.volumes()[:, None] * 1e3]).round(6)
    return sig[np.lexsort(sig.T[::-1])]


@pytest.mark.parametrize("stop", [0.5, 0.43, 0.31])
def test_a_cut_in_two_strokes_has_the_topology_of_one_stroke(stop):
    """The blade stops inside tets (progressive records), a second stroke completes them: the same cells."""
    m = _box(5)

    def stroke(s, y0, y1):
        ys = np.linspace(y0, y1, 12)
        a = np.column_stack([np.full_like(ys, 0.5), ys, np.full_like(ys, -0.5)])
        return cut(s, SweepSurface.from_blade(a, a + (0, 0, 2.0)))

    one = TetStructure.from_tetmesh(m)
    stroke(one, -0.5, 1.5)
    two = TetStructure.from_tetmesh(m)
    first = stroke(two, -0.5, stop)
    assert first.components == 1 and np.asarray(two.cell_parent).max() >= 0  # progressive records kept
    second = stroke(two, stop - 0.05, 1.5)
    _invariants(two, 1.0)
    assert second.components == 2 and two.cell_count == one.cell_count
    np.testing.assert_allclose(_cell_signature(two), _cell_signature(one), atol=1e-5)
    assert np.all(np.asarray(two.cell_parent)[np.asarray(two.cell_alive)] == -1)  # every record completed


def test_drill_bores_a_closed_plug_out_of_a_slab():
    """A trephine through a slab: the plug is one closed piece whose volume is the wall polygon's prism."""
    m = box_tetmesh((0, 0, 0), (1, 1, 0.3), (12, 12, 4))
    s = TetStructure.from_tetmesh(m)
    drill = wb.tools.Drill(0.2, 0.6, segments=16)
    path = wb.tools.Path.line((0.51, 0.49, 0.5), (0.51, 0.49, -0.2), 1.0, align=True)
    sweep = SweepSurface.from_path(drill, path, dt=0.1)
    r = cut(s, sweep)
    tm = _invariants(s, 0.3)
    assert r.components == 2
    labels = s.components()[np.asarray(s.cell_alive)]
    plug = int(np.argmin(np.bincount(labels)))
    volume = tm.volumes()[labels == plug].sum()
    prism = 16 / 2 * 0.2**2 * np.sin(2 * np.pi / 16) * 0.3  # the 16-gon wall's area x the slab
    wall_area = 16 * 2 * 0.2 * np.sin(np.pi / 16) * 0.3
    edge = np.sqrt((1 / 12) ** 2 * 2 + (0.3 / 4) ** 2)
    assert abs(volume - prism) <= wall_area * SNAP * edge
    c = tm.nodes[tm.tets[labels == plug]].mean(axis=1)
    assert np.all(np.hypot(c[:, 0] - 0.51, c[:, 1] - 0.49) < 0.2 + SNAP * edge)
    surf = s.surface()
    assert surf.is_closed_manifold() and surf.shell_count() == 2
    # the sweep is ordered by time: the first triangles are the top ring's, all segments
    assert set(sweep.strips[: 2 * 16].tolist()) == set(range(16))
