"""The stencil table of isosurface stuffing, generated from the BCC lattice geometry.

Labelle & Shewchuk (2007) fill each tetrahedron of the body-centred cubic
(BCC) lattice with a fixed *stencil* chosen by the signs of its four vertices
(``+`` inside, ``-`` outside, ``0`` on the surface) after warping. The paper
draws the stencils; here they are derived, not typed in: for every
lattice tetrahedron type and sign pattern the part inside the surface is a
tetrahedron, a pyramid or a triangular prism whose faces on the lattice
tetrahedron's faces are fixed (quadrilaterals split by the rule below, so
that the two tetrahedra sharing a face agree) and whose surface face is free;
the smallest set of tetrahedra whose boundary is exactly that (found by
enumeration) is the stencil.

Quadrilateral faces (two inside lattice vertices ``P``, ``Q``, the outside
vertex ``N``, cut points ``cP`` on ``PN`` and ``cQ`` on ``QN``) are split by
the paper's rules: when a cut point lies on a long (axis-parallel) edge the
diagonal joins it to the other lattice vertex; when ``PQ`` is the long edge,
the *parity rule* picks the diagonal from the parity of the long edge's grid
(cube corners or cube centres) and of its orientation relative to ``N``, so
that neighbouring tetrahedra agree and every prism can be split without a
Steiner point.

Lattice coordinates here are in half cells: cube corners (black points) have
even coordinates, cube centres (red points) odd ones. The 12 tetrahedron types
are those owned by one cube: for each axis ``a`` the red long edge from the
cube's centre to the next centre along ``+a``, with one of the four black
edges of the square face the two cubes share.
"""

from __future__ import annotations

import functools
import itertools

import numpy as np

from ..mesh._tetmesh import TET_EDGES, TET_FACES

__all__ = [
    "EDGES",
    "MAX_STENCIL",
    "PATTERNS",
    "TET_TYPES",
    "build_stencils",
    "edge_table",
    "pattern_labels",
    "ref_positions",
    "stencil",
    "tet_types",
    "vertex_table",
]

EDGES = tuple(tuple(int(v) for v in e) for e in TET_EDGES)
"""Local edges of a tetrahedron (warpblob's :data:`~warpblob.mesh._tetmesh.TET_EDGES`);
stencil reference ``4 + e`` is the cut point on edge ``e``."""
PATTERNS = 81  # 3^4 sign patterns: digit v of the pattern is label(v) + 1
TET_TYPES = 12
MAX_STENCIL = 3

_OUTWARD_FACES = tuple(tuple(int(v) for v in f) for f in TET_FACES)  # of a positively oriented tetrahedron
_LONG = 4  # squared length of a long edge in half cells (a short edge has 3)


def _signed_volume(x0, x1, x2, x3) -> float:
    return float(np.dot(np.cross(x1 - x0, x2 - x0), x3 - x0)) / 6.0


@functools.cache
def tet_types() -> np.ndarray:
    """(12, 4, 3) int vertices of the lattice tetrahedra owned by the cube at the origin, half cells.

    Vertices 0 and 1 are the red long edge (cube centres), 2 and 3 the black
    one (cube corners); each tetrahedron is positively oriented.
    """
    square = ((0, 0), (2, 0), (2, 2), (0, 2))
    out = np.zeros((TET_TYPES, 4, 3), dtype=np.int64)
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        for e in range(4):
            c0 = np.array([1, 1, 1])
            c1 = c0.copy()
            c1[a] += 2
            p = np.zeros(3, dtype=np.int64)
            q = np.zeros(3, dtype=np.int64)
            p[a] = q[a] = 2
            p[b], p[c] = square[e]
            q[b], q[c] = square[(e + 1) % 4]
            if _signed_volume(c0, c1, p, q) < 0:
                p, q = q, p
            out[4 * a + e] = (c0, c1, p, q)
    return out


def pattern_labels(pattern: int) -> tuple[int, int, int, int]:
    """The four vertex labels (-1 outside, 0 on the surface, +1 inside) of a pattern index."""
    return tuple((pattern // 3**v) % 3 - 1 for v in range(4))


def _edge_index(u: int, v: int) -> int:
    return EDGES.index((min(u, v), max(u, v)))


def _cut(u: int, v: int) -> int:
    return 4 + _edge_index(u, v)


def _quad_diagonal(x: np.ndarray, p: int, q: int, n: int) -> tuple[int, int]:
    """The diagonal (lattice vertex, cut point) of the quadrilateral P, Q, cQ, cP on face PQN."""
    if int(np.sum((x[p] - x[n]) ** 2)) == _LONG:
        return q, _cut(p, n)
    if int(np.sum((x[q] - x[n]) ** 2)) == _LONG:
        return p, _cut(q, n)
    # parity rule: PQ is the long edge, along axis k
    k = int(np.nonzero(x[p] != x[q])[0][0])
    count = int(x[p][k] > x[q][k]) + sum(int(x[n][j] < x[q][j]) for j in range(3) if j != k)
    black = int(x[p][0] % 2 == 0)
    if (black + count) % 2 == 0:
        return p, _cut(q, n)
    return q, _cut(p, n)


def _face_pieces(x: np.ndarray, labels) -> list[tuple[int, int, int]]:
    """Outward triangles of the inside part of the tetrahedron's four faces."""
    pieces = []
    for face in _OUTWARD_FACES:
        poly = []
        for s in range(3):
            u, v = face[s], face[(s + 1) % 3]
            if labels[u] >= 0:
                poly.append(u)
            if labels[u] * labels[v] < 0:
                poly.append(_cut(u, v))
        if len(poly) == 3:
            pieces.append(tuple(poly))
        elif len(poly) == 4:
            p, q = (r for r in poly if r < 4)
            n = next(v for v in face if labels[v] < 0)
            i = poly.index(_quad_diagonal(x, p, q, n)[0])
            pieces.append((poly[i], poly[(i + 1) % 4], poly[(i + 2) % 4]))
            pieces.append((poly[i], poly[(i + 2) % 4], poly[(i + 3) % 4]))
    return pieces


def _oriented(tri) -> tuple[tuple[int, ...], int]:
    """(sorted vertices, +1 or -1): a triangle as a key and its orientation parity."""
    order = sorted(range(3), key=lambda i: tri[i])
    sign = 1 if order in ([0, 1, 2], [1, 2, 0], [2, 0, 1]) else -1
    return tuple(tri[i] for i in order), sign


def ref_positions(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(10, 3) positions of the stencil references: the 4 vertices, then a cut at ``t[e]`` along each edge."""
    x = np.asarray(x, dtype=np.float64)
    cuts = [x[u] + t[e] * (x[v] - x[u]) for e, (u, v) in enumerate(EDGES)]
    return np.vstack([x, np.array(cuts)])


def stencil(x: np.ndarray, labels) -> list[tuple[int, int, int, int]]:
    """The stencil of one lattice tetrahedron ``x`` (4, 3) for vertex ``labels``.

    Returns positively oriented tetrahedra over references 0-3 (vertices) and
    4-9 (cut points on :data:`EDGES`); empty when no vertex is inside.
    """
    labels = tuple(int(v) for v in labels)
    if max(labels) < 1:
        return []
    if min(labels) > -1:
        return [(0, 1, 2, 3)]
    refs = [v for v in range(4) if labels[v] >= 0]
    refs += [4 + e for e, (u, v) in enumerate(EDGES) if labels[u] * labels[v] < 0]
    surface = {r for r in refs if r >= 4 or labels[r] == 0}
    pos = ref_positions(x, np.full(6, 0.5))
    candidates = []
    for quad in itertools.combinations(refs, 4):
        vol = _signed_volume(*pos[list(quad)])
        if abs(vol) > 1e-9:
            candidates.append(quad if vol > 0 else (quad[1], quad[0], quad[2], quad[3]))
    target = {}
    for tri in _face_pieces(x, labels):
        key, sign = _oriented(tri)
        target[key] = sign
    for k in range(1, MAX_STENCIL + 1):
        found = []
        for combo in itertools.combinations(candidates, k):
            chain: dict = {}
            for tet in combo:
                for face in _OUTWARD_FACES:
                    key, sign = _oriented(tuple(tet[i] for i in face))
                    chain[key] = chain.get(key, 0) + sign
            chain = {key: s for key, s in chain.items() if s != 0}
            if any(chain.get(key) != s for key, s in target.items()):
                continue
            rest = [key for key in chain if key not in target]
            if len(rest) == len(surface) - 2 and all(abs(chain[key]) == 1 and set(key) <= surface for key in rest):
                found.append(combo)
        if found:
            if len(found) != 1:
                raise AssertionError(f"stencil for labels {labels} is not unique: {found}")
            return list(found[0])
    raise AssertionError(f"no stencil of at most {MAX_STENCIL} tetrahedra for labels {labels}")


@functools.cache
def build_stencils() -> tuple[np.ndarray, np.ndarray]:
    """``(counts (12, 81) int32, refs (12, 81, 3, 4) int32)``: the stencil of every type and pattern."""
    counts = np.zeros((TET_TYPES, PATTERNS), dtype=np.int32)
    refs = np.zeros((TET_TYPES, PATTERNS, MAX_STENCIL, 4), dtype=np.int32)
    for t, x in enumerate(tet_types()):
        for pattern in range(PATTERNS):
            tets = stencil(x, pattern_labels(pattern))
            counts[t, pattern] = len(tets)
            for i, tet in enumerate(tets):
                refs[t, pattern, i] = tet
    return counts, refs


def vertex_table() -> np.ndarray:
    """(12, 4, 4) int32 ``(is_red, dx, dy, dz)`` of each type's vertices, relative to the owning cube.

    A black vertex is the cube corner ``(i+dx, j+dy, k+dz)``, a red one the
    centre of cube ``(i+dx, j+dy, k+dz)``.
    """
    x = tet_types()
    is_red = x[:, :, :1] % 2
    return np.concatenate([is_red, (x - is_red) // 2], axis=2).astype(np.int32)


def edge_table() -> tuple[np.ndarray, np.ndarray]:
    """Owner and slot of each type's six edges: ``(owners (12, 6, 4) int32, slots (12, 6) int32)``.

    Every lattice edge is owned by one lattice point: a long edge by its end
    with the smaller coordinate (slot = axis 0-2), a short edge by its red end
    (slot ``3 + dx + 2 dy + 4 dz`` for the corner ``(dx, dy, dz)`` of the cube).
    Owners are ``(is_red, dx, dy, dz)`` like :func:`vertex_table`.
    """
    x = tet_types()
    vt = vertex_table()
    owners = np.zeros((TET_TYPES, 6, 4), dtype=np.int32)
    slots = np.zeros((TET_TYPES, 6), dtype=np.int32)
    for t in range(TET_TYPES):
        for e, (u, v) in enumerate(EDGES):
            d = x[t, v] - x[t, u]
            if int(np.sum(d * d)) == _LONG:
                axis = int(np.nonzero(d)[0][0])
                owner = u if d[axis] > 0 else v
                owners[t, e], slots[t, e] = vt[t, owner], axis
            else:
                red, black = (u, v) if x[t, u, 0] % 2 else (v, u)
                corner = (x[t, black] - (x[t, red] - 1)) // 2
                owners[t, e] = vt[t, red]
                slots[t, e] = 3 + int(corner[0] + 2 * corner[1] + 4 * corner[2])
    return owners, slots
