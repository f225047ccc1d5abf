"""Triangle meshes from the files users already have: STL, OBJ, PLY, VTK (PyVista's readers) and USD.

The readers are VTK's, through PyVista (already a dependency); USD goes to
:func:`warpblob.io.usd.load_mesh`. Polygons are triangulated, and points at
exactly the same position are merged into one vertex: STL stores every
triangle's corners separately and OBJ repeats a position for each normal
index, which would otherwise leave a closed surface open at every edge.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from .._errors import SceneError

__all__ = ["load_mesh", "MESH_SUFFIXES"]

#: file types read by PyVista (VTK); USD files go to the USD reader
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".vtk", ".vtp")
_USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (zero where a vertex has no faces)."""
    v = vertices.astype(np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    face_normals = np.cross(b - a, c - a)
    normals = np.zeros_like(v)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0).astype(np.float32)


def load_mesh(path, *, prim_path: str | None = None):
    """Read a triangle mesh file as a :class:`~warpblob.mesh.SurfaceMesh`.

    Args:
        path: an ``.stl``, ``.obj``, ``.ply``, ``.vtk`` or ``.vtp`` file (read by
            PyVista), or a ``.usd``/``.usda``/``.usdc``/``.usdz`` file holding a
            triangle ``UsdGeom.Mesh``.
        prim_path: the Mesh prim of a USD file (default: its default prim).

    Returns:
        The mesh: polygons triangulated, coincident points merged; the file's
        point normals (else area-weighted normals of the faces) and colours
        (else white).

    Raises:
        SceneError: a missing or unreadable file, an unknown suffix, or a file
            with no triangles; the message names the file.

    Example:
        >>> import os, tempfile, warpblob as wb
        >>> from warpblob.io._meshfile import load_mesh
        >>> path = os.path.join(tempfile.mkdtemp(), "ball.stl")
        >>> wb.polygonize(wb.Point((0, 0, 0), 1.0), cellsize=0.2).to_pyvista().save(path)
        >>> load_mesh(path).is_closed_manifold()
        True
    """
    from ..mesh import SurfaceMesh

    source = os.fspath(path)
    suffix = os.path.splitext(source)[1].lower()
    if suffix in _USD_SUFFIXES:
        from .usd import load_mesh as load_usd_mesh

        return load_usd_mesh(source, prim_path)
    if suffix not in MESH_SUFFIXES:
        known = ", ".join(MESH_SUFFIXES + _USD_SUFFIXES)
        raise SceneError(f"load_mesh: {source}: unknown mesh file type {suffix!r}; expected one of {known}")
    if not os.path.isfile(source):
        raise SceneError(f"load_mesh: {source}: no such file")
    import pyvista as pv

    try:
        with warnings.catch_warnings():
            # VTK's complaint comes back as the error below
            warnings.simplefilter("ignore")
            data = pv.read(source)
    except Exception as exc:  # VTK's readers raise anything from ValueError to RuntimeError
        raise SceneError(f"load_mesh: {source}: not a readable mesh file ({exc})") from None
    if not isinstance(data, pv.PolyData):
        data = data.extract_surface()
    if data.n_cells == 0 or data.n_points == 0:
        raise SceneError(f"load_mesh: {source}: the file holds no faces")
    if not data.is_all_triangles:
        data = data.triangulate()
    faces = np.asarray(data.regular_faces, dtype=np.int64).reshape(-1, 3)
    points = np.asarray(data.points, dtype=np.float32)
    normals = data.point_data.get("Normals")
    colors = None
    for name in ("RGB", "RGBA", "Colors"):
        if name in data.point_data:
            rgb = np.asarray(data.point_data[name])[:, :3]
            colors = rgb / 255.0 if rgb.dtype == np.uint8 else rgb
            break
    unique, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    # points merged to one keep the attributes of the first of them
    normals = np.asarray(normals, dtype=np.float32)[first] if normals is not None else _vertex_normals(unique, faces)
    colors = np.asarray(colors, dtype=np.float32)[first] if colors is not None else np.ones_like(unique)
    return SurfaceMesh(unique, faces.astype(np.int32), normals, colors)
