"""Simulation against analytic mechanics: the static deflection of a cantilever beam under its own weight.

A 1.0 x 0.2 x 0.2 beam clamped at x = 0 (every node of that face fixed) sags under gravity; with E = 1e7 Pa
and rho = 1000 kg/m^3 the tip deflection is about 3.8% of the length, small enough for linear beam theory:
Euler-Bernoulli ``q L^4 / (8 E I)`` plus Timoshenko's shear term ``q L^2 / (2 kappa G A)`` (``q = rho g A``,
``kappa = 5/6`` for a square section, ``G = E / (2 (1 + nu))``). Linear tets are too stiff in bending (shear
locking), so the error shrinks as the mesh refines; at 40 x 8 x 8 cubes it is within 10%.
"""

import pytest

import warpblob as wb
from warpblob.mesh import box_tetmesh

E, NU, RHO, G = 1e7, 0.3, 1000.0, 9.81
LENGTH, SIDE = 1.0, 0.2


def analytic_tip_deflection() -> float:
    area, inertia = SIDE**2, SIDE**4 / 12
    q = RHO * G * area
    shear = E / (2 * (1 + NU))
    return q * LENGTH**4 / (8 * E * inertia) + q * LENGTH**2 / (2 * (5 / 6) * shear * area)


def tip_deflection(n: int) -> float:
    beam = box_tetmesh((0, 0, 0), (LENGTH, SIDE, SIDE), (5 * n, n, n))
    sim = wb.Simulation(beam, young=E, poisson=NU, density=RHO, gravity=(0, 0, -G), fixed=beam.nodes[:, 0] == 0)
    info = sim.solve_static()
    assert info["update"] < 1e-4
    tip = beam.nodes[:, 0] == LENGTH
    return float(-(sim.positions[tip, 2] - beam.nodes[tip, 2]).mean())


def test_cantilever_tip_deflection_converges_to_beam_theory():
    expected = analytic_tip_deflection()
    assert expected / LENGTH == pytest.approx(0.038, abs=0.001)
    errors = [tip_deflection(n) / expected - 1 for n in (2, 4, 8)]
    # too stiff (locking), less so on every refinement, within 10% on the finest mesh
    assert all(e < 0 for e in errors)
    assert abs(errors[0]) > abs(errors[1]) > abs(errors[2])
    assert abs(errors[2]) < 0.10
