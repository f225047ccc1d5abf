"""Tools in a simulation's time-sampled USD stage: each tool an Xform whose pose is sampled per frame.

:class:`ToolAnimationWriter` is the :class:`~warpblob.io._anim.AnimationWriter`
plus rigid tools: each tool is ``/<root>/Tools/Tool<k>``, a ``UsdGeom.Xform``
with a translate and an orient op sampled at every frame (the pose
``(position, (x, y, z, w))`` of :class:`~warpblob.tools.Pose`), holding the
tool's ``UsdGeom.Mesh`` (authored once, in the tool's frame). Optional
per-frame surface colours are written as time samples of the surface's
``primvars:displayColor`` (the contact area highlighted, for instance).
"""

from __future__ import annotations

import pathlib

import numpy as np
from pxr import Gf, Usd, UsdGeom, Vt

from .._errors import SceneError
from ._anim import AnimationWriter
from .usd import export_atomically

__all__ = ["ToolAnimationWriter"]

#: displayColor of the tool meshes (steel grey)
TOOL_COLOR = (0.62, 0.64, 0.68)


class ToolAnimationWriter(AnimationWriter):
    """Collect frames of a tet mesh, its surface and rigid tools, then write them as one stage.

    Args:
        path, tets, surface_faces, surface, fps, meters_per_unit, root: as
            :class:`~warpblob.io._anim.AnimationWriter`.
        tools: the :class:`~warpblob.tools.Tool` meshes, in their own frames.

    Example:
        >>> import os, tempfile, numpy as np
        >>> from warpblob.io._anim_tools import ToolAnimationWriter
        >>> from warpblob.tools import Pose, Probe
        >>> nodes = np.eye(4, 3, k=-1).astype(np.float32)
        >>> path = os.path.join(tempfile.mkdtemp(), "a.usda")
        >>> writer = ToolAnimationWriter(path, [[0, 1, 2, 3]], [[1, 2, 3]], tools=[Probe(0.5)])
        >>> for frame in range(3):
        ...     writer.add(nodes, poses=[Pose((0, 0, 1.0 - 0.1 * frame))])
        >>> writer.save().suffix, writer.frame_count
        ('.usda', 3)
    """

    def __init__(self, path, tets, surface_faces, surface=None, *, tools=(), **options):
        super().__init__(path, tets, surface_faces, surface, **options)
        self.tools = list(tools)
        self._poses: list[np.ndarray] = []
        self._colors: list[np.ndarray | None] = []

    def add(self, nodes, surface_vertices=None, *, poses=(), surface_colors=None) -> None:
        """Record the next frame: nodes and surface vertices (see the base class), one pose per tool,
        and optionally the surface's (V, 3) RGB colours at this frame."""
        if len(poses) != len(self.tools):
            raise SceneError(f"ToolAnimationWriter.add: {len(self.tools)} tools but {len(poses)} poses")
        if surface_colors is not None and self.surface is None:
            raise SceneError("ToolAnimationWriter.add: surface_colors need a surface")
        super().add(nodes, surface_vertices)
        self._poses.append(np.array([p.numpy() for p in poses], dtype=np.float64).reshape(len(self.tools), 7))
        self._colors.append(None if surface_colors is None else np.array(surface_colors, dtype=np.float32))

    def save(self) -> pathlib.Path:
        """Write the stage (the base writer's, then the tools and colours added to it, atomically) and return its path.

        Raises:
            SceneError: no frame was added.
            OSError: the directory does not exist or USD could not write.
        """
        target = super().save()
        stage = Usd.Stage.Open(str(target))
        base = "/" + self.root
        UsdGeom.Scope.Define(stage, base + "/Tools")
        for index, tool in enumerate(self.tools):
            xform = UsdGeom.Xform.Define(stage, f"{base}/Tools/Tool{index}")
            translate = xform.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
            orient = xform.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
            # USD takes one time sample per call
            for code, frame in enumerate(self._poses):
                p = frame[index]
                translate.Set(Gf.Vec3d(*p[:3].tolist()), code)
                orient.Set(Gf.Quatd(float(p[6]), float(p[3]), float(p[4]), float(p[5])), code)
            mesh = UsdGeom.Mesh.Define(stage, f"{base}/Tools/Tool{index}/Mesh")
            points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(tool.vertices, dtype=np.float32))
            mesh.CreatePointsAttr(points)
            mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(tool.face_count, 3, dtype=np.int32)))
            mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tool.faces).ravel()))
            mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            mesh.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*TOOL_COLOR)]))
            mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
        if any(c is not None for c in self._colors):
            colors = UsdGeom.Mesh(stage.GetPrimAtPath(base + "/Surface")).GetDisplayColorPrimvar()
            for code, frame in enumerate(self._colors):
                if frame is not None:
                    colors.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(frame)), code)
        return export_atomically(stage.GetRootLayer(), target, "ToolAnimationWriter.save")
