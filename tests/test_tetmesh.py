"""TetMesh: validation, volumes, surface faces, conformity, PyVista and USD (UsdGeom.TetMesh) output.

The meshes are made here: a unit cube split into five tets and a structured
grid of cubes split into six tets each (Kuhn's split along the diagonal).
Other test modules import :func:`cube_mesh` and :func:`grid_mesh` from here.
"""

import itertools
import os

import numpy as np
import pytest
from pxr import Usd, UsdGeom, Vt

import warpblob as wb
import warpblob.usd
from warpblob.mesh import SurfaceMesh
from warpblob.mesh._tetmesh import TET_EDGES, TET_FACES, TetMesh


def positive(nodes, tets):
    """``tets`` with the negatively oriented ones reordered (two nodes swapped)."""
    tets = np.array(tets, dtype=np.int32)
    p = np.asarray(nodes, dtype=np.float64)[tets]
    det = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets[det < 0] = tets[det < 0][:, [0, 2, 1, 3]]
    return tets


def cube_mesh():
    """The unit cube as five tets: the corners 0, 3, 5, 6 cut off a central regular tet."""
    nodes = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=np.float32)
    tets = [[0, 1, 2, 4], [3, 1, 2, 7], [5, 1, 4, 7], [6, 2, 4, 7], [1, 2, 4, 7]]
    return TetMesh(nodes, positive(nodes, tets), np.array([0, 0, 0, 0, 1]))


def grid_mesh(n, size=(1.0, 1.0, 1.0), origin=(0.0, 0.0, 0.0)):
    """A box of ``n^3`` cubes, each split into six tets around its diagonal (6 n^3 tets)."""
    axes = [np.linspace(o, o + s, n + 1) for o, s in zip(origin, size)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.float32)
    ids = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    i, j, k = (a.ravel() for a in np.meshgrid(*[np.arange(n)] * 3, indexing="ij"))
    corner = np.stack([ids[i + (b & 1), j + (b >> 1 & 1), k + (b >> 2 & 1)] for b in range(8)], axis=-1)
    tets = []
    for perm in itertools.permutations((1, 2, 4)):
        path = np.cumsum((0, *perm))  # a monotone path from corner 0 to corner 7
        tets.append(corner[:, path])
    return TetMesh(nodes, positive(nodes, np.concatenate(tets)))


def regular_tet(edge=1.0):
    """A regular tet of edge length ``edge``, positively oriented."""
    s = edge / np.sqrt(8.0)
    nodes = s * np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], dtype=np.float64)
    return TetMesh(nodes, positive(nodes, [[0, 1, 2, 3]]))


def canonical(faces):
    """Faces as a set of node triples rotated to start at their smallest node (orientation kept)."""
    faces = np.asarray(faces)
    r = np.argmin(faces, axis=1)
    rolled = np.stack([faces[np.arange(len(faces)), (r + s) % 3] for s in range(3)], axis=1)
    return {tuple(f) for f in rolled.tolist()}


# ---------------------------------------------------------------------------
# construction and validation
# ---------------------------------------------------------------------------


def test_tables_are_consistent():
    # face k is opposite node k; the edges of face k are the edges without node k
    for k, face in enumerate(TET_FACES):
        assert k not in face
    assert {tuple(sorted(e)) for e in TET_EDGES} == set(itertools.combinations(range(4), 2))
    for j in range(6):
        assert set(TET_EDGES[j]) | set(TET_EDGES[5 - j]) == {0, 1, 2, 3}


def test_arrays_are_coerced_and_read_only():
    nodes = np.eye(4, 3, k=-1)
    tets = np.array([[0, 1, 2, 3]], dtype=np.int64)
    mesh = TetMesh(nodes, tets)
    assert mesh.nodes.dtype == np.float32 and mesh.tets.dtype == np.int32 and mesh.material is None
    assert (mesh.node_count, mesh.tet_count) == (4, 1)
    with pytest.raises(ValueError):
        mesh.nodes[0, 0] = 5.0
    with pytest.raises(AttributeError):
        mesh.tets = tets
    tets[0, 0] = 0  # the caller's array is not frozen
    assert mesh.surface_faces() is mesh.surface_faces()  # cached


@pytest.mark.parametrize(
    "nodes, tets, material, message",
    [
        (np.zeros((4, 2)), [[0, 1, 2, 3]], None, "nodes must have shape (N, 3), got shape (4, 2)"),
        (np.eye(4, 3), [[0, 1, 2]], None, "tets must have shape (T, 4), got shape (1, 3)"),
        (np.eye(4, 3), [[0.0, 1.0, 2.0, 3.0]], None, "tets must hold integers, got dtype float64"),
        (np.eye(4, 3), [[0, 1, 2, 4]], None, "tets[0] = [0, 1, 2, 4] names a node outside [0, 4)"),
        (np.eye(4, 3), [[0, 1, 2, 3], [0, 1, 1, 3]], None, "tets[1] = [0, 1, 1, 3] repeats a node"),
        ([[0, 0, 0], [1, 0, np.nan], [0, 1, 0], [0, 0, 1]], [[0, 1, 2, 3]], None, "nodes[1] = [1.0, 0.0, nan]"),
        (np.eye(4, 3), [[0, 1, 2, 3]], [1, 2], "material must have shape (1,), got shape (2,)"),
    ],
)
def test_validation_names_the_value(nodes, tets, material, message):
    with pytest.raises(wb.WarpblobError) as info:
        TetMesh(nodes, tets, material)
    assert message in str(info.value)


def test_empty_mesh():
    mesh = TetMesh(np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int32))
    assert mesh.volume() == 0.0 and mesh.surface_faces().shape == (0, 3) and mesh.is_conforming()


# ---------------------------------------------------------------------------
# geometry and topology
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("mesh, box", [(cube_mesh(), 1.0), (grid_mesh(10, (2.0, 1.0, 0.5), (-1, 3, 2)), 1.0)])
def test_volumes_positive_and_sum_to_the_box(mesh, box):
    v = mesh.volumes()
    assert v.shape == (mesh.tet_count,) and np.all(v > 0)
    assert mesh.volume() == pytest.approx(box, rel=1e-6)


def test_cube_mesh_volumes():
    v = cube_mesh().volumes()
    np.testing.assert_allclose(v, [1 / 6] * 4 + [1 / 3], rtol=1e-12)


@pytest.mark.parametrize("n", [1, 4])
def test_surface_faces_closed_and_outward(n):
    mesh = grid_mesh(n, (1.0, 2.0, 3.0))
    faces = mesh.surface_faces()
    assert faces.dtype == np.int32 and faces.shape == (12 * n * n, 3)  # two triangles per square
    surface = SurfaceMesh(mesh.nodes, faces, np.zeros_like(mesh.nodes), np.zeros_like(mesh.nodes))
    assert surface.is_closed_manifold()
    # divergence theorem: outward faces enclose the tets' volume (inward ones would give its negative)
    assert surface.volume() == pytest.approx(mesh.volume(), rel=1e-6)
    assert surface.area() == pytest.approx(2 * (1 * 2 + 2 * 3 + 1 * 3), rel=1e-6)
    # every boundary node lies on the box
    on_box = np.isclose(mesh.nodes, 0).any(axis=1) | np.isclose(mesh.nodes, [1, 2, 3]).any(axis=1)
    assert np.all(on_box[np.unique(faces)])


def test_surface_faces_of_one_tet_are_its_outward_faces():
    mesh = regular_tet()
    assert canonical(mesh.surface_faces()) == canonical(mesh.tets[0][TET_FACES])
    p = mesh.nodes.astype(np.float64)
    centre = p.mean(axis=0)
    for f in mesh.surface_faces():
        normal = np.cross(p[f[1]] - p[f[0]], p[f[2]] - p[f[0]])
        assert np.dot(normal, p[f[0]] - centre) > 0


def test_conformity():
    assert cube_mesh().is_conforming()
    assert grid_mesh(3).is_conforming()
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [0.2, 0.2, 0.5]], dtype=np.float32)
    # two tets on opposite sides of face (0, 1, 2): conforming
    assert TetMesh(nodes, positive(nodes, [[0, 1, 2, 3], [0, 1, 2, 4]])).is_conforming()
    # two tets on the same side of it: they overlap
    assert not TetMesh(nodes, positive(nodes, [[0, 1, 2, 3], [0, 1, 2, 5]])).is_conforming()
    # three tets on one face
    assert not TetMesh(nodes, positive(nodes, [[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 2, 5]])).is_conforming()


# ---------------------------------------------------------------------------
# PyVista
# ---------------------------------------------------------------------------


def test_to_pyvista_cells_and_quality():
    import pyvista as pv

    mesh = cube_mesh()
    grid = mesh.to_pyvista()
    assert grid.n_cells == mesh.tet_count and grid.n_points == mesh.node_count
    assert np.all(grid.celltypes == pv.CellType.TETRA)
    q = mesh.quality()
    np.testing.assert_allclose(grid.cell_data["volume"], mesh.volumes(), rtol=1e-12)
    np.testing.assert_allclose(grid.cell_data["min_dihedral"], q.tet_dihedral_min)
    np.testing.assert_allclose(grid.cell_data["aspect_ratio"], q.tet_aspect_ratio)
    np.testing.assert_array_equal(grid.cell_data["material"], [0, 0, 0, 0, 1])
    for name in ("max_dihedral", "edge_ratio"):
        assert grid.cell_data[name].shape == (mesh.tet_count,)
    # VTK measures the same (positive) volumes
    np.testing.assert_allclose(grid.compute_cell_sizes()["Volume"], mesh.volumes(), rtol=1e-6)
    assert grid.cell_data["aspect_ratio"][4] == pytest.approx(1.0)  # the central tet is regular


# ---------------------------------------------------------------------------
# USD
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_usd_round_trip(tmp_path, suffix):
    mesh = grid_mesh(3, (1.0, 0.5, 2.0), (0.0, -1.0, 4.0))
    mesh = TetMesh(mesh.nodes, mesh.tets, np.arange(mesh.tet_count) % 3)
    path = wb.usd.save_tetmesh(mesh, tmp_path / f"grid{suffix}", prim_path="/World/Tissue")
    assert path == tmp_path / f"grid{suffix}" and sorted(os.listdir(tmp_path)) == [f"grid{suffix}"]

    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert stage.GetDefaultPrim().GetPath() == "/World"
    prim = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Tissue"))
    assert prim and prim.GetPrim().IsA(UsdGeom.TetMesh)
    assert len(UsdGeom.TetMesh.FindInvertedElements(prim, Usd.TimeCode.Default())) == 0
    np.testing.assert_array_equal(np.array(prim.GetPointsAttr().Get()), mesh.nodes)
    np.testing.assert_array_equal(np.array(prim.GetTetVertexIndicesAttr().Get()), mesh.tets)
    surface = np.array(prim.GetSurfaceFaceVertexIndicesAttr().Get())
    usd_surface = np.array(UsdGeom.TetMesh.ComputeSurfaceFaces(prim, Usd.TimeCode.Default()))
    assert canonical(surface) == canonical(usd_surface) == canonical(mesh.surface_faces())
    extent = np.array(prim.GetExtentAttr().Get())
    np.testing.assert_allclose(extent, [mesh.nodes.min(axis=0), mesh.nodes.max(axis=0)])

    back = wb.usd.load_tetmesh(path)
    np.testing.assert_array_equal(back.nodes, mesh.nodes)
    np.testing.assert_array_equal(back.tets, mesh.tets)
    np.testing.assert_array_equal(back.material, mesh.material)
    assert back.stats["prim"] == "/World/Tissue"
    assert wb.usd.load_tetmesh(path, "/World/Tissue").tet_count == mesh.tet_count


def test_usd_overwrite_and_no_material(tmp_path):
    path = tmp_path / "cube.usda"
    wb.usd.save_tetmesh(grid_mesh(2), path)
    wb.usd.save_tetmesh(TetMesh(cube_mesh().nodes, cube_mesh().tets), path, meters_per_unit=1.0)
    back = wb.usd.load_tetmesh(path)
    assert back.tet_count == 5 and back.material is None
    assert UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(str(path))) == 1.0
    assert os.listdir(tmp_path) == ["cube.usda"]


def test_usd_finds_inverted_tets_and_reads_left_handed(tmp_path):
    mesh = cube_mesh()
    flipped = mesh.tets[:, [0, 2, 1, 3]]
    stage = Usd.Stage.CreateNew(str(tmp_path / "left.usda"))
    prim = UsdGeom.TetMesh.Define(stage, "/Left")
    prim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.nodes)))
    prim.CreateTetVertexIndicesAttr(Vt.Vec4iArray.FromNumpy(np.ascontiguousarray(flipped)))
    # right-handed, these tets are all inverted; USD's own check agrees
    assert len(UsdGeom.TetMesh.FindInvertedElements(prim, Usd.TimeCode.Default())) == mesh.tet_count
    prim.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    assert len(UsdGeom.TetMesh.FindInvertedElements(prim, Usd.TimeCode.Default())) == 0
    stage.Save()
    back = wb.usd.load_tetmesh(tmp_path / "left.usda")  # no default prim: the first TetMesh
    assert np.all(back.volumes() > 0)
    assert back.volume() == pytest.approx(1.0)


def test_usd_errors(tmp_path):
    mesh = cube_mesh()
    with pytest.raises(wb.WarpblobError, match="must end in one of"):
        wb.usd.save_tetmesh(mesh, tmp_path / "mesh.obj")
    with pytest.raises(wb.WarpblobError, match="prim_path"):
        wb.usd.save_tetmesh(mesh, tmp_path / "mesh.usda", prim_path="relative")
    with pytest.raises(wb.SceneError, match="does not exist"):
        wb.usd.save_tetmesh(mesh, tmp_path / "missing" / "mesh.usda")
    with pytest.raises(wb.SceneError, match="no such file"):
        wb.usd.load_tetmesh(tmp_path / "nothing.usda")
    stage = Usd.Stage.CreateNew(str(tmp_path / "xform.usda"))
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/Root").GetPrim())
    stage.Save()
    with pytest.raises(wb.SceneError, match="no TetMesh prim under </Root>"):
        wb.usd.load_tetmesh(tmp_path / "xform.usda")
    with pytest.raises(wb.SceneError, match="not a TetMesh"):
        wb.usd.load_tetmesh(tmp_path / "xform.usda", "/Root")
    with pytest.raises(wb.SceneError, match="no prim"):
        wb.usd.load_tetmesh(tmp_path / "xform.usda", "/Other")
    bad = Usd.Stage.CreateNew(str(tmp_path / "bad.usda"))
    prim = UsdGeom.TetMesh.Define(bad, "/Bad")
    prim.CreatePointsAttr(Vt.Vec3fArray([(0, 0, 0), (1, 0, 0), (0, 1, 0)]))
    prim.CreateTetVertexIndicesAttr(Vt.Vec4iArray([(0, 1, 2, 7)]))
    bad.Save()
    with pytest.raises(wb.SceneError, match="names a node outside"):
        wb.usd.load_tetmesh(tmp_path / "bad.usda")


def test_repr_is_a_short_summary():
    mesh = grid_mesh(6)
    text = repr(mesh)
    assert len(text) < 400 and len(text.splitlines()) <= 5
    assert f"{mesh.node_count:,} nodes" in text and f"{mesh.tet_count:,} tets" in text
    assert "x [0, 1]" in text and "inverted tets 0" in text
    assert f"volume {mesh.volume():.6g}" in text
    # many materials: a few counts, then how many ids
    many = TetMesh(mesh.nodes, mesh.tets, np.arange(mesh.tet_count) % 9)
    assert len(repr(many)) < 400 and "(9 ids)" in repr(many)
    inverted = TetMesh(mesh.nodes, mesh.tets[:, [0, 2, 1, 3]])
    assert f"inverted tets {mesh.tet_count:,}" in repr(inverted)
    assert "0 nodes, 0 tets" in repr(TetMesh(np.zeros((0, 3)), np.zeros((0, 4), dtype=int)))
