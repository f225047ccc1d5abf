"""Material-selective cutting: only the chosen materials' tets are split; the others stay exactly as they were."""

import numpy as np
import pytest

import warpblob as wb
from warpblob.cut import CutError, SweepSurface, cut
from warpblob.mesh import TetStructure, box_tetmesh


def _layered(n=6):
    """The unit box in two materials: 1 above z = 0.5 (the 'bone'), 0 below."""
    m = box_tetmesh((0, 0, 0), (1, 1, 1), (n, n, n))
    z = m.nodes[m.tets].mean(axis=1)[:, 2]
    return wb.TetMesh(m.nodes, m.tets, material=(z > 0.5).astype(np.int32))


def _live(s):
    alive = np.asarray(s.cell_alive).astype(bool)
    return np.flatnonzero(alive)


@pytest.mark.parametrize("materials", [1, {1}, [1]])
def test_cut_restricted_to_a_material_leaves_the_others_bit_for_bit(materials, device):
    m = _layered()
    s = TetStructure.from_tetmesh(m)
    soft = np.flatnonzero(m.material == 0)
    soft_nodes = np.unique(m.tets[soft])
    rest0, pos0 = np.asarray(s.node_rest).copy(), np.asarray(s.node_position).copy()
    # a vertical plane through the whole box, off the lattice
    r = cut(s, SweepSurface.plane((0.513, 0.5, 0.5), (1.0, 0.3, 0.0), 4.0), materials=materials, collect=False,
            device=device)
    assert r.edges_cut > 0 and r.tets_added > 0
    live = _live(s)
    cells, mat = np.asarray(s.cell_nodes)[live], np.asarray(s.cell_material)[live]
    # the soft tets: all still alive, same ids, same nodes; their nodes unmoved
    assert np.all(np.asarray(s.cell_alive)[soft])
    assert np.array_equal(np.asarray(s.cell_nodes)[soft], m.tets[soft])
    assert np.array_equal(np.asarray(s.node_rest)[soft_nodes], rest0[soft_nodes])
    assert np.array_equal(np.asarray(s.node_position)[soft_nodes], pos0[soft_nodes])
    assert int((mat == 0).sum()) == len(soft)
    # only bone tets were replaced
    assert np.all(m.material[r.removed] == 1)
    # volume kept, nothing inverted, the structure consistent
    s.check()
    tm = s.to_tetmesh()
    assert tm.volumes().min() > 0
    assert abs(tm.volume() - 1.0) < 1e-6
    # every bone tet lies on one side of the plane (within the snapping bound), and the bone fell in two,
    # still held together through the soft layer under it
    n = np.array([1.0, 0.3, 0.0]) / np.linalg.norm([1.0, 0.3, 0.0])
    d = (tm.nodes[cells[mat == 1]].astype(np.float64) - (0.513, 0.5, 0.5)) @ n
    h = 1.0 / 6 * np.sqrt(3)
    assert np.all((d.min(axis=1) > -0.2 * h - 1e-6) | (d.max(axis=1) < 0.2 * h + 1e-6))
    bone = wb.TetMesh(tm.nodes, cells[mat == 1])
    assert len(np.unique(TetStructure.from_tetmesh(bone).components())) == 2
    assert r.components == 1


def test_unrestricted_cut_of_the_same_mesh_separates_it():
    s = TetStructure.from_tetmesh(_layered())
    assert cut(s, SweepSurface.plane((0.513, 0.5, 0.5), (1.0, 0.3, 0.0), 4.0)).components == 2


def test_a_cut_of_a_material_the_sweep_misses_changes_nothing():
    m = _layered()
    s = TetStructure.from_tetmesh(m)
    r = cut(s, SweepSurface.plane((0.5, 0.5, 0.25), (0.0, 0.0, 1.0), 4.0), materials={1}, collect=False)
    assert r.tets_removed == 0 and r.edges_cut == 0
    assert np.array_equal(s.to_tetmesh().tets, m.tets)


@pytest.mark.parametrize("bad", [{}, "skull", {1.5}, {True}, object()])
def test_bad_materials_are_refused(bad):
    m = _layered()
    s = TetStructure.from_tetmesh(m)
    with pytest.raises(CutError, match="materials"):
        cut(s, SweepSurface.plane((0.5, 0.5, 0.5), (1, 0, 0), 4.0), materials=bad)
    assert np.array_equal(s.to_tetmesh().tets, m.tets)
