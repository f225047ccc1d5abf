"""Cell tables for marching cubes with consistent, face-resolved topology.

Instead of Lorensen & Cline's hand-written 256-case table (whose complementary
cases resolve ambiguous faces inconsistently and leave cracks), the table is
generated: for every corner configuration and every resolution of the
ambiguous faces, the crossings on each cube face are joined into segments,
the segments are chained into closed loops and the loops are oriented so that
their normals point out of the solid. An ambiguous face (diagonal corners on
the same side) is resolved by the asymptotic decider (Nielson & Hamann 1991),
which depends only on the face's four values, so the two cells sharing a face
always agree and the surface is crack-free and 2-manifold; interior
ambiguities need no decision because loops only come from faces. The kernel
triangulates each loop at run time, choosing the fan that maximizes the
smallest angle.

Conventions: corner ``c = i + 2 j + 4 k`` sits at ``(i, j, k)``; edge
``e = 4 * axis + n`` runs from its lower corner :data:`EDGE_ORIGIN[e]` along
``axis``; ``inside`` is ``F >= iso``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["EDGE_CORNERS", "EDGE_AXIS", "EDGE_ORIGIN", "FACES", "build_loop_table", "MAX_LOOPS", "ENTRY", "APEX"]

CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


def _edges():
    edges = []
    for axis in range(3):
        for c in range(8):
            if CORNERS[c][axis] == 0:
                edges.append((c, c | (1 << axis)))
    return edges


EDGE_CORNERS = np.array(_edges())  # (12, 2)
EDGE_AXIS = np.repeat(np.arange(3), 4)
EDGE_ORIGIN = CORNERS[EDGE_CORNERS[:, 0]]  # (12, 3)
_EDGE_OF = {tuple(sorted(map(int, e))): k for k, e in enumerate(EDGE_CORNERS)}

# faces: (axis, side) -> corners in cyclic order; the outward normal is +/- axis
FACES = []
for _axis in range(3):
    for _side in range(2):
        _u, _v = [a for a in range(3) if a != _axis]
        cyc = []
        for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
            p = [0, 0, 0]
            p[_axis], p[_u], p[_v] = _side, du, dv
            cyc.append(p[0] + 2 * p[1] + 4 * p[2])
        FACES.append((_axis, _side, cyc))

MAX_LOOPS = 4
#: one table entry: total loop vertices, loop count, MAX_LOOPS lengths, 12 edge
#: ids, then per loop the bit mask of the loop positions that may be a fan apex
ENTRY = 2 + MAX_LOOPS + 12 + MAX_LOOPS
APEX = 2 + MAX_LOOPS + 12


def _face_segments(face, inside, joined):
    """Oriented segments (edge_from, edge_to) of one face."""
    axis, side, cyc = face
    normal = np.zeros(3)
    normal[axis] = 1.0 if side else -1.0
    crossed = []
    for n in range(4):
        a, b = cyc[n], cyc[(n + 1) % 4]
        if inside[a] != inside[b]:
            crossed.append(n)
    if not crossed:
        return []
    pairs = []
    if len(crossed) == 2:
        pairs.append(tuple(crossed))
    else:
        # ambiguous: corner n sits between face edges n-1 and n; cut off the
        # inside corners (separated) or the outside corners (joined)
        for n in range(4):
            corner_inside = inside[cyc[n]]
            if corner_inside != joined:
                pairs.append(((n - 1) % 4, n))
    segs = []
    for n1, n2 in pairs:
        e1 = _EDGE_OF[tuple(sorted((cyc[n1], cyc[(n1 + 1) % 4])))]
        e2 = _EDGE_OF[tuple(sorted((cyc[n2], cyc[(n2 + 1) % 4])))]
        p = 0.5 * (CORNERS[cyc[n1]] + CORNERS[cyc[(n1 + 1) % 4]])
        q = 0.5 * (CORNERS[cyc[n2]] + CORNERS[cyc[(n2 + 1) % 4]])
        # corners between the two face edges (walking n1+1 .. n2) are cut off
        cut = []
        k = (n1 + 1) % 4
        while True:
            cut.append(cyc[k])
            if k == n2:
                break
            k = (k + 1) % 4
        centroid = CORNERS[cut].mean(axis=0)
        mid = 0.5 * (p + q)
        out = (mid - centroid) if inside[cut[0]] else (centroid - mid)
        d = q - p
        if np.dot(np.cross(out, d), normal) < 0.0:
            segs.append((e1, e2))
        else:
            segs.append((e2, e1))
    return segs


def _ambiguous_faces(inside):
    amb = []
    for f, (_, _, cyc) in enumerate(FACES):
        s = [inside[c] for c in cyc]
        if s[0] == s[2] and s[1] == s[3] and s[0] != s[1]:
            amb.append(f)
    return amb


def build_loop_table() -> np.ndarray:
    """The (256 * 64, ENTRY) int32 table indexed by ``config * 64 + face_bits``.

    ``face_bits`` bit f is 1 when ambiguous face f joins its inside corners
    (its bilinear saddle is inside); bits of unambiguous faces are ignored
    (entries repeat for them).
    """
    table = np.zeros((256 * 64, ENTRY), dtype=np.int32)
    all_bits = np.arange(64)
    for config in range(256):
        inside = [(config >> c) & 1 == 1 for c in range(8)]
        amb = _ambiguous_faces(inside)
        amb_mask = sum(1 << f for f in amb)
        for sub in range(1 << len(amb)):
            bits = sum(1 << f for n, f in enumerate(amb) if (sub >> n) & 1)
            row = _loops_row(inside, bits)
            table[config * 64 + all_bits[(all_bits & amb_mask) == bits]] = row
    return table


def _loops_row(inside, bits):
    segs = []
    for f, face in enumerate(FACES):
        segs.extend(_face_segments(face, inside, (bits >> f) & 1 == 1))
    nxt = {}
    for a, b in segs:
        assert a not in nxt, "an edge starts two segments: inconsistent orientation"
        nxt[a] = b
    loops, seen = [], set()
    for start in sorted(nxt):
        if start in seen:
            continue
        loop, e = [], start
        while e not in seen:
            seen.add(e)
            loop.append(e)
            e = nxt[e]
        assert e == start, "segments do not close into loops"
        loops.append(loop)
    assert len(loops) <= MAX_LOOPS
    row = np.zeros(ENTRY, dtype=np.int32)
    row[0] = sum(len(lp) for lp in loops)
    row[1] = len(loops)
    row[2 : 2 + len(loops)] = [len(lp) for lp in loops]
    flat = [e for lp in loops for e in lp]
    row[2 + MAX_LOOPS : 2 + MAX_LOOPS + len(flat)] = flat
    row[APEX : APEX + len(loops)] = [_apex_mask(lp) for lp in loops]
    return row


_EDGE_FACES = [
    {f for f, (_, _, cyc) in enumerate(FACES) if int(a) in cyc and int(b) in cyc} for a, b in EDGE_CORNERS
]


def _apex_mask(loop) -> int:
    """Bit s set when the fan from loop position s has no diagonal inside a cube face."""
    n = len(loop)
    mask = 0
    for s in range(n):
        if all(not (_EDGE_FACES[loop[s]] & _EDGE_FACES[loop[(s + t) % n]]) for t in range(2, n - 1)):
            mask |= 1 << s
    return mask

