"""Pictures of sliced meshes: the pieces pulled apart, caps flat in their own colours."""

from __future__ import annotations

import numpy as np

from ..mesh import SurfaceMesh

__all__ = ["exploded", "opened", "render_pieces"]


def exploded(pieces, *, gap: float = 0.15) -> SurfaceMesh:
    """One mesh for display: each piece moved away from the centre of them all, caps
    given their own vertices so that they show flat, with the cap colours.

    The result is for pictures only (the caps are not joined to the sides).

    Args:
        pieces: the :class:`~warpblob.mesh.SurfaceMesh` pieces of :func:`warpblob.slice.slice`.
        gap: how far each piece moves, as a fraction of the largest box side of them all.

    Returns:
        The display mesh.
    """
    pieces = [p for p in pieces if p.face_count]
    if not pieces:
        z = np.zeros((0, 3), dtype=np.float32)
        return SurfaceMesh(z, np.zeros((0, 3), dtype=np.int32), z, z)
    every = np.concatenate([p.vertices for p in pieces]).astype(np.float64)
    centre = every.mean(axis=0)
    size = float(np.ptp(every, axis=0).max())
    parts, base = [], 0
    for p in pieces:
        direction = p.vertices.astype(np.float64).mean(axis=0) - centre
        length = np.linalg.norm(direction)
        shift = direction / length * gap * size if length > 0 else np.zeros(3)
        caps = np.asarray(p.is_cap if p.is_cap is not None else np.zeros(p.face_count, dtype=bool), dtype=bool)
        cap_faces = p.faces[caps]
        corners = p.vertices[cap_faces].reshape(-1, 3).astype(np.float64)
        a, b, c = corners[0::3], corners[1::3], corners[2::3]
        face_normal = np.cross(b - a, c - a)
        face_normal /= np.maximum(np.linalg.norm(face_normal, axis=1, keepdims=True), 1e-30)
        cap_rgb = np.asarray(p.cap_colors if p.cap_colors is not None else np.zeros((len(cap_faces), 3)), dtype=np.float32)
        n_side = p.vertex_count
        parts.append(
            (
                np.concatenate([p.vertices + shift, corners + shift]),
                np.concatenate([p.faces[~caps], n_side + np.arange(3 * len(cap_faces)).reshape(-1, 3)]) + base,
                np.concatenate([p.normals, np.repeat(face_normal, 3, axis=0)]),
                np.concatenate([p.colors, np.repeat(cap_rgb, 3, axis=0)]),
            )
        )
        base += n_side + len(corners)
    v, f, n, c = (np.concatenate(x) for x in zip(*parts))
    return SurfaceMesh(v.astype(np.float32), f.astype(np.int32), n.astype(np.float32), c.astype(np.float32))


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix about unit ``axis`` by ``angle`` radians (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def opened(below: SurfaceMesh, above: SurfaceMesh, normal, *, view=(0.3, -1.0, 0.45), gap: float = 0.12) -> list:
    """The two halves of one cut opened like a book: each turned so that its cap faces
    the camera (``view``: from the scene towards the camera, z up), side by side.

    Each half turns about the vertical through its centre (about the camera's
    horizontal axis when the cut is horizontal), the part below on the left.

    Returns:
        [below, above] moved copies (with ``is_cap`` and ``cap_colors``).
    """
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    w = np.asarray(view, dtype=np.float64) / np.linalg.norm(view)
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(up, w)
    right /= np.linalg.norm(right)
    axis = up if abs(n @ up) < 0.9 else right
    placed = []
    for piece, cap_normal in ((below, n), (above, -n)):
        c = cap_normal - (cap_normal @ axis) * axis
        t = w - (w @ axis) * axis
        turn = _rotation(axis, float(np.arctan2(axis @ np.cross(c, t), c @ t)))
        centre = piece.vertices.astype(np.float64).mean(axis=0) if piece.vertex_count else np.zeros(3)
        v = (piece.vertices - centre) @ turn.T
        moved = SurfaceMesh(v, piece.faces, (piece.normals @ turn.T).astype(np.float32), piece.colors)
        moved.is_cap, moved.cap_colors = piece.is_cap, piece.cap_colors
        placed.append(moved)
    widths = [float(np.ptp(p.vertices @ right)) if p.vertex_count else 0.0 for p in placed]
    space = gap * max(sum(widths), 1e-9)
    shifts = [-(0.5 * widths[0] + 0.5 * space), 0.5 * widths[1] + 0.5 * space]
    for p, shift, width in zip(placed, shifts, widths):
        if p.vertex_count:
            middle = 0.5 * (p.vertices @ right).max() + 0.5 * (p.vertices @ right).min()
            p.vertices = (p.vertices + (shift - middle) * right).astype(np.float32)
    return placed


def render_pieces(pieces, path: str, *, normal=None, title: str = "", view=(0.3, -1.0, 0.45)) -> str:
    """Render the pieces of a cut to a PNG, caps flat in their colours; returns ``path``.

    With ``normal`` (the two halves of one plane) the halves are opened like a
    book (:func:`opened`), else pulled apart (:func:`exploded`).
    """
    from .._render import render_mesh

    shown = opened(*pieces, normal, view=view) if normal is not None else pieces
    return render_mesh(exploded(shown, gap=0.0 if normal is not None else 0.15), path, title=title, view=view)
