"""The triangle surface mesh type shared by polygonization, slicing and I/O."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["SurfaceMesh", "triangle_min_angles"]


def _components(count: int, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Connected components of the graph on ``count`` elements with edges ``(a[i], b[i])``.

    Hook-and-compress (Shiloach & Vishkin 1982, without the random mating):
    every pass hangs the larger of two joined roots under the smaller, then
    jumps pointers until each element points at its root. Roots only ever
    point to smaller ids, so no cycle can form, and every pass is a handful
    of array operations over the edges still joining two trees.

    Args:
        count: number of elements.
        a, b: (E,) integer element ids, the two ends of each edge.

    Returns:
        (count,) int64: the smallest element id of each element's component.
    """
    label = np.arange(count, dtype=np.int64)
    a, b = np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64)
    while True:
        la, lb = label[a], label[b]
        joining = la != lb
        if not joining.any():
            return label
        a, b, la, lb = a[joining], b[joining], la[joining], lb[joining]
        # any one of the smaller roots will do: among repeated indices one write wins
        label[np.maximum(la, lb)] = np.minimum(la, lb)
        while True:
            up = label[label]
            if np.array_equal(up, label):
                break
            label = up


def bounds_text(points) -> str:
    """One repr line: the box of (N, 3) ``points`` as ``x [lo, hi]  y [lo, hi]  z [lo, hi]``."""
    p = np.asarray(points).reshape(-1, 3)
    if not len(p):
        return "  bounds: none (no points)"
    lo, hi = p.min(axis=0), p.max(axis=0)
    return "  bounds " + "  ".join(f"{a} [{lo[i]:.4g}, {hi[i]:.4g}]" for i, a in enumerate("xyz"))


def triangle_min_angles(vertices, faces) -> np.ndarray:
    """Smallest interior angle of each triangle of ``faces`` (F, 3) over ``vertices`` (V, 3), degrees."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    angles = []
    for k in range(3):
        a, b, c = v[f[:, k]], v[f[:, (k + 1) % 3]], v[f[:, (k + 2) % 3]]
        u, w = b - a, c - a
        nu, nw = np.linalg.norm(u, axis=1), np.linalg.norm(w, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos = np.einsum("ij,ij->i", u, w) / (nu * nw)
        angles.append(np.degrees(np.arccos(np.clip(np.nan_to_num(cos, nan=1.0), -1.0, 1.0))))
    return np.min(angles, axis=0)


@dataclass(eq=False, repr=False)
class SurfaceMesh:
    """A shared-vertex triangle mesh with per-vertex normals and colours.

    Attributes:
        vertices: (V, 3) float32 positions, model units.
        faces: (F, 3) int32 vertex indices, counter-clockwise seen from outside.
        normals: (V, 3) float32 unit outward normals.
        colors: (V, 3) float32 RGB in [0, 1].
        stats: facts about how the mesh was made (counts, seconds per stage).
        is_cap: (F,) bool, faces that cap a planar cut (:func:`warpblob.slice`),
            or None for a mesh no slice made.
        cap_colors: (C, 3) float32 RGB of the cap faces in face order
            (``C = is_cap.sum()``), or None.
        is_cut: (F,) bool, faces a blade made (the boundary of a cut tet
            mesh, :meth:`~warpblob.mesh.TetStructure.surface`), or None.

    Example:
        >>> import warpblob as wb
        >>> mesh = wb.polygonize(wb.Point((0, 0, 0), 1.0), cellsize=0.1)
        >>> mesh.faces.shape[1], bool(abs(mesh.area() - 4 * 3.14159 * 0.4541**2) < 0.05)
        (3, True)
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    stats: dict = field(default_factory=dict)
    is_cap: np.ndarray | None = None
    cap_colors: np.ndarray | None = None
    is_cut: np.ndarray | None = None

    @property
    def vertex_count(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])

    def area(self) -> float:
        """Total surface area (model units squared)."""
        v = self.vertices.astype(np.float64)
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())

    def volume(self) -> float:
        """Enclosed volume (divergence theorem; meaningful for closed meshes)."""
        v = self.vertices.astype(np.float64)
        a, b, c = v[self.faces[:, 0]], v[self.faces[:, 1]], v[self.faces[:, 2]]
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)

    def min_angles(self) -> np.ndarray:
        """Smallest interior angle of each triangle, degrees, (F,) float64 (0 for degenerate ones)."""
        return triangle_min_angles(self.vertices, self.faces)

    def edge_face_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """Undirected edges (E, 2) and how many faces use each."""
        e = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        edges, counts = np.unique(e, axis=0, return_counts=True)
        return edges, counts

    def shells(self) -> np.ndarray:
        """Shell (connected component over shared edges) of each face, (F,) int32.

        Shells are numbered 0, 1, ... in the order of their first face. A
        closed solid with ``k`` separate cavities has ``k + 1`` shells.

        Example:
            >>> import warpblob as wb
            >>> mesh = wb.polygonize(wb.scenes.eggshell(), cellsize=0.1)  # outer and inner surface
            >>> int(mesh.shells().max()) + 1
            2
        """
        f = self.face_count
        edges = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1).astype(np.int64)
        keys = edges[:, 0] * max(self.vertex_count, 1) + edges[:, 1]
        order = np.argsort(keys, kind="stable")
        same = keys[order[1:]] == keys[order[:-1]]
        # faces listed next to each other in edge order share that edge (a chain covers edges of 3+ faces)
        label = _components(f, order[:-1][same] // 3, order[1:][same] // 3)
        return np.unique(label, return_inverse=True)[1].astype(np.int32).reshape(-1)

    def shell_count(self) -> int:
        """Number of shells (see :meth:`shells`); 0 for a mesh without faces."""
        return int(self.shells().max()) + 1 if self.face_count else 0

    def is_closed_manifold(self) -> bool:
        """Whether the mesh is a closed, consistently oriented 2-manifold.

        True when every edge is in exactly two faces, used once in each
        direction, and the faces around every vertex form one closed fan (a
        pinched vertex, where two fans meet at one point, is not a manifold).
        Vertices used by no face are ignored.

        Example:
            >>> import numpy as np
            >>> from warpblob.mesh import SurfaceMesh
            >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)
            >>> tet = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
            >>> SurfaceMesh(v, tet, v, v).is_closed_manifold()
            True
            >>> w = np.vstack([v, -v[1:]])  # a mirrored copy touching the first at the origin
            >>> both = np.vstack([tet, np.where(tet > 0, tet + 3, 0)[:, ::-1]])
            >>> SurfaceMesh(w, both, w, w).is_closed_manifold()
            False
        """
        if self.face_count == 0:
            return False
        f = self.faces.astype(np.int64)
        if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
            return False
        n = max(self.vertex_count, int(f.max()) + 1)
        # corner c = 3 i + k of face i sits at vertex f[i, k]; its edge runs to the next corner's vertex
        at, to = f.ravel(), np.roll(f, -1, axis=1).ravel()
        keys = np.minimum(at, to) * n + np.maximum(at, to)
        order = np.argsort(keys)
        k = keys[order]
        # sorted, the edges of a closed mesh come in pairs, and an oriented one runs each pair both ways
        if len(k) % 2 or not np.array_equal(k[0::2], k[1::2]) or np.any(k[1:-1:2] == k[2::2]):
            return False
        forward = (at < to)[order]
        if np.any(forward[0::2] == forward[1::2]):
            return False
        twin = np.empty_like(order)
        twin[order[0::2]], twin[order[1::2]] = order[1::2], order[0::2]
        # around vertex v the face after corner c = (v, a, b) holds the twin of edge b -> v; walking
        # from one corner, a manifold vertex gets back only after visiting all its corners
        corners = np.arange(len(at))
        after = twin[corners - corners % 3 + (corners + 2) % 3]
        valence = np.bincount(at, minlength=n)
        start = np.full(n, -1, dtype=np.int64)
        start[at] = corners  # any corner of each vertex
        used = valence > 0
        start, left = start[used], valence[used]
        walk, step = start, 1
        while len(walk):
            walk = after[walk]
            if np.any((walk == start) & (step < left)):
                return False  # back early: another fan of faces meets this one at the vertex
            going = left > step
            walk, start, left = walk[going], start[going], left[going]
            step += 1
        return True

    def __repr__(self) -> str:
        lines = [f"SurfaceMesh: {self.vertex_count:,} vertices, {self.face_count:,} triangles"]
        lines.append(bounds_text(self.vertices))
        if self.face_count:
            lines.append(f"  area {self.area():.6g}, enclosed volume {self.volume():.6g}")
        return "\n".join(lines)

    def slice(self, origin=None, normal=None, **options):
        """Cut by a plane into two closed, capped halves (or by ``planes=`` into pieces): :func:`warpblob.slice`."""
        from ..slice import slice as slice_mesh

        return slice_mesh(self, origin, normal, **options)

    def numpy(self) -> dict:
        """The arrays as a dict of numpy arrays."""
        return {"vertices": self.vertices, "faces": self.faces, "normals": self.normals, "colors": self.colors}

    def to_pyvista(self):
        """A ``pyvista.PolyData`` with ``Normals`` and ``RGB`` point data."""
        import pyvista as pv

        faces = np.column_stack([np.full(self.face_count, 3, dtype=np.int64), self.faces]).ravel()
        poly = pv.PolyData(self.vertices.astype(np.float64), faces)
        poly.point_data["Normals"] = self.normals
        poly.point_data["RGB"] = (np.clip(self.colors, 0, 1) * 255).astype(np.uint8)
        poly.point_data.active_normals_name = "Normals"
        if self.is_cap is not None:
            poly.cell_data["is_cap"] = np.asarray(self.is_cap, dtype=bool)
        if self.is_cut is not None:
            poly.cell_data["is_cut"] = np.asarray(self.is_cut, dtype=bool)
        return poly
