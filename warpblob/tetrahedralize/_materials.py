"""Multi-material domains: one conforming tet mesh of a domain, each tet in one material.

``tetrahedralize(model, cellsize=h, materials=[s0, s1, ...])`` stuffs the
domain ``model`` (``None``: the union of the listed solids) exactly as a
single model, then:

1. **Labels.** Each tet gets the material of its centroid: the *innermost*
   listed solid that contains it, the highest index ``i`` with
   ``F_i(centroid) >= 0.5``, and 0 where no listed solid contains it (so
   ``s0`` is also the background of the domain). One field evaluation per
   tet and material (a kernel per material), combined in numpy.
2. **Interface snapping.** The faces shared by two tets of different
   materials ``a < b`` form the material interfaces; on the ``b`` side every
   point has ``F_b >= 0.5`` and on the ``a`` side ``F_b < 0.5``, so the true
   interface there is the iso-surface ``F_b = 0.5``. Centroid labels leave a
   staircase of lattice faces up to about a cell from it. Every interface
   node that is not on the domain's boundary and whose interface faces all
   have the same inner material ``b`` is moved towards its projection onto
   ``F_b = 0.5`` (Newton steps along the gradient, each at most half a cell,
   in all at most one cell), guarded: a move is kept only if no tet around
   the node inverts, falls below ``min(SNAP_MIN_DIHEDRAL, its own dihedral
   minimum before)`` or rises above ``max(SNAP_MAX_DIHEDRAL, its maximum
   before)`` (14 deg and 160 deg); moves that fail are retried at half and
   a quarter of the distance, then dropped. The nodes move in independent
   sets (no two in one tet), so the guard kernel judges each move exactly
   against the node's own tets; two sweeps over all sets, each projecting
   afresh. A node on two interfaces (faces of two inner materials
   ``b1 < b2``: a layer about a cell thin) aims at the midpoint of its
   projections onto both; nodes on the domain boundary stay.
   So every tet keeps its dihedral angles within [14 deg, 160 deg] or within
   its own range before snapping, whichever is wider, and the stuffed mesh's
   bounds ([10.7 deg, 164.8 deg], see :mod:`warpblob.tetrahedralize`) hold
   after snapping too; the domain's boundary, the tets' connectivity and the
   total volume are untouched.

This is **not** lattice cleaving (Bronson, Levine and Whitaker 2012): the
interfaces are the labelled tets' faces moved as far as the quality guard
allows, so their distance from the true interfaces is not bounded a priori.
It is measured instead on every call (``stats["interface_error"]``: the
distance of each interface node from the iso-surface of its inner material,
by the same projection, in cell sizes) and the tests bound it (measured
figures in ``docs/tetrahedralize.md``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import warp as wp

from .._errors import WarpblobError
from .._linearize import LinearModel
from .._parallel import launch
from .._stages import compact
from ..field import evaluate
from ..mesh._tetmesh import TET_FACES
from ..tree import ISO_VALUE, Node, Union
from ._kernels import Lattice, edge_end, incident_edge, point_coords, point_index, point_position
from ._pinch import groups

__all__ = ["SNAP_MAX_DIHEDRAL", "SNAP_MIN_DIHEDRAL", "interface_faces", "parse_materials", "snap"]

SNAP_MIN_DIHEDRAL = 14.0  # degrees
SNAP_MAX_DIHEDRAL = 160.0  # degrees
_ISO = float(ISO_VALUE)
_PROJECT_ITERATIONS = 8
_PROJECT_TOLERANCE = 1e-4  # |F - iso| of a converged projection
_FRACTIONS = (1.0, 0.5, 0.25)
_SWEEPS = 2  # projections and independent-set passes of the snapping (a third gains about 1%)


def parse_materials(materials) -> tuple[list[str], list]:
    """``(names, solids)`` of a sequence of solids (names ``material0``, ...) or a mapping name -> solid."""
    if isinstance(materials, (Node, LinearModel, str, bytes)):
        raise WarpblobError(f"tetrahedralize: materials must be a sequence or mapping of solids, got {materials!r}")
    if isinstance(materials, Mapping):
        names, solids = [str(k) for k in materials], list(materials.values())
    else:
        try:
            solids = list(materials)
        except TypeError:
            raise WarpblobError(
                f"tetrahedralize: materials must be a sequence or mapping of solids, got {materials!r}"
            ) from None
        names = [f"material{i}" for i in range(len(solids))]
    if not solids:
        raise WarpblobError("tetrahedralize: materials must name at least one solid, got an empty list")
    for i, s in enumerate(solids):
        if not isinstance(s, (Node, LinearModel)):
            raise WarpblobError(f"tetrahedralize: materials[{i}] must be a model (Node), got {s!r}")
    if len(set(names)) != len(names):
        raise WarpblobError(f"tetrahedralize: material names must be distinct, got {names!r}")
    return names, solids


def domain_of(solids: list):
    """The union of the listed solids (the domain when ``model`` is None)."""
    if not all(isinstance(s, Node) for s in solids):
        raise WarpblobError("tetrahedralize: model=None needs every material as a Node (to form their union)")
    return solids[0] if len(solids) == 1 else Union(*solids)


def label(lms: list[LinearModel], centroids: wp.array, threads) -> np.ndarray:
    """(T,) int32 material of each centroid: the highest ``i`` with ``F_i >= 0.5``, else 0."""
    inside = np.stack([evaluate(lm, centroids, derivatives=False, threads=threads)[0].numpy() >= _ISO for lm in lms])
    top = len(lms) - 1 - np.argmax(inside[::-1], axis=0)
    return np.where(inside.any(axis=0), top, 0).astype(np.int32)


def interface_faces(tets: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Faces shared by two tets of different materials.

    Returns:
        ``(faces, pair, tet_pair)``: (F, 3) node ids, (F, 2) the materials
        ``(a, b)``, ``a < b``, and (F, 2) the two tets (the ``a`` tet first).
    """
    t = tets.astype(np.int64)
    n_nodes = int(t.max()) + 1 if t.size else 1
    # only faces whose three nodes all lie in tets of two materials or more can be interface faces
    kinds = np.zeros(n_nodes, dtype=np.int32)
    for m in np.unique(ids).tolist():
        kinds += np.bincount(t[ids == m].reshape(-1), minlength=n_nodes) > 0
    mixed = kinds >= 2
    keep = np.flatnonzero(mixed[t].sum(axis=1) >= 3)
    t = t[keep]
    # the sorted node triple of every face by min / max (row 4 i + k: face k of tet keep[i])
    corners = [t[:, list(f)] for f in TET_FACES]
    x, y, z = (np.stack([c[:, j] for c in corners], axis=1).reshape(-1) for j in range(3))
    face_ok = mixed[x] & mixed[y] & mixed[z]
    rows = np.flatnonzero(face_ok)
    x, y, z = x[rows], y[rows], z[rows]
    lo, hi = np.minimum(np.minimum(x, y), z), np.maximum(np.maximum(x, y), z)
    s = np.stack([lo, x + y + z - lo - hi, hi], axis=1)
    order, starts, sizes = groups(s)
    same = starts[sizes == 2]  # rows order[same], order[same + 1] share a face
    t0, t1 = keep[rows[order[same]] // 4], keep[rows[order[same + 1]] // 4]
    m0, m1 = ids[t0], ids[t1]
    cross = m0 != m1
    t0, t1, m0, m1 = t0[cross], t1[cross], m0[cross], m1[cross]
    swap = m0 > m1
    ta, tb = np.where(swap, t1, t0), np.where(swap, t0, t1)
    pair = np.stack([np.minimum(m0, m1), np.maximum(m0, m1)], axis=1)
    return s[order[same[cross]]], pair, np.stack([ta, tb], axis=1)


def project(lm: LinearModel, points: np.ndarray, h: float, threads, device=None) -> tuple[np.ndarray, np.ndarray]:
    """Newton projection of (K, 3) ``points`` onto ``F = 0.5`` of ``lm``: (targets, converged).

    Steps ``-(F - 0.5) grad F / |grad F|^2``, each at most ``h / 2`` long, the
    whole displacement at most ``h``; converged: ``|F - 0.5| <= 1e-4`` at the end."""
    start = np.asarray(points, dtype=np.float64)
    x = start.copy()
    for _ in range(_PROJECT_ITERATIONS):
        values, grads, _ = evaluate(lm, x.astype(np.float32), device=device, threads=threads)
        f = values.astype(np.float64) - _ISO
        if not len(f) or np.abs(f).max() <= _PROJECT_TOLERANCE:
            return x, np.ones(len(x), dtype=bool)
        g = grads.astype(np.float64)
        g2 = np.einsum("ij,ij->i", g, g)
        step = np.where((g2 > 0.0)[:, None], -(f / np.where(g2 > 0.0, g2, 1.0))[:, None] * g, 0.0)
        length = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, 0.5 * h / np.maximum(length, 1e-300))[:, None]
        x = x + step
        d = x - start
        dl = np.linalg.norm(d, axis=1)
        x = start + d * np.minimum(1.0, h / np.maximum(dl, 1e-300))[:, None]
    values = evaluate(lm, x.astype(np.float32), device=device, derivatives=False, threads=threads)[0]
    return x, np.abs(values.astype(np.float64) - _ISO) <= _PROJECT_TOLERANCE


def node_targets(n_nodes: int, faces: np.ndarray, pair: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per node: the smallest and largest inner material of its interface faces (-1 for a node
    on no interface) and whether it is on one."""
    lo = np.full(n_nodes, np.iinfo(np.int64).max, dtype=np.int64)
    hi = np.full(n_nodes, -1, dtype=np.int64)
    inner = np.repeat(pair[:, 1], 3)
    flat = faces.reshape(-1)
    np.minimum.at(lo, flat, inner)
    np.maximum.at(hi, flat, inner)
    on = hi >= 0
    return np.where(on, lo, -1), hi, on


def _goals(current: np.ndarray, movable: np.ndarray, lo: np.ndarray, hi: np.ndarray, lms: list, h: float, threads,
           device) -> np.ndarray:  # fmt: skip
    """Where each movable node should go: its projection onto its inner material's iso-surface,
    or, on two interfaces (inner materials ``lo < hi``: a layer about a cell thin), the midpoint
    of its projections onto both; a node whose projection fails stays (``current``)."""
    goal = current.astype(np.float64).copy()
    x_hi = goal.copy()
    ok_hi = np.zeros(len(goal), dtype=bool)
    for b in np.unique(hi[movable]).tolist():
        v = movable[hi[movable] == b]
        x, ok = project(lms[b], goal[v], h, threads, device)
        x_hi[v], ok_hi[v] = x, ok
    two = movable[lo[movable] != hi[movable]]
    x_lo = x_hi.copy()
    ok_lo = np.ones(len(goal), dtype=bool)
    for b in np.unique(lo[two]).tolist():
        v = two[lo[two] == b]
        x, ok = project(lms[b], goal[v], h, threads, device)
        x_lo[v], ok_lo[v] = x, ok
    ok = ok_hi & ok_lo
    goal[ok] = 0.5 * (x_hi[ok] + x_lo[ok])
    return goal


def interface_distances(nodes, faces, pair, lms, h, threads, device=None) -> tuple[np.ndarray, np.ndarray]:
    """Distance of every (interface node, inner material) incidence from that material's iso-surface.

    Returns:
        ``(incidences, distances)``: (K, 2) int (node, inner material) pairs and
        (K,) float64 model units (the projection's displacement; not converged:
        plus ``|F - 0.5| / |grad F|``)."""
    incid = np.unique(np.stack([faces.reshape(-1), np.repeat(pair[:, 1], 3)], axis=1), axis=0)
    out = np.zeros(len(incid))
    for b in np.unique(incid[:, 1]).tolist():
        rows = np.flatnonzero(incid[:, 1] == b)
        pts = nodes[incid[rows, 0]].astype(np.float64)
        target, ok = project(lms[b], pts, 4.0 * h, threads, device)
        d = np.linalg.norm(target - pts, axis=1)
        if not ok.all():
            values, grads, _ = evaluate(lms[b], target[~ok].astype(np.float32), device=device, threads=threads)
            g = np.maximum(np.linalg.norm(grads.astype(np.float64), axis=1), 1e-300)
            d[~ok] += np.abs(values.astype(np.float64) - _ISO) / g
        out[rows] = d
    return incid, out


_DEG = 57.29577951308232


@wp.func
def _edge_angle(pi: wp.vec3d, pj: wp.vec3d, pk: wp.vec3d, pl: wp.vec3d):
    """Dihedral angle (degrees) at edge ``pi pj`` between the faces through ``pk`` and ``pl``."""
    e = pj - pi
    le = wp.length(e)
    angle = wp.float64(0.0)
    if le > wp.float64(0.0):
        e = e / le
        u = pk - pi
        w = pl - pi
        u = u - wp.dot(u, e) * e
        w = w - wp.dot(w, e) * e
        lu = wp.length(u)
        lw = wp.length(w)
        if lu > wp.float64(0.0) and lw > wp.float64(0.0):
            c = wp.clamp(wp.dot(u, w) / (lu * lw), wp.float64(-1.0), wp.float64(1.0))
            angle = wp.acos(c) * wp.float64(_DEG)
    return angle


@wp.func
def _angle_range(p0: wp.vec3d, p1: wp.vec3d, p2: wp.vec3d, p3: wp.vec3d):
    """(smallest, largest) dihedral angle of a tet, degrees."""
    a0 = _edge_angle(p0, p1, p2, p3)
    a1 = _edge_angle(p0, p2, p1, p3)
    a2 = _edge_angle(p0, p3, p1, p2)
    a3 = _edge_angle(p1, p2, p0, p3)
    a4 = _edge_angle(p1, p3, p0, p2)
    a5 = _edge_angle(p2, p3, p0, p1)
    lo = wp.min(wp.min(wp.min(a0, a1), wp.min(a2, a3)), wp.min(a4, a5))
    hi = wp.max(wp.max(wp.max(a0, a1), wp.max(a2, a3)), wp.max(a4, a5))
    return wp.vec2d(lo, hi)


@wp.func
def _corner(nodes: wp.array(dtype=wp.vec3), t: wp.vec4i, k: int, c: int, x: wp.vec3):
    q = x
    if k != c:
        q = nodes[t[k]]
    return wp.vec3d(wp.float64(q[0]), wp.float64(q[1]), wp.float64(q[2]))


@wp.kernel(enable_backward=False)
def measure_angles_kernel(
    nodes: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    offset: int,
    lo: wp.array(dtype=wp.float64),
    hi: wp.array(dtype=wp.float64),
):
    """Smallest and largest dihedral angle of every tet, degrees (as :func:`guard_moves_kernel` measures them)."""
    i = wp.tid() + offset
    t = tets[i]
    x = wp.vec3(0.0)
    r = _angle_range(_corner(nodes, t, 0, -1, x), _corner(nodes, t, 1, -1, x), _corner(nodes, t, 2, -1, x),
                     _corner(nodes, t, 3, -1, x))  # fmt: skip
    lo[i] = r[0]
    hi[i] = r[1]


@wp.kernel(enable_backward=False)
def guard_moves_kernel(
    nodes: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.vec4i),
    inc_tet: wp.array(dtype=wp.int32),
    inc_corner: wp.array(dtype=wp.int32),
    candidates: wp.array(dtype=wp.vec3),
    floor: wp.array(dtype=wp.float64),
    ceiling: wp.array(dtype=wp.float64),
    offset: int,
    ok: wp.array(dtype=wp.int32),
):
    """1 when tet ``j = inc_tet[i]`` with its corner ``inc_corner[i]`` at ``candidates[i]`` has positive
    volume and dihedral angles in ``[floor[j], ceiling[j]]`` (float64 throughout)."""
    i = wp.tid() + offset
    j = inc_tet[i]
    t = tets[j]
    c = inc_corner[i]
    x = candidates[i]
    p0 = _corner(nodes, t, 0, c, x)
    p1 = _corner(nodes, t, 1, c, x)
    p2 = _corner(nodes, t, 2, c, x)
    p3 = _corner(nodes, t, 3, c, x)
    good = int(0)
    if wp.dot(p1 - p0, wp.cross(p2 - p0, p3 - p0)) > wp.float64(0.0):
        r = _angle_range(p0, p1, p2, p3)
        if r[0] >= floor[j] and r[1] <= ceiling[j]:
            good = 1
    ok[i] = good


@wp.kernel(enable_backward=False)
def gather_points_kernel(
    l: Lattice, indices: wp.array(dtype=wp.int32), offset: int, positions: wp.array(dtype=wp.vec3)
):
    """Positions of the lattice points ``indices``, model units."""
    i = wp.tid() + offset
    positions[i] = point_position(l, point_coords(l, indices[i]))


@wp.kernel(enable_backward=False)
def mark_interface_points_kernel(
    l: Lattice,
    labels: wp.array(dtype=wp.int32),
    material: wp.array(dtype=wp.int32),
    offset: int,
    out: wp.array(dtype=wp.int32),
):
    """``labels``, but 0 for an inside point with a lattice neighbour inside another material
    (``material`` -1: not inside the domain, ignored), so no coarse cube straddles an interface."""
    p = wp.tid() + offset
    s = labels[p]
    if s == 1:
        q = point_coords(l, p)
        m = material[p]
        for k in range(14):
            e = incident_edge(l, q, k)
            if e[0] >= 0:
                other = e[0]
                if e[2] == 1:
                    f = edge_end(q, e[1])
                    other = point_index(l, f[0], wp.vec3i(f[1], f[2], f[3]))
                if other >= 0:
                    mo = material[other]
                    if mo >= 0 and mo != m:
                        s = 0
    out[p] = s


def coarse_labels(lattice: Lattice, labels: wp.array, lms: list, device, threads) -> wp.array:
    """Labels for the graded interior's classification: the lattice points' labels, with the
    inside points next to a lattice point of another material set to 0 (not ``+``)."""
    n = labels.shape[0]
    inside = wp.empty(n, dtype=wp.int32, device=device)
    launch(flag_inside_kernel, n, [labels], [inside], device, threads)
    idx = compact(inside, device, threads)
    positions = wp.empty(idx.shape[0], dtype=wp.vec3, device=device)
    launch(gather_points_kernel, idx.shape[0], [lattice, idx], [positions], device, threads)
    material = np.full(n, -1, dtype=np.int32)
    if idx.shape[0]:
        material[idx.numpy()] = label(lms, positions, threads)
    out = wp.empty(n, dtype=wp.int32, device=device)
    launch(mark_interface_points_kernel, n, [lattice, labels, wp.array(material, dtype=wp.int32, device=device)],
           [out], device, threads)  # fmt: skip
    return out


@wp.kernel(enable_backward=False)
def flag_inside_kernel(labels: wp.array(dtype=wp.int32), offset: int, flags: wp.array(dtype=wp.int32)):
    p = wp.tid() + offset
    flags[p] = wp.where(labels[p] == 1, 1, 0)


def _priority(ids: np.ndarray) -> np.ndarray:
    """A fixed pseudo-random order of node ids (a 32-bit integer hash): deterministic, no seed."""
    x = ids.astype(np.uint64) * np.uint64(2654435761) % np.uint64(1 << 32)
    x ^= x >> np.uint64(16)
    x = x * np.uint64(2246822519) % np.uint64(1 << 32)
    return (x << np.uint64(32)) | ids.astype(np.uint64)  # ties impossible: the id breaks them


def _independent_sets(n: int, movable: np.ndarray, pa: np.ndarray, pb: np.ndarray) -> list[np.ndarray]:
    """The ``movable`` nodes split into sets of which no two nodes are neighbours (``pa[i]``, ``pb[i]``).

    Luby style with a fixed order: each round takes every node left that
    outranks (:func:`_priority`) all its neighbours still left. Neighbour
    lists are sorted once; each round is one masked segment maximum."""
    key = np.unique(np.minimum(pa, pb).astype(np.int64) * n + np.maximum(pa, pb))  # each pair once
    lo, hi = key // n, key % n
    src = np.concatenate([lo, hi])
    dst = np.concatenate([hi, lo])
    order = np.argsort(src, kind="stable")
    src, dst = src[order], dst[order]
    rank = _priority(np.arange(n))
    heads = np.flatnonzero(np.append(True, src[1:] != src[:-1])) if len(src) else np.zeros(0, np.int64)
    owners = src[heads]
    left = np.zeros(n, dtype=bool)
    left[movable] = True
    sets = []
    while left.any():
        best = np.zeros(n, dtype=np.uint64)
        if len(src):
            best[owners] = np.maximum.reduceat(np.where(left[dst], rank[dst], np.uint64(0)), heads)
        chosen = np.flatnonzero(left & (rank > best))
        sets.append(chosen)
        left[chosen] = False
    return sets


def snap(nodes: np.ndarray, tets: np.ndarray, ids: np.ndarray, lms: list, h: float, fixed: np.ndarray, threads,
         faces=None, pair=None, device=None):  # fmt: skip
    """Move interface nodes towards their interface under the quality guard (module docstring).

    The movable nodes are processed in independent sets (no two in one tet,
    :func:`_independent_sets`, computed once), so each move is judged exactly
    against its own tets: a :func:`guard_moves_kernel` launch per set tries the
    whole move, then half and a quarter of it for the nodes that failed, and
    each node takes the largest that keeps every one of its tets within the
    bounds. :data:`_SWEEPS` sweeps over all sets, each projecting the nodes
    afresh.

    Args:
        nodes: (N, 3) float32 positions. tets: (T, 4) int. ids: (T,) materials.
        lms: the materials' linear models. h: cell size. fixed: (N,) bool
            nodes that must not move (the domain's boundary). faces, pair:
            :func:`interface_faces` when known.

    Returns:
        ``(nodes, info)``: new (N, 3) float32 positions and counts
        ``interface_nodes``, ``snap_candidates``, ``snapped_nodes``.
    """
    if faces is None:
        faces, pair, _ = interface_faces(tets, ids)
    n = len(nodes)
    lo, hi, on = node_targets(n, faces, pair)
    movable = np.flatnonzero(on & ~fixed)
    info = {"interface_nodes": int(on.sum()), "snap_candidates": len(movable), "snapped_nodes": 0}
    if not len(movable):
        return nodes, info
    dev = wp.get_device(device)
    mask = np.zeros(n, dtype=bool)
    mask[movable] = True
    around = np.flatnonzero(mask[tets].any(axis=1))  # every tet a move can change
    local = tets[around]
    wp_tets = wp.array(local.astype(np.int32), dtype=wp.vec4i, device=dev)
    old_min = wp.empty(len(local), dtype=wp.float64, device=dev)
    old_max = wp.empty(len(local), dtype=wp.float64, device=dev)
    launch(measure_angles_kernel, len(local), [wp.array(nodes, dtype=wp.vec3, device=dev), wp_tets], [old_min, old_max], dev,
           threads)  # fmt: skip
    floor_t = wp.array(np.minimum(SNAP_MIN_DIHEDRAL, old_min.numpy()), dtype=wp.float64, device=dev)
    ceiling_t = wp.array(np.maximum(SNAP_MAX_DIHEDRAL, old_max.numpy()), dtype=wp.float64, device=dev)
    # incidences (node, local tet, corner) of the movable nodes, grouped by node
    corner = np.nonzero(mask[local])
    inc_node = local[corner]
    order = np.argsort(inc_node, kind="stable")
    inc_node, inc_tet, inc_corner = inc_node[order], corner[0][order], corner[1][order]
    first = np.searchsorted(inc_node, movable)
    # neighbour pairs: movable nodes sharing a tet
    a_idx, b_idx = np.triu_indices(4, 1)
    pa, pb = local[:, a_idx].reshape(-1), local[:, b_idx].reshape(-1)
    both = mask[pa] & mask[pb]
    sets = _independent_sets(n, movable, pa[both], pb[both])
    # per set: the rows of its nodes' incidences and the owning node's place in the set
    stops = np.append(first[1:], len(inc_node))
    plans = []
    for chosen in sets:
        k = np.searchsorted(movable, chosen)
        counts = stops[k] - first[k]
        rows = np.repeat(first[k] - np.cumsum(np.append(0, counts[:-1])), counts) + np.arange(counts.sum())
        plans.append((chosen, rows, np.repeat(np.arange(len(chosen)), counts)))
    current = nodes.astype(np.float32).copy()
    moved = np.zeros(n, dtype=bool)
    for _ in range(_SWEEPS):
        goal = _goals(current, movable, lo, hi, lms, h, threads, dev)
        # the whole displacement from the stuffed position stays within one cell
        d = goal - nodes
        dl = np.linalg.norm(d, axis=1)
        goal = nodes + d * np.minimum(1.0, h / np.maximum(dl, 1e-300))[:, None]
        for chosen, rows, owner in plans:
            # the whole move first, then half, then a quarter for the nodes whose move failed
            pending = np.any(goal[chosen] != current[chosen], axis=1)
            if not pending.any():
                continue
            wp_current = wp.array(current, dtype=wp.vec3, device=dev)
            for f in _FRACTIONS:
                sel = pending[owner]
                r, o = rows[sel], owner[sel]
                if not len(r):
                    break
                cand = current[chosen[o]] + f * (goal[chosen[o]] - current[chosen[o]])
                ok = wp.empty(len(r), dtype=wp.int32, device=dev)
                launch(guard_moves_kernel, len(r),
                       [wp_current, wp_tets, wp.array(inc_tet[r].astype(np.int32), dtype=wp.int32, device=dev),
                        wp.array(inc_corner[r].astype(np.int32), dtype=wp.int32, device=dev),
                        wp.array(cand.astype(np.float32), dtype=wp.vec3, device=dev), floor_t, ceiling_t],
                       [ok], dev, threads, min_chunk=8192)  # fmt: skip
                bad = np.bincount(o, weights=1 - ok.numpy(), minlength=len(chosen))
                take = pending & (bad == 0)
                v = chosen[take]
                current[v] = (current[v] + f * (goal[v] - current[v])).astype(np.float32)
                moved[v] = True
                pending &= ~take
    info["snapped_nodes"] = int(np.count_nonzero(moved))
    return current, info
