"""Simulation: polar decomposition, co-rotational forces and stiffness against a float64 reference and finite
differences, rigid-motion invariance, momentum and energy of backward Euler, determinism across thread counts,
fixed nodes, ground contact, the embedded surface, element rebuilds, errors and divergence.

The reference (:func:`reference_forces`, :func:`reference_energy`) is written here in numpy, float64, from the
definitions: ``F = Ds Dm^-1``, ``R`` from the SVD with the reflection fixed, strain ``sym(R^T F) - I``, energy
``V (mu |eps|^2 + lambda / 2 tr(eps)^2)``, force ``-R K (R^T x - X)`` through ``V R sigma Dm^-T``.
The cantilever beam is in ``test_sim_beam.py``, the tumor and the command line in ``test_sim_tumor.py``.
"""

import numpy as np
import pytest
import warp as wp

import warpblob as wb
from warpblob import SimulationError
from warpblob.mesh import TetMesh, TetStructure, box_tetmesh
from warpblob.sim import _coarse, _simulation, _solver
from warpblob.sim import _kernels as k

E, NU, RHO = 1e5, 0.3, 1000.0


def rotation(axis, angle) -> np.ndarray:
    """Rodrigues' rotation matrix about ``axis`` by ``angle`` radians."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


ROTATIONS = [((0, 0, 1), np.pi / 2), ((1, 0, 0), np.pi), ((1, 1, 1), np.pi), ((0, 1, 0), -np.pi / 2), ((1, 2, 3), 2.0)]


def block(shape=(3, 2, 2), size=(0.3, 0.2, 0.2)) -> TetMesh:
    return box_tetmesh((0, 0, 0), size, shape)


def simulation(mesh, **kw) -> wb.Simulation:
    options = dict(young=E, poisson=NU, density=RHO, gravity=(0, 0, 0))
    options.update(kw)
    return wb.Simulation(mesh, **options)


def deformed(mesh, seed=0, amount=0.08) -> np.ndarray:
    """A smooth large deformation: a bend and a twist, a rotation, then a little noise."""
    rng = np.random.default_rng(seed)
    x = mesh.nodes.astype(np.float64).copy()
    x[:, 2] += 0.4 * x[:, 0] ** 2
    angle = 2.0 * x[:, 0]
    y, z = x[:, 1].copy(), x[:, 2].copy()
    x[:, 1], x[:, 2] = np.cos(angle) * y - np.sin(angle) * z, np.sin(angle) * y + np.cos(angle) * z
    x *= 1.0 + amount * np.array([1.0, -0.5, 0.3])
    x = x @ rotation((1, 2, 3), 0.7).T
    return x + rng.normal(scale=0.002, size=x.shape)


# -- float64 reference ----------------------------------------------------------------------------------------


def reference_polar(F: np.ndarray) -> np.ndarray:
    U, s, Vt = np.linalg.svd(F)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U = U.copy()
        U[:, np.argmin(s)] *= -1
        R = U @ Vt
    return R


def _shape(p, tets):
    q = p[tets]
    return np.stack([q[:, 1] - q[:, 0], q[:, 2] - q[:, 0], q[:, 3] - q[:, 0]], axis=-1)


def reference_rotations(rest, tets, x):
    Dm_inv = np.linalg.inv(_shape(rest, tets))
    return np.array([reference_polar(F) for F in _shape(x, tets) @ Dm_inv])


def reference_energy(rest, tets, x, mu, lam) -> float:
    Dm = _shape(rest, tets)
    V = np.linalg.det(Dm) / 6
    F = _shape(x, tets) @ np.linalg.inv(Dm)
    total = 0.0
    for t in range(len(tets)):
        eps = 0.5 * (reference_polar(F[t]).T @ F[t] + F[t].T @ reference_polar(F[t])) - np.eye(3)
        total += V[t] * (mu * np.sum(eps * eps) + 0.5 * lam * np.trace(eps) ** 2)
    return total


def reference_forces(rest, tets, x, mu, lam, R=None) -> np.ndarray:
    """``-R K (R^T x - X)`` per node; with ``R`` given (T, 3, 3) the rotations are held fixed."""
    Dm = _shape(rest, tets)
    V = np.linalg.det(Dm) / 6
    B = np.linalg.inv(Dm)
    F = _shape(x, tets) @ B
    R = np.array([reference_polar(f) for f in F]) if R is None else R
    G = np.transpose(R, (0, 2, 1)) @ F - np.eye(3)
    eps = 0.5 * (G + np.transpose(G, (0, 2, 1)))
    sigma = 2 * mu * eps + lam * np.trace(eps, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    H = -V[:, None, None] * R @ sigma @ np.transpose(B, (0, 2, 1))
    corner = np.concatenate([-H.sum(axis=2)[:, None], np.transpose(H, (0, 2, 1))], axis=1)
    out = np.zeros_like(x)
    np.add.at(out, tets.ravel(), corner.reshape(-1, 3))
    return out


MU, LAM = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))


# -- the structured box mesh ----------------------------------------------------------------------------------


def test_box_tetmesh_is_a_conforming_positive_fill_of_the_box():
    mesh = box_tetmesh((-1.0, 0.0, 2.0), (1.0, 0.5, 2.3), (4, 2, 3))
    assert mesh.node_count == 5 * 3 * 4 and mesh.tet_count == 6 * 4 * 2 * 3
    assert mesh.volumes().min() > 0 and mesh.is_conforming()
    assert mesh.volume() == pytest.approx(2.0 * 0.5 * 0.3, rel=1e-6)
    np.testing.assert_allclose(mesh.nodes.min(axis=0), [-1.0, 0.0, 2.0])
    np.testing.assert_allclose(mesh.nodes.max(axis=0), [1.0, 0.5, 2.3])
    # the boundary is the box's six faces, two triangles per grid square
    assert len(mesh.surface_faces()) == 4 * (4 * 2 + 2 * 3 + 4 * 3)
    for bad in [dict(upper=(1, 0, 1), shape=(1, 1, 1)), dict(upper=(1, 1, 1), shape=(1, 0, 1))]:
        with pytest.raises(wb.MeshError, match="box_tetmesh"):
            box_tetmesh((0, 0, 0), bad["upper"], bad["shape"])


# -- polar decomposition --------------------------------------------------------------------------------------


@wp.kernel
def polar_kernel(F: wp.array(dtype=wp.mat33), R: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    R[i] = k.polar_rotation(F[i])


def polar(F: np.ndarray, device) -> np.ndarray:
    a = wp.array(F.astype(np.float32), dtype=wp.mat33, device=device)
    out = wp.zeros_like(a)
    wp.launch(polar_kernel, len(F), inputs=[a, out], device=device)
    return out.numpy().astype(np.float64)


def test_polar_rotation_is_a_rotation_for_any_deformation(device):
    rng = np.random.default_rng(1)
    rotations = np.array([rotation(a, t) for a, t in ROTATIONS])
    stretch = np.diag([1.3, 0.8, 1.1])
    general = rotations @ (stretch + 0.2 * rng.normal(size=(len(ROTATIONS), 3, 3)))
    mirror = np.diag([1.0, 1.0, -1.0])
    inverted = general @ mirror  # det < 0: an inverted tet
    flat = rotations @ np.diag([1.2, 0.9, 0.0])  # a tet squashed into a plane
    line = rotations @ np.diag([1.0, 0.0, 0.0])  # a tet squashed onto a line
    cases = np.concatenate([rotations, general, inverted, flat, line, np.zeros((1, 3, 3))])
    R = polar(cases, device)
    np.testing.assert_allclose(R @ np.transpose(R, (0, 2, 1)), np.broadcast_to(np.eye(3), R.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-5)
    n = len(ROTATIONS)
    # a pure rotation (90 and 180 degrees included) is its own rotation part
    np.testing.assert_allclose(R[:n], rotations, atol=1e-5)
    # general and inverted: the closest rotation, as the float64 reference finds it; R^T F is symmetric
    for F, Rk in zip(cases[n : 3 * n], R[n : 3 * n]):
        np.testing.assert_allclose(Rk, reference_polar(F), atol=1e-4)
        S = Rk.T @ F
        np.testing.assert_allclose(S, S.T, atol=1e-4)
    # inverted: S has exactly one negative eigenvalue (the tet pushes back out of the inversion)
    for F, Rk in zip(cases[2 * n : 3 * n], R[2 * n : 3 * n]):
        assert np.sum(np.linalg.eigvalsh(0.5 * (Rk.T @ F + F.T @ Rk)) < 0) == 1
    # flat: the rotation still carries the plane's two directions
    for F, Rk, Q in zip(cases[3 * n : 4 * n], R[3 * n : 4 * n], rotations):
        np.testing.assert_allclose(Rk[:, :2], Q[:, :2], atol=1e-4)


# -- forces and stiffness -------------------------------------------------------------------------------------


@pytest.mark.parametrize("axis, angle", ROTATIONS)
def test_rigid_motion_has_no_elastic_force_and_stays_still(device, axis, angle):
    mesh = block()
    sim = simulation(mesh, device=device)
    Q = rotation(axis, angle)
    x = mesh.nodes @ Q.T + np.array([1.0, -2.0, 3.0])
    sim.positions = x
    force_scale = E * 0.1**2  # stress E on a face of the cell size
    assert np.abs(sim.elastic_forces()).max() < 1e-5 * force_scale
    assert sim.energy()["elastic"] < 1e-9 * E * mesh.volume()
    sim.step(20)
    np.testing.assert_allclose(sim.positions, x, atol=2e-6)
    assert np.abs(sim.velocities).max() < 1e-4


def test_forces_match_the_reference_and_are_minus_the_energy_gradient(device):
    mesh = block()
    rest, tets = mesh.nodes.astype(np.float64), mesh.tets
    x = deformed(mesh)
    sim = simulation(mesh, device=device)
    sim.positions = x
    f_ref = reference_forces(rest, tets, x, MU, LAM)
    scale = np.abs(f_ref).max()
    np.testing.assert_allclose(sim.elastic_forces(), f_ref, atol=2e-4 * scale)
    assert sim.energy()["elastic"] == pytest.approx(reference_energy(rest, tets, x, MU, LAM), rel=1e-4)
    # the reference force is minus the gradient of the co-rotated energy (central differences, float64)
    rng = np.random.default_rng(2)
    for _ in range(3):
        d = rng.normal(size=x.shape)
        d /= np.linalg.norm(d)
        step = 1e-6
        up = reference_energy(rest, tets, x + step * d, MU, LAM)
        down = reference_energy(rest, tets, x - step * d, MU, LAM)
        slope = (up - down) / (2 * step)
        assert -np.sum(f_ref * d) == pytest.approx(slope, rel=1e-6, abs=1e-9 * scale)
    # and so is the kernels' force of the kernels' energy (float32: a coarser step and tolerance)
    d = rng.normal(size=x.shape)
    d /= np.linalg.norm(d)
    step = 1e-3
    energies = []
    for s in (step, -step):
        sim.positions = x + s * d
        energies.append(sim.energy()["elastic"])
    sim.positions = x
    assert -np.sum(sim.elastic_forces() * d) == pytest.approx((energies[0] - energies[1]) / (2 * step), rel=2e-3)


def test_system_matrix_is_the_force_derivative(device):
    mesh = block()
    rest, tets = mesh.nodes.astype(np.float64), mesh.tets
    rng = np.random.default_rng(3)
    v = rng.normal(size=(mesh.node_count, 3))
    sim = simulation(mesh, device=device)
    # at a rotated rest shape K' is the exact stiffness: compare with differences of the kernels' forces
    Q = rotation((1, 1, 0), 2.0)
    x = rest @ Q.T
    sim.positions = x
    Kv = sim.multiply(v)
    step = 1e-4
    sim.positions = x + step * v
    f_plus = sim.elastic_forces().astype(np.float64)
    sim.positions = x - step * v
    f_minus = sim.elastic_forces().astype(np.float64)
    np.testing.assert_allclose(Kv, -(f_plus - f_minus) / (2 * step), atol=5e-3 * np.abs(Kv).max())
    # at a large deformation it is the derivative with the rotations held (lagged): the reference, exactly linear
    x = deformed(mesh)
    sim.positions = x
    R = reference_rotations(rest, tets, x)
    df = (reference_forces(rest, tets, x + v, MU, LAM, R) - reference_forces(rest, tets, x - v, MU, LAM, R)) / 2
    Kv = sim.multiply(v)
    np.testing.assert_allclose(Kv, -df, atol=2e-4 * np.abs(df).max())
    # the step's matrix: mass and stiffness terms combine
    h, alpha, beta = 1 / 60, 0.1, 0.01
    A = sim.multiply(v, mass=1 + h * alpha, stiffness=h * beta + h * h)
    expected = (1 + h * alpha) * sim.masses[:, None] * v + (h * beta + h * h) * Kv
    np.testing.assert_allclose(A, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())


def test_lumped_masses_sum_to_the_total_mass():
    mesh = block()
    sim = simulation(mesh, density=RHO)
    assert sim.masses.sum() == pytest.approx(RHO * mesh.volume(), rel=1e-6)
    corner = sim.masses[mesh.tets[0, 0]]
    assert corner > 0


# -- time stepping --------------------------------------------------------------------------------------------


def test_linear_momentum_is_conserved_without_gravity_or_fixed_nodes(device):
    mesh = block()
    sim = simulation(mesh, device=device, young=1e6, tolerance=1e-6)
    rng = np.random.default_rng(4)
    sim.positions = deformed(mesh, amount=0.05)
    sim.velocities = np.array([0.3, -0.2, 0.1]) + rng.normal(scale=0.2, size=(mesh.node_count, 3))
    m = sim.masses[:, None]
    p0 = (m * sim.velocities).sum(axis=0)
    sim.step(60)
    p = (m * sim.velocities).sum(axis=0)
    scale = np.sqrt(np.sum(m * sim.velocities**2) * m.sum())  # |p| of the same kinetic energy all moving as one
    np.testing.assert_allclose(p, p0, atol=1e-4 * scale)


def test_energy_does_not_grow_over_1000_undamped_steps():
    mesh = block((3, 1, 1))
    sim = simulation(mesh, young=1e6, dt=1 / 60, damping=(0.0, 0.0))
    x = mesh.nodes.astype(np.float64) * np.array([1.1, 0.95, 0.95])
    x[:, 1] += 0.3 * x[:, 0] ** 2
    sim.positions = x
    e0 = sim.energy()["total"]
    assert e0 > 0
    history = []
    for _ in range(1000):
        sim.step()
        history.append(sim.energy()["total"])
    assert max(history) <= e0 * (1 + 1e-4)
    assert history[-1] < e0
    assert np.all(np.diff(history) <= 1e-4 * e0)


@pytest.mark.parametrize("preconditioner", ["two_level", "block_jacobi"])
def test_results_are_bit_identical_for_one_and_two_threads(monkeypatch, preconditioner):
    # small grains split every launch into pieces, so the threads really share the work; small aggregates
    # give the coarse space several (its coupling and prolongation launches split too)
    monkeypatch.setattr(_solver, "TET_GRAIN", 8)
    monkeypatch.setattr(_solver, "NODE_GRAIN", 8)
    monkeypatch.setattr(_solver, "BLOCK_NODES", 4)
    monkeypatch.setattr(_coarse, "COUPLE_GRAIN", 8)
    monkeypatch.setattr(_coarse, "AGGREGATE_NODES", 8)
    mesh = block((6, 3, 3))
    runs = []
    for threads in (1, 2):
        sim = simulation(mesh, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0, ground=(-0.05, 0.4), threads=threads,
                         preconditioner=preconditioner)  # fmt: skip
        if preconditioner == "two_level":
            assert sim.stats["coarse_size"] > 6 * 4
        sim.velocities = np.tile([0.5, 0.0, 0.0], (mesh.node_count, 1))
        sim.step(8)
        runs.append((sim.positions, sim.velocities, sim.stats["cg_iterations_total"], sim.volume()))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    assert runs[0][2] == runs[1][2] and runs[0][3] == runs[1][3]


def test_stats_report_every_stage():
    mesh = block()
    sim = simulation(mesh, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    sim.step(3)
    s = sim.stats
    assert s["steps"] == 3 and sim.time == pytest.approx(3 / 60)
    assert set(s["seconds"]) == {"contact", "assembly", "cg", "update", "elements", "check"}
    assert all(v >= 0 for v in s["seconds"].values())
    assert s["cg_iterations"] > 0 and s["cg_iterations_total"] >= s["cg_iterations"]
    assert s["residual"] >= 0 and s["tet_count"] == mesh.tet_count


# -- fixed nodes and ground -----------------------------------------------------------------------------------


def test_fixed_nodes_hold_and_follow_their_targets(device):
    mesh = block()
    left = mesh.nodes[:, 0] == 0
    sim = simulation(mesh, device=device, gravity=(0, 0, -9.81), fixed=left)
    assert np.array_equal(sim.fixed, np.flatnonzero(left))
    sim.step(5)
    np.testing.assert_array_equal(sim.positions[left], mesh.nodes[left])
    assert sim.positions[~left, 2].min() < -1e-4  # the rest sags
    target = sim.fixed_positions + np.array([0.0, 0.0, 0.01])
    sim.fixed_positions = target
    before = sim.positions
    sim.step()
    np.testing.assert_allclose(sim.positions[left], target, atol=1e-7)
    np.testing.assert_allclose(sim.velocities[left], (target - before[left]) / sim.dt, rtol=1e-4)
    # indices work as well as a mask, and moving the whole body moves the targets with it
    sim.fixed = np.flatnonzero(left)[:2]
    assert len(sim.fixed) == 2 and sim.fixed_positions.shape == (2, 3)
    sim.positions = sim.positions + 1.0
    np.testing.assert_allclose(sim.fixed_positions, sim.positions[sim.fixed])


def test_a_dropped_block_comes_to_rest_on_the_ground(device):
    mesh = block((2, 2, 2), (0.2, 0.2, 0.2))
    sim = simulation(mesh, device=device, gravity=(0, 0, -9.81), ground=(-0.1, 0.5), young=2e5)
    sim.step(90)
    z = sim.positions[:, 2]
    assert z.min() >= -0.1 - 1e-6
    assert z.min() < -0.1 + 1e-3  # it landed
    assert np.abs(sim.velocities).max() < 0.05
    assert sim.volume() == pytest.approx(mesh.volume(), rel=0.05)


@pytest.mark.parametrize("friction", [0.0, 0.3])
def test_ground_friction_is_coulomb(friction):
    mesh = block((2, 2, 1), (0.2, 0.2, 0.1))
    sim = simulation(mesh, gravity=(0, 0, -9.81), ground=(0.0, friction), young=1e6, damping=(0.0, 0.02))
    sim.step(30)  # settle on the ground
    sim.velocities = np.tile([1.0, 0.0, 0.0], (mesh.node_count, 1))
    t = 0.2
    sim.step(round(t / sim.dt))
    speed = np.average(sim.velocities[:, 0], weights=sim.masses)
    # Coulomb: the sliding body decelerates by friction * g
    assert speed == pytest.approx(max(1.0 - friction * 9.81 * t, 0.0), abs=0.08)
    assert sim.positions[:, 2].min() >= -1e-6


# -- embedded surface -----------------------------------------------------------------------------------------


def test_surface_rides_on_the_volume(device):
    model = wb.scenes.tumor()
    volume = wb.tetrahedralize(model, cellsize=0.35)
    surface = wb.polygonize(model, cellsize=0.25)
    sim = simulation(volume, device=device)
    binding = sim.surface(surface)
    assert binding.tet.shape == (surface.vertex_count,) and np.all(binding.tet >= 0)
    np.testing.assert_allclose(binding.bary.sum(axis=1), 1.0, atol=1e-5)
    inside = binding.distance == 0
    assert np.all(binding.bary[inside] >= -1e-5)
    np.testing.assert_allclose(sim.surface_positions(), surface.vertices, atol=1e-6)
    Q = rotation((1, 2, 0.5), 2.5)
    shift = np.array([0.5, -1.0, 2.0])
    sim.positions = volume.nodes @ Q.T + shift
    np.testing.assert_allclose(sim.surface_positions(), surface.vertices @ Q.T + shift, atol=1e-5)


def test_a_point_outside_binds_to_the_nearest_tet(device):
    mesh = block((2, 2, 2), (1.0, 1.0, 1.0))
    sim = simulation(mesh, device=device)
    points = np.array([[0.3, 0.6, -0.25], [1.5, 0.5, 0.5], [0.25, 0.25, 0.25]])
    binding = sim.surface(wb.SurfaceMesh(points, np.zeros((0, 3), np.int32), points, points))
    np.testing.assert_allclose(binding.distance, [0.25, 0.5, 0.0], atol=1e-6)
    corners = mesh.nodes[mesh.tets[binding.tet]]
    assert corners[0, :, 2].min() == 0.0 and corners[1, :, 0].max() == 1.0
    np.testing.assert_allclose(sim.surface_positions(), points, atol=1e-6)


def test_record_writes_the_motion_of_volume_and_surface(tmp_path):
    from pxr import Usd, UsdGeom

    mesh = block()
    sim = simulation(mesh, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    points = mesh.nodes[::5]
    sim.surface(wb.SurfaceMesh(points, np.zeros((0, 3), np.int32), points, points))
    path = sim.record(tmp_path / "beam.usdc", 6, every=2)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == pytest.approx(30.0) and stage.GetEndTimeCode() == 3
    volume = UsdGeom.TetMesh(stage.GetPrimAtPath("/Simulation/Volume"))
    np.testing.assert_allclose(np.asarray(volume.GetPointsAttr().Get(3)), sim.positions, atol=1e-7)
    surface = UsdGeom.Mesh(stage.GetPrimAtPath("/Simulation/Surface"))
    np.testing.assert_allclose(np.asarray(surface.GetPointsAttr().Get(3)), sim.surface_positions(), atol=1e-7)
    assert len(volume.GetSurfaceFaceVertexIndicesAttr().Get(0)) == len(mesh.surface_faces())
    with pytest.raises(SimulationError, match="every"):
        sim.record(tmp_path / "x.usda", 3, every=0)


# -- topology changes -----------------------------------------------------------------------------------------


def test_rebuild_after_killing_and_adding_tets():
    mesh = block()
    sim = simulation(mesh, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    dead = np.arange(6)
    sim.rebuild(dead, alive=np.zeros(6, dtype=bool))
    kept = np.setdiff1d(np.arange(mesh.tet_count), dead)
    assert sim.volume() == pytest.approx(mesh.volumes()[kept].sum(), rel=1e-6)
    fresh = simulation(TetMesh(mesh.nodes, mesh.tets[kept]), gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    np.testing.assert_allclose(sim.masses, fresh.masses, rtol=1e-6)
    # the dead tets come back as new slots, with one new node splitting nothing (it stays inert)
    rest = np.vstack([mesh.nodes, [[5.0, 5.0, 5.0]]])
    sim.rebuild(np.arange(mesh.tet_count, mesh.tet_count + 6), tets=mesh.tets[dead], rest=rest,
                young=np.full(6, E), poisson=np.full(6, NU), density=np.full(6, RHO))  # fmt: skip
    assert sim.tet_count == mesh.tet_count + 6 and sim.node_count == mesh.node_count + 1
    assert sim.volume() == pytest.approx(mesh.volume(), rel=1e-6)
    sim.step(2)
    np.testing.assert_array_equal(sim.positions[-1], [5.0, 5.0, 5.0])


def test_a_tet_structure_simulates_like_its_tet_mesh():
    mesh = block()
    a = simulation(mesh, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    s = TetStructure.from_tetmesh(mesh)
    b = simulation(s, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    a.step(3)
    b.step(3)
    np.testing.assert_array_equal(a.positions, b.positions)
    volume = b.volume()
    s.remove_cell(0)
    b.rebuild([0])
    assert not b.elements.alive_host[0]
    assert volume - b.volume() == pytest.approx(mesh.volumes()[0], rel=0.05)


# -- errors and divergence ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kw, words",
    [
        (dict(young=0.0), ["young", "0.0", "tet 0", "positive"]),
        (dict(young=-5.0), ["young", "-5.0"]),
        (dict(poisson=0.5), ["poisson", "0.5", "(-1.0, 0.5)"]),
        (dict(poisson=-1.0), ["poisson", "-1.0"]),
        (dict(density=0.0), ["density", "0.0"]),
        (dict(young=float("nan")), ["young", "nan", "not finite"]),
        (dict(young={0: "soft"}), ["young[material 0]", "'soft'"]),
        (dict(young={7: 1e5}), ["material 0"]),
        (dict(dt=0.0), ["dt", "0.0"]),
        (dict(gravity=(0, float("nan"), 0)), ["gravity"]),
        (dict(damping=(-0.1, 0.0)), ["damping", "-0.1"]),
        (dict(ground=(0.0, -1.0)), ["friction", "-1.0"]),
        (dict(fixed=np.zeros(5, dtype=bool)), ["fixed", "(5,)"]),
        (dict(fixed=[0, 10_000]), ["fixed", "10000"]),
        (dict(tolerance=0.0), ["tolerance"]),
        (dict(max_iterations=0), ["max_iterations", "0"]),
    ],
)
def test_bad_parameters_raise_simulation_error_naming_the_value(kw, words):
    mesh = block()
    with pytest.raises(SimulationError) as info:
        simulation(mesh, **kw)
    for word in words:
        assert word in str(info.value)


def test_per_tet_arrays_name_the_bad_tet():
    mesh = block()
    young = np.full(mesh.tet_count, E)
    young[7] = np.nan
    with pytest.raises(SimulationError, match="at tet 7"):
        simulation(mesh, young=young)
    poisson = np.full(mesh.tet_count, NU)
    poisson[3] = 0.7
    with pytest.raises(SimulationError, match="poisson = 0.7 at tet 3"):
        simulation(mesh, poisson=poisson)


def test_inverted_and_flat_rest_tets_are_refused_by_index():
    mesh = block()
    tets = mesh.tets.copy()
    tets[4] = tets[4][[0, 2, 1, 3]]
    with pytest.raises(SimulationError, match="tet 4 .* inverted"):
        simulation(TetMesh(mesh.nodes, tets))
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=np.float32)
    with pytest.raises(SimulationError, match="tet 0 .* zero-volume"):
        simulation(TetMesh(nodes, [[0, 1, 2, 3]]))


def _reference_check(rest, tets, alive):
    """The rest check in numpy float64, tet by tet: (kind, tet) of the first bad tet of the first kind found
    (1 a node outside [0, N), 2 a repeated node, 3 volume <= 1e-7 longest edge^3), or None."""
    n = len(rest)
    found = {}
    for t, (tet, live) in enumerate(zip(tets, alive)):
        if not live:
            continue
        if any(i < 0 or i >= n for i in tet):
            found.setdefault(1, t)
            continue
        if len(set(tet.tolist())) < 4:
            found.setdefault(2, t)
            continue
        p = rest[tet].astype(np.float64)
        volume = np.dot(p[1] - p[0], np.cross(p[2] - p[0], p[3] - p[0])) / 6.0
        longest = max(np.linalg.norm(p[j] - p[i]) for i in range(4) for j in range(i + 1, 4))
        if volume <= 1e-7 * longest**3:
            found.setdefault(3, t)
    for kind in (1, 2, 3):
        if kind in found:
            return kind, found[kind]
    return None


@pytest.mark.parametrize("seed", range(6))
def test_rest_check_matches_a_numpy_reference(seed):
    """The kernel's rest check refuses exactly the tets a tet-by-tet float64 reference does, with the same
    tet named first, by kind: nodes out of range, repeated nodes, inverted and flat tets (dead tets are
    never refused), on random tets mixing all of them; each refused tet is then killed and the check run
    again, down to none."""
    from warpblob.sim._elements import check_tets

    rng = np.random.default_rng(seed)
    rest = rng.random((40, 3)).astype(np.float32)
    rest[30:] = rest[0] + np.outer(np.arange(10), [0.1, 0.2, 0.3])  # collinear nodes: flat tets
    tets = np.stack([rng.choice(40, 4, replace=False) for _ in range(300)]).astype(np.int32)
    p = rest[tets].astype(np.float64)
    volume = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]))
    tets[volume < 0] = tets[volume < 0][:, [0, 2, 1, 3]]  # positive ...
    bad = rng.choice(300, 12, replace=False)
    kinds = rng.integers(0, 4, 12)
    tets[bad[kinds == 0], 3] = 40 + seed  # ... but a few out of range,
    tets[bad[kinds == 1], 2] = tets[bad[kinds == 1], 0]  # repeated,
    tets[bad[kinds == 2]] = tets[bad[kinds == 2]][:, [1, 0, 2, 3]]  # inverted, or flat:
    tets[bad[kinds == 3]] = [rng.choice(np.arange(30, 40), 4, replace=False) for _ in range(int((kinds == 3).sum()))]
    seen = set()
    for subset in (np.arange(300), np.sort(rng.choice(300, 150, replace=False))):
        alive = rng.random(300) > 0.1
        while (want := _reference_check(rest, tets[subset], alive[subset])) is not None:
            kind, j = want
            message = {1: "names a node outside", 2: "repeats a node", 3: "(inverted|zero-volume) at rest"}[kind]
            with pytest.raises(SimulationError, match=rf"^tet {int(subset[j])} = .*{message}"):
                check_tets(rest, tets, alive, subset)
            seen.add(kind)
            alive[subset[j]] = False  # the next one
        check_tets(rest, tets, alive, subset)  # none left: no error
    assert seen == {1, 2, 3}


def test_non_finite_state_is_refused():
    mesh = block()
    sim = simulation(mesh)
    bad = mesh.nodes.astype(np.float64)
    bad[5, 1] = np.inf
    with pytest.raises(SimulationError, match=r"positions\[5\]"):
        sim.positions = bad
    with pytest.raises(SimulationError, match="shape"):
        sim.velocities = np.zeros((3, 3))
    with pytest.raises(SimulationError, match="TetMesh or a TetStructure"):
        simulation(mesh.nodes)


def test_the_divergence_check_reduces_like_numpy():
    mesh = block()
    sim = simulation(mesh, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    sim.external_forces = np.tile([0.0, 2.0, 0.0], (mesh.node_count, 1))
    sim.step()
    sim.fixed_positions = sim.fixed_positions + np.array([0.0, 0.0, 0.01], np.float32)
    sim.step()  # the fixed nodes move: the constraints do work
    cur = sim._cur
    x0, x1, v1, state = sim._x[1 - cur], sim._x[cur], sim._v[cur], sim._state
    bad, sums = sim._reduce(x0, x1, v1, state)
    assert bad == -1
    m, v = sim.masses, v1.numpy().astype(np.float64)
    dx = x1.numpy().astype(np.float64) - x0.numpy()
    expected = {
        "kinetic": 0.5 * np.dot(m, (v**2).sum(axis=1)),
        "elastic": state.energy.numpy().astype(np.float64).sum(),
        "gravity": np.dot(m, dx @ np.array([0, 0, -9.81])),
        "external": np.sum(sim.external_forces * dx),
        "constraint": np.abs(np.sum(state.node_force.numpy() * sim._moved.numpy(), axis=1)).sum(),
    }
    assert sums["constraint"] > 0 and sums["external"] != 0
    for name, value in expected.items():
        assert sums[name] == pytest.approx(value, rel=1e-5, abs=1e-12), name
    broken = wp.clone(v1)
    values = broken.numpy()
    values[[7, 11]] = np.nan
    broken.assign(values)
    assert sim._reduce(x0, x1, broken, state)[0] == 7


def test_a_diverging_step_raises_and_keeps_the_previous_state(monkeypatch):
    mesh = block()
    sim = simulation(mesh, gravity=(0, 0, -9.81), fixed=mesh.nodes[:, 0] == 0)
    sim.step(3)
    before = sim.positions, sim.velocities, sim.time, sim.energy()
    forces = np.zeros((mesh.node_count, 3))
    forces[-1] = 1e30  # overflows the float32 dot products of the solve
    sim.external_forces = forces
    with pytest.raises(SimulationError, match="diverged"):
        sim.step()
    assert np.array_equal(sim.positions, before[0]) and np.array_equal(sim.velocities, before[1])
    assert sim.time == before[2] and sim.energy() == before[3]
    # an energy blow-up (made so by a zero growth allowance) is refused the same way
    sim.external_forces = np.zeros((mesh.node_count, 3))
    monkeypatch.setattr(_simulation, "BLOWUP", 0.0)
    with pytest.raises(SimulationError, match="exceeds"):
        sim.step()
    assert np.array_equal(sim.positions, before[0]) and sim.time == before[2]
    monkeypatch.undo()
    sim.step()
    assert sim.time > before[2]
