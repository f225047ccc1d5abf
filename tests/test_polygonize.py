"""Polygonization: watertight, manifold, on the surface, and against a dense reference."""

import numpy as np
import pytest
from reference import reference_evaluate
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

import warpblob as wb
from warpblob.polygonize import _tables, _weld

R = 1.0
# head's layers are 0.04 apart: resolving them (and so comparing topology with
# another extractor) needs h < 0.02, a 300^3 dense grid; it is checked for
# watertightness below
SMALL_MODELS = ["peanut", "tumor", "eggshell", "cake", "three_slabs", "mug"]


def components(vertices, faces):
    n = len(vertices)
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[0]


def grid_like_polygonize(model, h):
    """The grid polygonize uses by default: the model box plus half a cell."""
    lo, hi = model.bounds()
    lo = (lo - 0.5 * h).astype(np.float32).astype(np.float64)
    cells = np.maximum(np.ceil((hi + 0.5 * h - lo) / h).astype(int), 1)
    axes = [lo[a] + h * np.arange(cells[a] + 1) for a in range(3)]
    return lo, axes


def dense_reference_mesh(model, h):
    from skimage.measure import marching_cubes

    lo, axes = grid_like_polygonize(model, h)
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    f = reference_evaluate(model, pts)[0].reshape([len(a) for a in axes])
    verts, faces, _, _ = marching_cubes(f, level=0.5, spacing=(h, h, h))
    return verts + lo, faces


def assert_closed_outward(mesh, model):
    assert mesh.face_count > 0
    assert mesh.is_closed_manifold(), "mesh is not a closed, consistently oriented 2-manifold"
    assert mesh.volume() > 0.0, "faces are oriented inwards"
    err = np.abs(wb.field(model, mesh.vertices) - 0.5)
    assert err.max() <= 1e-4, f"vertex off the surface by {err.max():.3g} in F"
    v = mesh.vertices
    fn = np.cross(v[mesh.faces[:, 1]] - v[mesh.faces[:, 0]], v[mesh.faces[:, 2]] - v[mesh.faces[:, 0]])
    assert np.all(np.linalg.norm(fn, axis=1) > 0.0), "zero-area triangle"


def test_lone_point_is_a_sphere_of_radius_04541R(device):
    model = wb.Point((0.1, -0.2, 0.3), R)
    mesh = wb.polygonize(model, cellsize=R / 20, device=device)
    r = wb.ISO_DISTANCE * R
    assert abs(mesh.area() / (4 * np.pi * r * r) - 1) < 0.01
    assert abs(mesh.volume() / (4 / 3 * np.pi * r**3) - 1) < 0.01
    d = np.linalg.norm(mesh.vertices - np.array([0.1, -0.2, 0.3]), axis=1)
    assert np.all(np.abs(d - r) < 1e-3)
    assert_closed_outward(mesh, model)
    stats = mesh.stats
    assert stats["triangles"] == mesh.face_count and stats["vertices"] == mesh.vertex_count
    assert stats["blocks_rejected"] > 0 and stats["field_evaluations"] > 0
    assert set(stats["seconds"]) >= {"classify", "classify_subblocks", "sample", "count", "vertices", "faces"}


@pytest.mark.parametrize("name", list(wb.scenes.ALL))
def test_reference_models_are_watertight_and_outward(name):
    model = wb.scenes.ALL[name]()
    h = 0.14 if name in ("towers", "medusa") else 0.08
    mesh = wb.polygonize(model, cellsize=h)
    assert_closed_outward(mesh, model)


@pytest.mark.parametrize("name", SMALL_MODELS)
def test_matches_dense_reference(name):
    model = wb.scenes.ALL[name]()
    h = 0.1
    mesh = wb.polygonize(model, cellsize=h)
    ref_v, ref_f = dense_reference_mesh(model, h)
    assert components(mesh.vertices, mesh.faces) == components(ref_v, ref_f)
    d1 = cKDTree(ref_v).query(mesh.vertices)[0].max()
    d2 = cKDTree(mesh.vertices).query(ref_v)[0].max()
    assert max(d1, d2) < h, f"Hausdorff distance {max(d1, d2):.3g} >= cellsize {h}"


def thin_and_tiny():
    """A thin plate, a hollow shell whose inner wall is a Difference, and tiny separate blobs."""
    h = 0.05
    plate = wb.Disc((0, 0, 0), (0, 0, 1), 1.0, 0.08)  # about 1.5 cells thick
    shell = wb.Point((2.5, 0, 0), 1.2) - wb.Point((2.5, 0, 0), 0.9)  # wall 0.136 thick, under 3 cells
    blobs = [wb.Point((x, 1.6, 0.0), 0.12) for x in np.linspace(-1, 1, 6)]  # ~2 cells across
    return wb.Union(plate, shell, *blobs), h


def test_thin_features_and_tiny_blobs_match_dense_reference():
    model, h = thin_and_tiny()
    mesh = wb.polygonize(model, cellsize=h)
    ref_v, ref_f = dense_reference_mesh(model, h)
    n = components(mesh.vertices, mesh.faces)
    assert n == components(ref_v, ref_f)
    assert n >= 1 + 2 + 6  # plate, outer and inner shell walls, six blobs
    d1 = cKDTree(ref_v).query(mesh.vertices)[0].max()
    d2 = cKDTree(mesh.vertices).query(ref_v)[0].max()
    assert max(d1, d2) < h
    assert_closed_outward(mesh, model)


def test_many_ambiguous_cells_stay_manifold():
    # blobs about one cell wide put many cells in ambiguous configurations
    rng = np.random.default_rng(4)
    h = 0.1
    model = wb.Blend(*[wb.Point(rng.uniform(-1, 1, 3), rng.uniform(0.18, 0.3)) for _ in range(300)])
    mesh = wb.polygonize(model, cellsize=h)
    assert_closed_outward(mesh, model)
    assert mesh.stats["centre_vertices"] >= 0


def test_normals_follow_the_reference_gradient():
    model = wb.scenes.tumor()
    mesh = wb.polygonize(model, cellsize=0.08)
    _, grad, colors = reference_evaluate(model, mesh.vertices.astype(np.float64))
    ref = -grad / np.linalg.norm(grad, axis=1, keepdims=True)
    cos = np.einsum("ij,ij->i", ref, mesh.normals)
    assert cos.min() > 1 - 1e-4
    np.testing.assert_allclose(mesh.colors, colors, atol=1e-4)


def test_one_and_two_threads_give_identical_meshes():
    model = wb.scenes.mug()
    a = wb.polygonize(model, cellsize=0.06, threads=1)
    b = wb.polygonize(model, cellsize=0.06, threads=2)
    for key in ("vertices", "faces", "normals", "colors"):
        assert np.array_equal(getattr(a, key), getattr(b, key)), key


def test_user_bounds_clip_the_surface():
    model = wb.Point((0, 0, 0), R)
    mesh = wb.polygonize(model, cellsize=0.05, bounds=((-1, -1, 0), (1, 1, 1)))
    assert mesh.face_count > 0
    assert mesh.vertices[:, 2].min() >= -1e-6
    _, counts = mesh.edge_face_counts()
    assert np.any(counts == 1)  # open along the cut
    empty = wb.polygonize(model, cellsize=0.05, bounds=((5, 5, 5), (6, 6, 6)))
    assert empty.face_count == 0 and empty.vertex_count == 0


def test_resource_error_names_the_estimate():
    with pytest.raises(wb.ResourceError, match=r"needs an estimated [\d.]+ (KiB|MiB|GiB), more than the 64.0 KiB"):
        wb.polygonize(wb.scenes.tumor(), cellsize=0.02, max_memory=1 << 16)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), "x"])
def test_bad_cellsize(bad):
    with pytest.raises(wb.WarpblobError, match="cellsize"):
        wb.polygonize(wb.scenes.tumor(), cellsize=bad)


def test_bad_bounds():
    with pytest.raises(wb.WarpblobError, match="bounds"):
        wb.polygonize(wb.scenes.tumor(), cellsize=0.1, bounds=((0, 0, 0), (0, 1, 1)))


def test_loop_table_is_consistent():
    """Every face segment of the generated table is shared, reversed, by the neighbouring cell."""
    table = _tables.build_loop_table()
    rng = np.random.default_rng(0)
    face_pairs = [(1, 0), (3, 2), (5, 4)]  # +x of a cell against -x of its +x neighbour, etc.
    for _ in range(3000):
        values = rng.normal(size=12).reshape(3, 2, 2)  # two cells sharing the middle face along x
        cfg_a = sum(1 << c for c in range(8) if values[c & 1, (c >> 1) & 1, (c >> 2) & 1] >= 0)
        cfg_b = sum(1 << c for c in range(8) if values[1 + (c & 1), (c >> 1) & 1, (c >> 2) & 1] >= 0)
        shared = values[1]
        s = [shared[0, 0], shared[1, 0], shared[1, 1], shared[0, 1]]  # (y, z) cycle
        joined = (s[0] >= 0) == (s[2] >= 0) and (s[0] >= 0) != (s[1] >= 0)
        inside_pair = s[0] * s[2] if s[0] >= 0 else s[1] * s[3]
        outside_pair = s[1] * s[3] if s[0] >= 0 else s[0] * s[2]
        bit = int(joined and inside_pair >= outside_pair)
        row_a = table[cfg_a * 64 + (bit << face_pairs[0][0])]
        row_b = table[cfg_b * 64 + (bit << face_pairs[0][1])]
        seg_a = _face_segments(row_a, face=1)
        seg_b = _face_segments(row_b, face=0)
        assert sorted(seg_a) == sorted((b, a) for a, b in seg_b)


def _face_segments(row, face):
    """Directed segments of a row's loops lying on ``face``, as pairs of (axis, corner-offset) edge ids."""
    corners = _tables.FACES[face][2]
    on_face = {e for e, (a, b) in enumerate(_tables.EDGE_CORNERS) if a in corners and b in corners}
    axis = _tables.FACES[face][0]
    segs, first = [], 0
    for lp in range(row[1]):
        n = row[2 + lp]
        loop = row[2 + _tables.MAX_LOOPS + first : 2 + _tables.MAX_LOOPS + first + n]
        first += n
        for t in range(n):
            a, b = loop[t], loop[(t + 1) % n]
            if a in on_face and b in on_face:
                # name the edge by its axis and its origin with the face axis dropped
                segs.append(tuple((int(_tables.EDGE_AXIS[e]), *np.delete(_tables.EDGE_ORIGIN[e], axis)) for e in (a, b)))
    return segs


@pytest.mark.parametrize("name", SMALL_MODELS + ["towers", "medusa"])
def test_fewer_skinny_triangles_than_classic_marching_cubes(name):
    import warp as wp
    import warp.geometry  # noqa: F401

    from warpblob.mesh._surface import triangle_min_angles

    model = wb.scenes.ALL[name]()
    h = 0.14 if name in ("towers", "medusa") else 0.08  # towers' exact vertices made 12% skinny ones before relaxation
    mesh = wb.polygonize(model, cellsize=h)
    lo, axes = grid_like_polygonize(model, h)
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float32)
    f = wb.field(model, pts).reshape([len(a) for a in axes])
    hi = [a[-1] for a in axes]
    mc = wp.geometry.IsoSurfaceMarchingCubes(*f.shape, tuple(lo), tuple(hi))
    mc.surface(wp.array(f, dtype=wp.float32), 0.5)
    theirs = np.mean(triangle_min_angles(mc.verts.numpy(), mc.indices.numpy().reshape(-1, 3)) < 10.0)
    ours = np.mean(mesh.min_angles() < 10.0)
    assert ours <= theirs, f"{ours:.3%} of our triangles are under 10 degrees, {theirs:.3%} of classic MC's"


@pytest.mark.parametrize("case", ["thin_and_tiny", "twisted", "mug"])
def test_block_and_point_sampling_give_the_same_mesh(case, monkeypatch):
    """The CPU samples the grid in array mode (one tree walk per block); the
    GPU path samples point by point. Both must give the same surface."""
    import importlib

    pipeline = importlib.import_module("warpblob.polygonize._pipeline")
    if case == "thin_and_tiny":
        model, h = thin_and_tiny()
    elif case == "twisted":
        arms = wb.Union(*[wb.Segment((0, 0, -1), (0.5 * np.cos(a), 0.5 * np.sin(a), 1), 0.35) for a in (0.0, 2.1, 4.2)])
        model, h = wb.Twist(arms - wb.Point((0, 0, 0), 0.5), (0, 0, 1), 1.5).translate((0.1, 0.0, 0.0)), 0.07
    else:
        model, h = wb.scenes.mug(), 0.06
    meshes = {}
    monkeypatch.setattr(pipeline, "SUBBLOCKS", "bounds")  # the same samples taken on both
    for mode in ("points", "rows"):
        monkeypatch.setattr(pipeline, "SAMPLING", mode)
        meshes[mode] = wb.polygonize(model, cellsize=h)
    a, b = meshes["points"], meshes["rows"]
    assert a.stats["grid_evaluations"] == b.stats["grid_evaluations"]
    np.testing.assert_array_equal(a.faces, b.faces)
    assert np.abs(a.vertices - b.vertices).max() < 1e-3 * h
    assert_closed_outward(b, model)


@pytest.mark.parametrize("case", ["thin_and_tiny", "tumor", "mug", "medusa"])
@pytest.mark.parametrize("sampling", ["points", "rows"])
def test_dense_and_sub_block_sampling_give_the_same_mesh(case, sampling, monkeypatch):
    """The cost model may sample every vertex of the active blocks instead of
    bounding their sub-blocks first. The crossed edges and configurations are
    the same (a stand-in lies on the proven side, like the sample it stands
    for); the roots start from other guesses where a stand-in was one of the
    four samples on an edge's line, so each vertex is the same to the root
    tolerance, on the same grid edge."""
    import importlib

    pipeline = importlib.import_module("warpblob.polygonize._pipeline")
    if case == "thin_and_tiny":
        model, h = thin_and_tiny()
    else:
        model, h = wb.scenes.ALL[case](), 0.1
    monkeypatch.setattr(pipeline, "SAMPLING", sampling)
    meshes = {}
    for path in ("bounds", "dense"):
        monkeypatch.setattr(pipeline, "SUBBLOCKS", path)
        meshes[path] = wb.polygonize(model, cellsize=h, relax=False)
    a, b = meshes["bounds"], meshes["dense"]
    assert not a.stats["dense_sampling"] and b.stats["dense_sampling"]
    assert a.stats["grid_evaluations"] < b.stats["grid_evaluations"]
    assert a.stats["interval_evaluations"] > b.stats["interval_evaluations"]
    assert (a.vertex_count, a.face_count) == (b.vertex_count, b.face_count)
    # vertex k of both meshes sits on the same grid edge, each within the tolerance of the surface
    assert np.abs(a.vertices - b.vertices).max() < 1e-2 * h
    for mesh in (a, b):
        assert_closed_outward(mesh, model)
    same = np.all(a.faces == b.faces, axis=1)
    assert same.mean() > 0.99  # only fans whose smallest-angle choice was a near tie differ


def test_the_cost_model_samples_densely_on_long_tapes_in_array_mode(monkeypatch):
    """Array mode samples a long tape densely (the sub-block bounds cost more
    than they save) and a short one after the bounds; point mode always bounds."""
    import importlib

    pipeline = importlib.import_module("warpblob.polygonize._pipeline")
    monkeypatch.setattr(pipeline, "SAMPLING", "rows")
    assert wb.polygonize(wb.scenes.towers(), cellsize=0.3).stats["dense_sampling"]
    assert not wb.polygonize(wb.scenes.tumor(), cellsize=0.2).stats["dense_sampling"]
    monkeypatch.setattr(pipeline, "SAMPLING", "points")
    assert not wb.polygonize(wb.scenes.towers(), cellsize=0.3).stats["dense_sampling"]


def test_zero_area_triangles_are_dropped_after_welding_their_coincident_corners(device):
    """An octahedron whose top vertex is split into two coincident copies, the
    gap closed by two zero-area triangles (what the grid pipeline makes where
    the surface passes through a grid vertex): dropping those triangles alone
    would open a hole; welding the copies first gives back the closed
    octahedron, without the unused copy."""
    import warp as wp

    # 0a = 0 and 0b = 6 both at the top; ring 1..4; bottom 5
    v = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1], [0, 0, 1]], np.float32)
    faces = np.array(
        [[0, 1, 2], [0, 2, 3], [6, 3, 4], [6, 4, 1], [0, 3, 6], [6, 1, 0],  # top fan, split, and the two slivers
         [5, 2, 1], [5, 3, 2], [5, 4, 3], [5, 1, 4]],
        np.int32,
    )  # fmt: skip
    split = wb.SurfaceMesh(v, faces, v, v)
    assert split.is_closed_manifold()
    arrays = [wp.array(a, dtype=wp.vec3, device=device) for a in (v, v, 0.5 * v)]
    tris = wp.array(faces, dtype=wp.vec3i, device=device)
    tris, pos, nrm, col, welded = _weld.weld(tris, *arrays, 0.1, device)
    mesh = wb.SurfaceMesh(pos.numpy(), tris.numpy().reshape(-1, 3), nrm.numpy(), col.numpy())
    assert welded == 1
    assert mesh.face_count == 8 and mesh.vertex_count == 6
    assert mesh.is_closed_manifold() and mesh.volume() > 0.0
    np.testing.assert_allclose(mesh.volume(), 4.0 / 3.0, rtol=1e-6)  # the octahedron
    np.testing.assert_array_equal(mesh.normals, mesh.vertices)  # vertex data moved with the vertices
    np.testing.assert_array_equal(mesh.colors, 0.5 * mesh.vertices)


def test_towers_at_h_004_is_closed():
    """The reference model where the surface passes exactly through grid
    vertices (coincident vertices, zero-area triangles) at h = 0.04."""
    mesh = wb.polygonize(wb.scenes.towers(), cellsize=0.04)
    assert mesh.stats["welded_vertices"] > 0, "test set-up: no coincident vertices at this cellsize"
    assert mesh.is_closed_manifold()


@pytest.mark.parametrize("name", ["towers", "head"])
def test_relaxation_improves_skinny_triangles_and_keeps_the_surface(name, device):
    """Relaxation moves the vertices of triangles under 10 degrees along the
    surface: the connectivity is unchanged, every vertex is still on the
    surface, nothing turned over, normals follow the reference gradient, and
    far fewer triangles are skinny than without it."""
    model = wb.scenes.ALL[name]()
    h = 0.14 if name == "towers" else 0.08
    plain = wb.polygonize(model, cellsize=h, relax=False, device=device)
    mesh = wb.polygonize(model, cellsize=h, device=device)
    np.testing.assert_array_equal(mesh.faces, plain.faces)
    assert_closed_outward(mesh, model)
    moved = np.linalg.norm(mesh.vertices - plain.vertices, axis=1)
    assert mesh.stats["relaxed_vertices"] == int(np.count_nonzero(moved > 0.0)) > 0
    assert moved.max() <= h  # a move goes at most half way to the neighbours' centroid, then onto the surface
    before = np.mean(plain.min_angles() < 10.0)
    after = np.mean(mesh.min_angles() < 10.0)
    assert after < 0.25 * before, f"skinny share {before:.2%} -> {after:.2%}"
    # no triangle turned over: each keeps its orientation, but for those with an edge the weld
    # could not close (shorter than the weld length: too short to give them an orientation)
    def normals(m):
        v = m.vertices.astype(np.float64)
        return np.cross(v[m.faces[:, 1]] - v[m.faces[:, 0]], v[m.faces[:, 2]] - v[m.faces[:, 0]])

    v = plain.vertices.astype(np.float64)
    f = plain.faces
    shortest = np.min([np.linalg.norm(v[f[:, k]] - v[f[:, (k + 1) % 3]], axis=1) for k in range(3)], axis=0)
    turned = np.einsum("ij,ij->i", normals(mesh), normals(plain)) <= 0.0
    assert np.all(shortest[turned] < _weld.WELD * h)
    # the moved vertices' data come from the evaluation at their new place (a sample: the reference is slow)
    check = np.random.default_rng(0).permutation(np.flatnonzero(moved > 0.0))[:300]
    f, g, colors = reference_evaluate(model, mesh.vertices[check].astype(np.float64))
    assert np.abs(f - 0.5).max() <= 1e-4 + 2e-6
    ref = -g / np.linalg.norm(g, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", ref, mesh.normals[check]).min() > 1 - 1e-4
    np.testing.assert_allclose(mesh.colors[check], colors, atol=1e-4)


def test_progress_bar_shows_the_stages_on_a_terminal(monkeypatch, capsys):
    """``progress=True`` draws a bar of the stages on stderr when it is a terminal, and
    nothing when it is not (logs, pipes)."""
    import sys

    model = wb.scenes.tumor()
    wb.polygonize(model, cellsize=0.1, progress=True)
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    mesh = wb.polygonize(model, cellsize=0.1, progress=True)
    err = capsys.readouterr().err
    assert "polygonize" in err and "7/7" in err and "relax" in err
    assert mesh.is_closed_manifold()



def _tape_reference(lm, lo, hi):
    """Leaves whose boxes meet the closed box [lo, hi] and whose ancestors' boxes all do (a walk prunes a
    subtree at the first box that misses), a warp counting as one leaf with nothing below it (the block
    walks take a warp's subtree whole): an independent count over the linearized arrays."""
    kinds = wb.tree._kinds
    visited = np.all((lm.lower <= hi) & (lm.upper >= lo), axis=1)
    warped = np.zeros(len(lm.kind), dtype=bool)  # below a warp
    for i in range(1, len(lm.kind)):  # pre-order: a parent comes before its children
        p = lm.parent[i]
        visited[i] &= visited[p]
        warped[i] = warped[p] or lm.kind[p] in kinds.WARP_KINDS
    leaf = (lm.kind < kinds.PRIMITIVE_KIND_END) | np.isin(lm.kind, kinds.WARP_KINDS)
    return int((visited & leaf & ~warped).sum())


@pytest.mark.parametrize("sampling", ["rows", "points"])
def test_stats_give_the_tape_pruned_over_each_block(sampling, monkeypatch):
    """Per active block, the primitives whose boxes (and their ancestors') meet its cube, the tape its samples
    walk, against a numpy count over the linearized boxes: counted by the array-mode walk of the samples
    (``rows``) and by the interval walk used where samples are taken point by point (``points``); a wide
    blend (grid-listed operands), a Difference (the subtracted operand's box outside the result's) and a
    warp."""
    from warpblob.polygonize import _pipeline

    monkeypatch.setattr(_pipeline, "SAMPLING", sampling)
    rng = np.random.default_rng(7)
    blobs = [wb.Point(tuple(c), 0.35) for c in rng.uniform(-1.0, 1.0, (24, 3))]
    arm = wb.Twist(wb.Segment((1.2, -0.8, -0.3), (1.2, 0.8, 0.3), 0.25), (0, 1, 0), 1.0)  # a warp: one leaf
    model = wb.Union(wb.Difference(wb.Blend(*blobs), wb.Point((0.9, 0.9, 0.9), 0.5)),
                     wb.Segment((-1.5, 0.0, 0.0), (1.5, 0.2, 0.1), 0.2), arm)  # fmt: skip
    h = 0.05
    s = wb.polygonize(model, cellsize=h, relax=False, device="cpu").stats
    lm = wb.linearize(model)
    assert s["tape_leaves"] == lm.primitive_count == 27
    blocks, leaves = s["block_tapes"]["blocks"], s["block_tapes"]["leaves"]
    assert len(blocks) == len(leaves) == s["blocks_total"] - s["blocks_rejected"] > 8
    lo, hi = lm.bounds
    origin = (lo - 0.5 * h).astype(np.float32).astype(np.float64)
    dims = np.maximum(np.ceil((hi - lo + h) / h).astype(np.int64), 1) // 8 + 1
    coords = np.stack([blocks % dims[0], (blocks // dims[0]) % dims[1], blocks // (dims[0] * dims[1])], axis=1)
    expected = []
    for c in coords:
        a, z = origin + h * 8 * c, origin + h * (8 * c + 7)
        centre, half = 0.5 * (a + z), 0.5 * float(np.max(z - a)) * 1.0001
        expected.append(_tape_reference(lm, centre - half, centre + half))
    np.testing.assert_array_equal(leaves, expected)
    assert len(np.unique(leaves)) > 3  # blocks prune differently
    assert s["block_tape_mean"] == pytest.approx(np.mean(expected))
    assert s["block_tape_max"] == max(expected) < lm.primitive_count
