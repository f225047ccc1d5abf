"""Pinched boundaries of stuffed meshes: detection, local thickness, the cell size that resolves it.

A wall (or a gap) thinner than about a lattice cell is not resolved by
isosurface stuffing: lattice points of both sides warp onto the two surfaces,
the solid between them vanishes, and the boundary of the mesh touches itself
along lattice edges or at lattice points. The tets stay valid and conforming,
but the boundary is no longer a 2-manifold, which cutting, drilling and
surface extraction rely on. :func:`find_pinches` finds it:

* a **pinched edge** is an edge of more than two boundary faces;
* a **pinched vertex** is a boundary vertex whose boundary faces form more
  than one fan (faces joined across edges through the vertex that lie in
  exactly two boundary faces); the ends of pinched edges are among them.

Only tets with at least three surface nodes (cut points and lattice points on
the surface) can own a boundary face, so the faces are gathered from those
tets alone (one kernel and a compaction), then sorted in numpy: the work is
proportional to the surface, not the volume. Fans are the connected
components of face corners, by min-label propagation over the corner graph
(numpy, a few sweeps: fans are small).

:func:`thickness` estimates how thin the model is at the pinched spots: along
the field's gradient through each spot, the field is sampled on a fine
segment and the shortest run of inside (or outside) samples that meets the
spot is the local thickness ``t``. :data:`RESOLVING_FACTOR` turns the
thinnest ``t`` into the suggested cell size ``t / RESOLVING_FACTOR``.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from .._errors import MeshError
from .._parallel import launch
from .._stages import compact
from ..field import evaluate
from ..mesh._tetmesh import TET_FACES

__all__ = ["RESOLVING_FACTOR", "PinchedBoundaryError", "PinchedBoundaryWarning", "find_pinches", "thickness"]

#: suggested cell size = thinnest local thickness / RESOLVING_FACTOR (see ``docs/tetrahedralize.md``
#: for the sweep that sets it)
RESOLVING_FACTOR = 2.0
_PROBE_SAMPLES = 257  # samples along each probe segment
_PROBE_REACH = 3.0  # probe segment half length, in cell sizes


class PinchedBoundaryError(MeshError):
    """``strict=True`` and the mesh's boundary is pinched (a wall or gap thinner than the cells)."""


class PinchedBoundaryWarning(UserWarning):
    """The mesh's boundary is pinched: a wall or gap of the model is thinner than the cells."""


@wp.kernel(enable_backward=False)
def flag_surface_nodes_kernel(
    n_points: int,
    labels: wp.array(dtype=wp.int32),
    used: wp.array(dtype=wp.int32),
    node_ids: wp.array(dtype=wp.int32),
    offset: int,
    flags: wp.array(dtype=wp.int32),
):
    """1 for a node on the surface (a cut point, a warped point, a lattice point with F = iso)."""
    u = wp.tid() + offset
    if used[u] == 0:
        return
    on = int(1)
    if u < n_points and labels[u] != 0:
        on = 0
    flags[node_ids[u]] = on


@wp.kernel(enable_backward=False)
def flag_surface_tets_kernel(
    flags: wp.array(dtype=wp.int32), tets: wp.array(dtype=wp.vec4i), offset: int, out: wp.array(dtype=wp.int32)
):
    """1 for a tet with at least three surface nodes (the only tets that can own a boundary face)."""
    tid = wp.tid() + offset
    t = tets[tid]
    n = flags[t[0]] + flags[t[1]] + flags[t[2]] + flags[t[3]]
    out[tid] = wp.where(n >= 3, 1, 0)


def candidate_tets(flags: wp.array, tets: wp.array, device, threads) -> np.ndarray:
    """Indices (K,) int32 of the tets with at least three surface nodes (``flags`` per node)."""
    marks = wp.empty(tets.shape[0], dtype=wp.int32, device=device)
    launch(flag_surface_tets_kernel, tets.shape[0], [flags, tets], [marks], device, threads)
    return compact(marks, device, threads).numpy()


def groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of (n, k) non-negative int ``keys`` grouped: (order, group starts, group sizes) over ``keys[order]``."""
    keys = np.asarray(keys, dtype=np.int64)
    span = int(keys.max()) + 1 if keys.size else 1
    if span ** keys.shape[1] < (1 << 62):  # one int64 key per row: a single sort
        flat = np.zeros(len(keys), dtype=np.int64)
        for j in range(keys.shape[1]):
            flat = flat * span + keys[:, j]
        order = np.argsort(flat)
        s = flat[order]
        new = np.ones(len(s), dtype=bool)
        new[1:] = s[1:] != s[:-1]
    else:
        order = np.lexsort(keys.T[::-1])
        s = keys[order]
        new = np.ones(len(s), dtype=bool)
        new[1:] = (s[1:] != s[:-1]).any(axis=1)
    starts = np.flatnonzero(new)
    return order, starts, np.diff(np.append(starts, len(keys)))


def boundary_faces(tets: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """(F, 3) boundary faces, outward, among the faces of ``tets`` whose three nodes have ``flags`` set.

    ``tets`` must hold every tet that has a face with three flagged nodes (the
    faces are counted among them only)."""
    faces = tets[:, TET_FACES].reshape(-1, 3)
    keep = flags[faces[:, 0]] & flags[faces[:, 1]] & flags[faces[:, 2]]  # (three gathers: 2x faster than .all)
    faces = faces[keep]
    if not len(faces):
        return np.zeros((0, 3), dtype=np.int64)
    # each face's nodes in ascending order, by minimum, maximum and the rest (a row sort costs 3x that)
    a, b, c = (faces[:, k].astype(np.int64) for k in range(3))
    lo, hi = np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)
    order, starts, sizes = groups(np.stack([lo, a + b + c - lo - hi, hi], axis=1))
    return faces[order[starts[sizes == 1]]]


def find_pinches(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinched edges and vertices of a consistently oriented closed boundary given by its (F, 3) ``faces``.

    Fans: around node ``a``, the corner of ``a`` in face ``f`` is followed by
    its corner in the face across ``f``'s edge from ``a`` to the next node
    (the twin half-edge), so the corners of one fan form a cycle; a pointer-
    doubling pass takes each corner's minimum over its cycle, and a node has as
    many fans as corners that are their cycle's minimum. Across an edge in more
    than two faces the corners have no successor (their chains end there), so
    the ends of pinched edges count as pinched vertices.

    Returns:
        ``(edges, vertices)``: (E, 2) sorted node pairs of the edges in more
        than two faces, and (V,) node ids of the vertices whose faces form
        more than one fan, both ascending.

    Example:
        >>> import numpy as np
        >>> from warpblob.tetrahedralize._pinch import find_pinches
        >>> # two tetrahedra's surfaces touching at node 0: one pinched vertex, no pinched edge
        >>> a = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        >>> b = np.where(a == 0, 0, a + 3)
        >>> edges, vertices = find_pinches(np.vstack([a, b]))
        >>> edges.shape, vertices.tolist()
        ((0, 2), [0])
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n_faces = len(faces)
    if not n_faces:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0, dtype=np.int64)
    # half-edge 3 f + k runs from faces[f, k] to faces[f, (k + 1) % 3]
    tail = faces.reshape(-1)
    head = np.roll(faces, -1, axis=1).reshape(-1)
    keys = np.stack([np.minimum(tail, head), np.maximum(tail, head)], axis=1)
    order, starts, sizes = groups(keys)
    pinched_edges = keys[order[starts[sizes > 2]]]
    corners = np.arange(3 * n_faces)
    nxt = corners.copy()
    two = starts[sizes == 2]
    h0, h1 = order[two], order[two + 1]  # twin half-edges (opposite directions on an oriented surface)
    # the corner of h's tail in the twin's face: the twin's head, position (k + 1) % 3 of its face
    nxt[h0] = 3 * (h1 // 3) + (h1 % 3 + 1) % 3
    nxt[h1] = 3 * (h0 // 3) + (h0 % 3 + 1) % 3
    label = corners.copy()
    longest = int(np.bincount(tail).max())  # no fan has more corners than its node
    for _ in range(max(1, int(np.ceil(np.log2(longest))) + 1)):
        label = np.minimum(label, label[nxt])
        nxt = nxt[nxt]
    fans = np.bincount(tail[label == corners], minlength=int(tail.max()) + 1)
    return pinched_edges, np.flatnonzero(fans > 1)


def thickness(model, points: np.ndarray, cellsize: float, *, device=None, threads=None) -> np.ndarray:
    """Local thickness (K,) float64 of the thin part at each of (K, 3) ``points``, model units.

    Along the field's gradient through each point, ``F`` is sampled at
    :data:`_PROBE_SAMPLES` points over ``+-3 cellsize``; the runs of samples on
    one side of the iso value are the inside and outside intervals, and the
    thickness is the length of the shortest complete run (both ends within the
    segment) that starts or ends within one cell size of the point. NaN where
    there is none (the part is thick there, or the gradient vanishes).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(pts), np.nan)
    if not len(pts):
        return out
    _, grads, _ = evaluate(model, pts.astype(np.float32), device=device, threads=threads)
    g = grads.astype(np.float64)
    norm = np.linalg.norm(g, axis=1)
    ok = norm > 0.0
    n = np.where(ok[:, None], g / np.where(ok, norm, 1.0)[:, None], 0.0)
    reach = _PROBE_REACH * cellsize
    s = np.linspace(-reach, reach, _PROBE_SAMPLES)
    step = s[1] - s[0]
    probe = pts[:, None, :] + s[None, :, None] * n[:, None, :]
    values, _, _ = evaluate(model, probe.reshape(-1, 3).astype(np.float32), device=device, derivatives=False,
                            threads=threads)  # fmt: skip
    inside = (values.reshape(len(pts), -1) >= 0.5).astype(np.int8)
    change = np.diff(inside, axis=1) != 0  # (K, S - 1): a crossing between samples j and j + 1
    for_each = np.arange(len(pts))
    # crossings as positions (midway between samples); runs between consecutive crossings
    rows, cols = np.nonzero(change)
    if not len(rows):
        return out
    pos = s[cols] + 0.5 * step
    same_row = rows[1:] == rows[:-1]
    lo, hi, r = pos[:-1][same_row], pos[1:][same_row], rows[:-1][same_row]
    near = (np.abs(lo) <= cellsize) | (np.abs(hi) <= cellsize) | ((lo < 0.0) & (hi > 0.0))
    length = np.where(near, hi - lo, np.inf)
    best = np.full(len(pts), np.inf)
    np.minimum.at(best, r, length)
    out[for_each] = np.where(np.isfinite(best) & ok, best, np.nan)
    return out
