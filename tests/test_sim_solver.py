"""The linear solve of a step: the two solvers and the two preconditioners.

The fused PCG and ``warp.optim.linear.cg`` solve the same filtered backward-Euler system with the same
preconditioner and stopping rule, so a step agrees to the CG tolerance (free, with fixed and moving fixed nodes,
with ground contact and with a tool pressing). The two-level preconditioner (:mod:`warpblob.sim._coarse`) gives
the same step as block-Jacobi to the tolerance, in far fewer iterations on a stiff beam, and is symmetric positive
definite: it matches a dense numpy reference built from the operator itself.
"""

import numpy as np
import pytest
import warp as wp

import warpblob as wb
from warpblob import SimulationError
from warpblob.mesh import box_tetmesh
from warpblob.sim import _coarse
from warpblob.tools import Path, Probe

TOLERANCE = 1e-7


def beam(linear_solver, **kw) -> tuple:
    mesh = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (8, 2, 2))
    options = dict(young=1e6, poisson=0.3, density=1000.0, tolerance=TOLERANCE, max_iterations=500,
                   linear_solver=linear_solver)  # fmt: skip
    options.update(kw)
    return mesh, wb.Simulation(mesh, **options)


def same_step(make, kinds=("pcg", "warp")) -> tuple:
    """The first kind's simulation after three steps, and the second's put in its state; then one step of each."""
    a, b = make(kinds[0]), make(kinds[1])
    a.step(3)
    b.positions, b.velocities, b.time = a.positions, a.velocities, a.time
    # setting the state rebuilds b's lagged coarse matrix there: rebuild a's too, so both use one preconditioner
    a.velocities = a.velocities
    a.step()
    b.step()
    return a, b


def disagreement(a: wb.Simulation, b: wb.Simulation) -> dict:
    """How far the two steps are apart: velocities and positions relative to the step's largest velocity
    (and that velocity times dt, past a float32 rounding allowance of 1e-7), the difference of the CG iteration
    counts, the second solve's residual."""
    dv = float(np.abs(a.velocities).max())
    return {
        "motion": dv,
        "velocity": float(np.abs(a.velocities - b.velocities).max()) / dv,
        "position": (float(np.abs(a.positions - b.positions).max()) - 1e-7) / (dv * a.dt),
        "iterations": abs(a.stats["cg_iterations"] - b.stats["cg_iterations"]),
        "residual": b.stats["relative_residual"],
    }


def assert_same_step(d: dict) -> None:
    # the same step to the CG tolerance, iteration counts within one
    assert d["motion"] > 0, d
    assert d["velocity"] <= 1e-4 and d["position"] <= 1e-4, d
    assert d["iterations"] <= 1 and d["residual"] <= TOLERANCE * 1.0001, d


@pytest.mark.parametrize("case", ["free", "fixed", "moving", "ground"])
def test_warp_cg_gives_the_same_step(case):
    def make(solver):
        mesh, sim = beam(solver, ground=-0.01 if case == "ground" else None)
        if case in ("fixed", "moving"):
            sim.fixed = mesh.nodes[:, 0] == 0.0
        if case == "moving":
            sim.fixed_positions = sim.fixed_positions + np.array([0.0, 0.0, 0.01], np.float32)
        return sim

    d = disagreement(*same_step(make))
    assert d["motion"] > 0 and d["velocity"] <= 1e-4 and d["position"] <= 1e-4, d
    assert d["iterations"] <= 1 and d["residual"] <= TOLERANCE * 1.0001, d


def test_warp_cg_gives_the_same_step_with_a_tool_pressing():
    model = wb.Box((0, 0, 0), (0.5, 0.5, 0.2), 0.3)
    volume = wb.tetrahedralize(model, cellsize=0.2)
    top = float(volume.nodes[:, 2].max())

    def make(solver):
        sim = wb.Simulation(volume, young=1e5, poisson=0.45, density=1000.0, gravity=(0, 0, 0), model=model,
                            fixed=volume.nodes[:, 2] < volume.nodes[:, 2].min() + 0.05, tolerance=TOLERANCE,
                            max_iterations=500, linear_solver=solver)  # fmt: skip
        sim.add_tool(Probe(0.4), Path.line((0, 0, top), (0, 0, top - 0.1), 0.1), stiffness=1e7)
        return sim

    a, b = same_step(make)
    assert a.stats["contact"]["penetrating"] > 0
    assert_same_step(disagreement(a, b))
    np.testing.assert_allclose(a.contact_force(0), b.contact_force(0), rtol=1e-3)


def test_an_unknown_linear_solver_is_refused():
    with pytest.raises(SimulationError, match="'scipy'"):
        beam("scipy")


def test_an_unknown_preconditioner_is_refused():
    with pytest.raises(SimulationError, match="preconditioner .*'multigrid'"):
        beam("pcg", preconditioner="multigrid")


# -- the two-level preconditioner ---------------------------------------------------------------------------


@pytest.mark.parametrize("case", ["fixed", "ground", "rebuilt"])
def test_two_level_gives_the_same_step_as_block_jacobi(case, monkeypatch):
    # small aggregates, so the coarse space has several (the 8 x 2 x 2 beam has 81 nodes)
    monkeypatch.setattr(_coarse, "AGGREGATE_NODES", 12)

    def make(preconditioner):
        mesh, sim = beam("pcg", young=1e7, preconditioner=preconditioner, ground=-0.01 if case == "ground" else None)
        sim.fixed = mesh.nodes[:, 0] == 0.0
        if case == "rebuilt":
            sim.rebuild(np.arange(6), alive=np.zeros(6, dtype=bool))
        return sim

    a, b = same_step(make, ("block_jacobi", "two_level"))
    assert b.stats["preconditioner"] == "two_level" and b.stats["coarse_size"] >= 6 * 3
    assert a.stats["coarse_size"] == 0
    d = disagreement(a, b)
    # both stop at a relative residual of 1e-7 from different iterates: the steps differ by at most about
    # cond(A) (~1e3 for this stiff beam at dt = 1/60) times that
    assert d["motion"] > 0 and d["velocity"] <= 1e-3 and d["position"] <= 1e-3, d
    assert d["residual"] <= TOLERANCE * 1.0001 and a.stats["relative_residual"] <= TOLERANCE * 1.0001, d


def cut_beam(preconditioner: str = "two_level") -> tuple:
    """The 8 x 2 x 2 beam, fixed at x = 0, cut through by a tilted plane near its middle (two pieces)."""
    mesh = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (8, 2, 2))
    s = wb.TetStructure.from_tetmesh(mesh)
    sim = wb.Simulation(s, young=1e7, poisson=0.3, density=1000.0, tolerance=TOLERANCE, max_iterations=500,
                        fixed=mesh.nodes[:, 0] == 0.0, preconditioner=preconditioner)  # fmt: skip
    result = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.53, 0.1, 0.1), (1.0, 0.15, 0.1), 2.0), collect=False)
    sim.apply_cut(result)
    return sim, result


def flood_pieces(tets: np.ndarray, node_count: int) -> np.ndarray:
    """Connected pieces of the nodes through the tets, by a breadth-first flood (the reference)."""
    neighbours = [set() for _ in range(node_count)]
    for tet in tets:
        for a in tet:
            neighbours[a].update(int(b) for b in tet)
    piece = np.full(node_count, -1)
    for start in np.unique(tets):
        if piece[start] >= 0:
            continue
        piece[start], queue = piece.max() + 1, [int(start)]
        while queue:
            for b in neighbours[queue.pop()]:
                if piece[b] < 0:
                    piece[b] = piece[start]
                    queue.append(b)
    return piece


def test_aggregates_hold_one_piece_each_after_a_cut(monkeypatch):
    """After a cut severs the beam, no aggregate of the coarse space holds nodes of both pieces (an aggregate
    of a lattice cell the cut crosses is split in two, one per side), and the two-level step still agrees
    with block-Jacobi's."""
    monkeypatch.setattr(_coarse, "AGGREGATE_NODES", 12)
    sim, result = cut_beam()
    assert result.components == 2
    live = sim.elements.tets_host[sim.elements.alive_host]
    piece = flood_pieces(live, sim.node_count)
    assert piece.max() == 1
    aggregate = sim._solver.coarse.node_aggregate.numpy()
    assert aggregate.max() >= 3
    for g in range(int(aggregate.max()) + 1):
        assert len(np.unique(piece[aggregate == g])) == 1, g
    # a lattice cell the cut crosses makes an aggregate on each side: more aggregates than cells
    cells = np.floor((sim.elements.rest_host[piece >= 0] - sim.elements.rest_host[piece >= 0].min(axis=0))
                     / sim._solver.coarse.cell).astype(np.int64)  # fmt: skip
    assert int(aggregate.max()) + 1 > len(np.unique(cells, axis=0))

    a, b = same_step(lambda kind: cut_beam(kind)[0], ("block_jacobi", "two_level"))
    d = disagreement(a, b)
    assert d["motion"] > 0 and d["velocity"] <= 1e-3 and d["position"] <= 1e-3, d
    assert d["residual"] <= TOLERANCE * 1.0001 and a.stats["relative_residual"] <= TOLERANCE * 1.0001, d


def test_a_cut_that_severs_nothing_keeps_the_aggregates(monkeypatch):
    """A cut that leaves one piece: the structure knows its count of one piece, and a coarse space told so
    (pieces=1, which skips counting the nodes' pieces) aggregates as one that counts them."""
    monkeypatch.setattr(_coarse, "AGGREGATE_NODES", 12)
    mesh = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (8, 2, 2))
    s = wb.TetStructure.from_tetmesh(mesh)
    sim = wb.Simulation(s, young=1e7, poisson=0.3, density=1000.0, fixed=mesh.nodes[:, 0] == 0.0)
    # a notch: the plane cut only where the blade's square reaches (half the beam's depth)
    result = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.53, 0.1, 0.2), (1.0, 0.0, 0.0), 0.16), collect=False)
    sim.apply_cut(result)
    assert result.tets_added > 0 and result.components == 1 and s._known_pieces() == 1
    hinted = _coarse.CoarseSpace(sim.elements, sim._solver.coarse_axes, pieces=1)
    counted = _coarse.CoarseSpace(sim.elements, sim._solver.coarse_axes)
    np.testing.assert_array_equal(hinted.node_aggregate.numpy(), counted.node_aggregate.numpy())


def test_two_level_cuts_the_cg_iterations_on_a_stiff_beam():
    # Block-Jacobi PCG needs O(sqrt(kappa)) iterations with kappa ~ (L / h)^2 on a stiffness-dominated system:
    # its slowest error is the bending of the whole beam. The rigid modes of aggregates of size H capture that
    # bending piecewise, leaving kappa ~ (H / h)^2: about L / H times fewer iterations, L / H ~ 10 here (aggregates
    # of ~64 nodes on the 41 x 9 x 9 nodes: 10 along the beam, 2 x 2 across). Asserting a factor 3 leaves room for
    # the constants.
    mesh = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (40, 8, 8))
    iterations = {}
    for preconditioner in ("block_jacobi", "two_level"):
        sim = wb.Simulation(mesh, young=1e7, poisson=0.3, density=1000.0, fixed=mesh.nodes[:, 0] == 0.0,
                            tolerance=1e-6, max_iterations=5000, preconditioner=preconditioner)  # fmt: skip
        sim.step(3)
        assert sim.stats["relative_residual"] <= 1e-6
        iterations[preconditioner] = sim.stats["cg_iterations_total"]
    assert iterations["two_level"] < iterations["block_jacobi"] / 3, iterations


def dense_operator(sim, state, c_mass: float, c_stiff: float) -> np.ndarray:
    """The filtered system ``A'`` of the last assembly as a dense (3 N, 3 N) float64 matrix, column by column."""
    n = 3 * sim.node_count
    out = wp.zeros(sim.node_count, dtype=wp.vec3)
    A = np.zeros((n, n))
    for j in range(n):
        e = np.zeros(n, dtype=np.float32)
        e[j] = 1.0
        sim._solver.multiply(state, wp.array(e.reshape(-1, 3), dtype=wp.vec3), out, c_mass, c_stiff)
        A[:, j] = out.numpy().ravel()
    return 0.5 * (A + A.T)


def apply(solver, r: np.ndarray) -> np.ndarray:
    z = wp.zeros(len(r), dtype=wp.vec3)
    solver.precondition(wp.array(r.astype(np.float32), dtype=wp.vec3), z)
    return z.numpy().astype(np.float64)


def test_two_level_is_a_symmetric_positive_definite_match_of_its_dense_reference(monkeypatch):
    monkeypatch.setattr(_coarse, "AGGREGATE_NODES", 6)
    mesh = box_tetmesh((0, 0, 0), (0.3, 0.2, 0.2), (3, 2, 2))
    sim = wb.Simulation(mesh, young=1e7, poisson=0.3, density=1000.0, fixed=mesh.nodes[:, 0] == 0.0)
    x = mesh.nodes.astype(np.float64)
    x[:, 2] += 0.3 * x[:, 0] ** 2  # bent: the rotations are not the identity
    sim.positions = x
    solver, state, h = sim._solver, sim._state, sim.dt
    c_mass, c_stiff = 1.0, h * h
    cur = sim._cur
    solver.assemble(state, sim._x[cur], sim._v[cur], sim._target, sim._external, sim.gravity, h, c_mass, c_stiff,
                    wp.zeros(sim.node_count, dtype=wp.vec3))  # fmt: skip
    coarse = solver.coarse
    G = coarse.aggregate_count
    assert G >= 3
    A = dense_operator(sim, state, c_mass, c_stiff)
    # P: node i of aggregate g moves by S_i (t + w x d_i) for the coarse unknowns (t, w) of g
    aggregate, d, s = coarse.node_aggregate.numpy(), coarse.node_mode.numpy(), solver.axes.numpy()
    P = np.zeros((3 * sim.node_count, 6 * G))
    for i in np.flatnonzero(aggregate >= 0):
        g = aggregate[i]
        cross = np.array([[0, -d[i, 2], d[i, 1]], [d[i, 2], 0, -d[i, 0]], [-d[i, 1], d[i, 0], 0]])
        P[3 * i : 3 * i + 3, 6 * g : 6 * g + 6] = np.diag(s[i]) @ np.hstack([np.eye(3), -cross])
    Ac = P.T @ A @ P
    np.testing.assert_allclose(coarse.matrix(), Ac, rtol=1e-4, atol=1e-5 * np.abs(Ac).max())
    D = np.zeros_like(A)
    for i in range(sim.node_count):
        D[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = np.linalg.inv(A[3 * i : 3 * i + 3, 3 * i : 3 * i + 3])
    # aggregates of fixed nodes alone move nothing: the pseudo-inverse leaves them out, as the solver does
    reference = D + P @ np.linalg.pinv(Ac, rcond=1e-9, hermitian=True) @ P.T
    rng = np.random.default_rng(3)
    r1, r2 = rng.normal(size=(2, sim.node_count, 3))
    z1, z2 = apply(solver, r1), apply(solver, r2)
    for r, z in ((r1, z1), (r2, z2)):
        expected = (reference @ r.ravel()).reshape(-1, 3)
        np.testing.assert_allclose(z, expected, rtol=0, atol=1e-4 * np.abs(expected).max())
        assert float(np.sum(r * z)) > 0
    # symmetric: r1 . M^-1 r2 == r2 . M^-1 r1 (to float32 rounding of the products)
    assert abs(np.sum(r1 * z2) - np.sum(r2 * z1)) <= 1e-5 * np.sqrt(np.sum(r1 * z1) * np.sum(r2 * z2))
    # positive definite: the dense reference's spectrum (D^-1 is, and the coarse part is semi-definite)
    assert np.linalg.eigvalsh(0.5 * (reference + reference.T)).min() > 0



def test_a_recorded_launch_follows_its_sizes(device):
    """A recorded launch split in pieces (block-Jacobi's ``z = alpha D^-1 r + beta y``), rebound to other
    sizes and arrays as a rebuild does, writes what numpy gives over the new range, every piece included; a
    rebind to another number of pieces is refused and recorded anew; an empty range runs nothing."""
    from warpblob.sim import _kernels as sk
    from warpblob.sim._solver import Prepared

    dev = wp.get_device(device)
    rng = np.random.default_rng(5)

    def case(n):
        blocks = rng.standard_normal((n, 3, 3)).astype(np.float32)
        r, y = (rng.standard_normal((n, 3)).astype(np.float32) for _ in range(2))
        arrays = [wp.array(blocks, dtype=wp.mat33, device=dev), wp.array(r, dtype=wp.vec3, device=dev),
                  wp.array(y, dtype=wp.vec3, device=dev)]  # fmt: skip
        z = wp.zeros(n + 5, dtype=wp.vec3, device=dev)  # (room past n: left untouched)
        expected = 0.5 * np.einsum("nij,nj->ni", blocks, r) - 2.0 * y
        return [*arrays, 0.5, -2.0], [z], expected

    before, after, expected = case(40)
    recorded = Prepared(sk.precondition_kernel, 40, before, after, dev, 2, 8)
    recorded()
    np.testing.assert_allclose(after[0].numpy()[:40], expected, rtol=1e-5, atol=1e-5)
    pieces = len(recorded._launches)
    for n in (64, 17):  # more items, then fewer, in the same number of pieces
        before, after, expected = case(n)
        assert Prepared.reuse(recorded, sk.precondition_kernel, n, before, after, dev, 2, 8) is recorded
        recorded()
        np.testing.assert_allclose(after[0].numpy()[:n], expected, rtol=1e-5, atol=1e-5)
        assert (after[0].numpy()[n:] == 0).all()
    before, after, expected = case(9)  # one piece below twice the grain (two on a CPU with two threads)
    fresh = Prepared.reuse(recorded, sk.precondition_kernel, 9, before, after, dev, 2, 8)
    assert (fresh is recorded) == (len(fresh._launches) == pieces)
    fresh()
    np.testing.assert_allclose(after[0].numpy()[:9], expected, rtol=1e-5, atol=1e-5)
    before, after, _ = case(3)
    empty = Prepared(sk.precondition_kernel, 0, before, after, dev, 2, 8)
    empty()
    assert (after[0].numpy() == 0).all() and not empty.rebind(sk.precondition_kernel, 3, before, after, dev, 2, 8)
