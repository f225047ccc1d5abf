"""The generated cut tables, walked exhaustively: every code, every global node order, random and degenerate tets.

The walk checks the generator's own output (``_build``, not a cached file); the cache is checked apart: the
tables :func:`cut_tables` reads from it are those the generator makes, and a damaged file is built anew."""

import itertools
from collections import Counter, defaultdict
from dataclasses import fields

import numpy as np
import pytest

from warpblob.cut import _tables, cut_tables, rank_index
from warpblob.cut._tables import RANK_PERMUTATIONS, REF_CELL, REF_FACE, REF_NODE, REF_SPLIT
from warpblob.mesh._tetmesh import TET_EDGES, TET_FACES

SNAP = 0.2
TABLES = _tables._build()
ENTRIES = [(int(TABLES.edge_code[e]), int(TABLES.node_code[e]), e) for e in range(len(TABLES.kind))]
EDGE_OF = {frozenset(map(int, e)): j for j, e in enumerate(TET_EDGES)}


def _parents():
    """Parent tets (positive): regular, random, a needle and a near-flat sliver."""
    rng = np.random.default_rng(7)
    tets = [np.array([[1, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]], float)]
    while len(tets) < 4:
        p = rng.normal(size=(4, 3))
        if np.linalg.det(p[1:] - p[0]) > 0.05:
            tets.append(p)
    tets.append(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 50.0]]))  # needle
    tets.append(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 1e-4]]))  # sliver
    return tets


def _positions(ref: int, corners: np.ndarray, t: np.ndarray) -> np.ndarray:
    if ref < REF_SPLIT or REF_NODE <= ref < REF_FACE:
        return corners[ref if ref < REF_SPLIT else (ref - REF_NODE) // 2]
    if ref < REF_NODE:
        u, v = TET_EDGES[(ref - REF_SPLIT) // 2]
        j = (ref - REF_SPLIT) // 2
        return corners[u] + t[j] * (corners[v] - corners[u])
    if ref < REF_CELL:
        return corners[TET_FACES[ref - REF_FACE]].mean(axis=0)
    return corners.mean(axis=0)


def _point(ref: int) -> tuple:
    """The geometric point a reference names (copies of one point are one point)."""
    if ref < REF_SPLIT:
        return ("v", ref)
    if ref < REF_NODE:
        return ("s", (ref - REF_SPLIT) // 2)
    if ref < REF_FACE:
        return ("v", (ref - REF_NODE) // 2)
    return ("f", ref - REF_FACE) if ref < REF_CELL else ("m",)


def _on_face(point: tuple, f: int) -> bool:
    nodes = set(map(int, TET_FACES[f]))
    if point[0] == "v":
        return point[1] in nodes
    if point[0] == "s":
        return set(map(int, TET_EDGES[point[1]])) <= nodes
    return point == ("f", f)


def _expected_surface(edge_code: int, node_code: int, kind: str) -> set:
    """The cut surface as geometric triangles, from the codes alone (independently of the generator)."""
    cut = [j for j in range(6) if edge_code >> j & 1]
    nodes = [k for k in range(4) if node_code >> k & 1]
    segments = []
    for f in range(4):
        fn = set(map(int, TET_FACES[f]))
        marks = [("s", j) for j in cut if set(map(int, TET_EDGES[j])) <= fn] + [("v", k) for k in nodes if k in fn]
        if any(m[0] == "s" for m in marks) and len(marks) == 2:
            segments.append(tuple(marks))
        elif len(marks) == 1 and marks[0][0] == "s":
            segments.append((marks[0], ("f", f)))
    if kind in ("C", "D", "E", "Xp"):
        return {frozenset({("m",), *s}) for s in segments}
    return set()  # complete: checked as "every separated face lies on the cut" below


def _components(tets: np.ndarray) -> int:
    """Connected pieces of a set of sub-tets joined through shared (topologically equal) faces."""
    parent = list(range(len(tets)))

    def root(i):
        while parent[i] != i:
            i = parent[i]
        return i

    owner = {}
    for i, t in enumerate(tets):
        for face in itertools.combinations(sorted(t.tolist()), 3):
            if face in owner:
                parent[root(i)] = root(owner[face])
            owner[face] = i
    return len({root(i) for i in range(len(tets))})


def _side(ref: int, corner_side: np.ndarray) -> int:
    if ref < REF_SPLIT:
        return int(corner_side[ref])
    if ref < REF_NODE:
        j, e = divmod(ref - REF_SPLIT, 2)
        return int(corner_side[TET_EDGES[j][e]])
    assert ref < REF_FACE, "a complete entry names a progressive point"
    return (ref - REF_NODE) % 2


def _plane_codes() -> set:
    """Every (edge_code, node_code) that a plane section, or a blade stopped inside, can give."""
    codes = {(0, n) for n in range(16)}  # cut nodes alone: the sweep only touches the tet
    for signs in itertools.product((-1, 0, 1), repeat=4):
        nodes = sum(1 << k for k in range(4) if signs[k] == 0)
        full = [j for j, (u, v) in enumerate(TET_EDGES) if signs[u] * signs[v] < 0]
        for r in range(len(full) + 1):
            for sub in itertools.combinations(full, r):
                codes.add((sum(1 << j for j in sub), nodes))
    return codes


def test_cut_tables_cover_exactly_the_codes_that_can_occur():
    possible = _plane_codes()
    for edge_code, node_code in itertools.product(range(64), range(16)):
        assert (TABLES.entry[edge_code, node_code] >= 0) == ((edge_code, node_code) in possible), (edge_code, node_code)
    incident = [
        (e, n)
        for e, n in itertools.product(range(64), range(16))
        if any(e >> j & 1 and (n >> int(TET_EDGES[j][0]) & 1 or n >> int(TET_EDGES[j][1]) & 1) for j in range(6))
    ]
    assert all(TABLES.entry[e, n] < 0 for e, n in incident)
    assert Counter(TABLES.kind.tolist()) == {
        "uncut": 1, "C": 6, "D": 15, "E": 12, "A": 4, "B": 3,
        "touch": 11, "X": 12, "Xp": 12, "Y": 6, "Z": 4,
    }  # fmt: skip


def test_cut_tables_counts_match_the_thesis():
    want = {"A": 4, "B": 6, "X": 3, "Y": 2, "Z": 1, "touch": 1, "uncut": 1}
    for edge_code, node_code, e in ENTRIES:
        kind = str(TABLES.kind[e])
        if kind in want:
            assert (TABLES.count[e] == want[kind]).all(), (kind, edge_code, node_code)


@pytest.mark.parametrize("parent", range(len(_parents())))
def test_cut_tables_tile_separate_and_never_invert(parent):
    corners = _parents()[parent]
    rng = np.random.default_rng(parent)
    volume = np.linalg.det(corners[1:] - corners[0]) / 6
    for edge_code, node_code, e in ENTRIES:
        kind = str(TABLES.kind[e])
        surface = _expected_surface(edge_code, node_code, kind)
        for p in range(24):
            tets = TABLES.subtets(edge_code, node_code, p)
            for t in (rng.uniform(SNAP, 1 - SNAP, 6), np.full(6, SNAP), np.full(6, 1 - SNAP)):
                pts = np.array([[_positions(int(r), corners, t) for r in tet] for tet in tets])
                vols = np.linalg.det(pts[:, 1:] - pts[:, :1]) / 6
                assert (vols > 1e-9 * volume).all(), (kind, edge_code, node_code, p, vols)
                assert np.isclose(vols.sum(), volume, rtol=1e-9, atol=0), (kind, edge_code, node_code, p)
            # the sub-tets form a simplicial complex whose boundary is the parent's
            faces = defaultdict(list)
            for tet in tets:
                for face in itertools.combinations(tet.tolist(), 3):
                    faces[frozenset(_point(r) for r in face)].append(frozenset(face))
            separated = set()
            for geo, topo in faces.items():
                assert len(geo) == 3 and len(topo) <= 2, (kind, p, geo)
                if len(topo) == 1:
                    assert any(all(_on_face(q, f) for q in geo) for f in range(4)), (kind, p, geo)
                elif topo[0] != topo[1]:
                    separated.add(geo)
            if kind in ("A", "B", "X", "Y"):
                assert separated and all(q[0] == "s" or q[0] == "v" and node_code >> q[1] & 1 for g in separated
                                         for q in g), (kind, p)  # fmt: skip
                assert _components(tets) == 2
                for tet in tets:
                    assert len({_side(int(r), TABLES.corner_side[e]) for r in tet}) == 1, (kind, p, tet)
            else:
                assert separated == surface, (kind, edge_code, node_code, p)
                assert _components(tets) == 1
                for tet in tets:
                    # never both copies of one split point, nor two groups of one cut node, in one sub-tet
                    assert len({_point(int(r)) for r in tet}) == 4, (kind, p, tet)


def _face_local(ref: int, order: dict):
    """A boundary reference in the face's own terms: its nodes by their rank among the face's three."""
    if ref < REF_SPLIT or REF_NODE <= ref < REF_FACE:
        return ("v", order[ref if ref < REF_SPLIT else (ref - REF_NODE) // 2])
    if ref < REF_NODE:
        j, e = divmod(ref - REF_SPLIT, 2)
        return ("s", frozenset(order[int(k)] for k in TET_EDGES[j]), order[int(TET_EDGES[j][e])])
    return ("f",)


def test_cut_tables_neighbours_conform():
    """Any two tets sharing a face with the same face code triangulate it identically.

    A face's triangulation is keyed by what both tets see of it: its cut edges, its cut nodes and the order of
    its three global ids. Every entry, every global order and every one of its four faces is collected under
    that key, so every pair of tets that can meet on a face, in any local orientation, is compared.
    """
    seen = {}
    for edge_code, node_code, e in ENTRIES:
        for p in range(24):
            rank = RANK_PERMUTATIONS[p]
            tets = TABLES.subtets(edge_code, node_code, p)
            for f in range(4):
                nodes = [int(k) for k in TET_FACES[f]]
                order = {k: i for i, k in enumerate(sorted(nodes, key=lambda k: rank[k]))}
                key = (
                    frozenset(frozenset(order[int(k)] for k in TET_EDGES[j]) for j in range(6)
                              if edge_code >> j & 1 and set(map(int, TET_EDGES[j])) <= set(nodes)),
                    frozenset(order[k] for k in nodes if node_code >> k & 1),
                )  # fmt: skip
                tris = frozenset(
                    frozenset(_face_local(int(r), order) for r in face)
                    for tet in tets
                    for face in itertools.combinations(tet.tolist(), 3)
                    if all(_on_face(_point(r), f) for r in face)
                )
                assert seen.setdefault(key, tris) == tris, (str(TABLES.kind[e]), edge_code, node_code, p, f)
    assert len(seen) > 10


def test_cut_tables_progressive_cuts_complete():
    """Every progressive state has a complete state reachable by cutting more edges (a later stroke)."""
    complete = [(ec, nc) for ec, nc, e in ENTRIES if str(TABLES.kind[e]) in ("A", "B", "X", "Y")]
    for edge_code, node_code, e in ENTRIES:
        if str(TABLES.kind[e]) in ("C", "D", "E", "Xp"):
            assert any(nc == node_code and ec & edge_code == edge_code and ec != edge_code for ec, nc in complete)


def test_rank_index_matches_permutations():
    rng = np.random.default_rng(0)
    ids = np.array([rng.choice(1000, 4, replace=False) for _ in range(200)])
    ranks = RANK_PERMUTATIONS[rank_index(ids)]
    assert (np.argsort(np.argsort(ids, axis=1), axis=1) == ranks).all()
    assert sorted(set(rank_index(np.array(list(itertools.permutations(range(4))))).tolist())) == list(range(24))


def test_cut_tables_unknown_code_is_refused():
    with pytest.raises(ValueError, match="cannot occur"):
        TABLES.subtets(0b000001, 0b0001)


def _same_tables(a, b) -> None:
    for f in fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        assert x.dtype == y.dtype and np.array_equal(x, y), f.name


def test_cached_tables_are_the_generated_ones(tmp_path, monkeypatch):
    """A first use writes the cache file, a later one reads it: both the generator's tables, field by field
    and dtype by dtype; a damaged file is built anew and rewritten; an unwritable folder only skips the file."""
    _same_tables(cut_tables(), TABLES)
    path = tmp_path / "tables.npz"
    monkeypatch.setattr(_tables, "_cache_file", lambda: path)
    built = []

    def build():
        built.append(1)
        return _tables._build()

    _same_tables(_tables._cached(build), TABLES)  # no file: built, written
    assert path.is_file() and len(built) == 1
    _same_tables(_tables._cached(build), TABLES)  # read back, not built
    assert len(built) == 1
    path.write_bytes(b"not a table file")
    _same_tables(_tables._cached(build), TABLES)  # damaged: built, rewritten
    assert len(built) == 2
    _same_tables(_tables._cached(build), TABLES)
    assert len(built) == 2
    blocked = tmp_path / "file" / "tables.npz"
    (tmp_path / "file").write_text("a file where the folder would be")
    monkeypatch.setattr(_tables, "_cache_file", lambda: blocked)
    _same_tables(_tables._cached(build), TABLES)
    assert len(built) == 3 and list(tmp_path.glob("*.tmp")) == []
