"""The tetrahedral volume mesh type: nodes, positively oriented tets, materials.

A :class:`TetMesh` is what volume discretization produces (SPEC section 3),
what the edge-based structure (:mod:`warpblob.mesh._structure`, SPEC
section 4) is built from and what is written to USD as a ``UsdGeom.TetMesh``
(SPEC section 8). It is immutable: derived data (volumes, surface faces,
quality) is computed once and cached, and a changed mesh is a new object.

Local numbering, shared by every tet kernel in warpblob (it is USD's and
VTK's): a tet ``(p0, p1, p2, p3)`` is positive when
``det[p1 - p0, p2 - p0, p3 - p0] > 0``; face ``k`` (:data:`TET_FACES`) is the
one opposite node ``k``, listed counter-clockwise seen from outside; edge
``j`` (:data:`TET_EDGES`) is opposite edge ``5 - j``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from .._errors import WarpblobError
from ._surface import bounds_text

__all__ = ["TetMesh", "TET_FACES", "TET_EDGES"]

#: (4, 3) local node indices of face ``k``, the face opposite node ``k``, outward for a positive tet.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int32)
#: (6, 2) local node indices of edge ``j``; edge ``5 - j`` is the opposite edge.
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int32)

# the same tables as Warp constants, for kernels (one source of truth: the numpy tables above)
_local_edge = np.full((4, 4), -1, dtype=np.int32)
_local_edge[TET_EDGES[:, 0], TET_EDGES[:, 1]] = np.arange(6)
_local_edge[TET_EDGES[:, 1], TET_EDGES[:, 0]] = np.arange(6)
TET_FACES_WP = wp.constant(wp.types.matrix(shape=(4, 3), dtype=wp.int32)(*TET_FACES.ravel().tolist()))
TET_EDGES_WP = wp.constant(wp.types.matrix(shape=(6, 2), dtype=wp.int32)(*TET_EDGES.ravel().tolist()))
#: (4, 4) index into TET_EDGES of the edge joining two local nodes (-1 on the diagonal)
TET_LOCAL_EDGE_WP = wp.constant(wp.types.matrix(shape=(4, 4), dtype=wp.int32)(*_local_edge.ravel().tolist()))



def _frozen(arr: np.ndarray) -> np.ndarray:
    """A read-only view (the caller's own array stays writable)."""
    view = arr.view()
    view.flags.writeable = False
    return view


def _int_array(name: str, value, shape_text: str, ndim: int, width: int | None) -> np.ndarray:
    arr = np.asarray(value)
    if arr.ndim != ndim or (width is not None and arr.shape[1] != width):
        raise WarpblobError(f"TetMesh: {name} must have shape {shape_text}, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise WarpblobError(f"TetMesh: {name} must hold integers, got dtype {arr.dtype}")
    if arr.size and (arr.min() < np.iinfo(np.int32).min or arr.max() > np.iinfo(np.int32).max):
        raise WarpblobError(f"TetMesh: {name} must fit in int32, got values in [{arr.min()}, {arr.max()}]")
    return np.ascontiguousarray(arr, dtype=np.int32)


@dataclass(eq=False, frozen=True, repr=False)
class TetMesh:
    """A tetrahedral mesh: shared nodes and positively oriented tets.

    The mesh is immutable (its arrays are read-only views); derived data is
    cached on first use. Build a new mesh (``dataclasses.replace``) to change it.

    Attributes:
        nodes: (N, 3) float32 positions, model units.
        tets: (T, 4) int32 node indices, positive orientation
            (``det[p1 - p0, p2 - p0, p3 - p0] > 0``, as in USD and VTK).
        material: optional (T,) int32 material id per tet.
        stats: facts about how the mesh was made (counts, seconds per stage).

    Raises:
        WarpblobError: an array has the wrong shape or type, a node is not
            finite, or a tet names a node out of range or the same node twice.

    Example:
        >>> import numpy as np
        >>> from warpblob.mesh import TetMesh
        >>> mesh = TetMesh(np.eye(4, 3, k=-1), [[0, 1, 2, 3]])
        >>> float(mesh.volumes()[0]), mesh.surface_faces().shape, mesh.is_conforming()
        (0.16666666666666666, (4, 3), True)
    """

    nodes: np.ndarray
    tets: np.ndarray
    material: np.ndarray | None = None
    stats: dict = field(default_factory=dict)
    _cache: dict = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        nodes = np.asarray(self.nodes)
        if nodes.ndim != 2 or nodes.shape[1] != 3:
            raise WarpblobError(f"TetMesh: nodes must have shape (N, 3), got shape {nodes.shape}")
        if nodes.size and not np.issubdtype(nodes.dtype, np.number):
            raise WarpblobError(f"TetMesh: nodes must be numbers, got dtype {nodes.dtype}")
        nodes = np.ascontiguousarray(nodes, dtype=np.float32)
        bad = np.flatnonzero(~np.isfinite(nodes).all(axis=1))
        if bad.size:
            raise WarpblobError(f"TetMesh: nodes[{bad[0]}] = {nodes[bad[0]].tolist()} is not finite")
        tets = _int_array("tets", self.tets, "(T, 4)", 2, 4)
        if tets.size:
            out = np.flatnonzero(((tets < 0) | (tets >= len(nodes))).any(axis=1))
            if out.size:
                raise WarpblobError(
                    f"TetMesh: tets[{out[0]}] = {tets[out[0]].tolist()} names a node outside [0, {len(nodes)})"
                )
            s = np.sort(tets, axis=1)
            twice = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
            if twice.size:
                raise WarpblobError(f"TetMesh: tets[{twice[0]}] = {tets[twice[0]].tolist()} repeats a node")
        material = self.material
        if material is not None:
            material = _int_array("material", material, f"({len(tets)},)", 1, None)
            if len(material) != len(tets):
                raise WarpblobError(f"TetMesh: material must have shape ({len(tets)},), got shape {material.shape}")
            material = _frozen(material)
        object.__setattr__(self, "nodes", _frozen(nodes))
        object.__setattr__(self, "tets", _frozen(tets))
        object.__setattr__(self, "material", material)

    @classmethod
    def _trusted(cls, nodes: np.ndarray, tets: np.ndarray, material: np.ndarray | None, stats: dict) -> TetMesh:
        """A mesh from a warpblob pipeline's own arrays, valid by construction (finite float32 (N, 3)
        nodes, int32 (T, 4) tets of distinct in-range nodes, int32 (T,) material): not checked again."""
        mesh = object.__new__(cls)
        for name, value in (("nodes", nodes), ("tets", tets), ("material", material)):
            object.__setattr__(mesh, name, None if value is None else _frozen(value))
        object.__setattr__(mesh, "stats", stats)
        object.__setattr__(mesh, "_cache", {})
        return mesh

    @property
    def node_count(self) -> int:
        return int(self.nodes.shape[0])

    @property
    def tet_count(self) -> int:
        return int(self.tets.shape[0])

    def __repr__(self) -> str:
        volumes = self.volumes()
        lines = [f"TetMesh: {self.node_count:,} nodes, {self.tet_count:,} tets", bounds_text(self.nodes)]
        if self.tet_count:
            inverted = int(np.count_nonzero(volumes <= 0))
            lines.append(f"  volume {volumes.sum():.6g}, inverted tets {inverted:,}")
        if self.material is not None:
            ids, counts = np.unique(self.material, return_counts=True)
            shown = ", ".join(f"{i}: {c:,}" for i, c in zip(ids[:4].tolist(), counts[:4].tolist()))
            lines.append(f"  tets per material {shown}" + (f", ... ({len(ids)} ids)" if len(ids) > 4 else ""))
        return "\n".join(lines)

    def _cached(self, name, compute):
        if name not in self._cache:
            value = compute()
            self._cache[name] = _frozen(value) if isinstance(value, np.ndarray) else value
        return self._cache[name]

    def volumes(self) -> np.ndarray:
        """Signed tet volumes (T,) float64, model units cubed; positive for positive tets."""

        def compute():
            p = self.nodes.astype(np.float64)[self.tets]
            a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
            return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0

        return self._cached("volumes", compute)

    def volume(self) -> float:
        """Total volume (model units cubed): the sum of the signed tet volumes."""
        return float(self.volumes().sum())

    def _face_groups(self):
        """Every tet face once per tet, grouped: (faces (4T, 3) outward, order, group starts, group sizes).

        ``faces[order]`` lists equal faces (same node set) next to each other;
        group ``g`` is ``order[starts[g] : starts[g] + sizes[g]]``.
        """

        def compute():
            faces = self.tets[:, TET_FACES].reshape(-1, 3)
            s = np.sort(faces, axis=1)
            order = np.lexsort((s[:, 2], s[:, 1], s[:, 0]))
            s = s[order]
            new = np.ones(len(s), dtype=bool)
            new[1:] = (s[1:] != s[:-1]).any(axis=1)
            starts = np.flatnonzero(new)
            sizes = np.diff(np.append(starts, len(s)))
            return faces, order, starts, sizes

        return self._cached("face_groups", compute)

    def surface_faces(self) -> np.ndarray:
        """Boundary faces (F, 3) int32: the faces of exactly one tet, counter-clockwise seen from outside.

        Listed in the order of their tets (face ``k`` of tet ``t`` at ``4 t + k``).
        """

        def compute():
            faces, order, starts, sizes = self._face_groups()
            return faces[np.sort(order[starts[sizes == 1]])].astype(np.int32)

        return self._cached("surface_faces", compute)

    def is_conforming(self) -> bool:
        """Whether the tets meet face to face.

        True when every face is in one tet (boundary) or two tets that see it
        with opposite orientation, that is, lie on its two sides (interior).
        A combinatorial test: it assumes consistently oriented tets and cannot
        see a node lying inside another tet's face.
        """

        def compute():
            faces, order, starts, sizes = self._face_groups()
            if np.any(sizes > 2):
                return False
            pairs = order[starts[sizes == 2]]
            twins = order[starts[sizes == 2] + 1]
            return bool(np.all(_parity(faces[pairs]) != _parity(faces[twins])))

        return self._cached("conforming", compute)

    def quality(self):
        """The :class:`~warpblob.mesh.TetQuality` of the mesh (computed once, on Warp's default device)."""
        from ._quality import quality

        return self._cached("quality", lambda: quality(self))

    def numpy(self) -> dict:
        """The arrays as a dict of numpy arrays (``material`` only when present)."""
        out = {"nodes": self.nodes, "tets": self.tets}
        if self.material is not None:
            out["material"] = self.material
        return out

    def to_pyvista(self):
        """A ``pyvista.UnstructuredGrid`` of ``VTK_TETRA`` cells with quality cell data.

        Cell data: ``volume`` (signed, model units cubed), ``min_dihedral`` and
        ``max_dihedral`` (degrees), ``aspect_ratio`` (beta = CR / (3 IR), 1 for a
        regular tet), ``edge_ratio`` (longest / shortest edge of the tet) and,
        when present, ``material``.
        """
        import pyvista as pv

        cells = np.column_stack([np.full(self.tet_count, 4, dtype=np.int64), self.tets]).ravel()
        types = np.full(self.tet_count, pv.CellType.TETRA, dtype=np.uint8)
        grid = pv.UnstructuredGrid(cells, types, self.nodes.astype(np.float64))
        q = self.quality()
        grid.cell_data["volume"] = q.tet_volume
        grid.cell_data["min_dihedral"] = q.tet_dihedral_min
        grid.cell_data["max_dihedral"] = q.tet_dihedral_max
        grid.cell_data["aspect_ratio"] = q.tet_aspect_ratio
        grid.cell_data["edge_ratio"] = q.tet_edge_ratio
        if self.material is not None:
            grid.cell_data["material"] = self.material
        return grid


def _parity(faces: np.ndarray) -> np.ndarray:
    """Parity (0 or 1) of the permutation that sorts each row of (M, 3) ``faces``."""
    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    return ((a > b).astype(np.int8) + (a > c) + (b > c)) % 2
