"""Rigid materials in the simulator: anchored pieces stay put bit for bit, a free rigid block falls (and spins) on
the backward-Euler trajectory computed here in closed form and stays rigid, a rigid block on a soft one sags less
than an all-soft one and its reactions balance its weight, a rebuild or a cut that separates a rigid piece from the
anchored one frees it, ground contact holds a resting block, and bad input is refused.

References are independent of the code: ``z_n = z_0 + v_0 n h + g h^2 n (n + 1) / 2`` (backward Euler under
gravity), rotations by Rodrigues' formula, the total weight ``sum m g``, pairwise node distances.
"""

import numpy as np
import pytest

import warpblob as wb
from warpblob import SimulationError
from warpblob.mesh import TetMesh, TetStructure, box_tetmesh

H = 1.0 / 60.0
G = 9.81


def layered(shape=(2, 2, 6), size=(0.1, 0.1, 0.3), rigid_below=0.1, rigid_above=0.2) -> TetMesh:
    """A column whose tets below ``rigid_below`` and above ``rigid_above`` (by centroid z) are material 1, the
    rest material 0."""
    m = box_tetmesh((0, 0, 0), size, shape)
    cz = m.nodes[m.tets].mean(axis=1)[:, 2]
    return TetMesh(m.nodes, m.tets, material=np.where((cz < rigid_below) | (cz > rigid_above), 1, 0))


def distances(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return np.linalg.norm(x[:, None] - x[None], axis=2)


def rodrigues(w: np.ndarray, t: float) -> np.ndarray:
    angle = float(np.linalg.norm(w)) * t
    a = np.asarray(w, dtype=np.float64) / np.linalg.norm(w)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_anchored_rigid_nodes_stay_bit_identical_while_the_soft_part_moves(device):
    # a bar whose first cell is rigid and anchored at one node: the soft rest hangs from it as a cantilever
    m = box_tetmesh((0, 0, 0), (0.4, 0.1, 0.1), (4, 1, 1))
    cx = m.nodes[m.tets].mean(axis=1)[:, 0]
    mesh = TetMesh(m.nodes, m.tets, material=np.where(cx < 0.1, 7, 0))
    sim = wb.Simulation(mesh, young=2e5, poisson=0.3, density=1000.0, rigid={7}, anchors=[0], device=device)
    assert sim.stats["rigid"] == {"pieces": 1, "anchored": 1, "free": 0, "tets": 6, "nodes": 8, "free_nodes": 0}
    x0 = sim.positions
    sim.step(8)
    x = sim.positions
    rigid = m.nodes[:, 0] <= 0.1 + 1e-6  # the rigid cell's nodes, the ones it shares with soft tets included
    np.testing.assert_array_equal(x[rigid], x0[rigid])
    assert (x0 - x)[~rigid, 2].max() > 1e-3  # the soft part sags
    assert sim.fixed.size == 0  # anchoring fixes nothing the user did not
    np.testing.assert_array_equal(sim.anchors, [0])


def test_a_free_rigid_block_falls_and_spins_on_the_backward_euler_trajectory(device):
    m = box_tetmesh((0, 0, 0), (0.1, 0.1, 0.1), (2, 2, 2))
    mesh = TetMesh(m.nodes, m.tets, material=np.ones(m.tet_count, dtype=np.int32))
    sim = wb.Simulation(mesh, young=1e5, poisson=0.3, density=1000.0, rigid={1}, device=device)
    assert sim.stats["rigid"]["free"] == 1 and sim.stats["rigid"]["free_nodes"] == m.node_count
    x0 = m.nodes.astype(np.float64)
    c0 = x0.mean(axis=0)  # a uniform box: the lumped masses are symmetric, the centre of mass is the centroid
    v0 = np.array([0.3, -0.2, 0.5])
    w = np.array([0.0, 0.0, 2.0])  # about a principal axis of the cube: no gyroscopic torque
    sim.velocities = v0 + np.cross(w, x0 - c0)
    n = 12
    sim.step(n)
    t = n * H
    centre = c0 + v0 * t + np.array([0.0, 0.0, -G]) * H * H * n * (n + 1) / 2
    expected = centre + (x0 - c0) @ rodrigues(w, t).T
    np.testing.assert_allclose(sim.positions, expected, atol=2e-6)
    np.testing.assert_allclose(distances(sim.positions), distances(x0), atol=1e-6)
    body = sim.rigid_bodies
    np.testing.assert_allclose(body["centre"][0], centre, atol=2e-6)
    np.testing.assert_allclose(body["velocity"][0], v0 + [0.0, 0.0, -G * t], atol=1e-5)
    np.testing.assert_allclose(body["angular_velocity"][0], w, atol=1e-5)


def test_a_rigid_block_on_a_soft_one_sags_less_and_its_weight_is_balanced():
    # soft below (material 0), rigid above (material 1), fixed at the bottom; static equilibrium under gravity
    mesh = layered(shape=(2, 2, 4), size=(0.1, 0.1, 0.2), rigid_below=-1.0, rigid_above=0.1)
    bottom = mesh.nodes[:, 2] == 0.0
    top = mesh.nodes[:, 2] >= 0.2 - 1e-6
    options = dict(young=2e4, poisson=0.3, density=1000.0, fixed=bottom)
    rigid = wb.Simulation(mesh, rigid={1}, **options)
    soft = wb.Simulation(mesh, **options)
    for sim in (rigid, soft):
        sim.solve_static(max_iterations=60)
    sag = {name: float((mesh.nodes[top, 2] - sim.positions[top, 2]).mean()) for name, sim in
           (("rigid", rigid), ("soft", soft))}  # fmt: skip
    assert 0.0 < sag["rigid"] < 0.9 * sag["soft"]
    upper = mesh.nodes[:, 2] >= 0.1 - 1e-6
    np.testing.assert_allclose(distances(rigid.positions[upper]), distances(mesh.nodes[upper]), atol=1e-6)
    # the supports carry the weight of everything they hold up: the body presses on the fixed nodes with the
    # elastic force sum m g over the other nodes (the rigid block's included, through the soft block)
    reaction = rigid.elastic_forces()[bottom].astype(np.float64).sum(axis=0)
    weight = rigid.masses[~bottom].sum() * G
    assert -reaction[2] == pytest.approx(weight, rel=2e-3)
    assert np.abs(reaction[:2]).max() < 2e-3 * weight


def test_both_preconditioners_and_warps_cg_give_the_same_coupled_step():
    # a rigid block hanging from a soft layer below an anchored rigid top: the coupled solve, three ways
    mesh = layered()
    top = mesh.nodes[:, 2] >= 0.3 - 1e-6
    runs = []
    for options in ({}, {"preconditioner": "block_jacobi"}, {"linear_solver": "warp"}):
        sim = wb.Simulation(mesh, young=2e4, poisson=0.3, density=1000.0, rigid={1}, fixed=top,
                            tolerance=1e-6, **options)  # fmt: skip
        assert sim.stats["rigid"]["free"] == 1 and sim.stats["rigid"]["anchored"] == 1
        sim.step(5)
        runs.append(sim.positions.astype(np.float64) - mesh.nodes)
    scale = np.abs(runs[0]).max()
    assert scale > 1e-3
    for other in runs[1:]:
        np.testing.assert_allclose(other, runs[0], atol=1e-4 * scale)


def test_a_rebuild_that_splits_off_a_rigid_piece_frees_it(device):
    # two rigid cubes (z in [0, 0.1] and [0.1, 0.3]) joined through the nodes at z = 0.1, the top one fixed at
    # the top; duplicating the joining nodes for the lower cube's tets separates it: it falls, the top stays
    m = box_tetmesh((0, 0, 0), (0.1, 0.1, 0.3), (1, 1, 3))
    mesh = TetMesh(m.nodes, m.tets, material=np.full(m.tet_count, 4, dtype=np.int32))
    top = m.nodes[:, 2] >= 0.3 - 1e-6
    sim = wb.Simulation(mesh, young=1e5, poisson=0.3, density=1000.0, rigid={4}, fixed=top, device=device)
    assert sim.stats["rigid"] == {"pieces": 1, "anchored": 1, "free": 0, "tets": 18, "nodes": 16, "free_nodes": 0}
    sim.step(3)
    x0 = sim.positions
    np.testing.assert_array_equal(x0, m.nodes)
    joint = np.flatnonzero(np.isclose(m.nodes[:, 2], 0.1))
    copies = np.arange(m.node_count, m.node_count + len(joint))
    lower = np.flatnonzero(m.nodes[m.tets].mean(axis=1)[:, 2] < 0.1)
    tets = m.tets[lower].copy()
    remap = np.arange(m.node_count)
    remap[joint] = copies
    tets = remap[tets]
    rest = np.vstack([m.nodes, m.nodes[joint]])
    sim.rebuild(lower, tets=tets, rest=rest)
    assert sim.stats["rigid"] == {"pieces": 2, "anchored": 1, "free": 1, "tets": 18, "nodes": 20, "free_nodes": 8}
    n = 10
    sim.step(n)
    x = sim.positions
    falling = np.unique(tets)
    staying = np.setdiff1d(np.arange(m.node_count), falling)
    np.testing.assert_array_equal(x[staying], rest[staying])
    drop = -G * H * H * n * (n + 1) / 2
    np.testing.assert_allclose(x[falling] - rest[falling], np.tile([0.0, 0.0, drop], (len(falling), 1)), atol=2e-6)


def test_a_cut_through_the_soft_layer_frees_the_rigid_piece_below():
    # a rigid block hangs from a soft layer under an anchored rigid top; a planar cut through the soft layer
    # (the cutting code rebuilds the simulation) leaves the block with the soft tissue below the cut: that piece
    # has no support, so its momentum grows by h M g per step exactly (internal forces cancel)
    mesh = layered()
    structure = TetStructure.from_tetmesh(mesh)
    top = mesh.nodes[:, 2] >= 0.3 - 1e-6
    sim = wb.Simulation(structure, young=2e4, poisson=0.3, density=1000.0, rigid={1}, fixed=top,
                        damping=(2.0, 0.0), tolerance=1e-6)  # fmt: skip
    sim.step(10)
    assert sim.stats["rigid"]["free"] == 1
    structure.set_positions(sim.positions)
    result = wb.cut.cut(structure, wb.cut.SweepSurface.plane((0.05, 0.05, 0.15), (0, 0, 1), 1.0), collect=False)
    sim.apply_cut(result)
    assert result.components == 2
    assert sim.stats["rigid"] == {**sim.stats["rigid"], "pieces": 2, "anchored": 1, "free": 1}
    x = sim.positions
    upper = x[:, 2] > 0.15 + 0.02
    held = (mesh.nodes[:, 2] >= 0.2 - 1e-6)
    before = x[: mesh.node_count][held]
    live = sim.elements.tets_host[sim.elements.alive_host]
    below = np.zeros(sim.node_count, dtype=bool)
    below[live[(x[live][:, :, 2].mean(axis=1) < 0.15)].ravel()] = True
    assert not (below & upper).any()
    mass = sim.masses[below]
    momentum = [(mass[:, None] * sim.velocities[below]).sum(axis=0)]
    for _ in range(4):
        sim.step()
        momentum.append((mass[:, None] * sim.velocities[below]).sum(axis=0))
    # with Rayleigh mass damping alpha, backward Euler gives p' (1 + h alpha) = p + h M g
    p = np.array(momentum)
    np.testing.assert_allclose(p[1:, 2] * (1 + 2.0 * H) - p[:-1, 2], -H * mass.sum() * G, rtol=2e-4)
    np.testing.assert_array_equal(sim.positions[: mesh.node_count][held], before)


def test_ground_contact_holds_a_resting_rigid_block(device):
    m = box_tetmesh((0, 0, 0.05), (0.1, 0.1, 0.15), (2, 2, 2))
    mesh = TetMesh(m.nodes, m.tets, material=np.ones(m.tet_count, dtype=np.int32))
    sim = wb.Simulation(mesh, young=1e5, poisson=0.3, density=1000.0, rigid={1}, ground=(0.0, 0.5), device=device)
    sim.velocities = np.tile([0.2, 0.0, 0.0], (m.node_count, 1))
    sim.step(60)
    x = sim.positions
    assert x[:, 2].min() == pytest.approx(0.0, abs=1e-5)
    np.testing.assert_allclose(distances(x), distances(m.nodes), atol=2e-6)
    v = sim.velocities
    assert np.abs(v).max() < 1e-3  # landed, and friction stopped the slide
    assert 0.0 < x[:, 0].mean() - m.nodes[:, 0].mean() < 0.2 * 1.0  # it slid a little before it stopped


def test_rigid_is_settable_and_bad_values_are_refused():
    mesh = layered()
    sim = wb.Simulation(mesh, young=2e4, poisson=0.3, density=1000.0)
    assert sim.rigid == frozenset() and sim.stats["rigid"]["pieces"] == 0
    sim.rigid = {1}
    assert sim.rigid == {1} and sim.stats["rigid"]["free"] == 2
    assert sim.elements.rigid_host.sum() == (mesh.material == 1).sum()
    sim.rigid = None
    assert sim.stats["rigid"]["pieces"] == 0 and not sim.elements.rigid_host.any()
    for bad, match in (("1", "'1'"), (1, "got 1"), ({1.5}, "1.5"), ({True}, "True"), ({9}, "material 9"),
                       ({1: 2}, "1: 2")):  # fmt: skip
        with pytest.raises(SimulationError, match=match):
            sim.rigid = bad
        with pytest.raises(SimulationError, match=match):
            wb.Simulation(mesh, young=2e4, poisson=0.3, density=1000.0, rigid=bad)
    with pytest.raises(SimulationError, match="anchors: node index 999"):
        sim.anchors = [999]
    assert sim.rigid == frozenset()


def test_a_cut_through_the_rigid_material_frees_the_far_piece():
    # a rigid bar anchored at its x = 0 end, cut across at x = 0.25: the split tets keep their (rigid) material,
    # the far piece is a new free body that falls from rest on the closed form, the anchored piece stays put
    m = box_tetmesh((0, 0, 0), (0.4, 0.1, 0.1), (4, 1, 1))
    mesh = TetMesh(m.nodes, m.tets, material=np.full(m.tet_count, 2, dtype=np.int32))
    structure = TetStructure.from_tetmesh(mesh)
    sim = wb.Simulation(structure, young=1e5, poisson=0.3, density=1000.0, rigid={2},
                        anchors=np.flatnonzero(m.nodes[:, 0] == 0.0))  # fmt: skip
    sim.step(2)
    assert sim.stats["rigid"]["anchored"] == 1 and sim.stats["rigid"]["free"] == 0
    result = wb.cut.cut(structure, wb.cut.SweepSurface.plane((0.25, 0.05, 0.05), (1, 0, 0), 1.0), collect=False)
    sim.apply_cut(result)
    assert result.components == 2
    assert sim.stats["rigid"]["pieces"] == 2 and sim.stats["rigid"]["free"] == 1
    far = sim.rigid_bodies["nodes"][0]
    x0 = sim.positions
    assert (x0[far, 0] >= 0.25 - 1e-6).all()
    n = 6
    sim.step(n)
    x = sim.positions
    near = np.setdiff1d(np.arange(sim.node_count), far)
    np.testing.assert_array_equal(x[near], x0[near])
    drop = -G * H * H * n * (n + 1) / 2
    np.testing.assert_allclose(x[far] - x0[far], np.tile([0.0, 0.0, drop], (len(far), 1)), atol=2e-6)
    np.testing.assert_allclose(distances(x[far]), distances(x0[far]), atol=1e-6)


def test_rigid_bodies_give_the_same_bits_for_one_and_two_threads():
    mesh = layered()
    top = mesh.nodes[:, 2] >= 0.3 - 1e-6
    runs = []
    for threads in (1, 2):
        sim = wb.Simulation(mesh, young=2e4, poisson=0.3, density=1000.0, rigid={1}, fixed=top, ground=(-0.01, 0.5),
                            threads=threads)  # fmt: skip
        sim.step(4)
        runs.append(sim.positions)
    np.testing.assert_array_equal(runs[0], runs[1])


def test_a_one_tet_bone_fragment_on_stiff_tissue_is_stable():
    # a case a staggered coupling (body, then tissue) cannot take at dt = 1/60: the fragment's mass is grams and
    # the tissue's stiffness about E L = 1e5 N/m, so h^2 k / m is in the thousands (explicit limit 4); the coupled
    # solve is implicit as a whole, so the tissue comes to rest with the fragment in it, rigid
    m = box_tetmesh((0, 0, 0), (0.03, 0.03, 0.03), (3, 3, 3))
    centroid = m.nodes[m.tets].mean(axis=1)
    fragment = int(np.argmax(centroid[:, 2] + centroid[:, 0]))
    material = np.zeros(m.tet_count, dtype=np.int32)
    material[fragment] = 1
    sim = wb.Simulation(TetMesh(m.nodes, m.tets, material=material), young=1e7, poisson=0.45, density=1900.0,
                        rigid={1}, fixed=m.nodes[:, 2] == 0.0)  # fmt: skip
    assert sim.stats["rigid"]["free"] == 1 and sim.stats["rigid"]["free_nodes"] == 4
    sim.velocities = np.tile([0.0, 0.0, 5.0], (m.node_count, 1))
    sim.step(60)
    x = sim.positions
    corners = m.tets[fragment]
    np.testing.assert_allclose(distances(x[corners]), distances(m.nodes[corners]), atol=1e-7)
    assert np.abs(sim.velocities).max() < 1e-2
    assert np.isfinite(x).all()
