"""The triangle surface mesh type shared by polygonization, slicing and I/O."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["SurfaceMesh", "triangle_min_angles"]


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


@dataclass(eq=False)
class SurfaceMesh:
    """A shared-vertex triangle mesh with per-vertex normals and colours.

    Attributes:
        vertices: (V, 3) float32 positions, model units.
        faces: (F, 3) int32 vertex indices, counter-clockwise seen from outside.
        normals: (V, 3) float32 unit outward normals.
        colors: (V, 3) float32 RGB in [0, 1].
        stats: facts about how the mesh was made (counts, seconds per stage).

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

    def is_closed_manifold(self) -> bool:
        """Every edge in exactly two faces, used once in each direction (consistent orientation)."""
        if self.face_count == 0:
            return False
        directed = self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
        _, counts = self.edge_face_counts()
        if not np.all(counts == 2):
            return False
        keys = directed[:, 0].astype(np.int64) * (self.vertex_count + 1) + directed[:, 1]
        return bool(len(np.unique(keys)) == len(keys))

    def numpy(self) -> dict:
        """The arrays as a dict of numpy arrays."""
        return {"vertices": self.vertices, "faces": self.faces, "normals": self.normals, "colors": self.colors}

    def to_usd(self, path, *, prim_path: str = "/Surface"):
        """Write the mesh as a ``UsdGeom.Mesh`` stage at ``path`` (see :func:`warpblob.usd.save_mesh`)."""
        from ..io.usd import save_mesh

        return save_mesh(self, path, prim_path=prim_path)

    def to_pyvista(self):
        """A ``pyvista.PolyData`` with ``Normals`` and ``RGB`` point data."""
        import pyvista as pv

        faces = np.column_stack([np.full(self.face_count, 3, dtype=np.int64), self.faces]).ravel()
        poly = pv.PolyData(self.vertices.astype(np.float64), faces)
        poly.point_data["Normals"] = self.normals
        poly.point_data["RGB"] = (np.clip(self.colors, 0, 1) * 255).astype(np.uint8)
        poly.point_data.active_normals_name = "Normals"
        return poly
