"""Element data of the co-rotational FEM in flat arrays, rebuildable for any subset of tets.

Per tet: node indices, a live flag, ``Dm^-1`` (rest shape matrix inverse),
rest volume, Lamé parameters and density; per node: the lumped mass and the
CSR node -> corner incidence (corner ``4 t + a`` is local node ``a`` of tet
``t``) through which every per-node kernel gathers per-corner results in a
fixed order. The host copies of topology and materials are the source of
truth; :meth:`Elements.rebuild` is the call a topology change makes (cutting
splits, adds and kills tets): it recomputes the geometry and the Lamé
parameters of the given tets with a kernel, the incidence of all nodes (a
stable counting sort on one CPU thread, a radix sort on a GPU) and the
masses of the nodes the changed tets touch (the others' stay in place, in
buffers kept with room to grow).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .._errors import SimulationError
from .._parallel import launch
from .._stages import room
from ..mesh._structure import csr
from . import _kernels as k

__all__ = ["Elements", "material_values", "lame"]

#: a tet whose rest volume is below this fraction of its longest edge cubed is degenerate
DEGENERATE_VOLUME = 1e-7


def material_values(
    name: str, value, material: np.ndarray, *, positive: bool = False, bounds=None, tet_ids=None
) -> np.ndarray:
    """Per-tet float64 values of a material parameter given as a scalar, a (T,) array or a dict by material id.

    ``tet_ids`` (default ``arange(T)``) are the tet numbers the messages name.

    Raises:
        SimulationError: a wrong shape, a missing material id, a value that
            is not finite, not positive (``positive``) or outside the open
            interval ``bounds``, naming the value and its tet.
    """
    count = len(material)
    if isinstance(value, dict):
        ids = np.unique(material)
        missing = [int(m) for m in ids if int(m) not in value]
        if missing:
            raise SimulationError(
                f"{name}: no value for material {missing[0]} (the mesh has materials {ids.tolist()}, "
                f"the dict gives {sorted(value)})"
            )
        table = {int(m): value[int(m)] for m in ids}
        for m, v in table.items():
            if not isinstance(v, (int, float, np.integer, np.floating)) or isinstance(v, bool):
                raise SimulationError(f"{name}[material {m}] must be a number, got {v!r}")
        out = np.zeros(count, dtype=np.float64)
        for m, v in table.items():
            out[material == m] = float(v)
    else:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise SimulationError(
                f"{name} must be a number, a ({count},) array or a dict by material id, got {value!r}"
            ) from None
        if arr.ndim == 0:
            out = np.full(count, float(arr))
        elif arr.shape == (count,):
            out = arr.copy()
        else:
            raise SimulationError(
                f"{name} must be a number, a ({count},) array or a dict by material id, got shape {arr.shape}"
            )
    tet = (lambda j: int(j)) if tet_ids is None else (lambda j: int(tet_ids[j]))  # noqa: E731
    bad = np.flatnonzero(~np.isfinite(out))
    if bad.size:
        raise SimulationError(f"{name} = {out[bad[0]]} at tet {tet(bad[0])} is not finite")
    if positive:
        bad = np.flatnonzero(out <= 0)
        if bad.size:
            raise SimulationError(f"{name} = {out[bad[0]]} at tet {tet(bad[0])} must be positive")
    if bounds is not None:
        lo, hi = bounds
        bad = np.flatnonzero((out <= lo) | (out >= hi))
        if bad.size:
            raise SimulationError(f"{name} = {out[bad[0]]} at tet {tet(bad[0])} must lie in ({lo}, {hi})")
    return out


def lame(young: np.ndarray, poisson: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lamé parameters ``(mu, lambda)`` from Young's modulus and Poisson's ratio."""
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return mu, lam


def check_tets(rest: np.ndarray, tets: np.ndarray, alive: np.ndarray, ids: np.ndarray, threads=None) -> None:
    """SimulationError for a live tet among ``ids`` that names a bad node or is inverted or flat at rest.

    One kernel thread per tet (:func:`~warpblob.sim._kernels.check_tets_kernel`, float64); the error names
    the first tet of the first kind found, in this order: a node outside ``[0, N)``, a repeated node, an
    inverted or flat tet (volume at most :data:`DEGENERATE_VOLUME` times its longest edge cubed).
    """
    N = len(rest)
    ids = np.ascontiguousarray(ids, dtype=np.int32).ravel()
    if not ids.size:
        return
    cpu = wp.get_device("cpu")
    tets = np.ascontiguousarray(tets, dtype=np.int32).reshape(-1, 4)
    code = np.empty(len(ids), dtype=np.int32)
    volume = np.empty(len(ids), dtype=np.float64)
    longest = np.empty(len(ids), dtype=np.float64)
    launch(k.check_tets_kernel, len(ids),
           [wp.array(np.asarray(rest, dtype=np.float64).reshape(-1, 3), dtype=wp.vec3d, device=cpu),
            wp.array(tets, dtype=wp.vec4i, device=cpu, copy=False),
            wp.array(np.ascontiguousarray(alive, dtype=bool).view(np.uint8), dtype=wp.uint8, device=cpu, copy=False),
            wp.array(ids, dtype=wp.int32, device=cpu, copy=False), wp.float64(DEGENERATE_VOLUME)],
           [wp.array(a, dtype=d, device=cpu, copy=False) for a, d in
            ((code, wp.int32), (volume, wp.float64), (longest, wp.float64))], cpu, threads,
           min_chunk=8192)  # fmt: skip
    if not code.any():
        return
    for kind in (1, 2, 3):
        where = np.flatnonzero(code == kind)
        if not where.size:
            continue
        j = int(where[0])
        t = int(ids[j])
        if kind == 1:
            raise SimulationError(f"tet {t} = {tets[t].tolist()} names a node outside [0, {N})")
        if kind == 2:
            raise SimulationError(f"tet {t} = {tets[t].tolist()} repeats a node")
        what = "inverted" if volume[j] < 0 else "zero-volume"
        raise SimulationError(
            f"tet {t} = {tets[t].tolist()} is {what} at rest: volume {volume[j]:.6g} "
            f"(longest edge {longest[j]:.6g}); rest tets must be positively oriented"
        )


class Elements:
    """Element data on one device: tets, ``Dm^-1``, rest volumes, Lamé parameters, densities, masses, incidence.

    Args:
        rest: (N, 3) rest positions.
        tets: (T, 4) node indices, positive orientation at rest.
        alive: (T,) bool; dead tets keep their slot and contribute nothing.
        young, poisson, density: (T,) float64 per-tet values (validated by
            :func:`material_values`).
        device: Warp device.
        threads: CPU threads of the launches (None: the default).

    Attributes (Warp arrays): ``tets`` (T,) vec4i, ``dm_inv`` (T,) mat33,
    ``volume`` (T,) rest volume (0 for dead tets), ``mu``, ``lam``,
    ``density`` (T,), ``mass`` (N,) lumped mass, ``node_offsets`` (N + 1,)
    and ``node_corners`` the CSR incidence. ``rigid_host`` (T,) bool marks
    the tets of rigid materials (:meth:`set_rigid`): their ``mu`` and ``lam``
    are zero on the device, so they add mass but no elastic force or
    stiffness (their nodes move as rigid bodies, :mod:`warpblob.sim._rigid`).
    ``touched_nodes``: (K,) int32 the nodes whose incidence the last
    :meth:`rebuild` changed (the changed tets' corners before and after it,
    and every new node), or None after a rebuild of every tet.
    """

    def __init__(self, rest, tets, alive, young, poisson, density, *, device, threads=None):
        self.device = device
        self.threads = threads
        self.rest_host = np.ascontiguousarray(rest, dtype=np.float32)
        self.tets_host = np.ascontiguousarray(tets, dtype=np.int32).reshape(-1, 4)
        self.alive_host = np.ascontiguousarray(alive, dtype=bool)
        self.young_host = np.asarray(young, dtype=np.float64)
        self.poisson_host = np.asarray(poisson, dtype=np.float64)
        self.density_host = np.asarray(density, dtype=np.float64)
        self.dm_inv = wp.zeros(0, dtype=wp.mat33, device=device)
        self.volume = wp.zeros(0, dtype=float, device=device)
        # the kept buffers (:func:`~warpblob._stages.room`) under dm_inv, volume, mass, the incidence sort's
        # keys and, alternating, its lists (_spare: the one the next rebuild writes)
        self._bases: dict = {}
        self._spare = 1
        self.rigid_host = np.zeros(self.tet_count, dtype=bool)
        ids = np.arange(self.tet_count, dtype=np.int32)
        check_tets(self.rest_host, self.tets_host, self.alive_host, ids, threads)
        self._rebuild(ids)

    @property
    def tet_count(self) -> int:
        return int(self.tets_host.shape[0])

    @property
    def node_count(self) -> int:
        return int(self.rest_host.shape[0])

    def rebuild(
        self, tet_ids=None, *, tets=None, alive=None, rest=None, young=None, poisson=None, density=None
    ) -> None:
        """Recompute the element data of tets ``tet_ids`` after a topology change (all tets when None).

        The cutting issue calls this after every edit: pass the changed slots,
        their new node indices, live flags and materials; ids at or past
        :attr:`tet_count` (consecutive from it) append tets, and a longer
        ``rest`` appends nodes. ``Dm^-1`` and volumes of ``tet_ids`` are
        recomputed by a kernel, the incidence of every node by a sort, the
        masses of the nodes those tets touch by a gather (all cheap next to a
        step).

        Args:
            tet_ids: (K,) tet slots to rebuild, or None for all.
            tets: (K, 4) new node indices of those slots (default: unchanged).
            alive: (K,) live flags (default: unchanged; True for new slots).
            rest: (N', 3) rest positions of every node, N' >= N (default: unchanged).
            young, poisson, density: (K,) values for those slots (default:
                unchanged; new slots must give them).

        Raises:
            SimulationError: bad ids, shapes or values, or a live tet that
                names a bad node or is inverted or flat at rest.
        """
        T = self.tet_count
        if tet_ids is None:
            ids = np.arange(T, dtype=np.int64)
        else:
            ids = np.asarray(tet_ids)
            if ids.ndim != 1 or (ids.size and not np.issubdtype(ids.dtype, np.integer)):
                raise SimulationError(f"rebuild: tet_ids must be a 1-D integer array, got {tet_ids!r}")
            ids = ids.astype(np.int64)
        new = np.unique(ids[ids >= T])
        if ids.size and ids.min() < 0:
            raise SimulationError(f"rebuild: tet id {int(ids.min())} is negative")
        if new.size and not np.array_equal(new, np.arange(T, T + new.size)):
            raise SimulationError(f"rebuild: new tet ids must continue from {T} without gaps, got {new.tolist()}")
        grown = T + new.size

        def values(name, arr, width, dtype, fill):
            if arr is None:
                if new.size and fill is None:
                    raise SimulationError(f"rebuild: {name} must be given for the new tets {new.tolist()}")
                return None
            a = np.asarray(arr, dtype=dtype)
            shape = (len(ids),) if width is None else (len(ids), width)
            if a.shape != shape:
                raise SimulationError(f"rebuild: {name} must have shape {shape}, got {a.shape}")
            return a

        tets = values("tets", tets, 4, np.int64, None)
        alive = values("alive", alive, None, bool, True)
        params = {n: values(n, v, None, np.float64, None) for n, v in
                  (("young", young), ("poisson", poisson), ("density", density))}  # fmt: skip
        if rest is not None:
            r = np.asarray(rest, dtype=np.float64)
            if r.ndim != 2 or r.shape[1] != 3 or len(r) < self.node_count:
                raise SimulationError(
                    f"rebuild: rest must have shape (N', 3) with N' >= {self.node_count}, got {r.shape}"
                )
            bad = np.flatnonzero(~np.isfinite(r).all(axis=1))
            if bad.size:
                raise SimulationError(f"rebuild: rest[{bad[0]}] = {r[bad[0]].tolist()} is not finite")

        def grow(a, fill):
            return np.concatenate([a, np.full((grown - T, *a.shape[1:]), fill, dtype=a.dtype)])

        tets_h, alive_h = grow(self.tets_host, 0), grow(self.alive_host, True)
        if tets is not None:
            tets_h[ids] = tets
        if alive is not None:
            alive_h[ids] = alive
        mats = {}
        for name, host, bounds, positive in (("young", self.young_host, None, True),
                                             ("poisson", self.poisson_host, (-1.0, 0.5), False),
                                             ("density", self.density_host, None, True)):  # fmt: skip
            h = grow(host, np.nan)
            if params[name] is not None:
                h[ids] = params[name]
            sub = material_values(name, h[ids], np.zeros(len(ids), dtype=np.int32), positive=positive, bounds=bounds,
                                  tet_ids=ids)
            h[ids] = sub
            mats[name] = h
        rest_h = self.rest_host if rest is None else np.ascontiguousarray(rest, dtype=np.float32)
        check_tets(rest_h, tets_h, alive_h, ids, self.threads)
        touched = None
        if tet_ids is not None:  # the nodes whose incidence changed: the changed tets' corners, old and new
            touched = np.unique(np.concatenate([self.tets_host[ids[ids < T]].ravel(), tets_h[ids].ravel(),
                                                np.arange(self.node_count, len(rest_h))]))  # fmt: skip
        self.rest_host, self.tets_host, self.alive_host = rest_h, tets_h, alive_h
        self.young_host, self.poisson_host, self.density_host = mats["young"], mats["poisson"], mats["density"]
        self.rigid_host = grow(self.rigid_host, False)
        self._rebuild(ids.astype(np.int32), touched)

    def set_rigid(self, mask) -> None:
        """Mark the (T,) bool ``mask`` of tets as rigid: zero Lamé parameters on the device (mass unchanged)."""
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (self.tet_count,):
            raise SimulationError(f"set_rigid: the mask must have shape ({self.tet_count},), got {mask.shape}")
        self.rigid_host = mask.copy()
        self._lame()

    def _lame(self, ids: np.ndarray | None = None) -> None:
        """Lamé parameters on the device (zero for rigid tets): of every tet, or of tets ``ids`` only (the
        others as before, new slots past the old count)."""
        T, old = self.tet_count, getattr(self, "_lame_host", None)
        if ids is None or old is None or len(old[0]) > T:
            mu, lam = (a.astype(np.float32) for a in lame(self.young_host, self.poisson_host))
            mu[self.rigid_host] = 0.0
            lam[self.rigid_host] = 0.0
        else:
            mu, lam = (np.concatenate([a, np.zeros(T - len(a), dtype=np.float32)]) for a in old)
            ids = np.asarray(ids, dtype=np.int64)
            rigid = self.rigid_host[ids]
            m, l = lame(self.young_host[ids], self.poisson_host[ids])
            mu[ids] = np.where(rigid, 0.0, m)
            lam[ids] = np.where(rigid, 0.0, l)
        self._lame_host = (mu, lam)
        if getattr(self, "mu", None) is not None and self.mu.shape[0] == T:
            # in place: the solver's recorded launches hold these arrays
            self.mu.assign(mu)
            self.lam.assign(lam)
        else:
            self.mu = wp.array(mu, dtype=float, device=self.device)
            self.lam = wp.array(lam, dtype=float, device=self.device)

    def _rebuild(self, ids: np.ndarray, touched: np.ndarray | None = None) -> None:
        """Element data of tets ``ids``, the incidence, and the masses of the ``touched`` nodes (None: all;
        the others' stay in place)."""
        dev, T, N = self.device, self.tet_count, self.node_count
        old_n = self.mass.shape[0] if getattr(self, "mass", None) is not None else 0
        self.rest = wp.array(self.rest_host, dtype=wp.vec3, device=dev)
        self.tets = wp.array(self.tets_host, dtype=wp.vec4i, device=dev)
        alive = wp.array(self.alive_host.view(np.uint8), dtype=wp.uint8, device=dev)
        self._lame(ids)
        self.density = wp.array(self.density_host.astype(np.float32), dtype=float, device=dev)
        # kept buffers (room to grow): the tets not in ids keep their values in place, the new ones are in ids
        keep = min(T, self.dm_inv.shape[0])
        for name, dtype in (("dm_inv", wp.mat33), ("volume", float)):
            base = self._bases.get(name)
            self._bases[name], view = room(base, T, dtype, dev)
            if self._bases[name] is not base and keep:
                wp.copy(view, getattr(self, name), count=keep)
            setattr(self, name, view)
        if ids.size:
            ids_wp = wp.array(ids, dtype=wp.int32, device=dev)
            launch(k.prepare_elements_kernel, len(ids), [self.rest, self.tets, alive, ids_wp],
                   [self.dm_inv, self.volume], dev, self.threads, min_chunk=256)  # fmt: skip
        # corners of dead tets sort past the last node, out of every row; the second half is the radix
        # sort's scratch (not initialized); the columns are the corners' indices. On the CPU the keys are
        # written in a kept buffer (scratch), and the lists into the one of two kept buffers the current
        # lists are not in (fresh pages of a 16 MB array at 1M tets cost more than the sort's writes)
        count = 4 * T
        cpu = not wp.get_device(dev).is_cuda
        if cpu:
            self._bases["rows"], rows_wp = room(self._bases.get("rows"), count, wp.int32, dev)
            rows = rows_wp.numpy()
            self._spare = spare = 1 - self._spare  # (0, 1, 0, ...: never the buffer of the lists in use)
            self._bases[("corners", spare)], order = room(self._bases.get(("corners", spare)), count, wp.int32, dev)
        else:
            rows = np.empty(2 * count, dtype=np.int32)
            order = None
        corner_nodes = rows[:count].reshape(T, 4)
        corner_nodes[:] = self.tets_host
        corner_nodes[~self.alive_host] = N
        if not cpu:
            rows_wp = wp.array(rows, dtype=wp.int32, device=dev)
        offsets, corners = csr(rows_wp, None, count, N, dev, self.threads, order)
        self.node_offsets = wp.array(offsets, dtype=wp.int32, device=dev)
        self.node_corners = wp.array(corners, dtype=wp.int32, device=dev, copy=not cpu)
        mass, base = self.mass if old_n else None, self._bases.get("mass")
        self._bases["mass"], self.mass = room(base, N, float, dev)
        gather = [self.node_offsets, self.node_corners, self.volume, self.density]
        self.touched_nodes = None if touched is None or not old_n else touched.astype(np.int32)
        if self.touched_nodes is None:
            # (a light kernel: pieces of 2^15 nodes, not the launcher's default, whose many small pieces cost
            # more in launches than the gather)
            every = wp.zeros(0, dtype=wp.int32, device=dev)
            launch(k.gather_masses_kernel, N, [every, *gather], [self.mass], dev, self.threads, min_chunk=1 << 15)
            return
        if self._bases["mass"] is not base:
            wp.copy(self.mass, mass, count=min(old_n, N))
        nodes = wp.array(self.touched_nodes, dtype=wp.int32, device=dev)
        launch(k.gather_masses_kernel, len(self.touched_nodes), [nodes, *gather], [self.mass], dev, self.threads,
               min_chunk=1 << 14)  # fmt: skip
