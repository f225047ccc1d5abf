"""Solver adapters for the FEM benchmark: warpblob and its peers behind one interface.

Every adapter takes the same :class:`Problem` (nodes, tets, fixed nodes,
material, gravity, frame time step) and advances it one frame of
``Problem.frame_dt`` seconds per :meth:`frame` call, however many substeps or
iterations its setting asks for. The harness (``bench_fem.py``) times frames,
damps velocities between frames (identically for every peer that exposes its
velocities) and reads positions back.

Material mapping. Every solver is given the same small-strain material: the
Lame parameters ``mu = E / (2 (1 + nu))``, ``lambda = E nu / ((1 + nu)(1 - 2 nu))``
of the problem's Young's modulus and Poisson ratio, converted to what its
energy expects so its linearization at rest is that linear material:

* warpblob (co-rotational linear): ``young``, ``poisson`` as they are.
* Newton ``SolverVBD`` (stable Neo-Hookean without the log term,
  ``lambda_NH = lambda + mu`` applied inside the solver): Lame ``mu, lambda``.
* pbatoolkit VBD (stable Neo-Hookean ``mu/2 (I_C - 3) + lambda/2 (J - 1 - mu/lambda)^2``,
  no conversion inside): ``mu``, ``lambda + mu``.
* Newton ``SolverSemiImplicit`` (stable Neo-Hookean with the ``-mu/2 log(I_C + 1)``
  term, Smith et al. 2018 eq. 13): ``4/3 mu``, ``lambda + 5/6 mu``.
* Newton ``SolverXPBD`` (constraints ``tr(F^T F) - 3`` and ``det F - 1``, compliances
  ``1 / (V mu)`` and ``1 / (V lambda)``): Lame ``mu, lambda``. Both constraints
  are volumetric to first order in the strain (``tr(F^T F) - 3 = 2 tr(eps) + O(eps^2)``),
  so no choice of parameters gives it the linear material's shear stiffness;
  the benchmark reports the deflection it reaches.

Checked: run to rest with enough substeps (a 240-tet beam, 100 substeps),
the semi-implicit solver and both VBDs reach that mesh's static linear FEM
deflection within 0.2%.

Contact is off for every peer (the beam and the sag scenes have no ground):
Newton's particle-particle contact (``Model.particle_grid``,
``Model.particle_max_radius``) and the semi-implicit solver's
triangle-particle contact (``enable_tri_contact``, a
``tri_count * particle_count`` launch) are disabled, and the collision
pipeline is not run. Newton models are built with ``ModelBuilder.add_soft_mesh``
(mass lumped as a quarter of each tet's mass per node, unlike ``add_soft_grid``,
which gives every node a full cell's mass); fixed nodes get zero mass, which
every Newton solver treats as kinematic. ``add_soft_mesh`` also adds the
surface triangles (zero stiffness, for collision); the solvers still visit them.

Heavy packages (newton, pbatoolkit) are imported inside the adapters.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Problem:
    """One simulation set-up, shared by every solver.

    Attributes:
        name: scene label (``beam``, ``tumor``).
        nodes: (N, 3) float64 rest positions [m].
        tets: (T, 4) int32 positively oriented tets.
        fixed: (N,) bool, nodes held at their rest position.
        probe: (N,) bool, nodes whose mean z displacement is the measured deflection.
        young: Young's modulus [Pa].
        poisson: Poisson ratio.
        density: mass density [kg/m^3].
        gravity: (3,) acceleration [m/s^2].
        frame_dt: seconds of simulated time per frame.
    """

    name: str
    nodes: np.ndarray
    tets: np.ndarray
    fixed: np.ndarray
    probe: np.ndarray
    young: float
    poisson: float
    density: float
    gravity: tuple = (0.0, 0.0, -9.81)
    frame_dt: float = 1.0 / 60.0
    extra: dict = field(default_factory=dict)

    @property
    def lame(self) -> tuple[float, float]:
        """``(mu, lambda)`` [Pa]."""
        e, nu = self.young, self.poisson
        return e / (2.0 * (1.0 + nu)), e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def tet_count(self) -> int:
        return int(self.tets.shape[0])

    @property
    def node_count(self) -> int:
        return int(self.nodes.shape[0])


class Adapter:
    """One solver at one setting. Subclasses set ``name`` and implement the four methods."""

    name = ""
    #: True when the solver uses the thread count the harness asks for (else it runs on one thread)
    threaded = False

    def __init__(self, problem: Problem, **setting):
        self.problem = problem
        self.setting = setting
        self.build_s = 0.0

    def frame(self) -> None:
        """Advance one frame (``problem.frame_dt`` seconds)."""
        raise NotImplementedError

    def positions(self) -> np.ndarray:
        """(N, 3) current positions."""
        raise NotImplementedError

    def scale_velocity(self, factor: float) -> bool:
        """Multiply every velocity by ``factor``; False when the solver does not expose them."""
        return False

    def stages(self) -> dict | None:
        """Seconds by stage of the last frame and solver facts (iterations), or None."""
        return None

    def describe(self) -> dict:
        """The settings as they go into the results."""
        return dict(self.setting)


# --------------------------------------------------------------------------- Newton


def _newton_model(problem: Problem, k_mu: float, k_lambda: float):
    import warp as wp

    import newton

    t0 = time.perf_counter()
    builder = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=tuple(float(g) for g in problem.gravity))
    builder.add_soft_mesh(
        pos=(0.0, 0.0, 0.0),
        rot=wp.quat_identity(),
        scale=1.0,
        vel=(0.0, 0.0, 0.0),
        vertices=problem.nodes.tolist(),
        indices=problem.tets.ravel().tolist(),
        density=problem.density,
        k_mu=k_mu,
        k_lambda=k_lambda,
        k_damp=0.0,
        add_surface_mesh_edges=False,
    )
    for i in np.flatnonzero(problem.fixed):
        builder.particle_mass[i] = 0.0
    builder.color()
    model = builder.finalize(device="cpu")
    # no contact in these scenes: drop particle-particle contact (grid and radius)
    model.particle_grid = None
    model.particle_max_radius = 0.0
    return model, time.perf_counter() - t0


class _NewtonAdapter(Adapter):
    def _start(self, solver, model, build_s):
        self.model, self.solver = model, solver
        self.state_0, self.state_1 = model.state(), model.state()
        self.control = model.control()
        self.build_s = build_s

    def frame(self):
        sub = int(self.setting.get("substeps", 1))
        dt = self.problem.frame_dt / sub
        for _ in range(sub):
            self.state_0.clear_forces()
            self.solver.step(self.state_0, self.state_1, self.control, None, dt)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def positions(self):
        return self.state_0.particle_q.numpy().astype(np.float64)

    def scale_velocity(self, factor):
        qd = self.state_0.particle_qd
        qd.assign(qd.numpy() * np.float32(factor))
        return True


class NewtonVBD(_NewtonAdapter):
    """Newton ``SolverVBD`` (vertex block descent, implicit Euler, stable Neo-Hookean)."""

    name = "newton-vbd"

    def __init__(self, problem, *, substeps=1, iterations=10):
        super().__init__(problem, substeps=substeps, iterations=iterations)
        import newton

        mu, lam = problem.lame
        model, build_s = _newton_model(problem, mu, lam)
        solver = newton.solvers.SolverVBD(
            model, iterations=iterations, particle_enable_self_contact=False, particle_enable_tile_solve=False
        )
        self._start(solver, model, build_s)


class NewtonXPBD(_NewtonAdapter):
    """Newton ``SolverXPBD`` (extended position-based dynamics)."""

    name = "newton-xpbd"

    def __init__(self, problem, *, substeps=1, iterations=10):
        super().__init__(problem, substeps=substeps, iterations=iterations)
        import newton

        mu, lam = problem.lame
        model, build_s = _newton_model(problem, mu, lam)
        self._start(newton.solvers.SolverXPBD(model, iterations=iterations), model, build_s)


class NewtonSemiImplicit(_NewtonAdapter):
    """Newton ``SolverSemiImplicit`` (symplectic Euler: explicit forces)."""

    name = "newton-semi"

    def __init__(self, problem, *, substeps=300):
        super().__init__(problem, substeps=substeps)
        import newton

        mu, lam = problem.lame
        model, build_s = _newton_model(problem, 4.0 / 3.0 * mu, lam + 5.0 / 6.0 * mu)
        solver = newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
        self._start(solver, model, build_s)


# --------------------------------------------------------------------------- pbatoolkit


class PbatVBD(Adapter):
    """pbatoolkit's CPU VBD integrator (``pbat.sim.vbd``, TBB threads, stable Neo-Hookean)."""

    name = "pbat-vbd"
    threaded = True

    def __init__(self, problem, *, substeps=1, iterations=10, chebyshev=None):
        super().__init__(problem, substeps=substeps, iterations=iterations, chebyshev=chebyshev)
        import pbatoolkit as pbat

        vbd = pbat.pbat.sim.vbd
        mu, lam = problem.lame
        t = problem.tet_count
        t0 = time.perf_counter()
        x = np.ascontiguousarray(problem.nodes.T, dtype=np.float64)
        e = np.ascontiguousarray(problem.tets.T, dtype=np.int64)
        aext = np.repeat(np.asarray(problem.gravity, dtype=np.float64)[:, None], problem.node_count, axis=1)
        data = (
            vbd.Data()
            .with_volume_mesh(x, e)
            .with_acceleration(aext)
            .with_material(np.full(t, problem.density), np.full(t, mu), np.full(t, lam + mu))
            .with_dirichlet_vertices(np.flatnonzero(problem.fixed).astype(np.int64))
            .with_initialization_strategy(vbd.InitializationStrategy.KineticEnergyMinimum)
        )
        if chebyshev:
            data = data.with_chebyshev_acceleration(float(chebyshev))
        self.vbd = vbd.Integrator(data.construct(validate=True))
        self.build_s = time.perf_counter() - t0

    def frame(self):
        s = self.setting
        self.vbd.step(self.problem.frame_dt, int(s["iterations"]), int(s["substeps"]))

    def positions(self):
        return np.asarray(self.vbd.x, dtype=np.float64).T.copy()

    def scale_velocity(self, factor):
        self.vbd.v = np.asarray(self.vbd.v) * factor
        return True


# --------------------------------------------------------------------------- warpblob


class Warpblob(Adapter):
    """warpblob's implicit co-rotational linear FEM (``warpblob.Simulation``)."""

    name = "warpblob"
    threaded = True

    def __init__(self, problem, *, damping=(0.0, 0.0), **options):
        super().__init__(problem, damping=tuple(damping), **options)
        import warpblob as wb

        if not hasattr(wb, "Simulation"):
            raise ImportError("warpblob.Simulation is not available in this checkout")
        t0 = time.perf_counter()
        mesh = wb.TetMesh(problem.nodes.astype(np.float32), problem.tets)
        self.sim = wb.Simulation(
            mesh,
            young=problem.young,
            poisson=problem.poisson,
            density=problem.density,
            dt=problem.frame_dt,
            gravity=tuple(problem.gravity),
            damping=tuple(damping),
            fixed=np.flatnonzero(problem.fixed),
            ground=None,
            **options,
        )
        self.build_s = time.perf_counter() - t0

    def frame(self):
        self.sim.step(1)

    def positions(self):
        return np.asarray(self.sim.positions, dtype=np.float64)

    def scale_velocity(self, factor):
        self.sim.velocities = self.sim.velocities * np.float32(factor)
        return True

    def stages(self):
        return dict(self.sim.stats)

    def describe(self):
        return {**self.setting, "tolerance": self.sim.tolerance, "max_iterations": self.sim.max_iterations}


ADAPTERS = {a.name: a for a in (Warpblob, NewtonVBD, NewtonXPBD, NewtonSemiImplicit, PbatVBD)}
#: ``--peers`` group names
GROUPS = {"newton": ["newton-vbd", "newton-xpbd", "newton-semi"], "pbat": ["pbat-vbd"]}


def versions() -> dict:
    """Installed versions of every package a solver comes from (None when missing)."""
    from importlib import metadata

    out = {}
    for dist in ("warpblob", "warp-lang", "newton", "pbatoolkit", "numpy", "scipy"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return out
