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
from .._stages import ROOM, device_array, device_empty, host_array, room, rows_any
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


def check_tets(rest: np.ndarray, tets: np.ndarray, alive: np.ndarray, ids: np.ndarray, threads=None,
               names: np.ndarray | None = None) -> None:  # fmt: skip
    """SimulationError for a live tet among ``ids`` that names a bad node or is inverted or flat at rest.

    ``names``: the tet ids the errors name, per entry of ``ids`` (default: ``ids``; the rows of a rebuild's
    listed slots are checked before they are written).

    One kernel thread per tet (:func:`~warpblob.sim._kernels.check_tets_kernel`, float64); the error names
    the first tet of the first kind found, in this order: a node outside ``[0, N)``, a repeated node, an
    inverted or flat tet (volume at most :data:`DEGENERATE_VOLUME` times its longest edge cubed).
    """
    N = len(rest)
    ids = np.ascontiguousarray(ids, dtype=np.int32).ravel()
    if not ids.size:
        return
    cpu = wp.get_device("cpu")
    tets = np.asarray(tets).reshape(-1, 4)
    rows, live = tets[ids].astype(np.int64), np.asarray(alive, dtype=bool)[ids]
    outside = live & rows_any((rows < 0) | (rows >= N))
    names = ids if names is None else np.asarray(names).ravel()
    if outside.any():
        j = int(np.argmax(outside))
        raise SimulationError(f"tet {int(names[j])} = {tets[ids[j]].tolist()} names a node outside [0, {N})")
    # a few tets (a cut's): their nodes' rest positions only, in float64
    if 16 * len(ids) < N:
        nodes, local = np.unique(np.where(live[:, None], rows, 0), return_inverse=True)
        rest, rows = np.asarray(rest)[nodes], local.reshape(-1, 4)
    code = np.empty(len(ids), dtype=np.int32)
    volume = np.empty(len(ids), dtype=np.float64)
    longest = np.empty(len(ids), dtype=np.float64)
    launch(k.check_tets_kernel, len(ids),
           [host_array(np.asarray(rest, dtype=np.float64).reshape(-1, 3), wp.vec3d),
            host_array(rows.astype(np.int32), wp.vec4i),
            host_array(live.view(np.uint8), wp.uint8),
            host_array(np.arange(len(ids), dtype=np.int32), wp.int32),
            wp.float64(DEGENERATE_VOLUME)],
           [host_array(a, d) for a, d in
            ((code, wp.int32), (volume, wp.float64), (longest, wp.float64))], cpu, threads,
           min_chunk=8192)  # fmt: skip
    if not code.any():
        return
    for kind in (2, 3):
        where = np.flatnonzero(code == kind)
        if not where.size:
            continue
        j = int(where[0])
        t, row = int(names[j]), tets[ids[j]].tolist()
        if kind == 2:
            raise SimulationError(f"tet {t} = {row} repeats a node")
        what = "inverted" if volume[j] < 0 else "zero-volume"
        raise SimulationError(
            f"tet {t} = {row} is {what} at rest: volume {volume[j]:.6g} "
            f"(longest edge {longest[j]:.6g}); rest tets must be positively oriented"
        )


def _ascending(ids: np.ndarray) -> np.ndarray:
    """``np.unique(ids)``, without its sort where ``ids`` ascend strictly already (a cut's: removed, then added)."""
    return ids if ids.size < 2 or bool((ids[1:] > ids[:-1]).all()) else np.unique(ids)


#: the free tail the incidence lists get after a sort (slots for the lists a rebuild makes longer): this share
#: of the lists' length, and at least _TAIL slots
_TAIL_SHARE = 0.25
_TAIL = 1 << 12


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
    ``density`` (T,), ``mass`` (N,) lumped mass, and the incidence: node
    ``i``'s corners (``4 * tet + local corner``, ascending) are
    ``node_corners[node_range[i][0]:node_range[i][1]]`` (``node_range`` (N,)
    vec2i; a sort packs the lists, and a list that a rebuild makes longer
    moves to the free tail after them with room to grow, so that a rebuild
    rewrites only the lists it changes; :meth:`incidence` packs them). ``rigid_host`` (T,) bool marks
    the tets of rigid materials (:meth:`set_rigid`): their ``mu`` and ``lam``
    are zero on the device, so they add mass but no elastic force or
    stiffness (their nodes move as rigid bodies, :mod:`warpblob.sim._rigid`).
    ``touched_nodes``: (K,) int32 the nodes whose incidence the last
    :meth:`rebuild` changed (the corners of the changed tets that were live
    before it or are live after it, and every new node), or None after a
    rebuild of every tet; ``revision`` counts the rebuilds (0: as made).
    """

    def __init__(self, rest, tets, alive, young, poisson, density, *, device, threads=None):
        self.device = device
        self.threads = threads
        self.rest_host = np.ascontiguousarray(rest, dtype=np.float32)
        # copies: on the CPU the device's tets and live flags are these arrays, never the caller's
        self.tets_host = np.array(tets, dtype=np.int32).reshape(-1, 4)
        self.alive_host = np.array(alive, dtype=bool)
        self.young_host = np.asarray(young, dtype=np.float64)
        self.poisson_host = np.asarray(poisson, dtype=np.float64)
        self.density_host = np.asarray(density, dtype=np.float64)
        self.dm_inv = wp.zeros(0, dtype=wp.mat33, device=device)
        self.volume = wp.zeros(0, dtype=float, device=device)
        # the kept buffers (:func:`~warpblob._stages.room`) under dm_inv, volume, mass, the incidence sort's
        # keys and the incidence lists
        self._bases: dict = {}
        # the kept host buffers under the per-tet host arrays (:meth:`_grown`)
        self._host_bases: dict = {}
        # the incidence's (N, 2) first and past-last slot of each node's list, and the slots it may fill in place
        self._range_host = np.zeros((0, 2), dtype=np.int32)
        self._room_host = np.zeros(0, dtype=np.int32)
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
        recomputed by a kernel, the incidence lists of the nodes those tets
        touch merged anew (every other list moved as it was; all of them
        sorted afresh when ``tet_ids`` is None), their masses by a gather
        (all cheap next to a step). The listed rows are checked before
        anything changes; the per-tet host arrays then grow in place, in
        kept buffers with room (so an array read from this object before a
        rebuild may see its changed rows).

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
        new = _ascending(ids[ids >= T])
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
            r = np.asarray(rest)
            if r.ndim != 2 or r.shape[1] != 3 or len(r) < self.node_count:
                raise SimulationError(
                    f"rebuild: rest must have shape (N', 3) with N' >= {self.node_count}, got {r.shape}"
                )
            if not np.isfinite(r).all():
                bad = np.flatnonzero(~np.isfinite(r).all(axis=1))
                raise SimulationError(f"rebuild: rest[{bad[0]}] = {r[bad[0]].tolist()} is not finite")
        # the listed slots' new rows, checked before anything changes (old slots keep what is not given)
        old = ids[ids < T]
        at_old = ids < T

        def rows(given, host, fill):
            out = np.empty((len(ids), *host.shape[1:]), dtype=host.dtype)
            out[at_old] = host[old]
            out[~at_old] = fill
            if given is not None:
                out[:] = given
            return out

        tets_ids = rows(tets, self.tets_host, 0)
        alive_ids = rows(alive, self.alive_host, True)
        mats = {}
        for name, host, bounds, positive in (("young", self.young_host, None, True),
                                             ("poisson", self.poisson_host, (-1.0, 0.5), False),
                                             ("density", self.density_host, None, True)):  # fmt: skip
            mats[name] = material_values(name, rows(params[name], host, np.nan), np.zeros(len(ids), dtype=np.int32),
                                         positive=positive, bounds=bounds, tet_ids=ids)  # fmt: skip
        rest_h = self.rest_host if rest is None else np.ascontiguousarray(rest, dtype=np.float32)
        check_tets(rest_h, tets_ids, alive_ids, np.arange(len(ids)), self.threads, names=ids)
        touched = None
        if tet_ids is not None:  # the nodes whose incidence changed: the changed live tets' corners, old and new
            mark = np.zeros(len(rest_h), dtype=bool)  # (marks, not a sort of every corner)
            mark[self.tets_host[old][self.alive_host[old]].ravel()] = True
            mark[tets_ids[alive_ids].ravel()] = True
            mark[self.node_count :] = True
            touched = np.flatnonzero(mark)
        # commit: the per-tet host arrays grow in kept buffers (room for later cuts' tets) and take the rows
        self.rest_host = rest_h
        for name, value, fill in (("tets_host", tets_ids, 0), ("alive_host", alive_ids, True),
                                  ("young_host", mats["young"], np.nan), ("poisson_host", mats["poisson"], np.nan),
                                  ("density_host", mats["density"], np.nan), ("rigid_host", None, False)):  # fmt: skip
            grown_host = self._grown(name, grown, fill)
            if value is not None:
                grown_host[ids] = value
            setattr(self, name, grown_host)
        self._rebuild(ids.astype(np.int32), touched)

    def _grown(self, name: str, rows: int, fill) -> np.ndarray:
        """Host array ``name`` grown to ``rows`` rows (the new ones ``fill``), a view of a kept buffer with
        room (:data:`~warpblob._stages.ROOM` more when it must be made): its first rows stay in place."""
        a, base = getattr(self, name), self._host_bases.get(name)
        if base is None or a.base is not base or len(base) < rows:
            base = np.empty((rows + int(rows * ROOM), *a.shape[1:]), dtype=a.dtype)
            base[: len(a)] = a
            self._host_bases[name] = base
        base[len(a) : rows] = fill
        return base[:rows]

    def _sort_incidence(self) -> None:
        """The incidence (:attr:`node_range`, :attr:`node_corners`) of every node by a sort of all corners:
        the lists packed in node order, with a free tail of about a quarter of them for the lists that later
        rebuilds make longer (:meth:`_update_incidence`)."""
        dev, T, N = self.device, self.tet_count, self.node_count
        # corners of dead tets sort past the last node, out of every row; the second half is the radix
        # sort's scratch (not initialized); the columns are the corners' indices. On the CPU the keys are
        # written in a kept buffer (scratch), and the lists into the kept buffer of the lists (fresh pages
        # of a 16 MB array at 1M tets cost more than the sort's writes)
        count = 4 * T
        capacity = count + max(int(count * _TAIL_SHARE), _TAIL)
        cpu = not wp.get_device(dev).is_cuda
        self._bases["corners"], lists = room(self._bases.get("corners"), capacity, wp.int32, dev)
        if cpu:
            self._bases["rows"], rows_wp = room(self._bases.get("rows"), count, wp.int32, dev)
            rows = rows_wp.numpy()
        else:
            rows = np.empty(2 * count, dtype=np.int32)
        corner_nodes = rows[:count].reshape(T, 4)
        corner_nodes[:] = self.tets_host
        corner_nodes[~self.alive_host] = N
        if not cpu:
            rows_wp = device_array(rows, wp.int32, dev)
        offsets, corners = csr(rows_wp, None, count, N, dev, self.threads, lists if cpu else None)
        if not cpu:
            wp.copy(lists, device_array(corners, wp.int32, dev), count=len(corners))
        self.node_corners = lists
        self._tail = int(offsets[-1])
        self._range_host = self._grown("_range_host", N, 0)
        self._range_host[:, 0], self._range_host[:, 1] = offsets[:-1], offsets[1:]
        self._room_host = self._grown("_room_host", N, 0)
        np.subtract(offsets[1:], offsets[:-1], out=self._room_host)
        self._bind_range()

    def _bind_range(self) -> None:
        """:attr:`node_range` on the device from the host's ranges (on the CPU the host array itself)."""
        cuda = wp.get_device(self.device).is_cuda
        self.node_range = device_array(self._range_host, wp.vec2i, self.device, copy=cuda)

    def incidence(self) -> tuple[np.ndarray, np.ndarray]:
        """The incidence as packed CSR on the host: ``(offsets (N + 1,) int32, corners (4 T_live,) int32)``;
        node ``i``'s corners (``4 * tet + local corner``, ascending) are ``corners[offsets[i]:offsets[i + 1]]``.

        Example:
            >>> import numpy as np
            >>> from warpblob.mesh import box_tetmesh
            >>> m = box_tetmesh((0, 0, 0), (1, 1, 1), (1, 1, 1))
            >>> T = len(m.tets)
            >>> e = Elements(m.nodes, m.tets, np.ones(T, bool), np.full(T, 1e3), np.full(T, 0.3), np.full(T, 1e3),
            ...              device="cpu")
            >>> offsets, corners = e.incidence()
            >>> int(offsets[-1]) == 4 * T, bool(np.all(np.diff(corners[offsets[0]:offsets[1]]) > 0))
            (True, True)
        """
        r = self._range_host.astype(np.int64)
        counts = r[:, 1] - r[:, 0]
        offsets = np.zeros(len(r) + 1, dtype=np.int32)
        np.cumsum(counts, out=offsets[1:])
        lists = self.node_corners.numpy()
        # each list's slots: its start plus 0 .. count - 1
        slots = np.repeat(r[:, 0] - offsets[:-1], counts) + np.arange(int(offsets[-1]))
        return offsets, lists[slots]

    def incidence_lists(self) -> tuple[np.ndarray, np.ndarray]:
        """The incidence as it is kept, lists with room, not packed: ``(ranges (N, 2) int32, lists)`` on the
        host; node ``i``'s corners are ``lists[ranges[i, 0]:ranges[i, 1]]`` (:meth:`incidence` packs them,
        a pass over every list). Valid until the next edit of the elements."""
        return self._range_host, self.node_corners.numpy()

    def _update_incidence(self, ids: np.ndarray, touched: np.ndarray) -> None:
        """The incidence after tets ``ids`` changed: the lists of the ``touched`` nodes (every corner of those
        tets, old and new; ascending) merged anew, in place where they fit in their slots, else in the free
        tail with room to grow; every other list stays where it is (one kernel over the touched nodes; the
        same lists as :meth:`_sort_incidence`'s, which packs them again when the tail is full)."""
        dev, T, N, th = self.device, self.tet_count, self.node_count, self.threads
        old_n = len(self._room_host)
        changed = np.zeros(T, dtype=np.uint8)
        changed[ids] = 1
        live = _ascending(ids[self.alive_host[ids]]).astype(np.int64)
        nodes = self.tets_host[live].ravel()
        cols = (4 * live[:, None] + np.arange(4)).ravel()
        order = np.argsort(nodes, kind="stable")  # (the columns ascend already: by node, then column)
        nodes, cols = nodes[order], cols[order].astype(np.int32)
        # every changed tet's corner is a touched node: the nodes' runs follow each other in touched order
        add_start = np.append(np.searchsorted(nodes, touched), len(nodes)).astype(np.int32)
        touched_wp = device_array(touched, wp.int32, dev)
        changed_wp = device_array(changed, wp.uint8, dev)
        add_start_wp = device_array(add_start, wp.int32, dev)
        count = device_empty(len(touched), wp.int32, dev)
        launch(k.incidence_count_kernel, len(touched), [touched_wp, self.node_range, self.node_corners, changed_wp,
               add_start_wp], [count], dev, th, min_chunk=1 << 12)  # fmt: skip
        counts = count.numpy()
        # a list that fits its slots stays; one that does not moves to the tail, with half as many again
        inside = touched < old_n
        fits = np.zeros(len(touched), dtype=bool)
        fits[inside] = counts[inside] <= self._room_host[touched[inside]]
        moved = np.flatnonzero(~fits)
        size = counts[moved] + counts[moved] // 2 + 4
        if self._tail + int(size.sum()) > self.node_corners.shape[0]:
            self._sort_incidence()  # (the tail is full: every list packed again)
            return
        start = np.zeros(len(touched), dtype=np.int32)
        start[fits] = self._range_host[touched[fits], 0]
        start[moved] = self._tail + np.cumsum(size) - size
        scratch_start = np.zeros(len(touched) + 1, dtype=np.int32)  # (each merged list's place in the scratch)
        np.cumsum(counts, out=scratch_start[1:])
        scratch = device_empty(max(int(scratch_start[-1]), 1), wp.int32, dev)
        launch(k.incidence_merge_kernel, len(touched),
               [touched_wp, self.node_range, self.node_corners, changed_wp, add_start_wp,
                device_array(cols, wp.int32, dev), device_array(scratch_start, wp.int32, dev),
                device_array(start, wp.int32, dev), scratch], [self.node_corners], dev, th,
               min_chunk=1 << 12)  # fmt: skip
        # commit: the ranges (new nodes' rows appended) and the moved lists' slots
        self._range_host = self._grown("_range_host", N, 0)
        self._room_host = self._grown("_room_host", N, 0)
        self._range_host[touched, 0] = start
        self._range_host[touched, 1] = start + counts
        self._room_host[touched[moved]] = size
        self._tail += int(size.sum())
        self._bind_range()

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
        self._per_tet(("mu", "lam"), ids, lambda rows: np.where(self.rigid_host[rows], 0.0,
                                                                  lame(self.young_host[rows], self.poisson_host[rows])))

    def _per_tet(self, names: tuple, ids: np.ndarray | None, values) -> None:
        """Device arrays ``names`` (T,) float of per-tet values: ``values(rows)`` ((len(names), len(rows)))
        written for tets ``ids`` (None: all) into kept float32 host buffers, the other tets' kept in place.
        On the CPU the device arrays are those buffers; on CUDA copies, assigned in place where the length
        is unchanged (the solver's recorded launches hold them; :meth:`set_rigid` changes them)."""
        T, dev = self.tet_count, self.device
        rows = np.arange(T) if ids is None else np.asarray(ids, dtype=np.int64)
        computed = np.asarray(values(rows))
        cuda = wp.get_device(dev).is_cuda
        for name, value in zip(names, computed):
            host = f"_{name}_host"
            if getattr(self, host, None) is None:
                setattr(self, host, np.zeros(0, dtype=np.float32))
            view = self._grown(host, T, 0.0)
            view[rows] = value
            setattr(self, host, view)
            current = getattr(self, name, None)
            if cuda and current is not None and current.shape[0] == T:
                current.assign(view)
            else:
                setattr(self, name, device_array(view, float, dev, copy=cuda))

    def _rebuild(self, ids: np.ndarray, touched: np.ndarray | None = None) -> None:
        """Element data of tets ``ids``, the incidence, and the masses of the ``touched`` nodes (None: all;
        the others' stay in place)."""
        dev, T, N = self.device, self.tet_count, self.node_count
        old_n = self.mass.shape[0] if getattr(self, "mass", None) is not None else 0
        self.rest = device_array(self.rest_host, wp.vec3, dev)
        # on the CPU the tets and live flags are the host arrays themselves (written only by a rebuild)
        copy = wp.get_device(dev).is_cuda
        self.tets = device_array(self.tets_host, wp.vec4i, dev, copy=copy)
        self.alive = alive = device_array(self.alive_host.view(np.uint8), wp.uint8, dev, copy=copy)
        self._lame(ids)
        self._per_tet(("density",), ids, lambda rows: self.density_host[rows][None])
        # kept buffers (room to grow): the tets not in ids keep their values in place, the new ones are in ids
        keep = min(T, self.dm_inv.shape[0])
        for name, dtype in (("dm_inv", wp.mat33), ("volume", float)):
            base = self._bases.get(name)
            self._bases[name], view = room(base, T, dtype, dev)
            if self._bases[name] is not base and keep:
                wp.copy(view, getattr(self, name), count=keep)
            setattr(self, name, view)
        if ids.size:
            ids_wp = device_array(ids, wp.int32, dev)
            # (a light kernel: split from 64K tets; a cut's few hundred in one launch, where waking the pool
            # for a second piece took 0.3 ms against 0.05 for the whole)
            launch(k.prepare_elements_kernel, len(ids), [self.rest, self.tets, alive, ids_wp],
                   [self.dm_inv, self.volume], dev, self.threads, min_chunk=1 << 15)  # fmt: skip
        if touched is not None and old_n and getattr(self, "node_range", None) is not None:
            self._update_incidence(ids, touched)
        else:
            self._sort_incidence()
        mass, base = self.mass if old_n else None, self._bases.get("mass")
        self._bases["mass"], self.mass = room(base, N, float, dev)
        gather = [self.node_range, self.node_corners, self.volume, self.density]
        self.touched_nodes = None if touched is None or not old_n else touched.astype(np.int32)
        # (the tets this rebuild changed, where it followed a local edit: as ``touched_nodes``, for the contact)
        self.changed_tets = None if self.touched_nodes is None else ids.astype(np.int64)
        self.revision = getattr(self, "revision", -1) + 1
        if self.touched_nodes is None:
            # (a light kernel: pieces of 2^15 nodes, not the launcher's default, whose many small pieces cost
            # more in launches than the gather)
            every = wp.zeros(0, dtype=wp.int32, device=dev)
            launch(k.gather_masses_kernel, N, [every, *gather], [self.mass], dev, self.threads, min_chunk=1 << 15)
            return
        if self._bases["mass"] is not base:
            wp.copy(self.mass, mass, count=min(old_n, N))
        nodes = device_array(self.touched_nodes, wp.int32, dev)
        launch(k.gather_masses_kernel, len(self.touched_nodes), [nodes, *gather], [self.mass], dev, self.threads,
               min_chunk=1 << 14)  # fmt: skip
