"""The soft-body simulation: implicit co-rotational linear FEM on tetrahedra (SPEC section 5.1).

Müller & Gross 2004 ("Interactive virtual materials", GI 2004) give the
method: per tet a rotation from the deformation gradient, the linear-elastic
stiffness rotated by it, lumped masses, Rayleigh damping and backward Euler
solved by conjugate gradients (:mod:`warpblob.sim._solver` says what is kept
and lagged). Rotations come from a polar decomposition by SVD with the
reflection fixed (Irving et al. 2004, :func:`warpblob.sim._kernels.polar_rotation`),
so inverted and flat tets push back. Fixed nodes use the projection filter
of Baraff & Witkin 1998. Units are any consistent set: with positions in
metres, use pascals, kilograms per cubic metre and metres per second squared.
Results are bit-identical for any CPU thread count: per-tet results are
gathered per node in a fixed order and CG's dot products are summed over
fixed node blocks (:mod:`warpblob.sim._kernels`), never with atomics.

Ground contact (``ground=``): the plane ``z = height`` (z is up), inside the
implicit solve as velocity constraints (Baraff & Witkin's filter). Each
step predicts every free node's velocity from its own force; a node whose
predicted position lies below the plane is in contact: its normal velocity
is prescribed to land it on the plane (lifting it if it was below), which
removes the normal velocity ``dv_n`` (inelastic contact). Coulomb friction
with coefficient ``friction``: a contact whose predicted tangential speed is
at most ``friction * dv_n`` sticks (its tangential velocity is held at 0),
else it slides with the impulse ``friction * m * dv_n`` against its
predicted tangential motion. Contacts separate when the prediction leaves
the plane.

Tools (:meth:`Simulation.add_tool`): rigid tools on paths press the tissue
through the model's field carried by the deformation, a penalty inside the
implicit solve (:mod:`warpblob.sim._contact`, after the thesis' chapter 6).

Rigid materials (``rigid={material_id, ...}``): the nodes of rigid tets move
as one rigid body per connected piece, anchored (held in place) when the
piece holds a fixed node or an anchor, else free and integrated with the
soft tissue in the same implicit solve, in reduced coordinates
(:mod:`warpblob.sim._rigid`).
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from .._device import resolve_device
from .._errors import SimulationError, ToolError
from .._parallel import check_threads
from .._stages import column_bounds, device_empty, room, set_rows
from ..mesh import TetMesh, TetStructure
from . import _kernels as k
from ._coarse import node_pieces
from ._contact import Contact, ToolContact
from ._elements import Elements, material_values
from ._embed import Embedding, embed, interpolate
from ._rigid import RigidBodies
from ._solver import (
    LINEAR_SOLVERS,
    NODE_GRAIN,
    PRECONDITIONERS,
    ElementState,
    ImplicitSolver,
    block_count,
    split_launch,
)

__all__ = ["Simulation"]

#: a step diverged when its kinetic plus elastic energy exceeds this many times its budget (see Simulation.step)
BLOWUP = 10.0
_STAGES = ("contact", "assembly", "cg", "update", "elements", "check")


def _vector(name: str, value, length: int = 3) -> tuple:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SimulationError(f"{name} must be {length} numbers, got {value!r}") from None
    if arr.shape != (length,) or not np.isfinite(arr).all():
        raise SimulationError(f"{name} must be {length} finite numbers, got {value!r}")
    return tuple(float(a) for a in arr)


def _number(name: str, value, *, low: float | None = None, strict: bool = True) -> float:
    number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    if not number or not np.isfinite(value):
        raise SimulationError(f"{name} must be a finite number, got {value!r}")
    if low is not None and (value <= low if strict else value < low):
        raise SimulationError(f"{name} must be {'>' if strict else '>='} {low}, got {value!r}")
    return float(value)


class Simulation:
    """Implicit co-rotational FEM of a tet mesh, every per-element and per-node loop a Warp kernel.

    Rigid tools on paths press it through the model's field
    (:meth:`add_tool`, :meth:`contact_force`, :meth:`contact_points`).

    Args:
        volume: a :class:`~warpblob.mesh.TetMesh` (rest shape = its nodes) or a
            :class:`~warpblob.mesh.TetStructure` (rest and current positions
            from its nodes; node and tet indices are its slots, dead ones
            included and inert).
        young: Young's modulus E (> 0, e.g. Pa): a number, a (T,) array or a
            dict from material id (``volume.material``) to value.
        poisson: Poisson's ratio nu in (-1, 0.5), likewise.
        density: mass density (> 0, e.g. kg/m^3), likewise.
        dt: time step (s).
        gravity: acceleration (3,) (e.g. m/s^2).
        damping: Rayleigh coefficients ``(alpha, beta)`` >= 0, ``C = alpha M + beta K'``.
        fixed: Dirichlet nodes, a (N,) bool mask or node indices; they keep
            their positions until moved by :attr:`fixed_positions`.
        ground: None, a height, or ``(height, friction)``: the plane
            ``z = height`` with Coulomb friction coefficient ``friction``
            (default 0.5); see the module docstring for the contact model.
        tolerance: CG tolerance, relative to the right-hand side's norm.
        max_iterations: CG iteration cap per step.
        linear_solver: ``"pcg"`` (default): the fused preconditioned CG of
            :mod:`warpblob.sim._solver`; ``"warp"``:
            ``warp.optim.linear.cg`` on a ``LinearOperator`` of the same
            product, with the same preconditioner and tolerance
            rule: the same step to CG tolerance, for comparison (per CG
            iteration at 10K tets on one CPU thread, Warp 1.19: 12.3 ms
            against 0.23 ms; :mod:`warpblob.sim._solver` says why).
        preconditioner: ``"two_level"`` (default): block-Jacobi plus a
            coarse correction on aggregates of about 64 nodes carrying their
            rigid modes (:mod:`warpblob.sim._coarse`; its coarse matrix is
            lagged, rebuilt every few steps); ``"block_jacobi"``: the 3 x 3
            node blocks alone. Measured on these 2 CPU cores at 10K tets
            (``benchmarks/bench_fem.py``, one thread): a stiff beam (E = 1e7
            Pa) takes 30 iterations per step instead of the cap of 200 (it
            needs 340-420), 13.7 ms instead of 52.7 ms (plus 0.3 ms for the
            rebuild every 10 steps); a soft tumor (E = 1e6 Pa) 26 instead of
            46, 12.0 ms instead of 16.8 ms. Both give the same step to the
            CG tolerance.
        device: Warp device (default: Warp's default device).
        threads: CPU threads (default: :func:`warpblob.thread_count` when the
            simulation is built); results are bit-identical for any count.
        model: the model (:class:`~warpblob.tree.Node`) the volume was made
            from, for tool contact through its field and :meth:`field` (a
            :class:`~warpblob.mesh.TetMesh` does not keep it); or give it to
            :meth:`add_tool`.
        rigid: a set of material ids (``volume.material``) whose tets are
            rigid (:attr:`rigid`): the nodes of their tets (nodes shared with
            soft tets included) move as one rigid body per connected piece.
            A piece holding a fixed node or an anchor stays where it is (its
            other nodes are held in place even if :attr:`fixed_positions`
            moves its fixed ones); any other piece is a free rigid body under gravity, the ground, the
            external forces and the soft tets attached to it, integrated in
            one implicit solve with them (:mod:`warpblob.sim._rigid`).
            Rigid tets give mass but no elastic force (their ``young`` and
            ``poisson`` are still validated, and used again if the material
            is made soft).
        anchors: nodes that anchor the rigid piece holding them, a (N,) bool
            mask or node indices (:attr:`anchors`); unlike fixed nodes they
            are not copied by cuts: after a cut, a piece that holds none of
            them (nor a fixed node) is free. Anchor a skull at nodes away
            from where it will be drilled.

    Attributes:
        time: simulated time (s), advanced by :meth:`step`.
        dt, gravity, damping, ground, tolerance, max_iterations, linear_solver, preconditioner: as given.
        elements: the :class:`~warpblob.sim.Elements` (flat per-tet and per-node data).
        stats: the last step's ``seconds`` per stage (``contact``: the tools;
            ``assembly``: right-hand side and preconditioner; ``cg``;
            ``update``: positions and ground contacts; ``elements``: the
            rotation and force pass; ``check``: divergence), their
            ``seconds_total``, ``cg_iterations`` (last and
            ``cg_iterations_total``), the CG ``residual`` and
            ``relative_residual``, ``steps``, ``tet_count``, ``node_count``,
            ``device``, ``preconditioner``, ``coarse_size`` (coarse unknowns, 6 per
            aggregate; 0 for block-Jacobi), ``coarse_setup_seconds`` (aggregation,
            when the simulation or :meth:`rebuild` built it), ``coarse_refreshes``
            and ``coarse_refresh_seconds`` (the last rebuild of the coarse
            matrix, counted in ``assembly``); with tools, ``contact``: the last step's ``seconds``
            of tool contact by stage (``locate``: tool poses, boxes, BVH refit,
            location and the nearest-node search; ``field``: the field evaluation; ``spread``:
            forces, the sort by node and the k-ring spread), their
            ``seconds_total``, ``samples`` and ``penetrating`` (sample counts);
            ``rigid``: the rigid pieces, ``{"pieces", "anchored", "free",
            "tets", "nodes", "free_nodes"}`` (counts; the free bodies' poses
            are :attr:`rigid_bodies`).

    Raises:
        SimulationError: a bad parameter, a NaN in the mesh or the inputs, a
            fixed mask of the wrong length or a bad node index, an inverted or
            zero-volume rest tet, a ``rigid`` that is not a set of material
            ids of the mesh; the message names the value and the tet or node.

    Example:
        >>> import numpy as np, warpblob as wb
        >>> beam = wb.mesh.box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (5, 1, 1))
        >>> sim = wb.Simulation(beam, young=1e6, poisson=0.3, density=1000.0, fixed=beam.nodes[:, 0] == 0.0)
        >>> sim.step(10)
        >>> bool(sim.positions[:, 2].min() < 0.0), round(sim.time, 4)
        (True, 0.1667)
    """

    def __init__(
        self,
        volume,
        *,
        young,
        poisson,
        density,
        dt: float = 1.0 / 60.0,
        gravity=(0.0, 0.0, -9.81),
        damping=(0.0, 0.0),
        fixed=None,
        ground=None,
        tolerance: float = 1e-4,
        max_iterations: int = 200,
        linear_solver: str = "pcg",
        preconditioner: str = "two_level",
        device=None,
        threads: int | None = None,
        model=None,
        rigid=None,
        anchors=None,
    ):
        self.threads = check_threads(threads)
        if linear_solver not in LINEAR_SOLVERS:
            raise SimulationError(f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {linear_solver!r}")
        self.linear_solver = linear_solver
        if preconditioner not in PRECONDITIONERS:
            raise SimulationError(f"preconditioner must be one of {', '.join(PRECONDITIONERS)}, got {preconditioner!r}")
        self.preconditioner = preconditioner
        self.device = resolve_device(device)
        if isinstance(volume, TetStructure):
            self._structure = volume
            rest = np.asarray(volume.node_rest, dtype=np.float64)
            positions = np.asarray(volume.node_position, dtype=np.float64)
            tets = np.asarray(volume.cell_nodes)
            alive = np.asarray(volume.cell_alive, dtype=bool)
            material = np.asarray(volume.cell_material, dtype=np.int32)
        elif isinstance(volume, TetMesh):
            self._structure = None
            rest = positions = np.asarray(volume.nodes, dtype=np.float64)
            tets = volume.tets
            alive = np.ones(volume.tet_count, dtype=bool)
            material = volume.material if volume.material is not None else np.zeros(volume.tet_count, dtype=np.int32)
        else:
            raise SimulationError(f"volume must be a TetMesh or a TetStructure, got {type(volume).__name__}")
        if len(tets) == 0 or not alive.any():
            raise SimulationError("volume has no tets")
        for name, arr in (("rest position", rest), ("position", positions)):
            bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
            if bad.size:
                raise SimulationError(f"node {bad[0]} has {name} {arr[bad[0]].tolist()}, which is not finite")
        material = np.asarray(material)
        self._material = np.asarray(material, dtype=np.int32).copy()
        self._specs = {"young": young, "poisson": poisson, "density": density}
        E = material_values("young", young, material, positive=True)
        nu = material_values("poisson", poisson, material, bounds=(-1.0, 0.5))
        rho = material_values("density", density, material, positive=True)
        self.dt = _number("dt", dt, low=0.0)
        self.gravity = _vector("gravity", gravity)
        d = _vector("damping", damping, 2)
        if min(d) < 0:
            raise SimulationError(f"damping coefficients must be >= 0, got {damping!r}")
        self.damping = d
        self.ground = self._ground(ground)
        self.tolerance = _number("tolerance", tolerance, low=0.0)
        if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) or max_iterations < 1:
            raise SimulationError(f"max_iterations must be a positive integer, got {max_iterations!r}")
        self.max_iterations = int(max_iterations)
        self.elements = Elements(rest, tets, alive, E, nu, rho, device=self.device, threads=self.threads)
        # what _allocate keeps between rebuilds: the node buffers' bases with room, the masses and their box
        self._kept: dict = {}
        self._mass: np.ndarray | None = None
        self._bounds: tuple | None = None
        self._allocate(positions, np.zeros_like(positions))
        self._rigid_ids = self._check_rigid(rigid)
        self._anchor_mask = self._node_mask("anchors", anchors)
        self._rigid_fixed = np.zeros(self.node_count, dtype=bool)
        self._bodies: RigidBodies | None = None
        self._rigid_stats = {"pieces": 0, "anchored": 0, "free": 0, "tets": 0, "nodes": 0, "free_nodes": 0}
        self.fixed = fixed
        self.time = 0.0
        self._embedding: Embedding | None = None
        self.model = model
        self._contact: Contact | None = None
        self._cutters: list = []
        self.stats: dict = {
            "steps": 0,
            "seconds": dict.fromkeys(_STAGES, 0.0),
            "seconds_total": dict.fromkeys(_STAGES, 0.0),
            "cg_iterations": 0,
            "cg_iterations_total": 0,
            "residual": 0.0,
            "relative_residual": 0.0,
            "tet_count": self.tet_count,
            "node_count": self.node_count,
            "device": str(self.device),
            "rigid": dict(self._rigid_stats),
            **self._coarse_stats(),
        }

    # -- set-up ----------------------------------------------------------------

    @staticmethod
    def _ground(ground):
        if ground is None:
            return None
        if isinstance(ground, (tuple, list)):
            if len(ground) != 2:
                raise SimulationError(f"ground must be a height or (height, friction), got {ground!r}")
            height, friction = ground
        else:
            height, friction = ground, 0.5
        return _number("ground height", height), _number("ground friction", friction, low=0.0, strict=False)

    def _allocate(self, positions: np.ndarray, velocities: np.ndarray, sources: np.ndarray | None = None, *,
                  kept: int = 0) -> None:  # fmt: skip
        """Buffers, element states and the solver for the current elements (``sources``: the new nodes'
        sources after a cut's edit, for the coarse space to be carried over, :meth:`rebuild`).

        ``kept``: a rebuild's old node count, whose positions, velocities, targets and external forces stay
        in place (``positions`` and ``velocities`` then give the added nodes' rows only: the added nodes'
        targets are their positions, their external forces zero); 0 sets every row from the arrays.
        """
        dev, e = self.device, self.elements
        self._carry = None  # (state, tets, changed tets): what the next _refresh may carry over (rebuild)
        N, T = e.node_count, e.tet_count
        # the per-node buffers live in kept bases with room (a rebuild after a cut reuses them: fresh pages
        # cost more than the writes); double buffers: a step writes the other one, so a failed step leaves
        # the state as it was. A rebuild's current buffers become the first ones, their rows in place.
        cur = getattr(self, "_cur", 0)
        old = {}
        if kept:
            old = {"x": self._x[cur], "v": self._v[cur], "target": self._target, "external": self._external}
        if kept and cur == 1:
            bases = self._kept
            for name in ("x", "v"):
                bases[f"{name}0"], bases[f"{name}1"] = bases[f"{name}1"], bases[f"{name}0"]
        before = dict(self._kept)  # (a base made anew has no rows to keep)
        self._x = [self._node_buffer(f"x{i}", N, wp.vec3, old.get("x") if i == 0 else None, kept) for i in (0, 1)]
        self._v = [self._node_buffer(f"v{i}", N, wp.vec3, old.get("v") if i == 0 else None, kept) for i in (0, 1)]
        self._target = self._node_buffer("target", N, wp.vec3, old.get("target"), kept)
        self._external = self._node_buffer("external", N, wp.vec3, old.get("external"), kept)
        added = np.asarray(positions, dtype=np.float32)
        if N > kept:
            for buffer, rows in ((self._x[0], added), (self._v[0], np.asarray(velocities, dtype=np.float32)),
                                 (self._target, added), (self._external, 0.0)):  # fmt: skip
                set_rows(buffer, kept, rows)
        # (the other buffers, and ``moved``, hold what the next step writes at every node before reading it:
        # a rebuild sets the added rows only)
        for name, buffer in (("x1", self._x[1]), ("v1", self._v[1])):
            set_rows(buffer, kept if self._kept[name] is before.get(name) else 0, 0.0)
        # a rebuild's element states keep their buffers: the current one becomes state 0 (its values for the
        # tets that stay are then in place for the carried pass, see _refresh)
        states = getattr(self, "_states", None)
        reuse = (None, None) if states is None else (states[cur], states[1 - cur])
        self._cur = 0
        self._moved = self._node_buffer("moved", N, wp.vec3)
        self._flags = self._node_buffer("flags", N, wp.uint8)
        set_rows(self._moved, kept if self._kept["moved"] is before.get("moved") else 0, 0.0)
        self._flags.zero_()
        self._states = [ElementState(T, N, dev, reuse[0]), ElementState(T, N, dev, reuse[1])]
        # the structure's piece count (through faces, so through nodes too), where it knows it: one piece
        # spares the coarse space its count of the pieces, and a cut that leaves the count lets it carry over
        known = None if self._structure is None else self._structure._known_pieces()
        self._solver = ImplicitSolver(e, self._flags, self._states, self.threads, self.linear_solver,
                                      self.preconditioner, known, getattr(self, "_solver", None),
                                      sources)  # fmt: skip
        blocks = block_count(N, dev)
        self._check_bad = device_empty(blocks, wp.int32, dev, zero=True)
        self._check_sums = wp.zeros((len(k.CHECK_ROWS), blocks), dtype=wp.float64, device=dev)
        old_mass = self._mass if kept else None
        self._mass = e.mass.numpy().astype(np.float64)
        # |m|_2: the right-hand side's norm per unit velocity, the scale of CG's absolute tolerance
        self._momentum = float(np.sqrt(np.sum(self._mass**2)))
        if not (self._mass > 0).any():
            raise SimulationError("volume has no mass: every live tet has zero volume")
        self._bounds = self._mass_bounds(old_mass, kept)
        self._size = float(np.linalg.norm(self._bounds[1] - self._bounds[0])) or 1.0
        self._fixed_mask = np.zeros(N, dtype=bool)
        self._moving = False

    def _mass_bounds(self, old_mass: np.ndarray | None, kept: int) -> tuple:
        """The rest box ``(low, high)`` (3,) of the nodes with mass. After a local edit (``old_mass``: the
        masses before it, its ``kept`` old nodes) only the touched nodes' masses changed, so the box before it
        holds unless a node that lost its mass lay on it; it grows to the nodes that gained mass. Else a pass
        over every node."""
        e, prev = self.elements, self._bounds
        touched = e.touched_nodes
        if old_mass is not None and prev is not None and touched is not None and len(old_mass) == kept:
            t = touched.astype(np.int64)
            had = np.zeros(len(t), dtype=bool)
            old = t < kept
            had[old] = old_mass[t[old]] > 0
            has = self._mass[t] > 0
            lost, gained = e.rest_host[t[had & ~has]], e.rest_host[t[has & ~had]]
            lo, hi = prev
            if not (np.any(lost == lo) or np.any(lost == hi)):
                if len(gained):
                    lo, hi = np.minimum(lo, gained.min(axis=0)), np.maximum(hi, gained.max(axis=0))
                return lo, hi
        # (np.compress: a boolean row selection takes numpy several times as long, 0.5 ms at 20K nodes)
        return column_bounds(np.compress(self._mass > 0, e.rest_host, axis=0))

    def _node_buffer(self, name: str, n: int, dtype, old: wp.array | None = None, kept: int = 0) -> wp.array:
        """(n,) buffer ``name`` (not initialized) in a base kept between rebuilds (:func:`room`); with ``old``,
        its first ``kept`` rows hold ``old``'s (copied where the base had to be made anew)."""
        bases = self._kept
        base = bases.get(name)
        bases[name], view = room(base, n, dtype, self.device)
        if kept and old is not None and bases[name] is not base:
            wp.copy(view, old, count=kept)
        return view

    def _coarse_stats(self) -> dict:
        c = self._solver.coarse
        return {
            "preconditioner": self.preconditioner,
            "coarse_size": 0 if c is None else c.size,
            "coarse_setup_seconds": 0.0 if c is None else c.setup_seconds,
            "coarse_refreshes": 0 if c is None else c.refreshes,
            "coarse_refresh_seconds": 0.0 if c is None else c.refresh_seconds,
        }

    def _update_flags(self, keep_coarse: bool = False) -> None:
        """Set the node flags and refresh the state. ``keep_coarse``: a rebuild whose solver carried its
        coarse factor over (a cut's, :meth:`CoarseSpace.carry_modes`) keeps it where every old node keeps
        its flag or leaves the system (inactive: no live tet holds it any more, as a scalpel's last crack
        front once the next frame cut past it); otherwise the coarse matrix is rebuilt at the next step."""
        rigid_free = self._rigid_pieces()
        fixed = self._fixed_mask | self._rigid_fixed
        flags = np.where(fixed, k.FIXED, np.where(rigid_free, k.RIGID, np.where(self._mass > 0, k.FREE, k.INACTIVE)))
        set_rows(self._flags, 0, flags)
        self._solver.set_rigid(self._bodies)
        before = getattr(self, "_flags_host", None)
        same = keep_coarse and before is not None and len(before) <= len(flags)
        if same:
            old = flags[: len(before)]
            same = not np.any((old != before) & (old != k.INACTIVE))
        if not same:
            self._solver.invalidate()
        self._flags_host = flags
        self._refresh()

    # -- rigid materials -------------------------------------------------------

    def _check_rigid(self, value) -> frozenset:
        """The validated set of rigid material ids (SimulationError naming the value)."""
        if value is None:
            return frozenset()
        if not isinstance(value, (set, frozenset, list, tuple)):
            raise SimulationError(f"rigid must be a set of material ids (ints), got {value!r}")
        ids = set()
        for m in value:
            if isinstance(m, (bool, np.bool_)) or not isinstance(m, (int, np.integer)):
                raise SimulationError(f"rigid: material id {m!r} is not an int (rigid={value!r})")
            ids.add(int(m))
        present = set(np.unique(self._material).tolist())
        unknown = sorted(ids - present)
        if unknown:
            raise SimulationError(f"rigid: material {unknown[0]} is not in the mesh (rigid={value!r}; the mesh has "
                                  f"materials {sorted(present)})")  # fmt: skip
        return frozenset(ids)

    def _node_mask(self, name: str, value) -> np.ndarray:
        """A (N,) bool mask from a mask, node indices or None (SimulationError naming the value)."""
        N = self.node_count
        mask = np.zeros(N, dtype=bool)
        if value is None:
            return mask
        arr = np.asarray(value)
        if arr.dtype == bool:
            if arr.shape != (N,):
                raise SimulationError(f"{name}: a mask must have shape ({N},) (one flag per node), got {arr.shape}")
            return arr.copy()
        if arr.ndim != 1 or (arr.size and not np.issubdtype(arr.dtype, np.integer)):
            raise SimulationError(f"{name} must be a ({N},) bool mask or 1-D node indices, got {value!r}")
        bad = np.flatnonzero((arr < 0) | (arr >= N))
        if bad.size:
            raise SimulationError(f"{name}: node index {arr[bad[0]]} is outside [0, {N})")
        mask[arr] = True
        return mask

    @property
    def rigid(self) -> frozenset:
        """The rigid material ids (a frozenset of ints; empty: all soft). Set a set of ids (or None).

        The rigid pieces are recomputed whenever this, :attr:`fixed`, :attr:`anchors`,
        the state or the topology (:meth:`rebuild`) changes; a free piece starts
        with the rigid velocity of its nodes' linear and angular momentum.

        Example:
            >>> import numpy as np, warpblob as wb
            >>> from warpblob.mesh import TetMesh, box_tetmesh
            >>> m = box_tetmesh((0, 0, 0), (0.1, 0.1, 0.1), (1, 1, 1))
            >>> sim = wb.Simulation(TetMesh(m.nodes, m.tets, material=np.ones(6, np.int32)), young=1e5,
            ...                     poisson=0.3, density=1000.0, rigid={1})
            >>> sim.step(3)
            >>> round(float(sim.rigid_bodies["velocity"][0, 2]), 4)  # backward Euler: -3 h g, m/s
            -0.4905
            >>> sim.rigid, sim.stats["rigid"]["free"]
            (frozenset({1}), 1)
        """
        return self._rigid_ids

    @rigid.setter
    def rigid(self, value) -> None:
        self._rigid_ids = self._check_rigid(value)
        self._update_flags()

    @property
    def anchors(self) -> np.ndarray:
        """Sorted (A,) int indices of the anchor nodes. Set a (N,) bool mask, node indices or None."""
        return np.flatnonzero(self._anchor_mask)

    @anchors.setter
    def anchors(self, value) -> None:
        self._anchor_mask = self._node_mask("anchors", value)
        self._update_flags()

    @property
    def rigid_bodies(self) -> dict:
        """The free rigid bodies now: ``centre`` (F, 3) centres of mass, ``orientation`` (F, 4) unit
        quaternions (x, y, z, w) from the pose when the piece was formed, ``velocity`` and
        ``angular_velocity`` (F, 3) of the last step, ``nodes`` (list of F node index arrays)."""
        if self._bodies is None:
            z = np.zeros((0, 3), dtype=np.float32)
            return {"centre": z, "orientation": np.zeros((0, 4), np.float32), "velocity": z,
                    "angular_velocity": z, "nodes": []}  # fmt: skip
        return self._bodies.state()

    def _rigid_pieces(self) -> np.ndarray:
        """Recompute the rigid pieces: the rigid tets' Lamé parameters, the anchored nodes (held where they
        are), the free bodies (:class:`~warpblob.sim._rigid.RigidBodies`, their nodes given the rigid
        velocity of their momentum). Returns the (N,) mask of the free bodies' nodes."""
        e, N = self.elements, self.node_count
        # (no rigid material, and no rigid tet marked the last time: a rebuild marks none, so none is; the
        # passes over every tet below are skipped)
        none = not self._rigid_ids and getattr(self, "_rigid_stats", {}).get("tets") == 0
        rigid_tets = np.zeros(e.tet_count, dtype=bool)
        if self._rigid_ids:
            rigid_tets = e.alive_host & np.isin(self._material, np.fromiter(self._rigid_ids, dtype=np.int64))
        if not none and not np.array_equal(rigid_tets, e.rigid_host):
            e.set_rigid(rigid_tets)
        self._bodies = None
        self._rigid_fixed = np.zeros(N, dtype=bool)
        free = np.zeros(N, dtype=bool)
        stats = {"pieces": 0, "anchored": 0, "free": 0, "tets": 0 if none else int(rigid_tets.sum()), "nodes": 0,
                 "free_nodes": 0}  # fmt: skip
        if not none and rigid_tets.any():
            label = node_pieces(e.tets_host[rigid_tets], N)
            nodes = label >= 0
            count = int(label.max()) + 1
            anchored = np.zeros(count, dtype=bool)
            anchored[label[nodes & (self._fixed_mask | self._anchor_mask)]] = True
            self._rigid_fixed = nodes & anchored[np.maximum(label, 0)]
            free = nodes & ~self._rigid_fixed
            x = self._x[self._cur].numpy()
            held = self._rigid_fixed & ~self._fixed_mask
            if held.any():
                # anchored nodes are held where they are: their targets are their positions
                target = self._target.numpy().copy()
                target[held] = x[held]
                self._target.assign(target)
            if free.any():
                ids = np.flatnonzero(free)
                order = ids[np.argsort(label[ids], kind="stable")]
                cuts = np.flatnonzero(np.diff(label[order])) + 1
                v = self._v[self._cur].numpy().copy()
                self._bodies = RigidBodies(np.split(order, cuts), x, v, self._mass, self.device)
                v[self._bodies.nodes_host] = self._bodies.rigid_velocities
                self._v[self._cur].assign(v.astype(np.float32))
            stats.update(pieces=count, anchored=int(anchored.sum()), free=count - int(anchored.sum()),
                         nodes=int(nodes.sum()), free_nodes=int(free.sum()))  # fmt: skip
        self._rigid_stats = stats
        if hasattr(self, "stats"):
            self.stats["rigid"] = dict(stats)
        return free

    def _refresh(self) -> None:
        """Recompute the element pass at the current positions (after the caller changed the state); after a
        topology change (:meth:`rebuild`) only for the changed tets, the others' carried over."""
        x, v = self._x[self._cur], self._v[self._cur]
        carry, self._carry = self._carry, None
        prior, self._prior = getattr(self, "_prior", None), None
        if carry is None or prior is None or self._bodies is not None:
            self._state.compute(self.elements, x, self.threads, carry=carry)
            _, sums = self._reduce(x, x, v, self._state)
            self._budget = sums["kinetic"] + sums["elastic"]
            return
        # a rebuild's budget (kinetic + elastic energy) follows the change: the energies of the changed tets
        # and the kinetic energies of the nodes whose masses changed, old ones out, new ones in (float64 sums
        # of a few hundred terms, not a pass over every node and tet; the same to rounding)
        budget, mass = prior
        state, count, ids, nodes = carry
        T = self.elements.tet_count
        old = np.unique(ids[(ids >= 0) & (ids < count)])
        before = state.energy.numpy()[old].astype(np.float64).sum()
        self._state.compute(self.elements, x, self.threads, carry=carry)
        after = self._state.energy.numpy()[np.concatenate([old, np.arange(count, T)])].astype(np.float64).sum()
        nodes = np.asarray(nodes, dtype=np.int64)
        was = np.zeros(len(nodes))  # the nodes' masses before (0 for an added node)
        inside = nodes < len(mass)
        was[inside] = mass[nodes[inside]]
        vn = v.numpy()[nodes].astype(np.float64)
        speed = np.einsum("ij,ij->i", vn, vn)  # |v|^2 per node
        self._budget = budget + float(after - before) + 0.5 * float((self._mass[nodes] - was) @ speed)

    @property
    def _state(self) -> ElementState:
        return self._states[self._cur]

    # -- sizes and state -------------------------------------------------------

    @property
    def node_count(self) -> int:
        return self.elements.node_count

    @property
    def tet_count(self) -> int:
        return self.elements.tet_count

    @property
    def rest_positions(self) -> np.ndarray:
        """(N, 3) float32 rest positions (a copy)."""
        return self.elements.rest_host.copy()

    def _nodal(self, name: str, value, rows: int | None = None) -> np.ndarray:
        rows = self.node_count if rows is None else rows
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise SimulationError(
                f"{name} must be a ({rows}, 3) array of numbers, got {type(value).__name__}"
            ) from None
        if arr.shape != (rows, 3):
            raise SimulationError(f"{name} must have shape ({rows}, 3), got {arr.shape}")
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if bad.size:
            raise SimulationError(f"{name}[{bad[0]}] = {arr[bad[0]].tolist()} is not finite")
        return arr.astype(np.float32)

    @property
    def positions(self) -> np.ndarray:
        """(N, 3) float32 current node positions (a copy). Setting them also moves the fixed nodes' targets there."""
        return self._x[self._cur].numpy().copy()

    @positions.setter
    def positions(self, value) -> None:
        arr = self._nodal("positions", value)
        self._x[self._cur].assign(arr)
        target = self._target.numpy().copy()
        target[self._fixed_mask] = arr[self._fixed_mask]
        self._target.assign(target)
        self._moving = False
        # the body may have moved far (a teleport, a turn): the coarse modes follow at the next step; the
        # rigid bodies are formed again at the new positions
        self._update_flags()

    @property
    def velocities(self) -> np.ndarray:
        """(N, 3) float32 current node velocities (a copy); settable (the nodes of a free rigid body then take
        the rigid velocity with the same linear and angular momentum)."""
        return self._v[self._cur].numpy().copy()

    @velocities.setter
    def velocities(self, value) -> None:
        self._v[self._cur].assign(self._nodal("velocities", value))
        if self._bodies is not None:
            self._update_flags()  # the free bodies take the rigid velocity of the new momentum
        else:
            self._refresh()

    @property
    def external_forces(self) -> np.ndarray:
        """(N, 3) float32 extra nodal forces applied every step (e.g. N; zero by default); settable."""
        return self._external.numpy().copy()

    @external_forces.setter
    def external_forces(self, value) -> None:
        self._external.assign(self._nodal("external_forces", value))

    @property
    def masses(self) -> np.ndarray:
        """(N,) float64 lumped node masses (a quarter of ``density * volume`` of each incident tet)."""
        return self._mass.copy()

    @property
    def fixed(self) -> np.ndarray:
        """Sorted (F,) int indices of the fixed nodes. Set a (N,) bool mask, node indices or None."""
        return np.flatnonzero(self._fixed_mask)

    @fixed.setter
    def fixed(self, value) -> None:
        mask = self._node_mask("fixed", value)
        newly = mask & ~self._fixed_mask
        if newly.any():
            target = self._target.numpy().copy()
            target[newly] = self._x[self._cur].numpy()[newly]
            self._target.assign(target)
        self._fixed_mask = mask
        self._update_flags()

    @property
    def fixed_positions(self) -> np.ndarray:
        """(F, 3) float32 targets of the fixed nodes, in :attr:`fixed` order.

        Set new targets to move the fixed nodes: the next step gives each the
        velocity ``(target - x) / dt``, which lands it on its target.
        """
        return self._target.numpy()[self._fixed_mask].copy()

    @fixed_positions.setter
    def fixed_positions(self, value) -> None:
        arr = self._nodal("fixed_positions", value, int(self._fixed_mask.sum()))
        target = self._target.numpy().copy()
        target[self._fixed_mask] = arr
        self._target.assign(target)
        self._moving = bool(np.any(arr != self._x[self._cur].numpy()[self._fixed_mask]))

    # -- measures --------------------------------------------------------------

    def volume(self) -> float:
        """Current total volume (model units cubed): the sum of the signed volumes of the deformed tets."""
        return float(self._state.volume.numpy().astype(np.float64).sum())

    def energy(self) -> dict:
        """Kinetic, elastic (co-rotated), gravitational (``-sum m g . x``) and total energy (e.g. J)."""
        v = self._v[self._cur].numpy().astype(np.float64)
        x = self._x[self._cur].numpy().astype(np.float64)
        kinetic = 0.5 * float(np.dot(self._mass, (v**2).sum(axis=1)))
        elastic = float(self._state.energy.numpy().astype(np.float64).sum())
        gravitational = -float(np.dot(self._mass, x @ np.asarray(self.gravity)))
        return {
            "kinetic": kinetic,
            "elastic": elastic,
            "gravitational": gravitational,
            "total": kinetic + elastic + gravitational,
        }

    def elastic_forces(self) -> np.ndarray:
        """(N, 3) float32 elastic node forces ``-R K (R^T x - X)`` at the current positions."""
        return self._state.node_force.numpy().copy()

    def multiply(self, p, *, stiffness: float = 1.0, mass: float = 0.0) -> np.ndarray:
        """``(mass M + stiffness K') p`` for (N, 3) ``p``, with ``K'`` at the current rotations.

        The step's system matrix is ``mass = 1 + dt alpha``, ``stiffness =
        dt beta + dt^2``; fixed rows are identity rows (ground contacts are
        left out: they depend on the step). For tests and tools.
        """
        arr = wp.array(self._nodal("p", p), dtype=wp.vec3, device=self.device)
        out = wp.zeros_like(arr)
        free = (self._flags.numpy() == k.FREE).astype(np.float32)
        self._solver.axes.assign(np.repeat(free[:, None], 3, axis=1))
        self._solver.multiply(self._state, arr, out, float(mass), float(stiffness), rigid=False)
        return out.numpy().copy()

    # -- time stepping ---------------------------------------------------------

    def _sync(self) -> float:
        if self.device.is_cuda:
            wp.synchronize_device(self.device)
        return time.perf_counter()

    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of ``dt``.

        Each step: move the tools to their poses at the end of the step and
        compute their contact forces and penalty stiffness (``contact``, when
        a tool's box meets the tissue's; :meth:`add_tool`); assemble the
        right-hand side and the preconditioner (block-Jacobi, and when due the
        coarse matrix of the two-level one) from the element pass at the
        current positions (``assembly``); solve the backward-Euler system by CG (``cg``);
        move the nodes, with ground contact (``update``); run the element
        pass at the new positions, which the next step reuses (``elements``);
        and check for divergence (``check``: one reduction kernel, one host
        sync of a few scalars). :attr:`stats`
        gets each stage's seconds, the CG iterations and residual.

        A step diverged when a position or velocity is not finite, or when
        its kinetic plus elastic energy exceeds ``BLOWUP`` (10) times the
        budget: the previous kinetic plus elastic energy, plus the work that
        gravity, the external forces, the tools' contact forces and the
        constraints (moved fixed nodes, ground lifts; at the end force) did
        in the step. Backward Euler only
        dissipates, so a legitimate step stays within 1x.

        Raises:
            SimulationError: a step diverged; the state (positions,
                velocities, time) is that before the failed step.
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise SimulationError(f"step: n must be a non-negative integer, got {n!r}")
        for _ in range(int(n)):
            for cutter in self._cutters:
                result = cutter.step(self, self.time, self.time + self.dt)
                if result is not None:
                    self.stats["cut"] = result.summary()
            self._step()

    def _step(self) -> None:
        h = self.dt
        alpha, beta = self.damping
        cur, nxt = self._cur, 1 - self._cur
        e, dev, th = self.elements, self.device, self.threads
        x0, v0, x1, v1 = self._x[cur], self._v[cur], self._x[nxt], self._v[nxt]
        state, new_state = self._states[cur], self._states[nxt]
        ground = self.ground or (0.0, 0.0)

        tc = self._sync()
        touching = self._contact is not None and self._contact.update(x0, self._solver, self.time, h)
        # the penalty enters as h^2 K_c (no Rayleigh term); 0 leaves every contact branch out
        c_contact = h * h if touching else 0.0
        t0 = self._sync()
        self._solver.assemble(state, x0, v0, self._target, self._external, self.gravity, h, 1.0 + h * alpha,
                              h * beta + h * h, v1, ground=None if self.ground is None else ground[0],
                              friction=ground[1], moving=self._moving, c_contact=c_contact)  # fmt: skip
        t1 = self._sync()
        atol = self.tolerance * 1e-6 * self._size / h * self._momentum
        iterations, residual, rhs_norm = self._solver.solve(state, v1, 1.0 + h * alpha, h * beta + h * h,
                                                            self.tolerance, atol, self.max_iterations,
                                                            c_contact)  # fmt: skip
        if not (np.isfinite(residual) and np.isfinite(rhs_norm)):
            raise SimulationError(
                f"step at t = {self.time:.6g} diverged: the linear solve overflowed (residual {residual:.6g}, "
                f"right-hand side {rhs_norm:.6g}); the state is that before the step (try a smaller dt)"
            )
        t2 = self._sync()
        split_launch(k.advance_nodes_kernel, e.node_count,
                     [x0, self._flags, self._target, self._solver.axes, float(h), int(self.ground is not None),
                      ground[0]],
                     [v1, x1, self._moved], dev, th, NODE_GRAIN)  # fmt: skip
        bodies = self._bodies
        if bodies is not None:
            bodies.save()
            bodies.advance(x0, x1, v1, self._moved, h, self.ground)
        t3 = self._sync()
        new_state.compute(e, x1, th)
        t4 = self._sync()
        # host sync: the divergence check reads the new state
        try:
            energy = self._check(x0, x1, v1, new_state, touching)
        except SimulationError:
            if bodies is not None:
                bodies.restore()
            raise
        if touching:
            self._contact.finish(v1, h)
        t5 = time.perf_counter()

        self._cur = nxt
        self._budget = energy
        self.time += h
        self._moving = False
        laps = dict(zip(_STAGES, (t0 - tc, t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)))
        s = self.stats
        if self._contact is not None:
            c = self._contact.stats
            total = s.setdefault("contact", {"seconds_total": dict.fromkeys(c["seconds"], 0.0)})["seconds_total"]
            s["contact"] = {"seconds": dict(c["seconds"]),
                            "seconds_total": {name: total[name] + c["seconds"][name] for name in total},
                            "samples": c["samples"], "penetrating": c["penetrating"] if touching else 0}  # fmt: skip
        s["steps"] += 1
        s["seconds"] = laps
        s["seconds_total"] = {name: s["seconds_total"][name] + laps[name] for name in _STAGES}
        s["cg_iterations"] = iterations
        s["cg_iterations_total"] += iterations
        s["residual"] = residual
        s["relative_residual"] = residual / rhs_norm if rhs_norm > 0 else 0.0
        s.update(self._coarse_stats())

    def _reduce(self, x0, x1, v1, state: ElementState, touching: bool = False) -> tuple[int, dict]:
        """The first node whose new position or velocity is not finite (-1: none) and the sums of
        :data:`~warpblob.sim._kernels.CHECK_ROWS` (float64) over fixed blocks, by one kernel."""
        e = self.elements
        split_launch(k.check_step_kernel, self._check_bad.shape[0],
                     [x0, x1, v1, e.mass, self._external, state.node_force, self._moved, self._solver.contact_force,
                      int(touching), wp.vec3(*self.gravity), state.energy, e.node_count, e.tet_count],
                     [self._check_bad, self._check_sums], self.device, self.threads,
                     max(1, self._check_bad.shape[0] * NODE_GRAIN // max(e.node_count, 1)))  # fmt: skip
        # host sync: a few scalars (on the CPU, views of the partials)
        bad = self._check_bad.numpy()
        first = bad[bad >= 0]
        sums = self._check_sums.numpy().sum(axis=1)
        return int(first[0]) if first.size else -1, dict(zip(k.CHECK_ROWS, (float(a) for a in sums)))

    def _check(self, x0, x1, v1, state, touching: bool = False) -> float:
        bad, sums = self._reduce(x0, x1, v1, state, touching)
        if bad >= 0:
            # host sync: the message names the bad node's values
            xb, vb = x1.numpy()[bad].astype(np.float64), v1.numpy()[bad].astype(np.float64)
            raise SimulationError(
                f"step at t = {self.time:.6g} diverged: node {bad} has position {xb.tolist()} and "
                f"velocity {vb.tolist()}; the state is that before the step (try a smaller dt)"
            )
        energy = sums["kinetic"] + sums["elastic"]
        # the tools are driven: the work of their contact forces on the tissue counts (zero without contact)
        work = abs(sums["gravity"]) + abs(sums["external"]) + sums["constraint"] + sums["contact"]
        floor = 1e-12 * float(self._mass.sum()) * (self._size / self.dt) ** 2
        budget = self._budget + work
        if not np.isfinite(energy) or energy > BLOWUP * budget + floor:
            raise SimulationError(
                f"step at t = {self.time:.6g} diverged: kinetic + elastic energy {energy:.6g} exceeds "
                f"{BLOWUP:g} x the budget {budget:.6g}; the state is that before the step (try a smaller dt)"
            )
        return energy

    def solve_static(
        self, *, max_iterations: int = 30, tolerance: float = 1e-4, cg_max_iterations: int = 20000
    ) -> dict:
        """Move to static equilibrium under gravity, the external forces and the fixed nodes (velocities zero).

        Newton's method with the rotations lagged per iteration: solve
        ``K' dx = f(x) + M g + f_ext`` (fixed nodes: ``dx`` to their targets)
        by CG, ``x += dx``, until the largest update is below ``tolerance``
        times the largest displacement so far. (The force imbalance itself
        bottoms out at float32 rounding: the elastic forces are large terms
        that cancel, so it only informs.) The ground is ignored, and every
        part of the mesh must hold a fixed node (``K'`` of a free part is singular).

        Returns:
            ``{"iterations", "update", "residual", "cg_iterations"}``: Newton
            iterations, last update relative to the displacement, final force
            imbalance of the free nodes relative to the load (or to the fixed
            nodes' reactions, without a load), total CG iterations.

        Raises:
            SimulationError: no fixed node, or a non-finite result.
        """
        held = self._fixed_mask | self._rigid_fixed
        if not held.any():
            raise SimulationError("solve_static needs fixed nodes (an unconstrained body has no static equilibrium)")
        e, dev, th = self.elements, self.device, self.threads
        free = (self._mass > 0) & ~held
        body = np.zeros(len(free), dtype=bool)
        if self._bodies is not None:
            body[self._bodies.nodes_host] = True
        load = self._mass[:, None] * np.asarray(self.gravity)[None, :] + self._external.numpy()
        scale = float(np.linalg.norm(load[free]))
        start = self.positions.astype(np.float64)
        zero = wp.zeros(e.node_count, dtype=wp.vec3, device=dev)
        dx = wp.zeros(e.node_count, dtype=wp.vec3, device=dev)
        cg_total, update, residual, iterations = 0, np.inf, np.inf, 0
        for iterations in range(1, max_iterations + 1):
            cur = self._cur
            x0, x1, state = self._x[cur], self._x[1 - cur], self._states[cur]
            self._solver.assemble(state, x0, zero, self._target, self._external, self.gravity, 1.0, 0.0, 1.0, dx,
                                  moving=True)  # fmt: skip
            it, _, _ = self._solver.solve(state, dx, 0.0, 1.0, tolerance * 0.1, tolerance * 1e-4 * max(scale, 1e-30),
                                          cg_max_iterations)  # fmt: skip
            cg_total += it
            split_launch(k.advance_nodes_kernel, e.node_count,
                         [x0, self._flags, self._target, self._solver.axes, 1.0, 0, 0.0],
                         [dx, x1, self._moved], dev, th, NODE_GRAIN)  # fmt: skip
            if self._bodies is not None:
                self._bodies.advance(x0, x1, dx, self._moved, 1.0)
            self._states[1 - cur].compute(e, x1, th)
            self._cur = 1 - cur
            # host sync: the update and the imbalance decide the next iteration
            step = np.abs(dx.numpy()[free]).max(initial=0.0)
            moved = np.abs(self._x[self._cur].numpy() - start).max(initial=0.0)
            imbalance = self._state.node_force.numpy().astype(np.float64) + load
            # relative to the load, or to the reactions of the fixed nodes when they alone load the body
            reaction = float(np.linalg.norm(imbalance[held]))
            residual = float(np.linalg.norm(imbalance[free & ~body])) / max(scale, reaction, 1e-30)
            if self._bodies is not None:
                # a rigid body balances as a whole: its net force, and its net torque over its size
                x = self._x[self._cur].numpy().astype(np.float64)
                for nodes in self._bodies.state()["nodes"]:
                    r = x[nodes] - x[nodes].mean(axis=0)
                    size = max(float(np.sqrt((r**2).sum(axis=1).max())), 1e-30)
                    f = imbalance[nodes]
                    net = np.concatenate([f.sum(axis=0), np.cross(r, f).sum(axis=0) / size])
                    residual = float(np.hypot(residual, np.linalg.norm(net) / max(scale, reaction, 1e-30)))
            update = float(step / max(moved, 1e-30))
            if not (np.isfinite(residual) and np.isfinite(update)):
                raise SimulationError(f"solve_static diverged at iteration {iterations}")
            if update < tolerance or step <= 1e-7 * self._size:
                break
        self._v[self._cur].zero_()
        self._moving = False
        self._refresh()
        return {"iterations": iterations, "update": update, "residual": residual, "cg_iterations": cg_total}

    def record(self, path, steps: int, *, every: int = 1, progress: bool | None = None,
               meters_per_unit: float | None = None, material_colors=None, on_frame=None):  # fmt: skip
        """Step ``steps`` times and write the motion as a time-sampled USD stage (:class:`warpblob.usd.Recorder`).

        The stage's root is ``/Simulation``: ``/Simulation/Volume``, a
        ``UsdGeom.TetMesh`` whose topology is re-sampled on the frames a cut
        changed it; the surface, ``/Simulation/Surface`` for a bound surface
        (its display colour sampled per frame with tools, the contact area
        highlighted: :meth:`surface_contact`) or, on a
        :class:`~warpblob.mesh.TetStructure`, one prim per separated piece
        under ``/Simulation/Pieces``; tools and cutters at
        ``/Simulation/Tools/Tool<k>``, their poses sampled per frame. It holds
        the current state at time code 0 and one frame per ``every`` steps
        after it, at ``1 / (every dt)`` time codes per second (it plays in real
        time). ``.usdc`` and ``.usd`` files stream to disk as frames come;
        the file appears, atomically, at the end.

        Args:
            path: ``.usda`` / ``.usdc`` / ``.usd`` file; its directory must exist.
            steps: number of steps (>= 1).
            every: steps per recorded frame (>= 1).
            progress: show a progress bar (default: on a terminal, for runs of 100 steps or more).
            meters_per_unit: the stage's metres per model unit (default 1: the simulator's
                constants are SI, so its lengths are metres).
            material_colors: tissue colours by material id, ``{id: (r, g, b)}`` (default: the
                model's colour field, :meth:`warpblob.usd.Recorder.add`).
            on_frame: called as ``on_frame(index)`` after each recorded frame
                (index 0 is the state before the first step), e.g. to render pictures.

        Returns:
            ``path`` as a :class:`pathlib.Path`.

        Raises:
            SimulationError: bad ``steps`` or ``every``, or a diverged step (nothing is written).
            WarpblobError: a bad path suffix or a missing directory.
            OSError: USD could not write.
        """
        from .._progress import progress as bar
        from ..io._recorder import Recorder

        for name, value in (("steps", steps), ("every", every)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise SimulationError(f"record: {name} must be a positive integer, got {value!r}")
        mpu = 1.0 if meters_per_unit is None else float(meters_per_unit)
        with Recorder(path, fps=1.0 / (self.dt * every), meters_per_unit=mpu, root="Simulation") as rec:
            rec.add(self, prim_path="/Simulation", material_colors=material_colors)
            rec.frame()
            if on_frame is not None:
                on_frame(0)
            show = progress if progress is not None else steps >= 100
            for i in bar(range(steps), desc="simulate", total=steps) if show else range(steps):
                self.step()
                if (i + 1) % every == 0:
                    rec.frame()
                    if on_frame is not None:
                        on_frame(rec.frame_count - 1)
        return rec.path

    # -- topology changes ------------------------------------------------------

    def rebuild(self, tet_ids=None, *, new_velocities=None, new_fixed=None, new_sources=None, **changes) -> None:
        """Rebuild element data after a topology change: the call the cutting code makes after each edit.

        ``tet_ids`` and ``changes`` (``tets``, ``alive``, ``rest``, ``young``,
        ``poisson``, ``density``) are those of
        :meth:`~warpblob.sim._elements.Elements.rebuild`. Built from a
        :class:`~warpblob.mesh.TetStructure` and called without ``tets``, the
        changed slots (default: all) are re-read from the structure: cell
        nodes, live flags, the materials' values by material id, node rest
        positions. Nodes added since start at the structure's current
        position (a TetMesh's: at rest) with velocity ``new_velocities``
        ((K, 3) for the K added nodes, default zero) and fixed where
        ``new_fixed`` ((K,) bool) says (default free); positions,
        velocities and fixed flags of the others stay. The solver is rebuilt
        with the element data, the two-level preconditioner's aggregates and
        coarse matrix included (their set-up is in :attr:`stats`), except
        after a cut's kind of edit: given ``new_sources`` ((K,) ints, the old
        node each added node was made from, as :meth:`apply_cut` gives), on a
        TetStructure, where the changed old tets are all dead and the
        structure's piece count is the one the aggregates were split by and
        the nodes have grown by at most
        :data:`~warpblob.sim._coarse.FOLLOW_GROWTH` since they were made, the
        aggregates are kept and the added nodes join their sources'
        (:meth:`~warpblob.sim._coarse.CoarseSpace.follow`: no new lattice, no
        count of the pieces, the slot layout extended rather than rebuilt).

        Material ids: on a TetStructure they are re-read (a cut's new tets keep
        their parent's); on a TetMesh give ``material=`` ((K,) ints for the
        slots, default: unchanged, new slots 0). The rigid pieces
        (:attr:`rigid`) are then recomputed: a rigid piece a cut separated
        from the one holding the anchors or fixed nodes becomes a free rigid
        body, with the momentum of its nodes (new nodes are not anchors).

        Raises:
            SimulationError: as :meth:`Elements.rebuild`.
        """
        e = self.elements
        material_new = changes.pop("material", None)
        if self._structure is not None and "tets" not in changes:
            s = self._structure
            material_new = None
            ids = np.arange(len(s.cell_nodes)) if tet_ids is None else np.asarray(tet_ids, dtype=np.int64)
            read = {"tets": np.asarray(s.cell_nodes)[ids], "alive": np.asarray(s.cell_alive, dtype=bool)[ids],
                    "rest": np.asarray(s.node_rest)}  # fmt: skip
            material = np.asarray(s.cell_material)[ids]
            for name, spec in self._specs.items():
                if name in changes:
                    continue
                if np.ndim(spec) == 0 or isinstance(spec, dict):
                    read[name] = material_values(name, spec, material, tet_ids=ids)
                elif ids.size and ids.max() >= len(spec):
                    raise SimulationError(f"rebuild: {name} was given per tet; give {name}= for the new tets")
                else:
                    read[name] = np.asarray(spec, dtype=np.float64)[ids]
            changes = {**read, **changes}
            tet_ids = ids
        old_n = e.node_count
        # the added nodes' data, checked before anything changes
        grow = max(0, len(changes["rest"]) - old_n) if changes.get("rest") is not None else 0
        vnew = np.zeros((grow, 3)) if new_velocities is None else np.asarray(new_velocities, np.float64)
        fnew = np.zeros(grow, dtype=bool) if new_fixed is None else np.asarray(new_fixed, dtype=bool)
        if vnew.shape != (grow, 3) or fnew.shape != (grow,):
            raise SimulationError(f"rebuild: {grow} nodes were added; new_velocities must be ({grow}, 3) and "
                                  f"new_fixed ({grow},), got {vnew.shape} and {fnew.shape}")  # fmt: skip
        src = None if new_sources is None else np.asarray(new_sources)
        if src is not None and (src.shape != (grow,) or (src.size and (not np.issubdtype(src.dtype, np.integer)
                                                                       or src.min() < 0 or src.max() >= old_n))):
            raise SimulationError(f"rebuild: {grow} nodes were added; new_sources must be ({grow},) ints in "
                                  f"[0, {old_n}), got {new_sources!r}")  # fmt: skip
        mask = self._fixed_mask
        if material_new is not None:
            values = np.asarray(material_new)
            slots = np.arange(e.tet_count) if tet_ids is None else np.asarray(tet_ids).ravel()
            if values.shape != slots.shape or (values.size and not np.issubdtype(values.dtype, np.integer)):
                raise SimulationError(f"rebuild: material must be ({len(slots)},) ints, got {material_new!r}")
        old_t = e.tet_count
        e.rebuild(tet_ids, **changes)
        grow = e.node_count - old_n
        if self._structure is not None:
            self._material = np.asarray(self._structure.cell_material, dtype=np.int32)[: e.tet_count].copy()
        else:
            material = np.concatenate([self._material, np.zeros(e.tet_count - old_t, dtype=np.int32)])
            if material_new is not None:
                material[slots.astype(np.int64)] = values
            self._material = material
        added = e.rest_host[old_n:]
        if self._structure is not None:
            added = np.asarray(self._structure.node_position, dtype=np.float32)[old_n : e.node_count]
        pad = lambda a, fill: np.concatenate([a, fill])  # noqa: E731
        # the element pass of the tets not rebuilt carries over (same positions, same element data)
        carry = None if tet_ids is None else (self._state, old_t, np.asarray(tet_ids, dtype=np.int64),
                                              e.touched_nodes)  # fmt: skip
        # (and the energy budget at this state with the masses it was taken with, for the refresh to update)
        prior = None if carry is None or e.touched_nodes is None else (self._budget, self._mass)
        # a cut's kind of edit (the changed old tets all dead now) lets the coarse space be carried over
        old_ids = None if tet_ids is None else np.asarray(tet_ids, dtype=np.int64).ravel()
        follow = src is not None and old_ids is not None and not e.alive_host[old_ids[old_ids < old_t]].any()
        # the old nodes' positions, velocities, targets and external forces stay where they are
        self._allocate(added, vnew, src.astype(np.int64) if follow else None, kept=old_n)
        self._carry, self._prior = carry, prior
        self._fixed_mask = pad(mask, fnew)
        self._anchor_mask = pad(self._anchor_mask, np.zeros(grow, dtype=bool))
        try:
            self._update_flags(keep_coarse=True)  # (its _refresh takes the carried state)
        finally:
            self._carry = self._prior = None  # never to a later refresh, whose positions may differ
        self.stats["tet_count"], self.stats["node_count"] = self.tet_count, self.node_count
        if self._embedding is not None:
            self._embedding = embed(e, self._embedding.mesh, threads=self.threads)
        if self._contact is not None:
            self._contact.bind(e)

    # -- embedded surface ------------------------------------------------------

    def surface(self, mesh) -> Embedding:
        """Bind a surface (e.g. the polygonized model) to the rest tets; it then follows the volume.

        Each vertex gets the barycentric coordinates of the rest tet holding
        it, or of the nearest tet when it lies outside the volume (found with
        a ``wp.Bvh``). Replaces any surface bound before.

        Returns:
            The :class:`~warpblob.sim._embed.Embedding` (tet, barycentric
            coordinates and rest distance per vertex).
        """
        self._embedding = embed(self.elements, mesh, threads=self.threads)
        return self._embedding

    @property
    def embedding(self) -> Embedding | None:
        """The bound surface's :class:`~warpblob.sim._embed.Embedding` (its ``mesh`` is the rest surface), or None."""
        return self._embedding

    def surface_positions(self) -> np.ndarray:
        """(V, 3) float32 deformed vertices of the bound surface (one kernel).

        Raises:
            SimulationError: no surface is bound (:meth:`surface`).
        """
        if self._embedding is None:
            raise SimulationError("surface_positions: bind a surface first with sim.surface(mesh)")
        return interpolate(self._embedding, self.elements, self._x[self._cur], threads=self.threads)

    # -- tools -----------------------------------------------------------------

    def apply_cut(self, result) -> None:
        """Follow a :func:`warpblob.cut.cut` of this simulation's structure (made with ``collect=False``).

        Rebuilds the element data of the removed and added tets only
        (:meth:`rebuild`); new nodes take the velocity of the points they were
        made at, copies of fixed nodes stay fixed. Cut with the structure at
        the simulation's positions (``structure.set_positions(sim.positions)``).

        Raises:
            SimulationError: the simulation is not built on a TetStructure, or
                the cut compacted it (``collect=True``).

        Example:
            >>> import warpblob as wb
            >>> s = wb.TetStructure.from_tetmesh(wb.mesh.box_tetmesh((0, 0, 0), (1, 0.2, 0.2), (5, 1, 1)))
            >>> sim = wb.Simulation(s, young=1e5, poisson=0.3, density=1000.0, fixed=[0, 1, 2, 3])
            >>> r = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.5, 0.1, 0.1), (1, 0, 0), 1.0), collect=False)
            >>> sim.apply_cut(r)
            >>> sim.tet_count == len(s.cell_nodes), r.components
            (True, 2)
        """
        from ..cut._sim import apply_cut

        apply_cut(self, result)

    @property
    def cutters(self) -> tuple:
        """The cutting tools (:meth:`add_tool` with ``cut=True``), in the order added."""
        return tuple(self._cutters)

    def add_tool(self, tool, path, *, stiffness: float | None = None, kring: int = 2, contact: str = "field",
                 model=None, spacing: float | None = None, cut: bool = False, mode: str = "on_release",
                 snap: float = 0.2, materials=None):  # fmt: skip
        """Add a rigid tool on a path: each :meth:`step` moves it to ``path.pose(t + dt)`` and applies its contact.

        With ``cut=True`` a :class:`~warpblob.tools.Scalpel` or
        :class:`~warpblob.tools.Drill` cuts the volume instead
        (:class:`~warpblob.cut._sim.Cutter`; the simulation must be built on
        a :class:`~warpblob.mesh.TetStructure`): ``mode="on_release"`` (the
        default, the thesis' cutter) records the stroke and cuts once, at the
        step in which the path ends; ``mode="progressive"`` cuts every step
        with the stroke so far (the tissue opens as the blade goes); it may
        make more cells than one stroke and, rarely, leave a few single-tet
        fragments (measured in docs/cut.md). Each cut rebuilds the element data of the
        changed tets (:meth:`apply_cut`); pieces it severs fall on their own.
        A cutting tool does not push (give ``stiffness`` as well for contact).
        The first cutting tool of a process (per device) runs
        :func:`warpblob.cut.warm_up` here (0.05-0.2 s): the loads a first cut
        would otherwise take in the frame it cuts.

        The contact follows the thesis' field-based model, with the field
        carried by the deformation (:mod:`warpblob.sim._contact`: sampling,
        penetration, force, k-ring spread and the implicit penalty).

        Args:
            tool: a :class:`~warpblob.tools.Tool` (``Probe``, ``Scalpel``, ``Drill``...).
            path: its :class:`~warpblob.tools.Path` (poses over time, s).
            stiffness: penalty stiffness per unit tool area, > 0: N per model
                unit of penetration per model unit squared of tool surface
                (a face of area ``A`` pressed ``d`` deep pushes with about ``s A d``).
            kring: rings of nodes the force spreads over (weights
                ``(k + 1 - r) / (k + 1)`` for the ring ``r``), >= 0.
            contact: ``"field"`` (the deformation-mapped field, located in the
                deformed tets) or ``"nearest"`` (the thesis: the rest field
                at the world position, the force at the nearest node).
            model: the model whose field gives the contact (default: the
                simulation's ``model``); the first one given is kept.
            spacing: tool sampling distance, model units (default: the
                mesh's median edge length).
            cut: the tool cuts (see above).
            mode: "progressive" or "on_release" (cutting tools).
            snap: the cut's snapping fraction (:func:`warpblob.cut.cut`), in [0, 0.5).
            materials: a cutting tool cuts only tets of these material ids
                (:func:`warpblob.cut.cut`; default: every tet).

        Returns:
            The :class:`~warpblob.sim._contact.ToolContact` record (its index
            in :attr:`tools` numbers the tool in :meth:`contact_force`), or for
            a cutting tool without ``stiffness`` its
            :class:`~warpblob.cut._sim.Cutter` (:attr:`cutters`; its
            ``results`` are the cuts made).

        Raises:
            ToolError: a bad tool, path, stiffness (<= 0), kring, contact or
                spacing, naming the value (a path with non-increasing times or
                NaN poses and an open tool mesh are refused when made, by
                :class:`~warpblob.tools.Path` and :class:`~warpblob.tools.Tool`).
            SimulationError: no model, or a model other than the simulation's.

        Example:
            >>> import warpblob as wb
            >>> from warpblob.tools import Path, Probe
            >>> model = wb.Box((0, 0, 0), (0.5, 0.5, 0.2), 0.3)
            >>> sim = wb.Simulation(wb.tetrahedralize(model, cellsize=0.15), young=1e5, poisson=0.45,
            ...                     density=1000.0, gravity=(0, 0, 0), model=model)
            >>> top = float(sim.positions[:, 2].max())
            >>> path = Path.line((0, 0, top + 0.1), (0, 0, top - 0.1), 0.2)
            >>> probe = sim.add_tool(Probe(0.4), path, stiffness=1e7)
            >>> sim.step(12)
            >>> bool(sim.contact_force(0)[2] > 0)  # the tissue pushes the probe back up
            True
        """
        if cut:
            from ..cut._sim import Cutter, warm_up

            if self._structure is None:
                raise SimulationError("add_tool(cut=True): cutting edits the mesh; build the simulation on a "
                                      "TetStructure (wb.TetStructure.from_tetmesh(mesh))")  # fmt: skip
            cutter = Cutter(tool, path, mode=mode, snap=snap, materials=materials)
            warm_up(self.device, self.threads)  # (the first cut's one-off loads here, not in a frame)
            self._cutters.append(cutter)
            if stiffness is None:
                return cutter
        if stiffness is None:
            raise ToolError("add_tool: a contact tool needs its stiffness (or cut=True for a cutting tool)")
        if model is not None:
            if self.model is not None and model is not self.model:
                raise SimulationError("add_tool: the simulation already has a model; tools share the tissue's model")
            self.model = model
        if self.model is None:
            raise SimulationError(
                "add_tool: field contact needs the model the volume was made from: Simulation(..., model=m) "
                "or add_tool(..., model=m) (a TetMesh does not keep it)"
            )
        return self._contact_state().add(tool, path, stiffness=stiffness, kring=kring, contact=contact,
                                         spacing=spacing)  # fmt: skip

    def _contact_state(self) -> Contact:
        if self._contact is None:
            if self.model is None:
                raise SimulationError("field: give the model the volume was made from: Simulation(..., model=m)")
            self._contact = Contact(self.elements, self.model, self.threads)
        return self._contact

    @property
    def tools(self) -> tuple:
        """The added tools' :class:`~warpblob.sim._contact.ToolContact` records, in the order added."""
        return tuple(self._contact.tools) if self._contact is not None else ()

    def _tool_index(self, tool) -> int:
        count = len(self.tools)
        if isinstance(tool, ToolContact):
            for i, r in enumerate(self.tools):
                if r is tool:
                    return i
            raise ToolError("the tool record belongs to another simulation")
        if isinstance(tool, bool) or not isinstance(tool, (int, np.integer)) or not 0 <= tool < count:
            raise ToolError(f"tool must be an index in [0, {count}) or a record of sim.tools, got {tool!r}")
        return int(tool)

    def contact_force(self, tool=None) -> np.ndarray:
        """Force the tissue exerted on a tool in the last step (what a haptic device renders), e.g. N.

        Summed over the tool's penetrating samples at the end of the step
        (the penalty linearized as in the solve); zero for a step without contact.

        Args:
            tool: an index into :attr:`tools` or its record; None: every tool.

        Returns:
            (3,) float64, or (K, 3) for every tool.
        """
        forces = self._contact.forces.copy() if self._contact is not None else np.zeros((0, 3))
        return forces if tool is None else forces[self._tool_index(tool)]

    def contact_points(self, tool=None) -> np.ndarray:
        """(P, 3) float32 world positions of the tool samples that penetrated the tissue in the last step.

        Args:
            tool: an index into :attr:`tools` or its record; None: every tool.
        """
        if self._contact is None:
            return np.zeros((0, 3), dtype=np.float32)
        return self._contact.penetrating(None if tool is None else self._tool_index(tool))

    def contact_nodes(self) -> np.ndarray:
        """Sorted (C,) int indices of the nodes the tools pushed in the last step (after the k-ring spread)."""
        return np.flatnonzero(self._solver.contact_weight.numpy() > 0)

    def surface_contact(self) -> np.ndarray:
        """(V,) float32 in [0, 1]: how strongly the tools pushed each vertex of the bound surface in the last step.

        The nodes' contact stiffness interpolated at each vertex (its tet's
        barycentric weights, clamped), over its largest value: 0 away from
        the contact, 1 at its strongest. For pictures.

        Raises:
            SimulationError: no surface is bound.
        """
        if self._embedding is None:
            raise SimulationError("surface_contact: bind a surface first with sim.surface(mesh)")
        emb = self._embedding
        weight = self._solver.contact_weight.numpy()
        bary = np.clip(emb.bary, 0.0, None)
        vertex = (weight[self.elements.tets_host[emb.tet]] * bary).sum(axis=1) / bary.sum(axis=1)
        top = vertex.max(initial=0.0)
        return (vertex / top if top > 0 else vertex).astype(np.float32)

    def field(self, points) -> tuple[np.ndarray, np.ndarray]:
        """The model's field carried by the deformation, and its gradient, at world ``points``.

        A point in a deformed tet maps to the rest point with the same
        barycentric coordinates; the field is the model's there, the
        gradient the rest gradient pushed forward by the tet's deformation
        gradient (``F^-T grad F``). This is the field the tools' contact
        reads. Points outside the deformed volume get 0 and a zero gradient.

        Args:
            points: (P, 3) world positions.

        Returns:
            ``(values (P,), gradients (P, 3))`` float32.

        Raises:
            SimulationError: no model was given, or bad points.
        """
        shape = np.shape(points)
        if len(shape) != 2 or shape[1] != 3:
            raise SimulationError(f"field: points must have shape (P, 3), got {shape}")
        pts = self._nodal("field: points", points, shape[0])
        return self._contact_state().field(self._x[self._cur], pts, self.threads)

    def __repr__(self) -> str:
        return (
            f"Simulation({self.tet_count} tets, {self.node_count} nodes, {int(self._fixed_mask.sum())} fixed, "
            f"dt={self.dt:.6g}, t={self.time:.6g}, device={self.device})"
        )
