"""Pictures of a cut tet mesh: its pieces pulled apart along the cutting planes, cut faces flat in the inside colour."""

from __future__ import annotations

import numpy as np

from ..mesh import SurfaceMesh, TetStructure

__all__ = ["face_pieces", "pieces", "render_cut"]


def pieces(structure: TetStructure, *, model=None, planes=None, gap: float = 0.2) -> list[SurfaceMesh]:
    """The boundary of each connected piece of ``structure``, moved apart for display.

    Each piece moves by ``gap`` x the mesh's largest box side along every
    plane's normal, towards the side of that plane its centroid lies on, so
    the pieces of ``k`` planes drift apart like an exploded drawing; without
    ``planes`` each moves away from the centre of them all.

    Args:
        structure: the cut mesh (current positions).
        model: BlobTree node whose colour field colours the surface at rest
            positions (cut faces show the inside), or None for grey.
        planes: ``[(origin (3,), normal (3,)), ...]`` the cuts, model units.
        gap: how far the pieces move, a fraction of the largest box side.

    Returns:
        One :class:`~warpblob.mesh.SurfaceMesh` per piece (by piece label),
        with ``is_cap`` set to the cut faces and ``cap_colors`` (C, 3) the
        colour at each cut face's rest centroid, as
        :func:`warpblob.slice._picture.exploded` draws them.
    """
    surf = structure.surface(model=model)
    if not surf.face_count:
        return []
    face_piece = face_pieces(structure, surf)
    vertices = surf.vertices.astype(np.float64)
    size = float(np.ptp(vertices, axis=0).max())
    centre = vertices.mean(axis=0)
    rest = np.asarray(structure.node_rest, dtype=np.float32)[surf.stats["nodes"]]
    out = []
    for p in np.unique(face_piece):
        faces = surf.faces[face_piece == p]
        used, local = np.unique(faces, return_inverse=True)
        local = local.reshape(-1, 3).astype(np.int32)
        middle = vertices[used].mean(axis=0)
        if planes:
            shift = sum(np.sign((middle - np.asarray(o, float)) @ n) * n for o, n in _unit(planes))
        else:
            shift = middle - centre
        length = float(np.linalg.norm(shift))
        shift = shift / length * gap * size if length > 0 else np.zeros(3)
        is_cut = surf.is_cut[face_piece == p]
        if model is not None and is_cut.any():
            from ..field import evaluate

            centroids = rest[faces[is_cut]].mean(axis=1)
            cap_colors = np.asarray(evaluate(model, centroids)[2], dtype=np.float32)
        else:
            cap_colors = surf.colors[faces[is_cut]].mean(axis=1)
        mesh = SurfaceMesh((vertices[used] + shift).astype(np.float32), local, surf.normals[used], surf.colors[used])
        mesh.is_cap, mesh.cap_colors = is_cut, cap_colors.astype(np.float32)
        out.append(mesh)
    return out


def face_pieces(structure: TetStructure, surface: SurfaceMesh) -> np.ndarray:
    """(F,) int32 the connected piece (:meth:`~warpblob.mesh.TetStructure.components`) of each face of
    ``surface``, a boundary made by :meth:`~warpblob.mesh.TetStructure.surface` of ``structure``.

    A face takes the piece of a cell at its first corner: the cut gives every
    separated piece its own copies of the nodes, so the pieces share none.
    """
    label = structure.components()
    live = np.asarray(structure.cell_alive)
    node_piece = np.full(len(structure.node_rest), -1, dtype=np.int32)
    node_piece[np.asarray(structure.cell_nodes)[live].ravel()] = np.repeat(label[live], 4)
    return node_piece[surface.stats["nodes"][surface.faces[:, 0]]]


def _unit(planes):
    for origin, normal in planes:
        n = np.asarray(normal, dtype=np.float64)
        yield origin, n / np.linalg.norm(n)


def render_cut(structure: TetStructure, path: str, *, model=None, planes=None, gap: float = 0.2, title: str = "",
               view=(1.0, -1.3, 0.9)) -> str:  # fmt: skip
    """Render the pieces of a cut mesh pulled apart (:func:`pieces`) to a PNG (atomically); returns ``path``.

    Cut faces are drawn flat, each in the model's colour at its rest centroid
    (the inside of the model); the rest of the boundary is smooth-shaded in
    the colour field at its rest positions.

    Args:
        structure: the cut mesh.
        path: the PNG file.
        model: BlobTree node for the colours (None: grey).
        planes: ``[(origin, normal), ...]`` the cuts, to pull the pieces apart along.
        gap: how far the pieces move, a fraction of the largest box side.
        title: text at the top left.
        view: direction from the scene towards the camera (z up).

    Example:
        >>> import os, tempfile, warpblob as wb
        >>> from warpblob.cut import render_cut
        >>> s = wb.TetStructure.from_tetmesh(wb.mesh.box_tetmesh((0, 0, 0), (1, 1, 1), (3, 3, 3)))
        >>> plane = ((0.5, 0.5, 0.5), (0.0, 0.0, 1.0))
        >>> _ = wb.cut.cut(s, wb.cut.SweepSurface.plane(*plane, 2.0))
        >>> png = render_cut(s, os.path.join(tempfile.mkdtemp(), "cut.png"), planes=[plane])
        >>> open(png, "rb").read(4)
        b'\\x89PNG'
    """
    from .._render import render_mesh
    from ..slice._picture import exploded

    shown = exploded(pieces(structure, model=model, planes=planes, gap=gap), gap=0.0)
    return render_mesh(shown, path, title=title, view=view)
