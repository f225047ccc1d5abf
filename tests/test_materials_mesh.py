"""Multi-material tetrahedralization: ``tetrahedralize(model, materials=[...])``.

References are independent of the mesher: concentric point primitives have
spherical interfaces at known radii (``ISO_DISTANCE * R``), so materials,
interface distances and volumes are checked against closed forms; face
sharing is recounted here in numpy; dihedral angles come from
:meth:`TetMesh.quality` (the quality kernel, not the snapping guard).
"""

import math

import numpy as np
import pytest

import warpblob as wb
from warpblob.mesh._tetmesh import TET_FACES
from warpblob.tetrahedralize import SNAP_MIN_DIHEDRAL, tetrahedralize
from warpblob.tree import ISO_DISTANCE

RADII = (1.0, 0.72, 0.45)  # primitive radii, outermost first
NAMES = ("outer", "middle", "core")
CELL = 0.06
PAPER_MIN_DIHEDRAL = 10.7
PAPER_MAX_DIHEDRAL = 164.8
#: stated bounds (docs/tetrahedralize.md), in cell sizes: interface nodes from the true interface,
#: and centroids labelled with the material across an interface from that interface
INTERFACE_MAX = 0.45
INTERFACE_MEAN = 0.1
CENTROID_SLACK = 0.3


def _spheres():
    return {n: wb.Point((0.0, 0.0, 0.0), r) for n, r in zip(NAMES, RADII)}


@pytest.fixture(scope="module")
def nested():
    return tetrahedralize(None, cellsize=CELL, materials=_spheres())


def _faces(mesh):
    """(sorted face triples, tet of each, group starts, group sizes) of every tet face, recounted."""
    f = np.sort(mesh.tets[:, TET_FACES].reshape(-1, 3), axis=1)
    order = np.lexsort((f[:, 2], f[:, 1], f[:, 0]))
    f = f[order]
    new = np.ones(len(f), dtype=bool)
    new[1:] = (f[1:] != f[:-1]).any(axis=1)
    starts = np.flatnonzero(new)
    return f, order // 4, starts, np.diff(np.append(starts, len(f)))


def test_nested_spheres_conform_and_keep_their_quality(nested):
    mesh = nested
    assert mesh.is_conforming()
    _, _, _, sizes = _faces(mesh)
    assert sizes.max() == 2  # every face in one tet (boundary) or exactly two (interior)
    q = mesh.quality()
    assert q.inverted_count == 0 and mesh.volumes().min() > 0
    assert PAPER_MIN_DIHEDRAL <= q.dihedral_min and q.dihedral_max <= PAPER_MAX_DIHEDRAL
    s = mesh.stats
    assert s["materials"] == list(NAMES)
    for m in range(3):
        lo, hi = q.tet_dihedral_min[mesh.material == m], q.tet_dihedral_max[mesh.material == m]
        assert s["dihedral_min_per_material"][m] == pytest.approx(lo.min(), abs=1e-9)
        assert s["dihedral_max_per_material"][m] == pytest.approx(hi.max(), abs=1e-9)
        # the snapping guard keeps every tet above SNAP_MIN_DIHEDRAL (or its unsnapped minimum, >= 10.7)
        assert lo.min() >= min(SNAP_MIN_DIHEDRAL, PAPER_MIN_DIHEDRAL) - 1e-6
    assert s["interface_dihedral_min"] >= q.dihedral_min


def test_nested_spheres_interfaces_are_shared_faces_near_the_true_spheres(nested):
    mesh = nested
    f, tet, starts, sizes = _faces(mesh)
    two = starts[sizes == 2]
    a, b = mesh.material[tet[two]], mesh.material[tet[two + 1]]
    cross = a != b
    pairs = {tuple(p) for p in np.sort(np.stack([a[cross], b[cross]], axis=1), axis=1).tolist()}
    assert pairs == {(0, 1), (1, 2)}  # outer | middle and middle | core; outer never touches core
    counts = mesh.stats["interface_faces"]
    for lo_m, hi_m in pairs:
        n = int(np.count_nonzero(cross & (np.minimum(a, b) == lo_m) & (np.maximum(a, b) == hi_m)))
        assert counts[f"{lo_m}-{hi_m}"] == n
    # interface nodes against the analytic sphere of the inner material of their face
    faces = f[two[cross]]
    inner = np.maximum(a, b)[cross]
    radius = ISO_DISTANCE * np.asarray(RADII)[inner]
    r = np.linalg.norm(mesh.nodes[faces].astype(np.float64), axis=2)
    d = np.abs(r - radius[:, None]) / CELL
    assert d.max() <= INTERFACE_MAX and d.mean() <= INTERFACE_MEAN, (d.max(), d.mean())
    e = mesh.stats["interface_error"]
    assert e["max"] == pytest.approx(d.max(), abs=0.01)
    assert e["max_single"] == e["max"]  # thick layers, no interface meets the boundary: every node is single
    # snapping moved the staircase of centroid labels towards the spheres
    assert e["mean"] < 0.5 * mesh.stats["interface_error_unsnapped"]["mean"]


def test_nested_spheres_tets_lie_in_their_material(nested):
    mesh = nested
    c = mesh.nodes[mesh.tets].astype(np.float64).mean(axis=1)
    rc = np.linalg.norm(c, axis=1)
    radii = ISO_DISTANCE * np.asarray(RADII)
    true = (rc <= radii[1]).astype(int) + (rc <= radii[2]).astype(int)
    wrong = true != mesh.material
    assert np.count_nonzero(wrong) < 0.05 * mesh.tet_count
    distance = np.min(np.abs(rc[:, None] - radii[None, 1:]), axis=1)
    assert np.all(distance[wrong] <= CENTROID_SLACK * CELL)


def test_nested_spheres_volumes(nested):
    mesh = nested
    radii = ISO_DISTANCE * np.asarray(RADII)
    ball = 4.0 / 3.0 * math.pi * radii**3
    # stuffing inscribes the outer boundary: a little short of the ball, as for one sphere
    assert 0.99 * ball[0] < mesh.volume() < ball[0]
    v = mesh.volumes()
    exact = [ball[0] - ball[1], ball[1] - ball[2], ball[2]]
    for m in range(3):
        assert v[mesh.material == m].sum() == pytest.approx(exact[m], rel=0.04)


def test_one_material_is_the_single_model_mesh(device):
    model = wb.scenes.peanut()
    plain = tetrahedralize(model, cellsize=0.12, device=device)
    one = tetrahedralize(model, cellsize=0.12, device=device, materials=[model])
    assert np.array_equal(plain.tets, one.tets) and np.array_equal(plain.nodes, one.nodes)
    assert np.all(one.material == 0) and one.stats["materials"] == ["material0"]
    assert one.stats["interface_faces"] == {} and set(one.stats["interface_error"].values()) == {0.0}


def test_innermost_listed_solid_wins_and_the_domain_is_the_union():
    a = wb.Point((-0.25, 0.0, 0.0), 1.0)
    b = wb.Point((0.25, 0.0, 0.0), 1.0)  # overlaps a: not nested
    mesh = tetrahedralize(None, cellsize=0.06, materials=[a, b])
    union = tetrahedralize(wb.Union(a, b), cellsize=0.06)
    assert mesh.tet_count == union.tet_count and mesh.volume() == pytest.approx(union.volume(), rel=1e-6)
    c = mesh.nodes[mesh.tets].astype(np.float64).mean(axis=1)
    r = ISO_DISTANCE
    in_b = np.linalg.norm(c - [0.25, 0.0, 0.0], axis=1) <= r
    far = np.abs(np.linalg.norm(c - [0.25, 0.0, 0.0], axis=1) - r) > CENTROID_SLACK * 0.06
    assert np.array_equal(mesh.material[far], in_b[far].astype(np.int32))  # b wins wherever it holds
    assert mesh.is_conforming() and mesh.quality().inverted_count == 0


def test_contiguous_head_layers_share_faces():
    layers = wb.scenes.head_materials()
    mesh = tetrahedralize(layers["skull"], cellsize=0.4, materials=layers)
    s = mesh.stats
    assert s["materials"] == list(wb.scenes.HEAD_MATERIALS)
    assert mesh.is_conforming() and mesh.quality().inverted_count == 0
    assert min(s["tets_per_material"][:4]) > 0
    _, tet, starts, sizes = _faces(mesh)
    two = starts[sizes == 2]
    a, b = mesh.material[tet[two]], mesh.material[tet[two + 1]]
    pairs = set(map(tuple, np.sort(np.stack([a, b], axis=1)[a != b], axis=1).tolist()))
    assert {(0, 1), (1, 2), (2, 3)} <= pairs  # skull | CSF, CSF | grey, grey | white
    assert s["interface_error"]["max"] < 1.0
    # nodes on one interface and off the outer boundary reach it within half a cell
    assert s["interface_error"]["max_single"] <= 0.5
    # the domain is the whole head: the skull solid's volume, as meshed alone
    alone = tetrahedralize(layers["skull"], cellsize=0.4)
    assert mesh.volume() == pytest.approx(alone.volume(), rel=1e-6)


def test_bad_materials():
    p = wb.Point((0.0, 0.0, 0.0), 1.0)
    with pytest.raises(wb.WarpblobError, match="at least one"):
        tetrahedralize(p, cellsize=0.1, materials=[])
    with pytest.raises(wb.WarpblobError, match=r"materials\[1\]"):
        tetrahedralize(p, cellsize=0.1, materials=[p, 3])
    with pytest.raises(wb.WarpblobError, match="sequence or mapping"):
        tetrahedralize(p, cellsize=0.1, materials=p)
    with pytest.raises(wb.WarpblobError, match="sequence or mapping"):
        tetrahedralize(p, cellsize=0.1, materials=5)


def test_inputs_are_not_modified():
    solids = _spheres()
    listed = list(solids.items())
    tetrahedralize(None, cellsize=0.15, materials=solids)
    assert list(solids.items()) == listed


def test_graded_interior_keeps_coarse_cubes_off_the_interfaces():
    solids = [wb.Point((0.0, 0.0, 0.0), 1.0), wb.Point((0.0, 0.0, 0.0), 0.8)]
    uniform = tetrahedralize(None, cellsize=0.05, materials=solids)
    graded = tetrahedralize(None, cellsize=0.05, interior_cellsize=0.2, materials=solids)
    assert graded.stats["coarse_tets"] > 0 and graded.tet_count < uniform.tet_count
    assert graded.is_conforming() and graded.quality().inverted_count == 0
    assert graded.volume() == pytest.approx(uniform.volume(), rel=1e-9)
    # coarse cubes never reach an interface: the same interface faces (the snapping visits the
    # nodes in an order of their ids, which differ, so the snapped positions may differ a little)
    s, u = graded.stats, uniform.stats
    assert s["interface_faces"] == u["interface_faces"]
    assert s["interface_error"]["max"] <= INTERFACE_MAX and s["interface_error"]["mean"] <= INTERFACE_MEAN
    for m in range(2):
        assert graded.volumes()[graded.material == m].sum() == pytest.approx(
            uniform.volumes()[uniform.material == m].sum(), rel=0.01
        )
    # and every coarse tet (the last ones) lies inside the core, away from its sphere
    coarse = graded.tets[graded.tet_count - s["coarse_tets"] :]
    r = np.linalg.norm(graded.nodes[coarse].astype(np.float64), axis=2)
    assert r.max() < ISO_DISTANCE * 0.8
