"""A minimal time-sampled USD writer for simulations: a ``UsdGeom.TetMesh`` and a surface whose points move.

The stage has upAxis Z, ``metersPerUnit``, ``timeCodesPerSecond`` (one time
code per recorded frame), start and end codes and a default prim; topology
is authored once, points and extents as time samples (OpenUSD's own
TetMesh tests do the same). The surface's normals are blocked, since they
change with the points: viewers compute them.
"""

from __future__ import annotations

import pathlib

import numpy as np
from pxr import Sdf, UsdGeom, Vt

from .._errors import SceneError
from .usd import METERS_PER_UNIT, author_mesh, export_atomically, new_stage

__all__ = ["AnimationWriter"]

_SUFFIXES = (".usda", ".usdc", ".usd")


class AnimationWriter:
    """Collect frames of a tet mesh (and an optional embedded surface), then write them as one stage.

    Args:
        path: target ``.usda``/``.usdc``/``.usd`` file (written by :meth:`save`, atomically).
        tets: (T, 4) node indices of the volume.
        surface_faces: (F, 3) boundary faces of the volume (counter-clockwise from outside).
        surface: optional :class:`~warpblob.mesh.SurfaceMesh` whose vertices move with the volume.
        fps: time codes per second (``1 / (dt * steps per frame)`` plays in real time).
        meters_per_unit: stage metres per model unit.
        root: name of the root prim (the default prim); the volume is ``/<root>/Volume``, the
            surface ``/<root>/Surface``.

    Example:
        >>> import os, tempfile, numpy as np
        >>> from warpblob.io._anim import AnimationWriter
        >>> nodes = np.eye(4, 3, k=-1).astype(np.float32)
        >>> writer = AnimationWriter(os.path.join(tempfile.mkdtemp(), "a.usda"), [[0, 1, 2, 3]], [[1, 2, 3]])
        >>> for frame in range(3):
        ...     writer.add(nodes + [0, 0, 0.1 * frame])
        >>> writer.save().suffix, writer.frame_count
        ('.usda', 3)
    """

    def __init__(self, path, tets, surface_faces, surface=None, *, fps: float = 60.0,
                 meters_per_unit: float = METERS_PER_UNIT, root: str = "Simulation"):  # fmt: skip
        self.path = pathlib.Path(path)
        if self.path.suffix not in _SUFFIXES:
            raise SceneError(f"AnimationWriter: path must end in one of {', '.join(_SUFFIXES)}, got {str(path)!r}")
        if not Sdf.Path.IsValidIdentifier(root):
            raise SceneError(f"AnimationWriter: root must be a prim name, got {root!r}")
        if not (np.isfinite(fps) and fps > 0):
            raise SceneError(f"AnimationWriter: fps must be a positive number, got {fps!r}")
        self.tets = np.ascontiguousarray(tets, dtype=np.int32).reshape(-1, 4)
        self.surface_faces = np.ascontiguousarray(surface_faces, dtype=np.int32).reshape(-1, 3)
        self.surface = surface
        self.fps = float(fps)
        self.meters_per_unit = float(meters_per_unit)
        self.root = root
        self._frames: list[tuple[np.ndarray, np.ndarray | None]] = []

    @property
    def frame_count(self) -> int:
        return len(self._frames)

    def add(self, nodes, surface_vertices=None) -> None:
        """Record the next frame (time code = frame index): (N, 3) node positions, (V, 3) surface vertices."""
        nodes = np.array(nodes, dtype=np.float32).reshape(-1, 3)
        if self._frames and nodes.shape != self._frames[0][0].shape:
            shape = self._frames[0][0].shape
            raise SceneError(f"AnimationWriter.add: nodes must have shape {shape}, got {nodes.shape}")
        if (surface_vertices is None) != (self.surface is None):
            raise SceneError("AnimationWriter.add: give surface_vertices exactly when the writer has a surface")
        verts = None if surface_vertices is None else np.array(surface_vertices, dtype=np.float32).reshape(-1, 3)
        self._frames.append((nodes, verts))

    def save(self) -> pathlib.Path:
        """Write the stage (atomically) and return its path.

        Raises:
            SceneError: no frame was added.
            OSError: the directory does not exist or USD could not write.
        """
        if not self._frames:
            raise SceneError("AnimationWriter.save: no frames were added")
        last = len(self._frames) - 1
        stage = new_stage(meters_per_unit=self.meters_per_unit, default_prim=self.root, start=0, end=last, fps=self.fps)
        base = "/" + self.root
        volume = UsdGeom.TetMesh.Define(stage, base + "/Volume")
        volume.CreateTetVertexIndicesAttr(Vt.Vec4iArray.FromNumpy(self.tets))
        volume.CreateSurfaceFaceVertexIndicesAttr(Vt.Vec3iArray.FromNumpy(self.surface_faces))
        volume.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        attrs = [(volume.CreatePointsAttr(), volume.CreateExtentAttr(), 0)]
        if self.surface is not None:
            mesh = author_mesh(stage, base + "/Surface", self.surface)
            mesh.GetNormalsAttr().Block()
            attrs.append((mesh.GetPointsAttr(), mesh.GetExtentAttr(), 1))
        for code, frame in enumerate(self._frames):
            for points_attr, extent_attr, which in attrs:
                points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(frame[which]))
                points_attr.Set(points, code)
                extent_attr.Set(UsdGeom.PointBased.ComputeExtent(points), code)
        return export_atomically(stage.GetRootLayer(), self.path, "AnimationWriter.save")
