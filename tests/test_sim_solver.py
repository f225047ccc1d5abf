"""The two linear solvers of a step: the fused block-Jacobi PCG and ``warp.optim.linear.cg`` on the same operator.

Both solve the same filtered backward-Euler system with the same preconditioner and stopping rule, so a step
agrees to the CG tolerance (free, with fixed and moving fixed nodes, with ground contact and with a tool pressing).
"""

import numpy as np
import pytest

import warpblob as wb
from warpblob import SimulationError
from warpblob.mesh import box_tetmesh
from warpblob.tools import Path, Probe

TOLERANCE = 1e-7


def beam(linear_solver, **kw) -> tuple:
    mesh = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (8, 2, 2))
    options = dict(young=1e6, poisson=0.3, density=1000.0, tolerance=TOLERANCE, max_iterations=500,
                   linear_solver=linear_solver)  # fmt: skip
    options.update(kw)
    return mesh, wb.Simulation(mesh, **options)


def same_step(make) -> tuple:
    """The pcg simulation after three steps, and a warp one put in its state; then one step of each."""
    a, b = make("pcg"), make("warp")
    a.step(3)
    b.positions, b.velocities, b.time = a.positions, a.velocities, a.time
    a.step()
    b.step()
    return a, b


def disagreement(a: wb.Simulation, b: wb.Simulation) -> dict:
    """How far the two steps are apart: velocities and positions relative to the step's largest velocity
    (and that velocity times dt, past a float32 rounding allowance of 1e-7), the difference of the CG iteration
    counts, the warp solve's residual."""
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
